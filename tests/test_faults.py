"""Faults: `kill -9` at several points of `twin run`, `twin sweep` (and its pool workers),
a diverging pretraining, and bad numbers on the command line."""

from __future__ import annotations

import contextlib
import os
import signal
import subprocess
import sys
import time
import warnings
from pathlib import Path

import pytest
from helpers import small_sumo_scenario

ROOT = Path(__file__).resolve().parents[1]
ENV = {**os.environ, "PYTHONPATH": str(ROOT)}


def twin(args: list[str], cwd: Path, **kwargs) -> subprocess.Popen:
    """``python -m twin ARGS`` in a session of its own (so a leftover can be killed as a group)."""
    return subprocess.Popen(
        [sys.executable, "-m", "twin", *args],
        cwd=cwd,
        env=ENV,
        stdout=subprocess.DEVNULL,
        stderr=subprocess.PIPE,
        start_new_session=True,
        **kwargs,
    )


def alive(pid: int) -> bool:
    """True while ``pid`` runs (a zombie waiting for its reaper counts as dead)."""
    try:
        stat = Path(f"/proc/{pid}/stat").read_text()
    except (FileNotFoundError, ProcessLookupError):
        return False
    return stat.rsplit(")", 1)[1].split()[0] not in ("Z", "X")


def children(pid: int) -> list[int]:
    kids = []
    for stat in Path("/proc").glob("[0-9]*/stat"):
        try:
            fields = stat.read_text().rsplit(")", 1)[1].split()
        except (FileNotFoundError, ProcessLookupError):
            continue
        if int(fields[1]) == pid:
            kids.append(int(stat.parent.name))
    return kids


def kill_group(proc: subprocess.Popen) -> None:
    with contextlib.suppress(ProcessLookupError):
        os.killpg(proc.pid, signal.SIGKILL)
    proc.wait()


# ----------------------------------------------------------------------------- sweep workers
def sweep_file(tmp: Path, seeds: int, horizon: int) -> Path:
    text = (ROOT / "configs" / "synthetic.toml").read_text()
    (tmp / "scenario.toml").write_text(text.replace("horizon = 2000", f"horizon = {horizon}"))
    path = tmp / "sweep.toml"
    path.write_text(
        f"""
[sweep]
name = "t"
swarms = ["random", "greedy", "sweeping"]
seeds = {seeds}

[[scenario]]
name = "syn"
config = "scenario.toml"
"""
    )
    return path


@pytest.mark.skipif(not Path("/proc/self/stat").exists(), reason="needs /proc")
def test_sweep_workers_exit_when_the_sweep_is_killed(tmp_path: Path) -> None:
    path = sweep_file(tmp_path, seeds=4, horizon=100_000)  # cells of minutes each
    proc = twin(
        ["sweep", "--config", str(path), "--out", str(tmp_path / "s"), "--workers", "2",
         "--quiet", "--no-report"],
        tmp_path,
    )  # fmt: skip
    try:
        deadline = time.monotonic() + 60
        workers: list[int] = []
        while len(workers) < 2 and time.monotonic() < deadline and proc.poll() is None:
            time.sleep(0.2)
            workers = [
                p
                for p in children(proc.pid)
                if b"spawn_main" in Path(f"/proc/{p}/cmdline").read_bytes()
            ]
        assert len(workers) == 2, proc.stderr.read().decode()[-2000:]
        time.sleep(3)  # the workers are computing their cells
        assert all(alive(p) for p in workers)
        os.kill(proc.pid, signal.SIGKILL)  # the sweep alone, not its process group
        proc.wait()
        deadline = time.monotonic() + 5
        while any(alive(p) for p in workers) and time.monotonic() < deadline:
            time.sleep(0.1)
        assert not [p for p in workers if alive(p)], "pool workers outlived the sweep"
    finally:
        kill_group(proc)


# ----------------------------------------------------------------------------- pretraining
TINY_PRETRAIN = """
layers = [13, 16, 5]
episodes = 2
epochs = {epochs}
iters_per_epoch = 2
batch_size = 16
log_every = 5
checkpoint_every = 5
scenario_overrides = {{ "grid.nx" = 6, "grid.ny" = 6, "traffic.horizon" = 50, \
"traffic.disturbances" = [{{kind = "big", i = 2, j = 2, amplitude = 1.0, sigma = 2.0}}]{extra} }}
"""


def test_diverging_pretraining_stops_with_one_line_and_writes_no_model(
    tmp_path: Path, monkeypatch, capsys
) -> None:
    # the weights blow up in the first epoch (a reward scale that squared to inf did this
    # once; reward weights are now bounded, so the blow-up is forced)
    torch = pytest.importorskip("torch")
    from twin.cli import main
    from twin.training import pretrain as pt

    real = pt.train_epoch

    def exploding(net, *args):
        loss, q = real(net, *args)
        with torch.no_grad():
            next(net.parameters()).mul_(torch.inf)
        return loss, q

    monkeypatch.setattr(pt, "train_epoch", exploding)
    path = tmp_path / "diverge.toml"
    path.write_text(TINY_PRETRAIN.format(epochs=40, extra=""))
    out = tmp_path / "out"
    assert main(["pretrain", "--config", str(path), "--out", str(out), "--quiet"]) == 2
    err = capsys.readouterr().err
    lines = err.strip().splitlines()
    assert len(lines) == 1 and "diverged" in lines[0] and "Traceback" not in err, err
    assert not (out / "qnet.pt").exists() and not (out / "state.pt").exists()


def test_divergence_keeps_the_last_good_checkpoint(tmp_path: Path, monkeypatch) -> None:
    torch = pytest.importorskip("torch")
    from twin.errors import UserError
    from twin.learning.checkpoint import read_checkpoint
    from twin.training import pretrain as pt

    path = tmp_path / "tiny.toml"
    path.write_text(TINY_PRETRAIN.format(epochs=10, extra=""))
    out = tmp_path / "out"
    pt.pretrain(pt.load_config(path, out=str(out)), progress=False)
    before = {name: (out / name).read_bytes() for name in ("state.pt", "qnet.pt")}

    # resumed to 30 epochs, the weights blow up at epoch 13 (between two checkpoints)
    calls = {"n": 0}
    real = pt.train_epoch

    def exploding(net, *args):
        calls["n"] += 1
        loss, q = real(net, *args)
        if calls["n"] >= 3:
            with torch.no_grad():
                next(net.parameters()).mul_(torch.inf)
        return loss, q

    monkeypatch.setattr(pt, "train_epoch", exploding)
    cfg = pt.load_config(path, out=str(out), epochs=30)
    with pytest.raises(UserError, match=r"diverged by epoch 15 .*state.pt \(epoch 10\) is kept"):
        pt.pretrain(cfg, progress=False)
    assert {name: (out / name).read_bytes() for name in before} == before
    assert all(
        torch.isfinite(w).all() for w in read_checkpoint(out / "qnet.pt")["weights"].values()
    )


def test_a_checkpoint_with_nan_weights_is_refused_on_load(tmp_path: Path) -> None:
    torch = pytest.importorskip("torch")
    from twin.errors import UserError
    from twin.learning.checkpoint import load_qnet, model_metadata, save_model
    from twin.learning.qnet import QNetwork

    net = QNetwork([13, 16, 5])
    weights = net.state_dict()
    weights["net.0.weight" if "net.0.weight" in weights else next(iter(weights))][0, 0] = torch.nan
    path = tmp_path / "nan.pt"
    save_model(path, weights, model_metadata([13, 16, 5], {}, 0, 1))
    with pytest.raises(UserError, match=r"nan\.pt.*non-finite") as info:
        load_qnet(path)
    assert "\n" not in str(info.value)


def _scaled(weights, factor):
    return {k: v * factor for k, v in weights.items()}


def _as_int32(weights):
    """Weights cast to integers (truncated: mostly 0), a kind of tensor twin never writes."""
    import torch

    return {k: v.to(torch.int32) for k, v in weights.items()}


def _last_bias_plus(weights, shift):
    """The output layer's bias shifted: finite Q-values whose differences float32 loses."""
    last = [k for k in weights if k.endswith("bias")][-1]
    return {**weights, last: weights[last] + shift}


@pytest.mark.parametrize(
    ("change", "words"),
    [
        (lambda w, m: (_scaled(w, 1e38), m), r"huge\.pt: its Q-values overflow to inf or NaN"),
        (lambda w, m: (_last_bias_plus(w, 1e30), m), r"huge\.pt: its Q-values are equal for"),
        (lambda w, m: (_scaled(w, 0.0), m), r"huge\.pt: its Q-values are equal for every"),
        (
            lambda w, m: (_as_int32(w), m),
            r"huge\.pt: weights 'net\.0\.weight' are int32, not the dense floating-point",
        ),
        (
            lambda w, m: ({k: v.to_sparse() if v.dim() == 2 else v for k, v in w.items()}, m),
            r"huge\.pt: weights 'net\.0\.weight' are sparse_coo, not the dense",
        ),
        (lambda w, m: (w, {**m, "epoch": -1}), r"huge\.pt: meta\.epoch = -1 is not a whole"),
        (lambda w, m: (w, {**m, "seed": -5}), r"huge\.pt: meta\.seed = -5 is not a whole"),
        (lambda w, m: (w, {**m, "seed": True}), r"huge\.pt: meta\.seed = True is not a whole"),
    ],
)
def test_a_checkpoint_whose_q_values_overflow_or_meta_is_absurd_is_refused(
    tmp_path: Path, change, words
) -> None:
    """Finite weights scaled by 1e38 give inf or NaN Q-values (the argmax then picks no action);
    an output bias of 1e30 or all-zero weights give one Q-value for every action (the argmax
    always picks the first); a negative epoch or seed is no training's."""
    pytest.importorskip("torch")
    from twin.errors import UserError
    from twin.learning.checkpoint import load_qnet, model_metadata, save_model
    from twin.learning.qnet import QNetwork

    weights = QNetwork([13, 16, 5]).state_dict()
    path = tmp_path / "huge.pt"
    save_model(path, *change(weights, model_metadata([13, 16, 5], {}, 0, 1)))
    with warnings.catch_warnings(), pytest.raises(UserError, match=words) as info:
        warnings.simplefilter("error")  # the refusal alone: no warning of torch's before it
        load_qnet(path)
    assert "\n" not in str(info.value)
    save_model(path, weights, model_metadata([13, 16, 5], {}, 0, 1))
    load_qnet(path)  # the same network as trained loads


# ----------------------------------------------------------------------------- bad numbers
BIG = str(2**63)


@pytest.mark.parametrize(
    ("argv", "flag"),
    [
        (["evaluate", "--seed", "-1"], "--seed = -1"),
        (["evaluate", "--seed", BIG], f"--seed = {BIG}"),
        (
            ["evaluate", "--seed", "2147483646", "--seeds", "3"],
            "--seeds = 3 runs seeds 2147483646 .. 2147483648, past the largest seed 2147483647; "
            "give at most 2, or --seed at most 2147483645",
        ),
        (["evaluate", "--seeds", "3000000000"], "--seeds = 3000000000 runs seeds 0 .. 2999999999"),
        (["run", "--net", "n.net.xml", "--seeds", "10" + "0" * 14], "--seeds = 1000000000000000"),
        (["run", "--sumo-seed", "2147483647", "--seeds", "2"], "--seeds = 2 runs seeds"),
        (["evaluate", "--seeds", "0"], "--seeds = 0"),
        (["evaluate", "--seeds", "-3"], "--seeds = -3"),
        (["run", "--seed", "-1"], "--seed = -1"),
        (["run", "--seed", BIG], f"--seed = {BIG}"),
        (["run", "--sumo-seed", "-5"], "--sumo-seed = -5"),
        (["run", "--sumo-seed", "2147483648"], "--sumo-seed = 2147483648"),
        (["run", "--seeds", "0"], "--seeds = 0"),
        (["run", "--horizon", "0"], "--horizon = 0"),
        (["run", "--horizon", "-10"], "--horizon = -10"),
        (["sweep", "--config", "configs/sweep-demo.toml", "--workers", "0"], "--workers = 0"),
        (["sweep", "--config", "configs/sweep-demo.toml", "--workers", "-2"], "--workers = -2"),
        (["pretrain", "--epochs", "0"], "--epochs = 0"),
        (["pretrain", "--epochs", "-1"], "--epochs = -1"),
    ],
)
def test_bad_numbers_on_the_command_line_are_one_line_errors(
    argv: list[str], flag: str, tmp_path: Path, capsys
) -> None:
    from twin.cli import main

    before = sorted(tmp_path.rglob("*"))
    code = main([*argv, "--out", str(tmp_path / "out")])
    err = capsys.readouterr().err.strip()
    assert code == 2
    assert len(err.splitlines()) == 1 and flag in err, err
    assert sorted(tmp_path.rglob("*")) == before  # nothing written


# ----------------------------------------------------------------------------- kill -9
RUN_FILES = ("series.parquet", "trajectories.parquet", "per_seed.csv", "summary.csv",
             "importance.npz", "network.json", "mfd.json", "mfd_samples.parquet",
             "tape.parquet")  # fmt: skip


@pytest.fixture(scope="module")
def small(tmp_path_factory) -> Path:
    """The small grid scenario of tests/helpers.py (horizon 20)."""
    pytest.importorskip("libsumo")
    return small_sumo_scenario(tmp_path_factory.mktemp("small"), horizon=20)


def claims_complete(run_dir: Path) -> bool:
    if not (run_dir / "run.json").exists() or not (run_dir / "summary.csv").exists():
        return False
    import json

    return json.loads((run_dir / "run.json").read_text()).get("partial") is False


def _kill_run_when(small: Path, out: Path, when) -> None:
    err = out.parent / f"{out.name}.stderr"
    with open(err, "w") as fh:
        proc = subprocess.Popen(
            [sys.executable, "-m", "twin", "run", "--config", str(small / "small.toml"),
             "--out", str(out), "--no-report", "--quiet"],
            cwd=out.parent, env=ENV, stdout=subprocess.DEVNULL, stderr=fh,
            start_new_session=True,
        )  # fmt: skip
    try:
        deadline = time.monotonic() + 120
        while not when(err.read_text(), out) and proc.poll() is None:
            assert time.monotonic() < deadline, "timed out"
            time.sleep(0.005)
    finally:
        kill_group(proc)


@pytest.mark.parametrize(
    "phase",
    [
        "warm-up",  # the simulation is built: the announcement is printed before the warm-up
        "mid-run",
        "writing",  # the first file of the run folder appears
    ],
)
def test_kill_9_of_twin_run_leaves_no_folder_claiming_completeness(small, tmp_path, phase):
    out = tmp_path / "run"
    t = {"announced": None}

    def when(stderr: str, out: Path) -> bool:
        if "SUMO:" in stderr and t["announced"] is None:
            t["announced"] = time.monotonic()
        if phase == "warm-up":
            return t["announced"] is not None
        if phase == "mid-run":
            return t["announced"] is not None and time.monotonic() > t["announced"] + 1.0
        return out.exists() and any(out.iterdir())

    _kill_run_when(small, out, when)
    if claims_complete(out):  # finished before the kill, or a folder claiming too much
        missing = [name for name in RUN_FILES if not (out / name).exists()]
        assert not missing, f"run.json says complete but {missing} are missing"
    rerun = subprocess.run(
        [sys.executable, "-m", "twin", "run", "--config", str(small / "small.toml"),
         "--out", str(tmp_path / "again"), "--no-report", "--quiet"],
        cwd=tmp_path, env=ENV, capture_output=True, text=True, timeout=300,
    )  # fmt: skip
    assert rerun.returncode == 0, rerun.stderr
    assert claims_complete(tmp_path / "again")
    assert all((tmp_path / "again" / name).exists() for name in RUN_FILES)


def _results(sweep_dir: Path):
    import pandas as pd

    frame = pd.read_csv(sweep_dir / "results.csv")
    frame = frame.drop(columns=[c for c in ("seconds", "worker") if c in frame])
    return frame.sort_values(["cell", "swarm"]).reset_index(drop=True)


@pytest.mark.parametrize("kill_after_cells", [1])
def test_kill_9_of_twin_sweep_mid_cell_resumes_to_the_same_results(tmp_path, kill_after_cells):
    from twin.sweep import done_cells

    path = sweep_file(tmp_path, seeds=3, horizon=2000)
    out = tmp_path / "s"
    cmd = ["sweep", "--config", str(path), "--workers", "1", "--quiet", "--no-report"]
    proc = twin([*cmd, "--out", str(out)], tmp_path)
    try:
        deadline = time.monotonic() + 120
        while len(done_cells(out)) < kill_after_cells and proc.poll() is None:
            assert time.monotonic() < deadline, "timed out"
            time.sleep(0.05)
        time.sleep(0.5)  # into the next cell
        os.kill(proc.pid, signal.SIGKILL)  # the sweep alone: its worker must follow
        proc.wait()
    finally:
        kill_group(proc)
    assert len(done_cells(out)) < 3, "kill the sweep while cells remain"
    resumed = subprocess.run(
        [sys.executable, "-m", "twin", *cmd, "--out", str(out)],
        cwd=tmp_path, env=ENV, capture_output=True, text=True, timeout=300,
    )  # fmt: skip
    assert resumed.returncode == 0, resumed.stderr
    whole = subprocess.run(
        [sys.executable, "-m", "twin", *cmd, "--out", str(tmp_path / "whole")],
        cwd=tmp_path, env=ENV, capture_output=True, text=True, timeout=300,
    )  # fmt: skip
    assert whole.returncode == 0, whole.stderr
    a, b = _results(out), _results(tmp_path / "whole")
    assert len(a) == 3 * 3
    pd_testing = pytest.importorskip("pandas.testing")
    pd_testing.assert_frame_equal(a.drop(columns=["code"], errors="ignore"),
                                  b.drop(columns=["code"], errors="ignore"))  # fmt: skip
