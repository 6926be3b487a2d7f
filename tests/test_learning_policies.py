"""The learned swarms: registry, coordination, decentralized maps, outages, online learning."""

import numpy as np
import pytest
import torch

from twin.grid import Grid
from twin.learning.checkpoint import model_metadata, save_model
from twin.learning.policies import RLPolicy, local_drone_states
from twin.learning.qnet import QNetwork
from twin.patrol import run_patrol
from twin.policies import SwarmView
from twin.scores import ScoreParams, drone_states, update_idleness
from twin.swarms import make_policy
from twin.traffic.synthetic import Disturbance, SyntheticTraffic

LAYERS = [13, 24, 5]


@pytest.fixture(scope="module")
def checkpoint(tmp_path_factory):
    torch.manual_seed(0)
    net = QNetwork(LAYERS)
    path = tmp_path_factory.mktemp("ckpt") / "q.pt"
    save_model(path, net.state_dict(), model_metadata(LAYERS, {}, seed=0, epoch=0))
    return path


def _source(horizon=40):
    grid = Grid.open(8, 10)
    disturbances = [Disturbance("big", 2, 3, 1.0, 2.0), Disturbance("small", 6, 8, 0.5, 1.0)]
    return SyntheticTraffic(grid, disturbances, horizon=horizon)


STARTS = np.array([[0, 0], [0, 1], [1, 0], [4, 4]])


@pytest.mark.parametrize("name", ["rl", "rl-decentralized", "rl-online"])
def test_registry_builds_the_learned_swarms(checkpoint, name):
    policy = make_policy(name, checkpoint=checkpoint)
    assert isinstance(policy, RLPolicy) and policy.name == name
    assert policy.describe()["checkpoint"] == str(checkpoint)


def test_central_swarm_never_puts_two_drones_in_one_cell(checkpoint):
    result = run_patrol(_source(), {"rl": make_policy("rl", checkpoint=checkpoint)}, STARTS,
                        ScoreParams(), seed=0)  # fmt: skip
    pos = result.positions[0]  # (T+1, N, 2)
    flat = pos[..., 0] * 10 + pos[..., 1]
    assert all(len(np.unique(row)) == len(row) for row in flat)


def test_local_states_equal_the_shared_formula_per_drone():
    rng = np.random.default_rng(0)
    grid = Grid(rng.random((7, 9)) < 0.15)
    free = grid.free_cells()
    pos = free[rng.choice(len(free), 5, replace=False)]
    maps = np.where(grid.free, rng.random((5, 7, 9)), 0.0)
    importance = rng.random((7, 9))
    others = rng.random((5, 2)) * [7, 9]
    states = local_drone_states(grid, maps, importance, pos, others)
    for d in range(5):
        one = drone_states(grid, maps[d], importance, pos[d : d + 1], others[d : d + 1])
        assert np.allclose(states[d], one[0])


def _views(source, positions_per_step, params):
    """SwarmViews of a scripted walk, with the true shared idleness map."""
    grid = source.grid
    maps = list(source.importance_maps())
    idle = grid.free.astype(float)
    for k, pos in enumerate(positions_per_step):
        if k:
            idle = update_idleness(idle, pos, grid, params.eta, params.delta)
        yield SwarmView(k, source.horizon, grid, pos, idle, maps[k],
                        grid.feasible_actions(pos), params)  # fmt: skip


def test_outage_runs_decentralized_then_merges_maps(checkpoint):
    params = ScoreParams()
    source = _source(horizon=12)
    rng = np.random.default_rng(1)
    # two drones walking right along their rows; an outage over steps 3..7
    walk = [np.array([[1, k], [5, k]]) for k in range(10)]
    policy = make_policy("rl", checkpoint=checkpoint, outages=[[3, 8]], eps=0.0)
    policy.reset(source.grid, 2, rng)
    for view in _views(source, walk, params):
        policy.act(view)
        if 3 <= view.k < 8:
            assert policy.maps.local is not None
            # each drone's map holds its own visits only
            assert policy.maps.local[0][walk[view.k][1][0], walk[view.k][1][1]] > params.eta
        else:
            assert policy.maps.local is None
        if view.k == 8:  # back: each cell the smallest idleness any drone held
            assert np.allclose(policy.maps.shared, view.idleness)  # rows disjoint: exact


def test_merged_map_after_overlapping_visits_is_the_cellwise_minimum(checkpoint):
    params = ScoreParams()
    source = _source(horizon=8)
    walk = [np.array([[2, 2], [2, 3]]), np.array([[2, 3], [2, 2]]),
            np.array([[2, 4], [2, 1]]), np.array([[2, 5], [2, 0]])]  # fmt: skip
    policy = make_policy("rl", checkpoint=checkpoint, outages=[[1, 3]])
    policy.reset(source.grid, 2, np.random.default_rng(0))
    for view in _views(source, walk, params):
        if view.k == 3:
            local = policy.maps.local.copy()
        policy.act(view)
    expected = np.empty_like(local)
    for d in range(2):  # advance each drone's own map with its own visit, then take the min
        expected[d] = np.where(source.grid.free, np.minimum(1, local[d] + params.delta), 0)
        expected[d][tuple(walk[3][d])] = params.eta * local[d][tuple(walk[3][d])]
    assert np.allclose(policy.maps.shared, expected.min(axis=0))
    assert np.all(policy.maps.shared >= view.idleness - 1e-12)  # never below the true map


def test_decentralized_swarm_uses_exploration(checkpoint):
    source = _source()
    greedy_only = run_patrol(source, {"d": make_policy("rl-decentralized", checkpoint=checkpoint,
                                                       eps=0.0)}, STARTS, ScoreParams(), seed=0)  # fmt: skip
    exploring = run_patrol(source, {"d": make_policy("rl-decentralized", checkpoint=checkpoint,
                                                     eps=1.0)}, STARTS, ScoreParams(), seed=0)  # fmt: skip
    assert not np.array_equal(greedy_only.positions, exploring.positions)


@pytest.mark.parametrize("decentralized", [False, True])
def test_online_learning_changes_the_weights(checkpoint, decentralized):
    policy = make_policy("rl-online", checkpoint=checkpoint, decentralized=decentralized,
                         batch_size=8, lr=1e-2)  # fmt: skip
    run_patrol(_source(horizon=30), {"o": policy}, STARTS, ScoreParams(), seed=0)
    assert policy.learner.updates > 0
    assert len(policy.learner.buffer) == 30 * 4
    before = policy.net.state_dict()
    for net in policy.nets:
        after = net.state_dict()
        assert any(not torch.equal(before[k], after[k]) for k in before)
    if decentralized:  # each drone trained its own copy on its own buffer
        assert len(policy.nets) == 4
        a, b = policy.nets[0].state_dict(), policy.nets[1].state_dict()
        assert any(not torch.equal(a[k], b[k]) for k in a)


def test_missing_checkpoint_is_a_user_error(tmp_path):
    from twin.errors import UserError

    with pytest.raises(UserError, match="does not exist"):
        make_policy("rl", checkpoint=tmp_path / "nothing.pt")


def test_default_checkpoint_is_found_inside_the_package_or_the_checkout():
    from twin.learning.checkpoint import default_checkpoint

    path = default_checkpoint()
    assert path.name == "qnet.pt" and path.parent.name == "data"
