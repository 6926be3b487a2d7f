"""The run folder: what ``twin evaluate`` and ``twin run`` write and ``twin report`` reads.

Files (every write goes to a temporary name first and is then renamed into place, so an
interrupted run never leaves a half-written file):

- ``series.parquet``: seed, swarm, step (k = 0..T-1), reward (R^k), cumulative_reward,
  coverage (C^{k+1}), visited_share;
- ``trajectories.parquet``: seed, swarm, step (0..T), drone, i, j;
- ``per_seed.csv``: seed, swarm and the Table 2 columns; ``summary.csv``: their mean over seeds
  with ``<column>_ci95`` half-widths and ``n_seeds``;
- ``importance.npz``: ``importance`` (T+1, nx, ny) of the first seed, ``obstacles`` (nx, ny);
- ``run.json``: metadata (command, configuration, seeds, traffic source, versions, timings).
"""

from __future__ import annotations

import contextlib
import json
import os
import platform
import sys
import tempfile
from collections.abc import Callable, Sequence
from datetime import UTC, datetime
from importlib import metadata as importlib_metadata
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

from twin import __version__
from twin.errors import UserError
from twin.metrics import aggregate, table2
from twin.patrol import PatrolResult


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


def atomic_write(path: Path, write: Callable[[Path], None]) -> None:
    """Call ``write(tmp)`` on a temporary file beside ``path``, then rename it to ``path``."""
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=path.suffix)
    os.close(fd)
    try:
        write(Path(tmp))
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise


def write_json(path: Path, data: dict[str, Any]) -> None:
    atomic_write(path, lambda p: p.write_text(json.dumps(data, indent=2, default=_jsonable) + "\n"))


def _jsonable(value: Any) -> Any:
    if isinstance(value, np.generic):
        return value.item()
    if isinstance(value, np.ndarray):
        return value.tolist()
    if isinstance(value, Path):
        return str(value)
    raise TypeError(f"not JSON serialisable: {type(value).__name__}")


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


def write_run(
    run_dir: Path,
    results: Sequence[PatrolResult],
    metadata: dict[str, Any],
) -> pd.DataFrame:
    """Write the run folder for one or several seeds; return the summary table."""
    run_dir.mkdir(parents=True, exist_ok=True)
    series = pd.concat([series_frame(r) for r in results], ignore_index=True)
    trajectories = pd.concat([trajectories_frame(r) for r in results], ignore_index=True)
    per_seed = pd.concat([table2(r).assign(seed=r.seed) for r in results], ignore_index=True)[
        ["seed", "swarm", "R_hat_T", "C_hat_T", "pct_time_max_C", "pct_map_covered"]
    ]
    summary = aggregate(per_seed)

    atomic_write(run_dir / "series.parquet", lambda p: series.to_parquet(p, index=False))
    atomic_write(
        run_dir / "trajectories.parquet", lambda p: trajectories.to_parquet(p, index=False)
    )
    atomic_write(run_dir / "per_seed.csv", lambda p: per_seed.to_csv(p, index=False))
    atomic_write(run_dir / "summary.csv", lambda p: summary.to_csv(p, index=False))
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
        "versions": package_versions(),
        **metadata,
    }
    write_json(run_dir / "run.json", meta)
    return summary


def read_summary(run_dir: str | Path) -> pd.DataFrame:
    return pd.read_csv(Path(run_dir) / "summary.csv")
