"""The ``nowcast`` state variant against the paper's 13 values, at one small budget.

Both variants are pretrained with the same schedule and seed (:data:`SCHEDULE`, for each of
the training seeds :data:`TRAIN_SEEDS`: the dynamic
training traffic, whose days differ, so that the nowcast's history has a spread; the
``nowcast`` run's history is that generator's days 1000000-1000007, apart from the training
episodes' seeds ``seed * 100003 + e``, e < 20), then the coordinated learned swarm ``rl`` of each runs on
configs/synthetic.toml at T = :data:`HORIZON` over the evaluation seeds :data:`SEEDS`, paired
(same traffic, same starts). Both read the same history of the synthetic map: 8 days of the
dynamic generator on its grid (seeds 2000000-2000007, :data:`EVAL_HISTORY_SEEDS`), a prior
that does not know the fixed map of the day, so that the drones' sightings are what corrects
it. Reported per variant: R_hat_T and the belief error of the swarm's nowcast (its filter
fed by its own sightings; :func:`twin.belief.belief_table`), each paired difference
(nowcast - paper) with its Student-t 95% interval over the evaluation seeds, per training
seed, and over the training seeds (each one's mean over the evaluation seeds: the unit that
carries the training's randomness). Nothing is tuned here.

    nice -n 10 python benchmarks/nowcast_state.py [--out runs/nowcast-state] [--train-seeds 0 1 2]

A finished variant's folder is reused when its provenance matches.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import pandas as pd

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from twin.belief import belief_table  # noqa: E402
from twin.config import load_config, make_grid, shipped_config, with_overrides  # noqa: E402
from twin.experiment import Experiment, run_experiment  # noqa: E402
from twin.metrics import ci95_halfwidth, table2  # noqa: E402
from twin.traffic.dynamic import dynamics_history  # noqa: E402
from twin.training.pretrain import PretrainConfig, pretrain  # noqa: E402
from twin.transfer.runner import provenance_mismatch  # noqa: E402

#: The pretraining keys shared by both variants (a small budget: 20000 updates of batch 32).
SCHEDULE = {
    "seed": 0,
    "traffic": "dynamics",
    "scenario_overrides": {"traffic.horizon": 500},
    "episodes": 20,
    "epochs": 20000,
    "iters_per_epoch": 1,
    "batch_size": 32,
    "lr": 2e-4,
    "gamma": 0.9,
    "target_update_epochs": 500,
    "log_every": 1000,
    "checkpoint_every": 5000,
    "history_days": 8,
    "history_seed": 1_000_000,
}
#: Hidden layers of both networks (the first layer is the state's size).
HIDDEN = [256, 64]
VARIANTS = ("paper", "nowcast")
HORIZON = 500
SEEDS = range(0, 6)
#: Training seeds: each trains both variants (the seed of the data, the network and batches).
TRAIN_SEEDS = (0, 1, 2)
COLUMNS = ("R_hat_T", "belief_error")
EVAL_HISTORY_SEEDS = range(2_000_000, 2_000_008)


def train(out: Path, seed: int) -> tuple[dict[str, Path], dict[str, float]]:
    """Both variants' networks of training seed ``seed`` (reused when already trained)."""
    from twin.states import STATE_VARIANTS

    checkpoints, walls = {}, {}
    for state in VARIANTS:
        folder = out / f"train-seed-{seed}" / state
        layers = [STATE_VARIANTS[state].size, *HIDDEN, 5]
        cfg = PretrainConfig(**{**SCHEDULE, "seed": seed}, state=state, layers=layers,
                             out=str(folder))  # fmt: skip
        if provenance_mismatch(folder, cfg) is not None:
            pretrain(cfg, progress=False)
        record = json.loads((folder / "provenance.json").read_text())
        walls[state] = record["wall_s"] + (record.get("collect_s") or 0.0)
        checkpoints[state] = folder / "qnet.pt"
        print(f"training seed {seed}, {state}: trained in {walls[state]:.0f} s", flush=True)
    return checkpoints, walls


def evaluate(checkpoints: dict[str, Path], config, history) -> pd.DataFrame:
    """R_hat_T and the nowcast's belief error of each variant's ``rl`` per evaluation seed."""
    swarms = [f"rl@{s}" for s in VARIANTS]
    options = {f"rl@{s}": {"checkpoint": checkpoints[s], "history": history} for s in VARIANTS}
    outcome = run_experiment(Experiment(config, swarms=swarms, seeds=SEEDS,
                                        swarm_options=options))  # fmt: skip
    rows = []
    for result in outcome.results:
        scores = table2(result, config.params).set_index("swarm")
        beliefs = belief_table(result, history)
        nowcast = beliefs[beliefs.model == "nowcast"].set_index("swarm")
        for swarm in swarms:
            rows.append({"seed": result.seed, "state": swarm.split("@")[1],
                         "R_hat_T": float(scores.loc[swarm, "R_hat_T"]),
                         "belief_error": float(nowcast.loc[swarm, "belief_error"])})  # fmt: skip
    return pd.DataFrame(rows)


def paired(frame: pd.DataFrame, column: str) -> dict[str, list[float]]:
    """Each variant's mean and 95% half-width, and nowcast - paper paired over the rows."""
    wide = frame.pivot(index="seed", columns="state", values=column)
    a, b = wide["nowcast"].to_numpy(), wide["paper"].to_numpy()
    return {"paper": [float(b.mean()), ci95_halfwidth(b)],
            "nowcast": [float(a.mean()), ci95_halfwidth(a)],
            "nowcast_minus_paper": [float((a - b).mean()), ci95_halfwidth(a - b)],
            "n": [len(a)]}  # fmt: skip


def line(label: str, column: str, entry: dict[str, list[float]]) -> str:
    (pm, ph), (nm, nh), (dm, dh) = (entry[k] for k in ("paper", "nowcast",
                                                       "nowcast_minus_paper"))  # fmt: skip
    return (f"{label:22s} {column:13s} paper {pm:.4f} ± {ph:.4f}   nowcast {nm:.4f} ± "
            f"{nh:.4f}   nowcast - paper {dm:+.4f} ± {dh:.4f} (95%, n = {entry['n'][0]})")  # fmt: skip


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, default=ROOT / "runs" / "nowcast-state")
    parser.add_argument("--train-seeds", type=int, nargs="+", default=list(TRAIN_SEEDS))
    args = parser.parse_args(argv)
    config = with_overrides(load_config(shipped_config("synthetic")),
                            {"traffic.horizon": HORIZON}, {})  # fmt: skip
    history = dynamics_history(make_grid(config), HORIZON, EVAL_HISTORY_SEEDS)
    frames, summary = [], {"schedule": SCHEDULE, "hidden": HIDDEN, "horizon": HORIZON,
                           "seeds": list(SEEDS), "eval_history_seeds": list(EVAL_HISTORY_SEEDS),
                           "train_seeds": args.train_seeds, "wall_s": {}, "results": {}}  # fmt: skip
    for seed in args.train_seeds:
        checkpoints, walls = train(args.out, seed)
        start = time.perf_counter()
        frame = evaluate(checkpoints, config, history).assign(train_seed=seed)
        print(f"evaluated in {time.perf_counter() - start:.0f} s", flush=True)
        frames.append(frame)
        summary["wall_s"][seed] = walls
        for column in COLUMNS:
            entry = paired(frame, column)
            summary["results"][f"train seed {seed} {column}"] = entry
            print(line(f"training seed {seed}", column, entry), flush=True)
    per_seed = pd.concat(frames, ignore_index=True)
    args.out.mkdir(parents=True, exist_ok=True)
    per_seed.to_csv(args.out / "per_seed.csv", index=False)
    if len(args.train_seeds) > 1:  # the unit: a training seed (its mean over evaluation seeds)
        means = per_seed.groupby(["train_seed", "state"], as_index=False)[list(COLUMNS)].mean()
        for column in COLUMNS:
            entry = paired(means.rename(columns={"train_seed": "seed"}), column)
            summary["results"][f"over training seeds {column}"] = entry
            print(line("over training seeds", column, entry))
    (args.out / "summary.json").write_text(json.dumps(summary, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
