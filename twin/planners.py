"""Coordinated classical swarms: a score per drone and action, then the exact coordinator.

Each swarm scores the cell every action leads to and hands the ``(N, 5)`` scores to
:func:`twin.coordinator.coordinate` (eq. maxi:op2), which picks the joint action with the
largest sum of scores among those whose next cells are distinct. So no two drones ever share a
cell (when they start on distinct cells) and the only difference with the learned swarm is the
score.

- ``greedy-coordinated``: greedy's score ``I^k T^k`` of the cell reached;
- ``visit-gain``: the one-step gain of visiting the cell reached (:func:`visit_gain`);
- ``lookahead``: the best summed visit gain over paths of ``H`` steps starting with the move,
  plus the value of the idleness the path leaves behind, the drones planned in turn.

Ties (equal scores, common where ``T = 0``) are broken by a jitter of at most
:data:`TIE_JITTER` times the largest score magnitude, drawn from the swarm's generator at every
step: deterministic given the seed, uniform among tied joint actions, never biased to "stay".
"""

from __future__ import annotations

import itertools
from typing import NamedTuple

import numpy as np

from twin.coordinator import coordinate
from twin.errors import UserError
from twin.grid import ACTION_DELTAS, Grid
from twin.policies import Policy, SwarmView, number_option, whole_option
from twin.scores import visit_gain

#: Relative size of the tie-breaking jitter: scores closer than this count as tied.
TIE_JITTER = 1e-9
#: Default planning horizon of ``lookahead``, chosen on R_hat_T (see :class:`LookaheadPolicy`).
DEFAULT_HORIZON = 8
#: Largest horizon of the full tree: 5^H paths per drone (H = 5: 1.7 s per step with 1000
#: drones, path by path).
MAX_HORIZON = 5
#: Largest horizon of the beam search (``beam > 0``).
MAX_BEAM_HORIZON = 16
#: Default weight of ``lookahead``'s end value (0: none).
DEFAULT_END_WEIGHT = 1.1
#: Default steps between ``lookahead``'s horizon and the later visit its end value prices.
DEFAULT_END_WAIT = 3
#: How ``lookahead`` treats the other drones' future visits.
PLANS = ("independent", "sequential")
DEFAULT_PLAN = "sequential"
#: Default prefixes kept per first action by ``lookahead``'s beam search (0: the full tree).
DEFAULT_BEAM = 20


def tie_jitter(scores: np.ndarray, feasible: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """Uniform noise of at most ``TIE_JITTER * max(1, max |feasible score|)`` per entry."""
    finite = np.abs(scores[feasible]) if feasible.any() else np.zeros(1)
    scale = TIE_JITTER * max(1.0, float(finite.max()))
    return scale * rng.random(scores.shape)


class CoordinatedPolicy(Policy):
    """A swarm that scores every drone's actions and lets the exact coordinator choose."""

    name = "coordinated"

    def scores(self, view: SwarmView) -> np.ndarray:
        """``(N, 5)`` score of each drone's actions (infeasible entries are ignored)."""
        raise NotImplementedError

    def act(self, view: SwarmView) -> np.ndarray:
        scores = self.scores(view)
        scores = scores + tie_jitter(scores, view.feasible, self.rng)
        return self.joint_action(scores, view)

    def joint_action(self, scores: np.ndarray, view: SwarmView) -> np.ndarray:
        """The coordinator's joint action (eq. maxi:op2); while it is down, each drone's own
        best-scored feasible move, collisions unresolved."""
        if self.coordinator_down(view.k):
            return np.argmax(np.where(view.feasible, scores, -np.inf), axis=1)
        return coordinate(scores, view.positions, view.feasible, view.grid)


class GreedyCoordinatedPolicy(CoordinatedPolicy):
    """Greedy's score ``I^k T^k`` of the cell each action leads to, by assignment."""

    name = "greedy-coordinated"

    def scores(self, view: SwarmView) -> np.ndarray:
        grid, fov = view.grid, view.grid.view_index(view.positions)
        return grid.values_in_view(view.idleness, None, fov) * grid.values_in_view(
            view.importance, None, fov
        )


class VisitGainPolicy(CoordinatedPolicy):
    """The one-step gain of the visit at the next cell ``p'``, by assignment:
    ``(alpha_T T^k + alpha_I) (min(1, I^k + delta) - eta I^k)`` at ``p'``.

    This is the headline score's exact one-step greedy maximiser: ``R^k`` pays the visit gain
    of every distinct cell visited (:func:`twin.scores.rewards_on_arrival`), and the coordinator
    keeps the drones' next cells distinct. The score uses ``T^k`` where the reward uses
    ``T^{k+1}``, which the swarm has not seen yet.
    """

    name = "visit-gain"

    def scores(self, view: SwarmView) -> np.ndarray:
        grid, fov, p = view.grid, view.grid.view_index(view.positions), view.params
        weight = p.alpha_T * grid.values_in_view(view.importance, None, fov) + p.alpha_I
        return visit_gain(weight, grid.values_in_view(view.idleness, None, fov), p)


def action_paths(horizon: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Every sequence of ``horizon`` actions, first action slowest (so the ``5^(H-1)`` paths
    starting with action ``u`` are block ``u``).

    Returns ``(offsets, last, first)``: ``offsets`` ``(P, H, 2)`` the cell after each step relative to
    the start, ``last`` ``(P, H)`` the earlier step at which the path stood on the same cell
    (-1 if none), and ``first`` ``(P,)`` the first actions.
    """
    seqs = np.array(list(itertools.product(range(len(ACTION_DELTAS)), repeat=horizon)))
    offsets = np.cumsum(ACTION_DELTAS[seqs], axis=1)
    same = (offsets[:, :, None, :] == offsets[:, None, :, :]).all(axis=3)  # (P, h, s)
    earlier = np.tril(np.ones((horizon, horizon), dtype=bool), k=-1)
    same &= earlier[None]
    # last earlier step s < h on the same cell: argmax over reversed s
    rev = same[:, :, ::-1]
    last = np.where(same.any(axis=2), horizon - 1 - rev.argmax(axis=2), -1)
    return offsets, last, seqs[:, 0]


class LookaheadPolicy(CoordinatedPolicy):
    """Receding-horizon planner: the score of a drone's move is the best summed visit gain
    (:func:`visit_gain`, discounted by ``discount^h``, undiscounted by default) over the
    ``5^(H-1)`` feasible paths of ``H`` steps that start with it (those a beam search kept,
    with ``beam > 0``), plus an end value; then the assignment.

    Along a path the idleness of each cell is predicted from ``I^k``: ``min(1, I + h delta)``
    after ``h`` steps, ``eta I`` at the path's own visits, recovering again after them.

    End value (``end_weight > 0``): what the path leaves behind for later visits. For each
    cell the path visits, the visit gain a visit ``end_wait`` steps after the horizon would
    earn there, minus what it would earn had the path not visited the cell (both predicted as
    above), times ``end_weight * discount^H``. It is (but for a sliver near saturation, where
    ``g`` falls with ``I``) negative: it charges each visit the gain it takes from later ones,
    more on cells that were fresh, so a path that takes cells a later visit would harvest
    better is preferred less than its summed gain says. The
    unvisited cells' future gains do not depend on the path and are left out. With
    ``end_weight = 0`` the scores are those without the term, bit for bit.

    Planning (``plan``): ``"independent"`` ignores the other drones' future visits (only the
    first moves are coordinated); ``"sequential"`` plans the drones in turn (by index), each
    against the best paths of the drones before it: a cell on such a path is claimed, read as
    visited from now on (``eta I`` until the step of that visit, recovering after it), for the
    visit gains and the end value alike (the drone's own revisits ignore the claims). Reading
    a claimed cell as fresh until the claim's step made later drones take the cells earlier
    drones planned to visit (worse than independent planning on the validation seeds). The
    cost is a loop over the drones.

    What it reads: the swarm's idleness map ``I^k`` (all cells, as ``rl`` does) and a belief
    of the importance: for each cell the last ``T`` seen in any drone's field of view (the
    current ``T^k`` there), 0 for cells never seen, held constant along the path. With
    ``H = 1`` and ``end_weight = 0`` the only cells scored are in view, so the scores are
    exactly ``visit-gain``'s.

    How: the paths form a tree (level ``h`` holds the ``5^(h+1)`` prefixes of ``h + 1``
    steps); each node adds its step's gain to its parent's sum, so a shared prefix is summed
    once, in the same order as path by path (bit for bit the same sums). A node's gain depends
    only on its visit class (its cell and the earlier steps at which the prefix stood there),
    so gains are computed per class, the end value's change included (a visit's end term
    replaces that of the cell's previous visit on the path). The last level needs no sums
    when the best path itself is not wanted: rounding is monotone, so
    ``max_c (v + g_c) = v + max_c g_c``. Cost per step: about ``N 5^H`` lookups, all drones at
    once when independent, one drone at a time when sequential. Past ``H = 5`` the tree is too
    big (``5^H`` paths); ``beam > 0`` searches instead level by level, one drone at a time,
    keeping after each step only the ``beam`` best prefixes that start with each action (so
    every first move keeps a score; the best path may be missed, ``beam >= 5^(H-1)`` keeps
    all), the same gains and end value as the tree.

    Defaults (:data:`DEFAULT_HORIZON` 8, :data:`DEFAULT_END_WEIGHT` 1.1,
    :data:`DEFAULT_END_WAIT` 3, :data:`DEFAULT_PLAN` sequential, :data:`DEFAULT_BEAM` 20) were
    chosen on R_hat_T of ``configs/synthetic.toml``, validation seeds 100-109 only, where
    visit-gain scores 2.634 (``python benchmarks/bench_swarms.py --pick-horizon`` runs these
    settings; R_hat_T means): no end value, H = 4 2.594 (H = 1 decides as visit-gain but for
    tie-breaks); independent H = 4 with end values 0.7-1.2 and waits 0-30: 2.63-2.68 (weight
    1.5: the drones hover, 0.07), a longer horizon no better (H = 5 2.676); sequential H = 4,
    end 0.9, wait 3: 2.755 (wait 8 2.746; wait 5 with claimed cells read fresh until the
    claim's step 2.546); sequential H = 5, end 0.9 / 1.1, wait 3: 2.785 / 2.792; beam 20,
    H = 8, end 0.9 / 1.1, wait 3: 2.822 / 2.827 (wait 1: 2.801).

    Measured once on the evaluation seeds 0-9 with the defaults, paired against visit-gain
    (same starts and traffic per seed; mean ± 95% interval of the paired difference):
    R_hat_T 2.810 ± 0.016 against visit-gain's 2.628 ± 0.014, a difference of +0.183 ± 0.019
    (1.069 x visit-gain; ``python benchmarks/bench_swarms.py --pick-horizon --seeds 0-9``
    prints the same runs among the other settings). Cost per decision
    (``bench_swarms.py``'s scenes, a loaded 2-core machine): 3.4 ms with 4 drones on 20 x 30
    cells, 160 ms with 200 drones on 100 x 150 (the full tree with H = 4 and no end value:
    2.5 ms there, visit-gain 0.5 ms), 0.86 s with 1000 drones on 200 x 300; it grows with the
    number of drones, planned one at a time.
    """

    name = "lookahead"

    def __init__(
        self,
        horizon: int = DEFAULT_HORIZON,
        discount: float = 1.0,
        end_weight: float = DEFAULT_END_WEIGHT,
        end_wait: int = DEFAULT_END_WAIT,
        plan: str = DEFAULT_PLAN,
        beam: int = DEFAULT_BEAM,
    ):
        if isinstance(beam, bool) or not isinstance(beam, int | np.integer) or beam < 0:
            raise UserError(f"lookahead: beam = {beam!r} must be an integer >= 0; e.g. 0")
        if isinstance(horizon, bool) or not isinstance(horizon, int | np.integer):
            raise UserError(f"lookahead: horizon = {horizon!r} must be an integer; e.g. 2")
        if beam == 0 and not 1 <= horizon <= MAX_HORIZON:
            raise UserError(
                f"lookahead: horizon = {horizon} with beam = 0 (every path: 5^H per drone) must "
                f"lie in 1..{MAX_HORIZON}; give a horizon of at most {MAX_HORIZON}, or a beam > 0 "
                f"(a horizon up to {MAX_BEAM_HORIZON})"
            )
        if beam > 0 and not 1 <= horizon <= MAX_BEAM_HORIZON:
            raise UserError(
                f"lookahead: horizon = {horizon} must lie in 1..{MAX_BEAM_HORIZON} with a beam; "
                f"e.g. {DEFAULT_HORIZON}"
            )
        discount = number_option("lookahead", "discount", discount, 0.0, 1.0, 1.0, low_open=True)
        end_weight = number_option("lookahead", "end_weight", end_weight, 0, 10, DEFAULT_END_WEIGHT)
        end_wait = whole_option("lookahead", "end_wait", end_wait, 0, 1000, 5)
        if plan not in PLANS:
            raise UserError(f"lookahead: plan = {plan!r} must be one of {', '.join(PLANS)}")
        self.horizon = int(horizon)
        self.discount = float(discount)
        self.end_weight = float(end_weight)
        self.end_wait = int(end_wait)
        self.plan = plan
        self.beam = int(beam)
        if self.beam == 0:
            self.offsets, self.last, self.first = action_paths(self.horizon)
            self.cells, self.levels = path_tree(self.offsets, self.last)

    def reset(self, grid: Grid, n_drones: int, rng: np.random.Generator) -> None:
        super().reset(grid, n_drones, rng)
        h = self.horizon
        self.width = grid.ny + 2 * h  # maps padded by H: every path stays inside
        self.free_padded = np.pad(grid.free, h, constant_values=False).ravel()
        self.belief_padded = np.zeros((grid.nx + 2 * h, grid.ny + 2 * h))
        self.belief = self.belief_padded[h:-h, h:-h]  # last seen T per cell, 0 if never seen
        self.idle_padded = np.zeros_like(self.belief_padded)
        self.moves = ACTION_DELTAS[:, 0] * self.width + ACTION_DELTAS[:, 1]  # flat steps
        if self.beam == 0:
            self.cell_flat = self.cells[:, 0] * self.width + self.cells[:, 1]  # (C,) rel. ids
            flat = self.offsets[..., 0] * self.width + self.offsets[..., 1]  # (P, H)
            self.path_cells = np.searchsorted(self.cell_flat, flat)  # cell_flat is sorted

    def scores(self, view: SwarmView) -> np.ndarray:
        p, h_max = view.params, self.horizon
        self.update_belief(view)
        self.idle_padded[h_max:-h_max, h_max:-h_max] = view.idleness

        pos = np.asarray(view.positions, dtype=np.int64)
        base = (pos[:, 0] + h_max) * self.width + pos[:, 1] + h_max
        if self.plan == "independent" and self.beam == 0:
            near = self.cell_flat[:, None] + base[None, :]  # (C, N) padded flat ids
            idle = self.idle_padded.ravel()[near]
            fresh = [np.minimum(1.0, idle + h * p.delta) for h in range(h_max)]
            fresh.append(np.minimum(1.0, idle + (h_max + self.end_wait) * p.delta))
            return self._tree(near, fresh, p)[0]
        # sequential: predicted idleness before step h (h = H: the visit after the wait)
        steps = np.append(np.arange(h_max), h_max + self.end_wait)
        future = np.minimum(1.0, self.idle_padded.ravel()[None, :] + steps[:, None] * p.delta)
        out = np.empty((len(pos), len(ACTION_DELTAS)))
        weight = p.alpha_T * self.belief_padded.ravel() + p.alpha_I
        for d in range(len(pos)):
            if self.beam > 0:
                out[d], cells = self._beam(base[d], future, weight, p)
            else:
                near = self.cell_flat[:, None] + base[d]  # (C, 1)
                fresh = [future[h][near] for h in range(h_max + 1)]
                out[d], best = self._tree(near, fresh, p, best_path=True)
                cells = None if best is None else self.cell_flat[self.path_cells[best]] + base[d]
            if cells is None or self.plan == "independent":
                continue
            for t, c in enumerate(cells):
                # claimed: eta I from now on, recovering only after the visit at step t
                recovery = np.maximum(steps - 1 - t, 0) * p.delta
                future[:, c] = np.minimum(1.0, p.eta * future[t, c] + recovery)
        return out

    def update_belief(self, view: SwarmView) -> None:
        """The importance the planner assumes: the last ``T`` seen in a field of view."""
        flat, valid = view.grid.view_index(view.positions)
        i, j = np.divmod(flat[valid], view.grid.ny)
        self.belief[i, j] = view.importance[i, j]

    def _beam(self, start, future, weight, p):
        """Beam search of one drone's paths: after each step only the ``beam`` best prefixes
        starting with each action are extended. Returns its ``(5,)`` scores (the best value of
        a kept path per first action) and the padded flat cells ``(H,)`` of its best path (None
        if it has none). ``future``: as in :meth:`scores`, ``weight`` the padded flat map."""
        h_max, n_act = self.horizon, len(ACTION_DELTAS)
        wait, end = h_max + self.end_wait, self.end_weight > 0
        end_scale = self.end_weight * self.discount**h_max
        cells = np.empty((1, 0), dtype=np.int64)  # (B, h) kept prefixes
        pres = np.empty((1, 0))  # idleness before each step
        value, first = np.zeros(1), np.zeros(1, dtype=np.int64)
        for h in range(h_max):
            here = cells[:, -1] if h else np.array([start])
            new = (here[:, None] + self.moves[None, :]).ravel()  # (5B,) children
            cells = np.repeat(cells, n_act, axis=0)
            pres = np.repeat(pres, n_act, axis=0)
            value = np.repeat(value, n_act)
            first = np.repeat(first, n_act) if h else np.arange(n_act)
            w = weight[new]
            pre, before = future[h][new], None
            if h:
                same = cells == new[:, None]  # (5B, h)
                again = same.any(axis=1)
                s = h - 1 - same[:, ::-1].argmax(axis=1)  # the last earlier visit
                pre_s = pres[np.arange(len(new)), s]
                pre = np.where(again, np.minimum(1.0, p.eta * pre_s + (h - 1 - s) * p.delta), pre)
            gain = self.discount**h * visit_gain(w, pre, p)
            if end:
                later = np.minimum(1.0, p.eta * pre + (wait - 1 - h) * p.delta)
                before = visit_gain(w, future[h_max][new], p)
                if h:
                    earlier = np.minimum(1.0, p.eta * pre_s + (wait - 1 - s) * p.delta)
                    before = np.where(again, visit_gain(w, earlier, p), before)
                gain = gain + end_scale * (visit_gain(w, later, p) - before)
            value = value + np.where(self.free_padded[new], gain, -np.inf)
            cells = np.column_stack([cells, new])
            pres = np.column_stack([pres, pre])
            keep = np.isfinite(value)
            if h < h_max - 1:  # the best ``beam`` per first action
                order = np.lexsort((-value, first))
                start_of = np.searchsorted(first[order], np.arange(n_act))
                rank = np.empty(len(order), dtype=np.int64)
                rank[order] = np.arange(len(order)) - start_of[first[order]]
                keep &= rank < self.beam
            cells, pres, value, first = cells[keep], pres[keep], value[keep], first[keep]
        scores = np.full(n_act, -np.inf)
        np.maximum.at(scores, first, value)
        if not len(value):
            return scores, None
        return scores, cells[int(np.argmax(value))]

    def _tree(self, near, fresh, p, best_path=False):
        """``(N, 5)`` scores over the path tree; with ``best_path`` (one drone) also the index of
        its best path (None if it has none). ``fresh[h]`` ``(C, N)``: the idleness of each near
        cell before step ``h`` if the path has not visited it, ``fresh[H]`` at the end visit."""
        h_max, end = self.horizon, self.end_weight > 0
        weight = p.alpha_T * self.belief_padded.ravel()[near] + p.alpha_I
        blocked = ~self.free_padded[near]
        wait = h_max + self.end_wait  # the step of the visit after the horizon
        end_scale = self.end_weight * self.discount**h_max
        pre, ends, value = [], [], None  # pre[s]: idleness before the step, per visit class
        for h, level in enumerate(self.levels):
            pre_h = fresh[h][level.cell]  # first visits
            for s, classes, earlier in level.revisits:  # the cell's previous visit at level s
                pre_h[classes] = np.minimum(1.0, p.eta * pre[s][earlier] + (h - 1 - s) * p.delta)
            w = weight[level.cell]
            gain = self.discount**h * visit_gain(w, pre_h, p)
            if end:  # this visit's end term replaces the previous one (no visit: fresh[H])
                end_h = visit_gain(w, np.minimum(1.0, p.eta * pre_h + (wait - 1 - h) * p.delta), p)
                before = visit_gain(w, fresh[h_max][level.cell], p)
                for s, classes, earlier in level.revisits:
                    before[classes] = ends[s][earlier]
                gain = gain + end_scale * (end_h - before)
                ends.append(end_h)
            gain[blocked[level.cell]] = -np.inf
            pre.append(pre_h)
            gain = gain[level.klass]  # (5^(h+1), N): every prefix of h + 1 steps
            if h == 0:
                value = 0.0 + gain
            elif h < h_max - 1 or best_path:
                value = np.repeat(value, 5, axis=0) + gain
            else:  # last level: best child per parent, then the parent's sum
                value = value + gain.reshape(len(value), 5, -1).max(axis=1)
        n_first = len(ACTION_DELTAS)
        scores = value.reshape(n_first, -1, value.shape[1]).max(axis=1).T
        if not best_path:
            return scores, None
        best = int(np.argmax(value[:, 0]))
        return scores, (best if np.isfinite(value[best, 0]) else None)


class _Level(NamedTuple):
    """Level ``h`` of the path tree. A prefix's gain depends only on its last cell and the
    steps at which the prefix stood there before (its *visit class*), so gains are computed
    per class: ``cell`` ``(K,)`` index of each class's cell among the near cells, ``klass``
    ``(5^(h+1),)`` the class of each prefix, and ``revisits``: ``(s, classes, earlier)`` for
    the classes whose cell was last visited at level ``s``, with their class at level ``s``."""

    cell: np.ndarray
    klass: np.ndarray
    revisits: list[tuple[int, np.ndarray, np.ndarray]]


def path_tree(offsets: np.ndarray, last: np.ndarray) -> tuple[np.ndarray, list[_Level]]:
    """The paths of :func:`action_paths` as a tree of prefixes, grouped in visit classes.

    Returns ``(cells, levels)``: ``cells`` ``(C, 2)`` the offsets within ``H`` steps that
    some prefix ends on, and one :class:`_Level` per step.
    """
    n_paths, horizon = last.shape
    cells, index = np.unique(offsets.reshape(-1, 2), axis=0, return_inverse=True)
    index = index.reshape(n_paths, horizon)
    levels, class_of = [], []  # class_of[h]: {(cell, visit steps): class index}
    for h in range(horizon):
        keys, klass = {}, []
        for path in np.arange(5 ** (h + 1)) * 5 ** (horizon - 1 - h):  # first path per prefix
            cell = int(index[path, h])
            steps = tuple(int(t) for t in np.flatnonzero(index[path, : h + 1] == cell))
            klass.append(keys.setdefault((cell, steps), len(keys)))
        revisits = {}
        for (cell, steps), k in keys.items():
            if len(steps) > 1:
                s = steps[-2]
                revisits.setdefault(s, []).append((k, class_of[s][(cell, steps[:-1])]))
        groups = [
            (s, *(np.array(v) for v in zip(*pairs, strict=True)))
            for s, pairs in sorted(revisits.items())
        ]
        cell_of = np.array([cell for cell, _ in keys], dtype=np.int64)
        levels.append(_Level(cell_of, np.array(klass, dtype=np.int64), groups))
        class_of.append(keys)
    return cells, levels


#: The swarms of this module by registry name (see :data:`twin.swarms.SWARMS`).
PLANNERS: dict[str, type[CoordinatedPolicy]] = {
    "greedy-coordinated": GreedyCoordinatedPolicy,
    "visit-gain": VisitGainPolicy,
    "lookahead": LookaheadPolicy,
}
