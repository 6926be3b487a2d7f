"""Running a transfer matrix: record the tapes, train (or load) each row's checkpoint, then
evaluate every row on every column with one sweep (:func:`twin.sweep.run_sweep`), each cell
one traffic pass with the classical swarms, every row's learned swarms (``rl@<row>``,
``rl-online@<row>``) and the ceilings side by side.

The run folder::

    transfer.json            the config, the rows' checkpoints, every invocation's timings
    tapes/<seed>.parquet     the earlier days' SUMO runs (rows trained on tapes)
    rows/<row>/              each row's pretraining folder: qnet.pt, provenance.json,
                             curve.csv, train_log.csv (a loaded row: provenance.json only)
    sweep/                   the evaluation sweep: cells/, results.csv, summary.csv
    matrix.csv               one line per (row, learned swarm, column)
    report/transfer.html     the matrix, the heatmap, the ceilings, the rows' provenance

Every stage skips what is done: a rerun resumes.
"""

from __future__ import annotations

import json
import math
import shutil
import time
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

from twin.boundary import folder_claimed
from twin.errors import UserError
from twin.files import atomic_write, read_record, rebased
from twin.transfer.config import TransferConfig

#: What a transfer writes into its folder (and the boundary's error.log).
TRANSFER_FILES = frozenset(
    {"transfer.json", "tapes", "rows", "sweep", "matrix.csv", "report", "error.log"}
)


def check_transfer_folder(out: Path, flag: str = "--out") -> None:
    """Refuse (one line) a folder that holds anything a transfer does not write."""
    if not out.is_dir():
        return
    foreign = sorted(
        p.name for p in out.iterdir() if p.name not in TRANSFER_FILES and ".tmp" not in p.name
    )
    if foreign:
        raise UserError(
            f"{flag} {out}: holds {foreign[0]!r}, which `twin transfer` does not write; give an "
            "empty or new folder, or the folder of the transfer to resume"
        )


def run_tasks(
    fn: Callable, tasks: Sequence[dict], executor: str, workers: int, address: str | None
) -> list[Any]:
    """``fn(task)`` for every task on the executor (:mod:`twin.executors`), results in task
    order; the first failure is one line naming the task."""
    from twin.executors import _error_line, local_tasks, ray_tasks

    if not tasks:
        return []
    workers = max(1, min(workers, len(tasks)))
    args = [(t,) for t in tasks]
    if workers == 1 and executor == "local":  # one after another, in this process
        return [fn(t) for t in tasks]
    runs = (
        local_tasks(fn, args, workers)
        if executor == "local"
        else ray_tasks(fn, args, workers, address)
    )
    results: list[Any] = [None] * len(tasks)
    for n, value, error in runs:
        if error is not None:
            if isinstance(error, UserError):
                raise UserError(f"{tasks[n]['what']}: {error}") from None
            raise UserError(f"{tasks[n]['what']} failed: {_error_line(error)}") from None
        results[n] = value
    return results


# ----------------------------------------------------------------------------- 1. tapes
def record_tape(task: dict[str, Any]) -> str:
    """Run one SUMO simulation of the tapes' scenario (seed ``task["seed"]``) to its end and
    write its tape to ``task["path"]`` (a worker task: plain dict in, path out)."""
    from twin.experiment import limit_threads
    from twin.sweep.cells import scenario_config
    from twin.traffic_kinds import build_traffic

    limit_threads()
    config = scenario_config(Path(task["config"]), task["overrides"])
    source = build_traffic(config, 0, int(task["seed"]), separate_process=False)
    try:
        for _ in source.importance_maps():
            pass
        Path(task["path"]).parent.mkdir(parents=True, exist_ok=True)
        atomic_write(Path(task["path"]), source.tape().write)
    finally:
        source.close()
    return task["path"]


#: What a tape's recorded settings must share with its task's scenario to be its tape.
TAPE_KEYS = ("seed", "horizon", "begin", "step_s", "warmup_s", "mesoscopic", "net_file",
             "route_files", "sumocfg", "reads_per_step", "read_offsets_s", "mfd_fit",
             "mfd_prior", "detection_p", "identity.cell_m", "identity.grid")  # fmt: skip


def tape_still_holds(task: dict[str, Any]) -> bool:
    """Whether the tape of ``task`` (:func:`tape_tasks`) recorded before is there, is the
    tape of its scenario and seed (its settings those of the scenario built again: a tape of
    another seed, window or network copied over it is not), and its scenario's SUMO files
    (its traffic identity: network, routes, additional files, sumocfg) are still what it was
    recorded on; otherwise that is said, and the tape recorded again."""
    from twin.notices import notify
    from twin.sweep.store import inputs_changed
    from twin.traffic.tape import tape_footer

    path = Path(task["path"])
    if not path.is_file():
        return False
    settings = (tape_footer(path) or {}).get("settings")  # damaged: its reader says why
    changed = inputs_changed({"traffic": settings}) if isinstance(settings, dict) else "file"
    why = f"its {changed} changed since it was recorded" if changed else _other_tape(task, settings)
    if why is None:
        return True
    notify(f"twin: notice: tape {path.name}: {why}; recording it again")
    return False


def _other_tape(task: dict[str, Any], settings: dict[str, Any]) -> str | None:
    """The first of :data:`TAPE_KEYS` in which the tape's ``settings`` differ from those of
    its task's scenario built again (unstarted), in words, or None."""
    from twin.sweep.cells import scenario_config
    from twin.sweep.runner import live_settings

    try:
        config = scenario_config(Path(task["config"]), task["overrides"])
        expected = live_settings(config, int(task["seed"]))
    except UserError:  # recording it again says what is wrong with the scenario
        return "its scenario cannot be built as it stands"

    def value(record: dict[str, Any], key: str) -> Any:
        for part in key.split("."):
            record = record.get(part) if isinstance(record, dict) else None
        return record

    def same(a: Any, b: Any) -> bool:  # numbers as recorded, to their rounding
        if isinstance(a, list) and isinstance(b, list):
            return len(a) == len(b) and all(same(x, y) for x, y in zip(a, b, strict=True))
        numbers = all(isinstance(v, (int, float)) and not isinstance(v, bool) for v in (a, b))
        return math.isclose(a, b, rel_tol=1e-9, abs_tol=1e-12) if numbers else a == b

    for key in TAPE_KEYS:
        if not same(value(settings, key), value(expected, key)):
            return (
                f"it was recorded with {key} = {value(settings, key)!r}, not its scenario's "
                f"{value(expected, key)!r}"
            )
    return None


def trains_on_tapes(config: TransferConfig) -> bool:
    """Whether a row is trained on the ``[tapes]`` runs (which are then recorded)."""
    return config.tapes is not None and any(
        r.traffic == "tapes" and r.checkpoint is None for r in config.row
    )


def tape_tasks(config: TransferConfig, out: Path) -> list[dict[str, Any]]:
    t = config.tapes
    if not trains_on_tapes(config):
        return []
    return [
        {
            "what": f"tape of seed {seed}",
            "config": str(t.config),
            "overrides": t.overrides,
            "seed": seed,
            "path": str((out / "tapes" / f"{tape_stem(t)}-seed-{seed}.parquet").resolve()),
        }
        for seed in t.seeds
    ]


def tape_stem(tapes) -> str:
    """``<config>-<hash>``: the hash covers the scenario file's text and the overrides, so a
    changed scenario records new tapes instead of reusing the old ones."""
    import hashlib

    text = Path(tapes.config).read_bytes() + json.dumps(tapes.overrides, sort_keys=True).encode()
    return f"{Path(tapes.config).stem}-{hashlib.sha256(text).hexdigest()[:8]}"


# ----------------------------------------------------------------------------- 2. rows
def row_pretrain_config(config: TransferConfig, row, out: Path, checkpoints: dict[str, str]):
    """The :class:`PretrainConfig` of a trained row: the defaults with ``[schedule]``, the
    row's own schedule keys, its traffic, tapes and init (a row's name resolved to that row's
    checkpoint) set as overrides (:func:`twin.config.with_overrides`), each named in an error
    by its key in the transfer config; paths relative to the transfer config."""
    from twin.config import with_overrides
    from twin.training.pretrain import PretrainConfig
    from twin.transfer.config import row_schedule

    where = f"{config.path}: [[row]] {row.name}"
    overrides, labels = row_schedule(config, row)
    overrides |= {"traffic": row.traffic, "out": str(out)}
    labels |= {"traffic": f"{where}.traffic", "out": f"{where} (its folder {out})"}
    if row.traffic == "tapes":
        overrides["tapes"] = [t["path"] for t in tape_tasks(config, out.parents[1])]
        labels["tapes"] = f"{config.path}: [tapes]"
    if row.init is not None:
        overrides["init"] = checkpoints.get(row.init, row.init)
        labels["init"] = f"{where}.init"
    return with_overrides(PretrainConfig.from_data(config.path, {}), overrides, labels)


def row_schedule_config(config: TransferConfig, row, **more: Any):
    """The :class:`PretrainConfig` of a row's schedule alone (``[schedule]`` and the row's own
    keys, ``more`` on top): what is known of it before its tapes are recorded."""
    from twin.config import with_overrides
    from twin.training.pretrain import PretrainConfig
    from twin.transfer.config import row_schedule

    overrides, labels = row_schedule(config, row)
    return with_overrides(PretrainConfig.from_data(config.path, {}), overrides | more, labels)


def check_tapes_scenario(config: TransferConfig) -> None:
    """The ``[tapes]`` scenario rows train on is a SUMO scenario: tapes are recorded from a
    live simulation (a synthetic one has no tape to record)."""
    from twin.sweep.cells import scenario_config

    if not trains_on_tapes(config):
        return
    labels = {k: f"{config.path}: [tapes].overrides.{k!r}" for k in config.tapes.overrides}
    scenario = scenario_config(Path(config.tapes.config), config.tapes.overrides, labels)
    kind = scenario.traffic.kind
    if kind != "sumo":
        raise UserError(
            f"{config.path}: [tapes].config = {config.tapes.config}: its traffic is {kind!r}, "
            'not a SUMO scenario; tapes are recorded from SUMO (e.g. config = "shenzhen.toml")'
        )
    check_tape_rows_fit(config, scenario)


def check_tape_rows_fit(config: TransferConfig, scenario) -> None:
    """The drones a tapes row trains with (its training map's) fit on the free cells of the
    ``[tapes]`` scenario's grid, found before a tape is recorded (its network read, its grid
    laid, SUMO not started)."""
    from twin.notices import drop_notices, hold_notices, release_notices
    from twin.sweep.runner import prepare_sumo
    from twin.traffic_kinds import build_traffic

    drones = {
        row.name: row_schedule_config(config, row).n_drones
        for row in config.row
        if row.traffic == "tapes" and row.checkpoint is None
    }
    hold_notices()  # the scenario's notices follow a fit, and a refusal is one line
    try:
        prepare_sumo(scenario)
        source = build_traffic(scenario, 0, config.tapes.seeds[0])
        free = source.grid.n_free
        getattr(source, "close", lambda: None)()
    except BaseException:
        drop_notices()
        raise
    for name, n in drones.items():
        if n > free:
            drop_notices()
            raise UserError(
                f"{config.path}: [[row]] {name} trains {n} drones on tapes of "
                f"{config.tapes.config.name}, whose grid has {free} free "
                f"cell{'s' * (free != 1)}; give [schedule] scenario_overrides = "
                f'{{ "swarm.n_drones" = {free} }}, or a [tapes] scenario with more room'
            )
    release_notices()


def check_row_starts(config: TransferConfig) -> None:
    """Each fine-tuned row's start fits it (state and layers) before any stage runs: a
    checkpoint file is loaded, a row trained before is compared by its schedule (its tapes
    are not recorded yet: only the schedule's keys are read)."""
    from twin.learning.checkpoint import checkpoint_state, read_checkpoint
    from twin.training.pretrain import check_initial_fit, initial_network

    def schedule(row, **more: Any):
        return row_schedule_config(config, row, **more)

    names = {r.name: r for r in config.row}
    for row in config.row:
        if row.checkpoint is not None or row.init is None:
            continue
        start = names.get(row.init)
        if start is None:  # a checkpoint file
            try:
                initial_network(schedule(row, init=row.init))
            except UserError as exc:
                raise UserError(f"{config.path}: [[row]] {row.name}: {exc}") from None
            continue
        if start.checkpoint is not None:
            meta = read_checkpoint(start.checkpoint)["meta"]
            state, layers = checkpoint_state(start.checkpoint, meta).name, meta.get("layers")
        else:
            before = schedule(start)
            state, layers = before.state, list(before.layers)
        where = f"{config.path}: [[row]] {row.name}.init = {row.init}"
        check_initial_fit(schedule(row), where, state, layers)


def train_row(task: dict[str, Any]) -> dict[str, Any]:
    """Train one row (a worker task), or reuse its folder when its provenance matches."""
    from twin.experiment import limit_threads
    from twin.training.pretrain import PretrainConfig, pretrain

    limit_threads()
    cfg = PretrainConfig.from_data(task["where"], task["pretrain"])
    out = Path(cfg.out)
    why = provenance_mismatch(out, cfg)
    if why is not None:
        if (out / "provenance.json").is_file():  # finished, but not as this row asks now
            from twin.notices import notify

            clear_row_folder(out, why)  # its checkpoint resumes nothing
            notify(f"twin: notice: row {out.name}: {why}; training it again")
        pretrain(cfg, progress=False, max_memory_gb=task.get("max_memory_gb"))
    return json.loads(read_record(out / "provenance.json"))


def clear_row_folder(
    out: Path, why: str = "its settings, tapes, start or scenario changed"
) -> None:
    """Remove what pretraining wrote into a row's folder, to train it again (``why``: its
    :func:`provenance_mismatch`); a file it did not write (the user's) is refused in one line,
    and nothing is removed."""
    from twin.training.pretrain import written_by_pretraining

    entries = sorted(out.iterdir())
    foreign = [e.name for e in entries if not written_by_pretraining(e)]
    if foreign:
        raise UserError(
            f"row {out.name}: must be trained again ({why}), but {out} holds {foreign[0]!r}, "
            "which twin did not write; move it out of the folder and run again"
        )
    for entry in entries:
        if entry.is_dir() and not entry.is_symlink():
            shutil.rmtree(entry)
        else:
            entry.unlink()


def provenance_mismatch(out: Path, cfg) -> str | None:
    """None when ``out`` holds a finished model whose provenance records ``cfg``'s settings,
    else why not (said when a finished row is trained again)."""
    from twin.files import file_sha256

    path, model = out / "provenance.json", out / "qnet.pt"
    if not path.is_file():
        return "not trained"
    if not model.is_file():
        return "its model qnet.pt is missing"
    try:
        record = json.loads(read_record(path))
    except (OSError, ValueError):
        return "its provenance.json cannot be read"
    if not isinstance(record, dict):
        return "its provenance.json is not a record of its training"
    if isinstance(record.get("config"), dict):
        recorded = record["config"].get("out")  # <transfer>/rows/<row> when it was trained
        if isinstance(recorded, str):  # a transfer folder moved since: its own paths moved
            record = rebased(record, Path(recorded).parent.parent, Path(out).parent.parent)
    if record.get("config") != json.loads(json.dumps(cfg.training_dict(), default=str)):
        return "its settings changed since it was trained"
    if record.get("qnet_sha256") != file_sha256(model):
        return "its model qnet.pt is not the one it trained (changed or damaged)"
    recipe = record.get("recipe") if isinstance(record.get("recipe"), dict) else {}
    try:  # the files it learnt from are still those: tapes, its start, its scenario
        init = recipe.get("init") or {}
        same = (
            recipe.get("tapes") == {t: file_sha256(t) for t in cfg.tapes}
            and (init.get("sha256") if cfg.init else None)
            == (file_sha256(cfg.init) if cfg.init else None)
            and (recipe.get("scenario") or {}).get("sha256") == file_sha256(cfg.scenario)
        )
    except (OSError, AttributeError):
        same = False
    return None if same else "its tapes, start or scenario changed since it was trained"


def loaded_provenance(row, out: Path) -> dict[str, Any]:
    """``provenance.json`` of a row loaded from a checkpoint: what the checkpoint says of its
    training (its own recipe, epochs, wall time), its hash and path."""
    from twin.files import file_sha256
    from twin.learning.checkpoint import read_checkpoint
    from twin.training.pretrain import SCHEDULE_KEYS

    meta = read_checkpoint(row.checkpoint)["meta"]
    config = meta.get("config") if isinstance(meta.get("config"), dict) else {}
    record = {
        "loaded": str(row.checkpoint),
        "qnet_sha256": file_sha256(row.checkpoint),
        "recipe": {
            "traffic": config.get("traffic", "paper"),
            "collector": config.get("collector", "random"),
            "n_step": config.get("n_step", 1),
        },
        "schedule": {k: config.get(k) for k in SCHEDULE_KEYS},
        "seeds": {"training": meta.get("seed")},
        "updates": int(meta.get("epoch") or 0) * int(config.get("iters_per_epoch") or 1),
        "wall_s": meta.get("wall_s"),
        "epoch": meta.get("epoch"),
        "config": config,
    }
    out.mkdir(parents=True, exist_ok=True)
    text = json.dumps(record, indent=1, default=str)
    atomic_write(out / "provenance.json", lambda p: p.write_text(text))
    return record


def train_rows(
    config: TransferConfig,
    out: Path,
    executor: str,
    workers: int,
    address: str | None,
    max_memory_gb: float | None = None,
) -> dict[str, dict[str, Any]]:
    """Every row's checkpoint and provenance: loaded rows first, then the trained rows in
    waves (a row fine-tuned from another waits for it), each wave on the executor."""
    rows: dict[str, dict[str, Any]] = {}
    checkpoints: dict[str, str] = {}
    for row in config.row:
        if row.checkpoint is not None:
            rows[row.name] = loaded_provenance(row, out / "rows" / row.name)
            checkpoints[row.name] = str(row.checkpoint)
    waiting = [r for r in config.row if r.checkpoint is None]
    while waiting:
        ready = [
            r for r in waiting if r.init is None or r.init in checkpoints or Path(r.init).is_file()
        ]
        tasks = [
            {
                "what": f"row {r.name!r}",
                "pretrain": row_pretrain_config(
                    config, r, out / "rows" / r.name, checkpoints
                ).model_dump(mode="json"),
                "where": str(config.path),
                "max_memory_gb": max_memory_gb,
            }
            for r in ready
        ]
        for r, record in zip(
            ready, run_tasks(train_row, tasks, executor, workers, address), strict=True
        ):
            rows[r.name] = record
            checkpoints[r.name] = str(out / "rows" / r.name / "qnet.pt")
        waiting = [r for r in waiting if r not in ready]
    for name, path in checkpoints.items():
        rows[name]["checkpoint"] = path
    return rows


# ----------------------------------------------------------------------------- 3. the sweep
def column_overrides(column) -> dict[str, Any]:
    """A column's overrides, with a generated network's file (built here, once)."""
    overrides = dict(column.overrides)
    if column.generate is not None:
        from twin.sumo.network import generated_network

        overrides["traffic.net"] = str(generated_network(column.generate))
    return overrides


def sweep_config(config: TransferConfig, rows: dict[str, dict[str, Any]], out: Path):
    """The evaluation sweep: the columns as scenarios, the classical and learned swarms, the
    rows' checkpoints, the evaluation seeds, the ceilings; its cells name the files of the
    transfer folder ``out`` relative to it (a folder moved keeps its cells)."""
    from pydantic import ValidationError

    from twin.sweep.config import SweepConfig

    learned = config.learned_swarms()
    data = {
        "sweep": {
            "name": config.name,
            "swarms": [*config.transfer.classical, *(s for s, _, _ in learned)],
            "seeds": config.seeds,
            "ceilings": True,
        },
        "scenario": [
            {"name": c.name, "config": str(c.config), "overrides": column_overrides(c)}
            for c in config.column
        ],
        "swarm_options": {s: {"checkpoint": rows[row]["checkpoint"]} for s, row, _ in learned},
    }
    try:
        sweep = SweepConfig.model_validate(data, context={"path": config.path})
    except ValidationError as exc:  # a checkpoint gone between training and evaluation
        from twin.config import check_message

        raise UserError(
            f"{config.path}: {check_message(exc.errors(include_url=False)[0])}"
        ) from None
    sweep._path, sweep._scenario_table, sweep._home = config.path, "[[column]]", out
    return sweep


def check_columns(config: TransferConfig, max_memory_gb: float | None = None) -> None:
    """Every column's scenario with its overrides, checked as the evaluation's sweep checks its
    cells (:func:`twin.sweep.check_cells`, against the same memory limit), before any tape is
    recorded or row trained: a value a column's scenario refuses is one line naming the
    transfer file's key (the notices of the columns said before it are held back)."""
    from twin.notices import drop_notices, hold_notices, release_notices
    from twin.sweep import check_cells
    from twin.sweep.cells import override_labels

    cells = [
        {
            "scenario": c.name,
            "config": str(c.config),
            "overrides": column_overrides(c),
            "labels": override_labels(config.path, c, {}, "[[column]]"),
            "tape": None,
            "seed": config.seeds[0],
            "swarms": list(config.transfer.classical),
            "max_memory_gb": max_memory_gb,
        }
        for c in config.column
    ]
    hold_notices()
    try:
        check_cells(cells)
    except BaseException:
        drop_notices()
        raise
    release_notices()


def check_row_states(config: TransferConfig) -> None:
    """Every row's network reads a state without a nowcast, before any stage runs: a nowcast
    state's swarm needs a history of earlier days of each column's scenario, which a transfer
    does not build."""
    from twin.learning.checkpoint import checkpoint_state, read_checkpoint

    for row in config.row:
        if row.checkpoint is not None:
            variant = checkpoint_state(row.checkpoint, read_checkpoint(row.checkpoint)["meta"])
            what = f"loads {row.checkpoint}, whose network reads state {variant.name!r}"
            fix = "give it a checkpoint trained on a state without one"
        else:
            variant = row_schedule_config(config, row).variant
            what = f"trains state {variant.name!r} ([schedule].state)"
            fix = 'train it on a state without one (e.g. state = "paper")'
        if variant.needs_belief:
            raise UserError(
                f"{config.path}: [[row]] {row.name} {what}: a nowcast of a history of "
                f"earlier days, which a transfer does not build for its columns; {fix}, or "
                "evaluate that network with `twin evaluate --history`"
            )


def run_transfer(
    config: TransferConfig,
    out: Path,
    executor: str = "local",
    workers: int = 1,
    address: str | None = None,
    progress: bool = False,
    say: Callable[[str], None] = lambda text: None,
    max_memory_gb: float | None = None,
) -> Path:
    """All the stages; returns the report's path. ``max_memory_gb`` (``--max-memory-gb``)
    bounds each row's pretraining and each cell's estimate."""
    from twin.learning.checkpoint import load_qnet

    for row in config.row:  # a checkpoint the rows load is refused before any stage starts
        if row.checkpoint is not None:
            load_qnet(row.checkpoint)
    check_row_starts(config)
    check_row_states(config)
    check_tapes_scenario(config)
    check_columns(config, max_memory_gb)
    out.mkdir(parents=True, exist_ok=True)
    with folder_claimed(out):  # one transfer at a time writes into a transfer folder
        # the rows' provenance names files the same from any folder
        return _transfer_stages(
            config, out.resolve(), executor, workers, address, progress, say, max_memory_gb
        )


def _transfer_stages(
    config: TransferConfig,
    out: Path,
    executor: str,
    workers: int,
    address: str | None,
    progress: bool,
    say: Callable[[str], None],
    max_memory_gb: float | None,
) -> Path:
    """:func:`run_transfer`'s stages once its config is checked and its folder is held: the
    tapes, the rows, the evaluation sweep, the matrix and the report."""
    from twin.sweep import run_sweep
    from twin.transfer.matrix import transfer_matrix
    from twin.transfer.report import write_transfer_report

    timings: dict[str, float] = {}

    t0 = time.perf_counter()
    tasks = [t for t in tape_tasks(config, out) if not tape_still_holds(t)]
    if tasks:
        say(f"recording {len(tasks)} tapes ({config.tapes.config.name}, seeds "
            f"{[t['seed'] for t in tasks]})")  # fmt: skip
    run_tasks(record_tape, tasks, executor, workers, address)
    timings["tapes_s"] = round(time.perf_counter() - t0, 2)

    t0 = time.perf_counter()
    say(f"training or loading {len(config.row)} rows: {', '.join(r.name for r in config.row)}")
    rows = train_rows(config, out, executor, workers, address, max_memory_gb)
    timings["rows_s"] = round(time.perf_counter() - t0, 2)

    t0 = time.perf_counter()
    sweep = sweep_config(config, rows, out)
    say(f"evaluating on {len(config.column)} columns x {len(config.seeds)} seeds "
        f"(seeds {config.seeds})")  # fmt: skip
    failure = None
    try:
        run_sweep(sweep, out / "sweep", executor=executor, workers=workers, address=address,
                  progress=progress, report=False, max_memory_gb=max_memory_gb)  # fmt: skip
    except UserError as exc:  # failed cells: the matrix of the others, then the error
        if not (out / "sweep" / "results.csv").exists():
            raise
        failure = exc
    timings["evaluation_s"] = round(time.perf_counter() - t0, 2)

    import pandas as pd

    results = pd.read_csv(out / "sweep" / "results.csv")
    matrix = transfer_matrix(results, config)
    atomic_write(out / "matrix.csv", lambda p: matrix.to_csv(p, index=False))
    history = []
    try:  # earlier invocations of this transfer (a resumed run skips what they did)
        history = json.loads(read_record(out / "transfer.json")).get("invocations", [])
    except (OSError, ValueError, AttributeError):
        history = []
    invocation = {
        "executor": executor,
        "workers": workers,
        "timings": timings,
        "finished": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
    }
    manifest = {
        "name": config.name,
        "config": str(config.path),
        "seeds": config.seeds,
        "rows": rows,
        "columns": [c.model_dump(mode="json") for c in config.column],
        "classical": config.transfer.classical,
        "timings": timings,
        "invocations": [*history, invocation],
    }
    text = json.dumps(manifest, indent=1, default=str)
    atomic_write(out / "transfer.json", lambda p: p.write_text(text))
    report = write_transfer_report(out, matrix, results, manifest)
    if failure is not None:
        raise failure
    return report
