"""Ctrl-C on `twin evaluate` and `twin run`: the steps done so far are written as a partial run
(exit 130); a second Ctrl-C stops at once. The commands run for real in a subprocess."""

from __future__ import annotations

import json
import os
import re
import signal
import subprocess
import sys
import time
from pathlib import Path

import pandas as pd
import pytest
from helpers import small_sumo_scenario

from twin.experiment import stop_on_interrupt

ROOT = Path(__file__).resolve().parents[1]


def scenario_file(tmp: Path, horizon: int) -> Path:
    """configs/synthetic.toml with another horizon."""
    text = (ROOT / "configs" / "synthetic.toml").read_text()
    assert "horizon = 2000" in text
    path = tmp / "scenario.toml"
    path.write_text(text.replace("horizon = 2000", f"horizon = {horizon}"))
    return path


def _default_sigint() -> None:
    signal.signal(signal.SIGINT, signal.SIG_DFL)  # background jobs start with SIGINT ignored


class Command:
    """``python -m twin ARGS`` in a subprocess of its own session, output into files."""

    def __init__(self, args: list[str], cwd: Path) -> None:
        self.out, self.err = cwd / "stdout.txt", cwd / "stderr.txt"
        env = {**os.environ, "PYTHONPATH": str(ROOT)}
        with open(self.out, "w") as out, open(self.err, "w") as err:
            self.proc = subprocess.Popen(
                [sys.executable, "-m", "twin", *args],
                cwd=cwd,
                env=env,
                stdout=out,
                stderr=err,
                preexec_fn=_default_sigint,
                start_new_session=True,
            )

    def stderr(self) -> str:
        return self.err.read_text()

    def wait_for(self, predicate, seconds: float = 120.0) -> None:
        deadline = time.monotonic() + seconds
        while not predicate():
            if self.proc.poll() is not None:
                pytest.fail(f"ended early ({self.proc.returncode}): {self.stderr()[-2000:]}")
            if time.monotonic() > deadline:
                self.proc.kill()
                pytest.fail("timed out")
            time.sleep(0.05)

    def interrupt(self, times: int = 1, gap: float = 0.0, signum=signal.SIGINT) -> int:
        for n in range(times):
            if n:
                time.sleep(gap)
            self.proc.send_signal(signum)
        try:
            return self.proc.wait(timeout=120)
        finally:
            if self.proc.poll() is None:
                self.proc.kill()


@pytest.fixture(autouse=True)
def _python_sigint():
    """Python's own Ctrl-C handler, as a command starts with (a pytest-xdist worker ignores
    SIGINT, so that only its controller stops on Ctrl-C)."""
    import threading

    if threading.current_thread() is not threading.main_thread():
        yield
        return
    before = signal.getsignal(signal.SIGINT)
    signal.signal(signal.SIGINT, signal.default_int_handler)
    try:
        yield
    finally:
        signal.signal(signal.SIGINT, before)


def test_stop_flag_is_set_by_sigint_and_the_handler_restored() -> None:
    before = signal.getsignal(signal.SIGINT)
    with stop_on_interrupt() as stop:
        if signal.getsignal(signal.SIGINT) is before:
            pytest.skip("SIGINT is not Python's default handler here")
        assert not stop()
        os.kill(os.getpid(), signal.SIGINT)
        time.sleep(0.05)
        assert stop()
        with pytest.raises(KeyboardInterrupt):  # a second Ctrl-C stops at once
            os.kill(os.getpid(), signal.SIGINT)
            time.sleep(0.5)
    assert signal.getsignal(signal.SIGINT) is before


def test_stop_flag_is_off_when_not_asked_for() -> None:
    before = signal.getsignal(signal.SIGINT)
    with stop_on_interrupt(enabled=False) as stop:
        assert signal.getsignal(signal.SIGINT) is before
        assert not stop()


# SIGTERM (`kill`, a batch scheduler's stop, `timeout`) stops a command as Ctrl-C does; it
# used to end the process at once, leaving a run folder with run.json alone
STOPS = pytest.mark.parametrize("signum", [signal.SIGINT, signal.SIGTERM], ids=["int", "term"])


@STOPS
def test_ctrl_c_on_evaluate_writes_a_partial_run(tmp_path: Path, signum) -> None:
    config = scenario_file(tmp_path, horizon=200_000)
    out = tmp_path / "run"
    cmd = Command(
        ["evaluate", "--config", str(config), "--seeds", "3", "--swarms", "random,greedy",
         "--out", str(out), "--no-report", "--quiet"],
        tmp_path,
    )  # fmt: skip
    cmd.wait_for((out / "run.json").exists)  # past the imports: the run is starting
    time.sleep(2)  # the synthetic maps, then some steps
    assert cmd.interrupt(signum=signum) == 130, cmd.stderr()
    stderr = cmd.stderr()
    assert "Traceback" not in stderr
    assert "partial run written" in stderr
    meta = json.loads((out / "run.json").read_text())
    assert meta["partial"] is True
    assert any("interrupted" in e for e in meta["errors"])
    per_seed = pd.read_csv(out / "per_seed.csv")
    assert set(per_seed["swarm"]) == {"random", "greedy"}
    series = pd.read_parquet(out / "series.parquet")
    steps = series.groupby(["seed", "swarm"])["step"].max() + 1
    assert 1 <= steps.max() < 200_000
    assert meta["seeds"] == [0]  # stopped within the first seed: no other seed was run


@STOPS
def test_second_ctrl_c_stops_at_once(tmp_path: Path, signum) -> None:
    config = scenario_file(tmp_path, horizon=200_000)
    out = tmp_path / "run"
    cmd = Command(
        ["evaluate", "--config", str(config), "--seeds", "1", "--swarms", "random",
         "--out", str(out), "--no-report", "--quiet"],
        tmp_path,
    )  # fmt: skip
    cmd.wait_for((out / "run.json").exists)  # past the imports: the run is starting
    time.sleep(2)
    assert cmd.interrupt(times=2, gap=0.3, signum=signum) == 130
    assert "Traceback" not in cmd.stderr()
    # whatever was written is whole: no temporary file is left behind
    assert not [p for p in out.rglob("*") if p.name.endswith(".tmp")]


#: About 80 s of an idle machine's steps: far past the Ctrl-C, and a disk estimate of ~2 GB
#: (a million steps asked ~10 GB free of the machine, and failed on a fuller disk).
HORIZON = 200_000


@pytest.fixture(scope="module")
def small(tmp_path_factory) -> Path:
    """The small grid scenario of tests/helpers.py, with a horizon no run reaches before its
    Ctrl-C (5000 steps took 2 s on an idle machine: the run had finished)."""
    pytest.importorskip("libsumo")
    return small_sumo_scenario(tmp_path_factory.mktemp("small"), horizon=HORIZON)


@STOPS
def test_ctrl_c_on_run_writes_a_partial_run_with_its_tape(
    small: Path, tmp_path: Path, signum
) -> None:
    from twin.traffic.tape import Tape

    out = tmp_path / "run"
    cmd = Command(
        ["run", "--config", str(small / "small.toml"), "--out", str(out), "--no-report"],
        tmp_path,
    )  # fmt: skip
    cmd.wait_for(lambda: "SUMO:" in cmd.stderr())  # the simulation is built and warming up
    time.sleep(2.0)
    assert cmd.interrupt(signum=signum) == 130, cmd.stderr()
    stderr = cmd.stderr()
    assert "Traceback" not in stderr
    done = int(re.search(r"partial run of (\d+) steps", stderr).group(1))
    assert 1 <= done < HORIZON
    meta = json.loads((out / "run.json").read_text())
    assert meta["partial"] is True
    series = pd.read_parquet(out / "series.parquet")
    assert series["step"].max() + 1 == done
    tape = Tape.read(out / "tape.parquet")
    assert tape.steps.max() == done  # T^0 .. T^done
    assert (out / "per_seed.csv").exists()
    from twin.report import write_report

    html = write_report(out, animation=False)
    assert "PARTIAL" in (html.parent / "report.md").read_text().splitlines()[0]
    assert "PARTIAL" in re.search(r"<h1>(.*?)</h1>", html.read_text()).group(1)


def test_the_same_command_completes_a_run_stopped_by_ctrl_c(tmp_path: Path) -> None:
    config = scenario_file(tmp_path, horizon=20_000)
    out = tmp_path / "run"
    args = ["evaluate", "--config", str(config), "--seeds", "1", "--swarms", "random",
            "--out", str(out), "--no-report", "--no-ceiling", "--quiet"]  # fmt: skip
    cmd = Command(args, tmp_path)
    cmd.wait_for((out / "run.json").exists)
    time.sleep(0.5)
    assert cmd.interrupt() == 130, cmd.stderr()
    assert json.loads((out / "run.json").read_text())["partial"] is True
    again = subprocess.run(
        [sys.executable, "-m", "twin", *args],
        cwd=tmp_path,
        env={**os.environ, "PYTHONPATH": str(ROOT)},
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert again.returncode == 0, again.stderr
    meta = json.loads((out / "run.json").read_text())
    assert meta["partial"] is False
    series = pd.read_parquet(out / "series.parquet")
    assert series["step"].max() + 1 == 20_000


def test_a_source_stopped_while_sumo_works_ahead_keeps_the_mfd_of_its_used_maps(small: Path):
    """SUMO's process works ahead of slow swarms; the run stops (Ctrl-C) after the maps it
    used. The MFD's samples and fit are those of the kept snapshots, as a replay of the tape
    gives them (they held the steps SUMO computed ahead, so the folder's own read-back
    refused it: probe 12's i01)."""
    from twin.config import load_config
    from twin.traffic_kinds import build_traffic

    config = load_config(small / "small.toml")
    source = build_traffic(config, separate_process=True)
    maps = source.importance_maps()
    for _ in range(3):
        next(maps)
        time.sleep(1.0)  # the child computes the maps after these meanwhile
    maps.close()
    kept = source.snapshots[-1][0]
    assert kept == 2
    samples = source.model.samples()
    assert samples["step"].max() <= kept
    replayed = source.model_after(source.snapshots)
    assert len(replayed.samples()["step"]) == len(samples["step"])
    assert json.dumps(replayed.report(), sort_keys=True) == json.dumps(
        source.model.report(), sort_keys=True
    )


def test_ctrl_c_while_a_finished_run_is_written_finishes_the_folder(tmp_path, monkeypatch, capsys):
    """A Ctrl-C after the last step, while the run folder is written: the folder is finished
    (every file, its manifest), then the command stops with exit 130; it lost every result
    before, leaving run.json alone (probe 12's i02)."""
    import twin.cli.recording as recording
    from twin.cli import main
    from twin.runs import check_run_folder

    if signal.getsignal(signal.SIGINT) is not signal.default_int_handler:
        pytest.skip("SIGINT is not Python's default handler here")
    real = recording.record

    def interrupted_record(*args, **kwargs):
        os.kill(os.getpid(), signal.SIGINT)
        time.sleep(0.2)  # the handler runs: the old one raised KeyboardInterrupt here
        return real(*args, **kwargs)

    monkeypatch.setattr(recording, "record", interrupted_record)
    out = tmp_path / "run"
    argv = ["evaluate", "--config", str(scenario_file(tmp_path, horizon=20)), "--seeds", "1",
            "--swarms", "random", "--out", str(out), "--no-report", "--quiet"]  # fmt: skip
    assert main(argv) == 130
    assert "finishing the run folder first" in capsys.readouterr().err
    manifest = check_run_folder(out)
    assert not manifest["partial"] and "per_seed.csv" in manifest["files"]


def test_a_stop_before_any_seed_started_is_exit_130_and_leaves_no_folder(
    tmp_path, monkeypatch, capsys
):
    """Ctrl-C or SIGTERM while the workers start (no seed began: no result at all): exit 130,
    the folder's start marker removed (an internal IndexError before: probe 12's w01)."""
    import twin.cli.recording as recording
    from twin.cli import main
    from twin.experiment import ExperimentResult, leave_out_unfinished_seed

    def nothing_done(experiment, **options):
        outcome = ExperimentResult(experiment, [], [], {}, 0.0, interrupted=True)
        leave_out_unfinished_seed(outcome)  # no seed to leave out: nothing to do
        return outcome

    monkeypatch.setattr(recording, "run_experiment", nothing_done)
    out = tmp_path / "run"
    argv = ["evaluate", "--config", str(scenario_file(tmp_path, horizon=20)), "--seeds", "2",
            "--swarms", "random", "--out", str(out), "--no-report", "--quiet"]  # fmt: skip
    assert main(argv) == 130
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "interrupted" in err[0], err
    assert not out.exists()
