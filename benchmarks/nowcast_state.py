"""The ``nowcast`` state variant against the paper's 13 values, at one small budget.

Both variants are pretrained with the same schedule and seed (:data:`SCHEDULE`: the dynamic
training traffic, whose days differ, so that the nowcast's history has a spread; the
``nowcast`` run's history is that generator's days 1000000-1000007, apart from the training
episodes' seeds 0-19), then the coordinated learned swarm ``rl`` of each runs on
configs/synthetic.toml at T = :data:`HORIZON` over the evaluation seeds :data:`SEEDS`, paired
(same traffic, same starts). Both read the same history of the synthetic map: 8 days of the
dynamic generator on its grid (seeds 2000000-2000007, :data:`EVAL_HISTORY_SEEDS`), a prior
that does not know the fixed map of the day, so that the drones' sightings are what corrects
it. Reported per variant: R_hat_T and the belief error of the swarm's nowcast (its filter
fed by its own sightings; :func:`twin.belief.belief_table`), each paired difference
(nowcast - paper) with its Student-t 95% interval over the seeds. Nothing is tuned here.

    nice -n 10 python benchmarks/nowcast_state.py [--out runs/nowcast-state]

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

from twin.belief import belief_table, dynamics_history  # noqa: E402
from twin.config import load_config, make_grid, shipped_config, with_overrides  # noqa: E402
from twin.experiment import Experiment, run_experiment  # noqa: E402
from twin.metrics import ci95_halfwidth, table2  # noqa: E402
from twin.training.pretrain import PretrainConfig, pretrain  # noqa: E402
from twin.transfer.runner import provenance_matches  # noqa: E402

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
EVAL_HISTORY_SEEDS = range(2_000_000, 2_000_008)


def main(argv: list[str] | None = None) -> int:
    from twin.states import STATE_VARIANTS

    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, default=ROOT / "runs" / "nowcast-state")
    args = parser.parse_args(argv)
    checkpoints, walls = {}, {}
    for state in VARIANTS:
        out = args.out / state
        layers = [STATE_VARIANTS[state].size, *HIDDEN, 5]
        cfg = PretrainConfig(**SCHEDULE, state=state, layers=layers, out=str(out))
        if not provenance_matches(out, cfg):
            pretrain(cfg, progress=False)
        record = json.loads((out / "provenance.json").read_text())
        walls[state] = record["wall_s"] + (record.get("collect_s") or 0.0)
        checkpoints[state] = out / "qnet.pt"
        print(f"{state}: trained in {walls[state]:.0f} s", flush=True)

    config = with_overrides(load_config(shipped_config("synthetic")),
                            {"traffic.horizon": HORIZON}, {})  # fmt: skip
    history = dynamics_history(make_grid(config), HORIZON, EVAL_HISTORY_SEEDS)
    swarms = [f"rl@{s}" for s in VARIANTS]
    options = {f"rl@{s}": {"checkpoint": checkpoints[s], "history": history} for s in VARIANTS}
    start = time.perf_counter()
    outcome = run_experiment(Experiment(config, swarms=swarms, seeds=SEEDS,
                                        swarm_options=options))  # fmt: skip
    rows = []
    for result in outcome.results:
        scores = table2(result, config.params).set_index("swarm")
        beliefs = belief_table(result, history)
        nowcast = beliefs[beliefs.model == "nowcast"].set_index("swarm")
        for swarm in swarms:
            rows.append({"seed": result.seed, "swarm": swarm,
                         "R_hat_T": float(scores.loc[swarm, "R_hat_T"]),
                         "belief_error": float(nowcast.loc[swarm, "belief_error"])})  # fmt: skip
    per_seed = pd.DataFrame(rows)
    args.out.mkdir(parents=True, exist_ok=True)
    per_seed.to_csv(args.out / "per_seed.csv", index=False)
    print(f"evaluated in {time.perf_counter() - start:.0f} s; configs/synthetic.toml, T = "
          f"{HORIZON}, seeds {SEEDS.start}-{SEEDS.stop - 1}")  # fmt: skip
    summary = {"schedule": SCHEDULE, "hidden": HIDDEN, "horizon": HORIZON,
               "seeds": list(SEEDS), "eval_history_seeds": list(EVAL_HISTORY_SEEDS),
               "wall_s": walls, "columns": {}}  # fmt: skip
    for column in ("R_hat_T", "belief_error"):
        wide = per_seed.pivot(index="seed", columns="swarm", values=column)
        a, b = wide["rl@nowcast"].to_numpy(), wide["rl@paper"].to_numpy()
        diff = a - b
        entry = {
            "paper": [float(b.mean()), ci95_halfwidth(b)],
            "nowcast": [float(a.mean()), ci95_halfwidth(a)],
            "nowcast_minus_paper": [float(diff.mean()), ci95_halfwidth(diff)],
        }
        summary["columns"][column] = entry
        print(f"{column:13s} paper {b.mean():.4f} ± {ci95_halfwidth(b):.4f}   nowcast "
              f"{a.mean():.4f} ± {ci95_halfwidth(a):.4f}   nowcast - paper "
              f"{diff.mean():+.4f} ± {ci95_halfwidth(diff):.4f} (95%, {len(diff)} seeds)")  # fmt: skip
    (args.out / "summary.json").write_text(json.dumps(summary, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
