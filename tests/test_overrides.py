"""Dotted overrides of a scenario config (twin.config.with_overrides): the one path of the
command-line flags and a sweep's keys, validated by the config's models."""

from __future__ import annotations

from pathlib import Path

import pytest

from twin.config import load_config, with_overrides
from twin.errors import UserError

ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture
def synthetic():
    return load_config(ROOT / "configs" / "synthetic.toml")


def test_an_override_sets_the_key_and_keeps_the_rest(synthetic):
    config = with_overrides(synthetic, {"swarm.n_drones": 2, "evaluate.seeds": 3})
    assert (config.swarm.n_drones, config.evaluate.seeds) == (2, 3)
    assert config.grid == synthetic.grid and config.traffic == synthetic.traffic
    assert config.path == synthetic.path
    assert synthetic.swarm.n_drones != 2  # the config overridden is left as it was


def test_a_flag_is_remembered_through_further_overrides(synthetic):
    config = with_overrides(synthetic, {"swarm.n_drones": 2}, {"swarm.n_drones": "--drones"})
    again = with_overrides(config, {"evaluate.seeds": 3})
    assert again.flag_of("swarm.n_drones") == "--drones"
    assert again.flag_of("evaluate.seeds") is None and synthetic.flag_of("swarm.n_drones") is None


@pytest.mark.parametrize(
    ("overrides", "flags", "line"),
    [
        ({"evaluate.seeds": 0}, {"evaluate.seeds": "--seeds"}, "--seeds = 0 must be >= 1"),
        (
            {"evaluate.seeds": 0},
            None,
            "synthetic.toml: override 'evaluate.seeds' = 0 must be >= 1",
        ),
        ({"swarm.n_drone": 3}, None, "override 'swarm.n_drone' is not a known key"),
        ({"traffic.beta1": "x"}, {"traffic.beta1": "--beta1"}, "--beta1 = 'x' must be a number"),
        (
            {"swarm.n_drones": 10_000},
            {"swarm.n_drones": "--drones"},
            "--drones 10000 exceeds the 600 free cells",
        ),
        ({"swarm.n_drones.x": 1}, None, "goes through 'n_drones', which is not a table"),
    ],
)
def test_a_bad_override_is_one_line_naming_the_flag_or_key(synthetic, overrides, flags, line):
    with pytest.raises(UserError) as info:
        with_overrides(synthetic, overrides, flags)
    assert line in str(info.value) and "\n" not in str(info.value)
