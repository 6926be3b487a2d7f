"""Decision time of each swarm, and the choice of lookahead's default horizon.

- default: wall time of one decision (``act``) of random, greedy, sweeping,
  greedy-coordinated, visit-gain and lookahead at paper scale (20 x 30 cells, 4 drones), at
  city scale (100 x 150 cells, 200 drones: configs/shenzhen-city-scale.toml) and at 200 x 300
  cells with 1000 drones, in ms and as a ratio against greedy in the same process; lookahead
  with H = 4 and no end value (the full tree) and the sweep's tour (``reset``) also against
  their previous implementations, kept below (``ReferenceLookahead``,
  ``reference_boustrophedon_tour``), as a speed-up;
- ``--quick``: small sizes; checks that every swarm's actions are feasible and lead to
  distinct cells over a short run, and that lookahead's scores and the sweep's tour equal the
  previous implementations' bit for bit (exit 1 otherwise);
- ``--pick-horizon``: R_hat_T of lookahead settings (``CANDIDATES``: horizon, end value,
  planning, beam) on ``configs/synthetic.toml``, validation seeds 100-109 by default (mean
  and 95% interval, and paired against visit-gain), with ms per decision at 20 x 30 with 4
  drones and 100 x 150 with 200: how lookahead's defaults were chosen (largest mean R_hat_T).
  ``--seeds 0-9`` measures on the evaluation seeds.

    python benchmarks/bench_swarms.py [--quick | --pick-horizon [--seeds 100-109]]
"""

from __future__ import annotations

import argparse
import itertools
import sys
import time
from pathlib import Path

import numpy as np

from twin.grid import Grid
from twin.patrol import random_starts, swarm_rng
from twin.planners import LookaheadPolicy
from twin.policies import SwarmView, boustrophedon_tour
from twin.scores import ScoreParams, update_idleness, visit_gain
from twin.swarms import make_policy, needs_history

SWARMS = ("random", "greedy", "sweeping", "greedy-coordinated", "visit-gain", "lookahead")
UNCOORDINATED = ("random", "greedy", "sweeping")  # may put two drones on one cell
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


def flat_history(grid, horizon: int = 1000):
    """A history for the swarms that plan on one: mean 0.3, std 0.02, rho 0.5 everywhere."""
    from twin.belief import History

    shape = (horizon + 1, *grid.shape)
    rho = np.full(grid.shape, 0.5)
    return History(np.full(shape, 0.3), np.full(shape, 4e-4), rho, grid.obstacles.copy(), 3)


def ms_per_decision(name: str, grid, positions, idleness, importance, repeats: int, **options):
    """Median ms of one ``act`` on a fixed view (after one warm-up call)."""
    if name == REFERENCE:
        policy = ReferenceLookahead(**options)
    elif name == TREE:
        policy = make_policy("lookahead", **TREE_OPTIONS, **options)
    else:
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
    print(f"{'cells':>10s} {'drones':>7s} {'swarm':>22s} {'ms':>10s} {'x greedy':>9s}")
    for nx, ny, n in sizes:
        maps = scene(nx, ny, n, obstacles=0.3)
        names = (*SWARMS, TREE, REFERENCE)
        ms = {name: ms_per_decision(name, *maps, repeats) for name in names}
        for name in names:
            ratio = ms[name] / ms["greedy"]
            print(f"{f'{nx} x {ny}':>10s} {n:7d} {name:>22s} {ms[name]:10.3f} {ratio:9.1f}")
        print(f"{'':>10s} {'':>7s} {'lookahead speed-up':>22s} {ms[REFERENCE] / ms[TREE]:9.1f}x")
        new, old = (
            _seconds(lambda f=f, grid=maps[0]: f(grid))
            for f in (boustrophedon_tour, reference_boustrophedon_tour)
        )
        print(
            f"{'':>10s} {'':>7s} {'sweep tour (reset) ms':>22s} {1e3 * new:10.1f} "
            f"(previous {1e3 * old:.1f}, {old / new:.1f}x)"
        )


def _seconds(fn, repeats: int = 3) -> float:
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return min(times)


def check_collision_free(steps: int = 30) -> bool:
    """Every swarm over a short run on grids with obstacles: feasible, distinct cells."""
    ok = True
    params = ScoreParams()
    for seed, (nx, ny, n) in enumerate([(6, 7, 8), (10, 12, 20), (20, 30, 4)]):
        for name in SWARMS:
            grid, pos, idle, imp = scene(nx, ny, n, seed, obstacles=0.2)
            options = {"history": flat_history(grid)} if needs_history(name) else {}
            policy = make_policy(name, **options)
            policy.reset(grid, n, swarm_rng(seed, name))
            rng = np.random.default_rng(seed)
            for k in range(steps):
                view = view_of(grid, pos, idle, imp, k)
                actions = policy.act(view)
                feasible = view.feasible[np.arange(n), actions].all()
                pos = grid.move(pos, actions)
                distinct = len(np.unique(pos[:, 0] * ny + pos[:, 1])) == n
                if not feasible or (name not in UNCOORDINATED and not distinct):
                    print(f"FAIL {name} on {nx} x {ny}, {n} drones, step {k}")
                    ok = False
                    break
                idle = update_idleness(idle, pos, grid, params.eta, params.delta)
                imp = rng.random(grid.shape) ** 4
    print("feasible and collision-free (coordinated swarms):", "yes" if ok else "NO")
    return ok


def check_same_as_previous(steps: int = 15) -> bool:
    """Lookahead's scores and the sweep's tour against the previous implementations: equal
    bit for bit on random grids with obstacles, horizons 1-4 and discounts 1 and 0.9."""
    ok = True
    for seed in range(12):
        rng = np.random.default_rng(seed)
        nx, ny = (int(v) for v in rng.integers(3, 25, 2))
        grid, pos, idle, _ = scene(nx, ny, int(rng.integers(2, 12)), seed, obstacles=0.25)
        if not np.array_equal(boustrophedon_tour(grid), reference_boustrophedon_tour(grid)):
            print(f"FAIL sweep tour on {nx} x {ny}, seed {seed}")
            ok = False
        horizon, discount = 1 + seed % 4, (1.0, 0.9)[seed % 2]
        new = LookaheadPolicy(horizon, discount, end_weight=0.0, plan="independent", beam=0)
        old = ReferenceLookahead(horizon, discount)
        for policy in (new, old):
            policy.reset(grid, len(pos), np.random.default_rng(seed))
        params = ScoreParams()
        for k in range(steps):
            view = view_of(grid, pos, idle, rng.random(grid.shape) ** 4, k)
            if not np.array_equal(new.scores(view), old.scores(view)):
                print(f"FAIL lookahead H={horizon} on {nx} x {ny}, seed {seed}, step {k}")
                ok = False
                break
            pos = grid.move(pos, old.act(view))
            idle = update_idleness(idle, pos, grid, params.eta, params.delta)
    print("same as the previous lookahead and sweep tour:", "yes" if ok else "NO")
    return ok


#: Lookahead settings compared by ``--pick-horizon`` (name, options).
CANDIDATES = [
    *((f"tree H={h}", {"horizon": h, "end_weight": 0.0, "plan": "independent", "beam": 0})
      for h in (1, 4, 5)),
    ("tree H=4, end 0.9/5", {"horizon": 4, "end_weight": 0.9, "end_wait": 5,
                             "plan": "independent", "beam": 0}),
    ("sequential H=4, end 0.9/3", {"horizon": 4, "end_weight": 0.9, "end_wait": 3,
                                   "plan": "sequential", "beam": 0}),
    ("sequential H=5, end 0.9/3", {"horizon": 5, "end_weight": 0.9, "end_wait": 3,
                                   "plan": "sequential", "beam": 0}),
    *((f"seq. beam 20 H=8, end {e}/3", {"horizon": 8, "end_weight": e, "end_wait": 3,
                                        "plan": "sequential", "beam": 20})
      for e in (0.9, 1.1)),
]  # fmt: skip


def pick_horizon(seeds) -> None:
    """R_hat_T of each candidate and its paired difference with visit-gain on ``seeds``."""
    from twin.config import load_config, start_positions, synthetic_source
    from twin.metrics import ci95_halfwidth
    from twin.patrol import run_patrol
    from twin.traffic.base import RecordedTraffic

    config = load_config(CONFIG)
    source = RecordedTraffic.from_source(synthetic_source(config))
    small, city = scene(20, 30, 4), scene(100, 150, 200)

    def r_hat(name, **options):
        values = []
        for seed in seeds:
            starts = start_positions(config, source.grid, np.random.default_rng(seed))
            policies = {name: make_policy(name, **options)}
            result = run_patrol(
                source, policies, starts, config.params, seed, keep_importance=False
            )
            values.append(result.rewards[0].mean())
        return np.array(values)

    base = r_hat("visit-gain")
    print(f"lookahead on {CONFIG.name}, seeds {seeds[0]}-{seeds[-1]}, T = {source.horizon}")
    print(f"visit-gain R_hat_T {base.mean():.3f} ± {ci95_halfwidth(base):.3f}")
    print(
        f"{'setting':>28s} {'R_hat_T':>8s} {'± 95%':>6s} {'- visit-gain':>13s} {'± 95%':>6s} "
        f"{'x':>6s} {'ms 20x30,4':>11s} {'ms 100x150,200':>15s}"
    )
    for label, options in CANDIDATES:
        r = r_hat("lookahead", **options)
        diff = r - base
        ms_small = ms_per_decision("lookahead", *small, 50, **options)
        ms_city = ms_per_decision("lookahead", *city, 3, **options)
        print(
            f"{label:>28s} {r.mean():8.3f} {ci95_halfwidth(r):6.3f} {diff.mean():13.3f} "
            f"{ci95_halfwidth(diff):6.3f} {r.mean() / base.mean():6.3f} {ms_small:11.2f} "
            f"{ms_city:15.1f}",
            flush=True,
        )


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    mode = p.add_mutually_exclusive_group()
    mode.add_argument("--quick", action="store_true", help="small sizes and a correctness check")
    mode.add_argument("--pick-horizon", action="store_true", help="lookahead's H on R_hat_T")
    p.add_argument(
        "--seeds", default="100-109", help="seeds for --pick-horizon, e.g. 100-109 (validation)"
    )
    args = p.parse_args()
    if args.pick_horizon:
        first, _, last = args.seeds.partition("-")
        pick_horizon(list(range(int(first), int(last or first) + 1)))
        return 0
    if args.quick:
        timing([(20, 30, 4), (50, 60, 50)], repeats=5)
        return 0 if check_collision_free() & check_same_as_previous() else 1
    timing([(20, 30, 4), (100, 150, 200), (200, 300, 1000)], repeats=20)
    return 0


# --- the previous implementations (main 7d5d5fb), the in-process baselines ------------------

#: Name of the previous lookahead in the timing table.
REFERENCE = "lookahead (previous)"
#: The same planner as the previous one (H = 4, no end value, independent), by the tree.
TREE = "lookahead H=4 (tree)"
TREE_OPTIONS = {"horizon": 4, "end_weight": 0.0, "plan": "independent", "beam": 0}


class ReferenceLookahead(LookaheadPolicy):
    """Lookahead as it was before (main 7d5d5fb): every one of the ``5^H`` paths of every
    drone summed step by step, no end value, independent plans. Kept here only as the
    baseline and the reference."""

    def __init__(self, horizon: int = 4, discount: float = 1.0):
        super().__init__(horizon, discount, end_weight=0.0, plan="independent", beam=0)

    def reset(self, grid, n_drones, rng) -> None:
        super().reset(grid, n_drones, rng)
        self.step_flat = self.offsets[..., 0] * self.width + self.offsets[..., 1]  # (P, H)
        self.belief = np.zeros(grid.shape)

    def scores(self, view: SwarmView) -> np.ndarray:
        grid, p, h_max = view.grid, view.params, self.horizon
        flat, valid = grid.view_index(view.positions)
        seen = flat[valid]
        self.belief.ravel()[seen] = view.importance.ravel()[seen]
        weight = np.pad(p.alpha_T * self.belief + p.alpha_I, h_max).ravel()
        idle = np.pad(view.idleness, h_max).ravel()
        pos = np.asarray(view.positions, dtype=np.int64)
        base = (pos[:, 0] + h_max) * self.width + pos[:, 1] + h_max
        cells = base[:, None, None] + self.step_flat[None]  # (N, P, H) padded flat ids
        ok = self.free_padded[cells].all(axis=2)
        n_paths = cells.shape[1]
        pre = np.zeros(cells.shape)  # predicted idleness of the cell just before step h
        value = np.zeros(cells.shape[:2])
        for h in range(h_max):
            pre_h = np.minimum(1.0, idle[cells[:, :, h]] + h * p.delta)
            s = self.last[:, h]
            again = s >= 0
            if again.any():
                revisit = np.minimum(
                    1.0,
                    p.eta * pre[:, np.arange(n_paths), np.maximum(s, 0)] + (h - 1 - s) * p.delta,
                )
                pre_h = np.where(again[None, :], revisit, pre_h)
            pre[:, :, h] = pre_h
            value += self.discount**h * visit_gain(weight[cells[:, :, h]], pre_h, p)
        value = np.where(ok, value, -np.inf)
        return value.reshape(len(pos), 5, -1).max(axis=2)


def reference_boustrophedon_tour(grid: Grid) -> np.ndarray:
    """The sweep's tour as it was before (main 7d5d5fb): one unlimited shortest-path search
    per detour target over the whole grid."""
    from scipy.sparse.csgraph import shortest_path

    from twin.paths import free_cell_graph, largest_free_component

    reachable = largest_free_component(grid)
    order = []
    for i in range(grid.nx):
        cols = np.flatnonzero(reachable[i])
        order.extend((i, j) for j in (cols if i % 2 == 0 else cols[::-1]))
    order = np.array(order, dtype=np.int64)
    if len(order) <= 1:
        return order
    steps = np.abs(np.diff(order, axis=0)).sum(axis=1)
    if np.all(steps == 1):
        return order
    ny = grid.ny
    targets = order[np.flatnonzero(steps != 1) + 1]
    roots = np.unique(targets[:, 0] * ny + targets[:, 1])
    _, pred = shortest_path(
        free_cell_graph(grid), unweighted=True, indices=roots, return_predecessors=True
    )
    row = {int(root): n for n, root in enumerate(roots)}
    tour = [order[0]]
    for a, b in itertools.pairwise(order):
        if np.abs(a - b).sum() == 1:
            tour.append(b)
            continue
        target, node, path = int(b[0] * ny + b[1]), int(a[0] * ny + a[1]), []
        while node != target:
            path.append((node // ny, node % ny))
            node = int(pred[row[target]][node])
        tour.extend([*path[1:], (int(b[0]), int(b[1]))])
    return np.array(tour, dtype=np.int64)


if __name__ == "__main__":
    sys.exit(main())
