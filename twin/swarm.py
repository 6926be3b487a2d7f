"""The one swarm step: move, pay each visited cell's gain once (Def. 4 as the project reads
it), update idleness (Def. 3).

The patrol loop, the pretraining rollouts and the environment (:mod:`twin.env`) all advance a
swarm with :func:`step`. A :class:`SwarmState` holds what the step needs at step ``k``: the
positions ``P_k``, the shared idleness map ``I^k`` (after step k's reset), the importance map
``T^k``, the cells visited so far and the feasible actions ``U_d(p)``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from twin.errors import UserError
from twin.grid import ACTIONS, N_ACTIONS, Grid
from twin.scores import ScoreParams, initial_idleness, reward_parts, update_idleness


class InfeasibleActionError(UserError, ValueError):
    """An action leaves the map or enters an obstacle (or is not an action at all)."""


@dataclass(frozen=True)
class SwarmState:
    """The swarm at step ``k``."""

    k: int
    positions: np.ndarray  # (N, 2) int: P_k
    idleness: np.ndarray  # (nx, ny): I^k
    importance: np.ndarray  # (nx, ny): T^k
    visited: np.ndarray  # (nx, ny) bool: cells stood on at steps 0..k
    feasible: np.ndarray  # (N, 5) bool: U_d(p) at P_k
    #: (N,) bool: the drones whose arrival at P_k was recorded (None: all; see twin.faults)
    recorded: np.ndarray | None = None


@dataclass(frozen=True)
class StepOutcome:
    """What one step paid, per drone (``(N,)`` each), and ``U_d`` at the new positions."""

    rewards: np.ndarray  # r_d^k: the gain of the drone's visit, shared on a shared cell
    importance: np.ndarray  # its alpha_T part
    idleness: np.ndarray  # its alpha_I part
    paper: np.ndarray  # Def. 4 as printed: every drone paid its field of view (gameable)
    feasible: np.ndarray  # (N, 5) bool at P_{k+1}


def random_starts(grid: Grid, n_drones: int, rng: np.random.Generator) -> np.ndarray:
    """``n_drones`` distinct free cells drawn uniformly."""
    free = grid.free_cells()
    if n_drones > len(free):
        raise ValueError(f"{n_drones} drones do not fit on {len(free)} free cells")
    return free[rng.choice(len(free), size=n_drones, replace=False)]


def initial_state(grid: Grid, positions: np.ndarray, importance: np.ndarray) -> SwarmState:
    """The swarm at step 0: ``I^0`` = 1 on free cells, the start cells visited."""
    positions = np.asarray(positions, dtype=np.int64)
    visited = np.zeros(grid.shape, dtype=bool)
    visited[positions[:, 0], positions[:, 1]] = True
    return SwarmState(
        0, positions, initial_idleness(grid), importance, visited, grid.feasible_actions(positions)
    )


def step(
    state: SwarmState,
    actions: np.ndarray,
    next_importance: np.ndarray,
    grid: Grid,
    params: ScoreParams,
    recorded: np.ndarray | None = None,
) -> tuple[SwarmState, StepOutcome]:
    """Advance the swarm one step: ``P_{k+1} = P_k + u^k``, ``r^k`` (the headline reward), ``I^{k+1}``.

    ``recorded`` ``(N,)`` bool: the drones whose arrival at ``P_{k+1}`` counts (a scripted
    fault, :mod:`twin.faults`: a lost drone, a missed sighting); the others are paid nothing
    and reset no idleness. None: every drone's.
    Raises :class:`InfeasibleActionError` when an action is not in ``U_d(p)``.
    """
    actions = check_actions(state, actions)
    if recorded is not None:
        return _step_recorded(state, actions, next_importance, grid, params, recorded)
    nxt = grid.move(state.positions, actions)
    parts = reward_parts(
        grid, params, state.idleness, state.importance, next_importance, state.positions, nxt
    )
    idle = update_idleness(state.idleness, nxt, grid, params.eta, params.delta)
    visited = state.visited.copy()
    visited[nxt[:, 0], nxt[:, 1]] = True
    feasible = grid.feasible_actions(nxt)
    return (
        SwarmState(state.k + 1, nxt, idle, next_importance, visited, feasible),
        StepOutcome(parts.total, parts.importance, parts.idleness, parts.paper, feasible),
    )


def _step_recorded(state, actions, next_importance, grid, params, recorded):
    """:func:`step` with only the ``recorded`` drones' arrivals paid and visited."""
    nxt = grid.move(state.positions, actions)
    rec = np.asarray(recorded, dtype=bool)
    zero = np.zeros(len(nxt))
    total, importance, idleness, paper = zero, zero.copy(), zero.copy(), zero.copy()
    if rec.any():
        parts = reward_parts(
            grid, params, state.idleness, state.importance, next_importance,
            state.positions[rec], nxt[rec],
        )  # fmt: skip
        total, importance, idleness, paper = (zero.copy() for _ in range(4))
        total[rec], importance[rec] = parts.total, parts.importance
        idleness[rec], paper[rec] = parts.idleness, parts.paper
    idle = update_idleness(state.idleness, nxt[rec], grid, params.eta, params.delta)
    visited = state.visited.copy()
    visited[nxt[rec, 0], nxt[rec, 1]] = True
    feasible = grid.feasible_actions(nxt)
    return (
        SwarmState(state.k + 1, nxt, idle, next_importance, visited, feasible, rec.copy()),
        StepOutcome(total, importance, idleness, paper, feasible),
    )


def check_actions(state: SwarmState, actions) -> np.ndarray:
    """``actions`` as int64 if every drone's action is in ``U_d(p)``, else an
    :class:`InfeasibleActionError` naming the first bad one."""
    actions = np.asarray(actions)
    n = len(state.positions)
    if actions.shape != (n,) or not np.issubdtype(actions.dtype, np.integer):
        raise InfeasibleActionError(
            f"need {n} integer actions (one per drone), got {actions.dtype} {actions.shape}"
        )
    actions = actions.astype(np.int64, copy=False)
    bad = (actions < 0) | (actions >= N_ACTIONS)
    if bad.any():
        d = int(np.flatnonzero(bad)[0])
        raise InfeasibleActionError(
            f"step {state.k}: drone {d}: action {int(actions[d])} is not one of 0..{N_ACTIONS - 1} "
            f"({', '.join(ACTIONS)})"
        )
    ok = state.feasible[np.arange(n), actions]
    if not ok.all():
        d = int(np.flatnonzero(~ok)[0])
        i, j = (int(v) for v in state.positions[d])
        raise InfeasibleActionError(
            f"step {state.k}: drone {d} at ({i}, {j}): action {int(actions[d])} "
            f"({ACTIONS[actions[d]]}) leaves the map or enters an obstacle"
        )
    return actions
