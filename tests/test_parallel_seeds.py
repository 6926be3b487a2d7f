"""`twin run --seeds N --workers W`: seeds in worker processes, each SUMO simulation with its
swarms in one; the run folder equals the one of the seeds run one after another."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

pytest.importorskip("libsumo")

from helpers import small_sumo_scenario

from twin.cli import main as twin_main

ROOT = Path(__file__).resolve().parents[1]

#: Files of a run folder that hold wall times (or list the files' sizes): not compared.
WALL_TIME_FILES = {"timing.csv", "run.json", "manifest.json"}


@pytest.fixture(scope="module")
def small(tmp_path_factory) -> Path:
    return small_sumo_scenario(tmp_path_factory.mktemp("small"), horizon=10)


def _run(small: Path, out: Path, *extra: str) -> int:
    """``twin run`` on the small scenario over 3 seeds, in this process: its exit code (a
    refused flag's too: the parser exits as the command would)."""
    try:
        return twin_main(
            ["run", "--config", str(small / "small.toml"), "--seeds", "3", "--out", str(out),
             "--no-report", "--quiet", *extra]
        )  # fmt: skip
    except SystemExit as exc:
        return exc.code


def _files(folder: Path) -> list[str]:
    return sorted(
        p.relative_to(folder).as_posix()
        for p in folder.rglob("*")
        if p.is_file() and p.name not in WALL_TIME_FILES
    )


def test_two_workers_give_the_sequential_run_folder(small, tmp_path, capsys):
    sequential, parallel = tmp_path / "one", tmp_path / "two"
    assert _run(small, sequential) == 0
    assert _run(small, parallel, "--workers", "2") == 0
    capsys.readouterr()
    names = _files(sequential)
    assert names == _files(parallel)
    assert {"per_seed.csv", "summary.csv", "tapes/seed-2.parquet"} <= set(names)
    for name in names:  # every table, tape and map, byte for byte
        assert (sequential / name).read_bytes() == (parallel / name).read_bytes(), name
    per_seed = pd.read_csv(parallel / "per_seed.csv")
    assert list(per_seed["seed"].unique()) == [0, 1, 2]  # seed order
    assert per_seed.groupby("seed")["R_hat_T"].sum().nunique() == 3  # three simulations
    timing = pd.read_csv(parallel / "timing.csv")
    assert list(timing["seed"].unique()) == [0, 1, 2]
    meta = (json.loads((f / "run.json").read_text()) for f in (sequential, parallel))
    one, two = meta
    for key in ("seeds", "traffic_by_seed", "partial", "policies", "horizon"):
        assert one[key] == two[key], key
    for meta in (one, two):  # SUMO's own peak, measured there, with workers too (not a worker's)
        assert 0 < meta["timings"]["peak_memory_sumo_process_mb"] < 4000, meta["timings"]


def test_ray_gives_the_sequential_run_folder(small, tmp_path, capsys):
    pytest.importorskip("ray")
    sequential, on_ray = tmp_path / "one", tmp_path / "ray"
    assert _run(small, sequential) == 0
    assert _run(small, on_ray, "--workers", "2", "--executor", "ray") == 0
    capsys.readouterr()
    assert _files(sequential) == _files(on_ray)
    for name in _files(sequential):
        assert (sequential / name).read_bytes() == (on_ray / name).read_bytes(), name


@pytest.mark.parametrize("value", ["0", "-2", "1.5", "two"])
def test_a_bad_workers_value_is_one_line(small, tmp_path, capsys, value):
    out = tmp_path / "out"
    code = _run(small, out, "--workers", value)
    err = capsys.readouterr().err.strip()
    assert code == 2, err
    assert err.count("\n") == 0 and err.startswith("twin: "), err
    assert "--workers" in err and "Traceback" not in err
    assert not out.exists()


def test_gui_with_workers_is_refused(small, tmp_path, capsys):
    code = _run(small, tmp_path / "out", "--workers", "2", "--gui")
    err = capsys.readouterr().err.strip()
    assert code == 2 and "--workers" in err and err.count("\n") == 0, err


def _twin_process(small: Path, out: Path, *extra: str) -> subprocess.CompletedProcess:
    """``twin run`` on the small scenario over 2 seeds in its own process (the workers' output
    reaches its stderr)."""
    argv = [
        sys.executable,
        "-m",
        "twin",
        "run",
        "--config",
        str(small / "small.toml"),
        "--seeds",
        "2",
        "--out",
        str(out),
        "--no-report",
        "--quiet",
        "--cell-m",
        "400",
        *extra,
    ]  # fmt: skip (coarse cells: a notice of each seed)
    return subprocess.run(argv, capture_output=True, text=True, timeout=600, cwd=small)


def test_workers_say_what_one_after_another_says(small, tmp_path):
    """With --workers, a refusal that comes when a seed's simulation starts is its one line
    (the workers' notices are dropped with it), and a run's notices are those of the same run
    without workers, each once."""
    bad = tmp_path / "bad.add.xml"
    bad.write_text(
        '<additional><inductionLoop id="x" lane="nolane_0" pos="1" period="60" file="x.xml"/>'
        "</additional>"
    )
    for extra in ((), ("--workers", "2")):
        done = _twin_process(small, tmp_path / f"bad{len(extra)}", "--additional", str(bad), *extra)
        err = done.stderr.strip()
        assert done.returncode == 2 and err.count("\n") == 0, (extra, err)
        assert "nolane_0" in err and "Traceback" not in err, err
        assert "notice" not in err, err
    said = {}
    for extra in ((), ("--workers", "2")):
        done = _twin_process(small, tmp_path / f"good{len(extra)}", *extra)
        assert done.returncode == 0, done.stderr
        said[extra] = sorted(done.stderr.strip().splitlines())
    assert said[()] == said[("--workers", "2")]
    assert len(said[()]) == len(set(said[()])), said[()]  # each notice once
    assert any("notice: " in line for line in said[()]), said[()]


def test_a_failed_seed_stops_the_seeds_after_it_as_one_after_another(small, monkeypatch):
    """Seed 1's simulation fails mid-run: kept is seed 0, seed 1 is left out of the tables
    (stopped before its last step) and seed 2 never counts, as sequentially, whatever order
    the workers finish in (here the last seed first)."""
    from twin import executors
    from twin.config import load_config
    from twin.experiment import Experiment, run_experiment
    from twin.sumo.session import SumoRunError, SumoSession

    original = SumoSession.advance_to

    def failing(self, t):
        if self.seed == 4 and t > 600.0:  # SUMO seed 3 + 1: the second simulation
            raise SumoRunError(f"SUMO failed before t = {t:g} s: simulated crash")
        original(self, t)

    def backwards(fn, tasks, workers, **options):  # in this process, last task first
        for n in reversed(range(len(tasks))):
            yield n, fn(*tasks[n]), None

    monkeypatch.setattr(SumoSession, "advance_to", failing)
    monkeypatch.setattr(executors, "local_tasks", backwards)
    config = load_config(small / "small.toml")

    def experiment(workers):
        return Experiment(config, ["random", "greedy"], range(3), workers=workers)

    one, two = run_experiment(experiment(1)), run_experiment(experiment(3))
    assert [r.seed for r in one.results] == [r.seed for r in two.results] == [0]
    assert one.left_out.seed == two.left_out.seed == 1
    assert "simulated crash" in two.left_out.error
    assert two.partial and not two.interrupted
    for a, b in zip(one.results, two.results, strict=True):
        np.testing.assert_array_equal(a.rewards, b.rewards)
        np.testing.assert_array_equal(a.positions, b.positions)


def test_memory_estimate_counts_every_worker(small):
    from twin.config import load_config
    from twin.errors import UserError
    from twin.experiment import WORKER_BYTES, Experiment, check_memory, estimate_memory
    from twin.sumo.scenario import sumo_source

    config = load_config(small / "small.toml")
    source = sumo_source(config)
    shape, horizon = source.grid.shape, source.horizon

    def need(workers, seeds=4):
        experiment = Experiment(config, ["random"], range(seeds), workers=workers)
        return estimate_memory(experiment, shape, horizon, source.warmup_steps(), live=True)

    assert need(2) - need(1) > 2 * WORKER_BYTES
    assert need(4) - need(2) > 2 * WORKER_BYTES
    assert need(8) == need(4)  # no more workers than seeds
    assert need(2, seeds=1) == need(1, seeds=1)  # one seed: no worker
    limit = (need(1) + 1.5 * WORKER_BYTES) / 1e9  # one after another fits, two workers do not
    check_memory(
        Experiment(config, ["random"], range(4), max_memory_gb=limit), shape, horizon, source
    )
    experiment = Experiment(config, ["random"], range(4), workers=2, max_memory_gb=limit)
    if limit * 1e9 < 2 * WORKER_BYTES:  # the workers alone: only fewer of them help
        words = r"--workers 2: 2 worker processes at once need at least 1.6 GB"
        with pytest.raises(UserError, match=words):
            check_memory(experiment, shape, horizon, source)
    limit = (max(2 * WORKER_BYTES, need(1)) + need(2)) / 2e9  # the workers fit, the run not
    experiment = Experiment(config, ["random"], range(4), workers=2, max_memory_gb=limit)
    with pytest.raises(
        UserError, match=r"(4 seeds on 2 workers need|on 2 workers) .* fewer --workers"
    ):
        check_memory(experiment, shape, horizon, source)


def _default_sigint() -> None:
    signal.signal(signal.SIGINT, signal.SIG_DFL)  # background jobs start with SIGINT ignored


def _group_gone(pgid: int, seconds: float = 15.0) -> bool:
    """Whether every process of the process group ``pgid`` has ended within ``seconds``."""
    deadline = time.monotonic() + seconds
    while time.monotonic() < deadline:
        try:
            os.killpg(pgid, 0)
        except ProcessLookupError:
            return True
        time.sleep(0.2)
    return False


@pytest.fixture(scope="module")
def endless(tmp_path_factory) -> Path:
    """The small scenario with a horizon no test waits for."""
    return small_sumo_scenario(tmp_path_factory.mktemp("endless"), horizon=5000)


def _start(endless: Path, out: Path, cwd: Path, *extra: str) -> subprocess.Popen:
    args = ["run", "--config", str(endless / "small.toml"), "--seeds", "3", "--workers", "2",
            "--out", str(out), "--no-report", "--no-ceiling", *extra]  # fmt: skip
    return subprocess.Popen(
        [sys.executable, "-m", "twin", *args],
        cwd=cwd,
        env={**os.environ, "PYTHONPATH": str(ROOT)},
        stdout=subprocess.DEVNULL,
        stderr=open(cwd / "stderr.txt", "w"),
        preexec_fn=_default_sigint,
        start_new_session=True,
    )


def _wait_for_workers(proc: subprocess.Popen, n: int = 2, seconds: float = 120.0) -> None:
    """Until ``proc`` has ``n`` worker processes that each run SUMO in a child of their own."""
    deadline = time.monotonic() + seconds
    while time.monotonic() < deadline:
        assert proc.poll() is None, "ended early"
        group = subprocess.run(
            ["ps", "-o", "pid=,ppid=", "-s", str(proc.pid)], capture_output=True, text=True
        ).stdout.split()
        parents = dict(zip(group[::2], group[1::2], strict=True))
        workers = {p for p, pp in parents.items() if pp == str(proc.pid)}
        if sum(pp in workers for pp in parents.values()) >= n:
            time.sleep(2.0)  # some steps done
            return
        time.sleep(0.2)
    proc.kill()
    pytest.fail("the workers did not start")


def _stop_when(proc: subprocess.Popen, ready, sig: int) -> int:
    """Send ``sig`` to ``proc`` once ``ready(proc)`` returns; its exit code (killed if it
    outlives two minutes)."""
    try:
        ready(proc)
        proc.send_signal(sig)
        return proc.wait(timeout=120)
    finally:
        if proc.poll() is None:
            proc.kill()


def test_ctrl_c_keeps_the_seeds_done_and_ends_every_worker(endless, tmp_path):
    out = tmp_path / "run"
    proc = _start(endless, out, tmp_path)
    code = _stop_when(proc, _wait_for_workers, signal.SIGINT)
    stderr = (tmp_path / "stderr.txt").read_text()
    assert code == 130, stderr
    assert "Traceback" not in stderr
    assert _group_gone(proc.pid), "a worker outlived the run"
    meta = json.loads((out / "run.json").read_text())
    assert meta["partial"] is True
    # both running seeds stopped (the third never started); those that ran the most steps are
    # kept, so that no table compares seeds of unequal lengths (probe 25's f11)
    series = pd.read_parquet(out / "series.parquet")
    kept = set(series["seed"])
    assert kept <= {0, 1} and meta["seeds"] == sorted(kept)
    assert series.groupby("seed")["step"].max().nunique() == 1
    assert 1 <= series["step"].max() + 1 < 5000
    for seed in {0, 1} - kept:
        assert f"seed {seed} after " in stderr and "left out, the tables hold" in stderr, stderr
        assert f"; seed {seed} after " in meta["partial_reason"], meta
    assert (out / "manifest.json").exists() and (out / "tape.parquet").exists()


@pytest.mark.parametrize(
    ("steps", "kept", "left"),
    [({0: 41, 1: 19}, [0], [1]), ({0: 1, 1: 34, 2: 34}, [1, 2], [0]), ({0: 5, 1: 5}, [0, 1], [])],
)
def test_seeds_stopped_at_once_keep_the_longest(steps, kept, left):
    from twin.experiment import longest_seeds

    assert longest_seeds(steps) == (kept, left)


def test_the_reason_names_every_seed_left_out():
    """Seeds run at once and stopped at different steps: the reason names each seed left out
    and how long the kept ones ran (it said "every step" of seeds that stopped too)."""
    from types import SimpleNamespace

    from twin.experiment import ExperimentResult

    def result(seed, steps):
        return SimpleNamespace(seed=seed, completed_steps=steps, error="interrupted by Ctrl-C")

    outcome = ExperimentResult(None, [result(1, 34)], [{}], {}, 1.0)
    outcome.left_out, outcome.left_out_seeds = result(2, 3), {0: 33, 2: 3}
    assert outcome.partial_reason() == (
        "seeds 0 after 33, 2 after 3 stopped before step 34: left out, the tables hold seed 1 "
        "(34 steps)"
    )


def test_sigterm_stops_a_ray_run_as_it_stops_a_local_one(endless, tmp_path):
    """SIGTERM (a batch scheduler's stop) to a run on Ray: Ray's driver had taken SIGTERM, so
    it printed a C++ stack and died, leaving a folder of one marker file (probe 25b). twin's
    own stop runs: a partial run, exit 130."""
    pytest.importorskip("ray")
    out = tmp_path / "run"
    proc = _start(endless, out, tmp_path, "--executor", "ray")
    code = _stop_when(proc, _wait_for_ray_workers, signal.SIGTERM)
    stderr = (tmp_path / "stderr.txt").read_text()
    assert code == 130, stderr
    assert "SIGTERM received" not in stderr and "Traceback" not in stderr, stderr
    meta = json.loads((out / "run.json").read_text())
    assert meta["partial"] is True and meta["seeds"], meta
    assert (out / "manifest.json").exists()


def _wait_for_ray_workers(proc: subprocess.Popen, seconds: float = 120.0) -> None:
    """Until a Ray worker of ``proc`` (in its session: Ray's processes are not its children)
    runs a seed, and some steps are done (a SIGTERM while Ray starts meets Ray's handler)."""
    deadline = time.monotonic() + seconds
    while time.monotonic() < deadline:
        assert proc.poll() is None, "ended early"
        group = subprocess.run(["ps", "-o", "args=", "-s", str(proc.pid)],  # its own session
                               capture_output=True, text=True).stdout  # fmt: skip
        if "ray::run_seed_in_worker" in group:
            time.sleep(8.0)  # SUMO started in the worker, some steps done
            return
        time.sleep(0.3)
    proc.kill()
    pytest.fail("the Ray workers did not start")


def test_workers_die_with_a_killed_parent(endless, tmp_path):
    proc = _start(endless, tmp_path / "run", tmp_path)
    try:
        _wait_for_workers(proc)
        proc.kill()  # kill -9: no cleanup runs in the parent
        proc.wait(timeout=30)
    finally:
        if proc.poll() is None:
            proc.kill()
    assert _group_gone(proc.pid), "a worker outlived its killed parent"


def test_evaluate_with_two_workers_gives_the_sequential_run_folder(tmp_path, capsys):
    """Synthetic traffic takes the same path: each worker builds the shared traffic itself."""
    text = (ROOT / "configs" / "synthetic.toml").read_text()
    assert "horizon = 2000" in text
    config = tmp_path / "short.toml"
    config.write_text(text.replace("horizon = 2000", "horizon = 40"))
    folders = []
    for workers in ("1", "2"):
        out = tmp_path / f"workers-{workers}"
        argv = ["evaluate", "--config", str(config), "--seeds", "3", "--swarms", "random,greedy",
                "--workers", workers, "--out", str(out), "--no-report", "--quiet"]  # fmt: skip
        assert twin_main(argv) == 0, capsys.readouterr().err
        folders.append(out)
    capsys.readouterr()
    one, two = folders
    assert _files(one) == _files(two)
    for name in _files(one):
        assert (one / name).read_bytes() == (two / name).read_bytes(), name


def test_one_progress_bar_over_the_seeds(tmp_path, capsys):
    """With workers, the bar counts seeds (each worker's step bar is off); without progress,
    nothing is drawn."""
    from twin.config import load_config
    from twin.experiment import Experiment, run_experiment

    text = (ROOT / "configs" / "synthetic.toml").read_text()
    config = tmp_path / "short.toml"
    config.write_text(text.replace("horizon = 2000", "horizon = 20"))
    experiment = Experiment(load_config(config), ["random"], range(3), workers=2)
    run_experiment(experiment, progress=True)
    err = capsys.readouterr().err
    assert "seeds" in err and "/3 [" in err and "patrol" not in err, err
    run_experiment(experiment, progress=False)
    assert capsys.readouterr().err == ""


def test_more_live_workers_than_the_memory_holds_are_refused_before_any_starts(
    small, tmp_path, capsys
):
    """Each live worker holds a simulation (the grid is known only inside it): workers past the
    memory limit are one line before any worker process starts."""
    code = _run(small, tmp_path / "out", "--workers", "64", "--max-memory-gb", "2")
    err = capsys.readouterr().err.strip()
    assert code == 2 and err.count("\n") == 0, err
    assert "--workers 64: 3 live simulations at once need at least 2.4 GB" in err, err
    assert not (tmp_path / "out").exists()


def _peak_rss_bytes(argv: list[str], cwd: Path) -> int:
    """Peak resident memory of ``twin argv`` in a fresh process (its own children only)."""
    import subprocess
    import sys

    probe = (
        "import resource, subprocess, sys\n"
        "subprocess.run([sys.executable, '-m', 'twin', *sys.argv[1:]], check=True,\n"
        "               stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)\n"
        "print(resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss)\n"
    )
    env = {**os.environ, "PYTHONPATH": str(Path(__file__).resolve().parents[1])}
    done = subprocess.run([sys.executable, "-c", probe, *argv], cwd=cwd, env=env,
                          capture_output=True, text=True, check=True, timeout=600)  # fmt: skip
    return int(done.stdout.split()[-1]) * 1024  # KB on Linux


def test_the_memory_estimate_covers_what_many_seeds_take(tmp_path):
    """The growth of a run's peak memory from 1 to many seeds stays within the estimate (it
    was 1.6x over it: each seed's series rows and result objects were not counted, and a run
    estimated under the limit could take more than the machine has; probe 13's f07)."""
    from twin.config import load_config
    from twin.experiment import Experiment, estimate_memory

    text = (ROOT / "configs" / "synthetic.toml").read_text()
    config = tmp_path / "s.toml"
    config.write_text(text.replace("nx = 20", "nx = 10").replace("ny = 30", "ny = 12")
                      .replace("horizon = 2000", "horizon = 60")
                      .replace("i = 14, j = 21", "i = 8, j = 10")
                      .replace("i = 3, j = 24", "i = 3, j = 10")
                      .replace("i = 16, j = 5", "i = 8, j = 5"))  # fmt: skip
    seeds = 1500

    def argv(n: int) -> list[str]:
        return ["evaluate", "--config", str(config), "--seeds", str(n), "--swarms", "random",
                "--no-ceiling", "--no-report", "--quiet", "--out", str(tmp_path / f"r{n}")]  # fmt: skip

    growth = _peak_rss_bytes(argv(seeds), tmp_path) - _peak_rss_bytes(argv(1), tmp_path)
    need = estimate_memory(Experiment(load_config(config), ["random"], range(seeds)), (10, 12), 60)
    assert growth <= need, (growth / 1e6, need / 1e6)


def test_a_limit_below_any_run_says_to_raise_it(tmp_path, capsys):
    """A memory limit below what the run takes on a 1 x 1 grid: the fix is to raise it, not
    a grid "2113...0 times coarser per side" (probe 15's f08)."""
    argv = ["evaluate", "--config", "synthetic", "--seeds", "1", "--swarms", "random",
            "--out", str(tmp_path / "o"), "--max-memory-gb"]  # fmt: skip
    for limit in ("1e-300", "1e-6"):
        assert twin_main([*argv, limit]) == 2
        err = capsys.readouterr().err
        assert err.count("\n") == 1 and "is below what this run takes on any grid" in err, err
        assert "coarser" not in err


def test_a_live_runs_estimate_counts_its_warm_up_snapshots_and_their_tape():
    """Each warm-up snapshot is held once (SUMO's process sends it on) and stacked once more
    into the tape as it is written: 16 B per cell for one seed. The estimate counted 8, and a
    run of 1 s steps peaked at 1.37 GB under a 0.6 GB limit (probe 28's n01)."""
    from twin.config import load_config
    from twin.experiment import Experiment, estimate_memory

    experiment = Experiment(load_config(ROOT / "configs" / "shenzhen.toml"), ["random"], [0])
    shape, cells = (251, 251), 251 * 251

    def need(warmup: int) -> float:
        return estimate_memory(experiment, shape, 1, warmup, live=True)

    assert need(898) - need(0) >= 16 * cells * 898


@pytest.mark.parametrize("live", [False, True])
def test_a_limit_below_the_interpreter_and_simulator_is_refused(small, tmp_path, capsys, live):
    """A limit of 1 MB let a one-process run through (its run.json: 0.21 GB for twin, 0.20
    for SUMO) while two workers were refused at 0.8 GB: the interpreter and the simulator were
    counted for workers only (probe 29's p02)."""
    from twin.experiment import PROCESS_BYTES, SIMULATOR_BYTES

    config = ["--config", str(small / "small.toml")] if live else ["--config", "synthetic"]
    argv = ["evaluate", *config, "--seeds", "1", "--swarms", "random", "--no-ceiling",
            "--no-report", "--quiet", "--out", str(tmp_path / "o"),
            "--max-memory-gb", "0.3"]  # fmt: skip
    if live:
        argv[0] = "run"
    assert twin_main(argv) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "is below what this run takes on any grid" in err, err
    floor = (PROCESS_BYTES + (SIMULATOR_BYTES if live else 0)) / 1e9
    assert f"(about {floor:.1f} GB" in err or f"(about {floor + 0.1:.1f} GB" in err, err


def test_a_refusal_past_the_limit_names_the_warm_up_when_its_snapshots_dominate(tmp_path):
    """A run of 1 step after 7,200 warm-up snapshots was told to use fewer steps, which could
    not help: the warm-up held nearly all of it (probe 30's r02)."""
    from helpers import small_sumo_scenario

    from twin.config import load_config
    from twin.sumo.scenario import sumo_source

    for horizon, words in ((2, "a shorter warm-up ([traffic].warmup_min: its 5 snapshots"),
                           (10, "fewer steps (--horizon)")):  # fmt: skip
        folder = tmp_path / f"h{horizon}"
        folder.mkdir()
        source = sumo_source(load_config(small_sumo_scenario(folder, horizon) / "small.toml"))
        assert source.warmup_steps() == 5
        assert words in source.coarser_hint(2.0), source.coarser_hint(2.0)
