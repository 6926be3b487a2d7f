"""The sweep report: the merged Table 2 (mean and 95% interval over seeds per scenario,
parameter combination and swarm), the same as a chart, and the cumulative-score curves of every
scenario and combination; HTML (self-contained) and Markdown, from the sweep folder's files."""

from __future__ import annotations

import html
import json
from pathlib import Path

import numpy as np
import pandas as pd
from matplotlib.figure import Figure

from twin.errors import UserError
from twin.files import atomic_write, check_staged_folder, staged_folder
from twin.readback import BOUNDS, CELL_SERIES_COLUMNS, TEXT, read_json, read_table
from twin.report.document import (
    CSS,
    PAPER_TABLE_COLUMNS,
    TABLE_COLUMNS,
    _data_uri,
    format_cell,
    html_table,
    markdown_table,
    md_escape,
    report_dir,
)
from twin.report.figures import swarm_colours
from twin.report.stats import ci95_half_width

REPORT_DIR = "report"


def group_columns(summary: pd.DataFrame) -> list[str]:
    """Columns that identify a group of seeds: the scenario and the swept parameters."""
    return ["scenario"] + [c for c in summary.columns if "." in c and not c.endswith("_ci95")]


def group_label(row: pd.Series, columns: list[str]) -> str:
    parts = [str(row["scenario"])] + [f"{c.split('.')[-1]}={row[c]}" for c in columns[1:]]
    return ", ".join(parts)


def sweep_table(summary: pd.DataFrame) -> tuple[list[str], list[list[str]]]:
    groups = group_columns(summary)
    columns = [c for c in TABLE_COLUMNS if c[0] in summary and summary[c[0]].notna().any()]
    header = [*groups, "swarm"] + [h for _, h, _ in columns] + ["seeds"]
    rows = []
    for _, row in summary.iterrows():
        rows.append(
            [str(row[c]) for c in groups]
            + [str(row["swarm"])]
            + [format_cell(row, c, d) for c, _, d in columns]
            + [str(int(row["n_seeds"]))]
        )
    return header, rows


def figure_table2(summary: pd.DataFrame) -> Figure:
    """Each Table 2 column per group and swarm, with 95% error bars (cut to the values the
    column can take, :data:`twin.readback.BOUNDS`)."""
    groups = group_columns(summary)
    labels = list(dict.fromkeys(group_label(r, groups) for _, r in summary.iterrows()))
    swarms = list(dict.fromkeys(summary["swarm"]))
    colours = swarm_colours(swarms)
    fig = Figure(figsize=(max(8.0, 2.2 * len(labels) + 3), 6.5), layout="constrained")
    axes = fig.subplots(2, 2).ravel()
    width = 0.8 / len(swarms)
    x = np.arange(len(labels))
    for ax, (col, header, _) in zip(axes, PAPER_TABLE_COLUMNS, strict=True):
        for s, swarm in enumerate(swarms):
            rows = summary[summary["swarm"] == swarm]
            lookup = {group_label(r, groups): r for _, r in rows.iterrows()}
            mean = np.array([lookup[lb][col] if lb in lookup else np.nan for lb in labels])
            half = np.array([lookup[lb][f"{col}_ci95"] if lb in lookup else 0 for lb in labels])
            lo, hi = BOUNDS.get(col, (-np.inf, np.inf))
            yerr = np.clip(
                np.stack([np.minimum(half, mean - lo), np.minimum(half, hi - mean)]), 0, None
            )
            ax.bar(
                x + (s - (len(swarms) - 1) / 2) * width, mean, width, yerr=yerr,
                color=colours[swarm], label=swarm, capsize=2, error_kw={"lw": 0.8},
            )  # fmt: skip
        ax.set_title(header, fontsize=10)
        ax.set_xticks(x, labels, fontsize=8, rotation=15 if len(labels) > 2 else 0)
        ax.grid(axis="y", alpha=0.3)
    fig.legend(*axes[0].get_legend_handles_labels(), loc="outside lower center", ncols=len(swarms))
    fig.suptitle(
        "Table 2 columns per scenario (mean and 95% interval over seeds, cut to the values "
        "each can take)",
        fontsize=11,
    )
    return fig


def figure_curves(out_dir: Path, results: pd.DataFrame) -> Figure | None:
    """Cumulative patrolling score R^k per group: mean and 95% band over the cells' seeds."""
    groups = group_columns(results)
    cells = results.drop_duplicates("cell")
    keyed = list(cells.groupby(groups, sort=False))
    if not keyed:
        return None
    swarms = list(dict.fromkeys(results["swarm"]))
    colours = swarm_colours(swarms)
    cols = min(3, len(keyed))
    rows = int(np.ceil(len(keyed) / cols))
    fig = Figure(figsize=(4.5 * cols, 3.3 * rows + 0.6), layout="constrained")
    axes = fig.subplots(rows, cols, squeeze=False).ravel()
    for ax, (_, group) in zip(axes, keyed, strict=False):
        frames = [
            read_table(
                out_dir / "cells" / f"{cid}.parquet",
                CELL_SERIES_COLUMNS,
            )
            for cid in group["cell"]
            if (out_dir / "cells" / f"{cid}.parquet").exists()
        ]
        if not frames:
            continue
        series = pd.concat(frames)
        for swarm in swarms:
            table = series[series["swarm"] == swarm].pivot_table(
                index="step", columns="seed", values="cumulative_reward"
            )
            if table.empty:
                continue
            values = table.to_numpy()
            mean, half = values.mean(axis=1), ci95_half_width(values, axis=1)
            steps = table.index.to_numpy() + 1
            ax.plot(steps, mean, color=colours[swarm], label=swarm)
            ax.fill_between(steps, mean - half, mean + half, color=colours[swarm], alpha=0.2)
        ax.set_title(f"{group_label(group.iloc[0], groups)} ({values.shape[1]} seeds)", fontsize=9)
        ax.set_xlabel("step k", fontsize=8)
        ax.set_ylabel("cumulative score $R^k$", fontsize=8)
        ax.grid(alpha=0.3)
    for ax in axes[len(keyed) :]:
        ax.set_visible(False)
    axes[0].legend(fontsize=8)
    fig.suptitle("Cumulative patrolling score (mean and 95% band over seeds)", fontsize=11)
    return fig


def _failed_cells(out_dir: Path) -> dict[str, str]:
    """``failed.json``: the cells the last invocation could not compute, and why."""
    failed = read_json(out_dir / "failed.json")
    if failed is None:
        return {}
    if not isinstance(failed, dict) or not all(
        isinstance(k, str) and isinstance(v, str) for k, v in failed.items()
    ):
        raise UserError(
            f"{out_dir / 'failed.json'}: not a table of cell ids and errors; rerun the sweep"
        )
    return failed


def write_sweep_report(out_dir: Path) -> Path:
    """Write ``out_dir/report/sweep.html``, ``sweep.md`` and the PNGs; return the HTML path.

    Drawn into a temporary folder inside the sweep folder and renamed into place at the end,
    as a run's report (:func:`twin.files.staged_folder`): a failure mid-way leaves the previous
    report, or none, never a partial one."""
    summary = read_table(out_dir / "summary.csv", {"swarm": TEXT})
    results = read_table(out_dir / "results.csv", {"swarm": TEXT, "cell": TEXT})
    manifest = read_json(out_dir / "sweep.json", required=True)
    if not isinstance(manifest, dict):
        raise UserError(f"{out_dir / 'sweep.json'}: not an object; rerun the sweep")
    out = report_dir(out_dir)  # never a link out of the sweep folder
    with staged_folder(out, _written_by_a_sweep_report) as stage:
        _draw_sweep_report(out_dir, stage, summary, results, manifest)
    return out / "sweep.html"


def check_sweep_report_folder(out_dir: Path) -> None:
    """The sweep's ``report/`` holds nothing of the user's, which drawing it again would
    delete (checked before any cell runs)."""
    check_staged_folder(out_dir / "report", _written_by_a_sweep_report)


def _written_by_a_sweep_report(name: str) -> bool:
    """A name an earlier twin's sweep report wrote into ``report/``."""
    return name in ("sweep.html", "sweep.md") or name.endswith(".png")


def _draw_sweep_report(
    out_dir: Path, out: Path, summary: pd.DataFrame, results: pd.DataFrame, manifest: dict
) -> None:
    """The sweep report's files, drawn into the folder ``out``."""
    images = []
    figure_table2(summary).savefig(out / "table2.png", dpi=100)
    images.append(("Table 2 columns per scenario", "table2.png"))
    curves = figure_curves(out_dir, results)
    if curves is not None:
        curves.savefig(out / "curves.png", dpi=100)
        images.append(("Cumulative patrolling score", "curves.png"))
    header, rows = sweep_table(summary)
    n_cells, n_done = len(manifest["cells"]), results["cell"].nunique()
    cell_seconds = results.drop_duplicates("cell")["seconds"]
    lede = (
        f"Sweep {manifest['name']!r}: {n_done} of {n_cells} cells done "
        f"({len(manifest['scenarios'])} scenarios x {max(1, n_cells // max(1, len(manifest['scenarios']) * len(manifest['seeds'])))} "
        f"parameter combinations x {len(manifest['seeds'])} seeds), swarms {', '.join(manifest['swarms'])}; "
        f"cell time {cell_seconds.sum():.1f} s in total, {cell_seconds.mean():.1f} s on average. "
        "Every number is read from summary.csv, results.csv and sweep.json."
    )
    codes = sorted(str(c) for c in results.get("code", pd.Series(dtype=str)).dropna().unique())
    if len(codes) > 1:
        lede += (
            f" WARNING: the cells were computed by {len(codes)} versions of the code "
            f"({', '.join(codes)}, column 'code' of results.csv); delete the cells of the old "
            "version and rerun to make the table consistent."
        )
    failed = _failed_cells(out_dir)
    if failed:
        lede += (
            f" {len(failed)} cells FAILED in the last invocation and are not in the tables "
            f"(failed.json): {', '.join(failed)}; fix the cause and rerun the sweep."
        )
    runs = manifest.get("invocations", [])
    run_rows = [
        [
            str(r.get(k))
            for k in ("finished", "executor", "workers", "ran", "skipped", "failed", "wall_seconds")
        ]
        for r in runs
    ]
    run_header = [
        "finished",
        "executor",
        "workers",
        "cells run",
        "already done",
        "failed",
        "wall s",
    ]
    parts = [
        "<!DOCTYPE html>",
        '<html lang="en"><head><meta charset="utf-8">',
        f"<title>twin sweep: {html.escape(manifest['name'])}</title>",
        f"<style>{CSS}</style></head><body>",
        f"<h1>Sweep report: {html.escape(manifest['name'])}</h1>",
        f"<p>{html.escape(lede)}</p>",
        "<h2>Table 2 per scenario (mean ± 95% interval over seeds)</h2>",
        html_table(header, rows, "summary"),
    ]
    md = [
        f"# Sweep report: {md_escape(manifest['name'])}",
        "",
        md_escape(lede),
        "",
        "## Table 2 per scenario (mean ± 95% interval over seeds)",
        "",
        markdown_table(header, rows),
        "",
    ]
    for title, name in images:
        parts += [
            f"<h2>{html.escape(title)}</h2>",
            f'<img src="{_data_uri(out / name)}" alt="{html.escape(title)}">',
        ]
        md += [f"## {md_escape(title)}", "", f"![{md_escape(title)}]({name})", ""]
    if failed:
        fail_rows = [[cid, error] for cid, error in failed.items()]
        parts += ["<h2>Failed cells</h2>", html_table(["cell", "error"], fail_rows, "failed")]
        md += ["## Failed cells", "", markdown_table(["cell", "error"], fail_rows), ""]
    if run_rows:
        parts += ["<h2>Invocations</h2>", html_table(run_header, run_rows, "runs")]
        md += ["## Invocations", "", markdown_table(run_header, run_rows), ""]
    parts.append("<h2>Sweep definition (sweep.json)</h2><pre>")
    parts.append(html.escape(json.dumps(manifest, indent=2)))
    parts.append("</pre></body></html>")
    html_path = out / "sweep.html"
    page, text = "\n".join(parts), "\n".join(md) + "\n"
    atomic_write(html_path, lambda p: p.write_text(page, encoding="utf-8"))
    atomic_write(out / "sweep.md", lambda p: p.write_text(text, encoding="utf-8"))
