"""``twin evaluate``: swarms side by side on a scenario, the Table 2 analog over seeds."""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

from twin.config import (
    ScenarioConfig,
    check_swarm_fits,
    load_config,
    shipped_config,
    start_positions,
)
from twin.errors import UserError
from twin.metrics import format_table2
from twin.patrol import run_patrol
from twin.policies import available_policies
from twin.runs import new_run_dir, prepare_run_dir, write_run

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
    p.add_argument("--no-report", action="store_true", help="do not render the HTML report")
    p.add_argument("--quiet", action="store_true", help="no progress bars")
    p.set_defaults(func=main)


def parse_swarms(text: str | None, config: ScenarioConfig) -> list[str]:
    names = (
        [s.strip() for s in text.split(",") if s.strip()] if text else list(config.evaluate.swarms)
    )
    if not names:
        raise UserError("--swarms: give at least one swarm name")
    known = available_policies()
    for name in names:
        if name not in known:
            raise UserError(f"--swarms: unknown swarm {name!r}; choose from {', '.join(known)}")
    if len(set(names)) != len(names):
        raise UserError("--swarms: a swarm is listed twice")
    return names


def load_source(config: ScenarioConfig, tape: Path | None):
    """The traffic to evaluate on: a replayed tape, or the config's synthetic traffic."""
    from twin.traffic.base import RecordedTraffic

    if tape is not None:
        from twin.traffic.tape import TapeTraffic

        return TapeTraffic.from_file(tape, config)
    if config.traffic["kind"] != "synthetic":
        raise UserError(
            f"{config.path}: [traffic].kind = {config.traffic['kind']!r} runs live with `twin run`; "
            "`twin evaluate` takes synthetic configs or --traffic TAPE"
        )
    from twin.config import synthetic_source

    return RecordedTraffic.from_source(synthetic_source(config))


def main(args: argparse.Namespace) -> int:
    config = load_config(shipped_config(args.config or DEFAULT_CONFIG))
    seeds = args.seeds if args.seeds is not None else config.evaluate.seeds
    first = args.seed if args.seed is not None else config.evaluate.seed
    if seeds < 1:
        raise UserError(f"--seeds {seeds}: give at least 1")
    names = parse_swarms(args.swarms, config)
    source = load_source(config, args.traffic)
    check_swarm_fits(config, source.grid)
    run_dir = prepare_run_dir(args.out or new_run_dir("runs", "evaluate"))
    progress = not args.quiet and sys.stderr.isatty()

    t0 = time.perf_counter()
    results = []
    for seed in range(first, first + seeds):
        starts = start_positions(config, source.grid, np.random.default_rng(seed))
        policies = {name: config.make_swarm(name) for name in names}
        results.append(run_patrol(source, policies, starts, config.params, seed, progress))
    meta = {
        "kind": "evaluate",
        "config": str(config.path),
        "traffic": source.metadata(),
        "params": vars(config.params),
        "n_drones": config.swarm.n_drones,
        "wall_seconds": round(time.perf_counter() - t0, 3),
    }
    for name, policy in policies.items():
        if hasattr(policy, "describe"):
            meta.setdefault("policies", {})[name] = policy.describe()
    summary = write_run(run_dir, results, meta)
    label = f"{seeds} seed{'s' if seeds > 1 else ''} from {first}"
    print(f"Table 2 analog ({config.path.name}, {label}, T = {source.horizon}):")
    print(format_table2(summary))
    if not args.no_report:
        _report(run_dir)
    print(f"run folder: {run_dir}")
    return 0


def _report(run_dir: Path) -> None:
    try:
        from twin.report import write_report
    except ImportError:
        return
    print(f"report: {write_report(run_dir)}")
