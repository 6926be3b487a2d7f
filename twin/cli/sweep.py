"""``twin sweep --config FILE``: a grid of scenarios x parameters x seeds on a process pool or Ray."""

from __future__ import annotations

import argparse
import os
import sys
from pathlib import Path

from twin.cli import path_arg


def add_parser(subparsers) -> None:
    p = subparsers.add_parser(
        "sweep",
        help="run a grid of scenarios x parameters x seeds (local process pool or Ray)",
        description="Run every cell (scenario, parameter combination, seed) of a sweep config, "
        "each one traffic pass with all swarms side by side, writing one result file per cell "
        "into the sweep folder. Cells already done are skipped, so an interrupted sweep resumes "
        "where it stopped. Results merge into results.csv, summary.csv (mean and 95% interval "
        "over seeds) and report/sweep.html.",
    )
    p.add_argument("--config", type=path_arg, required=True, help="sweep config (TOML)")
    p.add_argument(
        "--out",
        type=path_arg,
        default=None,
        help="sweep folder (default runs/sweep-<name>; rerun with the same folder to resume)",
    )
    p.add_argument(
        "--executor",
        choices=("local", "ray"),
        default="local",
        help="local process pool (default) or Ray (pip install 'twin[ray]')",
    )
    p.add_argument(
        "--workers",
        type=int,
        default=None,
        help=f"parallel cells (default: CPU count, here {os.cpu_count()})",
    )
    p.add_argument(
        "--address", default=None, help="Ray cluster address (default: start a local Ray)"
    )
    p.add_argument(
        "--max-memory-gb",
        type=float,
        default=None,
        help="memory limit in GB: refuse more --workers than it holds, and a cell whose estimate "
        "passes it (default $TWIN_MAX_MEMORY_GB or 8)",
    )
    p.add_argument("--no-report", action="store_true", help="skip the HTML/Markdown report")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    p.set_defaults(func=main)


def main(args: argparse.Namespace) -> int:
    from twin.boundary import hold_notices, notify, set_run_folder
    from twin.cli import check_count
    from twin.errors import UserError
    from twin.experiment import check_workers_fit, memory_limit_gb
    from twin.metrics import format_table2
    from twin.outputs import check_output_dir
    from twin.resources import check_cache, shipped_config
    from twin.sweep import load_sweep_config, run_sweep
    from twin.sweep.store import check_sweep_folder

    hold_notices()  # printed once the cells start; a refusal is one line
    check_count("--workers", args.workers)
    limit = memory_limit_gb(args.max_memory_gb)  # a bad limit is refused first
    if args.workers is not None:  # each worker runs a cell: an interpreter and its simulator
        check_workers_fit(args.workers, args.workers, limit, "sweep cells")
    if args.address and args.executor != "ray":
        raise UserError("--address is for --executor ray")
    config = load_sweep_config(shipped_config(args.config))
    out = args.out or Path("runs") / f"sweep-{config.name}"
    check_output_dir(out, "--out", owner=check_sweep_folder)
    if not args.no_report:
        check_cache("the report's figures keep their font cache there")
    set_run_folder(out)  # an unexpected error's traceback goes to its error.log
    progress = not args.quiet and sys.stderr.isatty()
    outcome = run_sweep(
        config,
        out,
        executor=args.executor,
        workers=args.workers,
        address=args.address,
        progress=progress,
        report=not args.no_report,
        max_memory_gb=args.max_memory_gb,
    )
    print(
        f"sweep {config.name!r} on {args.executor}: ran {len(outcome.ran)} cells, "
        f"{len(outcome.skipped)} already done, {outcome.seconds:.1f} s"
    )
    import pandas as pd

    results = pd.read_csv(out / "results.csv") if (out / "results.csv").exists() else None
    if results is not None and "code" in results and results["code"].nunique() > 1:
        notify(
            f"twin: warning: the cells in {out} were computed by {results['code'].nunique()} "
            "versions of the code (column 'code' of results.csv)"
        )
    summary = outcome.summary
    if not summary.empty:
        groups = [c for c in summary.columns if c == "scenario" or ("." in c and "_ci95" not in c)]
        for key, table in summary.groupby(groups, sort=False):
            key = key if isinstance(key, tuple) else (key,)
            print("\n" + ", ".join(f"{g}={k}" for g, k in zip(groups, key, strict=True)))
            print(format_table2(table))
    if not args.no_report:
        print(f"\nreport: {out / 'report' / 'sweep.html'}")
    print(f"sweep folder: {out}")
    return 0
