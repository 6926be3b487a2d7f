"""Idleness (Def. 3), the patrolling score (Def. 4), coverage (Def. 5), and the 13-value
drone state (eq. s), vectorised over drones.

The score follows ``shared/notes/paper-notes.md``, "The headline score": each step pays the
visit gain of every DISTINCT cell the swarm visits, once (:func:`rewards_on_arrival`). Def. 4
as printed (every drone paid its whole field of view on arrival) is kept as a comparison
column, :func:`paper_rewards`, which formations game.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from twin.grid import Grid

STATE_SIZE = 13
#: Names of the 13 state values, in order (eq. s as read in the project notes).
STATE_LAYOUT: tuple[str, ...] = (
    "i/nx", "j/ny",
    "IT_centre", "IT_up", "IT_down", "IT_left", "IT_right",
    "nu_down", "nu_up", "nu_left", "nu_right",
    "i_cm/nx", "j_cm/ny",
)  # fmt: skip


@dataclass(frozen=True)
class ScoreParams:
    """Forgetting ``eta`` and recovery ``delta`` of Def. 3, reward weights of Def. 4."""

    eta: float = 0.1
    delta: float = 0.025
    alpha_T: float = 1.0
    alpha_I: float = 0.5


def initial_idleness(grid: Grid) -> np.ndarray:
    """``I^0``: 1 on free cells (nothing observed yet), 0 on obstacles."""
    return grid.free.astype(np.float64)


def recovered_idleness(idleness: np.ndarray, grid: Grid, delta: float) -> np.ndarray:
    """``Ibar = min(1, I + delta)`` on free cells, 0 on obstacles."""
    new = idleness + delta
    np.minimum(new, 1.0, out=new)
    new *= grid.free_float
    return new


def update_idleness(
    idleness: np.ndarray, positions: np.ndarray, grid: Grid, eta: float, delta: float
) -> np.ndarray:
    """Def. 3: visited cells ``eta * I``, other free cells ``min(1, I + delta)``, obstacles 0.

    A cell visited by several drones is reduced once.
    """
    new = recovered_idleness(idleness, grid, delta)
    i, j = positions[:, 0], positions[:, 1]
    new[i, j] = eta * idleness[i, j]
    return new


def visit(visited: np.ndarray, positions: np.ndarray) -> None:
    """Mark the cells the drones stand on as visited (in place)."""
    visited[positions[:, 0], positions[:, 1]] = True


def visit_gain(weight: np.ndarray, idleness: np.ndarray, params: ScoreParams) -> np.ndarray:
    """Gain of visiting a cell: ``weight * (min(1, I + delta) - eta I)``.

    ``weight = alpha_T T + alpha_I``; the bracket is how much lower the cell's idleness is
    after the visit (``eta I``, Def. 3) than without it (``min(1, I + delta)``).
    """
    return weight * (np.minimum(1.0, idleness + params.delta) - params.eta * idleness)


@dataclass(frozen=True)
class RewardParts:
    """Per-drone rewards of one step, each ``(N,)``.

    ``importance`` and ``idleness`` are the alpha_T and alpha_I parts of the headline reward
    (:func:`rewards_on_arrival`; their sum, :attr:`total`, adds up over drones to ``R^k``).
    ``paper`` is Def. 4 as printed, every drone paid its whole field of view on arrival: kept
    for comparison with the paper, and gameable (overlapping views and stacked drones are paid
    several times for one visit).
    """

    importance: np.ndarray
    idleness: np.ndarray
    paper: np.ndarray

    @property
    def total(self) -> np.ndarray:
        return self.importance + self.idleness


def reward_parts(
    grid: Grid,
    params: ScoreParams,
    idleness: np.ndarray,
    importance: np.ndarray,
    next_importance: np.ndarray,
    positions: np.ndarray,
    next_positions: np.ndarray,
) -> RewardParts:
    """The headline reward's parts and the paper's accounting; see :func:`rewards_on_arrival`
    and :func:`paper_rewards` for the formulas."""
    i, j = next_positions[:, 0], next_positions[:, 1]
    share = 1.0 / _sharing(i * grid.ny + j)
    bracket = visit_gain(np.ones(len(i)), idleness[i, j], params) * share
    return RewardParts(
        importance=params.alpha_T * next_importance[i, j] * bracket,
        idleness=params.alpha_I * bracket,
        paper=paper_rewards(
            grid, params, idleness, importance, next_importance, positions, next_positions
        ),
    )


def rewards_on_arrival(
    grid: Grid,
    params: ScoreParams,
    idleness: np.ndarray,
    importance: np.ndarray,
    next_importance: np.ndarray,
    positions: np.ndarray,
    next_positions: np.ndarray,
) -> np.ndarray:
    """Per-drone reward ``r_d^k`` of the headline score: the gain of the visit a drone makes.

    A drone arriving on ``c = p'_d`` is paid ``g(c) / m(c)``, with ``m(c)`` the number of drones
    arriving on ``c`` and, for ``I^k`` after step k's reset and ``T^{k+1}`` seen on arrival,

        g(c) = (alpha_T T^{k+1}(c) + alpha_I) (min(1, I^k(c) + delta) - eta I^k(c)),

    the value Def. 3's reset removes from ``c``. So the swarm's ``R^k = sum_d r_d^k`` is the sum
    of ``g`` over the DISTINCT cells visited, each paid once however many drones stand on it or
    see it. This is the project's reading of Def. 4 (``shared/notes/paper-notes.md``, "The
    headline score"), which departs from the printed Def. 4 (:func:`paper_rewards`): that pays
    every drone its field of view, so drones flying as a pack are paid several times for one
    visit. A drone that hovers earns only what recovered on its own cell (``g`` of an idleness
    near 0 is about ``weight * delta``). ``positions`` and ``importance`` (``P_k``, ``T^k``) are
    not used; they keep the signature of :func:`paper_rewards`.
    """
    return reward_parts(
        grid, params, idleness, importance, next_importance, positions, next_positions
    ).total


def paper_rewards(
    grid: Grid,
    params: ScoreParams,
    idleness: np.ndarray,
    importance: np.ndarray,
    next_importance: np.ndarray,
    positions: np.ndarray,
    next_positions: np.ndarray,
) -> np.ndarray:
    """Def. 4 as printed, read on arrival: gameable by overlapping views and stacking.

    For drone ``d`` moving ``p -> p'``, with ``Ibar = min(1, I^k + delta)`` on free cells::

        A_T = sum_{Adj(p')} Ibar T^{k+1}     B_T = sum_{Adj(p)} I^k T^k
        A_I = sum_{Adj(p')} Ibar             B_I = sum_{Adj(p)} I^k
        r_d = alpha_T (A_T - B_T) + alpha_I (A_I - B_I)

    Summed over a horizon this is (up to end terms) every visit gain counted once per drone
    whose field of view holds the visited cell: a 1 x 4 line of drones is paid about three
    times for each visit. Reported beside the headline, never used to rank or to learn.
    """
    here, there = grid.view_index(positions), grid.view_index(next_positions)
    arrive = np.minimum(1.0, grid.values_in_view(idleness, None, there) + params.delta)
    arrive *= grid.values_in_view(grid.free_float, None, there)
    leave = grid.values_in_view(idleness, None, here)
    a_t = (arrive * grid.values_in_view(next_importance, None, there)).sum(axis=1)
    b_t = (leave * grid.values_in_view(importance, None, here)).sum(axis=1)
    return params.alpha_T * (a_t - b_t) + params.alpha_I * (arrive.sum(axis=1) - leave.sum(axis=1))


def _sharing(cells: np.ndarray) -> np.ndarray:
    """For every drone, how many drones stand on its cell (``cells``: flat cell indices)."""
    _, inverse, counts = np.unique(cells, return_inverse=True, return_counts=True)
    return counts[inverse].astype(np.float64)


def coverage(idleness: np.ndarray, grid: Grid) -> float:
    """Def. 5: ``C^k = 1 - mean idleness over free cells``."""
    return 1.0 - float(idleness.sum(where=grid.free)) / grid.n_free


def directional_idleness(idleness: np.ndarray, grid: Grid, positions: np.ndarray) -> np.ndarray:
    """``(N, 4)`` mean idleness of free cells strictly below, above, left, right of each drone.

    ``idleness`` is one map ``(nx, ny)`` or one map per drone ``(N, nx, ny)`` (drone ``d`` reads
    ``idleness[d]``). Prefix sums over the one map, O(cells); over each drone's own row and
    column only, O(N (nx + ny)), with a map per drone. 0 where a direction holds no free cell.
    """
    i, j = positions[:, 0], positions[:, 1]
    if idleness.ndim == 3:
        d = np.arange(len(positions))
        return directional_means(idleness[d, i, :], idleness[d, :, j], grid, positions)
    values = idleness * grid.free_float
    col_cum, row_cum = values.cumsum(axis=0), values.cumsum(axis=1)
    return _means(grid, positions, values[i, j], col_cum[i, j], col_cum[-1, j],
                  row_cum[i, j], row_cum[i, -1])  # fmt: skip


def directional_means(
    rows: np.ndarray, cols: np.ndarray, grid: Grid, positions: np.ndarray
) -> np.ndarray:
    """:func:`directional_idleness` from each drone's own row ``(N, ny)`` and column ``(N, nx)``
    of its map (a drone at ``(i, j)`` reads row ``i`` and column ``j``).

    Prefix sums along the row and the column: the same sequential sums as prefix sums over the
    whole map, so the same bits.
    """
    i, j = positions[:, 0], positions[:, 1]
    n = np.arange(len(positions))
    col_cum = (cols * grid.free_float[:, j].T).cumsum(axis=1)
    row_cum = (rows * grid.free_float[i, :]).cumsum(axis=1)
    own = rows[n, j] * grid.free_float[i, j]
    return _means(grid, positions, own, col_cum[n, i], col_cum[:, -1],
                  row_cum[n, j], row_cum[:, -1])  # fmt: skip


def _means(grid, positions, own_v, col_i, col_end, row_j, row_end) -> np.ndarray:
    """The four means from the prefix sums of each drone's column and row at its cell and at
    their ends (``own_v``: the value at its cell)."""
    i, j = positions[:, 0], positions[:, 1]
    col_n, row_n, own_n = grid.free_cumsum_down, grid.free_cumsum_right, grid.free_float[i, j]
    sums = np.empty((len(positions), 4))
    ns = np.empty((len(positions), 4))
    sums[:, 0], ns[:, 0] = col_end - col_i, col_n[-1, j] - col_n[i, j]  # below
    sums[:, 1], ns[:, 1] = col_i - own_v, col_n[i, j] - own_n  # above
    sums[:, 2], ns[:, 2] = row_j - own_v, row_n[i, j] - own_n  # left
    sums[:, 3], ns[:, 3] = row_end - row_j, row_n[i, -1] - row_n[i, j]  # right
    return np.divide(sums, ns, out=np.zeros_like(sums), where=ns > 0)


def others_centre_of_mass(positions: np.ndarray) -> np.ndarray:
    """``(N, 2)`` mean cell of the other drones; a lone drone gets its own position."""
    n = len(positions)
    if n == 1:
        return positions.astype(np.float64)
    total = positions.sum(axis=0, dtype=np.float64)
    return (total[None, :] - positions) / (n - 1)


def drone_states(
    grid: Grid,
    idleness: np.ndarray,
    importance: np.ndarray,
    positions: np.ndarray,
    others: np.ndarray | None = None,
) -> np.ndarray:
    """The ``(N, 13)`` state of eq. (s), laid out as :data:`STATE_LAYOUT`.

    ``idleness`` is the swarm's map ``(nx, ny)`` or, in the decentralized mode, one map per
    drone ``(N, nx, ny)``. ``others`` optionally gives each drone's view of the others' centre
    of mass (``(N, 2)``, in cells), as in the decentralized mode; by default the true one.
    """
    view = grid.view_index(positions)
    if idleness.ndim == 2:
        idle_seen = grid.values_in_view(idleness, None, view)
    else:
        flat, valid = view
        rows = np.arange(len(positions))[:, None]
        idle_seen = np.where(valid, idleness.reshape(len(idleness), -1)[rows, flat], 0.0)
    directional = directional_idleness(idleness, grid, positions)
    return assemble_states(grid, importance, positions, view, idle_seen, directional, others)


def assemble_states(
    grid: Grid,
    importance: np.ndarray,
    positions: np.ndarray,
    view: tuple[np.ndarray, np.ndarray],
    idle_seen: np.ndarray,
    directional: np.ndarray,
    others: np.ndarray | None = None,
) -> np.ndarray:
    """:func:`drone_states` from what each drone read of its idleness map: ``idle_seen``
    ``(N, 5)`` over its field of view ``view`` (:meth:`Grid.view_index`) and ``directional``
    ``(N, 4)`` (:func:`directional_means`)."""
    scale = np.array([grid.nx, grid.ny], dtype=np.float64)
    seen = idle_seen * grid.values_in_view(importance, None, view)
    cm = others_centre_of_mass(positions) if others is None else others
    return np.concatenate([positions / scale, seen, directional, cm / scale], axis=1)
