"""Experiment sweeps: a grid of scenarios x parameters x seeds, each cell one traffic pass with
every swarm side by side, run on a local process pool or on Ray.

A sweep config (TOML, e.g. ``configs/sweep-demo.toml``)::

    [sweep]
    name = "demo"
    swarms = ["random", "greedy", "sweeping"]
    seeds = [0, 1, 2]                 # or: seeds = 3 (and seed = first seed)

    [swarm_options.rl]                # keyword options of make_policy("rl", ...)
    checkpoint = "../data/qnet.pt"    # paths relative to the sweep config

    [[scenario]]
    name = "synthetic"
    config = "synthetic.toml"         # a scenario config, as `twin evaluate`/`twin run` take
    overrides = { "traffic.horizon" = 144 }

    [parameters]                      # every combination is a cell (per scenario and seed)
    "swarm.n_drones" = [2, 4]

A cell is plain data (a dict) handed to the top-level :func:`run_cell`, so both executors can
ship it; it writes ``cells/<id>.json`` (and the per-step series ``cells/<id>.parquet``)
atomically, and a restarted sweep skips every cell whose JSON exists. The cell's seed fixes
the drones' starts (``default_rng(seed)``, as ``twin evaluate``), the swarms' randomness
(``run_patrol``) and the traffic's, so the same seeds give the same numbers on either
executor and in ``twin evaluate``.
"""

from __future__ import annotations

import copy
import functools
import hashlib
import itertools
import json
import multiprocessing
import os
import sys
import time
from collections.abc import Callable, Iterable
from concurrent.futures import FIRST_COMPLETED, ProcessPoolExecutor, wait
from concurrent.futures.process import BrokenProcessPool
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

from twin.errors import UserError

CELLS_DIR = "cells"
EXECUTORS = ("local", "ray")
#: Columns of results.csv that identify a cell (plus one column per swept parameter).
KEY_COLUMNS = ("cell", "scenario", "seed", "swarm")


@dataclass
class ScenarioSpec:
    """One scenario of a sweep: a scenario config file and overrides of its keys."""

    name: str
    config: Path
    overrides: dict[str, Any] = field(default_factory=dict)
    tape: Path | None = None  # replay a recorded traffic tape instead of the config's traffic


@dataclass
class SweepConfig:
    path: Path
    name: str
    swarms: list[str]
    seeds: list[int]
    scenarios: list[ScenarioSpec]
    parameters: dict[str, list[Any]]
    swarm_options: dict[str, dict[str, Any]]


def _fail(path: Path, key: str, problem: str) -> UserError:
    return UserError(f"{path}: {key} {problem}")


def load_sweep_config(path: str | Path) -> SweepConfig:
    """Read and validate a sweep config; every problem is one line naming the key."""
    from twin.config import read_toml

    path = Path(path)
    data = read_toml(path)
    known = {"sweep", "scenario", "parameters", "swarm_options"}
    for key in data:
        if key not in known:
            raise _fail(
                path, f"[{key}]", f"is not a known section; use: {', '.join(sorted(known))}"
            )
    sweep = data.get("sweep")
    if not isinstance(sweep, dict):
        raise _fail(path, "[sweep]", "is missing; give at least name, swarms and seeds")
    for key in sweep:
        if key not in ("name", "swarms", "seeds", "seed"):
            raise _fail(path, f"[sweep].{key}", "is not a known key; use name, swarms, seeds, seed")
    name = sweep.get("name", path.stem)
    if not isinstance(name, str) or not name or "/" in name:
        raise _fail(path, "[sweep].name", f"= {name!r} must be a non-empty name without '/'")
    swarms = sweep.get("swarms")
    if not isinstance(swarms, list) or not swarms or not all(isinstance(s, str) for s in swarms):
        raise _fail(
            path, "[sweep].swarms", 'must be a list of swarm names, e.g. ["random", "greedy"]'
        )
    if len(set(swarms)) != len(swarms):
        raise _fail(path, "[sweep].swarms", "lists a swarm twice")
    from twin.policies import available_policies

    for swarm in swarms:
        if swarm not in available_policies():
            raise _fail(
                path,
                "[sweep].swarms",
                f"has unknown swarm {swarm!r}; use {', '.join(available_policies())}",
            )
    seeds = _seeds(path, sweep)
    scenarios = _scenarios(path, data.get("scenario"))
    parameters = data.get("parameters", {})
    if not isinstance(parameters, dict):
        raise _fail(path, "[parameters]", "must be a table of dotted keys to lists of values")
    for key, values in parameters.items():
        _check_dotted(path, f"[parameters].{key!r}", key)
        if not isinstance(values, list) or not values:
            raise _fail(path, f"[parameters].{key!r}", f"= {values!r} must be a non-empty list")
    options = data.get("swarm_options", {})
    if not isinstance(options, dict) or not all(isinstance(v, dict) for v in options.values()):
        raise _fail(
            path, "[swarm_options]", "must hold one table per swarm, e.g. [swarm_options.rl]"
        )
    for swarm, table in options.items():
        if swarm not in swarms:
            raise _fail(
                path, f"[swarm_options.{swarm}]", f"names a swarm not in [sweep].swarms {swarms}"
            )
        if "checkpoint" in table:
            table["checkpoint"] = str(_relative(path, table["checkpoint"]))
            if not Path(table["checkpoint"]).is_file():
                raise _fail(
                    path,
                    f"[swarm_options.{swarm}].checkpoint",
                    f"= {table['checkpoint']} does not exist; run `twin pretrain` or fix the path",
                )
    return SweepConfig(path, name, swarms, seeds, scenarios, parameters, options)


def _seeds(path: Path, sweep: dict[str, Any]) -> list[int]:
    seeds = sweep.get("seeds", 1)
    first = sweep.get("seed", 0)
    if isinstance(seeds, bool) or not isinstance(first, int):
        raise _fail(path, "[sweep].seeds", "must be a count or a list of whole numbers")
    if isinstance(seeds, int):
        if seeds < 1:
            raise _fail(path, "[sweep].seeds", f"= {seeds} must be at least 1")
        return list(range(first, first + seeds))
    if not isinstance(seeds, list) or not seeds or not all(isinstance(s, int) for s in seeds):
        raise _fail(path, "[sweep].seeds", "must be a count or a non-empty list of whole numbers")
    if len(set(seeds)) != len(seeds):
        raise _fail(path, "[sweep].seeds", "lists a seed twice")
    return list(seeds)


def _relative(path: Path, value: Any) -> Path:
    p = Path(value)
    return p if p.is_absolute() else (path.parent / p).resolve()


def _check_dotted(path: Path, where: str, key: str) -> None:
    parts = key.split(".")
    if len(parts) < 2 or parts[0] not in ("grid", "swarm", "traffic", "evaluate") or "" in parts:
        raise _fail(
            path, where, "must be a dotted key into a scenario config, e.g. 'swarm.n_drones'"
        )


def _scenarios(path: Path, tables: Any) -> list[ScenarioSpec]:
    if not isinstance(tables, list) or not tables:
        raise _fail(path, "[[scenario]]", "is missing; give at least one with name and config")
    out, names = [], set()
    for n, table in enumerate(tables):
        where = f"[[scenario]] #{n + 1}"
        unknown = set(table) - {"name", "config", "overrides", "tape"}
        if unknown:
            raise _fail(
                path,
                f"{where}.{sorted(unknown)[0]}",
                "is not a known key; use name, config, overrides, tape",
            )
        name = table.get("name")
        if not isinstance(name, str) or not name or name in names:
            raise _fail(path, f"{where}.name", f"= {name!r} must be a distinct non-empty name")
        names.add(name)
        if not isinstance(table.get("config"), str):
            raise _fail(path, f"{where}.config", "must name a scenario config file")
        config = _relative(path, table["config"])
        if not config.exists():
            raise _fail(path, f"{where}.config", f"= {table['config']!r}: {config} does not exist")
        overrides = table.get("overrides", {})
        if not isinstance(overrides, dict):
            raise _fail(path, f"{where}.overrides", "must be a table of dotted keys to values")
        for key in overrides:
            _check_dotted(path, f"{where}.overrides.{key!r}", key)
        tape = _relative(path, table["tape"]) if "tape" in table else None
        out.append(ScenarioSpec(name, config, dict(overrides), tape))
    return out


def parameter_combinations(parameters: dict[str, list[Any]]) -> list[dict[str, Any]]:
    """Every combination of the swept values (one empty combination when none is swept)."""
    keys = list(parameters)
    return [
        dict(zip(keys, values, strict=True)) for values in itertools.product(*parameters.values())
    ]


#: What defines a cell's numbers; the cell id hashes these.
DEFINING_KEYS = (
    "scenario", "config", "overrides", "tape", "seed", "swarms", "swarm_options", "checkpoints",
)  # fmt: skip


def file_sha256(path: str | Path) -> str:
    digest = hashlib.sha256()
    with open(path, "rb") as fh:
        for block in iter(lambda: fh.read(1 << 20), b""):
            digest.update(block)
    return digest.hexdigest()


def cell_id(cell: dict[str, Any]) -> str:
    """``<scenario>-s<seed>-<hash>``: the hash covers everything that defines the cell's numbers
    (a retrained checkpoint, a changed scenario file's path or overrides give new cells)."""
    defining = {k: cell.get(k) for k in DEFINING_KEYS}
    digest = hashlib.sha1(json.dumps(defining, sort_keys=True, default=str).encode()).hexdigest()[
        :10
    ]
    return f"{cell['scenario']}-s{cell['seed']}-{digest}"


def expand_cells(config: SweepConfig, out_dir: Path) -> list[dict[str, Any]]:
    """The sweep's cells, scenario-major, then parameters, then seeds."""
    checkpoints = {
        swarm: file_sha256(options["checkpoint"])
        for swarm, options in config.swarm_options.items()
        if Path(options.get("checkpoint", "")).is_file()
    }
    cells = []
    for scenario in config.scenarios:
        for params in parameter_combinations(config.parameters):
            for seed in config.seeds:
                cell = {
                    "scenario": scenario.name,
                    "config": str(scenario.config),
                    "overrides": {**scenario.overrides, **params},
                    "parameters": params,
                    "tape": str(scenario.tape) if scenario.tape else None,
                    "seed": int(seed),
                    "swarms": list(config.swarms),
                    "swarm_options": copy.deepcopy(config.swarm_options),
                    "checkpoints": checkpoints,
                    "cells_dir": str(out_dir / CELLS_DIR),
                }
                cell["id"] = cell_id(cell)
                cells.append(cell)
    return cells


# --- one cell -------------------------------------------------------------------------------


def scenario_config(path: Path, overrides: dict[str, Any]):
    """The scenario config at ``path`` with dotted-key ``overrides`` applied, validated."""
    from twin import config as cfg

    data = cfg.read_toml(path)
    for key, value in overrides.items():
        node = data
        *parents, last = key.split(".")
        for part in parents:
            node = node.setdefault(part, {})
            if not isinstance(node, dict):
                raise UserError(
                    f"{path}: override {key!r} goes through {part!r}, which is not a table"
                )
        node[last] = value
    return cfg.config_from_data(path, data)


def scenario_source(config, tape: str | None, seed: int):
    """The traffic of one cell: a replayed tape, the synthetic maps, or a live SUMO run."""
    if tape is not None:
        from twin.traffic.tape import TapeTraffic

        return TapeTraffic.from_file(Path(tape), config)
    kind = config.traffic["kind"]
    if kind == "synthetic":
        from twin.config import synthetic_source

        return synthetic_source(config)
    if kind == "sumo":
        from twin.sumo.scenario import sumo_source

        return sumo_source(config, seed=seed)  # the cell's seed is SUMO's seed too
    raise UserError(f"{config.path}: [traffic].kind = {kind!r} is not one a sweep can run")


def _limit_threads() -> None:
    """One core per cell: the pool provides the parallelism."""
    for var in ("OMP_NUM_THREADS", "MKL_NUM_THREADS", "OPENBLAS_NUM_THREADS"):
        os.environ.setdefault(var, "1")
    if "torch" in sys.modules:
        sys.modules["torch"].set_num_threads(1)


def _atomic_write(path: Path, write: Callable[[Path], None]) -> None:
    tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
    try:
        write(tmp)
        os.replace(tmp, path)
    finally:
        tmp.unlink(missing_ok=True)


def run_cell(cell: dict[str, Any]) -> dict[str, Any]:
    """Run one cell (plain dict in, plain dict out) and write its result files atomically.

    Returns ``{"id", "seconds", "rows": [one dict per swarm: Table 2 columns], "error"}``.
    """
    from twin.config import check_swarm_fits, start_positions
    from twin.metrics import table2
    from twin.patrol import run_patrol
    from twin.policies import make_policy
    from twin.runs import series_frame

    _limit_threads()
    code = code_fingerprint()
    start = time.perf_counter()
    seed = int(cell["seed"])
    config = scenario_config(Path(cell["config"]), cell["overrides"])
    source = scenario_source(config, cell.get("tape"), seed)
    try:
        check_swarm_fits(config, source.grid)
        starts = start_positions(config, source.grid, np.random.default_rng(seed))
        options = cell.get("swarm_options", {})
        policies = {name: make_policy(name, **options.get(name, {})) for name in cell["swarms"]}
        _limit_threads()  # an RL swarm may just have imported torch
        result = run_patrol(
            source, policies, starts, config.params, seed, progress=False, keep_importance=False
        )
        traffic = source.metadata()
    finally:
        source.close()
    rows = table2(result).to_dict(orient="records")
    record = {
        "id": cell["id"],
        "cell": {k: v for k, v in cell.items() if k != "cells_dir"},
        "traffic": traffic,
        "policies": {n: p.describe() for n, p in policies.items() if hasattr(p, "describe")},
        "rows": [{k: (None if _isnan(v) else v) for k, v in r.items()} for r in rows],
        "horizon": int(result.horizon),
        "error": result.error,
        "seconds": round(time.perf_counter() - start, 3),
        "worker": f"{os.uname().nodename}:{os.getpid()}",
        "code": code,
    }
    cells_dir = Path(cell["cells_dir"])
    cells_dir.mkdir(parents=True, exist_ok=True)
    series = series_frame(result)
    _atomic_write(cells_dir / f"{cell['id']}.parquet", lambda p: series.to_parquet(p, index=False))
    write_cell_record(cells_dir, record)
    return record


@functools.lru_cache(maxsize=1)
def code_fingerprint() -> str:
    """sha256 (first 12 hex digits) of the twin package's Python sources, taken once per
    process when its first cell starts: cells computed by different code are told apart when
    results merge."""
    root = Path(__file__).resolve().parent
    digest = hashlib.sha256()
    for path in sorted(root.rglob("*.py")):
        digest.update(str(path.relative_to(root)).encode())
        digest.update(path.read_bytes())
    return digest.hexdigest()[:12]


def _isnan(value: Any) -> bool:
    return isinstance(value, float) and value != value


def write_cell_record(cells_dir: Path, record: dict[str, Any]) -> None:
    """The cell's JSON: written last, it marks the cell as done."""
    text = json.dumps(record, indent=1, default=_json_default)
    _atomic_write(cells_dir / f"{record['id']}.json", lambda p: p.write_text(text))


def _json_default(value: Any) -> Any:
    if isinstance(value, np.generic):
        return value.item()
    raise TypeError(f"not JSON serialisable: {type(value).__name__}")


# --- executors ------------------------------------------------------------------------------


#: What an executor yields per cell: (cell id, result record or None, error message or None).
Outcome = tuple[str, dict[str, Any] | None, str | None]


def _error_line(exc: BaseException) -> str:
    cause = getattr(exc, "cause", None) or exc  # Ray wraps the task's exception
    text = str(cause).strip().splitlines()
    return f"{type(cause).__name__}: {text[0] if text else ''}"


def _local_executor(cells: list[dict], workers: int) -> Iterable[Outcome]:
    """Run cells on a process pool (spawn: one fresh interpreter, hence one SUMO, per worker)."""
    context = multiprocessing.get_context("spawn")
    pool = ProcessPoolExecutor(max_workers=workers, mp_context=context)
    try:
        pending = {pool.submit(run_cell, cell): cell["id"] for cell in cells}
        while pending:
            done, _ = wait(pending, return_when=FIRST_COMPLETED)
            for future in done:
                cid = pending.pop(future)
                try:
                    yield cid, future.result(), None
                except BrokenProcessPool as exc:
                    raise UserError(
                        f"a sweep worker died while running cell {cid} ({exc}); finished cells "
                        "are saved, rerun the same command to resume"
                    ) from None
                except Exception as exc:
                    yield cid, None, _error_line(exc)
    finally:
        pool.shutdown(wait=True, cancel_futures=True)


def _ray_executor(cells: list[dict], workers: int, address: str | None) -> Iterable[Outcome]:
    """Run cells as Ray tasks, one CPU each, on a cluster at ``address`` or a local one."""
    os.environ.setdefault("RAY_USAGE_STATS_ENABLED", "0")  # offline: never phone home
    try:
        import ray
    except ImportError:
        raise UserError("--executor ray needs Ray: pip install 'twin[ray]'") from None
    started = False
    if not ray.is_initialized():
        if address:
            ray.init(address=address, log_to_driver=False)
        else:
            ray.init(
                num_cpus=workers,
                include_dashboard=False,
                log_to_driver=False,
                configure_logging=False,
            )
        started = True
    pending: dict = {}
    try:
        task = ray.remote(num_cpus=1, max_retries=0)(run_cell)
        pending = {task.remote(cell): cell["id"] for cell in cells}
        while pending:
            done, _ = ray.wait(list(pending), num_returns=1)
            for ref in done:
                cid = pending.pop(ref)
                try:
                    yield cid, ray.get(ref), None
                except Exception as exc:
                    yield cid, None, _error_line(exc)
    finally:
        for ref in pending:
            ray.cancel(ref, force=True)
        if started:
            ray.shutdown()


@dataclass
class SweepOutcome:
    out_dir: Path
    ran: list[str]
    skipped: list[str]
    seconds: float
    summary: pd.DataFrame
    failed: dict[str, str] = field(default_factory=dict)


def run_sweep(
    config: SweepConfig,
    out_dir: str | Path,
    executor: str = "local",
    workers: int | None = None,
    address: str | None = None,
    progress: bool = False,
    report: bool = True,
) -> SweepOutcome:
    """Run every cell not yet done, then merge all cells and write the sweep report.

    A cell that fails does not stop the others; after merging what is done, the failures are
    raised as one :class:`UserError` (and listed in ``failed.json``).
    """
    if executor not in EXECUTORS:
        raise UserError(f"--executor {executor!r}: choose from {', '.join(EXECUTORS)}")
    out_dir = Path(out_dir)
    (out_dir / CELLS_DIR).mkdir(parents=True, exist_ok=True)
    cells = expand_cells(config, out_dir)
    done = done_cells(out_dir)
    todo = [c for c in cells if c["id"] not in done]
    skipped = [c["id"] for c in cells if c["id"] in done]
    _write_manifest(out_dir, config, cells)
    check_cells(todo)
    workers = max(1, min(workers or os.cpu_count() or 1, len(todo) or 1))
    start = time.perf_counter()
    ran: list[str] = []
    failed: dict[str, str] = {}
    if todo:
        outcomes = (
            _local_executor(todo, workers)
            if executor == "local"
            else _ray_executor(todo, workers, address)
        )
        bar = _progress(len(todo), progress)
        try:
            for cid, record, error in outcomes:
                if record is None:
                    failed[cid] = error or "unknown error"
                else:
                    if not (out_dir / CELLS_DIR / f"{cid}.json").exists():
                        write_cell_record(out_dir / CELLS_DIR, record)  # a worker without our disk
                    ran.append(cid)
                if bar is not None:
                    bar.update(1)
        finally:
            if bar is not None:
                bar.close()
    seconds = time.perf_counter() - start
    _write_manifest(
        out_dir,
        config,
        cells,
        {
            "executor": executor,
            "workers": workers,
            "address": address,
            "ran": len(ran),
            "skipped": len(skipped),
            "failed": len(failed),
            "wall_seconds": round(seconds, 3),
            "finished": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
        },
    )
    failed_path = out_dir / "failed.json"
    if failed:
        failed_path.write_text(json.dumps(failed, indent=2))
    else:
        failed_path.unlink(missing_ok=True)
    _, summary = merge(out_dir, [c["id"] for c in cells], config)
    if report and not summary.empty:
        write_sweep_report(out_dir)
    if failed:
        cid, error = next(iter(failed.items()))
        raise UserError(
            f"{len(failed)} of {len(todo)} cells failed (first: {cid}: {error}); the other cells "
            f"are saved in {out_dir}, fix the cause and rerun to run only the missing ones"
        )
    return SweepOutcome(out_dir, ran, skipped, seconds, summary, failed)


def check_cells(cells: list[dict[str, Any]]) -> None:
    """Validate every distinct scenario config and overrides before running anything."""
    seen = set()
    for cell in cells:
        key = (cell["config"], json.dumps(cell["overrides"], sort_keys=True, default=str))
        if key in seen:
            continue
        seen.add(key)
        try:
            config = scenario_config(Path(cell["config"]), cell["overrides"])
            if config.traffic["kind"] == "sumo" and cell.get("tape") is None:
                prepare_sumo(config)
        except UserError as exc:
            raise UserError(
                f"scenario {cell['scenario']!r} with {cell['overrides']}: {exc}"
            ) from None


def prepare_sumo(config) -> None:
    """Check a SUMO scenario's settings and build its built-in network once, here, so that
    parallel cells never build the same network at the same time."""
    from twin.sumo.network import build_named_network
    from twin.sumo.scenario import sumo_settings

    settings = sumo_settings(config)
    if settings.network and not (settings.net or settings.sumocfg or settings.osm):
        build_named_network(settings.network)


def _progress(total: int, enabled: bool):
    if not enabled:
        return None
    from tqdm.auto import tqdm

    return tqdm(total=total, desc="sweep", unit="cell", dynamic_ncols=True, file=sys.stderr)


def done_cells(out_dir: Path) -> set[str]:
    """Ids of the cells whose result JSON exists (the JSON is written last)."""
    return {p.stem for p in (out_dir / CELLS_DIR).glob("*.json") if not p.name.startswith(".")}


def _write_manifest(
    out_dir: Path, config: SweepConfig, cells: list[dict], invocation: dict[str, Any] | None = None
) -> None:
    """sweep.json: the sweep's definition, its cells and one entry per invocation (timings)."""
    path = out_dir / "sweep.json"
    history = []
    if path.exists():
        try:
            history = json.loads(path.read_text()).get("invocations", [])
        except json.JSONDecodeError:
            history = []
    manifest = {
        "name": config.name,
        "config": str(config.path),
        "swarms": config.swarms,
        "seeds": config.seeds,
        "scenarios": [s.name for s in config.scenarios],
        "parameters": config.parameters,
        "cells": [c["id"] for c in cells],
        "invocations": history + ([invocation] if invocation else []),
    }
    text = json.dumps(manifest, indent=2, default=str)
    _atomic_write(path, lambda p: p.write_text(text))


def merge(
    out_dir: Path, ids: list[str] | None = None, config: SweepConfig | None = None
) -> tuple[pd.DataFrame, pd.DataFrame]:
    """results.csv (one row per cell and swarm) and summary.csv (mean, 95% interval over seeds)."""
    from twin.metrics import aggregate

    if ids is None:
        ids = json.loads((out_dir / "sweep.json").read_text())["cells"]
    parameters = list(config.parameters) if config else None
    rows = []
    for cid in ids:
        path = out_dir / CELLS_DIR / f"{cid}.json"
        if not path.exists():
            continue
        record = json.loads(path.read_text())
        cell = record["cell"]
        for row in record["rows"]:
            rows.append(
                {
                    "cell": cid,
                    "scenario": cell["scenario"],
                    **cell["parameters"],
                    "seed": cell["seed"],
                    **row,
                    "seconds": record["seconds"],
                    "code": record.get("code"),
                }
            )
    results = pd.DataFrame(rows)
    if results.empty:
        return results, results
    if parameters is None:
        parameters = [c for c in results.columns if "." in c]
    by = ["scenario", *parameters, "swarm"]
    summary = aggregate(results, by=by)
    _atomic_write(out_dir / "results.csv", lambda p: results.to_csv(p, index=False))
    _atomic_write(out_dir / "summary.csv", lambda p: summary.to_csv(p, index=False))
    return results, summary


def write_sweep_report(out_dir: str | Path) -> Path:
    """The sweep report (HTML + Markdown) from summary.csv, results.csv and the cells' series."""
    from twin.report.sweep import write_sweep_report as write

    return write(Path(out_dir))
