"""Print docs/faults.md's tables from the run folder of
``twin evaluate --config configs/drone-loss.toml --seeds 3 --ceiling --out RUN``.

Usage: ``python docs/make_faults.py RUN`` (Markdown on stdout).
"""

from __future__ import annotations

import sys

from twin.report.document import (
    DEGRADATION_HEADER,
    degradation_rows,
    markdown_table,
)
from twin.report.load import load_run


def score_table(rf) -> str:
    """R_hat per phase, with the faults / fault-free (change %), one row per swarm."""
    frame = rf.degradation
    keys = ["swarm", "phase", "label", "start", "stop"]
    means = frame.groupby(keys, sort=False).mean(numeric_only=True).reset_index()
    phases = means.drop_duplicates("phase")[["phase", "label", "start", "stop"]]
    header = ["swarm"] + [f"{r.label} (k = {r.start}–{r.stop})" for r in phases.itertuples()]
    rows = []
    for swarm, part in means.groupby("swarm", sort=False):
        row = [swarm]
        for r in part.itertuples():
            change = 100.0 * (r.R_hat - r.R_hat_fault_free) / r.R_hat_fault_free
            row.append(f"{r.R_hat:.3f} / {r.R_hat_fault_free:.3f} ({change:+.1f}%)")
        rows.append(row)
    return markdown_table(header, rows)


def oracle_line(rf) -> str:
    summary = rf.summary.set_index("swarm")
    if "oracle (ceiling)" not in summary.index:
        return ""
    swarms = summary[summary["role"] == "swarm"]["R_hat_T"]
    best = swarms.idxmax()
    return (
        f"Under the same faults the oracle (ceiling) scores R_hat_T = "
        f"{summary.loc['oracle (ceiling)', 'R_hat_T']:.3f} over the whole run, the best swarm "
        f"({best}) {swarms.max():.3f}."
    )


def main(run_dir: str) -> None:
    rf = load_run(run_dir)
    seeds = sorted(set(rf.degradation["seed"].tolist()))
    print(f"Seeds {', '.join(map(str, seeds))}; command: `{rf.run.get('command')}`.\n")
    print(score_table(rf))
    print()
    print(oracle_line(rf))
    print()
    print(markdown_table(DEGRADATION_HEADER, degradation_rows(rf)))


if __name__ == "__main__":
    main(sys.argv[1])
