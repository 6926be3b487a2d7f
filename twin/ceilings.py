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
  through "at most N cells visited per step", which is relaxed with a price ``lambda_k >= 0``
  per step. Then every cell is its own problem, a DP over its visit times (:func:`cell_dp`),
  and for ANY prices

      R_hat_T * T <= L(lambda) = sum_c V_c(lambda) + N sum_k lambda_k,

  so the bound is the smallest ``L`` the subgradient steps find, divided by ``T``.
- :func:`oracle`, "oracle (ceiling)": real swarms (moves, the coordinator's distinct cells)
  planned on the true maps; the row is the best of them on each seed. One is the price-directed
  swarm (:class:`PricedPolicy`): each drone scores a cell by its gain now plus what the cell's
  own DP (on the true maps, at the bound's prices) says a visit now is worth against waiting;
  the other is the one-step visit gain scored with the true ``T^{k+1}``
  (:class:`TrueVisitGainPolicy`).

Measured (synthetic, ``configs/synthetic.toml``, seeds 0-9, T = 2000, 4 drones, by
``twin evaluate --seeds 10 --swarms visit-gain``): see :data:`MEASURED`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
import pandas as pd

from twin.grid import Grid
from twin.planners import CoordinatedPolicy
from twin.policies import SwarmView
from twin.scores import ScoreParams, visit_gain

#: Names of the ceiling rows in the results tables.
ORACLE = "oracle (ceiling)"
BOUND = "bound (ceiling)"
CEILINGS = (ORACLE, BOUND)
SWARM_ROLE, CEILING_ROLE = "swarm", "ceiling"

#: Filled in by measurement; quoted by the module docstring.
MEASURED = ""


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
    values: np.ndarray | None = None  # (T+1, C, S) float32 V_k(c, state) when kept


def cell_dp(
    weights: np.ndarray, prices: np.ndarray, states: CellStates, keep_values: bool = False
) -> CellDP:
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
    values = np.empty((horizon + 1, n_cells, n_states), np.float32) if keep_values else None
    if values is not None:
        values[horizon] = 0.0
    factors = states.factors[None, :]
    for k in range(horizon - 1, -1, -1):
        skip = value[:, states.skip]
        visit = value[:, states.visit]
        visit += weights[k][:, None] * factors
        visit -= prices[k]
        np.greater(visit, skip, out=visit_best[k])
        value = np.maximum(visit, skip, out=visit)
        if values is not None:
            values[k] = value
    state = np.zeros(n_cells, dtype=np.int64)
    cells = np.arange(n_cells)
    visits = np.empty(horizon)
    for k in range(horizon):
        v = visit_best[k, cells, state]
        visits[k] = v.sum()
        state = np.where(v, states.visit[state], states.skip[state])
    return CellDP(float(value[:, 0].sum()), visits, values)


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
) -> Bound:
    """Upper bound on the ``R_hat_T`` of any ``n_drones``-drone swarm on the true ``maps``.

    ``L(lambda) = sum_c V_c(lambda) + N sum_k lambda_k`` (:func:`cell_dp`) bounds ``T R_hat_T``
    for every ``lambda >= 0``: a swarm's visits are one visit plan per cell with at most N
    cells a step, each plan's pay is at most its cell's DP value at those prices plus
    ``lambda_k`` per visit, and the visits are at most N a step. Subgradient of ``L`` at
    ``lambda``: ``N - n_k`` (``n_k`` the DP's visits at step k); projected steps
    ``lambda <- max(0, lambda - s (N - n))`` with Polyak's step towards ``target`` (a value
    reached by a swarm, ``R_hat_T`` scale; default 0.99 of the best bound so far), the step
    halved when 3 steps bring no progress. Initial prices: the one price for every step with
    the smallest ``L`` (a golden-section search; ``L`` is convex in it).
    """
    import time

    t0 = time.perf_counter()
    weights = cell_weights(maps, grid, params)
    horizon, n_cells = weights.shape
    factors = CellStates.build(params, horizon, levels)
    n = min(n_drones, n_cells)
    if n >= n_cells:  # the constraint never binds
        prices = np.zeros(horizon)
        dp = cell_dp(weights, prices, factors)
        return Bound(dp.total / horizon, prices, [dp.total / horizon], time.perf_counter() - t0)
    evaluate = _dual(weights, factors, n)
    prices = np.full(
        horizon,
        _best_flat_price(evaluate, horizon, (1.0 - params.eta + params.delta) * weights.max()),
    )
    best, best_prices, history = math.inf, prices.copy(), []
    theta, stall = 0.5, 0
    for _ in range(iterations):
        value, visits = evaluate(prices)
        history.append(value / horizon)
        if value < best - 1e-9 * abs(best if math.isfinite(best) else 1.0):
            best, best_prices, stall = value, prices.copy(), 0
        else:
            stall += 1
            if stall >= 3:
                theta, stall = theta / 2.0, 0
        grad = n - visits
        norm = float(grad @ grad)
        if norm == 0.0:  # the DP's plans visit exactly N cells a step: L is the optimum
            break
        goal = target * horizon if target is not None else 0.99 * best
        step = theta * max(value - goal, 1e-6 * abs(value)) / norm
        prices = np.maximum(0.0, prices - step * grad)
    return Bound(best / horizon, best_prices, history, time.perf_counter() - t0)


def _dual(weights: np.ndarray, factors: CellStates, n: int):
    """``prices -> (L(prices), visits per step)``."""

    def evaluate(prices: np.ndarray) -> tuple[float, np.ndarray]:
        dp = cell_dp(weights, prices, factors)
        return dp.total + n * float(prices.sum()), dp.visits

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


class PricedPolicy(CoordinatedPolicy):
    """The price-directed swarm: a drone's move to cell c at step k scores

        g_k(c) + V_{k+1}(c, 1) - V_{k+1}(c, next(d_c)),

    the true gain now (:func:`twin.scores.visit_gain` with ``T^{k+1}`` and ``I^k``) plus what
    the cell's DP (:func:`cell_dp` at the bound's prices, on the true maps) values a visit now
    against leaving it (``d_c``: the gap since the swarm last visited c). So a hot cell is not
    revisited before it has recovered enough to be worth it; the coordinator keeps cells
    distinct.
    """

    name = "priced"

    def __init__(
        self,
        maps: np.ndarray,
        grid: Grid,
        params: ScoreParams,
        prices: np.ndarray,
        levels: int = DEFAULT_LEVELS,
    ):
        self.maps = np.asarray(maps)
        horizon = len(self.maps) - 1
        self.states = CellStates.build(params, horizon, levels)
        weights = cell_weights(self.maps, grid, params)
        self.values = cell_dp(weights, prices, self.states, keep_values=True).values
        self.cell_of = np.full(grid.shape, -1, dtype=np.int64)
        self.cell_of[grid.free] = np.arange(grid.n_free)

    def reset(self, grid: Grid, n_drones: int, rng: np.random.Generator) -> None:
        super().reset(grid, n_drones, rng)
        self.state = np.zeros(grid.n_free, dtype=np.int64)  # gap state of every free cell
        self.last_k = -1

    def scores(self, view: SwarmView) -> np.ndarray:
        grid, p, k = view.grid, view.params, view.k
        if k != self.last_k + 1:
            raise RuntimeError("the price-directed swarm must be run step by step from k = 0")
        if k > 0:  # the cells at P_k were visited at step k - 1
            visited = np.zeros(grid.n_free, dtype=bool)
            visited[self.cell_of[view.positions[:, 0], view.positions[:, 1]]] = True
            self.state = np.where(
                visited, self.states.visit[self.state], self.states.skip[self.state]
            )
        self.last_k = k
        fov = grid.view_index(view.positions)
        t_next = self.maps[min(k + 1, len(self.maps) - 1)]
        weight = p.alpha_T * grid.values_in_view(t_next, None, fov) + p.alpha_I
        gain = visit_gain(weight, grid.values_in_view(view.idleness, None, fov), p)
        flat, valid = fov
        cells = np.where(valid, self.cell_of.ravel()[np.where(valid, flat, 0)], -1)
        ok = cells >= 0
        later = self.values[min(k + 1, len(self.values) - 1)]
        c = np.where(ok, cells, 0)
        now = self.state[c]
        future = later[c, self.states.visit[now]] - later[c, self.states.skip[now]]
        return np.where(ok, gain + future, gain)


def oracle(
    maps: np.ndarray,
    grid: Grid,
    starts: np.ndarray,
    params: ScoreParams,
    seed: int = 0,
    bound: Bound | None = None,
) -> tuple[pd.Series, str, pd.DataFrame]:
    """Run the oracle swarms on the true ``maps`` from ``starts``; return the best one's Table 2
    row (:func:`twin.metrics.table2`), its name, and every oracle swarm's rows."""
    from twin.metrics import table2
    from twin.patrol import run_patrol
    from twin.traffic.base import RecordedTraffic

    maps = np.asarray(maps, dtype=np.float64)
    if bound is None:
        bound = lagrangian_bound(maps, grid, len(starts), params)
    swarms = {
        "priced": PricedPolicy(maps, grid, params, bound.prices),
        "visit-gain-true": TrueVisitGainPolicy(maps),
    }
    result = run_patrol(RecordedTraffic(grid, maps), swarms, starts, params, seed=seed)
    table = table2(result, params)
    best = table.loc[table["R_hat_T"].idxmax()]
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
    if key not in cache:
        cache[key] = lagrangian_bound(maps, result.grid, len(starts), params)
    bound = cache[key]
    row, name, _ = oracle(maps, result.grid, starts, params, result.seed, bound)
    oracle_row = row.to_dict()
    oracle_row.update(swarm=ORACLE, pct_time_max_C=np.nan, oracle_swarm=name)
    bound_row = {"swarm": BOUND, "R_hat_T": bound.value}
    table = pd.DataFrame([oracle_row, bound_row])
    table["role"] = CEILING_ROLE
    return table


def astuple_params(params: ScoreParams) -> tuple[float, ...]:
    return (params.eta, params.delta, params.alpha_T, params.alpha_I)


def is_ceiling_row(frame: pd.DataFrame) -> pd.Series:
    """Which rows of a results table are ceilings (``role == "ceiling"``), not swarms."""
    if "role" not in frame.columns:
        return pd.Series(False, index=frame.index)
    return frame["role"].eq(CEILING_ROLE)


def swarm_rows(frame: pd.DataFrame) -> pd.DataFrame:
    """The rows of a results table that are swarms (ceilings left out)."""
    return frame[~is_ceiling_row(frame)]


def headroom(summary: pd.DataFrame, column: str = "R_hat_T") -> str | None:
    """``best swarm X reaches a% of the bound; oracle b%`` from a summary with ceiling rows
    (``None`` without them): how much of the headline score is left above the best swarm."""
    if column not in summary.columns:
        return None
    ceilings = summary[is_ceiling_row(summary)].set_index("swarm")[column]
    swarms = swarm_rows(summary).set_index("swarm")[column].dropna()
    if swarms.empty or BOUND not in ceilings or not np.isfinite(ceilings[BOUND]):
        return None
    best = str(swarms.idxmax())
    text = f"best swarm {best} reaches {swarms[best] / ceilings[BOUND]:.1%} of the bound"
    if ORACLE in ceilings and np.isfinite(ceilings[ORACLE]):
        text += f"; oracle {ceilings[ORACLE] / ceilings[BOUND]:.1%}"
    return (
        f"Headroom ({column}): {text} (bound {ceilings[BOUND]:.3f}, "
        f"oracle {ceilings.get(ORACLE, float('nan')):.3f}, {best} {swarms[best]:.3f})"
    )
