"""Faults: `kill -9` at several points of `twin run`, `twin sweep` (and its pool workers),
a diverging pretraining, and bad numbers on the command line."""

from __future__ import annotations

import contextlib
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

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
