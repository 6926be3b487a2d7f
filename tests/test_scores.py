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
    reward_parts,
    rewards_on_arrival,
    update_idleness,
)

PARAMS = ScoreParams(eta=0.1, delta=0.025, alpha_T=1.0, alpha_I=0.5)


def test_hand_computed_step_on_3x3():
    grid = Grid.open(3, 3)
    idle = np.array([[1.0, 0.5, 1.0], [1.0, 0.1, 1.0], [1.0, 1.0, 1.0]])
    t = np.array([[0.0, 0.5, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 0.0]])
    pos, nxt = np.array([[1, 1]]), np.array([[0, 1]])  # one drone moves up

    # arrival: Ibar = min(1, I + delta) over Adj(0,1) = (0,1), (1,1), (0,0), (0,2)
    a_t, a_i = 0.525 * 0.5 + 0.125 * 1.0, 0.525 + 0.125 + 1 + 1
    # leaving: I over Adj(1,1) = (1,1), (0,1), (2,1), (1,0), (1,2)
    b_t, b_i = 0.1 * 1.0 + 0.5 * 0.5, 0.1 + 0.5 + 1 + 1 + 1
    r = rewards_on_arrival(grid, PARAMS, idle, t, t, pos, nxt)
    assert r == pytest.approx([1.0 * (a_t - b_t) + 0.5 * (a_i - b_i)])
    assert r[0] == pytest.approx(-0.4375)

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


def test_hovering_drone_earns_delta_times_importance_in_view():
    """On arrival: a drone that stays earns delta * sum of T over unsaturated cells in view."""
    grid = Grid.open(5, 5)
    rng = np.random.default_rng(1)
    t = rng.random((5, 5))
    idle = np.full((5, 5), 0.3)  # nothing saturated: every cell in view recovers by delta
    pos = np.array([[2, 2]])
    r = rewards_on_arrival(grid, PARAMS, idle, t, t, pos, pos)
    in_view = grid.sum_in_view(t, pos)[0]
    assert r[0] == pytest.approx(PARAMS.delta * (PARAMS.alpha_T * in_view + PARAMS.alpha_I * 5))


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


def test_drones_sharing_a_cell_share_its_reward():
    """Two drones stacked on one cell earn together what one drone alone earns there."""
    grid = Grid.open(5, 5)
    rng = np.random.default_rng(3)
    t, t1, idle = rng.random((5, 5)), rng.random((5, 5)), rng.random((5, 5))
    one = rewards_on_arrival(grid, PARAMS, idle, t, t1, np.array([[2, 2]]), np.array([[2, 3]]))
    pack = rewards_on_arrival(
        grid, PARAMS, idle, t, t1, np.array([[2, 2], [2, 2]]), np.array([[2, 3], [2, 3]])
    )
    assert pack.sum() == pytest.approx(one[0])
    # two drones that meet on a cell coming from different cells: each pays its own departure
    met = rewards_on_arrival(
        grid, PARAMS, idle, t, t1, np.array([[2, 2], [3, 3]]), np.array([[2, 3], [2, 3]])
    )
    alone_b = rewards_on_arrival(grid, PARAMS, idle, t, t1, np.array([[3, 3]]), np.array([[2, 3]]))
    # met = A/2 - B(2,2) and A/2 - B(3,3); alone: A - B(2,2) and A - B(3,3)
    assert met[0] - met[1] == pytest.approx(one[0] - alone_b[0])
    ibar = np.minimum(1.0, grid.values_in_view(idle, np.array([[2, 3]])) + PARAMS.delta)
    arrival = PARAMS.alpha_T * (ibar * grid.values_in_view(t1, np.array([[2, 3]]))).sum()
    arrival += PARAMS.alpha_I * ibar.sum()
    assert met.sum() == pytest.approx(one[0] + alone_b[0] - arrival)


def test_reward_parts_on_the_hand_computed_step_and_a_stacked_pack():
    grid = Grid.open(3, 3)
    idle = np.array([[1.0, 0.5, 1.0], [1.0, 0.1, 1.0], [1.0, 1.0, 1.0]])
    t = np.array([[0.0, 0.5, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 0.0]])
    parts = reward_parts(grid, PARAMS, idle, t, t, np.array([[1, 1]]), np.array([[0, 1]]))
    # the terms of test_hand_computed_step_on_3x3
    a_t, a_i = 0.525 * 0.5 + 0.125 * 1.0, 0.525 + 0.125 + 1 + 1
    b_t, b_i = 0.1 * 1.0 + 0.5 * 0.5, 0.1 + 0.5 + 1 + 1 + 1
    assert parts.importance == pytest.approx([1.0 * (a_t - b_t)])
    assert parts.idleness == pytest.approx([0.5 * (a_i - b_i)])
    assert parts.plain == pytest.approx(parts.total)  # one drone: both readings agree
    # two drones stacked on one cell: the shared reading splits, the plain one pays each in full
    pack = reward_parts(
        grid, PARAMS, idle, t, t, np.array([[1, 1], [1, 1]]), np.array([[0, 1], [0, 1]])
    )
    assert pack.total == pytest.approx([parts.total[0] / 2] * 2)
    assert pack.plain == pytest.approx([parts.plain[0]] * 2)


@settings(max_examples=100, deadline=None)
@given(scenes())
def test_reward_parts_sum_to_the_reward_and_plain_agrees_without_sharing(scene):
    grid, pos, seed = scene
    rng = np.random.default_rng(seed)
    idle, t, t1 = (np.where(grid.free, rng.random(grid.shape), 0.0) for _ in range(3))
    actions = np.array([rng.choice(np.flatnonzero(f)) for f in grid.feasible_actions(pos)])
    nxt = grid.move(pos, actions)
    parts = reward_parts(grid, PARAMS, idle, t, t1, pos, nxt)
    r = rewards_on_arrival(grid, PARAMS, idle, t, t1, pos, nxt)
    np.testing.assert_array_equal(parts.importance + parts.idleness, r)
    alone = (
        len({tuple(p) for p in pos.tolist()}) == len(pos) == len({tuple(p) for p in nxt.tolist()})
    )
    if alone:
        np.testing.assert_allclose(parts.plain, r, rtol=1e-12, atol=1e-12)
