"""The central coordinator: feasible, collision-free, and exactly optimal (eq. maxi:op2)."""

import os

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.optimize import linear_sum_assignment

from twin.coordinator import brute_force, coordinate
from twin.grid import ACTION_DELTAS, Grid


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


def _whole_swarm_optimum(q, positions, feasible, grid):
    """Independent exact solver: one dense assignment over all drones x all candidate cells,
    plus one private penalised "stay anyway" column per drone. Returns (shared cells, Q sum)."""
    n = len(q)
    cells = positions[:, None, :] + ACTION_DELTAS[None, :, :]
    flat = cells[..., 0] * grid.ny + cells[..., 1]
    candidates = np.unique(flat[feasible])
    k = len(candidates)
    penalty = (q[feasible].max() - q[feasible].min() + 1.0) * n
    cost = np.full((n, k + n), np.inf)
    drone, action = np.nonzero(feasible)
    cost[drone, np.searchsorted(candidates, flat[drone, action])] = -q[drone, action]
    cost[np.arange(n), k + np.arange(n)] = penalty - q[:, 0]
    rows, cols = linear_sum_assignment(cost)
    shared = int((cols >= k).sum())
    return shared, shared * penalty - cost[rows, cols].sum()


@st.composite
def dense_packs(draw):
    """Drones packed one or two cells apart in a block, some stacked on one cell, some
    obstacles; Q rounded so that ties are common."""
    seed = draw(st.integers(0, 2**32 - 1))
    rng = np.random.default_rng(seed)
    nx, ny = draw(st.integers(2, 14)), draw(st.integers(2, 14))
    gap = draw(st.sampled_from([1, 1, 2]))
    grid = Grid(rng.random((nx, ny)) < draw(st.sampled_from([0.0, 0.0, 0.15])))
    if grid.n_free == 0:
        grid = Grid.open(nx, ny)
    free = grid.free_cells()
    packed = free[(free[:, 0] % gap == 0) & (free[:, 1] % gap == 0)]
    if not len(packed):  # obstacles on every packed cell: one drone on a free cell
        packed = free[:1]
    keep = rng.random(len(packed)) < draw(st.sampled_from([1.0, 0.9, 0.6]))
    positions = packed[keep] if keep.any() else packed[:1]
    stack = draw(st.integers(0, 3))  # drones sharing a start cell, as after an outage
    if stack:
        positions = np.concatenate([positions, positions[rng.integers(0, len(positions), stack)]])
    q = np.round(rng.normal(size=(len(positions), 5)), 1)
    return grid, positions, q, grid.feasible_actions(positions)


@settings(max_examples=150, deadline=None)
@given(dense_packs())
def test_dense_packs_reach_the_whole_swarm_optimum(case):
    grid, positions, q, feasible = case
    n = len(positions)
    actions = coordinate(q, positions, feasible, grid)
    assert feasible[np.arange(n), actions].all()
    nxt = grid.move(positions, actions)
    shared = n - len(np.unique(nxt, axis=0))
    best_shared, best_sum = _whole_swarm_optimum(q, positions, feasible, grid)
    assert shared == best_shared
    assert q[np.arange(n), actions].sum() == pytest.approx(best_sum)


@pytest.mark.parametrize("solver", ["_solve", "_solve_sparse"])
def test_an_input_on_which_lapjvsp_looped_forever_is_solved_to_the_brute_force_optimum(solver):
    """8 drones whose float regrets made scipy's LAPJVsp loop forever (found by the hypothesis
    test of the coordinated swarms); whole-number costs make it terminate, at the optimum (and
    the dense solver, which takes sets this small, reaches it too)."""
    from pathlib import Path

    import twin.coordinator

    d = np.load(Path(__file__).parent / "data" / "coordinator_lapjvsp_loop.npz")
    q, masked, flat, feasible = d["q"], d["masked"], d["flat"], d["feasible"]
    solve = getattr(twin.coordinator, solver)
    actions = solve(q, masked, flat, feasible, bool(d["stacked"]), int(d["n_cells"]))
    targets = flat[np.arange(len(q)), actions]
    assert feasible[np.arange(len(q)), actions].all()
    assert len(np.unique(targets)) == len(q)
    # the optimum over all joint actions with distinct targets
    import itertools

    best = -np.inf
    for joint in itertools.product(*[np.flatnonzero(f) for f in feasible]):
        cells = flat[np.arange(len(q)), joint]
        if len(np.unique(cells)) == len(q):
            best = max(best, q[np.arange(len(q)), joint].sum())
    assert q[np.arange(len(q)), actions].sum() == pytest.approx(best, abs=1e-6)


@pytest.mark.parametrize("copies", [1, 7])
def test_a_jam_filling_the_grid_on_which_lapjvsp_never_returned_is_solved(tmp_path, copies):
    """42 drones filling a 6 x 7 grid, each planned one move by the oracle (the Q values of
    ``twin evaluate`` with n_drones = 42 there), and 7 such jams side by side (294 drones, a
    set past any small-set threshold): LAPJVsp never returned on either, whole-number costs or
    not. Solved in a child process, stopped after 60 s, at the whole swarm's optimum."""
    import subprocess
    import sys
    from pathlib import Path

    jam = np.load(Path(__file__).parent / "data" / "coordinator_lapjvsp_jam.npz")
    n_cells = int(jam["n_cells"])  # the copies side by side: cell ids shifted by a grid each
    d = {
        "q": np.concatenate([jam["q"]] * copies),
        "masked": np.concatenate([jam["masked"]] * copies),
        "flat": np.concatenate([jam["flat"] + c * n_cells for c in range(copies)]),
        "feasible": np.concatenate([jam["feasible"]] * copies),
    }
    data = tmp_path / "jam.npz"
    np.savez(data, stacked=bool(jam["stacked"]), n_cells=n_cells * copies, **d)
    out = tmp_path / "actions.npy"
    code = (
        "import sys, numpy as np; from twin.coordinator import _solve; "
        "d = np.load(sys.argv[1]); "
        "a = _solve(d['q'], d['masked'], d['flat'], d['feasible'], bool(d['stacked']), "
        "int(d['n_cells'])); np.save(sys.argv[2], a)"
    )
    root = Path(__file__).resolve().parents[1]
    try:
        subprocess.run([sys.executable, "-c", code, str(data), str(out)], check=True,
                       timeout=60, env={**os.environ, "PYTHONPATH": str(root)})  # fmt: skip
    except subprocess.TimeoutExpired:
        pytest.fail("the coordinator did not return within 60 s")
    actions = np.load(out)
    q, flat, feasible = d["q"], d["flat"], d["feasible"]
    n = len(q)
    assert feasible[np.arange(n), actions].all()
    assert len(np.unique(flat[np.arange(n), actions])) == n
    grid = Grid.open(6, 7)
    one = len(jam["q"])
    positions = np.stack(np.divmod(jam["flat"][:, 0], grid.ny), axis=1)
    shared, best = _whole_swarm_optimum(jam["q"], positions, jam["feasible"], grid)
    assert shared == 0
    assert q[np.arange(n), actions].sum() == pytest.approx(best * copies)
    assert n == one * copies
