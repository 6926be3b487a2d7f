"""The patrol loop: several swarms side by side on one pass over a traffic source.

Each swarm keeps its own :class:`twin.swarm.SwarmState` (positions, idleness map, visited
cells) and advances with :func:`twin.swarm.step`; all swarms see the same ``T^k``. Per step and
swarm the loop records ``R^k`` (the headline score: each distinct visited cell paid once) and
its parts, Def. 4 as printed, ``C^{k+1}`` (Def. 5) and the share of free cells visited so far.
"""

from __future__ import annotations

import time
import zlib
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field, replace

import numpy as np

from twin.boundary import release_notices
from twin.errors import UserError
from twin.faults import FaultPlan, LiveDrones, recorded_arrivals
from twin.grid import Grid
from twin.policies import Policy, SwarmView, Transition
from twin.scores import ScoreParams, coverage
from twin.swarm import InfeasibleActionError, SwarmState, initial_state, random_starts, step
from twin.timing import (
    LIVE_VIEW,
    RECORDING,
    SCORING,
    TRAFFIC,
    TRAFFIC_OTHER,
    StageTimer,
    swarm_stage,
)
from twin.traffic.base import TrafficSource

__all__ = ["PatrolResult", "random_starts", "run_patrol", "swarm_rng", "swarm_view"]

#: How ``PatrolResult.error`` begins when the run was stopped on request (Ctrl-C).
INTERRUPTED = "interrupted"


@dataclass
class PatrolResult:
    """What one pass of several swarms over a traffic source produced."""

    swarms: list[str]
    grid: Grid
    seed: int
    rewards: np.ndarray  # (S, T): R^k, summed over drones
    reward_importance: np.ndarray  # (S, T): the alpha_T part of R^k
    reward_idleness: np.ndarray  # (S, T): the alpha_I part of R^k
    reward_paper: np.ndarray  # (S, T): Def. 4 as printed, summed over drones (gameable)
    coverage: np.ndarray  # (S, T): C^{k+1}
    visited_share: np.ndarray  # (S, T): share of free cells stood on up to step k+1
    positions: np.ndarray  # (S, T+1, N, 2): P_0 .. P_T
    importance: np.ndarray | None  # (T+1, nx, ny) float32, T^0 .. T^T
    truth: np.ndarray | None = None  # (T+1, nx, ny) float32 true T^k; None: same as importance
    params: ScoreParams | None = None  # eta, delta, alpha_T, alpha_I of the run
    seconds: float = 0.0
    completed_steps: int = 0
    error: str | None = None  # set when the source failed mid-run; arrays hold what was done
    extra: dict = field(default_factory=dict)
    #: wall seconds per stage of the loop (:mod:`twin.timing`), in the order of the step
    stage_seconds: dict[str, float] = field(default_factory=dict)
    faults: FaultPlan | None = None  # the scripted faults the swarms ran under (twin.faults)
    fault_free: PatrolResult | None = None  # the same swarms without them, same traffic

    @property
    def horizon(self) -> int:
        return self.rewards.shape[1]

    def select(self, rows) -> PatrolResult:
        """The result of the swarms at places ``rows`` alone (shared maps and timings kept)."""
        rows = list(rows)
        picked = {
            key: getattr(self, key)[rows]
            for key in ("rewards", "reward_importance", "reward_idleness", "reward_paper",
                        "coverage", "visited_share", "positions")
        }  # fmt: skip
        return replace(self, swarms=[self.swarms[s] for s in rows], extra=dict(self.extra),
                       **picked)  # fmt: skip


def swarm_rng(seed: int, name: str) -> np.random.Generator:
    """A generator per (seed, swarm): a swarm's randomness does not depend on the others."""
    return np.random.default_rng([seed, zlib.crc32(name.encode())])


def check_outages(name: str, policy: Policy, horizon: int) -> None:
    """A swarm's own coordinator outages (its option ``outages``) end by the horizon ``T``, as
    ``[faults].coordinator_down``'s do."""
    late = [w for w in getattr(policy, "outages", ()) if w[1] > horizon]
    if late:
        raise UserError(
            f"[swarm_options.{name}].outages has [{late[0][0]}, {late[0][1]}] past the horizon "
            f"T = {horizon}; end it by {horizon}"
        )


def run_patrol(
    source: TrafficSource,
    policies: Mapping[str, Policy],
    starts: np.ndarray,
    params: ScoreParams,
    seed: int = 0,
    progress: bool = False,
    keep_importance: bool = True,
    stop: Callable[[], bool] | None = None,
    on_step: Callable[[int, dict[str, np.ndarray], np.ndarray], None] | None = None,
    faults: FaultPlan | None = None,
    fault_free: Mapping[str, Policy] | None = None,
) -> PatrolResult:
    """Run every swarm in ``policies`` from ``starts`` over the whole horizon of ``source``.

    If the source fails mid-run (a simulation crash), or ``stop()`` turns true between two steps
    (Ctrl-C, see :func:`twin.experiment.stop_on_interrupt`), the result keeps the steps completed
    so far, truncated to them, and says why in ``error``.

    ``on_step(k, positions, importance)``, if given, is called at ``k = 0 .. T`` once every
    swarm stands at ``P_k`` (``{swarm: (N, 2)}``) under ``T^k``, before ``T^{k+1}`` is pulled
    (a live source is still at step k's time): the GUI draws there.

    ``faults`` (:class:`twin.faults.FaultPlan`) applies to every swarm of ``policies``;
    ``fault_free`` (the same swarm names, fresh policies) runs beside them without the faults,
    on the same traffic and with the same randomness, and comes back as the result's
    ``fault_free``.
    """
    grid, horizon = source.grid, source.horizon
    plan = faults if faults is not None and faults.active else None
    names = list(policies)
    runs = [(name, policies[name], plan) for name in names]
    if plan is not None and fault_free:
        runs += [(name, fault_free[name], None) for name in names]
    for name, policy, _ in runs:
        check_outages(name, policy, horizon)
    acting: dict[int, Policy] = {}  # each run's policy, by its place in ``runs``
    for s, (_, policy, faulted) in enumerate(runs):
        if faulted is not None and faulted.coordinator_down:
            policy.outages = tuple(faulted.coordinator_down)
        acting[s] = LiveDrones(policy, faulted) if faulted and faulted.drone_loss else policy
    stages = [swarm_stage(name if faulted or plan is None else f"{name} (fault-free)")
              for name, _, faulted in runs]  # fmt: skip
    n_swarms, n_drones = len(runs), len(starts)
    starts = np.asarray(starts, dtype=np.int64)
    series = {
        key: np.zeros((n_swarms, horizon))
        for key in ("rewards", "importance", "idleness", "paper", "coverage", "visited")
    }
    positions = np.zeros((n_swarms, horizon + 1, n_drones, 2), dtype=np.int64)
    importance = np.zeros((horizon + 1, *grid.shape), np.float32) if keep_importance else None
    truth = None
    timer = StageTimer()

    states: list[SwarmState] = []
    views: list[SwarmView] = []
    maps = source.importance_maps()
    t0 = time.perf_counter()
    bar = None
    done, error = 0, None
    in_swarm = False  # a swarm's own error before any step done is no partial result
    try:
        with timer.stage(TRAFFIC):
            t_now = next(maps)
        release_notices()  # the simulation started: its notices, then the progress bar
        bar = _progress_bar(source, horizon, progress)
        truth = _record_truth(source, truth, 0, horizon, keep_importance)
        if importance is not None:
            importance[0] = t_now
        for s, (name, _, _) in enumerate(runs):
            t_reset = time.perf_counter()
            in_swarm = True
            acting[s].reset(grid, n_drones, swarm_rng(seed, name))
            in_swarm = False
            timer.add(stages[s], time.perf_counter() - t_reset, calls=0)
            states.append(initial_state(grid, starts.copy(), t_now))
            views.append(swarm_view(states[s], horizon, grid, params))
            positions[s, 0] = starts
        if on_step is not None:
            with timer.stage(LIVE_VIEW):
                on_step(0, {name: states[s].positions for s, name in enumerate(names)}, t_now)
        for k in range(horizon):
            with timer.stage(TRAFFIC):
                t_next = next(maps)
            with timer.stage(RECORDING):
                truth = _record_truth(source, truth, k + 1, horizon, keep_importance)
                if importance is not None:
                    importance[k + 1] = t_next
            for s, (name, _, faulted) in enumerate(runs):
                policy, view = acting[s], views[s]
                stage = stages[s]
                recorded = recorded_arrivals(faulted, seed, k + 1, n_drones, horizon)
                in_swarm = True
                with timer.stage(stage):
                    actions = np.asarray(policy.act(view), dtype=np.int64)
                t_score = time.perf_counter()
                try:
                    states[s], out = step(states[s], actions, t_next, grid, params, recorded)
                except InfeasibleActionError as exc:
                    raise RuntimeError(f"swarm {name!r} chose an infeasible action: {exc}") from exc
                for key, values in (
                    ("rewards", out.rewards),
                    ("importance", out.importance),
                    ("idleness", out.idleness),
                    ("paper", out.paper),
                ):
                    series[key][s, k] = values.sum()
                series["coverage"][s, k] = coverage(states[s].idleness, grid)
                series["visited"][s, k] = states[s].visited[grid.free].mean()
                positions[s, k + 1] = states[s].positions
                views[s] = swarm_view(states[s], horizon, grid, params)
                t1 = time.perf_counter()
                timer.add(SCORING, t1 - t_score)
                policy.learn(Transition(view, actions, out.rewards, views[s]))
                in_swarm = False
                timer.add(stage, time.perf_counter() - t1, calls=0)
            done = k + 1
            if on_step is not None:
                with timer.stage(LIVE_VIEW):
                    positions_now = {name: states[s].positions for s, name in enumerate(names)}
                    on_step(done, positions_now, t_next)
            if bar is not None:
                bar.update(1)
                clock = source.clock(k + 1)
                if clock:
                    bar.set_postfix_str(clock, refresh=False)
            if stop is not None and stop() and done < horizon:
                error = f"{INTERRUPTED} after {done} of {horizon} steps"
                break
    except StopIteration:
        release_notices()
        error = f"traffic source ended after {done} of {horizon} steps"
    except Exception as exc:
        if (
            isinstance(exc, UserError)
            or not source.keeps_partial_results
            or ((in_swarm or isinstance(exc, MemoryError)) and done == 0)
        ):  # bad input (a file a simulator refuses to start on), a swarm that failed before its
            raise  # first step (no torch cache) or memory that ran out before it (a warm-up of
            # the city): no partial result of the simulation
        release_notices()  # a partial run: what it said of its scenario still holds
        error = f"{type(exc).__name__}: {exc}" if str(exc) else f"{type(exc).__name__}"
        if isinstance(exc, MemoryError):
            error = f"out of memory ({error}); use a smaller grid, horizon or fewer seeds"
    finally:
        if bar is not None:
            bar.close()
        maps.close()  # ends a live simulation now (one in its own process reports back)
    cut = {key: values[:, :done] for key, values in series.items()}
    result = PatrolResult(
        swarms=[name for name, _, _ in runs],
        grid=grid,
        seed=seed,
        rewards=cut["rewards"],
        reward_importance=cut["importance"],
        reward_idleness=cut["idleness"],
        reward_paper=cut["paper"],
        coverage=cut["coverage"],
        visited_share=cut["visited"],
        positions=positions[:, : done + 1],
        importance=None if importance is None else importance[: done + 1],
        truth=None if truth is None else truth[: done + 1],
        params=params,
        seconds=time.perf_counter() - t0,
        completed_steps=done,
        error=error,
        stage_seconds=_stage_seconds(timer, source),
        extra={
            "process_stages": source.process_stages(),
            "process_peak_mb": source.process_peak_mb,
        },
        faults=plan,
    )
    if len(runs) > len(names):  # the fault-free twins: a result of their own
        result, twin = result.select(range(len(names))), result.select(range(len(names), len(runs)))
        twin.faults = None
        result.fault_free = twin
    return result


def _stage_seconds(timer: StageTimer, source: TrafficSource) -> dict[str, float]:
    """The loop's stages, the traffic source's time split into the source's own stages (a live
    simulation times its stepping, reads and observation model) and the rest. When the source
    runs in its own process, the loop only waits for it: that wait is the traffic stage
    (:attr:`TrafficSource.waiting_stage`), and that process's stages are kept apart
    (:meth:`TrafficSource.process_stages`)."""
    seconds = timer.as_dict()
    own = source.timer
    traffic = seconds.pop(TRAFFIC, 0.0)
    if source.separate_process:
        return {source.waiting_stage: traffic, **seconds}
    if own is None or not own.seconds:
        return {TRAFFIC: traffic, **seconds}
    split = own.as_dict()
    split[TRAFFIC_OTHER] = max(traffic - sum(split.values()), 0.0)
    return {**split, **seconds}


def swarm_view(state: SwarmState, horizon: int, grid: Grid, params: ScoreParams) -> SwarmView:
    """What a policy sees of ``state``."""
    return SwarmView(
        k=state.k,
        horizon=horizon,
        grid=grid,
        positions=state.positions,
        idleness=state.idleness,
        importance=state.importance,
        feasible=state.feasible,
        params=params,
        recorded=state.recorded,
    )


def _record_truth(source, truth, k, horizon, keep):
    """Store the source's true ``T^k`` when it knows one (:meth:`TrafficSource.truth_map`)."""
    if not keep:
        return None
    t = source.truth_map()
    if t is None:
        return truth
    if truth is None:
        truth = np.zeros((horizon + 1, *t.shape), np.float32)
    truth[k] = t
    return truth


def _progress_bar(source: TrafficSource, horizon: int, enabled: bool):
    if not enabled:
        return None
    from tqdm.auto import tqdm

    return tqdm(total=horizon, desc="patrol", unit="step", leave=False, dynamic_ncols=True)
