"""``twin evaluate``: swarms side by side on a scenario, the Table 2 analog over seeds."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from twin.cli import add_worker_arguments, check_count, check_seeds
from twin.cli.run import belief_models, belief_writer, print_beliefs, print_degradation
from twin.config import load_config, shipped_config
from twin.errors import UserError
from twin.experiment import (
    Experiment,
    check_resources,
    limit_threads,
    parse_swarm_names,
    record,
    run_experiment,
    run_metadata,
)
from twin.metrics import format_comparison, format_results
from twin.runs import discard_run_dir, invocation, new_run_dir, prepare_run_dir
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
        type=Path,
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
        type=Path,
        default=None,
        help="replay a traffic tape (tape.parquet of a `twin run`) instead of the config's traffic",
    )
    p.add_argument(
        "--out", type=Path, default=None, help="run folder to write (default runs/evaluate-<time>)"
    )
    p.add_argument(
        "--max-memory-gb",
        type=float,
        default=None,
        help="refuse a run whose estimated memory exceeds this (default $TWIN_MAX_MEMORY_GB or 8)",
    )
    p.add_argument(
        "--ceiling",
        action=argparse.BooleanOptionalAction,
        default=True,
        help="add the rows oracle (ceiling) and bound (ceiling): a swarm planning on the true "
        "future maps and an upper bound no swarm can exceed, computed after the swarms' run "
        "(default on, left out of a run stopped by Ctrl-C; --no-ceiling skips them)",
    )
    add_worker_arguments(p, live=False)
    p.add_argument(
        "--history",
        type=Path,
        help="a history of earlier days (`twin history`): also score each swarm's belief "
        "models (last-seen, history, nowcast) and write belief_models.csv",
    )
    p.add_argument("--no-report", action="store_true", help="do not render the HTML report")
    p.add_argument("--quiet", action="store_true", help="no progress bars")
    p.add_argument("--help-config", action="store_true",
                   help="list every table and key of a scenario config with its default, "
                   "then exit")  # fmt: skip
    p.set_defaults(func=main)


def main(args: argparse.Namespace) -> int:
    if args.help_config:
        from twin.config import config_help

        print(config_help())
        return 0
    limit_threads()
    config = load_config(shipped_config(args.config or DEFAULT_CONFIG))
    check_count("--seeds", args.seeds)
    check_count("--workers", args.workers)
    seeds = args.seeds if args.seeds is not None else config.evaluate.seeds
    first = args.seed if args.seed is not None else config.evaluate.seed
    check_seeds(
        "--seed" if args.seed is not None else f"{config.path}: [evaluate].seed", first, seeds
    )
    experiment = Experiment(
        config=config,
        swarms=parse_swarm_names(args.swarms, config.evaluate.swarms),
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

    check_resources(experiment, args.out or Path("runs"))  # before any folder is made
    run_dir = prepare_run_dir(
        args.out or new_run_dir("runs", "evaluate"), invocation("evaluate", args)
    )
    try:
        outcome = run_experiment(
            experiment,
            progress=not args.quiet and sys.stderr.isatty(),
            interruptible=True,
            on_source=on_source,
        )
    except UserError:
        discard_run_dir(run_dir)
        raise
    meta = run_metadata(outcome, "evaluate")
    beliefs = belief_models(outcome, history, meta)
    summary, comparison = record(
        run_dir,
        outcome,
        meta,
        ceilings=args.ceiling and not outcome.interrupted,
        more_files=belief_writer(beliefs),
    )
    done = outcome.results[-1]
    planned = (outcome.traffic[-1] or {}).get("horizon", done.horizon)
    partial = outcome.partial or done.completed_steps < planned
    if partial:
        print(
            f"twin: partial run: {done.error or 'the traffic ended early'}; "
            f"{done.completed_steps} of {planned} steps written to {run_dir}",
            file=sys.stderr,
        )
    horizon = done.completed_steps
    label = f"{seeds} seed{'s' if seeds > 1 else ''} from {first}"
    print(format_results(summary, f"Table 2 analog ({config.path.name}, {label}, T = {horizon})"))
    if not comparison.empty:
        print(format_comparison(comparison))
    print_degradation(run_dir)
    print_beliefs(beliefs, args.history, label)
    if not args.no_report and done.completed_steps > 0:
        _report(run_dir)
    print(f"run folder: {run_dir}")
    if outcome.interrupted:
        print(f"twin: interrupted; partial run written to {run_dir}", file=sys.stderr)
        return 130
    return 1 if partial else 0


def _report(run_dir: Path) -> None:
    try:
        from twin.report import write_report
    except ImportError:
        return
    print(f"report: {write_report(run_dir)}")
