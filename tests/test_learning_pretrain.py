"""Pretraining: config errors, Double DQN target, resumption after a kill."""

import csv
import os
import re
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
import torch

from twin.errors import UserError
from twin.learning.qnet import QNetwork
from twin.training.pretrain import double_dqn_target, load_config, pretrain

TINY = """
layers = [13, 16, 5]
scenario_overrides = {{ "traffic.horizon" = 60 }}
episodes = 2
epochs = {epochs}
iters_per_epoch = 2
target_update_epochs = 5
log_every = 5
checkpoint_every = {every}
"""


def _grid(nx, ny, n_drones=4):
    return (
        f'scenario_overrides = {{ "grid.nx" = {nx}, "grid.ny" = {ny}, '
        f'"swarm.n_drones" = {n_drones} }}'
    )


def _config(tmp_path, epochs=40, every=10, name="tiny.toml", out="out"):
    path = tmp_path / name
    path.write_text(TINY.format(epochs=epochs, every=every) + f'out = "{tmp_path / out}"\n')
    return path


def _logged_epochs(path):
    with open(path, newline="") as f:
        return [int(r["epoch"]) for r in csv.DictReader(f)]


def _weights(path):
    return torch.load(path, weights_only=True)["weights"]


def test_resumed_run_equals_uninterrupted_run(tmp_path):
    whole = load_config(_config(tmp_path, out="whole"))
    pretrain(whole, progress=False)
    # the same run stopped at epoch 20 (a checkpoint), then resumed to 40
    split = _config(tmp_path, name="split.toml", out="split")
    pretrain(load_config(split, epochs=20), progress=False)
    pretrain(load_config(split), progress=False)
    a, b = _weights(tmp_path / "whole/qnet.pt"), _weights(tmp_path / "split/qnet.pt")
    assert all(torch.equal(a[k], b[k]) for k in a)
    epochs = _logged_epochs(tmp_path / "split/train_log.csv")
    assert epochs == list(range(5, 41, 5))


def test_kill_9_mid_run_resumes_with_the_same_command(tmp_path):
    config = _config(tmp_path, epochs=1500, every=50)
    cmd = [sys.executable, "-m", "twin", "pretrain", "--config", str(config), "--quiet"]
    env = {**os.environ, "PYTHONPATH": str(Path(__file__).resolve().parents[1])}
    state = tmp_path / "out/state.pt"
    proc = subprocess.Popen(cmd, env=env, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
    deadline = time.monotonic() + 60
    while not state.exists() and time.monotonic() < deadline and proc.poll() is None:
        time.sleep(0.05)
    time.sleep(0.3)
    if proc.poll() is not None:
        pytest.skip("run finished before it could be killed; machine too fast for this test")
    os.kill(proc.pid, signal.SIGKILL)
    proc.wait()
    killed_at = torch.load(state, weights_only=True)["epoch"]
    assert 0 < killed_at < 1500
    done = subprocess.run(cmd, env=env, capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr
    assert torch.load(state, weights_only=True)["epoch"] == 1500
    epochs = _logged_epochs(tmp_path / "out/train_log.csv")
    assert epochs == sorted(set(epochs)) and epochs[-1] == 1500  # no duplicate rows


def test_resuming_with_other_settings_is_refused(tmp_path):
    config = _config(tmp_path, epochs=10)
    pretrain(load_config(config), progress=False)
    with pytest.raises(UserError, match="other settings"):
        pretrain(_changed(config), progress=False)


def test_rerunning_a_finished_run_with_fewer_epochs_is_refused(tmp_path, capsys):
    """A folder trained 20 epochs, rerun with ``--epochs 10``: refused in one line, the model
    and its record untouched (they were rewritten as 10 epochs' for weights of 20: probe 21's
    f06); the same epochs again still writes its model."""
    config = _config(tmp_path, epochs=20)
    pretrain(load_config(config), progress=False)
    model = (tmp_path / "out" / "qnet.pt").read_bytes()
    provenance = (tmp_path / "out" / "provenance.json").read_bytes()
    code, err = _run_cli(["pretrain", "--config", str(config), "--epochs", "10", "--quiet"], capsys)
    assert code == 2 and err.count("\n") == 0, err
    assert "state.pt: its run trained 20 epochs, past --epochs 10; give at least 20 epochs" in err
    assert (tmp_path / "out" / "qnet.pt").read_bytes() == model
    assert (tmp_path / "out" / "provenance.json").read_bytes() == provenance
    code, err = _run_cli(["pretrain", "--config", str(config), "--quiet"], capsys)
    assert code == 0, err


def test_threads_past_the_cpus_train_on_the_cpus_with_a_notice(tmp_path, capsys):
    """``threads`` past the CPUs twin may use: training runs on those CPUs, with a notice (it
    failed as "out of memory; use a smaller grid": probe 21's f04); the config keeps its
    value, so its checkpoint resumes on a smaller machine."""
    import torch

    cpus = len(os.sched_getaffinity(0))
    config = _config(tmp_path, epochs=10)
    config.write_text(config.read_text() + f"threads = {100 * cpus}\n")
    before = torch.get_num_threads()
    try:
        code, err = _run_cli(["pretrain", "--config", str(config), "--quiet"], capsys)
        assert torch.get_num_threads() == cpus
    finally:
        torch.set_num_threads(before)  # this test process's own
    assert code == 0, err
    assert f"threads = {100 * cpus}, but this machine gives twin {cpus} CPUs" in err, err


def test_a_damaged_resume_checkpoint_gives_a_fix_that_works(tmp_path, capsys):
    """A truncated ``state.pt`` in ``out``: the line says to delete the folder (or set another
    ``out``), which works; "re-create it with twin pretrain" failed the same way (probe 22's
    f04)."""
    import shutil

    config = _config(tmp_path, epochs=10)
    pretrain(load_config(config), progress=False)
    state = tmp_path / "out" / "state.pt"
    state.write_bytes(state.read_bytes()[:1000])
    code, err = _run_cli(["pretrain", "--config", str(config), "--quiet"], capsys)
    assert code == 2 and err.count("\n") == 0, err
    assert "state.pt is corrupt" in err and f"delete {tmp_path / 'out'} or set another" in err
    shutil.rmtree(tmp_path / "out")  # the fix
    code, err = _run_cli(["pretrain", "--config", str(config), "--quiet"], capsys)
    assert code == 0, err


def _changed(config):
    text = config.read_text().replace("iters_per_epoch = 2", "iters_per_epoch = 3")
    config.write_text(text)
    return load_config(config)


@pytest.mark.parametrize(
    ("text", "match"),
    [
        ("lr = -1.0", "lr"),
        ("epochs = 'many'", "epochs"),
        ("learning_rate = 0.1", "learning_rate is not a known key"),
        ("layers = [12, 5]", "layer"),
        ("gamma = 1.5", "gamma"),
        ("epochs = [", "not valid TOML"),
    ],
)
def test_bad_configs_are_one_line_user_errors(tmp_path, text, match):
    path = tmp_path / "bad.toml"
    path.write_text(text + "\n")
    with pytest.raises(UserError, match=match) as err:
        load_config(path)
    assert "\n" not in str(err.value)


def test_double_dqn_target_uses_feasible_argmax_of_online_net_and_target_value():
    torch.manual_seed(0)
    net, target = QNetwork([13, 8, 5]), QNetwork([13, 8, 5])
    s1 = torch.randn(6, 13)
    feasible = torch.rand(6, 5) < 0.6
    feasible[:, 0] = True
    r = torch.randn(6)
    y = double_dqn_target(net, target, r, s1, feasible, 0.9)
    with torch.no_grad():
        q_online = net(s1).numpy()
        q_target = target(s1).numpy()
    best = np.where(feasible.numpy(), q_online, -np.inf).argmax(axis=1)
    expected = r.numpy() + 0.9 * q_target[np.arange(6), best]
    assert np.allclose(y.numpy(), expected, atol=1e-6)


def test_cli_pretrain_bad_config_exits_2(tmp_path):
    from twin.cli import main

    path = tmp_path / "bad.toml"
    path.write_text("batch_size = 0\n")
    assert main(["pretrain", "--config", str(path), "--quiet"]) == 2


def _run_cli(argv, capsys):
    from twin.cli import main

    code = main(argv)
    err = capsys.readouterr().err
    assert "Traceback" not in err
    return code, err.strip()


@pytest.mark.parametrize(
    ("text", "words"),
    [
        ("layers = [13, 100000000, 5]", "lower batch_size or layers"),
        ("layers = [13, 20000, 20000, 5]", "(network: "),
        ("batch_size = 100000000000", "lower batch_size"),
        ("episodes = 100000000", "lower episodes, traffic.horizon or swarm.n_drones"),
        (_grid(100000, 100000), "scenario_overrides 'grid.nx': a 100000 x 100000 grid"),
        (_grid(3000, 3000), "lower grid.nx, grid.ny"),
        (_grid(10, 10, n_drones=1000), "'swarm.n_drones' 1000 exceeds the 100 free cells"),
        # the nowcast's history of days is counted (it ran out of memory: probe 23's f10)
        ('state = "nowcast"\nhistory_days = 10000000', "lower history_days, traffic.horizon"),
        ('traffic = "dynamics"\ndynamics_disturbances = 100000000', "dynamics_disturbances"),
    ],
)
def test_pretraining_past_memory_or_map_is_refused(tmp_path, capsys, text, words):
    path = tmp_path / "big.toml"
    path.write_text(text + f'\nout = "{tmp_path / "out"}"\nepochs = 1\n')
    code, err = _run_cli(["pretrain", "--config", str(path), "--quiet"], capsys)
    assert code == 2 and err.count("\n") == 0 and words in err, err
    assert str(path) in err
    assert not (tmp_path / "out").exists()


@pytest.mark.parametrize(
    ("curve", "words"),
    [
        ('"no-such-map.toml"', "curve_config = 'no-such-map.toml' names "),
        ('"map.toml"', "curve_config = 'map.toml' names "),  # beside the cwd, not the file
    ],
)
def test_a_curve_config_naming_no_file_is_refused_before_training(
    tmp_path, capsys, monkeypatch, curve, words
):
    """curve_config is found as scenario is, relative to the pretraining config (else a
    shipped one), and read before training: it failed after the last epoch, naming no key."""
    folder = tmp_path / "configs"
    folder.mkdir()
    path = folder / "pt.toml"
    path.write_text(
        f'out = "{tmp_path / "out"}"\nepochs = 2\ncurve_every = 1\ncurve_config = {curve}\n'
    )
    shipped = Path(__file__).resolve().parents[1] / "configs" / "synthetic.toml"
    (tmp_path / "map.toml").write_text(shipped.read_text())
    monkeypatch.chdir(tmp_path)  # map.toml is here, not beside pt.toml
    code, err = _run_cli(["pretrain", "--config", str(path), "--quiet"], capsys)
    assert code == 2 and err.count("\n") == 0 and words in err and str(path) in err, err
    assert "(the default)" in err and '"synthetic"' in err
    assert not (tmp_path / "out").exists()


@pytest.mark.parametrize(
    ("lines", "said", "unsaid"),
    [
        (  # a shipped config of another kind (a pretraining config): the file is the cause
            'curve_config = "pretrain"\n',
            ["cannot measure the curve:"],
            "curve_horizon",
        ),
        (  # the shipped incident scenario at 5 steps: its incident misses the curve's window
            'curve_config = "incident"\ncurve_horizon = 5\n',
            ["is outside the scenario's window", "over curve_horizon = 5 steps",
             "set curve_horizon = "],
            None,
        ),
    ],
)  # fmt: skip
def test_a_curve_config_that_cannot_measure_the_curve_is_refused_naming_the_key(
    tmp_path, capsys, lines, said, unsaid
):
    """curve_config naming a config of another kind, or a scenario whose incident falls
    outside the curve's shorter window, is refused before training by a line naming the key
    and the pretraining config, not the shipped file (it failed after the last epoch)."""
    path = tmp_path / "pt.toml"
    path.write_text(f'out = "{tmp_path / "out"}"\nepochs = 2\ncurve_every = 1\n{lines}')
    code, err = _run_cli(["pretrain", "--config", str(path), "--quiet"], capsys)
    assert code == 2 and err.count("\n") == 0, err
    assert f"{path}: curve_config = " in err and all(words in err for words in said), err
    assert unsaid is None or unsaid not in err, err  # the file is the cause, not the window
    assert not (tmp_path / "out").exists()


def test_pretraining_memory_limit_flag(tmp_path, capsys):
    config = _config(tmp_path)
    argv = ["pretrain", "--config", str(config), "--quiet", "--max-memory-gb", "1e-9"]
    code, err = _run_cli(argv, capsys)
    assert code == 2 and "over the 1e-09 GB limit" in err and err.count("\n") == 0


def _foreign_files(out):
    out.mkdir()
    (out / "qnet.pt").write_text("my own model")
    (out / "train_log.csv").write_text("mine\n1\n")


@pytest.mark.parametrize(
    ("make", "words"),
    [
        (_foreign_files, "train_log.csv is not a pretraining log"),
        (lambda out: (out.mkdir(), (out / "qnet.pt").write_text("x")), "no checkpoint state.pt"),
        (lambda out: (out.mkdir(), (out / "notes.txt").write_text("x")), "'notes.txt'"),
        (
            lambda out: (out.mkdir(), (out / "snapshots").mkdir(), (out / "snapshots/a").touch()),
            "snapshots/a",
        ),
        (lambda out: (out.mkdir(), (out / "state.pt").write_text("x")), "state.pt"),
    ],
)
def test_out_holding_files_pretraining_did_not_write_is_refused(tmp_path, capsys, make, words):
    out = tmp_path / "own"
    make(out)
    before = {p: p.read_bytes() for p in out.rglob("*") if p.is_file()}
    argv = ["pretrain", "--config", str(_config(tmp_path)), "--out", str(out), "--quiet"]
    code, err = _run_cli(argv, capsys)
    assert code == 2 and err.count("\n") == 0 and words in err, err
    assert {p: p.read_bytes() for p in out.rglob("*") if p.is_file()} == before


def test_out_with_a_checkpoint_of_other_settings_is_refused_before_collecting(tmp_path, capsys):
    config = _config(tmp_path, epochs=10)
    argv = ["pretrain", "--config", str(config), "--quiet"]
    assert _run_cli(argv, capsys)[0] == 0
    _changed(config)
    code, err = _run_cli(argv, capsys)
    assert code == 2 and "other settings (iters_per_epoch)" in err and err.count("\n") == 0


def test_a_damaged_log_row_is_one_line_naming_the_file(tmp_path):
    from twin.errors import UserError
    from twin.training.pretrain import _truncate_log

    log = tmp_path / "train_log.csv"
    log.write_text("epoch,updates,loss\n1000,1000,0.02\ngarbage,,,\n")
    with pytest.raises(UserError, match=r"train_log.csv: row 3 starts with 'garbage'"):
        _truncate_log(log, 1000)
    log.write_text("epoch,updates,loss\n1000,1000,0.02\n2000,2000,0.01\n")
    _truncate_log(log, 1000)
    assert log.read_text().splitlines() == ["epoch,updates,loss", "1000,1000,0.02"]


# ----------------------------------------------------------------------------- recipes
def test_recipes_collect_on_their_traffic_and_record_curve_and_provenance(tmp_path):
    import json

    from helpers import random_tape

    from twin.training.pretrain import collect_buffer

    tape_a, tape_b = tmp_path / "a.parquet", tmp_path / "b.parquet"
    random_tape(seed=1, nx=6, ny=6, horizon=30).write(tape_a)
    random_tape(seed=2, nx=6, ny=6, horizon=25).write(tape_b)
    paper = load_config(_config(tmp_path, out="paper"))
    tapes = load_config(_config(tmp_path, out="tapes"), tapes=[str(tape_a), str(tape_b)])
    assert tapes.traffic == "tapes"
    # one episode per tape, each as long as its tape
    assert collect_buffer(tapes).steps == 30 + 25
    dyn = load_config(_config(tmp_path, out="dyn")).model_copy(update={"traffic": "dynamics"})
    buffers = [collect_buffer(c) for c in (paper, dyn)]
    assert not np.array_equal(buffers[0].rewards[:60], buffers[1].rewards[:60])

    # fine-tuning starts from the given weights: the curve's first point is that network
    pretrain(paper, progress=False)
    tuned = tapes.model_copy(
        update={"init": str(tmp_path / "paper/qnet.pt"), "curve_every": 20, "curve_horizon": 8}
    )
    pretrain(tuned, progress=False)
    start, final = (
        _weights(tmp_path / "tapes/snapshots/qnet_e0000000.pt"),
        _weights(tmp_path / "paper/qnet.pt"),
    )
    assert all(torch.equal(start[k], final[k]) for k in start)
    with open(tmp_path / "tapes/curve.csv", newline="") as f:
        rows = list(csv.DictReader(f))
    assert [int(r["epoch"]) for r in rows] == [0, 0, 20, 20, 40, 40]
    assert {int(r["seed"]) for r in rows} == {100, 101}
    record = json.loads((tmp_path / "tapes/provenance.json").read_text())
    assert record["recipe"]["traffic"] == "tapes" and len(record["recipe"]["tapes"]) == 2
    # the episodes' grid and steps are the tapes', said (only the unused map's were: probe 27e)
    episodes = record["recipe"]["episodes"]
    assert episodes["from"] == "tapes" and episodes["tapes"] == {
        str(tape_a): {"grid": [6, 6], "horizon": 30},
        str(tape_b): {"grid": [6, 6], "horizon": 25},
    }
    paper_record = json.loads((tmp_path / "paper/provenance.json").read_text())
    assert paper_record["recipe"]["episodes"]["from"] == "scenario"
    assert record["recipe"]["init"]["path"].endswith("paper/qnet.pt")
    assert record["updates"] == 40 * 2 and len(record["curve"]["points"]) == 6


@pytest.mark.parametrize(
    ("text", "match"),
    [
        ("curve_seeds = [3, 100]\n", "evaluation seed"),
        ("curve_seeds = [9223372036854775808]\n", r"curve_seeds\[0\] = 9223372036854775808 must"),
        (  # an empty curve, silently (probe 20's f12)
            "curve_every = 10\ncurve_seeds = []\n",
            r"curve_every = 10 asks for a learning curve, but curve_seeds = \[\] gives it no seed",
        ),
        ("seed = 2147483648\n", "seed = 2147483648 must be <= 2147483647"),
        ("history_seed = 2147483648\n", "history_seed = 2147483648 must be <= 2147483647"),
        ('traffic = "tapes"\n', "needs tape files"),
        ('traffic = "tapes"\ntapes = ["nowhere.parquet"]\n', "does not exist"),
        ('traffic = "weather"\n', "traffic"),
        ("n_step = 0\n", "n_step"),
        ('collector = "greedy"\n', "collector"),
        ("epsilon_start = 1.5\n", "epsilon_start"),
        ("epsilon_start = 0.1\nepsilon_end = 0.5\n", "epsilon_end = 0.5 is above"),
        ("collect_every = 0\n", "collect_every"),
    ],
)
def test_bad_recipes_are_one_line_errors(tmp_path, text, match):
    path = _config(tmp_path)
    path.write_text(path.read_text() + text)
    with pytest.raises(UserError, match=match) as info:
        load_config(path)
    assert "\n" not in str(info.value)


def test_init_of_other_layers_is_refused(tmp_path):
    pretrain(load_config(_config(tmp_path, out="small")), progress=False)
    path = _config(tmp_path, name="big.toml", out="big")
    path.write_text(path.read_text().replace("[13, 16, 5]", "[13, 32, 5]"))
    config = load_config(path, init=str(tmp_path / "small/qnet.pt"))
    with pytest.raises(UserError, match="layers"):
        pretrain(config, progress=False)


def test_init_whose_weights_do_not_fit_its_layers_is_one_line(tmp_path):
    """A checkpoint whose meta.layers match but one weight has another shape: refused in
    one line, not an internal error of torch's loader."""
    pretrain(load_config(_config(tmp_path, out="small")), progress=False)
    blob = torch.load(tmp_path / "small/qnet.pt", weights_only=True)
    blob["weights"]["net.0.weight"] = blob["weights"]["net.0.weight"][:3]
    torch.save(blob, tmp_path / "bent.pt")
    config = load_config(_config(tmp_path, out="again"), init=str(tmp_path / "bent.pt"))
    with pytest.raises(UserError, match="weights do not match") as info:
        pretrain(config, progress=False)
    assert "\n" not in str(info.value)


# ----------------------------------------------------------------------------- the scenario
def test_the_shipped_config_trains_on_the_shipped_models_settings():
    """configs/pretrain.toml on the training map scenario gives the settings recorded in
    data/qnet.pt, key for key (keys the checkpoint predates are at their defaults), so the
    command its README names still trains that model."""
    from twin.learning.checkpoint import read_checkpoint
    from twin.resources import shipped_checkpoint, shipped_config
    from twin.training.pretrain import PretrainConfig

    saved = read_checkpoint(shipped_checkpoint())["meta"]["config"]
    now = load_config(shipped_config("pretrain"), out=saved["out"]).training_dict()
    defaults = PretrainConfig().training_dict()
    assert {k: saved.get(k, defaults[k]) for k in now} == now
    assert [k for k in now if k in saved] == list(saved)  # the same order: the same pickle
    assert (now["nx"], now["ny"], now["n_drones"], len(now["disturbances"])) == (20, 30, 4, 7)


def test_a_scenario_of_another_grid_trains_end_to_end(tmp_path, capsys):
    """A pretraining config naming its own scenario (a 7 x 9 map with an obstacle, 3 drones):
    the random swarm collects on that map, and the model records its settings."""
    import json

    from twin.training.pretrain import collect_buffer, training_source

    (tmp_path / "small-map.toml").write_text(
        "[grid]\nnx = 7\nny = 9\nobstacles = [[3, 4]]\n[swarm]\nn_drones = 3\neta = 0.2\n"
        '[traffic]\nhorizon = 30\ndisturbances = [{ kind = "big", i = 2, j = 3, '
        "amplitude = 1.0, sigma = 2.0 }]\n"
    )
    path = _config(tmp_path, epochs=10)
    path.write_text(path.read_text().replace('"traffic.horizon" = 60', '"traffic.horizon" = 25'))
    path.write_text(path.read_text() + 'scenario = "small-map.toml"\n')
    cfg = load_config(path)
    assert training_source(cfg).grid.shape == (7, 9)
    assert not training_source(cfg).grid.free[3, 4]
    assert collect_buffer(cfg).steps == 2 * 25  # 2 episodes of the overridden horizon
    code, err = _run_cli(["pretrain", "--config", str(path), "--quiet", "--epochs", "5"], capsys)
    assert code == 0, err
    meta = torch.load(tmp_path / "out/qnet.pt", weights_only=True)["meta"]
    settings = meta["config"]
    assert (settings["nx"], settings["ny"], settings["n_drones"], settings["eta"]) == (7, 9, 3, 0.2)
    assert settings["horizon"] == 25 and settings["obstacles"] == [[3, 4]]
    assert settings["epochs"] == 5
    record = json.loads((tmp_path / "out/provenance.json").read_text())
    assert record["recipe"]["scenario"]["path"] == str(tmp_path / "small-map.toml")
    assert record["recipe"]["scenario"]["overrides"] == {"traffic.horizon": 25}


def test_the_same_map_declared_two_ways_trains_the_same_network(tmp_path):
    """The training map with its horizon overridden, and a copy of its file with that horizon
    written in: the same settings, the same weights bit for bit."""
    from twin.resources import shipped_config

    text = shipped_config("training-map").read_text().replace("horizon = 2000", "horizon = 60")
    (tmp_path / "map60.toml").write_text(text)
    overridden = load_config(_config(tmp_path, epochs=10, out="a"))
    copied = _config(tmp_path, epochs=10, name="b.toml", out="b")
    copied.write_text(
        copied.read_text().replace('{ "traffic.horizon" = 60 }', "{}") + 'scenario = "map60.toml"\n'
    )
    copied = load_config(copied)
    assert {**overridden.training_dict(), "out": ""} == {**copied.training_dict(), "out": ""}
    pretrain(overridden, progress=False)
    pretrain(copied, progress=False)
    a, b = _weights(tmp_path / "a/qnet.pt"), _weights(tmp_path / "b/qnet.pt")
    assert all(torch.equal(a[k], b[k]) for k in a)


@pytest.mark.parametrize(
    ("argv", "words"),
    [
        (["--epochs", "0"], "--epochs = 0 must be >= 1"),
        (["--out", ""], "--out = '': "),
        (["--traffic", "nowhere.parquet"], "--traffic = ["),
        (["--traffic", "/"], "--traffic = ['/'] names /, a folder; give its tape.parquet"),
    ],
)
def test_a_bad_flag_is_one_line_naming_it(tmp_path, capsys, argv, words):
    """(A folder given as a tape was said not to exist; probe 15's f21.)"""
    code, err = _run_cli(["pretrain", "--config", str(_config(tmp_path)), *argv], capsys)
    assert code == 2 and err.count("\n") == 0 and err.startswith(f"twin: error: {words}"), err


def test_a_flag_supplies_what_the_file_lacks(tmp_path):
    """traffic = "tapes" in the file, the tapes from --traffic: one validation of both."""
    from helpers import random_tape

    tape = tmp_path / "a.parquet"
    random_tape(seed=1, nx=6, ny=6, horizon=30).write(tape)
    path = _config(tmp_path)
    path.write_text(path.read_text() + 'traffic = "tapes"\n')
    assert load_config(path, tapes=[str(tape)]).tapes == [str(tape)]


@pytest.mark.parametrize(
    ("text", "words"),
    [
        ('scenario = "shenzhen"\n', 'has [traffic] kind = "sumo"'),
        ('scenario = "drone-loss"\n', "scripts faults"),
        ('scenario = "nowhere.toml"\n', "nowhere.toml, which does not exist"),
    ],
)
def test_a_scenario_pretraining_cannot_collect_on_is_refused(tmp_path, text, words):
    path = _config(tmp_path)
    path.write_text(path.read_text().replace('{ "traffic.horizon" = 60 }', "{}") + text)
    with pytest.raises(UserError, match=re.escape(words)) as info:
        load_config(path)
    assert "\n" not in str(info.value) and str(path) in str(info.value)


# ----------------------------------------------------------------------------- n-step, collector
def test_n_step_transitions_match_a_hand_computed_episode():
    from twin.learning.replay import n_step_transitions

    rewards = np.array([[1, 10], [2, 20], [3, 30], [4, 40]], np.float32)  # (T = 4, N = 2)
    next_states = np.arange(4 * 2 * 13, dtype=np.float32).reshape(4, 2, 13)
    next_feasible = np.zeros((4, 2, 5), bool)
    next_feasible[np.arange(4), :, np.arange(4)] = True  # step t's mask marks action t
    ret, s1, f1, disc = n_step_transitions(rewards, next_states, next_feasible, 0.5, 3)
    # t = 0: 1 + .5 * 2 + .25 * 3; t = 1: 2 + .5 * 3 + .25 * 4; then cut by the episode's end
    assert ret[:, 0].tolist() == [2.75, 4.5, 5.0, 4.0]
    assert ret[:, 1].tolist() == [27.5, 45.0, 50.0, 40.0]
    assert disc.tolist() == [0.125, 0.125, 0.25, 0.5]  # gamma^m, m = 3, 3, 2, 1
    assert np.array_equal(s1, next_states[[2, 3, 3, 3]])
    assert np.array_equal(f1.argmax(axis=2)[:, 0], [2, 3, 3, 3])
    one = n_step_transitions(rewards, next_states, next_feasible, 0.5, 1)
    assert np.array_equal(one[0], rewards) and np.array_equal(one[1], next_states)
    assert one[3].tolist() == [0.5] * 4


def test_n_step_batches_bootstrap_with_their_own_discounts():
    from twin.learning.dqn import train_epoch
    from twin.learning.replay import Batch

    torch.manual_seed(0)
    net, target = QNetwork([13, 8, 5]), QNetwork([13, 8, 5])
    rng = np.random.default_rng(0)
    s, s1 = rng.random((4, 13), np.float32), rng.random((4, 13), np.float32)
    feasible = np.ones((4, 5), bool)
    r = np.array([1.0, 2.0, 3.0, 4.0], np.float32)
    disc = np.array([0.729, 0.729, 0.81, 0.9], np.float32)
    expected = double_dqn_target(
        net, target, torch.from_numpy(r), torch.from_numpy(s1), torch.from_numpy(feasible),
        torch.from_numpy(disc),
    )  # fmt: skip
    with torch.no_grad():
        best = net(torch.from_numpy(s1)).argmax(1)
        hand = r + disc * target(torch.from_numpy(s1)).numpy()[np.arange(4), best.numpy()]
    assert np.allclose(expected.numpy(), hand, atol=1e-6)
    # train_epoch uses the batch's discounts, not gamma: with lr = 0 nothing moves, so the
    # loss it reports is the one towards the hand-computed targets
    opt = torch.optim.Adam(net.parameters(), lr=0.0)
    batch = Batch(s, np.zeros(4, np.int64), r, s1, feasible, disc)
    loss, _ = train_epoch(net, target, opt, batch, gamma=0.0, iters=1)
    with torch.no_grad():
        q = net(torch.from_numpy(s))[:, 0].numpy()
    assert np.isclose(float(loss), np.mean((hand - q) ** 2), rtol=1e-5)


def test_n_step_buffer_holds_the_random_swarms_n_step_returns(tmp_path):
    from twin.learning.replay import n_step_transitions
    from twin.training.pretrain import collect_buffer

    one = load_config(_config(tmp_path))
    three = one.model_copy(update={"n_step": 3})
    a, b = collect_buffer(one), collect_buffer(three)
    assert a.discounts is None and np.array_equal(a.states, b.states)
    for e in range(one.episodes):  # each episode cut at its own end
        rows = slice(e * one.horizon, (e + 1) * one.horizon)
        ret, s1, f1, disc = n_step_transitions(
            a.rewards[rows], a.next_states[rows], a.next_feasible[rows], one.gamma, 3
        )
        assert np.array_equal(b.rewards[rows], ret) and np.array_equal(b.next_states[rows], s1)
        assert np.array_equal(b.next_feasible[rows], f1) and np.array_equal(b.discounts[rows], disc)
    assert np.isclose(b.discounts[0], 0.9**3) and np.isclose(b.discounts[one.horizon - 1], 0.9)


def _coordinated(tmp_path, out, **update):
    cfg = load_config(_config(tmp_path, epochs=40, every=20, out=out))
    update = {"collector": "coordinated", "collect_every": 15, "epsilon_decay_epochs": 30,
              "n_step": 2, **update}  # fmt: skip
    return cfg.model_copy(update=update)


def test_coordinated_collector_is_deterministic_and_collects_the_learned_swarm(tmp_path):
    from twin.training.pretrain import CoordinatedCollector

    cfg = _coordinated(tmp_path, "a")
    collector = CoordinatedCollector(cfg)
    assert [collector.epsilon(e) for e in (0, 15, 30, 40)] == [1.0, 0.525, 0.05, 0.05]
    net = QNetwork(cfg.layers)
    for epoch in (0, 15, 30):  # episodes 0, 1, 2 into a buffer of the last 2 (episodes = 2)
        assert collector.due(epoch)
        collector.collect(epoch, net)
    buf = collector.buffer
    assert buf.steps == buf.capacity == 2 * cfg.horizon and buf.states.shape[1:] == (4, 13)
    assert buf.next_feasible.shape[1:] == (4, 5) and buf.discounts.shape == (buf.capacity,)
    # the coordinator never puts two drones on one cell (the random swarm does)
    cells = np.round(buf.next_states[: buf.steps, :, :2] * [cfg.nx, cfg.ny]).astype(int)
    flat = cells[..., 0] * cfg.ny + cells[..., 1]
    assert all(len(set(row)) == cfg.n_drones for row in flat)
    # same seed, same run: the whole training twice, and once stopped and resumed
    pretrain(cfg, progress=False)
    pretrain(_coordinated(tmp_path, "b"), progress=False)
    split = tmp_path / "split"
    pretrain(_coordinated(tmp_path, "split", epochs=20), progress=False)
    pretrain(_coordinated(tmp_path, "split"), progress=False)
    a = _weights(tmp_path / "a/qnet.pt")
    for other in ("b", "split"):
        b = _weights(tmp_path / other / "qnet.pt")
        assert all(torch.equal(a[k], b[k]) for k in a), other
    assert _logged_epochs(split / "train_log.csv") == list(range(5, 41, 5))
    # another seed, other data
    pretrain(_coordinated(tmp_path, "c", seed=1), progress=False)
    c = _weights(tmp_path / "c/qnet.pt")
    assert not all(torch.equal(a[k], c[k]) for k in a)


def test_recipe_is_recorded_in_provenance(tmp_path):
    import json

    pretrain(_coordinated(tmp_path, "a"), progress=False)
    recipe = json.loads((tmp_path / "a/provenance.json").read_text())["recipe"]
    assert recipe["collector"] == "coordinated" and recipe["n_step"] == 2
    assert recipe["exploration"]["epsilon_decay_epochs"] == 30


def test_coordinated_collector_on_tapes_and_dynamic_maps(tmp_path):
    from helpers import random_tape

    from twin.training.pretrain import CoordinatedCollector

    tape_a, tape_b = tmp_path / "a.parquet", tmp_path / "b.parquet"
    random_tape(seed=1, nx=6, ny=6, horizon=30).write(tape_a)
    random_tape(seed=2, nx=6, ny=6, horizon=25).write(tape_b)
    tapes = _coordinated(tmp_path, "t", traffic="tapes", tapes=[str(tape_a), str(tape_b)])
    collector = CoordinatedCollector(tapes)
    assert collector.buffer.capacity == 2 * 30  # the last 2 episodes, as long as the longest
    net = QNetwork(tapes.layers)
    for epoch in (0, 15):
        collector.collect(epoch, net)
    assert collector.buffer.steps == 30 + 25
    dyn = CoordinatedCollector(_coordinated(tmp_path, "d", traffic="dynamics"))
    assert dyn.source(0) is not dyn.source(1)
    dyn.collect(0, net)
    assert dyn.buffer.steps == 60


def test_a_tape_without_room_for_the_training_drones_is_refused(tmp_path):
    """A tape whose grid has fewer free cells than the training map's drones: one line naming
    the tape and the override that fits (it was an internal error in the first episode)."""
    from helpers import random_tape

    from twin.training.pretrain import episode_source

    tape = tmp_path / "small.parquet"
    random_tape(seed=1, nx=2, ny=2, horizon=10).write(tape)
    path = _config(tmp_path)
    path.write_text(path.read_text() + 'traffic = "tapes"\n')
    cfg = load_config(path, tapes=[str(tape)])
    assert cfg.n_drones > 3  # the tape's grid has one obstacle
    with pytest.raises(UserError, match=r"small\.parquet: its 2 x 2 grid has 3 free cells for "
                       r"the \d+ drones of the training map; give scenario_overrides = "
                       r'\{ "swarm.n_drones" = 3 \}') as info:  # fmt: skip
        episode_source(cfg)
    assert "\n" not in str(info.value)


def test_a_tape_that_stopped_early_is_refused_for_training(tmp_path):
    """A tape whose run stopped before its horizon: an episode runs every step of T, so the
    tape is refused in one line naming it (it ended in an internal StopIteration)."""
    from helpers import cut_tape, random_tape

    from twin.training.pretrain import episode_source

    short = cut_tape(random_tape(seed=1, nx=6, ny=6, horizon=30), 29)
    tape = tmp_path / "short.parquet"
    short.write(tape)
    path = _config(tmp_path)
    path.write_text(path.read_text() + 'traffic = "tapes"\n')
    with pytest.raises(
        UserError, match=r"short\.parquet: holds steps to 29 of its horizon"
    ) as info:
        episode_source(load_config(path, tapes=[str(tape)]))
    assert "\n" not in str(info.value)


@pytest.mark.parametrize("traffic", ["paper", "dynamics"])
def test_tapes_given_to_a_recipe_that_trains_on_none_are_refused(tmp_path, traffic):
    """tapes = [...] beside traffic = "paper" or "dynamics": one line naming both (the tapes
    were silently left unused; probe 17's P2-07)."""
    from helpers import random_tape

    tape = tmp_path / "a.parquet"
    random_tape(seed=1, nx=6, ny=6, horizon=30).write(tape)
    path = _config(tmp_path)
    path.write_text(path.read_text() + f'traffic = "{traffic}"\ntapes = ["{tape}"]\n')
    with pytest.raises(UserError, match=f'are given, but traffic = "{traffic}" trains on no '
                                        'tape; set traffic = "tapes"') as info:  # fmt: skip
        load_config(path)
    assert "\n" not in str(info.value)


def test_a_tape_changed_under_a_run_to_resume_is_named_with_a_fix_that_works(tmp_path):
    """A tape replaced at its path, then the run resumed: the refusal named neither the tape
    nor a fix that works ("delete it", the state.pt, led to a second refusal and lost the
    checkpoint; probe 27e's m02)."""
    from helpers import random_tape

    tape = tmp_path / "t.parquet"
    random_tape(seed=1, nx=6, ny=6, horizon=20).write(tape)
    pretrain(load_config(_config(tmp_path, out="t"), epochs=20, tapes=[str(tape)]), progress=False)
    random_tape(seed=2, nx=6, ny=6, horizon=20).write(tape)  # another day, same name
    with pytest.raises(UserError) as info:
        pretrain(load_config(_config(tmp_path, out="t"), tapes=[str(tape)]), progress=False)
    said = str(info.value)
    assert "\n" not in said and f"its traffic ({tape} or its scenario) changed" in said, said
    assert f"delete {tmp_path / 't'} or set another `out`" in said, said
