"""The belief models of a run folder replayed on read-back: ``belief_models.csv`` and
``belief_maps.npz`` (:mod:`twin.belief`) computed again from the run's trajectories, its maps
(``importance.npz``, its tapes replayed), its detectors' readings and the history it was
scored with (run.json ``history``: the file and its sha256). A history that is gone or changed,
a seed whose maps the folder does not hold, or a truth other than the observed maps: the models
are not replayed, and a notice says why (their ranges and relations are checked by
:func:`twin.report.load.check_belief_scores` all the same)."""

from __future__ import annotations

import json
from pathlib import Path
from types import SimpleNamespace
from typing import Any

import numpy as np
import pandas as pd

from twin.errors import UserError
from twin.grid import Grid
from twin.readback import RERUN
from twin.report.derived import (
    OBSERVED_TRUTH,
    SLACK,
    Primary,
    _maps_by_seed,
    _show,
    compare,
    fault_plan,
    folder_format,
)

#: How far a replayed belief figure may lie from the run's (relative, at least absolute): the
#: Kalman filter's sums over the same float32 maps, in the same order.
BELIEF_TOLERANCE = 1e-6


def replayable_history(primary: Primary):
    """The :class:`twin.belief.History` run.json's ``history`` names, when the file is there
    with its recorded sha256; else None and the reason, in words."""
    from twin.belief import History
    from twin.files import file_sha256

    record = primary.run.get("history")
    if not isinstance(record, dict) or not all(
        isinstance(record.get(k), str) for k in ("path", "sha256")
    ):
        if folder_format(primary) >= 4:  # every twin of format 4 records it
            raise UserError(
                f"{primary.run_dir / 'run.json'}: history = {json.dumps(record)[:60]} names no "
                f"history file and its sha256, which a run with belief models records; {RERUN}"
            )
        return None, "run.json records no history file (an earlier twin's run)"
    path = Path(record["path"])
    if not path.is_absolute():  # twin records it resolved
        raise UserError(
            f"{primary.run_dir / 'run.json'}: history.path = {record['path'][:60]!r} is not an "
            f"absolute path, as twin records it; {RERUN}"
        )
    try:
        same = path.is_file() and file_sha256(path) == record.get("sha256")
    except OSError:
        same = False
    if not same:
        return None, f"the history {path} is gone or changed since the run"
    return History.load(path), None


def _sighting(primary: Primary, seed: int):
    """The drones' sighting model of ``seed`` (:meth:`twin.traffic.base.TrafficSource.
    sighting_model`): exact on synthetic maps; a live run's, or a run's on a tape, that of its
    tape as the read-back replayed it (None: the tape was not replayed)."""
    from twin.belief import EXACT_SIGHTINGS

    traffic = primary.run.get("traffic")
    kind = traffic.get("kind") if isinstance(traffic, dict) else None
    if kind in ("synthetic", "dynamic"):
        return EXACT_SIGHTINGS
    return primary.tape_sightings.get(seed) if kind in ("sumo", "tape") else None


def _detectors(readings: pd.DataFrame | None, seed: int, horizon: int, ny: int):
    """The fixed detectors' observations of ``seed`` (``detectors.parquet``'s ``readings``),
    None without."""
    from twin.belief import DetectorObservations

    if readings is None:
        return None
    rows = readings[readings["seed"] == seed]
    readings = zip(rows["step"], rows["i"] * ny + rows["j"], rows["importance"], strict=True)
    return DetectorObservations.from_readings(readings, horizon)


def _results(primary: Primary) -> tuple[list[Any] | None, str | None]:
    """Each seed's result as :func:`twin.belief.belief_table` reads it, or None and why not."""
    monitoring = primary.run.get("monitoring")
    if not isinstance(monitoring, dict) or monitoring.get("truth") != OBSERVED_TRUTH:
        return None, "the run scored them against a truth the folder does not keep"
    from twin.readback import read_table

    maps, grid = _maps_by_seed(primary), Grid(primary.obstacles)
    plan = fault_plan(primary)
    path = primary.run_dir / "detectors.parquet"
    readings = read_table(path) if path.is_file() else None
    results = []
    for seed in sorted(int(s) for s in primary.series["seed"].unique()):
        if seed not in maps:
            return None, f"the folder does not hold seed {seed}'s maps"
        sighting = _sighting(primary, seed)
        if sighting is None:
            return None, f"seed {seed}'s sightings are not known (its tape was not replayed)"
        positions = np.stack([primary.positions(seed, s) for s in primary.swarms])
        extra: dict[str, Any] = {"sighting": sighting}
        detectors = _detectors(readings, seed, positions.shape[1] - 1, grid.ny)
        if detectors is not None:
            extra["detectors"] = detectors
        results.append(
            SimpleNamespace(
                seed=seed,
                swarms=list(primary.swarms),
                grid=grid,
                positions=positions,
                importance=np.asarray(maps[seed], dtype=np.float32)[: positions.shape[1]],
                truth=None,
                faults=plan,
                extra=extra,
            )
        )
    return results, None


def check_belief_replay(
    primary: Primary, frame: pd.DataFrame, maps: dict[str, Any] | None
) -> str | None:
    """``belief_models.csv`` (and ``belief_maps.npz``, the first seed's) equal the models
    replayed with the run's history (:func:`twin.belief.run_beliefs`, :func:`twin.belief.
    belief_maps`); a differing figure is a :class:`UserError` line. Returns why they were not
    replayed (None: replayed)."""
    from twin.belief import belief_maps, run_beliefs
    from twin.runs import step_seconds_of

    history, why = replayable_history(primary)
    if history is None:
        return why
    results, why = _results(primary)
    if results is None:
        return why
    expected = run_beliefs(results, history, step_seconds_of(primary.run))
    source = "the models replayed with the run's history"
    frame = frame.assign(swarm=frame["swarm"].astype(str), model=frame["model"].astype(str))
    _compare(primary.run_dir, frame, expected, source)
    if maps is not None and maps["seed"] == results[0].seed:
        _compare_maps(primary.run_dir / "belief_maps.npz", maps, belief_maps(results[0], history))
    return None


def _compare(run_dir: Path, frame: pd.DataFrame, expected: pd.DataFrame, source: str) -> None:
    """:func:`twin.report.derived.compare` by (swarm, model), within :data:`BELIEF_TOLERANCE`."""
    slack = {
        c + SLACK: BELIEF_TOLERANCE * np.maximum(1.0, np.abs(expected[c].to_numpy(float)))
        for c in expected.columns
        if c not in ("swarm", "model") and pd.api.types.is_numeric_dtype(expected[c])
    }
    compare(run_dir, "belief_models.csv", frame, expected.assign(**slack), ("swarm", "model"),
            source, complete=True)  # fmt: skip


def _compare_maps(path: Path, have: dict[str, Any], want: dict[str, Any]) -> None:
    """Every array of ``belief_maps.npz`` as replayed (importances within
    :data:`BELIEF_TOLERANCE`, steps, events and the steps they were known exactly)."""
    for key, value in want.items():
        if key == "swarms":
            continue
        mine, theirs = np.asarray(have.get(key)), np.asarray(value)
        if mine.shape != theirs.shape:
            raise UserError(
                f"{path}: {key} has the shape {mine.shape}, but the nowcast replayed with the "
                f"run's history gives {theirs.shape}; {RERUN}"
            )
        if theirs.dtype.kind == "f":
            off = ~np.isclose(mine, theirs, rtol=BELIEF_TOLERANCE, atol=BELIEF_TOLERANCE)
        else:
            off = mine != theirs
        if np.any(off):
            at = tuple(int(x) for x in np.argwhere(off)[0])
            raise UserError(
                f"{path}: {key}{list(at)} = {_show(mine[at], theirs[at])}, but the nowcast "
                f"replayed with the run's history gives {_show(theirs[at], mine[at])}; {RERUN}"
            )
