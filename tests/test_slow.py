"""The issues' done-criteria on the full scenarios (minutes): `python -m pytest -m long`."""

from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from twin.cli import main

pytestmark = pytest.mark.long
ROOT = Path(__file__).resolve().parents[1]


def test_synthetic_table2_over_ten_seeds(tmp_path):
    out = tmp_path / "run"
    args = ["evaluate", "--config", str(ROOT / "configs/synthetic.toml"), "--seeds", "10",
            "--swarms", "random,greedy,sweeping,rl", "--out", str(out), "--no-report", "--quiet"]  # fmt: skip
    assert main(args) == 0
    t = pd.read_csv(out / "summary.csv").set_index("swarm")
    assert t.loc["greedy", "R_hat_T"] >= 1.5 * t.loc["random", "R_hat_T"]
    assert t.loc["sweeping", "pct_map_covered"] == 100.0
    assert t.loc["greedy", "pct_map_covered"] <= 70.0
    assert t.loc["random", "pct_map_covered"] >= 90.0
    assert t.loc["rl", "R_hat_T"] >= 1.05 * t.loc["greedy", "R_hat_T"]
    assert t.loc[t["role"] == "swarm", "C_hat_T"].idxmax() == "rl"  # ceiling rows aside


def test_default_rush_hour_run_shows_congestion_forming_and_dissolving(tmp_path):
    out = tmp_path / "run"
    assert main(["run", "--out", str(out), "--quiet"]) == 0
    maps = np.load(out / "importance.npz")["importance"]
    busiest = np.unravel_index(maps.max(axis=0).argmax(), maps.shape[1:])
    series = maps[:, busiest[0], busiest[1]]
    peak = int(series.argmax())
    assert 0 < peak < len(series) - 1
    assert series[peak] > 3 * max(series[0], series[-1])
    assert (out / "report" / "report.html").exists()
    t = pd.read_csv(out / "summary.csv").set_index("swarm")
    assert {"random", "greedy", "sweeping", "rl"} <= set(t.index)
