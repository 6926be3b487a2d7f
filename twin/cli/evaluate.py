"""``twin evaluate``: swarms side by side on a scenario, the Table 2 analog over seeds."""

from __future__ import annotations

import argparse
import sys

from twin.cli import (
    add_scoring_arguments,
    add_worker_arguments,
    check_count,
    check_seeds,
    path_arg,
)
from twin.cli.recording import (
    print_beliefs,
    print_degradation,
    print_tables,
    render_report,
    run_and_record,
    with_flags,
)
from twin.config import load_config, shipped_config
from twin.errors import UserError
from twin.experiment import Experiment, limit_threads, parse_swarm_names
from twin.swarms import available_policies

DEFAULT_CONFIG = "configs/synthetic.toml"


def add_parser(subparsers) -> None:
    p = subparsers.add_parser(
        "evaluate",
        help="run swarms side by side on a scenario and print the Table 2 analog",
        description="Run several swarms side by side on the same traffic (each with its own "
        "idleness map), print the paper's Table 2 columns (mean and 95% interval over seeds) "
        "and write per-step series, trajectories and the summary into a run folder.",
    )
    p.add_argument(
        "--config",
        type=path_arg,
        default=None,
        help=f"scenario config (TOML); default {DEFAULT_CONFIG}",
    )
    p.add_argument(
        "--seeds", type=int, default=None, help="number of seeds (overrides [evaluate].seeds)"
    )
    p.add_argument(
        "--seed",
        type=int,
        default=None,
        help="first seed (overrides [evaluate].seed); seeds are seed, seed+1, ...",
    )
    p.add_argument(
        "--swarms",
        type=str,
        default=None,
        help=f"comma-separated swarms to run, from: {', '.join(available_policies())}",
    )
    p.add_argument(
        "--traffic",
        type=path_arg,
        default=None,
        help="replay a traffic tape (tape.parquet of a `twin run`) instead of the config's traffic",
    )
    p.add_argument(
        "--out",
        type=path_arg,
        default=None,
        help="run folder to write (default runs/evaluate-<time>)",
    )
    add_worker_arguments(p, live=False)
    add_scoring_arguments(p)
    p.set_defaults(func=main)


def _seed_of_tape(tape, run: dict) -> int | None:
    """The seed of the run ``run`` whose traffic ``tape`` recorded: ``tapes/seed-<s>.parquet``
    is seed s's, ``tape.parquet`` the first seed's (None when the run has no such seed)."""
    import re

    seeds = [s for s in run.get("seeds") or [] if isinstance(s, int) and not isinstance(s, bool)]
    match = re.fullmatch(r"seed-(\d+)\.parquet", tape.name)
    if tape.parent.name == "tapes" and match:
        seed = int(match[1])
    elif tape.name == "tape.parquet" and seeds:
        seed = seeds[0]
    else:
        return None
    return seed if seed in seeds else None


def _check_seed_of_tape(tape, run: dict, seed: int | None, settings: dict, record) -> None:
    """The tape of seed ``seed`` (by its name) records that seed's traffic in run.json
    (``traffic_by_seed``), not another seed's: tapes swapped or renamed in a run folder would
    replay one seed's swarm on another's day (refused in one line)."""
    from twin.readback import RERUN

    seeds = run.get("seeds")
    records = run.get("traffic_by_seed")
    if seed is None or not isinstance(records, list) or not isinstance(seeds, list):
        return
    if len(records) != len(seeds) or seed not in seeds:
        return
    if _records_the_tape(records[seeds.index(seed)], settings):
        return
    other = [s for s, r in zip(seeds, records, strict=True) if _records_the_tape(r, settings)]
    whose = f"seed {other[0]}'s traffic" if other else "another traffic"
    raise UserError(
        f"{tape}: records {whose} in {record}, not that of seed {seed}, which its name gives "
        f"(tapes swapped or renamed); {RERUN}, or replay it with --config and --seed"
    )


#: What names a day of traffic in a source's record (run.json's ``traffic``, a tape's
#: settings): its kind and scenario, seed, clock, step, incidents and network.
TRAFFIC_IDENTITY = ("kind", "name", "seed", "begin", "step_s", "warmup_s", "incidents")


def _records_the_tape(record, settings: dict) -> bool:
    """run.json's traffic record of a seed names the traffic a tape's settings name
    (:data:`TRAFFIC_IDENTITY` and the network's sha256)."""
    import json

    if not isinstance(record, dict):
        return False

    def identity(node: dict) -> str:
        net = node.get("identity") if isinstance(node.get("identity"), dict) else {}
        named = {k: node.get(k) for k in TRAFFIC_IDENTITY} | {"net": net.get("net_sha256")}
        return json.dumps(named, sort_keys=True, default=str)

    return identity(record) == identity(settings)


def with_swarm_of_run(config, tape, seed_flag: int | None = None, seeds_flag: int | None = None):
    """``config`` with the swarm of the run that recorded ``tape`` (its drones, start cells and
    score weights, from the ``run.json`` of the tape's run folder, and its seed, unless
    ``--seed`` (``seed_flag``) gives another), said in a notice naming the seeds that run
    (``--seeds``: ``seeds_flag``): a
    replay of a run's tape without ``--config`` gives the run's swarm results, not those of
    the default config's swarm. A tape outside a run folder keeps the config's swarm, and so
    does one that its folder's manifest does not list or whose grid is not the run's (another
    run's ``run.json``); a damaged ``run.json`` is refused in one line."""
    from pathlib import Path

    from twin.boundary import notify
    from twin.config import with_overrides
    from twin.readback import RERUN, check_run_json, read_json
    from twin.runs import MANIFEST, check_run_folder
    from twin.traffic.tape import read_tape_meta

    tape = Path(tape)
    folder = tape.parent.parent if tape.parent.name == "tapes" else tape.parent
    record = folder / "run.json"
    if not record.exists() and not record.is_symlink():  # a tape copied out of its run folder
        notify(
            f"twin: notice: no run.json beside {tape} (not in its run folder), so "
            f"{config.path.name}'s swarm ({config.swarm.n_drones} drones) replays it; give "
            "the config of the run that recorded it with --config for that run's swarm"
        )
        return config
    if (folder / MANIFEST).exists():  # a finished run's folder: it must have written the tape
        try:
            listed = check_run_folder(folder).get("files") or {}
        except UserError as exc:
            raise UserError(f"{exc}, or give --config to replay the tape with its swarm") from None
        if tape.relative_to(folder).as_posix() not in listed:
            notify(
                f"twin: notice: {folder / MANIFEST} does not list {tape.name}: not the tape of "
                f"the run of {record}, so {config.path.name}'s swarm replays it"
            )
            return config
    run = check_run_json(record, read_json(record, required=True))
    meta = read_tape_meta(tape)
    grid = run.get("grid") or {}
    why = None
    if not grid:
        why = "records no grid (an unfinished run)"
    elif (grid.get("nx"), grid.get("ny")) != (meta["nx"], meta["ny"]):
        why = (
            f"gives a grid of {grid.get('nx')} x {grid.get('ny')}, the tape {meta['nx']} x "
            f"{meta['ny']}"
        )
    elif not any(_records_the_tape(r, meta["settings"]) for r in
                 run.get("traffic_by_seed") or [run.get("traffic")]):  # fmt: skip
        why = "records another traffic than the tape's (its settings differ)"
    if why is not None:
        notify(
            f"twin: notice: {record} {why}: not the tape of its run, so "
            f"{config.path.name}'s swarm replays it"
        )
        return config
    params = run.get("params") or {}
    fields = {  # override -> the field of run.json that gives it, and its value
        "swarm.n_drones": ("n_drones", run.get("n_drones")),
        "swarm.starts": ("starts", run.get("starts")),
        **{f"swarm.{k}": (f"params.{k}", params.get(k)) for k in ("eta", "delta", "alpha_T",
                                                                  "alpha_I")},
    }  # fmt: skip
    missing = [name for name, value in fields.values() if value is None]
    if missing:
        raise UserError(
            f"{record}: no {missing[0]}: the swarm that recorded {tape.name} is unknown; "
            f"{RERUN}, or give --config"
        )
    overrides = {key: value for key, (_, value) in fields.items()}
    seed = _seed_of_tape(tape, run)
    _check_seed_of_tape(tape, run, seed, meta["settings"], record)
    if seed is not None:  # the run's seed of this tape (--seed still chooses another)
        overrides["evaluate.seed"] = seed
    labels = {key: f"{folder / 'run.json'}: {key.split('.')[1]}" for key in overrides}
    mine = with_overrides(config, overrides, labels)
    faults = (
        " (this run had [faults]: the results differ from its own)" if run.get("faults") else ""
    )
    first = seed_flag if seed_flag is not None else seed
    count = seeds_flag or 1
    seeds = "" if first is None else f", seed {first}" if count == 1 else (
        f", seeds {first} to {first + count - 1}"
    )  # fmt: skip
    if seed is not None and seed_flag is not None and seed_flag != seed:
        seeds += f" by --seed; the run had {seed}"
    notify(
        f"twin: notice: the swarm of {folder / 'run.json'} ({mine.swarm.n_drones} drones, its "
        f"starts and score weights{seeds}) replays its tape, not {config.path.name}'s; its "
        f"[swarm_options] and [faults] are not replayed{faults}: give the run's config with "
        "--config for them"
    )
    return mine


def say_grid_set_aside(config, tape) -> None:
    """A notice when the tape's grid replaces the explicit ``[grid]`` of a synthetic
    ``--config`` (its traffic and map give way to the tape's; a SUMO config's grid must be the
    tape's, :meth:`twin.traffic.tape.TapeTraffic.from_file`)."""
    from twin.boundary import notify
    from twin.traffic.tape import read_tape_meta

    shape = config.explicit_shape()
    if config.traffic.kind != "synthetic" or shape is None:
        return
    try:
        meta = read_tape_meta(tape)
    except UserError:  # a tape that does not read: its replay refuses it in its own words
        return
    if tuple(shape) != (meta["nx"], meta["ny"]):
        notify(
            f"twin: notice: {tape}: its {meta['nx']} x {meta['ny']} grid replaces "
            f"{config.path.name}'s [grid] of {shape[0]} x {shape[1]} (a synthetic config's "
            "traffic and map give way to the tape's)"
        )


def main(args: argparse.Namespace) -> int:
    from twin.boundary import hold_notices

    if args.help_config:
        from twin.config import config_help

        print(config_help())
        return 0
    limit_threads()
    hold_notices()  # printed once the simulation has started; a refusal is one line
    config = load_config(shipped_config(args.config or DEFAULT_CONFIG))
    if args.traffic is not None and args.config is None:
        config = with_swarm_of_run(config, args.traffic, args.seed, args.seeds)
    elif args.traffic is not None:
        say_grid_set_aside(config, args.traffic)
    swarms = parse_swarm_names(args.swarms, []) if args.swarms is not None else None
    config = with_flags(
        config,
        {
            "--seeds": ("evaluate.seeds", args.seeds),
            "--seed": ("evaluate.seed", args.seed),
            "--swarms": ("evaluate.swarms", swarms),
        },
    )
    check_count("--workers", args.workers)
    seeds, first = config.evaluate.seeds, config.evaluate.seed
    count = config.flag_of("evaluate.seeds") or f"{config.path}: [evaluate].seeds"
    check_seeds(config.flag_of("evaluate.seed") or f"{config.path}: [evaluate].seed", first, seeds,
                count)  # fmt: skip
    experiment = Experiment(
        config=config,
        swarms=config.evaluate.swarms,
        seeds=range(first, first + seeds),
        tape=args.traffic,
        max_memory_gb=args.max_memory_gb,
        workers=args.workers,
        executor=args.executor,
    )
    if experiment.tape is None and config.traffic.kind != "synthetic":
        raise UserError(
            f"{config.path}: [traffic].kind = {config.traffic.kind!r} runs live with `twin run`; "
            "`twin evaluate` takes synthetic configs or --traffic TAPE"
        )
    history = on_source = None
    if args.history is not None:
        from twin.belief import History, check_source

        history = History.load(args.history)

        def on_source(source) -> None:
            check_source(history, args.history, source)

    recorded = run_and_record("evaluate", args, experiment, history, on_source)
    outcome, run_dir = recorded.outcome, recorded.run_dir
    done = outcome.stopped
    planned = (outcome.traffic[-1] or {}).get("horizon", done.horizon)
    partial = outcome.partial or done.completed_steps < planned
    if outcome.left_out is not None:
        print(
            f"twin: partial run: {outcome.partial_reason()}; written to {run_dir}", file=sys.stderr
        )
    elif partial:
        print(
            f"twin: partial run: {done.error or 'the traffic ended early'}; "
            f"{done.completed_steps} of {planned} steps written to {run_dir}",
            file=sys.stderr,
        )
    horizon = outcome.results[0].completed_steps
    label = f"{seeds} seed{'s' if seeds > 1 else ''} from {first}"
    kept = [r.seed for r in outcome.results]
    if len(kept) != seeds:  # some left out (stopped shorter): the tables hold these
        from twin.experiment import seed_ranges

        label = f"seed{'s' * (len(kept) > 1)} {seed_ranges(kept)}"
    traffic = config.path.name if args.traffic is None else f"the tape {args.traffic}"
    title = f"Table 2 analog ({traffic}, {label}, T = {horizon})"
    print_tables(recorded, title)
    print_degradation(run_dir)
    print_beliefs(recorded.beliefs, args.history, label)
    if not args.no_report and outcome.results[0].completed_steps > 0:
        render_report(run_dir)
    print(f"run folder: {run_dir}")
    if outcome.interrupted:
        print(f"twin: interrupted; partial run written to {run_dir}", file=sys.stderr)
        return 130
    return 1 if partial else 0
