"""Read a run folder (the format documented in ``twin/runs.py``) into one object for the report.

Only the run's own files are read; nothing is recomputed here except what the files determine
exactly (the idleness maps, replayed from the trajectories with Def. 3).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from functools import cached_property
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

from twin.clock import clock_label, parse_clock
from twin.errors import UserError
from twin.grid import Grid
from twin.metrics import BOUND, is_ceiling_row, swarm_rows
from twin.mfd import EMPTY_SAMPLE_COLUMNS
from twin.readback import (
    BELIEF_MODEL_COLUMNS,
    DEGRADATION_COLUMNS,
    EVENT_COLUMNS,
    INT,
    MFD_FIELDS,
    MFD_RANGES,
    MFD_SAMPLE_COLUMNS,
    NETWORK_FIELDS,
    NETWORK_RANGES,
    NUMBER,
    RERUN,
    SERIES_COLUMNS,
    TEXT,
    TIMING_COLUMNS,
    TRAJECTORY_COLUMNS,
    check_bounds,
    check_column,
    check_fields,
    check_headline,
    check_incidents,
    check_known_columns,
    check_ranges,
    check_run_json,
    check_series,
    check_timing,
    check_trajectories,
    numeric_columns,
    off_grid,
    parquet_columns,
    read_json,
    read_maps,
    read_table,
)
from twin.report.derived import (
    Primary,
    _show,
    check_degradation_replay,
    check_derived,
    folder_format_of,
)
from twin.runs import (
    COMPLETE_SINCE_FORMAT,
    FOLDER_FORMAT,
    LIVE_RUN_WRITTEN,
    REQUIRED_FILES,
    RUN_WRITTEN,
)
from twin.scores import ScoreParams, initial_idleness, update_idleness
from twin.sumo.detectors import DETECTOR_COLUMNS
from twin.swarms import check_policy_records, is_learned


@dataclass
class RunFiles:
    """Everything a report shows, as read from one run folder."""

    run_dir: Path
    series: pd.DataFrame
    trajectories: pd.DataFrame
    summary: pd.DataFrame
    per_seed: pd.DataFrame | None
    importance: np.ndarray  # (T+1, nx, ny), first seed
    obstacles: np.ndarray  # (nx, ny) bool
    run: dict[str, Any]
    network: dict[str, Any] | None = None
    mfd: dict[str, Any] | None = None
    mfd_samples: pd.DataFrame | None = None
    monitoring: pd.DataFrame | None = None  # monitoring.csv
    beliefs: pd.DataFrame | None = None  # belief_models.csv (twin run --history)
    belief_maps: dict[str, Any] | None = None  # belief_maps.npz (twin run --history)
    events: pd.DataFrame | None = None  # events.parquet
    incidents: list[dict[str, Any]] | None = None  # incidents.json (scheduled SUMO incidents)
    timing: pd.DataFrame | None = None  # timing.csv (wall time per stage)
    degradation: pd.DataFrame | None = None  # degradation.csv (runs with [faults])
    manifest: dict[str, Any] = field(default_factory=dict)  # manifest.json
    #: each seed's tape replayed through its MFD on read-back (by seed; a tape too large to
    #: replay on read-back is not here): the maps the run scored
    tape_maps: dict[int, np.ndarray] = field(default_factory=dict, repr=False)
    _idleness: dict[tuple[int, str], np.ndarray] = field(default_factory=dict, repr=False)

    @property
    def partial(self) -> bool:
        return bool(self.manifest.get("partial") or self.run.get("partial"))

    @property
    def partial_reason(self) -> str:
        return str(
            self.manifest.get("partial_reason") or self.run.get("partial_reason") or "unknown"
        )

    @property
    def grid(self) -> Grid:
        return Grid(self.obstacles)

    @property
    def swarms(self) -> list[str]:
        """Swarm names in the order of ``summary.csv`` (ceiling rows left out: they have no
        series or trajectories)."""
        from twin.metrics import swarm_rows

        return [str(s) for s in swarm_rows(self.summary)["swarm"]]

    @property
    def seeds(self) -> list[int]:
        return sorted(int(s) for s in self.series["seed"].unique())

    @property
    def first_seed(self) -> int:
        """The seed whose importance maps ``importance.npz`` holds."""
        seed = self.run.get("importance_seed")
        return int(seed) if seed is not None else self.seeds[0]

    @property
    def horizon(self) -> int:
        return int(self.importance.shape[0]) - 1

    @cached_property
    def importance_vmax(self) -> float:
        """Top of the colour scale of importance maps: the run's peak ``T`` rounded up to 0.05
        (1 for a run that reaches it), so that congestion stands out when it stays mild."""
        peak = float(self.importance[:, ~self.obstacles].max(initial=0.0))
        return 1.0 if peak <= 0 else min(1.0, float(np.ceil(peak * 20.0 - 1e-9) / 20.0))

    def clock_start(self) -> tuple[str | None, float]:
        """Clock time of ``T^0`` and seconds per step of a simulated run (None, 0 otherwise)."""
        traffic = self.run.get("traffic") or {}
        begin, step_s = traffic.get("begin"), traffic.get("step_s")
        if isinstance(begin, str) and isinstance(step_s, (int, float)):
            return begin, float(step_s)
        return None, 0.0

    def clock(self, k: int) -> str | None:
        """``HH:MM`` of step ``k`` of a simulated run, None for synthetic traffic."""
        begin, step_s = self.clock_start()
        if begin is None:
            return None
        return clock_label(parse_clock(begin, "run.json: traffic.begin") + k * step_s, False)

    def positions(self, swarm: str, seed: int | None = None) -> np.ndarray:
        """``(T+1, N, 2)`` drone cells ``P_0 .. P_T`` of one swarm and seed."""
        seed = self.first_seed if seed is None else seed
        t = self.trajectories
        rows = t[(t["seed"] == seed) & (t["swarm"] == swarm)]
        if rows.empty:
            raise UserError(
                f"{self.run_dir / 'trajectories.parquet'}: no rows for swarm {swarm!r}, seed {seed}"
            )
        rows = rows.sort_values(["step", "drone"])
        n_steps = int(rows["step"].max()) + 1
        n_drones = int(rows["drone"].max()) + 1
        return rows[["i", "j"]].to_numpy(dtype=np.int64).reshape(n_steps, n_drones, 2)

    @property
    def faults(self):
        """The run's :class:`twin.faults.FaultPlan` (run.json ``faults``), None without."""
        from twin.faults import FaultPlan

        return FaultPlan.from_record(self.run.get("faults"))

    def live(self, seed: int | None = None) -> np.ndarray | None:
        """``(T+1, N)`` bool: the drones live at each step under the run's faults (None
        without drone losses)."""
        plan = self.faults
        if plan is None or not plan.drone_loss:
            return None
        pos = self.positions(self.swarms[0], seed)
        return plan.live_steps(len(pos), pos.shape[1])

    def score_params(self) -> tuple[ScoreParams, str]:
        """The run's ``eta``/``delta`` and where they came from (run.json, or the defaults)."""
        for where in (("params",), ("score_params",), ("config", "params"), ("config", "score")):
            node: Any = self.run
            for key in where:
                node = node.get(key) if isinstance(node, dict) else None
            if isinstance(node, dict) and "eta" in node and "delta" in node:
                known = {
                    k: float(node[k]) for k in ("eta", "delta", "alpha_T", "alpha_I") if k in node
                }
                return ScoreParams(**known), "run.json " + ".".join(where)
        return ScoreParams(), "defaults (run.json records none)"

    def idleness(self, swarm: str, seed: int | None = None) -> np.ndarray:
        """``(T+1, nx, ny)`` idleness ``I^0 .. I^T`` replayed from the trajectories (Def. 3).

        ``I^0 = 1`` on free cells; ``I^{k+1} = update(I^k, P_{k+1})``, the convention under which
        ``series.parquet``'s ``coverage`` column is ``C^{k+1}``.
        """
        seed = self.first_seed if seed is None else seed
        key = (seed, swarm)
        if key not in self._idleness:
            params, _ = self.score_params()
            grid, pos = self.grid, self.positions(swarm, seed)
            plan = self.faults
            recorded = None if plan is None else plan.recorded(seed, len(pos), pos.shape[1])
            maps = np.empty((len(pos), *grid.shape))
            maps[0] = initial_idleness(grid)
            for k in range(1, len(pos)):
                visits = pos[k] if recorded is None else pos[k][recorded[k, :, 0]]
                maps[k] = update_idleness(maps[k - 1], visits, grid, params.eta, params.delta)
            self._idleness[key] = maps
        return self._idleness[key]


def read_belief_maps(path: Path, shape: tuple[int, int]) -> dict[str, Any] | None:
    """``belief_maps.npz`` (:func:`twin.belief.belief_maps`) checked, or None when the run has
    none; a damaged file is one :class:`UserError` line naming it."""
    import json

    if not path.exists():
        return None
    keys = ("seed", "swarms", "steps", "truth", "mean", "std", "threshold", "event_i",
            "event_j", "event_onset", "event_duration", "known_at", "history_known_at")  # fmt: skip
    try:
        with np.load(path, allow_pickle=False) as npz:
            missing = [k for k in keys if k not in npz.files]
            if missing:
                raise UserError(f"{path}: no array {missing[0]!r}; {RERUN}")
            data = {k: npz[k] for k in keys}
        swarms = json.loads(str(data["swarms"]))
        assert isinstance(swarms, list) and all(isinstance(s, str) for s in swarms)
    except UserError:
        raise
    except Exception as exc:  # zip, JSON and format errors of a damaged file
        why = type(exc).__name__
        raise UserError(f"{path}: not a readable belief_maps.npz ({why}); {RERUN}") from None
    n_steps, n_events = len(data["steps"]), len(data["event_i"])
    expected = {
        "truth": (n_steps, *shape),
        "mean": (len(swarms), n_steps, *shape),
        "std": (len(swarms), n_steps, *shape),
        "known_at": (len(swarms), n_events),
        "history_known_at": (n_events,),
    }
    for key in ("event_j", "event_onset", "event_duration"):
        expected[key] = (n_events,)
    for key, want in expected.items():
        if tuple(data[key].shape) != want:
            raise UserError(f"{path}: {key} has shape {data[key].shape}, not {want}; {RERUN}")
    for key in ("truth", "mean", "std"):
        if not np.isfinite(data[key]).all():
            raise UserError(f"{path}: {key} holds NaN or infinite values; {RERUN}")
    return {**data, "swarms": swarms, "seed": int(data["seed"]),
            "threshold": float(data["threshold"])}  # fmt: skip


#: Text columns of the results tables: the row's name, whether it is a swarm or a ceiling, and
#: which oracle swarm gave the oracle row.
TABLE_TEXT = ("swarm", "role", "oracle_swarm")


def _read_json(path: Path) -> Any:
    """The JSON file at ``path``, None when absent; unreadable JSON is a one-line error."""
    return read_json(path)


def read_fault_free(run_dir: Path, run: dict[str, Any], obstacles: np.ndarray):
    """``fault_free.parquet``: the fault-free twin's cells beside ``degradation.csv``; None in
    a folder of format 2 or earlier, which did not keep them."""
    path = run_dir / "fault_free.parquet"
    if not path.exists() and folder_format_of(run) < 3:
        return None
    if not path.is_file():
        raise UserError(
            f"{run_dir / 'degradation.csv'}: its fault-free twin's cells (fault_free.parquet) "
            f"are missing; {RERUN}"
        )
    frame = read_table(path)
    check_trajectories(path, frame, obstacles.shape, obstacles)
    return frame


def check_written_files(run_dir: Path, run: dict[str, Any]) -> None:
    """A folder of :data:`twin.runs.COMPLETE_SINCE_FORMAT` or later holds the files its run
    always writes (:data:`twin.runs.RUN_WRITTEN`, :data:`twin.runs.LIVE_RUN_WRITTEN` and a
    live run's tape of each seed): one removed with its manifest entry would leave its figures
    or its checks out of the report unsaid."""
    if folder_format_of(run) < COMPLETE_SINCE_FORMAT:
        return
    traffic = run.get("traffic")
    live = run.get("kind") == "run" and isinstance(traffic, dict) and traffic.get("kind") == "sumo"
    seeds = run.get("seeds") if isinstance(run.get("seeds"), list) else []
    tapes = [f"tapes/seed-{s}.parquet" for s in seeds] if live and len(seeds) > 1 else []
    for name in (*RUN_WRITTEN, *(LIVE_RUN_WRITTEN if live else ()), *tapes):
        if not (run_dir / name).is_file():
            whose = "every run" if name in RUN_WRITTEN else "a live SUMO run"
            raise UserError(f"{run_dir}: {name} is missing, which {whose} writes; {RERUN}")


def _say_folder_format(run_dir: Path, run: dict[str, Any]) -> None:
    """A folder of an earlier format (:data:`twin.runs.FOLDER_FORMAT`) reads back, with a
    notice of what its read-back cannot replay; a later format than this twin's is refused."""
    from twin.boundary import notify

    found = run.get("folder_format", 1)
    if not isinstance(found, int) or isinstance(found, bool) or found < 1:
        raise UserError(f"{run_dir / 'run.json'}: folder_format = {found!r} is no format; {RERUN}")
    if found > FOLDER_FORMAT:
        raise UserError(
            f"{run_dir}: a run folder of format {found}, written by a later twin (this one reads "
            f"up to {FOLDER_FORMAT}); update twin"
        )
    # what the folder holds that its format did not have: a later folder relabelled, whose
    # checks the earlier format's read-back would leave out
    later = [
        (1, "folder_format" in run, "folder_format (format 1 folders have none)"),
        (2, (run_dir / "oracle.parquet").exists(), "oracle.parquet (format 3 added it)"),
        (2, (run_dir / "fault_free.parquet").exists(), "fault_free.parquet (format 3 added it)"),
    ]
    said = f"folder_format = {found}" if "folder_format" in run else "no folder_format (format 1)"
    for upto, held, what in later:
        if found <= upto and held:
            raise UserError(f"{run_dir / 'run.json'}: {said}, but the folder holds {what}; {RERUN}")
    missing = [] if found >= 2 else ["bound row", "incident schedule"]
    if found < 3 and (run_dir / "degradation.csv").exists():
        missing.append("fault-free twin")
    if found < 3 and (run_dir / "bound.npz").exists():  # its ceiling rows: an oracle row
        missing.append("oracle row")
    if missing:
        notify(
            f"twin: notice: {run_dir}: written by an earlier twin (folder format {found}): its "
            f"{' and '.join(missing)} are not replayed; rerun it for every check"
        )


def load_run(run_dir: str | Path) -> RunFiles:
    """Read a finished run folder: its ``manifest.json`` must be there and agree with the files
    (:func:`twin.runs.check_run_folder`); a missing required file, an incomplete folder, a
    damaged file (unreadable, a column missing, a string or NaN where a number belongs, rows
    missing or duplicated, a cell off the grid, arrays of the wrong shape) or a run in which no
    step ran is a one-line :class:`UserError` naming the file and the field."""
    from twin.runs import check_run_folder

    run_dir = Path(run_dir)
    if not run_dir.is_dir():
        what = "a file, not a run folder" if run_dir.exists() else "no such run folder"
        raise UserError(f"{run_dir}: {what}; pass the folder `twin run`/`evaluate` wrote")
    if (run_dir / "run.json").exists():  # a run folder: interrupted ones say so first
        check_run_folder(run_dir)
    missing = [name for name in REQUIRED_FILES if not (run_dir / name).is_file()]
    if missing:
        raise UserError(
            f"{run_dir}: missing {', '.join(missing)}; is this a run folder written by "
            "`twin run` or `twin evaluate`?"
        )
    manifest = check_run_folder(run_dir)
    run_path = run_dir / "run.json"
    run = check_run_json(run_path, read_json(run_path) or {})
    check_policy_records(run_path, run)
    if any(is_learned(swarm) for swarm in run.get("policies") or {}):  # (torch, only then)
        from twin.learning.checkpoint import check_recorded_checkpoints

        check_recorded_checkpoints(run_path, run["policies"])
    _say_folder_format(run_dir, run)
    check_written_files(run_dir, run)
    importance, obstacles = read_maps(run_dir / "importance.npz")
    if importance.shape[0] < 2:
        raise UserError(
            f"{run_dir}: partial run in which no step ran "
            f"({run.get('partial_reason') or 'no reason recorded'}); nothing to report, "
            "fix the inputs and rerun"
        )
    series_path, traj_path = run_dir / "series.parquet", run_dir / "trajectories.parquet"
    series = read_table(series_path)
    check_series(series_path, series)
    check_known_columns(series_path, series, [*SERIES_COLUMNS, "belief_error"])
    trajectories = read_table(traj_path)
    check_trajectories(traj_path, trajectories, obstacles.shape, obstacles)
    check_known_columns(traj_path, trajectories, TRAJECTORY_COLUMNS)
    summary_path = run_dir / "summary.csv"
    summary = read_table(summary_path, {"swarm": TEXT})
    if "n_seeds" in summary.columns:
        check_column(summary_path, summary, "n_seeds", INT)
    numeric_columns(summary_path, summary, TABLE_TEXT)
    check_headline(summary_path, summary)

    def optional(name: str, columns: dict[str, str], text: tuple[str, ...] = ()):
        path = run_dir / name
        if not path.exists():
            return None
        frame = read_table(path, columns)
        if text:
            numeric_columns(path, frame, text)
            if "n_seeds" in frame.columns:
                check_column(path, frame, "n_seeds", INT)
        return frame

    per_seed = optional("per_seed.csv", {"seed": INT, "swarm": TEXT}, TABLE_TEXT)
    if per_seed is not None:
        check_headline(run_dir / "per_seed.csv", per_seed)
        dup = per_seed.duplicated(["seed", "swarm"])
        if dup.any():
            r = per_seed[dup].iloc[0]
            raise UserError(
                f"{run_dir / 'per_seed.csv'}: the row of seed {r['seed']}, swarm {r['swarm']!r} "
                f"appears twice; {RERUN}"
            )
    monitoring = optional("monitoring.csv", {"swarm": TEXT}, TABLE_TEXT)
    events = optional("events.parquet", EVENT_COLUMNS)
    beliefs = optional("belief_models.csv", BELIEF_MODEL_COLUMNS, ("swarm", "model"))
    belief_maps = read_belief_maps(run_dir / "belief_maps.npz", obstacles.shape)
    timing = optional("timing.csv", TIMING_COLUMNS)
    degradation = optional("degradation.csv", DEGRADATION_COLUMNS, ("swarm", "label"))
    if degradation is not None:
        check_known_columns(run_dir / "degradation.csv", degradation, DEGRADATION_COLUMNS)
    # columns written since before COMPLETE_SINCE_FORMAT: required of a folder of it or later
    current = folder_format_of(run) >= COMPLETE_SINCE_FORMAT
    if timing is not None:
        extra = ("process", "share")
        check_known_columns(
            run_dir / "timing.csv", timing, [*TIMING_COLUMNS, *extra], extra if current else ()
        )
        for name, kind in (("process", TEXT), ("share", NUMBER)):
            if name in timing.columns:
                check_column(run_dir / "timing.csv", timing, name, kind)
        check_bounds(run_dir / "timing.csv", timing)
        check_timing(run_dir / "timing.csv", timing, series)
    samples = optional("mfd_samples.parquet", MFD_SAMPLE_COLUMNS)
    if samples is not None:
        written = EMPTY_SAMPLE_COLUMNS.keys()
        check_known_columns(
            run_dir / "mfd_samples.parquet", samples, written, written if current else ()
        )
    if samples is not None and "speed_limit" in samples.columns:
        check_column(run_dir / "mfd_samples.parquet", samples, "speed_limit", NUMBER)
    path = run_dir / "detectors.parquet"
    if path.exists():  # its columns (its readings: check_detector_readings)
        written = parquet_columns(path)
        check_known_columns(path, written, DETECTOR_COLUMNS, DETECTOR_COLUMNS if current else ())
    network, mfd = read_json(run_dir / "network.json"), read_json(run_dir / "mfd.json")
    incidents = read_json(run_dir / "incidents.json")
    if network is not None:
        check_fields(run_dir / "network.json", network, NETWORK_FIELDS)
        check_ranges(run_dir / "network.json", network, NETWORK_RANGES)
    if network is not None and network.get("row_0") not in (None, *ROW_0):
        raise UserError(
            f"{run_dir / 'network.json'}: row_0 = {str(network['row_0'])[:40]!r} must be "
            f"{' or '.join(repr(r) for r in ROW_0)}; {RERUN}"
        )
    if mfd is not None:
        check_fields(run_dir / "mfd.json", mfd, MFD_FIELDS)
        check_ranges(run_dir / "mfd.json", mfd, MFD_RANGES)
    if incidents is not None:
        check_incidents(run_dir / "incidents.json", incidents)
    check_consistent(run_dir, run, series, trajectories, summary, importance, obstacles, per_seed)
    check_partial(run_dir, run, manifest)
    swarms = {str(s) for s in summary["swarm"]}
    if degradation is not None:
        check_degradation(run_dir / "degradation.csv", degradation, swarms, series)
    if beliefs is not None:
        check_beliefs(run_dir / "belief_models.csv", beliefs, swarms, series)
    if belief_maps is not None:
        check_belief_maps(run_dir / "belief_maps.npz", belief_maps, swarms, series)
    if events is not None:
        check_events(run_dir / "events.parquet", events, obstacles.shape, series)
    if monitoring is not None:
        check_monitoring(run_dir / "monitoring.csv", monitoring)
    check_sumo_files(run_dir, run, network, mfd, samples)
    first = run.get("importance_seed")
    primary = Primary(
        run_dir, series, trajectories, events, obstacles, run, [str(s) for s in
        summary.loc[~is_ceiling_row(summary), "swarm"]], importance=importance,
        first_seed=int(first) if first is not None else int(series["seed"].min()),
        incidents=incidents,
    )  # fmt: skip
    comparison = optional(
        "comparison.csv",
        {"swarm": TEXT, "against": TEXT, "column": TEXT},
        ("swarm", "against", "column"),
    )
    check_derived(
        primary,
        {"series.parquet": series, "events.parquet": events, "per_seed.csv": per_seed,
         "summary.csv": summary, "monitoring.csv": monitoring, "comparison.csv": comparison},
    )  # fmt: skip
    if degradation is not None:
        fault_free = read_fault_free(run_dir, run, obstacles)
        check_degradation_replay(primary, degradation, fault_free)
    if beliefs is not None:
        check_belief_scores(run_dir, beliefs, primary, belief_maps)
        from twin.report.beliefs import check_belief_replay

        why = check_belief_replay(primary, beliefs, belief_maps)
        if why is not None:
            from twin.boundary import notify

            notify(
                f"twin: notice: {run_dir}: belief_models.csv and belief_maps.npz not replayed "
                f"({why}); their ranges and relations are checked"
            )
    return RunFiles(
        run_dir=run_dir,
        series=series,
        trajectories=trajectories,
        summary=summary,
        per_seed=per_seed,
        importance=importance,
        obstacles=obstacles,
        run=run,
        network=network,
        mfd=mfd,
        mfd_samples=samples,
        monitoring=monitoring,
        beliefs=beliefs,
        belief_maps=belief_maps,
        events=events,
        incidents=incidents,
        timing=timing,
        degradation=degradation,
        manifest=manifest,
        tape_maps=primary.tape_maps,
    )


def check_consistent(
    run_dir: Path,
    run: dict[str, Any],
    series: pd.DataFrame,
    trajectories: pd.DataFrame,
    summary: pd.DataFrame,
    importance: np.ndarray,
    obstacles: np.ndarray,
    per_seed: pd.DataFrame | None,
) -> None:
    """The run folder's files describe one run: the same seeds and swarms, and the first
    seed's trajectories as long as its importance maps."""
    traj = run_dir / "trajectories.parquet"
    seeds = sorted(int(s) for s in series["seed"].unique())
    if not seeds:
        raise UserError(f"{run_dir / 'series.parquet'}: no rows; {RERUN}")
    traj_seeds = sorted(int(s) for s in trajectories["seed"].unique())
    if seeds != traj_seeds:
        raise UserError(f"{traj}: seeds {traj_seeds} differ from series.parquet's {seeds}; {RERUN}")
    swarms = [str(s) for s in summary["swarm"]]
    if not swarms or len(set(swarms)) != len(swarms):
        raise UserError(
            f"{run_dir / 'summary.csv'}: swarm must list each swarm once (has {swarms}); {RERUN}"
        )
    if "role" in summary.columns:  # ceilings (oracle, bound) are rows without paths
        swarms = [s for s, role in zip(swarms, summary["role"], strict=True) if role != "ceiling"]
    listed = set(swarms)
    for name, held in (
        ("series.parquet", series["swarm"].unique()),
        ("trajectories.parquet", trajectories["swarm"].unique()),
        ("run.json", run.get("swarms") if isinstance(run.get("swarms"), list) else []),
    ):
        extra = [str(s) for s in held if str(s) not in listed]
        if extra:
            raise UserError(
                f"{run_dir / 'summary.csv'}: no row for swarm {extra[0]!r}, which {name} "
                f"holds; {RERUN}"
            )
    ran = run.get("swarms")
    if isinstance(ran, list):  # and every swarm with a row is one the run ran
        unknown = [s for s in swarms if s not in {str(r) for r in ran}]
        if unknown:
            raise UserError(
                f"{run_dir / 'summary.csv'}: holds swarm {unknown[0]!r}, which run.json's "
                f"swarms {[str(r) for r in ran][:8]} does not list; {RERUN}"
            )
    first = run.get("importance_seed")
    first = int(first) if first is not None else seeds[0]
    if first not in seeds:
        raise UserError(
            f"{run_dir / 'run.json'}: importance_seed = {first} is not a seed of the run; {RERUN}"
        )
    rows = trajectories[trajectories["seed"] == first]
    known = {str(s) for s in rows["swarm"].unique()}
    for swarm in swarms:
        if swarm not in known:
            raise UserError(
                f"{traj}: no rows for swarm {swarm!r} (summary.csv), seed {first}; {RERUN}"
            )
        steps = int(rows.loc[rows["swarm"].astype(str) == swarm, "step"].max()) + 1
        if steps != importance.shape[0]:
            raise UserError(
                f"{traj}: swarm {swarm!r} has {steps} steps in seed {first}, importance.npz "
                f"{importance.shape[0]}; {RERUN}"
            )
    s_rows = series[series["seed"] == first]
    for swarm in swarms:
        n = int((s_rows["swarm"].astype(str) == swarm).sum())
        if n != importance.shape[0] - 1:
            raise UserError(
                f"{run_dir / 'series.parquet'}: swarm {swarm!r} has {n} steps in seed {first}, "
                f"not {importance.shape[0] - 1}; {RERUN}"
            )
    grid = run.get("grid")
    if isinstance(grid, dict) and [grid.get("nx"), grid.get("ny")] != list(importance.shape[1:]):
        raise UserError(
            f"{run_dir / 'run.json'}: grid = {grid.get('nx')} x {grid.get('ny')}, but "
            f"importance.npz holds {importance.shape[1]} x {importance.shape[2]} maps; {RERUN}"
        )
    if isinstance(grid, dict) and grid.get("n_free") not in (None, int((~obstacles).sum())):
        raise UserError(
            f"{run_dir / 'run.json'}: grid.n_free = {grid.get('n_free')}, but importance.npz "
            f"has {int((~obstacles).sum())} free cells; {RERUN}"
        )
    n_drones = run.get("n_drones")
    if isinstance(n_drones, int):
        flying = trajectories.groupby(["seed", "swarm"])["drone"].max() + 1
        off = flying[flying != n_drones]
        if len(off):
            (seed, swarm), n = off.index[0], int(off.iloc[0])
            raise UserError(
                f"{run_dir / 'run.json'}: n_drones = {n_drones}, but trajectories.parquet has "
                f"{n} drones for swarm {swarm!r}, seed {seed}; {RERUN}"
            )
    horizon = run.get("horizon")
    if isinstance(horizon, int) and horizon != importance.shape[0] - 1:
        raise UserError(
            f"{run_dir / 'run.json'}: horizon = {horizon}, but seed {first} ran "
            f"{importance.shape[0] - 1} steps (importance.npz, series.parquet); {RERUN}"
        )
    network = read_json(run_dir / "network.json")
    net_grid = network.get("grid") if isinstance(network, dict) else None
    if isinstance(net_grid, dict) and [net_grid.get("nx"), net_grid.get("ny")] != list(
        importance.shape[1:]
    ):
        raise UserError(
            f"{run_dir / 'network.json'}: grid = {net_grid.get('nx')} x {net_grid.get('ny')}, "
            f"but importance.npz holds {importance.shape[1]} x {importance.shape[2]} maps; {RERUN}"
        )
    if per_seed is not None:
        extra = sorted(set(int(s) for s in per_seed["seed"]) - set(seeds))
        if extra:
            raise UserError(
                f"{run_dir / 'per_seed.csv'}: seed {extra[0]} has rows but no results in "
                f"series.parquet (seeds {seeds}); {RERUN}"
            )
    recorded = run.get("seeds")
    if isinstance(recorded, list) and len(set(recorded)) != len(recorded):
        twice = next(s for n, s in enumerate(recorded) if s in recorded[:n])
        raise UserError(
            f"{run_dir / 'run.json'}: seeds = {str(recorded)[:60]} lists seed {twice} twice; "
            f"{RERUN}"
        )
    if isinstance(recorded, list) and sorted(set(recorded)) != seeds:
        raise UserError(
            f"{run_dir / 'run.json'}: seeds = {str(recorded)[:60]} differ from those with "
            f"results in series.parquet, {seeds}; {RERUN}"
        )
    check_scores(run_dir, series, summary)


#: How far a swarm's R_hat_T may lie above the bound row's (float rounding).
SCORE_TOLERANCE = 1e-9


def check_scores(run_dir: Path, series: pd.DataFrame, summary: pd.DataFrame) -> None:
    """No swarm of ``summary.csv`` lies above its bound row (the bound is an upper bound of
    every swarm, :mod:`twin.ceilings`); the swarms' own figures are checked against their
    series by :func:`twin.report.derived.check_derived`."""
    path = run_dir / "summary.csv"
    if "R_hat_T" not in summary.columns:
        return
    values = swarm_rows(summary)["R_hat_T"].to_numpy(np.float64)
    values = values[np.isfinite(values)]
    best = float(values.max()) if len(values) else None
    bound = summary.loc[summary["swarm"].astype(str) == BOUND, "R_hat_T"].astype(float)
    limit = float(bound.iloc[0]) if len(bound) else np.nan
    if best is not None and best > limit + SCORE_TOLERANCE * max(1.0, abs(best)):
        raise UserError(
            f"{path}: the {BOUND} row's R_hat_T = {limit:.6g} lies below a swarm's "
            f"{best:.6g}, which no swarm can exceed; {RERUN}"
        )


def check_sumo_files(
    run_dir: Path,
    run: dict[str, Any],
    network: dict[str, Any] | None,
    mfd: dict[str, Any] | None,
    samples: pd.DataFrame | None,
) -> None:
    """A live SUMO run's ``network.json`` and ``mfd.json`` agree with what the run used: the
    cell size of run.json ``traffic.identity``, the prior MFD of run.json ``traffic.mfd_prior``
    when mfd.json says the prior was used, and the fit's R2 and RMSE recomputed from
    ``mfd_samples.parquet`` with mfd.json's ``a`` and ``k_c`` (:func:`twin.mfd.fit_quality`)."""
    from twin.mfd import MFD, fit_quality

    traffic = run.get("traffic") if isinstance(run.get("traffic"), dict) else {}
    cell = _dotted_get(traffic, "identity", "cell_m")
    net_cell = _dotted_get(network, "grid", "cell_m")
    if (
        isinstance(cell, (int, float))
        and isinstance(net_cell, (int, float))
        and not _close(net_cell, cell)
    ):
        raise UserError(
            f"{run_dir / 'network.json'}: grid.cell_m = {net_cell:g}, but run.json has "
            f"traffic.identity.cell_m = {cell:g}; {RERUN}"
        )
    if not isinstance(mfd, dict):
        return
    prior = traffic.get("mfd_prior")
    if mfd.get("used") == "prior" and isinstance(prior, list) and len(prior) == 2:
        for name, want in zip(("a", "k_c"), prior, strict=True):
            have = mfd.get(name)
            numbers = isinstance(have, (int, float)) and isinstance(want, (int, float))
            if numbers and not _close(have, want):
                raise UserError(
                    f'{run_dir / "mfd.json"}: {name} = {have:g} with used = "prior", but '
                    f"run.json has traffic.mfd_prior = {prior}; {RERUN}"
                )
    a, k_c = mfd.get("a"), mfd.get("k_c")
    need = {"density", "speed", "speed_limit"}
    if samples is None or not need <= set(samples.columns) or not len(samples):
        return
    if not (isinstance(a, (int, float)) and isinstance(k_c, (int, float))):
        return
    quality = fit_quality(MFD(float(a), float(k_c)), samples["density"], samples["speed"],
                          samples["speed_limit"])  # fmt: skip
    for name, key in (("r2", "r2"), ("rmse_kmh", "rmse_kmh")):
        have = mfd.get(name)
        want = quality[key]
        if not isinstance(have, (int, float)):
            continue
        if np.isnan(want) and np.isnan(have):
            continue
        if np.isnan(want) or np.isnan(have) or not _close(have, want, 1e-6):
            raise UserError(
                f"{run_dir / 'mfd.json'}: {name} = {have:.6g} of a = {a:g}, k_c = {k_c:g}, but "
                f"mfd_samples.parquet gives {want:.6g} for that curve; {RERUN}"
            )


def _dotted_get(node: Any, *keys: str) -> Any:
    for key in keys:
        node = node.get(key) if isinstance(node, dict) else None
    return node


def _close(have: float, want: float, tolerance: float = SCORE_TOLERANCE) -> bool:
    return abs(float(have) - float(want)) <= tolerance * max(1.0, abs(float(want)))


#: The values ``network.json``'s ``row_0`` takes (:meth:`twin.sumo.source.SumoSource.network_info`):
#: the side of the map that row ``j = 0`` of the grid lies on.
ROW_0 = ("north",)


def check_partial(run_dir: Path, run: dict[str, Any], manifest: dict[str, Any]) -> None:
    """``manifest.json`` and ``run.json`` say alike whether the run is partial (both are
    written from the same outcome, :func:`twin.runs.record`)."""
    said, recorded = manifest.get("partial"), run.get("partial")
    if isinstance(said, bool) and isinstance(recorded, bool) and said != recorded:
        raise UserError(
            f"{run_dir / 'manifest.json'}: partial = {str(said).lower()}, but run.json has "
            f"partial = {str(recorded).lower()}; {RERUN}"
        )


def _steps_per_seed(series: pd.DataFrame) -> pd.Series:
    """The steps ``T`` each seed ran (its longest swarm's rows in ``series.parquet``)."""
    counts = series.groupby(["seed", "swarm"]).size()
    return counts.groupby(level="seed").max()


def check_degradation(
    path: Path, frame: pd.DataFrame, swarms: set[str], series: pd.DataFrame
) -> None:
    """``degradation.csv``: one row per seed, swarm and phase, of swarms of ``summary.csv`` and
    seeds with results, each phase's steps ``0 <= start <= stop <= T``."""
    dup = frame.duplicated(["seed", "swarm", "phase"])
    if dup.any():
        r = frame[dup].iloc[0]
        raise UserError(
            f"{path}: the row of seed {r['seed']}, swarm {r['swarm']!r}, phase {r['phase']} "
            f"appears twice; {RERUN}"
        )
    extra = [str(s) for s in frame["swarm"].unique() if str(s) not in swarms]
    if extra:
        raise UserError(f"{path}: swarm {extra[0]!r} has no row in summary.csv; {RERUN}")
    steps = _steps_per_seed(series)
    for n, r in enumerate(frame.itertuples(index=False)):
        seed, start, stop = int(r.seed), int(r.start), int(r.stop)
        if seed not in steps.index:
            raise UserError(
                f"{path}: seed {seed} (row {n}) has no results in series.parquet; {RERUN}"
            )
        if r.phase < 1 or start < 0 or stop < start or stop > int(steps[seed]):
            raise UserError(
                f"{path}: phase {r.phase} (row {n}) runs from start = {start} to stop = {stop}, "
                f"not phase >= 1 and 0 <= start <= stop <= {int(steps[seed])} (the steps seed "
                f"{seed} ran); {RERUN}"
            )
    check_degradation_scores(path, frame, series)


def check_degradation_scores(path: Path, frame: pd.DataFrame, series: pd.DataFrame) -> None:
    """Each row's ``R_hat`` is the mean of its seed's and swarm's rewards over its phase's
    steps in ``series.parquet``, and every swarm of a seed has the same phases (none missing)."""
    rewards = {
        key: group.set_index("step")["reward"].sort_index()
        for key, group in series.groupby(["seed", "swarm"])
    }
    phases: dict[int, dict[str, set]] = {}
    for n, r in enumerate(frame.itertuples(index=False)):
        seed, swarm, start, stop = int(r.seed), str(r.swarm), int(r.start), int(r.stop)
        phases.setdefault(seed, {}).setdefault(swarm, set()).add((int(r.phase), start, stop))
        got = rewards.get((seed, swarm))
        if got is None:
            raise UserError(
                f"{path}: seed {seed}, swarm {swarm!r} (row {n}) has no rewards in "
                f"series.parquet; {RERUN}"
            )
        want = float(got.loc[start : stop - 1].mean()) if stop > start else float("nan")
        have = float(r.R_hat)
        same = (np.isnan(want) and np.isnan(have)) or abs(have - want) <= 1e-6 * max(1.0, abs(want))
        if not same:
            raise UserError(
                f"{path}: R_hat = {have:.6g} for seed {seed}, swarm {swarm!r}, phase {r.phase} "
                f"(row {n}), but its rewards in series.parquet average {want:.6g} over steps "
                f"{start} .. {stop - 1}; {RERUN}"
            )
    for seed, by_swarm in phases.items():
        sets = list(by_swarm.values())
        if any(s != sets[0] for s in sets):
            counts = {swarm: len(s) for swarm, s in by_swarm.items()}
            raise UserError(
                f"{path}: the swarms of seed {seed} have different phases (rows per swarm: "
                f"{counts}); a row is missing or added; {RERUN}"
            )


#: The reference rows of ``belief_models.csv`` besides the swarms (:mod:`twin.belief`).
def _belief_references() -> tuple[str, ...]:
    from twin.belief import DETECTORS_ONLY, NO_DRONES

    return (NO_DRONES, DETECTORS_ONLY)


#: The belief models of ``belief_models.csv`` (:func:`twin.belief.belief_table`).
BELIEF_MODELS = ("history", "nowcast", "nowcast-spatial", "last-seen", "nowcast+detectors")


def check_beliefs(
    path: Path, frame: pd.DataFrame, swarms: set[str], series: pd.DataFrame | None = None
) -> None:
    """``belief_models.csv``: rows of the swarms of ``summary.csv`` and of twin's reference rows
    (the history's row among them), each (swarm, model) once, of twin's models, over at most
    the seeds the run has results of."""
    from twin.belief import NO_DRONES

    models = [str(m) for m in frame["model"].unique() if str(m) not in BELIEF_MODELS]
    if models:
        raise UserError(
            f"{path}: model {models[0]!r} is none of twin's belief models "
            f"({', '.join(BELIEF_MODELS)}); {RERUN}"
        )
    if not ((frame["swarm"] == NO_DRONES) & (frame["model"] == "history")).any():
        raise UserError(
            f"{path}: the row of swarm {NO_DRONES!r}, model 'history' is missing; {RERUN}"
        )
    if series is not None and "n_seeds" in frame.columns:
        seeds = int(series["seed"].nunique())
        n = pd.to_numeric(frame["n_seeds"], errors="coerce")
        bad = ~((n >= 1) & (n <= seeds) & (n == n.round()))
        if bad.any():
            r = frame[bad].iloc[0]
            raise UserError(
                f"{path}: n_seeds = {r['n_seeds']} for swarm {r['swarm']!r}, model "
                f"{r['model']!r}, not a count of 1 .. {seeds} (the seeds with results); {RERUN}"
            )
    known = swarms | set(_belief_references())
    extra = [str(s) for s in frame["swarm"].unique() if str(s) not in known]
    if extra:
        raise UserError(
            f"{path}: swarm {extra[0]!r} has no row in summary.csv (nor is it "
            f"{' or '.join(repr(r) for r in _belief_references())}); {RERUN}"
        )
    dup = frame.duplicated(["swarm", "model"])
    if dup.any():
        r = frame[dup].iloc[0]
        raise UserError(
            f"{path}: the row of swarm {r['swarm']!r}, model {r['model']!r} appears twice; {RERUN}"
        )


def check_belief_scores(
    run_dir: Path, frame: pd.DataFrame, primary: Primary, maps: dict[str, Any] | None
) -> None:
    """What ``belief_models.csv`` must agree with in the folder (its models' maps need the
    history, which the folder does not hold: they are not replayed). Every seed scored every
    row (``n_seeds``); every swarm has the same models, last-seen and nowcast among them; all
    rows count the same events; minutes and rates are steps and counts over ``step_s``; each
    swarm's last-seen ``belief_error`` is its ``belief_error`` of ``summary.csv`` (the same
    belief, :func:`twin.monitoring.belief_error_curve`); with the run's monitoring settings
    the events are ``events.parquet``'s; a run of one seed counts the events, and the ones
    known, of ``belief_maps.npz``."""
    from twin.belief import NO_DRONES
    from twin.monitoring import MonitorSettings
    from twin.runs import step_seconds_of

    path = run_dir / "belief_models.csv"
    seeds = sorted(int(s) for s in primary.series["seed"].unique())
    rows = frame.assign(swarm=frame["swarm"].astype(str), model=frame["model"].astype(str))

    def number(row: Any, column: str) -> float:
        return float(row[column]) if column in row and pd.notna(row[column]) else np.nan

    def say(row: Any, what: str) -> UserError:
        return UserError(f"{path}: swarm {row['swarm']!r}, model {row['model']!r}: {what}; {RERUN}")

    for _, r in rows.iterrows():
        if "n_seeds" in rows.columns and number(r, "n_seeds") != len(seeds):
            raise say(r, f"n_seeds = {r['n_seeds']}, but every row is of all {len(seeds)} seeds")
        for column, top in (("calibration_90", 1.0), ("pct_events_known", 100.0)):
            v = number(r, column)
            if not np.isnan(v) and not 0 <= v <= top:
                raise say(r, f"{column} = {v:.6g} is not a share in 0 .. {top:g}")
        for column in ("belief_error", "events", "latency_median_steps", "false_alarms"):
            v = number(r, column)
            if v < 0:
                raise say(r, f"{column} = {v:.6g} is negative")
    models = {swarm: set(part["model"]) for swarm, part in rows.groupby("swarm")}
    for swarm in primary.swarms:
        have = models.get(swarm, set())
        if not {"last-seen", "nowcast"} <= have or have != models.get(primary.swarms[0]):
            raise UserError(
                f"{path}: swarm {swarm!r} has the models {sorted(have)}, not those of every "
                f"swarm (last-seen and nowcast among them); {RERUN}"
            )
    if "events" in rows.columns and rows["events"].nunique(dropna=False) > 1:
        raise UserError(
            f"{path}: the rows count different events ({sorted(set(rows['events']))[:4]}); "
            f"every model is scored on the same events of the truth; {RERUN}"
        )
    step_s = step_seconds_of(primary.run)
    steps = primary.series.groupby(["seed", "swarm"]).size().groupby(level="seed").max()
    for _, r in rows.iterrows():
        pairs = []
        if step_s:
            pairs.append(("latency_median_min", number(r, "latency_median_steps") * step_s / 60))
        if step_s and steps.nunique() == 1:  # the beliefs' steps: k = 0 .. T
            hours = (float(steps.iloc[0]) + 1) * step_s / 3600.0
            pairs.append(("false_alarms_per_hour", number(r, "false_alarms") / hours))
        for column, want in pairs:
            have = number(r, column)
            if column in rows.columns and not _close_or_nan(have, want):
                raise say(r, f"{column} = {_show(have, want)}, but the row's steps and "
                             f"step_s = {step_s:g} give {_show(want, have)}")  # fmt: skip
    summary = primary.summary
    if summary is not None and "belief_error" in summary.columns:
        errors = summary.set_index(summary["swarm"].astype(str))["belief_error"]
        for _, r in rows[rows["model"] == "last-seen"].iterrows():
            want = float(errors.get(r["swarm"], np.nan))
            have = number(r, "belief_error")
            if not _close_or_nan(have, want):
                raise say(r, f"belief_error = {_show(have, want)}, but summary.csv's "
                             f"belief_error of the swarm (the same last-seen belief) is "
                             f"{_show(want, have)}")  # fmt: skip
    monitoring = primary.run.get("monitoring")
    default = MonitorSettings()
    same = isinstance(monitoring, dict) and all(
        monitoring.get(k) == getattr(default, k) for k in ("threshold", "min_duration")
    )
    if not same or primary.events is None or "events" not in rows.columns or not len(rows):
        return
    found = primary.events.drop_duplicates(["seed", "event"]).groupby("seed").size()
    want = float(np.mean([found.get(s, 0) for s in seeds]))
    have = number(rows.iloc[0], "events")
    if not _close_or_nan(have, want):
        raise UserError(
            f"{path}: events = {have:.6g}, but events.parquet holds {want:.6g} events per seed "
            f"(found on the same truth with the same settings); {RERUN}"
        )
    if maps is None or len(seeds) != 1 or maps["seed"] != seeds[0]:
        return
    onset = np.asarray(maps["event_onset"])
    if len(onset) != have:
        raise UserError(
            f"{run_dir / 'belief_maps.npz'}: {len(onset)} events, but belief_models.csv counts "
            f"{have:.6g} of the run's one seed; {RERUN}"
        )
    known = {("nowcast", s): k for s, k in zip(maps["swarms"], maps["known_at"], strict=False)}
    known[("history", NO_DRONES)] = maps["history_known_at"]
    for _, r in rows.iterrows():
        at = known.get((r["model"], r["swarm"]))
        if at is None:
            continue
        at = np.asarray(at)
        hit = at >= 0
        pct = 100.0 * hit.mean() if len(at) else np.nan
        latency = float(np.median((at - onset)[hit])) if hit.any() else np.nan
        for column, want in (("pct_events_known", pct), ("latency_median_steps", latency)):
            have = number(r, column)
            if column in rows.columns and not _close_or_nan(have, want):
                raise say(r, f"{column} = {_show(have, want)}, but belief_maps.npz's "
                             f"known_at gives {_show(want, have)}")  # fmt: skip


def _close_or_nan(have: float, want: float) -> bool:
    """``have`` is ``want`` within :data:`SCORE_TOLERANCE` (NaN only where NaN is wanted)."""
    if np.isnan(have) or np.isnan(want):
        return bool(np.isnan(have) and np.isnan(want))
    return _close(have, want)


def check_belief_maps(
    path: Path, maps: dict[str, Any], swarms: set[str], series: pd.DataFrame
) -> None:
    """``belief_maps.npz``: a seed with results, swarms of the run, snapshot steps rising
    within the steps it ran, importances in [0, 1], standard deviations >= 0, a threshold in
    (0, 1], and each event on the grid, within those steps, known (if ever) while it lasts."""
    steps = _steps_per_seed(series)
    seed = maps["seed"]
    if seed not in steps.index:
        raise UserError(f"{path}: seed = {seed} has no results in series.parquet; {RERUN}")
    horizon = int(steps[seed])
    extra = [s for s in maps["swarms"] if s not in swarms]
    if extra or len(set(maps["swarms"])) < len(maps["swarms"]):
        what = f"swarm {extra[0]!r} has no row in summary.csv" if extra else "a swarm is twice"
        raise UserError(f"{path}: swarms: {what}; {RERUN}")
    at = np.asarray(maps["steps"])
    if at.size and (at.min() < 0 or at.max() > horizon or (np.diff(at) <= 0).any()):
        raise UserError(
            f"{path}: steps = {at.tolist()[:6]} are not rising steps within 0 .. {horizon} (the "
            f"steps seed {seed} ran); {RERUN}"
        )
    for key in ("truth", "mean"):
        values = np.asarray(maps[key])
        if values.size and (values.min() < 0 or values.max() > 1):
            raise UserError(f"{path}: {key} holds values outside 0 .. 1 (importances); {RERUN}")
    if np.asarray(maps["std"]).size and np.asarray(maps["std"]).min() < 0:
        raise UserError(f"{path}: std holds negative values (standard deviations); {RERUN}")
    if not 0 < maps["threshold"] <= 1:
        raise UserError(f"{path}: threshold = {maps['threshold']}, not in (0, 1]; {RERUN}")
    nx, ny = (int(n) for n in np.asarray(maps["truth"]).shape[1:])
    i, j = np.asarray(maps["event_i"]), np.asarray(maps["event_j"])
    onset, duration = np.asarray(maps["event_onset"]), np.asarray(maps["event_duration"])
    bad = (i < 0) | (i >= nx) | (j < 0) | (j >= ny) | (onset < 0) | (duration < 1)
    bad |= onset + duration - 1 > horizon
    if bad.any():
        e = int(np.flatnonzero(bad)[0])
        raise UserError(
            f"{path}: event {e} on cell ({i[e]}, {j[e]}), onset {onset[e]}, duration "
            f"{duration[e]}: not on the {nx} x {ny} grid within steps 0 .. {horizon}; {RERUN}"
        )
    for key in ("known_at", "history_known_at"):
        known = np.asarray(maps[key])
        inside = (known >= onset) & (known < onset + duration)
        if (~((known == -1) | inside)).any():
            raise UserError(
                f"{path}: {key} names a step outside its event's span (and not -1: never); {RERUN}"
            )


def check_events(
    path: Path, frame: pd.DataFrame, shape: tuple[int, int], series: pd.DataFrame
) -> None:
    """``events.parquet``: every event on a cell of the grid, between steps 0 and the ``T``
    its seed ran (onset, last step), at least one step long."""
    nx, ny = shape
    off = off_grid(frame, shape)
    if off.any():
        r = frame[off].iloc[0]
        raise UserError(
            f"{path}: event {r['event']} of seed {r['seed']} is on cell ({r['i']}, {r['j']}), "
            f"off the {nx} x {ny} grid; {RERUN}"
        )
    steps = _steps_per_seed(series)
    for r in frame.itertuples(index=False):
        seed, onset, duration = int(r.seed), int(r.onset), int(r.duration)
        horizon = int(steps.get(seed, -1))
        if horizon < 0:
            raise UserError(
                f"{path}: event {r.event} is of seed {seed}, which has no results in "
                f"series.parquet; {RERUN}"
            )
        if onset < 0 or duration < 1 or onset + duration - 1 > horizon:
            raise UserError(
                f"{path}: event {r.event} of seed {seed} has onset = {onset}, duration = "
                f"{duration}, not within steps 0 .. {horizon} (the steps the seed ran); {RERUN}"
            )


#: Columns of ``monitoring.csv`` that are NaN for a swarm with no event to see
#: (:meth:`twin.monitoring.Monitoring.table`).
EVENT_SHARES = ("pct_events_seen", "pct_congested_observed")


def check_monitoring(path: Path, frame: pd.DataFrame) -> None:
    """``monitoring.csv``: a row with no event has no share of events seen (NaN, or 0)."""
    if "events" not in frame.columns:
        return
    none = frame["events"].to_numpy(dtype=np.float64) == 0
    for name in EVENT_SHARES:
        if name not in frame.columns:
            continue
        values = frame[name].to_numpy(dtype=np.float64)
        off = none & np.isfinite(values) & (values != 0)
        if off.any():
            n = int(np.flatnonzero(off)[0])
            raise UserError(
                f"{path}: column {name!r} of swarm {frame['swarm'].iloc[n]!r} (row {n}) is "
                f"{values[n]:.6g}, but the row has 0 events; {RERUN}"
            )
