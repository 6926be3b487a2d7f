"""The transfer report: ``report/transfer.html`` (self-contained) with the matrix, its heatmap
(``report/heatmap.png``: learned minus best classical R_hat_T per row and column), the learning
curves (``report/curves.png``), the classical swarms and ceilings per column, and the rows'
provenance."""

from __future__ import annotations

import html
import json
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd
from matplotlib.figure import Figure

from twin.files import atomic_write
from twin.metrics import BOUND, ORACLE
from twin.report.document import CSS, _data_uri, html_table, report_dir
from twin.transfer.matrix import format_matrix, verdict


def figure_heatmap(matrix: pd.DataFrame) -> Figure:
    """Rows (trained on, learned swarm) x columns (evaluated on), coloured by the paired
    difference to the best classical swarm, each cell annotated with it and its 95% interval."""
    rows = list(dict.fromkeys(matrix["swarm"]))
    cols = list(dict.fromkeys(matrix["evaluated_on"]))
    values = np.full((len(rows), len(cols)), np.nan)
    notes = [["" for _ in cols] for _ in rows]
    for r in matrix.itertuples(index=False):
        i, j = rows.index(r.swarm), cols.index(r.evaluated_on)
        values[i, j] = r.difference
        spread = f"± {r.difference_ci95:.3f}" if np.isfinite(r.difference_ci95) else "(one seed)"
        notes[i][j] = f"{r.difference:+.3f}\n{spread}"
    fig = Figure(figsize=(2.2 + 1.8 * len(cols), 1.0 + 0.55 * len(rows)))
    ax = fig.add_subplot()
    span = float(np.nanmax(np.abs(values))) if np.isfinite(values).any() else 1.0
    image = ax.imshow(values, cmap="RdBu", vmin=-span, vmax=span, aspect="auto")
    ax.set_xticks(range(len(cols)), cols)
    ax.set_yticks(range(len(rows)), rows)
    ax.set_xlabel("evaluated on")
    ax.set_ylabel("trained on (learned swarm)")
    for i in range(len(rows)):
        for j in range(len(cols)):
            ax.text(j, i, notes[i][j], ha="center", va="center", fontsize=8)
    fig.colorbar(image, ax=ax, label="R_hat_T: learned - best classical")
    fig.tight_layout()
    return fig


def figure_curves(curves: dict[str, pd.DataFrame]) -> Figure | None:
    """Each trained row's learning curve: mean R_hat_T over the validation seeds against
    gradient updates."""
    curves = {name: c for name, c in curves.items() if not c.empty}
    if not curves:
        return None
    fig = Figure(figsize=(7, 3.5))
    ax = fig.add_subplot()
    for name, curve in curves.items():
        mean = curve.groupby("updates")["R_hat_T"].mean()
        ax.plot(mean.index, mean.to_numpy(), marker="o", label=name)
    ax.set_xlabel("gradient updates")
    ax.set_ylabel("R_hat_T, validation seeds")
    ax.legend(fontsize=8)
    fig.tight_layout()
    return fig


def _save(fig: Figure, path: Path) -> None:
    atomic_write(path, lambda p: fig.savefig(p, format="png", dpi=110))


def write_transfer_report(
    out: Path, matrix: pd.DataFrame, results: pd.DataFrame, manifest: dict[str, Any]
) -> Path:
    """Write ``report/transfer.html`` and its figures; returns the page's path."""
    folder = report_dir(out)
    folder.mkdir(parents=True, exist_ok=True)
    parts = [f"<h1>Transfer matrix: {html.escape(manifest['name'])}</h1>"]
    parts.append(f"<p><b>{html.escape(verdict(matrix))}</b></p>")
    parts.append(
        f"<p class='caption'>Evaluation seeds {manifest['seeds']} per column; config "
        f"{html.escape(manifest['config'])}. Each cell: the learned swarm's R_hat_T minus the "
        "best classical swarm's (highest mean on that column) on the same traffic, paired over "
        "the seeds, with the 95% interval; the share of the gap from that swarm to the oracle "
        "it closes; events seen and median latency (the best classical swarm's in brackets).</p>"
    )
    if not matrix.empty:
        _save(figure_heatmap(matrix), folder / "heatmap.png")
        parts.append(f"<img src='{_data_uri(folder / 'heatmap.png')}' alt='heatmap'>")
        header = ["trained on", "swarm", "evaluated on", "best classical", "learned - best",
                  "95% CI", "gap to oracle closed", "gap to bound closed", "events seen %",
                  "best: events seen %", "median latency (steps)", "best: median latency"]  # fmt: skip
        rows = [
            [
                r.trained_on,
                r.swarm,
                r.evaluated_on,
                r.best_classical,
                f"{r.difference:+.4f}",
                f"± {r.difference_ci95:.4f}"
                if np.isfinite(r.difference_ci95)
                else "one seed: none",
                _pct(r.gap_closed_oracle),
                _pct(r.gap_closed_bound),
                _num(r.pct_events_seen, 1),
                _num(r.best_pct_events_seen, 1),
                _num(r.latency_median_steps, 1),
                _num(r.best_latency_median_steps, 1),
            ]
            for r in matrix.itertuples(index=False)
        ]
        parts.append("<h2>Matrix</h2>" + html_table(header, rows))
    parts.append("<h2>Every swarm and ceiling per column (mean R_hat_T over the seeds)</h2>")
    means = results.groupby(["scenario", "swarm"], sort=False)["R_hat_T"].agg(["mean", "count"])
    rows = [[col, swarm, f"{m:.4f}", str(int(n))] for (col, swarm), (m, n) in means.iterrows()]
    parts.append(html_table(["evaluated on", "swarm", "R_hat_T", "seeds"], rows))
    parts.append(
        f"<p class='caption'>{html.escape(ORACLE)}: the best of several planners told the true "
        f"maps; {html.escape(BOUND)}: a relaxation no swarm can exceed.</p>"
    )
    curves = {}
    prov_rows = []
    for name, record in manifest["rows"].items():
        curve = pd.DataFrame((record.get("curve") or {}).get("points", []))
        curves[name] = curve
        last = ""
        if not curve.empty:
            final = curve[curve["updates"] == curve["updates"].max()]["R_hat_T"].mean()
            last = f"{final:.4f}"
        recipe = record.get("recipe") or {}
        init = recipe.get("init") or {}
        prov_rows.append([
            name, "loaded " + record["loaded"] if "loaded" in record else "trained",
            str(recipe.get("traffic")), "/".join(Path(init["path"]).parts[-3:]) if init else "",
            str(record.get("updates", "")), str(record.get("wall_s")), last,
            record.get("qnet_sha256", "")[:12],
        ])  # fmt: skip
    figure = figure_curves(curves)
    parts.append("<h2>Rows: how each checkpoint was made</h2>")
    parts.append(html_table(
        ["row", "checkpoint", "traffic", "init from", "updates", "wall s",
         "final R_hat_T (validation)", "sha256"], prov_rows))  # fmt: skip
    if figure is not None:
        _save(figure, folder / "curves.png")
        parts.append(f"<img src='{_data_uri(folder / 'curves.png')}' alt='learning curves'>")
        parts.append(
            "<p class='caption'>Learning curves: R_hat_T of the rl swarm on the validation "
            "seeds (never the evaluation seeds) against gradient updates; provenance.json "
            "beside each checkpoint in rows/ holds the command, recipe, seeds and schedule.</p>"
        )
    parts.append("<h2>Matrix (Markdown)</h2><pre>" + html.escape(format_matrix(matrix)) + "</pre>")
    parts.append(
        "<h2>Invocations</h2><pre>"
        + html.escape(json.dumps(manifest["invocations"], indent=1))
        + "</pre>"
    )
    page = (
        "<!doctype html><html><head><meta charset='utf-8'><title>transfer matrix</title>"
        f"<style>{CSS}</style></head><body>" + "\n".join(parts) + "</body></html>"
    )
    path = folder / "transfer.html"
    atomic_write(path, lambda p: p.write_text(page, encoding="utf-8"))
    return path


def _pct(value: float) -> str:
    return "n/a" if not np.isfinite(value) else f"{100 * value:+.1f}%"


def _num(value: float, digits: int) -> str:
    return "n/a" if not np.isfinite(value) else f"{value:.{digits}f}"
