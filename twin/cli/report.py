"""``twin report RUN_DIR``: render a run folder into a self-contained HTML report."""

from __future__ import annotations

import argparse
import time

from twin.cli import path_arg


def add_parser(subparsers) -> None:
    p = subparsers.add_parser(
        "report",
        help="render a run folder into an HTML report (figures, Table 2, MFD, animation)",
        description="Read a run folder written by `twin run` or `twin evaluate` and write "
        "RUN_DIR/report/: report.html (self-contained: every image inlined, opens offline), "
        "report.md and the PNG figures and GIF animation it shows. Every number comes from "
        "the run folder's own files.",
    )
    p.add_argument("run_dir", type=path_arg, metavar="RUN_DIR", help="run folder to render")
    p.add_argument(
        "--no-animation", action="store_true", help="skip the GIF animation (the slowest part)"
    )
    p.set_defaults(func=main)


def main(args: argparse.Namespace) -> int:
    from twin.boundary import hold_notices, set_run_folder
    from twin.resources import check_cache

    hold_notices(to_end=True)  # said when the report is written; a refusal is its one line

    if args.run_dir.is_dir() and not args.run_dir.is_symlink():
        set_run_folder(args.run_dir)  # an unexpected error's traceback goes to its error.log
    check_cache("the report's figures keep their font cache there")
    from twin.cli import check_command_line
    from twin.report import load_run, write_report  # after the check: matplotlib is set up there

    start = time.perf_counter()
    run = load_run(args.run_dir)
    check_command_line(run.run_dir / "run.json", run.run)  # the report shows that line
    path = write_report(run, animation=not args.no_animation)
    print(f"report: {path} ({time.perf_counter() - start:.1f} s)")
    return 0
