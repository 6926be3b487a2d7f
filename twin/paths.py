"""Paths over the free cells of a grid: the 4-neighbour graph, its largest connected area, and
shortest paths between cells (the sweep's detours, the tours' transfers)."""

from __future__ import annotations

import numpy as np
from scipy.sparse import csr_matrix
from scipy.sparse.csgraph import connected_components, dijkstra

from twin.grid import Grid


def free_cell_graph(grid: Grid) -> csr_matrix:
    """The 4-neighbour graph of free cells, nodes numbered ``i * ny + j``."""
    nx, ny = grid.shape
    flat = np.arange(nx * ny).reshape(nx, ny)
    rows, cols = [], []
    for di, dj in ((1, 0), (0, 1)):
        a = flat[: nx - di, : ny - dj]
        b = flat[di:, dj:]
        ok = grid.free[: nx - di, : ny - dj] & grid.free[di:, dj:]
        rows += [a[ok], b[ok]]
        cols += [b[ok], a[ok]]
    r, c = np.concatenate(rows), np.concatenate(cols)
    return csr_matrix((np.ones(len(r)), (r, c)), shape=(nx * ny, nx * ny))


def largest_free_component(grid: Grid) -> np.ndarray:
    """Mask of the largest 4-connected area of free cells."""
    _, labels = connected_components(free_cell_graph(grid), directed=False)
    labels = labels.reshape(grid.shape)
    counts = np.bincount(labels[grid.free])
    return grid.free & (labels == counts.argmax())


#: Roots per call of the shortest-path search in :func:`free_paths` (bounds its memory).
_ROOTS_PER_CALL = 256


def free_paths(grid: Grid, starts: np.ndarray, ends: np.ndarray) -> dict[int, list]:
    """Cells of a shortest free path from each ``starts[n]`` to ``ends[n]``, keyed by ``n``
    (left out when they lie in different connected areas): walked back from the start along Dijkstra's tree rooted
    at the end (``scipy.sparse.csgraph.dijkstra``, unweighted).

    The search from each root stops at a distance ``limit`` (tried at 8, then x4 until the
    start is reached). The tree up to the limit is the unlimited tree's: every node within
    ``limit`` gets its predecessor while nodes closer than ``limit`` are scanned, and until
    then both searches do the same heap operations. So the paths are the ones of one full
    search per root, at a fraction of the cost.
    """
    graph = free_cell_graph(grid)
    ny = grid.ny
    start = starts[:, 0] * ny + starts[:, 1]
    end = ends[:, 0] * ny + ends[:, 1]
    paths: dict[int, list] = {}
    todo, limit = np.arange(len(start)), 8.0
    while len(todo):
        roots = np.unique(end[todo])
        if limit >= grid.nx * grid.ny:
            limit = np.inf
        for chunk in range(0, len(roots), _ROOTS_PER_CALL):
            some = roots[chunk : chunk + _ROOTS_PER_CALL]
            _, pred = dijkstra(
                graph, indices=some, unweighted=True, limit=limit, return_predecessors=True
            )
            row_of = {int(r): k for k, r in enumerate(some)}
            for n in todo[np.isin(end[todo], some)]:
                path = _walk(pred[row_of[int(end[n])]], int(start[n]), int(end[n]), ny)
                if path is not None:
                    paths[int(n)] = path
        todo = np.array([n for n in todo if int(n) not in paths], dtype=np.int64)
        if limit == np.inf:  # searched without a limit: the rest lie in another area
            break
        limit *= 4
    return paths


def _walk(pred: np.ndarray, node: int, target: int, ny: int) -> list | None:
    """Cells from ``node`` to ``target`` along a predecessor row; None if not reached."""
    if node != target and pred[node] < 0:
        return None
    path = []
    while node != target:
        path.append((node // ny, node % ny))
        node = int(pred[node])
    path.append((target // ny, target % ny))
    return path
