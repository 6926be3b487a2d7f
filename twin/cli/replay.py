"""``twin replay RUN_DIR --gui``: watch a finished ``twin run`` in sumo-gui, swarms as recorded.

The run's SUMO scenario is rebuilt from the flags in its ``run.json`` (config, files, seeds) and
simulated again under sumo-gui (the same simulation: same options and seed); the drones are
drawn where ``trajectories.parquet`` says they were, no swarm is recomputed.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

from twin.cli import path_arg
from twin.errors import UserError


def add_parser(subparsers) -> None:
    from twin.cli.run import add_gui_arguments

    p = subparsers.add_parser(
        "replay",
        help="watch a finished `twin run` in sumo-gui (recorded trajectories, same traffic)",
        description="Re-run a `twin run` folder's SUMO simulation under sumo-gui and draw the "
        "drones along their recorded trajectories (no swarm is recomputed); --record saves it "
        "as a video. Relative paths in the run's flags are read from the folder the run was "
        "started in (run.json records it), whatever the current folder.",
    )
    p.add_argument("run_dir", type=path_arg, help="a run folder written by `twin run`")
    p.add_argument("--seed", type=int, help="which of the run's seeds to replay (default: first)")
    add_gui_arguments(p, always=True)
    p.set_defaults(func=main)


def run_arguments(run_dir: Path) -> argparse.Namespace:
    """``twin run``'s flags of a run folder, from the invocation its ``run.json`` records."""
    from twin.cli import build_parser
    from twin.readback import check_run_json, read_json
    from twin.swarms import check_policy_records

    path = run_dir / "run.json"
    run = check_run_json(path, read_json(path, required=True))
    check_policy_records(path, run)
    invocation = run.get("invocation") or {}
    if invocation.get("command") != "run":
        raise UserError(
            f"{path}: invocation = {invocation.get('command')!r} is not a "
            "`twin run`; only live SUMO runs can be replayed"
        )
    parser = build_parser()
    args = parser.parse_args(["run"])
    args.quiet = True
    actions = _run_actions(parser)
    cwd = invocation.get("cwd")  # an absolute folder (read back above); None for an older run
    started_in = None if cwd is None else Path(cwd)
    for key, value in (invocation.get("options") or {}).items():
        if key not in actions:
            raise UserError(
                f"{path}: invocation.options.{key} is not an option of `twin run`; {_RERUN}"
            )
        value = _option_value(path, key, value, actions[key])
        setattr(args, key, _from_folder(key, value, started_in))
    return args


def _from_folder(key: str, value, started_in: Path | None):
    """A recorded path option read from the folder the run was started in: the same file
    whatever the current folder. A config that was not found there was a shipped one (its
    name, ``configs/shenzhen.toml``), and is looked up among the shipped configs again."""
    if isinstance(value, list):
        return [_from_folder(key, v, started_in) for v in value]
    if not isinstance(value, Path) or value.is_absolute() or started_in is None:
        return value
    there = started_in / value
    if key == "config" and not there.exists() and not there.is_symlink():
        from twin.resources import shipped_config_named

        return shipped_config_named(value) or there
    return there


_RERUN = "the run.json was edited or written by another twin: rerun `twin run`"


def _run_actions(parser: argparse.ArgumentParser) -> dict[str, argparse.Action]:
    """``twin run``'s options by destination."""
    for action in parser._subparsers._group_actions:  # the subcommands
        run = action.choices.get("run")
        if run is not None:
            return {a.dest: a for a in run._actions if a.dest != "help"}
    return {}


def _option_value(path: Path, key: str, value, action: argparse.Action):
    """``value`` of the recorded option ``key``, typed as ``twin run`` would parse it; a
    value of another type is a one-line error."""
    if value is None:
        return None
    where = f"{path}: invocation.options.{key} = {str(value)[:60]!r}"
    many = action.nargs in ("*", "+") or isinstance(action, argparse._AppendAction)
    if isinstance(action, (argparse._StoreTrueAction, argparse._StoreFalseAction)):
        if not isinstance(value, bool):
            raise UserError(f"{where} must be true or false; {_RERUN}")
        return value
    if many:
        if not isinstance(value, list):
            raise UserError(f"{where} must be a list; {_RERUN}")
        return [_typed(where, v, action) for v in value]
    return _typed(where, value, action)


def _typed(where: str, value, action: argparse.Action):
    kind = action.type or (type(action.default) if action.default is not None else str)
    if kind in (path_arg, Path, str):
        if not isinstance(value, str) or (kind is not str and value == ""):
            raise UserError(f"{where} must be {'text' if kind is str else 'a path'}; {_RERUN}")
        value = Path(value) if kind is not str else value
    elif kind in (int, float):
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise UserError(f"{where} must be a number; {_RERUN}")
        if kind is int and value != int(value):
            raise UserError(f"{where} must be a whole number; {_RERUN}")
        value = kind(value)
    elif not isinstance(value, (str, int, float)):
        raise UserError(f"{where} must be text or a number; {_RERUN}")
    if action.choices is not None and value not in action.choices:
        raise UserError(f"{where} is not one of {sorted(map(str, action.choices))}; {_RERUN}")
    return value


def main(args: argparse.Namespace) -> int:
    from twin.boundary import hold_notices, notify, release_notices
    from twin.cli.run import build_experiment, finish_video, gui_drawer
    from twin.experiment import build_source, limit_threads
    from twin.readback import RERUN, TRAJECTORY_COLUMNS, check_trajectories, read_table
    from twin.report.load import load_run
    from twin.runs import check_run_folder
    from twin.sumo.gui import display

    limit_threads()
    hold_notices()  # printed once the simulation has started; a refusal is one line
    run_dir = args.run_dir
    if not run_dir.is_dir():
        what = "a file, not a run folder" if run_dir.exists() else "no such run folder"
        raise UserError(f"{run_dir}: {what}; pass the folder `twin run` wrote")
    check_run_folder(run_dir)
    # every file read back and checked against the others, as for a report
    replayed_tapes = load_run(run_dir).tape_maps
    experiment = build_experiment(run_arguments(run_dir))
    path = run_dir / "trajectories.parquet"
    trajectories = read_table(path, TRAJECTORY_COLUMNS)
    seeds = list(experiment.seeds)
    seed = seeds[0] if args.seed is None else args.seed
    if seed not in seeds:
        raise UserError(f"--seed {seed}: not among the run's seeds {seeds}")
    rows = trajectories[trajectories["seed"] == seed]
    recorded = _recorded_shape(run_dir)
    if recorded is not None:  # checked before SUMO starts; the source's grid is checked below
        check_trajectories(path, rows, recorded)
    if rows.empty:
        raise UserError(f"{path}: no trajectory of seed {seed}")
    swarms = list(experiment.swarms)
    present = set(rows["swarm"])
    missing = [s for s in swarms if s not in present]
    unknown = sorted(map(str, present - set(swarms)))
    if missing or unknown:
        what = (
            f"no rows of swarm {missing[0]!r}, which run.json lists"
            if missing
            else f"rows of swarm {unknown[0]!r}, which run.json does not list"
        )
        raise UserError(f"{path}: seed {seed} has {what}; {RERUN}")
    args.gui = True
    # its flags are checked before the scenario loads; the run's report is drawn afresh
    report = run_dir / "report"
    drawer = gui_drawer(args, swarms, owned=(report, f"{report}, the run's report"))
    source = build_source(experiment, seeds.index(seed))
    check_identity(run_dir, source)
    check_cells(path, rows, source.grid.shape)
    check_trajectories(path, rows, source.grid.shape, source.grid.obstacles)
    positions = {s: _positions(rows[rows["swarm"] == s]) for s in swarms}
    steps = min(len(p) for p in positions.values())
    tape_path = run_dir / ("tape.parquet" if seed == seeds[0] else f"tapes/seed-{seed}.parquet")
    kept = replayed_tapes.get(seed)
    if kept is not None and kept.shape[1:] == source.grid.shape:
        recorded_maps = iter(kept)  # the tape as read back: not replayed twice
    else:
        recorded_maps = recorded_importance(tape_path, source.grid.shape)
    drawer.attach(source)
    notify(drawer.legend())
    with display():
        maps = source.importance_maps()
        try:
            for k, importance in enumerate(maps):
                if k >= steps:
                    break
                check_same_traffic(tape_path, k, importance, next(recorded_maps, None))
                if k == 0:
                    release_notices()  # the simulation started as recorded
                drawer(k, {s: p[k] for s, p in positions.items()}, importance)
            drawer.flush()  # a partial run ends before the source's horizon
        finally:
            maps.close()
    ok = not args.record or finish_video(drawer)
    print(f"replayed {steps - 1} steps of seed {seed} from {run_dir}")
    return 0 if ok else 1


def recorded_importance(tape_path: Path, shape: tuple[int, int]):
    """The seed's recorded importance maps, step by step: its tape replayed through the MFD
    as ``twin evaluate --traffic`` does (the same maps the run scored); nothing without a
    tape (a run recorded before tapes were kept)."""
    from twin.traffic.tape import Tape, TapeTraffic

    if not tape_path.is_file():
        return iter(())
    return TapeTraffic(Tape.read(tape_path, shape), source_name=str(tape_path)).importance_maps()


def check_same_traffic(tape_path: Path, k: int, replayed: np.ndarray, recorded) -> None:
    """Refuse (one line) a replay whose simulation, rebuilt from ``run.json``, gives other
    importance at step ``k`` than the run recorded: its files, hashes and versions may all be
    as recorded and the traffic still not (a run.json edited to name other files)."""
    if recorded is None:
        return
    diff = np.abs(np.asarray(replayed, float) - np.asarray(recorded, float))
    if diff.max() <= 1e-9:
        return
    i, j = np.unravel_index(int(diff.argmax()), diff.shape)
    raise UserError(
        f"{tape_path}: the replayed simulation's importance at step {k} differs from the "
        f"recorded run's (cell ({i}, {j}): {float(replayed[i, j]):.4f} against "
        f"{float(recorded[i, j]):.4f}); the scenario rebuilt from run.json is not the one "
        "recorded: replay with the run's files and versions, or rerun `twin run`"
    )


def _recorded_shape(run_dir: Path) -> tuple[int, int] | None:
    """The grid ``(nx, ny)`` the run's ``run.json`` records (None when it records none)."""
    from twin.readback import read_json

    grid = (read_json(run_dir / "run.json") or {}).get("grid")
    if not isinstance(grid, dict):
        return None
    nx, ny = grid.get("nx"), grid.get("ny")
    ok = all(isinstance(v, int) and not isinstance(v, bool) and v >= 1 for v in (nx, ny))
    return (nx, ny) if ok else None


#: What a run folder's ``run.json`` (traffic.identity) records, as named in the messages.
IDENTITY_NAMES = {
    "net_sha256": "network file (sha256)",
    "cell_m": "cell size (m)",
    "grid": "grid (nx, ny)",
    "sumo": "SUMO version",
    "twin": "twin version",
}


def check_identity(run_dir: Path, source) -> None:
    """Refuse (one line) to replay a run whose network, cell size, grid, SUMO or twin differ
    from what its ``run.json`` records; a run recorded without them is replayed with a
    notice."""
    from twin.readback import read_json

    run = read_json(run_dir / "run.json") or {}
    recorded = (run.get("traffic") or {}).get("identity")
    if not isinstance(recorded, dict):
        from twin.boundary import notify

        notify(
            f"twin: notice: {run_dir / 'run.json'} records no network hash or versions (an "
            "older run); the replay cannot check it simulates the same scenario"
        )
        return
    now = source.identity()
    for key, name in IDENTITY_NAMES.items():
        if key in recorded and recorded[key] != now[key]:
            was, is_ = recorded[key], now[key]
            if key == "net_sha256":
                was, is_ = f"{was[:12]}...", f"{is_[:12]}... ({source.scenario.net_file})"
            raise UserError(
                f"{run_dir / 'run.json'}: the {name} was {was}, now {is_}; the replay would "
                "not show the recorded run: replay with the run's files and versions, or rerun "
                "`twin run`"
            )
    check_input_files(run_dir, recorded.get("files"), source)


#: Roles of input files that every run recording its inputs' hashes records when it loads
#: one (later roles, such as included files, are not checked against older runs).
ALWAYS_RECORDED = ("network", "route file", "additional file", "sumocfg")


def check_input_files(run_dir: Path, recorded, source) -> None:
    """Refuse (one line) to replay a run one of whose SUMO input files (network, route,
    additional files, sumocfg) changed since the run, or that loads a file the run did not: a
    file recorded under another name (another folder) must have the sha256 of one the run
    recorded in the same role. A run that records no file hashes (an older run), or none in a
    role, is not checked."""
    from twin.files import file_sha256

    if recorded is None:
        return
    if not isinstance(recorded, list) or not all(isinstance(f, dict) for f in recorded):
        raise UserError(
            f"{run_dir / 'run.json'}: traffic.identity.files = {str(recorded)[:40]!r} is not a "
            "list of files with their sha256; rerun `twin run`"
        )
    was = {
        (f.get("role"), f.get("path")): f.get("sha256")
        for f in recorded
        if isinstance(f, dict) and isinstance(f.get("sha256"), str)
    }
    hashed = any(r == "network" for r, _ in was)  # the run recorded its inputs' hashes
    for role, path in source.input_files():
        before = was.get((role, str(path)))
        same_role = {(p, h) for (r, p), h in was.items() if r == role}
        if before is None and not same_role:
            if hashed and role in ALWAYS_RECORDED:
                raise UserError(
                    f"{path}: this {role} is not one the run loaded ({run_dir / 'run.json'} "
                    f"records no {role}); replay with the run's files, or rerun `twin run`"
                )
            continue
        try:
            now = file_sha256(path)
        except OSError as exc:
            raise UserError(
                f"{path}: the run's {role} cannot be read ({exc.strerror}); restore it or "
                "rerun `twin run`"
            ) from None
        if before is None:  # another name: one of the run's files of that role, moved?
            if now in {h for _, h in same_role}:
                continue
            other, sha = sorted(same_role)[0]
            raise UserError(
                f"{path}: this {role} is not one the run loaded ({run_dir / 'run.json'} "
                f"records {other}, sha256 {sha[:12]}..., now {now[:12]}...); replay with the "
                "run's files, or rerun `twin run`"
            )
        if now != before:
            raise UserError(
                f"{path}: the {role} changed since the run (sha256 {before[:12]}... in "
                f"{run_dir / 'run.json'}, now {now[:12]}...); restore it or rerun `twin run`"
            )


def check_cells(path: Path, rows, shape: tuple[int, int]) -> None:
    """Refuse (one line) trajectories with a cell off the ``shape`` grid."""
    nx, ny = shape
    off = rows[(rows["i"] < 0) | (rows["i"] >= nx) | (rows["j"] < 0) | (rows["j"] >= ny)]
    if len(off):
        r = off.iloc[0]
        raise UserError(
            f"{path}: swarm {r['swarm']} drone {r['drone']} at step {r['step']} is on cell "
            f"({r['i']}, {r['j']}), off the {nx} x {ny} grid; the trajectories are not this "
            "run's: rerun `twin run`"
        )


def _positions(rows) -> np.ndarray:
    """``(T+1, N, 2)`` cells of one swarm from its trajectory rows."""
    rows = rows.sort_values(["step", "drone"])
    steps, drones = rows["step"].nunique(), rows["drone"].nunique()
    return rows[["i", "j"]].to_numpy().reshape(steps, drones, 2)
