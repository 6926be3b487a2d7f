"""Pretraining data (Sec. III-A): transitions of a swarm on a training map.

Two collectors: the paper's randomly moving swarm (uniform feasible actions), and the swarm
being learned, ``rl`` (the coordinator's joint action on the network's Q values, eq.
maxi:op2) with epsilon-greedy exploration. The drones' states are those of a state variant
(:mod:`twin.states`; the paper's 13 values by default); a variant that reads the nowcast
belief gets it from a :class:`~twin.belief.NowcastFilter` on the episode's ``history``, updated
each step on the cells the drones see, as in a run. Both advance with :func:`twin.swarm.step`, the step
of the patrol loop: idleness per Def. 3, every drone's reward read on arrival (Def. 4).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from twin.belief import EXACT_SIGHTINGS, History, NowcastFilter, SightingModel
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
    history: History | None = None,
) -> Episode:
    """Run a random swarm over the whole horizon of ``source`` and record every transition,
    its states those of ``variant`` (``history``: the nowcast's, for a variant that reads it)."""
    return _swarm_episode(
        source, n_drones, params, rng,
        lambda state, states: random_feasible(state.feasible, rng), variant, history,
    )  # fmt: skip


def coordinated_swarm_episode(
    source: TrafficSource,
    n_drones: int,
    params: ScoreParams,
    rng: np.random.Generator,
    net: torch.nn.Module,
    epsilon: float,
    variant: StateVariant = PAPER,
    history: History | None = None,
) -> Episode:
    """Run the coordinated learned swarm (``rl``: the joint action with the largest sum of
    ``Q(s_d; theta)`` and all next cells distinct, eq. maxi:op2) over the horizon of
    ``source``, exploring: each step each drone, with probability ``epsilon``, asks for a
    uniform feasible action instead of its Q values (granted unless another drone takes that
    cell). ``net`` is held fixed for the episode and reads the states of ``variant`` (``history``:
    the nowcast's, for a variant that reads it)."""
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

    return _swarm_episode(source, n_drones, params, rng, choose, variant, history)


class SightedBelief:
    """The nowcast of an episode: the filter on ``history``, advanced to each step and updated
    on the free cells in the drones' fields of view with the importance seen there, of the
    variance ``sighting`` gives (as :class:`twin.nowcast_gain.NowcastGainPolicy` sights)."""

    def __init__(self, history: History, grid, sighting: SightingModel = EXACT_SIGHTINGS):
        self.filter = NowcastFilter(history, sighting=sighting)
        self.grid = grid
        self.free = grid.free.ravel()

    def at(self, k: int, positions: np.ndarray, importance: np.ndarray):
        """``(mean, std)`` at step ``k`` once the drones at ``positions`` saw ``importance``."""
        self.filter.advance(k)
        flat, valid = self.grid.view_index(positions)
        cells = np.unique(flat[valid])
        cells = cells[self.free[cells]]
        self.filter.observe(cells, np.asarray(importance, dtype=np.float64).ravel()[cells])
        return self.filter.mean(), self.filter.std()


def _swarm_episode(source, n_drones, params, rng, choose, variant: StateVariant,
                   history: History | None = None) -> Episode:  # fmt: skip
    """Every transition of a swarm whose actions are ``choose(state, drone_states)``, the
    drones' states built by ``variant`` (on the nowcast of ``history`` when it reads one)."""
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
    belief = None
    if variant.needs_belief:
        if history is None:
            raise ValueError(f"state {variant.name!r} needs a history for its nowcast")
        belief = SightedBelief(history, grid)

    def states_of(state, k):
        seen = None if belief is None else belief.at(k, state.positions, state.importance)
        return variant.states(grid, state.idleness, state.importance, state.positions,
                              belief=seen)  # fmt: skip

    maps = source.importance_maps()
    state = initial_state(grid, random_starts(grid, n_drones, rng), next(maps))
    states = states_of(state, 0)
    for k in range(horizon):
        actions = choose(state, states)
        state, out = step(state, actions, next(maps), grid, params)
        next_states = states_of(state, k + 1)
        ep.states[k], ep.actions[k], ep.rewards[k] = states, actions, out.rewards
        ep.next_states[k], ep.next_feasible[k] = next_states, out.feasible
        states = next_states
    return ep
