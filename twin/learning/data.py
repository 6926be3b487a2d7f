"""Pretraining data (Sec. III-A): transitions of a randomly moving swarm on a synthetic map.

The swarm takes uniform feasible actions and advances with :func:`twin.swarm.step`, the step of
the patrol loop: idleness per Def. 3, every drone's reward read on arrival (Def. 4).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from twin.grid import N_ACTIONS
from twin.policies import random_feasible
from twin.scores import STATE_SIZE, ScoreParams, drone_states
from twin.swarm import initial_state, random_starts, step
from twin.traffic.base import TrafficSource

__all__ = ["Episode", "random_starts", "random_swarm_episode"]


@dataclass
class Episode:
    """``(T, N, ...)`` arrays of one random-swarm episode, ready for the replay buffer."""

    states: np.ndarray
    actions: np.ndarray
    rewards: np.ndarray
    next_states: np.ndarray
    next_feasible: np.ndarray


def random_swarm_episode(
    source: TrafficSource, n_drones: int, params: ScoreParams, rng: np.random.Generator
) -> Episode:
    """Run a random swarm over the whole horizon of ``source`` and record every transition."""
    grid = source.grid
    horizon = source.horizon
    shape = (horizon, n_drones)
    ep = Episode(
        np.empty((*shape, STATE_SIZE), np.float32),
        np.empty(shape, np.int64),
        np.empty(shape, np.float32),
        np.empty((*shape, STATE_SIZE), np.float32),
        np.empty((*shape, N_ACTIONS), bool),
    )
    maps = source.importance_maps()
    state = initial_state(grid, random_starts(grid, n_drones, rng), next(maps))
    states = drone_states(grid, state.idleness, state.importance, state.positions)
    for k in range(horizon):
        actions = random_feasible(state.feasible, rng)
        state, out = step(state, actions, next(maps), grid, params)
        next_states = drone_states(grid, state.idleness, state.importance, state.positions)
        ep.states[k], ep.actions[k], ep.rewards[k] = states, actions, out.rewards
        ep.next_states[k], ep.next_feasible[k] = next_states, out.feasible
        states = next_states
    return ep
