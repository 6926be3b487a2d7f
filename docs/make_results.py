"""Write docs/results.md from run folders, so the published results cannot drift from the code.

    python docs/make_results.py --synthetic RUN_DIR --shenzhen RUN_DIR [--city RUN_DIR] \
        [--out docs/results.md]

Each RUN_DIR is the folder of the command printed in its section (``run.json`` holds it). Every
figure on the page is read from the folder's ``summary.csv`` and ``per_seed.csv``; every claim
that one swarm beats another is a paired difference over the run's seeds with its 95% interval
(:func:`twin.metrics.paired_difference`), against the strongest swarm the run has.
"""

from __future__ import annotations

import argparse
import json
import re
import sys
from pathlib import Path

import pandas as pd

from twin.metrics import paired_difference
from twin.swarms import is_learned

#: the repository: a config given by its absolute path is shown relative to it
ROOT = Path(__file__).resolve().parents[1]

#: (column, header, decimals, with interval) of the results tables.
COLUMNS = (
    ("R_hat_T", "R_hat_T", 3, True),
    ("R_hat_T_importance", "R importance", 3, False),
    ("R_hat_T_idleness", "R idleness", 3, False),
    ("R_hat_T_paper", "R paper (gameable)", 3, False),
    ("C_hat_T", "C_hat_T", 3, False),
    ("pct_map_covered", "% map covered", 1, False),
    ("belief_error", "belief error", 3, True),
    ("pct_events_seen", "% events seen", 1, True),
)

SECTIONS = {
    "synthetic": "The synthetic case study (Sec. IV-A)",
    "shenzhen": "The Shenzhen-like twin in rush hour (Sec. IV-B)",
    "city": "City scale: 200 drones on 100 m cells",
}


def ceiling_rows(summary: pd.DataFrame) -> set[str]:
    """The rows that are ceilings (an oracle, an upper bound), not swarms."""
    if "role" not in summary.columns:
        return set()
    return set(summary.loc[summary["role"] == "ceiling", "swarm"])


def _label(swarm: str, ceilings: set[str]) -> str:
    if swarm not in ceilings:
        return swarm
    return f"*{swarm}*" if "ceiling" in swarm else f"*{swarm} (ceiling)*"


def _cell(row: pd.Series, column: str, digits: int, interval: bool, several: bool) -> str:
    if column not in row or pd.isna(row[column]):
        return "-"
    text = f"{row[column]:.{digits}f}"
    ci = row.get(f"{column}_ci95")
    if interval and several and ci is not None and not pd.isna(ci):
        text += f" ± {ci:.{digits}f}"
    return text


def _difference(d: dict) -> str:
    if d["n_seeds"] < 2:
        return f"{d['difference']:+.3f} (one seed: no interval)"
    return f"**{d['difference']:+.3f} ± {d['difference_ci95']:.3f}**"


def section(name: str, run_dir: Path) -> str:
    """One scenario: its command, the table, and the plain sentences of who wins by how much."""
    meta = json.loads((run_dir / "run.json").read_text())
    summary = pd.read_csv(run_dir / "summary.csv")
    per_seed = pd.read_csv(run_dir / "per_seed.csv")
    seeds = sorted(per_seed["seed"].unique().tolist())
    several = len(seeds) > 1
    lines = [
        f"## {SECTIONS[name]}",
        "",
        "```bash",
        # where it was written and what it printed are not the recipe
        re.sub(r" --out \S+| --quiet| --no-report", "", meta["command"]).replace(f"{ROOT}/", ""),
        "```",
        "",
        f"Seeds {seeds[0]}-{seeds[-1]} ({len(seeds)}); {meta.get('horizon')} steps; "
        f"{meta.get('n_drones')} drones; {meta.get('wall_seconds', 0):.0f} s on the 2-core "
        f"machine. Mean ± 95% interval over seeds. Rows in italics are ceilings, not swarms.",
        "",
    ]
    present = [c for c in COLUMNS if c[0] in summary.columns and summary[c[0]].notna().any()]
    lines.append("| swarm | " + " | ".join(h for _, h, _, _ in present) + " |")
    lines.append("|---" * (len(present) + 1) + "|")
    ceilings = ceiling_rows(summary)
    for _, row in summary.iterrows():
        label = _label(row["swarm"], ceilings)
        cells = [_cell(row, c, d, i, several) for c, _, d, i in present]
        lines.append(f"| {label} | " + " | ".join(cells) + " |")
    lines += ["", *claims(summary, per_seed), ""]
    return "\n".join(lines)


def claims(summary: pd.DataFrame, per_seed: pd.DataFrame) -> list[str]:
    """Which swarm wins and by how much (paired over seeds), where the learned swarm stands
    against the best classical swarm, and how far the ceilings lie above."""
    means = summary.set_index("swarm")["R_hat_T"]
    ceilings = ceiling_rows(summary)
    swarms = [s for s in means.index if s not in ceilings]
    ranked = sorted(swarms, key=lambda s: -means[s])
    out = []
    if len(ranked) >= 2:
        best, second = ranked[0], ranked[1]
        d = paired_difference(per_seed, best, second)
        out.append(
            f"- **Which swarm wins:** `{best}`, ahead of `{second}` by {_difference(d)} R_hat_T "
            f"(paired over {d['n_seeds']} seeds; ratio {d['ratio']:.3f})."
        )
    classical = [s for s in ranked if not is_learned(s)]
    learned = [s for s in ranked if is_learned(s)]
    if classical and learned:
        top = classical[0]
        for s in learned:
            d = paired_difference(per_seed, s, top)
            out.append(
                f"- `{s}` against the best classical swarm `{top}`: {_difference(d)} "
                f"(ratio {d['ratio']:.3f})."
            )
    for ceiling in sorted(ceilings):
        if ranked:
            gap = means[ceiling] / means[ranked[0]]
            out.append(
                f"- `{ceiling}` lies at {means[ceiling]:.3f}: the best swarm `{ranked[0]}` "
                f"reaches {1 / gap:.1%} of it ({gap:.3f} x)."
            )
    return out


HEADER = """# Results

Generated by `python docs/make_results.py` from the run folders of the commands shown; do not
edit by hand. The score is the project's headline score (each visited cell's gain paid once;
see docs/model.md). "R paper (gameable)" is Def. 4 as printed, which pays drones with
overlapping views several times for one visit: it is shown for comparison with the paper and
ranks nothing. With alpha_I = 0.5 the idleness part is about two thirds of a good swarm's score,
so a swarm scores well by visiting fresh cells whatever their importance; the monitoring
columns (belief error against the true map, share of congestion events seen) say how well a
swarm watches the traffic.
"""


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    for name in SECTIONS:
        parser.add_argument(f"--{name}", type=Path, help=f"run folder of the {name} results")
    parser.add_argument("--out", type=Path, default=Path(__file__).with_name("results.md"))
    args = parser.parse_args(argv)
    parts = [HEADER]
    for name in SECTIONS:
        run_dir = getattr(args, name)
        if run_dir is None:
            continue
        if not (run_dir / "manifest.json").is_file():
            print(f"make_results: {run_dir} is not a complete run folder", file=sys.stderr)
            return 2
        parts.append(section(name, run_dir))
    args.out.write_text("\n".join(parts))
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
