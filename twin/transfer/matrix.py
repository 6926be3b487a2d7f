"""The transfer matrix from the evaluation sweep's per-seed results: one line per (row, learned
swarm, column).

Each line: the learned swarm's R_hat_T minus the best classical swarm's on the same traffic
(the classical swarm with the highest mean R_hat_T over the column's seeds), paired over the
seeds, with the 95% interval (:func:`twin.metrics.paired_difference`); the share of the gap
between that swarm and each ceiling (oracle, bound; :mod:`twin.ceilings`) that the learned
swarm closes, ``(R_learned - R_best) / (R_ceiling - R_best)`` of the means (negative: it
widens the gap); and the monitoring columns (:mod:`twin.monitoring`) of both swarms.
"""

from __future__ import annotations

import numpy as np
import pandas as pd

from twin.metrics import BOUND, ORACLE, paired_difference

MATRIX_COLUMNS = (
    "trained_on", "swarm", "evaluated_on", "best_classical", "R_learned", "R_best_classical",
    "difference", "difference_ci95", "n_seeds", "seeds", "R_oracle", "R_bound",
    "gap_closed_oracle", "gap_closed_bound", "pct_events_seen", "best_pct_events_seen",
    "latency_median_steps", "best_latency_median_steps",
)  # fmt: skip


def best_classical(per_seed: pd.DataFrame, classical: list[str]) -> str | None:
    """The classical swarm with the highest mean R_hat_T on this column (None if none ran)."""
    means = per_seed[per_seed["swarm"].isin(classical)].groupby("swarm")["R_hat_T"].mean()
    return None if means.empty else str(means.idxmax())


def _mean(per_seed: pd.DataFrame, swarm: str, column: str) -> float:
    if column not in per_seed.columns:
        return float("nan")
    values = pd.to_numeric(per_seed.loc[per_seed["swarm"] == swarm, column], errors="coerce")
    return float(values.mean()) if values.notna().any() else float("nan")


def _share(learned: float, best: float, ceiling: float) -> float:
    gap = ceiling - best
    return float((learned - best) / gap) if np.isfinite(gap) and gap > 1e-12 else float("nan")


def transfer_matrix(results: pd.DataFrame, config) -> pd.DataFrame:
    """The matrix of ``config`` (:class:`~twin.transfer.config.TransferConfig`) from the
    sweep's ``results.csv`` (one row per cell and swarm)."""
    lines = []
    for column in config.column:
        per_seed = results[results["scenario"] == column.name]
        best = best_classical(per_seed, config.transfer.classical)
        r_best = _mean(per_seed, best, "R_hat_T") if best else float("nan")
        r_oracle, r_bound = _mean(per_seed, ORACLE, "R_hat_T"), _mean(per_seed, BOUND, "R_hat_T")
        for swarm, row, _kind in config.learned_swarms():
            if best is None or not (per_seed["swarm"] == swarm).any():
                continue
            paired = paired_difference(per_seed, swarm, best)
            r_learned = _mean(per_seed, swarm, "R_hat_T")
            seeds = sorted(per_seed.loc[per_seed["swarm"] == swarm, "seed"].astype(int).tolist())
            lines.append(
                {
                    "trained_on": row,
                    "swarm": swarm,
                    "evaluated_on": column.name,
                    "best_classical": best,
                    "R_learned": r_learned,
                    "R_best_classical": r_best,
                    "difference": paired["difference"],
                    # no interval from one seed (ci95_halfwidth's 0 would read as certainty)
                    "difference_ci95": paired["difference_ci95"]
                    if paired["n_seeds"] >= 2
                    else float("nan"),
                    "n_seeds": paired["n_seeds"],
                    "seeds": " ".join(map(str, seeds)),
                    "R_oracle": r_oracle,
                    "R_bound": r_bound,
                    "gap_closed_oracle": _share(r_learned, r_best, r_oracle),
                    "gap_closed_bound": _share(r_learned, r_best, r_bound),
                    "pct_events_seen": _mean(per_seed, swarm, "pct_events_seen"),
                    "best_pct_events_seen": _mean(per_seed, best, "pct_events_seen"),
                    "latency_median_steps": _mean(per_seed, swarm, "latency_median_steps"),
                    "best_latency_median_steps": _mean(per_seed, best, "latency_median_steps"),
                }
            )
    return pd.DataFrame(lines, columns=list(MATRIX_COLUMNS))


def format_matrix(matrix: pd.DataFrame) -> str:
    """The matrix as a Markdown table (README, docs, the terminal)."""
    head = (
        "| trained on | swarm | evaluated on | best classical | learned - best (95% CI) | "
        "gap to oracle closed | events seen % (best) | median latency, steps (best) |\n"
        "|---|---|---|---|---|---|---|---|\n"
    )
    lines = []
    for r in matrix.itertuples(index=False):
        lines.append(
            f"| {r.trained_on} | {r.swarm.split('@')[0]} | {r.evaluated_on} | {r.best_classical} "
            f"| {interval_text(r.difference, r.difference_ci95)} | {_pct(r.gap_closed_oracle)} "
            f"| {_num(r.pct_events_seen, 0)} ({_num(r.best_pct_events_seen, 0)}) "
            f"| {_num(r.latency_median_steps, 1)} ({_num(r.best_latency_median_steps, 1)}) |"
        )
    return head + "\n".join(lines)


def interval_text(difference: float, ci95: float, digits: int = 3) -> str:
    """``+0.123 ± 0.045``, or ``+0.123 (one seed: no interval)`` when there is no interval."""
    if not np.isfinite(ci95):
        return f"{difference:+.{digits}f} (one seed: no interval)"
    return f"{difference:+.{digits}f} ± {ci95:.{digits}f}"


def _num(value: float, digits: int) -> str:
    return "n/a" if not np.isfinite(value) else f"{value:.{digits}f}"


def _pct(value: float) -> str:
    return "n/a" if not np.isfinite(value) else f"{100 * value:+.0f}%"


def verdict(matrix: pd.DataFrame) -> str:
    """One plain sentence: does any learned swarm beat the best classical swarm anywhere (its
    whole 95% interval above zero, over at least 2 seeds)?"""
    if matrix.empty:
        return "The matrix is empty."
    interval = (matrix["n_seeds"] >= 2) & (matrix["difference"] - matrix["difference_ci95"] > 0)
    wins = matrix[interval]
    if wins.empty:
        best = matrix.loc[matrix["difference"].idxmax()]
        return (
            "No learned swarm beats the best classical swarm in any cell (95% interval above "
            "zero); the closest is "
            f"{best['swarm']} on {best['evaluated_on']}, "
            f"{interval_text(best['difference'], best['difference_ci95'])}."
        )
    parts = [
        f"{w.swarm} on {w.evaluated_on} ({w.difference:+.3f} ± {w.difference_ci95:.3f}, "
        f"{_pct(w.gap_closed_oracle)} of the gap to the oracle)"
        for w in wins.itertuples(index=False)
    ]
    return "A learned swarm beats the best classical swarm in: " + "; ".join(parts) + "."
