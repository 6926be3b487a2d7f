"""How ``tours``'s defaults were chosen: R_hat_T of candidate settings on
``configs/synthetic.toml``, validation seeds 100-109 (never the evaluation seeds 0-9), each
paired with ``visit-gain`` on the same starts and traffic (mean ± 95% interval of the per-seed
ratio); the defaults are the setting with the largest mean ratio, ties (within 0.002) going to
the one whose step counts derive from eta and delta.

    python benchmarks/validate_tours.py [--seeds 100-109] [NAME ...]

Without names it runs every candidate of ``CANDIDATES`` (about 30 s each on the shared 2-core
machine).
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from twin.config import load_config, start_positions, synthetic_source  # noqa: E402
from twin.metrics import ci95_halfwidth  # noqa: E402
from twin.patrol import run_patrol  # noqa: E402
from twin.swarms import make_policy  # noqa: E402
from twin.traffic.base import RecordedTraffic  # noqa: E402

CONFIG = ROOT / "configs" / "synthetic.toml"
SURVEY = {"survey": True, "prior": 0.0, "memory": None}
#: name -> tours options (the defaults: "explore 37 prior 0.25 memory 300").
CANDIDATES = {
    "survey stretch 0.95": {**SURVEY, "stretch": 0.95},
    "survey stretch 1.0": {**SURVEY, "stretch": 1.0},
    "survey stretch 1.05": {**SURVEY, "stretch": 1.05},
    "survey stretch 1.1": {**SURVEY, "stretch": 1.1},
    "survey per_tour 1": {**SURVEY, "per_tour": 1},
    "survey after 20 steps": {**SURVEY, "explore": 20},
    "survey after 37 steps": {**SURVEY, "explore": 37},
    "survey walks": {**SURVEY, "layout": "walks", "stretch": 1.05},
    "explore 37 prior 0.1 memory 300": {"prior": 0.1, "memory": 300},
    "explore 37 prior 0.2 memory 600": {"prior": 0.2, "memory": 600},
    "explore 37 prior 0.25 memory 300": {"prior": 0.25, "memory": 300},
    "explore 37 prior 0.25 memory 600": {"prior": 0.25, "memory": 600},
    "explore 37 prior 0.25 no memory": {"prior": 0.25, "memory": None},
    "explore 20 prior 0.25 memory 300": {"prior": 0.25, "memory": 300, "explore": 20},
    "explore 20 prior 0.25 memory 600": {"prior": 0.25, "memory": 600, "explore": 20},
    "explore 74 prior 0.25 memory 300": {"prior": 0.25, "memory": 300, "explore": 74},
    "explore 37 prior 0.4 memory 300": {"prior": 0.4, "memory": 300},
    "explore 37 walks": {"layout": "walks", "stretch": 1.05, "shift": 0.2},
}


def seed_range(text: str) -> list[int]:
    first, _, last = text.partition("-")
    return list(range(int(first), int(last or first) + 1))


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seeds", default="100-109")
    parser.add_argument("names", nargs="*", help="candidates to run (default: all)")
    args = parser.parse_args(argv)
    unknown = [n for n in args.names if n not in CANDIDATES]
    if unknown:
        print(f"validate_tours: unknown candidate {unknown[0]!r}; see CANDIDATES", file=sys.stderr)
        return 2
    config = load_config(CONFIG)
    source = RecordedTraffic.from_source(synthetic_source(config))
    seeds = seed_range(args.seeds)

    def score(name: str, options: dict, seed: int) -> float:
        starts = start_positions(config, source.grid, np.random.default_rng(seed))
        swarm = {name: make_policy(name, **options)}
        result = run_patrol(source, swarm, starts, config.params, seed, keep_importance=False)
        return float(result.rewards[0].mean())

    base = np.array([score("visit-gain", {}, s) for s in seeds])
    print(f"visit-gain: mean {base.mean():.4f} ± {ci95_halfwidth(base):.4f}", flush=True)
    for name in args.names or CANDIDATES:
        vals = np.array([score("tours", CANDIDATES[name], s) for s in seeds])
        ratio = vals / base
        print(
            f"{name}: mean {vals.mean():.4f} ± {ci95_halfwidth(vals):.4f}, "
            f"ratio {ratio.mean():.4f} ± {ci95_halfwidth(ratio):.4f}, "
            f"worst seed {vals.min():.3f}",
            flush=True,
        )
    return 0


if __name__ == "__main__":
    sys.exit(main())
