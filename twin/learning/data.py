"""Pretraining data (Sec. III-A): transitions of a randomly moving swarm on a synthetic map.

One numpy step serves all drones: the swarm takes uniform feasible actions, the idleness map
follows Def. 3 and every drone's reward is read on arrival (Def. 4), exactly as in a patrol.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from twin.grid import N_ACTIONS, Grid
from twin.scores import (
    STATE_SIZE,
    ScoreParams,
    drone_states,
    initial_idleness,
    rewards_on_arrival,
    update_idleness,
)
from twin.traffic.base import TrafficSource


@dataclass
class Episode:
    """``(T, N, ...)`` arrays of one random-swarm episode, ready for the replay buffer."""

    states: np.ndarray
    actions: np.ndarray
    rewards: np.ndarray
    next_states: np.ndarray
    next_feasible: np.ndarray


def random_feasible_actions(feasible: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """A uniform feasible action per drone: argmax of uniform noise over the feasible set."""
    return np.argmax(np.where(feasible, rng.random(feasible.shape), -1.0), axis=1)


def random_starts(grid: Grid, n_drones: int, rng: np.random.Generator) -> np.ndarray:
    """``n_drones`` distinct free cells, uniformly."""
    free = grid.free_cells()
    if n_drones > len(free):
        raise ValueError(f"{n_drones} drones do not fit on {len(free)} free cells")
    return free[rng.choice(len(free), size=n_drones, replace=False)]


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
    importance = next(maps)
    positions = random_starts(grid, n_drones, rng)
    idleness = initial_idleness(grid)  # as twin.patrol.run_patrol: I^0 = 1 on free cells
    states = drone_states(grid, idleness, importance, positions)
    feasible = grid.feasible_actions(positions)
    for k in range(horizon):
        actions = random_feasible_actions(feasible, rng)
        next_positions = grid.move(positions, actions)
        next_importance = next(maps)
        rewards = rewards_on_arrival(
            grid, params, idleness, importance, next_importance, positions, next_positions
        )
        idleness = update_idleness(idleness, next_positions, grid, params.eta, params.delta)
        next_states = drone_states(grid, idleness, next_importance, next_positions)
        next_feasible = grid.feasible_actions(next_positions)
        ep.states[k], ep.actions[k], ep.rewards[k] = states, actions, rewards
        ep.next_states[k], ep.next_feasible[k] = next_states, next_feasible
        positions, importance, states, feasible = (
            next_positions,
            next_importance,
            next_states,
            next_feasible,
        )
    return ep
