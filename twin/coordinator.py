"""The central coordinator (eq. maxi:op2): the joint action that maximises the sum of the
drones' Q values with all next cells distinct, solved exactly as an assignment problem.

Drones are rows, candidate next cells are columns, the cost of putting drone ``d`` on the cell
reached by its feasible action ``u`` is ``-Q_d(u)``. Two drones more than two cells apart
share no candidate cell and never compete, so the "share a candidate cell" graph is split
into connected components and only components whose unconstrained choices collide are solved,
each with :func:`scipy.optimize.linear_sum_assignment` (large components with the sparse
solver :func:`scipy.sparse.csgraph.min_weight_full_bipartite_matching`, same optimum):
polynomial in the component's size, never an enumeration of ``5^N`` joint actions.

Stay is always feasible, so when the drones stand on distinct cells a distinct assignment
always exists. Drones that stand on one cell (after a communication outage) may have no
distinct assignment; each drone then also owns a private "stay anyway" column with a penalty
larger than any difference of Q sums, so the solution keeps as few shared cells as possible.
"""

from __future__ import annotations

import numpy as np
from scipy.optimize import linear_sum_assignment
from scipy.sparse import csr_matrix
from scipy.sparse.csgraph import connected_components, min_weight_full_bipartite_matching

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
    cells = positions[:, None, :] + ACTION_DELTAS[None, :, :]
    flat = cells[..., 0] * grid.ny + cells[..., 1]
    chosen = flat[np.arange(n), actions]
    collide = _duplicated(chosen)
    if not collide.any():
        return actions  # the unconstrained maximum already uses distinct cells

    labels = _components(flat, feasible, n)
    todo = np.unique(labels[collide])
    members_of = np.argsort(labels, kind="stable")
    bounds = np.searchsorted(labels[members_of], np.concatenate([todo, todo + 1]))
    for start, stop in zip(bounds[: len(todo)], bounds[len(todo) :], strict=True):
        members = members_of[start:stop]
        actions[members] = _solve_component(q[members], flat[members], feasible[members])
    return actions


def _duplicated(values: np.ndarray) -> np.ndarray:
    """Mask of entries whose value occurs more than once."""
    _, inverse, counts = np.unique(values, return_inverse=True, return_counts=True)
    return counts[inverse] > 1


def _components(flat: np.ndarray, feasible: np.ndarray, n: int) -> np.ndarray:
    """Component label of every drone in the graph "shares a candidate cell".

    Drones that share no cell with anyone are singletons; only the others enter the graph.
    """
    drone, action = np.nonzero(feasible)
    cell = flat[drone, action]
    order = np.argsort(cell, kind="stable")
    cell, drone = cell[order], drone[order]
    same = cell[1:] == cell[:-1]  # chain the drones listed under one cell
    rows, cols = drone[:-1][same], drone[1:][same]
    labels = np.arange(n)  # singletons keep their own index as label
    nodes = np.unique(np.concatenate([rows, cols]))
    r, c = np.searchsorted(nodes, rows), np.searchsorted(nodes, cols)
    by_row = np.argsort(r, kind="stable")
    indptr = np.searchsorted(r[by_row], np.arange(len(nodes) + 1))
    graph = csr_matrix(
        (np.ones(len(r), dtype=np.int8), c[by_row], indptr), shape=(len(nodes), len(nodes))
    )
    sub = connected_components(graph, directed=False)[1]
    labels[nodes] = n + sub  # component labels after every drone index
    return labels


#: Components with more drones than this are solved with the sparse assignment solver.
SPARSE_ABOVE = 48


def _solve_component(q: np.ndarray, flat: np.ndarray, feasible: np.ndarray) -> np.ndarray:
    """Exact assignment for one component: rows drones, columns its candidate cells plus one
    private penalised "stay" column per drone (used only if no distinct assignment exists)."""
    m = len(q)
    drone, action = np.nonzero(feasible)
    cells, col = np.unique(flat[drone, action], return_inverse=True)
    k = len(cells)
    finite = q[feasible]
    penalty = (finite.max() - finite.min() + 1.0) * m
    # edges: (drone, its candidate cell) at cost -Q, (drone, its private column) at penalty
    rows = np.concatenate([drone, np.arange(m)])
    cols = np.concatenate([col, k + np.arange(m)])
    costs = np.concatenate([-q[drone, action], penalty - q[:, 0]])
    acts = np.concatenate([action, np.zeros(m, dtype=np.int64)])  # private column = stay
    if m > SPARSE_ABOVE:
        # every drone takes exactly one edge, so shifting all costs to >= 1 keeps the optimum
        # (the sparse solver treats an explicit 0 as a missing edge)
        shifted = costs - costs.min() + 1.0
        graph = csr_matrix((shifted, (rows, cols)), shape=(m, k + m))
        match = min_weight_full_bipartite_matching(graph)[1]
        chosen = np.arange(m), match
    else:
        cost = np.full((m, k + m), np.inf)
        cost[rows, cols] = costs
        chosen = linear_sum_assignment(cost)
    action_of = np.zeros((m, k + m), dtype=np.int64)
    action_of[rows, cols] = acts
    out = np.empty(m, dtype=np.int64)
    out[chosen[0]] = action_of[chosen]
    return out


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
