"""Assemble the report: PNGs and a GIF next to one self-contained HTML file (every image inlined
as base64, no external resource) and a Markdown summary that links the image files."""

from __future__ import annotations

import base64
import html
import json
import math
import os
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd
from matplotlib.figure import Figure

from twin.errors import UserError
from twin.files import atomic_write, staged_folder
from twin.readback import INT, NUMBER, read_table
from twin.report import figures
from twin.report.animation import MAX_FRAMES, write_animation
from twin.report.load import RunFiles, load_run
from twin.runs import written_by_a_report
from twin.scores import coverage

#: Table 2 columns of summary.csv: (column, header, decimals); a column absent from the run's
#: summary (or empty) is left out.
TABLE_COLUMNS = (
    ("R_hat_T", "R̂_T (mean score per step)", 4),
    ("R_hat_T_importance", "of which importance (α_T)", 4),
    ("R_hat_T_idleness", "of which idleness (α_I)", 4),
    ("R_hat_T_paper", "R̂_T as Def. 4 prints it (gameable)", 4),
    ("C_hat_T", "Ĉ_T (mean coverage)", 4),
    ("C_hat_T_ceiling", "Ĉ_T of jumping drones (reference)", 4),
    ("pct_time_max_C", "% of time with max C^k", 2),
    ("pct_map_covered", "% of map covered", 2),
)
#: The paper's four Table 2 columns.
PAPER_TABLE_COLUMNS = tuple(
    c for c in TABLE_COLUMNS if c[0] in ("R_hat_T", "C_hat_T", "pct_time_max_C", "pct_map_covered")
)
#: Monitoring columns of monitoring.csv: (column, header, decimals).
MONITORING_TABLE_COLUMNS = (
    ("belief_error", "belief error", 4),
    ("events", "events", 1),
    ("pct_events_seen", "% events seen", 1),
    ("latency_median_steps", "latency median (steps)", 1),
    ("latency_p90_steps", "latency p90 (steps)", 1),
    ("latency_median_min", "latency median (min)", 1),
    ("latency_p90_min", "latency p90 (min)", 1),
    ("pct_congested_observed", "% congested cell-steps observed", 1),
    ("incidents", "incidents", 1),
    ("pct_incidents_seen", "% incidents seen", 1),
    ("incident_latency_steps", "incident latency (steps)", 1),
    ("incident_latency_min", "incident latency (min)", 1),
)
#: Columns of belief_models.csv shown: (column, header, decimals).
BELIEF_TABLE_COLUMNS = (
    ("belief_error", "belief error", 4),
    ("calibration_90", "in 90% interval", 3),
    ("events", "events", 1),
    ("pct_events_known", "% events known", 1),
    ("latency_median_min", "latency median (min)", 1),
    ("latency_median_steps", "latency median (steps)", 1),
    ("false_alarms_per_hour", "false alarms / h", 1),
)
BELIEF_CAPTION = (
    "From belief_models.csv (twin run --history): each swarm's picture of the city under three "
    "belief models, mean over seeds. last-seen: the last importance a drone saw (the monitoring "
    "table's belief map); history: the mean of earlier days' runs per cell and time of day, "
    "no drones; nowcast: the history fused with the drones' sightings (a per-cell Kalman "
    "filter on the deviation from the history); with fixed detectors, nowcast+detectors also "
    "takes their readings, and (detectors only) is that filter without drones. "
    "belief error: importance-weighted MAE against "
    "the truth; in 90% interval: share of true values inside the stated 90% interval (none for "
    "last-seen); % events known: congestion events whose cell is believed >= the threshold "
    "while they last, latency from onset; false alarms: onsets of a believed >= threshold "
    "where the truth is below it."
)
REPORT_DIR = "report"


def belief_rows(beliefs: pd.DataFrame) -> tuple[list[str], list[list[str]]]:
    """Header and rows of the belief-model table (swarm, model, the shown columns)."""
    columns = [c for c in BELIEF_TABLE_COLUMNS if c[0] in beliefs.columns]
    columns = [c for c in columns if beliefs[c[0]].notna().any()]
    header = ["swarm", "model"] + [h for _, h, _ in columns]
    if "n_seeds" in beliefs.columns:
        header.append("seeds")
    rows = []
    for _, row in beliefs.iterrows():
        cells = [str(row["swarm"]), str(row["model"])]
        cells += [format_cell(row, c, d) for c, _, d in columns]
        if "n_seeds" in beliefs.columns:
            cells.append(str(int(row["n_seeds"])))
        rows.append(cells)
    return header, rows


@dataclass
class Section:
    title: str
    image: str | None  # file name inside the report folder
    caption: str


DEGRADATION_HEADER = [
    "swarm", "phase", "steps", "R̂ with faults", "R̂ fault-free", "change %", "events",
    "% seen with faults", "% seen fault-free", "latency (steps) with faults",
    "latency (steps) fault-free", "% congested observed with faults",
    "% congested observed fault-free",
]  # fmt: skip


def degradation_rows(rf: RunFiles) -> list[list[str]]:
    """degradation.csv averaged over seeds: per swarm and phase, the score per step and the
    monitoring with the faults and in the fault-free twin."""
    frame = rf.degradation
    keys = ["swarm", "phase", "label", "start", "stop"]
    means = frame.groupby(keys, sort=False).mean(numeric_only=True).reset_index()

    def num(value: float, decimals: int) -> str:
        return "–" if value is None or not np.isfinite(value) else f"{value:.{decimals}f}"

    rows = []
    for _, r in means.iterrows():
        change = 100.0 * (r["R_hat"] - r["R_hat_fault_free"]) / r["R_hat_fault_free"]
        rows.append(
            [str(r["swarm"]), str(r["label"]), f"{int(r['start'])}–{int(r['stop'])}",
             num(r["R_hat"], 4), num(r["R_hat_fault_free"], 4), num(change, 1),
             num(r["events"], 1), num(r["pct_events_seen"], 1),
             num(r["pct_events_seen_fault_free"], 1), num(r["latency_median_steps"], 1),
             num(r["latency_median_steps_fault_free"], 1),
             num(r["pct_congested_observed"], 1), num(r["pct_congested_observed_fault_free"], 1)]
        )  # fmt: skip
    return rows


def degradation_caption(rf: RunFiles) -> str:
    seeds = sorted(set(rf.degradation["seed"].tolist()))
    faults = json.dumps(rf.run.get("faults", {}))
    return (
        "From degradation.csv, means over seeds "
        + ", ".join(map(str, seeds))
        + ". Each swarm ran under the scripted faults and, in the same pass over the same "
        "traffic with the same seed, without them (its fault-free twin). A phase is a stretch "
        "of steps between two changes of the faults; R̂ is the mean score per step R^k over "
        "its steps; events are the congestion events that last into it, cut to it: the share "
        "seen in the phase, the median latency (steps from the event's start in the phase to "
        "its first sighting that counts) and the share of their cell-steps in view. Faults: "
        + faults
        + "."
    )


def format_cell(row: pd.Series, column: str, decimals: int) -> str:
    """``mean``, or ``mean ± half-width`` over several seeds, as printed in both tables; ``-``
    when there is no value (e.g. no latency: no event was seen)."""
    value = float(row[column])
    if math.isnan(value):
        return "-"
    text = f"{value:.{decimals}f}"
    ci = row.get(f"{column}_ci95")
    several = int(row.get("n_seeds", 2)) > 1
    if several and ci is not None and not (isinstance(ci, float) and math.isnan(ci)):
        text += f" ± {float(ci):.{decimals}f}"
    return text


def summary_table(
    summary: pd.DataFrame, table_columns=TABLE_COLUMNS
) -> tuple[list[str], list[list[str]]]:
    """Header and rows of the Table 2 analog (or of ``table_columns``), straight from the CSV."""
    columns = [c for c in table_columns if c[0] in summary.columns and summary[c[0]].notna().any()]
    header = ["swarm"] + [h for _, h, _ in columns]
    if "n_seeds" in summary.columns:
        header.append("seeds")
    rows = []
    for _, row in summary.iterrows():
        cells = [str(row["swarm"])] + [format_cell(row, c, d) for c, _, d in columns]
        if "n_seeds" in summary.columns:
            cells.append(str(int(row["n_seeds"])))
        rows.append(cells)
    return header, rows


_MD_ESCAPES = str.maketrans(
    {
        "&": "&amp;", "<": "&lt;", ">": "&gt;", "|": "\\|", "[": "\\[", "]": "\\]",
        "`": "\\`", "\\": "\\\\", "\n": " ", "\r": " ",
    }
)  # fmt: skip


def md_escape(text: Any) -> str:
    """``text`` safe to embed in Markdown: no raw HTML (``<``, ``>``, ``&`` as entities), no
    link, code span or table cell break (``[ ] ` |`` backslash-escaped), on one line."""
    return str(text).translate(_MD_ESCAPES)


def markdown_table(header: list[str], rows: list[list[str]]) -> str:
    """A Markdown table; every cell is escaped with :func:`md_escape`."""
    lines = [
        "| " + " | ".join(map(md_escape, header)) + " |",
        "|" + "---|" * len(header),
    ]
    lines += ["| " + " | ".join(map(md_escape, r)) + " |" for r in rows]
    return "\n".join(lines)


def html_table(header: list[str], rows: list[list[str]], css_class: str = "") -> str:
    head = "".join(f"<th>{html.escape(h)}</th>" for h in header)
    body = "".join(
        "<tr>" + "".join(f"<td>{html.escape(c)}</td>" for c in r) + "</tr>" for r in rows
    )
    return f'<table class="{css_class}"><thead><tr>{head}</tr></thead><tbody>{body}</tbody></table>'


def _flatten(node: Any, prefix: str = "") -> list[tuple[str, str]]:
    """Dotted key/value pairs of a JSON tree (long lists abbreviated)."""
    if isinstance(node, dict):
        out = []
        for key, value in node.items():
            out += _flatten(value, f"{prefix}.{key}" if prefix else str(key))
        return out
    if isinstance(node, list) and (
        len(node) > 12 or any(isinstance(v, (dict, list)) for v in node)
    ):
        return [(prefix, f"[{len(node)} items, see run.json]")]
    return [(prefix, json.dumps(node) if not isinstance(node, str) else node)]


def metadata_rows(run: dict[str, Any]) -> list[list[str]]:
    return [[k, v] for k, v in _flatten(run)]


def idleness_check(rf: RunFiles) -> str:
    """Replay the first seed's idleness and compare its coverage with series.parquet's."""
    worst = 0.0
    series = rf.series[rf.series["seed"] == rf.first_seed]
    grid = rf.grid
    for swarm in rf.swarms:
        maps = rf.idleness(swarm)
        stored = series[series["swarm"] == swarm].sort_values("step")["coverage"].to_numpy()
        replayed = np.array([coverage(maps[k + 1], grid) for k in range(len(stored))])
        worst = max(worst, float(np.abs(replayed - stored).max(initial=0.0)))
    params, origin = rf.score_params()
    verdict = "matches" if worst < 1e-6 else "DOES NOT match"
    return (
        f"Idleness maps replayed from trajectories.parquet with eta = {params.eta}, "
        f"delta = {params.delta} ({origin}); their coverage {verdict} series.parquet "
        f"(largest difference {worst:.2g})."
    )


def _save(fig: Figure, path: Path) -> str:
    try:
        fig.savefig(path, dpi=100)
    except OSError as exc:  # name the file being written
        if exc.filename is None:
            exc.filename = str(path)
        raise
    return path.name


def build_sections(
    rf: RunFiles, out: Path, animation: bool
) -> tuple[list[Section], dict[str, float]]:
    timings: dict[str, float] = {}
    sections: list[Section] = []

    def timed(name: str, fn):
        start = time.perf_counter()
        result = fn()
        timings[name] = time.perf_counter() - start
        return result

    n_seeds = len(rf.seeds)
    sections.append(
        Section(
            "Patrolling scores over time (paper's Fig. 3)",
            timed("scores", lambda: _save(figures.figure_scores(rf), out / "scores.png")),
            "Cumulative patrolling score R^k, score per step R^k, share of free cells visited so "
            "far and coverage C^k, all swarms on the same axes"
            + (
                f"; lines are means and bands 95% intervals over {n_seeds} seeds."
                if n_seeds > 1
                else "."
            ),
        )
    )
    sections.append(
        Section(
            "Drones over the importance map (paper's Fig. 4)",
            timed("snapshots", lambda: _save(figures.figure_snapshots(rf), out / "snapshots.png")),
            "Importance T^k (bright = congested, grey = obstacle) at the paper's snapshot steps, "
            "with each swarm's drones (markers) and their last steps (lines).",
        )
    )
    fig, peak = timed("trajectories", lambda: figures.figure_trajectories(rf))
    sections.append(
        Section(
            "Trajectories over unvisited importance (paper's Fig. 2)",
            _save(fig, out / "trajectories.png"),
            f"Cell colour I^k·T^k at k = {peak}, the step with the highest mean importance from "
            f"k = {figures.first_peak_step(rf, figures.TRAIL_STEPS)} on (the lines show up to "
            f"{figures.TRAIL_STEPS} steps before it): bright cells are important and long "
            "unvisited. " + idleness_check(rf),
        )
    )
    if rf.live() is not None:
        sections.append(
            Section(
                "Surviving drones' paths",
                timed(
                    "faults",
                    lambda: _save(figures.figure_surviving_paths(rf), out / "surviving.png"),
                ),
                "Each row a phase of the run with drones lost (run.json faults), each panel a "
                "swarm: the live drones' paths over the phase's first steps on the importance "
                "map at its start; grey crosses are the lost drones, which stay where they were "
                "lost.",
            )
        )
    if animation:
        sections.append(
            Section(
                "Animation",
                timed("animation", lambda: write_animation(rf, out / "animation.gif").name),
                "Every swarm over the importance map T^k, frames subsampled to at most "
                f"{MAX_FRAMES} steps.",
            )
        )
    sections.append(
        Section(
            "Traffic over the horizon",
            timed("traffic", lambda: _save(figures.figure_traffic(rf), out / "traffic.png")),
            "How congestion forms and dissolves: statistics of T^k over the free cells"
            + (", and the cells' simulated speed." if rf.mfd_samples is not None else "."),
        )
    )
    fig, note = timed("network", lambda: figures.figure_network(rf))
    sections.append(
        Section(
            "Network and monitoring grid",
            _save(fig, out / "network.png"),
            "Grid cells coloured by their peak importance over the horizon; obstacle cells "
            "hatched. " + note,
        )
    )
    if rf.events is not None:
        drawn, total = figures.events_drawn(rf)
        sections.append(
            Section(
                "Congestion events and who saw them",
                timed("events", lambda: _save(figures.figure_events(rf), out / "events.png")),
                f"Each bar is a congestion event of seed {rf.first_seed} from events.parquet "
                f"({total} events"
                + (f", the {len(drawn)} earliest drawn" if total > len(drawn) else "")
                + "): a cell whose true importance stays at or above the threshold, from onset "
                "to end, darker for a higher peak. A dot marks the step at which a swarm's "
                "drones first had the cell in view while the event lasted; a cross at the end "
                "of the bar an event the swarm missed.",
            )
        )
    if "belief_error" in rf.series.columns:
        sections.append(
            Section(
                "Belief error over time",
                timed("belief", lambda: _save(figures.figure_belief(rf), out / "belief.png")),
                "Each swarm believes, for every cell, the last importance its drones observed "
                "(0 before the first sighting). The curve is the importance-weighted mean "
                "absolute error of that map against the true importance (series.parquet, "
                "belief_error); lower is better.",
            )
        )
    if rf.belief_maps is not None and figures.belief_map_swarms(rf):
        drawn = figures.belief_map_swarms(rf)
        who = " and ".join(drawn)
        sections.append(
            Section(
                "Believed against true importance (nowcast)",
                timed(
                    "belief maps",
                    lambda: _save(figures.figure_belief_maps(rf), out / "belief_maps.png"),
                ),
                f"From belief_maps.npz (twin run --history), seed {rf.belief_maps['seed']}: the "
                "true importance, then for "
                + who
                + " (the best swarm by R_hat_T, and the swarm that plans on its nowcast when the "
                "run has it) the nowcast's mean (the history fused with the drones' sightings) "
                "and its standard deviation, with the drones and their last 3 steps, half-way "
                "to the peak of the mean true importance, at the peak, and half-way after it.",
            )
        )
        sections.append(
            Section(
                "When the nowcast knew each congestion event",
                timed(
                    "belief timeline",
                    lambda: _save(figures.figure_belief_timeline(rf), out / "belief_timeline.png"),
                ),
                "Each bar is a congestion event (true importance at or above the threshold, "
                "onset to end); a mark at the first step at which the belief (the history "
                "alone, or each drawn swarm's nowcast) reached the threshold while it lasted, a "
                "cross at the bar's end for an event it never knew: the belief table's "
                "% events known and latency, event by event.",
            )
        )
    if rf.mfd is not None:
        fig, note = timed("mfd", lambda: figures.figure_mfd(rf))
        sections.append(
            Section(
                "Macroscopic fundamental diagram",
                _save(fig, out / "mfd.png"),
                "Cell samples of the simulation (density, speed relative to the cell's limit) "
                "and the fitted curve. mfd.json: "
                + "; ".join(f"{k} = {v}" for k, v in _flatten(rf.mfd))
                + ". "
                + note,
            )
        )
    return sections, timings


def _data_uri(path: Path) -> str:
    mime = "image/gif" if path.suffix == ".gif" else "image/png"
    return f"data:{mime};base64," + base64.b64encode(path.read_bytes()).decode("ascii")


CSS = """
body{font-family:system-ui,-apple-system,Segoe UI,Helvetica,Arial,sans-serif;max-width:1200px;
margin:2em auto;padding:0 1em;color:#222}
h1{font-size:1.6em}h2{font-size:1.25em;border-bottom:1px solid #ddd;padding-bottom:.2em;margin-top:2em}
table{border-collapse:collapse;margin:1em 0;font-size:.92em}
th,td{border:1px solid #ccc;padding:.3em .6em;text-align:right}
th:first-child,td:first-child{text-align:left}
table.meta td{text-align:left;font-family:ui-monospace,monospace;font-size:.85em}
img{max-width:100%;height:auto;border:1px solid #eee}
.caption{color:#555;font-size:.9em;margin:.3em 0 1em}
pre{background:#f6f6f6;padding:1em;overflow:auto;font-size:.8em}
"""


def render_html(
    rf: RunFiles, out: Path, sections: list[Section], report_seconds: float = 0.0
) -> str:
    header, rows = summary_table(rf.summary)
    parts = [
        "<!DOCTYPE html>",
        '<html lang="en"><head><meta charset="utf-8">',
        f"<title>twin report: {html.escape(rf.run_dir.name)}</title>",
        f"<style>{CSS}</style></head><body>",
        f"<h1>Drone-swarm patrol report: {html.escape(rf.run_dir.name + _partial(rf))}</h1>",
        f"<p>{html.escape(_lede(rf))}</p>",
        "<h2>Scores (paper's Table 2)</h2>",
        html_table(header, rows, "summary"),
        f'<p class="caption">{html.escape(_table_caption(rf))}</p>',
    ]
    if rf.monitoring is not None:
        m_header, m_rows = summary_table(rf.monitoring, MONITORING_TABLE_COLUMNS)
        parts += [
            "<h2>Monitoring against ground truth</h2>",
            html_table(m_header, m_rows, "monitoring"),
            f'<p class="caption">{html.escape(_monitoring_caption(rf))}</p>',
        ]
    if rf.degradation is not None:
        parts += [
            "<h2>Faults: degradation against the fault-free twin</h2>",
            html_table(DEGRADATION_HEADER, degradation_rows(rf), "degradation"),
            f'<p class="caption">{html.escape(degradation_caption(rf))}</p>',
        ]
    if rf.beliefs is not None:
        b_header, b_rows = belief_rows(rf.beliefs)
        parts += [
            "<h2>Belief models</h2>",
            html_table(b_header, b_rows, "beliefs"),
            f'<p class="caption">{html.escape(BELIEF_CAPTION)}</p>',
        ]
    if rf.incidents:
        parts += [
            "<h2>Incidents</h2>",
            html_table(INCIDENT_HEADER, incident_rows(rf), "incidents"),
            f'<p class="caption">{html.escape(INCIDENT_CAPTION)}</p>',
        ]
    if rf.per_seed is not None and len(rf.seeds) > 1:
        parts.append("<details><summary>Per seed</summary>")
        parts.append(
            html_table(list(map(str, rf.per_seed.columns)), _rows(rf.per_seed), "per-seed")
        )
        parts.append("</details>")
    for section in sections:
        parts.append(f"<h2>{html.escape(section.title)}</h2>")
        if section.image:
            parts.append(
                f'<img src="{_data_uri(out / section.image)}" alt="{html.escape(section.title)}">'
            )
        parts.append(f'<p class="caption">{html.escape(section.caption)}</p>')
    timing = timing_rows(rf, report_seconds)
    if timing:
        parts += [
            "<h2>Where the time went</h2>",
            html_table(TIMING_HEADER, timing, "timing"),
            f'<p class="caption">{html.escape(_timing_caption(rf, timing))}</p>',
        ]
    parts.append("<h2>Run metadata (run.json)</h2>")
    parts.append(html_table(["key", "value"], metadata_rows(rf.run), "meta"))
    parts.append("<details><summary>run.json</summary><pre>")
    parts.append(html.escape(json.dumps(rf.run, indent=2)))
    parts.append("</pre></details></body></html>")
    return "\n".join(parts)


def _rows(frame: pd.DataFrame) -> list[list[str]]:
    def fmt(v: Any) -> str:
        return f"{v:.4f}" if isinstance(v, float) else str(v)

    return [[fmt(v) for v in row] for row in frame.itertuples(index=False)]


def _partial(rf: RunFiles) -> str:
    """A title suffix for a run that stopped early (the lede says why)."""
    return " (PARTIAL run)" if rf.partial else ""


def _lede(rf: RunFiles) -> str:
    nx, ny = rf.obstacles.shape
    traffic = rf.run.get("traffic") or {}
    where = (
        f"a {nx} x {ny} grid ({rf.grid.n_free} free cells, {rf.run.get('n_drones', '?')} drones)"
    )
    if traffic.get("kind") == "sumo":
        begin, step_s = rf.clock_start()
        where += f" over the SUMO network {traffic.get('name', '?')}"
        if begin:
            where += f", from {begin} ({step_s:g} s per step, {rf.clock(rf.horizon)} at the end)"
        where += _empty_steps(rf)
    elif traffic.get("kind"):
        where += f" with {traffic['kind']} traffic"
    text = (
        f"{len(rf.swarms)} swarms ({', '.join(rf.swarms)}) patrolling {where}, "
        f"T = {rf.horizon} steps, seeds {', '.join(map(str, rf.seeds))}. Every number below is "
        "read from this run folder's files."
    )
    if rf.partial:  # said first, so that no reader takes a partial run for a whole one
        planned = rf.run.get("traffic", {}) or {}
        of = planned.get("horizon") if isinstance(planned, dict) else None
        steps = f"{rf.horizon} of {of}" if isinstance(of, int) else f"{rf.horizon}"
        text = f"PARTIAL RUN ({steps} steps): {rf.partial_reason}. " + text
    return text


def _empty_steps(rf: RunFiles) -> str:
    """Steps of the traffic tape with no vehicle on the grid, e.g. after the demand ended."""
    tape = rf.run_dir / "tape.parquet"
    if not tape.exists():
        return ""
    counts = read_table(tape, {"step": INT, "count": NUMBER})
    per_step = counts[counts["step"] >= 0].groupby("step")["count"].sum()
    empty = [k for k in range(rf.horizon + 1) if per_step.get(k, 0) == 0]
    if not empty:
        return ""
    shown = ", ".join(map(str, empty[:12])) + (" ..." if len(empty) > 12 else "")
    return (
        f"; {len(empty)} of {rf.horizon + 1} steps had no vehicle on the network "
        f"(steps {shown}): there is nothing to monitor then"
    )


def _table_caption(rf: RunFiles) -> str:
    if len(rf.seeds) > 1:
        text = "From summary.csv: mean ± 95% interval half-width over seeds."
    else:
        text = "From summary.csv (one seed, so no interval)."
    columns = set(rf.summary.columns)
    text += (
        " % of time with max C^k is relative to the swarms compared here "
        f"({', '.join(rf.swarms)}): the share of steps at which a swarm has the highest C^k "
        "among them (ties count for each), so it changes when a swarm is added or removed."
    )
    if "R_hat_T_importance" in columns:
        text += (
            " R̂_T pays the visit gain of every distinct visited cell once, however many drones "
            "stand on it or see it; it is the sum of its importance (α_T) and idleness (α_I) "
            "parts."
        )
    if "R_hat_T_paper" in columns:
        text += (
            " The column of Def. 4 as printed pays every drone its whole field of view, so "
            "drones with overlapping views or stacked on one cell are paid several times for "
            "one visit: it is gameable by flying in a pack, shown only for comparison with "
            "the paper."
        )
    from twin.metrics import headroom, is_ceiling_row

    if is_ceiling_row(rf.summary).any():
        text += (
            " Rows marked (ceiling) are not swarms: the oracle plans on the true future maps "
            "and the bound is a Lagrangian relaxation no swarm can exceed (twin/ceilings.py)."
        )
        line = headroom(rf.summary)
        if line:
            text += f" {line}."
    if "C_hat_T_ceiling" in columns:
        text += (
            " The Ĉ_T ceiling is the coverage of drones that jump, each step, to the freshest "
            "distinct cells: a reference, not a bound (pacing revisits can exceed it slightly), "
            "so a Ĉ_T near it shows a swarm that neither stacks nor hovers, not more."
        )
    return text


INCIDENT_HEADER = ["#", "kind", "edge", "cell (i, j)", "begin", "minutes", "steps"]


def incident_rows(rf: RunFiles) -> list[list[str]]:
    """One row per scheduled incident of incidents.json (the numbers of the map's markers)."""
    rows = []
    for n, inc in enumerate(rf.incidents or [], start=1):
        edge = str(inc.get("edge"))
        if inc.get("lane") is not None:
            edge += f" lane {inc['lane']}"
        if inc.get("vehicle"):
            edge += f" ({inc['vehicle']})"
        cell = inc.get("cell") or ["?", "?"]
        rows.append(
            [str(n), str(inc.get("kind")), edge, f"({cell[0]}, {cell[1]})", str(inc.get("begin")),
             f"{inc.get('duration_min', 0):g}", f"{inc.get('onset_step')}-{inc.get('end_step')}"]
        )  # fmt: skip
    return rows


INCIDENT_CAPTION = (
    "Scheduled incidents (incidents.json), the red numbered markers of the network map. A swarm "
    "sees an incident when a drone's field of view covers its cell at one of its steps; the "
    "monitoring table gives the share seen and the mean latency from onset to first sighting."
)


TIMING_HEADER = ["process", "stage", "seconds", "ms per step", "share of its process"]


def timing_rows(rf: RunFiles, report_seconds: float = 0.0) -> list[list[str]]:
    """The first seed's stages (``timing.csv``), then the time to draw this report."""
    t = rf.timing
    if t is None or t.empty:
        return []
    if "process" not in t.columns:
        t = t.assign(process="main")
    first = t[t["seed"] == t["seed"].iloc[0]]
    steps = max(len(rf.series.query(f"seed == {rf.first_seed}")["step"].unique()), 1)
    totals = first.groupby("process")["seconds"].sum().to_dict()
    totals["main"] = totals.get("main", 0.0) + report_seconds
    rows = [
        [
            str(r.process),
            str(r.stage),
            f"{r.seconds:.2f}",
            f"{r.ms_per_step:.2f}",
            f"{100 * r.seconds / (totals[r.process] or 1.0):.1f}%",
        ]
        for r in first.itertuples()
    ]
    if report_seconds > 0:
        rows.append(
            [
                "main",
                "report figures",
                f"{report_seconds:.2f}",
                f"{1000 * report_seconds / steps:.2f}",
                f"{100 * report_seconds / (totals['main'] or 1.0):.1f}%",
            ]
        )
    return rows


def _timing_caption(rf: RunFiles, rows: list[list[str]]) -> str:
    main = [r for r in rows if r[0] == "main"]
    largest = max(main or rows, key=lambda r: float(r[2]))
    timings = rf.run.get("timings") or {}
    peak, peak_sumo = timings.get("peak_memory_mb"), timings.get("peak_memory_sumo_process_mb")
    memory = f" Peak memory: {peak:.0f} MB" if peak else ""
    if memory and peak_sumo and any(r[0] == "sumo" for r in rows):
        memory += f", SUMO's process {peak_sumo:.0f} MB"
    separate = (
        " SUMO ran in its own process beside the main one (twin/sumo/worker.py): the main "
        "process waited for it only as long as 'waiting for SUMO' says."
        if any(r[0] == "sumo" for r in rows)
        else ""
    )
    return (
        f"Wall time per stage of seed {rf.first_seed}'s run (timing.csv; twin/timing.py): SUMO "
        "stepping, reads and binning, the observation model, each swarm's decisions, the "
        "step and scoring of all swarms, recording, then the monitoring and writing of the "
        f"run folder and the figures of this report. Largest in the main process: "
        f"{largest[1]} ({largest[4]})." + separate + (memory + "." if memory else "")
    )


def _monitoring_caption(rf: RunFiles) -> str:
    settings = rf.run.get("monitoring") or {}
    threshold = settings.get("threshold")
    level = f"{threshold:g}" if isinstance(threshold, (int, float)) else "the threshold"
    truth = settings.get("truth", "the true importance")
    text = (
        "From monitoring.csv"
        + (": mean ± 95% interval over seeds. " if len(rf.seeds) > 1 else " (one seed). ")
        + f"Truth: {truth}. Belief error: importance-weighted mean absolute error of each "
        "swarm's believed map (last observed value per cell, 0 before the first sighting) "
        "against the truth, averaged over the run. Events: maximal runs of steps in which a "
        f"cell's true importance stays >= {level}"
        + (" (the MFD speed at half its free-flow value). " if threshold == 0.5 else ". ")
        + "An event is seen when a drone's field of view covers its cell while it lasts; latency "
        "runs from onset to the first sighting (median and 90th percentile over seen events). "
        "% congested cell-steps observed: share of the events' cell-steps in some drone's view."
    )
    return text


def render_markdown(rf: RunFiles, sections: list[Section], report_seconds: float = 0.0) -> str:
    header, rows = summary_table(rf.summary)
    lines = [
        f"# Drone-swarm patrol report: {md_escape(rf.run_dir.name + _partial(rf))}",
        "",
        md_escape(_lede(rf)),
        "",
        "## Scores (paper's Table 2)",
        "",
        markdown_table(header, rows),
        "",
        md_escape(_table_caption(rf)),
        "",
    ]
    if rf.monitoring is not None:
        m_header, m_rows = summary_table(rf.monitoring, MONITORING_TABLE_COLUMNS)
        lines += [
            "## Monitoring against ground truth",
            "",
            markdown_table(m_header, m_rows),
            "",
            md_escape(_monitoring_caption(rf)),
            "",
        ]
    if rf.degradation is not None:
        lines += [
            "## Faults: degradation against the fault-free twin",
            "",
            markdown_table(DEGRADATION_HEADER, degradation_rows(rf)),
            "",
            md_escape(degradation_caption(rf)),
            "",
        ]
    if rf.beliefs is not None:
        b_header, b_rows = belief_rows(rf.beliefs)
        lines += [
            "## Belief models",
            "",
            markdown_table(b_header, b_rows),
            "",
            md_escape(BELIEF_CAPTION),
            "",
        ]
    if rf.incidents:
        lines += [
            "## Incidents",
            "",
            markdown_table(INCIDENT_HEADER, incident_rows(rf)),
            "",
            INCIDENT_CAPTION,
            "",
        ]
    for section in sections:
        lines += [f"## {md_escape(section.title)}", ""]
        if section.image:
            lines += [f"![{md_escape(section.title)}]({section.image})", ""]
        lines += [md_escape(section.caption), ""]
    timing = timing_rows(rf, report_seconds)
    if timing:
        lines += [
            "## Where the time went",
            "",
            markdown_table(TIMING_HEADER, timing),
            "",
            md_escape(_timing_caption(rf, timing)),
            "",
        ]
    lines += [
        "## Run metadata (run.json)",
        "",
        markdown_table(["key", "value"], metadata_rows(rf.run)),
    ]
    return "\n".join(lines) + "\n"


def report_dir(run_dir: Path) -> Path:
    """``RUN_DIR/report``, refused (one line) when writing into it would write outside the run
    folder: a symbolic link (to anywhere), a file in its place, or links inside it that lead
    out of the run folder."""
    out = run_dir / REPORT_DIR
    fix = "remove it (twin writes the report afresh) and rerun `twin report`"
    if out.is_symlink():
        raise UserError(
            f"{out}: is a symbolic link (to {os.readlink(out)}); twin writes only inside the "
            f"run folder: {fix}"
        )
    if out.exists() and not out.is_dir():
        raise UserError(f"{out}: a file is in the way of the report folder; {fix}")
    if out.is_dir():
        root = run_dir.resolve()
        for entry in out.rglob("*"):
            if entry.is_symlink() and not entry.resolve().is_relative_to(root):
                raise UserError(
                    f"{entry}: is a symbolic link out of the run folder (to "
                    f"{os.readlink(entry)}); twin writes only inside the run folder: {fix}"
                )
    return out


def write_report(run_dir: str | Path | RunFiles, animation: bool = True) -> Path:
    """Write ``RUN_DIR/report/`` (report.html, report.md, PNGs, GIF) of a run folder or of one
    already read; return the HTML's path.

    The report is drawn into a temporary folder inside the run folder and renamed into place
    at the end: a report that fails mid-way (a full disk ...) leaves the previous report, or
    none, never a partial one."""
    rf = run_dir if isinstance(run_dir, RunFiles) else load_run(run_dir)
    out = report_dir(rf.run_dir)
    with staged_folder(out, written_by_a_report) as stage:
        sections, drawing = build_sections(rf, stage, animation)
        seconds = sum(drawing.values())
        page = render_html(rf, stage, sections, seconds)
        md = render_markdown(rf, sections, seconds)
        atomic_write(stage / "report.html", lambda p: p.write_text(page, encoding="utf-8"))
        atomic_write(stage / "report.md", lambda p: p.write_text(md, encoding="utf-8"))
    return out / "report.html"
