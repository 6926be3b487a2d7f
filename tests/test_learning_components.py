"""Q-network, replay buffer, checkpoints and the random-swarm data."""

import numpy as np
import pytest
import torch

from twin.errors import UserError
from twin.grid import Grid
from twin.learning.checkpoint import load_qnet, model_metadata, save_model
from twin.learning.data import random_swarm_episode
from twin.learning.qnet import TABLE1_LAYERS, QNetwork, masked_argmax, n_parameters
from twin.learning.replay import ReplayBuffer
from twin.scores import ScoreParams
from twin.traffic.synthetic import Disturbance, SyntheticTraffic

SMALL = [13, 16, 8, 5]


def test_table1_network_shape_and_size():
    net = QNetwork(TABLE1_LAYERS)
    linears = [m for m in net.net if isinstance(m, torch.nn.Linear)]
    assert [(m.in_features, m.out_features) for m in linears] == [
        (13, 2048), (2048, 1024), (1024, 256), (256, 64), (64, 5)
    ]  # fmt: skip
    assert isinstance(net.net[-1], torch.nn.Linear)  # linear output
    assert sum(isinstance(m, torch.nn.ReLU) for m in net.net) == 4
    assert 2_300_000 < n_parameters(net) < 2_500_000
    assert net(torch.zeros(7, 13)).shape == (7, 5)


def test_network_rejects_wrong_ends():
    """Any state size in (the state variant's, twin/states.py), the 5 actions out."""
    assert QNetwork([33, 8, 5])(torch.zeros(2, 33)).shape == (2, 5)
    for layers in ([13, 8, 4], [0, 8, 5], [5]):
        with pytest.raises(ValueError):
            QNetwork(layers)


def test_masked_argmax_ignores_infeasible():
    q = torch.tensor([[0.0, 5.0, 1.0, 2.0, 3.0]])
    feasible = torch.tensor([[True, False, True, False, True]])
    assert masked_argmax(q, feasible).item() == 4


def _fill(buffer, steps, rng):
    n = buffer.n_drones
    for t in range(steps):
        buffer.add(
            np.full((n, 13), t, np.float32),
            np.arange(n) % 5,
            np.arange(n, dtype=np.float32) + 100 * t,
            np.full((n, 13), t + 1, np.float32),
            np.ones((n, 5), bool),
        )


def test_replay_buffer_ring_pooled_and_per_drone_views():
    rng = np.random.default_rng(0)
    buffer = ReplayBuffer(capacity=5, n_drones=3, state_size=13)
    _fill(buffer, 7, rng)  # wraps: steps 2..6 kept
    assert len(buffer) == 15
    kept = set(buffer.states[:, 0, 0].astype(int))
    assert kept == {2, 3, 4, 5, 6}
    view = buffer.drone(1)
    assert len(view) == 5 and np.all(view.rewards % 100 == 1)
    batch = view.sample(64, rng)
    assert np.all(batch.rewards % 100 == 1)  # only drone 1's transitions
    pooled = buffer.sample(256, rng)
    assert set((pooled.rewards % 100).astype(int)) == {0, 1, 2}  # every drone's
    assert np.all(pooled.next_states[:, 0] == pooled.states[:, 0] + 1)  # rows stay together


def test_replay_buffer_add_steps_equals_add():
    rng = np.random.default_rng(1)
    a, b = ReplayBuffer(10, 2, state_size=13), ReplayBuffer(10, 2, state_size=13)
    s = rng.random((4, 2, 13), dtype=np.float32)
    act = rng.integers(0, 5, (4, 2))
    r = rng.random((4, 2), dtype=np.float32)
    f = rng.random((4, 2, 5)) < 0.5
    for t in range(4):
        a.add(s[t], act[t], r[t], s[t], f[t])
    b.add_steps(s, act, r, s, f)
    assert np.array_equal(a.states, b.states) and np.array_equal(a.next_feasible, b.next_feasible)
    assert a.cursor == b.cursor and a.steps == b.steps


def test_random_swarm_episode_is_consistent():
    grid = Grid.open(6, 7)
    source = SyntheticTraffic(grid, [Disturbance("big", 2, 3, 1.0, 2.0)], horizon=30)
    ep = random_swarm_episode(source, 3, ScoreParams(), np.random.default_rng(0))
    assert ep.states.shape == (30, 3, 13) and ep.next_feasible.shape == (30, 3, 5)
    # s' of step k is s of step k+1, and the actions were feasible moves
    assert np.array_equal(ep.next_states[:-1], ep.states[1:])
    pos = np.rint(ep.states[..., :2] * [6, 7]).astype(int)
    nxt = np.rint(ep.next_states[..., :2] * [6, 7]).astype(int)
    from twin.grid import ACTION_DELTAS

    assert np.array_equal(nxt - pos, ACTION_DELTAS[ep.actions])


def _checkpoint(tmp_path, layers=SMALL):
    net = QNetwork(layers)
    path = tmp_path / "q.pt"
    save_model(path, net.state_dict(), model_metadata(layers, {"lr": 1e-4}, seed=3, epoch=7))
    return net, path


def test_checkpoint_round_trip_with_metadata(tmp_path):
    net, path = _checkpoint(tmp_path)
    loaded, meta = load_qnet(path)
    x = torch.randn(4, 13)
    assert torch.equal(net(x), loaded(x))
    assert meta["layers"] == SMALL and meta["seed"] == 3 and meta["epoch"] == 7
    assert meta["actions"] == ["stay", "up", "down", "left", "right"]
    blob = torch.load(path, weights_only=True)  # plain types only
    assert isinstance(blob["meta"]["torch_version"], str)


def test_truncated_checkpoint_is_one_line_user_error(tmp_path):
    _, path = _checkpoint(tmp_path)
    data = path.read_bytes()
    path.write_bytes(data[: len(data) // 2])
    with pytest.raises(UserError) as err:
        load_qnet(path)
    assert "\n" not in str(err.value) and str(path) in str(err.value)


def test_garbage_and_missing_checkpoints_are_user_errors(tmp_path):
    bad = tmp_path / "bad.pt"
    bad.write_bytes(b"not a checkpoint at all")
    with pytest.raises(UserError):
        load_qnet(bad)
    with pytest.raises(UserError, match="does not exist"):
        load_qnet(tmp_path / "missing.pt")
    torch.save({"weights": {}}, tmp_path / "nometa.pt")
    with pytest.raises(UserError, match="not a twin"):
        load_qnet(tmp_path / "nometa.pt")


def test_mismatched_checkpoints_are_user_errors(tmp_path):
    _, path = _checkpoint(tmp_path)
    blob = torch.load(path, weights_only=True)
    blob["meta"]["layers"] = [13, 32, 5]  # weights of another shape
    torch.save(blob, tmp_path / "shape.pt")
    with pytest.raises(UserError, match="do not match"):
        load_qnet(tmp_path / "shape.pt")
    blob = torch.load(path, weights_only=True)
    blob["meta"]["actions"] = ["stay", "left", "right", "up", "down"]
    torch.save(blob, tmp_path / "order.pt")
    with pytest.raises(UserError, match="action order"):
        load_qnet(tmp_path / "order.pt")


@pytest.mark.parametrize("layers", [SMALL, [13, 64, 32, 16, 5]])
def test_gradient_in_place_equals_autograd_bit_for_bit(layers):
    import torch.nn.functional as F

    from twin.learning.dqn import gradient

    torch.manual_seed(3)
    net, ref = QNetwork(layers), QNetwork(layers)
    ref.load_state_dict(net.state_dict())
    s, y = torch.randn(32, 13), torch.randn(32)
    s[:4] = -5.0  # rows with dead ReLUs
    a = torch.randint(0, 5, (32, 1))
    for _ in range(2):  # the second time into the existing .grad
        loss, q = gradient([m for m in net.net if isinstance(m, torch.nn.Linear)], s, a, y)
        ref.zero_grad(set_to_none=True)
        q_ref = ref(s).gather(1, a).squeeze(1)
        loss_ref = F.mse_loss(q_ref, y)
        loss_ref.backward()
        assert torch.equal(loss, loss_ref.detach()) and torch.equal(q, q_ref.detach())
        for p, p_ref in zip(net.parameters(), ref.parameters(), strict=True):
            assert torch.equal(p.grad, p_ref.grad)


def test_flat_adam_step_equals_fused_adam_bit_for_bit_and_survives_a_resume():
    import copy

    from twin.learning.dqn import adam_step, make_optimizer

    torch.manual_seed(4)
    nets = [QNetwork(SMALL), QNetwork(SMALL)]
    nets[1].load_state_dict(nets[0].state_dict())
    opts = [make_optimizer(n, 1e-3, True) for n in nets]
    for k in range(6):
        grads = [torch.randn_like(p) for p in nets[0].parameters()]
        for net in nets:
            for p, g in zip(net.parameters(), grads, strict=True):
                if p.grad is None:
                    p.grad = g.clone()
                else:
                    p.grad.copy_(g)
        opts[0].step()
        adam_step(opts[1])
        if k == 3:  # a resume replaces the state: flattened anew at the next step
            opts[1].load_state_dict(copy.deepcopy(opts[0].state_dict()))
        for a, b in zip(nets[0].parameters(), nets[1].parameters(), strict=True):
            assert torch.equal(a, b)
    assert hasattr(opts[1], "_twin_flat")  # the flat step ran
    state0, state1 = opts[0].state_dict()["state"], opts[1].state_dict()["state"]
    for i in state0:
        for key in ("step", "exp_avg", "exp_avg_sq"):
            assert torch.equal(state0[i][key], state1[i][key])


def test_building_an_optimizer_writes_nothing_in_the_system_temporary_folder(tmp_path):
    """torch makes its compiler cache when an optimizer is first built (it imports its
    compiler): in twin's cache, not $TMPDIR/torchinductor_<user> (probe 23's f07). A fresh
    process: this one has imported torch's compiler already."""
    import os
    import subprocess
    import sys

    system, cache = tmp_path / "sys", tmp_path / "cache"
    system.mkdir()
    code = ("import torch, twin.learning.dqn as d; from twin.learning.qnet import QNetwork; "
            "d.make_optimizer(QNetwork(), 1e-3, True)")  # fmt: skip
    env = {**os.environ, "TMPDIR": str(system), "TWIN_CACHE_DIR": str(cache)}
    env.pop("TORCHINDUCTOR_CACHE_DIR", None)
    subprocess.run([sys.executable, "-c", code], env=env, check=True)
    assert list(system.iterdir()) == []
    assert (cache / "torch").is_dir()
