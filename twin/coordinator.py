"""The central coordinator (eq. maxi:op2): the joint action that maximises the sum of the
drones' Q values with all next cells distinct, solved exactly as an assignment problem.

Drones are rows, candidate next cells are columns, the cost of putting drone ``d`` on the cell
reached by its feasible action ``u`` is ``-Q_d(u)``. Polynomial, never an enumeration of
``5^N`` joint actions, and only the drones that matter enter the solver:

- every drone first takes its own best action; if the chosen cells are distinct, done;
- otherwise the drones that collide, and every drone whose chosen cell one of them could take
  (recursively: the ones they can push), are solved together. The others keep their best
  action: no solved drone can reach their cells, so each already holds its row optimum and the
  two parts are independent; the joint optimum is exact;
- the solved drones go to the dense solver :func:`scipy.optimize.linear_sum_assignment`
  (drones x candidate cells) whenever its matrix has at most :data:`DENSE_ENTRIES` entries
  (about 3000 drones packed in a block); only larger sets go to the sparse solver
  :func:`scipy.sparse.csgraph.min_weight_full_bipartite_matching` (LAPJVsp), posed as a
  *square* problem (one slack row per cell, one slack column per drone; see
  :func:`_square_problem`). LAPJVsp never returned on a jam of 42 drones filling a 6 x 7 grid
  (whole-number costs too), and on 294 drones of seven such jams side by side; the dense
  solver is several times slower on large packs (about 1 ms for 1000 drones) but always
  returns.

Stay is always feasible, so when the drones stand on distinct cells a distinct assignment
always exists. Drones that stand on one cell (after a communication outage) may have no
distinct assignment; each solved drone then also owns a private "stay anyway" column with a
penalty larger than any difference of Q sums, so the solution keeps as few shared cells as
possible.
"""

from __future__ import annotations

import numpy as np
from scipy.optimize import linear_sum_assignment
from scipy.sparse import csr_matrix
from scipy.sparse.csgraph import breadth_first_order, min_weight_full_bipartite_matching

from twin.grid import ACTION_DELTAS, Grid


def coordinate(q: np.ndarray, positions: np.ndarray, feasible: np.ndarray, grid: Grid):
    """``(N,)`` actions maximising ``sum_d Q_d(u_d)`` over feasible actions with distinct
    next cells. ``q`` and ``feasible`` are ``(N, 5)``, ``positions`` ``(N, 2)``."""
    q = np.asarray(q, dtype=np.float64)
    feasible = np.asarray(feasible, dtype=bool)
    positions = np.asarray(positions, dtype=np.int64)
    n = len(q)
    masked = np.where(feasible, q, -np.inf)
    actions = masked.argmax(axis=1)
    if n <= 1:
        return actions
    # flat ids of every drone's candidate cells (off-map ones are masked by `feasible`)
    flat = (positions[:, 0] * grid.ny + positions[:, 1])[:, None] + _flat_steps(grid.ny)
    chosen = flat[np.arange(n), actions]
    collide = _duplicated(chosen)
    if not collide.any():
        return actions  # the unconstrained maximum already uses distinct cells

    n_cells = grid.nx * grid.ny
    solved = _pushed(flat, feasible, chosen, collide, n_cells)
    stacked = _duplicated(flat[solved, 0]).any()  # drones sharing a start cell
    actions[solved] = _solve(
        q[solved], masked[solved], flat[solved], feasible[solved], stacked, n_cells
    )
    return actions


def _flat_steps(ny: int) -> np.ndarray:
    """Flat-index offset of each action on a grid ``ny`` cells wide."""
    return ACTION_DELTAS[:, 0] * ny + ACTION_DELTAS[:, 1]


def _duplicated(values: np.ndarray) -> np.ndarray:
    """Mask of entries whose value occurs more than once."""
    order = np.argsort(values, kind="stable")
    ordered = values[order]
    same = ordered[1:] == ordered[:-1]
    dup = np.zeros(len(values), dtype=bool)
    dup[order[1:][same]] = True
    dup[order[:-1][same]] = True
    return dup


def _pushed(flat, feasible, chosen, collide, n_cells: int) -> np.ndarray:
    """Indices of the colliding drones and of every drone they can push, recursively.

    Graph: ``x -> y`` when ``y``'s chosen cell is a candidate cell of ``x``; the answer is
    everything reachable from the colliding drones (one breadth-first search from a virtual
    root ``n`` linked to them).
    """
    n = len(chosen)
    keep = np.flatnonzero(~collide)  # their chosen cells are distinct
    owner = np.full(n_cells, -1, dtype=np.int32)
    owner[chosen[keep]] = keep
    drone, action = np.nonzero(feasible)  # drone-major: the graph's rows in order
    pushes = owner[flat[drone, action]]
    hit = (pushes >= 0) & (pushes != drone)
    roots = np.flatnonzero(collide)
    indices = np.concatenate([pushes[hit], roots], dtype=np.int32)
    indptr = np.zeros(n + 2, dtype=np.int32)
    np.cumsum(np.bincount(drone[hit], minlength=n), out=indptr[1 : n + 1])
    indptr[n + 1] = len(indices)
    graph = csr_matrix((np.ones(len(indices)), indices, indptr), (n + 1, n + 1))
    reached = breadth_first_order(graph, n, directed=True, return_predecessors=False)
    return np.sort(reached[1:])


#: The largest dense matrix (solved drones x their candidate cells, plus private columns)
#: given to the dense solver: 10^7 entries, 80 MB.
DENSE_ENTRIES = 10**7


def _solve(q, masked, flat, feasible, stacked: bool, n_cells: int) -> np.ndarray:
    """Exact assignment of the given drones to their candidate cells (with private "stay
    anyway" columns when some of them stand on one cell)."""
    m = len(q)
    if m * (int(feasible.sum()) + m * int(stacked)) <= DENSE_ENTRIES:  # columns at most
        return _solve_dense(q, masked, flat, feasible, stacked)
    return _solve_sparse(q, masked, flat, feasible, stacked, n_cells)


def _solve_sparse(q, masked, flat, feasible, stacked: bool, n_cells: int) -> np.ndarray:
    """:func:`_solve` by LAPJVsp on the square problem (:func:`_square_problem`)."""
    graph, cells = _square_problem(q, masked, flat, feasible, stacked, n_cells)
    graph.data = _whole_costs(graph.data, graph.shape[0])
    column = min_weight_full_bipartite_matching(graph)[1][: len(q)]
    # the action reaching the matched cell; a private column (past the cells) means stay
    on_cell = column < len(cells)
    target = cells[np.minimum(column, len(cells) - 1)]
    action = ((flat == target[:, None]) & feasible).argmax(axis=1)
    return np.where(on_cell, action, 0)


def _solve_dense(q, masked, flat, feasible, stacked: bool) -> np.ndarray:
    """:func:`_solve` as a dense rectangular problem: rows the drones, columns their candidate
    cells (then a private "stay anyway" column per drone when ``stacked``), costs the
    regrets ``max_u Q - Q``, infeasible pairs infinite."""
    m = len(q)
    drone, action = np.nonzero(feasible)
    cells, col = np.unique(flat[drone, action], return_inverse=True)
    k = len(cells)
    best = masked.max(axis=1)
    cost = np.full((m, k + m * int(stacked)), np.inf)
    cost[drone, col] = best[drone] - q[drone, action]
    if stacked:
        finite = q[feasible]
        penalty = (finite.max() - finite.min() + 1.0) * m
        cost[np.arange(m), k + np.arange(m)] = best - q[:, 0] + penalty
    rows, column = linear_sum_assignment(cost)
    column = column[np.argsort(rows)]
    on_cell = column < k
    target = cells[np.minimum(column, k - 1)]
    action = ((flat == target[:, None]) & feasible).argmax(axis=1)
    return np.where(on_cell, action, 0)


def _whole_costs(costs: np.ndarray, rows: int) -> np.ndarray:
    """Costs as whole numbers (scaled by a power of two, at most 2^30, so that any sum over a
    matching stays below 2^52 and is exact): LAPJVsp can loop forever on some float inputs
    whose sums round differently along different paths (as scipy gh-17269); in exact
    arithmetic it terminates. Assignments whose float sums differ by less than about
    ``rows * 2^-30`` are ties at this resolution."""
    top = float(costs.max(initial=1.0)) * rows
    scale = min(2.0**30, 2.0 ** np.floor(np.log2(2.0**52 / top)))
    return np.maximum(np.round(costs * scale), 1.0)  # >= 1: the solver drops explicit zeros


def _square_problem(q, masked, flat, feasible, stacked: bool, n_cells: int):
    """The assignment as a square sparse matrix, and the cell behind each of its first columns.

    Rows: the ``m`` drones, then one slack row per candidate cell; columns: the ``k`` cells,
    then one slack column per drone. A cell's slack row takes the cell when no drone does, or
    else the slack column of a drone that could reach the cell. Every perfect matching is an
    assignment of drones to distinct cells and back, and all slack edges cost the same, so
    the optimum is the drones' optimum. A drone's own slack column is its private "stay
    anyway" column (only when ``stacked``). Costs are regrets ``max_u Q - Q + 1 >= 1``: the
    solver drops explicit zeros.
    """
    m = len(q)
    drone, action = np.nonzero(feasible)  # drone-major
    cell = flat[drone, action]
    used = np.zeros(n_cells, dtype=bool)
    used[cell] = True
    cells = np.flatnonzero(used)
    k = len(cells)
    column_of = np.empty(n_cells, dtype=np.int32)
    column_of[cells] = np.arange(k, dtype=np.int32)
    col = column_of[cell]
    best = masked.max(axis=1)
    regret = best[drone] - q[drone, action] + 1.0
    private = int(stacked)
    # drone rows: their cells (then their private column)
    per_drone = np.bincount(drone, minlength=m) + private
    d_ptr = np.zeros(m + 1, dtype=np.int32)
    np.cumsum(per_drone, out=d_ptr[1:])
    d_idx = np.empty(d_ptr[-1], dtype=np.int32)
    d_val = np.empty(d_ptr[-1])
    slot = np.arange(len(drone)) + private * drone  # entries shift by one per earlier drone
    d_idx[slot], d_val[slot] = col, regret
    if stacked:
        finite = q[feasible]
        penalty = (finite.max() - finite.min() + 1.0) * m
        last = d_ptr[1:] - 1
        d_idx[last], d_val[last] = k + np.arange(m), best - q[:, 0] + 1.0 + penalty
    # slack rows (one per cell, in cell order): the cell itself, then the drones reaching it
    s_ptr = np.zeros(k + 1, dtype=np.int32)
    np.cumsum(np.bincount(col, minlength=k) + 1, out=s_ptr[1:])
    if stacked:  # rank the drones reaching each cell by a stable sort
        by_cell = np.argsort(col, kind="stable")
        rank = np.empty(len(col), dtype=np.int64)
        rank[by_cell] = np.arange(1, len(col) + 1) - (s_ptr[col[by_cell]] - col[by_cell])
    else:  # distinct positions: at most one drone reaches a cell by each action
        reaches = np.zeros((k, 5), dtype=np.int32)
        reaches[col, action] = 1
        for u in range(1, 5):  # running count along the actions
            reaches[:, u] += reaches[:, u - 1]
        rank = reaches[col, action]
    # rank is 1-based: slot 0 of a slack row is the cell itself
    s_idx = np.empty(s_ptr[-1], dtype=np.int32)
    s_idx[s_ptr[:-1]] = np.arange(k)
    s_idx[s_ptr[col] + rank] = k + drone
    indptr = np.concatenate([d_ptr, d_ptr[-1] + s_ptr[1:]])
    data = np.concatenate([d_val, np.ones(len(s_idx))])
    graph = csr_matrix((data, np.concatenate([d_idx, s_idx]), indptr), shape=(m + k, m + k))
    return graph, cells


def brute_force(q: np.ndarray, positions: np.ndarray, feasible: np.ndarray, grid: Grid):
    """Reference solution by enumerating every joint action (tests and benchmarks only).

    Returns ``(actions, best_sum)``; ``best_sum`` is ``-inf`` when no joint action with
    distinct next cells exists.
    """
    import itertools

    n = len(q)
    cells = positions[:, None, :] + ACTION_DELTAS[None, :, :]
    flat = cells[..., 0] * grid.ny + cells[..., 1]
    options = [np.flatnonzero(feasible[d]) for d in range(n)]
    best, best_sum = None, -np.inf
    for joint in itertools.product(*options):
        joint = np.array(joint)
        targets = flat[np.arange(n), joint]
        if len(np.unique(targets)) < n:
            continue
        total = q[np.arange(n), joint].sum()
        if total > best_sum:
            best, best_sum = joint, total
    return best, best_sum
