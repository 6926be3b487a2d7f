"""The traffic tape: per-cell counts and speeds of a SUMO run, replayed without SUMO.

``tape.parquet`` has one row per cell and snapshot: ``step`` (negative during the warm-up,
``k`` for ``T^k``), ``time_s``, ``i``, ``j``, ``count`` (vehicles in the cell), ``speed`` (their
space-mean speed, m/s, NaN when empty). The file's metadata (key ``twin_tape``) holds what the
replay needs besides: obstacles, lane-km and speed limit per cell, the horizon and the MFD
observation settings. :class:`TapeTraffic` feeds the snapshots through the same
:class:`twin.mfd.MFDImportance` as the live source, so a replay gives the live run's ``T^k``.
"""

from __future__ import annotations

import json
import math
from collections.abc import Callable, Generator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from twin.clock import clock_label, clock_seconds
from twin.errors import UserError
from twin.files import not_a_file
from twin.grid import Grid
from twin.mfd import MFD, SETTING_RANGES, MFDImportance
from twin.notices import notify
from twin.seeds import MAX_SEED, is_seed
from twin.traffic.base import TrafficSource

TAPE_VERSION = 1
_META_KEY = b"twin_tape"


@dataclass
class Tape:
    steps: np.ndarray  # (S,) int
    times: np.ndarray  # (S,) float, s since midnight
    counts: np.ndarray  # (S, nx, ny) int
    speeds: np.ndarray  # (S, nx, ny) float, NaN where empty
    obstacles: np.ndarray  # (nx, ny) bool
    lane_km: np.ndarray  # (nx, ny)
    speed_limit: np.ndarray  # (nx, ny) m/s
    horizon: int
    settings: dict[str, Any] = field(default_factory=dict)  # mfd_fit, detection_p, seed, ...

    @classmethod
    def from_source(cls, source) -> Tape:
        """The tape of a :class:`twin.sumo.source.SumoTraffic` (what it has read so far)."""
        snaps = source.snapshots
        g = source.geometry
        nx, ny = source.grid.shape
        return cls(
            steps=np.array([s[0] for s in snaps], dtype=np.int64),
            times=np.array([s[1] for s in snaps], dtype=float),
            counts=np.array([s[2] for s in snaps], dtype=np.int32).reshape(-1, nx, ny),
            speeds=np.array([s[3] for s in snaps], dtype=np.float32).reshape(-1, nx, ny),
            obstacles=source.grid.obstacles.copy(),
            lane_km=g.lane_km.copy(),
            speed_limit=g.speed_limit.copy(),
            horizon=source.horizon,
            settings={**source.metadata(), "network": source.network_info()},
        )

    def frame(self):
        import pandas as pd

        s, nx, ny = self.counts.shape
        i, j = np.indices((nx, ny)).reshape(2, -1)
        return pd.DataFrame(
            {
                "step": np.repeat(self.steps, nx * ny),
                "time_s": np.repeat(self.times, nx * ny),
                "i": np.tile(i, s),
                "j": np.tile(j, s),
                "count": self.counts.reshape(-1),
                "speed": self.speeds.reshape(-1),
            }
        )

    def write(self, path: Path, chunk: int = 64) -> None:
        """Write the long table ``chunk`` snapshots at a time (one row group each), so that a
        city-scale tape never sits in memory as one table."""
        import pyarrow as pa
        import pyarrow.parquet as pq

        meta = {
            "version": TAPE_VERSION,
            "nx": int(self.obstacles.shape[0]),
            "ny": int(self.obstacles.shape[1]),
            "horizon": int(self.horizon),
            "obstacles": self.obstacles.astype(int).tolist(),
            "lane_km": self.lane_km.tolist(),  # exact: JSON keeps float64
            "speed_limit": self.speed_limit.tolist(),
            "settings": self.settings,
        }
        schema = pa.schema(
            [
                ("step", pa.int64()),
                ("time_s", pa.float64()),
                ("i", pa.int64()),
                ("j", pa.int64()),
                ("count", pa.int32()),
                ("speed", pa.float32()),
            ],
            metadata={_META_KEY: json.dumps(meta).encode()},
        )
        s, nx, ny = self.counts.shape
        i, j = np.indices((nx, ny)).reshape(2, -1)
        with pq.ParquetWriter(path, schema) as writer:
            for a in range(0, max(s, 1), chunk):
                b = min(a + chunk, s)
                n = b - a
                columns = [
                    np.repeat(self.steps[a:b].astype(np.int64), nx * ny),
                    np.repeat(self.times[a:b].astype(np.float64), nx * ny),
                    np.tile(i, n),
                    np.tile(j, n),
                    self.counts[a:b].reshape(-1).astype(np.int32, copy=False),
                    self.speeds[a:b].reshape(-1).astype(np.float32, copy=False),
                ]
                writer.write_table(pa.Table.from_arrays(columns, schema=schema))

    @classmethod
    def read(cls, path: Path, shape: tuple[int, int] | None = None) -> Tape:
        """Read and check a tape; every problem is a one-line :class:`UserError` naming the
        file, the column or step, the bad value and the fix. ``shape`` (a config's explicit
        ``[grid] nx, ny``) must match the tape's grid when given."""
        import pyarrow.parquet as pq

        path = Path(path)
        why = not_a_file(path)
        if why == "does not exist":
            raise UserError(f"{path}: no such traffic tape; pass the tape.parquet of a `twin run`")
        if why is not None:
            raise UserError(f"{path}: {why} (a traffic tape: the tape.parquet of a `twin run`)")
        try:
            table = pq.read_table(path)
            df = table.to_pandas()
        except Exception as exc:  # pyarrow raises several types on a broken file
            raise UserError(
                f"{path}: not a parquet file or truncated ({type(exc).__name__}); "
                "pass the tape.parquet of a finished `twin run`"
            ) from exc
        meta = _tape_meta(path, table.schema.metadata or {})
        nx, ny = meta["nx"], meta["ny"]
        if shape is not None and tuple(shape) != (nx, ny):
            raise UserError(
                f"{path}: grid {nx} x {ny} differs from the config's [grid] nx, ny = "
                f"{shape[0]} x {shape[1]}; record the tape with this config or drop [grid] nx, ny"
            )
        _check_columns(path, df)
        if df.empty:
            raise UserError(f"{path}: no rows; the run that wrote it recorded no step")
        for col, hi in (("i", nx), ("j", ny)):
            values = df[col].to_numpy()
            bad = (values < 0) | (values >= hi)
            if bad.any():
                raise UserError(
                    f"{path}: column {col} = {int(values[bad][0])} is off the {nx} x {ny} grid "
                    "of the tape's metadata; the tape is corrupt, record it again"
                )
        steps = np.unique(df["step"].to_numpy())
        gaps = np.flatnonzero(np.diff(steps) != 1)
        if len(gaps):
            raise UserError(
                f"{path}: step {int(steps[gaps[0]]) + 1} missing (steps {int(steps[0])}.."
                f"{int(steps[-1])} must be contiguous); the tape is incomplete, record it again"
            )
        if int(steps.max()) < 0:
            raise UserError(f"{path}: only warm-up steps (< 0); no step k >= 0 to replay")
        dup = df.duplicated(["step", "i", "j"])
        if dup.any():
            row = df[dup].iloc[0]
            raise UserError(
                f"{path}: step {int(row['step'])} has cell ({int(row['i'])}, {int(row['j'])}) "
                "twice; the tape is corrupt, record it again"
            )
        if len(df) != len(steps) * nx * ny:
            counts = df.groupby("step").size()
            short = counts[counts != nx * ny]
            raise UserError(
                f"{path}: step {int(short.index[0])} has {int(short.iloc[0])} rows, not the "
                f"{nx * ny} cells of the {nx} x {ny} grid; the tape is corrupt, record it again"
            )
        df = df.sort_values(["step", "i", "j"])
        times = df["time_s"].to_numpy(dtype=float).reshape(-1, nx, ny)
        counts = df["count"].to_numpy().reshape(-1, nx, ny)
        speeds = df["speed"].to_numpy(dtype=float).reshape(-1, nx, ny)
        _check_values(path, steps, times, counts, speeds)
        times = times[:, 0, 0]
        _check_against_meta(path, steps, times, counts, meta)
        return cls(
            steps=steps.astype(np.int64),
            times=times,
            counts=counts,
            speeds=speeds,
            obstacles=meta["obstacles"],
            lane_km=meta["lane_km"],
            speed_limit=meta["speed_limit"],
            horizon=meta["horizon"],
            settings=meta["settings"],
        )


#: Columns of tape.parquet and the kind of number each holds ("i": integer, "f": real).
TAPE_COLUMNS = {"step": "i", "time_s": "f", "i": "i", "j": "i", "count": "i", "speed": "f"}


def _check_columns(path: Path, df) -> None:
    missing = [c for c in TAPE_COLUMNS if c not in df.columns]
    if missing:
        raise UserError(
            f"{path}: column {missing[0]} missing (has {', '.join(map(str, df.columns))}); "
            f"a tape has {', '.join(TAPE_COLUMNS)}"
        )
    for col, kind in TAPE_COLUMNS.items():
        dtype = df[col].dtype
        ok = dtype.kind in "iu" if kind == "i" else dtype.kind in "iuf"
        if not ok:
            what = "whole numbers" if kind == "i" else "numbers"
            raise UserError(
                f"{path}: column {col} has type {dtype}, not {what}; the tape is corrupt, "
                "record it again"
            )


def _check_values(path: Path, steps, times, counts, speeds) -> None:
    """Finite non-negative counts, one finite time per step (``times``: per step and cell),
    speeds finite and >= 0 where vehicles are."""

    def fail(col: str, idx: tuple, value, problem: str) -> None:
        s, *cell = idx
        where = f"step {int(steps[s])}" + (f", cell ({cell[0]}, {cell[1]})" if cell else "")
        raise UserError(
            f"{path}: column {col} = {value} at {where} {problem}; the tape is corrupt, "
            "record it again"
        )

    bad = ~np.isfinite(times)
    if bad.any():
        idx = tuple(int(x) for x in np.argwhere(bad)[0])
        fail("time_s", idx, times[idx], "is not finite")
    bad = times != times[:, :1, :1]  # one time per step, in every cell's row
    if bad.any():
        idx = tuple(int(x) for x in np.argwhere(bad)[0])
        fail("time_s", idx, times[idx], f"differs from the step's time {times[idx[0], 0, 0]}")
    bad = counts < 0
    if bad.any():
        idx = tuple(int(x) for x in np.argwhere(bad)[0])
        fail("count", idx, int(counts[idx]), "is negative")
    occupied = counts > 0
    bad = (occupied & ~np.isfinite(speeds)) | np.isinf(speeds) | (speeds < 0)
    bad |= speeds > MAX_SPEED
    if bad.any():
        idx = tuple(int(x) for x in np.argwhere(bad)[0])
        problem = (
            "is negative" if speeds[idx] < 0
            else f"is faster than any road vehicle (over {MAX_SPEED:g} m/s)"
            if speeds[idx] > MAX_SPEED else "is not finite where vehicles are"
        )  # fmt: skip
        fail("speed", idx, speeds[idx], problem)


#: The fastest a tape's speeds and speed limits may be (m/s, 3600 km/h): faster than any
#: vehicle SUMO drives on a road or rail; more is a corrupt value.
MAX_SPEED = 1000.0


#: The most vehicles per lane-km a tape's cell may hold at one instant: a car every metre,
#: about seven times a jam's density (some 140 veh/lane-km); more is a corrupt count.
MAX_DENSITY = 1000.0
#: The lane length (km) a cell counts as at least in that cap: a cell of little lane (a few
#: metres of a lane, vehicles on a junction) may still hold up to 100 vehicles.
MIN_CAP_LANE_KM = 0.1


def _check_against_meta(path: Path, steps, times, counts, meta: dict[str, Any]) -> None:
    """What the rows must agree with besides their types: times that increase step by step
    (by the metadata's ``step_s`` when it has one, step 0 at its ``begin``), no step after the
    metadata's horizon (nor, given ``warmup_s``, before its warm-up), ``read_offsets_s`` those
    of its ``reads_per_step`` (:func:`read_offsets`), counts a lane can hold
    (:data:`MAX_DENSITY`)."""
    fix = "the tape is corrupt, record it again"
    back = np.flatnonzero(np.diff(times) <= 0)
    if len(back):
        s = int(back[0])
        raise UserError(
            f"{path}: column time_s goes from {times[s]} at step {int(steps[s])} to "
            f"{times[s + 1]} at step {int(steps[s + 1])}, not forward; {fix}"
        )
    horizon = meta["horizon"]
    if int(steps[-1]) > horizon:
        raise UserError(
            f"{path}: steps go to {int(steps[-1])}, past the metadata's horizon = {horizon}; {fix}"
        )
    settings = meta["settings"]
    step_s, warmup_s = (_positive(settings.get(k)) for k in ("step_s", "warmup_s"))
    if step_s is not None:
        off = np.flatnonzero(np.abs(np.diff(times) - step_s) > 0.01)
        if len(off):
            s = int(off[0])
            raise UserError(
                f"{path}: column time_s advances {times[s + 1] - times[s]:g} s from step "
                f"{int(steps[s])} to {int(steps[s + 1])}, the metadata's step_s = {step_s:g}; "
                f"{fix}"
            )
        if warmup_s is not None and int(steps[0]) < -int(warmup_s / step_s + 1e-9):
            raise UserError(
                f"{path}: steps start at {int(steps[0])}, before the metadata's warm-up of "
                f"{int(warmup_s / step_s + 1e-9)} steps (warmup_s = {warmup_s:g}, step_s = "
                f"{step_s:g}); {fix}"
            )
    begin = settings.get("begin")
    if step_s is not None and isinstance(begin, str):
        t0 = clock_seconds(begin)
        if t0 is None:
            raise UserError(f"{path}: metadata begin = {begin[:40]!r} is not a clock time; {fix}")
        want = t0 + steps * step_s
        off = np.flatnonzero(np.abs(times - want) > 0.01)
        if len(off):
            s = int(off[0])
            raise UserError(
                f"{path}: column time_s = {times[s]:g} at step {int(steps[s])}, but the "
                f"metadata's begin = {begin} (step 0) and step_s = {step_s:g} put it at "
                f"{want[s]:g}; {fix}"
            )
    reads = settings.get("reads_per_step", 1)
    reads = reads if isinstance(reads, int) and not isinstance(reads, bool) and reads >= 1 else 1
    offsets = settings.get("read_offsets_s")
    if step_s is not None and isinstance(offsets, list) and "reads_per_step" in settings:
        want = read_offsets(step_s, reads)
        numbers = all(isinstance(o, (int, float)) and not isinstance(o, bool) for o in offsets)
        if not (numbers and len(offsets) == len(want) and np.allclose(offsets, want, atol=0.01)):
            raise UserError(
                f"{path}: metadata read_offsets_s = {str(offsets)[:60]}, but reads_per_step = "
                f"{reads} reads in a step of {step_s:g} s are at "
                f"{want} s before its end; {fix}"
            )
    cap = MAX_DENSITY * reads * np.maximum(meta["lane_km"], MIN_CAP_LANE_KM)
    over = counts > cap
    if over.any():
        s, i, j = (int(x) for x in np.argwhere(over)[0])
        raise UserError(
            f"{path}: column count = {int(counts[s, i, j])} at step {int(steps[s])}, cell "
            f"({i}, {j}) is more vehicles than its {meta['lane_km'][i, j]:.3g} lane-km hold "
            f"(at most {cap[i, j]:.0f}: {MAX_DENSITY:.0f} per lane-km"
            + (f" x {reads} reads" if reads > 1 else "")
            + f"); {fix}"
        )


def distinct_reads(step_s: float, reads: int) -> int:
    """The most reads, up to ``reads``, whose :func:`read_offsets` in a step of ``step_s``
    fall on distinct SUMO steps (a step of 2 s holds two)."""
    for n in range(reads, 1, -1):
        if len(set(read_offsets(step_s, n))) == n:
            return n
    return 1


def read_offsets(step_s: float, reads: int) -> list[float]:
    """Seconds before a step's sample time of its ``reads`` read instants, evenly spread over
    the step in whole SUMO steps, the last at the sample time."""
    return [float(round(step_s * (reads - 1 - m) / reads)) for m in range(reads)]


def _positive(value: Any) -> float | None:
    """``value`` as a finite number > 0, else None (a setting left out or of no use)."""
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        return None
    value = float(value)
    return value if np.isfinite(value) and value > 0 else None


def tape_footer(path: str | Path) -> dict[str, Any] | None:
    """The tape's metadata as written, unchecked, or None when it does not read: for a cheap
    look (a memory estimate, a provenance record, a tape's settings) whose caller leaves the
    refusal of a damaged tape to :func:`read_tape_meta` or the reader of its rows."""
    import pyarrow.parquet as pq

    try:
        meta = json.loads((pq.read_schema(path).metadata or {})[_META_KEY])
    except Exception:  # pyarrow, json and a missing key raise several types on a broken file
        return None
    return meta if isinstance(meta, dict) else None


def read_tape_meta(path: Path) -> dict[str, Any]:
    """The metadata of the tape at ``path``, checked, without reading its rows."""
    import pyarrow.parquet as pq

    try:
        schema = pq.read_schema(path)
    except Exception as exc:  # pyarrow raises several types on a broken file
        raise UserError(
            f"{path}: not a parquet file or truncated ({type(exc).__name__}); "
            "pass the tape.parquet of a finished `twin run`"
        ) from None
    return _tape_meta(path, schema.metadata or {})


def _tape_meta(path: Path, schema_meta: dict) -> dict[str, Any]:
    """The tape's metadata, checked: version, grid, per-cell maps and horizon."""
    raw = schema_meta.get(_META_KEY)
    if raw is None:
        raise UserError(
            f"{path}: not a twin traffic tape (no {_META_KEY.decode()} metadata); "
            "pass the tape.parquet of a `twin run`"
        )
    try:
        meta = json.loads(raw)
    except (json.JSONDecodeError, UnicodeDecodeError) as exc:
        raise UserError(f"{path}: tape metadata is not valid JSON; record the tape again") from exc
    if not isinstance(meta, dict):
        raise UserError(f"{path}: tape metadata is not a table; record the tape again")
    if meta.get("version") != TAPE_VERSION:
        raise UserError(
            f"{path}: tape version = {meta.get('version')!r}, expected {TAPE_VERSION}; "
            "record the tape again with this twin"
        )
    out: dict[str, Any] = {}
    for key, low in (("nx", 1), ("ny", 1), ("horizon", 1)):
        value = meta.get(key)
        if not isinstance(value, int) or isinstance(value, bool) or value < low:
            raise UserError(
                f"{path}: tape metadata {key} = {value!r} is not a whole number >= {low}; "
                "the tape is corrupt, record it again"
            )
        out[key] = value
    shape = (out["nx"], out["ny"])
    for key, dtype in (("obstacles", bool), ("lane_km", float), ("speed_limit", float)):
        value = meta.get(key)
        wrong = _first_not(value, _flag if dtype is bool else _real)  # (finite: below)
        if wrong is not None:
            want = "true or false (1 or 0)" if dtype is bool else "a number"
            raise UserError(
                f"{path}: tape metadata {key} holds {str(wrong)[:30]!r} where {want} belongs; "
                "the tape is corrupt, record it again"
            )
        try:
            arr = np.asarray(value, dtype=float)
        except (TypeError, ValueError):
            arr = np.empty(0)
        if arr.shape != shape:
            raise UserError(
                f"{path}: tape metadata {key} has shape {arr.shape}, not the grid's "
                f"{shape[0]} x {shape[1]}; the tape is corrupt, record it again"
            )
        bad = ~np.isfinite(arr) | (arr < 0)
        if bad.any():
            i, j = (int(x) for x in np.argwhere(bad)[0])
            raise UserError(
                f"{path}: tape metadata {key} = {arr[i, j]} at cell ({i}, {j}) is not a finite "
                "number >= 0; the tape is corrupt, record it again"
            )
        out[key] = arr.astype(dtype)
    roadless = ~out["obstacles"] & (out["lane_km"] <= 0)
    if roadless.any():  # a cell without lanes is an obstacle (twin.sumo.cells)
        i, j = (int(x) for x in np.argwhere(roadless)[0])
        raise UserError(
            f"{path}: tape metadata lane_km = 0 at cell ({i}, {j}), which its obstacles leave "
            "free (a cell without lanes is an obstacle); the tape is corrupt, record it again"
        )
    limits = out["speed_limit"]
    wrong = ~out["obstacles"] & ((limits <= 0) | (limits > MAX_SPEED))
    if wrong.any():  # every lane has a speed > 0, and a free cell has lanes
        i, j = (int(x) for x in np.argwhere(wrong)[0])
        raise UserError(
            f"{path}: tape metadata speed_limit = {limits[i, j]:g} at cell ({i}, {j}), which its "
            f"obstacles leave free, is not a lane speed (above 0, at most {MAX_SPEED:g} m/s); "
            "the tape is corrupt, record it again"
        )
    settings = meta.get("settings", {})
    out["settings"] = settings if isinstance(settings, dict) else {}
    _check_observation_settings(path, out["settings"])
    return out


def _first_not(rows: Any, kind: type | Callable[[Any], bool]) -> Any:
    """The first item of a list of lists that is not of ``kind`` (a type, or a test), else
    None (the shape is checked apart)."""
    test = (lambda x: isinstance(x, kind)) if isinstance(kind, type) else kind
    for row in rows if isinstance(rows, list) else []:
        for x in row if isinstance(row, list) else []:
            if not test(x):
                return x
    return None


def _flag(value: Any) -> bool:
    return isinstance(value, bool) or (isinstance(value, int) and value in (0, 1))


def _real(value: Any) -> bool:
    return isinstance(value, (int, float)) and not isinstance(value, bool)


def _number(value: Any) -> bool:
    return isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value)


#: The settings a replay observes a tape with, which every tape records: left out, a replay
#: would observe other maps than the run (``reads_per_step`` divides the counts).
REPLAY_SETTINGS = ("mfd_fit", "mfd_prior", "detection_p", "reads_per_step")


def _check_observation_settings(path: Path, settings: dict[str, Any]) -> None:
    """The settings a replay observes the tape with (:data:`REPLAY_SETTINGS`, each recorded),
    in the ranges of ``[traffic.mfd]`` (``mfd_fit``, ``mfd_prior`` ``[a, k_c]`` and
    ``detection_p`` in :data:`twin.mfd.SETTING_RANGES`); its clock: ``step_s`` above 0, ``warmup_s``
    >= 0 (each optional: they only label the steps), ``reads_per_step`` a whole number >= 1."""
    fix = "the tape is corrupt, record it again"
    missing = [key for key in REPLAY_SETTINGS if key not in settings]
    if missing:
        raise UserError(
            f"{path}: tape metadata settings lack {', '.join(missing)} (a tape records every "
            f"setting its replay observes with: {', '.join(REPLAY_SETTINGS)}); {fix}"
        )
    prior = settings["mfd_prior"]
    if not (isinstance(prior, list) and len(prior) == 2):
        raise UserError(
            f"{path}: tape metadata mfd_prior = {str(prior)[:40]} is not [a, k_c]; {fix}"
        )
    fit, p = settings["mfd_fit"], settings["detection_p"]
    if fit not in ("online", "fixed"):
        raise UserError(
            f'{path}: tape metadata mfd_fit = {str(fit)[:40]!r} is not "online" or "fixed"; {fix}'
        )
    for key, name, value in (("mfd_prior", "a", prior[0]), ("mfd_prior", "k_c", prior[1]),
                             ("detection_p", "detection_p", p)):  # fmt: skip
        low, high = SETTING_RANGES[name]
        if not (_number(value) and low <= value <= high):
            raise UserError(
                f"{path}: tape metadata {key} = {str(settings[key])[:40]} holds {name} = "
                f"{str(value)[:20]}, not a number in [{low:g}, {high:g}] ([traffic.mfd]'s "
                f"range); {fix}"
            )
    for key, low in (("step_s", 0.0), ("warmup_s", None)):
        value = settings.get(key)
        if value is None:
            continue
        if not _number(value) or (value <= low if low is not None else value < 0):
            want = "above 0" if low is not None else ">= 0"
            raise UserError(
                f"{path}: tape metadata {key} = {str(value)[:40]!r} is not a number {want}; {fix}"
            )
    reads = settings.get("reads_per_step", 1)
    if not isinstance(reads, int) or isinstance(reads, bool) or reads < 1:
        raise UserError(
            f"{path}: tape metadata reads_per_step = {str(reads)[:40]!r} is not a whole number "
            f">= 1; {fix}"
        )
    seed, begin = settings.get("seed"), settings.get("begin")
    if seed is not None and not is_seed(seed):
        raise UserError(
            f"{path}: tape metadata seed = {str(seed)[:40]!r} is not a SUMO seed (a whole "
            f"number from 0 to {MAX_SEED}); {fix}"
        )
    if begin is not None and not isinstance(begin, str):
        raise UserError(
            f"{path}: tape metadata begin = {str(begin)[:40]!r} is not a clock time (text, "
            f'e.g. "07:00:00"); {fix}'
        )


class TapeTraffic(TrafficSource):
    """Replays a tape: the live run's ``T^k`` without SUMO.

    ``detection_p`` and ``seed`` default to the live run's; another detection probability
    replays the same traffic seen through other eyes.
    """

    def __init__(self, tape: Tape, detection_p: float | None = None, source_name: str = "tape"):
        self.tape = tape
        self.grid = Grid(tape.obstacles)
        # the recorded horizon: a tape that stops short of it (a SUMO run that stopped early)
        # ends the replay early, and the evaluation says it is partial
        self.horizon = tape.horizon
        self.detection_p = (
            float(tape.settings.get("detection_p", 1.0)) if detection_p is None else detection_p
        )
        self.source_name = source_name
        self.source_file: Path | None = None  # the tape.parquet read (from_file)
        self._file_record: dict[str, str] | None = None

    @classmethod
    def from_file(cls, path: str | Path, config=None) -> TapeTraffic:
        """Read ``path``; ``config`` (a scenario config) is accepted for the CLI's sake and
        only its ``[traffic.mfd].detection_p``, if set, overrides the tape's, and its explicit
        ``[grid] nx, ny``, if set, must match the tape's grid; what else of its traffic the
        replay sets aside is said in a notice (:meth:`config_set_aside`)."""
        p, shape = None, None
        if config is not None and config.traffic.kind == "sumo":
            mfd = config.traffic.mfd
            p = mfd.detection_p if "detection_p" in mfd.model_fields_set else None
            shape = config.explicit_shape()
        source = cls(Tape.read(Path(path), shape), p, source_name=str(path))
        source.source_file = Path(path).resolve()
        if config is not None:
            set_aside = source.config_set_aside(config)
            if set_aside:
                notify(f"twin: notice: {path}: {'; '.join(set_aside)}")
        return source

    def config_set_aside(self, config) -> list[str]:
        """What of a SUMO ``config``'s own traffic the replay does not use, in words (empty
        when nothing it sets differs): the tape's horizon replaces the config's, and its
        recorded vehicles meet no incident; the incidents its own run applied are not scored.
        (A synthetic config's traffic is replaced whole, as ``--traffic`` says; a SUMO
        config's grid must be the tape's, :meth:`from_file`.)"""
        traffic, where, said = config.traffic, config.path.name, []
        recorded = self.tape.settings.get("incidents")
        if isinstance(recorded, list) and recorded:
            one = len(recorded) == 1
            said.append(f"the {len(recorded)} incident{'' if one else 's'} of its run "
                        f"{'is' if one else 'are'} in its vehicles, but not scored as incidents "
                        "here (their detection and incidents.json come with `twin run`)")  # fmt: skip
        if traffic.kind != "sumo":
            return said
        if "horizon" in traffic.model_fields_set and traffic.horizon != self.horizon:
            said.append(f"its T = {self.horizon} replaces {where}'s [traffic].horizon = "
                        f"{traffic.horizon}")  # fmt: skip
        if traffic.incidents:
            said.append(f"{where}'s {len(traffic.incidents)} [[traffic.incidents]] are not "
                        "applied (a tape replays recorded vehicles: run them live with `twin "
                        "run`)")  # fmt: skip
        return said

    def check_complete(self, what: str) -> None:
        """Refuse (one line) a tape that stopped before its horizon for ``what`` (pretraining,
        an env), whose episodes run every step of ``T``."""
        last = int(self.tape.steps.max()) if len(self.tape.steps) else -1
        if last < self.horizon:
            raise UserError(
                f"{self.source_name}: holds steps to {last} of its horizon T = {self.horizon} "
                f"(a run that stopped early); {what} needs every step: give a finished run's "
                "tape"
            )

    def model(self) -> MFDImportance:
        s = self.tape.settings
        return MFDImportance(
            self.grid.free,
            self.tape.lane_km,
            self.tape.speed_limit,
            s.get("mfd_fit", "online"),
            MFD(*s.get("mfd_prior", (MFD().a, MFD().k_c))),
            self.detection_p,
            int(s.get("seed", 0)),
            int(s.get("reads_per_step", 1)),  # counts are vehicle-instants over the reads
        )

    def sighting_model(self):
        """The drones count the tape's vehicles through its detection probability, reads per
        step and MFD prior (:class:`twin.belief.SightingModel`)."""
        from twin.belief import SightingModel

        s = self.tape.settings
        return SightingModel(
            self.detection_p,
            np.asarray(self.tape.lane_km, dtype=float).ravel(),
            float(s.get("mfd_prior", (MFD().a, MFD().k_c))[1]),
            int(s.get("reads_per_step", 1)),
        )

    def truth_map(self):
        """The true ``T^k`` of the map last yielded, when vehicles may be missed (detection
        probability below 1): the same MFD on every vehicle."""
        observer = getattr(self, "_observer", None)
        return observer.truth if observer is not None and self.detection_p < 1.0 else None

    def model_observed(self) -> MFDImportance | None:
        """The MFD observation of the last replay (its fit and samples), None before one."""
        return getattr(self, "_observer", None)

    def importance_maps(self) -> Generator[np.ndarray, None, None]:
        model = self._observer = self.model()
        self.mfd_before: dict[int, Any] = {}  # the MFD in effect as each step was read
        for step, count, speed in zip(
            self.tape.steps, self.tape.counts, self.tape.speeds, strict=True
        ):
            self.mfd_before[int(step)] = model.mfd
            importance = model.observe(int(step), count, speed.astype(float))
            if 0 <= step <= self.horizon:
                yield importance

    def clock(self, k: int) -> str | None:
        t = self.tape.times[self.tape.steps == k]
        if not len(t):
            return None
        return clock_label(float(t[0]))

    def metadata(self) -> dict[str, Any]:
        return {
            "kind": "tape",
            "tape": self.source_name,
            "horizon": self.horizon,
            "detection_p": self.detection_p,
            "recorded": {k: v for k, v in self.tape.settings.items() if k != "network"},
            **({"tape_file": self.file_record()} if self.source_file is not None else {}),
        }

    def file_record(self) -> dict[str, str]:
        """run.json's ``traffic.tape_file``: the tape's path and sha256, by which ``twin
        report`` finds it again to replay the run's maps and sightings."""
        if self._file_record is None:
            from twin.files import file_sha256

            path = self.source_file
            self._file_record = {"path": str(path), "sha256": file_sha256(path)}
        return self._file_record
