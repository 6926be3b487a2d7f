"""Decision time of the central coordinator (eq. maxi:op2).

- swarms of 4, 64, 256 and 1024 drones on a 200 x 300 grid, positions drawn uniformly
  ("spread") and packed into a square block at one cell spacing ("packed": every drone
  competes with its neighbours, one large assignment);
- against brute-force enumeration of the 5^N joint actions for N = 2..7 drones crowded on a
  small grid (same optimum checked).

    python benchmarks/bench_coordinator.py [--quick]
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from twin.coordinator import brute_force, coordinate
from twin.grid import Grid


def timed(fn, repeats: int) -> float:
    """Median seconds per call."""
    fn()
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return float(np.median(times))


def spread(grid: Grid, n: int, rng) -> np.ndarray:
    free = grid.free_cells()
    return free[rng.choice(len(free), size=n, replace=False)]


def packed(grid: Grid, n: int, rng) -> np.ndarray:
    side = int(np.ceil(np.sqrt(n)))
    cells = np.array([(i, j) for i in range(side) for j in range(side)])[:n]
    return cells * 2 + [grid.nx // 2 - side, grid.ny // 2 - side]  # two cells apart: compete


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    p.add_argument("--quick", action="store_true", help="fewer repeats and smaller swarms")
    args = p.parse_args()
    rng = np.random.default_rng(0)
    repeats = 5 if args.quick else 50
    grid = Grid.open(200, 300)
    sizes = (4, 64) if args.quick else (4, 64, 256, 1024)
    print(f"coordinator on a {grid.nx} x {grid.ny} grid (median of {repeats} calls)")
    print(f"{'drones':>7s} {'layout':>7s} {'ms':>9s}")
    for layout in (spread, packed):
        for n in sizes:
            pos = layout(grid, n, rng)
            q = rng.normal(size=(n, 5))
            feasible = grid.feasible_actions(pos)
            ms = 1e3 * timed(lambda: coordinate(q, pos, feasible, grid), repeats)  # noqa: B023
            print(f"{n:7d} {layout.__name__:>7s} {ms:9.3f}")

    small = Grid.open(4, 5)
    print(f"\nagainst brute force on a {small.nx} x {small.ny} grid (crowded swarms)")
    print(f"{'drones':>7s} {'coordinator ms':>15s} {'brute force ms':>15s} {'ratio':>8s} same")
    for n in range(2, 6 if args.quick else 8):
        pos = spread(small, n, rng)
        q = rng.normal(size=(n, 5))
        feasible = small.feasible_actions(pos)
        ours = timed(lambda: coordinate(q, pos, feasible, small), repeats)  # noqa: B023
        brute = timed(lambda: brute_force(q, pos, feasible, small), 1 if n > 5 else 3)  # noqa: B023
        a = coordinate(q, pos, feasible, small)
        _, best = brute_force(q, pos, feasible, small)
        same = np.isclose(q[np.arange(n), a].sum(), best)
        print(f"{n:7d} {1e3 * ours:15.3f} {1e3 * brute:15.1f} {brute / ours:8.0f} {same}")


if __name__ == "__main__":
    main()
