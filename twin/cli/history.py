"""``twin history``: the per-step, per-cell history of earlier days from SUMO runs' tapes.

Each tape (``tape.parquet``, ``tapes/seed-<s>.parquet`` of a ``twin run`` folder, or a tape
file) is replayed without SUMO through the run's own MFD observation model
(:class:`twin.traffic.tape.TapeTraffic`); the true maps ``T^0..T^T`` of all of them give the
mean, variance and autocorrelation of :class:`twin.belief.History`, written as ``.npz`` for
``twin run --history``. Runs that read fixed detectors add each station's calibration (its
readings against the replayed truth, :func:`twin.belief.fit_detector_calibration`).
"""

from __future__ import annotations

import argparse
import contextlib
import os
from pathlib import Path

from twin.cli import check_seeds, path_arg
from twin.errors import UserError


def add_parser(subparsers) -> None:
    p = subparsers.add_parser(
        "history",
        help="build the history of earlier days (belief models' prior) from SUMO runs",
        description="Replay the traffic tapes of earlier `twin run` folders (every seed's) "
        "without SUMO and write, per step and cell, the mean and variance of the true "
        "importance and, per cell, the lag-1 autocorrelation of its deviations: the history "
        "that `twin run --history FILE` scores its belief models with. Runs that read fixed "
        "detectors (detectors.parquet) also give each station's bias and variance against "
        "the truth, with which the nowcast takes that station's readings. Use SUMO seeds that "
        "the runs you evaluate do not use (e.g. `twin run --sumo-seed 100 --seeds 3`).",
    )
    origin = p.add_mutually_exclusive_group(required=True)
    origin.add_argument(
        "--from",
        dest="sources",
        type=path_arg,
        nargs="+",
        metavar="RUN_DIR",
        help="`twin run` folders (all their seeds' tapes) or tape.parquet files; at least 2 "
        "simulations in all",
    )
    origin.add_argument(
        "--dynamics",
        type=path_arg,
        metavar="CONFIG",
        help="instead of SUMO runs, --days days of the dynamic synthetic generator "
        "(twin/traffic/dynamic.py, seeds --seed, --seed + 1, ...) on a synthetic scenario "
        "config's grid and horizon: the history of a synthetic map",
    )
    p.add_argument("--days", type=int, default=8, help="--dynamics: days (default 8, >= 2)")
    p.add_argument(
        "--seed",
        type=int,
        default=2_000_000,
        help="--dynamics: seed of the first day (default 2000000; keep it apart from the "
        "seeds a pretraining used, recorded in its checkpoint)",
    )
    p.add_argument(
        "--disturbances",
        type=int,
        default=8,
        help="--dynamics: disturbances per day (default 8, at most 10000)",
    )
    p.add_argument("--out", type=path_arg, required=True, help="history file to write (.npz)")
    p.add_argument(
        "--max-memory-gb",
        type=float,
        default=None,
        help="refuse a history whose days or tapes pass this memory, in GB (default "
        "$TWIN_MAX_MEMORY_GB or 8)",
    )
    p.set_defaults(func=main)


#: Peak memory of ``twin history`` beside the interpreter (:data:`twin.experiment.
#: PROCESS_BYTES`), per cell and step of each day of the dynamic generator
#: (:data:`twin.belief.DAY_BYTES`), of each tape (its truth maps held, float64) and of the one
#: tape being replayed.
TAPE_BYTES, REPLAY_BYTES = 24, 130


def check_days_memory(config, days: int, limit_gb: float | None) -> None:
    """Refuse (one line) ``days`` days of maps of ``config``'s grid and horizon past the memory
    limit (:data:`DAY_BYTES`), before any is computed."""
    from twin.belief import DAY_BYTES
    from twin.experiment import MEMORY_ENV, PROCESS_BYTES, memory_limit_gb
    from twin.resources import check_grid_size

    g, horizon = config.grid, config.traffic.horizon
    check_grid_size(g.nx, g.ny, f"--dynamics {config.path}", "use a smaller grid")
    limit = memory_limit_gb(limit_gb)
    need = PROCESS_BYTES + days * (horizon + 1) * g.nx * g.ny * DAY_BYTES
    if need > limit * 1e9:
        raise UserError(
            f"--dynamics {config.path}: {days} days of {g.nx} x {g.ny} cells x {horizon + 1} "
            f"maps need about {need / 1e9:,.1f} GB, over the {limit:g} GB limit; use fewer "
            f"--days, a smaller grid or horizon, or raise --max-memory-gb / ${MEMORY_ENV}"
        )


def check_tapes_memory(paths: list[Path], limit_gb: float | None) -> None:
    """Refuse (one line) a history of the tapes ``paths`` past the memory limit, from their
    recorded grids and horizons (a tape whose metadata does not read is left to its replay,
    which says why): every tape's truth maps are held, one tape is replayed at a time."""
    from twin.experiment import MEMORY_ENV, PROCESS_BYTES, memory_limit_gb
    from twin.traffic.tape import tape_footer

    limit = memory_limit_gb(limit_gb)
    sizes = []
    for path in paths:
        try:
            settings = (tape_footer(path) or {})["settings"]
            nx, ny = settings["identity"]["grid"]
            sizes.append((int(settings["horizon"]) + 1) * int(nx) * int(ny))
        except (TypeError, KeyError, ValueError):  # damage: the replay refuses it by name
            continue
    need = PROCESS_BYTES + sum(sizes) * TAPE_BYTES + max(sizes, default=0) * REPLAY_BYTES
    if need > limit * 1e9:
        raise UserError(
            f"--from: {len(paths)} tapes of {sum(sizes):,} cell-steps in all need about "
            f"{need / 1e9:,.1f} GB, over the {limit:g} GB limit; use fewer runs, or raise "
            f"--max-memory-gb / ${MEMORY_ENV}"
        )


def dynamics_days(args):
    """The history of ``--days`` days of the dynamic generator on ``--dynamics``' grid."""
    from twin.config import load_config, make_grid, shipped_config
    from twin.traffic.dynamic import MAX_DISTURBANCES, dynamics_history

    config = load_config(shipped_config(args.dynamics))
    if config.traffic.kind != "synthetic":
        raise UserError(
            f"--dynamics {args.dynamics}: [traffic].kind = {config.traffic.kind!r}; give a "
            "synthetic scenario config (its grid and horizon)"
        )
    for flag, value, low in (("--days", args.days, 2), ("--seed", args.seed, 0),
                             ("--disturbances", args.disturbances, 1)):  # fmt: skip
        if value < low:
            raise UserError(f"{flag} {value}: give a whole number >= {low}")
    if args.disturbances > MAX_DISTURBANCES:
        raise UserError(
            f"--disturbances {args.disturbances}: give at most {MAX_DISTURBANCES} a day (more "
            "make one flat jam of the map)"
        )
    check_seeds("--seed", args.seed, args.days, "--days", least=2)
    check_days_memory(config, args.days, args.max_memory_gb)
    seeds = range(args.seed, args.seed + args.days)
    return dynamics_history(make_grid(config), config.traffic.horizon, seeds, args.disturbances)


def tapes_of(path: Path) -> list[Path]:
    """The tapes of a run folder (every seed's, else ``tape.parquet``), once the folder reads
    back (:func:`twin.report.load.load_run`: its tapes agree with its results), or a tape
    file."""
    if path.is_file():
        return [path]
    if not path.is_dir():
        raise UserError(f"{path}: no such run folder or tape; pass `twin run` folders")
    per_seed = sorted((path / "tapes").glob("seed-*.parquet"))
    if (path / "run.json").is_file():  # a run folder: its tapes agree with its results
        from twin.report.load import load_run

        seeds = load_run(path).run.get("seeds") or []
        own = {f"seed-{s}.parquet" for s in seeds}
        stray = [p for p in per_seed if p.name not in own]
        if stray:
            raise UserError(
                f"{stray[0]}: no tape of the run's seeds {seeds} (its run.json), so not one of "
                f"its days; remove it from {path / 'tapes'}, or pass it as a tape of its own"
            )
    if per_seed:
        return per_seed
    if (path / "tape.parquet").is_file():
        return [path / "tape.parquet"]
    raise UserError(
        f"{path}: no tape.parquet (nor tapes/); a history needs the folders of SUMO runs "
        "(`twin run`)"
    )


def replay_truth(path: Path):
    """The true maps ``(T+1, nx, ny)`` of a tape, its obstacles and recorded settings."""
    import numpy as np

    from twin.traffic.tape import Tape, TapeTraffic

    source = TapeTraffic(Tape.read(path), source_name=str(path))
    maps = []
    for importance in source.importance_maps():
        truth = source.truth_map()
        maps.append(np.array(importance if truth is None else truth, dtype=np.float64))
    if len(maps) != source.horizon + 1:
        raise UserError(
            f"{path}: the tape holds {len(maps)} of the {source.horizon + 1} steps T^0..T^"
            f"{source.horizon} (a partial run); use finished runs"
        )
    return np.stack(maps), source.grid.obstacles, source.tape.settings


#: The columns of ``detectors.parquet`` a history's detector calibration reads.
READING_COLUMNS = {"seed": "int", "step": "int", "i": "int", "j": "int", "importance": "finite"}


def detector_readings(tape: Path, obstacles, horizon: int):
    """The fixed detectors' readings of the day a run folder's tape recorded
    (``detectors.parquet`` beside ``tape.parquet`` or above ``tapes/``, rows of the tape's
    seed) as :class:`twin.belief.DetectorObservations`; None for a run without detectors. A
    reading off the grid, on an obstacle, outside ``0..horizon`` or outside [0, 1] is refused
    in one line."""
    from twin.belief import DetectorObservations
    from twin.readback import RERUN, read_table

    per_seed = tape.parent.name == "tapes" and tape.name.startswith("seed-")
    path = (tape.parent.parent if per_seed else tape.parent) / "detectors.parquet"
    if not path.is_file():
        return None
    rows = read_table(path, READING_COLUMNS)
    seed = int(tape.stem.removeprefix("seed-")) if per_seed else rows["seed"].min()
    rows = rows[rows["seed"] == seed]
    nx, ny = obstacles.shape
    i, j, k, v = (rows[c].to_numpy() for c in ("i", "j", "step", "importance"))
    bad = (i < 0) | (i >= nx) | (j < 0) | (j >= ny) | (k < 0) | (k > horizon) | (v < 0) | (v > 1)
    bad |= ~bad & obstacles[i.clip(0, nx - 1), j.clip(0, ny - 1)]
    if bad.any():
        n = int(bad.argmax())
        raise UserError(
            f"{path}: seed {seed}, step {k[n]}: a reading {v[n]} at cell ({i[n]}, {j[n]}) is off "
            f"the {nx} x {ny} grid's free cells, steps 0..{horizon} or [0, 1]; {RERUN}"
        )
    return DetectorObservations.from_readings(zip(k, i * ny + j, v, strict=True), horizon)


def main(args: argparse.Namespace) -> int:
    from twin.boundary import hold_notices
    from twin.experiment import memory_limit_gb
    from twin.outputs import check_output_file

    hold_notices(to_end=True)  # said when the history is written; a refusal is its one line
    memory_limit_gb(args.max_memory_gb)  # a bad limit is refused first
    if args.out.suffix != ".npz":
        raise UserError(f"--out {args.out}: give a file name ending in .npz")
    check_output_file(args.out, "--out")
    if os.path.islink(args.out) and not args.out.exists():
        raise UserError(f"--out {args.out}: a link to nothing; give a new file name")
    claim = _claim(args.out)  # two commands at once into one --out: the second is refused
    try:
        return _write_history(args)
    except BaseException:
        with contextlib.suppress(OSError):
            if claim is not None and args.out.stat().st_size == 0:
                args.out.unlink()  # the empty claim, never a history written meanwhile
        raise
    finally:
        if claim is not None:
            os.close(claim)


def _claim(out: Path) -> int | None:
    """Claim ``out`` for this command: create it empty and hold a lock on it while the history
    is computed (the written history replaces it). A file there with content is refused (twin
    history never overwrites one), an empty one held by another command too; an empty one no
    command holds (left by a command that was killed) is taken over. Its folder is made only
    when the history is written (a refusal leaves no folder behind): None then."""
    import fcntl

    if not out.parent.is_dir():
        return None
    exists = f"--out {out}: exists; give a new file name (twin history never overwrites a file)"
    try:
        fd = os.open(out, os.O_CREAT | os.O_EXCL | os.O_WRONLY, 0o644)
    except FileExistsError:
        if not out.is_file() or out.stat().st_size > 0:
            raise UserError(exists) from None
        fd = os.open(out, os.O_WRONLY)
    except OSError:
        return None  # the write itself says what is wrong with the folder
    try:
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except OSError:
        os.close(fd)
        raise UserError(
            f"--out {out}: another command is writing it now; give a new file name (twin "
            "history never overwrites a file)"
        ) from None
    if os.fstat(fd).st_size > 0:  # written in between: a history now
        os.close(fd)
        raise UserError(exists)
    return fd


def _write_history(args: argparse.Namespace) -> int:
    import numpy as np

    from twin.belief import fit_detector_calibration, fit_history
    from twin.files import atomic_write
    from twin.outputs import make_parent

    if args.dynamics is not None:
        history = dynamics_days(args)
        atomic_write(make_parent(args.out, "--out"), history.save)
        days = f"days of the dynamic generator (seeds {args.seed}-{args.seed + args.days - 1})"
        _say_written(history, days, args.out)
        return 0
    paths = [t for p in args.sources for t in tapes_of(p)]
    if len(paths) < 2:
        raise UserError(
            f"--from gives {len(paths)} simulation; a history needs at least 2 (variance "
            "across days): run more seeds, e.g. `twin run --sumo-seed 100 --seeds 3`"
        )
    check_tapes_memory(paths, args.max_memory_gb)
    maps, seeds, first, stations = [], {}, None, []
    networks: dict[str | None, Path] = {}  # each network file's first tape
    for path in paths:
        truth, obstacles, settings = replay_truth(path)
        readings = detector_readings(path, obstacles, truth.shape[0] - 1)
        if readings is not None:
            stations.append((readings, truth))
        seed = settings.get("seed")
        key = (truth.shape[0] - 1, settings.get("step_s"), settings.get("begin"))
        if first is None:
            first = (path, obstacles, key)
        elif obstacles.shape != first[1].shape or not np.array_equal(obstacles, first[1]):
            raise UserError(
                f"{path}: grid or obstacles differ from those of {first[0]}; a history needs "
                "runs of one scenario"
            )
        elif key != first[2]:
            raise UserError(
                f"{path}: horizon, step or start (T, step_s, begin) = {key} differs from "
                f"{first[0]}'s {first[2]}; a history needs runs of one scenario"
            )
        if not isinstance(seed, int) or isinstance(seed, bool):
            raise UserError(
                f"{path}: the tape records no SUMO seed; a history keeps each day's "
                "seed, so that a run on one of them is refused (record the tape again)"
            )
        if seed in seeds:
            raise UserError(
                f"{path}: SUMO seed {seed} again (also {seeds[seed]}); a history needs "
                "distinct simulations"
            )
        seeds[seed] = path
        maps.append(truth)
        identity = settings.get("identity")
        network = identity.get("net_sha256") if isinstance(identity, dict) else None
        networks.setdefault(network, path)
    _, obstacles, (_, step_s, begin) = first
    if len(networks) > 1:  # days of other demand are a history; of another network, rarely
        (a, pa), (b, pb) = list(networks.items())[:2]
        from twin.notices import notify

        notify(
            f"twin: notice: {pb} ran on another network file than {pa} (sha256 "
            f"{str(b)[:12]}... against {str(a)[:12]}...); their grids and obstacles match, so "
            "the history pairs their cells by position: keep days of one network for a prior "
            "of its traffic"
        )
    history = fit_history(
        maps,
        obstacles,
        float(step_s) if isinstance(step_s, (int, float)) else None,
        begin if isinstance(begin, str) else None,
        list(seeds),
        [str(p) for p in paths],
        fit_detector_calibration(stations),
    )
    atomic_write(make_parent(args.out, "--out"), history.save)
    simulations = f"simulations (SUMO seeds {', '.join(map(str, seeds))})"
    _say_written(history, simulations, args.out, f", from {begin or '?'}", len(stations))
    return 0


def _say_written(history, days: str, out: Path, start: str = "", with_detectors: int = 0) -> None:
    """What ``twin history`` wrote: its days, grid, steps and spread (mean and standard
    deviation over days, the median autocorrelation rho), the detector calibration when there
    is one, and the file."""
    import numpy as np

    free = ~history.obstacles
    print(
        f"history: {history.n_runs} {days}, {free.shape[0]} x {free.shape[1]} cells, "
        f"T = {history.horizon}{start}; mean importance {history.mean[:, free].mean():.3f}, "
        f"mean std {np.sqrt(history.var[:, free]).mean():.3f}, "
        f"median rho {np.median(history.rho[free]):.2f}"
    )
    if history.detectors is not None:
        c = history.detectors
        print(
            f"detector calibration: {len(c.cells)} station cells from {with_detectors} "
            f"simulations with detectors; bias {c.bias.min():+.3f} .. {c.bias.max():+.3f}, "
            f"std {np.sqrt(c.var).min():.3f} .. {np.sqrt(c.var).max():.3f}"
        )
    print(f"written: {out}")
