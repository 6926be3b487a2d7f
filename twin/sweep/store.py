"""A sweep folder's files: one ``cells/<id>.json`` (+ ``.parquet`` series) per finished cell,
``sweep.json`` (definition, cells, invocations), and the merged ``results.csv`` and
``summary.csv``. Every file is written atomically; a cell's JSON, written last, marks it done.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
import pandas as pd

from twin.errors import UserError
from twin.files import atomic_write, file_sha256, read_record
from twin.readback import CELL_SERIES_COLUMNS

if TYPE_CHECKING:
    from twin.sweep.config import SweepConfig

CELLS_DIR = "cells"
#: Names twin writes into a sweep folder: a folder holding anything else is not a sweep's.
SWEEP_FILE_NAMES = frozenset(
    {CELLS_DIR, "sweep.json", "results.csv", "summary.csv", "failed.json", "report", "error.log"}
)
#: A damaged sweep.json is kept under this name (``.1``, ``.2``... when taken), not overwritten.
DAMAGED_RECORD = "sweep.json.damaged"
#: Columns of results.csv that identify a cell (plus one column per swept parameter).
KEY_COLUMNS = ("cell", "scenario", "seed", "swarm")


def check_sweep_folder(out_dir: Path) -> None:
    """One-line :class:`UserError` if ``out_dir`` holds anything a sweep does not write: a sweep
    resumes in its own folder, and never writes over a user's files."""
    out_dir = Path(out_dir)
    if not out_dir.is_dir():
        return
    foreign = sorted(
        p.name
        for p in out_dir.iterdir()
        if p.name not in SWEEP_FILE_NAMES
        and not (p.name.startswith(".") and ".tmp" in p.name)
        and not p.name.startswith(DAMAGED_RECORD)
    )
    fix = "give an empty or new folder, or the folder of the sweep to resume"
    for name in sorted(SWEEP_FILE_NAMES):
        path = out_dir / name
        folder = name in (CELLS_DIR, "report")
        if path.exists() and not (path.is_dir() if folder else path.is_file()):
            what = "a folder" if path.is_dir() else "a pipe or device"
            want = "a folder" if folder else "a file"
            raise UserError(
                f"--out {out_dir}: {name} is {what if not folder else 'not a folder'}, where "
                f"the sweep writes {want}; remove it, or {fix}"
            )
    if foreign:
        raise UserError(f"--out {out_dir}: holds {foreign[0]!r}, which no twin sweep writes; {fix}")
    names = {p.name for p in out_dir.iterdir()}
    if names and not names & {"sweep.json", CELLS_DIR}:
        raise UserError(
            f"--out {out_dir}: holds {sorted(names)[0]!r} but no sweep.json, so no twin sweep "
            f"wrote it; {fix}"
        )


def write_cell_record(cells_dir: Path, record: dict[str, Any]) -> None:
    """The cell's JSON: written last, it marks the cell as done."""
    text = json.dumps(record, indent=1, default=_json_default)
    atomic_write(cells_dir / f"{record['id']}.json", lambda p: p.write_text(text))


def _json_default(value: Any) -> Any:
    if isinstance(value, np.generic):
        return value.item()
    raise TypeError(f"not JSON serialisable: {type(value).__name__}")


def done_cells(out_dir: Path, expected: dict[str, dict[str, Any]] | None = None) -> set[str]:
    """Ids of the cells whose result JSON exists (the JSON is written last) and reads back
    whole with its series, agreeing with it (and with the ``expected`` cell of its id, when
    given); a damaged cell is reported in one line and is not done, so the sweep computes it
    again."""
    from twin.notices import notify

    done = set()
    for path in sorted((out_dir / CELLS_DIR).glob("*.json")):
        if path.name.startswith("."):
            continue
        if expected is not None and path.stem not in expected:
            continue  # no cell of this sweep (an earlier definition's): not read, not merged
        try:
            record = read_cell(path)
            check_cell(path, record, (expected or {}).get(path.stem))
        except UserError as exc:
            reason = str(exc).split("; ")[0]
            notify(
                f"twin: notice: sweep cell {path.stem} is damaged ({reason}); computing it again"
            )
            continue
        changed = inputs_changed(record)
        if changed:
            notify(
                f"twin: notice: sweep cell {path.stem}'s {changed} changed since it ran; "
                "computing it again"
            )
            continue
        if record.get("error"):  # a partial run: failed, not done
            notify(
                f"twin: notice: sweep cell {path.stem} did not finish last time "
                f"({record['error']}); computing it again"
            )
            continue
        done.add(path.stem)
    return done


def inputs_changed(record: dict[str, Any]) -> str | None:
    """The first SUMO file a finished live cell loaded (its traffic identity: network, route,
    additional files, sumocfg and what they include) whose content is no longer what the cell
    ran on, in words (``route file /path``), or None: a resumed sweep runs such a cell again."""
    traffic = record.get("traffic")
    identity = traffic.get("identity") if isinstance(traffic, dict) else None
    files = identity.get("files") if isinstance(identity, dict) else None
    for entry in files if isinstance(files, list) else []:
        if not isinstance(entry, dict):
            continue
        role, path, sha = entry.get("role"), entry.get("path"), entry.get("sha256")
        if not isinstance(path, str):
            continue
        try:
            now = file_sha256(path)
        except OSError:
            now = None
        if now != sha:
            return f"{role} {path}"
    return None


def _write_manifest(
    out_dir: Path, config: SweepConfig, cells: list[dict], invocation: dict[str, Any] | None = None
) -> None:
    """sweep.json: the sweep's definition, its cells and one entry per invocation (timings)."""
    path = out_dir / "sweep.json"
    history = []
    if path.exists():
        try:
            history = json.loads(read_record(path))["invocations"]
            if not isinstance(history, list):
                raise TypeError("invocations is not a list")
        except (OSError, ValueError, KeyError, TypeError) as exc:
            from twin.notices import notify

            kept = _free_name(path.with_name(DAMAGED_RECORD))
            path.rename(kept)
            notify(
                f"twin: notice: {path} was damaged ({type(exc).__name__}); kept as {kept.name}, "
                "and a new record of the sweep's invocations is started"
            )
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
    atomic_write(path, lambda p: p.write_text(text))


def _free_name(path: Path) -> Path:
    """``path``, or ``path.1``, ``path.2``... : the first name not taken."""
    candidate, n = path, 0
    while candidate.exists():
        n += 1
        candidate = path.with_name(f"{path.name}.{n}")
    return candidate


def check_cell(path: Path, record: dict[str, Any], expected: dict[str, Any] | None) -> None:
    """A finished cell agrees with itself: its id, seed, scenario and parameters those of the
    cell it was run for, one row per swarm of the cell with a finite ``R_hat_T`` >= 0 equal to
    its series' mean reward (Def. 4) in ``cells/<id>.parquet``."""
    from twin.metrics import series_columns
    from twin.readback import FINITE, check_bounds, read_table

    cell = record["cell"]
    if record.get("id") != path.stem or not path.stem.startswith(
        f"{cell['scenario']}-s{cell['seed']}-"
    ):
        raise UserError(f"{path}: its id, scenario or seed is not the file's ({path.stem})")
    if expected is not None:
        for key in ("scenario", "seed", "parameters", "swarms", "inputs"):
            if key in expected and cell.get(key) != expected.get(key):
                raise UserError(f"{path}: cell.{key} = {cell.get(key)!r} is not the cell's")
    rows = pd.DataFrame(record["rows"])
    if "R_hat_T" not in rows.columns or "swarm" not in rows.columns:
        raise UserError(f"{path}: rows without swarm or R_hat_T")
    swarm_rows = rows[rows["role"] != "ceiling"] if "role" in rows.columns else rows
    swarms = [str(s) for s in swarm_rows["swarm"]]
    if sorted(swarms) != sorted(map(str, cell.get("swarms", swarms))):
        raise UserError(f"{path}: rows of swarms {swarms}, the cell runs {cell.get('swarms')}")
    for column in rows.columns:  # numbers, or null where a figure is undefined (NaN)
        if column in CELL_TEXT_COLUMNS:
            continue
        kinds = [v for v in rows[column] if v is not None and not _is_number(v)]
        if kinds:
            raise UserError(f"{path}: rows' {column} holds {kinds[0]!r}, not a number")
    values = pd.to_numeric(swarm_rows["R_hat_T"], errors="coerce").to_numpy(dtype=float)
    if not np.isfinite(values).all():
        raise UserError(f"{path}: an R_hat_T is not a finite number")
    check_bounds(path, swarm_rows)
    series_path = path.with_suffix(".parquet")
    if not series_path.is_file():
        raise UserError(f"{series_path}: missing")
    columns = {**CELL_SERIES_COLUMNS, "reward": FINITE, "coverage": FINITE,
               "visited_share": FINITE}  # fmt: skip
    series = read_table(series_path, columns)
    check_cell_series(series_path, series, int(cell["seed"]), swarms, record.get("horizon"))
    wide = series.assign(swarm=series["swarm"].astype(str)).pivot(index="swarm", columns="step")
    wide = wide.loc[swarms]
    want = series_columns(
        wide["reward"].to_numpy(np.float64),
        wide["coverage"].to_numpy(np.float64),
        wide["visited_share"].to_numpy(np.float64),
    )
    for column, expected_values in want.items():
        if column not in swarm_rows.columns:
            continue
        have = pd.to_numeric(swarm_rows[column], errors="coerce").to_numpy(dtype=float)
        for swarm, h, w in zip(swarms, have, expected_values, strict=True):
            if not (abs(h - w) <= 1e-9 * max(1.0, abs(w))):
                raise UserError(
                    f"{path}: swarm {swarm!r} has {column} = {h:.6g}, its series give {w:.6g}"
                )


#: Columns of a cell's rows that hold text (the others hold numbers, or null).
CELL_TEXT_COLUMNS = ("swarm", "role", "oracle_swarm")


def _is_number(value: Any) -> bool:
    return isinstance(value, (int, float)) and not isinstance(value, bool)


def check_cell_series(
    path: Path, series: pd.DataFrame, seed: int, swarms: list[str], horizon: Any
) -> None:
    """A cell's series: of its seed, each swarm's steps ``0 .. T-1`` once (``T`` the record's
    ``horizon``), coverage and visited shares within 0 .. 1 (Def. 5), the cumulative reward the
    running sum of the rewards."""
    if set(series["seed"].unique()) != {seed}:
        raise UserError(
            f"{path}: rows of seeds {sorted(set(series['seed']))}, the cell's is {seed}"
        )
    names = series["swarm"].astype(str)
    if sorted(set(names)) != sorted(swarms):
        raise UserError(f"{path}: series of swarms {sorted(set(names))}, the cell runs {swarms}")
    steps = int(horizon) if isinstance(horizon, int) and not isinstance(horizon, bool) else None
    for swarm, part in series.groupby(names):
        got = np.sort(part["step"].to_numpy())
        if steps is None or not np.array_equal(got, np.arange(steps)):
            raise UserError(
                f"{path}: swarm {swarm!r} has steps {got[:3].tolist()} .. ({len(got)} rows), not "
                f"each of 0 .. {steps} - 1 once (the record's horizon)"
            )
        ordered = part.sort_values("step")
        running = ordered["reward"].cumsum().to_numpy()
        if not np.allclose(ordered["cumulative_reward"].to_numpy(), running, rtol=1e-9, atol=1e-9):
            raise UserError(f"{path}: swarm {swarm!r}'s cumulative_reward is not its rewards' sum")
    for column in ("coverage", "visited_share"):
        values = series[column].to_numpy(dtype=float)
        if ((values < 0) | (values > 1)).any():
            raise UserError(f"{path}: {column} holds values outside 0 .. 1 (shares)")


CELL_FIELDS: dict[str, Any] = {
    "cell": {"scenario": str, "parameters": dict, "seed": int},
    "rows": list,
    "seconds": (int, float),
    "code": str,
}


def read_cell(path: Path) -> dict[str, Any]:
    """One cell's result record, checked; a damaged one is a one-line error that says to
    delete it (the next run of the sweep computes the cell again)."""
    from twin.errors import UserError
    from twin.readback import check_fields, read_json

    fix = f"delete {path} and rerun the sweep to compute that cell again"
    try:
        record = read_json(path, required=True)
        check_fields(path, record, CELL_FIELDS)
        cell = record.get("cell")
        if not isinstance(cell, dict) or not isinstance(record.get("rows"), list):
            raise UserError(f"{path}: no cell or rows")
        for key in ("scenario", "parameters", "seed"):
            if key not in cell:
                raise UserError(f"{path}: cell.{key} is missing")
        if "seconds" not in record:
            raise UserError(f"{path}: seconds is missing")
        if not all(isinstance(r, dict) for r in record["rows"]):
            raise UserError(f"{path}: every row must be an object")
    except UserError as exc:
        raise UserError(f"{str(exc).split('; rerun')[0]}; {fix}") from None
    return record


def _sweep_cells(path: Path) -> list[str]:
    from twin.errors import UserError
    from twin.readback import read_json

    manifest = read_json(path, required=True)
    cells = manifest.get("cells") if isinstance(manifest, dict) else None
    if not isinstance(cells, list) or not all(isinstance(c, str) for c in cells):
        raise UserError(f"{path}: cells must be a list of cell ids; rerun the sweep")
    return cells


def parameter_label(value: Any) -> Any:
    """A swept value as a table cell: numbers and text as they are, a list or a table (e.g.
    ``grid.obstacles``) as its JSON text."""
    if value is None or isinstance(value, (str, int, float, bool)):
        return value
    return json.dumps(value, sort_keys=True)


def merge(
    out_dir: Path, ids: list[str] | None = None, config: SweepConfig | None = None
) -> tuple[pd.DataFrame, pd.DataFrame]:
    """results.csv (one row per cell and swarm) and summary.csv (mean, 95% interval over seeds)."""
    from twin.metrics import aggregate

    if ids is None:
        ids = _sweep_cells(out_dir / "sweep.json")
    parameters = list(config.parameters) if config else None
    rows = []
    for cid in ids:
        path = out_dir / CELLS_DIR / f"{cid}.json"
        if not path.exists():
            continue
        record = read_cell(path)
        if record.get("error"):  # a partial run's numbers are no cell's result
            continue
        cell = record["cell"]
        for row in record["rows"]:
            rows.append(
                {
                    "cell": cid,
                    "scenario": cell["scenario"],
                    **{k: parameter_label(v) for k, v in cell["parameters"].items()},
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
    atomic_write(out_dir / "results.csv", lambda p: results.to_csv(p, index=False))
    atomic_write(out_dir / "summary.csv", lambda p: summary.to_csv(p, index=False))
    return results, summary


def write_sweep_report(out_dir: str | Path) -> Path:
    """The sweep report (HTML + Markdown) from summary.csv, results.csv and the cells' series."""
    from twin.report.sweep import write_sweep_report as write

    return write(Path(out_dir))
