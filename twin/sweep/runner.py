"""Running a sweep: expand its cells, skip those done, validate the rest, run them on an
executor, then merge the results and write the report."""

from __future__ import annotations

import json
import os
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import pandas as pd

from twin.boundary import folder_claimed, notify, release_notices
from twin.errors import UserError
from twin.executors import EXECUTORS, _local_executor, _ray_executor
from twin.files import atomic_write
from twin.sweep.cells import expand_cells, run_cell, scenario_config
from twin.sweep.config import SweepConfig
from twin.sweep.store import (
    CELLS_DIR,
    _write_manifest,
    done_cells,
    merge,
    write_cell_record,
    write_sweep_report,
)


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
    max_memory_gb: float | None = None,
) -> SweepOutcome:
    """Run every cell not yet done, then merge all cells and write the sweep report.

    A cell that fails does not stop the others; after merging what is done, the failures are
    raised as one :class:`UserError` (and listed in ``failed.json``). ``max_memory_gb``
    (``--max-memory-gb``) bounds each cell's memory estimate, as ``twin evaluate``'s.
    """
    if executor not in EXECUTORS:
        raise UserError(f"--executor {executor!r}: choose from {', '.join(EXECUTORS)}")
    out_dir = Path(out_dir)
    cells = expand_cells(config, out_dir)
    done = done_cells(out_dir, {c["id"]: c for c in cells})
    todo = [c for c in cells if c["id"] not in done]
    for cell in todo:  # not a defining key: the limit changes no number
        cell["max_memory_gb"] = max_memory_gb
    skipped = [c["id"] for c in cells if c["id"] in done]
    # before anything is written: a refused sweep leaves no folder (a transfer's sweep has no
    # [swarm_options] of its own file to name)
    check_cells(todo, config.path if config._home is None else None)
    if report:
        from twin.report.sweep import check_sweep_report_folder

        check_sweep_report_folder(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    with folder_claimed(out_dir):  # one sweep at a time writes into a sweep folder
        return _run_cells(
            config, out_dir, cells, todo, skipped, executor, workers, address, progress, report
        )


def _run_cells(
    config: SweepConfig,
    out_dir: Path,
    cells: list[dict[str, Any]],
    todo: list[dict[str, Any]],
    skipped: list[str],
    executor: str,
    workers: int | None,
    address: str | None,
    progress: bool,
    report: bool,
) -> SweepOutcome:
    """:func:`run_sweep`'s work once its cells are checked and its folder is held: run
    ``todo``, merge every cell, write the report."""
    (out_dir / CELLS_DIR).mkdir(exist_ok=True)
    _write_manifest(out_dir, config, cells)
    release_notices()  # every cell is valid: what the checks noticed is printed now
    workers = max(1, min(workers or os.cpu_count() or 1, len(todo) or 1))
    start = time.perf_counter()
    ran: list[str] = []
    failed: dict[str, str] = {}
    if todo:
        outcomes = (
            _local_executor(todo, workers, run_cell)
            if executor == "local"
            else _ray_executor(todo, workers, address, run_cell)
        )
        bar = _progress(len(todo), progress)
        try:
            for cid, record, error in outcomes:
                if record is None:
                    failed[cid] = error or "unknown error"
                else:
                    for line in record.pop("notices", []):
                        notify(line)  # each once, whichever cells said it
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
        text = json.dumps(failed, indent=2)
        atomic_write(failed_path, lambda p: p.write_text(text))
    else:
        failed_path.unlink(missing_ok=True)
    _, summary = merge(out_dir, [c["id"] for c in cells], config)
    if report and not summary.empty:
        write_sweep_report(out_dir)
    if failed:
        cid, error = next(iter(failed.items()))
        raise UserError(
            f"{len(failed)} of {len(todo)} cells failed (first: {cid}: {error}; all in "
            f"{failed_path}); the other cells are saved in {out_dir}, fix the cause and rerun "
            "to run only the missing ones"
        )
    return SweepOutcome(out_dir, ran, skipped, seconds, summary, failed)


def check_cells(cells: list[dict[str, Any]], sweep_file: Path | None = None) -> None:
    """Validate every distinct scenario config and overrides before running anything: a live
    one is built as its cells build it (files, window, grid, incidents, detectors), without
    starting SUMO; one whose grid is known (synthetic, a tape) has its memory estimated
    against the sweep's limit, as its cells will; every swarm is built with its options (a
    swarm that plans on a history reads it), an option the sweep file's own
    ``[swarm_options]`` gives refused naming ``sweep_file``.
    """
    from twin.experiment import check_swarm_outages
    from twin.swarms import base_name

    seen = set()
    for cell in cells:
        key = (cell["config"], json.dumps(cell["overrides"], sort_keys=True, default=str))
        if key in seen:
            continue
        seen.add(key)
        try:
            config = scenario_config(Path(cell["config"]), cell["overrides"], cell.get("labels"))
            if config.traffic.kind == "sumo" and cell.get("tape") is None:
                prepare_sumo(config)
                horizon = live_settings(config, int(cell["seed"]))["horizon"]
            else:
                horizon = check_cell_memory(config, cell)
            for name in cell["swarms"]:  # a history read now, not after the cell's SUMO ran
                options = cell.get("swarm_options", {}).get(name, {})
                try:  # the sweep's options on the scenario's, as the cell runs
                    policy = config.make_swarm(name, **options)
                except UserError as exc:
                    text = str(exc)
                    lead = (f"{base_name(name)}: ", "[swarm_options.")
                    if not options or sweep_file is None or not text.startswith(lead):
                        raise  # not an option of the sweep's own table
                    if not text.startswith("[swarm_options."):
                        text = f"[swarm_options.{name}]: " + text.removeprefix(
                            f"{base_name(name)}: "
                        )
                    raise UserError(f"{sweep_file}: {text}") from None
                if horizon is not None:
                    check_swarm_outages(
                        config, {name: policy}, horizon, {name: options}, sweep_file
                    )
        except UserError as exc:
            if sweep_file is not None and str(exc).startswith(f"{sweep_file}: [swarm_"):
                raise
            if any(str(exc).startswith(label) for label in cell.get("labels", {}).values()):
                raise UserError(
                    f"{exc} (scenario {cell['scenario']!r}, {cell['config']})"
                ) from None
            raise UserError(
                f"scenario {cell['scenario']!r} with {cell['overrides']}: {exc}"
            ) from None


def check_cell_memory(config, cell: dict[str, Any]) -> int | None:
    """The memory estimate of a cell whose grid is known before it runs, against the limit its
    run will have (the sweep's ``--max-memory-gb``); the cell's horizon (``None`` for a broken
    tape, whose reader says why)."""
    from twin.experiment import Experiment, check_memory, planned_shape

    tape = Path(cell["tape"]) if cell.get("tape") else None
    experiment = Experiment(config, swarms=cell["swarms"], seeds=[int(cell["seed"])], tape=tape,
                            max_memory_gb=cell.get("max_memory_gb"))  # fmt: skip
    shape, horizon = planned_shape(experiment)
    check_memory(experiment, shape, horizon)
    return horizon


def live_settings(config, seed: int) -> dict[str, Any]:
    """The settings (``metadata()``, as JSON reads them) of a live scenario's source for SUMO
    seed ``seed``, built as a cell or a tape builds it (reading its files, laying its grid) and
    closed unstarted: what it refuses is refused here, before any cell or tape runs."""
    from twin.traffic_kinds import build_traffic

    source = build_traffic(config, 0, seed)
    try:
        return json.loads(json.dumps(source.metadata(), default=str))
    finally:
        close = getattr(source, "close", None)
        if close is not None:
            close()


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
