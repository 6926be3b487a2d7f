"""A run folder's derived files checked against its primary files before a report shows them.

``twin run`` and ``twin evaluate`` compute ``per_seed.csv`` from what ``series.parquet``,
``trajectories.parquet`` and ``events.parquet`` record, ``summary.csv`` from ``per_seed.csv``,
``monitoring.csv`` from ``summary.csv``. :data:`DERIVED` lists, for each derived file, the
columns that its sources determine and how they are recomputed, with the functions that computed
them at run time (:func:`twin.metrics.series_columns`, :func:`twin.monitoring.ceiling_coverage`,
:class:`twin.monitoring.RunMonitoring`, :func:`twin.metrics.aggregate`). A value further than
:data:`TOLERANCE` from its recomputation is one :class:`UserError` line naming both files, the
column, the swarm and the seed: the report never shows a figure its run's files contradict.

Not recomputed (their inputs are not all in the folder): the reward split and the paper's
accounting (``R_hat_T_importance``, ``R_hat_T_idleness``, ``R_hat_T_paper``: the importance maps
of seeds other than the first are not kept; the split is checked to add up to ``R_hat_T``), the
ceiling rows (:mod:`twin.ceilings`) and the incident columns.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

from twin.errors import UserError
from twin.grid import Grid
from twin.metrics import aggregate, is_ceiling_row, series_columns
from twin.monitoring import (
    EVENT_COLUMNS,
    RunMonitoring,
    ceiling_coverage,
    event_sightings,
    sightings,
)
from twin.readback import RERUN
from twin.scores import ScoreParams

#: How far a derived figure may lie from its recomputation (relative, at least absolute):
#: float rounding of the same sums done in the same order, and the CSV round trip.
TOLERANCE = 1e-9


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

    def positions(self, seed: int, swarm: str) -> np.ndarray:
        """``(T+1, N, 2)`` drone cells of one swarm and seed."""
        t = self.trajectories
        rows = t[(t["seed"] == seed) & (t["swarm"].astype(str) == swarm)]
        if rows.empty:
            raise UserError(
                f"{self.run_dir / 'trajectories.parquet'}: no rows for swarm {swarm!r}, seed "
                f"{seed}, which series.parquet holds; {RERUN}"
            )
        rows = rows.sort_values(["step", "drone"])
        n_drones = int(rows["drone"].max()) + 1
        return rows[["i", "j"]].to_numpy(np.int64).reshape(-1, n_drones, 2)

    def params(self) -> ScoreParams | None:
        from twin.runs import score_params_of

        return score_params_of(self.run)


@dataclass(frozen=True)
class Derivation:
    """Columns of ``file`` that ``source`` determines: ``recompute(primary, frame)`` gives
    them for the rows of ``key``, ``frame`` being the derived file's own table."""

    file: str
    source: str
    key: tuple[str, ...]
    recompute: Callable[[Primary, pd.DataFrame], pd.DataFrame]


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
    ``series.parquet``."""
    from twin.faults import FaultPlan

    grid = Grid(primary.obstacles)
    events = seed_events(primary, seed)
    plan = FaultPlan.from_record(primary.run.get("faults"))
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


def reward_split(primary: Primary, frame: pd.DataFrame) -> pd.DataFrame:
    """``R_hat_T`` as the sum of its parts ``R_hat_T_importance + R_hat_T_idleness``."""
    if not {"R_hat_T_importance", "R_hat_T_idleness"} <= set(frame.columns):
        return frame.iloc[:0][[c for c in frame.columns if c in ("seed", "swarm")]]
    rows = frame[~is_ceiling_row(frame)]
    keys = [c for c in ("seed", "swarm") if c in frame.columns]
    return rows[keys].assign(R_hat_T=rows["R_hat_T_importance"] + rows["R_hat_T_idleness"])


def seed_aggregate(primary: Primary, frame: pd.DataFrame) -> pd.DataFrame:
    """``summary.csv`` as :func:`twin.metrics.aggregate` makes it of ``per_seed.csv``."""
    return aggregate(primary.per_seed)


def summary_columns(primary: Primary, frame: pd.DataFrame) -> pd.DataFrame:
    """``monitoring.csv``: the monitoring columns of ``summary.csv``'s swarms, as they are
    there."""
    return primary.summary[~is_ceiling_row(primary.summary)]


#: Each derived file's columns that other files of the run determine, in the order checked:
#: a file is checked against its sources before it serves as one.
DERIVED: tuple[Derivation, ...] = (
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
    Derivation("per_seed.csv", "its reward split", ("seed", "swarm"), reward_split),
    Derivation("summary.csv", "per_seed.csv", ("swarm",), seed_aggregate),
    Derivation("summary.csv", "its reward split", ("swarm",), reward_split),
    Derivation("monitoring.csv", "summary.csv", ("swarm",), summary_columns),
)


def check_derived(primary: Primary, tables: dict[str, pd.DataFrame | None]) -> None:
    """Every derived file of ``tables`` (name -> its table, None when absent) agrees with what
    its sources give (:data:`DERIVED`). Without ``per_seed.csv``, ``summary.csv`` is checked
    against the per-seed figures the primary files give."""
    per_seed = tables.get("per_seed.csv")
    if per_seed is None:  # summary.csv is then checked against the primary files themselves
        parts = [d.recompute(primary, pd.DataFrame()) for d in DERIVED[1:4]]
        per_seed = parts[0]
        for part in parts[1:]:
            if len(part):
                per_seed = per_seed.merge(part, on=["seed", "swarm"], how="left")
        per_seed = per_seed[per_seed["swarm"].isin(primary.swarms)]
    primary.per_seed, primary.summary = per_seed, tables.get("summary.csv")
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
        compare(primary.run_dir, d.file, frame, d.recompute(primary, frame), d.key, source)


def compare(
    run_dir: Path,
    name: str,
    frame: pd.DataFrame,
    expected: pd.DataFrame,
    key: tuple[str, ...],
    source: str,
) -> None:
    """Each row of ``expected`` (by ``key``) is in ``frame`` with the same value in every column
    both hold, within :data:`TOLERANCE`; NaN only where NaN is expected."""
    path = run_dir / name
    key = tuple(k for k in key if k in expected.columns)
    if not len(expected) or not all(k in frame.columns for k in key):
        return
    columns = [c for c in expected.columns if c in frame.columns and c not in key]
    mine = _keyed(frame, key)
    theirs = _keyed(expected, key)
    for at, row in theirs.iterrows():
        who = _who(key, at)
        if at not in mine.index:
            raise UserError(f"{path}: no row for {who}, which {source} holds; {RERUN}")
        got = mine.loc[at]
        for column in columns:
            want, have = row[column], got[column]
            if _same(have, want):
                continue
            raise UserError(
                f"{path}: {column} = {_show(have)} for {who}, but {source} "
                f"{'give' if ' and ' in source else 'gives'} "
                f"{_show(want)}; {RERUN}"
            )


def _keyed(frame: pd.DataFrame, key: tuple[str, ...]) -> pd.DataFrame:
    frame = frame.copy()
    for k in key:
        frame[k] = frame[k].astype(str) if k == "swarm" else frame[k].astype(np.int64)
    return frame.drop_duplicates(list(key)).set_index(list(key))


def _who(key: tuple[str, ...], at: Any) -> str:
    values = at if isinstance(at, tuple) else (at,)
    parts = [f"{k} {v!r}" if k == "swarm" else f"{k} {v}" for k, v in zip(key, values, strict=True)]
    return ", ".join(parts)


def _same(have: Any, want: Any) -> bool:
    if isinstance(want, (bool, np.bool_)) or isinstance(have, (bool, np.bool_)):
        return bool(have) == bool(want)
    try:
        h, w = float(have), float(want)
    except (TypeError, ValueError):
        return str(have) == str(want)
    if np.isnan(w) or np.isnan(h):
        return bool(np.isnan(w) and np.isnan(h))
    return abs(h - w) <= TOLERANCE * max(1.0, abs(w))


def _show(value: Any) -> str:
    if isinstance(value, (bool, np.bool_)):
        return str(bool(value)).lower()
    try:
        return f"{float(value):.6g}"
    except (TypeError, ValueError):
        return repr(value)
