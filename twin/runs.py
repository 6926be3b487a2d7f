"""The run folder: what ``twin evaluate`` and ``twin run`` write and ``twin report`` reads.

Files (every write goes to a temporary name first and is then renamed into place, so an
interrupted run never leaves a half-written file):

- ``series.parquet``: seed, swarm, step (k = 0..T-1), reward (R^k), cumulative_reward,
  coverage (C^{k+1}), visited_share, and belief_error (of the belief after the drones' view
  from ``P_{k+1}``, against ``T_true^{k+1}``; see ``twin/monitoring.py``);
- ``trajectories.parquet``: seed, swarm, step (0..T), drone, i, j;
- ``per_seed.csv``: seed, swarm, the Table 2 columns, the gain columns (reward split, plain
  accounting, coverage ceiling) and the monitoring columns (``twin/metrics.py``);
  ``summary.csv``: their mean over seeds with ``<column>_ci95`` half-widths and ``n_seeds``;
- ``monitoring.csv``: the monitoring columns of ``summary.csv`` alone;
- ``events.parquet``: the congestion events, one row per (seed, event, swarm): seed, event, i, j,
  onset, duration, peak, swarm, seen, first_seen (step, -1 when not seen while the event
  lasted), latency_steps (-1 likewise);
- ``importance.npz``: ``importance`` (T+1, nx, ny) of the first seed, ``obstacles`` (nx, ny);
- ``run.json``: metadata (command, configuration, seeds, traffic source, versions, timings).
"""

from __future__ import annotations

import contextlib
import platform
import sys
from collections.abc import Sequence
from datetime import UTC, datetime
from importlib import metadata as importlib_metadata
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

from twin import __version__
from twin.errors import UserError
from twin.files import atomic_write, write_json
from twin.metrics import MONITORING_COLUMNS, aggregate, learned_against_best_classical, table2
from twin.monitoring import MonitorSettings, RunMonitoring, monitor_run
from twin.patrol import PatrolResult
from twin.scores import ScoreParams


def new_run_dir(root: str | Path, prefix: str) -> Path:
    """A fresh folder ``root/prefix-YYYYmmdd-HHMMSS`` (suffixed if it exists)."""
    stamp = datetime.now().strftime("%Y%m%d-%H%M%S")
    base = Path(root) / f"{prefix}-{stamp}"
    path, n = base, 1
    while path.exists():
        n += 1
        path = Path(f"{base}-{n}")
    return path


def prepare_run_dir(path: str | Path) -> Path:
    """Create ``path``; refuse a folder that already holds a run, so nothing is overwritten."""
    path = Path(path)
    if (path / "run.json").exists() or (path / "summary.csv").exists():
        raise UserError(f"{path} already holds a run; pass another --out folder")
    try:
        path.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise UserError(f"cannot create output folder {path}: {exc.strerror}") from exc
    return path


def series_frame(result: PatrolResult) -> pd.DataFrame:
    """Per-step metrics of one run, long format."""
    n_swarms, horizon = result.rewards.shape
    return pd.DataFrame(
        {
            "seed": np.full(n_swarms * horizon, result.seed, dtype=np.int64),
            "swarm": np.repeat(result.swarms, horizon),
            "step": np.tile(np.arange(horizon), n_swarms),
            "reward": result.rewards.ravel(),
            "cumulative_reward": result.rewards.cumsum(axis=1).ravel(),
            "coverage": result.coverage.ravel(),
            "visited_share": result.visited_share.ravel(),
        }
    )


def trajectories_frame(result: PatrolResult) -> pd.DataFrame:
    """Every drone's cell at every step of one run, long format."""
    n_swarms, steps, n_drones, _ = result.positions.shape
    idx = np.indices((n_swarms, steps, n_drones)).reshape(3, -1)
    flat = result.positions.reshape(-1, 2)
    return pd.DataFrame(
        {
            "seed": np.full(len(flat), result.seed, dtype=np.int64),
            "swarm": np.asarray(result.swarms)[idx[0]],
            "step": idx[1],
            "drone": idx[2],
            "i": flat[:, 0],
            "j": flat[:, 1],
        }
    )


def package_versions() -> dict[str, str]:
    names = ["numpy", "scipy", "pandas", "torch", "eclipse-sumo", "libsumo", "shapely", "ray"]
    versions = {"python": platform.python_version(), "twin": __version__}
    for name in names:
        with contextlib.suppress(importlib_metadata.PackageNotFoundError):
            versions[name] = importlib_metadata.version(name)
    return versions


def score_params_of(metadata: dict[str, Any]) -> ScoreParams | None:
    """The run's :class:`ScoreParams` from its metadata's ``params`` (None when absent)."""
    node = metadata.get("params")
    if not isinstance(node, dict) or "eta" not in node or "delta" not in node:
        return None
    known = {k: float(node[k]) for k in ("eta", "delta", "alpha_T", "alpha_I") if k in node}
    return ScoreParams(**known)


def step_seconds_of(metadata: dict[str, Any]) -> float | None:
    """Seconds per step of a simulated run (``traffic.step_s`` or the tape's recorded one)."""
    traffic = metadata.get("traffic") or {}
    for node in (traffic, traffic.get("recorded") or {}):
        value = node.get("step_s") if isinstance(node, dict) else None
        if isinstance(value, (int, float)) and value > 0:
            return float(value)
    return None


def seed_table(
    result: PatrolResult,
    params: ScoreParams | None = None,
    step_s: float | None = None,
    monitoring: RunMonitoring | None = None,
) -> pd.DataFrame:
    """One row per swarm of one seed: the Table 2 columns and, when monitored, the monitoring
    columns."""
    table = table2(result, params)
    if monitoring is not None:
        table = table.merge(monitoring.table(step_s), on="swarm", how="left")
    table.insert(0, "seed", result.seed)
    return table


def write_run(
    run_dir: Path,
    results: Sequence[PatrolResult],
    metadata: dict[str, Any],
    monitor: MonitorSettings | None = None,
) -> pd.DataFrame:
    """Write the run folder for one or several seeds; return the summary table and the
    comparison of each learned swarm with the best classical one (``comparison.csv``)."""
    run_dir.mkdir(parents=True, exist_ok=True)
    monitor = monitor or MonitorSettings()
    params = score_params_of(metadata)
    step_s = step_seconds_of(metadata)
    monitored: list[RunMonitoring | None] = [
        monitor_run(r, monitor) if r.importance is not None else None for r in results
    ]
    series = pd.concat(
        [_with_belief(series_frame(r), m) for r, m in zip(results, monitored, strict=True)],
        ignore_index=True,
    )
    trajectories = pd.concat([trajectories_frame(r) for r in results], ignore_index=True)
    per_seed = pd.concat(
        [seed_table(r, params, step_s, m) for r, m in zip(results, monitored, strict=True)],
        ignore_index=True,
    )
    summary = aggregate(per_seed)
    comparison = learned_against_best_classical(per_seed)
    keep = [c for c in MONITORING_COLUMNS if c in summary.columns]
    monitoring = summary[["swarm", *[x for c in keep for x in (c, f"{c}_ci95")], "n_seeds"]]
    event_frames = [m.events_frame() for m in monitored if m is not None]
    event_frames = [f for f in event_frames if len(f)] or event_frames[:1]
    events = pd.concat(event_frames, ignore_index=True) if event_frames else None

    atomic_write(run_dir / "series.parquet", lambda p: series.to_parquet(p, index=False))
    atomic_write(
        run_dir / "trajectories.parquet", lambda p: trajectories.to_parquet(p, index=False)
    )
    atomic_write(run_dir / "per_seed.csv", lambda p: per_seed.to_csv(p, index=False))
    atomic_write(run_dir / "summary.csv", lambda p: summary.to_csv(p, index=False))
    if not comparison.empty:
        atomic_write(run_dir / "comparison.csv", lambda p: comparison.to_csv(p, index=False))
    if keep and events is not None:
        atomic_write(run_dir / "monitoring.csv", lambda p: monitoring.to_csv(p, index=False))
        atomic_write(run_dir / "events.parquet", lambda p: events.to_parquet(p, index=False))
    first = results[0]
    if first.importance is not None:

        def save_maps(p: Path) -> None:
            with open(p, "wb") as fh:
                np.savez_compressed(
                    fh,
                    importance=first.importance.astype(np.float32),
                    obstacles=first.grid.obstacles,
                )

        atomic_write(run_dir / "importance.npz", save_maps)
    meta = {
        "created": datetime.now(UTC).isoformat(timespec="seconds"),
        "command": " ".join(["twin", *sys.argv[1:]]),
        "seeds": [r.seed for r in results],
        "swarms": list(first.swarms),
        "grid": {"nx": first.grid.nx, "ny": first.grid.ny, "n_free": first.grid.n_free},
        "horizon": first.horizon,
        "timings": {"patrol_seconds": [round(r.seconds, 3) for r in results]},
        "errors": [r.error for r in results if r.error],
        "monitoring": {
            "threshold": monitor.threshold,
            "min_duration": monitor.min_duration,
            "weight_floor": monitor.weight_floor,
            "step_s": step_s,
            "truth": (
                "recorded truth"
                if any(r.truth is not None for r in results)
                else "the observed importance"
            ),
        },
        "versions": package_versions(),
        **metadata,
    }
    write_json(run_dir / "run.json", meta)
    return summary, comparison


def _with_belief(series: pd.DataFrame, monitoring: RunMonitoring | None) -> pd.DataFrame:
    """Add ``belief_error`` at step k = the error after observing from ``P_{k+1}``."""
    if monitoring is None:
        return series
    return series.assign(belief_error=monitoring.belief_error[:, 1:].ravel())


def read_summary(run_dir: str | Path) -> pd.DataFrame:
    return pd.read_csv(Path(run_dir) / "summary.csv")
