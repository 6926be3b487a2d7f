"""The SUMO coupling's cost, as ratios against bare SUMO stepping in the same process.

Runs the same scenario (network, demand, seed, time window) several times, one libsumo session
after the other, and reports CPU seconds (process time, robust to other load on the machine) and
wall seconds of:

- ``bare``: SUMO advanced to each sample time, nothing read (the floor);
- ``coupled, 1 swarm``: the live source (bulk read of every vehicle at each sample time, cell
  binning, online MFD) driving one swarm through ``run_patrol``;
- ``coupled, K swarms``: the same with K swarms side by side on the same SUMO run;
- ``bare, mesoscopic``: SUMO's mesoscopic model, against the microscopic ``bare``;
- ``bare + N loop stations``: bare stepping with N fixed-detector stations loaded (twin's
  virtual loops, :mod:`twin.sumo.detectors`) and read at every sample time; its CPU against
  ``bare`` is the detectors' coupling cost (SUMO's own work for the loops plus the reads), which
  must stay within 2% of bare SUMO time (``--detectors N``, default 48, 8 with ``--quick``).

The 1-swarm and K-swarm runs must read the same vehicles and importance maps and move the
greedy swarm alike (exit 1 otherwise).

``--aliasing 1,2,3,5``: observations over the step. One SUMO run read at every instant any of
the given reads-per-step needs gives, for each R, the network-mean importance ``T^k`` the twin
would see; signal cycles aliased by one read every 75 s show as a swing of about 4 steps. Swing
measures of the detrended series (minus its centred 9-step mean): its standard deviation, the
share of its power at periods of 3-5 steps, and the autocorrelation at lags 2 and 4 (a 4-step
swing: lag 2 negative, lag 4 positive). Then the cost of each R: the live source alone (reads,
binning, MFD) against bare stepping, CPU ratio. The per-R counts of the shared run must equal
the live source's (exit 1 otherwise).

Usage: ``python benchmarks/bench_sumo.py [--horizon 144] [--swarms 6] [--aliasing 1,2,3,5]``;
``--quick`` uses a small generated grid (seconds).
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
from twin.scores import ScoreParams
from twin.sumo.scenario import sumo_source
from twin.swarms import make_policy

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


def with_detectors(config, horizon: int, n: int):
    """Bare stepping with ``n`` loop stations loaded and read at every sample time; returns
    the CPU seconds of the reads alone and the number of loops."""
    from twin.sumo.detectors import (
        DetectorPlan,
        main_edges,
        place_loops,
        scenario_reader,
        station_cells,
    )
    from twin.sumo.session import _libsumo

    source = sumo_source(config, horizon=horizon)
    edges = main_edges(source.scenario.net_file, source.geometry)
    with_edge = np.zeros(source.grid.shape, dtype=bool)
    for cell in edges:
        with_edge[cell] = source.grid.free[cell]
    cells = station_cells(source.geometry.lane_km, with_edge, n)
    plan = DetectorPlan(loops=place_loops(edges, source.geometry, cells))
    source.scenario.detectors = plan
    folder = tempfile.TemporaryDirectory()

    def run():
        session = source.session(Path(folder.name)).start()
        reader = scenario_reader(source.scenario, source.geometry, _libsumo())
        reading = 0.0
        try:
            for _, t in source.sample_times():
                session.advance_to(t)
                c0 = time.process_time()
                reader.read()
                reading += time.process_time() - c0
            return reading, len(reader.detectors)
        finally:
            session.close()

    out = timed(run)
    folder.cleanup()
    return out


def detectors_only(config, horizon: int, stations: int, repeat: int, run_bare) -> None:
    """Bare stepping against bare stepping with ``stations`` loop stations read, interleaved;
    every run's CPU printed (their spread is the measure's noise), the fastest of each counts."""
    bare_cpu, loops_cpu, reads = [], [], []
    for _ in range(repeat):
        bare_cpu.append(run_bare()[0])
        cpu, _, (read, n_loops) = with_detectors(config, horizon, stations)
        loops_cpu.append(cpu)
        reads.append(read)
    b, d = min(bare_cpu), min(loops_cpu)
    print(f"T = {horizon}, {stations} loop stations ({n_loops} loops), {repeat} runs of each")
    print("bare SUMO CPU s: " + ", ".join(f"{c:.2f}" for c in bare_cpu))
    print("bare + loops CPU s: " + ", ".join(f"{c:.2f}" for c in loops_cpu))
    print(f"fastest: x{d / b:.4f} bare ({100 * (d / b - 1):+.2f}%); reads "
          f"{100 * min(reads) / b:.3f}% of bare")  # fmt: skip


def coupled(config, horizon: int, names: list[str], first: int = 0):
    source = sumo_source(config, horizon=horizon)
    swarms = {}
    for n, name in enumerate(names):  # a swarm's name seeds its randomness (ties of greedy)
        swarms[f"{name}-{n + first}"] = make_policy(name)
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
        a, b = res1.swarms.index("greedy-1"), res_k.swarms.index("greedy-1")
        for field in ("rewards", "coverage", "positions"):
            if not np.array_equal(getattr(res1, field)[a], getattr(res_k, field)[b]):
                return f"greedy swarm's {field}"
    return ""


def shared_reads(config, horizon: int, reads: list[int]):
    """One SUMO run read at the union of the instants of every R: per R, the per-snapshot
    vehicle-instants (summed here, apart from the source's code) and network-mean T^k."""
    from twin.mfd import MFDImportance

    source = sumo_source(config, horizon=horizon)
    s = source.scenario
    offsets = {}
    for r in reads:
        s.reads_per_step = r
        offsets[r] = s.read_offsets()
    union = sorted({o for offs in offsets.values() for o in offs}, reverse=True)
    models = {
        r: MFDImportance(
            source.grid.free, source.geometry.lane_km, source.geometry.speed_limit,
            s.mfd_fit, source.model.mfd, s.detection_p, s.seed, r,
        )
        for r in reads
    }  # fmt: skip
    counts: dict[int, list[np.ndarray]] = {r: [] for r in reads}
    mean_t: dict[int, list[float]] = {r: [] for r in reads}
    speed_kmh: dict[int, list[float]] = {r: [] for r in reads}
    session = source.session().start()
    try:
        for k, t in source.sample_times():
            read = {}
            for o in union:
                session.advance_to(max(t - o, min(s.sim_begin + 1.0, t)))
                n, v = source.geometry.count_and_speed(*session.vehicles())
                read[o] = (n, np.nan_to_num(v) * n)
            for r in reads:
                n = sum(read[o][0] for o in offsets[r])
                dist = sum(read[o][1] for o in offsets[r])
                with np.errstate(invalid="ignore", divide="ignore"):
                    v = np.where(n > 0, dist / np.maximum(n, 1), np.nan)
                if r == 1:
                    v = source.geometry.count_and_speed(*session.vehicles())[1]
                v = v.astype(np.float32).astype(float)
                importance = models[r].observe(k, n, v)
                counts[r].append(n.astype(np.int32))
                if k >= 0:
                    mean_t[r].append(float(importance[source.grid.free].mean()))
                    speed_kmh[r].append(3.6 * float(dist.sum() / max(n.sum(), 1)))
    finally:
        session.close()
    return counts, {r: np.array(v) for r, v in mean_t.items()}, speed_kmh


def swing(series: np.ndarray) -> dict[str, float]:
    """Swing measures of a per-step series, detrended by its centred 9-step mean."""
    x = np.asarray(series, dtype=float)
    trend = np.convolve(np.pad(x, 4, mode="edge"), np.ones(9) / 9, mode="valid")
    d = x - trend
    d = d - d.mean()
    power = np.abs(np.fft.rfft(d)) ** 2
    freq = np.fft.rfftfreq(len(d))
    band = (freq >= 1 / 5) & (freq <= 1 / 3)
    var = float((d * d).sum())

    def acf(lag: int) -> float:
        return float((d[:-lag] * d[lag:]).sum() / var) if var > 0 else float("nan")

    return {
        "std": float(d.std()),
        "band": float(power[band].sum() / power[1:].sum()) if power[1:].sum() > 0 else 0.0,
        "acf2": acf(2),
        "acf4": acf(4),
    }


def source_only(config, horizon: int, reads: int):
    source = sumo_source(config, horizon=horizon)
    source.scenario.reads_per_step = reads
    return timed(lambda: (sum(1 for _ in source.importance_maps()), source))


def aliasing(config, horizon: int, reads: list[int], repeat: int) -> str:
    """Print the aliasing table; return what disagrees ("" when all agree)."""
    counts, mean_t, speed = shared_reads(config, horizon, reads)
    best: dict[object, tuple] = {}
    for _ in range(repeat):  # interleaved rounds, the fastest of each kind counts
        for kind in ["bare", *reads]:
            run = bare(config, horizon) if kind == "bare" else source_only(config, horizon, kind)
            if kind not in best or run[0] < best[kind][0]:
                best[kind] = run
    cpu_b = best["bare"][0]
    print(f"\naliasing of the network-mean importance T^k ({horizon} steps), one shared SUMO run:")
    print(f"{'reads/step':>10s} {'swing std':>10s} {'power 3-5 steps':>16s} {'acf lag 2':>10s} "
          f"{'acf lag 4':>10s} {'speed swing km/h':>17s} {'cpu / bare':>11s}")  # fmt: skip
    disagree = ""
    for r in reads:
        m, v = swing(mean_t[r]), swing(np.array(speed[r]))
        cpu, _, (_, src) = best[r]
        print(f"{r:10d} {m['std']:10.4f} {100 * m['band']:15.1f}% {m['acf2']:10.3f} "
              f"{m['acf4']:10.3f} {v['std']:17.2f} {cpu / cpu_b:11.3f}")  # fmt: skip
        live = [c for _, _, c, _ in src.snapshots]
        if len(live) != len(counts[r]) or any(
            not np.array_equal(a, b) for a, b in zip(live, counts[r], strict=False)
        ):
            disagree = disagree or f"the counts of {r} reads per step"
    print(f"bare SUMO stepping: {cpu_b:.2f} s CPU; a swing of 4 steps: acf lag 2 < 0 < lag 4")
    return disagree


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--config", type=Path, default=ROOT / "configs/shenzhen.toml")
    p.add_argument("--horizon", type=int, default=144, help="steps (144 = 07:00-10:00)")
    p.add_argument("--swarms", type=int, default=6, help="K for the K-swarm run")
    p.add_argument("--quick", action="store_true", help="small generated grid, seconds")
    p.add_argument("--no-meso", action="store_true", help="skip the mesoscopic run")
    p.add_argument("--repeat", type=int, default=1, help="runs of each kind; the fastest counts")
    p.add_argument("--aliasing", default="", help="reads per step to compare, e.g. 1,2,3,5")
    p.add_argument("--only-aliasing", action="store_true", help="skip the swarm runs")
    p.add_argument("--detectors", type=int, help="loop stations (default 48; 8 with --quick)")
    p.add_argument(
        "--only-detectors", action="store_true", help="only bare and bare + loop stations"
    )
    args = p.parse_args()
    tmp = tempfile.TemporaryDirectory()
    config_path = quick_config(Path(tmp.name)) if args.quick else args.config
    config = load_config(config_path)
    horizon = 25 if args.quick else args.horizon
    base = ["random", "greedy", "sweeping"]
    k_names = (base * args.swarms)[: args.swarms]

    repeat = args.repeat
    reads = [int(r) for r in args.aliasing.split(",") if r] or ([1, 3] if args.quick else [])
    if args.only_aliasing:
        disagree = aliasing(config, horizon, reads, repeat)
        tmp.cleanup()
        if disagree:
            sys.exit(f"bench_sumo: the shared-run and live counts disagree: {disagree}")
        return
    # Interleaved rounds (bare, 1 swarm, K swarms, meso), the fastest of each kind counts: load
    # from other processes then hits every kind alike.
    kinds = {
        "bare": lambda: bare(config, horizon),
        "one": lambda: coupled(config, horizon, ["greedy"], first=1),
        "k": lambda: coupled(config, horizon, k_names),
    }
    stations = args.detectors if args.detectors is not None else (8 if args.quick else 48)
    if args.only_detectors:
        detectors_only(config, horizon, stations, repeat, kinds["bare"])
        tmp.cleanup()
        return
    if not args.no_meso:
        kinds["meso"] = lambda: bare(config, horizon, mesoscopic=True)
    if stations:
        kinds["loops"] = lambda: with_detectors(config, horizon, stations)
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
    if stations:
        cpu_d, _, (read_d, n_loops) = best["loops"]
        share = cpu_d / cpu_b - 1
        verdict = "within" if share <= 0.02 else "OVER"
        print(f"bare + {stations} loop stations ({n_loops} loops): {cpu_d:.2f} s CPU, x{cpu_d / cpu_b:.3f} "
              f"bare; reads {read_d:.3f} s CPU = {100 * read_d / cpu_b:.2f}% of bare; detectors' "
              f"cost {100 * share:+.2f}% of bare SUMO time: {verdict} the 2% budget")  # fmt: skip
    if not args.no_meso:
        print(f"mesoscopic speed-up over microscopic: x{cpu_b / cpu_m:.2f}")
    if reads:
        bad = aliasing(config, horizon, reads, repeat)
        disagree = disagree or (bad and f"shared-run and live source: {bad}")
    tmp.cleanup()
    if disagree:
        sys.exit(f"bench_sumo: the implementations disagree: {disagree}")


if __name__ == "__main__":
    main()
