"""What the learned swarms compute per step besides the Q-network, at city scale, against the
former implementation in the same process.

The decentralized swarm keeps one idleness map per drone. Formerly every map was stored in
full, ``(N, nx, ny)``, advanced in full every step (Def. 3 with the drone's own visit) and
read through prefix sums over every whole map for the directional means of eq. (s). Now the
maps are one common map plus each drone's own visited cells (:class:`twin.idleness_maps.
OwnMaps`) and each drone reads only its row and column. The coordinated swarm's shared map
is read the same way. Both run side by side along one walk and must give the same states bit
for bit (exit 1 otherwise); the figure is the ratio, in steps per CPU second. The Q-network's
forward pass on the same states is timed alongside: the part no bookkeeping removes.

    python benchmarks/bench_learned_swarms.py            # 100 x 150 cells, 200 drones
    python benchmarks/bench_learned_swarms.py --quick    # smaller, seconds
"""

from __future__ import annotations

import argparse
import sys
import time

import numpy as np

from twin.grid import Grid
from twin.idleness_maps import OwnMaps, own_visits_update
from twin.learning.policies import local_drone_states
from twin.scores import ScoreParams, drone_states

P = ScoreParams()


def former_directional(idleness, grid, positions):
    """Directional means through prefix sums over every whole map (the former code)."""
    maps = idleness[None] if idleness.ndim == 2 else idleness
    values = maps * grid.free_float
    i, j = positions[:, 0], positions[:, 1]
    d = np.zeros(len(positions), np.intp) if len(maps) == 1 else np.arange(len(positions))
    col_v, col_n = values.cumsum(axis=1), grid.free_cumsum_down
    row_v, row_n = values.cumsum(axis=2), grid.free_cumsum_right
    own_v, own_n = values[d, i, j], grid.free_float[i, j]
    sums = np.stack([col_v[d, -1, j] - col_v[d, i, j], col_v[d, i, j] - own_v,
                     row_v[d, i, j] - own_v, row_v[d, i, -1] - row_v[d, i, j]], axis=1)  # fmt: skip
    ns = np.stack([col_n[-1, j] - col_n[i, j], col_n[i, j] - own_n,
                   row_n[i, j] - own_n, row_n[i, -1] - row_n[i, j]], axis=1)  # fmt: skip
    return np.divide(sums, ns, out=np.zeros_like(sums), where=ns > 0)


def former_states(grid, idleness, importance, positions, others=None):
    """eq. (s) as formerly computed (dense maps, full prefix sums)."""
    scale = np.array([grid.nx, grid.ny], dtype=np.float64)
    view = grid.view_index(positions)
    if idleness.ndim == 2:
        idle_seen = grid.values_in_view(idleness, None, view)
    else:
        flat, valid = view
        rows = np.arange(len(positions))[:, None]
        idle_seen = np.where(valid, idleness.reshape(len(idleness), -1)[rows, flat], 0.0)
    seen = idle_seen * grid.values_in_view(importance, None, view)
    if others is None:
        total = positions.sum(axis=0, dtype=np.float64)
        others = (total[None, :] - positions) / (len(positions) - 1)
    parts = [positions / scale, seen, former_directional(idleness, grid, positions), others / scale]
    return np.concatenate(parts, axis=1)


def walk(grid, n_drones, steps, seed=0):
    """Random feasible walks of ``n_drones`` drones (positions per step)."""
    rng = np.random.default_rng(seed)
    free = grid.free_cells()
    pos = free[rng.choice(len(free), n_drones, replace=False)]
    out = []
    for _ in range(steps):
        feasible = grid.feasible_actions(pos)
        choice = (rng.random(feasible.shape) * feasible).argmax(axis=1)
        pos = grid.move(pos, choice)
        out.append(pos)
    return out


class Former:
    """The decentralized swarm's per-step work as formerly done."""

    def __init__(self, grid, n):
        self.maps = np.repeat(grid.free_float[None], n, axis=0)

    def step(self, grid, importance, pos, others):
        self.maps = own_visits_update(self.maps, pos, grid, P)
        return former_states(grid, self.maps, importance, pos, others)


class Current:
    def __init__(self, grid, n):
        self.maps = OwnMaps(grid.free_float, n)

    def step(self, grid, importance, pos, others):
        self.maps.advance(pos, grid, P)
        return local_drone_states(grid, self.maps, importance, pos, others)


def cpu_ms_per_step(kind, grid, importance, path, others):
    swarm = kind(grid, len(path[0]))
    start = time.process_time()
    for pos in path:
        swarm.step(grid, importance, pos, others)
    return 1000 * (time.process_time() - start) / len(path)


def shared_ms(states, grid, idle, importance, path):
    start = time.process_time()
    for pos in path:
        states(grid, idle, importance, pos)
    return 1000 * (time.process_time() - start) / len(path)


def qnet_ms(states, repeats=5):
    try:
        import torch

        from twin.learning.policies import shared_qnet
    except ImportError:
        return float("nan")
    torch.set_num_threads(1)
    net, _ = shared_qnet(None)
    s = torch.from_numpy(states.astype(np.float32))
    with torch.inference_mode():
        net(s)
        start = time.process_time()
        for _ in range(repeats):
            net(s)
    return 1000 * (time.process_time() - start) / repeats


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--quick", action="store_true", help="smaller sizes, a few seconds")
    args = parser.parse_args()
    nx, ny, n, steps = (40, 60, 50, 40) if args.quick else (100, 150, 200, 120)
    rng = np.random.default_rng(0)
    grid = Grid(rng.random((nx, ny)) < 0.1)
    importance = np.where(grid.free, rng.random(grid.shape), 0.0)
    idle = np.where(grid.free, rng.random(grid.shape), 0.0)
    path = walk(grid, n, steps)
    others = rng.random((n, 2)) * [nx, ny]

    former, current = Former(grid, n), Current(grid, n)
    for k, pos in enumerate(path):  # agreement, bit for bit, along the whole walk
        a = former.step(grid, importance, pos, others)
        b = current.step(grid, importance, pos, others)
        if not np.array_equal(a, b):
            sys.exit(f"bench_learned_swarms: decentralized states differ at step {k}")
        if not np.array_equal(
            former_states(grid, idle, importance, pos), drone_states(grid, idle, importance, pos)
        ):
            sys.exit(f"bench_learned_swarms: shared-map states differ at step {k}")
    kept = len(current.maps.value)

    old = cpu_ms_per_step(Former, grid, importance, path, others)
    new = cpu_ms_per_step(Current, grid, importance, path, others)
    old_s = shared_ms(former_states, grid, idle, importance, path)
    new_s = shared_ms(drone_states, grid, idle, importance, path)
    q = qnet_ms(a)
    print(f"{nx} x {ny} cells, {n} drones, {steps} steps; states agree bit for bit")
    print(f"{'per step (CPU ms)':<40}{'former':>9}{'now':>9}{'ratio':>9}")
    print(f"{'decentralized: own maps + states':<40}{old:>9.2f}{new:>9.2f}{old / new:>8.1f}x")
    print(
        f"{'coordinated: states from shared map':<40}{old_s:>9.2f}{new_s:>9.2f}{old_s / new_s:>8.1f}x"
    )
    print(f"{'Q-network forward (1 thread)':<40}{q:>9.2f}")
    print(f"own values kept at the end: {kept} (dense maps: {n * nx * ny})")


if __name__ == "__main__":
    main()
