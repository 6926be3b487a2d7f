"""A sweep cell on live SUMO gives the numbers `twin run` gives for the same seeds."""

from __future__ import annotations

from pathlib import Path

import pandas as pd
import pytest

from twin.cli import main as cli
from twin.sweep import load_sweep_config, run_sweep

ROOT = Path(__file__).resolve().parents[1]
pytest.importorskip("libsumo", reason="SUMO (libsumo) not installed")


def test_sumo_cell_equals_twin_run(tmp_path: Path) -> None:
    text = (ROOT / "configs" / "shenzhen.toml").read_text()
    text = text.replace("warmup_min = 30.0", "warmup_min = 5.0")
    assert "warmup_min = 5.0" in text
    scenario = tmp_path / "short.toml"
    scenario.write_text(text)
    sweep = tmp_path / "sweep.toml"
    sweep.write_text(
        '[sweep]\nname = "s"\nswarms = ["random", "greedy", "sweeping"]\nseeds = [3]\n'
        f'[[scenario]]\nname = "sz"\nconfig = "{scenario.name}"\n'
        'overrides = { "traffic.horizon" = 5 }\n'
    )
    run_sweep(load_sweep_config(sweep), tmp_path / "sw", workers=1, report=False)
    args = ["run", "--config", str(scenario), "--horizon", "5", "--seed", "3", "--sumo-seed", "3"]
    assert cli([*args, "--swarms", "random,greedy,sweeping", "--out", str(tmp_path / "run"),
                "--no-report", "--no-ceiling", "--quiet"]) == 0  # fmt: skip
    expected = pd.read_csv(tmp_path / "run" / "per_seed.csv").sort_values("swarm")
    got = pd.read_csv(tmp_path / "sw" / "results.csv").sort_values("swarm")
    for col in ("R_hat_T", "C_hat_T", "pct_time_max_C", "pct_map_covered"):
        assert got[col].tolist() == pytest.approx(expected[col].tolist(), rel=1e-12, abs=1e-12)


def test_a_live_cell_says_which_outputs_it_does_not_keep(tmp_path: Path, capsys) -> None:
    """A sweep's live cell runs SUMO in a forked process: what that process noticed (the
    outputs the scenario asks for, which a sweep keeps nowhere) is said by the sweep (it was
    lost with the process; probe 15's f01)."""
    from helpers import small_sumo_scenario

    (tmp_path / "scen").mkdir()
    folder = small_sumo_scenario(tmp_path / "scen", horizon=3)
    (folder / "c.sumocfg").write_text(
        '<configuration><input><net-file value="small.net.xml"/><route-files '
        'value="small.trips.xml"/></input><output><tripinfo-output value="trips.out.xml"/>'
        "</output></configuration>"
    )
    text = (folder / "small.toml").read_text()
    text = text.replace(
        'net = "small.net.xml"\nroutes = ["small.trips.xml"]', 'sumocfg = "c.sumocfg"'
    )
    (folder / "cfg.toml").write_text(text)
    sweep = folder / "sweep.toml"
    sweep.write_text(
        '[sweep]\nname = "o"\nswarms = ["random"]\nseeds = 1\n[[scenario]]\nname = "c"\n'
        'config = "cfg.toml"\n'
    )
    before = sorted(p.name for p in folder.iterdir())
    args = ["sweep", "--config", str(sweep), "--out", str(tmp_path / "sw"), "--workers", "1"]
    assert cli([*args, "--quiet", "--no-report"]) == 0
    err = capsys.readouterr().err
    assert "the outputs its files ask SUMO for (trips.out.xml) are not kept" in err, err
    assert sorted(p.name for p in folder.iterdir()) == before
