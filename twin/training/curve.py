"""R_hat_T against training epochs: evaluate a folder of weight snapshots on a scenario.

``python -m twin.training.curve runs/pretrain/snapshots --config configs/synthetic.toml``
runs, for every snapshot and seed, the "rl" swarm beside the comparison swarms (greedy by
default) on the same traffic, and writes one row per (snapshot, seed, swarm) to a CSV plus a
printed summary (mean and 95% half-width over seeds). This is how the pretraining schedule of
``configs/pretrain.toml`` was chosen.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import pandas as pd
import torch

from twin.config import load_config, shipped_config
from twin.experiment import Experiment, limit_threads, run_experiment
from twin.metrics import aggregate, table2


def evaluate_snapshots(snapshots, config_path, seeds, first_seed=0, others=("greedy",)):
    """One Table 2 row per (snapshot, seed, swarm)."""
    config = load_config(shipped_config(config_path))
    rows = []
    for snap in snapshots:
        epoch = int(torch.load(snap, weights_only=True)["meta"]["epoch"])
        experiment = Experiment(
            config,
            swarms=["rl", *others],
            seeds=range(first_seed, first_seed + seeds),
            swarm_options={"rl": {"checkpoint": snap}},
            keep_importance=False,
        )
        for result in run_experiment(experiment).results:
            table = table2(result)
            table.insert(0, "seed", result.seed)
            table.insert(0, "epoch", epoch)
            table.insert(0, "snapshot", str(snap))
            rows.append(table)
    return pd.concat(rows, ignore_index=True)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m twin.training.curve", description=__doc__)
    p.add_argument("snapshots", type=Path, nargs="+", help="snapshot files or folders of them")
    p.add_argument(
        "--config", default="synthetic", help="scenario config (default: shipped synthetic)"
    )
    p.add_argument("--seeds", type=int, default=10)
    p.add_argument("--seed", type=int, default=0, help="first seed")
    p.add_argument("--others", default="greedy", help="comma-separated comparison swarms")
    p.add_argument("--out", type=Path, default=None, help="CSV of the per-seed rows")
    args = p.parse_args(argv)
    limit_threads()
    files = []
    for s in args.snapshots:
        files += sorted(s.glob("*.pt")) if s.is_dir() else [s]
    per_seed = evaluate_snapshots(
        files, args.config, args.seeds, args.seed, [o for o in args.others.split(",") if o]
    )
    if args.out:
        per_seed.to_csv(args.out, index=False)
    summary = aggregate(per_seed, by=["epoch", "swarm"])
    cols = ["epoch", "swarm", "R_hat_T", "R_hat_T_ci95", "C_hat_T", "pct_map_covered"]
    pd.set_option("display.width", 160)
    print(summary[cols].to_string(index=False, float_format=lambda x: f"{x:.4f}"))
    return 0


if __name__ == "__main__":
    sys.exit(main())
