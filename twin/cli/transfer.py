"""``twin transfer --config FILE``: the sim-to-real transfer matrix, trained on x evaluated on."""

from __future__ import annotations

import argparse
import os
import sys
from pathlib import Path

DEFAULT_CONFIG = "configs/transfer.toml"


def add_parser(subparsers) -> None:
    p = subparsers.add_parser(
        "transfer",
        help="the transfer matrix: learned swarms trained on several traffics, evaluated on "
        "several scenarios against the best classical swarm",
        description="Record the earlier days' SUMO tapes, train (or load, when the folder holds "
        "a model whose provenance matches) each row's Q-network, then evaluate every row (rl "
        "and rl-online) beside the classical swarms and the ceilings on every column and seed, "
        "as one sweep on a local process pool or Ray. Writes one run folder: matrix.csv, "
        "report/transfer.html with the heatmap, rows/<row>/provenance.json beside each "
        "checkpoint. Rerunning the same command resumes.",
    )
    p.add_argument("--config", type=Path, default=None,
                   help=f"transfer config (TOML); default {DEFAULT_CONFIG}")  # fmt: skip
    p.add_argument("--out", type=Path, default=None,
                   help="run folder (default runs/transfer-<name>; the same folder resumes)")  # fmt: skip
    p.add_argument("--executor", choices=("local", "ray"), default="local",
                   help="local process pool (default) or Ray (pip install 'twin[ray]')")  # fmt: skip
    p.add_argument("--workers", type=int, default=None,
                   help=f"tasks at once: tapes, rows, cells (default: CPU count, here "
                   f"{os.cpu_count()}); 1 runs them one after another in this process")  # fmt: skip
    p.add_argument("--address", default=None, help="Ray cluster address (default: a local Ray)")
    p.add_argument("--max-memory-gb", type=float, default=None,
                   help="memory limit in GB: refuse more --workers than it holds, and a "
                   "row or cell whose estimate passes it (default $TWIN_MAX_MEMORY_GB or 8)")  # fmt: skip
    p.add_argument("--quiet", action="store_true", help="no progress")
    p.set_defaults(func=main)


def main(args: argparse.Namespace) -> int:
    from twin.boundary import set_run_folder
    from twin.cli import check_count
    from twin.errors import UserError
    from twin.experiment import check_workers_fit, memory_limit_gb
    from twin.outputs import check_output_dir
    from twin.resources import check_cache, shipped_config
    from twin.transfer.config import load_transfer_config
    from twin.transfer.runner import check_transfer_folder, run_transfer

    check_count("--workers", args.workers)
    limit = memory_limit_gb(args.max_memory_gb)  # a bad limit is refused first
    if args.workers is not None:  # each worker runs a task: an interpreter and its simulator
        check_workers_fit(args.workers, args.workers, limit, "tasks")
    if args.address and args.executor != "ray":
        raise UserError("--address is for --executor ray")
    config = load_transfer_config(shipped_config(args.config or DEFAULT_CONFIG))
    out = args.out or Path("runs") / f"transfer-{config.name}"
    check_output_dir(out, "--out", owner=check_transfer_folder)
    check_cache("the report's figures keep their font cache there")
    set_run_folder(out)  # an unexpected error's traceback goes to its error.log

    def say(text: str) -> None:
        if not args.quiet:
            print(f"twin transfer: {text}", file=sys.stderr, flush=True)

    report = run_transfer(
        config,
        out,
        executor=args.executor,
        workers=args.workers or os.cpu_count() or 1,
        address=args.address,
        progress=not args.quiet and sys.stderr.isatty(),
        say=say,
        max_memory_gb=args.max_memory_gb,
    )
    import pandas as pd

    from twin.transfer.matrix import format_matrix, verdict

    matrix = pd.read_csv(out / "matrix.csv")
    print(format_matrix(matrix))
    print("\n" + verdict(matrix))
    print(f"\nmatrix: {out / 'matrix.csv'}\nreport: {report}\nrun folder: {out}")
    return 0
