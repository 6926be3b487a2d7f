"""The central coordinator: feasible, collision-free, and exactly optimal (eq. maxi:op2)."""

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from twin.coordinator import brute_force, coordinate
from twin.grid import Grid


def _case(seed, max_drones, max_side=6, obstacle_share=0.2):
    rng = np.random.default_rng(seed)
    nx, ny = rng.integers(1, max_side + 1, size=2)
    obstacles = rng.random((nx, ny)) < obstacle_share
    grid = Grid(obstacles)
    if grid.n_free == 0:
        grid = Grid.open(nx, ny)
    free = grid.free_cells()
    n = int(rng.integers(1, min(max_drones, len(free)) + 1))
    positions = free[rng.choice(len(free), size=n, replace=False)]
    # ties are likely with rounded values: the optimum must still be found
    q = np.round(rng.normal(size=(n, 5)), 1)
    return grid, positions, q, grid.feasible_actions(positions)


@settings(max_examples=300, deadline=None)
@given(st.integers(0, 2**32 - 1))
def test_joint_action_is_feasible_and_collision_free(seed):
    grid, positions, q, feasible = _case(seed, max_drones=12, max_side=8)
    actions = coordinate(q, positions, feasible, grid)
    n = len(positions)
    assert feasible[np.arange(n), actions].all()
    nxt = grid.move(positions, actions)
    assert len(np.unique(nxt, axis=0)) == n, "two drones in one cell"


@pytest.mark.parametrize("seed", range(400))
def test_equals_brute_force_optimum_up_to_six_drones(seed):
    grid, positions, q, feasible = _case(seed, max_drones=6, max_side=5)
    actions = coordinate(q, positions, feasible, grid)
    _, best = brute_force(q, positions, feasible, grid)
    assert q[np.arange(len(q)), actions].sum() == pytest.approx(best)


def test_crowded_corner_needs_the_assignment():
    # three drones in a 2 x 2 corner all prefer the same cell (0, 0)
    grid = Grid.open(2, 2)
    positions = np.array([[0, 1], [1, 0], [1, 1]])
    feasible = grid.feasible_actions(positions)
    q = np.full((3, 5), -1.0)
    q[0, 3] = q[1, 1] = 5.0  # 0 -> left, 1 -> up: both into (0, 0)
    q[2, 0] = 0.0
    actions = coordinate(q, positions, feasible, grid)
    _, best = brute_force(q, positions, feasible, grid)
    assert q[np.arange(3), actions].sum() == pytest.approx(best) == 4.0


def test_never_chooses_infeasible_even_if_its_q_is_best():
    grid = Grid.open(3, 3)
    positions = np.array([[0, 0]])
    q = np.array([[0.0, 9.0, 1.0, 9.0, 2.0]])  # up and left leave the map
    assert coordinate(q, positions, grid.feasible_actions(positions), grid)[0] == 4


def test_drones_on_one_cell_still_get_feasible_actions_with_fewest_shared_cells():
    # after an outage several drones may stand on one cell of a 1 x 2 corridor:
    # 3 drones, 2 cells: exactly one cell must be shared, never an infeasible move
    grid = Grid.open(1, 2)
    positions = np.array([[0, 0], [0, 0], [0, 0]])
    feasible = grid.feasible_actions(positions)
    q = np.random.default_rng(0).normal(size=(3, 5))
    actions = coordinate(q, positions, feasible, grid)
    assert feasible[np.arange(3), actions].all()
    nxt = grid.move(positions, actions)
    assert len(np.unique(nxt, axis=0)) == 2


def test_far_apart_drones_take_their_own_best():
    grid = Grid.open(50, 50)
    positions = np.array([[5, 5], [5, 9], [40, 40]])  # 4 cells apart: no shared candidate
    q = np.random.default_rng(1).normal(size=(3, 5))
    feasible = grid.feasible_actions(positions)
    expected = np.where(feasible, q, -np.inf).argmax(axis=1)
    assert np.array_equal(coordinate(q, positions, feasible, grid), expected)


def test_many_drones_on_a_large_grid_are_collision_free():
    rng = np.random.default_rng(3)
    grid = Grid.open(200, 300)
    free = grid.free_cells()
    positions = free[rng.choice(len(free), size=1024, replace=False)]
    q = rng.normal(size=(1024, 5))
    feasible = grid.feasible_actions(positions)
    nxt = grid.move(positions, coordinate(q, positions, feasible, grid))
    assert len(np.unique(nxt, axis=0)) == 1024


def test_large_component_sparse_solver_matches_dense_optimum(monkeypatch):
    import twin.coordinator as coordinator

    rng = np.random.default_rng(5)
    grid = Grid.open(30, 30)
    cells = np.array([(i, j) for i in range(0, 20, 2) for j in range(0, 20, 2)])  # 100 drones
    positions = cells + rng.integers(0, 2, size=cells.shape)  # jitter: many collisions
    positions = np.unique(positions, axis=0)
    q = rng.normal(size=(len(positions), 5))
    feasible = grid.feasible_actions(positions)
    sparse = coordinator.coordinate(q, positions, feasible, grid)
    monkeypatch.setattr(coordinator, "SPARSE_ABOVE", 10**9)
    dense = coordinator.coordinate(q, positions, feasible, grid)
    n = len(positions)
    assert q[np.arange(n), sparse].sum() == pytest.approx(q[np.arange(n), dense].sum())
    assert len(np.unique(grid.move(positions, sparse), axis=0)) == n
