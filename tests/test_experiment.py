"""The experiment runner: one path from a scenario to results for every command."""

from __future__ import annotations

import json

import numpy as np
import pandas as pd
import pytest

from twin.cli import main as twin_main
from twin.config import load_config
from twin.experiment import Experiment, run_experiment
from twin.swarms import make_policy

SYNTHETIC = """
[grid]
nx = 6
ny = 8
[swarm]
n_drones = 3
[traffic]
kind = "synthetic"
horizon = 40
[[traffic.disturbances]]
kind = "big"
i = 2
j = 3
sigma = 2.0
[evaluate]
swarms = ["random", "greedy"]
[swarm_options.rl-decentralized]
eps = 0.5
"""


@pytest.fixture
def synthetic(tmp_path):
    path = tmp_path / "tiny.toml"
    path.write_text(SYNTHETIC)
    return path


def test_runner_gives_evaluate_the_same_numbers(synthetic, tmp_path):
    out = tmp_path / "run"
    assert twin_main(["evaluate", "--config", str(synthetic), "--seeds", "2", "--seed", "4",
                      "--no-report", "--quiet", "--out", str(out)]) == 0  # fmt: skip
    per_seed = pd.read_csv(out / "per_seed.csv")
    experiment = Experiment(load_config(synthetic), ["random", "greedy"], seeds=[4, 5])
    for result in run_experiment(experiment).results:
        rows = per_seed[per_seed.seed == result.seed].set_index("swarm")
        for s, name in enumerate(result.swarms):
            assert rows.loc[name, "R_hat_T"] == pytest.approx(result.rewards[s].mean())


def test_config_swarm_options_reach_the_swarm(synthetic):
    pytest.importorskip("torch")
    experiment = Experiment(load_config(synthetic), ["rl-decentralized"], seeds=[0])
    assert run_experiment(experiment).policies["rl-decentralized"]["eps"] == 0.5
    experiment.swarm_options = {"rl-decentralized": {"eps": 0.2}}  # a sweep's options win
    assert run_experiment(experiment).policies["rl-decentralized"]["eps"] == 0.2


def test_run_with_several_sumo_seeds(tmp_path):
    pytest.importorskip("libsumo")
    from twin.sumo.network import generate_grid_scenario

    generate_grid_scenario(tmp_path, blocks=4, block_m=300, end_s=900, period_s=2.0, seed=5)
    config = tmp_path / "small.toml"
    config.write_text(
        '[swarm]\nn_drones = 2\n[traffic]\nkind = "sumo"\nnet = "small.net.xml"\n'
        'routes = ["small.trips.xml"]\ncell_m = 200.0\ndrone_speed_kmh = 12.0\n'
        'begin = "00:05"\nwarmup_min = 5.0\nhorizon = 4\nseed = 3\n'
    )
    out = tmp_path / "run"
    code = twin_main(["run", "--config", str(config), "--seeds", "2", "--swarms", "random,greedy",
                      "--no-report", "--quiet", "--out", str(out)])  # fmt: skip
    assert code == 0
    meta = json.loads((out / "run.json").read_text())
    assert meta["seeds"] == [0, 1]
    assert [t["seed"] for t in meta["traffic_by_seed"]] == [3, 4]  # SUMO seeds 3, 4
    assert (out / "tape.parquet").exists()
    tapes = [pd.read_parquet(out / "tapes" / f"seed-{s}.parquet") for s in (0, 1)]
    assert not np.array_equal(tapes[0]["count"].to_numpy(), tapes[1]["count"].to_numpy())
    assert set(pd.read_csv(out / "per_seed.csv").seed) == {0, 1}


def test_the_core_imports_neither_sumo_nor_torch():
    import subprocess
    import sys

    core = ["grid", "scores", "swarm", "paths", "policies", "planners", "tours", "swarms",
            "coordinator", "idleness_maps", "patrol", "experiment", "metrics", "monitoring",
            "mfd", "runs", "files", "config", "resources", "sweep", "traffic.synthetic",
            "traffic.tape"]  # fmt: skip
    code = (
        "import sys\n"
        + "".join(f"import twin.{m}\n" for m in core)
        + "print(sorted({m.split('.')[0] for m in sys.modules} & "
        "{'torch', 'libsumo', 'sumolib', 'traci'}))"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "[]"


def test_with_missed_vehicles_the_run_keeps_the_truth_apart():
    from helpers import random_tape

    from twin.patrol import run_patrol
    from twin.scores import ScoreParams
    from twin.traffic.tape import TapeTraffic

    tape = random_tape(seed=2, nx=4, ny=5, horizon=8)
    exact = run_patrol(TapeTraffic(tape), {"g": make_policy("greedy")}, [[0, 1]], ScoreParams())
    assert exact.truth is None  # every vehicle seen: truth = what the drones see
    blurred = TapeTraffic(tape, detection_p=0.5)
    result = run_patrol(blurred, {"g": make_policy("greedy")}, [[0, 1]], ScoreParams())
    np.testing.assert_allclose(result.truth, exact.importance, atol=1e-6)
    assert not np.allclose(result.importance, exact.importance)


def test_a_seed_stopped_midway_is_left_out_of_the_tables(synthetic, tmp_path, monkeypatch, capsys):
    """Ctrl-C in the second seed's pass, the first having run every step: the run folder
    holds the first seed alone (R_hat_T over 40 steps is not averaged with one over a few) and
    says which seed it left out."""
    import contextlib

    import twin.experiment as experiment_module

    calls = {"n": 0}

    @contextlib.contextmanager
    def stop_in_the_second_seed(enabled=True, on_stop=None):
        def stop() -> bool:
            calls["n"] += 1
            return calls["n"] > 45  # seed 4 polls 40 times, seed 5 stops after a few steps

        yield stop

    monkeypatch.setattr(experiment_module, "stop_on_interrupt", stop_in_the_second_seed)
    out = tmp_path / "run"
    code = twin_main(["evaluate", "--config", str(synthetic), "--seeds", "3", "--seed", "4",
                      "--no-report", "--quiet", "--out", str(out)])  # fmt: skip
    err = capsys.readouterr().err
    assert code == 130, err
    assert "seed 5: interrupted after " in err and "left out, the tables hold seed 4" in err, err
    run = json.loads((out / "run.json").read_text())
    assert run["seeds"] == [4] and run["partial"] is True
    assert run["partial_reason"].startswith("seed 5: interrupted after ")
    assert run["partial_reason"].endswith(
        "of 40 steps; left out, the tables hold seed 4 (every step)"
    )
    assert set(pd.read_csv(out / "per_seed.csv")["seed"]) == {4}
    assert set(pd.read_parquet(out / "series.parquet")["seed"]) == {4}
    assert twin_main(["report", str(out), "--no-animation"]) == 0, capsys.readouterr().err
    head = (out / "report" / "report.md").read_text()
    assert "PARTIAL RUN (40 of 40 steps): seed 5: interrupted after" in head


@pytest.mark.parametrize(
    ("seeds", "text"),
    [
        ([4], "4"),
        ([0, 1], "0, 1"),
        (list(range(47566)), "0 .. 47565"),  # it was one line of 300 KB
        ([0, 1, 2, 3, 7, 9, 10, 11], "0 .. 3, 7, 9 .. 11"),
    ],
)
def test_a_partial_run_names_its_kept_seeds_in_ranges(seeds, text):
    from twin.experiment import seed_ranges

    assert seed_ranges(seeds) == text
