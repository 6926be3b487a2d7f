"""The SUMO coupling's cost, as ratios against bare SUMO stepping in the same process.

Runs the same scenario (network, demand, seed, time window) several times, one libsumo session
after the other, and reports CPU seconds (process time, robust to other load on the machine) and
wall seconds of:

- ``bare``: SUMO advanced to each sample time, nothing read (the floor);
- ``coupled, 1 swarm``: the live source (bulk read of every vehicle at each sample time, cell
  binning, online MFD) driving one swarm through ``run_patrol``;
- ``coupled, K swarms``: the same with K swarms side by side on the same SUMO run;
- ``bare, mesoscopic``: SUMO's mesoscopic model, against the microscopic ``bare``.

The 1-swarm and K-swarm runs must read the same vehicles and importance maps and move the
greedy swarm alike (exit 1 otherwise).

Usage: ``python benchmarks/bench_sumo.py [--horizon 144] [--swarms 6]``; ``--quick`` uses a small
generated grid (seconds).
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from twin.config import load_config
from twin.patrol import run_patrol
from twin.policies import make_policy
from twin.scores import ScoreParams
from twin.sumo.scenario import sumo_source

ROOT = Path(__file__).resolve().parents[1]
QUICK_CONFIG = """
[traffic]
kind = "sumo"
net = "small.net.xml"
routes = ["small.trips.xml"]
cell_m = 200.0
drone_speed_kmh = 12.0
begin = "00:05"
warmup_min = 5.0
horizon = 25
"""


def quick_config(folder: Path) -> Path:
    from twin.sumo.network import generate_grid_scenario

    generate_grid_scenario(folder, blocks=6, block_m=300, end_s=1800, period_s=1.0, seed=5)
    path = folder / "quick.toml"
    path.write_text(QUICK_CONFIG)
    return path


def timed(fn) -> tuple[float, float, object]:
    c0, w0 = time.process_time(), time.perf_counter()
    out = fn()
    return time.process_time() - c0, time.perf_counter() - w0, out


def bare(config, horizon: int, mesoscopic: bool = False):
    source = sumo_source(config, horizon=horizon, mesoscopic=mesoscopic)

    def run():
        session = source.session().start()
        try:
            for _, t in source.sample_times():
                session.advance_to(t)
            return session.n_running()
        finally:
            session.close()

    return timed(run)


def coupled(config, horizon: int, names: list[str]):
    source = sumo_source(config, horizon=horizon)
    swarms = {}
    for n, name in enumerate(names):
        swarms[f"{name}-{n}"] = make_policy(name)
    starts = np.argwhere(source.grid.free)[:: max(1, source.grid.n_free // 4)][:4]

    def run():
        result = run_patrol(source, swarms, starts, ScoreParams(), seed=0)
        return result, source

    return timed(run)


def coupled_runs_disagree(res1, src1, res_k, src_k) -> str:
    """The 1-swarm and the K-swarm run step the same SUMO run: they must read the same
    vehicles and importance maps, and the greedy swarm (deterministic) must patrol alike."""
    if src1.vehicles_seen != src_k.vehicles_seen:
        return "vehicles read at the sample times"
    if not np.array_equal(res1.importance, res_k.importance):
        return "importance maps"
    if "greedy-1" in res_k.swarms:
        a, b = res1.swarms.index("greedy-0"), res_k.swarms.index("greedy-1")
        for field in ("rewards", "coverage", "positions"):
            if not np.array_equal(getattr(res1, field)[a], getattr(res_k, field)[b]):
                return f"greedy swarm's {field}"
    return ""


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--config", type=Path, default=ROOT / "configs/shenzhen.toml")
    p.add_argument("--horizon", type=int, default=144, help="steps (144 = 07:00-10:00)")
    p.add_argument("--swarms", type=int, default=6, help="K for the K-swarm run")
    p.add_argument("--quick", action="store_true", help="small generated grid, seconds")
    p.add_argument("--no-meso", action="store_true", help="skip the mesoscopic run")
    p.add_argument("--repeat", type=int, default=1, help="runs of each kind; the fastest counts")
    args = p.parse_args()
    tmp = tempfile.TemporaryDirectory()
    config_path = quick_config(Path(tmp.name)) if args.quick else args.config
    config = load_config(config_path)
    horizon = 25 if args.quick else args.horizon
    base = ["random", "greedy", "sweeping"]
    k_names = (base * args.swarms)[: args.swarms]

    repeat = args.repeat
    # Interleaved rounds (bare, 1 swarm, K swarms, meso), the fastest of each kind counts: load
    # from other processes then hits every kind alike.
    kinds = {
        "bare": lambda: bare(config, horizon),
        "one": lambda: coupled(config, horizon, ["greedy"]),
        "k": lambda: coupled(config, horizon, k_names),
    }
    if not args.no_meso:
        kinds["meso"] = lambda: bare(config, horizon, mesoscopic=True)
    best: dict[str, tuple] = {}
    for _ in range(repeat):
        for kind, fn in kinds.items():
            run = fn()
            if kind not in best or run[0] < best[kind][0]:
                best[kind] = run
    cpu_b, wall_b, _ = best["bare"]
    cpu_1, wall_1, (res1, src1) = best["one"]
    cpu_k, wall_k, (res_k, src_k) = best["k"]
    disagree = coupled_runs_disagree(res1, src1, res_k, src_k)
    rows = [
        ("bare SUMO stepping (micro)", cpu_b, wall_b, 1.0),
        ("coupled, 1 swarm", cpu_1, wall_1, cpu_1 / cpu_b),
        (f"coupled, {args.swarms} swarms", cpu_k, wall_k, cpu_k / cpu_b),
    ]
    if not args.no_meso:
        cpu_m, wall_m, _ = best["meso"]
        rows.append(("bare SUMO stepping (meso)", cpu_m, wall_m, cpu_m / cpu_b))

    print(f"scenario: {config_path.name}, T = {horizon}, best of {repeat}, {src1.grid.nx} x {src1.grid.ny} cells, "
          f"{max(src1.vehicles_seen)} vehicles at most on the road")  # fmt: skip
    print(f"{'run':34s} {'cpu s':>8s} {'wall s':>8s} {'cpu / bare micro':>17s}")
    for name, cpu, wall, ratio in rows:
        print(f"{name:34s} {cpu:8.2f} {wall:8.2f} {ratio:17.3f}")
    print(f"coupling overhead over bare stepping: {100 * (cpu_1 / cpu_b - 1):+.1f}% CPU")
    print(f"{args.swarms} swarms against 1: x{cpu_k / cpu_1:.3f} CPU")
    print(f"vehicle reads and binning inside the coupled run: {src1.read_seconds:.2f} s wall")
    if not args.no_meso:
        print(f"mesoscopic speed-up over microscopic: x{cpu_b / cpu_m:.2f}")
    tmp.cleanup()
    if disagree:
        sys.exit(f"bench_sumo: the 1-swarm and {args.swarms}-swarm runs disagree: {disagree}")


if __name__ == "__main__":
    main()
