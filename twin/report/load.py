"""Read a run folder (the format documented in ``twin/runs.py``) into one object for the report.

Only the run's own files are read; nothing is recomputed here except what the files determine
exactly (the idleness maps, replayed from the trajectories with Def. 3).
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from functools import cached_property
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

from twin.clock import clock_label, parse_clock
from twin.errors import UserError
from twin.grid import Grid
from twin.scores import ScoreParams, initial_idleness, update_idleness

REQUIRED_FILES = ("series.parquet", "trajectories.parquet", "summary.csv", "importance.npz")


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
    events: pd.DataFrame | None = None  # events.parquet
    incidents: list[dict[str, Any]] | None = None  # incidents.json (scheduled SUMO incidents)
    timing: pd.DataFrame | None = None  # timing.csv (wall time per stage)
    manifest: dict[str, Any] = field(default_factory=dict)  # manifest.json
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
        from twin.ceilings import swarm_rows

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
            maps = np.empty((len(pos), *grid.shape))
            maps[0] = initial_idleness(grid)
            for k in range(1, len(pos)):
                maps[k] = update_idleness(maps[k - 1], pos[k], grid, params.eta, params.delta)
            self._idleness[key] = maps
        return self._idleness[key]


def _read_json(path: Path) -> dict[str, Any] | None:
    if not path.exists():
        return None
    try:
        return json.loads(path.read_text())
    except json.JSONDecodeError as exc:
        raise UserError(f"{path}: not valid JSON ({exc}); rerun the command that wrote it") from exc


def load_run(run_dir: str | Path) -> RunFiles:
    """Read a finished run folder: its ``manifest.json`` must be there and agree with the files
    (:func:`twin.runs.check_run_folder`); a missing required file, an incomplete folder or a run
    in which no step ran is a one-line :class:`UserError`."""
    from twin.runs import check_run_folder

    run_dir = Path(run_dir)
    if not run_dir.is_dir():
        raise UserError(
            f"{run_dir}: no such run folder; pass the folder `twin run`/`evaluate` wrote"
        )
    if (run_dir / "run.json").exists():  # a run folder: interrupted ones say so first
        check_run_folder(run_dir)
    missing = [name for name in REQUIRED_FILES if not (run_dir / name).exists()]
    if missing:
        raise UserError(
            f"{run_dir}: missing {', '.join(missing)}; is this a run folder written by "
            "`twin run` or `twin evaluate`?"
        )
    manifest = check_run_folder(run_dir)
    with np.load(run_dir / "importance.npz") as npz:
        importance = np.asarray(npz["importance"], dtype=np.float64)
        obstacles = np.asarray(npz["obstacles"], dtype=bool)
    if importance.shape[0] < 2:
        run = _read_json(run_dir / "run.json") or {}
        raise UserError(
            f"{run_dir}: partial run in which no step ran "
            f"({run.get('partial_reason') or 'no reason recorded'}); nothing to report, "
            "fix the inputs and rerun"
        )
    per_seed_path = run_dir / "per_seed.csv"
    samples_path = run_dir / "mfd_samples.parquet"
    monitoring_path, events_path = run_dir / "monitoring.csv", run_dir / "events.parquet"
    timing_path = run_dir / "timing.csv"
    return RunFiles(
        run_dir=run_dir,
        series=pd.read_parquet(run_dir / "series.parquet"),
        trajectories=pd.read_parquet(run_dir / "trajectories.parquet"),
        summary=pd.read_csv(run_dir / "summary.csv"),
        per_seed=pd.read_csv(per_seed_path) if per_seed_path.exists() else None,
        importance=importance,
        obstacles=obstacles,
        run=_read_json(run_dir / "run.json") or {},
        network=_read_json(run_dir / "network.json"),
        mfd=_read_json(run_dir / "mfd.json"),
        mfd_samples=pd.read_parquet(samples_path) if samples_path.exists() else None,
        monitoring=pd.read_csv(monitoring_path) if monitoring_path.exists() else None,
        events=pd.read_parquet(events_path) if events_path.exists() else None,
        incidents=_read_json(run_dir / "incidents.json"),
        timing=pd.read_csv(timing_path) if timing_path.exists() else None,
        manifest=manifest,
    )
