"""`twin report`: every figure present, table values equal the run's files, HTML self-contained
and every image loads in headless Chromium."""

from __future__ import annotations

import html.parser
import json
import os
import re
import shutil
import subprocess
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from twin.errors import UserError
from twin.grid import Grid
from twin.mfd import MFD, fit_quality
from twin.readback import BOUNDS
from twin.report import load_run, write_report
from twin.report.document import MONITORING_TABLE_COLUMNS, TABLE_COLUMNS
from twin.runs import FOLDER_FORMAT, write_manifest
from twin.scores import ScoreParams, coverage, initial_idleness, reward_parts, update_idleness

SWARMS = ("random", "greedy", "sweeping", "rl")

NET_XML = """<?xml version="1.0" encoding="UTF-8"?>
<net version="1.20">
  <location netOffset="0.00,0.00" convBoundary="0.00,0.00,1500.00,1000.00"/>
  <edge id=":j0_0" function="internal"><lane id=":j0_0_0" index="0" speed="13.9" length="5"
    shape="100.00,100.00 105.00,100.00"/></edge>
  <edge id="e0" from="a" to="b"><lane id="e0_0" index="0" speed="13.9" length="1400"
    shape="50.00,500.00 1450.00,500.00"/><lane id="e0_1" index="1" speed="13.9" length="1400"
    shape="50.00,503.00 1450.00,503.00"/></edge>
  <edge id="e1" from="b" to="c"><lane id="e1_0" index="0" speed="13.9" length="900"
    shape="750.00,50.00 750.00,950.00"/></edge>
</net>
"""


def _write_timing(run: Path, series: pd.DataFrame, seeds) -> None:
    """timing.csv, as every run writes it: each swarm's stage of each seed in the main process,
    its ms per step over the seed's steps and its share of the seed's seconds."""
    rows = []
    for seed in seeds:
        steps = int(series[series["seed"] == seed].groupby("swarm").size().max())
        stages = [(f"swarm {name}", 0.5 + 0.25 * n) for n, name in enumerate(SWARMS)]
        total = sum(seconds for _, seconds in stages)
        for stage, seconds in stages:
            rows.append({"seed": seed, "process": "main", "stage": stage, "seconds": seconds,
                         "ms_per_step": round(1000.0 * seconds / steps, 4),
                         "share": round(seconds / total, 4)})  # fmt: skip
    pd.DataFrame(rows).to_csv(run / "timing.csv", index=False)


def write_fixture_run(
    root: Path, seeds=(0, 1), horizon: int = 40, nx: int = 6, ny: int = 9, sumo: bool = True
) -> Path:
    """A run folder in the documented format (twin/runs.py), from random walks on a toy map.

    Independent of the core's writer: the idleness, coverage and visited share are computed here
    with twin.scores, so the report's replay check has something real to agree with.
    """
    rng = np.random.default_rng(7)
    obstacles = np.zeros((nx, ny), dtype=bool)
    obstacles[0, 0] = obstacles[2, 4] = True
    grid, params = Grid(obstacles), ScoreParams()
    ii, jj = np.indices((nx, ny))
    steps = np.arange(horizon + 1)[:, None, None]
    bump = np.exp(-((ii - 3) ** 2 + (jj - 6) ** 2) / 4.0)[None]
    importance = np.where(grid.free, np.clip(bump * steps / horizon, 0, 1), 0.0)
    series, trajectories, per_seed = [], [], []
    for seed in seeds:
        covs = {}
        for swarm in SWARMS:
            pos = np.empty((horizon + 1, 3, 2), dtype=np.int64)
            pos[0] = grid.free_cells()[rng.choice(grid.n_free, 3, replace=False)]
            idle, visited = initial_idleness(grid), np.zeros_like(obstacles)
            visited[pos[0, :, 0], pos[0, :, 1]] = True
            rows = []
            for k in range(horizon):
                feasible = grid.feasible_actions(pos[k])
                actions = np.array([rng.choice(np.flatnonzero(f)) for f in feasible])
                pos[k + 1] = grid.move(pos[k], actions)
                parts = reward_parts(grid, params, idle, importance[k], importance[k + 1],
                                     pos[k], pos[k + 1])  # fmt: skip
                idle = update_idleness(idle, pos[k + 1], grid, params.eta, params.delta)
                visited[pos[k + 1, :, 0], pos[k + 1, :, 1]] = True
                rows.append(
                    (k, parts.total.sum(), parts.importance.sum(), parts.paper.sum(),
                     coverage(idle, grid), visited[grid.free].mean())
                )  # fmt: skip
            frame = pd.DataFrame(
                rows,
                columns=["step", "reward", "importance", "paper", "coverage", "visited_share"],
            )
            frame["cumulative_reward"] = frame["reward"].cumsum()
            frame["belief_error"] = rng.uniform(0.0, 0.3, horizon)
            series.append(frame.assign(seed=seed, swarm=swarm))
            covs[swarm] = frame["coverage"].to_numpy()
            n = pos.shape[1]
            trajectories.append(
                pd.DataFrame(
                    {
                        "seed": seed,
                        "swarm": swarm,
                        "step": np.repeat(np.arange(horizon + 1), n),
                        "drone": np.tile(np.arange(n), horizon + 1),
                        "i": pos[..., 0].ravel(),
                        "j": pos[..., 1].ravel(),
                    }
                )
            )
        best = np.max(list(covs.values()), axis=0)
        for swarm in SWARMS:
            f = series[-len(SWARMS) + SWARMS.index(swarm)]
            per_seed.append(
                {
                    "seed": seed,
                    "swarm": swarm,
                    "R_hat_T": f["reward"].mean(),
                    "R_hat_T_importance": f["importance"].mean(),
                    "R_hat_T_idleness": (f["reward"] - f["importance"]).mean(),
                    "R_hat_T_paper": f["paper"].mean(),
                    "C_hat_T": f["coverage"].mean(),
                    "C_hat_T_ceiling": 0.2,
                    "pct_time_max_C": 100.0 * np.mean(covs[swarm] >= best),
                    "pct_map_covered": 100.0 * f["visited_share"].iloc[-1],
                }
            )
    per_seed = pd.DataFrame(per_seed)
    summary = per_seed.groupby("swarm", sort=False).agg(["mean", "std"])
    out = pd.DataFrame({"swarm": list(SWARMS)})
    for col, _, _ in TABLE_COLUMNS:
        out[col] = summary[(col, "mean")].to_numpy()
        if len(seeds) > 1:
            out[f"{col}_ci95"] = 2.0 * summary[(col, "std")].to_numpy()  # any half-width will do
    out["n_seeds"] = len(seeds)
    run = root / "run"
    run.mkdir(parents=True)
    # monitoring: any numbers in the documented format (twin/runs.py) will do
    monitoring = pd.DataFrame({"swarm": list(SWARMS)})
    for col, _, _ in MONITORING_TABLE_COLUMNS:  # within each column's range
        monitoring[col] = rng.uniform(0, min(50.0, BOUNDS.get(col, (0, 50))[1]), len(SWARMS))
        monitoring[f"{col}_ci95"] = rng.uniform(0, 5, len(SWARMS))
    monitoring.loc[1, "latency_p90_steps"] = np.nan  # a swarm that saw no event
    monitoring["n_seeds"] = len(seeds)
    monitoring.to_csv(run / "monitoring.csv", index=False)
    events = []
    for seed in seeds:
        for e in range(5):
            onset, duration = int(rng.integers(0, horizon - 5)), int(rng.integers(1, 6))
            for swarm in SWARMS:
                seen = bool(rng.random() < 0.5)
                first = onset + int(rng.integers(0, duration)) if seen else -1
                events.append(
                    {"seed": seed, "event": e, "i": int(rng.integers(0, nx)),
                     "j": int(rng.integers(0, ny)), "onset": onset, "duration": duration,
                     "peak": float(rng.uniform(0.5, 1.0)), "swarm": swarm, "seen": seen,
                     "first_seen": first, "latency_steps": first - onset if seen else -1}
                )  # fmt: skip
    pd.DataFrame(events).to_parquet(run / "events.parquet", index=False)
    series = pd.concat(series).drop(columns=["importance", "paper"])
    series.to_parquet(run / "series.parquet", index=False)
    pd.concat(trajectories).to_parquet(run / "trajectories.parquet", index=False)
    per_seed.to_csv(run / "per_seed.csv", index=False)
    out.to_csv(run / "summary.csv", index=False)
    np.savez_compressed(
        run / "importance.npz", importance=importance.astype(np.float32), obstacles=obstacles
    )
    meta = {
        "command": "twin run --config fixture.toml",
        "seeds": list(seeds),
        "swarms": list(SWARMS),
        "horizon": horizon,
        "params": {"eta": params.eta, "delta": params.delta, "alpha_T": 1.0, "alpha_I": 0.5},
        "checkpoint": {"path": "data/qnet.pt", "sha256": "ab12cd34"},
        "timings": {"patrol_seconds": [round(1.234 + 1.111 * n, 3) for n in range(len(seeds))]},
        "versions": {"python": "3.11.7", "numpy": "2.4.6"},
        "monitoring": {"threshold": 0.5, "min_duration": 1, "weight_floor": 0.05},
        "folder_format": FOLDER_FORMAT,  # the intervals of one seed left empty, as now
    }
    (run / "run.json").write_text(json.dumps(meta))
    _write_timing(run, series, seeds)
    if sumo:
        (run / "net.net.xml").write_text(NET_XML)
        cell = 1500.0 / ny
        network = {
            "name": "toy",
            "net_file": "net.net.xml",
            "grid": {"x0": 0.0, "y_top": nx * cell, "cell_m": cell, "nx": nx, "ny": ny,
                     "bbox": [50.0, 50.0, 1450.0, 950.0]},
            "row_0": "north",
        }  # fmt: skip
        (run / "network.json").write_text(json.dumps(network))
        n = 600
        count = rng.integers(1, 40, n)
        density = count / 0.5
        limit = np.full(n, 13.9)
        speed = limit * 0.7 * np.exp(-density / 40.0) * rng.uniform(0.9, 1.1, n)
        pd.DataFrame(
            {"step": np.arange(n) % (horizon + 1), "i": rng.integers(0, nx, n),
             "j": rng.integers(0, ny, n), "count": count, "lane_km": 0.5, "density": density,
             "speed": speed, "speed_limit": limit,
             "speed_mfd_online": MFD(0.7013, 39.87).speed(density, limit)}
        ).to_parquet(run / "mfd_samples.parquet", index=False)  # fmt: skip
        quality = fit_quality(MFD(0.7013, 39.87), density, speed, limit)
        mfd = {"form": "underwood: v(k) = a * v_lim * exp(-k / k_c)", "a": 0.7013, "k_c": 39.87,
               "fit": "online", "n_samples": n, "r2": quality["r2"],
               "rmse_kmh": quality["rmse_kmh"],
               "density_unit": "veh per lane-km", "speed_unit": "m/s"}  # fmt: skip
        (run / "mfd.json").write_text(json.dumps(mfd))
        meta["traffic"] = {"kind": "sumo", "begin": "07:00:00", "step_s": 75.0}
        (run / "run.json").write_text(json.dumps(meta))
    _derive_files(run, obstacles)
    write_manifest(run)  # the last file of a finished run folder
    return run


def _derive_files(run: Path, obstacles: np.ndarray) -> None:
    """events.parquet's sightings, per_seed.csv, summary.csv and monitoring.csv made from the
    fixture's primary files as twin makes them, so the folder agrees with itself (the report
    refuses derived files that contradict their sources)."""
    from twin.metrics import aggregate, learned_against_best_classical
    from twin.report.derived import (
        Primary,
        ceiling_scores,
        event_rows,
        monitoring_scores,
        series_scores,
    )

    read = pd.read_parquet
    primary = Primary(run, read(run / "series.parquet"), read(run / "trajectories.parquet"),
                      read(run / "events.parquet"), obstacles,
                      json.loads((run / "run.json").read_text()), list(SWARMS))  # fmt: skip
    events = event_rows(primary, pd.DataFrame())
    events.to_parquet(run / "events.parquet", index=False)
    primary.events = events
    forged = pd.read_csv(run / "per_seed.csv")
    per_seed = series_scores(primary, forged)
    for part in (ceiling_scores(primary, forged), monitoring_scores(primary, forged)):
        per_seed = per_seed.merge(part, on=["seed", "swarm"], how="left")
    split = forged[["seed", "swarm", "R_hat_T_importance", "R_hat_T_paper"]].copy()
    per_seed = per_seed.merge(split, on=["seed", "swarm"], how="left")
    per_seed["R_hat_T_idleness"] = per_seed["R_hat_T"] - per_seed["R_hat_T_importance"]
    order = per_seed["swarm"].map(SWARMS.index)
    per_seed = per_seed.assign(order=order).sort_values(["seed", "order"]).drop(columns="order")
    per_seed.to_csv(run / "per_seed.csv", index=False)
    learned_against_best_classical(per_seed).to_csv(run / "comparison.csv", index=False)
    summary = aggregate(per_seed)
    summary.to_csv(run / "summary.csv", index=False)
    columns = ["swarm"] + [
        c for col, _, _ in MONITORING_TABLE_COLUMNS for c in (col, f"{col}_ci95")
        if c in summary.columns
    ] + ["n_seeds"]  # fmt: skip
    summary[columns].to_csv(run / "monitoring.csv", index=False)


@pytest.fixture(scope="module")
def report(tmp_path_factory) -> Path:
    run = write_fixture_run(tmp_path_factory.mktemp("report"))
    return write_report(run)


FIGURES = ("scores.png", "snapshots.png", "trajectories.png", "animation.gif", "traffic.png",
           "network.png", "events.png", "belief.png", "mfd.png")  # fmt: skip


def test_every_figure_is_written_and_inlined(report: Path) -> None:
    text = report.read_text()
    for name in FIGURES:
        assert (report.parent / name).stat().st_size > 1000, name
    inlined = re.findall(r'<img src="data:image/(png|gif);base64,', text)
    assert len(inlined) == len(FIGURES)
    assert (report.parent / "animation.gif").stat().st_size < 3_000_000
    # self-contained: no external resource at all
    assert not re.search(r'(src|href)="(https?:)?//', text)
    md = (report.parent / "report.md").read_text()
    for name in FIGURES:
        assert f"]({name})" in md


def test_the_reports_words_agree_with_its_files(report: Path) -> None:
    """Fig. 2's step is the peak of mean importance from the step its trails need on, as the
    caption now says (it said "the step with the highest mean importance", which the run's
    importance.npz contradicted); the Ĉ_T ceiling is a reference, as the CLI says, not "an
    upper bound" (probe 27d's k01, k02)."""
    import numpy as np

    from twin.report import figures

    md = (report.parent / "report.md").read_text()
    said = re.search(
        r"at k = (\d+), the step with the highest mean importance from k = (\d+) on", md
    )
    assert said, md
    peak, start = int(said[1]), int(said[2])
    with np.load(report.parent.parent / "importance.npz") as data:
        maps = data[data.files[0]]
    run = json.loads((report.parent.parent / "run.json").read_text())
    assert start == min(figures.TRAIL_STEPS, run["horizon"])
    mean = maps.reshape(len(maps), -1).mean(axis=1)
    assert peak == start + int(np.argmax(mean[start:]))  # (an obstacle, 0 throughout, alike)
    assert "upper bound, so a" not in md and "a reference, not a bound" in md


def _parse_cell(text: str) -> tuple[float, float | None]:
    parts = text.split("±")
    return float(parts[0]), float(parts[1]) if len(parts) > 1 else None


def _check_rows(
    rows: list[list[str]], summary: pd.DataFrame, spec=TABLE_COLUMNS, header=None
) -> None:
    """Every cell equals the CSV; with ``header``, the columns shown are exactly the CSV's
    columns of ``spec`` that hold a value."""
    expected_cols = [c for c in spec if c[0] in summary.columns and summary[c[0]].notna().any()]
    if header is not None:
        assert header[1 : 1 + len(expected_cols)] == [h for _, h, _ in expected_cols]
    assert [r[0] for r in rows] == list(summary["swarm"])
    for row, (_, expected) in zip(rows, summary.iterrows(), strict=True):
        assert len(row) == len(expected_cols) + 2
        for cell, (col, _, decimals) in zip(row[1:], expected_cols, strict=False):
            if cell == "-":
                assert np.isnan(expected[col]), (col, expected[col])
                continue
            value, half = _parse_cell(cell)
            tol = 0.5 * 10**-decimals + 1e-12
            assert abs(value - expected[col]) <= tol, (col, cell, expected[col])
            if np.isnan(expected[f"{col}_ci95"]):  # one seed gave the figure: no interval
                assert half is None, (col, cell)
            else:
                assert half is not None and abs(half - expected[f"{col}_ci95"]) <= tol
        assert int(row[-1]) == expected["n_seeds"]


def _markdown_block(md: str, title: str) -> tuple[list[str], list[list[str]]]:
    block = md.split(f"## {title}")[1].split("\n\n")[1]
    lines = [[c.strip() for c in line.strip("|").split("|")] for line in block.splitlines()]
    return lines[0], lines[2:]


def test_markdown_tables_equal_summary_and_monitoring_csv(report: Path) -> None:
    run_dir = report.parent.parent
    md = (report.parent / "report.md").read_text()
    header, rows = _markdown_block(md, "Scores (paper's Table 2)")
    summary = pd.read_csv(run_dir / "summary.csv")
    _check_rows(rows, summary, header=header)
    assert "as Def. 4 prints it" in " ".join(header) and "jumping drones (reference)" in " ".join(
        header
    )
    header, rows = _markdown_block(md, "Monitoring against ground truth")
    _check_rows(rows, pd.read_csv(run_dir / "monitoring.csv"), MONITORING_TABLE_COLUMNS, header)
    assert "relative to the swarms compared here (random, greedy, sweeping, rl)" in md


class _TableParser(html.parser.HTMLParser):
    def __init__(self) -> None:
        super().__init__()
        self.tables: dict[str, list[list[str]]] = {}
        self._current: str | None = None
        self._cell: list[str] | None = None

    def handle_starttag(self, tag, attrs):
        if tag == "table":
            self._current = dict(attrs).get("class", "")
            self.tables[self._current] = []
        elif tag == "tr" and self._current is not None:
            self.tables[self._current].append([])
        elif tag in ("td", "th"):
            self._cell = []

    def handle_endtag(self, tag):
        if tag in ("td", "th") and self._cell is not None and self._current is not None:
            self.tables[self._current][-1].append("".join(self._cell).strip())
            self._cell = None
        elif tag == "table":
            self._current = None

    def handle_data(self, data):
        if self._cell is not None:
            self._cell.append(data)


def test_html_table_and_metadata_equal_run_files(report: Path) -> None:
    run_dir = report.parent.parent
    parser = _TableParser()
    parser.feed(report.read_text())
    summary = parser.tables["summary"]
    _check_rows(summary[1:], pd.read_csv(run_dir / "summary.csv"), header=summary[0])
    monitoring = parser.tables["monitoring"]
    _check_rows(
        monitoring[1:],
        pd.read_csv(run_dir / "monitoring.csv"),
        MONITORING_TABLE_COLUMNS,
        monitoring[0],
    )
    meta = dict(parser.tables["meta"][1:])
    run = json.loads((run_dir / "run.json").read_text())
    assert meta["checkpoint.sha256"] == run["checkpoint"]["sha256"]
    assert json.loads(meta["timings.patrol_seconds"]) == run["timings"]["patrol_seconds"]
    assert json.loads(meta["seeds"]) == run["seeds"]
    mfd = json.loads((run_dir / "mfd.json").read_text())
    for key in ("a", "k_c", "r2", "rmse_kmh", "n_samples"):
        assert f"{key} = {json.dumps(mfd[key])}" in report.read_text()


def test_replayed_idleness_matches_stored_coverage(report: Path) -> None:
    text = report.read_text()
    assert "coverage matches series.parquet" in text
    rf = load_run(report.parent.parent)
    assert rf.idleness("greedy").shape == (rf.horizon + 1, *rf.obstacles.shape)


def test_report_without_sumo_files_and_one_seed(tmp_path: Path) -> None:
    run = write_fixture_run(tmp_path, seeds=(3,), sumo=False)
    out = write_report(run, animation=False)
    names = {p.name for p in out.parent.iterdir()}
    assert {"scores.png", "snapshots.png", "trajectories.png", "network.png"} <= names
    assert "mfd.png" not in names and "animation.gif" not in names
    assert "one seed, so no interval" in out.read_text()


def test_missing_files_are_one_line_errors(tmp_path: Path, capsys) -> None:
    from twin.cli import main

    with pytest.raises(UserError, match=r"missing series\.parquet"):
        write_report(tmp_path)
    assert main(["report", str(tmp_path / "nope")]) == 2
    err = capsys.readouterr().err
    assert err.startswith("twin: error:") and err.count("\n") == 1


@pytest.mark.parametrize(
    "column, value, words",
    [
        ("difference", 9.0, "comparison.csv: difference = 9 for swarm 'rl', but per_seed.csv"),
        ("against", "random", "comparison.csv: against = 'random' for swarm 'rl', but per_seed"),
        ("n_seeds", 5, "comparison.csv: n_seeds = 5 for swarm 'rl', but per_seed.csv gives 2"),
    ],
)
def test_a_comparison_its_seeds_contradict_is_refused(tmp_path, column, value, words) -> None:
    run = write_fixture_run(tmp_path, sumo=False)
    load_run(run)  # as written, the learned swarm against the best classical one reads back
    frame = pd.read_csv(run / "comparison.csv")
    frame[column] = value
    frame.to_csv(run / "comparison.csv", index=False)
    write_manifest(run)
    with pytest.raises(UserError, match=re.escape(words)):
        load_run(run)


@pytest.mark.parametrize(
    ("name", "edit", "words"),
    [  # probe 20's P2-f09a: accepted
        ("comparison.csv", lambda f: f.drop(columns="ratio"), "lacks the column 'ratio'"),
        (
            "comparison.csv",
            lambda f: f.rename(columns={"difference_ci95": "difference_ci55"}),
            "holds a column 'difference_ci55', which twin does not write",
        ),
        ("comparison.csv", lambda f: f.assign(bogus=1), "holds a column 'bogus'"),
    ],
)
def test_a_comparison_of_other_columns_is_refused(tmp_path, name, edit, words) -> None:
    run = write_fixture_run(tmp_path, sumo=False)
    edit(pd.read_csv(run / name)).to_csv(run / name, index=False)
    write_manifest(run)
    with pytest.raises(UserError, match=re.escape(f"{name}: {words}")):
        load_run(run)


def test_a_column_named_twice_in_a_csv_header_is_named_as_written(tmp_path) -> None:
    """pandas reads a repeated header as 'R_hat_T.1': the message named that, not the file's
    column (probe 20's P2-f09a)."""
    run = write_fixture_run(tmp_path, sumo=False)
    text = (run / "per_seed.csv").read_text().splitlines()
    header, *rows = text
    (run / "per_seed.csv").write_text(
        "\n".join([header + ",R_hat_T", *(r + ",1.0" for r in rows)]) + "\n"
    )
    write_manifest(run)
    with pytest.raises(UserError, match=re.escape("per_seed.csv: column 'R_hat_T' appears twice")):
        load_run(run)


def test_report_of_a_real_patrol_run(tmp_path: Path) -> None:
    """The core's own run-folder writer, read back: the table equals its summary.csv."""
    from twin.patrol import random_starts, run_patrol
    from twin.runs import write_run
    from twin.swarms import make_policy
    from twin.traffic.synthetic import Disturbance, SyntheticTraffic

    grid = Grid.open(8, 12)
    source = SyntheticTraffic(grid, [Disturbance("big", 3, 4, 1.0, 2.0)], horizon=30)
    results = []
    for seed in (0, 1):
        starts = random_starts(grid, 3, np.random.default_rng(seed))
        swarms = {name: make_policy(name) for name in ("random", "greedy", "sweeping")}
        results.append(run_patrol(source, swarms, starts, ScoreParams(), seed))
    write_run(tmp_path, results, {"params": vars(ScoreParams())})
    out = write_report(tmp_path, animation=False)
    md = (out.parent / "report.md").read_text()
    header, rows = _markdown_block(md, "Scores (paper's Table 2)")
    summary = pd.read_csv(tmp_path / "summary.csv")
    _check_rows(rows, summary, header=header)
    assert "Ĉ_T of jumping drones (reference)" in header
    header, rows = _markdown_block(md, "Monitoring against ground truth")
    _check_rows(rows, pd.read_csv(tmp_path / "monitoring.csv"), MONITORING_TABLE_COLUMNS, header)
    assert "coverage matches series.parquet" in out.read_text()
    assert {"events.png", "belief.png"} <= {p.name for p in out.parent.iterdir()}
    events = pd.read_parquet(tmp_path / "events.parquet")
    n_first = events[events["seed"] == 0]["event"].nunique()
    assert f"({n_first} events" in md


CHECK_SCRIPT = """<script>
window.addEventListener('load', function () {
  var imgs = Array.prototype.slice.call(document.images);
  var ok = imgs.filter(function (i) { return i.complete && i.naturalWidth > 0; }).length;
  var p = document.createElement('pre');
  p.id = 'image-check';
  p.textContent = 'IMAGES ' + ok + '/' + imgs.length;
  document.body.appendChild(p);
});
</script></body>"""


def test_every_image_loads_in_headless_chromium(report: Path, tmp_path: Path) -> None:
    browser = shutil.which("chromium") or shutil.which("chromium-browser")
    if browser is None:
        pytest.skip("chromium not installed (apt-get install -y chromium)")
    page = tmp_path / "check.html"
    page.write_text(report.read_text().replace("</body>", CHECK_SCRIPT))
    cmd = [
        browser, "--headless", "--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
        "--disable-background-networking", "--disable-component-update", "--disable-sync",
        f"--user-data-dir={tmp_path / 'profile'}", "--virtual-time-budget=10000", "--dump-dom",
        page.as_uri(),
    ]  # fmt: skip
    dom = subprocess.run(cmd, capture_output=True, text=True, timeout=120).stdout
    found = re.search(r"IMAGES (\d+)/(\d+)", dom)
    assert found, "the check script did not run"
    assert found.group(1) == found.group(2) == str(len(FIGURES))


def _full_disk(monkeypatch, where: str, name: str, filename: bool) -> None:
    """The disk fills while the report writes ``name`` (a figure or a page)."""
    import errno

    import matplotlib.figure

    import twin.report.document as document

    def raise_full(path) -> None:
        raise OSError(errno.ENOSPC, "No space left on device", *([str(path)] if filename else []))

    if where == "figure":
        real_save = matplotlib.figure.Figure.savefig

        def savefig(self, path, *args, **kwargs):
            if Path(path).name == name:
                raise_full(path)
            return real_save(self, path, *args, **kwargs)

        monkeypatch.setattr(matplotlib.figure.Figure, "savefig", savefig)
    else:
        real_write = document.atomic_write

        def atomic_write(path, write):
            if Path(path).name == name:
                return real_write(path, lambda p: raise_full(p))
            return real_write(path, write)

        monkeypatch.setattr(document, "atomic_write", atomic_write)


# name -> (where the disk fills, the file being written, whether the error names it)
FULL_DISK = {
    "figure, named": ("figure", "traffic.png", True),
    "figure, unnamed": ("figure", "scores.png", False),
    "page, named": ("page", "report.html", True),
    "page, unnamed": ("page", "report.md", False),
}


@pytest.mark.parametrize("earlier", [False, True], ids=["first report", "earlier report"])
@pytest.mark.parametrize("case", list(FULL_DISK))
def test_full_disk_during_report_is_one_line_and_leaves_no_partial_report(
    tmp_path: Path, monkeypatch, capsys, case, earlier
) -> None:
    from twin.cli import main

    run = write_fixture_run(tmp_path, seeds=(3,), sumo=False)
    if earlier:
        write_report(run, animation=False)
        before = {p.name: p.read_bytes() for p in (run / "report").iterdir()}
    name = FULL_DISK[case][1]
    _full_disk(monkeypatch, *FULL_DISK[case])
    capsys.readouterr()
    assert main(["report", str(run), "--no-animation"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and err.startswith("twin: error: "), err
    assert f"{run / 'report' / name}: No space left on device" in err, err
    assert "free some space on that disk" in err and "--out" not in err, err
    assert ".tmp" not in err
    if earlier:  # the earlier report is left whole
        assert {p.name: p.read_bytes() for p in (run / "report").iterdir()} == before
    else:
        assert not (run / "report").exists()
    assert not [p for p in run.iterdir() if p.name.startswith(".report")]


def test_report_replaces_an_earlier_report_but_never_a_users_file(tmp_path: Path) -> None:
    """report/ is replaced whole, with what an earlier report wrote there (it lists its files);
    a file of the user's in it is refused in one line, and kept (it was deleted with the old
    report). An earlier twin's report, which lists nothing, may hold report files alone."""
    run = write_fixture_run(tmp_path, seeds=(3,), sumo=False)
    write_report(run, animation=False)
    folder = run / "report"
    listing = folder / ".twin-files"
    assert {"report.html", "report.md", "scores.png"} <= set(listing.read_text().split())
    (folder / "stale.png").write_text("a figure an earlier report drew")
    listing.write_text(listing.read_text() + "stale.png\n")
    out = write_report(run, animation=False)
    assert out == folder / "report.html" and out.is_file()
    assert not (folder / "stale.png").exists()
    assert sorted(p.name for p in run.iterdir() if p.name.startswith(".")) == []
    (folder / "notes.txt").write_text("mine")
    with pytest.raises(UserError, match=re.escape(f"{folder / 'notes.txt'}: not written by")):
        write_report(run, animation=False)
    assert (folder / "notes.txt").read_text() == "mine" and out.is_file()
    listing.unlink()  # as an earlier twin left it
    with pytest.raises(UserError, match=re.escape("notes.txt: not written by twin")):
        write_report(run, animation=False)
    (folder / "notes.txt").unlink()
    (folder / "old.png").write_text("a figure an earlier twin drew")
    write_report(run, animation=False)
    assert not (folder / "old.png").exists() and listing.is_file()


def test_matplotlib_keeps_its_cache_in_twins_cache_not_the_home(tmp_path):
    """Drawing a report writes matplotlib's font cache and config into twin's cache (unless
    MPLCONFIGDIR is set), never into the user's home."""
    import subprocess
    import sys

    env = {k: v for k, v in os.environ.items() if k not in ("MPLCONFIGDIR", "XDG_CACHE_HOME",
                                                             "XDG_CONFIG_HOME")}  # fmt: skip
    env |= {"HOME": str(tmp_path / "home"), "TWIN_CACHE_DIR": str(tmp_path / "cache")}
    (tmp_path / "home").mkdir()
    code = (
        "import twin.report, matplotlib, matplotlib.font_manager; "
        "print(matplotlib.get_configdir()); print(matplotlib.get_cachedir())"
    )
    out = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True)
    assert out.returncode == 0, out.stderr
    assert out.stdout.split() == [str(tmp_path / "cache" / "matplotlib")] * 2
    assert not any((tmp_path / "home").iterdir())
