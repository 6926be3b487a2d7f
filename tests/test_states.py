"""State variants (twin/states.py): the paper's state unchanged, the window and nowcast
variants' values, pretraining, loading and running each variant, and the refusals of a
mismatch."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from twin.errors import UserError
from twin.grid import Grid
from twin.idleness_maps import OwnMaps, own_visits_update
from twin.scores import STATE_SIZE, ScoreParams, drone_states, update_idleness
from twin.states import (
    NOWCAST_LAYOUT,
    STATE_VARIANTS,
    WINDOW_RADIUS,
    nowcast_states,
    paper_states,
    state_variant,
    window_states,
)

PARAMS = ScoreParams()


@st.composite
def swarm_maps(draw):
    """A random grid with obstacles, idleness and importance maps, and drones on free cells."""
    nx, ny = draw(st.integers(1, 9)), draw(st.integers(1, 9))
    seed = draw(st.integers(0, 2**32 - 1))
    rng = np.random.default_rng(seed)
    obstacles = rng.random((nx, ny)) < draw(st.sampled_from([0.0, 0.2, 0.5]))
    free = np.argwhere(~obstacles)
    if len(free) == 0:
        obstacles[0, 0] = False
        free = np.argwhere(~obstacles)
    grid = Grid(obstacles)
    n = draw(st.integers(1, min(len(free), 6)))
    positions = free[rng.choice(len(free), n, replace=False)]
    idleness = rng.random((nx, ny)) * grid.free_float
    importance = rng.random((nx, ny))
    return grid, idleness, importance, positions, rng


@settings(max_examples=150, deadline=None)
@given(swarm_maps())
def test_the_paper_variant_is_todays_state_bit_for_bit(case):
    grid, idleness, importance, positions, rng = case
    paper = STATE_VARIANTS["paper"]
    assert paper.size == STATE_SIZE == 13
    today = drone_states(grid, idleness, importance, positions)
    assert np.array_equal(paper.states(grid, idleness, importance, positions), today)
    # one map per drone, and each drone's view of the others' centre of mass
    n = len(positions)
    dense = rng.random((n, *grid.shape)) * grid.free_float
    others = rng.random((n, 2)) * np.array(grid.shape)
    expected = drone_states(grid, dense, importance, positions, others)
    assert np.array_equal(paper.states(grid, dense, importance, positions, others), expected)


@settings(max_examples=60, deadline=None)
@given(swarm_maps(), st.integers(1, 12))
def test_own_maps_give_the_dense_maps_states_in_every_variant(case, steps):
    """The decentralized mode's sparse own maps read as the dense ``(N, nx, ny)`` maps."""
    grid, _, importance, positions, rng = case
    start = grid.free_float.copy()
    own, dense = OwnMaps(start, len(positions)), np.repeat(start[None], len(positions), axis=0)
    pos = positions
    for _ in range(steps):
        own.advance(pos, grid, PARAMS)
        dense = own_visits_update(dense, pos, grid, PARAMS)
        feasible = grid.feasible_actions(pos)
        actions = np.array([rng.choice(np.flatnonzero(f)) for f in feasible])
        pos = grid.move(pos, actions)
    others = rng.random((len(pos), 2))
    belief = (rng.random(grid.nx * grid.ny), rng.random(grid.nx * grid.ny) * 0.6)
    for variant in STATE_VARIANTS.values():
        a = variant.states(grid, own, importance, pos, others, belief=belief)
        b = variant.states(grid, dense, importance, pos, others, belief=belief)
        assert np.array_equal(a, b), variant.name


def _window_by_hand(grid, idleness, importance, positions):
    """The 25 I*T values of the window, by loops: row by row, 0 off the map or on obstacles."""
    r = WINDOW_RADIUS
    out = []
    for i, j in positions:
        row = []
        for di in range(-r, r + 1):
            for dj in range(-r, r + 1):
                a, b = i + di, j + dj
                inside = 0 <= a < grid.nx and 0 <= b < grid.ny and grid.free[a, b]
                row.append(idleness[a, b] * importance[a, b] if inside else 0.0)
        out.append(row)
    return np.array(out)


@settings(max_examples=100, deadline=None)
@given(swarm_maps())
def test_window_variant_values_shape_and_range(case):
    grid, idleness, importance, positions, _ = case
    window = STATE_VARIANTS["window"]
    s = window.states(grid, idleness, importance, positions)
    assert s.shape == (len(positions), window.size) == (len(positions), 33)
    assert len(window.layout) == window.size
    assert np.isfinite(s).all() and (s >= 0).all() and (s <= 1).all()
    paper = drone_states(grid, idleness, importance, positions)
    # position, directional means and centre of mass: the paper's values
    assert np.array_equal(s[:, :2], paper[:, :2])
    assert np.array_equal(s[:, -6:], paper[:, -6:])
    cells = s[:, 2:27]
    np.testing.assert_allclose(cells, _window_by_hand(grid, idleness, importance, positions))
    # the window's centre and its four neighbours are the paper's field of view
    centre, up, down, left, right = 12, 7, 17, 11, 13
    assert np.array_equal(cells[:, [centre, up, down, left, right]], paper[:, 2:7])


def test_paper_states_are_in_the_unit_range_on_an_update():
    grid = Grid.open(5, 6)
    idle = update_idleness(grid.free_float, np.array([[0, 0], [4, 5]]), grid, 0.1, 0.025)
    belief = (np.full(30, 0.4), np.full(30, 0.2))
    for variant in STATE_VARIANTS.values():
        s = variant.states(grid, idle, np.full(grid.shape, 0.7), np.array([[0, 0], [4, 5]]),
                           belief=belief)  # fmt: skip
        assert (s >= 0).all() and (s <= 1).all()


def test_the_variant_functions_are_the_registrys():
    assert STATE_VARIANTS["paper"].build is paper_states
    assert STATE_VARIANTS["window"].build is window_states
    assert STATE_VARIANTS["nowcast"].build is nowcast_states


def _view_by_hand(grid, values, positions):
    """``values`` (flat) on the 5 view cells (centre, up, down, left, right), by loops: 0 off
    the map or on obstacles."""
    out = []
    for i, j in positions:
        row = []
        for di, dj in ((0, 0), (-1, 0), (1, 0), (0, -1), (0, 1)):
            a, b = i + di, j + dj
            inside = 0 <= a < grid.nx and 0 <= b < grid.ny and grid.free[a, b]
            row.append(values[a * grid.ny + b] if inside else 0.0)
        out.append(row)
    return np.array(out)


@settings(max_examples=120, deadline=None)
@given(swarm_maps(), st.sampled_from([0.0, 0.3, 0.7]))
def test_nowcast_variant_layout_size_range_and_paper_part(case, std_scale):
    """23 values: the paper's 13 exactly, the belief's mean and 2 std on the 5 view cells (0
    off the map and on obstacles), every value in [0, 1] (a std above 1/2 is clipped)."""
    grid, idleness, importance, positions, rng = case
    nowcast = STATE_VARIANTS["nowcast"]
    assert nowcast.size == len(nowcast.layout) == 23 and nowcast.layout == NOWCAST_LAYOUT
    assert nowcast.layout[:13] == STATE_VARIANTS["paper"].layout
    assert len(set(nowcast.layout)) == 23 and nowcast.needs_belief
    cells = grid.nx * grid.ny
    mean, std = rng.random(cells), rng.random(cells) * std_scale
    for idle, others in ((idleness, None), (rng.random((len(positions), *grid.shape)),
                                            rng.random((len(positions), 2))),):  # fmt: skip
        s = nowcast.states(grid, idle, importance, positions, others, belief=(mean, std))
        assert s.shape == (len(positions), 23)
        assert np.isfinite(s).all() and (s >= 0).all() and (s <= 1).all()
        paper = STATE_VARIANTS["paper"].states(grid, idle, importance, positions, others)
        assert np.array_equal(s[:, :13], paper)
        assert np.array_equal(s[:, 13:18], _view_by_hand(grid, mean, positions))
        scaled = _view_by_hand(grid, np.minimum(1.0, 2.0 * std), positions)
        assert np.array_equal(s[:, 18:], scaled)


def test_the_nowcast_variant_refuses_to_build_without_a_belief():
    grid = Grid.open(3, 3)
    with pytest.raises(ValueError, match="needs the nowcast belief"):
        STATE_VARIANTS["nowcast"].states(grid, grid.free_float, grid.free_float, np.array([[1, 1]]))


def test_an_unknown_variant_is_one_line():
    with pytest.raises(UserError, match="is not a state variant") as info:
        state_variant("wide")
    assert "\n" not in str(info.value) and "'nowcast'" in str(info.value)


# ----------------------------------------------------------------------------- pretraining
def _pretrain_config(tmp_path, state, layers=True, extra=""):
    size = STATE_VARIANTS[state].size if state in STATE_VARIANTS else 13
    path = tmp_path / f"pretrain-{state}.toml"
    path.write_text(
        f'state = "{state}"\n'
        + (f"layers = [{size}, 16, 5]\n" if layers else "")
        + 'scenario_overrides = { "traffic.horizon" = 20 }\n'
        "episodes = 2\nepochs = 6\niters_per_epoch = 1\ntarget_update_epochs = 3\n"
        f'log_every = 3\ncheckpoint_every = 3\nout = "{tmp_path / ("out-" + state)}"\n' + extra
    )
    return path


def _cli(argv, capsys):
    from twin.cli import main

    code = main(argv)
    err = capsys.readouterr().err
    assert "Traceback" not in err
    return code, err.strip()


def _evaluate_config(tmp_path, checkpoint):
    """configs/synthetic.toml over 4 steps, every learned swarm on ``checkpoint``, the ``rl``
    swarm with a coordinator outage (the decentralized fallback)."""
    from twin.resources import shipped_config

    text = shipped_config("synthetic").read_text().replace("horizon = 2000", "horizon = 4")
    text += (
        f'\n[swarm_options.rl]\ncheckpoint = "{checkpoint}"\noutages = [[1, 3]]\n'
        f'[swarm_options.rl-decentralized]\ncheckpoint = "{checkpoint}"\n'
        f'[swarm_options.rl-online]\ncheckpoint = "{checkpoint}"\nbatch_size = 4\n'
    )
    path = tmp_path / "evaluate.toml"
    path.write_text(text)
    return path


@pytest.mark.parametrize("state", ["paper", "window"])
def test_a_tiny_pretraining_per_variant_saves_reloads_and_evaluates(tmp_path, capsys, state):
    import json

    from twin.learning.checkpoint import load_qnet, read_checkpoint
    from twin.learning.policies import RLPolicy

    size = STATE_VARIANTS[state].size
    code, err = _cli(["pretrain", "--config", str(_pretrain_config(tmp_path, state)),
                      "--quiet"], capsys)  # fmt: skip
    assert code == 0, err
    model = tmp_path / f"out-{state}" / "qnet.pt"
    meta = read_checkpoint(model)["meta"]
    assert meta["state"] == state and meta["layers"] == [size, 16, 5]
    assert meta["state_layout"] == list(STATE_VARIANTS[state].layout)
    net, _ = load_qnet(model)
    assert net.layers[0] == size
    assert RLPolicy(checkpoint=model).variant.name == state
    provenance = json.loads((tmp_path / f"out-{state}" / "provenance.json").read_text())
    assert provenance["recipe"]["state"] == STATE_VARIANTS[state].summary
    # the same command again resumes (a finished run: nothing to do) rather than refusing
    code, err = _cli(["pretrain", "--config", str(_pretrain_config(tmp_path, state)),
                      "--quiet"], capsys)  # fmt: skip
    assert code == 0, err
    out = tmp_path / "run"
    code, err = _cli(["evaluate", "--config", str(_evaluate_config(tmp_path, model)),
                      "--swarms", "rl,rl-online,rl-decentralized", "--seeds", "1",
                      "--out", str(out), "--no-ceiling", "--no-report", "--quiet"],
                     capsys)  # fmt: skip
    assert code == 0, err
    recorded = (out / "config.json").read_text() if (out / "config.json").exists() else ""
    described = [p.read_text() for p in out.rglob("*.json")]
    assert any(f'"state": "{state}"' in text for text in [*described, recorded])


def test_config_sizes_the_first_layer_to_the_state(tmp_path):
    from twin.learning.qnet import TABLE1_LAYERS
    from twin.training.pretrain import PretrainConfig, load_config

    assert PretrainConfig().layers == list(TABLE1_LAYERS)
    window = load_config(_pretrain_config(tmp_path, "window", layers=False))
    assert window.layers == [33, *TABLE1_LAYERS[1:]]
    assert window.training_dict()["state"] == "window"
    assert "state" not in PretrainConfig().training_dict()  # the paper's: as before


@pytest.mark.parametrize(
    ("text", "words"),
    [
        (
            'state = "nowcast"\ntraffic = "dynamics"\nhistory_seed = 5\n',
            "history_seed = 5: the history's day 5 is also a training episode's seed",
        ),
        ('state = "wide"\n', "state = 'wide' is not a state variant"),
        ('state = "window"\nlayers = [13, 16, 5]\n', "state = 'window' has 33 values"),
    ],
)
def test_a_bad_state_is_one_line_naming_the_key(tmp_path, capsys, text, words):
    path = tmp_path / "bad.toml"
    path.write_text(text)
    code, err = _cli(["pretrain", "--config", str(path), "--quiet"], capsys)
    assert code == 2 and words in err and "\n" not in err, err
    assert "the file =" not in err  # a check of the whole file names its keys, not the file


def _checkpoint(tmp_path, name, layers, state="paper", drop_state=False, meta_state=None):
    from twin.learning.checkpoint import model_metadata, save_model
    from twin.learning.qnet import QNetwork

    meta = model_metadata(layers, {}, 0, 1, state)
    if drop_state:
        del meta["state"]
    if meta_state is not None:
        meta["state"] = meta_state
    path = tmp_path / name
    save_model(path, QNetwork(layers).state_dict(), meta)
    return path


def test_a_checkpoint_without_the_state_key_is_the_paper_state(tmp_path):
    from twin.learning.policies import RLPolicy

    old = _checkpoint(tmp_path, "old.pt", [13, 16, 5], drop_state=True)
    assert RLPolicy(checkpoint=old).variant.name == "paper"
    assert RLPolicy(checkpoint=old, state="paper").variant.name == "paper"


@pytest.mark.parametrize(
    ("layers", "state", "meta_state", "words"),
    [
        ([13, 16, 5], "window", None, "first layer takes 13 values but its state variant 'window'"),
        ([13, 16, 5], "paper", "wide", "state variant 'wide' is not one this version builds"),
    ],
)
def test_a_checkpoint_of_mismatched_state_is_refused_in_one_line(
    tmp_path, layers, state, meta_state, words
):
    from twin.learning.checkpoint import load_qnet

    path = _checkpoint(tmp_path, "bad.pt", layers, state, meta_state=meta_state)
    with pytest.raises(UserError, match=words) as info:
        load_qnet(path)
    assert str(path) in str(info.value) and "\n" not in str(info.value)


def test_a_swarm_expecting_another_state_is_refused_in_one_line(tmp_path):
    from twin.learning.policies import RLPolicy

    path = _checkpoint(tmp_path, "window.pt", [33, 16, 5], "window")
    with pytest.raises(UserError, match="reads state 'window', not 'paper'") as info:
        RLPolicy(checkpoint=path, state="paper")
    assert str(path) in str(info.value) and "\n" not in str(info.value)


def test_fine_tuning_from_a_checkpoint_of_another_state_is_refused(tmp_path, capsys):
    init = _checkpoint(tmp_path, "paper.pt", [13, 16, 5])
    path = _pretrain_config(tmp_path, "window", extra=f'init = "{init}"\n')
    code, err = _cli(["pretrain", "--config", str(path), "--quiet"], capsys)
    assert code == 2 and "reads state 'paper', this pretraining state = 'window'" in err, err
    assert str(init) in err and "\n" not in err


def test_the_replay_buffer_holds_any_state_size():
    from twin.learning.replay import ReplayBuffer, n_step_transitions

    rng = np.random.default_rng(0)
    buffer = ReplayBuffer(6, 2, state_size=33, discounted=True)
    states = rng.random((6, 2, 33), dtype=np.float32)
    rewards = rng.random((6, 2), dtype=np.float32)
    feasible = np.ones((6, 2, 5), bool)
    returns, nxt, nf, disc = n_step_transitions(rewards, states, feasible, 0.9, 3)
    buffer.add_steps(states, np.zeros((6, 2), np.int64), returns, nxt, nf, disc)
    batch = buffer.sample(8, rng)
    assert batch.states.shape == (8, 33) and batch.next_states.shape == (8, 33)


# ----------------------------------------------------------------------------- nowcast
def _nowcast_config(tmp_path, traffic="dynamics", extra=""):
    return _pretrain_config(tmp_path, "nowcast", extra=f'traffic = "{traffic}"\nhistory_days = 3\n'
                            + extra)  # fmt: skip


def _history_file(tmp_path, config, capsys, days=3, seed=2_000_000):
    path = tmp_path / f"history-{seed}.npz"
    code, err = _cli(["history", "--dynamics", str(config), "--days", str(days), "--seed",
                      str(seed), "--out", str(path)], capsys)  # fmt: skip
    assert code == 0, err
    return path


@pytest.mark.parametrize("traffic", ["dynamics", "paper"])
def test_a_tiny_nowcast_pretraining_saves_reloads_resumes_and_evaluates(tmp_path, capsys, traffic):
    import json

    from twin.learning.checkpoint import load_qnet, read_checkpoint
    from twin.learning.policies import RLPolicy

    config = _nowcast_config(tmp_path, traffic)
    code, err = _cli(["pretrain", "--config", str(config), "--quiet"], capsys)
    assert code == 0, err
    out = tmp_path / "out-nowcast"
    meta = read_checkpoint(out / "qnet.pt")["meta"]
    assert meta["state"] == "nowcast" and meta["layers"] == [23, 16, 5]
    assert meta["state_layout"] == list(NOWCAST_LAYOUT)
    seeds = [1_000_000, 1_000_001, 1_000_002] if traffic == "dynamics" else []
    assert meta["history"]["days"] == 3 and meta["history"]["seeds"] == seeds
    assert meta["config"]["history_days"] == 3 and meta["config"]["history_seed"] == 1_000_000
    state = read_checkpoint(out / "state.pt")["meta"]
    assert state["history"] == meta["history"] and state["epoch"] == 6
    provenance = json.loads((out / "provenance.json").read_text())
    assert provenance["recipe"]["history"] == meta["history"]
    net, _ = load_qnet(out / "qnet.pt")
    assert net.layers[0] == 23
    # resumed: the run of 6 epochs carried on to 9 from its state.pt
    code, err = _cli(["pretrain", "--config", str(config), "--epochs", "9", "--quiet"], capsys)
    assert code == 0, err
    assert read_checkpoint(out / "qnet.pt")["meta"]["epoch"] == 9
    # evaluated with the run's history (the dynamic generator's days on the synthetic grid)
    evaluate = _nowcast_evaluate_config(tmp_path, out / "qnet.pt")
    history = _history_file(tmp_path, evaluate, capsys)
    run = tmp_path / "run"
    code, err = _cli(["evaluate", "--config", str(evaluate), "--swarms", "rl,rl-online",
                      "--seeds", "1", "--history", str(history), "--out", str(run),
                      "--no-ceiling", "--no-report", "--quiet"], capsys)  # fmt: skip
    assert code == 0, err
    assert "belief_models.csv" in {p.name for p in run.iterdir()}
    described = json.loads((run / "run.json").read_text())["policies"]["rl"]
    assert described["state"] == "nowcast" and described["history_seeds"] == [
        2_000_000, 2_000_001, 2_000_002,
    ]  # fmt: skip
    assert RLPolicy(checkpoint=out / "qnet.pt", history=history).variant.name == "nowcast"


def _nowcast_evaluate_config(tmp_path, checkpoint):
    from twin.resources import shipped_config

    text = shipped_config("synthetic").read_text().replace("horizon = 2000", "horizon = 4")
    text += (
        f'\n[swarm_options.rl]\ncheckpoint = "{checkpoint}"\n'
        f'[swarm_options.rl-online]\ncheckpoint = "{checkpoint}"\nbatch_size = 4\n'
        f'[swarm_options.rl-decentralized]\ncheckpoint = "{checkpoint}"\n'
    )
    path = tmp_path / "evaluate-nowcast.toml"
    path.write_text(text)
    return path


def test_the_collected_nowcast_features_are_the_runs_nowcast():
    """Data collection updates the filter on the swarm's sightings each step, as a run does:
    the mean and std read in the recorded states are :func:`twin.belief.nowcast` of the
    episode's trajectory on the same history, on each drone's view cells."""
    from twin.belief import nowcast
    from twin.learning.data import random_swarm_episode
    from twin.traffic.dynamic import DynamicTraffic, dynamics_history

    grid, horizon = Grid.open(6, 7), 12
    history = dynamics_history(grid, horizon, [50, 51, 52], disturbances=3)
    source = DynamicTraffic(grid, horizon, 3, seed=9)
    variant = STATE_VARIANTS["nowcast"]
    ep = random_swarm_episode(source, 3, PARAMS, np.random.default_rng(4), variant, history)
    states = np.concatenate([ep.states, ep.next_states[-1:]]).astype(np.float64)  # (T+1, N, 23)
    positions = np.rint(states[..., :2] * np.array([grid.nx, grid.ny])).astype(np.int64)
    observed = np.stack(list(source.importance_maps()))
    mean, std = nowcast(grid, positions, observed, history)
    assert std.max() > 0.02  # the history has a spread: the features are not constant
    for k in range(horizon + 1):
        np.testing.assert_allclose(states[k, :, 13:18], _view_by_hand(grid, mean[k], positions[k]),
                                   atol=1e-6)  # fmt: skip
        scaled = _view_by_hand(grid, np.minimum(1.0, 2.0 * std[k]), positions[k])
        np.testing.assert_allclose(states[k, :, 18:], scaled, atol=1e-6)


def test_nowcast_refusals_are_one_line(tmp_path, capsys):
    from twin.env import SwarmParallelEnv
    from twin.learning.policies import RLPolicy
    from twin.traffic.dynamic import DynamicTraffic

    path = _checkpoint(tmp_path, "nowcast.pt", [23, 16, 5], "nowcast")
    with pytest.raises(UserError, match="give --history FILE") as info:
        RLPolicy(checkpoint=path)
    assert str(path) in str(info.value) and "\n" not in str(info.value)
    history = _history_file(tmp_path, _nowcast_evaluate_config(tmp_path, path), capsys)
    for options in ({"decentralized": True}, {"outages": [[1, 2]]}):
        with pytest.raises(UserError, match="runs with the coordinator only") as info:
            RLPolicy(checkpoint=path, history=history, **options)
        assert str(path) in str(info.value) and "\n" not in str(info.value)
    policy = RLPolicy(checkpoint=path, history=history)
    policy.outages = ((1, 2),)  # as a scripted coordinator outage ([faults]) sets them
    with pytest.raises(UserError, match="coordinator_down") as info:
        policy.reset(Grid.open(20, 30), 2, np.random.default_rng(0))
    assert str(path) in str(info.value) and "\n" not in str(info.value)
    with pytest.raises(UserError, match="envs do not carry") as info:
        SwarmParallelEnv(DynamicTraffic(Grid.open(4, 4), 5), 2, state="nowcast")
    assert "\n" not in str(info.value)
    # the CLI: no history, a history of another horizon
    evaluate = _nowcast_evaluate_config(tmp_path, path)
    code, err = _cli(["evaluate", "--config", str(evaluate), "--swarms", "rl", "--seeds", "1",
                      "--no-ceiling", "--no-report", "--quiet",
                      "--out", str(tmp_path / "r1")], capsys)  # fmt: skip
    assert code == 2 and str(path) in err and "--history" in err and "\n" not in err, err
    other = tmp_path / "other.toml"
    other.write_text(evaluate.read_text().replace("horizon = 4", "horizon = 6"))
    longer = _history_file(tmp_path, other, capsys, seed=3_000_000)
    code, err = _cli(["evaluate", "--config", str(evaluate), "--swarms", "rl", "--seeds", "1",
                      "--history", str(longer), "--no-ceiling", "--no-report", "--quiet",
                      "--out", str(tmp_path / "r2")], capsys)  # fmt: skip
    assert code == 2 and "horizon" in err and "\n" not in err, err


def test_nowcast_pretraining_on_tapes_is_refused_in_one_line(tmp_path, capsys):
    tape = tmp_path / "tape.parquet"
    tape.write_bytes(b"")
    path = _nowcast_config(tmp_path, "tapes", extra=f'tapes = ["{tape}"]\n')
    code, err = _cli(["pretrain", "--config", str(path), "--quiet"], capsys)
    assert code == 2 and 'traffic = "tapes" needs a history' in err and "\n" not in err, err


@pytest.mark.parametrize(
    ("argv", "words"),
    [
        (["--dynamics", "synthetic", "--days", "1"], "--days 1: give a whole number >= 2"),
        (["--dynamics", "shenzhen"], "[traffic].kind = 'sumo'; give a synthetic scenario"),
        (  # seeds past the range every command keeps to (probe 19's P2-04)
            ["--dynamics", "synthetic", "--seed", "9223372036854775808"],
            "--seed = 9223372036854775808 is out of range",
        ),
        (
            ["--dynamics", "synthetic", "--seed", "2147483647", "--days", "2"],
            "--days = 2 runs seeds 2147483647 .. 2147483648, past the largest seed 2147483647; "
            "give --seed at most 2147483646",  # not --days 1, which a history refuses (probe 20)
        ),
    ],
)
def test_a_bad_dynamics_history_is_one_line(tmp_path, capsys, argv, words):
    out = tmp_path / "h.npz"
    code, err = _cli(["history", *argv, "--out", str(out)], capsys)
    assert code == 2 and words in err and "\n" not in err, err
    assert not out.exists()


def test_a_seed_range_past_the_largest_seed_is_offered_fixes_its_flags_take():
    """Too many days from a good first seed: fewer days, or a smaller first seed when that
    fits them all, never a negative one (the review), nor fewer days than a history takes."""
    from twin.cli import check_seeds

    cases = [
        ((0, 3_000_000_000), "give at most 2147483648"),  # no first seed fits them all
        ((2_147_483_647, 2), "give --seed at most 2147483646"),  # --days 1: no history
        ((2_147_483_600, 100), "give at most 48, or --seed at most 2147483548"),
    ]
    for (first, days), fix in cases:
        with pytest.raises(UserError) as caught:
            check_seeds("--seed", first, days, "--days", least=2)
        assert str(caught.value).endswith(fix), caught.value
