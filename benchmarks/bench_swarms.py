"""Decision time of each swarm, and the choice of lookahead's default horizon.

- default: wall time of one decision (``act``) of random, greedy, greedy-coordinated,
  visit-gain and lookahead at paper scale (20 x 30 cells, 4 drones) and at 200 x 300 cells
  with 1000 drones, in ms and as a ratio against greedy in the same process;
- ``--quick``: small sizes; checks that every swarm's actions are feasible and lead to
  distinct cells over a short run (exit 1 otherwise);
- ``--pick-horizon``: R_hat_T of lookahead for H = 1 .. 5 on ``configs/synthetic.toml``,
  seeds 0-9 (mean and 95% interval), with ms per step at both scales: how
  ``twin.planners.DEFAULT_HORIZON`` was chosen (largest mean R_hat_T among the H whose step at
  200 x 300 with 1000 drones takes well under a second).

    python benchmarks/bench_swarms.py [--quick | --pick-horizon]
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

from twin.grid import Grid
from twin.patrol import random_starts, swarm_rng
from twin.policies import SwarmView, make_policy
from twin.scores import ScoreParams, update_idleness

SWARMS = ("random", "greedy", "greedy-coordinated", "visit-gain", "lookahead")
CONFIG = Path(__file__).resolve().parents[1] / "configs" / "synthetic.toml"


def scene(nx: int, ny: int, n: int, seed: int = 0, obstacles: float = 0.0):
    """A grid, distinct starts, and a mid-run idleness and importance map."""
    rng = np.random.default_rng(seed)
    grid = Grid(rng.random((nx, ny)) < obstacles)
    positions = random_starts(grid, n, rng)
    idleness = rng.random(grid.shape) * grid.free
    importance = rng.random(grid.shape) ** 4  # mostly low, a few hot cells
    return grid, positions, idleness, importance


def view_of(grid, positions, idleness, importance, k=0) -> SwarmView:
    return SwarmView(
        k=k,
        horizon=1000,
        grid=grid,
        positions=positions,
        idleness=idleness,
        importance=importance,
        feasible=grid.feasible_actions(positions),
        params=ScoreParams(),
    )


def ms_per_decision(name: str, grid, positions, idleness, importance, repeats: int, **options):
    """Median ms of one ``act`` on a fixed view (after one warm-up call)."""
    policy = make_policy(name, **options)
    policy.reset(grid, len(positions), swarm_rng(0, name))
    view = view_of(grid, positions, idleness, importance)
    policy.act(view)
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        policy.act(view)
        times.append(time.perf_counter() - t0)
    return 1e3 * float(np.median(times))


def timing(sizes, repeats: int) -> None:
    print(f"one decision per swarm (median of {repeats} calls; ratio = ms / greedy's ms)")
    print(f"{'cells':>10s} {'drones':>7s} {'swarm':>19s} {'ms':>10s} {'x greedy':>9s}")
    for nx, ny, n in sizes:
        maps = scene(nx, ny, n)
        ms = {name: ms_per_decision(name, *maps, repeats) for name in SWARMS}
        for name in SWARMS:
            ratio = ms[name] / ms["greedy"]
            print(f"{f'{nx} x {ny}':>10s} {n:7d} {name:>19s} {ms[name]:10.3f} {ratio:9.1f}")


def check_collision_free(steps: int = 30) -> bool:
    """Every swarm over a short run on grids with obstacles: feasible, distinct cells."""
    ok = True
    params = ScoreParams()
    for seed, (nx, ny, n) in enumerate([(6, 7, 8), (10, 12, 20), (20, 30, 4)]):
        for name in SWARMS:
            grid, pos, idle, imp = scene(nx, ny, n, seed, obstacles=0.2)
            policy = make_policy(name)
            policy.reset(grid, n, swarm_rng(seed, name))
            rng = np.random.default_rng(seed)
            for k in range(steps):
                view = view_of(grid, pos, idle, imp, k)
                actions = policy.act(view)
                feasible = view.feasible[np.arange(n), actions].all()
                pos = grid.move(pos, actions)
                distinct = len(np.unique(pos[:, 0] * ny + pos[:, 1])) == n
                if not feasible or (name != "random" and name != "greedy" and not distinct):
                    print(f"FAIL {name} on {nx} x {ny}, {n} drones, step {k}")
                    ok = False
                    break
                idle = update_idleness(idle, pos, grid, params.eta, params.delta)
                imp = rng.random(grid.shape) ** 4
    print("feasible and collision-free (coordinated swarms):", "yes" if ok else "NO")
    return ok


def pick_horizon(horizons, seeds: int) -> None:
    from twin.config import load_config, start_positions, synthetic_source
    from twin.metrics import ci95_halfwidth
    from twin.patrol import run_patrol
    from twin.traffic.base import RecordedTraffic

    config = load_config(CONFIG)
    source = RecordedTraffic.from_source(synthetic_source(config))
    big = scene(200, 300, 1000)
    small = scene(20, 30, 4)
    print(f"lookahead on {CONFIG.name}, seeds 0-{seeds - 1}, T = {source.horizon}")
    print(
        f"{'H':>3s} {'R_hat_T':>8s} {'± 95%':>7s} {'ms/step 20x30,4':>16s} {'ms/step 200x300,1000':>21s}"
    )
    for h in horizons:
        r_hat = []
        for seed in range(seeds):
            starts = start_positions(config, source.grid, np.random.default_rng(seed))
            policies = {"lookahead": make_policy("lookahead", horizon=h)}
            result = run_patrol(source, policies, starts, config.params, seed)
            r_hat.append(result.rewards[0].mean())
        ms_small = ms_per_decision("lookahead", *small, 50, horizon=h)
        ms_big = ms_per_decision("lookahead", *big, 3, horizon=h)
        r_hat = np.array(r_hat)
        print(
            f"{h:3d} {r_hat.mean():8.3f} {ci95_halfwidth(r_hat):7.3f} "
            f"{ms_small:16.2f} {ms_big:21.1f}"
        )


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    mode = p.add_mutually_exclusive_group()
    mode.add_argument("--quick", action="store_true", help="small sizes and a correctness check")
    mode.add_argument("--pick-horizon", action="store_true", help="lookahead's H on R_hat_T")
    p.add_argument("--seeds", type=int, default=10, help="seeds for --pick-horizon")
    args = p.parse_args()
    if args.pick_horizon:
        pick_horizon(range(1, 6), args.seeds)
        return 0
    if args.quick:
        timing([(20, 30, 4), (50, 60, 50)], repeats=5)
        return 0 if check_collision_free() else 1
    timing([(20, 30, 4), (200, 300, 1000)], repeats=20)
    return 0


if __name__ == "__main__":
    sys.exit(main())
