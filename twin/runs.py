"""The run folder: what ``twin evaluate`` and ``twin run`` write and ``twin report`` reads.

Files (every write goes to a temporary name first and is then renamed into place, so an
interrupted run never leaves a half-written file):

- ``series.parquet``: seed, swarm, step (k = 0..T-1), reward (R^k), cumulative_reward,
  coverage (C^{k+1}), visited_share, and belief_error (of the belief after the drones' view
  from ``P_{k+1}``, against ``T_true^{k+1}``; see ``twin/monitoring.py``);
- ``trajectories.parquet``: seed, swarm, step (0..T), drone, i, j;
- ``per_seed.csv``: seed, swarm, the Table 2 columns, the gain columns (reward split, the paper's
  accounting, coverage ceiling) and the monitoring columns (``twin/metrics.py``);
  ``summary.csv``: their mean over seeds with ``<column>_ci95`` half-widths and ``n_seeds``;
- ``monitoring.csv``: the monitoring columns of ``summary.csv`` alone;
- ``events.parquet``: the congestion events, one row per (seed, event, swarm): seed, event, i, j,
  onset, duration, peak, swarm, seen, first_seen (step, -1 when not seen while the event
  lasted), latency_steps (-1 likewise);
- ``importance.npz``: ``importance`` (T+1, nx, ny) of the first seed, ``obstacles`` (nx, ny);
- ``timing.csv``: wall time per stage of each seed's run (``twin/timing.py``): seed, process
  (``main``, or ``sumo`` when SUMO ran in its own process beside it), stage, seconds,
  ms_per_step, share of the process's total; the monitoring and the writing of the files
  above are the main process's last stage;
- ``run.json``: metadata (command, configuration, seeds, traffic source, versions, timings),
  ``partial`` and, when partial, ``partial_reason``; written first as a marker when the run
  starts (``partial: true``, reason: not finished) and rewritten when it ends;
- live SUMO runs add ``network.json``, ``mfd.json``, ``mfd_samples.parquet``, ``tape.parquet``
  (and ``tapes/seed-<s>.parquet`` for further seeds), and ``sumo/`` when the scenario asks SUMO
  for outputs (a sumocfg's ``<output>``, detectors of additional files): those outputs, under
  their own base names, and the rewritten copies of the additional files that name them
  (``sumo/seed-<s>/`` for further seeds; :mod:`twin.sumo.outputs`);
- ``manifest.json``, written LAST: ``{"partial", "partial_reason", "files": {name: bytes}}``.
  A folder is complete only when it has a manifest whose files all exist with those sizes; a
  kill at any instant leaves no manifest, and every reader (``twin report``, a rerun with the
  same ``--out``) calls :func:`check_run_folder`. ``report/`` (written later by ``twin
  report``) is not listed, nor is ``error.log`` (the traceback of an unexpected error of the
  command that wrote the folder or of ``twin report``; :mod:`twin.boundary`).
"""

from __future__ import annotations

import contextlib
import json
import os
import platform
import re
import shutil
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from datetime import UTC, datetime
from importlib import metadata as importlib_metadata
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
import pandas as pd

from twin import __version__
from twin.boundary import LOG_NAME, claim_run_folder, command_line, set_run_folder
from twin.ceilings import ceiling_table
from twin.errors import UserError
from twin.files import (
    NotARecord,
    atomic_write,
    check_staged_folder,
    not_a_file,
    read_record,
    write_json,
)
from twin.metrics import (
    MONITORING_COLUMNS,
    ORACLE,
    SWARM_ROLE,
    aggregate,
    learned_against_best_classical,
    swarm_rows,
    table2,
)
from twin.monitoring import MonitorSettings, RunMonitoring, monitor_run
from twin.patrol import PatrolResult
from twin.processes import peak_memory_mb
from twin.readback import check_manifest
from twin.scores import ScoreParams
from twin.timing import WRITING

if TYPE_CHECKING:
    from twin.experiment import ExperimentResult

MANIFEST = "manifest.json"


@dataclass(frozen=True)
class RunFile:
    """One entry of a run folder (docs/guide.md, "Run folders", describes each): which commands
    write it, which read it back, whether ``twin report`` needs it, whether the manifest lists
    it (with its size), whether it is a folder, and whose runs always write it (``"run"``:
    every run, ``"live"``: every live SUMO ``twin run``; in folders since
    :data:`COMPLETE_SINCE_FORMAT`)."""

    name: str
    written_by: str
    read_by: str
    required: bool = False
    listed: bool = True
    folder: bool = False
    always: str = ""


#: The run folder's format (run.json ``folder_format``; 1 when absent): 2 adds the bound's
#: prices (``bound.npz``), the drones' starts and the configured incident schedule, which the
#: read-back of a folder of format 1 cannot replay; 3 adds the fault-free twin's trajectories
#: (``fault_free.parquet``), which the read-back of ``degradation.csv`` replays, and the
#: oracle's (``oracle.parquet``), which the read-back of the oracle row replays; 4 leaves the
#: ``_ci95`` of a figure from one seed empty (earlier formats wrote 0).
FOLDER_FORMAT = 4


#: The run folder's schema: every name twin writes into a run folder. It drives the manifest
#: (:data:`UNLISTED`), the check that a partial run may be replaced (:data:`RUN_FILE_NAMES`),
#: the files ``twin report`` requires (:data:`REQUIRED_FILES`); a test checks the guide's table
#: against it.
RUN_FILES = (
    RunFile("series.parquet", "run, evaluate", "report", required=True),
    RunFile("trajectories.parquet", "run, evaluate", "report, replay", required=True),
    RunFile("summary.csv", "run, evaluate", "report, docs/make_results.py", required=True),
    RunFile("per_seed.csv", "run, evaluate", "report, docs/make_results.py", always="run"),
    RunFile("comparison.csv", "run, evaluate", "report"),
    RunFile("monitoring.csv", "run, evaluate", "report"),
    RunFile("events.parquet", "run, evaluate", "report"),
    RunFile("belief_models.csv", "run, evaluate (--history)", "report"),
    RunFile("belief_maps.npz", "run, evaluate (--history)", "report"),
    RunFile("importance.npz", "run, evaluate", "report", required=True),
    RunFile("network.json", "run (SUMO)", "report, replay", always="live"),
    RunFile("mfd.json", "run (SUMO)", "report", always="live"),
    RunFile("mfd_samples.parquet", "run (SUMO)", "report", always="live"),
    RunFile("tape.parquet", "run (SUMO)", "evaluate --traffic, history", always="live"),
    RunFile("tapes", "run (SUMO, several seeds)", "evaluate --traffic, history", folder=True),
    RunFile("incidents.json", "run (SUMO, incidents)", "report"),
    RunFile("detectors.parquet", "run (SUMO, [traffic.detectors])", "docs/measure_beliefs.py"),
    RunFile("degradation.csv", "run, evaluate ([faults])", "report"),
    RunFile("fault_free.parquet", "run, evaluate ([faults])", "report"),
    RunFile("bound.npz", "run, evaluate (ceilings)", "report"),
    RunFile("oracle.parquet", "run, evaluate (ceilings)", "report"),
    RunFile("sumo", "run (SUMO outputs of the scenario)", "the user", folder=True),
    RunFile("timing.csv", "run, evaluate", "report", always="run"),
    RunFile("run.json", "run, evaluate", "report, replay, the rerun check of --out"),
    RunFile(MANIFEST, "run, evaluate (last)", "report, replay", listed=False),
    RunFile("report", "report (run, evaluate)", "a browser", listed=False, folder=True),
    RunFile(LOG_NAME, "any command, after an unexpected error", "the user", listed=False),
)
#: Names twin writes into a run folder: a partial run made of these alone may be replaced.
RUN_FILE_NAMES = frozenset(f.name for f in RUN_FILES)
#: Names in a run folder that its manifest does not list: written after the run, or again later.
UNLISTED = tuple(f.name for f in RUN_FILES if not f.listed)
#: Files ``twin report`` cannot draw without.
REQUIRED_FILES = tuple(f.name for f in RUN_FILES if f.required)
#: The first folder format whose folders hold every file and column their runs always write
#: (:attr:`RunFile.always`; the columns of ``timing.csv``, ``mfd_samples.parquet`` and
#: ``detectors.parquet``): a folder of it or later missing one was edited.
COMPLETE_SINCE_FORMAT = 2
#: Files every run writes, and every live SUMO ``twin run`` (besides :data:`REQUIRED_FILES`).
RUN_WRITTEN = tuple(f.name for f in RUN_FILES if f.always == "run")
LIVE_RUN_WRITTEN = tuple(f.name for f in RUN_FILES if f.always == "live")
#: Options that change only what is printed: a rerun differing in these is the same command.
#: (``--workers``/``--executor`` change where seeds run, not their results)
DISPLAY_OPTIONS = frozenset(
    {"quiet", "no_report", "func", "gui", "gui_swarms", "gui_shade", "record"}
    | {"workers", "executor"}
)


def new_run_dir(root: str | Path, prefix: str) -> Path:
    """Create and return a fresh folder ``root/prefix-YYYYmmdd-HHMMSS`` (``-2``, ``-3``, ...
    when taken): ``mkdir`` without ``exist_ok`` claims the name atomically, so two runs
    started in the same second never share a folder."""
    stamp = datetime.now().strftime("%Y%m%d-%H%M%S")
    root = Path(root)
    try:
        root.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise UserError(
            f"{root}: cannot create the runs folder ({exc.strerror}); pass --out"
        ) from exc
    base = root / f"{prefix}-{stamp}"
    for n in range(1, 10_000):
        path = base if n == 1 else Path(f"{base}-{n}")
        try:
            path.mkdir()
        except FileExistsError:
            continue
        except OSError as exc:
            raise UserError(
                f"{path}: cannot create the run folder ({exc.strerror}); pass --out"
            ) from exc
        return path
    raise UserError(f"{base}: 10000 run folders in one second; pass --out")


def invocation(command: str, args: Any = None) -> dict[str, Any]:
    """What identifies a command for ``--out``: its name, options (display options left out)
    and the folder it runs in; a rerun with the same invocation may replace its partial run
    folder."""
    options = {
        k: (str(v) if isinstance(v, Path) else [str(x) for x in v] if isinstance(v, list) else v)
        for k, v in sorted(vars(args).items() if args is not None else [])
        if k not in DISPLAY_OPTIONS
    }
    return {"command": command, "options": options, "cwd": working_folder()}


def working_folder() -> str | None:
    """The folder the command runs in (relative paths among its options are read from it;
    ``twin replay`` reads them from there again), None when it no longer exists."""
    try:
        return os.getcwd()
    except OSError:
        return None


def prepare_run_dir(path: str | Path, started: dict[str, Any] | None = None) -> Path:
    """Create ``path`` for a run and mark it started (``run.json`` with ``partial: true``).

    A non-empty folder is refused, untouched, unless it is a partial or interrupted run of the
    same invocation (``started``) holding only files twin writes: those are then deleted
    (never anything else) and the run starts afresh in the same folder.
    """
    path = Path(path)
    if path.exists() and not path.is_dir():
        raise UserError(f"--out {path}: is a file, not a folder; pass a new or empty folder")
    try:
        path.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise UserError(f"--out {path}: cannot create the folder ({exc.strerror})") from exc
    claim_run_folder(path)  # one command at a time writes into a run folder
    if any(path.iterdir()):
        _replaceable(path, started)
        for entry in path.iterdir():
            if entry.is_dir() and not entry.is_symlink():
                shutil.rmtree(entry)
            else:
                entry.unlink()
    marker = {
        "created": datetime.now(UTC).isoformat(timespec="seconds"),
        "invocation": started,
        "partial": True,
        "partial_reason": "interrupted: the run did not finish writing its folder",
    }
    write_json(path / "run.json", marker)
    set_run_folder(path)  # an unexpected error's traceback goes to its error.log
    return path


def discard_run_dir(path: Path) -> None:
    """Undo :func:`prepare_run_dir` for a run refused before it wrote anything: remove the
    start marker and the folder if nothing else is in it."""
    run = _read_json(path / "run.json")
    if isinstance(run, dict) and set(run) == {"created", "invocation", "partial", "partial_reason"}:
        (path / "run.json").unlink(missing_ok=True)
        shutil.rmtree(path / "sumo", ignore_errors=True)  # SUMO's outputs of the refused run
    with contextlib.suppress(OSError):
        path.rmdir()  # only if empty


#: What to do with an --out folder a run may not reuse.
REUSE_FIX = "pass a new or empty --out folder"


def check_holds_a_run(path: Path) -> None:
    """Refuse (UserError) an existing --out folder that is not empty and holds no twin run
    (no ``run.json``): a user's folder, refused for that before its tree is walked."""
    if (
        path.is_dir()
        and any(path.iterdir())
        and not isinstance(_read_json(path / "run.json"), dict)
    ):
        raise UserError(f"--out {path}: not empty and holds no twin run; {REUSE_FIX}")


def _replaceable(path: Path, started: dict[str, Any] | None) -> None:
    """Refuse (UserError) to reuse the non-empty folder ``path`` unless it holds a partial run
    of the invocation ``started`` and nothing else."""
    check_holds_a_run(path)
    run = _read_json(path / "run.json")
    manifest = _read_json(path / MANIFEST)
    if isinstance(manifest, dict) and not manifest.get("partial"):
        raise UserError(f"--out {path}: already holds a complete run; {REUSE_FIX}")
    theirs = run.get("invocation")
    if started is None or theirs != json.loads(json.dumps(started)):
        what = (
            (theirs or {}).get("command", "another command")
            if isinstance(theirs, dict)
            else "another command"
        )
        raise UserError(
            f"--out {path}: holds a partial run of {what} with other options; {REUSE_FIX} "
            "(only a rerun of the same command replaces it)"
        )
    foreign = sorted(
        e.name for e in path.iterdir() if e.name not in RUN_FILE_NAMES and not _is_temp(e.name)
    )
    foreign += _foreign_in_folders(path, manifest)
    if foreign:
        raise UserError(
            f"--out {path}: holds {foreign[0]!r}, which twin did not write; {REUSE_FIX} "
            "(a partial run is replaced only when it holds twin's files alone)"
        )
    check_staged_folder(path / "report", written_by_a_report)  # the user's notes in report/


def written_by_a_report(name: str) -> bool:
    """A name an earlier twin's report wrote into ``report/`` (one without its listing of
    what it holds, :data:`twin.files.STAGED_LISTING`)."""
    return name in ("report.html", "report.md") or name.endswith((".png", ".gif"))


def _foreign_in_folders(path: Path, manifest: Any) -> list[str]:
    """Files in the run's listed folders (``sumo/``, ``tapes/``) that its manifest does not
    list (without a manifest, a run killed before writing it: tapes other than
    ``seed-<s>.parquet``; SUMO's outputs cannot be told apart then). ``report/`` is the
    report's own folder, drawn afresh."""
    listed = manifest.get("files") if isinstance(manifest, dict) else None
    foreign = []
    for entry in RUN_FILES:
        folder = path / entry.name
        if not (entry.folder and entry.listed and folder.is_dir()):
            continue
        for p in sorted(folder.rglob("*")):
            if p.is_dir() or _is_temp(p.name):
                continue
            rel = p.relative_to(path).as_posix()
            if isinstance(listed, dict):
                ours = rel in listed
            else:
                ours = entry.name != "tapes" or re.fullmatch(r"seed-\d+\.parquet", p.name)
            if not ours:
                foreign.append(rel)
    return foreign


def _is_temp(name: str) -> bool:
    return name.startswith(".") and name.endswith(".tmp")


def _read_json(path: Path) -> Any:
    """The JSON at ``path``; None when it cannot be read (absent, damaged, a pipe: :func:`twin.files.read_record`)."""
    try:
        return json.loads(read_record(path))
    except (OSError, ValueError, RecursionError):
        return None


def write_manifest(run_dir: Path, partial: bool = False, reason: str | None = None) -> None:
    """``manifest.json``, the last file of a run folder: every other file with its size."""
    files = {}
    for p in sorted(run_dir.rglob("*")):
        rel = p.relative_to(run_dir)
        if p.is_dir() or rel.parts[0] in UNLISTED or _is_temp(p.name):
            continue
        files[rel.as_posix()] = p.stat().st_size
    write_json(
        run_dir / MANIFEST,
        {"partial": bool(partial), "partial_reason": reason if partial else None, "files": files},
    )


def check_run_folder(run_dir: str | Path) -> dict[str, Any]:
    """The manifest of a finished run folder; a folder without one (interrupted, still
    running, or written before manifests) or whose files disagree with it is a one-line
    :class:`UserError`."""
    run_dir = Path(run_dir)
    rerun = "rerun the command that wrote it (same --out replaces it)"
    manifest_path = run_dir / MANIFEST
    if not manifest_path.exists() and not (run_dir / "run.json").exists():
        raise UserError(
            f"{run_dir}: no run.json nor {MANIFEST}: not a folder `twin run` or `twin evaluate` "
            "wrote (a sweep's, transfer's or pretraining's folder is not one); pass a run folder"
        )
    if not manifest_path.exists():
        from twin.boundary import written_by_another

        if written_by_another(run_dir):
            raise UserError(
                f"{run_dir}: another twin command is writing into this folder now; wait for it "
                "to end, then read it"
            )
        run = _read_json(run_dir / "run.json")
        why = run.get("partial_reason") if isinstance(run, dict) else None
        raise UserError(
            f"{run_dir}: incomplete run folder, partial: no {MANIFEST} "
            f"({why or 'the run was interrupted or is still running'}); {rerun}"
        )
    try:
        read_record(manifest_path)
    except NotARecord as exc:  # a FIFO would block forever, /dev/zero fill the memory
        raise UserError(f"{manifest_path}: {exc.strerror}; {rerun}") from None
    except (OSError, UnicodeError):
        pass  # refused below as unreadable
    manifest = _read_json(manifest_path)
    if not isinstance(manifest, dict) or not isinstance(manifest.get("files"), dict):
        raise UserError(f"{manifest_path}: not a run manifest (unreadable JSON); {rerun}")
    check_manifest(manifest_path, manifest)
    for name, size in manifest["files"].items():
        if Path(name).parts and Path(name).parts[0] in UNLISTED:  # written after the run
            raise UserError(
                f"{manifest_path}: lists {name}, which a run's manifest never lists (it is "
                f"written after the run, or again later); {rerun}"
            )
        p = run_dir / name
        if not p.exists():
            raise UserError(f"{run_dir}: {name} listed in {MANIFEST} is missing; {rerun}")
        why = not_a_file(p)
        if why is not None:
            raise UserError(f"{run_dir}: {name} listed in {MANIFEST} {why}; {rerun}")
        actual = p.stat().st_size
        if actual != size:
            raise UserError(
                f"{run_dir}: {name} has {actual} bytes, {MANIFEST} says {size}; the file "
                f"changed after the run, {rerun}"
            )
    return manifest


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
    return cells_frame(result.positions, result.swarms, result.seed)


def cells_frame(positions: np.ndarray, swarms, seed: int) -> pd.DataFrame:
    """The ``(S, T+1, N, 2)`` cells of swarms ``swarms`` of one seed, long format (the columns
    of ``trajectories.parquet``)."""
    n_swarms, steps, n_drones, _ = positions.shape
    idx = np.indices((n_swarms, steps, n_drones)).reshape(3, -1)
    flat = positions.reshape(-1, 2)
    return pd.DataFrame(
        {
            "seed": np.full(len(flat), seed, dtype=np.int64),
            "swarm": np.asarray(swarms)[idx[0]],
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
    extras: Callable[[Path], None] | None = None,
    ceilings: bool = False,
) -> pd.DataFrame:
    """Write the run folder for one or several seeds; return the summary table and the
    comparison of each learned swarm with the best classical one (``comparison.csv``).

    With ``ceilings``, ``per_seed.csv`` and ``summary.csv`` add the rows ``oracle (ceiling)``
    and ``bound (ceiling)`` (:mod:`twin.ceilings`), computed from each seed's recorded maps
    after the swarms ran; every row has a ``role``: ``swarm`` or ``ceiling``.

    Order: the result files, then ``extras(run_dir)`` (the SUMO files), then ``run.json``, then
    ``manifest.json`` last, so a kill at any instant leaves no manifest."""
    t_start = time.perf_counter()
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
    per_seed["role"] = SWARM_ROLE
    prices: dict[str, np.ndarray] = {}  # bound.npz: each seed's bound prices
    oracles = []  # oracle.parquet: each seed's oracle cells
    if ceilings:
        cache: dict = {}
        tables = []
        for r in results:
            table = ceiling_table(r, params, cache) if r.rewards.shape[1] > 0 else None
            if table is not None and len(table):
                if "bound_prices" in table.attrs:
                    prices[f"seed_{r.seed}"] = np.asarray(table.attrs["bound_prices"])
                if "oracle_positions" in table.attrs:
                    cells = table.attrs["oracle_positions"]
                    oracles.append(cells_frame(cells[None], [ORACLE], r.seed))
                tables.append(table.assign(seed=r.seed))
        if tables:
            per_seed = pd.concat([per_seed, *tables], ignore_index=True)
    summary = aggregate(per_seed)
    roles = per_seed.drop_duplicates("swarm").set_index("swarm")["role"]
    summary.insert(1, "role", summary["swarm"].map(roles).fillna(SWARM_ROLE))
    comparison = learned_against_best_classical(per_seed)
    keep = [c for c in MONITORING_COLUMNS if c in summary.columns]
    monitoring = swarm_rows(summary)[
        ["swarm", *[x for c in keep for x in (c, f"{c}_ci95")], "n_seeds"]
    ]
    degradation = _degradation(results, monitored)
    fault_free = [
        cells_frame(r.fault_free.positions, r.fault_free.swarms, r.seed)
        for r, m in zip(results, monitored, strict=True)
        if r.fault_free is not None and m is not None
    ]
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
    if degradation is not None:
        atomic_write(run_dir / "degradation.csv", lambda p: degradation.to_csv(p, index=False))
        free = pd.concat(fault_free, ignore_index=True)
        atomic_write(run_dir / "fault_free.parquet", lambda p: free.to_parquet(p, index=False))
    if prices:

        def save_prices(p: Path) -> None:
            with open(p, "wb") as fh:
                np.savez_compressed(fh, **prices)

        atomic_write(run_dir / "bound.npz", save_prices)
    if oracles:
        cells = pd.concat(oracles, ignore_index=True)
        atomic_write(run_dir / "oracle.parquet", lambda p: cells.to_parquet(p, index=False))
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
    if extras is not None:
        extras(run_dir)
    timing = timing_frame(results, time.perf_counter() - t_start)
    atomic_write(run_dir / "timing.csv", lambda p: timing.to_csv(p, index=False))
    errors = [r.error for r in results if r.error]
    no_step = min(r.rewards.shape[1] for r in results) == 0
    partial = bool(metadata.get("partial")) or bool(errors) or no_step
    left_out = metadata.get("partial_reason")  # seeds left out: said beside the kept ones' errors
    reason = (
        "; ".join(dict.fromkeys([*errors, *([left_out] if left_out else [])]))  # once each
        if errors
        else ("no step ran" if no_step else left_out)
    )
    started = _read_json(run_dir / "run.json")  # the marker of prepare_run_dir, if any
    meta = {
        "created": datetime.now(UTC).isoformat(timespec="seconds"),
        "command": command_line(),
        "seeds": [r.seed for r in results],
        "swarms": list(first.swarms),
        "grid": {"nx": first.grid.nx, "ny": first.grid.ny, "n_free": first.grid.n_free},
        "horizon": first.horizon,
        "timings": {
            "patrol_seconds": [round(r.seconds, 3) for r in results],
            "peak_memory_mb": peak_memory_mb(),
            # SUMO's own process, as it measured itself (the largest child process would be a
            # worker of a parallel run)
            "peak_memory_sumo_process_mb": max(
                (r.extra.get("process_peak_mb") or 0.0 for r in results), default=0.0
            )
            or None,
        },
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
        **({"faults": first.faults.describe()} if first.faults is not None else {}),
        "folder_format": FOLDER_FORMAT,
        "versions": package_versions(),
        "invocation": started.get("invocation") if isinstance(started, dict) else None,
        **metadata,
        "partial": partial,
        "partial_reason": reason if partial else None,
    }
    write_json(run_dir / "run.json", meta)
    write_manifest(run_dir, partial, reason)
    return summary, comparison


def record(
    run_dir: Path,
    outcome: ExperimentResult,
    meta: dict[str, Any],
    ceilings: bool = False,
    more_files: Callable[[Path], None] | None = None,
):
    """Write the run folder (with ``comparison.csv``: each learned swarm against the best
    classical one, paired over seeds); the kept sources add their own files
    (:meth:`TrafficSource.write_extras`: a live run's network, MFD fit and tape of each seed).
    With ``ceilings`` the tables add the oracle and bound rows (:mod:`twin.ceilings`),
    computed from each seed's recorded maps after the swarms' run.
    ``more_files(run_dir)`` writes the caller's own files (``twin run --history``'s
    ``belief_models.csv``) before ``run.json``.
    ``manifest.json`` is written last (see ``twin/runs.py``). Returns the summary table and
    the comparison."""
    from twin.notices import hold_notices

    # what writing notices (a ceiling left out) is printed once the command has ended well: a
    # write that fails after it (a full disk) is the error's line alone
    hold_notices(to_end=True)
    extras = more_files
    if outcome.sources:
        first = outcome.sources[0]
        by_seed = [(r.seed, s) for r, s in zip(outcome.results, outcome.sources, strict=False)]

        def extras(folder: Path) -> None:
            first.write_extras(folder, by_seed)
            if more_files is not None:
                more_files(folder)

    # the source's files go before run.json and manifest.json: a kill in between leaves no manifest
    return write_run(run_dir, outcome.results, meta, extras=extras, ceilings=ceilings)


def _degradation(results, monitored) -> pd.DataFrame | None:
    """``degradation.csv`` (:func:`twin.faults.degradation_frame`) of the seeds that ran a
    fault-free twin beside their faulted swarms; None when none did."""
    from twin.faults import degradation_frame

    frames = [
        degradation_frame(r, m.events)
        for r, m in zip(results, monitored, strict=True)
        if r.fault_free is not None and m is not None
    ]
    return pd.concat(frames, ignore_index=True) if frames else None


def timing_frame(results: Sequence[PatrolResult], writing_seconds: float = 0.0) -> pd.DataFrame:
    """``timing.csv``: each seed's stages (:attr:`PatrolResult.stage_seconds`), then the
    monitoring and writing of the run folder (once, on the first seed's rows); ``process`` is
    ``main``, or the traffic source's own process (``sumo``), which ran beside the main one
    (their shares are of that process)."""
    rows = []
    for n, r in enumerate(results):
        stages = dict(r.stage_seconds)
        if n == 0 and writing_seconds > 0:
            stages[WRITING] = writing_seconds
        steps = max(r.completed_steps, 1)
        for process, part in (("main", stages), *r.extra.get("process_stages", {}).items()):
            total = sum(part.values()) or 1.0
            for stage, seconds in part.items():
                rows.append(
                    {
                        "seed": r.seed,
                        "process": process,
                        "stage": stage,
                        "seconds": round(seconds, 6),
                        "ms_per_step": round(1000.0 * seconds / steps, 4),
                        "share": round(seconds / total, 4),
                    }
                )
    columns = ["seed", "process", "stage", "seconds", "ms_per_step", "share"]
    return pd.DataFrame(rows, columns=columns)


def _with_belief(series: pd.DataFrame, monitoring: RunMonitoring | None) -> pd.DataFrame:
    """Add ``belief_error`` at step k = the error after observing from ``P_{k+1}``."""
    if monitoring is None:
        return series
    return series.assign(belief_error=monitoring.belief_error[:, 1:].ravel())
