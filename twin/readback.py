"""Checks of the files twin reads back (run folders, their tables, maps and JSON) before use.

Every reader of a file twin wrote earlier (``twin report``, ``twin replay``) goes through these:
a file that cannot be parsed, a missing column, a string or NaN where a number belongs, a
missing or duplicated row, a cell off the grid or an array of the wrong shape is a one-line
:class:`~twin.errors.UserError` naming the file and the field, never a traceback further on.
"""

from __future__ import annotations

import json
import math
import operator
import re
from collections.abc import Iterable, Mapping
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

from twin.errors import UserError
from twin.files import NotARecord, read_record
from twin.seeds import MAX_SEED

RERUN = "rerun the command that wrote it"

#: Column kinds: whole numbers (no NaN), finite numbers, numbers (NaN allowed: an empty
#: interval, an event never seen), text (anything, read as text), a flag (true/false or 0/1).
INT, FINITE, NUMBER, TEXT, FLAG = "int", "finite", "number", "text", "flag"


def read_table(path: Path, columns: Mapping[str, str] | None = None) -> pd.DataFrame:
    """The parquet or CSV table at ``path``, its ``columns`` checked (:func:`check_columns`)."""
    path = Path(path)
    try:
        frame = pd.read_parquet(path) if path.suffix == ".parquet" else pd.read_csv(path)
    except (OSError, UnicodeError) as exc:
        raise UserError(f"{path}: cannot read it ({_why(exc)}); {RERUN}") from None
    except Exception as exc:  # the parsers' own errors on a damaged file
        kind = "parquet" if path.suffix == ".parquet" else "CSV"
        raise UserError(f"{path}: not a readable {kind} table ({_why(exc)}); {RERUN}") from None
    if path.suffix != ".parquet":  # the header as written (pandas renames a repeated name)
        repeated = [c for c in frame.columns if re.fullmatch(r".+\.\d+", str(c))
                    and str(c).rsplit(".", 1)[0] in frame.columns]  # fmt: skip
        if repeated:
            name = str(repeated[0]).rsplit(".", 1)[0]
            raise UserError(f"{path}: column {name!r} appears twice; {RERUN}")
    if columns:
        check_columns(path, frame, columns)
    return frame


def parquet_columns(path: Path) -> list[str]:
    """The column names of the parquet table at ``path``, from its footer (the table is not
    read); a file that is no readable table is refused as :func:`read_table` refuses it."""
    import pyarrow.parquet as pq

    try:
        return list(pq.read_schema(path).names)
    except Exception:  # read_table says what is wrong with it
        return list(read_table(path).columns)


def check_columns(path: Path, frame: pd.DataFrame, columns: Mapping[str, str]) -> None:
    """Every column of ``columns`` is in ``frame`` and holds values of its kind."""
    if frame.columns.duplicated().any():
        name = frame.columns[frame.columns.duplicated()][0]
        raise UserError(f"{path}: column {name!r} appears twice; {RERUN}")
    for name, kind in columns.items():
        if name not in frame.columns:
            raise UserError(f"{path}: no column {name!r}; {RERUN}")
        check_column(path, frame, name, kind)


def check_known_columns(
    path: Path,
    table: pd.DataFrame | list[str],
    known: Iterable[str],
    required: Iterable[str] = (),
) -> None:
    """``table`` (a frame, or its column names) holds no column but ``known`` (a table whose
    every column twin writes), and each of ``required`` (those its folder's format holds)."""
    known = set(known)
    columns = list(table.columns) if isinstance(table, pd.DataFrame) else list(table)
    other = [c for c in columns if c not in known]
    if other:
        raise UserError(f"{path}: holds a column {other[0]!r}, which twin does not write; {RERUN}")
    missing = [c for c in required if c not in columns]
    if missing:
        raise UserError(f"{path}: lacks the column {missing[0]!r}, which twin writes; {RERUN}")


def check_column(path: Path, frame: pd.DataFrame, name: str, kind: str) -> None:
    col = frame[name]
    if kind == TEXT:
        if col.isna().any():
            n = int(np.flatnonzero(col.isna().to_numpy())[0])
            raise UserError(f"{path}: column {name!r} row {n} is empty; {RERUN}")
        return
    if kind == FLAG:
        values = col.dropna()
        if col.isna().any() or not values.isin([True, False, 0, 1]).all():
            raise UserError(f"{path}: column {name!r} must hold true/false; {RERUN}")
        return
    if pd.api.types.is_bool_dtype(col) or not pd.api.types.is_numeric_dtype(col):
        bad = _first_non_number(col)
        raise UserError(
            f"{path}: column {name!r} holds {bad!r}, not a number (row {_row(col, bad)}); {RERUN}"
        )
    values = col.to_numpy(dtype=np.float64)
    if kind in (INT, FINITE):
        off = ~np.isfinite(values)
        if off.any():
            n = int(np.flatnonzero(off)[0])
            raise UserError(
                f"{path}: column {name!r} row {n} is {values[n]}, not a finite number; {RERUN}"
            )
    if kind == INT:
        off = values != np.round(values)
        if off.any():
            n = int(np.flatnonzero(off)[0])
            raise UserError(
                f"{path}: column {name!r} row {n} is {values[n]}, not a whole number; {RERUN}"
            )


def _first_non_number(col: pd.Series) -> Any:
    for v in col:
        if isinstance(v, bool) or not isinstance(v, (int, float, np.integer, np.floating)):
            return v
    return col.iloc[0] if len(col) else None


def _row(col: pd.Series, value: Any) -> int:
    for n, v in enumerate(col):
        if v is value or v == value:
            return n
    return 0


def _why(exc: BaseException) -> str:
    text = " ".join(str(exc).split()) or type(exc).__name__
    return text[:200]


def read_json(path: Path, required: bool = False) -> Any:
    """The JSON at ``path`` (None when absent and not ``required``)."""
    path = Path(path)
    if not path.exists():
        if required:
            raise UserError(f"{path}: missing; {RERUN}")
        return None
    try:
        text = read_record(path)
    except NotARecord as exc:
        raise UserError(f"{path}: {exc.strerror}; {RERUN}") from None
    except (OSError, UnicodeError) as exc:
        raise UserError(f"{path}: cannot read it ({_why(exc)}); {RERUN}") from None
    try:
        return json.loads(text)
    except (ValueError, RecursionError) as exc:
        raise UserError(f"{path}: not valid JSON ({_why(exc)}); {RERUN}") from None


def check_fields(path: Path, node: Any, fields: Mapping[str, Any], where: str = "") -> None:
    """Each present key of ``fields`` in the JSON object ``node`` has one of its types (a
    type, a tuple of types, or a nested mapping for an object); absent keys and null pass."""
    if not isinstance(node, dict):
        raise UserError(f"{path}: {where or 'the top level'} must be an object; {RERUN}")
    for key, kind in fields.items():
        value = node.get(key)
        name = f"{where}.{key}" if where else key
        if value is None:
            continue
        if isinstance(kind, Mapping):
            check_fields(path, value, kind, name)
            continue
        kinds = kind if isinstance(kind, tuple) else (kind,)
        ok = isinstance(value, kinds) and not (
            isinstance(value, bool) and bool not in kinds and (int in kinds or float in kinds)
        )
        if isinstance(value, float) and float in kinds and not np.isfinite(value):
            ok = False
        if not ok:
            want = " or ".join(_TYPE_NAMES.get(k, k.__name__) for k in kinds)
            shown = json.dumps(value)[:60] if _jsonable(value) else repr(value)[:60]
            raise UserError(f"{path}: {name} = {shown} must be {want}; {RERUN}")


_TYPE_NAMES = {
    int: "a whole number",
    float: "a number",
    str: "text",
    bool: "true or false",
    list: "a list",
    dict: "an object",
}


def _jsonable(value: Any) -> bool:
    try:
        json.dumps(value)
    except (TypeError, ValueError):
        return False
    return True


NUM = (int, float)


def _at_least(low: float) -> tuple[Any, str]:
    return (lambda v: v >= low), f"at least {low:g}"


_POSITIVE = ((lambda v: v > 0), "above 0")
_SECONDS = ((lambda v: math.isfinite(v) and v >= 0), "a finite number of seconds, at least 0")
_MEGABYTES = (_SECONDS[0], "a finite number of MB, at least 0")

#: The fields of a run folder's ``run.json`` that its readers use, with their types.
RUN_JSON_FIELDS: dict[str, Any] = {
    "partial": bool,
    "partial_reason": str,
    "importance_seed": int,
    "n_drones": int,
    "horizon": int,
    "seeds": list,
    "swarms": list,
    "errors": list,
    "params": {"eta": NUM, "delta": NUM, "alpha_T": NUM, "alpha_I": NUM},
    "score_params": {"eta": NUM, "delta": NUM, "alpha_T": NUM, "alpha_I": NUM},
    "grid": {"nx": int, "ny": int, "n_free": int},
    "traffic": {
        "kind": str,
        "name": str,
        "begin": str,
        "step_s": NUM,
        "horizon": int,
        "identity": {"net_sha256": str, "cell_m": NUM, "grid": list, "sumo": str, "twin": str},
        "recorded": {"step_s": NUM},
        "tape_file": {"path": str, "sha256": str},
    },
    "timings": {"peak_memory_mb": NUM, "peak_memory_sumo_process_mb": NUM, "patrol_seconds": list},
    "traffic_by_seed": list,
    "wall_seconds": NUM,
    "sumo_read_seconds": NUM,
    "kind": str,
    "command": str,
    "created": str,
    "monitoring": {"threshold": NUM, "min_duration": NUM, "weight_floor": NUM, "truth": str},
    "invocation": {"command": str, "options": dict, "cwd": str},
    "history": {"path": str, "sha256": str},
    "config": (str, dict),
}


#: ``network.json`` of a live run: the grid's placement on the network.
NETWORK_FIELDS: dict[str, Any] = {
    "name": str,
    "net_file": str,
    "route_files": list,
    "grid": {
        "x0": NUM,
        "y_top": NUM,
        "cell_m": NUM,
        "nx": int,
        "ny": int,
        "bbox": list,
        "lane_km_total": NUM,
    },
    "n_obstacles": int,
    "row_0": str,
}
#: The plausible values of ``network.json``'s numbers.
NETWORK_RANGES: dict[str, tuple[Any, str]] = {
    "grid.cell_m": _POSITIVE,
    "grid.nx": _at_least(1),
    "grid.ny": _at_least(1),
    "grid.lane_km_total": _at_least(0),
    "n_obstacles": _at_least(0),
}
#: ``mfd.json`` of a live run: the MFD fit and how it was used.
MFD_FIELDS: dict[str, Any] = {
    "form": str,
    "a": NUM,
    "k_c": NUM,
    "fit": str,
    "used": str,
    "why": str,
    "reads_per_step": NUM,
    "rejected_fit": {"a": NUM, "k_c": NUM},
    "detection_p": NUM,
    "r2_binned": NUM,
    "density_unit": str,
    "speed_unit": str,
    "n_samples": int,
    "r2": NUM,
    "rmse_kmh": NUM,
    "online_r2": NUM,
    "online_rmse_kmh": NUM,
    "importance": str,
}

#: The plausible values of ``mfd.json``'s numbers: the free-flow share ``a`` and the critical
#: density ``k_c`` of the Underwood curve above 0, a detection probability in (0, 1].
MFD_RANGES: dict[str, tuple[Any, str]] = {
    "a": _POSITIVE,
    "k_c": _POSITIVE,
    "rejected_fit.a": _POSITIVE,
    "rejected_fit.k_c": _POSITIVE,
    "detection_p": ((lambda v: 0 < v <= 1), "above 0 and at most 1"),
    "reads_per_step": _at_least(0),
    "n_samples": _at_least(0),
    "rmse_kmh": _at_least(0),
    "online_rmse_kmh": _at_least(0),
}

#: One scheduled incident of ``incidents.json``.
INCIDENT_FIELDS: dict[str, Any] = {
    "kind": str,
    "edge": (str, int),
    "lane": int,
    "vehicle": str,
    "cell": list,
    "begin": (str, int, float),
    "duration_min": NUM,
    "onset_step": int,
    "end_step": int,
}
#: ``mfd_samples.parquet``: the per-cell samples of the MFD fit.
MFD_SAMPLE_COLUMNS = {"step": INT, "count": NUMBER, "speed": NUMBER, "density": NUMBER}


def check_incidents(path: Path, incidents: Any) -> None:
    if not isinstance(incidents, list):
        raise UserError(f"{path}: must be a list of incidents; {RERUN}")
    for n, inc in enumerate(incidents):
        check_fields(path, inc, INCIDENT_FIELDS, f"[{n}]")
        cell = inc.get("cell")
        if cell is not None and not (
            len(cell) == 2 and all(isinstance(v, int) and not isinstance(v, bool) for v in cell)
        ):
            raise UserError(f"{path}: [{n}].cell = {cell} must be a cell [i, j]; {RERUN}")


_SCORE_RANGES = {
    "eta": ((lambda v: 0 < v < 1), "between 0 and 1"),
    "delta": ((lambda v: 0 < v < 1), "between 0 and 1"),
    "alpha_T": _at_least(0),
    "alpha_I": _at_least(0),
}
#: The plausible values of ``run.json``'s numbers (dotted name -> test, what it must be): a
#: run never records a horizon below 1, no drone, a cell of 0 m ...
RUN_JSON_RANGES: dict[str, tuple[Any, str]] = {
    "n_drones": _at_least(1),
    "horizon": _at_least(0),  # the steps that ran: 0 in a partial run where none did
    "importance_seed": _at_least(0),
    "grid.nx": _at_least(1),
    "grid.ny": _at_least(1),
    "grid.n_free": _at_least(0),
    "traffic.horizon": _at_least(1),
    "traffic.step_s": _POSITIVE,
    "traffic.recorded.step_s": _POSITIVE,
    "traffic.identity.cell_m": _POSITIVE,
    "monitoring.threshold": ((lambda v: 0 < v <= 1), "above 0 and at most 1"),
    "monitoring.min_duration": _at_least(1),
    "monitoring.weight_floor": _POSITIVE,
    "wall_seconds": _SECONDS,
    "sumo_read_seconds": _SECONDS,
    "timings.peak_memory_mb": _MEGABYTES,
    "timings.peak_memory_sumo_process_mb": _MEGABYTES,
    **{f"params.{k}": v for k, v in _SCORE_RANGES.items()},
    **{f"score_params.{k}": v for k, v in _SCORE_RANGES.items()},
}


def check_run_json(path: Path, run: Any) -> dict[str, Any]:
    """``run.json`` of a run folder: an object whose used fields have their types and
    plausible values (:data:`RUN_JSON_RANGES`)."""
    check_fields(path, run, RUN_JSON_FIELDS)
    config = run.get("config")
    if isinstance(config, dict):
        params = config.get("params", config.get("score"))
        if params is not None:
            check_fields(path, params, RUN_JSON_FIELDS["params"], "config.params")
    check_ranges(path, run, RUN_JSON_RANGES)

    for n, seed in enumerate(run.get("seeds") or []):
        if isinstance(seed, bool) or not isinstance(seed, int) or not 0 <= seed <= MAX_SEED:
            raise UserError(
                f"{path}: seeds[{n}] = {str(seed)[:40]} must be a whole number from 0 to "
                f"{MAX_SEED}; {RERUN}"
            )
    for n, swarm in enumerate(run.get("swarms") or []):
        if not isinstance(swarm, str):
            raise UserError(f"{path}: swarms[{n}] = {str(swarm)[:40]} must be a name; {RERUN}")
    grid = _dotted(run, "traffic.identity.grid")
    if grid is not None and not (
        len(grid) == 2
        and all(isinstance(v, int) and not isinstance(v, bool) and v >= 1 for v in grid)
    ):
        raise UserError(
            f"{path}: traffic.identity.grid = {str(grid)[:40]} must be [nx, ny], whole numbers "
            f"of at least 1; {RERUN}"
        )
    check_timings(path, run)
    if swarms := [s for s in run.get("swarms") or [] if isinstance(s, str)]:
        twice = sorted({s for s in swarms if swarms.count(s) > 1})
        if twice:
            raise UserError(f"{path}: swarms lists {twice[0]!r} twice; {RERUN}")
    for name, version in (run.get("versions") or {}).items():
        if not isinstance(version, str):
            raise UserError(f"{path}: versions.{name} = {str(version)[:40]} must be text; {RERUN}")
    check_same_fields(path, run)
    check_invocation(path, run)
    check_partial(path, run)
    check_sumo_outputs(path, run)
    return run


def check_timings(path: Path, run: dict[str, Any]) -> None:
    """``timings``: the fields twin writes there alone, and a patrol's seconds for each seed."""
    timings = run.get("timings")
    if not isinstance(timings, dict):
        return
    unknown = sorted(set(timings) - set(RUN_JSON_FIELDS["timings"]))
    if unknown:
        raise UserError(f"{path}: timings.{unknown[0][:40]} is no timing twin records; {RERUN}")
    patrols = timings.get("patrol_seconds") or []
    for n, seconds in enumerate(patrols):
        if not isinstance(seconds, NUM) or isinstance(seconds, bool) or not _SECONDS[0](seconds):
            raise UserError(
                f"{path}: timings.patrol_seconds[{n}] = {str(seconds)[:40]} must be {_SECONDS[1]}"
                f"; {RERUN}"
            )
    seeds = run.get("seeds")
    if patrols and isinstance(seeds, list) and len(patrols) != len(seeds):
        raise UserError(
            f"{path}: timings.patrol_seconds gives {len(patrols)} seeds' seconds, but seeds lists "
            f"{len(seeds)}; {RERUN}"
        )


def check_partial(path: Path, run: dict[str, Any]) -> None:
    """A run that records an error, or a reason it is partial, says it is partial (twin marks
    every run with an error partial)."""
    if run.get("partial"):
        return
    errors = run.get("errors") or []
    for n, error in enumerate(errors):
        if not isinstance(error, str):
            raise UserError(f"{path}: errors[{n}] = {str(error)[:40]} must be text; {RERUN}")
    said = [
        (name, value)
        for name, value in (
            ("errors", errors[0] if errors else None),
            ("partial_reason", run.get("partial_reason")),
            ("traffic.error", _dotted(run, "traffic.error")),
        )
        if value
    ]
    if said:
        name, value = said[0]
        raise UserError(
            f"{path}: {name} = {str(value)[:40]!r}, but partial = false (a run with an error is "
            f"partial); {RERUN}"
        )


def check_sumo_outputs(path: Path, run: dict[str, Any]) -> None:
    """``traffic.sumo_outputs``: files of the run folder's ``sumo/``, each there."""
    outputs = _dotted(run, "traffic.sumo_outputs")
    if not isinstance(outputs, list):
        return
    folder = path.parent / "sumo"
    for n, name in enumerate(outputs):
        where = f"traffic.sumo_outputs[{n}] = {str(name)[:60]!r}"
        if not isinstance(name, str) or Path(name).is_absolute() or ".." in Path(name).parts:
            raise UserError(f"{path}: {where} is not a name inside sumo/; {RERUN}")
        if not (folder / name).is_file():
            raise UserError(f"{path}: {where}, but {folder / name} is not there; {RERUN}")


def _same_swarms(given: Any, recorded: Any) -> bool:
    """``--swarms`` (comma-separated names, or all) names the run's swarms."""
    named = {s.strip() for s in str(given).split(",") if s.strip()}
    return "all" in named or not isinstance(recorded, list) or named == set(recorded)


def _same_file(given: Any, recorded: Any) -> bool:
    """A file given on the command line is the one recorded (as named from another folder)."""
    return Path(str(given)).name == Path(str(recorded)).name


def _same_config(given: Any, recorded: Any) -> bool:
    """``--config`` names the run's config: its path, or a shipped config by its name."""
    return str(given) == str(recorded) or Path(str(given)).stem == Path(str(recorded)).stem


#: The command-line options run.json's ``invocation`` records and the field of the run each
#: sets: (option, dotted field, only for a live `twin run`, how the two agree).
INVOCATION_FIELDS = (
    ("config", "config", False, _same_config),
    ("drones", "n_drones", False, operator.eq),
    ("swarms", "swarms", False, _same_swarms),
    ("horizon", "traffic.horizon", True, operator.eq),
    ("cell_m", "traffic.identity.cell_m", True, operator.eq),
    ("net", "traffic.net_file", True, _same_file),
)


def command_words(command: Any) -> list[str] | None:
    """run.json's ``command`` split as a shell would (None when it is no text or no ``twin``
    command line)."""
    import shlex

    if not isinstance(command, str):
        return None
    try:
        words = shlex.split(command)
    except ValueError:
        return None
    return words if words and words[0] == "twin" else None


def check_invocation(path: Path, run: dict[str, Any]) -> None:
    """run.json's command agrees with itself: ``kind`` is the invocation's command and the
    command line's, the options it gives are the run's (:data:`INVOCATION_FIELDS`), and
    ``created`` is a time."""
    from datetime import datetime

    kind, command = run.get("kind"), _dotted(run, "invocation.command")
    if kind is not None and command is not None and kind != command:
        raise UserError(
            f"{path}: kind = {str(kind)[:40]!r}, but invocation.command = {str(command)[:40]!r}; "
            f"{RERUN}"
        )
    words = command_words(run.get("command"))
    if kind is not None and words is not None and (len(words) < 2 or words[1] != kind):
        raise UserError(
            f"{path}: command = {str(run.get('command'))[:60]!r} is no `twin {kind}`, but kind = "
            f"{str(kind)[:40]!r}; {RERUN}"
        )
    for option, field, live, agree in INVOCATION_FIELDS:
        given, recorded = _dotted(run, f"invocation.options.{option}"), _dotted(run, field)
        if given is None or recorded is None or (live and kind != "run"):
            continue
        if agree(given, recorded):
            continue
        raise UserError(
            f"{path}: invocation.options.{option} = {repr(given)[:60]}, but {field} = "
            f"{repr(recorded)[:60]}; {RERUN}"
        )
    check_seed_options(path, run)
    cwd = _dotted(run, "invocation.cwd")
    if isinstance(cwd, str) and not Path(cwd).is_absolute():
        raise UserError(
            f"{path}: invocation.cwd = {cwd[:60]!r} is no absolute folder (the folder the "
            f"command ran in); {RERUN}"
        )
    created = run.get("created")
    if created is not None:
        try:
            datetime.fromisoformat(created)
        except ValueError:
            raise UserError(
                f"{path}: created = {created[:40]!r} is not a time (ISO 8601); {RERUN}"
            ) from None


def check_seed_options(path: Path, run: dict[str, Any]) -> None:
    """``--seed``/``--seeds`` the invocation gives are the run's seeds: ``seeds`` seeds from
    ``seed`` on (a partial run lists those it finished)."""
    seeds = run.get("seeds")
    if not isinstance(seeds, list) or not seeds:
        return
    given = {option: _dotted(run, f"invocation.options.{option}") for option in ("seed", "seeds")}
    for option, value in given.items():
        if value is not None and (isinstance(value, bool) or not isinstance(value, int)):
            raise UserError(
                f"{path}: invocation.options.{option} = {repr(value)[:40]} must be a whole "
                f"number; {RERUN}"
            )
    first, count = given["seed"], given["seeds"]
    partial = bool(run.get("partial"))
    if count is not None and (len(seeds) > count or (not partial and len(seeds) != count)):
        raise UserError(
            f"{path}: invocation.options.seeds = {count}, but seeds lists {len(seeds)}; {RERUN}"
        )
    if first is None:
        return
    last = first + (count if count is not None else len(seeds)) - 1
    if partial and count is None:
        last = max(seeds)  # how many the run was to have is not recorded
    if not all(first <= s <= last for s in seeds) or (
        not partial and seeds != list(range(first, first + len(seeds)))
    ):
        raise UserError(
            f"{path}: invocation.options.seed = {first}, but seeds are {str(seeds)[:40]}; {RERUN}"
        )


#: Fields of run.json that record one thing twice: each pair must agree.
SAME_FIELDS = (
    ("monitoring.step_s", "traffic.step_s"),
    ("traffic.identity.cell_m", "traffic.cell_m"),
    ("versions.eclipse-sumo", "traffic.identity.sumo"),
    ("versions.twin", "traffic.identity.twin"),
)


def check_same_fields(path: Path, run: dict[str, Any]) -> None:
    """run.json's fields that record one thing twice agree (:data:`SAME_FIELDS`), and its
    network's sha256 in ``traffic.identity`` is the one of the network among its files."""
    for a, b in SAME_FIELDS:
        x, y = _dotted(run, a), _dotted(run, b)
        if x is not None and y is not None and x != y:
            raise UserError(f"{path}: {a} = {str(x)[:40]}, but {b} = {str(y)[:40]}; {RERUN}")
    step_s = _dotted(run, "monitoring.step_s")
    simulated = [_dotted(run, f"traffic.{k}step_s") for k in ("", "recorded.")]
    if step_s is not None and simulated == [None, None]:
        raise UserError(
            f"{path}: monitoring.step_s = {str(step_s)[:40]}, but the traffic records no step "
            f"(traffic.step_s): it was not simulated; {RERUN}"
        )
    recorded = simulated[1]
    if step_s is not None and simulated[0] is None and recorded is not None and step_s != recorded:
        raise UserError(
            f"{path}: monitoring.step_s = {str(step_s)[:40]}, but traffic.recorded.step_s = "
            f"{str(recorded)[:40]}; {RERUN}"
        )
    grid, shape = (
        _dotted(run, "traffic.identity.grid"),
        [_dotted(run, "grid.nx"), _dotted(run, "grid.ny")],
    )
    if grid is not None and None not in shape and list(grid) != shape:
        raise UserError(
            f"{path}: traffic.identity.grid = {grid}, but grid is {shape[0]} x {shape[1]}; {RERUN}"
        )
    identity = _dotted(run, "traffic.identity")
    if not isinstance(identity, dict) or not isinstance(identity.get("files"), list):
        return
    nets = {
        f.get("sha256")
        for f in identity["files"]
        if isinstance(f, dict) and f.get("role") == "network"
    }
    net = identity.get("net_sha256")
    if net is not None and not nets:
        raise UserError(
            f'{path}: traffic.identity.files records no network (role "network"), but '
            f"traffic.identity.net_sha256 gives one; {RERUN}"
        )
    routes = _dotted(run, "traffic.route_files")
    if isinstance(routes, list) and all(isinstance(r, str) for r in routes):
        recorded = sorted(
            Path(str(f.get("path"))).name
            for f in identity["files"]
            if isinstance(f, dict) and f.get("role") == "route file"
        )
        if recorded != sorted(Path(r).name for r in routes):
            raise UserError(
                f"{path}: traffic.identity.files records the route files {recorded}, but "
                f"traffic.route_files are {sorted(Path(r).name for r in routes)}; {RERUN}"
            )
    if nets and net is not None and net not in nets:
        raise UserError(
            f"{path}: traffic.identity.net_sha256 = {str(net)[:16]}..., but its files record "
            f"the network's as {str(sorted(nets)[0])[:16]}...; {RERUN}"
        )


def check_ranges(path: Path, node: Any, ranges: Mapping[str, tuple[Any, str]]) -> None:
    """Each present number of ``ranges`` (dotted name -> test, what it must be) in the JSON
    object ``node`` passes its test (types are checked before, :func:`check_fields`)."""
    for name, (plausible, want) in ranges.items():
        value = _dotted(node, name)
        if value is not None and not plausible(value):
            raise UserError(f"{path}: {name} = {value!r} must be {want}; {RERUN}")


def _dotted(node: Any, name: str) -> Any:
    """``node[a][b]...`` for the dotted ``name`` (None where a level is missing)."""
    for key in name.split("."):
        if not isinstance(node, dict):
            return None
        node = node.get(key)
    return node


def check_manifest(path: Path, manifest: Any) -> dict[str, Any]:
    check_fields(path, manifest, {"partial": bool, "partial_reason": str, "files": dict})
    if not isinstance(manifest.get("files"), dict):
        raise UserError(f"{path}: files must be an object of file sizes; {RERUN}")
    for name, size in manifest["files"].items():
        if isinstance(size, bool) or not isinstance(size, int) or size < 0:
            raise UserError(f"{path}: files.{name} = {size!r} must be a size in bytes; {RERUN}")
        if Path(name).is_absolute() or ".." in Path(name).parts:
            raise UserError(f"{path}: files.{name} is not a name inside the run folder; {RERUN}")
    return manifest


# run-folder tables --------------------------------------------------------------------------

TRAJECTORY_COLUMNS = {"seed": INT, "swarm": TEXT, "step": INT, "drone": INT, "i": INT, "j": INT}
SERIES_COLUMNS = {
    "seed": INT,
    "swarm": TEXT,
    "step": INT,
    "reward": FINITE,
    "cumulative_reward": FINITE,
    "coverage": FINITE,
    "visited_share": FINITE,
}
#: Columns of a sweep cell's per-step series (``cells/<id>.parquet``) that the sweep reads back.
CELL_SERIES_COLUMNS = {"swarm": TEXT, "step": INT, "seed": INT, "cumulative_reward": FINITE}
TIMING_COLUMNS = {"seed": INT, "stage": TEXT, "seconds": FINITE, "ms_per_step": FINITE}
EVENT_COLUMNS = {
    "seed": INT,
    "event": INT,
    "i": INT,
    "j": INT,
    "onset": INT,
    "duration": INT,
    "peak": NUMBER,
    "swarm": TEXT,
    "seen": FLAG,
    "first_seen": INT,
    "latency_steps": INT,
}
#: Columns of ``degradation.csv`` (:func:`twin.faults.degradation_frame`): the phase's steps,
#: its scores (means over its steps, finite) and its monitoring (NaN without events).
DEGRADATION_COLUMNS = {
    "seed": INT,
    "swarm": TEXT,
    "phase": INT,
    "label": TEXT,
    "start": INT,
    "stop": INT,
    "R_hat": FINITE,
    "R_hat_fault_free": FINITE,
    "events": INT,
    **dict.fromkeys(  # (NaN: a phase without events)
        [f"{c}{twin}" for c in ("pct_events_seen", "latency_median_steps",
                                "pct_congested_observed") for twin in ("", "_fault_free")],
        NUMBER,
    ),
}  # fmt: skip
#: Columns of ``belief_models.csv`` (:func:`twin.belief.run_beliefs`): every row's belief error
#: is a number (the run has steps), the other scores may be NaN (no events, no interval).
BELIEF_MODEL_COLUMNS = {
    "swarm": TEXT,
    "model": TEXT,
    "belief_error": FINITE,
    **dict.fromkeys(  # (twin.belief.BELIEF_COLUMNS: every belief table has had them)
        ("calibration_90", "events", "pct_events_known", "latency_median_steps",
         "latency_median_min", "false_alarms", "false_alarms_per_hour", "n_seeds"),
        NUMBER,
    ),
}  # fmt: skip


#: The headline columns of a results table (``summary.csv``, ``per_seed.csv``): every swarm row
#: holds a finite number in each of them that the table has. Ceiling rows (``role`` =
#: ``ceiling``) leave the columns they do not fill empty.
HEADLINE_COLUMNS = (
    "R_hat_T",
    "R_hat_T_importance",
    "R_hat_T_idleness",
    "R_hat_T_paper",
    "C_hat_T",
    "pct_map_covered",
)


def check_headline(path: Path, frame: pd.DataFrame) -> None:
    """Every swarm row of the results table ``frame`` has a finite number in each headline
    column present (``R_hat_T`` is required)."""
    if "R_hat_T" not in frame.columns:
        raise UserError(f"{path}: no column 'R_hat_T'; {RERUN}")
    swarm = ~frame["role"].eq("ceiling") if "role" in frame.columns else None
    if swarm is not None:
        odd = ~frame["role"].isin(("swarm", "ceiling"))
        if odd.any():
            n = int(np.flatnonzero(odd.to_numpy())[0])
            raise UserError(
                f"{path}: column 'role' of row {n} is {frame['role'].iloc[n]!r}, not 'swarm' or "
                f"'ceiling'; {RERUN}"
            )
    for name in HEADLINE_COLUMNS:
        if name not in frame.columns:
            continue
        check_column(path, frame, name, NUMBER)
        values = frame[name].to_numpy(dtype=np.float64)
        off = ~np.isfinite(values)
        if swarm is not None:
            off &= swarm.to_numpy()
        if off.any():
            n = int(np.flatnonzero(off)[0])
            who = frame["swarm"].iloc[n] if "swarm" in frame.columns else "?"
            raise UserError(
                f"{path}: column {name!r} of swarm {who!r} (row {n}) is {values[n]}, not a "
                f"finite number; {RERUN}"
            )


#: The range of each number column twin writes (NaN, where allowed, is left to the column's
#: kind): shares of the map and of time, errors of importances in 0 .. 1 (Def. 2), the headline
#: score's visit gains and counts never below 0 (Def. 4 as printed can be: not bounded here).
BOUNDS: dict[str, tuple[float, float]] = {
    **dict.fromkeys(("reward", "cumulative_reward", "R_hat_T", "R_hat_T_importance",
                     "R_hat_T_idleness", "events", "latency_median_steps",
                     "latency_p90_steps", "latency_median_min", "latency_p90_min",
                     "seconds", "ms_per_step", "R_hat", "R_hat_fault_free",
                     "latency_median_steps_fault_free", "false_alarms",
                     "false_alarms_per_hour"), (0.0, np.inf)),
    **dict.fromkeys(("coverage", "visited_share", "belief_error", "C_hat_T", "C_hat_T_ceiling",
                     "calibration_90"), (0.0, 1.0)),
    **dict.fromkeys(("pct_time_max_C", "pct_map_covered", "pct_events_seen",
                     "pct_congested_observed", "pct_events_seen_fault_free",
                     "pct_congested_observed_fault_free", "pct_events_known"), (0.0, 100.0)),
}  # fmt: skip


def check_bounds(path: Path, frame: pd.DataFrame) -> None:
    """Every column of ``frame`` named in :data:`BOUNDS` lies in its range (NaN passes)."""
    for name, (low, high) in BOUNDS.items():
        if name not in frame.columns:
            continue
        values = pd.to_numeric(frame[name], errors="coerce").to_numpy(dtype=np.float64)
        slack = 1e-9 * np.maximum(1.0, np.abs(values))
        off = (values < low - slack) | (values > high + slack)
        if off.any():
            n = int(np.flatnonzero(off)[0])
            raise UserError(
                f"{path}: column {name!r} row {n} is {values[n]:.6g}, outside {low:g} .. "
                f"{high:g}; {RERUN}"
            )


def check_timing(path: Path, timing: pd.DataFrame, series: pd.DataFrame) -> None:
    """``timing.csv``'s derived columns follow from its seconds: ``ms_per_step`` is the
    stage's seconds over the steps its seed completed (its rows per swarm in ``series``), and
    ``share`` its part of its process's total for that seed (both as rounded when written);
    a swarm's stage names a swarm of ``series``."""
    swarms = set(series["swarm"].astype(str))
    for n, stage in enumerate(timing["stage"].astype(str)):
        # a swarm's stage, or its fault-free reference run's ("swarm greedy (fault-free)")
        name = stage[len("swarm ") :].split(" (")[0]
        if stage.startswith("swarm ") and name not in swarms:
            raise UserError(
                f"{path}: row {n} times stage {stage!r}, but series.parquet holds no swarm "
                f"{name!r}; {RERUN}"
            )
    steps = series.groupby(["seed", "swarm"]).size().groupby(level=0).max()
    process = timing["process"] if "process" in timing.columns else pd.Series("main", timing.index)
    totals = timing.groupby([timing["seed"], process])["seconds"].transform("sum")
    for n, row in enumerate(timing.itertuples(index=False)):
        done = max(int(steps.get(row.seed, 0)), 1)
        want = 1000.0 * row.seconds / done
        # written rounded: ms_per_step to 4 decimals, seconds to 6 (1000 / done times that)
        if abs(row.ms_per_step - want) > 1e-4 + 1e-3 / done + 1e-6 * abs(want):
            raise UserError(
                f"{path}: row {n} (seed {row.seed}, {row.stage}) has ms_per_step = "
                f"{row.ms_per_step:g}, but {row.seconds:g} s over the seed's {done} steps is "
                f"{want:.4f}; {RERUN}"
            )
        if "share" in timing.columns and totals.iloc[n] > 0:
            share = row.seconds / totals.iloc[n]
            rounding = 1e-6 * (1 + len(timing)) / totals.iloc[n]  # of the seconds written
            if abs(row.share - share) > 1e-4 + rounding:
                raise UserError(
                    f"{path}: row {n} (seed {row.seed}, {row.stage}) has share = {row.share:g}, "
                    f"but its seconds are {share:.4f} of its process's; {RERUN}"
                )


def numeric_columns(path: Path, frame: pd.DataFrame, text: tuple[str, ...]) -> None:
    """Every column of ``frame`` but ``text`` holds numbers (NaN allowed), each within its
    :data:`BOUNDS`."""
    for name in frame.columns:
        if name not in text:
            check_column(path, frame, str(name), NUMBER)
    check_bounds(path, frame)


def off_grid(frame: pd.DataFrame, shape: tuple[int, int]) -> np.ndarray:
    """Rows of ``frame`` whose cell (columns ``i``, ``j``) is off an ``(nx, ny)`` grid."""
    i, j = frame["i"].to_numpy(), frame["j"].to_numpy()
    return (i < 0) | (i >= shape[0]) | (j < 0) | (j >= shape[1])


def check_trajectories(
    path: Path, frame: pd.DataFrame, shape: tuple[int, int], obstacles: np.ndarray | None = None
) -> None:
    """One row per (seed, swarm, step, drone), steps ``0..S`` and drones ``0..N-1`` complete
    for each seed and swarm, every cell on the ``shape`` grid (and off the ``obstacles``)."""
    check_columns(path, frame, TRAJECTORY_COLUMNS)
    if frame.empty:
        raise UserError(f"{path}: no rows; {RERUN}")
    key = ["seed", "swarm", "step", "drone"]
    dup = frame.duplicated(key)
    if dup.any():
        r = frame[dup].iloc[0]
        raise UserError(
            f"{path}: row for seed {r['seed']}, swarm {r['swarm']}, step {r['step']}, drone "
            f"{r['drone']} appears twice; {RERUN}"
        )
    nx, ny = shape
    i, j = frame["i"].to_numpy(), frame["j"].to_numpy()
    off = off_grid(frame, shape)
    if off.any():
        r = frame[off].iloc[0]
        raise UserError(
            f"{path}: swarm {r['swarm']} drone {r['drone']} at step {r['step']} of seed "
            f"{r['seed']} is on cell ({r['i']}, {r['j']}), off the {nx} x {ny} grid; {RERUN}"
        )
    if obstacles is not None:
        blocked = obstacles[i.astype(np.int64), j.astype(np.int64)]
        if blocked.any():
            r = frame[blocked].iloc[0]
            raise UserError(
                f"{path}: swarm {r['swarm']} drone {r['drone']} at step {r['step']} of seed "
                f"{r['seed']} is on cell ({r['i']}, {r['j']}), an obstacle in importance.npz; "
                f"{RERUN}"
            )
    for (seed, swarm), rows in frame.groupby(["seed", "swarm"], sort=False):
        steps, drones = rows["step"].nunique(), rows["drone"].nunique()
        complete = (
            len(rows) == steps * drones
            and rows["step"].min() == 0
            and rows["step"].max() == steps - 1
            and rows["drone"].min() == 0
            and rows["drone"].max() == drones - 1
        )
        if not complete:
            raise UserError(
                f"{path}: rows of seed {seed}, swarm {swarm} are incomplete ({len(rows)} rows, "
                f"steps {rows['step'].min()}..{rows['step'].max()}, {drones} drones); {RERUN}"
            )
    ordered = frame.sort_values(["seed", "swarm", "drone", "step"], kind="stable")
    same = (ordered[["seed", "swarm", "drone"]] == ordered[["seed", "swarm", "drone"]].shift()).all(
        axis=1
    )
    jump = same & ((ordered["i"].diff().abs() + ordered["j"].diff().abs()) > 1)
    if jump.any():
        r = ordered[jump].iloc[0]
        raise UserError(
            f"{path}: swarm {r['swarm']} drone {r['drone']} of seed {r['seed']} reaches cell "
            f"({r['i']}, {r['j']}) at step {r['step']}, more than one cell from where it was "
            f"(a drone moves one cell per step); {RERUN}"
        )


def check_series(path: Path, frame: pd.DataFrame) -> None:
    """One row per (seed, swarm, step), steps ``0..T-1`` complete for each seed and swarm, and
    ``cumulative_reward`` the running sum of ``reward``."""
    check_columns(path, frame, SERIES_COLUMNS)
    check_bounds(path, frame)
    if "belief_error" in frame.columns:
        check_column(path, frame, "belief_error", NUMBER)
    dup = frame.duplicated(["seed", "swarm", "step"])
    if dup.any():
        r = frame[dup].iloc[0]
        raise UserError(
            f"{path}: row for seed {r['seed']}, swarm {r['swarm']}, step {r['step']} appears "
            f"twice; {RERUN}"
        )
    for (seed, swarm), rows in frame.groupby(["seed", "swarm"], sort=False):
        if rows["step"].min() != 0 or rows["step"].max() != len(rows) - 1:
            raise UserError(
                f"{path}: steps of seed {seed}, swarm {swarm} are not 0..{len(rows) - 1} "
                f"(rows missing); {RERUN}"
            )
    ordered = frame.sort_values(["seed", "swarm", "step"], kind="stable")
    running = ordered.groupby(["seed", "swarm"], sort=False)["reward"].cumsum()
    given = ordered["cumulative_reward"]
    off = (given - running).abs() > 1e-9 * np.maximum(1.0, running.abs())
    if off.any():
        r = ordered[off].iloc[0]
        raise UserError(
            f"{path}: cumulative_reward = {r['cumulative_reward']:.6g} at step {r['step']} of "
            f"seed {r['seed']}, swarm {r['swarm']} is not the sum of its rewards "
            f"({running[off].iloc[0]:.6g}); {RERUN}"
        )


def read_maps(path: Path) -> tuple[np.ndarray, np.ndarray]:
    """``importance`` ``(T+1, nx, ny)`` (finite) and ``obstacles`` ``(nx, ny)`` of
    ``importance.npz``."""
    from twin.resources import check_grid_size

    try:
        with np.load(path, allow_pickle=False) as npz:
            missing = [k for k in ("importance", "obstacles") if k not in npz.files]
            if missing:
                raise UserError(f"{path}: no array {missing[0]!r}; {RERUN}")
            importance, obstacles = npz["importance"], npz["obstacles"]
    except UserError:
        raise
    except (OSError, UnicodeError) as exc:
        raise UserError(f"{path}: cannot read it ({_why(exc)}); {RERUN}") from None
    except Exception as exc:  # zip, pickle and format errors of a damaged file
        raise UserError(f"{path}: not a readable .npz ({_why(exc)}); {RERUN}") from None
    if obstacles.ndim != 2 or min(obstacles.shape) < 1:
        raise UserError(f"{path}: obstacles has shape {obstacles.shape}, not (nx, ny); {RERUN}")
    check_grid_size(*obstacles.shape, str(path), RERUN)
    if importance.ndim != 3 or importance.shape[1:] != obstacles.shape:
        raise UserError(
            f"{path}: importance has shape {importance.shape}, not (T+1, "
            f"{obstacles.shape[0]}, {obstacles.shape[1]}); {RERUN}"
        )
    numeric = np.issubdtype(importance.dtype, np.number)
    if not numeric or not (obstacles.dtype == bool or np.issubdtype(obstacles.dtype, np.number)):
        raise UserError(f"{path}: importance or obstacles is not numeric; {RERUN}")
    importance = np.asarray(importance, dtype=np.float64)
    if not np.isfinite(importance).all():
        raise UserError(f"{path}: importance holds NaN or infinite values; {RERUN}")
    if importance.min() < 0.0 or importance.max() > 1.0:
        low, high = float(importance.min()), float(importance.max())
        raise UserError(
            f"{path}: importance spans {low:.3g} .. {high:.3g}, outside 0 .. 1 (Def. 2); {RERUN}"
        )
    if obstacles.dtype != bool and not np.isin(obstacles, (0, 1)).all():
        raise UserError(f"{path}: obstacles must hold true/false (or 0/1) per cell; {RERUN}")
    obstacles = np.asarray(obstacles, dtype=bool)
    if obstacles.all():
        raise UserError(f"{path}: obstacles cover every cell (no free cell to patrol); {RERUN}")
    return importance, obstacles
