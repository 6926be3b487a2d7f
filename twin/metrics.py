"""Table 2 columns, the monitoring columns, and their aggregation over seeds.

Table 2 analog (one row per swarm and run):

- ``R_hat_T``: mean of ``R^k`` over the horizon, the headline score: every distinct visited
  cell paid its visit gain once (:func:`twin.scores.rewards_on_arrival`);
  ``R_hat_T_importance`` and ``R_hat_T_idleness`` its alpha_T and alpha_I parts (they add up to
  ``R_hat_T``); ``R_hat_T_paper`` Def. 4 as printed, every drone paid its field of view: gameable
  by overlapping views and stacking, kept for comparison with the paper;
- ``C_hat_T``: mean of ``C^k`` (Def. 5); ``C_hat_T_ceiling`` the same for drones that jump
  each step to the N freshest distinct cells (:func:`twin.monitoring.ceiling_coverage`): a
  reference, not a bound (pacing revisits can exceed it slightly), so a value near it shows the
  swarm neither stacks nor hovers, not more;
- ``pct_time_max_C``: share of steps at which a swarm has the highest ``C^k`` among the swarms
  run side by side (ties count for each tied swarm), in percent: relative to the swarms
  compared, so it changes when a swarm is added or removed;
- ``pct_map_covered``: share of free cells a drone stood on at least once, in percent.

Monitoring (:mod:`twin.monitoring`): ``belief_error``, ``events``, ``pct_events_seen``,
``latency_median_steps``, ``latency_p90_steps`` (and ``_min`` when a step's length is known),
``pct_congested_observed``.

A results table may add the ceilings of :mod:`twin.ceilings` (rows :data:`ORACLE` and
:data:`BOUND`, ``role = "ceiling"``) to its swarms' rows (``role = "swarm"``): they are never
swarms compared (:func:`swarm_rows`), and :func:`headroom` reports the swarms against them.
"""

from __future__ import annotations

import numpy as np
import pandas as pd
from scipy import stats

from twin.monitoring import ceiling_coverage
from twin.patrol import PatrolResult
from twin.scores import ScoreParams
from twin.swarms import is_learned

TABLE2_COLUMNS = ("R_hat_T", "C_hat_T", "pct_time_max_C", "pct_map_covered")
#: Columns added to the paper's four: the reward split, the paper's accounting, the ceiling.
GAIN_COLUMNS = ("R_hat_T_importance", "R_hat_T_idleness", "R_hat_T_paper", "C_hat_T_ceiling")
#: The Table 2 analog as printed and reported, in this order.
SCORE_COLUMNS = (
    "R_hat_T",
    "R_hat_T_importance",
    "R_hat_T_idleness",
    "R_hat_T_paper",
    "C_hat_T",
    "C_hat_T_ceiling",
    "pct_time_max_C",
    "pct_map_covered",
)
MONITORING_COLUMNS = (
    "belief_error",
    "events",
    "pct_events_seen",
    "latency_median_steps",
    "latency_p90_steps",
    "latency_median_min",
    "latency_p90_min",
    "pct_congested_observed",
    "incidents",  # scheduled SUMO incidents (twin.sumo.incidents), when the run has some
    "pct_incidents_seen",
    "incident_latency_steps",
    "incident_latency_min",
)
TABLE2_HEADERS = {
    "R_hat_T": "R_hat_T",
    "R_hat_T_importance": "R importance",
    "R_hat_T_idleness": "R idleness",
    "R_hat_T_paper": "R paper (gameable)",
    "C_hat_T": "C_hat_T",
    "C_hat_T_ceiling": "C ceiling",
    "pct_time_max_C": "% time max C^k",
    "pct_map_covered": "% map covered",
}
MONITORING_HEADERS = {
    "belief_error": "belief error",
    "events": "events",
    "pct_events_seen": "% events seen",
    "latency_median_steps": "latency median",
    "latency_p90_steps": "latency p90",
    "latency_median_min": "median (min)",
    "latency_p90_min": "p90 (min)",
    "pct_congested_observed": "% congested observed",
    "incidents": "incidents",
    "pct_incidents_seen": "% incidents seen",
    "incident_latency_steps": "incident latency",
    "incident_latency_min": "incident (min)",
}
DIGITS = {
    "R_hat_T": 3,
    "R_hat_T_importance": 3,
    "R_hat_T_idleness": 3,
    "R_hat_T_paper": 3,
    "C_hat_T": 3,
    "C_hat_T_ceiling": 3,
    "pct_time_max_C": 2,
    "pct_map_covered": 1,
    "belief_error": 3,
    "events": 1,
    "pct_events_seen": 1,
    "latency_median_steps": 1,
    "latency_p90_steps": 1,
    "latency_median_min": 1,
    "latency_p90_min": 1,
    "pct_congested_observed": 1,
    "incidents": 1,
    "pct_incidents_seen": 1,
    "incident_latency_steps": 1,
    "incident_latency_min": 1,
}

#: Names of the ceiling rows (:mod:`twin.ceilings`) in the results tables.
ORACLE = "oracle (ceiling)"
BOUND = "bound (ceiling)"
CEILINGS = (ORACLE, BOUND)
#: The ``role`` column of a results table: a swarm's row or a ceiling's.
SWARM_ROLE, CEILING_ROLE = "swarm", "ceiling"


def table2(result: PatrolResult, params: ScoreParams | None = None) -> pd.DataFrame:
    """One row per swarm with the Table 2 columns of one run, and :data:`GAIN_COLUMNS`.

    The reward split and the paper's accounting come from the result's ``reward_importance``,
    ``reward_idleness`` and ``reward_paper``; the ceiling
    needs ``eta`` and ``delta``: ``params``, else ``result.params``, else NaN.
    """
    horizon = result.coverage.shape[1]
    frame = pd.DataFrame(
        {
            "swarm": result.swarms,
            **series_columns(result.rewards, result.coverage, result.visited_share),
        }
    )
    for column, name in (
        ("R_hat_T_importance", "reward_importance"),
        ("R_hat_T_idleness", "reward_idleness"),
        ("R_hat_T_paper", "reward_paper"),
    ):
        frame[column] = getattr(result, name).mean(axis=1) if horizon else np.nan
    params = params or result.params
    if params is not None and horizon:
        n_drones = result.positions.shape[2]
        ceiling = ceiling_coverage(result.grid, n_drones, params.eta, params.delta, horizon)
        frame["C_hat_T_ceiling"] = float(ceiling.mean())
    else:
        frame["C_hat_T_ceiling"] = np.nan
    return frame


def series_columns(
    rewards: np.ndarray, coverage: np.ndarray, visited_share: np.ndarray
) -> dict[str, np.ndarray]:
    """``R_hat_T``, ``C_hat_T`` (Def. 4, Def. 5), ``pct_time_max_C`` and ``pct_map_covered`` of
    the swarms run side by side, from their ``(S, T)`` per-step ``R^k``, ``C^{k+1}`` and share
    of free cells visited (NaN when no step ran)."""
    n_swarms, horizon = coverage.shape
    if not horizon:
        nan = np.full(n_swarms, np.nan)
        return dict.fromkeys(("R_hat_T", "C_hat_T", "pct_time_max_C", "pct_map_covered"), nan)
    best = coverage >= coverage.max(axis=0, keepdims=True) - 1e-12
    return {
        "R_hat_T": rewards.mean(axis=1),
        "C_hat_T": coverage.mean(axis=1),
        "pct_time_max_C": 100.0 * best.mean(axis=1),
        "pct_map_covered": 100.0 * visited_share[:, -1],
    }


def is_ceiling_row(frame: pd.DataFrame) -> pd.Series:
    """Which rows of a results table are ceilings (``role == "ceiling"``), not swarms."""
    if "role" not in frame.columns:
        return pd.Series(False, index=frame.index)
    return frame["role"].eq(CEILING_ROLE)


def swarm_rows(frame: pd.DataFrame) -> pd.DataFrame:
    """The rows of a results table that are swarms (ceilings left out)."""
    return frame[~is_ceiling_row(frame)]


NAN = float("nan")


def ci95_halfwidth(values: np.ndarray) -> float:
    """Half-width of the Student-t 95% interval of the mean; NaN values (e.g. the latency of a
    seed in which no event was seen) are left out. NaN from fewer than two values: one seed
    gives no interval (a 0 would read as certainty)."""
    values = np.asarray(values, dtype=float)
    values = values[~np.isnan(values)]
    n = len(values)
    if n < 2:
        return NAN
    return float(stats.t.ppf(0.975, n - 1) * values.std(ddof=1) / np.sqrt(n))


def aggregate(per_seed: pd.DataFrame, by: str | list[str] = "swarm") -> pd.DataFrame:
    """Mean, 95% half-width and seed count of the Table 2, gain and monitoring columns present
    in ``per_seed``, grouped by ``by``."""
    keys = [by] if isinstance(by, str) else list(by)
    columns = [c for c in (*SCORE_COLUMNS, *MONITORING_COLUMNS) if c in per_seed.columns]
    rows = []
    for key, group in per_seed.groupby(keys, sort=False):
        key = key if isinstance(key, tuple) else (key,)
        row = dict(zip(keys, key, strict=True))
        for col in columns:
            values = pd.to_numeric(group[col], errors="coerce").to_numpy(dtype=float)
            row[col] = float(np.nanmean(values)) if (~np.isnan(values)).any() else np.nan
            row[f"{col}_ci95"] = ci95_halfwidth(values)
        row["n_seeds"] = len(group)
        rows.append(row)
    return pd.DataFrame(rows)


def _present(summary: pd.DataFrame, columns) -> list[str]:
    """The columns of ``summary`` that hold at least one value."""
    return [c for c in columns if c in summary.columns and summary[c].notna().any()]


def _format(summary: pd.DataFrame, columns: list[str], headers: dict[str, str]) -> str:
    several = "n_seeds" in summary and (summary["n_seeds"] > 1).any()
    header = ["swarm"] + [headers[c] for c in columns]
    lines = [header]
    for _, row in summary.iterrows():
        cells = [str(row["swarm"])]
        for col in columns:
            d = DIGITS[col]
            if pd.isna(row[col]):
                text = "-"
            else:
                text = f"{row[col]:.{d}f}"
                ci = row.get(f"{col}_ci95")
                if several and ci is not None and not pd.isna(ci):
                    text += f" ± {ci:.{d}f}"
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


def format_table2(summary: pd.DataFrame) -> str:
    """The Table 2 analog as aligned text, with ``± half-width`` when several seeds; the gain
    columns appear when the summary holds them."""
    return _format(summary, _present(summary, SCORE_COLUMNS), TABLE2_HEADERS)


def table2_footnote(summary: pd.DataFrame) -> str:
    """What the printed Table 2 columns mean, naming the swarms compared."""
    swarms = ", ".join(str(s) for s in swarm_rows(summary)["swarm"])
    notes = [
        f"% time max C^k: share of steps with the highest C^k among the swarms in this table "
        f"({swarms}); it changes with the set of swarms compared.",
    ]
    present = _present(summary, GAIN_COLUMNS)
    if "R_hat_T_importance" in present:
        notes.append(
            "R_hat_T: every distinct visited cell paid its visit gain once; = R importance "
            "(alpha_T part) + R idleness (alpha_I part)."
        )
    if "R_hat_T_paper" in present:
        notes.append(
            "R paper (gameable): Def. 4 as printed, every drone paid its field of view; drones "
            "with overlapping views or on one cell are paid several times for one visit."
        )
    if "C_hat_T_ceiling" in present:
        notes.append(
            "C ceiling: C_hat_T of drones that jump each step to the freshest distinct cells; "
            "a reference, not a bound: near it means no stacking or hovering, not more."
        )
    if is_ceiling_row(summary).any():
        notes.append(
            "Rows marked (ceiling) are not swarms: the oracle plans on the true future maps, "
            "the bound is a Lagrangian relaxation no swarm can exceed (twin/ceilings.py)."
        )
    return "\n".join(notes)


def format_monitoring(summary: pd.DataFrame) -> str:
    """The monitoring table as aligned text (the columns of :data:`MONITORING_COLUMNS` that
    the summary holds); latencies in steps, and in minutes when a step's length is known."""
    return _format(summary, _present(summary, MONITORING_COLUMNS), MONITORING_HEADERS)


def headroom(summary: pd.DataFrame, column: str = "R_hat_T") -> str | None:
    """``best swarm X reaches a% of the bound; oracle b%`` from a summary with ceiling rows
    (``None`` without them): how much of the headline score is left above the best swarm."""
    if column not in summary.columns:
        return None
    ceilings = summary[is_ceiling_row(summary)].set_index("swarm")[column]
    swarms = swarm_rows(summary).set_index("swarm")[column].dropna()
    if swarms.empty or BOUND not in ceilings or not np.isfinite(ceilings[BOUND]):
        return None
    if ceilings[BOUND] <= 0:  # nothing to see on any step: no share of it
        return f"Headroom ({column}): none (the bound is {ceilings[BOUND]:.3f}: nothing to see)"
    best = str(swarms.idxmax())
    text = f"best swarm {best} reaches {swarms[best] / ceilings[BOUND]:.1%} of the bound"
    if ORACLE in ceilings and np.isfinite(ceilings[ORACLE]):
        text += f"; oracle {ceilings[ORACLE] / ceilings[BOUND]:.1%}"
        oracle = ceilings[ORACLE]  # a real swarm, not a bound; equal up to rounding is equal
        if swarms[best] > oracle and not np.isclose(swarms[best], oracle, rtol=1e-6, atol=0):
            text += (
                f"; {best} is above the oracle (the best of the planners told the true maps, "
                "a swarm that can be beaten; the bound cannot)"
            )
    return (
        f"Headroom ({column}): {text} (bound {ceilings[BOUND]:.3f}, "
        f"oracle {ceilings.get(ORACLE, float('nan')):.3f}, {best} {swarms[best]:.3f})"
    )


def format_results(summary: pd.DataFrame, title: str) -> str:
    """What ``twin evaluate`` and ``twin run`` print: the Table 2 analog under ``title``, its
    footnote, and the monitoring table when the summary holds it."""
    parts = [f"{title}:", format_table2(summary), table2_footnote(summary)]
    line = headroom(summary)
    if line:
        parts.append(line)
    if _present(summary, MONITORING_COLUMNS):
        parts += [
            "",
            "Monitoring against ground truth (belief error: importance-weighted MAE of the "
            "believed map; events: cells with true importance >= threshold; latency in steps "
            "from onset to first sighting):",
            format_monitoring(swarm_rows(summary)),
        ]
    return "\n".join(parts)


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
        "ratio": _ratio(float(both[a].mean()), float(both[b].mean())) if len(diff) else NAN,
        "n_seeds": len(diff),
    }


def _ratio(a: float, b: float) -> float:
    """``a / b``, NaN when ``b`` is 0 (a yardstick that scored nothing gives no ratio)."""
    return a / b if b != 0 else NAN


def learned_against_best_classical(per_seed: pd.DataFrame, column: str = "R_hat_T"):
    """Each learned swarm against the classical swarm with the highest mean ``column``, paired
    over seeds (empty when the run has no learned or no classical swarm). Ceiling rows
    (``role == "ceiling"``: the oracle, the bound) are never candidates."""
    means = swarm_rows(per_seed).groupby("swarm", sort=False)[column].mean()
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
            f"{row['difference']:+.3f}{ci}, ratio "
            + (f"{row['ratio']:.3f}" if np.isfinite(row["ratio"]) else "n/a (best scored 0)")
        )
    return "\n".join(lines)
