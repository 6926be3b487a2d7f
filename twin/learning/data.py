"""Pretraining data (Sec. III-A): transitions of a swarm on a training map.

Two collectors: the paper's randomly moving swarm (uniform feasible actions), and the swarm
being learned, ``rl`` (the coordinator's joint action on the network's Q values, eq.
maxi:op2) with epsilon-greedy exploration. The drones' states are those of a state variant
(:mod:`twin.states`; the paper's 13 values by default). Both advance with :func:`twin.swarm.step`, the step
of the patrol loop: idleness per Def. 3, every drone's reward read on arrival (Def. 4).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from twin.coordinator import coordinate
from twin.grid import N_ACTIONS
from twin.policies import random_feasible
from twin.scores import ScoreParams
from twin.states import STATE_VARIANTS, StateVariant
from twin.swarm import initial_state, random_starts, step
from twin.traffic.base import TrafficSource

__all__ = ["Episode", "coordinated_swarm_episode", "random_starts", "random_swarm_episode"]

#: Q value given to an exploring drone's random action, far above any learned Q, so that the
#: coordinator grants it unless another drone takes that cell.
EXPLORE_Q = 1e6


@dataclass
class Episode:
    """``(T, N, ...)`` arrays of one random-swarm episode, ready for the replay buffer."""

    states: np.ndarray
    actions: np.ndarray
    rewards: np.ndarray
    next_states: np.ndarray
    next_feasible: np.ndarray


PAPER = STATE_VARIANTS["paper"]


def random_swarm_episode(
    source: TrafficSource,
    n_drones: int,
    params: ScoreParams,
    rng: np.random.Generator,
    variant: StateVariant = PAPER,
) -> Episode:
    """Run a random swarm over the whole horizon of ``source`` and record every transition,
    its states those of ``variant``."""
    return _swarm_episode(
        source, n_drones, params, rng,
        lambda state, states: random_feasible(state.feasible, rng), variant,
    )  # fmt: skip


def coordinated_swarm_episode(
    source: TrafficSource,
    n_drones: int,
    params: ScoreParams,
    rng: np.random.Generator,
    net: torch.nn.Module,
    epsilon: float,
    variant: StateVariant = PAPER,
) -> Episode:
    """Run the coordinated learned swarm (``rl``: the joint action with the largest sum of
    ``Q(s_d; theta)`` and all next cells distinct, eq. maxi:op2) over the horizon of
    ``source``, exploring: each step each drone, with probability ``epsilon``, asks for a
    uniform feasible action instead of its Q values (granted unless another drone takes that
    cell). ``net`` is held fixed for the episode and reads the states of ``variant``."""
    grid = source.grid

    def choose(state, states):
        with torch.no_grad():
            q = net(torch.from_numpy(np.asarray(states, np.float32))).double().numpy()
        explore = rng.random(n_drones) < epsilon
        random_actions = random_feasible(state.feasible, rng)
        if explore.any():
            q[explore] = 0.0
            q[explore, random_actions[explore]] = EXPLORE_Q
        return coordinate(q, state.positions, state.feasible, grid)

    return _swarm_episode(source, n_drones, params, rng, choose, variant)


def _swarm_episode(source, n_drones, params, rng, choose, variant: StateVariant) -> Episode:
    """Every transition of a swarm whose actions are ``choose(state, drone_states)``, the
    drones' states built by ``variant``."""
    grid = source.grid
    horizon = source.horizon
    shape = (horizon, n_drones)
    ep = Episode(
        np.empty((*shape, variant.size), np.float32),
        np.empty(shape, np.int64),
        np.empty(shape, np.float32),
        np.empty((*shape, variant.size), np.float32),
        np.empty((*shape, N_ACTIONS), bool),
    )
    maps = source.importance_maps()
    state = initial_state(grid, random_starts(grid, n_drones, rng), next(maps))
    states = variant.states(grid, state.idleness, state.importance, state.positions)
    for k in range(horizon):
        actions = choose(state, states)
        state, out = step(state, actions, next(maps), grid, params)
        next_states = variant.states(grid, state.idleness, state.importance, state.positions)
        ep.states[k], ep.actions[k], ep.rewards[k] = states, actions, out.rewards
        ep.next_states[k], ep.next_feasible[k] = next_states, out.feasible
        states = next_states
    return ep
