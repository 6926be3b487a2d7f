"""A run folder's derived files checked against its primary files before a report shows them.

``twin run`` and ``twin evaluate`` score each swarm by stepping it through
:func:`twin.swarm.step` over the maps that ``importance.npz`` keeps for the first seed (a live
run's maps being its ``tape.parquet`` seen through the MFD), write ``series.parquet`` of those
scores, find the congestion events of ``events.parquet`` on the maps, compute ``per_seed.csv``
from what ``series.parquet``, ``trajectories.parquet``, ``events.parquet`` and
``incidents.json`` record, ``summary.csv`` from ``per_seed.csv``, ``monitoring.csv`` from
``summary.csv`` and ``comparison.csv`` from ``per_seed.csv``. :data:`DERIVED` lists, for each
derived file, the columns that its sources determine and how they are recomputed, with the
functions that computed them at run time (:func:`twin.swarm.step`,
:func:`twin.monitoring.belief_error_curve`, :func:`twin.monitoring.congestion_events`,
:func:`twin.monitoring.incident_sightings`, :func:`twin.metrics.series_columns`,
:func:`twin.monitoring.ceiling_coverage`, :class:`twin.monitoring.RunMonitoring`,
:func:`twin.metrics.aggregate`, :func:`twin.metrics.learned_against_best_classical`);
:func:`check_tape_maps` replays the tape (:class:`twin.traffic.tape.TapeTraffic`). A value
further than :data:`TOLERANCE` from its recomputation (and, for what the importance maps
weigh, their float32 rounding, :data:`MAP_ROUNDING`) is one :class:`UserError` line naming
both files, the column, the swarm and the seed: the report never shows a figure its run's
files contradict.

A synthetic run's ``importance.npz`` is what run.json's ``traffic`` generates
(:func:`check_synthetic_maps`); a live run's ``incidents.json`` is what its schedule records,
on its network when that is still at hand (:func:`check_incident_records`). A live run of several seeds keeps every seed's tape in ``tapes/``: the first seed's must be
``tape.parquet``, and each later seed's per-step scores, belief error and events are replayed
over its tape's maps (:func:`check_seed_tapes`).

Not recomputed (their inputs are not all in the folder): the per-step scores, belief error,
reward split and incident columns of seeds other than the first when their maps are not kept
(a synthetic run's, or without ``tapes/``: their scores are checked only to add up to the
per-seed figures, their reward split to add up to ``R_hat_T``), their incident columns; the events and belief error when the run scored them on a recorded
truth (run.json ``monitoring.truth``: vehicles the drones missed), which the folder does not
keep, or when run.json does not say which; ``importance.npz``, ``mfd_samples.parquet`` and
``mfd.json`` of a live run whose ``tape.parquet`` has more than :data:`TAPE_REPLAY_ROWS` rows
(a city-scale tape takes longer to read back than the report to draw; its tapes' SUMO seeds
and ``network.json`` are still checked against the tapes' metadata); the oracle row
(:mod:`twin.ceilings`: its trajectories are not kept; it is checked to lie below its seed's
bound row, which is replayed at ``bound.npz``'s prices, :func:`check_bound`).
"""

from __future__ import annotations

from collections.abc import Callable, Iterable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

from twin.errors import UserError
from twin.files import nan_as_null
from twin.grid import ACTION_DELTAS, Grid
from twin.metrics import (
    MONITORING_COLUMNS,
    aggregate,
    is_ceiling_row,
    learned_against_best_classical,
    series_columns,
)
from twin.monitoring import (
    EVENT_COLUMNS,
    RunMonitoring,
    ceiling_coverage,
    congestion_events,
    event_sightings,
    sightings,
)
from twin.readback import RERUN
from twin.runs import FOLDER_FORMAT
from twin.scores import ScoreParams, coverage, paper_rewards
from twin.swarm import InfeasibleActionError, initial_state, step

#: How far a derived figure may lie from its recomputation (relative, at least absolute):
#: float rounding of the same sums done in the same order, and the CSV round trip.
TOLERANCE = 1e-9
#: How far an importance kept in ``importance.npz`` may lie from the one a run scored on,
#: relative to it: the swarms were scored on the maps as their source gave them, which are kept
#: rounded to float32 (to nearest: within half of float32's epsilon; this allows all of it). A
#: score's alpha_T part (Def. 4) is linear in the maps, so it may differ from its replay by this
#: share of itself; the alpha_I part, coverage and visited share do not depend on them.
MAP_ROUNDING = float(np.finfo(np.float32).eps)
#: Suffix of a recomputed column's per-row slack (absolute) beyond :data:`TOLERANCE`.
SLACK = " slack"


@dataclass
class Primary:
    """The primary files of a run folder, read and checked (:func:`twin.report.load.load_run`)."""

    run_dir: Path
    series: pd.DataFrame
    trajectories: pd.DataFrame
    events: pd.DataFrame | None
    obstacles: np.ndarray
    run: dict[str, Any]
    swarms: list[str]  # the swarms of summary.csv (ceiling rows left out)
    #: per_seed.csv once checked (or, without one, the per-seed figures of the primary files)
    per_seed: pd.DataFrame | None = None
    summary: pd.DataFrame | None = None  # summary.csv once checked
    #: ``(T+1, nx, ny)`` importance maps of ``importance.npz`` and the seed they are of
    importance: np.ndarray | None = None
    first_seed: int | None = None
    incidents: list[dict[str, Any]] | None = None  # incidents.json (the first seed's)
    #: the first seed's swarms replayed over those maps (:func:`_replays`), once computed
    replayed: dict[str, dict[str, np.ndarray]] | None = field(default=None, repr=False)
    #: each seed's :func:`run_monitoring`, by seed and the events table it was made of
    monitored: dict[tuple[int, int], RunMonitoring] = field(default_factory=dict, repr=False)
    #: ``(steps, nx, ny)`` maps of each seed's tape replayed through its MFD, by seed, once
    #: replayed (:func:`check_tape_maps`, :func:`check_seed_tapes`)
    tape_maps: dict[int, np.ndarray] = field(default_factory=dict, repr=False)
    #: how each replayed tape's drones sighted (its source's :class:`twin.belief.SightingModel`),
    #: by seed: the belief models' replay needs it (:mod:`twin.report.beliefs`)
    tape_sightings: dict[int, Any] = field(default_factory=dict, repr=False)
    #: the later seeds' reward splits replayed over their tapes (:func:`replayed_split`), to
    #: check ``per_seed.csv`` with once the first seed's figures are (:func:`check_seed_tapes`)
    later_splits: list[pd.DataFrame] = field(default_factory=list, repr=False)

    def positions(self, seed: int, swarm: str) -> np.ndarray:
        """``(T+1, N, 2)`` drone cells of one swarm and seed."""
        return positions_of(self.run_dir / "trajectories.parquet", self.trajectories, seed, swarm)

    def params(self) -> ScoreParams | None:
        from twin.runs import score_params_of

        return score_params_of(self.run)


def positions_of(path: Path, frame: pd.DataFrame, seed: int, swarm: str) -> np.ndarray:
    """``(T+1, N, 2)`` drone cells of one swarm and seed of a trajectories table (checked by
    :func:`twin.readback.check_trajectories`) read from ``path``."""
    rows = frame[(frame["seed"] == seed) & (frame["swarm"].astype(str) == swarm)]
    if rows.empty:
        raise UserError(
            f"{path}: no rows for swarm {swarm!r}, seed {seed}, which series.parquet holds; {RERUN}"
        )
    rows = rows.sort_values(["step", "drone"])
    n_drones = int(rows["drone"].max()) + 1
    return rows[["i", "j"]].to_numpy(np.int64).reshape(-1, n_drones, 2)


@dataclass(frozen=True)
class Derivation:
    """Columns of ``file`` that ``source`` determines: ``recompute(primary, frame)`` gives
    them for the rows of ``key``, ``frame`` being the derived file's own table (a table
    without the key's columns: not recomputed)."""

    file: str
    source: str
    key: tuple[str, ...]
    recompute: Callable[[Primary, pd.DataFrame], pd.DataFrame]
    #: the file holds no row beyond those recomputed (of the seeds recomputed: the table's
    #: ``attrs["seeds"]``, else the seeds of its rows)
    complete: bool = False


def fault_plan(primary: Primary):
    """The run's scripted faults (:class:`twin.faults.FaultPlan`, run.json ``faults``), None
    without; a record that is not one is a :class:`UserError` line."""
    from twin.faults import FaultPlan

    record = primary.run.get("faults")
    try:
        plan = FaultPlan.from_record(record)
        if plan is not None:
            plan.recorded(0, 2, 1)  # every field of the right kind
            plan.phases(2, 1)
    except (TypeError, ValueError, AttributeError) as exc:
        raise UserError(
            f"{primary.run_dir / 'run.json'}: faults = {str(record)[:60]} is not a fault "
            f"record ({type(exc).__name__}); {RERUN}"
        ) from None
    return plan


#: The action (:data:`twin.grid.ACTIONS`) of each move ``(di, dj)``, at ``3 (di + 1) + dj + 1``.
_ACTION_OF_MOVE = np.full(9, -1, np.int64)
_ACTION_OF_MOVE[3 * (ACTION_DELTAS[:, 0] + 1) + ACTION_DELTAS[:, 1] + 1] = np.arange(
    len(ACTION_DELTAS)
)


def replay_scores(
    grid: Grid,
    params: ScoreParams,
    positions: np.ndarray,
    maps: np.ndarray,
    recorded: np.ndarray | None = None,
) -> dict[str, np.ndarray]:
    """One swarm's per-step scores ``k = 0 .. T-1`` replayed from its cells ``P_0 .. P_T``
    (``(T+1, N, 2)``) over the maps ``T^0 .. T^T``, stepped through :func:`twin.swarm.step`
    from :func:`twin.swarm.initial_state` as :func:`twin.patrol.run_patrol` stepped it:
    ``reward`` (``R^k``), its ``importance`` and ``idleness`` parts, ``paper`` (Def. 4 as
    printed) with ``paper_weight``, the sum of its alpha_T-weighted terms ``alpha_T (A_T + B_T)``
    (:func:`twin.scores.paper_rewards`: how far the maps' rounding can move it), ``coverage``
    (``C^{k+1}``, Def. 5) and ``visited_share``. ``recorded`` ``(T+1, N, 5)``: the sightings
    that count under scripted faults (:meth:`twin.faults.FaultPlan.recorded`; slot 0 is the
    drone's own cell, whose arrival then counts); None: all.

    A move that is no action (more than one cell) is a :class:`InfeasibleActionError`."""
    moves = np.diff(positions, axis=0)
    code = 3 * (moves[..., 0] + 1) + moves[..., 1] + 1
    valid = (np.abs(moves) <= 1).all(axis=-1)
    actions = np.where(valid, _ACTION_OF_MOVE[np.where(valid, code, 0)], -1)
    steps = len(moves)
    out = {key: np.empty(steps) for key in ("reward", "importance", "idleness", "paper",
                                            "paper_weight", "coverage", "visited_share")}  # fmt: skip
    # paper_rewards with alpha_T = 1, alpha_I = 0 and T^k negated: A_T + B_T
    weights = ScoreParams(params.eta, params.delta, 1.0, 0.0)
    state = initial_state(grid, positions[0], maps[0])
    free = grid.free
    for k in range(steps):
        arrived = None if recorded is None else recorded[k + 1, :, 0]
        before = state
        state, outcome = step(state, actions[k], maps[k + 1], grid, params, arrived)
        out["reward"][k] = outcome.rewards.sum()
        out["importance"][k] = outcome.importance.sum()
        out["idleness"][k] = outcome.idleness.sum()
        out["paper"][k] = outcome.paper.sum()
        movers = slice(None) if arrived is None else np.asarray(arrived, dtype=bool)
        terms = paper_rewards(grid, weights, before.idleness, -before.importance, maps[k + 1],
                              before.positions[movers], state.positions[movers])  # fmt: skip
        out["paper_weight"][k] = params.alpha_T * terms.sum()
        out["coverage"][k] = coverage(state.idleness, grid)
        out["visited_share"][k] = state.visited[free].mean()
    return out


def _replays(primary: Primary) -> dict[str, dict[str, np.ndarray]]:
    """:func:`replay_scores` of every swarm of the first seed over ``importance.npz``'s maps,
    with the run's score parameters and scripted faults (empty when run.json records no
    parameters); computed once."""
    if primary.replayed is not None:
        return primary.replayed
    params, maps, seed = primary.params(), primary.importance, primary.first_seed
    replays: dict[str, dict[str, np.ndarray]] = {}
    if params is not None and maps is not None and seed is not None:
        grid = Grid(primary.obstacles)
        plan = fault_plan(primary)
        plan = plan if plan is not None and plan.active else None
        for swarm in primary.swarms:
            pos = primary.positions(seed, swarm)
            recorded = None if plan is None else plan.recorded(seed, len(pos), pos.shape[1])
            try:
                replays[swarm] = replay_scores(grid, params, pos, maps[: len(pos)], recorded)
            except InfeasibleActionError as exc:
                raise UserError(
                    f"{primary.run_dir / 'trajectories.parquet'}: swarm {swarm!r}, seed {seed}: "
                    f"{exc}; {RERUN}"
                ) from None
    primary.replayed = replays
    return replays


def replayed_series(primary: Primary, frame: pd.DataFrame) -> pd.DataFrame:
    """The first seed's rows of ``series.parquet``: each swarm's trajectory replayed over
    ``importance.npz``'s maps (:func:`replay_scores`). The rewards' alpha_T parts may differ
    from the replay by the maps' float32 rounding (:data:`MAP_ROUNDING`)."""
    frames = []
    for swarm, r in _replays(primary).items():
        slack = MAP_ROUNDING * r["importance"]
        frames.append(
            pd.DataFrame(
                {
                    "seed": primary.first_seed,
                    "swarm": swarm,
                    "step": np.arange(len(r["reward"])),
                    "reward": r["reward"],
                    "reward" + SLACK: slack,
                    "cumulative_reward": r["reward"].cumsum(),
                    "cumulative_reward" + SLACK: slack.cumsum(),
                    "coverage": r["coverage"],
                    "visited_share": r["visited_share"],
                }
            )
        )
    if not frames:
        return pd.DataFrame(columns=["seed", "swarm", "step"])
    return pd.concat(frames, ignore_index=True)


def replayed_belief(primary: Primary, frame: pd.DataFrame) -> pd.DataFrame:
    """The first seed's ``belief_error`` of ``series.parquet``: each swarm's belief replayed
    from its trajectory over ``importance.npz``'s maps by
    :func:`twin.monitoring.belief_error_curve`, when the run scored it against those maps
    (run.json ``monitoring.truth``); not recomputed otherwise."""
    from twin.monitoring import DEFAULT_WEIGHT_FLOOR, belief_error_curve

    monitoring = primary.run.get("monitoring")
    seed = primary.first_seed
    if (
        "belief_error" not in frame.columns
        or not isinstance(monitoring, dict)
        or monitoring.get("truth") != OBSERVED_TRUTH
        or primary.importance is None
        or seed is None
    ):
        return pd.DataFrame()
    floor = float(monitoring.get("weight_floor", DEFAULT_WEIGHT_FLOOR))
    maps = primary.importance.astype(np.float32)  # as the run held them
    grid = Grid(primary.obstacles)
    plan = fault_plan(primary)
    frames = []
    for swarm in primary.swarms:
        pos = primary.positions(seed, swarm)
        recorded = None if plan is None else plan.recorded(seed, len(pos), pos.shape[1])
        curve = belief_error_curve(grid, pos, maps[: len(pos)], maps[: len(pos)], floor, recorded)
        steps = np.arange(len(pos) - 1)
        frames.append(
            pd.DataFrame({"seed": seed, "swarm": swarm, "step": steps, "belief_error": curve[1:]})
        )
    return pd.concat(frames, ignore_index=True) if frames else pd.DataFrame()


#: The incident columns of ``per_seed.csv`` (:func:`twin.monitoring.incident_scores`).
INCIDENT_COLUMNS = ("incidents", "pct_incidents_seen", "incident_latency_steps",
                    "incident_latency_min")  # fmt: skip


def replayed_incidents(primary: Primary, frame: pd.DataFrame) -> pd.DataFrame:
    """The first seed's incident columns: each swarm's sightings of ``incidents.json``'s
    incidents (the first seed's, as applied) replayed from its trajectory
    (:func:`twin.monitoring.incident_sightings`, :func:`twin.monitoring.incident_scores`); NaN
    when the folder has none (the run scheduled none, or none was applied). Their onset and
    last steps are checked against their times first (:func:`check_incident_steps`)."""
    from twin.monitoring import applied_incidents, incident_scores, incident_sightings
    from twin.runs import step_seconds_of

    seed, incidents = primary.first_seed, primary.incidents or []
    scheduled = bool(incidents)
    if folder_format(primary) >= 4:  # earlier twins counted one never applied as an incident
        incidents = applied_incidents(incidents)
    columns = [c for c in INCIDENT_COLUMNS if c in frame.columns]
    if seed is None or not columns:
        return pd.DataFrame()
    cells = [inc.get("cell") for inc in incidents]
    if not all(isinstance(c, list) and len(c) == 2 for c in cells):
        return pd.DataFrame()  # an incident never applied has no cell to be seen at
    for n, inc in enumerate(incidents):
        for name in ("onset_step", "end_step"):
            if not isinstance(inc.get(name), int) or isinstance(inc.get(name), bool):
                raise UserError(
                    f"{primary.run_dir / 'incidents.json'}: [{n}] has no {name}; {RERUN}"
                )
    check_incident_steps(primary)
    grid = Grid(primary.obstacles)
    plan = fault_plan(primary)
    step_s = step_seconds_of(primary.run)
    rows = []
    for swarm in primary.swarms:
        row = dict.fromkeys(columns, np.nan)
        if scheduled:  # (none applied: 0 incidents)
            pos = primary.positions(seed, swarm)
            recorded = None if plan is None else plan.recorded(seed, len(pos), pos.shape[1])
            first, latency = incident_sightings(grid, pos, incidents, recorded)
            scores = incident_scores(first, latency, step_s)
            row.update({c: scores[c] for c in columns if c in scores})
        rows.append({"seed": seed, "swarm": swarm, **row})
    return pd.DataFrame(rows)


def check_incident_steps(primary: Primary) -> None:
    """Each incident's ``onset_step`` and ``end_step`` are the steps its ``begin_s`` ..
    ``end_s`` meet (:func:`twin.sumo.incidents.onset_and_end_steps`, with run.json's
    ``traffic.begin``, ``step_s`` and ``horizon``), and ``end_s`` its ``begin_s`` plus its
    ``duration_min``."""
    from twin.clock import clock_seconds
    from twin.sumo.incidents import onset_and_end_steps

    traffic = primary.run.get("traffic")
    traffic = traffic if isinstance(traffic, dict) else {}
    begin, step_s, horizon = traffic.get("begin"), traffic.get("step_s"), traffic.get("horizon")
    t0 = clock_seconds(begin) if isinstance(begin, str) else None
    number = (int, float)
    if t0 is None or not isinstance(step_s, number) or not isinstance(horizon, int):
        return
    path = primary.run_dir / "incidents.json"
    for n, inc in enumerate(primary.incidents or []):
        start, end = inc.get("begin_s"), inc.get("end_s")
        if not (isinstance(start, number) and isinstance(end, number)):
            continue
        if not (np.isfinite(start) and np.isfinite(end)):
            raise UserError(f"{path}: [{n}].begin_s or end_s is not a finite time; {RERUN}")
        duration = inc.get("duration_min")
        given = start + 60.0 * duration if isinstance(duration, number) else None
        # on SUMO's milliseconds (twin before them wrote the end unrounded)
        if given is not None and not (_same(end, round(given, 3)) or _same(end, given)):
            raise UserError(
                f"{path}: [{n}].end_s = {_show(end, round(given, 3))}, but its begin_s and "
                "duration_min give "
                f"{_show(round(given, 3), end)}; {RERUN}"
            )
        onset, last = onset_and_end_steps(start, end, t0, step_s)
        for name, want in (("onset_step", onset), ("end_step", min(last, horizon))):
            if name in inc and inc[name] != want:
                raise UserError(
                    f"{path}: [{n}].{name} = {inc[name]}, but its begin_s and end_s give step "
                    f"{want} (run.json traffic.begin, step_s); {RERUN}"
                )


def check_incident_schedule(primary: Primary) -> None:
    """``incidents.json`` holds, in order, the incidents run.json's ``traffic.incidents``
    schedules (``[[traffic.incidents]]`` as configured,
    :func:`twin.sumo.incidents.configured_schedule`): each one's kind, lane, window
    (:func:`twin.sumo.incidents.incident_window`, with run.json's ``traffic.begin`` and
    ``step_s``) and its edge or cell as configured (an edge chosen from a cell at the onset is
    checked against the network by :func:`check_incident_records`, which runs first)."""
    from pydantic import ValidationError

    from twin.clock import clock_seconds
    from twin.config import IncidentSettings
    from twin.sumo.incidents import incident_window

    traffic = primary.run.get("traffic")
    if not isinstance(traffic, dict) or traffic.get("kind") != "sumo":
        return
    run_json, path = primary.run_dir / "run.json", primary.run_dir / "incidents.json"
    recorded = primary.incidents or []
    if "incidents" not in traffic:
        if recorded and folder_format(primary) >= 2:
            raise UserError(
                f"{run_json}: traffic.incidents (the configured schedule) is missing, but "
                f"{path} records {len(recorded)} incidents; {RERUN}"
            )
        return
    configured = traffic["incidents"]
    if not isinstance(configured, list):
        raise UserError(f"{run_json}: traffic.incidents is no list of incidents; {RERUN}")
    settings = []
    for n, item in enumerate(configured):
        try:
            settings.append(IncidentSettings.model_validate(item, context={"recorded": True}))
        except ValidationError as exc:
            why = exc.errors()[0]["msg"] if exc.errors() else str(exc)
            raise UserError(
                f"{run_json}: traffic.incidents[{n}] is no incident ({why}); {RERUN}"
            ) from None
    if len(settings) != len(recorded):
        raise UserError(
            f"{path}: {len(recorded)} incidents, but run.json's traffic.incidents schedules "
            f"{len(settings)}; {RERUN}"
        )
    begin, step_s = traffic.get("begin"), traffic.get("step_s")
    t0 = clock_seconds(begin) if isinstance(begin, str) else None
    if t0 is None or isinstance(step_s, bool) or not isinstance(step_s, (int, float)):
        return  # run.json's own checks refuse these
    for n, (want, inc) in enumerate(zip(settings, recorded, strict=True)):
        start, end = incident_window(want, n, t0, step_s)
        unrounded = incident_window(want, n, t0, step_s, ms=False)
        before = {"begin_s": unrounded[0], "end_s": unrounded[1]}
        expected = {
            "kind": want.kind,
            "lane": want.lane if want.kind == "lane_closed" else None,
            "begin_s": start,
            "end_s": end,
            "duration_min": want.duration_min,
        }
        if want.edge is not None:
            expected["edge"] = want.edge
        if want.cell is not None:
            expected["cell"] = list(want.cell)
        for name, value in expected.items():
            have = inc.get(name)
            same = (  # (on SUMO's milliseconds; earlier twins wrote the times unrounded)
                _same(have, value) or _same(have, before.get(name))
                if isinstance(value, float) else have == value
            )  # fmt: skip
            if not same:
                raise UserError(
                    f"{path}: [{n}].{name} = {_json_text(have)}, but run.json's "
                    f"traffic.incidents[{n}] schedules {_json_text(value)}; {RERUN}"
                )


#: The kinds of incident a run applies (:class:`twin.config.IncidentSettings`).
INCIDENT_KINDS = ("lane_closed", "edge_closed", "vehicle_stopped")


def _incidents_ran_to(primary: Primary) -> float | None:
    """The time (s) up to which every incident's lift was surely applied: the run's step
    before its last (its ``horizon`` steps of ``traffic.step_s`` from ``traffic.begin``), None
    when run.json does not say."""
    from twin.clock import parse_clock

    traffic = primary.run.get("traffic")
    horizon = primary.run.get("horizon")
    if not isinstance(traffic, dict) or not isinstance(horizon, int) or horizon < 1:
        return None
    begin, step_s = traffic.get("begin"), traffic.get("step_s")
    if not isinstance(begin, str) or not isinstance(step_s, (int, float)):
        return None
    try:
        return parse_clock(begin, "traffic.begin") + (horizon - 1) * float(step_s)
    except UserError:
        return None


def check_incident_records(primary: Primary) -> None:
    """Each incident of ``incidents.json`` is one :class:`twin.sumo.incidents.IncidentSchedule`
    records: a known kind; a lane for ``lane_closed`` only; a vehicle exactly when a stopped
    vehicle was applied; ``begin`` the clock of ``begin_s``; applied (``applied_s``) at the
    first SUMO step from ``begin_s`` (a vehicle stop: or a retry every 10 s while no vehicle
    is on the edge), before ``end_s``. When the network file run.json records (``traffic.
    net_file``) is present with the recorded ``identity.net_sha256``, an applied incident's
    edge is an edge of it, its lane one the edge has and its cell one the edge's lane 0 passes
    through (on the grid of ``network.json``; ``[-1, -1]``: an edge whose middle is off the
    grid); without the network these are not checked."""
    from twin.clock import clock_label
    from twin.readback import read_json
    from twin.sumo.session import SumoSession

    path = primary.run_dir / "incidents.json"
    step = SumoSession.step_length  # every SUMO step of a run (time advances in whole steps)
    number = (int, float)
    applied = []
    ran_to = _incidents_ran_to(primary)
    for n, inc in enumerate(primary.incidents or []):
        kind, lane, vehicle = inc.get("kind"), inc.get("lane"), inc.get("vehicle")
        start, end, when = inc.get("begin_s"), inc.get("end_s"), inc.get("applied_s")
        if kind not in INCIDENT_KINDS:
            raise UserError(
                f"{path}: [{n}].kind = {kind!r} is none of {', '.join(INCIDENT_KINDS)}; {RERUN}"
            )
        if (lane is not None) != (kind == "lane_closed") or (lane is not None and lane < 0):
            want = "a lane index >= 0" if kind == "lane_closed" else "null"
            raise UserError(
                f"{path}: [{n}].lane = {_json_text(lane)}, but kind {kind} records {want}; {RERUN}"
            )
        if not (isinstance(start, number) and isinstance(end, number)):
            continue
        if not (np.isfinite(start) and np.isfinite(end)):
            continue  # refused with its steps (check_incident_steps)
        if isinstance(inc.get("begin"), str) and inc["begin"] != clock_label(start):
            raise UserError(
                f"{path}: [{n}].begin = {inc['begin']!r}, but its begin_s = {_show(start)} is "
                f"{clock_label(start)!r}; {RERUN}"
            )
        stopped = kind == "vehicle_stopped" and when is not None
        if (vehicle is not None) != stopped:
            want = "the vehicle it stopped" if stopped else "null (no vehicle stopped)"
            raise UserError(
                f"{path}: [{n}].vehicle = {_json_text(vehicle)}, but kind {kind} applied at "
                f"applied_s = {_json_text(when)} records {want}; {RERUN}"
            )
        if when is None:
            continue
        first = np.ceil(start / step - 1e-9) * step
        # a stop with no vehicle on the edge is retried every 10 s: 0, 10, 20 ... s late
        if isinstance(when, bool) or not isinstance(when, number):
            raise UserError(f"{path}: [{n}].applied_s = {_json_text(when)} is no time; {RERUN}")
        retries = (when - first) / 10.0 if stopped else when - first
        on_time = abs(retries - round(retries)) < 1e-6 and round(retries) >= 0
        if not (on_time and (stopped or round(retries) == 0) and when < end):
            retry = " (or every 10 s after, while no vehicle is on the edge)" * stopped
            raise UserError(
                f"{path}: [{n}].applied_s = {_show(when)}, but an incident from begin_s = "
                f"{_show(start)} to end_s = {_show(end)} is applied at {_show(first)}{retry}; "
                f"{RERUN}"
            )
        lifted = inc.get("lifted_s")
        last = np.ceil(end / step - 1e-9) * step
        if lifted is None and ran_to is not None and last < ran_to:
            raise UserError(
                f"{path}: [{n}].lifted_s = null, but an incident to end_s = {_show(end)} is "
                f"lifted at {_show(last)}, before the run's last step ({clock_label(ran_to)}); "
                f"{RERUN}"
            )
        if lifted is not None and (
            isinstance(lifted, bool) or not isinstance(lifted, number) or lifted != last
        ):
            raise UserError(
                f"{path}: [{n}].lifted_s = {_json_text(lifted)}, but an incident to end_s = "
                f"{_show(end)} is lifted at {_show(last)} (or null: the run ended first); "
                f"{RERUN}"
            )
        applied.append((n, inc))
    traffic = primary.run.get("traffic")
    traffic = traffic if isinstance(traffic, dict) else {}
    net_file, identity = traffic.get("net_file"), traffic.get("identity")
    sha = identity.get("net_sha256") if isinstance(identity, dict) else None
    if not applied or not isinstance(net_file, str) or not isinstance(sha, str):
        return
    from twin.files import file_sha256

    try:
        if not Path(net_file).is_file() or file_sha256(net_file) != sha:
            return  # the network is gone or changed: its edges are not checked
    except OSError:
        return
    from twin.sumo.cells import CellGeometry
    from twin.sumo.incidents import edge_cells, edge_lanes, middle_cell

    edges = edge_lanes(net_file, {str(inc.get("edge")) for _, inc in applied})
    network = read_json(primary.run_dir / "network.json")
    grid = network.get("grid") if isinstance(network, dict) else None
    geometry = None
    if isinstance(grid, dict) and all(isinstance(grid.get(k), number)
                                      for k in ("x0", "y_top", "cell_m", "nx", "ny")):  # fmt: skip
        nx, ny = int(grid["nx"]), int(grid["ny"])
        geometry = CellGeometry(float(grid["x0"]), float(grid["y_top"]), float(grid["cell_m"]),
                                nx, ny, np.zeros((nx, ny)), np.zeros((nx, ny)), (0, 0, 0, 0))  # fmt: skip
    for n, inc in applied:
        edge, lane, cell = inc.get("edge"), inc.get("lane"), inc.get("cell")
        if edge not in edges:
            raise UserError(
                f"{path}: [{n}].edge = {_json_text(edge)} is not an edge of {net_file} (the "
                f"network run.json records); {RERUN}"
            )
        lanes, shape = edges[edge]
        if lane is not None and lane >= lanes:
            raise UserError(
                f"{path}: [{n}].lane = {lane}, but edge {edge!r} of {net_file} has {lanes} "
                f"lanes; {RERUN}"
            )
        configured = traffic.get("incidents")
        by_edge = (
            isinstance(configured, list)
            and n < len(configured)
            and isinstance(configured[n], dict)
            and configured[n].get("edge") is not None
        )
        if geometry is not None and by_edge and cell != list(middle_cell(shape, geometry)):
            raise UserError(
                f"{path}: [{n}].cell = {_json_text(cell)}, but an incident given by its edge "
                f"{edge!r} is recorded at the cell of the edge's middle, "
                f"{list(middle_cell(shape, geometry))} (network.json's grid); {RERUN}"
            )
        if geometry is not None and isinstance(cell, list) and cell != [-1, -1]:
            through = edge_cells(shape, geometry)
            if tuple(cell) not in through:
                raise UserError(
                    f"{path}: [{n}].cell = {cell}, but edge {edge!r} of {net_file} passes "
                    f"through cells {sorted(through)[:6]} (network.json's grid); {RERUN}"
                )


def replayed_split(primary: Primary, frame: pd.DataFrame) -> pd.DataFrame:
    """The first seed's reward split ``R_hat_T_importance``, ``R_hat_T_idleness`` (the means
    of ``R^k``'s parts) and the paper's accounting ``R_hat_T_paper`` replayed like
    :func:`replayed_series`."""
    rows = [
        {
            "seed": primary.first_seed,
            "swarm": swarm,
            "R_hat_T_importance": r["importance"].mean(),
            "R_hat_T_importance" + SLACK: MAP_ROUNDING * r["importance"].mean(),
            "R_hat_T_idleness": r["idleness"].mean(),
            "R_hat_T_paper": r["paper"].mean(),
            "R_hat_T_paper" + SLACK: MAP_ROUNDING * r["paper_weight"].mean(),
        }
        for swarm, r in _replays(primary).items()
        if len(r["reward"])
    ]
    return pd.DataFrame(rows) if rows else pd.DataFrame(columns=["seed", "swarm"])


#: What run.json's ``monitoring.truth`` says when the run found its events on the maps that
#: ``importance.npz`` keeps (:func:`twin.runs.write_run`).
OBSERVED_TRUTH = "the observed importance"


def map_events(primary: Primary, frame: pd.DataFrame) -> pd.DataFrame:
    """The first seed's congestion events (cell, onset, duration, peak) found on
    ``importance.npz``'s maps by :func:`twin.monitoring.congestion_events` with run.json's
    monitoring settings, when the run found them there (run.json ``monitoring.truth``);
    empty otherwise."""
    monitoring = primary.run.get("monitoring")
    maps = primary.importance
    if not isinstance(monitoring, dict) or monitoring.get("truth") != OBSERVED_TRUTH:
        return pd.DataFrame()
    if maps is None or primary.first_seed is None:
        return pd.DataFrame()
    from twin.monitoring import DEFAULT_THRESHOLD

    threshold = float(monitoring.get("threshold", DEFAULT_THRESHOLD))
    min_duration = int(monitoring.get("min_duration", 1))
    # the run found them on the maps as kept (float32), threshold and all
    events = congestion_events(
        maps.astype(np.float32), Grid(primary.obstacles), threshold, min_duration
    )
    events = events.assign(seed=primary.first_seed, event=np.arange(len(events)))
    events = events[["seed", "event", *EVENT_COLUMNS]]
    events.attrs["seeds"] = [primary.first_seed]  # found on its maps: none beyond these
    return events


def series_scores(primary: Primary, frame: pd.DataFrame) -> pd.DataFrame:
    """Per seed and swarm: the Table 2 columns of ``series.parquet``'s rewards, coverage and
    visited shares (the swarms of a seed side by side, as they ran)."""
    rows = []
    series = primary.series.assign(swarm=primary.series["swarm"].astype(str))
    for seed, part in series.groupby("seed", sort=True):
        wide = part.pivot(index="swarm", columns="step")
        swarms = list(wide.index)
        columns = series_columns(
            wide["reward"].to_numpy(np.float64),
            wide["coverage"].to_numpy(np.float64),
            wide["visited_share"].to_numpy(np.float64),
        )
        rows.append(pd.DataFrame({"seed": int(seed), "swarm": swarms, **columns}))
    return pd.concat(rows, ignore_index=True)


def ceiling_scores(primary: Primary, frame: pd.DataFrame) -> pd.DataFrame:
    """Per seed and swarm: ``C_hat_T_ceiling`` of the run's grid, drones, ``eta``/``delta`` and
    the steps the seed ran (empty when run.json records no parameters)."""
    params = primary.params()
    if params is None:
        return pd.DataFrame(columns=["seed", "swarm", "C_hat_T_ceiling"])
    grid = Grid(primary.obstacles)
    drones = primary.trajectories.groupby("seed")["drone"].max() + 1
    steps = primary.series.groupby(["seed", "swarm"]).size().groupby(level="seed").max()
    rows, done = [], {}
    for seed in sorted(int(s) for s in steps.index):
        key = (int(drones[seed]), int(steps[seed]))
        if key not in done:
            done[key] = float(ceiling_coverage(grid, *key[:1], params.eta, params.delta,
                                               key[1]).mean())  # fmt: skip
        rows += [(seed, s, done[key]) for s in primary.swarms]
    return pd.DataFrame(rows, columns=["seed", "swarm", "C_hat_T_ceiling"])


def seed_events(primary: Primary, seed: int) -> pd.DataFrame:
    """The congestion events of ``seed`` (:data:`twin.monitoring.EVENT_COLUMNS`), once each."""
    ev = primary.events
    rows = ev[ev["seed"] == seed].drop_duplicates("event").sort_values("event")
    return rows[["event", *EVENT_COLUMNS]].reset_index(drop=True)


def run_monitoring(primary: Primary, seed: int) -> RunMonitoring:
    """The monitoring of ``seed`` as :func:`twin.monitoring.monitor_run` made it: its events,
    each swarm's sightings of them replayed from its trajectories, its belief error from
    ``series.parquet`` (computed once per seed)."""
    key = (seed, id(primary.events))
    if key not in primary.monitored:
        primary.monitored[key] = _run_monitoring(primary, seed)
    return primary.monitored[key]


def _run_monitoring(primary: Primary, seed: int) -> RunMonitoring:
    grid = Grid(primary.obstacles)
    events = seed_events(primary, seed)
    plan = fault_plan(primary)
    s = primary.series
    n = len(primary.swarms)
    belief = []
    first = np.zeros((n, len(events)), np.int64)
    seen = np.zeros_like(first)
    for k, swarm in enumerate(primary.swarms):
        pos = primary.positions(seed, swarm)
        recorded = None if plan is None else plan.recorded(seed, len(pos), pos.shape[1])
        keys = sightings(grid, pos, recorded)
        first[k], seen[k] = event_sightings(events, keys, len(pos), grid.ny)
        rows = s[(s["seed"] == seed) & (s["swarm"].astype(str) == swarm)].sort_values("step")
        if "belief_error" in s.columns:
            error = rows["belief_error"].to_numpy(np.float64)
        else:
            error = np.full(len(rows), np.nan)
        belief.append(np.concatenate([[np.nan], error]))  # step 0 is not averaged
    return RunMonitoring(list(primary.swarms), seed, events, np.array(belief), first, seen)


def monitoring_scores(primary: Primary, frame: pd.DataFrame) -> pd.DataFrame:
    """Per seed and swarm: the monitoring columns of the events and the swarms' sightings."""
    from twin.runs import step_seconds_of

    if primary.events is None or "belief_error" not in primary.series.columns:
        return pd.DataFrame(columns=["seed", "swarm"])
    step_s = step_seconds_of(primary.run)
    tables = [
        run_monitoring(primary, int(seed)).table(step_s).assign(seed=int(seed))
        for seed in sorted(primary.series["seed"].unique())
    ]
    return pd.concat(tables, ignore_index=True)


def event_rows(primary: Primary, frame: pd.DataFrame) -> pd.DataFrame:
    """``events.parquet`` as :meth:`twin.monitoring.RunMonitoring.events_frame` writes it: every
    event of a seed once per swarm, seen, first_seen and latency replayed from the trajectories."""
    frames = [
        run_monitoring(primary, int(seed)).events_frame()
        for seed in sorted(primary.series["seed"].unique())
    ]
    return pd.concat(frames, ignore_index=True)


def comparison_rows(primary: Primary, frame: pd.DataFrame) -> pd.DataFrame:
    """``comparison.csv`` as :func:`twin.metrics.learned_against_best_classical` makes it of
    ``per_seed.csv``."""
    rows = learned_against_best_classical(primary.per_seed)
    return (
        _earlier_intervals(primary, frame, rows) if len(rows) else pd.DataFrame(columns=["swarm"])
    )


def reward_split(primary: Primary, frame: pd.DataFrame) -> pd.DataFrame:
    """``R_hat_T`` as the sum of its parts ``R_hat_T_importance + R_hat_T_idleness``, on every
    row that gives them (the swarms' and the oracle's, of any folder format; the bound has
    none)."""
    if not {"R_hat_T_importance", "R_hat_T_idleness"} <= set(frame.columns):
        return frame.iloc[:0][[c for c in frame.columns if c in ("seed", "swarm")]]
    parts = frame[["R_hat_T_importance", "R_hat_T_idleness"]].apply(pd.to_numeric, errors="coerce")
    given = parts.notna().all(axis=1)
    keys = [c for c in ("seed", "swarm") if c in frame.columns]
    return frame.loc[given, keys].assign(R_hat_T=parts[given].sum(axis=1))


def seed_aggregate(primary: Primary, frame: pd.DataFrame) -> pd.DataFrame:
    """``summary.csv`` as :func:`twin.metrics.aggregate` makes it of ``per_seed.csv`` (a folder
    of format 3 or earlier wrote 0 for the interval of one seed, where it is now empty)."""
    return _earlier_intervals(primary, frame, aggregate(primary.per_seed))


def _earlier_intervals(primary: Primary, frame: pd.DataFrame, expected: pd.DataFrame):
    """``expected`` with the 0 a folder of format 3 or earlier wrote where one seed gives no
    interval (``_ci95`` columns, now empty). Where ``per_seed.csv`` shows one seed's figure,
    such a folder holds 0, and an empty cell is a later folder relabelled; elsewhere (a
    paired difference) the 0 it holds is taken."""
    if folder_format(primary) >= 4 or "swarm" not in frame.columns:
        return expected
    written = frame.drop_duplicates("swarm").set_index("swarm")
    per_seed = primary.per_seed
    for column in [c for c in expected.columns if c.endswith("_ci95") and c in frame]:
        base = column.removesuffix("_ci95")
        was = pd.to_numeric(written[column], errors="coerce").reindex(expected["swarm"])
        zero = (was == 0).to_numpy().copy()  # a 0 it wrote where no interval is
        if per_seed is not None and base in per_seed.columns and "swarm" in per_seed.columns:
            values = pd.to_numeric(per_seed[base], errors="coerce")
            seeds = values.notna().groupby(per_seed["swarm"]).sum()
            zero |= expected["swarm"].map(seeds).eq(1).to_numpy()  # one seed's: 0, always
        expected.loc[expected[column].isna().to_numpy() & zero, column] = 0.0
    return expected


def summary_columns(primary: Primary, frame: pd.DataFrame) -> pd.DataFrame:
    """``monitoring.csv``: the monitoring columns of ``summary.csv``'s swarms, as they are
    there."""
    return primary.summary[~is_ceiling_row(primary.summary)]


#: Each derived file's columns that other files of the run determine, in the order checked:
#: a file is checked against its sources before it serves as one.
DERIVED: tuple[Derivation, ...] = (
    Derivation(
        "series.parquet",
        "trajectories.parquet and importance.npz",
        ("seed", "swarm", "step"),
        replayed_series,
    ),
    Derivation(
        "series.parquet",
        "trajectories.parquet and importance.npz",
        ("seed", "swarm", "step"),
        replayed_belief,
    ),
    Derivation("events.parquet", "importance.npz", ("seed", "event"), map_events, complete=True),
    Derivation(
        "events.parquet",
        "trajectories.parquet (with the seed's events)",
        ("seed", "event", "swarm"),
        event_rows,
    ),
    Derivation("per_seed.csv", "series.parquet", ("seed", "swarm"), series_scores),
    Derivation("per_seed.csv", "importance.npz and run.json", ("seed", "swarm"), ceiling_scores),
    Derivation(
        "per_seed.csv",
        "events.parquet, trajectories.parquet and series.parquet",
        ("seed", "swarm"),
        monitoring_scores,
    ),
    Derivation(
        "per_seed.csv",
        "incidents.json and trajectories.parquet",
        ("seed", "swarm"),
        replayed_incidents,
    ),
    Derivation("per_seed.csv", "its reward split", ("seed", "swarm"), reward_split),
    Derivation(
        "per_seed.csv",
        "trajectories.parquet and importance.npz",
        ("seed", "swarm"),
        replayed_split,
    ),
    Derivation("summary.csv", "per_seed.csv", ("swarm",), seed_aggregate),
    Derivation("summary.csv", "its reward split", ("swarm",), reward_split),
    Derivation("monitoring.csv", "summary.csv", ("swarm",), summary_columns),
    Derivation("comparison.csv", "per_seed.csv", ("swarm",), comparison_rows, complete=True),
)
#: The derivations of ``per_seed.csv``'s columns from the primary files, one seed at a time.
PER_SEED_PARTS = (series_scores, ceiling_scores, monitoring_scores)


#: The largest ``tape.parquet`` (rows: cells x snapshots) whose replay checks
#: ``importance.npz``: reading and replaying a tape costs about 1.4 s per million rows (the
#: city-scale tape, 96 x 146 cells x 721 snapshots: 14 s; the paper's Shenzhen tape, 20 x 30
#: cells x 145: 0.7 s). Larger tapes are not replayed on read-back.
TAPE_REPLAY_ROWS = 1_000_000


#: The settings of a SUMO run's traffic that its tapes record (:meth:`twin.sumo.source.
#: SumoTraffic.metadata`) and run.json repeats: its scenario (name, files, incidents), its
#: timing (step 0 at ``begin``, the reads of a step) and its MFD observation.
TAPE_SETTINGS = ("name", "net_file", "route_files", "sumocfg", "begin", "warmup_s", "step_s",
                 "horizon", "reads_per_step", "read_offsets_s", "mesoscopic", "mfd_fit",
                 "mfd_prior", "detection_p", "incidents")  # fmt: skip


def check_tape_seeds(primary: Primary) -> None:
    """Each tape of a live SUMO run (``tape.parquet``: the first seed's, ``tapes/seed-<s>``:
    seed ``s``'s) was recorded with the SUMO seed that run.json records for its seed
    (``traffic_by_seed``, in the order of ``seeds``; ``traffic.seed`` with one seed) and with
    the :data:`TAPE_SETTINGS` that run.json records for it (the tape's own times are checked
    against these when it is read, :meth:`twin.traffic.tape.Tape.read`). Reads the tapes'
    metadata only."""
    from twin.traffic.tape import read_tape_meta

    run = primary.run
    seeds = run.get("seeds")
    by_seed = run.get("traffic_by_seed")
    if not isinstance(seeds, list):
        return
    if not isinstance(by_seed, list):
        by_seed = [run.get("traffic")] if len(seeds) == 1 else []
    sumo_seeds = {
        seed: node.get("seed")
        for seed, node in zip(seeds, by_seed, strict=False)
        if isinstance(node, dict) and isinstance(node.get("seed"), int)
    }
    records = dict(zip(seeds, by_seed, strict=False))
    first = primary.first_seed
    tapes = [(primary.run_dir / "tape.parquet", first, run.get("traffic"), "traffic")]
    tapes += [
        (primary.run_dir / "tapes" / f"seed-{s}.parquet", s, records.get(s),
         f"traffic_by_seed[{n}]" if len(seeds) > 1 else "traffic")
        for n, s in enumerate(seeds)
    ]  # fmt: skip
    for path, seed, record, where in tapes:
        if not path.is_file():
            continue
        settings = read_tape_meta(path).get("settings")
        settings = settings if isinstance(settings, dict) else {}
        want = sumo_seeds.get(seed)
        got = settings.get("seed")
        if want is not None and got != want:
            raise UserError(
                f"{path}: recorded with SUMO seed {got}, but run.json has seed {seed} run with "
                f"SUMO seed {want}; {RERUN}"
            )
        if not isinstance(record, dict) or record.get("kind") != "sumo":
            continue
        for name in TAPE_SETTINGS:
            if name not in record or name not in settings:
                continue
            at = _first_difference(record[name], settings[name], name)
            if at is not None:
                field, have, recorded = at
                raise UserError(
                    f"{primary.run_dir / 'run.json'}: {where}.{field} = {have}, but "
                    f"{path.relative_to(primary.run_dir)} (seed {seed}'s tape) records "
                    f"{recorded}; {RERUN}"
                )


def check_tape_network(primary: Primary) -> None:
    """A live run's ``network.json`` is the network record its first seed's ``tape.parquet``
    keeps (both are :meth:`twin.sumo.source.SumoTraffic.network_info`): the grid's place on
    the network, its lane-km, its obstacles. Reads the tape's metadata only."""
    from twin.readback import read_json
    from twin.traffic.tape import read_tape_meta

    path = primary.run_dir / "tape.parquet"
    network = read_json(primary.run_dir / "network.json")
    if not isinstance(network, dict) or not path.is_file():
        return
    settings = read_tape_meta(path).get("settings")
    recorded = settings.get("network") if isinstance(settings, dict) else None
    if not isinstance(recorded, dict):
        return
    at = _first_difference(network, recorded)
    if at is not None:
        name, have, want = at
        raise UserError(
            f"{primary.run_dir / 'network.json'}: {name} = {have}, but tape.parquet records "
            f"{want} (the network the run used); {RERUN}"
        )


def _first_difference(have: Any, want: Any, name: str = "") -> tuple[str, str, str] | None:
    """The first dotted key at which the JSON values differ (numbers within
    :data:`TOLERANCE`), with both values shown; None when they agree."""
    if isinstance(have, dict) and isinstance(want, dict):
        for key in [*want, *(k for k in have if k not in want)]:
            at = _first_difference(have.get(key), want.get(key), f"{name}.{key}" if name else key)
            if at is not None:
                return at
        return None
    if isinstance(have, list) and isinstance(want, list) and len(have) == len(want):
        for n, (h, w) in enumerate(zip(have, want, strict=True)):
            at = _first_difference(h, w, f"{name}[{n}]")
            if at is not None:
                return at
        return None
    numbers = (int, float)
    both = isinstance(have, numbers) and isinstance(want, numbers)
    if both and not isinstance(have, bool) and not isinstance(want, bool):
        same = _same(have, want)
    else:
        same = have == want
    return None if same else (name, _json_text(have), _json_text(want))


def _json_text(value: Any) -> str:
    import json

    return json.dumps(value)[:60]


def check_tape_maps(primary: Primary) -> None:
    """A live SUMO run's ``importance.npz`` holds the maps its first seed's ``tape.parquet``
    gives when replayed through the run's MFD observation (:class:`twin.traffic.tape.TapeTraffic`:
    the counts and speeds the live source observed, bit for bit), each tape is of its seed
    (:func:`check_tape_seeds`) and ``network.json`` the tape's network
    (:func:`check_tape_network`). The replay is skipped for a tape of more than
    :data:`TAPE_REPLAY_ROWS` rows."""
    import pyarrow.parquet as pq

    from twin.traffic.tape import Tape, TapeTraffic

    check_tape_seeds(primary)
    check_tape_network(primary)
    path = primary.run_dir / "tape.parquet"
    maps = primary.importance
    if maps is None or not path.is_file():
        return
    try:
        rows = pq.read_metadata(path).num_rows
    except Exception:  # a damaged tape: Tape.read says what is wrong with it
        rows = 0
    if rows > TAPE_REPLAY_ROWS:
        return
    source = TapeTraffic(Tape.read(path), source_name=str(path))
    replays = _replayed_maps(primary, source, "tape.parquet", f" of seed {primary.first_seed}")
    check_mfd_files(primary.run_dir, source.model_observed())
    check_detector_readings(primary, source.mfd_before)
    if primary.first_seed is not None and replays is not None:
        primary.tape_maps[primary.first_seed] = replays
        primary.tape_sightings[primary.first_seed] = source.sighting_model()


def _replayed_maps(primary: Primary, source, tape: str, whose: str = "") -> np.ndarray | None:
    """The maps ``source`` (a :class:`twin.traffic.tape.TapeTraffic`) gives through its MFD
    observation, once ``importance.npz`` is found to hold them (a one-line error naming the
    first differing cell, or the missing maps, of ``tape``, the maps ``whose``); None when the
    folder keeps no map."""
    npz = primary.run_dir / "importance.npz"
    kept = primary.importance.astype(np.float32)  # as kept: float32
    replays: list[np.ndarray] = []  # the MFD observes every snapshot of the tape
    given, off = _first_differing_map(source.importance_maps(), kept, collect=replays)
    if off is not None:
        k, i, j, replayed = off
        raise UserError(
            f"{npz}: importance at step {k}, cell ({i}, {j}){whose} is "
            f"{_show(kept[k, i, j], replayed)}, but {tape} replayed through its MFD gives "
            f"{_show(replayed, kept[k, i, j])}; {RERUN}"
        )
    if given < len(kept):
        raise UserError(
            f"{npz}: holds {len(kept)} maps{whose}, but {tape} replays {given}; {RERUN}"
        )
    return np.stack(replays) if replays else None


def check_replayed_tape_maps(primary: Primary) -> None:
    """A run on a tape (``twin evaluate --traffic TAPE``): while the tape run.json names
    (``traffic.tape_file``) is there unchanged, ``importance.npz`` holds the maps it gives
    through the run's MFD observation and detection probability, the maps of every seed;
    its sightings are known for the belief models' replay. A tape gone or changed, or of more
    than :data:`TAPE_REPLAY_ROWS` rows, is not replayed (the belief read-back says so)."""
    import pyarrow.parquet as pq

    from twin.files import file_sha256
    from twin.traffic.tape import Tape, TapeTraffic

    traffic = primary.run.get("traffic")
    if not isinstance(traffic, dict) or traffic.get("kind") != "tape" or primary.importance is None:
        return
    record = traffic.get("tape_file")
    if not isinstance(record, dict) or not isinstance(record.get("path"), str):
        return  # an earlier folder: the tape is not known
    path = Path(record["path"])
    try:
        if not path.is_file() or file_sha256(path) != record.get("sha256"):
            return
        if pq.read_metadata(path).num_rows > TAPE_REPLAY_ROWS:
            return
        tape = Tape.read(path)
    except (OSError, UserError, ValueError):
        return
    p = traffic.get("detection_p")
    source = TapeTraffic(tape, float(p) if isinstance(p, (int, float)) else None, str(path))
    replays = _replayed_maps(primary, source, f"{path} (the tape run.json names)")
    if replays is None:
        return
    sighting = source.sighting_model()
    for seed in primary.run.get("seeds") or []:  # every seed ran on the tape's maps
        if isinstance(seed, int):
            primary.tape_maps[seed], primary.tape_sightings[seed] = replays, sighting


def check_synthetic_maps(primary: Primary) -> None:
    """A synthetic run's ``importance.npz`` holds the maps that run.json's ``traffic`` (its
    disturbances, ``beta1``, ``beta2``, ``z_lo``, ``z_hi``: Sec. IV's ``z^k`` normalised by Def.
    2) generates on the kept grid, within float32 rounding; every seed shares them, so each
    ``traffic_by_seed`` record is that ``traffic``. Costs one generation of the maps."""
    from twin.traffic.synthetic import Disturbance, SyntheticTraffic

    traffic, maps = primary.run.get("traffic"), primary.importance
    if not isinstance(traffic, dict) or traffic.get("kind") != "synthetic" or maps is None:
        return
    path = primary.run_dir / "run.json"
    for n, record in enumerate(primary.run.get("traffic_by_seed") or []):
        at = _first_difference(record, traffic)
        if at is not None:
            name, have, want = at
            raise UserError(
                f"{path}: traffic_by_seed[{n}].{name} = {have}, but traffic.{name} = {want} "
                f"(synthetic traffic is the same for every seed); {RERUN}"
            )
    disturbances = traffic.get("disturbances")
    try:
        source = SyntheticTraffic(
            Grid(primary.obstacles),
            [Disturbance(**d) for d in disturbances],
            int(traffic["horizon"]),
            float(traffic["beta1"]),
            float(traffic["beta2"]),
            float(traffic["z_lo"]),
            float(traffic["z_hi"]),
        )
    except (TypeError, ValueError, KeyError) as exc:
        raise UserError(
            f"{path}: traffic = {_json_text(traffic)} is not a synthetic traffic record "
            f"({type(exc).__name__}: {str(exc)[:60]}); {RERUN}"
        ) from None
    kept = maps.astype(np.float32)
    given, off = _first_differing_map(source.importance_maps(), kept, MAP_ROUNDING)
    if off is not None:
        k, i, j, generated = off
        raise UserError(
            f"{path}: traffic (disturbances, beta1, beta2, z_lo, z_hi) generates importance "
            f"{_show(generated, kept[k, i, j])} at step {k}, cell ({i}, {j}), but "
            f"importance.npz holds {_show(kept[k, i, j], generated)}; {RERUN}"
        )
    if given < len(kept):
        raise UserError(
            f"{path}: traffic.horizon = {traffic['horizon']} generates {given} maps, but "
            f"importance.npz holds {len(kept)}; {RERUN}"
        )


def _first_differing_map(
    maps: Iterable[np.ndarray],
    kept: np.ndarray,
    rounding: float = 0.0,
    collect: list[np.ndarray] | None = None,
) -> tuple[int, tuple[int, int, int, float] | None]:
    """Walk ``maps`` step by step against ``kept`` (float32, as ``importance.npz`` keeps them;
    a difference over ``rounding`` relative, or any NaN, counts): how many maps were walked,
    and the first differing ``(k, i, j, value given)`` or None. With ``collect``, every map
    given (also those past the kept ones) is appended there as float64; without it the walk
    ends one map past the kept ones."""
    k = -1
    for k, given in enumerate(maps):
        if collect is not None:
            collect.append(np.array(given, dtype=np.float64))
        if k >= len(kept):
            if collect is None:
                break
            continue
        given = np.asarray(given, dtype=np.float32)
        off = ~(np.abs(given - kept[k]) <= rounding * np.maximum(1.0, np.abs(kept[k])))
        if off.any():
            i, j = (int(v) for v in np.argwhere(off)[0])
            return k + 1, (k, i, j, float(given[i, j]))
    return k + 1, None


def check_same_tape(have: Path, want: Path) -> None:
    """``have`` holds the same tape as ``want`` (rows and metadata): the first seed's copy in
    ``tapes/`` is ``tape.parquet``."""
    import pyarrow.parquet as pq

    from twin.traffic.tape import read_tape_meta

    try:
        a, b = pq.read_table(have), pq.read_table(want)
    except Exception as exc:  # a damaged tape: Tape.read says what is wrong with it
        from twin.traffic.tape import Tape

        Tape.read(have)
        Tape.read(want)
        raise UserError(f"{have}: unreadable ({type(exc).__name__}); {RERUN}") from None
    if a.equals(b):
        at = _first_difference(read_tape_meta(have), read_tape_meta(want))
        if at is None:
            return
        name, mine, theirs = at
        raise UserError(
            f"{have}: metadata {name} = {mine}, but {want.name} (the same seed's tape) has "
            f"{theirs}; {RERUN}"
        )
    if a.num_rows != b.num_rows or a.column_names != b.column_names:
        raise UserError(
            f"{have}: {a.num_rows} rows of {a.column_names}, but {want.name} (the same seed's "
            f"tape) has {b.num_rows} of {b.column_names}; {RERUN}"
        )
    for column in a.column_names:
        x, y = a[column].to_numpy(), b[column].to_numpy()
        off = ~((x == y) | (pd.isna(x) & pd.isna(y)))
        if off.any():
            n = int(np.flatnonzero(off)[0])
            raise UserError(
                f"{have}: {column} = {_show(x[n])} in row {n}, but {want.name} (the same "
                f"seed's tape) has {_show(y[n])}; {RERUN}"
            )


def check_seed_tapes(primary: Primary) -> None:
    """Each seed's tape in ``tapes/`` of a several-seed live run: the first seed's is
    ``tape.parquet`` (:func:`check_same_tape`); every later seed's, replayed through its MFD
    (:class:`twin.traffic.tape.TapeTraffic`), gives the maps on which that seed's rows of
    ``series.parquet`` (rewards, coverage, visited shares, belief error) and ``events.parquet``
    (its events) replay from ``trajectories.parquet``, as :data:`DERIVED` checks the first
    seed's over ``importance.npz``. A tape of more than :data:`TAPE_REPLAY_ROWS` rows is not
    replayed. Costs a tape replay and one score replay per swarm and later seed."""
    import dataclasses

    import pyarrow.parquet as pq

    from twin.traffic.tape import Tape, TapeTraffic

    folder = primary.run_dir / "tapes"
    seeds = primary.run.get("seeds")
    if not folder.is_dir() or not isinstance(seeds, list):
        return
    first = folder / f"seed-{primary.first_seed}.parquet"
    if first.is_file() and (primary.run_dir / "tape.parquet").is_file():
        check_same_tape(first, primary.run_dir / "tape.parquet")
    for seed in seeds:
        path = folder / f"seed-{seed}.parquet"
        if seed == primary.first_seed or not isinstance(seed, int) or not path.is_file():
            continue
        try:
            rows = pq.read_metadata(path).num_rows
        except Exception:  # a damaged tape: Tape.read says what is wrong with it
            rows = 0
        if rows > TAPE_REPLAY_ROWS:
            continue
        source = TapeTraffic(Tape.read(path), source_name=str(path))
        maps = [np.array(m, dtype=np.float64) for m in source.importance_maps()]
        scored = primary.series.loc[primary.series["seed"] == seed, "step"]
        if scored.empty:
            continue  # a seed without results (refused with run.json's seeds)
        steps = int(scored.max()) + 1
        if len(maps) < steps + 1:
            raise UserError(
                f"{path}: replays {len(maps)} maps, but series.parquet scores seed {seed} over "
                f"{steps} steps ({steps + 1} maps); {RERUN}"
            )
        of_seed = dataclasses.replace(
            primary, importance=np.stack(maps), first_seed=seed, incidents=None,
            replayed=None, monitored={},
        )  # fmt: skip
        name = f"trajectories.parquet and tapes/{path.name}"
        checks = [("series.parquet", primary.series, ("seed", "swarm", "step"), replayed_series),
                  ("series.parquet", primary.series, ("seed", "swarm", "step"), replayed_belief),
                  ("events.parquet", primary.events, ("seed", "event"), map_events)]  # fmt: skip
        for file, frame, key, recompute in checks:
            if frame is not None:
                complete = recompute is map_events
                expected = recompute(of_seed, frame)
                compare(primary.run_dir, file, frame, expected, key, name, complete)
        primary.later_splits.append(replayed_split(of_seed, pd.DataFrame()).assign(source=name))
        primary.tape_maps[seed] = of_seed.importance
        primary.tape_sightings[seed] = source.sighting_model()


def check_shared_traffic_seeds(primary: Primary) -> None:
    """A run whose seeds all run on one traffic (synthetic maps, or one tape replayed for every
    seed; run.json records one ``traffic``): each later seed's rows of ``series.parquet``
    (rewards, coverage, visited shares, belief error), ``events.parquet`` and its reward split
    in ``per_seed.csv`` (:func:`replayed_split`) replay from its trajectories over
    ``importance.npz``'s maps, as the first seed's do; so does the split of a live run's later
    seeds over their tapes (:func:`check_seed_tapes`). Costs one score replay per swarm and
    later seed."""
    for split in primary.later_splits:
        if primary.per_seed is not None and len(split):
            name = str(split["source"].iloc[0])
            compare(primary.run_dir, "per_seed.csv", primary.per_seed,
                    split.drop(columns="source"), ("seed", "swarm"), name)  # fmt: skip
    import dataclasses

    traffic, maps = primary.run.get("traffic"), primary.importance
    if maps is None or not isinstance(traffic, dict) or traffic.get("kind") not in SHARED:
        return
    records = primary.run.get("traffic_by_seed") or []
    if any(_first_difference(record, traffic) is not None for record in records):
        return  # not one traffic (a synthetic run's records are checked to be one)
    for seed in primary.run.get("seeds") or []:
        if seed == primary.first_seed or not isinstance(seed, int):
            continue
        scored = primary.series.loc[primary.series["seed"] == seed, "step"]
        if scored.empty or int(scored.max()) + 2 > len(maps):
            continue  # a seed without results, or longer than the maps: other checks say so
        of_seed = dataclasses.replace(
            primary, first_seed=seed, incidents=None, replayed=None, monitored={}
        )
        name = "trajectories.parquet and importance.npz"
        checks = [("series.parquet", primary.series, ("seed", "swarm", "step"), replayed_series),
                  ("series.parquet", primary.series, ("seed", "swarm", "step"), replayed_belief),
                  ("events.parquet", primary.events, ("seed", "event"), map_events)]  # fmt: skip
        for file, frame, key, recompute in checks:
            if frame is not None:
                expected = recompute(of_seed, frame)
                compare(primary.run_dir, file, frame, expected, key, name, recompute is map_events)
        if primary.per_seed is not None:
            expected = replayed_split(of_seed, primary.per_seed)
            compare(primary.run_dir, "per_seed.csv", primary.per_seed, expected, ("seed", "swarm"),
                    name)  # fmt: skip


#: Traffic kinds whose every seed runs on the same maps.
SHARED = ("synthetic", "tape")


def check_mfd_files(run_dir: Path, model) -> None:
    """``mfd_samples.parquet`` and ``mfd.json`` as the MFD observation ``model``
    (:class:`twin.mfd.MFDImportance`, having observed the first seed's tape) writes them
    (:meth:`~twin.mfd.MFDImportance.samples`, :meth:`~twin.mfd.MFDImportance.report`)."""
    import json

    from twin.readback import read_json

    replay = "tape.parquet replayed through its MFD gives"
    path = run_dir / "mfd_samples.parquet"
    if path.is_file():
        mine = pd.read_parquet(path)
        theirs = pd.DataFrame(model.samples())
        if len(mine) != len(theirs):
            raise UserError(f"{path}: {len(mine)} samples, but {replay} {len(theirs)}; {RERUN}")
        for column in theirs.columns:
            if column not in mine.columns:
                continue
            off = _differ(mine[column].reset_index(drop=True), theirs[column], None)
            if off.any():
                n = int(np.flatnonzero(off)[0])
                raise UserError(
                    f"{path}: {column} = {_show(mine[column].iloc[n])} in row {n}, but {replay} "
                    f"{_show(theirs[column].iloc[n])}; {RERUN}"
                )
    fit = read_json(run_dir / "mfd.json")
    if isinstance(fit, dict):
        report = json.loads(json.dumps(nan_as_null(model.report()), default=float))
        for name, want in report.items():
            if name in fit and not isinstance(want, (dict, list)) and not _same(fit[name], want):
                raise UserError(
                    f"{run_dir / 'mfd.json'}: {name} = {_show(fit[name], want)}, but {replay} "
                    f"{_show(want, fit[name])}; {RERUN}"
                )
            if name in fit and isinstance(want, (dict, list)):
                at = _first_difference(fit[name], want, name)
                if at is not None:
                    field, have, theirs = at
                    raise UserError(
                        f"{run_dir / 'mfd.json'}: {field} = {have}, but {replay} {theirs}; {RERUN}"
                    )
        # the online fit the run rejected for its prior: there exactly when the replay has one
        if ("rejected_fit" in fit) != ("rejected_fit" in report):
            have = _json_text(fit.get("rejected_fit"))
            want = _json_text(report.get("rejected_fit"))
            raise UserError(
                f"{run_dir / 'mfd.json'}: rejected_fit = {have}, but {replay} {want}; {RERUN}"
            )


#: What a fixed detector's reading can be: its columns' ranges in ``detectors.parquet``.
READING_RANGES = {
    "vehicles": (0.0, np.inf, "a count of vehicles, at least 0"),
    # SUMO's own interval occupancy dips below 0 at times: kept as 0 (folder format 3; an
    # earlier format's readings hold SUMO's dips, of which only the top is checked)
    "occupancy_pct": (0.0, 100.0, "a share of time in %, 0 .. 100"),
    "speed": (0.0, np.inf, "a speed in m/s, at least 0 (NaN: no vehicle)"),
}
#: A detector's fields, the same in each of its readings.
DETECTOR_FIELDS = ("kind", "virtual", "lane", "i", "j")


def check_detector_readings(primary: Primary, mfd_before: dict[int, Any]) -> None:
    """``detectors.parquet``'s first-seed readings: in their ranges, each detector in one
    place, and each importance the MFD in effect at its step (the tape's replay,
    ``mfd_before``) of its occupancy, as the run computed it; a history learns the stations'
    biases from them."""
    from twin.mfd import density_from_occupancy

    path = primary.run_dir / "detectors.parquet"
    if not path.is_file():
        return
    from twin.readback import read_table

    rows = read_table(path, {"seed": "int", "step": "int", "i": "int", "j": "int",
                             "importance": "finite", "occupancy_pct": "number",
                             "vehicles": "number", "speed": "number"})  # fmt: skip
    for column, (low, high, what) in READING_RANGES.items():
        if column == "occupancy_pct" and folder_format(primary) < 3:
            low = -np.inf  # SUMO's dips below 0, as an earlier twin kept them
        value = rows[column].to_numpy(dtype=float)
        bad = (value < low) | (value > high) | (np.isnan(value) & (column != "speed"))
        if bad.any():
            n = int(np.flatnonzero(bad)[0])
            raise UserError(
                f"{path}: row {n} has {column} = {_show(value[n])}, not {what}; {RERUN}"
            )
    nx, ny = primary.obstacles.shape
    i, j = rows["i"].to_numpy(), rows["j"].to_numpy()
    off = (i < 0) | (i >= nx) | (j < 0) | (j >= ny)
    off |= ~off & primary.obstacles[i.clip(0, nx - 1), j.clip(0, ny - 1)]
    if off.any():
        n = int(np.flatnonzero(off)[0])
        raise UserError(
            f"{path}: seed {rows['seed'].iloc[n]}, step {rows['step'].iloc[n]}: a reading at "
            f"cell ({i[n]}, {j[n]}) is off the {nx} x {ny} grid's free cells; {RERUN}"
        )
    for column in (c for c in DETECTOR_FIELDS if c in rows.columns and "detector" in rows.columns):
        spread = rows.groupby("detector", observed=True)[column].nunique(dropna=False)
        if (spread > 1).any():
            name = spread.index[int(np.flatnonzero(spread.to_numpy() > 1)[0])]
            raise UserError(
                f"{path}: detector {str(name)!r} has more than one {column} among its "
                f"readings; {RERUN}"
            )
    mine = rows[rows["seed"] == primary.first_seed]
    for k, at_k in mine.groupby("step", sort=True):  # one MFD call per step, not per reading
        mfd = mfd_before.get(int(k))
        if mfd is None:
            raise UserError(f"{path}: a reading at step {k}, which tape.parquet lacks; {RERUN}")
        occupancy = at_k["occupancy_pct"].to_numpy(dtype=float)
        got = at_k["importance"].to_numpy(dtype=float)
        wanted = np.asarray(mfd.importance(density_from_occupancy(occupancy)), dtype=float)
        off = np.flatnonzero(~(np.abs(wanted - got) <= 1e-9 + 1e-6 * np.abs(wanted)))
        if off.size:
            occ, imp, want = occupancy[off[0]], got[off[0]], wanted[off[0]]
            raise UserError(
                f"{path}: seed {primary.first_seed}, step {k}: importance = {_show(imp, want)} "
                f"for occupancy {occ:g} %, but the MFD in effect at that step (tape.parquet "
                f"replayed) gives {_show(want, imp)}; {RERUN}"
            )


def check_starts(primary: Primary) -> None:
    """Every swarm of every seed starts where run.json's ``starts`` put its drones: the cells
    it lists, or (``"random"``) the seed's own draw on the map
    (:func:`twin.config.start_positions` with the drone seed): a folder relabelled to another
    seed is refused. Skipped for a run.json without ``starts``."""
    from twin.swarm import random_starts

    starts, n = primary.run.get("starts"), primary.run.get("n_drones")
    if starts is None or not isinstance(n, int) or isinstance(n, bool):
        return
    cells = isinstance(starts, list) and all(
        isinstance(c, list) and len(c) == 2 and all(type(v) is int for v in c) for c in starts
    )
    if starts != "random" and not cells:
        raise UserError(
            f"{primary.run_dir / 'run.json'}: starts = {_json_text(starts)} is neither "
            f'"random" nor a list of [i, j] cells; {RERUN}'
        )
    path = primary.run_dir / "trajectories.parquet"
    grid = Grid(primary.obstacles)
    t = primary.trajectories
    first = t[t["step"] == 0]
    for seed, rows in first.groupby("seed", sort=True):
        if starts == "random":
            if n > grid.n_free:
                return  # refused with run.json's drones
            want = random_starts(grid, n, np.random.default_rng(int(seed)))
            said = f"seed {int(seed)}'s random starts on this map are"
        else:
            want = np.asarray(starts)
            said = "run.json's starts are"
        for swarm, cells in rows.groupby("swarm", observed=True, sort=False):
            got = cells.sort_values("drone")[["i", "j"]].to_numpy()
            if got.shape != np.shape(want) or not np.array_equal(got, want):
                raise UserError(
                    f"{path}: swarm {str(swarm)!r}, seed {int(seed)} starts at "
                    f"{got.tolist()[:4]}, but {said} {np.asarray(want).tolist()[:4]}; {RERUN}"
                )


def folder_format(primary: Primary) -> int:
    """run.json's ``folder_format`` (:func:`folder_format_of`)."""
    return folder_format_of(primary.run)


def folder_format_of(run: dict[str, Any]) -> int:
    """run.json's ``folder_format`` (:data:`twin.runs.FOLDER_FORMAT`; 1 when absent: a folder
    an earlier twin wrote, without the bound's prices and the incident schedule)."""
    value = run.get("folder_format", 1)
    return value if isinstance(value, int) and not isinstance(value, bool) else 1


#: How far a replayed bound may differ from its row (relative): the folder keeps the maps in
#: float32, the run bounded them in float64.
BOUND_TOLERANCE = 1e-5


def _maps_by_seed(primary: Primary) -> dict[int, np.ndarray]:
    """The maps of each seed the folder holds: the first seed's (its tape replayed, else
    ``importance.npz``), every seed's of a run on one traffic, the later seeds' tapes
    replayed (:func:`check_seed_tapes`)."""
    maps = dict(primary.tape_maps)
    if primary.importance is not None and primary.first_seed is not None:
        maps.setdefault(primary.first_seed, primary.importance)
        traffic = primary.run.get("traffic")
        records = primary.run.get("traffic_by_seed") or []
        shared = isinstance(traffic, dict) and traffic.get("kind") in SHARED
        if shared and not any(_first_difference(r, traffic) is not None for r in records):
            for seed in primary.run.get("seeds") or []:
                if isinstance(seed, int):
                    maps.setdefault(seed, primary.importance)
    return maps


def check_bound(primary: Primary, per_seed: pd.DataFrame | None) -> None:
    """Each ``bound (ceiling)`` row of ``per_seed.csv`` is ``L(lambda) / T`` of the Lagrangian
    relaxation (:func:`twin.ceilings.bound_at`) at the prices ``bound.npz`` keeps for its seed,
    on that seed's maps, wherever the folder holds them (one DP pass per seed); and no
    ``oracle (ceiling)`` row lies above its seed's bound."""
    from twin.ceilings import MAX_DP_BYTES, bound_at, bound_dp_bytes
    from twin.metrics import BOUND, ORACLE
    from twin.runs import score_params_of

    if per_seed is None or not {"swarm", "seed", "R_hat_T"} <= set(per_seed.columns):
        return
    table = primary.run_dir / "per_seed.csv"
    names = per_seed["swarm"].astype(str)
    bounds = per_seed[names == BOUND]
    if bounds.empty:
        return
    path = primary.run_dir / "bound.npz"
    if not path.is_file() and folder_format(primary) < 2:
        return  # an earlier twin kept no prices (said once by load_run)
    if not path.is_file():
        raise UserError(
            f"{table}: holds {BOUND} rows, but the folder has no bound.npz (their prices); {RERUN}"
        )
    try:
        with np.load(path, allow_pickle=False) as data:
            prices = {key: np.asarray(data[key], dtype=float) for key in data.files}
    except Exception as exc:  # numpy raises several types on a damaged file
        raise UserError(f"{path}: not a readable .npz ({type(exc).__name__}); {RERUN}") from None
    params, n = score_params_of(primary.run), primary.run.get("n_drones")
    if params is None or not isinstance(n, int) or isinstance(n, bool):
        return  # run.json's own checks say what is wrong
    grid, maps = Grid(primary.obstacles), _maps_by_seed(primary)
    oracles = per_seed[names == ORACLE].set_index("seed")["R_hat_T"]
    for seed, recorded in zip(bounds["seed"], bounds["R_hat_T"], strict=True):
        seed, recorded = int(seed), float(recorded)
        if seed in oracles.index and float(oracles.loc[seed]) > recorded * (1 + BOUND_TOLERANCE):
            raise UserError(
                f"{table}: the {ORACLE} row of seed {seed} has R_hat_T = "
                f"{_show(oracles.loc[seed], recorded)}, above its {BOUND} row's "
                f"{_show(recorded, oracles.loc[seed])}; {RERUN}"
            )
        if seed not in maps:
            continue
        dp = bound_dp_bytes(params, len(maps[seed]) - 1, grid.n_free)
        if dp > MAX_DP_BYTES:
            raise UserError(
                f"{table}: holds a {BOUND} row for seed {seed}, but its DP would hold "
                f"{dp / 1e9:.1f} GB, past the {MAX_DP_BYTES / 1e9:g} GB for which a run computes "
                f"it (it leaves the row out); {RERUN}"
            )
        key = f"seed_{seed}"
        if key not in prices:
            raise UserError(f"{path}: no prices {key} for seed {seed}'s {BOUND} row; {RERUN}")
        try:
            value = bound_at(maps[seed], grid, n, params, prices[key])
        except ValueError as exc:
            raise UserError(f"{path}: {key} holds {exc}; {RERUN}") from None
        if not abs(value - recorded) <= BOUND_TOLERANCE * max(1.0, abs(value)):
            raise UserError(
                f"{table}: R_hat_T = {_show(recorded, value)} for seed {seed}, swarm {BOUND!r}, "
                f"but bound.npz's prices on the seed's maps give {_show(value, recorded)}; "
                f"{RERUN}"
            )


def check_oracle(primary: Primary, per_seed: pd.DataFrame | None) -> None:
    """The ceiling rows of ``per_seed.csv`` leave the monitoring columns empty; each
    ``oracle (ceiling)`` row of ``per_seed.csv`` is the scores of the oracle's cells
    that ``oracle.parquet`` keeps for its seed (from the swarms' starts, one action a step,
    under the run's faults), stepped again over the seed's maps wherever the folder holds them
    (a folder of format 2 or earlier kept no cells: not replayed)."""
    from twin.metrics import ORACLE

    if per_seed is None or not {"swarm", "seed"} <= set(per_seed.columns):
        return
    ceilings = per_seed[is_ceiling_row(per_seed)]
    for column in (c for c in MONITORING_COLUMNS if c in ceilings.columns):
        filled = ceilings[column].notna()
        if filled.any():
            r = ceilings[filled].iloc[0]
            raise UserError(
                f"{primary.run_dir / 'per_seed.csv'}: {column} = {_show(r[column])} for the "
                f"{r['swarm']} row of seed {r['seed']}, which monitors nothing (empty as a run "
                f"writes it); {RERUN}"
            )
    rows = per_seed[per_seed["swarm"].astype(str) == ORACLE]
    params, path = primary.params(), primary.run_dir / "oracle.parquet"
    if rows.empty or params is None or (not path.exists() and folder_format(primary) < 3):
        return
    if not path.is_file():
        raise UserError(
            f"{primary.run_dir / 'per_seed.csv'}: holds {ORACLE} rows, but the folder has no "
            f"oracle.parquet (their cells); {RERUN}"
        )
    from twin.readback import check_trajectories, read_table

    cells = read_table(path)
    check_trajectories(path, cells, primary.obstacles.shape, primary.obstacles)
    grid, plan, maps = Grid(primary.obstacles), fault_plan(primary), _maps_by_seed(primary)
    expected = []
    for seed in sorted(int(s) for s in rows["seed"]):
        if seed not in maps:
            continue
        pos = positions_of(path, cells, seed, ORACLE)
        starts = primary.positions(seed, primary.swarms[0])
        if pos.shape != starts.shape or (pos[0] != starts[0]).any():
            raise UserError(
                f"{path}: the oracle of seed {seed} does not start where the swarms start, or "
                f"has {pos.shape[0] - 1} steps and {pos.shape[1]} drones where "
                f"trajectories.parquet has {starts.shape[0] - 1} and {starts.shape[1]}; {RERUN}"
            )
        recorded = None if plan is None else plan.recorded(seed, len(pos), pos.shape[1])
        try:
            r = replay_scores(grid, params, pos, maps[seed][: len(pos)], recorded)
        except InfeasibleActionError as exc:
            raise UserError(f"{path}: seed {seed}: {exc}; {RERUN}") from None
        slack = MAP_ROUNDING * np.abs(r["importance"]).mean()
        expected.append(
            {
                "seed": seed,
                "swarm": ORACLE,
                "R_hat_T": r["reward"].mean(),
                "R_hat_T" + SLACK: slack,
                "R_hat_T_importance": r["importance"].mean(),
                "R_hat_T_importance" + SLACK: slack,
                "R_hat_T_idleness": r["idleness"].mean(),
                "R_hat_T_paper": r["paper"].mean(),
                "R_hat_T_paper" + SLACK: MAP_ROUNDING * np.abs(r["paper_weight"]).mean(),
                "C_hat_T": r["coverage"].mean(),
                "pct_map_covered": 100.0 * r["visited_share"][-1],
            }
        )
    if expected:
        source = "oracle.parquet replayed over the seed's maps"
        compare(primary.run_dir, "per_seed.csv", per_seed, pd.DataFrame(expected),
                ("seed", "swarm"), source)  # fmt: skip


def check_derived(primary: Primary, tables: dict[str, pd.DataFrame | None]) -> None:
    """Every derived file of ``tables`` (name -> its table, None when absent) agrees with what
    its sources give (:data:`DERIVED`), after ``importance.npz`` with its tape
    (:func:`check_tape_maps`); then the later seeds of a run on one traffic
    (:func:`check_shared_traffic_seeds`). Without ``per_seed.csv``, ``summary.csv`` is checked against the
    per-seed figures the primary files give."""
    check_starts(primary)
    check_tape_maps(primary)
    check_replayed_tape_maps(primary)
    check_seed_tapes(primary)
    check_synthetic_maps(primary)
    check_incident_records(primary)
    check_incident_schedule(primary)
    per_seed = tables.get("per_seed.csv")
    if per_seed is None:  # summary.csv is then checked against the primary files themselves
        parts = [part(primary, pd.DataFrame()) for part in PER_SEED_PARTS]
        per_seed = parts[0]
        for part in parts[1:]:
            if len(part):
                per_seed = per_seed.merge(part, on=["seed", "swarm"], how="left")
        per_seed = per_seed[per_seed["swarm"].isin(primary.swarms)]
    primary.per_seed, primary.summary = per_seed, tables.get("summary.csv")
    given: dict[str, set[str]] = {}  # columns each derived table's derivations give
    check_bound(primary, tables.get("per_seed.csv"))
    check_oracle(primary, tables.get("per_seed.csv"))
    for d in DERIVED:
        frame = tables.get(d.file)
        if frame is None:
            continue
        source = d.source
        if (
            d.file == "summary.csv"
            and d.recompute is seed_aggregate
            and (tables.get("per_seed.csv") is None)
        ):
            source = "series.parquet, events.parquet and trajectories.parquet"
        expected = d.recompute(primary, frame)
        compare(primary.run_dir, d.file, frame, expected, d.key, source, d.complete)
        if len(expected):
            given.setdefault(d.file, set()).update(expected.columns)
    for name in COLUMN_CHECKED:
        if name in given:
            check_columns(primary, name, tables[name], given[name])
    check_shared_traffic_seeds(primary)  # after the first seed's, which are said first


#: The derived tables whose every column a derivation gives (:func:`check_columns`).
COLUMN_CHECKED = ("per_seed.csv", "summary.csv", "monitoring.csv", "comparison.csv")
#: Columns those tables may hold that no derivation gives.
UNDERIVED_COLUMNS = {"seed", "swarm", "role", "n_seeds", "oracle_swarm"}


def check_columns(primary: Primary, name: str, frame: pd.DataFrame, given: set[str]) -> None:
    """``name``'s columns are those its derivations give (``given``; :data:`UNDERIVED_COLUMNS`
    besides; of ``monitoring.csv``, ``summary.csv``'s monitoring columns): none other, and, in
    a folder of the current format, none of them missing."""
    path = primary.run_dir / name
    given = {c for c in given if not c.endswith(SLACK)}
    if name == "monitoring.csv":  # summary.csv's monitoring columns (twin.runs.write_run)
        given = {c for c in given if c.removesuffix("_ci95") in MONITORING_COLUMNS}
    other = [c for c in frame.columns if c not in given | UNDERIVED_COLUMNS]
    if other:
        raise UserError(f"{path}: holds a column {other[0]!r}, which twin does not write; {RERUN}")
    if folder_format(primary) < FOLDER_FORMAT:
        return
    if name in ("summary.csv", "monitoring.csv", "comparison.csv"):  # each with its seeds
        given = given | {"n_seeds"}
    missing = sorted(given - set(frame.columns))
    if missing:
        raise UserError(f"{path}: lacks the column {missing[0]!r}, which twin writes; {RERUN}")


#: What ``degradation.csv`` is recomputed from (:func:`check_degradation_replay`).
DEGRADATION_SOURCES = (
    "run.json's faults, trajectories.parquet, series.parquet, events.parquet and fault_free.parquet"
)


def check_degradation_replay(
    primary: Primary, frame: pd.DataFrame, fault_free: pd.DataFrame | None
) -> None:
    """``degradation.csv`` is :func:`twin.faults.degradation_table` of every seed with results:
    its phases from run.json's faults, the swarms' cells (``trajectories.parquet``) and scores
    (``series.parquet``), the seed's events (``events.parquet``) and the fault-free twin's cells
    (``fault_free.parquet``: from the same starts, one action a step). The twin's scores are
    replayed over the seed's maps wherever the folder holds them (:func:`_maps_by_seed`);
    elsewhere ``R_hat_fault_free`` is as the run wrote it. ``fault_free`` None: a folder of an
    earlier format (said by the load), whose twin is not replayed."""
    from twin.faults import degradation_table

    path = primary.run_dir / "degradation.csv"
    plan = fault_plan(primary)
    if plan is None:
        raise UserError(
            f"{path}: a degradation table, but run.json records no faults (it is written only "
            f"for runs with [faults]); {RERUN}"
        )
    free_path = primary.run_dir / "fault_free.parquet"
    grid, params, maps = Grid(primary.obstacles), primary.params(), _maps_by_seed(primary)
    series = primary.series.assign(swarm=primary.series["swarm"].astype(str))
    events = primary.events
    no_events = pd.DataFrame({c: pd.Series(dtype=np.int64) for c in EVENT_COLUMNS})
    tables, replayed = [], []
    for seed in sorted(int(s) for s in series["seed"].unique()):
        part = series[series["seed"] == seed].pivot(index="swarm", columns="step", values="reward")
        swarms = [s for s in primary.swarms if s in part.index]
        rewards = part.loc[swarms].to_numpy(np.float64)
        positions = np.stack([primary.positions(seed, s) for s in swarms])
        if fault_free is None:
            free = positions  # its cells are not known: only the faulted columns are compared
        else:
            free = np.stack([positions_of(free_path, fault_free, seed, s) for s in swarms])
            if free.shape != positions.shape or (free[:, 0] != positions[:, 0]).any():
                raise UserError(
                    f"{free_path}: the fault-free twin of seed {seed} does not start where its "
                    f"swarms start, or has {free.shape[1] - 1} steps and {free.shape[2]} drones "
                    f"where trajectories.parquet has {positions.shape[1] - 1} and "
                    f"{positions.shape[2]}; {RERUN}"
                )
        free_rewards = np.full_like(rewards, np.nan)
        slack = np.zeros_like(rewards)
        if fault_free is not None and params is not None and seed in maps:
            for k, swarm in enumerate(swarms):
                try:
                    r = replay_scores(grid, params, free[k], maps[seed][: free.shape[1]])
                except InfeasibleActionError as exc:
                    raise UserError(
                        f"{free_path}: swarm {swarm!r}, seed {seed}: {exc}; {RERUN}"
                    ) from None
                free_rewards[k], slack[k] = r["reward"], MAP_ROUNDING * np.abs(r["importance"])
        found = seed_events(primary, seed) if events is not None else no_events
        table = degradation_table(
            seed, swarms, grid, plan, found, positions, rewards, free, free_rewards
        )
        if fault_free is None:
            table = table.drop(columns=[c for c in table.columns if c.endswith("_fault_free")])
        of = {swarm: k for k, swarm in enumerate(swarms)}
        table["R_hat_fault_free" + SLACK] = [
            slack[of[r.swarm], r.start : r.stop].mean() if r.stop > r.start else 0.0
            for r in table.itertuples(index=False)
        ]
        tables.append(table)
        replayed += [not np.isnan(free_rewards).all()] * len(table)
    expected = pd.concat(tables, ignore_index=True)
    known = np.asarray(replayed, dtype=bool)
    faulted = expected.drop(columns=["R_hat_fault_free", "R_hat_fault_free" + SLACK],
                            errors="ignore")  # fmt: skip
    key = ("seed", "swarm", "phase")
    compare(primary.run_dir, path.name, frame, faulted, key, DEGRADATION_SOURCES, complete=True)
    if known.any() and "R_hat_fault_free" in expected.columns:
        twin = expected[known][[*key, "R_hat_fault_free", "R_hat_fault_free" + SLACK]]
        source = "fault_free.parquet replayed over the seed's maps"
        compare(primary.run_dir, path.name, frame, twin, key, source)


def compare(
    run_dir: Path,
    name: str,
    frame: pd.DataFrame,
    expected: pd.DataFrame,
    key: tuple[str, ...],
    source: str,
    complete: bool = False,
) -> None:
    """Each row of ``expected`` (by ``key``) is in ``frame`` with the same value in every column
    both hold, within :data:`TOLERANCE` (plus the row's ``<column> slack``, when ``expected``
    gives one); NaN only where NaN is expected. With ``complete``, ``frame`` holds no row of
    ``expected``'s seeds beyond those."""
    path = run_dir / name
    give = "give" if " and " in source else "gives"
    if complete and all(k in expected.columns for k in key) and len(frame):
        mine = _keyed(frame, key)
        scope = np.ones(len(mine), dtype=bool)
        if "seed" in key:
            seeds = expected.attrs.get("seeds", expected["seed"].unique())
            scope = mine.index.get_level_values("seed").isin([int(s) for s in seeds])
        extra = scope & ~mine.index.isin(_keyed(expected, key).index)
        if extra.any():
            who = _who(key, mine.index[np.flatnonzero(extra)[0]])
            raise UserError(
                f"{path}: holds a row for {who}, which {source} "
                f"{'do' if give == 'give' else 'does'} not give; {RERUN}"
            )
    key = tuple(k for k in key if k in expected.columns)
    if not len(expected) or not all(k in frame.columns for k in key):
        return
    columns = [c for c in expected.columns if c in frame.columns and c not in key]
    mine = _keyed(frame, key)
    theirs = _keyed(expected, key)
    missing = ~theirs.index.isin(mine.index)
    if missing.any():
        who = _who(key, theirs.index[np.flatnonzero(missing)[0]])
        raise UserError(f"{path}: no row for {who}, which {source} holds; {RERUN}")
    got = mine.loc[theirs.index]
    if not columns:
        return
    bad = np.stack(
        [_differ(got[c], theirs[c], theirs.get(c + SLACK)) for c in columns],
        axis=1,
    )
    rows = np.flatnonzero(bad.any(axis=1))
    if not len(rows):
        return
    n = int(rows[0])
    column = columns[int(np.flatnonzero(bad[n])[0])]
    have, want = got[column].iloc[n], theirs[column].iloc[n]
    raise UserError(
        f"{path}: {column} = {_show(have, want)} for {_who(key, theirs.index[n])}, but {source} "
        f"{give} {_show(want, have)}; {RERUN}"
    )


def _differ(have: pd.Series, want: pd.Series, slack: pd.Series | None) -> np.ndarray:
    """Where ``have`` is not ``want`` (:func:`_same`, row by row), vectorised for numbers."""
    flags = pd.api.types.is_bool_dtype
    numbers = pd.api.types.is_numeric_dtype
    if flags(have) or flags(want) or not (numbers(have) and numbers(want)):
        extra = np.zeros(len(want)) if slack is None else slack.to_numpy(np.float64)
        return np.array(
            [not _same(h, w, e) for h, w, e in zip(have, want, extra, strict=True)], dtype=bool
        )
    h, w = have.to_numpy(np.float64), want.to_numpy(np.float64)
    allowed = TOLERANCE * np.maximum(1.0, np.abs(w))
    if slack is not None:
        allowed = allowed + slack.to_numpy(np.float64)
    nan_h, nan_w = np.isnan(h), np.isnan(w)
    with np.errstate(invalid="ignore"):
        off = ~(np.abs(h - w) <= allowed)
    return np.where(nan_h | nan_w, nan_h != nan_w, off)


#: Keys of a compared table that hold names (the others hold numbers: seed, step, phase...).
NAME_KEYS = ("swarm", "model")


def _keyed(frame: pd.DataFrame, key: tuple[str, ...]) -> pd.DataFrame:
    frame = frame.copy()
    for k in key:
        frame[k] = frame[k].astype(str) if k in NAME_KEYS else frame[k].astype(np.int64)
    return frame.drop_duplicates(list(key)).set_index(list(key))


def _who(key: tuple[str, ...], at: Any) -> str:
    values = at if isinstance(at, tuple) else (at,)
    parts = [
        f"{k} {v!r}" if k in NAME_KEYS else f"{k} {v}" for k, v in zip(key, values, strict=True)
    ]
    return ", ".join(parts)


def _same(have: Any, want: Any, slack: float = 0.0) -> bool:
    if isinstance(want, (bool, np.bool_)) or isinstance(have, (bool, np.bool_)):
        return bool(have) == bool(want)
    try:
        h, w = float(have), float(want)
    except (TypeError, ValueError):
        return str(have) == str(want)
    if np.isnan(w) or np.isnan(h):
        return bool(np.isnan(w) and np.isnan(h))
    return abs(h - w) <= TOLERANCE * max(1.0, abs(w)) + slack


def _show(value: Any, other: Any = None) -> str:
    """``value`` in 6 significant digits, or as many more as it takes to tell it from
    ``other`` (a figure rounded on a spreadsheet's save differs past the sixth)."""
    if isinstance(value, (bool, np.bool_)):
        return str(bool(value)).lower()
    try:
        number = float(value)
    except (TypeError, ValueError):
        return repr(value)
    try:
        against = float(other) if other is not None else None
    except (TypeError, ValueError):
        against = None
    for digits in (6, 9, 12, 17):
        text = f"{number:.{digits}g}"
        if against is None or number == against or text != f"{against:.{digits}g}":
            return text
    return text
