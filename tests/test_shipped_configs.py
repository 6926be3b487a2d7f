"""The shipped scenario and pretraining configs load, and the city-scale one is what the docs
say."""

from __future__ import annotations

from pathlib import Path

import pytest

from twin.config import load_config
from twin.experiment import Experiment, estimate_memory

ROOT = Path(__file__).resolve().parents[1]
SCENARIOS = [
    "synthetic.toml",
    "shenzhen.toml",
    "incident.toml",
    "shenzhen-city-scale.toml",
    "shenzhen-detectors.toml",
    "drone-loss.toml",
    "coordinator-down.toml",
    "training-map.toml",
]


@pytest.mark.parametrize("name", SCENARIOS)
def test_shipped_scenario_configs_load(name):
    config = load_config(ROOT / "configs" / name)
    assert config.evaluate.swarms


@pytest.mark.parametrize("name", ["pretrain.toml", "pretrain-paper.toml"])
def test_shipped_pretraining_configs_train_on_the_training_map(name):
    from twin.training.pretrain import load_config as load_pretrain

    config = load_pretrain(ROOT / "configs" / name)
    assert config.scenario.name == "training-map.toml" and config.scenario_overrides == {}
    assert (config.nx, config.ny, config.n_drones, config.horizon) == (20, 30, 4, 2000)


def test_city_scale_config_is_200_drones_on_100_m_cells_for_3_hours():
    config = load_config(ROOT / "configs" / "shenzhen-city-scale.toml")
    traffic = config.traffic
    assert config.swarm.n_drones == 200
    assert traffic.cell_m == 100.0 and traffic.step_s == pytest.approx(15.0)
    assert traffic.horizon * traffic.step_s == pytest.approx(3 * 3600)
    assert traffic.reads_per_step == 1
    assert len(config.evaluate.swarms) == 8
    # the measured grid (96 x 146 cells) passes the default memory limit, with room to spare
    experiment = Experiment(config=config, swarms=config.evaluate.swarms, seeds=[0])
    need = estimate_memory(experiment, (96, 146), traffic.horizon, warmup_steps=120, live=True)
    assert need < 4e9
