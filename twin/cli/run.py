"""``twin run``: the Shenzhen case study (Sec. IV-B) live on SUMO, all swarms on ONE SUMO run.

Builds the default network if missing, advances SUMO in lockstep with the swarms (one step =
cell size / drone speed of simulated time), prints the Table 2 analog and writes the run folder,
with the SUMO extras: ``network.json``, ``mfd.json``, ``mfd_samples.parquet``, ``tape.parquet``.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

from twin.errors import UserError

DEFAULT_CONFIG = "configs/shenzhen.toml"


def add_parser(subparsers) -> None:
    p = subparsers.add_parser(
        "run",
        help="run the swarms on a live SUMO simulation (default: the Shenzhen-like rush hour)",
        description="Run every swarm side by side on one SUMO simulation advanced in lockstep "
        "(one step = cell size / drone speed of simulated time). Without arguments: the "
        "Shenzhen-like network, 07:00-10:00, 20 x 30 cells of 500 m, 4 drones, T = 144. "
        "Swap in a network with --net/--routes, --sumocfg or --osm; without routes twin "
        "generates a rush-hour demand with SUMO's randomTrips.py.",
    )
    p.add_argument("--config", type=Path, default=None, help=f"scenario (default {DEFAULT_CONFIG})")
    p.add_argument("--net", type=Path, help="a SUMO network (.net.xml) instead of the config's")
    p.add_argument(
        "--routes", type=Path, action="append", help="route/trip file(s) for --net (repeatable)"
    )
    p.add_argument("--sumocfg", type=Path, help="a SUMO configuration (.sumocfg): network + demand")
    p.add_argument("--osm", type=Path, help="an OpenStreetMap extract, converted with netconvert")
    p.add_argument("--horizon", type=int, help="number of steps T (default from the config)")
    p.add_argument("--begin", type=str, help='time of T^0, e.g. "07:00" (default from the config)')
    p.add_argument("--swarms", type=str, help="comma-separated swarms (default from the config)")
    p.add_argument("--seed", type=int, help="seed of the drones' starts and swarms")
    p.add_argument("--sumo-seed", type=int, help="SUMO's seed (default [traffic].seed)")
    p.add_argument("--meso", action="store_true", help="SUMO's mesoscopic model (faster)")
    p.add_argument("--out", type=Path, help="run folder (default runs/run-<time>)")
    p.add_argument("--no-report", action="store_true", help="do not render the HTML report")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    p.set_defaults(func=main)


def make_swarms(config, names: list[str], explicit: bool) -> dict:
    """Policies by name; an unavailable learned swarm is skipped with a notice unless asked for."""
    swarms = {}
    for name in names:
        try:
            swarms[name] = config.make_swarm(name)
        except Exception as exc:  # a missing checkpoint or torch: skip the learned swarm
            if explicit or not name.startswith("rl"):
                raise
            print(f"twin: notice: swarm {name!r} skipped ({exc})", file=sys.stderr)
    if not swarms:
        raise UserError("no swarm to run; give --swarms random,greedy,sweeping")
    return swarms


def main(args: argparse.Namespace) -> int:
    from twin.config import check_swarm_fits, load_config, shipped_config, start_positions
    from twin.metrics import format_table2
    from twin.patrol import run_patrol
    from twin.runs import new_run_dir, prepare_run_dir
    from twin.sumo.scenario import sumo_source

    config = load_config(shipped_config(args.config or DEFAULT_CONFIG))
    if config.traffic.get("kind") != "sumo":
        raise UserError(
            f"{config.path}: [traffic].kind = {config.traffic.get('kind')!r}; `twin run` needs "
            '"sumo" (use `twin evaluate` for synthetic traffic)'
        )
    if args.routes and not args.net:
        raise UserError("--routes needs --net (the network the routes run on)")
    given = sum(x is not None for x in (args.net, args.sumocfg, args.osm))
    if given > 1:
        raise UserError("give one of --net, --sumocfg, --osm")
    names = [s.strip() for s in args.swarms.split(",") if s.strip()] if args.swarms else None
    seed = args.seed if args.seed is not None else config.evaluate.seed
    progress = not args.quiet and sys.stderr.isatty()

    t0 = time.perf_counter()
    source = sumo_source(
        config,
        seed=args.sumo_seed,
        net=args.net,
        routes=args.routes,
        sumocfg=args.sumocfg,
        osm=args.osm,
        horizon=args.horizon,
        mesoscopic=True if args.meso else None,
        begin=args.begin,
    )
    setup_s = time.perf_counter() - t0
    check_swarm_fits(config, source.grid)
    swarms = make_swarms(config, names or list(config.evaluate.swarms), explicit=names is not None)
    run_dir = prepare_run_dir(args.out or new_run_dir("runs", "run"))
    s = source.scenario
    print(
        f"SUMO: {s.name}, {source.grid.nx} x {source.grid.ny} cells of "
        f"{source.geometry.cell_m:g} m ({source.grid.n_free} free), "
        f"{source.clock(-s.warmup_steps())} warm-up, {source.clock(0)} - "
        f"{source.clock(s.horizon)}, step {s.step_s:g} s, swarms: {', '.join(swarms)}",
        file=sys.stderr,
    )
    starts = start_positions(config, source.grid, np.random.default_rng(seed))
    result = run_patrol(source, swarms, starts, config.params, seed, progress)
    wall = time.perf_counter() - t0
    meta = {
        "kind": "run",
        "config": str(config.path),
        "traffic": source.metadata(),
        "params": vars(config.params),
        "n_drones": config.swarm.n_drones,
        "wall_seconds": round(wall, 3),
        "setup_seconds": round(setup_s, 3),
        "sumo_read_seconds": round(source.read_seconds, 3),
        "partial": result.error is not None,
        "policies": {
            name: policy.describe()
            for name, policy in swarms.items()
            if hasattr(policy, "describe")
        },
    }
    summary = write_sumo_run(run_dir, source, result, meta)
    if result.error:
        print(
            f"twin: SUMO stopped early ({result.error}); partial results of "
            f"{result.completed_steps} of {source.horizon} steps written to {run_dir}",
            file=sys.stderr,
        )
    mfd = source.model.report()
    print(f"Table 2 analog ({s.name}, seed {seed}, T = {result.completed_steps}):")
    print(format_table2(summary))
    print(
        f"MFD ({mfd['form']}): a = {mfd['a']:.3f}, k_c = {mfd['k_c']:.1f} veh/lane-km, "
        f"R2 = {mfd.get('r2', float('nan')):.3f}, RMSE = {mfd.get('rmse_kmh', float('nan')):.2f} km/h "
        f"over {mfd['n_samples']} cell samples"
    )
    print(f"wall time {wall:.0f} s (SUMO + swarms)")
    if not args.no_report:
        try:
            from twin.report import write_report

            print(f"report: {write_report(run_dir)}")
        except ImportError:
            pass
    print(f"run folder: {run_dir}")
    return 1 if result.error else 0


def write_sumo_run(run_dir: Path, source, result, meta: dict):
    """The lead's run folder plus the SUMO extras (network, MFD fit and samples, tape)."""
    import pandas as pd

    from twin.runs import atomic_write, write_json, write_run

    summary = write_run(run_dir, [result], meta)
    write_json(run_dir / "network.json", source.network_info())
    write_json(run_dir / "mfd.json", source.model.report())
    samples = pd.DataFrame(source.model.samples())
    atomic_write(run_dir / "mfd_samples.parquet", lambda p: samples.to_parquet(p, index=False))
    tape = source.tape()
    atomic_write(run_dir / "tape.parquet", tape.write)
    return summary
