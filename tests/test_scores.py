"""Grid, idleness, reward, coverage and state: a hand-computed case and invariants."""

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from twin.grid import N_ACTIONS, Grid
from twin.scores import (
    STATE_SIZE,
    ScoreParams,
    coverage,
    directional_idleness,
    drone_states,
    initial_idleness,
    paper_rewards,
    reward_parts,
    rewards_on_arrival,
    update_idleness,
    visit_gain,
)

PARAMS = ScoreParams(eta=0.1, delta=0.025, alpha_T=1.0, alpha_I=0.5)


def test_hand_computed_step_on_3x3():
    grid = Grid.open(3, 3)
    idle = np.array([[1.0, 0.5, 1.0], [1.0, 0.1, 1.0], [1.0, 1.0, 1.0]])
    t = np.array([[0.0, 0.5, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 0.0]])
    pos, nxt = np.array([[1, 1]]), np.array([[0, 1]])  # one drone moves up to (0, 1)

    # headline: the visit gain of (0, 1): (1.0 * 0.5 + 0.5) * (min(1, 0.5 + 0.025) - 0.1 * 0.5)
    r = rewards_on_arrival(grid, PARAMS, idle, t, t, pos, nxt)
    assert r[0] == pytest.approx(1.0 * 0.475)
    # Def. 4 as printed: arrival Ibar over Adj(0,1) = (0,1), (1,1), (0,0), (0,2) minus what
    # the drone leaves in Adj(1,1) = (1,1), (0,1), (2,1), (1,0), (1,2)
    a_t, a_i = 0.525 * 0.5 + 0.125 * 1.0, 0.525 + 0.125 + 1 + 1
    b_t, b_i = 0.1 * 1.0 + 0.5 * 0.5, 0.1 + 0.5 + 1 + 1 + 1
    paper = paper_rewards(grid, PARAMS, idle, t, t, pos, nxt)
    assert paper == pytest.approx([1.0 * (a_t - b_t) + 0.5 * (a_i - b_i)])
    assert paper[0] == pytest.approx(-0.4375)

    new = update_idleness(idle, nxt, grid, PARAMS.eta, PARAMS.delta)
    np.testing.assert_allclose(new, [[1, 0.05, 1], [1, 0.125, 1], [1, 1, 1]])

    s = drone_states(grid, idle, t, pos)
    expected = [1 / 3, 1 / 3, 0.1, 0.25, 0, 0, 0, 1.0, 0.5, 1.0, 1.0, 1 / 3, 1 / 3]
    np.testing.assert_allclose(s[0], expected)


def test_two_drones_state_centre_of_mass_and_shared_cell_reduced_once():
    grid = Grid.open(3, 3)
    idle = np.full((3, 3), 0.5)
    pos = np.array([[0, 0], [2, 2]])
    s = drone_states(grid, idle, np.zeros((3, 3)), pos)
    np.testing.assert_allclose(s[:, 11:], [[2 / 3, 2 / 3], [0, 0]])
    both = np.array([[1, 1], [1, 1]])
    new = update_idleness(idle, both, grid, 0.1, 0.025)
    assert new[1, 1] == pytest.approx(0.05)


def test_hovering_drone_earns_only_what_recovers_on_its_own_cell():
    """A drone that stays earns the gain of its own cell; hovering on, that tends to
    ``weight * delta``: what recovered there, nothing of the cells around it."""
    grid = Grid.open(5, 5)
    t = np.random.default_rng(1).random((5, 5))
    idle = np.full((5, 5), 0.3)
    pos = np.array([[2, 2]])
    weight = PARAMS.alpha_T * t[2, 2] + PARAMS.alpha_I
    r = rewards_on_arrival(grid, PARAMS, idle, t, t, pos, pos)
    assert r[0] == pytest.approx(weight * (0.3 + PARAMS.delta - PARAMS.eta * 0.3))
    for _ in range(200):
        r = rewards_on_arrival(grid, PARAMS, idle, t, t, pos, pos)
        idle = update_idleness(idle, pos, grid, PARAMS.eta, PARAMS.delta)
    assert idle[2, 2] < 1e-12  # a visited cell's idleness is multiplied by eta every step
    assert r[0] == pytest.approx(weight * PARAMS.delta)


def test_obstacles_hold_zero_idleness_and_block_moves():
    obstacles = np.zeros((3, 3), dtype=bool)
    obstacles[0, 1] = True
    grid = Grid(obstacles)
    idle = initial_idleness(grid)
    assert idle[0, 1] == 0 and idle.sum() == 8
    feasible = grid.feasible_actions(np.array([[1, 1], [0, 0]]))
    #                stay   up     down   left   right
    assert feasible.tolist() == [
        [True, False, True, True, True],
        [True, False, True, False, False],
    ]


@st.composite
def scenes(draw):
    nx, ny = draw(st.integers(1, 8)), draw(st.integers(1, 8))
    obstacles = np.array(draw(st.lists(st.booleans(), min_size=nx * ny, max_size=nx * ny)))
    obstacles = obstacles.reshape(nx, ny)
    if obstacles.all():
        obstacles[0, 0] = False
    grid = Grid(obstacles)
    free = grid.free_cells()
    n = draw(st.integers(1, min(4, len(free))))
    picks = draw(st.lists(st.integers(0, len(free) - 1), min_size=n, max_size=n))
    seed = draw(st.integers(0, 2**31))
    return grid, free[picks], seed


@settings(max_examples=150, deadline=None)
@given(scenes())
def test_invariants_over_random_walks(scene):
    grid, pos, seed = scene
    rng = np.random.default_rng(seed)
    idle = initial_idleness(grid)
    for _ in range(10):
        feasible = grid.feasible_actions(pos)
        assert feasible[:, 0].all()  # staying is always feasible
        actions = np.array([rng.choice(np.flatnonzero(f)) for f in feasible])
        t = np.where(grid.free, rng.random(grid.shape), 0.0)
        nxt = grid.move(pos, actions)
        assert grid.is_free(nxt).all()  # never off the map, never on an obstacle
        r = rewards_on_arrival(grid, PARAMS, idle, t, t, pos, nxt)
        assert np.isfinite(r).all()
        idle = update_idleness(idle, nxt, grid, PARAMS.eta, PARAMS.delta)
        assert ((idle >= 0) & (idle <= 1)).all()
        assert (idle[grid.obstacles] == 0).all()
        assert 0.0 <= coverage(idle, grid) <= 1.0
        s = drone_states(grid, idle, t, nxt)
        assert s.shape == (len(nxt), STATE_SIZE) and np.isfinite(s).all()
        pos = nxt
    assert N_ACTIONS == 5


@settings(max_examples=100, deadline=None)
@given(scenes())
def test_directional_means_match_a_plain_loop(scene):
    grid, pos, seed = scene
    idle = np.where(grid.free, np.random.default_rng(seed).random(grid.shape), 0.0)
    got = directional_idleness(idle, grid, pos)
    for n, (i, j) in enumerate(pos):
        cells = {
            "down": [(a, j) for a in range(i + 1, grid.nx)],
            "up": [(a, j) for a in range(i)],
            "left": [(i, b) for b in range(j)],
            "right": [(i, b) for b in range(j + 1, grid.ny)],
        }
        for d, key in enumerate(("down", "up", "left", "right")):
            vals = [idle[c] for c in cells[key] if grid.free[c]]
            assert got[n, d] == pytest.approx(np.mean(vals) if vals else 0.0)


def _directional_by_full_prefix_sums(idleness, grid, positions):
    """The former implementation: prefix sums over every whole map (the bits to keep)."""
    maps = idleness[None] if idleness.ndim == 2 else idleness
    values = maps * grid.free_float
    i, j = positions[:, 0], positions[:, 1]
    d = np.zeros(len(positions), np.intp) if len(maps) == 1 else np.arange(len(positions))
    col_v, col_n = values.cumsum(axis=1), grid.free_cumsum_down
    row_v, row_n = values.cumsum(axis=2), grid.free_cumsum_right
    own_v, own_n = values[d, i, j], grid.free_float[i, j]
    sums = np.stack([col_v[d, -1, j] - col_v[d, i, j], col_v[d, i, j] - own_v,
                     row_v[d, i, j] - own_v, row_v[d, i, -1] - row_v[d, i, j]], axis=1)  # fmt: skip
    ns = np.stack([col_n[-1, j] - col_n[i, j], col_n[i, j] - own_n,
                   row_n[i, j] - own_n, row_n[i, -1] - row_n[i, j]], axis=1)  # fmt: skip
    return np.divide(sums, ns, out=np.zeros_like(sums), where=ns > 0)


@settings(max_examples=100, deadline=None)
@given(scenes())
def test_directional_means_from_row_and_column_keep_the_bits(scene):
    """Reading only each drone's row and column gives the full-map prefix sums' very bits."""
    grid, pos, seed = scene
    rng = np.random.default_rng(seed)
    one = rng.random(grid.shape) * 1e3
    per_drone = rng.random((len(pos), *grid.shape))
    for idle in (one, per_drone):
        expected = _directional_by_full_prefix_sums(idle, grid, pos)
        assert np.array_equal(directional_idleness(idle, grid, pos), expected)


def test_every_distinct_visited_cell_is_paid_once():
    """R^k is the sum of the visit gains of the distinct cells visited: a pack of drones on
    one cell earns together what one drone earns there, split evenly; drones on neighbouring
    cells are each paid their own cell, however their views overlap."""
    grid = Grid.open(5, 5)
    rng = np.random.default_rng(3)
    t, t1, idle = rng.random((5, 5)), rng.random((5, 5)), rng.random((5, 5))
    one = rewards_on_arrival(grid, PARAMS, idle, t, t1, np.array([[2, 2]]), np.array([[2, 3]]))
    pack = rewards_on_arrival(
        grid, PARAMS, idle, t, t1, np.array([[2, 2], [3, 3]]), np.array([[2, 3], [2, 3]])
    )
    assert pack == pytest.approx([one[0] / 2] * 2)
    line = np.array([[2, 0], [2, 1], [2, 2], [2, 3]])
    r = rewards_on_arrival(grid, PARAMS, idle, t, t1, line, line)
    gains = (PARAMS.alpha_T * t1[2, :4] + PARAMS.alpha_I) * (
        np.minimum(1, idle[2, :4] + PARAMS.delta) - PARAMS.eta * idle[2, :4]
    )
    assert r == pytest.approx(gains)


def test_reward_parts_split_the_reward_and_keep_the_paper_column():
    grid = Grid.open(3, 3)
    idle = np.array([[1.0, 0.5, 1.0], [1.0, 0.1, 1.0], [1.0, 1.0, 1.0]])
    t = np.array([[0.0, 0.5, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 0.0]])
    parts = reward_parts(grid, PARAMS, idle, t, t, np.array([[1, 1]]), np.array([[0, 1]]))
    assert parts.importance == pytest.approx([1.0 * 0.5 * 0.475])
    assert parts.idleness == pytest.approx([0.5 * 0.475])
    assert parts.paper == pytest.approx([-0.4375])
    # two drones stacked on one cell: the headline splits one gain, the paper pays each in full
    pack = reward_parts(
        grid, PARAMS, idle, t, t, np.array([[1, 1], [1, 1]]), np.array([[0, 1], [0, 1]])
    )
    assert pack.total == pytest.approx([parts.total[0] / 2] * 2)
    assert pack.paper == pytest.approx([parts.paper[0]] * 2)


@settings(max_examples=100, deadline=None)
@given(scenes())
def test_reward_is_the_sum_of_visit_gains_of_distinct_cells(scene):
    grid, pos, seed = scene
    rng = np.random.default_rng(seed)
    idle, t, t1 = (np.where(grid.free, rng.random(grid.shape), 0.0) for _ in range(3))
    actions = np.array([rng.choice(np.flatnonzero(f)) for f in grid.feasible_actions(pos)])
    nxt = grid.move(pos, actions)
    parts = reward_parts(grid, PARAMS, idle, t, t1, pos, nxt)
    r = rewards_on_arrival(grid, PARAMS, idle, t, t1, pos, nxt)
    np.testing.assert_array_equal(parts.importance + parts.idleness, r)
    cells = {tuple(c) for c in nxt.tolist()}
    expected = sum(
        visit_gain(PARAMS.alpha_T * t1[c] + PARAMS.alpha_I, idle[c], PARAMS) for c in cells
    )
    assert r.sum() == pytest.approx(expected, rel=1e-12, abs=1e-12)
    assert (r >= 0).all()
