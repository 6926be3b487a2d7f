"""A sweep's cells: expansion of scenarios x parameters x seeds into plain dicts, their ids
(a hash of everything that defines their numbers), and :func:`run_cell`, which runs one cell
anywhere (a pool worker, a Ray task) and writes its result files atomically.

The cell's seed fixes the drones' starts (``default_rng(seed)``, as ``twin evaluate``), the
swarms' randomness (``run_patrol``) and the traffic's, so the same seeds give the same numbers on
either executor and in ``twin evaluate``.
"""

from __future__ import annotations

import contextlib
import copy
import functools
import hashlib
import itertools
import json
import os
import time
from pathlib import Path
from typing import Any

from twin.errors import UserError
from twin.files import atomic_write, file_sha256, rebased
from twin.sweep.config import OPTION_FILES, SweepConfig
from twin.sweep.store import CELLS_DIR, write_cell_record


def parameter_combinations(parameters: dict[str, list[Any]]) -> list[dict[str, Any]]:
    """Every combination of the swept values (one empty combination when none is swept)."""
    keys = list(parameters)
    return [
        dict(zip(keys, values, strict=True)) for values in itertools.product(*parameters.values())
    ]


#: What defines a cell's numbers; the cell id hashes these.
DEFINING_KEYS = (
    "scenario", "config", "overrides", "tape", "seed", "swarms", "swarm_options", "checkpoints",
    "inputs",
)  # fmt: skip


def cell_id(cell: dict[str, Any]) -> str:
    """``<scenario>-s<seed>-<hash>``: the hash covers everything that defines the cell's numbers
    (a retrained checkpoint, a changed scenario file, tape or option file, their paths or the
    overrides give new cells; the SUMO files a live cell loaded are checked when it is resumed,
    :func:`twin.sweep.store.inputs_changed`)."""
    defining = {k: cell.get(k) for k in DEFINING_KEYS}
    if cell.get("home"):  # the files of a folder that may move, named relative to it
        defining = rebased(defining, cell["home"], ".")
    if cell.get("ceilings"):  # only when asked for, so earlier sweeps keep their ids
        defining["ceilings"] = True
    digest = hashlib.sha1(json.dumps(defining, sort_keys=True, default=str).encode()).hexdigest()[
        :10
    ]
    return f"{cell['scenario']}-s{cell['seed']}-{digest}"


def expand_cells(config: SweepConfig, out_dir: Path) -> list[dict[str, Any]]:
    """The sweep's cells, scenario-major, then parameters, then seeds."""
    checkpoints = {  # every option file's content: a checkpoint, a history
        swarm if key == "checkpoint" else f"{swarm}.{key}": file_sha256(options[key])
        for swarm, options in config.swarm_options.items()
        for key in OPTION_FILES
        if isinstance(options.get(key), str) and Path(options[key]).is_file()
    }
    cells = []
    for scenario in config.scenarios:
        for params in parameter_combinations(config.parameters):
            overrides = {**scenario.overrides, **params}
            inputs = cell_inputs(scenario.config, overrides, scenario.tape)
            for seed in config.seeds:
                cell = {
                    "scenario": scenario.name,
                    "config": str(scenario.config),
                    "overrides": overrides,
                    "parameters": params,
                    "labels": override_labels(
                        config.path, scenario, params, config._scenario_table
                    ),
                    "tape": str(scenario.tape) if scenario.tape else None,
                    "seed": int(seed),
                    "swarms": list(config.swarms),
                    "swarm_options": copy.deepcopy(config.swarm_options),
                    "checkpoints": checkpoints,
                    "inputs": inputs,
                    "cells_dir": str(out_dir / CELLS_DIR),
                }
                if config.sweep.ceilings:
                    cell["ceilings"] = True
                if config._home is not None:
                    cell["home"] = str(config._home)
                cell["id"] = cell_id(cell)
                cells.append(cell)
    return cells


def cell_inputs(config: Path, overrides: dict[str, Any], tape: Path | None) -> dict[str, str]:
    """``{path: sha256}`` of the files that define a cell's numbers besides its settings: the
    scenario config, the tape it replays and the checkpoints and histories its own
    ``[swarm_options]`` name (after ``overrides``), and a sumocfg's options as SUMO reads them
    (``${VAR}`` substituted: a variable now naming another route file is another cell); a file
    that cannot be read is left to the cell's checks, which say why."""
    paths = [Path(config), *([Path(tape)] if tape else [])]
    try:
        scenario = scenario_config(Path(config), overrides)
    except UserError:
        scenario = None  # check_cells refuses it, naming the scenario
    if scenario is not None:
        for options in scenario.swarm_options.values():
            for key in OPTION_FILES:
                if isinstance(options.get(key), str):
                    paths.append(scenario.path.parent / options[key])
    inputs = {}
    if scenario is not None and scenario.traffic.kind == "sumo":
        inputs.update(_sumocfg_options_digest(scenario))
    for path in paths:
        with contextlib.suppress(OSError):
            if path.is_file():
                inputs[os.path.abspath(path)] = file_sha256(path)
    return inputs


def _sumocfg_options_digest(scenario) -> dict[str, str]:
    """``{"<sumocfg>#options": sha256}`` of the options a scenario's sumocfg sets, read with its
    variables substituted, and of the files they name (``~`` expanded), or nothing (no
    sumocfg, or one the cell's checks refuse)."""
    from twin.sumo.readers import as_given, read_sumocfg
    from twin.sumo.scenario import sumo_settings

    settings = sumo_settings(scenario)
    if settings.sumocfg is None:
        return {}
    try:
        sumocfg = read_sumocfg(Path(settings.sumocfg), own_net=settings.net is None)
    except (UserError, OSError):
        return {}
    files = [str(as_given(p)) for p in sumocfg.files()]  # where SUMO finds them
    text = json.dumps([sumocfg.options, files], sort_keys=True).encode()
    return {f"{as_given(Path(settings.sumocfg))}#options": hashlib.sha256(text).hexdigest()}


def scenario_config(path: Path, overrides: dict[str, Any], labels: dict[str, str] | None = None):
    """The scenario config at ``path`` with dotted-key ``overrides`` applied, validated
    (:func:`twin.config.with_overrides`: an error names the key, by its label in ``labels``
    when it has one: the sweep file's key that set it)."""
    from twin.config import load_config, with_overrides

    return with_overrides(load_config(path), overrides, labels=labels)


def override_labels(
    sweep: Path, scenario, params: dict[str, Any], table: str = "[[scenario]]"
) -> dict[str, str]:
    """Each override's key in the sweep file ``sweep`` that set it: a ``[parameters]`` key, or
    the ``overrides`` of the scenario (its ``table``: a transfer's ``[[column]]``), named in a
    refusal instead of the scenario's file."""
    labels = {k: f"{sweep}: {table} {scenario.name}.overrides.{k!r}" for k in scenario.overrides}
    return {**labels, **{k: f"{sweep}: [parameters].{k!r}" for k in params}}


def run_cell(cell: dict[str, Any]) -> dict[str, Any]:
    """Run one cell (plain dict in, plain dict out) through the experiment runner and write its
    result files atomically. The cell's seed is the drones' seed and, live, SUMO's seed.

    Returns ``{"id", "seconds", "rows": [one dict per swarm: Table 2 and monitoring columns],
    "error", ...}``.
    """
    from twin.boundary import drop_notices, hold_notices

    drop_notices()  # a worker's earlier cell that failed keeps none of its notices
    hold_notices(to_end=True)  # sent back with the record and said once by the sweep; a
    try:  # failing cell is its error alone
        record = _run_cell(cell)
    finally:
        notices = drop_notices()
    return {**record, "notices": notices}


def _run_cell(cell: dict[str, Any]) -> dict[str, Any]:
    from twin.experiment import Experiment, limit_threads, run_experiment, run_metadata
    from twin.monitoring import monitor_run
    from twin.runs import seed_table, series_frame, step_seconds_of

    limit_threads()  # one core per cell: the pool provides the parallelism
    code = code_fingerprint()
    start = time.perf_counter()
    seed = int(cell["seed"])
    config = scenario_config(Path(cell["config"]), cell["overrides"], cell.get("labels"))
    experiment = Experiment(
        config,
        swarms=cell["swarms"],
        seeds=[seed],
        swarm_options=cell.get("swarm_options", {}),
        tape=Path(cell["tape"]) if cell.get("tape") else None,
        traffic_seed=seed,
        max_memory_gb=cell.get("max_memory_gb"),
    )
    outcome = run_experiment(experiment)
    result = outcome.results[0]
    if result.error:  # a partial run is no cell's result: nothing written, the cell is failed
        raise UserError(f"its run did not finish: {result.error}")
    meta = run_metadata(outcome, "sweep-cell")
    rows = seed_table(result, config.params, step_seconds_of(meta), monitor_run(result))
    if cell.get("ceilings"):  # the oracle and the bound on this cell's true maps
        import pandas as pd

        from twin.ceilings import ceiling_table

        rows["role"] = "swarm"
        rows = pd.concat([rows, ceiling_table(result, config.params)], ignore_index=True)
    rows = rows.drop(columns="seed").to_dict(orient="records")
    record = {
        "id": cell["id"],
        "cell": {k: v for k, v in cell.items() if k not in ("cells_dir", "max_memory_gb")},
        "traffic": outcome.traffic[0],
        "policies": outcome.policies,
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
    atomic_write(cells_dir / f"{cell['id']}.parquet", lambda p: series.to_parquet(p, index=False))
    write_cell_record(cells_dir, record)
    return record


@functools.lru_cache(maxsize=1)
def code_fingerprint() -> str:
    """sha256 (first 12 hex digits) of the twin package's Python sources, taken once per
    process when its first cell starts: cells computed by different code are told apart when
    results merge."""
    root = Path(__file__).resolve().parents[1]  # the twin package
    digest = hashlib.sha256()
    for path in sorted(root.rglob("*.py")):
        digest.update(str(path.relative_to(root)).encode())
        digest.update(path.read_bytes())
    return digest.hexdigest()[:12]


def _isnan(value: Any) -> bool:
    return isinstance(value, float) and value != value
