"""Swarm steps per second of the vectorised core against a per-drone Python loop.

One step = every drone's 13-value state (eq. s), a greedy action over its field of view, the
move, the headline rewards (each visited cell's gain paid once, Def. 4 as the project reads
it), the idleness update (Def. 3) and the coverage (Def. 5).
The loop version below is what a straightforward implementation writes: a Python loop over
drones, slicing the drone's row and column for the directional means. Both run in this process
on the same inputs and must agree along a trajectory (exit 1 otherwise); the figure that
matters is the ratio, in steps per CPU second (process time: robust to other load).

    python benchmarks/bench_core.py            # paper scale and city scale
    python benchmarks/bench_core.py --quick    # small sizes, seconds
"""

from __future__ import annotations

import argparse
import sys
import time

import numpy as np

from twin.grid import ACTION_DELTAS, Grid
from twin.scores import (
    ScoreParams,
    coverage,
    drone_states,
    rewards_on_arrival,
    update_idleness,
)

P = ScoreParams()


def vectorised_step(grid, idle, t, t1, pos):
    states = drone_states(grid, idle, t, pos)
    seen = np.where(grid.feasible_actions(pos), states[:, 2:7], -np.inf)
    actions = seen.argmax(axis=1)
    nxt = grid.move(pos, actions)
    r = rewards_on_arrival(grid, P, idle, t, t1, pos, nxt)
    new = update_idleness(idle, nxt, grid, P.eta, P.delta)
    return new, nxt, r, coverage(new, grid), states


def loop_step(grid, idle, t, t1, pos):
    nx, ny = grid.shape
    free = grid.free
    n = len(pos)
    states = np.zeros((n, 13))
    actions = np.zeros(n, dtype=np.int64)
    total = pos.sum(axis=0)

    def view(values, i, j):
        out = []
        for di, dj in ACTION_DELTAS:
            a, b = i + di, j + dj
            out.append(values[a, b] if 0 <= a < nx and 0 <= b < ny else 0.0)
        return out

    def mean_free(values, mask):
        return float(values[mask].mean()) if mask.any() else 0.0

    it = idle * t
    for d in range(n):
        i, j = pos[d]
        seen = view(it, i, j)
        col, colf, row, rowf = idle[:, j], free[:, j], idle[i, :], free[i, :]
        cm = (total - pos[d]) / (n - 1) if n > 1 else pos[d]
        states[d] = [
            i / nx, j / ny, *seen,
            mean_free(col[i + 1 :], colf[i + 1 :]), mean_free(col[:i], colf[:i]),
            mean_free(row[:j], rowf[:j]), mean_free(row[j + 1 :], rowf[j + 1 :]),
            cm[0] / nx, cm[1] / ny,
        ]  # fmt: skip
        best, best_a = -np.inf, 0
        for a, (di, dj) in enumerate(ACTION_DELTAS):
            x, y = i + di, j + dj
            if 0 <= x < nx and 0 <= y < ny and free[x, y] and seen[a] > best:
                best, best_a = seen[a], a
        actions[d] = best_a
    nxt = pos + ACTION_DELTAS[actions]
    ibar = np.where(free, np.minimum(1.0, idle + P.delta), 0.0)
    # each distinct visited cell pays its visit gain once, split among the drones on it
    arriving = {}
    for d in range(n):
        arriving[tuple(nxt[d])] = arriving.get(tuple(nxt[d]), 0) + 1
    rewards = np.zeros(n)
    for d in range(n):
        a, b = nxt[d]
        gain = (P.alpha_T * t1[a, b] + P.alpha_I) * (ibar[a, b] - P.eta * idle[a, b])
        rewards[d] = gain / arriving[(a, b)]
    new = ibar.copy()
    for d in range(n):
        new[nxt[d, 0], nxt[d, 1]] = P.eta * idle[nxt[d, 0], nxt[d, 1]]
    return new, nxt, rewards, 1.0 - new[free].mean(), states


def scene(nx, ny, n_drones, seed=0):
    rng = np.random.default_rng(seed)
    grid = Grid(rng.random((nx, ny)) < 0.1)
    free = grid.free_cells()
    pos = free[rng.choice(len(free), n_drones, replace=False)]
    maps = [np.where(grid.free, rng.random((nx, ny)), 0.0) for _ in range(2)]
    idle = np.where(grid.free, rng.random((nx, ny)), 0.0)
    return grid, idle, maps, pos


#: Steps of a trajectory on which both implementations must agree (greedy drones soon stack
#: on shared cells, which exercises the split of a shared cell's gain).
AGREE_STEPS = 8
FIELDS = ("idleness", "positions", "rewards", "coverage", "states")


def first_disagreement(grid, idle, maps, pos, steps) -> str:
    """Run both steps side by side along one trajectory; describe the first difference."""
    for k in range(steps):
        t, t1 = maps[k % 2], maps[(k + 1) % 2]
        a = vectorised_step(grid, idle, t, t1, pos)
        b = loop_step(grid, idle, t, t1, pos)
        for field, x, y in zip(FIELDS, a, b, strict=True):
            close = np.isclose(x, y, rtol=1e-9, atol=1e-12)
            if not np.all(close):
                return f"step {k}, {field}: {np.size(close) - np.count_nonzero(close)} of {np.size(close)} values"
        idle, pos = a[0], a[1]
    return ""


def steps_per_second(step, grid, idle, maps, pos, min_seconds):
    n, start = 0, time.process_time()
    while True:
        idle, pos, *_ = step(grid, idle, maps[n % 2], maps[(n + 1) % 2], pos)
        n += 1
        elapsed = time.process_time() - start
        if elapsed >= min_seconds and n >= 3:
            return n / elapsed


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--quick", action="store_true", help="small sizes, a few seconds")
    args = parser.parse_args()
    cases = [("paper", 20, 30, 4), ("city", 200, 300, 1000)]
    if args.quick:
        cases = [("paper", 20, 30, 4), ("city (small)", 60, 90, 100)]
    seconds = 0.5 if args.quick else 3.0
    print(
        f"{'scale':<14}{'grid':>10}{'drones':>8}{'loop steps/s':>15}{'core steps/s':>15}{'ratio':>9}"
    )
    for name, nx, ny, n in cases:
        grid, idle, maps, pos = scene(nx, ny, n)
        disagree = first_disagreement(grid, idle, maps, pos, AGREE_STEPS)
        if disagree:
            sys.exit(f"bench_core: {name}: vectorised and loop steps disagree: {disagree}")
        loop = steps_per_second(loop_step, grid, idle, maps, pos, seconds)
        core = steps_per_second(vectorised_step, grid, idle, maps, pos, seconds)
        print(f"{name:<14}{f'{nx}x{ny}':>10}{n:>8}{loop:>15.1f}{core:>15.1f}{core / loop:>8.1f}x")


if __name__ == "__main__":
    main()
