"""Decision time of the central coordinator (eq. maxi:op2), against the previous algorithm.

- swarms of 4, 64, 256 and 1024 drones on a 200 x 300 grid, and of 200 drones on a 100 x 150
  grid (the city scale of configs/shenzhen-city-scale.toml), positions drawn uniformly
  ("spread") and packed into a square block one cell apart ("packed-1": every cell of the
  block holds a drone) or two cells apart ("packed-2": neighbours share the cell between);
- the baseline is the previous algorithm (every colliding component solved on its own), kept
  below as ``previous_coordinate``; both run in this process, calls interleaved, and must
  reach the same optimum (Q sum and number of shared cells) on every case;
- against brute-force enumeration of the 5^N joint actions for N = 2..7 drones crowded on a
  small grid (same optimum checked).

Exits 1 when two solvers disagree.

    python benchmarks/bench_coordinator.py [--quick]
"""

from __future__ import annotations

import argparse
import sys
import time

import numpy as np
from scipy.optimize import linear_sum_assignment
from scipy.sparse import csr_matrix
from scipy.sparse.csgraph import connected_components, min_weight_full_bipartite_matching

from twin.coordinator import brute_force, coordinate
from twin.grid import ACTION_DELTAS, Grid


def interleaved(fns, repeats: int) -> list[float]:
    """Median seconds per call of each function, calls interleaved (load hits all alike)."""
    for fn in fns:
        fn()
    times = [[] for _ in fns]
    for _ in range(repeats):
        for fn, out in zip(fns, times, strict=True):
            t0 = time.perf_counter()
            fn()
            out.append(time.perf_counter() - t0)
    return [float(np.median(t)) for t in times]


def spread(grid: Grid, n: int, rng) -> np.ndarray:
    free = grid.free_cells()
    return free[rng.choice(len(free), size=n, replace=False)]


def packed(gap: int):
    def layout(grid: Grid, n: int, rng) -> np.ndarray:
        side = int(np.ceil(np.sqrt(n)))
        cells = np.array([(i, j) for i in range(side) for j in range(side)])[:n]
        return cells * gap + [grid.nx // 2 - side, grid.ny // 2 - side]

    layout.__name__ = f"packed-{gap}"
    return layout


def outcome(q, positions, actions, grid) -> tuple[int, float]:
    """(shared next cells, Q sum) of a joint action."""
    n = len(q)
    shared = n - len(np.unique(grid.move(positions, actions), axis=0))
    return shared, float(q[np.arange(n), actions].sum())


def same(a: tuple[int, float], b: tuple[int, float]) -> bool:
    return a[0] == b[0] and bool(np.isclose(a[1], b[1], rtol=1e-12, atol=1e-9))


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    p.add_argument("--quick", action="store_true", help="fewer repeats and smaller swarms")
    args = p.parse_args()
    rng = np.random.default_rng(0)
    repeats = 10 if args.quick else 100
    grid, city = Grid.open(200, 300), Grid.open(100, 150)
    cases = [(grid, spread, n) for n in (4, 64, 256, 1024)]
    cases += [(grid, packed(1), 1024), (grid, packed(2), 1024)]
    cases += [(city, layout, 200) for layout in (spread, packed(1), packed(2))]
    if args.quick:
        cases = [(grid, spread, 64), (grid, spread, 1024), (grid, packed(1), 256)]
        cases += [(grid, packed(2), 256), (city, spread, 200)]
    failed = []
    print(f"coordinator (median of {repeats} interleaved calls)")
    print(
        f"{'cells':>10s} {'drones':>7s} {'layout':>9s} {'ms':>8s} {'previous ms':>12s} "
        f"{'speed-up':>9s} same"
    )
    for grid, layout, n in cases:
        pos = layout(grid, n, rng)
        q = rng.normal(size=(n, 5))
        feasible = grid.feasible_actions(pos)
        ours, before = interleaved(
            [
                lambda: coordinate(q, pos, feasible, grid),  # noqa: B023
                lambda: previous_coordinate(q, pos, feasible, grid),  # noqa: B023
            ],
            repeats,
        )
        a = outcome(q, pos, coordinate(q, pos, feasible, grid), grid)
        b = outcome(q, pos, previous_coordinate(q, pos, feasible, grid), grid)
        ok = same(a, b) and a[0] == 0
        if not ok:
            failed.append(f"{n} {layout.__name__}: {a} against previous {b}")
        print(
            f"{f'{grid.nx} x {grid.ny}':>10s} {n:7d} {layout.__name__:>9s} {1e3 * ours:8.3f} "
            f"{1e3 * before:12.3f} "
            f"{before / ours:8.1f}x {ok}"
        )

    small = Grid.open(4, 5)
    print(f"\nagainst brute force on a {small.nx} x {small.ny} grid (crowded swarms)")
    print(f"{'drones':>7s} {'coordinator ms':>15s} {'brute force ms':>15s} {'ratio':>8s} same")
    for n in range(2, 6 if args.quick else 8):
        pos = spread(small, n, rng)
        q = rng.normal(size=(n, 5))
        feasible = small.feasible_actions(pos)
        ours = interleaved([lambda: coordinate(q, pos, feasible, small)], repeats)[0]  # noqa: B023
        brute = interleaved([lambda: brute_force(q, pos, feasible, small)], 1 if n > 5 else 3)[0]  # noqa: B023
        a = coordinate(q, pos, feasible, small)
        _, best = brute_force(q, pos, feasible, small)
        ok = bool(np.isclose(q[np.arange(n), a].sum(), best))
        if not ok:
            failed.append(f"{n} drones on {small.nx} x {small.ny}: brute force finds {best}")
        print(f"{n:7d} {1e3 * ours:15.3f} {1e3 * brute:15.1f} {brute / ours:8.0f} {ok}")
    if failed:
        sys.exit("bench_coordinator: solvers disagree: " + "; ".join(failed))


# --- the previous algorithm (main 8a31c98), the in-process baseline ------------------------


def previous_coordinate(q: np.ndarray, positions: np.ndarray, feasible: np.ndarray, grid: Grid):
    """The coordinator as it was before (main 8a31c98): every component of the "share a
    candidate cell" graph that holds a collision, solved one by one (dense or sparse
    rectangular assignment). Kept here only as the in-process baseline."""
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
    collide = _previous_duplicated(chosen)
    if not collide.any():
        return actions  # the unconstrained maximum already uses distinct cells

    labels = _previous_components(flat, feasible, n)
    todo = np.unique(labels[collide])
    members_of = np.argsort(labels, kind="stable")
    bounds = np.searchsorted(labels[members_of], np.concatenate([todo, todo + 1]))
    for start, stop in zip(bounds[: len(todo)], bounds[len(todo) :], strict=True):
        members = members_of[start:stop]
        actions[members] = _previous_solve_component(q[members], flat[members], feasible[members])
    return actions


def _previous_duplicated(values: np.ndarray) -> np.ndarray:
    """Mask of entries whose value occurs more than once."""
    _, inverse, counts = np.unique(values, return_inverse=True, return_counts=True)
    return counts[inverse] > 1


def _previous_components(flat: np.ndarray, feasible: np.ndarray, n: int) -> np.ndarray:
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
PREVIOUS_SPARSE_ABOVE = 48


def _previous_solve_component(q: np.ndarray, flat: np.ndarray, feasible: np.ndarray) -> np.ndarray:
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
    if m > PREVIOUS_SPARSE_ABOVE:
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


if __name__ == "__main__":
    main()
