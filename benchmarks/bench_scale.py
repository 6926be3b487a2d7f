"""City scale: the whole run against bare SUMO stepping of the same scenario, and how the cost
per step grows with cells and drones.

``python benchmarks/bench_scale.py`` (default ``configs/shenzhen-city-scale.toml``: 200 drones on
100 m cells, 720 steps of 15 s, every swarm of the config). Each run in a fresh process (libsumo
slows down with every simulation started in one process), ``--rounds`` x (bare, twin) in ABBA
order (default 2), each kind's mean counting:

- ``bare``: the scenario's SUMO run advanced to every sample time, nothing read (the floor);
- ``twin``: the same SUMO run through the one experiment runner (:func:`twin.experiment.
  run_experiment`): the config's reads per step, binning, the online MFD, every swarm side by side,
  scoring and recording; then the run folder's monitoring and files.

SUMO runs in its own process ahead of the swarms (``twin/sumo/worker.py``), so the twin run
uses both cores: its CPU seconds (both processes) exceed its wall seconds. ``--same-process``
runs SUMO inside the runner's process instead, as with ``Experiment(separate_process=False)``.

It prints wall and CPU seconds of each, their ratio (the target is at most 1.3), the peak
memory of the process, and the per-stage table of the ``twin`` run (``twin/timing.py``).

``--sweep`` measures the growth: for every cell size x drone count (default 500,250,100 m x
4,50,200 drones) one ``twin run`` of ``--hours`` of the rush hour in a fresh process (its wall
time, peak memory from ``run.json`` and its ``timing.csv``), and prints the table: wall time,
peak memory and milliseconds per step of SUMO, of the coupling (reads, binning, MFD) and of the
swarms together.

Checks (exit 1 when they fail): every run ends with the same vehicles on the road (the coupling
does not change the simulation), and the per-stage times add up to the patrol loop's wall
time within 2%. ``--meso`` runs the same with SUMO's mesoscopic model and compares speed and
monitoring results (R_hat_T, events, share seen, latency, belief error) swarm by swarm.
``--quick``: a small generated grid with 50 drones on 100 m cells (seconds).
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import pandas as pd

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from twin.config import load_config, with_overrides
from twin.experiment import Experiment, build_source, limit_threads, run_experiment
from twin.processes import peak_memory_mb
from twin.runs import timing_frame
from twin.timing import (
    OBSERVATION,
    READS,
    SUMO_STEPPING,
    SUMO_WARMUP,
    TRAFFIC_OTHER,
    WAITING_FOR_SUMO,
)

ROOT = Path(__file__).resolve().parents[1]
SCALE_CONFIG = ROOT / "configs/shenzhen-city-scale.toml"
QUICK_CONFIG = """
[swarm]
n_drones = 50

[traffic]
kind = "sumo"
net = "small.net.xml"
routes = ["small.trips.xml"]
cell_m = 100.0
drone_speed_kmh = 24.0
begin = "00:05"
warmup_min = 5.0
horizon = 40

[evaluate]
swarms = ["random", "greedy", "sweeping", "greedy-coordinated", "visit-gain", "lookahead",
          "rl", "rl-decentralized"]
"""
COUPLING = (READS, OBSERVATION, TRAFFIC_OTHER)


def quick_config(folder: Path) -> Path:
    from twin.sumo.network import generate_grid_scenario

    generate_grid_scenario(folder, blocks=6, block_m=300, end_s=1800, period_s=1.0, seed=5)
    path = folder / "quick.toml"
    path.write_text(QUICK_CONFIG)
    return path


def cpu_seconds() -> float:
    """CPU seconds of this process and of its ended children (SUMO's own process)."""
    t = os.times()
    return t.user + t.system + t.children_user + t.children_system


def timed(fn):
    c0, w0 = cpu_seconds(), time.perf_counter()
    out = fn()
    return cpu_seconds() - c0, time.perf_counter() - w0, out


def experiment_of(
    config_path: Path, horizon: int | None, meso: bool = False, same_process: bool = False
) -> Experiment:
    settings = {"traffic.horizon": horizon, "traffic.mesoscopic": True if meso else None}
    config = with_overrides(
        load_config(config_path), {k: v for k, v in settings.items() if v is not None}
    )
    return Experiment(
        separate_process=not same_process,
        config=config,
        swarms=config.evaluate.swarms,
        seeds=[config.evaluate.seed],
        skip_unavailable=True,
    )


def bare(experiment: Experiment):
    """SUMO alone over the run's sample times (warm-up included): the floor."""
    source = build_source(experiment)

    def run():
        session = source.session().start()
        try:
            for _, t in source.sample_times():
                session.advance_to(t)
            return len(session.vehicles()[0])  # one read at the very end: on the road
        finally:
            session.close()

    return timed(run)


def coupled(experiment: Experiment):
    def run():
        outcome = run_experiment(experiment, keep_sources=True)
        source = outcome.sources[0]
        running = source.vehicles_seen[-1] if source.vehicles_seen else 0  # at the last sample
        return outcome, running

    return timed(run)


def write_folder(outcome, folder: Path) -> float:
    """The run folder as ``twin run`` writes it (monitoring, tape, MFD samples); seconds."""
    from twin.experiment import close_sources, run_metadata
    from twin.runs import record

    t0 = time.perf_counter()
    record(folder, outcome, run_metadata(outcome, "run"))
    close_sources(outcome)
    return time.perf_counter() - t0


def stage_table(stages: dict[str, float], steps: int) -> str:
    total = sum(stages.values()) or 1.0
    lines = [f"{'stage':40s} {'s':>8s} {'ms/step':>9s} {'share':>7s}"]
    for name, s in stages.items():
        lines.append(f"{name:40s} {s:8.2f} {1000 * s / max(steps, 1):9.2f} {100 * s / total:6.1f}%")
    return "\n".join(lines)


def one_run(
    kind: str, config_path: Path, horizon: int | None, meso: bool, out: Path, same: bool = False
) -> dict:
    """One bare or twin run in this process (a child of :func:`scale_run`); its figures."""
    experiment = experiment_of(config_path, horizon, meso, same)
    if kind == "bare":
        cpu, wall, running = bare(experiment)
        return {"cpu": cpu, "wall": wall, "running": running, "peak_mb": peak_memory_mb()}
    cpu, wall, (outcome, running) = coupled(experiment)
    result = outcome.results[0]
    writing = write_folder(outcome, out)
    timing_frame([result], writing).to_csv(out / "bench_timing.csv", index=False)
    return {
        "cpu": cpu,
        "wall": wall,
        "running": running,
        "peak_mb": peak_memory_mb(),
        "stages": result.stage_seconds,
        "sumo_stages": result.extra.get("process_stages", {}).get("sumo", {}),
        "loop_seconds": result.seconds,
        "steps": result.completed_steps,
        "writing": writing,
        "grid": [result.grid.nx, result.grid.ny, result.grid.n_free],
        "drones": int(result.positions.shape[2]),
        "swarms": list(result.swarms),
    }


def scale_run(
    config_path: Path,
    horizon: int | None,
    out: Path,
    meso: bool = False,
    rounds: int = 1,
    same_process: bool = False,
) -> str:
    """Bare against twin, each run in a fresh process, ``rounds`` x (bare, twin) in ABBA order;
    returns a disagreement, or ''.

    Fresh processes: libsumo gets slower with every simulation started in one process (this
    scenario: 84 s for the first bare run, 107 s for the same run two simulations later), which
    would favour whichever kind runs first. ABBA order spreads the machine's drift over both."""
    out.mkdir(parents=True, exist_ok=True)
    runs: dict[str, list[dict]] = {"bare": [], "twin": []}
    for r in range(rounds):
        for kind in ("bare", "twin") if r % 2 == 0 else ("twin", "bare"):
            cmd = [sys.executable, __file__, "--child", kind, "--config", str(config_path),
                   "--out", str(out)]  # fmt: skip
            if horizon is not None:
                cmd += ["--horizon", str(horizon)]
            if meso:
                cmd.append("--meso")
            if same_process:
                cmd.append("--same-process")
            done = subprocess.run(cmd, capture_output=True, text=True, env=os.environ.copy())
            if done.returncode != 0:
                sys.exit(f"bench_scale: the {kind} run failed: {done.stderr.strip()[-500:]}")
            runs[kind].append(json.loads(done.stdout.strip().splitlines()[-1]))

    def mean(kind: str, key: str) -> float:
        return sum(r[key] for r in runs[kind]) / len(runs[kind])

    cpu_b, wall_b, cpu_t, wall_t = (mean(k, x) for k in ("bare", "twin") for x in ("cpu", "wall"))
    twin = runs["twin"][-1]
    steps, stages, writing = twin["steps"], twin["stages"], twin["writing"]
    nx, ny, n_free = twin["grid"]
    swarms = sum(s for k, s in stages.items() if k.startswith("swarm "))
    print(
        f"scenario: {config_path.name}, {nx} x {ny} cells ({n_free} free), {twin['drones']} "
        f"drones, T = {steps}, {len(twin['swarms'])} swarms ({', '.join(twin['swarms'])}), "
        f"SUMO {'mesoscopic' if meso else 'microscopic'} "
        f"{'in the runner' if same_process else 'in its own process'}; each run in a fresh process"
    )
    if rounds > 1:
        walls = lambda kind: ", ".join(f"{r['wall']:.1f}" for r in runs[kind])  # noqa: E731
        print(f"wall s per run, bare: {walls('bare')}; twin: {walls('twin')} (ABBA order)")
    label = f"mean of {rounds}" if rounds > 1 else "one run each"
    print(f"{'run (' + label + ')':30s} {'cpu s':>8s} {'wall s':>8s} {'wall / bare':>12s} "
          f"{'cpu / bare':>11s}")  # fmt: skip
    print(f"{'bare SUMO stepping':30s} {cpu_b:8.2f} {wall_b:8.2f} {1.0:12.3f} {1.0:11.3f}")
    print(
        f"{'twin run (all swarms)':30s} {cpu_t:8.2f} {wall_t:8.2f} {wall_t / wall_b:12.3f} "
        f"{cpu_t / cpu_b:11.3f}"
    )
    where = twin.get("sumo_stages") or stages
    sumo = where.get(SUMO_STEPPING, 0.0) + where.get(SUMO_WARMUP, 0.0)
    coupling = sum(where.get(k, 0.0) for k in COUPLING)
    print(
        f"inside the last twin run: SUMO {sumo:.1f} s, coupling {coupling:.1f} s, swarms "
        f"{swarms:.1f} s; then monitoring and the run folder {writing:.1f} s (not in the ratio)"
    )
    print(f"peak memory: twin run {twin['peak_mb']} MB, bare run {runs['bare'][-1]['peak_mb']} MB")
    print(stage_table(stages, steps))
    if twin.get("sumo_stages"):
        print("SUMO's own process, beside the runner:")
        print(stage_table(twin["sumo_stages"], steps))
    problems = []
    running = {r["running"] for r in runs["bare"] + runs["twin"]}
    if len(running) > 1:
        problems.append(f"vehicles on the road at the end differ between runs: {sorted(running)}")
    covered = sum(stages.values())
    loop = twin["loop_seconds"]
    if abs(covered - loop) > 0.02 * loop + 0.05:
        problems.append(f"stages add up to {covered:.2f} s of the loop's {loop:.2f} s")
    (out / "bench_walls.json").write_text(json.dumps({"bare": wall_b, "twin": wall_t}))
    return "; ".join(problems)


MESO_COLUMNS = {
    "R_hat_T": "R_hat_T",
    "events": "events",
    "pct_events_seen": "% seen",
    "latency_median_min": "latency (min)",
    "belief_error": "belief error",
}


def compare_meso(micro: Path, meso: Path) -> None:
    """Mesoscopic against microscopic SUMO: speed, and how the monitoring results differ."""
    walls = {k: json.loads((f / "bench_walls.json").read_text()) for k, f in (("micro", micro), ("meso", meso))}  # fmt: skip
    a = pd.read_csv(micro / "summary.csv").set_index("swarm")
    b = pd.read_csv(meso / "summary.csv").set_index("swarm")
    print(
        f"\nmesoscopic against microscopic: bare SUMO {walls['micro']['bare']:.1f} s -> "
        f"{walls['meso']['bare']:.1f} s (x{walls['micro']['bare'] / walls['meso']['bare']:.2f}), "
        f"whole twin run {walls['micro']['twin']:.1f} s -> {walls['meso']['twin']:.1f} s "
        f"(x{walls['micro']['twin'] / walls['meso']['twin']:.2f})"
    )
    columns = [c for c in MESO_COLUMNS if c in a.columns and c in b.columns]
    table = pd.DataFrame(
        {
            f"{MESO_COLUMNS[c]} {mode}": f[c]
            for c in columns
            for mode, f in (("micro", a), ("meso", b))
        }
    )
    print(table.round(3).to_string())


def sweep(config_path: Path, cells: list[float], drones: list[int], hours: float, out: Path):
    """One ``twin run`` per (cell size, drones) in a fresh process; the table of their costs."""
    config = load_config(config_path)
    speed = config.traffic.drone_speed_kmh
    rows = []
    for cell in cells:
        step_s = cell / (speed / 3.6)
        horizon = max(1, round(hours * 3600 / step_s))
        for n in drones:
            folder = out / f"cell{cell:g}-drones{n}"
            cmd = [
                sys.executable, "-m", "twin", "run", "--config", str(config_path),
                "--cell-m", f"{cell:g}", "--drones", str(n), "--horizon", str(horizon),
                "--out", str(folder), "--no-report", "--quiet", "--no-ceiling",
            ]  # fmt: skip
            t0 = time.perf_counter()
            done = subprocess.run(cmd, capture_output=True, text=True, env=os.environ.copy())
            wall = time.perf_counter() - t0
            if done.returncode != 0:
                tail = (done.stderr.strip().splitlines() or ["?"])[-1]
                sys.exit(f"bench_scale: {cell:g} m x {n} drones failed: {tail}")
            meta = json.loads((folder / "run.json").read_text())
            timing = pd.read_csv(folder / "timing.csv").set_index("stage")["ms_per_step"]
            grid = meta["grid"]
            rows.append(
                {
                    "cell_m": cell,
                    "drones": n,
                    "cells": grid["nx"] * grid["ny"],
                    "free": grid["n_free"],
                    "steps": horizon,
                    "wall_s": round(wall, 1),
                    "peak_mb": meta["timings"].get("peak_memory_mb"),
                    "sumo_peak_mb": meta["timings"].get("peak_memory_sumo_process_mb"),
                    "sumo_ms": round(timing.get(SUMO_STEPPING, 0.0), 2),
                    "waiting_ms": round(timing.get(WAITING_FOR_SUMO, 0.0), 2),
                    "coupling_ms": round(sum(timing.get(k, 0.0) for k in COUPLING), 2),
                    "swarms_ms": round(timing[timing.index.str.startswith("swarm ")].sum(), 2),
                    "scoring_ms": round(timing.get("step and scoring", 0.0), 2),
                }
            )
            print(pd.DataFrame(rows[-1:]).to_string(index=False, header=len(rows) == 1))
    table = pd.DataFrame(rows)
    table.to_csv(out / "scale_sweep.csv", index=False)
    print(
        "\nms per step (SUMO stepping and the coupling in SUMO's own process, warm-up apart; "
        f"waiting: the runner's wait for it); written to {out / 'scale_sweep.csv'}"
    )
    print(table.to_markdown(index=False) if _has_tabulate() else table.to_string(index=False))


def _has_tabulate() -> bool:
    try:
        import tabulate  # noqa: F401
    except ImportError:
        return False
    return True


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--config", type=Path, default=SCALE_CONFIG)
    p.add_argument("--horizon", type=int, default=None, help="steps (default: the config's)")
    p.add_argument("--quick", action="store_true", help="small generated grid, seconds")
    p.add_argument("--sweep", action="store_true", help="cell size x drones, fresh processes")
    p.add_argument(
        "--rounds", type=int, default=None, help="ABBA rounds of bare and twin (default 2, quick 1)"
    )
    p.add_argument("--child", choices=["bare", "twin"], help=argparse.SUPPRESS)
    p.add_argument("--same-process", action="store_true", help="SUMO inside the runner's process")
    p.add_argument("--cells", default="500,250,100", help="cell sizes (m) of the sweep")
    p.add_argument("--drones", default="4,50,200", help="drone counts of the sweep")
    p.add_argument("--hours", type=float, default=1.0, help="rush hour simulated per sweep run")
    p.add_argument("--out", type=Path, default=None, help="folder for the runs (default: temp)")
    p.add_argument(
        "--meso", action="store_true", help="also run mesoscopic SUMO and compare the results"
    )
    args = p.parse_args()
    limit_threads()
    if args.child:  # one run for the parent: its figures as one JSON line
        args.out.mkdir(parents=True, exist_ok=True)
        figures = one_run(
            args.child, args.config, args.horizon, args.meso, args.out, args.same_process
        )
        print(json.dumps(figures))
        return
    tmp = tempfile.TemporaryDirectory()
    out = args.out or Path(tmp.name)
    out.mkdir(parents=True, exist_ok=True)
    config_path = quick_config(Path(tmp.name)) if args.quick else args.config
    if args.sweep:
        cells = [float(c) for c in args.cells.split(",")]
        drones = [int(d) for d in args.drones.split(",")]
        hours = 0.1 if args.quick else args.hours
        if args.quick:
            cells, drones = [200.0, 100.0], [4, 20]
        sweep(config_path, cells, drones, hours, out)
        tmp.cleanup()
        return
    rounds = args.rounds if args.rounds is not None else (1 if args.quick else 2)
    same = args.same_process
    problem = scale_run(config_path, args.horizon, out / "scale-run", False, rounds, same)
    if args.meso:
        print()
        meso_run = scale_run(config_path, args.horizon, out / "scale-meso", True, rounds, same)
        problem = problem or meso_run
        compare_meso(out / "scale-run", out / "scale-meso")
    tmp.cleanup()
    if problem:
        sys.exit(f"bench_scale: the implementations disagree: {problem}")


if __name__ == "__main__":
    main()
