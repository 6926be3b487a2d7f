"""Score the belief models of a finished `twin run` folder against a history, after the run.

    python docs/measure_beliefs.py --history HISTORY.npz RUN_DIR [RUN_DIR ...] [--spatial] \
        [--meas-var V] [--csv OUT.csv]

Replays each seed's tape (``tapes/seed-<s>.parquet``, else ``tape.parquet``) without SUMO for
the observed and true maps, reads the swarms' positions from ``trajectories.parquet`` and
prints :func:`twin.belief.run_beliefs`' table (mean over seeds), the same numbers as
``twin run --history``; ``--spatial`` adds the nowcast with 4-neighbour coupling.
"""

from __future__ import annotations

import argparse
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pandas as pd

from twin.belief import DEFAULT_MEAS_VAR, History, belief_table, format_belief_table, summarize
from twin.traffic.tape import Tape, TapeTraffic


def seed_results(run_dir: Path):
    """One result-like object per seed of ``run_dir``: swarms, grid, seed, positions, maps."""
    trajectories = pd.read_parquet(run_dir / "trajectories.parquet")
    for seed, frame in trajectories.groupby("seed", sort=True):
        tape = run_dir / "tapes" / f"seed-{seed}.parquet"
        tape = tape if tape.is_file() else run_dir / "tape.parquet"
        source = TapeTraffic(Tape.read(tape), source_name=str(tape))
        observed, truth = [], []
        for importance in source.importance_maps():
            observed.append(np.array(importance, dtype=np.float32))
            t = source.truth_map()
            truth.append(observed[-1] if t is None else np.array(t, dtype=np.float32))
        swarms = list(dict.fromkeys(frame["swarm"]))
        steps = int(frame["step"].max()) + 1
        drones = int(frame["drone"].max()) + 1
        positions = np.zeros((len(swarms), steps, drones, 2), np.int64)
        for s, swarm in enumerate(swarms):
            f = frame[frame["swarm"] == swarm]
            positions[s, f["step"], f["drone"]] = f[["i", "j"]].to_numpy()
        yield SimpleNamespace(
            swarms=swarms,
            grid=source.grid,
            seed=int(seed),
            positions=positions,
            importance=np.stack(observed)[:steps],
            truth=np.stack(truth)[:steps],
            step_s=source.tape.settings.get("step_s"),
        )


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("run_dirs", type=Path, nargs="+")
    parser.add_argument("--history", type=Path, required=True)
    parser.add_argument("--spatial", action="store_true")
    parser.add_argument("--meas-var", type=float, default=DEFAULT_MEAS_VAR)
    parser.add_argument("--csv", type=Path, help="also write the table here")
    args = parser.parse_args()
    history = History.load(args.history)
    tables = []
    for run_dir in args.run_dirs:
        for r in seed_results(run_dir):
            print(f"{run_dir}: seed {r.seed} ({len(r.swarms)} swarms)", flush=True)
            tables.append(
                belief_table(
                    r, history, step_s=r.step_s, meas_var=args.meas_var, spatial=args.spatial
                )
            )
    table = summarize(pd.concat(tables, ignore_index=True))
    print(
        f"history {args.history}: rho median {np.median(history.rho[~history.obstacles]):.3f}, "
        f"neighbour correlation {history.neighbour_corr:.3f}"
    )
    print(format_belief_table(table))
    if args.csv:
        table.to_csv(args.csv, index=False)


if __name__ == "__main__":
    main()
