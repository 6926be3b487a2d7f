"""Seeds one after another against seeds at once: ``twin run --seeds N --workers 1`` and
``--workers W``, in the same process, one after the other.

Each seed of a live run is one SUMO simulation with all swarms; with ``--workers W`` the seeds run
in W worker processes (``twin/experiment.py``). Both run folders must hold the same files with
the same bytes, wall-time files aside (``timing.csv``, ``run.json``, ``manifest.json``): every
table, tape, trajectory and map (exit 1 otherwise). Reported: the wall seconds of each and their
ratio. Each seed already keeps about two cores busy (SUMO works ahead of the swarms in its own
process), so the speed-up depends on the cores free beside it.

Usage: ``python benchmarks/bench_seeds.py [--seeds 4] [--workers 2] [--horizon 24]
[--rounds 2]`` (the default Shenzhen-like scenario, without ceilings or report; ``--rounds R``:
R pairs of runs in ABBA order, wall times summed); ``--quick`` uses a small generated grid
(3 seeds, 10 steps; about 30 s).
"""

from __future__ import annotations

import argparse
import contextlib
import io
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from twin.cli import main as twin_main

#: Files of a run folder that hold wall times (or the sizes of files): not compared.
WALL_TIME_FILES = {"timing.csv", "run.json", "manifest.json"}

QUICK_CONFIG = """
[swarm]
n_drones = 2
[traffic]
kind = "sumo"
net = "small.net.xml"
routes = ["small.trips.xml"]
cell_m = 200.0
drone_speed_kmh = 12.0
begin = "00:05"
warmup_min = 5.0
horizon = 10
seed = 3
[evaluate]
swarms = ["random", "greedy", "sweeping"]
"""


def quick_config(folder: Path) -> Path:
    """A 5 x 5 signalised grid of 300 m blocks with 15 min of random trips."""
    from twin.sumo.network import generate_grid_scenario

    generate_grid_scenario(folder, blocks=5, block_m=300, end_s=900, period_s=1.5, seed=5)
    path = folder / "quick.toml"
    path.write_text(QUICK_CONFIG)
    return path


def run(args: list[str]) -> float:
    """``twin run ARGS`` in this process (its output kept back, shown if it fails): wall
    seconds."""
    start = time.perf_counter()
    out, err = io.StringIO(), io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
        code = twin_main(["run", *args])
    seconds = time.perf_counter() - start
    if code != 0:
        print(out.getvalue(), err.getvalue(), file=sys.stderr)
        sys.exit(f"bench_seeds: twin run {' '.join(args)} exited {code}")
    return seconds


def differences(a: Path, b: Path) -> list[str]:
    """Files of run folder ``a`` and ``b`` (wall-time files aside) that differ or exist in one."""

    def files(folder: Path) -> set[str]:
        return {
            p.relative_to(folder).as_posix()
            for p in folder.rglob("*")
            if p.is_file() and p.name not in WALL_TIME_FILES
        }

    names_a, names_b = files(a), files(b)
    differ = sorted(names_a ^ names_b)
    for name in sorted(names_a & names_b):
        if (a / name).read_bytes() != (b / name).read_bytes():
            differ.append(name)
    return differ


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--config", type=Path, default=None, help="scenario (default: twin run's)")
    p.add_argument("--seeds", type=int, default=4)
    p.add_argument("--workers", type=int, default=2)
    p.add_argument("--horizon", type=int, default=24)
    p.add_argument(
        "--rounds", type=int, default=1, help="pairs of runs, ABBA-ordered (default 1: A, B)"
    )
    p.add_argument("--quick", action="store_true", help="small generated grid, about 30 s")
    args = p.parse_args()
    tmp = Path(tempfile.mkdtemp(prefix="bench-seeds-"))
    config = quick_config(tmp) if args.quick else args.config
    seeds = 3 if args.quick else args.seeds
    common = ["--seeds", str(seeds), "--no-ceiling", "--no-report", "--quiet"]
    if config is not None:
        common += ["--config", str(config)]
    if not args.quick:
        common += ["--horizon", str(args.horizon)]
    order = ["1", str(args.workers)] * args.rounds
    for r in range(1, args.rounds, 2):  # ABBA: the machine's load drifts alike on both
        order[2 * r], order[2 * r + 1] = order[2 * r + 1], order[2 * r]
    seconds: dict[str, list[float]] = {"1": [], str(args.workers): []}
    folders: list[Path] = []
    for n, workers in enumerate(order):
        out = tmp / f"run-{n}-workers-{workers}"
        seconds[workers].append(run([*common, "--workers", workers, "--out", str(out)]))
        folders.append(out)
    t_one, t_many = sum(seconds["1"]), sum(seconds[str(args.workers)])
    print(f"twin run {' '.join(common)}   (runs in order: --workers {', '.join(order)})")
    each = {w: " + ".join(f"{x:.1f}" for x in ts) for w, ts in seconds.items()}
    print(f"  --workers 1: {t_one:8.1f} s   ({each['1']})")
    print(
        f"  --workers {args.workers}: {t_many:8.1f} s   ({each[str(args.workers)]})   "
        f"speed-up {t_one / t_many:.2f} x"
    )
    for folder in folders[1:]:
        differ = differences(folders[0], folder)
        if differ:
            sys.exit(f"bench_seeds: the run folders disagree: {', '.join(differ)} (in {tmp})")
    one = folders[0]
    n_files = len([p for p in one.rglob("*") if p.is_file()]) - len(WALL_TIME_FILES)
    print(f"  same files, byte for byte: {n_files} (timing.csv, run.json, manifest.json aside)")
    import shutil

    shutil.rmtree(tmp, ignore_errors=True)


if __name__ == "__main__":
    main()
