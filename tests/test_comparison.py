"""Paired comparison of a learned swarm against the best classical swarm."""

from __future__ import annotations

import pandas as pd
import pytest
from scipy import stats

from twin.metrics import learned_against_best_classical, paired_difference


def _per_seed(values: dict[str, list[float]]) -> pd.DataFrame:
    rows = [{"seed": s, "swarm": name, "R_hat_T": v}
            for name, vs in values.items() for s, v in enumerate(vs)]  # fmt: skip
    return pd.DataFrame(rows)


def test_paired_difference_by_hand():
    per_seed = _per_seed({"rl": [2.0, 2.5, 3.0], "greedy": [1.0, 2.0, 2.0]})
    d = paired_difference(per_seed, "rl", "greedy")
    # differences 1.0, 0.5, 1.0: mean 5/6, sample sd 0.288675, t(0.975, 2) = 4.302653
    assert d["difference"] == pytest.approx(5 / 6)
    assert d["difference_ci95"] == pytest.approx(stats.t.ppf(0.975, 2) * 0.2886751 / 3**0.5)
    assert d["ratio"] == pytest.approx(7.5 / 5.0)
    assert d["n_seeds"] == 3


def test_pairing_is_by_seed_not_by_order():
    per_seed = _per_seed({"rl": [1.0, 2.0], "greedy": [0.5, 1.5]}).iloc[::-1]
    d = paired_difference(per_seed, "rl", "greedy")
    assert d["difference"] == pytest.approx(0.5)
    assert d["difference_ci95"] == pytest.approx(0.0)  # the same gain on every seed


def test_learned_swarms_meet_the_strongest_classical_swarm():
    per_seed = _per_seed({"random": [1.0, 1.1], "sweeping": [2.0, 2.2], "greedy": [1.5, 1.6],
                          "rl": [1.9, 2.0], "rl-online": [2.1, 2.0]})  # fmt: skip
    table = learned_against_best_classical(per_seed)
    assert list(table["swarm"]) == ["rl", "rl-online"]
    assert set(table["against"]) == {"sweeping"}
    assert learned_against_best_classical(_per_seed({"random": [1.0]})).empty


def test_a_yardstick_that_scored_nothing_gives_no_ratio(recwarn):
    """The best classical swarm at 0 (every vehicle missed): the ratio is n/a, with no numpy
    warning on the terminal (it printed twin's source line four times)."""
    import math

    from twin.metrics import format_comparison

    per_seed = _per_seed({"rl": [0.0, 0.0], "greedy": [0.0, 0.0]})
    table = learned_against_best_classical(per_seed)
    assert math.isnan(table["ratio"].iloc[0])
    assert "ratio n/a (best scored 0)" in format_comparison(table)
    assert not [w for w in recwarn if issubclass(w.category, RuntimeWarning)]
