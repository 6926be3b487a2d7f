"""Ceilings on the headline score: an oracle swarm and an upper bound no swarm can exceed.

The headline score (``shared/notes/paper-notes.md``, "The headline score";
:func:`twin.scores.rewards_on_arrival`) pays at step k every DISTINCT visited cell c

    g(c) = (alpha_T T^{k+1}(c) + alpha_I) (min(1, I^k(c) + delta) - eta I^k(c)),

with Def. 3's idleness ``I^{k+1} = eta I^k`` on visited cells, ``min(1, I^k + delta)``
elsewhere, ``I^0 = 1``; ``R_hat_T`` is the mean of ``R^k = sum_c g(c)`` over the horizon.

Both ceilings read the TRUE importance maps of every step in advance (the maps a synthetic
source yields, or a live run's recorded maps), which no swarm has. They are rows of the
results tables with ``role = "ceiling"``, never candidates for the best swarm.

- :func:`lagrangian_bound`, "bound (ceiling)": a Lagrangian relaxation of the swarm's problem.
  Moves are ignored (any cell can be visited at any step); what remains couples the cells only
  through "between 1 and N cells visited per step", which is relaxed with a price
  ``lambda_k`` per step. Then every cell is its own problem, a DP over its visit times
  (:func:`cell_dp`), and for ANY prices

      R_hat_T * T <= L(lambda) = sum_c V_c(lambda) + sum_k max(N lambda_k, lambda_k),

  so the bound is the smallest ``L`` the subgradient steps find, divided by ``T``. The
  relaxation has a gap of its own besides the moves: on a 1 x 2 grid with two drones (every
  cell visited every step, moves irrelevant) it lies well above the only possible score.
- :func:`oracle`, "oracle (ceiling)": real swarms (moves, the coordinator's distinct cells)
  planned on the true maps, the row being the best of them on each seed (:data:`ORACLE_SWARMS`):
  the look-ahead on the true future maps with an end value for the idleness a path leaves
  (:class:`TrueLookaheadPolicy`), the one-step visit gain scored with the true
  ``T^{k+1}`` (:class:`TrueVisitGainPolicy`), and the ``lookahead`` and ``tours`` swarms told
  the whole present map (:class:`KnownMapLookaheadPolicy`, :class:`KnownMapToursPolicy`). A
  lower bound on the best swarm possible, so with the bound it brackets the headroom.

Measured (R_hat_T, mean ± 95% interval over seeds; the bound is one number when the seeds
share the traffic):

- synthetic, ``twin evaluate --seeds 10 --swarms visit-gain,lookahead`` (configs/synthetic.toml,
  seeds 0-9, T = 2000, 4 drones): visit-gain 2.628 ± 0.014, lookahead 2.591 ± 0.014,
  oracle 2.734 ± 0.016 (1.040 x visit-gain; won by the true-map look-ahead on every seed),
  bound 2.955 (1.124 x; 40 subgradient steps, 15 s). The best swarm reaches 88.9% of the
  bound, the oracle 92.5%. The dual's optimum lies a little lower: 150 subgradient steps give
  2.949; the smoothed dual (``lagrangian_bound(..., smoothing=(0.01, 0.002),
  smoothing_steps=45)``: soft-max DP, L-BFGS) 2.9215 then 2.918, in 13 min on the shared
  2-core machine. So the best swarm reaches 90.1% of that tighter bound, the oracle 93.7%.
- synthetic, ``twin evaluate --config configs/synthetic.toml --seeds 10`` with the known-map
  tours among the oracle's swarms: oracle 2.842 ± 0.005 (won by it on 9 seeds of 10), tours
  2.812 ± 0.034; tours is above the oracle on seeds 2 and 3 (by 0.007 and 0.011: told the map
  at step 0, the oracle's tours plan before the drones have spread, the swarm's after a
  saturation period of visit-gain).
- Shenzhen-like, ``twin run --seed 0 --swarms visit-gain,lookahead,greedy-coordinated``
  (configs/shenzhen.toml, T = 144): visit-gain 1.990, lookahead 2.034, oracle 2.108, bound
  2.365 (the best swarm reaches 86.0% of it, the oracle 89.1%); the ceilings took 1.4 s.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
import pandas as pd

from twin.grid import ACTION_DELTAS, Grid
from twin.metrics import BOUND, CEILING_ROLE, ORACLE, table2
from twin.planners import CoordinatedPolicy, LookaheadPolicy
from twin.policies import Policy, SwarmView
from twin.scores import ScoreParams, visit_gain
from twin.tours import ToursPolicy


def visit_factor(idleness: np.ndarray, params: ScoreParams) -> np.ndarray:
    """``f(I) = min(1, I + delta) - eta I``: the bracket of ``g`` (concave, largest at
    ``I = 1 - delta``)."""
    return np.minimum(1.0, idleness + params.delta) - params.eta * idleness


def n_gap_states(params: ScoreParams, horizon: int) -> int:
    """``D``: a cell last visited ``d >= D`` steps ago (or never) has ``I = 1`` exactly, since
    ``(D - 1) delta >= 1``; gaps ``1 .. D - 1`` are the DP's other states. Capped by the
    horizon (no gap is longer)."""
    if params.delta <= 0:
        return horizon + 1
    return int(min(1 + math.ceil(1.0 / params.delta - 1e-12), horizon + 1))


#: Levels of the upper bound on a cell's idleness after its last visit (the DP's states).
DEFAULT_LEVELS = 1


@dataclass(frozen=True)
class CellStates:
    """The states of one cell in the DP of :func:`cell_dp`.

    A cell's idleness right after a visit at step s is ``x = eta I^s``; from then on
    ``I^{s+d} = min(1, x + (d - 1) delta)``. A state is ``(m, d)``: ``d = 1 .. D-1`` steps since
    the last visit and a level ``m`` with ``x <= u_m = eta (m + 1) / M``; state 0: ``I = 1``
    exactly (never visited, or not for ``D`` steps: :func:`n_gap_states`).

    - ``factors[s]``: the largest bracket ``f(I) = min(1, I + delta) - eta I`` of a visit from
      state s, over ``x`` in ``[0, u_m]`` (``f`` is concave, top at ``1 - delta``); ``1 - eta``
      from state 0;
    - ``skip[s]``: the state a step later without a visit (``d + 1``, or 0 once ``d + 1 = D``);
    - ``visit[s]``: the state after a visit, gap 1 and the lowest level with
      ``u >= eta min(1, u_m + (d - 1) delta)`` (top level from state 0, where ``x = eta``).

    Every real history of the cell follows a path of states whose ``u_m`` is at least its true
    ``x`` (the visit map and ``factors`` grow with ``u``), and each visit pays at most
    ``w factors[s]``: so the DP's value bounds the cell's real pay from above. It is exact when
    ``eta = 0``; the levels only tighten (more levels, closer to the true ``x``).
    """

    factors: np.ndarray
    skip: np.ndarray
    visit: np.ndarray

    @classmethod
    def build(cls, params: ScoreParams, horizon: int, levels: int = DEFAULT_LEVELS) -> CellStates:
        n_gap = n_gap_states(params, horizon)
        eta, delta = params.eta, params.delta
        levels = max(1, int(levels)) if eta > 0 else 1
        upper = eta * np.arange(1, levels + 1) / levels  # u_m
        m, d = np.meshgrid(np.arange(levels), np.arange(1, n_gap), indexing="ij")
        m, d = m.ravel(), d.ravel()
        state = 1 + m * (n_gap - 1) + (d - 1)  # flat index of (m, d)
        lo = np.minimum(1.0, (d - 1.0) * delta)
        hi = np.minimum(1.0, upper[m] + (d - 1.0) * delta)
        n_states = 1 + levels * (n_gap - 1)
        factors = np.empty(n_states)
        factors[0] = 1.0 - eta
        factors[state] = visit_factor(np.clip(1.0 - delta, lo, hi), params)
        skip = np.zeros(n_states, dtype=np.int64)
        skip[state] = np.where(d + 1 < n_gap, state + 1, 0)
        after = eta * hi  # the largest x after the visit
        level = np.searchsorted(upper, after - 1e-12 * max(eta, 1.0))
        level = np.minimum(level, levels - 1)
        visit = np.empty(n_states, dtype=np.int64)
        visit[0] = 1 + (levels - 1) * (n_gap - 1)
        visit[state] = 1 + level * (n_gap - 1)
        return cls(factors, skip, visit)


@dataclass
class CellDP:
    """The per-cell DP of :func:`cell_dp` at fixed prices."""

    total: float  # sum over cells of V_c at step 0 (the cells start at I = 1: state 0)
    visits: np.ndarray  # (T,) cells visited per step by the DP's optimal visit plans


def cell_dp(weights: np.ndarray, prices: np.ndarray, states: CellStates) -> CellDP:
    """Every cell's best visit plan at prices ``lambda_k``, all cells at once (numpy over cells
    and states, a loop over steps).

    ``weights`` ``(T, C)``: ``w_k(c) = alpha_T T^{k+1}(c) + alpha_I`` of the free cells. Backward
    over k, with ``V_T = 0`` and the states of :class:`CellStates`::

        V_k(s) = max( V_{k+1}(skip[s]),                                  # no visit
                      w_k factors[s] - lambda_k + V_{k+1}(visit[s]) )    # visit: paid <= g

    Then a forward pass follows the argmax from state 0 and counts each step's visits (the
    subgradient's data).
    """
    horizon, n_cells = weights.shape
    n_states = len(states.factors)
    value = np.zeros((n_cells, n_states))
    visit_best = np.empty((horizon, n_cells, n_states), dtype=bool)
    factors = states.factors[None, :]
    for k in range(horizon - 1, -1, -1):
        skip = value[:, states.skip]
        visit = value[:, states.visit]
        visit += weights[k][:, None] * factors
        visit -= prices[k]
        np.greater(visit, skip, out=visit_best[k])
        value = np.maximum(visit, skip, out=visit)
    state = np.zeros(n_cells, dtype=np.int64)
    cells = np.arange(n_cells)
    visits = np.empty(horizon)
    for k in range(horizon):
        v = visit_best[k, cells, state]
        visits[k] = v.sum()
        state = np.where(v, states.visit[state], states.skip[state])
    return CellDP(float(value[:, 0].sum()), visits)


def cell_weights(maps: np.ndarray, grid: Grid, params: ScoreParams) -> np.ndarray:
    """``(T, C)`` weights ``alpha_T T^{k+1} + alpha_I`` of the free cells, from ``(T+1, nx,
    ny)`` maps ``T^0 .. T^T``."""
    flat = np.asarray(maps, dtype=np.float64).reshape(len(maps), -1)[1:, grid.free.ravel()]
    return params.alpha_T * flat + params.alpha_I


@dataclass
class Bound:
    """The Lagrangian upper bound on ``R_hat_T`` and the prices that give it."""

    value: float  # best (smallest) L(lambda) / T found
    prices: np.ndarray  # (T,) lambda_k of that bound
    history: list[float] = field(default_factory=list)  # L(lambda) / T per iteration
    seconds: float = 0.0


def lagrangian_bound(
    maps: np.ndarray,
    grid: Grid,
    n_drones: int,
    params: ScoreParams,
    iterations: int = 40,
    target: float | None = None,
    levels: int = DEFAULT_LEVELS,
    smoothing: tuple[float, ...] = (),
    smoothing_steps: int = 40,
) -> Bound:
    """Upper bound on the ``R_hat_T`` of any ``n_drones``-drone swarm on the true ``maps``.

    A swarm visits ``n_k`` distinct cells at step k, ``1 <= n_k <= N``. With a price
    ``lambda_k`` of any sign per step and ``h(lambda) = max(N lambda, lambda)`` (so
    ``lambda n_k <= h(lambda_k)``),

        T R_hat_T <= L(lambda) = sum_c V_c(lambda) + sum_k h(lambda_k)

    (:func:`cell_dp`): the swarm's visits are one visit plan per cell, each paying at most its
    cell's DP value at these prices plus ``lambda_k`` per visit. ``L`` is convex; a
    subgradient at ``lambda_k`` is ``h'(lambda_k) - n_k`` (``n_k`` now the DP plans' visits;
    at 0, ``clip(n_k, 1, N) - n_k``). Steps ``lambda <- lambda - s g`` with Polyak's ``s``
    towards ``target`` (``R_hat_T`` scale; default 0.99 of the best bound so far), halved when
    3 steps bring no progress. Initial prices: the one price for every step with the smallest
    ``L`` (golden-section search). Any prices give a valid bound; the smallest found is kept.

    ``smoothing`` (temperatures, e.g. ``(0.01, 0.002)``; none by default: slow) then refines
    the prices on the smoothed dual (:func:`soft_dual`: the DP's max replaced by a soft-max,
    which is at least the max, so it too bounds from above) with L-BFGS, up to
    ``smoothing_steps`` evaluations per temperature, and keeps the hard ``L`` at the prices
    found if lower. On the synthetic map it reaches 2.918 where 40 subgradient steps give 2.955,
    in 13 min instead of 15 s.
    """
    import time

    t0 = time.perf_counter()
    weights = cell_weights(maps, grid, params)
    horizon, n_cells = weights.shape
    factors = CellStates.build(params, horizon, levels)
    n = min(n_drones, n_cells)
    evaluate = _dual(weights, factors, n)
    top = (1.0 - params.eta + params.delta) * weights.max()  # no visit pays more
    prices = np.full(horizon, _best_flat_price(evaluate, horizon, top))
    best, best_prices, history = math.inf, prices.copy(), []
    theta, stall = 0.5, 0
    for _ in range(max(1, iterations)):
        value, visits = evaluate(prices)
        history.append(value / horizon)
        if value < best - 1e-9 * abs(best if math.isfinite(best) else 1.0):
            best, best_prices, stall = value, prices.copy(), 0
        else:
            stall += 1
            if stall >= 3:
                theta, stall = theta / 2.0, 0
        grad = np.where(prices > 0, n, np.where(prices < 0, 1, np.clip(visits, 1, n))) - visits
        norm = float(grad @ grad)
        if norm == 0.0:  # 0 is a subgradient: L is at its minimum
            break
        goal = target * horizon if target is not None else 0.99 * best
        step = theta * max(value - goal, 1e-6 * abs(value)) / norm
        prices = prices - step * grad
    if smoothing:
        from scipy.optimize import minimize

        prices = np.maximum(best_prices, 0.0)
        for tau in smoothing:
            found = minimize(
                soft_dual,
                prices,
                args=(weights, factors, n, float(tau)),
                jac=True,
                method="L-BFGS-B",
                bounds=[(0.0, None)] * horizon,
                options={"maxfun": int(smoothing_steps)},
            )
            prices = found.x
            value, _ = evaluate(prices)
            history.append(value / horizon)
            if value < best:
                best, best_prices = value, prices.copy()
    return Bound(best / horizon, best_prices, history, time.perf_counter() - t0)


def bound_dp_bytes(params: ScoreParams, horizon: int, n_free: int) -> int:
    """The bytes of the bound's DP decisions (steps x free cells x cell states): past
    :data:`MAX_DP_BYTES` the bound is left out, and not replayed."""
    n_states = len(CellStates.build(params, horizon).factors)
    return horizon * n_free * n_states


def bound_at(
    maps: np.ndarray, grid: Grid, n_drones: int, params: ScoreParams, prices: np.ndarray
) -> float:
    """``L(prices) / T`` of :func:`lagrangian_bound` on ``maps`` (any prices bound ``R_hat_T``
    from above; at the prices a run found, its bound row): one DP pass, what a run folder's
    read-back replays of its ``bound (ceiling)`` row."""
    weights = cell_weights(np.asarray(maps, dtype=np.float64), grid, params)
    horizon, n_cells = weights.shape
    if np.shape(prices) != (horizon,):
        raise ValueError(f"{np.shape(prices)} prices for {horizon} steps")
    factors = CellStates.build(params, horizon, DEFAULT_LEVELS)
    value, _ = _dual(weights, factors, min(n_drones, n_cells))(np.asarray(prices, dtype=float))
    return value / horizon


def soft_dual(
    prices: np.ndarray, weights: np.ndarray, states: CellStates, n: int, tau: float
) -> tuple[float, np.ndarray]:
    """The smoothed dual ``L_tau(lambda) / T`` for ``lambda >= 0`` and its gradient.

    :func:`cell_dp` with ``max(a, b)`` replaced by ``tau log(e^{a/tau} + e^{b/tau}) >= max(a, b)``,
    so ``L_tau >= L``: still an upper bound, and smooth. Its gradient in ``lambda_k`` is
    ``N - E[n_k]``: the expected visits of step k when each cell visits with probability
    ``sigmoid((visit - skip) / tau)`` (a forward pass over the state distributions).
    """
    horizon, n_cells = weights.shape
    n_states = len(states.factors)
    value = np.zeros((n_cells, n_states))
    chance = np.empty((horizon, n_cells, n_states), np.float32)
    for k in range(horizon - 1, -1, -1):
        skip = value[:, states.skip]
        visit = value[:, states.visit] + weights[k][:, None] * states.factors[None, :] - prices[k]
        diff = visit - skip
        value = np.maximum(visit, skip) + tau * np.log1p(np.exp(-np.abs(diff) / tau))
        chance[k] = 0.5 * (1.0 + np.tanh(diff / (2.0 * tau)))
    to_visit = np.zeros((n_states, n_states))
    to_visit[np.arange(n_states), states.visit] = 1.0
    to_skip = np.zeros((n_states, n_states))
    to_skip[np.arange(n_states), states.skip] = 1.0
    dist = np.zeros((n_cells, n_states))
    dist[:, 0] = 1.0
    visits = np.empty(horizon)
    for k in range(horizon):
        moving = dist * chance[k]
        visits[k] = moving.sum()
        dist = moving @ to_visit + (dist - moving) @ to_skip
    total = value[:, 0].sum() + n * float(prices.sum())
    return total / horizon, (n - visits) / horizon


def _dual(weights: np.ndarray, factors: CellStates, n: int):
    """``prices -> (L(prices), visits per step)``."""

    def evaluate(prices: np.ndarray) -> tuple[float, np.ndarray]:
        dp = cell_dp(weights, prices, factors)
        paid = np.where(prices > 0, n * prices, prices)
        return dp.total + float(paid.sum()), dp.visits

    return evaluate


def _best_flat_price(evaluate, horizon: int, high: float, rounds: int = 12) -> float:
    """The one price for every step with the smallest ``L``: ``L`` is convex in it, so a
    golden-section search on ``[0, high]`` (``high``: no visit pays more than it)."""
    ratio = (math.sqrt(5.0) - 1.0) / 2.0
    lo, hi = 0.0, high
    a, b = hi - ratio * (hi - lo), lo + ratio * (hi - lo)
    fa = fb = None
    for _ in range(rounds):
        if fa is None:
            fa = evaluate(np.full(horizon, a))[0]
        if fb is None:
            fb = evaluate(np.full(horizon, b))[0]
        if fa <= fb:
            hi, b, fb, fa = b, a, fa, None
            a = hi - ratio * (hi - lo)
        else:
            lo, a, fa, fb = a, b, fb, None
            b = lo + ratio * (hi - lo)
    return (lo + hi) / 2.0


class TrueVisitGainPolicy(CoordinatedPolicy):
    """The one-step visit gain scored with the true ``T^{k+1}`` that the reward will use (a
    swarm reads ``T^k``): the headline score's exact one-step maximiser, with foresight."""

    name = "visit-gain-true"

    def __init__(self, maps: np.ndarray):
        self.maps = np.asarray(maps)

    def scores(self, view: SwarmView) -> np.ndarray:
        grid, p = view.grid, view.params
        fov = grid.view_index(view.positions)
        t_next = self.maps[min(view.k + 1, len(self.maps) - 1)]
        weight = p.alpha_T * grid.values_in_view(t_next, None, fov) + p.alpha_I
        return visit_gain(weight, grid.values_in_view(view.idleness, None, fov), p)


class TrueLookaheadPolicy(LookaheadPolicy):
    """The receding-horizon planner of :class:`twin.planners.LookaheadPolicy` on the true maps,
    with an end value: a path's visit at level h (step ``k + h``) is paid its true gain
    ``g`` with ``T^{k+h+1}``, plus ``rho w`` times the change it makes to the cell's idleness at
    the path's end (``min(1, eta I + (H-1-h) delta) - min(1, I + (H-h) delta)``, ``I`` the
    predicted idleness before the visit), so that harvesting a cell that has not recovered
    costs what it takes from later visits (``rho = 0``: no end value).
    """

    name = "lookahead-true"

    def __init__(self, maps: np.ndarray, horizon: int = 4, end_value: float = 0.5):
        # its own end value and tree below: the parent's search with none of its options
        super().__init__(horizon, end_weight=0.0, plan="independent", beam=0)
        self.maps = np.asarray(maps)
        self.end_value = float(end_value)

    def scores(self, view: SwarmView) -> np.ndarray:
        p, h_max = view.params, self.horizon
        self.idle_padded[h_max:-h_max, h_max:-h_max] = view.idleness
        pos = np.asarray(view.positions, dtype=np.int64)
        base = (pos[:, 0] + h_max) * self.width + pos[:, 1] + h_max
        near = self.cell_flat[:, None] + base[None, :]  # (C, N) padded flat ids
        idle = self.idle_padded.ravel()[near]
        blocked = ~self.free_padded[near]
        last = len(self.maps) - 1
        pre, value = [], None
        for h, level in enumerate(self.levels):
            self.belief[:] = self.maps[min(view.k + 1 + h, last)]
            weight = p.alpha_T * self.belief_padded.ravel()[near] + p.alpha_I
            pre_h = np.minimum(1.0, idle[level.cell] + h * p.delta)
            for s, classes, earlier in level.revisits:
                pre_h[classes] = np.minimum(1.0, p.eta * pre[s][earlier] + (h - 1 - s) * p.delta)
            w = weight[level.cell]
            gain = visit_gain(w, pre_h, p)
            after = np.minimum(1.0, p.eta * pre_h + (h_max - 1 - h) * p.delta)
            without = np.minimum(1.0, pre_h + (h_max - h) * p.delta)
            gain += self.end_value * w * (after - without)
            gain[blocked[level.cell]] = -np.inf
            pre.append(pre_h)
            gain = gain[level.klass]
            if h == 0:
                value = 0.0 + gain
            elif h < h_max - 1:
                value = np.repeat(value, 5, axis=0) + gain
            else:
                value = value + gain.reshape(len(value), 5, -1).max(axis=1)
        return value.reshape(len(ACTION_DELTAS), -1, len(pos)).max(axis=1).T


class KnownMapLookaheadPolicy(LookaheadPolicy):
    """The ``lookahead`` swarm, with its own defaults, told the whole true map ``T^{k+1}`` at
    every step instead of the last ``T`` seen in its fields of view: the yardstick with
    perfect knowledge of the present. The oracle can still fall below the ``lookahead`` swarm
    on a seed (a plan on the present map is not better on every day than one on stale
    sightings); :func:`twin.metrics.headroom` says so when it does."""

    name = "lookahead-known-map"

    def __init__(self, maps: np.ndarray, **options):
        super().__init__(**options)
        self.maps = np.asarray(maps)

    def update_belief(self, view: SwarmView) -> None:
        self.belief[:] = self.maps[min(view.k + 1, len(self.maps) - 1)]


class KnownMapToursPolicy(ToursPolicy):
    """The ``tours`` swarm told the whole true map ``T^{k+1}`` at every step (no survey, its
    first plan at step 0): the cyclic patrol with perfect knowledge of the present, so the
    oracle stays above ``tours``."""

    name = "tours-known-map"

    def __init__(self, maps: np.ndarray, **options):
        super().__init__(**{"survey": False, "explore": 0, **options})
        self.maps = np.asarray(maps)

    def _see(self, view: SwarmView) -> None:
        self.belief[:] = self.maps[min(view.k + 1, len(self.maps) - 1)]
        self.seen[:] = True
        self.last_seen[:] = view.k
        self.now = view.k


#: The largest DP (steps x free cells x states, one byte each) the bound is computed for.
MAX_DP_BYTES = 2e9

#: The oracle's swarms: (name, planner options); the oracle row is the best on each seed.
ORACLE_SWARMS: tuple[tuple[str, dict], ...] = (
    ("visit-gain-true", {}),
    ("lookahead-known-map", {"known_map": True}),
    ("tours-known-map", {"known_map": "tours"}),
    ("lookahead-true H=4", {"horizon": 4, "end_value": 1.0}),
    ("lookahead-true H=5", {"horizon": 5, "end_value": 1.0}),
    ("lookahead-true H=4 rho=0.9", {"horizon": 4, "end_value": 0.9}),
)


def _oracle_swarm(maps: np.ndarray, options: dict) -> Policy:
    if not options:
        return TrueVisitGainPolicy(maps)
    if options.get("known_map") == "tours":
        return KnownMapToursPolicy(maps)
    if options.get("known_map"):
        return KnownMapLookaheadPolicy(maps)
    return TrueLookaheadPolicy(maps, **options)


def oracle(
    maps: np.ndarray,
    grid: Grid,
    starts: np.ndarray,
    params: ScoreParams,
    seed: int = 0,
    faults=None,
) -> tuple[pd.Series, str, pd.DataFrame]:
    """Run the oracle swarms (:data:`ORACLE_SWARMS`) on the true ``maps`` from ``starts``;
    return the best one's Table 2 row (:func:`twin.metrics.table2`), its name, and every
    oracle swarm's rows (``attrs["best_positions"]``: the best one's ``(T+1, N, 2)`` cells). Each is a real swarm (moves, distinct cells by the coordinator);
    choosing the best in hindsight is what makes it an oracle rather than a competitor.
    ``faults`` (:class:`twin.faults.FaultPlan`): the oracle swarms fly under the same faults."""
    from twin.patrol import run_patrol
    from twin.traffic.base import RecordedTraffic

    maps = np.asarray(maps, dtype=np.float64)
    swarms = {name: _oracle_swarm(maps, options) for name, options in ORACLE_SWARMS}
    result = run_patrol(
        RecordedTraffic(grid, maps), swarms, starts, params, seed=seed, faults=faults
    )
    table = table2(result, params)
    best = table.loc[table["R_hat_T"].idxmax()]
    table.attrs["best_positions"] = result.positions[list(table.index).index(best.name)]
    return best, str(best["swarm"]), table


def ceiling_table(
    result, params: ScoreParams | None = None, cache: dict | None = None
) -> pd.DataFrame:
    """The ceiling rows of one seed's :class:`twin.patrol.PatrolResult`, laid out as
    :func:`twin.metrics.table2` (``role = "ceiling"``): ``oracle (ceiling)`` with the columns
    of its best oracle swarm (``pct_time_max_C`` left empty: the oracle is not among the
    swarms compared), ``bound (ceiling)`` with ``R_hat_T`` alone.

    The true maps are those the swarms were scored on, ``result.importance`` (a live run's
    recorded maps): so the ceilings are computed after the swarms' run. ``cache`` (a dict)
    keeps bounds by maps, so seeds on the same traffic (synthetic, a replayed tape) share one.
    Empty when the result kept no maps or ran no step.
    """
    import hashlib

    params = params or result.params
    maps = result.importance
    if maps is None or params is None or len(maps) < 2:
        return pd.DataFrame()
    maps = np.asarray(maps, dtype=np.float64)
    starts = result.positions[0, 0]
    key = (hashlib.sha1(maps.tobytes()).hexdigest(), len(starts), astuple_params(params))
    cache = {} if cache is None else cache
    dp_bytes = bound_dp_bytes(params, len(maps) - 1, result.grid.n_free)
    if dp_bytes > MAX_DP_BYTES:
        from twin.boundary import notify

        notify(
            f"twin: notice: bound (ceiling) left out: its DP would hold {dp_bytes / 1e9:.1f} GB "
            f"({len(maps) - 1} steps x {result.grid.n_free} cells x "
            f"{dp_bytes // ((len(maps) - 1) * result.grid.n_free)} states)"
        )
        bound = None
    elif key not in cache:
        bound = cache[key] = lagrangian_bound(maps, result.grid, len(starts), params)
    else:
        bound = cache[key]
    row, name, oracles = oracle(maps, result.grid, starts, params, result.seed, result.faults)
    oracle_row = row.to_dict()
    oracle_row.update(swarm=ORACLE, pct_time_max_C=np.nan, oracle_swarm=name)
    rows = [oracle_row]
    if bound is not None:
        rows.append({"swarm": BOUND, "R_hat_T": bound.value})
    table = pd.DataFrame(rows)
    table["role"] = CEILING_ROLE
    if bound is not None:
        table.attrs["bound_prices"] = bound.prices  # kept in bound.npz: the row is replayed
    # kept in oracle.parquet: the row is replayed (twin.report.derived.check_ceilings)
    table.attrs["oracle_positions"] = oracles.attrs["best_positions"]
    return table


def astuple_params(params: ScoreParams) -> tuple[float, ...]:
    return (params.eta, params.delta, params.alpha_T, params.alpha_I)
