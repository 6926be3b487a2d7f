"""The drones' own idleness maps stored sparsely (OwnMaps) against the dense reference, bit for
bit: every map, the merge, and the states the learned swarm reads from them."""

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from twin.grid import Grid
from twin.idleness_maps import OwnMaps, own_visits_update
from twin.learning.policies import local_drone_states
from twin.scores import ScoreParams


@st.composite
def walks(draw):
    """A grid with obstacles, a start map, and drones walking (often stacking, revisiting)."""
    nx, ny = draw(st.integers(1, 7)), draw(st.integers(1, 7))
    seed = draw(st.integers(0, 2**32 - 1))
    rng = np.random.default_rng(seed)
    obstacles = rng.random((nx, ny)) < draw(st.sampled_from([0.0, 0.2, 0.4]))
    if obstacles.all():
        obstacles[0, 0] = False
    grid = Grid(obstacles)
    n = draw(st.integers(1, 6))
    free = grid.free_cells()
    pos = free[rng.integers(len(free), size=n)]  # drones may start stacked
    start = draw(st.sampled_from(["ones", "random"]))
    shared = grid.free_float.copy() if start == "ones" else grid.free_float * rng.random((nx, ny))
    # eta > 1 lets a drone's own value exceed the common map (exercises the merge)
    params = ScoreParams(eta=draw(st.sampled_from([0.0, 0.1, 0.5, 2.0])),
                         delta=draw(st.sampled_from([0.025, 0.3, 1 / 3])))  # fmt: skip
    steps = []
    for _ in range(draw(st.integers(1, 25))):
        feasible = grid.feasible_actions(pos)
        actions = np.array([rng.choice(np.flatnonzero(f)) for f in feasible])
        pos = grid.move(pos, actions)
        steps.append(pos)
    return grid, shared, params, steps, rng


@settings(max_examples=150, deadline=None)
@given(walks())
def test_own_maps_equal_the_dense_maps_bit_for_bit(walk):
    grid, shared, params, steps, rng = walk
    n = len(steps[0])
    dense = np.repeat(shared[None], n, axis=0)
    own = OwnMaps(shared, n)
    importance = rng.random(grid.shape)
    others = rng.random((n, 2))
    for pos in steps:
        dense = own_visits_update(dense, pos, grid, params)
        own.advance(pos, grid, params)
        assert np.array_equal(own.dense(), dense)
        assert np.array_equal(own.merged(), dense.min(axis=0))
        flat, _ = grid.view_index(pos)
        assert np.array_equal(own.at(flat), dense.reshape(n, -1)[np.arange(n)[:, None], flat])
        assert np.array_equal(
            local_drone_states(grid, own, importance, pos, others),
            local_drone_states(grid, dense, importance, pos, others),
        )
        assert len(own.value) <= n * grid.n_free  # at most one kept value per drone and cell


def test_saturated_cells_are_dropped_so_storage_stays_bounded():
    """With every map at 1, a visited cell recovers to 1 after 1/delta steps and is forgotten:
    the kept cells are bounded by drones x recovery time, not by the length of the run."""
    grid = Grid.open(30, 30)
    params = ScoreParams(eta=0.1, delta=0.25)
    rng = np.random.default_rng(0)
    pos = grid.free_cells()[rng.choice(900, 10, replace=False)]
    own = OwnMaps(grid.free_float, 10)
    most = 0
    for _ in range(200):
        pos = grid.move(pos, [rng.choice(np.flatnonzero(f)) for f in grid.feasible_actions(pos)])
        own.advance(pos, grid, params)
        most = max(most, len(own.value))
    assert most <= 10 * 5  # recovery from eta to 1 takes 4 steps; plus the visit itself
