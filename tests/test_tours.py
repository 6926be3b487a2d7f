"""The cyclic patrol swarm (twin.tours): legal, reproducible, general, and better than random."""

import numpy as np
import pytest

from twin.errors import UserError
from twin.grid import Grid
from twin.patrol import random_starts
from twin.policies import RandomPolicy, SwarmView
from twin.scores import ScoreParams, update_idleness, visit_gain
from twin.swarms import make_policy
from twin.tours import (
    ToursPolicy,
    best_period,
    closed_order,
    closed_walks,
    saturation_period,
    visit_gain_factor,
)

PARAMS = ScoreParams()


def blobs(grid: Grid, centres, sigma=2.0) -> np.ndarray:
    i, j = np.mgrid[: grid.nx, : grid.ny]
    t = sum(np.exp(-((i - a) ** 2 + (j - b) ** 2) / (2 * sigma**2)) for a, b in centres)
    return t / t.max() * grid.free


def patrol(policy, grid, n, steps, importance, seed=0, shift_at=None, moved=None):
    """Run ``policy``; check every move; return (total headline reward, positions per step)."""
    rng = np.random.default_rng(seed)
    positions = random_starts(grid, n, rng)
    policy.reset(grid, n, np.random.default_rng(seed + 1))
    idleness = grid.free.astype(float)
    total, trail = 0.0, []
    for k in range(steps):
        t = moved if shift_at is not None and k >= shift_at else importance
        view = SwarmView(
            k, steps, grid, positions, idleness, t, grid.feasible_actions(positions), PARAMS
        )
        actions = policy.act(view)
        assert actions.shape == (n,)
        assert view.feasible[np.arange(n), actions].all(), "an infeasible action"
        nxt = grid.move(positions, actions)
        assert grid.free[nxt[:, 0], nxt[:, 1]].all()
        cells = np.unique(nxt[:, 0] * grid.ny + nxt[:, 1])
        i, j = np.divmod(cells, grid.ny)
        total += visit_gain(PARAMS.alpha_T * t[i, j] + PARAMS.alpha_I, idleness[i, j], PARAMS).sum()
        idleness = update_idleness(idleness, nxt, grid, PARAMS.eta, PARAMS.delta)
        positions = nxt
        trail.append(positions.copy())
    return total, np.array(trail)


def test_registered_and_options_checked():
    assert isinstance(make_policy("tours"), ToursPolicy)
    for bad in ({"per_tour": 0}, {"per_tour": 99}, {"per_tour": 1.5}, {"shift": -1},
                {"explore": -1}, {"stretch": 0}, {"prior": 2}, {"bonus": -1}):  # fmt: skip
        with pytest.raises(UserError) as err:
            ToursPolicy(**bad)
        assert "\n" not in str(err.value)


def test_period_follows_eta_and_delta():
    assert saturation_period(PARAMS) == 37
    assert visit_gain_factor(37, PARAMS) == pytest.approx(0.9)
    assert visit_gain_factor(10, PARAMS) == pytest.approx(10 * PARAMS.delta)
    slow = ScoreParams(delta=0.01)
    assert saturation_period(slow) == 91
    flat = np.ones(10_000)
    assert best_period(flat, 4, PARAMS) == 36  # the first period with the full factor
    assert best_period(flat, 4, slow) > 80


def test_period_past_the_covering_one_gains_nothing_and_is_not_searched():
    """The best period's gain per step is the best of every period up to saturation, also when
    the tours hold every cell sooner; a tiny delta (saturation after 10^9 steps) is searched
    only up to the covering period (it took 8 GB and minutes: probe 26b's g01)."""
    rng = np.random.default_rng(0)
    weights = np.sort(rng.random(48))[::-1]

    def rate(p: int, params: ScoreParams) -> float:  # as best_period weighs a period
        count = min(p * 4, len(weights))
        return weights[:count].mean() * visit_gain_factor(p, params) * min(1.0, 48 / (p * 4))

    assert saturation_period(PARAMS) > 48 / 4  # the tours hold every cell before saturation
    every = max(rate(p, PARAMS) for p in range(1, saturation_period(PARAMS) + 1))
    assert rate(best_period(weights, 4, PARAMS), PARAMS) == pytest.approx(every, rel=1e-12)
    tiny = ScoreParams(delta=1e-9)  # saturation after 9e8 steps: the first 1000 periods
    every = max(rate(p, tiny) for p in range(1, 1001))
    assert rate(best_period(weights, 4, tiny), tiny) == pytest.approx(every, rel=1e-12)


def test_walks_are_closed_and_step_between_neighbours():
    grid = Grid(np.zeros((12, 12), dtype=bool))
    obstacles = np.zeros((12, 12), dtype=bool)
    obstacles[3:9, 6] = True
    grid = Grid(obstacles)
    cells = np.argwhere(grid.free)[::3]
    walk = closed_walks(grid, [cells[closed_order(cells)]])[0]
    steps = np.abs(np.diff(np.vstack([walk, walk[:1]]), axis=0)).sum(axis=1)
    assert (steps == 1).all()
    assert grid.free[walk[:, 0], walk[:, 1]].all()
    assert {tuple(c) for c in cells} <= {tuple(c) for c in walk}


@pytest.mark.parametrize("n", [1, 7])
def test_legal_moves_with_obstacles(n):
    rng = np.random.default_rng(3)
    obstacles = rng.random((15, 20)) < 0.2
    grid = Grid(obstacles)
    importance = blobs(grid, [(4, 5), (11, 15)])
    _, trail = patrol(ToursPolicy(), grid, n, 150, importance)
    if n > 1:  # the coordinator keeps next cells distinct
        flat = trail[..., 0] * grid.ny + trail[..., 1]
        assert all(len(np.unique(row)) == n for row in flat)


def test_deterministic_under_a_seed():
    grid = Grid.open(12, 16)
    importance = blobs(grid, [(3, 4), (9, 12)])
    a = patrol(ToursPolicy(), grid, 3, 120, importance, seed=5)
    b = patrol(ToursPolicy(), grid, 3, 120, importance, seed=5)
    assert a[0] == b[0] and np.array_equal(a[1], b[1])


def test_replans_when_the_map_shifts():
    grid = Grid.open(16, 24)
    before = blobs(grid, [(3, 4)])
    after = blobs(grid, [(8, 11)])  # moved, overlapping what the tours see
    policy = ToursPolicy()
    _, trail = patrol(policy, grid, 2, 400, before, shift_at=150, moved=after)
    assert policy.plans >= 2
    assert policy.planned_at > 150
    # the drones now stand on important cells of the new map far more than on average
    end = trail[-100:].reshape(-1, 2)
    assert after[end[:, 0], end[:, 1]].mean() > 2 * after.mean()


def test_beats_random_clearly():
    grid = Grid.open(14, 20)
    importance = blobs(grid, [(3, 4), (10, 15)])
    tours, _ = patrol(ToursPolicy(), grid, 3, 300, importance, seed=2)
    rand, _ = patrol(RandomPolicy(), grid, 3, 300, importance, seed=2)
    assert tours > 1.3 * rand


def test_tours_describes_itself_before_any_step():
    """A run that stops before its first step still records the swarm's description."""
    from twin.tours import ToursPolicy

    assert ToursPolicy().describe()["plans"] == 0


def test_block_cycles_visit_every_cell_of_their_region_once():
    from twin.tours import block_cycle, block_regions

    rng = np.random.default_rng(4)
    for trial in range(5):
        usable = rng.random((7, 9)) < 0.8
        weights = rng.random((7, 9))
        regions = block_regions(weights, usable, [12, 5, 1])
        taken = set()
        for region in regions:
            blocks = {b for b, _ in region}
            assert all(usable[b] for b in blocks) and not blocks & taken
            taken |= blocks
            cycle = block_cycle(region, (trial % 2, 1))
            cells = {tuple(c) for c in cycle}
            assert len(cells) == len(cycle) == 4 * len(blocks)  # each cell once
            steps = np.abs(np.diff(np.vstack([cycle, cycle[:1]]), axis=0)).sum(axis=1)
            assert (steps == 1).all()  # closed, between neighbours


@pytest.mark.parametrize("shape", [(1, 9), (2, 2), (9, 1), (10, 13), (17, 6)])
def test_survey_sees_every_cell_and_drones_share_it(shape):
    from twin.tours import open_walk, split_survey, survey_cells

    rng = np.random.default_rng(sum(shape))
    obstacles = rng.random(shape) < (0.15 if min(shape) > 2 else 0.0)
    grid = Grid(obstacles)
    policy = ToursPolicy()
    policy.reset(grid, 1, rng)
    area = policy.area  # the largest connected free area
    walk = open_walk(grid, survey_cells(area))
    assert area[walk[:, 0], walk[:, 1]].all()
    steps = np.abs(np.diff(walk, axis=0)).sum(axis=1)
    assert (steps == 1).all()
    seen = np.zeros(shape, dtype=bool)
    flat, valid = grid.view_index(walk)
    seen.ravel()[flat[valid]] = True
    assert seen[area].all()
    starts = random_starts(grid, 3, rng)
    pieces = split_survey(walk, starts)
    assert sum(len(p) for p in pieces) == len(walk)
    assert {tuple(c) for p in pieces for c in p} == {tuple(c) for c in walk}


@pytest.mark.parametrize("n", [1, 5])
def test_survey_phase_sees_the_area_then_plans(n):
    rng = np.random.default_rng(8)
    grid = Grid(rng.random((14, 18)) < 0.15)
    importance = blobs(grid, [(3, 4), (10, 14)])
    policy = ToursPolicy(survey=True)
    _, trail = patrol(policy, grid, n, 200, importance)
    assert policy.surveys == 1 and policy.plans >= 1
    assert policy.seen[policy.area].all()  # the survey saw every cell of the tours' area
    if n > 1:
        flat = trail[..., 0] * grid.ny + trail[..., 1]
        assert all(len(np.unique(row)) == n for row in flat)


def test_survey_again_when_the_map_moves():
    grid = Grid.open(16, 24)
    before = blobs(grid, [(3, 4)])
    after = blobs(grid, [(11, 17)])  # far from the tour: its cells go cold
    policy = ToursPolicy(survey=True)
    _, trail = patrol(policy, grid, 2, 500, before, shift_at=150, moved=after)
    assert policy.surveys >= 2 and policy.planned_at > 150
    end = trail[-100:].reshape(-1, 2)
    assert after[end[:, 0], end[:, 1]].mean() > 2 * after.mean()


def test_a_uniform_fade_replans_nothing():
    grid = Grid.open(14, 20)
    importance = blobs(grid, [(4, 5), (10, 14)])
    policy = ToursPolicy()
    patrol(policy, grid, 4, 300, importance, shift_at=120, moved=0.4 * importance)
    assert policy.plans == 1


def test_layouts_and_survey_checked():
    for bad in ({"layout": "spiral"}, {"survey": 1}):
        with pytest.raises(UserError) as err:
            ToursPolicy(**bad)
        assert "\n" not in str(err.value)
