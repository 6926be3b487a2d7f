"""Table 2 columns and their aggregation over seeds.

- ``R_hat_T``: mean of ``R^k`` over the horizon (Def. 4);
- ``C_hat_T``: mean of ``C^k`` (Def. 5);
- ``pct_time_max_C``: share of steps at which a swarm has the highest ``C^k`` among the swarms
  run side by side (ties count for each tied swarm), in percent;
- ``pct_map_covered``: share of free cells a drone stood on at least once, in percent.
"""

from __future__ import annotations

import numpy as np
import pandas as pd
from scipy import stats

from twin.patrol import PatrolResult

TABLE2_COLUMNS = ("R_hat_T", "C_hat_T", "pct_time_max_C", "pct_map_covered")
TABLE2_HEADERS = {
    "R_hat_T": "R_hat_T",
    "C_hat_T": "C_hat_T",
    "pct_time_max_C": "% time max C^k",
    "pct_map_covered": "% map covered",
}


def table2(result: PatrolResult) -> pd.DataFrame:
    """One row per swarm with the Table 2 columns of one run."""
    cov = result.coverage
    if cov.shape[1]:
        best = cov >= cov.max(axis=0, keepdims=True) - 1e-12
        pct_max = 100.0 * best.mean(axis=1)
        final_visit = 100.0 * result.visited_share[:, -1]
    else:
        pct_max = final_visit = np.full(len(result.swarms), np.nan)
    return pd.DataFrame(
        {
            "swarm": result.swarms,
            "R_hat_T": result.rewards.mean(axis=1) if cov.shape[1] else np.nan,
            "C_hat_T": cov.mean(axis=1) if cov.shape[1] else np.nan,
            "pct_time_max_C": pct_max,
            "pct_map_covered": final_visit,
        }
    )


def ci95_halfwidth(values: np.ndarray) -> float:
    """Half-width of the Student-t 95% interval of the mean (0 for a single value)."""
    values = np.asarray(values, dtype=float)
    n = len(values)
    if n < 2:
        return 0.0
    return float(stats.t.ppf(0.975, n - 1) * values.std(ddof=1) / np.sqrt(n))


def aggregate(per_seed: pd.DataFrame, by: str | list[str] = "swarm") -> pd.DataFrame:
    """Mean, 95% half-width and seed count of the Table 2 columns, grouped by ``by``."""
    keys = [by] if isinstance(by, str) else list(by)
    rows = []
    for key, group in per_seed.groupby(keys, sort=False):
        key = key if isinstance(key, tuple) else (key,)
        row = dict(zip(keys, key, strict=True))
        for col in TABLE2_COLUMNS:
            row[col] = group[col].mean()
            row[f"{col}_ci95"] = ci95_halfwidth(group[col].to_numpy())
        row["n_seeds"] = len(group)
        rows.append(row)
    return pd.DataFrame(rows)


def format_table2(summary: pd.DataFrame) -> str:
    """The Table 2 analog as aligned text, with ``± half-width`` when several seeds."""
    several = "n_seeds" in summary and (summary["n_seeds"] > 1).any()
    digits = {"R_hat_T": 3, "C_hat_T": 3, "pct_time_max_C": 2, "pct_map_covered": 1}
    header = ["swarm"] + [TABLE2_HEADERS[c] for c in TABLE2_COLUMNS]
    lines = [header]
    for _, row in summary.iterrows():
        cells = [str(row["swarm"])]
        for col in TABLE2_COLUMNS:
            text = f"{row[col]:.{digits[col]}f}"
            if several:
                text += f" ± {row[f'{col}_ci95']:.{digits[col]}f}"
            cells.append(text)
        lines.append(cells)
    widths = [max(len(line[c]) for line in lines) for c in range(len(header))]
    out = []
    for n, line in enumerate(lines):
        out.append(
            "  ".join(
                cell.rjust(w) if c else cell.ljust(w)
                for c, (cell, w) in enumerate(zip(line, widths, strict=True))
            )
        )
        if n == 0:
            out.append("  ".join("-" * w for w in widths))
    return "\n".join(out)


def paired_difference(per_seed: pd.DataFrame, a: str, b: str, column: str = "R_hat_T") -> dict:
    """``a - b`` of ``column`` paired over the seeds both swarms ran: mean, 95% half-width,
    the ratio of the means and the number of seeds."""
    rows = per_seed.pivot_table(index="seed", columns="swarm", values=column, aggfunc="first")
    both = rows[[a, b]].dropna()
    diff = (both[a] - both[b]).to_numpy()
    return {
        "swarm": a,
        "against": b,
        "column": column,
        "difference": float(diff.mean()) if len(diff) else float("nan"),
        "difference_ci95": ci95_halfwidth(diff),
        "ratio": float(both[a].mean() / both[b].mean()) if len(diff) else float("nan"),
        "n_seeds": len(diff),
    }


def learned_against_best_classical(per_seed: pd.DataFrame, column: str = "R_hat_T"):
    """Each learned swarm against the classical swarm with the highest mean ``column``, paired
    over seeds (empty when the run has no learned or no classical swarm)."""
    from twin.policies import is_learned

    means = per_seed.groupby("swarm", sort=False)[column].mean()
    classical = [s for s in means.index if not is_learned(s)]
    learned = [s for s in means.index if is_learned(s)]
    if not classical or not learned:
        return pd.DataFrame()
    best = max(classical, key=lambda s: means[s])
    return pd.DataFrame([paired_difference(per_seed, s, best, column) for s in learned])


def format_comparison(comparison: pd.DataFrame) -> str:
    """One line per learned swarm: its paired difference to the best classical swarm."""
    lines = []
    for _, row in comparison.iterrows():
        ci = (
            f" ± {row['difference_ci95']:.3f} (95% interval over {row['n_seeds']} seeds)"
            if row["n_seeds"] > 1
            else " (one seed: no interval)"
        )
        lines.append(
            f"{row['swarm']} - {row['against']} (best classical): {row['column']} "
            f"{row['difference']:+.3f}{ci}, ratio {row['ratio']:.3f}"
        )
    return "\n".join(lines)
