"""Coordinated classical swarms: a score per drone and action, then the exact coordinator.

Each swarm scores the cell every action leads to and hands the ``(N, 5)`` scores to
:func:`twin.coordinator.coordinate` (eq. maxi:op2), which picks the joint action with the
largest sum of scores among those whose next cells are distinct. So no two drones ever share a
cell (when they start on distinct cells) and the only difference with the learned swarm is the
score.

- ``greedy-coordinated``: greedy's score ``I^k T^k`` of the cell reached;
- ``visit-gain``: the one-step gain of visiting the cell reached (:func:`visit_gain`);
- ``lookahead``: the best summed visit gain over paths of ``H`` steps starting with the move.

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
from twin.policies import Policy, SwarmView
from twin.scores import visit_gain

#: Relative size of the tie-breaking jitter: scores closer than this count as tied.
TIE_JITTER = 1e-9
#: Default planning horizon of ``lookahead``, chosen on R_hat_T (see :class:`LookaheadPolicy`).
DEFAULT_HORIZON = 4
#: Largest horizon accepted: 5^H paths per drone (H = 5: 1.7 s per step with 1000 drones).
MAX_HORIZON = 5


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
    ``5^(H-1)`` feasible paths of ``H`` steps that start with it; then the assignment.

    Along a path the idleness of each cell is predicted from ``I^k``: ``min(1, I + h delta)``
    after ``h`` steps, ``eta I`` at the path's own visits, recovering again after them. The
    other drones' future visits are ignored (only the first moves are coordinated).

    What it reads: the swarm's idleness map ``I^k`` (all cells, as ``rl`` does) and a belief
    of the importance: for each cell the last ``T`` seen in any drone's field of view (the
    current ``T^k`` there), 0 for cells never seen, held constant along the path. With
    ``H = 1`` the only cells scored are in view, so the scores are exactly ``visit-gain``'s.

    How: the paths form a tree (level ``h`` holds the ``5^(h+1)`` prefixes of ``h + 1``
    steps); each node adds its step's gain to its parent's sum, so a shared prefix is summed
    once, in the same order as path by path (bit for bit the same sums). The gain of a first
    visit is looked up in a table over the ``2H(H+1)+1`` cells within ``H`` steps; only
    revisits are computed per node. The last level needs no sums: rounding is monotone, so
    ``max_c (v + g_c) = v + max_c g_c``. Cost per step: about ``N 5^H`` lookups, all drones
    at once (no loop over drones or paths).

    ``DEFAULT_HORIZON`` is the ``H`` with the largest mean R_hat_T on ``configs/synthetic.toml``,
    seeds 0-9, among those taking well under a second per step at 200 x 300 cells with 1000
    drones (``python benchmarks/bench_swarms.py --pick-horizon``; R_hat_T mean ± 95%, ms/step
    at 200 x 300 with 1000 drones, measured path by path before the tree): H=1 2.719 ± 0.031,
    2 ms; H=2 2.736 ± 0.032, 3 ms; H=3 2.705 ± 0.040, 10 ms; H=4 2.784 ± 0.046, 135 ms;
    H=5 2.782 ± 0.046, 1665 ms.
    """

    name = "lookahead"

    def __init__(self, horizon: int = DEFAULT_HORIZON, discount: float = 1.0):
        if isinstance(horizon, bool) or not isinstance(horizon, int | np.integer):
            raise UserError(f"lookahead: horizon = {horizon!r} must be an integer; e.g. 2")
        if not 1 <= horizon <= MAX_HORIZON:
            raise UserError(
                f"lookahead: horizon = {horizon} must lie in 1..{MAX_HORIZON} "
                f"(5^H paths per drone); e.g. {DEFAULT_HORIZON}"
            )
        if not 0.0 < float(discount) <= 1.0:
            raise UserError(f"lookahead: discount = {discount} must lie in (0, 1]; e.g. 1.0")
        self.horizon = int(horizon)
        self.discount = float(discount)
        self.offsets, self.last, self.first = action_paths(self.horizon)
        self.cells, self.levels = path_tree(self.offsets, self.last)

    def reset(self, grid: Grid, n_drones: int, rng: np.random.Generator) -> None:
        super().reset(grid, n_drones, rng)
        h = self.horizon
        self.width = grid.ny + 2 * h  # maps padded by H: every path stays inside
        self.cell_flat = self.cells[:, 0] * self.width + self.cells[:, 1]  # (C,) rel. flat ids
        self.free_padded = np.pad(grid.free, h, constant_values=False).ravel()
        self.belief_padded = np.zeros((grid.nx + 2 * h, grid.ny + 2 * h))
        self.belief = self.belief_padded[h:-h, h:-h]  # last seen T per cell, 0 if never seen
        self.idle_padded = np.zeros_like(self.belief_padded)

    def scores(self, view: SwarmView) -> np.ndarray:
        grid, p, h_max = view.grid, view.params, self.horizon
        flat, valid = grid.view_index(view.positions)
        i, j = np.divmod(flat[valid], grid.ny)
        self.belief[i, j] = view.importance[i, j]
        self.idle_padded[h_max:-h_max, h_max:-h_max] = view.idleness

        pos = np.asarray(view.positions, dtype=np.int64)
        base = (pos[:, 0] + h_max) * self.width + pos[:, 1] + h_max
        near = self.cell_flat[:, None] + base[None, :]  # (C, N) padded flat ids
        weight = p.alpha_T * self.belief_padded.ravel()[near] + p.alpha_I
        idle = self.idle_padded.ravel()[near]
        blocked = ~self.free_padded[near]
        pre, value = [], None  # pre[s]: predicted idleness before the step, per visit class
        for h, level in enumerate(self.levels):
            pre_h = np.minimum(1.0, idle[level.cell] + h * p.delta)  # first visits
            for s, classes, earlier in level.revisits:  # the cell's previous visit at level s
                pre_h[classes] = np.minimum(1.0, p.eta * pre[s][earlier] + (h - 1 - s) * p.delta)
            gain = self.discount**h * visit_gain(weight[level.cell], pre_h, p)
            gain[blocked[level.cell]] = -np.inf
            pre.append(pre_h)
            gain = gain[level.klass]  # (5^(h+1), N): every prefix of h + 1 steps
            if h == 0:
                value = 0.0 + gain
            elif h < h_max - 1:
                value = np.repeat(value, 5, axis=0) + gain
            else:  # last level: best child per parent, then the parent's sum
                value = value + gain.reshape(len(value), 5, -1).max(axis=1)
        n_first = len(ACTION_DELTAS)
        return value.reshape(n_first, -1, len(pos)).max(axis=1).T


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


#: The swarms of this module by registry name (see ``twin.policies._REGISTRY``).
PLANNERS: dict[str, type[CoordinatedPolicy]] = {
    "greedy-coordinated": GreedyCoordinatedPolicy,
    "visit-gain": VisitGainPolicy,
    "lookahead": LookaheadPolicy,
}
