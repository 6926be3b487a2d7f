"""Baseline swarms on the paper's evaluation case: the pattern of Table 2, reproducibility."""

from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from twin.config import load_config, start_positions, synthetic_source
from twin.grid import Grid
from twin.metrics import table2
from twin.patrol import run_patrol
from twin.policies import SweepingPolicy, boustrophedon_tour, make_policy, sweeping_roles
from twin.traffic.base import RecordedTraffic

CONFIG = Path(__file__).resolve().parents[1] / "configs" / "synthetic.toml"


@pytest.fixture(scope="module")
def evaluation():
    config = load_config(CONFIG)
    return config, RecordedTraffic.from_source(synthetic_source(config))


def run(config, source, seed, names=("random", "greedy", "sweeping")):
    starts = start_positions(config, source.grid, np.random.default_rng(seed))
    policies = {n: make_policy(n) for n in names}
    return run_patrol(source, policies, starts, config.params, seed)


def test_paper_pattern_on_the_evaluation_map(evaluation):
    """Issue 3's pattern, on the mean over seeds 0-4 (single seeds vary: greedy packs)."""
    config, source = evaluation
    tables = [table2(run(config, source, seed=s)) for s in range(5)]
    table = pd.concat(tables).groupby("swarm").mean()
    assert table.loc["greedy", "R_hat_T"] >= 1.5 * table.loc["random", "R_hat_T"]
    assert table.loc["sweeping", "pct_map_covered"] == 100.0
    assert table.loc["greedy", "pct_map_covered"] <= 70.0
    assert table.loc["random", "pct_map_covered"] >= 80.0


def test_same_seed_same_numbers_and_other_seed_differs(evaluation):
    config, source = evaluation
    a, b, c = run(config, source, 7), run(config, source, 7), run(config, source, 8)
    np.testing.assert_array_equal(a.rewards, b.rewards)
    np.testing.assert_array_equal(a.positions, b.positions)
    assert not np.array_equal(a.rewards, c.rewards)


def test_a_swarm_does_not_depend_on_which_others_run(evaluation):
    config, source = evaluation
    alone = run(config, source, 5, names=("greedy",))
    together = run(config, source, 5)
    np.testing.assert_array_equal(alone.rewards[0], together.rewards[1])


def test_boustrophedon_tour_is_a_walk_over_every_free_cell():
    rng = np.random.default_rng(0)
    obstacles = rng.random((9, 13)) < 0.2
    grid = Grid(obstacles)
    tour = boustrophedon_tour(grid)
    assert (np.abs(np.diff(tour, axis=0)).sum(axis=1) == 1).all()
    assert grid.is_free(tour).all()
    from twin.policies import largest_free_component

    reachable = {tuple(c) for c in np.argwhere(largest_free_component(grid))}
    assert {tuple(c) for c in tour} == reachable


def test_sweeper_covers_an_open_map_in_one_pass():
    grid = Grid.open(6, 7)
    source = RecordedTraffic(grid, np.zeros((grid.nx * grid.ny, 6, 7)))
    from twin.scores import ScoreParams

    result = run_patrol(source, {"s": SweepingPolicy()}, np.array([[0, 0]]), ScoreParams())
    assert result.visited_share[0, -1] == 1.0


@pytest.mark.parametrize(
    ("n", "roles"), [(1, (1, 0, 0)), (2, (1, 1, 0)), (4, (1, 2, 1)), (8, (2, 4, 2))]
)
def test_sweeping_roles(n, roles):
    assert sweeping_roles(n) == roles
    assert sum(roles) == n
