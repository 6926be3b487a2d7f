"""Cyclic patrol tours: drones spaced evenly along closed walks over the cells worth patrolling.

The swarm ``tours`` (:class:`ToursPolicy`) serves the headline score (``shared/notes/
paper-notes.md``, "The headline score"): ``R^k`` pays, for every distinct cell visited, the visit
gain ``g(c) = (alpha_T T(c) + alpha_I) (min(1, I + delta) - eta I)`` (:func:`twin.scores.
visit_gain`). A cell revisited every ``P`` steps is found at the steady idleness of
:func:`visit_gain_factor`: the bracket grows by ``delta`` per step of period until the cell is
fully recovered, ``1 - eta``, at ``P = 1 + ceil((1 - eta) / delta)`` (37 steps for the
paper's eta = 0.1, delta = 0.025). Each drone visits one cell per step, so a drone step is worth
at most ``0.9 (alpha_T T + alpha_I)``, earned by visiting, once per period, the cells with the
largest weight: the multi-agent patrolling answer is closed tours over those cells with the
drones spaced evenly along them. See :class:`ToursPolicy` for the planner and its figures.
"""

from __future__ import annotations

import heapq
import inspect
import math

import numpy as np
from scipy.cluster.vq import kmeans2
from scipy.optimize import linear_sum_assignment
from scipy.sparse.csgraph import connected_components

from twin.errors import UserError
from twin.grid import Grid
from twin.paths import free_cell_graph, free_paths
from twin.planners import CoordinatedPolicy
from twin.policies import SwarmView, flag_option, number_option, whole_option
from twin.scores import ScoreParams, visit_gain

#: Score added to a drone's planned move: larger than any visit gain, so the coordinator keeps
#: every planned move unless two planned moves collide.
PLAN_BONUS = 100.0
#: Largest number of drones sharing one tour (a tour holds about ``per_tour * period`` cells
#: and is ordered by 2-opt, quadratic in its cells).
MAX_PER_TOUR = 8
#: How tours are laid out: closed walks over whole 2 x 2 blocks, each cell once (``cycles``),
#: or walks ordered by local search over the chosen cells, gaps bridged (``walks``).
LAYOUTS = ("cycles", "walks")
#: Passes of 2-opt and Or-opt over a tour at most.
TWO_OPT_PASSES = 4
#: Action index of a step ``(di, dj)``, looked up at ``(di + 1) * 3 + (dj + 1)``; -1: not a step.
_STEP_ACTION = np.array([-1, 1, -1, 3, 0, 4, -1, 2, -1], dtype=np.int64)


def visit_gain_factor(period: int, params: ScoreParams) -> float:
    """The bracket of :func:`twin.scores.visit_gain` for a cell visited every ``period`` steps,
    in the steady state: ``min(1, I + delta) - eta I`` where ``I`` is the idleness a visit finds.

    A visit leaves ``eta I``; ``period - 1`` steps of recovery later the next visit finds
    ``min(1, eta I + (period - 1) delta)``. The factor grows by ``delta`` per step of period
    until the cell is fully recovered when visited (``1 - eta``), then stays there.
    """
    eta, delta = params.eta, params.delta
    idle = 1.0
    for _ in range(200):  # the fixed point; contraction by eta < 1
        new = min(1.0, eta * idle + (period - 1) * delta)
        if abs(new - idle) < 1e-12:
            break
        idle = new
    return float(min(1.0, idle + delta) - eta * idle)


def saturation_period(params: ScoreParams) -> int:
    """The shortest revisit period at which a visit finds the cell fully recovered (``I = 1``):
    ``1 + ceil((1 - eta) / delta)`` (37 steps for eta = 0.1, delta = 0.025). Beyond it a visit
    gains no more, so a longer period only spreads the drones over worse cells."""
    if params.delta <= 0:
        return 1_000_000
    return 1 + math.ceil((1.0 - params.eta) / params.delta - 1e-9)


def best_period(weights_desc: np.ndarray, n_drones: int, params: ScoreParams) -> int:
    """The revisit period ``P`` maximising the swarm's gain per step ``n_drones * mean(top
    n_drones * P weights) * visit_gain_factor(P)``, with ``P`` up to the saturation period:
    every drone visits one tour cell per step and each cell is revisited every ``P`` steps.

    Past the period whose tours hold every cell, the gain per step stays flat until the
    saturation period (each step of period adds ``delta`` to the factor and spreads the same
    cells over one more step), so ``P`` goes up to that period at most: a tiny ``delta`` (a
    saturation period of 10^9 steps) asks for no more periods than there are cells."""
    covering = max(1, math.ceil(len(weights_desc) / max(n_drones, 1)))
    top = min(saturation_period(params), covering)
    periods = np.arange(1, top + 1)
    counts = np.minimum(periods * n_drones, len(weights_desc))
    csum = np.concatenate([[0.0], np.cumsum(weights_desc)])
    mean_w = csum[counts] / np.maximum(counts, 1)
    factor = np.array([visit_gain_factor(int(p), params) for p in periods])
    rate = mean_w * factor * np.minimum(1.0, len(weights_desc) / (periods * n_drones))
    return int(periods[np.argmax(rate)])


def closed_order(cells: np.ndarray) -> np.ndarray:
    """An order of ``cells`` ``(n, 2)`` as a short closed tour (Manhattan lengths): nearest
    neighbour from the first cell, then 2-opt. Returns indices into ``cells``."""
    n = len(cells)
    if n <= 3:
        return np.arange(n)
    dist = np.abs(cells[:, None, :] - cells[None, :, :]).sum(axis=2)
    order = _warnsdorff(cells, dist)
    for _ in range(TWO_OPT_PASSES):
        improved = _two_opt(order, dist) | _or_opt(order, dist)
        if not improved:
            break
    return order


def _warnsdorff(cells: np.ndarray, dist: np.ndarray) -> np.ndarray:
    """A walk over ``cells`` that steps to a neighbouring cell not walked yet with the fewest
    such neighbours of its own (Warnsdorff's rule: it leaves no cell stranded, so on compact
    areas it rarely has to jump); when stuck it jumps to the nearest cell not walked yet. Starts
    at a cell with the fewest neighbours (an end of the area)."""
    n = len(cells)
    adjacent = dist == 1
    free_deg = adjacent.sum(axis=1)
    left = np.ones(n, dtype=bool)
    order = np.empty(n, dtype=np.int64)
    cur = int(np.argmin(free_deg))
    for t in range(n):
        order[t], left[cur] = cur, False
        free_deg -= adjacent[cur]
        if t == n - 1:
            break
        nbrs = np.flatnonzero(adjacent[cur] & left)
        if len(nbrs):
            cur = int(nbrs[np.argmin(free_deg[nbrs])])
        else:
            cur = int(np.argmin(np.where(left, dist[cur], np.iinfo(np.int64).max)))
    return order


def _two_opt(order: np.ndarray, dist: np.ndarray) -> bool:
    """One pass of 2-opt (reverse a stretch when that shortens the tour), in place."""
    n, improved = len(order), False
    for i in range(n - 2):
        a, b = order[i], order[i + 1]
        js = np.arange(i + 2, n if i > 0 else n - 1)
        if not len(js):
            continue
        c, d = order[js], order[(js + 1) % n]
        change = dist[a, c] + dist[b, d] - dist[a, b] - dist[c, d]
        best = int(change.argmin())
        if change[best] < 0:
            j = int(js[best])
            order[i + 1 : j + 1] = order[i + 1 : j + 1][::-1].copy()
            improved = True
    return improved


def _or_opt(order: np.ndarray, dist: np.ndarray) -> bool:
    """One pass of Or-opt (move a stretch of 1 or 2 cells, either way round, between two other
    consecutive cells when that shortens the tour), in place."""
    n, improved = len(order), False
    for size in (1, 2):
        if n < size + 3:
            break
        for i in range(n - size + 1):
            seg = order[i : i + size]
            prev, nxt = order[i - 1], order[(i + size) % n]
            removed = dist[prev, seg[0]] + dist[seg[-1], nxt] - dist[prev, nxt]
            rest = np.concatenate([order[i + size :], order[:i]])  # the tour without it
            a, b = rest[:-1], rest[1:]
            fwd = dist[a, seg[0]] + dist[seg[-1], b] - dist[a, b]
            rev = dist[a, seg[-1]] + dist[seg[0], b] - dist[a, b]
            both = np.minimum(fwd, rev)
            j = int(both.argmin())
            if both[j] < removed:
                piece = seg if fwd[j] <= rev[j] else seg[::-1]
                order[:] = np.concatenate([rest[: j + 1], piece, rest[j + 1 :]])
                improved = True
    return improved


def closed_walks(grid: Grid, orders: list[np.ndarray]) -> list[np.ndarray]:
    """Each ordered list of cells as a closed walk of neighbouring free cells: consecutive cells
    (and the last with the first) that are not neighbours are joined through free cells (the
    walk's last cell is a neighbour of its first, which is not repeated).

    A diagonal gap is bridged through whichever of its two corner cells is free and not on a
    tour yet (a repeat visit finds the cell barely recovered); longer gaps by a shortest free
    path.
    """
    taken = np.zeros(grid.shape, dtype=bool)
    for cells in orders:
        taken[cells[:, 0], cells[:, 1]] = True
    starts, ends, where, joins = [], [], [], {}
    for t, cells in enumerate(orders):
        nxt = np.roll(cells, -1, axis=0)
        gaps = np.flatnonzero(np.abs(nxt - cells).sum(axis=1) > 1) if len(cells) > 1 else []
        for g in gaps:
            a, b = cells[g], nxt[g]
            corner = _corner(grid, taken, a, b)
            if corner is not None:
                taken[corner] = True
                joins[(t, int(g))] = [tuple(a), corner, tuple(b)]
                continue
            starts.append(a)
            ends.append(b)
            where.append((t, int(g)))
    if starts:  # all cells lie in one connected area
        paths = free_paths(grid, np.array(starts), np.array(ends))
        joins.update({key: paths[n] for n, key in enumerate(where)})
    walks = []
    for t, cells in enumerate(orders):
        walk = []
        for g, cell in enumerate(cells):
            walk.append(tuple(cell))
            if (t, g) in joins:
                walk.extend(joins[(t, g)][1:-1])
        walks.append(np.array(walk, dtype=np.int64).reshape(-1, 2))
    return walks


def l_path(grid: Grid, a: np.ndarray, b: np.ndarray) -> list | None:
    """A shortest path from ``a`` to ``b`` (cells ``a`` .. ``b``) going first along one axis and
    then the other, if either way is all free; else None."""
    (ai, aj), (bi, bj) = (int(v) for v in a), (int(v) for v in b)
    si = 1 if bi >= ai else -1
    sj = 1 if bj >= aj else -1
    rows = list(range(ai, bi + si, si))
    cols = list(range(aj, bj + sj, sj))
    for path in (
        [(i, aj) for i in rows] + [(bi, j) for j in cols[1:]],
        [(ai, j) for j in cols] + [(i, bj) for i in rows[1:]],
    ):
        idx = np.array(path)
        if grid.free[idx[:, 0], idx[:, 1]].all():
            return path
    return None


def _corner(grid: Grid, taken: np.ndarray, a: np.ndarray, b: np.ndarray):
    """A free cell next to both ``a`` and ``b`` (two steps apart), preferring one not taken;
    None if there is none."""
    if np.abs(b - a).sum() != 2:
        return None
    options = {(int(a[0]), int(b[1])), (int(b[0]), int(a[1]))}
    options.discard((int(a[0]), int(a[1])))
    options.discard((int(b[0]), int(b[1])))
    if not options:  # a straight gap: the cell in between
        options = {(int(a[0] + b[0]) // 2, int(a[1] + b[1]) // 2)}
    free = sorted(c for c in options if grid.free[c])
    fresh = [c for c in free if not taken[c]]
    return (fresh or free or [None])[0]


def block_regions(
    weights: np.ndarray, usable: np.ndarray, sizes: list[int]
) -> list[list[tuple[tuple[int, int], tuple[int, int] | None]]]:
    """Disjoint connected regions of blocks, grown greedily one after the other: each starts at
    the unused block of largest weight and adds the unused block of largest weight next to it
    until it holds its size (fewer if it runs out). Returns per region its blocks in the order
    added, each with the block it was reached from (None for the first): a spanning tree."""
    used = ~usable.copy()
    bnx, bny = weights.shape
    regions = []
    for size in sizes:
        key = np.where(used, -np.inf, weights)
        start = np.unravel_index(int(np.argmax(key)), key.shape)
        if not np.isfinite(key[start]):
            break
        start = (int(start[0]), int(start[1]))
        heap = [(-float(weights[start]), 0, start, None)]
        region, pushes = [], 1
        while heap and len(region) < size:
            _, _, block, parent = heapq.heappop(heap)
            if used[block]:
                continue
            used[block] = True
            region.append((block, parent))
            bi, bj = block
            for nb in ((bi - 1, bj), (bi + 1, bj), (bi, bj - 1), (bi, bj + 1)):
                if 0 <= nb[0] < bnx and 0 <= nb[1] < bny and not used[nb]:
                    heapq.heappush(heap, (-float(weights[nb]), pushes, nb, block))
                    pushes += 1
        regions.append(region)
    return regions


def block_cycle(region, offset: tuple[int, int]) -> np.ndarray:
    """The closed walk through every cell of a region of 2 x 2 blocks, each cell once, that
    goes around the region's spanning tree (spanning-tree coverage, Gabriely and Rimon): each
    block starts as the 4-cycle of its cells; joining a block to its parent swaps the two
    facing sides for two edges across. Returns ``(4 * blocks, 2)`` cells in walk order."""
    oi, oj = offset

    def cells(block):
        i, j = 2 * block[0] + oi, 2 * block[1] + oj
        return (i, j), (i, j + 1), (i + 1, j), (i + 1, j + 1)  # TL, TR, BL, BR

    edges = set()
    for block, _ in region:
        tl, tr, bl, br = cells(block)
        edges |= {frozenset(e) for e in ((tl, tr), (tr, br), (br, bl), (bl, tl))}
    for block, parent in region:
        if parent is None:
            continue
        a, b = (parent, block) if parent < block else (block, parent)  # a above or left of b
        _, atr, abl, abr = cells(a)
        btl, btr, bbl, _ = cells(b)
        if a[0] == b[0]:  # side by side
            old, new = ((atr, abr), (btl, bbl)), ((atr, btl), (abr, bbl))
        else:  # a above b
            old, new = ((abl, abr), (btl, btr)), ((abl, btl), (abr, btr))
        edges -= {frozenset(e) for e in old}
        edges |= {frozenset(e) for e in new}
    nbrs: dict = {}
    for e in edges:
        u, v = tuple(e)
        nbrs.setdefault(u, []).append(v)
        nbrs.setdefault(v, []).append(u)
    first = cells(region[0][0])[0]
    walk, prev, cur = [first], None, first
    while True:
        nxt = nbrs[cur][0] if nbrs[cur][0] != prev else nbrs[cur][1]
        if nxt == first:
            break
        walk.append(nxt)
        prev, cur = cur, nxt
    return np.array(walk, dtype=np.int64)


def survey_cells(area: np.ndarray, need: np.ndarray | None = None) -> np.ndarray:
    """Cells ``(n, 2)`` of ``area`` from which the field of view (cell and four neighbours)
    covers every cell of ``need`` (by default all of ``area``), in boustrophedon order: every
    third lane along the longer axis (lanes 1, 4, 7, ..., and the last lane when the one before
    leaves it uncovered), back and forth, keeping the lane cells that see a needed cell; a
    needed cell no lane cell sees (next to obstacles) is inserted where it lengthens the order
    least (Manhattan)."""
    lanes_along_rows = area.shape[1] >= area.shape[0]
    need = area if need is None else need & area
    a = area if lanes_along_rows else area.T
    wanted = need if lanes_along_rows else need.T
    sees = wanted.copy()
    sees[1:] |= wanted[:-1]
    sees[:-1] |= wanted[1:]
    sees[:, 1:] |= wanted[:, :-1]
    sees[:, :-1] |= wanted[:, 1:]
    n = a.shape[0]
    lanes = list(range(min(1, n - 1), n, 3))
    if lanes[-1] + 1 < n - 1:
        lanes.append(n - 1)
    order = []
    for r, lane in enumerate(lanes):
        cols = np.flatnonzero(a[lane] & sees[lane])
        order.extend((lane, int(c)) for c in (cols if r % 2 == 0 else cols[::-1]))
    cells = np.array(order, dtype=np.int64).reshape(-1, 2)
    covered = np.zeros_like(a)
    for di, dj in ((0, 0), (1, 0), (-1, 0), (0, 1), (0, -1)):
        i, j = cells[:, 0] + di, cells[:, 1] + dj
        ok = (i >= 0) & (i < a.shape[0]) & (j >= 0) & (j < a.shape[1])
        covered[i[ok], j[ok]] = True
    for cell in np.argwhere(wanted & ~covered):
        if not len(cells):
            cells = cell[None, :]
            continue
        d_in = np.abs(cells - cell).sum(axis=1)
        extra = d_in[:-1] + d_in[1:] - np.abs(cells[1:] - cells[:-1]).sum(axis=1)
        where = int(np.argmin(extra)) + 1 if len(extra) else len(cells)
        if d_in[0] <= (extra.min() if len(extra) else np.inf):
            where = 0
        elif d_in[-1] <= extra.min():
            where = len(cells)
        cells = np.insert(cells, where, cell, axis=0)
    return cells if lanes_along_rows else cells[:, ::-1].copy()


def open_walk(grid: Grid, cells: np.ndarray) -> np.ndarray:
    """``cells`` in order as a walk of neighbouring free cells: gaps joined by an L-shaped
    path when free (:func:`l_path`), else by a shortest free path (all cells in one area)."""
    if len(cells) < 2:
        return cells.copy()
    joins, starts, ends, where = {}, [], [], []
    for g in np.flatnonzero(np.abs(cells[1:] - cells[:-1]).sum(axis=1) > 1):
        path = l_path(grid, cells[g], cells[g + 1])
        if path is not None:
            joins[int(g)] = path
        else:
            starts.append(cells[g])
            ends.append(cells[g + 1])
            where.append(int(g))
    if starts:
        found = free_paths(grid, np.array(starts), np.array(ends))
        joins.update({where[m]: path for m, path in found.items()})
    walk = []
    for g, cell in enumerate(cells):
        walk.append(tuple(cell))
        if g in joins:
            walk.extend(joins[g][1:-1])
    return np.array(walk, dtype=np.int64).reshape(-1, 2)


def split_survey(walk: np.ndarray, positions: np.ndarray) -> list[np.ndarray]:
    """The survey walk cut into one stretch per drone (consecutive, none shared), each drone
    given a stretch by a linear assignment on its squared distance to the nearer end, entering
    there. The cuts are moved once so that each drone's approach plus its stretch take about
    the same time (the survey ends when the last drone ends)."""
    n, length = len(positions), len(walk)

    def assign(bounds):
        first = walk[np.minimum(bounds[:-1], length - 1)]
        last = walk[np.maximum(bounds[1:] - 1, 0)]
        to_first = np.abs(positions[:, None, :] - first[None]).sum(axis=2)
        to_last = np.abs(positions[:, None, :] - last[None]).sum(axis=2)
        near = np.minimum(to_first, to_last)
        drones, stretch = linear_sum_assignment(near.astype(float) ** 2)
        return drones, stretch, to_first, to_last, near

    bounds = np.linspace(0, length, n + 1).round().astype(np.int64)
    drones, stretch, to_first, to_last, near = assign(bounds)
    approach = np.empty(n)
    approach[stretch] = near[drones, stretch]
    share = np.maximum(0.0, (length + approach.sum()) / n - approach)
    share *= length / max(share.sum(), 1e-9)
    bounds = np.concatenate([[0], np.cumsum(share)]).round().astype(np.int64)
    bounds[-1] = length
    drones, stretch, to_first, to_last, near = assign(bounds)
    out = [np.zeros((0, 2), dtype=np.int64)] * n
    for d, s in zip(drones, stretch, strict=True):
        piece = walk[bounds[s] : bounds[s + 1]]
        if len(piece) and to_last[d, s] < to_first[d, s]:
            piece = piece[::-1]
        out[d] = piece
    return out


class ToursPolicy(CoordinatedPolicy):
    """Drones spaced evenly along closed tours over the cells the swarm believes worth most.

    What it knows: what a swarm knows. A belief of the last ``T`` seen in any drone's field of
    view per cell (as :class:`twin.planners.LookaheadPolicy`), made optimistic where it is
    unknown or old (:meth:`_weights`: ``prior`` times the largest ``T`` seen, reached after
    ``memory`` steps), and the shared idleness map. Before its first plan (the first
    ``explore`` steps, by default one saturation period) it acts as ``visit-gain``.

    Survey (``survey = True``; off by default): before its first plan the swarm looks at the
    whole area once: the lanes of :func:`survey_cells` (every third lane, so the fields of view
    cover every cell not seen yet), one walk cut into one stretch per drone
    (:func:`split_survey`, no overlap), each drone flying its stretch; then it plans. With
    a survey, a shift of the map (below) starts a new survey before the re-plan.

    Planning (:meth:`_plan`): the revisit period ``P`` maximises ``N * mean(top N P weights) *
    visit_gain_factor(P)`` (:func:`best_period`, at most the saturation period). Layout
    ``cycles`` (default): ``ceil(N / per_tour)`` regions of whole free 2 x 2 blocks, each
    grown from the block of largest believed weight by the heaviest neighbouring block until it
    holds ``stretch * P`` cells per drone (:func:`block_regions`; the best of the four ways to
    cut the map in blocks), each walked by the closed walk around its spanning tree
    (:func:`block_cycle`): every cell once per lap, so with the drones spaced evenly every cell
    is revisited every ``P`` steps, no sooner. Layout ``walks`` (and the fallback when no block
    is free): the ``stretch * N * P`` cells of largest weight, split by k-means, each group
    a closed walk of neighbouring free cells (Warnsdorff's walk, 2-opt and Or-opt, gaps
    bridged: :func:`closed_walks`); its bridges and spurs revisit cells early (on the synthetic
    map a visit found 0.82 of the bracket's 0.9 where the cycles find 0.9). Drones are shared
    among the tours by their length, assigned by a linear assignment on distance, and each
    joins its tour where it arrives evenly spaced from the others (it flies a shortest free
    path there). Tours stay in the largest connected free area; a drone elsewhere acts as
    ``visit-gain``.

    Acting (:meth:`act`): each drone's planned move gets ``bonus`` (by default larger than any
    visit gain) added to its one-step visit gain, and the exact coordinator
    (:func:`twin.coordinator.coordinate`) picks the joint move: collision-free, and a drone
    pushed off its plan is routed back. A drone closer than ``L / m - 1`` cells behind the next
    drone of its tour waits; at a corner of its tour a drone takes the other corner cell when
    that lies off every tour and gains more.

    Re-planning (:meth:`_shifted`): when the believed importance over a tour changes shape
    (cosine to its value at planning below ``1 - shift``), falls under a tenth of it, or
    appears on a tour planned over none, at most once per saturation period; and every
    ``replan`` steps if set. A uniform fade or growth re-plans nothing.

    Cost: per step O(N) numpy work plus the coordinator (6 ms per step with 1000 drones on
    200 x 300 cells); a plan of the walks layout is k-means plus a local search per walk of
    ``per_tour * P`` cells: 0.1 s with 4 drones on 20 x 30 cells, 5 s with 300 drones and
    21 s with 1000 drones on 200 x 300 cells (``explore = 2``; 2-core machine shared with
    other jobs); the cycles layout grows regions with a heap, O(blocks log blocks).

    Defaults chosen on validation seeds 100-109 of ``configs/synthetic.toml`` only
    (``python benchmarks/validate_tours.py``; ratio = mean of per-seed ratios to
    ``visit-gain`` on the same starts and traffic, whose mean there is 2.634): tours without
    a survey, ``prior`` 0.25, ``memory`` 300, a saturation period of ``visit-gain`` first:
    1.072 ± 0.007; the best mean, ``explore`` 20 and ``memory`` 600, 1.073 ± 0.006 (a tie;
    the defaults keep step counts derived from eta and delta); ``prior`` 0.1 / 0.4:
    1.058 / 1.045; with the survey first (``prior`` 0, no ``memory``), stretch 1.0:
    1.063 ± 0.006, every seed within 2.785-2.817 (the survey takes about 66 steps, the
    swarm's loss to the swarm told the whole map at once, 2.849 there); stretch 0.95 / 1.1:
    1.023 / 1.050; ``per_tour`` 1: 1.054; the walks layout: 1.009 (0.969 with the survey). The
    earlier walks planner (the walks layout, its own defaults) scored 0.974 ± 0.036 on the
    evaluation seeds 0-9 (its first plan missed a big disturbance on seeds 1, 5 and 7).

    Measured once on the evaluation seeds 0-9 with the defaults, ``twin evaluate --config
    configs/synthetic.toml --seeds 10`` (all swarms; paired with visit-gain on the same starts
    and traffic): tours 2.812 ± 0.034 against visit-gain 2.628 ± 0.014, a difference of
    +0.184 ± 0.030, ratio 1.070 ± 0.011 (per seed 1.068, 1.081, 1.088, 1.082, 1.079, 1.032,
    1.069, 1.058, 1.073, 1.071); the look-ahead 2.810 ± 0.016 on the same run. On seed 5 its
    first plan missed a big disturbance (1.032). On the Shenzhen-like SUMO scenario (``twin run
    --seeds 1 --seed 0 --swarms visit-gain,tours``, T = 144): tours 1.890 against visit-gain
    1.990 (0.950 x; one seed): the horizon is four revisit periods, one spent before the plan.
    """

    name = "tours"

    def __init__(
        self,
        per_tour: int = 2,
        explore: int | None = None,
        replan: int | None = None,
        shift: float = 0.2,
        stretch: float = 1.0,
        bonus: float = PLAN_BONUS,
        prior: float = 0.25,
        memory: int | None = 300,
        survey: bool = False,
        layout: str = "cycles",
    ):
        def whole(value, key, low, example):
            return whole_option("tours", key, value, low, None, example)

        self.per_tour = whole_option("tours", "per_tour", per_tour, 1, MAX_PER_TOUR, 2)
        self.explore = None if explore is None else whole(explore, "explore", 0, 40)
        self.replan = None if replan is None else whole(replan, "replan", 1, 400)
        self.shift = number_option("tours", "shift", shift, 0.0, example=0.2, low_open=True)
        self.stretch = number_option("tours", "stretch", stretch, 0.0, example=1.0, low_open=True)
        self.bonus = number_option("tours", "bonus", bonus, 0.0, example=PLAN_BONUS)
        self.prior = number_option("tours", "prior", prior, 0.0, 1.0, 0.25)
        self.memory = None if memory is None else whole(memory, "memory", 1, 300)
        self.survey = flag_option("tours", "survey", survey)
        if layout not in LAYOUTS:
            raise UserError(f"tours: layout = {layout!r} must be one of {', '.join(LAYOUTS)}")
        self.layout = layout
        self.plans = 0  # plans made; described even by a run that stopped before its first step

    @classmethod
    def check_record(cls, record: dict) -> None:
        """run.json's record of a tours swarm (:meth:`describe`): its options, as the
        constructor checks them, and its counts of plans and surveys (at least 0). Options a
        later twin added (an earlier run records none of them) are checked where present."""
        missing = [
            k for k in ("per_tour", "explore", "replan", "shift", "plans") if k not in record
        ]
        if missing:
            raise UserError(f"records no {missing[0]}")
        cls(**{k: record[k] for k in inspect.signature(cls).parameters if k in record})
        for key in ("plans", "surveys"):
            if key not in record:
                continue
            value = record[key]
            if isinstance(value, bool) or not isinstance(value, int) or value < 0:
                raise UserError(f"{key} = {str(value)[:40]} must be a whole number of at least 0")

    def describe(self) -> dict:
        return {
            "per_tour": self.per_tour,
            "explore": self.explore,
            "replan": self.replan,
            "shift": self.shift,
            "stretch": self.stretch,
            "bonus": self.bonus,
            "prior": self.prior,
            "memory": self.memory,
            "survey": self.survey,
            "layout": self.layout,
            "plans": self.plans,
            "surveys": getattr(self, "surveys", 0),
        }

    def reset(self, grid: Grid, n_drones: int, rng: np.random.Generator) -> None:
        super().reset(grid, n_drones, rng)
        self.belief = np.zeros(grid.shape)  # last seen T per cell, 0 if never seen
        self.seen = np.zeros(grid.shape, dtype=bool)
        self.last_seen = np.zeros(grid.shape)  # step at which each cell was last in view
        _, labels = connected_components(free_cell_graph(grid), directed=False)
        labels = labels.reshape(grid.shape)
        counts = np.bincount(labels[grid.free])
        self.area = grid.free & (labels == counts.argmax())  # tours stay in the largest area
        self.plans = 0
        self.planned_at = None
        self.tours: list[np.ndarray] = []
        self.surveyed = not self.survey
        self.survey_left: list[np.ndarray] | None = None
        self.survey_fresh = False  # a survey has ended since the last plan
        self.surveys = 0

    def drones_changed(self, before: np.ndarray, after: np.ndarray) -> None:
        """Tours planned again for the live drones at the next step (what was seen is kept); a
        survey under way keeps each live drone's stretch (a lost drone's stays unflown)."""
        super().drones_changed(before, after)
        if self.planned_at is not None:
            self.planned_at = None
            self.approach = []
        if self.survey_left is not None:
            stretch = dict(zip(np.flatnonzero(before), self.survey_left, strict=True))
            empty = np.zeros((0, 2), dtype=np.int64)
            self.survey_left = [stretch.get(d, empty) for d in np.flatnonzero(after)]

    # -- what the swarm knows ---------------------------------------------------------------

    def _see(self, view: SwarmView) -> None:
        flat, valid = view.grid.view_index(view.positions)
        i, j = np.divmod(flat[valid], view.grid.ny)
        self.belief[i, j] = view.importance[i, j]
        self.seen[i, j] = True
        self.last_seen[i, j] = view.k
        self.now = view.k

    def _weights(self, params: ScoreParams) -> np.ndarray:
        """``alpha_T T + alpha_I`` with ``T`` the belief, made optimistic where it is old: a
        cell never seen counts ``prior`` times the largest ``T`` seen, and a cell last seen
        ``a`` steps ago moves from its last seen ``T`` towards that value by ``a / memory``
        (tours pass over unknown or stale areas while they rank among the cells worth
        patrolling, and what they reveal re-plans them)."""
        top = float(self.belief.max()) if self.seen.any() else 1.0
        hope = self.prior * top
        age = np.where(self.seen, getattr(self, "now", 0) - self.last_seen, np.inf)
        fade = np.minimum(1.0, age / self.memory) if self.memory else (~self.seen) * 1.0
        t = self.belief + np.maximum(0.0, hope - self.belief) * fade
        return params.alpha_T * t + params.alpha_I

    # -- planning ---------------------------------------------------------------------------

    def _due(self, view: SwarmView) -> bool:
        self.view_params = view.params
        if not self.surveyed:
            return False
        if view.k < self._explore(view.params):
            return False
        if self.planned_at is None or self.survey_fresh:
            return True
        since = view.k - self.planned_at
        if since < saturation_period(view.params):
            return False
        if self.replan is not None and since >= self.replan:
            return True
        shifted = self._shifted()
        if shifted and self.survey:  # the map moved: look at all of it again, then plan
            self.surveyed, self.survey_left = False, None
            return False
        return shifted

    def _explore(self, params: ScoreParams) -> int:
        """Steps of ``visit-gain`` before the survey (or the first plan, with no survey)."""
        if self.explore is not None:
            return self.explore
        return 0 if self.survey else self.period_hint(params)

    def _shifted(self) -> bool:
        """Whether the importance believed over some tour moved since its plan: its cells'
        importance (``alpha_T T``) as a vector, now against at planning, at a cosine below
        ``1 - shift``, or summing to under a tenth of what it did. A uniform fade or
        growth keeps the shape and re-plans nothing."""
        now = self._weights(self.view_params)[self.cell_i, self.cell_j] - self.view_params.alpha_I
        n_tours = len(self.tours)
        dot = np.bincount(self.cell_tour, now * self.t0, n_tours)
        norm_now = np.sqrt(np.bincount(self.cell_tour, now * now, n_tours))
        norm_0 = np.sqrt(np.bincount(self.cell_tour, self.t0 * self.t0, n_tours))
        sum_now = np.bincount(self.cell_tour, now, n_tours)
        sum_0 = np.bincount(self.cell_tour, self.t0, n_tours)
        both = (norm_now > 0) & (norm_0 > 0)
        cosine = np.where(both, dot / np.where(both, norm_now * norm_0, 1.0), 1.0)
        faded = sum_now < 0.1 * sum_0
        grew = (sum_0 <= 0) & (sum_now > 0)
        return bool(((cosine < 1.0 - self.shift) | faded | grew).any())

    def period_hint(self, params: ScoreParams) -> int:
        return saturation_period(params)

    def _plan(self, view: SwarmView) -> None:
        grid, n = view.grid, self.n_drones
        w = self._weights(view.params)
        # ties (cells seen at T = 0, cells never seen) go to cells near important ones
        key = w + 1e-3 * _blur(w * self.area) + 1e-9 * self.rng.random(w.shape)
        key = np.where(self.area, key, -np.inf)
        n_area = int(self.area.sum())
        ranked = np.argsort(-key.ravel(), kind="stable")[:n_area]
        period = best_period(w.ravel()[ranked], n, view.params)
        # the walks joining the chosen cells pass over others: choose fewer cells until the
        # walks hold about n * period cells, so each cell's revisit period is about `period`
        want = self.stretch * n * period
        count = min(round(want), n_area)
        cycles = self._cycles(key, period) if self.layout == "cycles" else []
        if cycles:
            self.tours = cycles
        for _ in range(3 if not cycles else 0):
            self.tours = self._walks(ranked[:count], grid)
            total = sum(len(t) for t in self.tours)
            if total <= want * 1.03 or count <= n:
                break
            count = max(n, round(count * want / total))
        lengths = np.array([len(t) for t in self.tours])
        self.period = period
        self._assign(view, lengths)
        self.cell_tour = np.repeat(np.arange(len(self.tours)), lengths)
        flat_tours = np.concatenate(self.tours)
        self.cell_i, self.cell_j = flat_tours[:, 0], flat_tours[:, 1]
        self.t0 = self._weights(view.params)[self.cell_i, self.cell_j] - view.params.alpha_I
        self.planned_at = view.k
        self.survey_fresh = False
        self.plans += 1

    def _cycles(self, key: np.ndarray, period: int) -> list[np.ndarray]:
        """Closed walks over whole 2 x 2 blocks of free cells, each cell once
        (:func:`block_cycle`), one per ``per_tour`` drones, over regions grown from the
        blocks of largest believed weight (:func:`block_regions`) to ``stretch * drones *
        period`` cells; of the four ways to cut the map in blocks, the one whose regions
        weigh most. Empty when no 2 x 2 block is free."""
        n, (nx, ny) = self.n_drones, self.grid.shape
        k = max(1, math.ceil(n / self.per_tour))
        drones = np.full(k, n // k) + (np.arange(k) < n % k)
        sizes = [max(1, round(self.stretch * d * period / 4)) for d in drones]
        best, best_total = [], -np.inf
        for oi in (0, 1):
            for oj in (0, 1):
                bnx, bny = (nx - oi) // 2, (ny - oj) // 2
                if bnx < 1 or bny < 1:
                    continue
                window = (slice(oi, oi + 2 * bnx), slice(oj, oj + 2 * bny))
                usable = self.area[window].reshape(bnx, 2, bny, 2).all(axis=(1, 3))
                if not usable.any():
                    continue
                value = np.where(self.area, key, 0.0)[window].reshape(bnx, 2, bny, 2)
                weights = value.sum(axis=(1, 3))
                regions = block_regions(weights, usable, sizes)
                total = sum(float(weights[b]) for region in regions for b, _ in region)
                if total > best_total:
                    best_total = total
                    best = [block_cycle(region, (oi, oj)) for region in regions]
        return best

    def _walks(self, chosen: np.ndarray, grid: Grid) -> list[np.ndarray]:
        """Closed walks over the chosen cells (flat ids): one group per tour, by k-means."""
        n = self.n_drones
        cells = np.stack(np.divmod(chosen, grid.ny), axis=1)
        k = max(1, min(math.ceil(n / self.per_tour), len(cells)))
        if k > 1:
            points = cells.astype(float)
            _, label = kmeans2(points, _kmeans_pp(points, k, self.rng), minit="matrix")
        else:
            label = np.zeros(len(cells), dtype=np.int64)
        groups = [cells[label == t] for t in range(k) if (label == t).any()]
        return closed_walks(grid, [g[closed_order(g)] for g in groups])

    def _assign(self, view: SwarmView, lengths: np.ndarray) -> None:
        """Drones per tour (each tour one, the rest to the longest periods), which drone on
        which tour (assignment on the distance to the tour), and where each joins it."""
        n, n_tours = self.n_drones, len(self.tours)
        per = np.ones(n_tours, dtype=np.int64)
        if n_tours > n:  # cannot happen with ceil(n / per_tour) tours; kept for safety
            raise AssertionError("more tours than drones")
        for _ in range(n - n_tours):
            per[np.argmax(lengths / per)] += 1
        pos = np.asarray(view.positions, dtype=np.int64)
        near = np.empty((n, n_tours))
        dists = []
        for t, tour in enumerate(self.tours):
            d = np.abs(pos[:, None, :] - tour[None, :, :]).sum(axis=2)  # (n, L)
            dists.append(d)
            near[:, t] = d.min(axis=1)
        slots = np.repeat(np.arange(n_tours), per)
        rows, cols = linear_sum_assignment(near[:, slots])
        self.tour_of = np.empty(n, dtype=np.int64)
        self.tour_of[rows] = slots[cols]
        self.per = per
        entry = np.zeros(n, dtype=np.int64)
        for t in range(n_tours):
            members = np.flatnonzero(self.tour_of == t)
            members = members[np.argsort(near[members, t], kind="stable")]
            length = lengths[t]
            idx = np.arange(length)
            first = None
            for r, d in enumerate(members):
                dist = dists[t][d]
                if first is None:
                    entry[d] = int(dist.argmin())
                    first = (entry[d] - dist[entry[d]]) % length
                    continue
                target = first + r * length / len(members)
                virtual = (idx - dist) % length  # where it would be had it been on the tour
                err = np.abs((virtual - target + length / 2) % length - length / 2)
                entry[d] = int(np.argmin(dist + err))
        self.phase = entry
        self.offset = np.concatenate([[0], np.cumsum(lengths)[:-1]])
        self.lengths = lengths
        self.flat = np.concatenate(self.tours)
        self.tour_cells = np.zeros(self.grid.shape, dtype=bool)
        self.tour_cells[self.flat[:, 0], self.flat[:, 1]] = True
        targets = self.flat[self.offset[self.tour_of] + entry]
        self._route(pos, np.arange(n), targets)

    def _route(self, pos: np.ndarray, drones: np.ndarray, targets: np.ndarray) -> None:
        """Shortest free paths from the given drones to their targets (kept as approaches)."""
        if not hasattr(self, "approach") or len(self.approach) != self.n_drones:
            self.approach = [np.zeros((0, 2), dtype=np.int64)] * self.n_drones
            self.off_plan = np.zeros(self.n_drones, dtype=bool)
        away = np.flatnonzero((pos[drones] != targets).any(axis=1))
        for d in drones:
            self.approach[d] = np.zeros((0, 2), dtype=np.int64)
        self.off_plan[drones] = False
        if not len(away):
            return
        paths, rest = {}, []
        for m in range(len(away)):
            straight = l_path(self.grid, pos[drones[away[m]]], targets[away[m]])
            if straight is not None:
                paths[m] = straight
            else:
                rest.append(m)
        if rest:
            rest = np.array(rest)
            found = free_paths(self.grid, pos[drones[away[rest]]], targets[away[rest]])
            paths.update({int(rest[m]): path for m, path in found.items()})
        for m, d in enumerate(drones[away]):
            if m in paths:
                self.approach[d] = np.array(paths[m][1:], dtype=np.int64)
            else:  # another area than the tour: this drone follows the visit gain
                self.off_plan[d] = True

    # -- acting -----------------------------------------------------------------------------

    def scores(self, view: SwarmView) -> np.ndarray:
        grid, fov, p = view.grid, view.grid.view_index(view.positions), view.params
        weight = p.alpha_T * grid.values_in_view(view.importance, None, fov) + p.alpha_I
        return visit_gain(weight, grid.values_in_view(view.idleness, None, fov), p)

    def act(self, view: SwarmView) -> np.ndarray:
        self._see(view)
        planned = None
        if not self.surveyed and view.k >= self._explore(view.params):
            planned = self._survey_actions(view)
            self.surveyed = self.survey_fresh = planned is None
        if self._due(view):
            self._plan(view)
        surveying = planned is not None
        scores = self.scores(view)
        if planned is None and self.planned_at is not None:
            planned = self._planned_actions(view)
        if planned is not None:
            has = planned >= 0
            scores[np.flatnonzero(has), planned[has]] += self.bonus
        scores = scores + _jitter(scores, view.feasible, self.rng)
        actions = self.joint_action(scores, view)
        if surveying:
            for d in np.flatnonzero((planned == actions) & (planned >= 0)):
                self.survey_left[d] = self.survey_left[d][1:]
        elif planned is not None:
            self._advance(view, planned, actions)
        return actions

    # -- survey -----------------------------------------------------------------------------

    def _survey_actions(self, view: SwarmView) -> np.ndarray | None:
        """Each drone's move along its stretch of the survey (-1: none left, it follows the
        visit gain); None once every stretch is flown (or after twice the longest one)."""
        pos = np.asarray(view.positions, dtype=np.int64)
        n = self.n_drones
        if self.survey_left is None:
            self.surveys += 1
            self.survey_left = [np.zeros((0, 2), dtype=np.int64)] * n
            inside = np.flatnonzero(self.area[pos[:, 0], pos[:, 1]])
            need = self.area & ~self.seen if self.surveys == 1 else self.area
            walk = open_walk(self.grid, survey_cells(self.area, need))
            if len(inside) and len(walk):
                pieces = split_survey(walk, pos[inside])
                for d, piece in zip(inside, pieces, strict=True):
                    self.survey_left[d] = piece
            longest = max(len(p) for p in self.survey_left)
            self.survey_end = view.k + 2 * (longest + self.grid.nx + self.grid.ny)
        if view.k >= self.survey_end:
            return None
        planned = np.full(n, -1, dtype=np.int64)
        redo = []
        for d in range(n):
            left = self.survey_left[d]
            while len(left) and (left[0] == pos[d]).all():
                left = left[1:]
            self.survey_left[d] = left
            if len(left) and np.abs(left[0] - pos[d]).sum() > 1:
                redo.append(d)  # pushed off its stretch: route back to it
        if redo:
            redo = np.array(redo)
            targets = np.array([self.survey_left[d][0] for d in redo])
            found = free_paths(self.grid, pos[redo], targets)
            for m, d in enumerate(redo):
                if m in found:
                    back = np.array(found[m][1:-1], dtype=np.int64).reshape(-1, 2)
                    self.survey_left[d] = np.concatenate([back, self.survey_left[d]])
        if not any(len(left) for left in self.survey_left):
            return None
        for d in range(n):
            left = self.survey_left[d]
            if len(left) and np.abs(left[0] - pos[d]).sum() > 1:  # no free path back
                self.survey_left[d] = left = left[:0]
            if len(left):
                di, dj = left[0] - pos[d]
                planned[d] = _STEP_ACTION[(di + 1) * 3 + (dj + 1)]
        return planned

    def _next_cells(self, pos: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Each drone's planned next cell and whether it is on its tour."""
        on_tour = np.array([len(a) == 0 for a in self.approach])
        flat = self.flat
        length = self.lengths[self.tour_of]
        nxt = flat[self.offset[self.tour_of] + (self.phase + 1) % length].copy()
        for d in np.flatnonzero(~on_tour):
            nxt[d] = self.approach[d][0]
        return nxt, on_tour

    def _planned_actions(self, view: SwarmView) -> np.ndarray:
        pos = np.asarray(view.positions, dtype=np.int64)
        nxt, on_tour = self._next_cells(pos)
        flat = self.flat
        here = flat[self.offset[self.tour_of] + self.phase]
        # a drone on its tour whose next tour cell is not a step away was pushed off (or took
        # a corner): route it back to the tour
        far = np.abs(nxt - pos).sum(axis=1) > 1
        lost = on_tour & far & ~self.off_plan
        bad = far & ~on_tour & ~self.off_plan
        if lost.any() or bad.any():
            redo = np.flatnonzero(lost | bad)
            targets = np.where(
                lost[redo, None],
                nxt[redo],
                np.array(
                    [self.approach[d][-1] if len(self.approach[d]) else here[d] for d in redo]
                ),
            )
            self.phase[lost] = (self.phase[lost] + 1) % self.lengths[self.tour_of[lost]]
            self._route(pos, redo, targets)
            nxt, on_tour = self._next_cells(pos)
        nxt = self._corners(view, pos, nxt, on_tour & ~self.off_plan, flat)
        step = nxt - pos
        code = (step[:, 0] + 1) * 3 + (step[:, 1] + 1)
        ok = (np.abs(step) <= 1).all(axis=1)
        planned = np.where(ok, _STEP_ACTION[np.clip(code, 0, 8)], -1)
        planned[self.off_plan] = -1
        # spacing: a drone on its tour too close behind the next one on the same tour waits
        wait = self._too_close(on_tour & ~self.off_plan & (planned >= 0))
        planned[wait] = 0
        self._waiting = wait
        return planned

    def _corners(self, view, pos, nxt, on_tour, flat) -> np.ndarray:
        """Where the tour turns a corner (the cell after next is diagonal to the drone), step
        on the other corner cell if it lies off every tour and has the larger visit gain: it
        bridges the same two cells, and the tour's own corner may have been visited moments ago
        (a corner on a tour is left alone: its own visit is scheduled)."""
        after = flat[self.offset[self.tour_of] + (self.phase + 2) % self.lengths[self.tour_of]]
        other = pos + (after - nxt)
        diagonal = on_tour & (np.abs(after - pos) == 1).all(axis=1)
        if not diagonal.any():
            return nxt
        d = np.flatnonzero(diagonal)
        ok = view.grid.is_free(other[d])
        ok[ok] = ~self.tour_cells[other[d[ok], 0], other[d[ok], 1]]  # off every tour
        d, alt, cur = d[ok], other[d[ok]], nxt[d[ok]]
        p = view.params

        def gain(cells):
            weight = p.alpha_T * view.importance[cells[:, 0], cells[:, 1]] + p.alpha_I
            return visit_gain(weight, view.idleness[cells[:, 0], cells[:, 1]], p)

        better = gain(alt) > gain(cur)
        nxt = nxt.copy()
        nxt[d[better]] = alt[better]
        return nxt

    def _too_close(self, on_tour: np.ndarray) -> np.ndarray:
        drones = np.flatnonzero(on_tour)
        wait = np.zeros(self.n_drones, dtype=bool)
        if len(drones) < 2:
            return wait
        tour, phase = self.tour_of[drones], self.phase[drones]
        order = np.lexsort((phase, tour))
        tour, phase, drones = tour[order], phase[order], drones[order]
        start = np.flatnonzero(np.r_[True, tour[1:] != tour[:-1]])
        size = np.diff(np.r_[start, len(tour)])
        group = np.repeat(np.arange(len(start)), size)
        rank = np.arange(len(tour)) - start[group]
        ahead = start[group] + (rank + 1) % size[group]
        length = self.lengths[tour]
        gap = (phase[ahead] - phase) % length
        ideal = length / self.per[tour]
        wait[drones] = (size[group] > 1) & (gap < ideal - 1) & (gap > 0)
        return wait

    def _advance(self, view: SwarmView, planned: np.ndarray, actions: np.ndarray) -> None:
        """Move each drone's place in its plan along when it made its planned move."""
        followed = (planned == actions) & (planned >= 0) & ~self.off_plan & ~self._waiting
        for d in np.flatnonzero(followed):
            if len(self.approach[d]):
                self.approach[d] = self.approach[d][1:]
            else:
                self.phase[d] = (self.phase[d] + 1) % self.lengths[self.tour_of[d]]


def _kmeans_pp(points: np.ndarray, k: int, rng: np.random.Generator) -> np.ndarray:
    """k-means++ seeds (each next seed drawn with probability proportional to the squared
    distance to the nearest seed so far), keeping that distance up to date: O(k n), where
    scipy's own seeding recomputes every distance at every draw."""
    seeds = np.empty((k, points.shape[1]))
    seeds[0] = points[rng.integers(len(points))]
    nearest = ((points - seeds[0]) ** 2).sum(axis=1)
    for s in range(1, k):
        total = nearest.sum()
        pick = (
            rng.choice(len(points), p=nearest / total) if total > 0 else rng.integers(len(points))
        )
        seeds[s] = points[pick]
        np.minimum(nearest, ((points - seeds[s]) ** 2).sum(axis=1), out=nearest)
    return seeds


def _blur(values: np.ndarray, radius: int = 2) -> np.ndarray:
    """Mean of ``values`` over the ``(2 radius + 1)^2`` square around each cell (box filter)."""
    padded = np.pad(values, radius)
    c = padded.cumsum(axis=0).cumsum(axis=1)
    c = np.pad(c, ((1, 0), (1, 0)))
    s = 2 * radius + 1
    box = c[s:, s:] - c[:-s, s:] - c[s:, :-s] + c[:-s, :-s]
    return box / s**2


def _jitter(scores, feasible, rng):
    from twin.planners import tie_jitter

    return tie_jitter(scores, feasible, rng)
