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
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from twin.errors import UserError
from twin.grid import Grid
from twin.mfd import MFD, MFDImportance
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

    def write(self, path: Path) -> None:
        import pyarrow as pa
        import pyarrow.parquet as pq

        table = pa.Table.from_pandas(self.frame(), preserve_index=False)
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
        merged = {**(table.schema.metadata or {}), _META_KEY: json.dumps(meta).encode()}
        pq.write_table(table.replace_schema_metadata(merged), path)

    @classmethod
    def read(cls, path: Path) -> Tape:
        import pyarrow.parquet as pq

        path = Path(path)
        if not path.exists():
            raise UserError(f"{path}: no such traffic tape")
        try:
            table = pq.read_table(path)
        except Exception as exc:  # pyarrow raises several types on a broken file
            raise UserError(f"{path}: not a parquet file ({type(exc).__name__})") from exc
        raw = (table.schema.metadata or {}).get(_META_KEY)
        if raw is None:
            raise UserError(f"{path}: not a twin traffic tape (no {_META_KEY.decode()} metadata)")
        meta = json.loads(raw)
        if meta.get("version") != TAPE_VERSION:
            raise UserError(f"{path}: tape version {meta.get('version')}, expected {TAPE_VERSION}")
        nx, ny = int(meta["nx"]), int(meta["ny"])
        df = table.to_pandas()
        steps = np.unique(df["step"].to_numpy())
        if len(df) != len(steps) * nx * ny:
            raise UserError(f"{path}: {len(df)} rows do not make {len(steps)} full {nx}x{ny} maps")
        df = df.sort_values(["step", "i", "j"])
        return cls(
            steps=steps,
            times=df["time_s"].to_numpy()[:: nx * ny],
            counts=df["count"].to_numpy().reshape(-1, nx, ny),
            speeds=df["speed"].to_numpy().reshape(-1, nx, ny),
            obstacles=np.asarray(meta["obstacles"], dtype=bool),
            lane_km=np.asarray(meta["lane_km"], dtype=float),
            speed_limit=np.asarray(meta["speed_limit"], dtype=float),
            horizon=int(meta["horizon"]),
            settings=meta.get("settings", {}),
        )


class TapeTraffic(TrafficSource):
    """Replays a tape: the live run's ``T^k`` without SUMO.

    ``detection_p`` and ``seed`` default to the live run's; another detection probability
    replays the same traffic seen through other eyes.
    """

    def __init__(self, tape: Tape, detection_p: float | None = None, source_name: str = "tape"):
        self.tape = tape
        self.grid = Grid(tape.obstacles)
        self.horizon = min(tape.horizon, int(tape.steps.max()))
        self.detection_p = (
            float(tape.settings.get("detection_p", 1.0)) if detection_p is None else detection_p
        )
        self.source_name = source_name

    @classmethod
    def from_file(cls, path: str | Path, config=None) -> TapeTraffic:
        """Read ``path``; ``config`` (a scenario config) is accepted for the CLI's sake and
        only its ``[traffic.mfd].detection_p``, if set, overrides the tape's."""
        p = None
        if config is not None and config.traffic.kind == "sumo":
            mfd = config.traffic.mfd
            p = mfd.detection_p if "detection_p" in mfd.model_fields_set else None
        return cls(Tape.read(Path(path)), p, source_name=str(path))

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

    def truth_map(self):
        """The true ``T^k`` of the map last yielded, when vehicles may be missed (detection
        probability below 1): the same MFD on every vehicle."""
        observer = getattr(self, "_observer", None)
        return observer.truth if observer is not None and self.detection_p < 1.0 else None

    def importance_maps(self) -> Iterator[np.ndarray]:
        model = self._observer = self.model()
        for step, count, speed in zip(
            self.tape.steps, self.tape.counts, self.tape.speeds, strict=True
        ):
            importance = model.observe(int(step), count, speed.astype(float))
            if 0 <= step <= self.horizon:
                yield importance

    def clock(self, k: int) -> str | None:
        t = self.tape.times[self.tape.steps == k]
        if not len(t):
            return None
        s = round(float(t[0]))
        return f"{s // 3600:02d}:{s % 3600 // 60:02d}:{s % 60:02d}"

    def metadata(self) -> dict[str, Any]:
        return {
            "kind": "tape",
            "tape": self.source_name,
            "horizon": self.horizon,
            "detection_p": self.detection_p,
            "recorded": {k: v for k, v in self.tape.settings.items() if k != "network"},
        }
