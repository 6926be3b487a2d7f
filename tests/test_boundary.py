"""The boundary between twin and its user: every bad input or fault is one line and an exit
code (2 refused, 3 unexpected with error.log, 130 interrupted), never a traceback, and nothing
outside the run folder changes."""

from __future__ import annotations

import contextlib
import errno
import hashlib
import os
import re
import shutil
import sys
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
from hypothesis import given
from hypothesis import strategies as st

from twin.boundary import EXIT_BUG, EXIT_INTERRUPTED, EXIT_REFUSED, LOG_NAME, run_command
from twin.cli import main
from twin.errors import UserError
from twin.resources import shipped_config
from twin.runs import RUN_FILE_NAMES, write_manifest

SYNTHETIC = shipped_config("configs/synthetic.toml")


def tree_hash(folder: Path, skip: Path | None = None) -> str:
    """A digest of every file (name and bytes) under ``folder``, ``skip``'s subtree left out."""
    digest = hashlib.sha256()
    for p in sorted(folder.rglob("*")):
        if skip is not None and (p == skip or skip in p.parents):
            continue
        digest.update(os.fsencode(p.relative_to(folder)))
        if p.is_file() and not p.is_symlink():
            digest.update(p.read_bytes())
    return digest.hexdigest()


def small_config(folder: Path, horizon: int = 12, **grid) -> Path:
    """The shipped synthetic config with a short horizon (and another grid, if given)."""
    text = SYNTHETIC.read_text().replace("horizon = 2000", f"horizon = {horizon}")
    for key, value in grid.items():
        text = text.replace(f"{key} = {20 if key == 'nx' else 30}\n", f"{key} = {value}\n", 1)
    path = folder / "small.toml"
    path.write_text(text)
    return path


@pytest.fixture(scope="module")
def run_folder(tmp_path_factory) -> Path:
    """A small finished `twin evaluate` run folder (2 seeds, 2 swarms), made once."""
    root = tmp_path_factory.mktemp("boundary-run")
    config = small_config(root)
    out = root / "run"
    argv = ["evaluate", "--config", str(config), "--swarms", "random,greedy", "--seeds", "2"]
    assert main([*argv, "--out", str(out), "--no-report", "--quiet"]) == 0
    return out


@pytest.fixture()
def run_copy(run_folder: Path, tmp_path: Path) -> Path:
    out = tmp_path / "work" / "run"
    shutil.copytree(run_folder, out)
    return out


def one_line(capsys) -> str:
    err = capsys.readouterr().err
    lines = err.strip().splitlines()
    assert "Traceback" not in err
    assert len(lines) == 1, err
    return lines[0]


def refresh_manifest(run: Path) -> None:
    """A damaged file that the manifest agrees with: the content checks must catch it."""
    write_manifest(run, False, None)


def as_format_3_wrote(run: Path) -> None:
    """The 0 twin wrote up to folder format 3 where one seed gives no interval (``_ci95``
    cells now left empty): a folder relabelled to an earlier format holds what that wrote."""
    for name in ("summary.csv", "monitoring.csv", "comparison.csv"):
        if (run / name).is_file():
            table = pd.read_csv(run / name)
            spans = [c for c in table.columns if c.endswith("_ci95")]
            table[spans] = table[spans].fillna(0.0)
            table.to_csv(run / name, index=False)


# --- the boundary itself ----------------------------------------------------------------------


def _raise(exc):
    def command(args):
        raise exc

    return command


@pytest.mark.parametrize(
    ("exc", "code", "words"),
    [
        (UserError("config.toml: [grid].nx = -1 must be >= 1"), EXIT_REFUSED, "[grid].nx"),
        (KeyboardInterrupt(), EXIT_INTERRUPTED, "interrupted"),
        (OSError(errno.ENOSPC, "No space left on device", "out/x"), EXIT_REFUSED, "free some"),
        (OSError(errno.EROFS, "Read-only file system", "out/x"), EXIT_REFUSED, "read-only"),
        (PermissionError(errno.EACCES, "Permission denied", "out/x"), EXIT_REFUSED, "permission"),
        (FileNotFoundError(errno.ENOENT, "No such file", "a/b"), EXIT_REFUSED, "a/b"),
        (MemoryError(), EXIT_REFUSED, "out of memory"),
        (ModuleNotFoundError("No module named 'ray'", name="ray"), EXIT_REFUSED, "pip install"),
        (ModuleNotFoundError("No module named 'twin.x'", name="twin.x"), EXIT_BUG, LOG_NAME),
        (RuntimeError("boom\nsecond line"), EXIT_BUG, LOG_NAME),
        (ZeroDivisionError("float division by zero"), EXIT_BUG, LOG_NAME),
    ],
)
def test_every_exception_is_one_line_and_an_exit_code(exc, code, words, capsys) -> None:
    assert run_command(_raise(exc), None) == code
    line = one_line(capsys)
    assert line.startswith("twin: ") and words in line


# errno, whether the command has --out -> words of the fix, and whether it names --out
OS_ERROR_FIXES = {
    "full disk, --out": (errno.ENOSPC, True, "free some space on that disk", True),
    "full disk, no --out": (errno.ENOSPC, False, "free some space on that disk", False),
    "quota, no --out": (errno.EDQUOT, False, "free some space on that disk", False),
    "read-only, --out": (errno.EROFS, True, "read-only", True),
    "read-only, no --out": (errno.EROFS, False, "read-only", False),
}


@pytest.mark.parametrize("case", list(OS_ERROR_FIXES))
def test_os_error_names_the_file_and_a_fix_the_command_has(case, capsys) -> None:
    import argparse

    code, has_out, words, names_out = OS_ERROR_FIXES[case]
    args = argparse.Namespace(run_dir=Path("r"), **({"out": None} if has_out else {}))
    exc = OSError(code, os.strerror(code), "r/report/scores.png")
    assert run_command(_raise(exc), args) == EXIT_REFUSED
    line = one_line(capsys)
    assert line.startswith(f"twin: error: r/report/scores.png: {os.strerror(code)}; ")
    assert words in line and ("--out" in line) == names_out


def test_unexpected_error_logs_its_traceback_in_the_run_folder(
    tmp_path: Path, monkeypatch, capsys
) -> None:
    import twin.cli.recording  # imported first: it binds ``record`` when imported

    def broken(*args, **kwargs):
        raise RuntimeError("a bug in the writer")

    monkeypatch.setattr(twin.cli.recording, "record", broken)
    config, out = small_config(tmp_path), tmp_path / "run"
    code = main(["evaluate", "--config", str(config), "--swarms", "random", "--out", str(out)])
    assert code == EXIT_BUG
    line = one_line(capsys)
    log = out / LOG_NAME
    assert str(log) in line and "RuntimeError: a bug in the writer" in line
    assert "Traceback" in log.read_text() and "a bug in the writer" in log.read_text()


def test_unexpected_error_before_a_run_folder_logs_in_the_cache(
    tmp_path: Path, monkeypatch, capsys
) -> None:
    cache = tmp_path / "cache"
    monkeypatch.setenv("TWIN_CACHE_DIR", str(cache))

    import twin.cli.evaluate

    def broken(*args, **kwargs):
        raise KeyError("nx")

    monkeypatch.setattr(twin.cli.evaluate, "load_config", broken)
    assert main(["evaluate", "--out", str(tmp_path / "run")]) == EXIT_BUG
    line = one_line(capsys)
    assert str(cache / LOG_NAME) in line
    assert "KeyError" in (cache / LOG_NAME).read_text()
    assert not (tmp_path / "run").exists()


def test_error_log_is_a_run_file_and_not_in_the_manifest() -> None:
    from twin.runs import UNLISTED

    assert LOG_NAME in RUN_FILE_NAMES and LOG_NAME in UNLISTED
    guide = (Path(__file__).parents[1] / "docs" / "guide.md").read_text()
    assert f"| `{LOG_NAME}` |" in guide


@pytest.mark.parametrize(
    "argv",
    [
        ["evaluate", "--seeds", "x"],
        ["nonsense"],
        ["run", "--gui-shade", "pink"],
        ["report"],
    ],
)
def test_command_line_errors_are_one_line(argv, capsys) -> None:
    with pytest.raises(SystemExit) as stop:
        main(argv)
    assert stop.value.code == EXIT_REFUSED
    assert "--help" in one_line(capsys)


# --- bad inputs through the CLI ---------------------------------------------------------------


def _edited_config(folder: Path, old: str, new: str) -> Path:
    """The small synthetic config with ``old`` replaced by ``new`` (which must be in it)."""
    path = small_config(folder)
    text = path.read_text()
    assert old in text
    path.write_text(text.replace(old, new, 1))
    return path


def _without_disturbances(folder: Path) -> Path:
    """The small synthetic config with ``disturbances = []``."""
    path = small_config(folder)
    head, rest = path.read_text().split("disturbances = [", 1)
    path.write_text(head + "disturbances = []\n\n[evaluate]" + rest.split("[evaluate]", 1)[1])
    return path


def _sparse(path: Path, size: int) -> Path:
    """A file of ``size`` bytes that takes no disk (a hole)."""
    with open(path, "wb") as fh:
        fh.truncate(size)
    return path


def _write(path: Path, text: str) -> Path:
    path.write_text(text)
    return path


def _linked(t: Path, name: str, target: str) -> Path:
    """``t/name``, a symbolic link to the folder ``t/target`` (made)."""
    (t / target).mkdir(exist_ok=True)
    (t / name).symlink_to(t / target)
    return t / name


CASES = {
    # name: (argv builder(tmp) -> argv, words expected in the line)
    "missing config": (lambda t: ["evaluate", "--config", str(t / "nope.toml")], "nope.toml"),
    "config read from a device": (
        lambda t: ["evaluate", "--config", "/dev/zero"],
        "/dev/zero: over 16 MB, larger than any config",
    ),
    "a huge config": (
        lambda t: ["sweep", "--config", str(_sparse(t / "huge.toml", 2**30))],
        "huge.toml: over 16 MB, larger than any config",
    ),
    "config not TOML": (
        lambda t: ["evaluate", "--config", str(_write(t / "bad.toml", "[grid\nnx = 1"))],
        "bad.toml",
    ),
    # a RecursionError was an internal error (probe 16's f16)
    "config nested 5000 deep": (
        lambda t: [
            "evaluate",
            "--config",
            str(_write(t / "deep.toml", "a = " + "[" * 5000 + "]" * 5000)),
        ],
        "deep.toml: not valid TOML for twin (nested deeper than Python reads)",
    ),
    "sweep config nested 5000 deep": (
        lambda t: [
            "sweep",
            "--config",
            str(_write(t / "deep.toml", "a = " + "[" * 5000 + "]" * 5000)),
        ],
        "deep.toml: not valid TOML for twin",
    ),
    "huge grid": (
        lambda t: ["evaluate", "--config", str(small_config(t, nx=100000, ny=100000))],
        "100000",
    ),
    "out is a file": (
        lambda t: ["evaluate", "--config", str(small_config(t)), "--out", str(_write(t / "f", ""))],
        "in the way",
    ),
    "out under a file": (
        lambda t: ["evaluate", "--config", str(small_config(t)), "--out", str(t / "f2" / "run")],
        "is a file",
    ),
    "report of no folder": (lambda t: ["report", str(t / "none")], "no such run folder"),
    "replay of no folder": (lambda t: ["replay", str(t / "none")], "no such run folder"),
    "bad tape": (
        lambda t: [
            "evaluate",
            "--config",
            str(small_config(t)),
            "--traffic",
            str(_write(t / "tape.parquet", "not parquet")),
        ],
        "tape.parquet",
    ),
    "out not UTF-8": (
        lambda t: [
            "evaluate",
            "--config",
            str(small_config(t)),
            "--out",
            os.fsdecode(bytes(t) + b"/\xff\xfe"),
        ],
        "not valid UTF-8",
    ),
    "network file not UTF-8": (
        lambda t: ["run", "--net", str(_write(t / os.fsdecode(b"city\xff.net.xml"), "<net/>"))],
        "city\\xff.net.xml': the name is not valid UTF-8; give a name in UTF-8 (rename",
    ),
    "config in a folder not UTF-8": (
        lambda t: ["evaluate", "--config", os.fsdecode(bytes(t) + b"/\xfe/small.toml")],
        "\\xfe/small.toml': the name is not valid UTF-8",
    ),
    "one of several tapes not UTF-8": (
        lambda t: ["pretrain", "--traffic", "a.parquet", os.fsdecode(b"b\xff.parquet")],
        "--traffic 'b\\xff.parquet': the name is not valid UTF-8",
    ),
    "run folder not UTF-8": (
        lambda t: ["report", os.fsdecode(bytes(t) + b"/run\xff")],
        "run\\xff': the name is not valid UTF-8",
    ),
    "sweep out not UTF-8": (
        lambda t: ["sweep", "--config", "sweep-demo", "--out", os.fsdecode(bytes(t) + b"/x\xff")],
        "not valid UTF-8",
    ),
    "swarms empty": (
        lambda t: ["evaluate", "--config", str(small_config(t)), "--swarms", ""],
        "--swarms is empty; name at least one swarm",
    ),
    "swarms only commas": (
        lambda t: ["evaluate", "--config", str(small_config(t)), "--swarms", " , "],
        "--swarms is empty",
    ),
    "swarms with an empty name": (
        lambda t: ["evaluate", "--config", str(small_config(t)), "--swarms", "random,,greedy"],
        "--swarms 'random,,greedy': name 2 of 3 is empty (two commas in a row, or one at an end)",
    ),
    "swarms with a trailing comma": (
        lambda t: ["run", "--swarms", "random, greedy,"],
        "--swarms 'random, greedy,': name 3 of 3 is empty",
    ),
    "gui swarms with an empty name": (
        lambda t: ["run", "--gui-swarms", ",random"],
        "--gui-swarms ',random': name 1 of 2 is empty",
    ),
    "config swarms with an empty name": (
        lambda t: [
            "evaluate",
            "--config",
            str(_edited_config(t, 'swarms = ["random",', 'swarms = ["", "random",')),
        ],
        "small.toml: [evaluate].swarms = ['', 'random', ",
    ),
    "record over an existing file": (
        lambda t: ["run", "--record", str(_write(t / "mine.mp4", "my video"))],
        "the file exists, and --record never overwrites a file",
    ),
    "record into a folder": (lambda t: ["run", "--record", str(t)], "--record"),
    "cell size below a metre": (
        lambda t: ["run", "--cell-m", "0.001"],
        "--cell-m 0.001: cell size 0.001 m is outside 1 .. 100000 m",
    ),
    "cell size huge": (lambda t: ["run", "--cell-m", "1e9"], "--cell-m 1e+09: cell size"),
    "cell size NaN": (
        lambda t: ["run", "--cell-m", "nan"],
        "--cell-m = nan must be a finite number",
    ),
    "begin not a clock": (lambda t: ["run", "--begin", "7:99"], "--begin = '7:99' must be"),
    "sweep out is a file": (
        lambda t: [
            "sweep",
            "--config",
            "sweep-demo",
            "--out",
            str(_write(t / "f3", "")),
        ],
        "in the way",
    ),
    "pretrain out is a file": (
        lambda t: ["pretrain", "--out", str(_write(t / "f4", "")), "--epochs", "1"],
        "in the way",
    ),
    "pretrain out empty": (
        lambda t: ["pretrain", "--out", "", "--epochs", "1"],
        "--out = '': string should have at least 1 character",
    ),
    "no disturbance on the map": (
        lambda t: ["evaluate", "--config", str(_without_disturbances(t))],
        "[traffic].disturbances is empty: the map has no z^k (Sec. IV)",
    ),
    "z_lo above every z of the map": (
        lambda t: ["evaluate", "--config", str(_edited_config(t, "z_lo = 0.0", "z_lo = 5.0"))],
        "[traffic].z_lo = 5 is not below the largest z of the map over the horizon",
    ),
    "a disturbance off the map": (
        lambda t: [
            "evaluate",
            "--config",
            str(_edited_config(t, "i = 5, j = 8", "i = 500, j = 8")),
        ],
        "[traffic].disturbances[0] is centred at (i, j) = (500, 8), 481 cells off the 20 x 30 map",
    ),
    "a disturbance wider than ten maps": (
        lambda t: ["evaluate", "--config", str(_edited_config(t, "sigma = 3.0", "sigma = 301.0"))],
        "[traffic].disturbances[0].sigma = 301 cells is more than 10 x the 20 x 30 map's side",
    ),
    "a disturbance whose width overflows": (
        lambda t: ["evaluate", "--config", str(_edited_config(t, "sigma = 3.0", "sigma = 1e200"))],
        "sigma = 1e+200 must be <= 1000000",
    ),
    "evaluate workers past the memory limit on a small grid": (  # only fewer workers help
        lambda t: [
            "evaluate",
            "--config",
            str(small_config(t, horizon=3)),
            "--seeds",
            "8",
            "--workers",
            "8",
            "--max-memory-gb",
            "2",
        ],
        "--workers 8: 8 worker processes at once need at least 6.4 GB",
    ),
    "a checkpoint that is a folder": (
        lambda t: [
            "evaluate",
            "--swarms",
            "rl",
            "--config",
            str(
                _write(
                    t / "ck.toml",
                    small_config(t).read_text() + f'\n[swarm_options.rl]\ncheckpoint = "{t}"\n',
                )
            ),
        ],
        "is a folder, not a file; run `twin pretrain`",
    ),
    "sweep workers past the memory limit": (
        lambda t: [
            "sweep",
            "--config",
            "sweep-demo",
            "--workers",
            "64",
            "--max-memory-gb",
            "2",
            "--out",
            str(t / "sw"),
        ],
        "--workers 64: 64 sweep cells at once need at least 51.2 GB",
    ),
    "transfer workers past the memory limit": (
        lambda t: ["transfer", "--workers", "64", "--max-memory-gb", "2", "--out", str(t / "tr")],
        "--workers 64: 64 tasks at once need at least 51.2 GB",
    ),
    "gui swarms without --gui": (
        lambda t: ["run", "--gui-swarms", "nosuch"],
        "--gui-swarms: 'nosuch' is not among the run's swarms",
    ),
    "gui swarms naming none": (
        lambda t: ["run", "--gui-swarms", " , "],
        "--gui-swarms ' , ': names no swarm",
    ),
    # a swarm drawn twice failed in SUMO's GUI, after the warm-up: an empty partial run (probe
    # 16's f03); 'all' beside a swarm was refused naming 'all' as the fix (f04)
    "gui swarm named twice": (
        lambda t: ["run", "--gui-swarms", "random,random"],
        "--gui-swarms 'random,random': 'random' is named twice",
    ),
    "gui swarms all and one": (
        lambda t: ["run", "--gui-swarms", "all,random"],
        "--gui-swarms 'all,random': 'all' stands alone",
    ),
    # a video in the run folder was removed with its report (probe 16's f13, f14)
    "record inside the run's report": (
        lambda t: ["run", "--record", str(t / "R" / "report" / "x.gif"), "--out", str(t / "R")],
        "/report/x.gif: lies in --out ",
    ),
    "record into the run's report through a link": (
        lambda t: [
            "run",
            "--record",
            str(_linked(t, "L", "R") / "report" / "x.gif"),
            "--out",
            str(t / "R"),
        ],
        "/report/x.gif: lies in --out ",
    ),
    "record as the run folder": (
        lambda t: ["run", "--record", str(t / "same.gif"), "--out", str(t / "same.gif")],
        "same.gif: lies in --out ",
    ),
    # a long path: the line was cut before its reason (probe 16's f02)
    "out too long for the files written below it": (
        lambda t: ["evaluate", "--out", str(t / "/".join(["d" * 200] * 20))],
        "bytes below it, past the 4096 the file system takes; pass a shorter path",
    ),
    "out with a name past NAME_MAX": (
        lambda t: ["evaluate", "--out", str(t / ("n" * 300))],
        "a name in it is 300 bytes long, past the 255 the file system takes",
    ),
    "report of a missing folder under a long path": (
        lambda t: ["report", str(t / "/".join(["x" * 200] * 3))],
        "no such run folder; pass the folder `twin run`/`evaluate` wrote",
    ),
}
#: output paths on a file system that reports no size and takes no files (Linux: /proc, /sys)
SPECIAL_FS = {
    "out on /proc": (
        lambda t: ["evaluate", "--config", str(small_config(t)), "--out", "/proc/twin-run"],
        "--out /proc/twin-run: /proc is on a special file system",
    ),
    "sweep out on /sys": (
        lambda t: ["sweep", "--config", "sweep-demo", "--out", "/sys/twin-sweep"],
        "--out /sys/twin-sweep: /sys is on a special file system",
    ),
    "record on /proc": (
        lambda t: ["run", "--record", "/proc/twin.mp4"],
        "--record /proc/twin.mp4: /proc is on a special file system",
    ),
    "pretrain out on /proc": (
        lambda t: ["pretrain", "--out", "/proc/twin-pretrain", "--epochs", "1"],
        "--out /proc/twin-pretrain: /proc is on a special file system",
    ),
    "history out on /proc": (
        lambda t: ["history", "--from", str(t / "run"), "--out", "/proc/twin-history.npz"],
        "--out /proc/twin-history.npz: /proc is on a special file system",
    ),
}


def _reports_no_size(path: str) -> bool:
    try:
        return os.statvfs(path).f_blocks == 0
    except OSError:
        return False


@pytest.mark.skipif(
    not (_reports_no_size("/proc") and _reports_no_size("/sys")),
    reason="needs /proc and /sys as file systems that report no size (Linux)",
)
@pytest.mark.parametrize("name", list(SPECIAL_FS))
def test_output_on_a_special_file_system_is_one_line(name, tmp_path: Path, capsys) -> None:
    """Not the misleading "0 MB free" of a file system that reports no size: the path and what
    is wrong with it."""
    build, words = SPECIAL_FS[name]
    argv = build(tmp_path)
    before = tree_hash(tmp_path)
    assert main(argv) == EXIT_REFUSED
    line = one_line(capsys)
    assert words in line and "MB free" not in line, line
    assert tree_hash(tmp_path) == before
    assert not Path(argv[argv.index("--out" if "--out" in argv else "--record") + 1]).exists()


def test_a_file_system_that_reports_no_size_but_takes_files_is_not_refused(
    tmp_path: Path, monkeypatch
) -> None:
    """Some mounts report no size and still take files: the estimate is skipped, not failed."""
    import twin.outputs
    from twin.outputs import check_output_dir

    real = os.statvfs

    def no_size(path):
        stats = real(path)
        return os.statvfs_result((*stats[:2], 0, 0, 0, *stats[5:]))

    monkeypatch.setattr(twin.outputs.os, "statvfs", no_size)
    monkeypatch.setattr(
        twin.outputs.shutil, "disk_usage", lambda p: shutil._ntuple_diskusage(0, 0, 0)
    )
    before = tree_hash(tmp_path)
    assert check_output_dir(tmp_path / "run", "--out") == tmp_path / "run"
    assert tree_hash(tmp_path) == before  # the probe folder is gone again


# every path argument: an empty one is refused, never read as the current folder
EMPTY_PATHS = {
    "run --out": ["run", "--out", ""],
    "evaluate --out": ["evaluate", "--out", ""],
    "sweep --out": ["sweep", "--config", "sweep-demo", "--out", ""],
    "history --out": ["history", "--from", "x", "--out", ""],
    "network --out": ["network", "import-osm", "x.osm", "--out", ""],
    "run --config": ["run", "--config", ""],
    "run --net": ["run", "--net", ""],
    "run --record": ["run", "--record", ""],
    "evaluate --traffic": ["evaluate", "--traffic", ""],
    "pretrain --traffic, one of two": ["pretrain", "--traffic", "a.parquet", ""],
    "pretrain --init": ["pretrain", "--init", ""],
    "report RUN_DIR": ["report", ""],
    "replay RUN_DIR": ["replay", ""],
}


@pytest.mark.parametrize("name", list(EMPTY_PATHS))
def test_an_empty_path_is_refused(name, tmp_path: Path, capsys, monkeypatch) -> None:
    monkeypatch.chdir(tmp_path)
    before = tree_hash(tmp_path)
    with pytest.raises(SystemExit) as stop:
        main(EMPTY_PATHS[name])
    assert stop.value.code == EXIT_REFUSED
    line = one_line(capsys)
    assert "an empty path; give a file or folder name" in line, line
    assert tree_hash(tmp_path) == before


@pytest.mark.parametrize("name", list(CASES))
def test_bad_input_is_one_line_exit_2(name, tmp_path: Path, capsys) -> None:
    build, words = CASES[name]
    (tmp_path / "f2").write_text("")
    argv = build(tmp_path)
    before = tree_hash(tmp_path)
    assert main(argv) == EXIT_REFUSED
    assert words in one_line(capsys)
    assert tree_hash(tmp_path) == before  # a refusal writes nothing


# --- run folders read back ------------------------------------------------------------------


def _edit_table(name, edit):
    def apply(run: Path) -> None:
        path = run / name
        frame = pd.read_parquet(path) if path.suffix == ".parquet" else pd.read_csv(path)
        frame = edit(frame)
        if path.suffix == ".parquet":
            frame.to_parquet(path, index=False)
        else:
            frame.to_csv(path, index=False)

    return apply


def _set(column, value, row=0):
    def edit(frame):
        frame[column] = frame[column].astype(object)
        frame.loc[frame.index[row], column] = value
        return frame

    return edit


def _jump(frame):
    """Drone 0 of the first swarm and seed two cells away at step 2 (a diagonal move of one
    cell each way)."""
    first = frame[(frame["drone"] == 0) & (frame["swarm"] == frame["swarm"].iloc[0])]
    row = first[(first["seed"] == first["seed"].min()) & (first["step"] == 2)].index[0]
    before = first[(first["seed"] == first["seed"].min()) & (first["step"] == 1)].iloc[0]
    frame.loc[row, "i"] = before["i"] + (1 if before["i"] == 0 else -1)
    frame.loc[row, "j"] = before["j"] + (1 if before["j"] == 0 else -1)
    return frame


def _maps(**arrays):
    def apply(run: Path) -> None:
        with np.load(run / "importance.npz") as npz:
            data = dict(npz)
        data.update({k: v(data) for k, v in arrays.items()})
        np.savez(run / "importance.npz", **data)

    return apply


def _json(name, key, value):
    def apply(run: Path) -> None:
        import json

        data = json.loads((run / name).read_text())
        node = data
        *parents, last = key
        for k in parents:
            node = node.setdefault(k, {})
        node[last] = value
        (run / name).write_text(json.dumps(data))

    return apply


def _json_edit(name, edit):
    def apply(run: Path) -> None:
        import json

        (run / name).write_text(json.dumps(edit(json.loads((run / name).read_text()))))

    return apply


def _both(*edits):
    def apply(run: Path) -> None:
        for edit in edits:
            edit(run)

    return apply


def _synthetic_traffic(edit, seeds_only: bool = False):
    """run.json's synthetic traffic record (and each seed's copy of it) passed through ``edit``;
    with ``seeds_only``, the seeds' copies only."""

    def apply(run: Path) -> None:
        import json

        data = json.loads((run / "run.json").read_text())
        for record in ([] if seeds_only else [data["traffic"]]) + data["traffic_by_seed"]:
            edit(record)
        (run / "run.json").write_text(json.dumps(data))

    return apply


def _network_json(**grid):
    """A network.json (as a SUMO run writes it) whose grid is changed by ``grid``."""

    def apply(run: Path) -> None:
        import json

        with np.load(run / "importance.npz") as npz:
            nx, ny = npz["obstacles"].shape
        network = {
            "name": "n", "net_file": "n.net.xml", "route_files": [],
            "grid": {"x0": 0.0, "y_top": 0.0, "cell_m": 500.0, "nx": nx, "ny": ny,
                     "bbox": [0, 0, 1, 1], "lane_km_total": 1.0, **grid},
        }  # fmt: skip
        (run / "network.json").write_text(json.dumps(network))

    return apply


def _built_file(name, make):
    """A file the fixture run lacks, as twin writes it, built from the run by ``make`` (a table
    or JSON)."""

    def apply(run: Path) -> None:
        import json

        data = make(run)
        if isinstance(data, pd.DataFrame):
            if name.endswith(".parquet"):
                data.to_parquet(run / name, index=False)
            else:
                data.to_csv(run / name, index=False)
        else:
            (run / name).write_text(json.dumps(data))

    return apply


def _degradation(run: Path, scored: bool = False, drop: int | None = None, **changes):
    """A degradation.csv (twin.faults.degradation_frame) of the run's seeds and swarms: a drone
    lost at step 6 of 12, then the whole run (``scored``: each R_hat its series' mean, as
    twin writes it; ``drop``: that row removed); ``changes`` set columns of row 0."""
    rows = []
    for seed in (0, 1):
        for swarm in ("random", "greedy"):
            for phase, (start, stop, label) in enumerate(
                [(0, 6, "no drone lost"), (6, 12, "1 of 3 drones lost"), (0, 12, "whole run")]
            ):
                rows.append(
                    {"seed": seed, "swarm": swarm, "phase": phase + 1, "label": label,
                     "start": start, "stop": stop, "R_hat": 0.4, "R_hat_fault_free": 0.5,
                     "events": 2, "pct_events_seen": 50.0, "pct_events_seen_fault_free": 100.0,
                     "latency_median_steps": 1.0, "latency_median_steps_fault_free": 0.0,
                     "pct_congested_observed": 20.0, "pct_congested_observed_fault_free": 30.0}
                )  # fmt: skip
    frame = pd.DataFrame(rows)
    if scored:
        series = pd.read_parquet(run / "series.parquet")
        for n, r in frame.iterrows():
            mine = series[(series["seed"] == r["seed"]) & (series["swarm"] == r["swarm"])]
            steps = mine["step"].between(r["start"], r["stop"] - 1)
            frame.loc[n, "R_hat"] = mine.loc[steps, "reward"].mean()
    if drop is not None:
        frame = frame.drop(index=drop).reset_index(drop=True)
    for column, value in changes.items():
        frame[column] = frame[column].astype(object)
        frame.loc[0, column] = value
    return frame


def _beliefs(run: Path, **changes) -> pd.DataFrame:
    """A belief_models.csv (twin.belief.run_beliefs) of the run's swarms and the history-only
    reference row; ``changes`` set columns of row 1."""
    rows = [("(no drones)", "history")] + [
        (swarm, model) for swarm in ("random", "greedy") for model in ("last-seen", "nowcast")
    ]
    frame = pd.DataFrame(rows, columns=["swarm", "model"]).assign(
        belief_error=0.1, calibration_90=0.9, events=2.0, pct_events_known=50.0,
        latency_median_steps=1.0, latency_median_min=0.5, false_alarms=1.0,
        false_alarms_per_hour=2.0, n_seeds=2,
    )  # fmt: skip
    for column, value in changes.items():
        frame[column] = frame[column].astype(object)
        frame.loc[1, column] = value
    return frame


def _events(run: Path, **changes) -> pd.DataFrame:
    """The run's events.parquet (twin.runs); ``changes`` set row 0."""
    frame = pd.read_parquet(run / "events.parquet")
    for column, value in changes.items():
        frame.loc[0, column] = value
    return frame


def _mfd(**changes) -> dict:
    """An mfd.json (twin.mfd) of a fit; ``changes`` replace its fields."""
    return {"form": "underwood", "a": 0.7, "k_c": 40.0, "fit": "online", "used": "fit",
            "why": "ok", "n_samples": 100, "r2": 0.5, "rmse_kmh": 5.0, **changes}  # fmt: skip


def _network(run: Path, **changes) -> dict:
    """A network.json as a SUMO run writes it; ``changes`` replace its fields."""
    with np.load(run / "importance.npz") as npz:
        nx, ny = npz["obstacles"].shape
    return {
        "name": "n", "net_file": "n.net.xml", "route_files": [],
        "grid": {"x0": 0.0, "y_top": 0.0, "cell_m": 500.0, "nx": nx, "ny": ny,
                 "bbox": [0, 0, 1, 1], "lane_km_total": 1.0},
        "n_obstacles": 0, "row_0": "north", **changes,
    }  # fmt: skip


def _shifted(swarm, **shifts):
    """``swarm``'s figures moved in both seeds, consistently in every file made of them: each
    ``series.parquet`` column of ``shifts`` (with ``cumulative_reward`` its running sum again)
    and each ``per_seed.csv``/``summary.csv``/``monitoring.csv`` column (their means over seeds;
    the intervals do not change). Only the trajectories and maps they were scored on disagree."""

    def apply(run: Path) -> None:
        series = pd.read_parquet(run / "series.parquet")
        mine = series["swarm"] == swarm
        for column, by in shifts.items():
            if column in series.columns:
                series.loc[mine, column] += by
        series["cumulative_reward"] = series.groupby(["seed", "swarm"])["reward"].cumsum()
        series.to_parquet(run / "series.parquet", index=False)
        for name in ("per_seed.csv", "summary.csv", "monitoring.csv"):
            frame = pd.read_csv(run / name)
            rows = frame["swarm"] == swarm
            for column, by in shifts.items():
                if column in frame.columns:
                    frame.loc[rows, column] += by
            frame.to_csv(run / name, index=False)

    return apply


def _swap_swarms(name, a, b):
    """The rows of swarms ``a`` and ``b`` of ``name`` under each other's name."""

    def edit(frame):
        swarm = frame["swarm"].astype(str)
        frame["swarm"] = swarm.mask(swarm == a, b).mask(swarm == b, a)
        return frame

    return _edit_table(name, edit)


def _event_rows(edit):
    """events.parquet with every swarm's row of its events changed alike by ``edit``."""
    return _edit_table("events.parquet", edit)


def _extra_event(frame):
    """Event 77 of seed 0 on the cell of event 0, a step later, for every swarm."""
    rows = frame[(frame["seed"] == 0) & (frame["event"] == 0)]
    more = rows.assign(event=77, onset=rows["onset"] + 1, seen=False, first_seen=-1,
                       latency_steps=-1)  # fmt: skip
    return pd.concat([frame, more], ignore_index=True)


def _comparison(**changes) -> pd.DataFrame:
    """A comparison.csv (twin.metrics.learned_against_best_classical) of a learned swarm."""
    return pd.DataFrame([{"swarm": "rl", "against": "greedy", "column": "R_hat_T",
                          "difference": 0.5, "difference_ci95": 0.1, "ratio": 1.2, "n_seeds": 2,
                          **changes}])  # fmt: skip


def _all(*damages):
    def apply(run: Path) -> None:
        for damage in damages:
            damage(run)

    return apply


def _samples(run: Path) -> pd.DataFrame:
    """An mfd_samples.parquet (twin.mfd) of three cell samples."""
    return pd.DataFrame({"step": [0, 1, 2], "i": [1, 1, 2], "j": [2, 3, 3],
                         "count": [1.0, 4.0, 9.0], "lane_km": [0.2] * 3,
                         "density": [5.0, 20.0, 60.0], "speed": [12.0, 9.0, 4.0],
                         "speed_limit": [13.9] * 3,
                         "speed_mfd_online": [12.0, 9.0, 4.0]})  # fmt: skip


def _relabel_seeds(run: Path) -> None:
    """Every seed of the folder relabelled as seed + 7, in every table and in run.json."""
    import json

    for path in [*run.glob("*.csv"), *run.glob("*.parquet")]:
        frame = pd.read_parquet(path) if path.suffix == ".parquet" else pd.read_csv(path)
        if "seed" in frame.columns and pd.api.types.is_integer_dtype(frame["seed"]):
            frame["seed"] = frame["seed"] + 7
            if path.suffix == ".parquet":
                frame.to_parquet(path, index=False)
            else:
                frame.to_csv(path, index=False)
    meta = json.loads((run / "run.json").read_text())
    meta["seeds"] = [s + 7 for s in meta["seeds"]]
    (run / "run.json").write_text(json.dumps(meta))


def _ceiling_set(swarm: str, column: str, value):
    """A ceiling row's ``column`` set to ``value``."""

    def edit(frame: pd.DataFrame) -> pd.DataFrame:
        frame = frame.copy()
        frame.loc[frame["swarm"] == swarm, column] = value
        return frame

    return edit


def _ceiling_scaled(swarm: str, factor: float):
    """A ceiling row's R_hat_T scaled alike in per_seed.csv and summary.csv."""

    def scale(frame: pd.DataFrame) -> pd.DataFrame:
        frame = frame.copy()
        frame.loc[frame["swarm"] == swarm, "R_hat_T"] *= factor
        return frame

    return _all(_edit_table("per_seed.csv", scale), _edit_table("summary.csv", scale))


READ_BACK = {
    "row deleted": (_edit_table("trajectories.parquet", lambda f: f.drop(f.index[5])), "rows"),
    "bound inflated alike in per_seed and summary": (
        _ceiling_scaled("bound (ceiling)", 1.5),
        "swarm 'bound (ceiling)', but bound.npz's prices on the seed's maps give",
    ),
    "oracle above the bound alike in per_seed and summary": (
        _ceiling_scaled("oracle (ceiling)", 3.0),
        "the oracle (ceiling) row of seed 0 has R_hat_T = ",
    ),
    "bound prices left out": (lambda run: (run / "bound.npz").unlink(), "no bound.npz"),
    # the oracle row is its cells' scores replayed (it was only kept under the bound)
    "oracle lowered alike in per_seed and summary": (
        _ceiling_scaled("oracle (ceiling)", 0.9),
        "swarm 'oracle (ceiling)', but oracle.parquet replayed over the seed's maps give",
    ),
    "oracle row given a monitoring figure alike in per_seed and summary": (
        _all(
            _edit_table("per_seed.csv", _ceiling_set("oracle (ceiling)", "belief_error", 0.5)),
            _edit_table("summary.csv", _ceiling_set("oracle (ceiling)", "belief_error", 0.5)),
        ),
        "belief_error = 0.5 for the oracle (ceiling) row of seed 0, which monitors nothing",
    ),
    "oracle cells left out": (
        lambda run: (run / "oracle.parquet").unlink(),
        "holds oracle (ceiling) rows, but the folder has no oracle.parquet",
    ),
    "oracle cells teleport": (
        _edit_table(
            "oracle.parquet",
            lambda f: f.assign(
                i=np.where(f["step"] == 3, 0, f["i"]), j=np.where(f["step"] == 3, 0, f["j"])
            ),
        ),
        "oracle.parquet: swarm oracle (ceiling) drone",
    ),
    "run.json lists fewer swarms than the tables hold": (
        _both(
            _json("run.json", ("swarms",), ["random"]),
            _json("run.json", ("invocation", "options", "swarms"), "random"),
        ),
        "holds swarm 'greedy', which run.json's swarms ['random'] does not list",
    ),
    "run.json swarms other than the command's": (
        _json("run.json", ("swarms",), ["random"]),
        "run.json: invocation.options.swarms = 'random,greedy', but swarms = ['random']",
    ),
    "run.json command of another kind": (
        _json("run.json", ("command",), "twin run --config x.toml"),
        "run.json: command = 'twin run --config x.toml' is no `twin evaluate`",
    ),
    # the report shows run.json's command as the line that made the run
    "run.json command giving other options": (
        _json_edit("run.json", lambda run: {**run, "command": run["command"] + " --seeds 7"}),
        "gives --seeds 7, but invocation.options.seeds = ",
    ),
    "run.json invocation with an option twin has not": (
        _json("run.json", ("invocation", "options", "bogus"), 1),
        "run.json: invocation.options.bogus is not an option of `twin evaluate`",
    ),
    "run.json command with an option twin has not": (
        _json("run.json", ("command",), "twin evaluate --faster"),
        "run.json: command = 'twin evaluate --faster' is no twin command line",
    ),
    "run.json --seeds other than its seeds": (
        _json("run.json", ("invocation", "options", "seeds"), 3),
        "run.json: invocation.options.seeds = 3, but seeds lists 2",
    ),
    "run.json --seed other than its first seed": (
        _json("run.json", ("invocation", "options", "seed"), 5),
        "run.json: invocation.options.seed = 5, but seeds are [0, 1]",
    ),
    "run.json --config other than its config": (
        _json("run.json", ("invocation", "options", "config"), "other.toml"),
        "run.json: invocation.options.config = 'other.toml', but config = ",
    ),
    "run.json invocation in a relative folder": (
        _json("run.json", ("invocation", "cwd"), "relative/dir"),
        "run.json: invocation.cwd = 'relative/dir' is no absolute folder",
    ),
    "run.json seconds of a step on synthetic traffic": (
        _json("run.json", ("monitoring", "step_s"), 30.0),
        "run.json: monitoring.step_s = 30.0, but the traffic records no step",
    ),
    "run.json timings of its own": (
        _json("run.json", ("timings", "x"), -1),
        "run.json: timings.x is no timing twin records",
    ),
    "run.json patrol seconds of fewer seeds": (
        _json("run.json", ("timings", "patrol_seconds"), [1.0]),
        "run.json: timings.patrol_seconds gives 1 seeds' seconds, but seeds lists 2",
    ),
    "run.json --seed as text": (
        _json("run.json", ("invocation", "options", "seed"), "0"),
        "run.json: invocation.options.seed = '0' must be a whole number",
    ),
    "every file relabelled to other seeds": (_relabel_seeds, "random starts on this map are"),
    "starts other than the drones'": (
        _json("run.json", ("starts",), [[0, 0], [0, 1], [0, 2]]),
        "run.json's starts are [[0, 0], [0, 1], [0, 2]]",
    ),
    "starts that are no cells": (_json("run.json", ("starts",), "line"), 'is neither "random"'),
    "row duplicated": (
        _edit_table("trajectories.parquet", lambda f: pd.concat([f, f.iloc[[3]]])),
        "twice",
    ),
    "cell off the grid": (_edit_table("trajectories.parquet", _set("i", 99)), "off the"),
    "drone jumps two cells": (
        _edit_table("trajectories.parquet", _jump),
        "more than one cell from where it was",
    ),
    "NaN in trajectories": (_edit_table("trajectories.parquet", _set("j", np.nan)), "'j'"),
    "string in trajectories": (
        _edit_table("trajectories.parquet", lambda f: f.astype({"i": str})),
        "'i'",
    ),
    "column dropped": (
        _edit_table("series.parquet", lambda f: f.drop(columns=["reward"])),
        "'reward'",
    ),
    "series step missing": (_edit_table("series.parquet", lambda f: f.drop(f.index[2])), "steps"),
    "NaN in series": (_edit_table("series.parquet", _set("coverage", np.nan, 4)), "coverage"),
    "string in summary": (_edit_table("summary.csv", _set("R_hat_T", "lots")), "R_hat_T"),
    "NaN headline in summary": (_edit_table("summary.csv", _set("R_hat_T", np.nan)), "R_hat_T"),
    "unknown role in summary": (_edit_table("summary.csv", _set("role", "xxxxx")), "'role'"),
    "per_seed row twice": (
        _edit_table("per_seed.csv", lambda f: pd.concat([f, f.iloc[[0]]])),
        "appears twice",
    ),
    "empty headline in per_seed": (
        _edit_table("per_seed.csv", _set("R_hat_T", np.nan, 1)),
        "per_seed.csv",
    ),
    # a column renamed (so one missing) or one added: accepted (probe 20's f09)
    **{
        f"a column renamed in {name}": (
            _edit_table(name, lambda f: f.rename(columns={"belief_error_ci95": "belief_ci55"})),
            f"{name}: holds a column 'belief_ci55', which twin does not write",
        )
        for name in ("summary.csv", "monitoring.csv")
    },
    "a column dropped from summary": (
        _edit_table("summary.csv", lambda f: f.drop(columns="pct_map_covered_ci95")),
        "summary.csv: lacks the column 'pct_map_covered_ci95', which twin writes",
    ),
    "a column dropped from monitoring": (
        _edit_table("monitoring.csv", lambda f: f.drop(columns="events")),
        "monitoring.csv: lacks the column 'events', which twin writes",
    ),
    **{  # probe 20's P2-f09d, P2-f09e
        f"a column added to {name}": (
            _edit_table(name, lambda f: f.assign(bogus=1.0)),
            f"{name}: holds a column 'bogus', which twin does not write",
        )
        for name in ("series.parquet", "trajectories.parquet", "timing.csv")
    },
    **{  # probe 20's P2-f09e: written since before the current format
        f"{column} dropped from timing": (
            _edit_table("timing.csv", lambda f, c=column: f.drop(columns=c)),
            f"timing.csv: lacks the column '{column}', which twin writes",
        )
        for column in ("process", "share")
    },
    **{
        f"{name} removed with its manifest entry": (
            lambda run, name=name: (run / name).unlink(),
            f"{name} is missing, which every run writes",
        )
        for name in ("timing.csv", "per_seed.csv")
    },
    "n_seeds dropped from monitoring": (
        _edit_table("monitoring.csv", lambda f: f.drop(columns="n_seeds")),
        "monitoring.csv: lacks the column 'n_seeds', which twin writes",
    ),
    "a column added to per_seed": (
        _edit_table("per_seed.csv", lambda f: f.assign(bogus=1.0)),
        "per_seed.csv: holds a column 'bogus', which twin does not write",
    ),
    "summary swarm row missing": (
        _edit_table("summary.csv", lambda f: f[f["swarm"] != "greedy"]),
        "'greedy'",
    ),
    "summary swarm duplicated": (
        _edit_table("summary.csv", lambda f: pd.concat([f, f.iloc[[0]]])),
        "swarm",
    ),
    "empty text in timing": (_edit_table("timing.csv", _set("process", np.nan)), "process"),
    "n_seeds not whole": (_edit_table("monitoring.csv", _set("n_seeds", np.nan)), "n_seeds"),
    "importance wrong shape": (_maps(importance=lambda d: d["importance"][:, :3]), "shape"),
    "importance NaN": (
        _maps(importance=lambda d: np.full(d["importance"].shape, np.nan)),
        "NaN",
    ),
    "importance below 0": (_maps(importance=lambda d: d["importance"] - 5.0), "outside 0 .. 1"),
    "obstacles everywhere": (_maps(obstacles=lambda d: np.ones_like(d["obstacles"])), "obstacle"),
    "npz truncated": (
        lambda run: (run / "importance.npz").write_bytes(
            (run / "importance.npz").read_bytes()[:100]
        ),
        "importance.npz",
    ),
    "run.json not JSON": (lambda run: (run / "run.json").write_text("{"), "run.json"),
    "run.json option of a wrong type": (_json("run.json", ("params", "eta"), "fast"), "params.eta"),
    "run.json traffic a list": (_json("run.json", ("traffic",), [1, 2]), "traffic"),
    # the report is written after the run: a listed one made the next report refuse the
    # folder as changed (probe 21's c25)
    "manifest listing the report": (
        _json("manifest.json", ("files", "report/report.html"), 10),
        "lists report/report.html, which a run's manifest never lists",
    ),
    "manifest size a string": (
        _json("manifest.json", ("files", "summary.csv"), "big"),
        "summary.csv",
    ),
    "summary headline off its series": (
        _edit_table("summary.csv", _set("R_hat_T", 0.123456)),
        "summary.csv: R_hat_T = 0.123456 for swarm 'random', but per_seed.csv gives",
    ),
    "bound below a swarm": (
        _edit_table(
            "summary.csv",
            lambda f: f.assign(R_hat_T=f["R_hat_T"].where(f["swarm"] != "bound (ceiling)", 1e-3)),
        ),
        "the bound (ceiling) row's R_hat_T = 0.001 lies below a swarm's",
    ),
    "cumulative reward off its rewards": (
        _edit_table("series.parquet", _set("cumulative_reward", 1e6, 3)),
        "cumulative_reward = 1e+06 at step 3 of seed 0",
    ),
    "run.json grid other than the maps": (
        _json("run.json", ("grid", "nx"), 99),
        "grid = 99 x",
    ),
    "coverage above 1": (_edit_table("series.parquet", _set("coverage", 5.0, 2)), "outside 0 .. 1"),
    "map covered above 100%": (
        _edit_table("summary.csv", _set("pct_map_covered", 250.0)),
        "column 'pct_map_covered' row 0 is 250, outside 0 .. 100",
    ),
    "per_seed seed without results": (
        _edit_table("per_seed.csv", lambda f: pd.concat([f, f.iloc[[0]].assign(seed=7)])),
        "per_seed.csv: seed 7 has rows but no results in series.parquet",
    ),
    "run.json horizon other than the steps": (
        _json("run.json", ("horizon",), 99),
        "horizon = 99, but seed 0 ran 12 steps",
    ),
    "run.json free cells other than the maps": (
        _json("run.json", ("grid", "n_free"), 3),
        "grid.n_free = 3, but importance.npz has",
    ),
    "run.json synthetic traffic other than the maps": (
        _synthetic_traffic(lambda t: t["disturbances"][0].update(amplitude=0.3)),
        "run.json: traffic (disturbances, beta1, beta2, z_lo, z_hi) generates importance",
    ),
    "run.json synthetic traffic of one seed not the run's": (
        _synthetic_traffic(lambda t: t.update(beta2=2.0), seeds_only=True),
        "run.json: traffic_by_seed[0].beta2 = 2.0, but traffic.beta2 = 5.0",
    ),
    "network.json grid other than the maps": (
        _network_json(nx=3),
        "network.json: grid = 3 x 30, but importance.npz holds 20 x 30 maps",
    ),
    "run.json seeds without results": (
        _both(
            _json("run.json", ("seeds",), [0, 1, 2]),
            _json("run.json", ("invocation", "options", "seeds"), 3),
            _json("run.json", ("timings", "patrol_seconds"), [1.0, 1.0, 1.0]),
        ),
        "seeds = [0, 1, 2] differ from those with results in series.parquet, [0, 1]",
    ),
    "a swarm's stage in timing renamed to a swarm the run did not run": (
        _edit_table("timing.csv", lambda f: f.replace({"stage": {"swarm greedy": "swarm rl"}})),
        "times stage 'swarm rl', but series.parquet holds no swarm 'rl'",
    ),
    "infinite seconds in timing": (
        _edit_table("timing.csv", _set("seconds", np.inf)),
        "column 'seconds' row 0 is inf, not a finite number",
    ),
    "run.json wall time not a number": (
        _json("run.json", ("wall_seconds",), float("nan")),
        "wall_seconds = NaN must be",
    ),
    "run.json negative peak memory": (
        _json("run.json", ("timings", "peak_memory_mb"), -5),
        "timings.peak_memory_mb = -5 must be a finite number of MB, at least 0",
    ),
    "run.json a seed's seconds not a number": (
        _json("run.json", ("timings", "patrol_seconds"), [float("nan"), 1.0]),
        "timings.patrol_seconds[0] = nan must be a finite number of seconds",
    ),
    "run.json kind of another command": (
        _json("run.json", ("kind",), "run"),
        "kind = 'run', but invocation.command = 'evaluate'",
    ),
    "run.json created not a time": (
        _json("run.json", ("created",), "yesterday"),
        "created = 'yesterday' is not a time",
    ),
    "run.json negative horizon": (
        _json("run.json", ("horizon",), -5),
        "horizon = -5 must be at least 0",
    ),
    "run.json no drones": (_json("run.json", ("n_drones",), 0), "n_drones = 0 must be at least"),
    "run.json cell size 0": (
        _json("run.json", ("traffic", "identity", "cell_m"), 0),
        "traffic.identity.cell_m = 0 must be above 0",
    ),
    "run.json grid of no rows": (_json("run.json", ("grid", "nx"), 0), "grid.nx = 0"),
    "run.json identity grid of one number": (
        _json("run.json", ("traffic", "identity", "grid"), [4]),
        "traffic.identity.grid = [4] must be [nx, ny]",
    ),
    "run.json step of 0 s": (_json("run.json", ("traffic", "step_s"), 0), "traffic.step_s = 0"),
    "run.json negative seed": (_json("run.json", ("seeds",), [-1]), "seeds[0] = -1"),
    "run.json eta above 1": (_json("run.json", ("params", "eta"), 3), "params.eta = 3 must be"),
    "run.json threshold 0": (
        _json("run.json", ("monitoring", "threshold"), 0),
        "monitoring.threshold = 0",
    ),
    "run.json faults of the wrong kind": (
        _json("run.json", ("faults",), {"drone_loss": [{"drone": 1, "step": "soon"}]}),
        "run.json: faults = {'drone_loss': [{'drone': 1, 'step': 'soon'}]} is not a fault record",
    ),
    "run.json folder not text": (_json("run.json", ("invocation", "cwd"), 5), "invocation.cwd"),
    "run.json a swarm listed twice": (
        _json("run.json", ("swarms",), ["random", "random", "greedy"]),
        "run.json: swarms lists 'random' twice",
    ),
    "run.json a version not text": (
        _json("run.json", ("versions", "python"), 3),
        "run.json: versions.python = 3 must be text",
    ),
    "run.json identity grid other than its grid": (
        _json("run.json", ("traffic", "identity", "grid"), [3, 27]),
        "run.json: traffic.identity.grid = [3, 27], but grid is",
    ),
    "run.json an error in a complete run": (
        _json("run.json", ("errors",), ["seed 0 failed badly"]),
        "run.json: errors = 'seed 0 failed badly', but partial = false",
    ),
    "run.json an error record not text": (
        _json("run.json", ("errors",), [{"x": 1}]),
        "run.json: errors[0] = {'x': 1} must be text",
    ),
    "run.json a partial reason in a complete run": (
        _json("run.json", ("partial_reason",), "it stopped"),
        "run.json: partial_reason = 'it stopped', but partial = false",
    ),
    "run.json a traffic error in a complete run": (
        _json("run.json", ("traffic", "error"), "SUMO crashed"),
        "run.json: traffic.error = 'SUMO crashed', but partial = false",
    ),
    "run.json SUMO outputs not in the folder": (
        _json("run.json", ("traffic", "sumo_outputs"), ["ghost.xml"]),
        "traffic.sumo_outputs[0] = 'ghost.xml', but",
    ),
    "run.json SUMO outputs out of the folder": (
        _json("run.json", ("traffic", "sumo_outputs"), ["../../x.xml"]),
        "traffic.sumo_outputs[0] = '../../x.xml' is not a name inside sumo/",
    ),
    "run.json a policy of no swarm of the run": (
        _json("run.json", ("policies",), {"rl": {"online": False}}),
        "run.json: policies.rl: 'rl' is no swarm of the run",
    ),
    "run.json drones other than the invocation's": (
        _json("run.json", ("invocation", "options", "drones"), 7),
        "run.json: invocation.options.drones = 7, but n_drones = ",
    ),
    "degradation infinite score": (
        _built_file("degradation.csv", lambda run: _degradation(run, R_hat=np.inf)),
        "degradation.csv: column 'R_hat' row 0 is inf, not a finite number",
    ),
    "degradation share above 100%": (
        _built_file(
            "degradation.csv", lambda run: _degradation(run, pct_events_seen_fault_free=400)
        ),
        "degradation.csv: column 'pct_events_seen_fault_free' row 0 is 400, outside 0 .. 100",
    ),
    "degradation row twice": (
        _built_file("degradation.csv", lambda run: _degradation(run, phase=2)),
        "degradation.csv: the row of seed 0, swarm 'random', phase 2 appears twice",
    ),
    "degradation swarm not in summary": (
        _built_file("degradation.csv", lambda run: _degradation(run, swarm="tours")),
        "degradation.csv: swarm 'tours' has no row in summary.csv",
    ),
    "degradation phase stops before it starts": (
        _built_file("degradation.csv", lambda run: _degradation(run, stop=-3)),
        "degradation.csv: phase 1 (row 0) runs from start = 0 to stop = -3",
    ),
    "degradation score off its series": (
        _built_file("degradation.csv", lambda run: _degradation(run, scored=True, R_hat=99.0)),
        "degradation.csv: R_hat = 99 for seed 0, swarm 'random', phase 1 (row 0), but its "
        "rewards in series.parquet average",
    ),
    "degradation phase row removed": (
        _built_file("degradation.csv", lambda run: _degradation(run, scored=True, drop=4)),
        "degradation.csv: the swarms of seed 0 have different phases",
    ),
    "degradation phase past the horizon": (
        _built_file("degradation.csv", lambda run: _degradation(run, stop=99)),
        "stop = 99, not phase >= 1 and 0 <= start <= stop <= 12",
    ),
    "belief error above 1": (
        _built_file("belief_models.csv", lambda run: _beliefs(run, belief_error=7.5)),
        "belief_models.csv: column 'belief_error' row 1 is 7.5, outside 0 .. 1",
    ),
    "belief error NaN": (
        _built_file("belief_models.csv", lambda run: _beliefs(run, belief_error=np.nan)),
        "belief_models.csv: column 'belief_error' row 1 is nan, not a finite number",
    ),
    "belief calibration above 1": (
        _built_file("belief_models.csv", lambda run: _beliefs(run, calibration_90=1.5)),
        "column 'calibration_90' row 1 is 1.5, outside 0 .. 1",
    ),
    "belief events known above 100%": (
        _built_file("belief_models.csv", lambda run: _beliefs(run, pct_events_known=-4)),
        "column 'pct_events_known' row 1 is -4, outside 0 .. 100",
    ),
    "belief swarm not in summary": (
        _built_file("belief_models.csv", lambda run: _beliefs(run, swarm="tours")),
        "belief_models.csv: swarm 'tours' has no row in summary.csv",
    ),
    "per_seed headline off its series": (
        _edit_table("per_seed.csv", _set("R_hat_T", 77.0, 1)),
        "per_seed.csv: R_hat_T = 77 for seed ",
    ),
    "run.json seed twice": (
        _both(
            _json("run.json", ("seeds",), [0, 1, 1]),
            _json("run.json", ("invocation", "options", "seeds"), 3),
            _json("run.json", ("timings", "patrol_seconds"), [1.0, 1.0, 1.0]),
        ),
        "run.json: seeds = [0, 1, 1] lists seed 1 twice",
    ),
    "run.json partial, the manifest not": (
        _json("run.json", ("partial",), True),
        "manifest.json: partial = false, but run.json has partial = true",
    ),
    "event off the grid": (
        _built_file("events.parquet", lambda run: _events(run, i=99)),
        "events.parquet: event 0 of seed 0 is on cell (99, ",
    ),
    "event past the horizon": (
        _built_file("events.parquet", lambda run: _events(run, onset=11, duration=5)),
        "events.parquet: event 0 of seed 0 has onset = 11, duration = 5, not within steps 0 .. 12",
    ),
    "event before step 0": (
        _built_file("events.parquet", lambda run: _events(run, onset=-4)),
        "has onset = -4, duration = ",
    ),
    "events seen without events": (
        _edit_table(
            "monitoring.csv", lambda f: f.assign(events=0.0, pct_events_seen=f["events"] * 0 + 40)
        ),
        "monitoring.csv: column 'pct_events_seen' of swarm 'random' (row 0) is 40, but the row "
        "has 0 events",
    ),
    "mfd.json free-flow share below 0": (
        _built_file("mfd.json", lambda run: _mfd(a=-0.5)),
        "mfd.json: a = -0.5 must be above 0",
    ),
    "mfd.json critical density 0": (
        _built_file("mfd.json", lambda run: _mfd(k_c=0)),
        "mfd.json: k_c = 0 must be above 0",
    ),
    "network.json row_0 unknown": (
        _built_file("network.json", lambda run: _network(run, row_0="sideways")),
        "network.json: row_0 = 'sideways' must be 'north'",
    ),
    "timing seconds below 0": (
        _edit_table("timing.csv", _set("seconds", -3.0)),
        "timing.csv: column 'seconds' row 0 is -3, outside 0 .. inf",
    ),
    "timing ms per step off its seconds": (
        _edit_table("timing.csv", lambda f: f.assign(ms_per_step=f["ms_per_step"] * 50)),
        "timing.csv: row 0 (seed 0, ",
    ),
    "timing share off its seconds": (
        _edit_table("timing.csv", lambda f: f.assign(share=f["share"] / 2)),
        "has share = ",
    ),
    "timing seconds off its ms per step": (
        _edit_table("timing.csv", lambda f: f.assign(seconds=f["seconds"] * 100)),
        "has ms_per_step = ",
    ),
    # a derived file edited to contradict the primary files it was computed from
    "summary coverage off its seeds": (
        _edit_table("summary.csv", _set("C_hat_T", 0.9)),
        "summary.csv: C_hat_T = 0.9 for swarm 'random', but per_seed.csv gives",
    ),
    "summary reward part off its seeds": (
        _edit_table("summary.csv", _set("R_hat_T_importance", 0.1)),
        "summary.csv: R_hat_T_importance = 0.1 for swarm 'random', but per_seed.csv gives",
    ),
    "summary time at max coverage off its seeds": (
        _edit_table("summary.csv", _set("pct_time_max_C", 90.0)),
        "summary.csv: pct_time_max_C = 90 for swarm 'random', but per_seed.csv gives",
    ),
    "summary paper reward off its seeds": (
        _edit_table("summary.csv", _set("R_hat_T_paper", 3.0)),
        "summary.csv: R_hat_T_paper = 3 for swarm 'random', but per_seed.csv gives",
    ),
    "summary seed count off its seeds": (
        _edit_table("summary.csv", lambda f: f.assign(n_seeds=5)),
        "summary.csv: n_seeds = 5 for swarm 'random', but per_seed.csv gives 2",
    ),
    "per_seed coverage off its series": (
        _edit_table("per_seed.csv", _set("C_hat_T", 0.9)),
        "per_seed.csv: C_hat_T = 0.9 for seed 0, swarm 'random', but series.parquet gives",
    ),
    "per_seed map covered off its series": (  # seed 1 (its series replays after per_seed)
        _edit_table(
            "series.parquet",
            lambda f: f.assign(
                visited_share=f["visited_share"].where(
                    (f["swarm"] != "random") | (f["seed"] != 1), f["visited_share"] / 2
                )
            ),
        ),
        "per_seed.csv: pct_map_covered = ",
    ),
    "series map covered off its trajectories": (
        _edit_table(
            "series.parquet",
            lambda f: f.assign(
                visited_share=f["visited_share"].where(
                    (f["swarm"] != "random") | (f["seed"] != 0), f["visited_share"] / 2
                )
            ),
        ),
        "series.parquet: visited_share = 0.005 for seed 0, swarm 'random', step 0, but "
        "trajectories.parquet and importance.npz give 0.01",
    ),
    "per_seed reward parts not adding up": (
        _edit_table("per_seed.csv", _set("R_hat_T_idleness", 0.0)),
        "per_seed.csv: R_hat_T = ",
    ),
    "per_seed belief error off its series": (
        _edit_table("per_seed.csv", _set("belief_error", 0.01)),
        "per_seed.csv: belief_error = 0.01 for seed 0, swarm 'random', but events.parquet, "
        "trajectories.parquet and series.parquet give",
    ),
    "per_seed coverage ceiling off the run's grid": (
        _edit_table("per_seed.csv", _set("C_hat_T_ceiling", 0.5)),
        "per_seed.csv: C_hat_T_ceiling = 0.5 for seed 0, swarm 'random', but importance.npz "
        "and run.json give",
    ),
    "monitoring belief error off the summary": (
        _edit_table("monitoring.csv", _set("belief_error", 0.01)),
        "monitoring.csv: belief_error = 0.01 for swarm 'random', but summary.csv gives",
    ),
    "monitoring events off the summary": (
        _edit_table("monitoring.csv", _set("events", 3)),
        "monitoring.csv: events = 3 for swarm 'random', but summary.csv gives",
    ),
    "events of one swarm missing": (
        _edit_table("events.parquet", lambda f: f[~((f["swarm"] == "greedy") & (f["event"] < 2))]),
        "events.parquet: no row for seed 0, event 0, swarm 'greedy', which trajectories.parquet",
    ),
    "event seen flag flipped": (
        _edit_table("events.parquet", lambda f: f.assign(seen=f["seen"] ^ (f.index == 0))),
        "events.parquet: seen = ",
    ),
    "event first sighting moved": (
        _edit_table("events.parquet", _set("first_seen", 99)),
        "events.parquet: first_seen = 99 for seed 0, event 0, swarm 'random', but "
        "trajectories.parquet",
    ),
    "run.json drones other than the trajectories": (
        _json("run.json", ("n_drones",), 3),
        "run.json: n_drones = 3, but trajectories.parquet has 4 drones",
    ),
    "network.json cell size other than the run's": (
        _all(
            _built_file("network.json", _network),
            _json("run.json", ("traffic", "identity", "cell_m"), 200.0),
        ),
        "network.json: grid.cell_m = 500, but run.json has traffic.identity.cell_m = 200",
    ),
    "mfd.json prior other than the run's": (
        _all(
            _built_file("mfd.json", lambda run: _mfd(used="prior", a=0.3)),
            _json("run.json", ("traffic", "mfd_prior"), [0.7, 40.0]),
        ),
        'mfd.json: a = 0.3 with used = "prior", but run.json has traffic.mfd_prior = [0.7, 40.0]',
    ),
    # a file edited to contradict the trajectories and maps the run was scored on
    "series rewards raised with their tables": (
        _shifted("random", reward=0.2, R_hat_T=0.2, R_hat_T_idleness=0.2),
        "series.parquet: reward = ",
    ),
    "series rewards named after the other swarm": (
        _swap_swarms("trajectories.parquet", "random", "greedy"),
        "swarm 'random', step 0, but trajectories.parquet and importance.npz give",
    ),
    "paper reward raised with its tables": (
        _shifted("greedy", R_hat_T_paper=0.1),
        "per_seed.csv: R_hat_T_paper = ",
    ),
    "belief error lowered with its tables": (
        _shifted("greedy", belief_error=-0.05),
        "series.parquet: belief_error = ",
    ),
    "trajectories of the other seed": (
        _edit_table("trajectories.parquet", lambda f: f.assign(seed=1 - f["seed"])),
        "random starts on this map are",  # each seed's drones start where its seed put them
    ),
    "reward split moved between its parts": (
        _shifted("greedy", R_hat_T_importance=-0.1, R_hat_T_idleness=0.1),
        "per_seed.csv: R_hat_T_importance = ",
    ),
    "event peaks raised": (
        _event_rows(lambda f: f.assign(peak=0.99)),
        "events.parquet: peak = 0.99 for seed 0, event 0, but importance.npz gives",
    ),
    "event moved to another cell": (
        _event_rows(lambda f: f.assign(i=f["i"].where(f["event"] != 0, (f["i"] + 3) % 20))),
        "events.parquet: i = ",
    ),
    "event the maps do not hold": (
        _event_rows(_extra_event),
        "events.parquet: holds a row for seed 0, event 77, which importance.npz does not give",
    ),
    "comparison of a learned swarm the run lacks": (
        _built_file("comparison.csv", lambda run: _comparison()),
        "comparison.csv: holds a row for swarm 'rl', which per_seed.csv does not give",
    ),
    "mfd.json fit quality other than its samples": (
        _all(
            _built_file("mfd.json", lambda run: _mfd()),
            _built_file("mfd_samples.parquet", _samples),
        ),
        "mfd.json: r2 = 0.5 of a = 0.7, k_c = 40, but mfd_samples.parquet gives",
    ),
}


def test_the_files_the_cases_build_read_back_whole(run_copy: Path) -> None:
    # undamaged, the files the cases above add to the run are accepted: only the damage is not
    # (degradation.csv and belief_models.csv are recomputed from a faulted or believed run's
    # files on read-back: their undamaged forms are read back in test_drone_faults.py and
    # test_belief_cli.py)
    from twin.report.load import load_run

    _built_file("events.parquet", _events)(run_copy)
    _built_file("mfd.json", lambda run: _mfd())(run_copy)
    _built_file("network.json", _network)(run_copy)
    refresh_manifest(run_copy)
    rf = load_run(run_copy)
    assert rf.network["row_0"] == "north" and rf.events is not None


@pytest.mark.parametrize("name", list(READ_BACK))
@pytest.mark.parametrize("command", ["report", "replay"])
def test_damaged_run_folder_is_one_line(name, command, run_copy: Path, capsys) -> None:
    damage, words = READ_BACK[name]
    damage(run_copy)
    if not name.startswith("manifest"):
        refresh_manifest(run_copy)
    parent = run_copy.parent
    before = tree_hash(parent, skip=run_copy)
    argv = [command, str(run_copy)] + (["--no-animation"] if command == "report" else [])
    assert main(argv) == EXIT_REFUSED
    line = one_line(capsys)
    assert not (run_copy / "report").exists()
    if command == "report":
        assert words in line
    else:  # replay reads the folder back as report does, then finds an evaluate folder's
        # run.json not replayable
        assert words in line or ("run.json" in line and "not" in line), line
    assert tree_hash(parent, skip=run_copy) == before


def _two_seeds_on_one_traffic(tmp_path: Path, capsys, traffic: str, horizon: int) -> Path:
    """``twin evaluate`` of 2 seeds of random and greedy on one traffic (``synthetic`` maps,
    or one ``tape`` replayed for both): the run folder."""
    from helpers import random_tape

    config = tmp_path / "c.toml"
    config.write_text(
        '[grid]\nnx = 8\nny = 10\n[swarm]\nn_drones = 3\n[traffic]\nkind = "synthetic"\n'
        f'horizon = {horizon}\ndisturbances = [{{ kind = "big", i = 3, j = 4, amplitude = 1.0, '
        'sigma = 2.0 }]\n[evaluate]\nswarms = ["random", "greedy"]\n'
    )
    out = tmp_path / "run"
    argv = ["evaluate", "--config", str(config), "--seeds", "2", "--out", str(out), "--quiet",
            "--no-report"]  # fmt: skip
    if traffic == "tape":
        tape = random_tape(seed=1, nx=8, ny=10, warmup=2, horizon=horizon, obstacle=(1, 1))
        tape.write(tmp_path / "tape.parquet")
        argv += ["--traffic", str(tmp_path / "tape.parquet")]
    assert main(argv) == 0, capsys.readouterr().err
    return out


@pytest.mark.parametrize("traffic", ["synthetic", "tape"])
def test_a_later_seeds_rewards_are_replayed_on_the_shared_traffic(tmp_path, capsys, traffic):
    """Seeds that share one traffic (synthetic maps, one tape): a later seed's rewards raised
    alike in series.parquet, per_seed.csv and summary.csv, its trajectories untouched, are
    refused (they replay over importance.npz as the first seed's do)."""
    from scipy import stats

    out = _two_seeds_on_one_traffic(tmp_path, capsys, traffic, horizon=30)
    assert main(["report", str(out), "--no-animation"]) == 0, capsys.readouterr().err
    shutil.rmtree(out / "report")
    series = pd.read_parquet(out / "series.parquet")
    at = (series["seed"] == 1) & (series["swarm"] == "greedy")
    series.loc[at, "reward"] += 0.05
    series.loc[at, "cumulative_reward"] = series.loc[at, "reward"].cumsum()
    series.to_parquet(out / "series.parquet")
    per_seed = pd.read_csv(out / "per_seed.csv")
    row = (per_seed["seed"] == 1) & (per_seed["swarm"] == "greedy")
    per_seed.loc[row, ["R_hat_T", "R_hat_T_idleness"]] += 0.05
    per_seed.to_csv(out / "per_seed.csv", index=False)
    summary = pd.read_csv(out / "summary.csv")
    for column in ("R_hat_T", "R_hat_T_idleness"):
        values = per_seed.loc[per_seed["swarm"] == "greedy", column].to_numpy()
        half = stats.t.ppf(0.975, len(values) - 1) * values.std(ddof=1) / np.sqrt(len(values))
        summary.loc[summary["swarm"] == "greedy", [column, column + "_ci95"]] = [
            values.mean(),
            half,
        ]
    summary.to_csv(out / "summary.csv", index=False)
    refresh_manifest(out)
    capsys.readouterr()
    assert main(["report", str(out), "--no-animation"]) == EXIT_REFUSED
    line = one_line(capsys)
    assert "series.parquet: reward = " in line and "for seed 1, swarm 'greedy'" in line, line


def forge_per_seed(out: Path, seed: int, swarm: str, column: str, delta: float) -> None:
    """Raise one seed's ``column`` of per_seed.csv by ``delta``, with summary.csv's mean and
    95% interval recomputed to agree (a consistent forgery of the per-seed table)."""
    from scipy import stats

    per_seed = pd.read_csv(out / "per_seed.csv")
    per_seed.loc[(per_seed["seed"] == seed) & (per_seed["swarm"] == swarm), column] += delta
    per_seed.to_csv(out / "per_seed.csv", index=False)
    summary = pd.read_csv(out / "summary.csv")
    values = per_seed.loc[per_seed["swarm"] == swarm, column].to_numpy()
    half = stats.t.ppf(0.975, len(values) - 1) * values.std(ddof=1) / np.sqrt(len(values))
    summary.loc[summary["swarm"] == swarm, [column, column + "_ci95"]] = [values.mean(), half]
    summary.to_csv(out / "summary.csv", index=False)


@pytest.mark.parametrize("traffic", ["synthetic", "tape"])
def test_a_later_seeds_paper_accounting_is_replayed(tmp_path, capsys, traffic):
    """A later seed's R_hat_T_paper raised in per_seed.csv and summary.csv alike is refused:
    it replays from the seed's trajectories as the first seed's does (only the first seed's
    was replayed: probe 23's f02)."""
    out = _two_seeds_on_one_traffic(tmp_path, capsys, traffic, horizon=20)
    forge_per_seed(out, 1, "random", "R_hat_T_paper", 0.05)
    refresh_manifest(out)
    capsys.readouterr()
    assert main(["report", str(out), "--no-animation"]) == EXIT_REFUSED
    line = one_line(capsys)
    assert "per_seed.csv: R_hat_T_paper = " in line and "for seed 1, swarm 'random'" in line
    assert "trajectories.parquet and importance.npz give" in line, line


def test_report_refuses_a_report_link_out_of_the_run_folder(run_copy: Path, capsys) -> None:
    outside = run_copy.parent / "outside"
    outside.mkdir()
    (run_copy / "report").symlink_to(outside)
    assert main(["report", str(run_copy), "--no-animation"]) == EXIT_REFUSED
    assert "symbolic link" in one_line(capsys)
    assert not any(outside.iterdir())


def test_report_refuses_links_inside_report_that_lead_out(run_copy: Path, capsys) -> None:
    outside = run_copy.parent / "victim.html"
    outside.write_text("keep me")
    (run_copy / "report").mkdir()
    (run_copy / "report" / "report.html").symlink_to(outside)
    assert main(["report", str(run_copy), "--no-animation"]) == EXIT_REFUSED
    assert "symbolic link" in one_line(capsys)
    assert outside.read_text() == "keep me"


def test_report_of_the_intact_copy_works(run_copy: Path, capsys) -> None:
    assert main(["report", str(run_copy), "--no-animation"]) == 0
    assert (run_copy / "report" / "report.html").is_file()


# --- output paths and the video ---------------------------------------------------------------


def test_output_checks(tmp_path: Path, monkeypatch) -> None:
    from twin import outputs

    (tmp_path / "file").write_text("")
    assert outputs.check_output_dir(tmp_path / "new" / "deeper") == tmp_path / "new" / "deeper"
    assert not (tmp_path / "new").exists()  # a check creates nothing
    with pytest.raises(UserError, match="in the way"):
        outputs.check_output_dir(tmp_path / "file")
    with pytest.raises(UserError, match="is a file"):
        outputs.check_output_file(tmp_path / "file" / "video.mp4", "--record")
    with pytest.raises(UserError, match="is a folder"):
        outputs.check_output_file(tmp_path, "--record")
    with pytest.raises(UserError, match=r"--record .*not valid UTF-8"):
        outputs.check_output_file(os.fsdecode(b"video\xff.mp4"), "--record")
    monkeypatch.setattr(outputs.shutil, "disk_usage", lambda p: shutil._ntuple_diskusage(1, 1, 0))
    with pytest.raises(UserError, match="MB free"):
        outputs.check_output_dir(tmp_path / "run", need_mb=10)
    monkeypatch.setattr(outputs, "_read_only", lambda p: True)
    with pytest.raises(UserError, match="read-only"):
        outputs.check_output_dir(tmp_path / "run")


@pytest.mark.parametrize(
    "exc",
    [
        UserError("--record v.mp4: no frame was recorded"),
        OSError(errno.ENOSPC, "No space left on device", "v.mp4"),
        RuntimeError("ffmpeg crashed"),
    ],
)
def test_a_failed_video_costs_only_the_video(exc, tmp_path: Path, monkeypatch, capsys) -> None:
    from twin.cli.run import finish_video

    monkeypatch.setenv("TWIN_CACHE_DIR", str(tmp_path / "cache"))

    class Drawer:
        def finish(self):
            raise exc

    assert finish_video(Drawer(), tmp_path) is False
    line = one_line(capsys)
    assert line.startswith("twin: warning:") and "results are written" in line


def test_huge_grid_is_refused_before_allocation() -> None:
    from twin.resources import check_cell_size, check_grid_size

    with pytest.raises(UserError, match="cells"):
        check_grid_size(100_000, 100_000, "x", "fix")
    for bad in (0, -5, float("nan"), 1e9, "abc"):
        with pytest.raises(UserError, match="cell size"):
            check_cell_size(bad, "--cell-m")


# --- clock, executors, envs ------------------------------------------------------------------


@pytest.mark.parametrize(
    ("t", "seconds", "label"),
    [
        (0, True, "00:00:00"),
        (86399, True, "23:59:59"),
        (86400 + 2 * 3600 + 15 * 60, False, "1d 02:15"),
        (3 * 86400 + 5, True, "3d 00:00:05"),
    ],
)
def test_clock_labels_show_days(t, seconds, label) -> None:
    from twin.clock import clock_label

    assert clock_label(t, seconds) == label


@given(st.integers(0, 999 * 86400 + 86399), st.booleans())
def test_clock_labels_read_back_as_written(t, seconds) -> None:
    """Every label twin writes (run.json's begin past midnight of a later day too) reads back."""
    from twin.clock import clock_label, clock_seconds

    back = clock_seconds(clock_label(t, seconds))
    assert back == (t if seconds else t - t % 60)


@pytest.mark.parametrize("text", ["", "7", "07:60", "1d", "d 07:00", "-1d 07:00", "07:00:61"])
def test_text_that_is_not_a_clock_time_is_refused(text) -> None:
    from twin.clock import parse_clock

    with pytest.raises(UserError, match="must be a clock time"):
        parse_clock(text, "--begin")


def test_ray_address_that_does_not_answer_fails_fast() -> None:
    from twin.executors import _probe_address

    start = time.monotonic()
    with pytest.raises(UserError, match=r"Ray address 127\.0\.0\.1:1"):
        _probe_address("127.0.0.1:1", timeout=2)
    with pytest.raises(UserError, match="Ray address"):
        _probe_address("ray://127.0.0.1:1", timeout=1)
    assert time.monotonic() - start < 60


@pytest.mark.parametrize("port", ["0", "65536", "99999999999999999999", "-1", "", "x", "²"])
def test_a_ray_address_with_no_tcp_port_is_said_so(port) -> None:
    """Port 65536 was reported as "connection refused", -1 waited 40 s for a cluster and an
    empty one got Ray's own error (probe 20's c48, P2-c48a)."""
    from twin.executors import _probe_address

    with pytest.raises(UserError, match=rf"Ray address 127\.0\.0\.1:{port}: port '{port}' is no"):
        _probe_address(f"127.0.0.1:{port}", timeout=1)


def _listen(answer: bytes | None) -> tuple[int, Callable[[], None]]:
    """A TCP listener on a free local port that sends ``answer`` to each connection (None:
    says nothing); its port and a function that stops it."""
    import socket
    import threading

    server = socket.create_server(("127.0.0.1", 0))
    server.settimeout(0.2)
    stop = threading.Event()
    held = []

    def serve() -> None:
        while not stop.is_set():
            try:
                conn, _ = server.accept()
            except OSError:
                continue
            held.append(conn)
            if answer == b"":
                conn.close()
            elif answer is not None:
                conn.sendall(answer)

    thread = threading.Thread(target=serve, daemon=True)
    thread.start()

    def close() -> None:
        stop.set()
        thread.join(5)
        for conn in held:
            conn.close()
        server.close()

    return server.getsockname()[1], close


#: what listens on a Ray address -> its first bytes (None: nothing), words of the refusal
NOT_RAY = {
    "a silent listener": (None, "it said nothing within 2 s, not gRPC"),
    "a web server": (b"HTTP/1.0 400 Bad Request\r\n\r\n", "answered 'HTTP/1.0 400 Bad Request'"),
    "an HTML page": (b"<!DOCTYPE HTML>\n<html>", "answered '<!DOCTYPE HTML>'"),
    "a listener that hangs up": (b"", "it closed the connection, not gRPC"),
}


@pytest.mark.parametrize("name", list(NOT_RAY))
def test_an_address_where_no_ray_listens_is_one_line(name, tmp_path, capfd, monkeypatch) -> None:
    """Refused before ``ray.init`` (whose C++ log lines would surround twin's): the address,
    what answered, and where the right address is found."""
    pytest.importorskip("ray", reason="Ray not installed (pip install 'twin[ray]')")
    from twin import executors

    monkeypatch.setattr(executors, "RAY_PROBE_S", 2.0)
    monkeypatch.setenv("TWIN_CACHE_DIR", str(tmp_path / "cache"))
    answer, words = NOT_RAY[name]
    port, close = _listen(answer)
    out = tmp_path / "sweep"
    argv = ["sweep", "--config", "sweep-demo", "--executor", "ray", "--quiet", "--no-report"]
    before = tree_hash(tmp_path, skip=out)
    try:
        assert main([*argv, "--address", f"127.0.0.1:{port}", "--out", str(out)]) == EXIT_REFUSED
    finally:
        close()
    err = capfd.readouterr().err
    lines = err.strip().splitlines()
    assert len(lines) == 1 and "Traceback" not in err, err
    assert f"Ray address 127.0.0.1:{port}: something listens there but it is not a Ray" in err
    assert words in err and "ray status" in err
    assert tree_hash(tmp_path, skip=out) == before


def test_what_ray_prints_while_joining_goes_to_a_log(tmp_path, capfd, monkeypatch) -> None:
    """Ray's C++ core writes its retries straight to file descriptor 2: while twin joins a
    cluster they go to the cache's log, and the refusal is the one line on stderr, naming it
    (and the token a cluster with token authentication wants)."""
    from twin import executors

    class NoisyRay:
        def init(self, **kwargs):
            for _ in range(3):
                os.write(2, b"[W gcs_client.cc:210] Unauthenticated: InvalidAuthToken\n")
            raise ConnectionError("Failed to connect to Ray cluster at 10.0.0.1:6379")

    monkeypatch.setenv("TWIN_CACHE_DIR", str(tmp_path / "cache"))
    monkeypatch.setattr(executors, "_probe_address", lambda address: None)
    assert run_command(lambda a: executors._connect_ray(NoisyRay(), "10.0.0.1:6379"), None) == 2
    err = capfd.readouterr().err
    assert len(err.strip().splitlines()) == 1 and "gcs_client" not in err, err
    log = tmp_path / "cache" / executors.RAY_LOG_NAME
    assert f"(Ray's log: {log})" in err and "RAY_AUTH_MODE=token" in err
    assert log.read_text().count("InvalidAuthToken") == 3
    os.write(2, b"after\n")  # stderr is the terminal's again
    assert capfd.readouterr().err == "after\n"


@pytest.fixture(scope="module")
def env():
    pytest.importorskip("pettingzoo")
    from twin.env import SwarmParallelEnv
    from twin.grid import Grid
    from twin.traffic.base import RecordedTraffic

    obstacles = np.zeros((4, 5), bool)
    obstacles[3, 4] = True
    maps = np.random.default_rng(0).uniform(0, 1, (6, 4, 5))
    source = RecordedTraffic(Grid(obstacles), maps)
    return SwarmParallelEnv, source


@pytest.mark.parametrize(
    ("starts", "words"),
    [
        ([[0.5, 1]], "whole numbers"),
        ([[9, 9]], "off the 4 x 5 grid"),
        ([[3, 4]], "obstacle"),
        ([["a", 1]], "cells"),
        ([[0, 0], [0, 0]], "two drones"),
        ([[True, False], [0, 2]], "not True/False"),  # it started a drone at (1, 0)
        (np.array([[1, 0], [0, 1]], dtype=bool), "not True/False"),
    ],
)
def test_env_refuses_bad_starts(env, starts, words) -> None:
    cls, source = env
    with pytest.raises(UserError, match=words):
        cls(source, starts=starts)


@pytest.mark.parametrize(
    ("actions", "words"),
    [
        ({"drone_0": 0, "drone_7": 0}, "not a live agent"),
        ({"drone_0": 1.5}, "whole number"),
        ({"drone_0": "up"}, "whole number"),
        ({"drone_0": 9}, "out of range"),
        ({"drone_0": -1}, "out of range"),
        ([0], "dict"),
    ],
)
def test_env_refuses_bad_actions(env, actions, words) -> None:
    cls, source = env
    e = cls(source, starts=[[1, 1]])
    e.reset(seed=0)
    with pytest.raises(UserError, match=words):
        e.step(actions)
    with pytest.raises(UserError, match="not one of this env's agents"):
        e.action_space("drone_3")


def test_gym_env_refuses_bad_joint_actions(env) -> None:
    from twin.env import SwarmGymEnv

    _, source = env
    e = SwarmGymEnv(source, starts=[[1, 1], [2, 2]])
    e.reset(seed=0)
    for bad in ([0], [0.5, 0], [1.0, 0], np.array([0.0, 0.0]), ["a", "b"], [[0, 0]]):
        with pytest.raises(UserError, match="whole numbers"):
            e.step(bad)
    e.step(np.array([0, 0]))
    e.step([0, 0])


@pytest.mark.parametrize(
    ("options", "words"),
    [
        ({"n_drones": 2.5}, "n_drones = 2.5 is not a whole number"),
        ({"n_drones": 2.0}, "n_drones = 2.0 is not a whole number"),
        ({"n_drones": True}, "n_drones = True is not a whole number"),
        ({"n_drones": "3"}, "n_drones = '3' is not a whole number"),
        ({"n_drones": None}, "n_drones = None"),
        ({"n_drones": 0}, "need 1 .. 19 drones"),
        ({"n_drones": 601}, "need 1 .. 19 drones"),
        ({"starts": [[1e20, 1], [0, 0]]}, r"starts\[0\] = \(1e\+20, 1\) is off"),
        ({"starts": [[-1e30, 1]]}, "is off the 4 x 5 grid"),
        ({"starts": [[0, 0], [1, 1]], "n_drones": 4}, "n_drones = 4 but starts gives 2 cells"),
    ],
)
@pytest.mark.parametrize("joint", [False, True])
def test_env_refuses_bad_options(env, options, words, joint) -> None:
    import warnings

    from twin.env import EnvInputError, SwarmGymEnv

    cls, source = env
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # no numpy warning on the way
        with pytest.raises(EnvInputError, match=words) as info:
            (SwarmGymEnv if joint else cls)(source, **options)
    assert "\n" not in str(info.value)


@pytest.mark.parametrize(
    ("seed", "words"),
    [
        ("abc", "seed = 'abc' is not a whole number"),
        (-1, "seed = -1 is negative"),
        (1.5, "1.5"),
        (True, "seed = True is not a whole number"),
        ([3], r"seed = \[3\] is not a whole number"),
    ],
)
@pytest.mark.parametrize("joint", [False, True])
def test_env_refuses_bad_reset_seeds(env, seed, words, joint) -> None:
    from twin.env import EnvInputError, SwarmGymEnv

    cls, source = env
    e = (SwarmGymEnv if joint else cls)(source, n_drones=2)
    with pytest.raises(EnvInputError, match=words):
        e.reset(seed=seed)
    e.reset(seed=np.int64(3))


def _steps(e, joint: bool, n: int) -> None:
    for _ in range(n):
        e.step([0, 0] if joint else {"drone_0": 0, "drone_1": 0})


# a call out of order -> what is done before it, the call, words of the one-line error
CALL_ORDER = {
    "step before reset": (lambda e, joint: None, "step", "step() before reset(): call env.reset"),
    "step after the episode": (
        lambda e, joint: (e.reset(seed=0), _steps(e, joint, 5)),
        "step",
        "step() after the episode ended (truncated after 5 steps): call env.reset() to start",
    ),
    "step after close": (lambda e, joint: (e.reset(seed=0), e.close()), "step", "after close()"),
    "reset after close": (lambda e, joint: e.close(), "reset", "reset() after close(): the env"),
}


@pytest.mark.parametrize("name", list(CALL_ORDER))
@pytest.mark.parametrize("joint", [False, True])
def test_env_calls_out_of_order_say_what_to_call_first(env, name, joint) -> None:
    """twin's error (a UserError, also Gymnasium's ResetNeeded and a RuntimeError, as
    PettingZoo and Gymnasium users catch), one line, not a bare RuntimeError; the env works
    again after reset() unless closed."""
    from gymnasium.error import ResetNeeded

    from twin.env import EnvCallOrderError, SwarmGymEnv

    cls, source = env
    e = (SwarmGymEnv if joint else cls)(source, n_drones=2)
    before, call, words = CALL_ORDER[name]
    before(e, joint)
    with pytest.raises(EnvCallOrderError, match=re.escape(words)) as info:
        e.step([0, 0] if joint else {"drone_0": 0, "drone_1": 0}) if call == "step" else e.reset()
    assert all(isinstance(info.value, kind) for kind in (UserError, ResetNeeded, RuntimeError))
    assert "\n" not in str(info.value)
    if "close" not in name:
        e.reset(seed=1)
        _steps(e, joint, 1)
    e.close()
    e.close()  # twice: nothing happens


def test_error_log_never_follows_a_link(tmp_path: Path, monkeypatch) -> None:
    from twin import boundary

    monkeypatch.setenv("TWIN_CACHE_DIR", str(tmp_path / "cache"))
    target = tmp_path / "elsewhere"
    target.mkdir()
    link = tmp_path / "run"
    link.symlink_to(target)
    boundary.set_run_folder(link)
    try:
        log = boundary.log_traceback(RuntimeError("x"))
    finally:
        boundary.set_run_folder(None)
    assert log == tmp_path / "cache" / LOG_NAME
    assert not any(target.iterdir())
    assert os.path.getsize(log) > 0


def test_an_error_log_that_is_a_link_is_not_written_through(tmp_path: Path, monkeypatch) -> None:
    """A run folder's error.log that links to a user's file outside it: the traceback goes to
    the cache's log, and the user's file is left as it was."""
    from twin import boundary

    monkeypatch.setenv("TWIN_CACHE_DIR", str(tmp_path / "cache"))
    run = tmp_path / "run"
    run.mkdir()
    precious = tmp_path / "precious.txt"
    precious.write_text("the user's own words\n")
    (run / LOG_NAME).symlink_to(precious)
    boundary.set_run_folder(run)
    try:
        log = boundary.log_traceback(RuntimeError("x"))
    finally:
        boundary.set_run_folder(None)
    assert log == tmp_path / "cache" / LOG_NAME
    assert precious.read_text() == "the user's own words\n"


def test_disk_full_while_writing_is_one_line_and_the_rerun_replaces_it(
    tmp_path: Path, monkeypatch, capsys
) -> None:
    import twin.runs

    real = twin.runs.atomic_write

    def full(path, write):
        if Path(path).name == "trajectories.parquet":
            raise OSError(errno.ENOSPC, "No space left on device", str(path))
        return real(path, write)

    config, out = small_config(tmp_path), tmp_path / "run"
    argv = ["evaluate", "--config", str(config), "--swarms", "random", "--out", str(out)]
    argv += ["--no-report", "--quiet"]
    monkeypatch.setattr(twin.runs, "atomic_write", full)
    before = tree_hash(tmp_path, skip=out)
    assert main(argv) == EXIT_REFUSED
    line = one_line(capsys)
    assert "trajectories.parquet" in line and "free some space" in line
    assert not (out / "manifest.json").exists()  # an incomplete folder says so
    assert tree_hash(tmp_path, skip=out) == before
    monkeypatch.setattr(twin.runs, "atomic_write", real)
    assert main(argv) == 0  # the same command replaces its partial folder
    assert (out / "manifest.json").is_file()


def test_the_guides_run_folder_table_names_every_run_file() -> None:
    """docs/guide.md's table of a run folder and the schema in twin/runs.py name the same files
    (``tapes/seed-<s>.parquet`` counts as ``tapes``); ``report/`` is the report's own folder."""
    import re

    from twin.runs import RUN_FILE_NAMES

    guide = (Path(__file__).parents[1] / "docs" / "guide.md").read_text()
    section = guide[guide.index("## Run folders") :]
    section = section[: section.index("\n## ", 3)]
    rows = [line for line in section.splitlines() if line.startswith("| `")]
    named = {
        name.split("/")[0] for row in rows for name in re.findall(r"`([^`]+)`", row.split(" | ")[0])
    }
    assert named == RUN_FILE_NAMES - {"report"}


def _notices_then(outcome):
    """A command that holds its notices, says two, then ``outcome`` ("start": the simulation
    starts, then it ends well; an exception: it is refused before the start)."""
    from twin.boundary import hold_notices, notify, release_notices

    def command(args):
        hold_notices()
        notify("twin: notice: first")
        notify("SUMO: second")
        if isinstance(outcome, BaseException):
            raise outcome
        if outcome == "start":
            release_notices()
        print("results", file=sys.stderr)
        return 0

    return command


# name -> (outcome, exit code, stderr lines)
HELD_NOTICES = {
    "started": ("start", 0, ["twin: notice: first", "SUMO: second", "results"]),
    "ended before a start": ("end", 0, ["results", "twin: notice: first", "SUMO: second"]),
    "refused": (UserError("x.rou.xml: SUMO refuses it"), EXIT_REFUSED,
                ["twin: error: x.rou.xml: SUMO refuses it"]),
    "system error": (OSError(errno.ENOSPC, "No space left on device", "r/x"), EXIT_REFUSED,
                     None),
}  # fmt: skip


@pytest.mark.parametrize("case", list(HELD_NOTICES))
def test_held_notices_print_after_the_start_and_vanish_on_a_refusal(case, capsys) -> None:
    outcome, code, lines = HELD_NOTICES[case]
    assert run_command(_notices_then(outcome), None) == code
    err = capsys.readouterr().err.splitlines()
    if lines is None:
        assert len(err) == 1 and err[0].startswith("twin: error: r/x: No space"), err
    else:
        assert err == lines
    from twin.boundary import notify

    notify("twin: notice: after")  # no command holds them any more
    assert capsys.readouterr().err == "twin: notice: after\n"


def test_a_notice_of_writing_is_held_behind_a_refusal_and_printed_after_success(
    tmp_path: Path, monkeypatch, capsys
) -> None:
    """The bound left out (too large a DP) is noticed while the run folder is written: a full
    disk after it is one line; a run that ends well prints the notice after its results."""
    import twin.ceilings
    import twin.runs

    monkeypatch.setattr(twin.ceilings, "MAX_DP_BYTES", 0)
    real = twin.runs.atomic_write

    def full(path, write):
        if Path(path).name == "trajectories.parquet":
            raise OSError(errno.ENOSPC, "No space left on device", str(path))
        return real(path, write)

    config, out = small_config(tmp_path), tmp_path / "run"
    argv = ["evaluate", "--config", str(config), "--swarms", "random", "--out", str(out)]
    argv += ["--no-report", "--quiet"]
    monkeypatch.setattr(twin.runs, "atomic_write", full)
    assert main(argv) == EXIT_REFUSED
    assert "No space left on device" in one_line(capsys)
    monkeypatch.setattr(twin.runs, "atomic_write", real)
    assert main(argv) == 0
    err = capsys.readouterr().err.splitlines()
    assert err == [next(line for line in err if "bound (ceiling) left out" in line)], err


def test_a_cache_rebuild_notice_is_held_behind_a_refusal(tmp_path: Path, capsys) -> None:
    from twin.boundary import hold_notices
    from twin.resources import BrokenEntry, build_once

    target = tmp_path / "entry"
    target.mkdir()  # an entry whose file went missing

    def verify(folder: Path) -> None:
        if not (folder / "data.txt").is_file():
            raise BrokenEntry("data.txt is missing")

    def command(args) -> int:
        hold_notices()  # as twin run, evaluate, sweep and pretrain do
        build_once(target, lambda folder: (folder / "data.txt").write_text("x"), verify=verify)
        raise UserError("x.toml: refused after the cache was rebuilt")

    assert run_command(command, None) == EXIT_REFUSED
    assert one_line(capsys) == "twin: error: x.toml: refused after the cache was rebuilt"
    assert (target / "data.txt").read_text() == "x"  # rebuilt all the same
    target.joinpath("data.txt").unlink()
    assert run_command(lambda args: build_once(target, lambda f: None, verify=verify) and 0, None)
    assert "cache entry" in capsys.readouterr().err


def test_a_sweep_cell_that_fails_leaves_no_notice_to_the_next(monkeypatch, capsys) -> None:
    """A worker runs cell after cell: a failed cell's held notices never go with the next; a
    good cell's go back with its record (the sweep says each once, whichever cells said it)."""
    import twin.sweep.cells as cells
    from twin.boundary import notify, release_notices

    def failing(cell):
        notify("twin: notice: of the failed cell")
        raise UserError("the failed cell's error")

    def starting(cell):
        notify("twin: notice: of the good cell")
        release_notices()  # its simulation starts
        return {"id": cell["id"]}

    monkeypatch.setattr(cells, "_run_cell", failing)
    with pytest.raises(UserError):
        cells.run_cell({"id": "a"})
    monkeypatch.setattr(cells, "_run_cell", starting)
    assert cells.run_cell({"id": "b"}) == {"id": "b", "notices": ["twin: notice: of the good cell"]}
    assert capsys.readouterr().err == ""


def test_a_write_into_a_missing_folder_names_the_file_not_a_temporary_one(tmp_path: Path) -> None:
    from twin.files import atomic_write, staged_folder

    target = tmp_path / "gone" / "h.npz"
    with pytest.raises(FileNotFoundError) as raised:
        atomic_write(target, lambda p: p.write_text("x"))
    assert raised.value.filename == str(target)
    with (
        pytest.raises(FileNotFoundError) as raised,
        staged_folder(tmp_path / "gone" / "report", lambda name: False),
    ):
        pass
    assert raised.value.filename == str(tmp_path / "gone" / "report")
    assert not (tmp_path / "gone").exists()


def test_a_notice_said_again_by_the_next_seed_is_printed_once(capsys) -> None:
    """Each seed's scenario says the same notices: the command prints each once."""
    from twin.boundary import notify

    def command(args) -> int:
        for _seed in range(3):
            notify("twin: notice: the run ends past the last departure")
            notify("SUMO: small.net.xml (seed 0)")
        notify("twin: notice: another")
        return 0

    assert run_command(command, None) == 0
    assert capsys.readouterr().err.splitlines() == [
        "twin: notice: the run ends past the last departure",
        "SUMO: small.net.xml (seed 0)",
        "twin: notice: another",
    ]
    assert run_command(command, None) == 0  # the next command says them again
    assert len(capsys.readouterr().err.splitlines()) == 3


@contextlib.contextmanager
def _held_by_another(folder: Path):
    """``folder`` claimed by another process (:func:`twin.boundary.claim_run_folder`) while
    the block runs."""
    import subprocess

    holder = subprocess.Popen(
        [sys.executable, "-c",
         "import sys, time; from twin.boundary import claim_run_folder; "
         "claim_run_folder(sys.argv[1]); print('held', flush=True); time.sleep(120)",
         str(folder)],
        stdout=subprocess.PIPE, text=True,
    )  # fmt: skip
    try:
        assert holder.stdout.readline().strip() == "held"
        yield
    finally:
        holder.kill()
        holder.wait()


@pytest.mark.parametrize(
    "argv",
    [["pretrain"], ["sweep", "--config", "sweep-demo", "--no-report"], ["transfer"]],
    ids=["pretrain", "sweep", "transfer"],
)
def test_a_folder_another_command_writes_is_refused_by_every_command(tmp_path, capsys, argv):
    """Two `twin pretrain`s into one folder at once both ran, each epoch logged twice and the
    model of whichever wrote last (probe 26's f04); sweeps and transfers alike: the second is
    refused in one line and writes nothing."""
    out = tmp_path / "out"
    out.mkdir()
    with _held_by_another(out):
        assert main([*argv, "--out", str(out), "--quiet"]) == EXIT_REFUSED
        line = one_line(capsys)
        assert f"--out {out}: another twin command is writing into this folder now" in line
        assert list(out.iterdir()) == []


@pytest.mark.parametrize(
    "argv",
    [["evaluate"], ["pretrain"], ["sweep", "--config", "sweep-demo"], ["transfer"]],
    ids=["evaluate", "pretrain", "sweep", "transfer"],
)
def test_a_users_folder_is_refused_as_not_the_commands_before_its_links(tmp_path, capsys, argv):
    """A user's project folder (a venv's link to its python in it) given as --out was refused
    for the link, advising to remove it, after walking its whole tree (probe 26's f05): it is
    refused as a folder the command did not write, untouched."""
    if argv == ["evaluate"]:
        argv = ["evaluate", "--config", str(small_config(tmp_path, horizon=3))]
    out = tmp_path / "project"
    (out / "venv" / "bin").mkdir(parents=True)
    (out / "venv" / "bin" / "python3").symlink_to(sys.executable)
    (out / "notes.txt").write_text("mine")
    before = tree_hash(out)
    assert main([*argv, "--out", str(out), "--quiet"]) == EXIT_REFUSED
    line = one_line(capsys)
    assert line.startswith(f"twin: error: --out {out}: ") and "symbolic link" not in line, line
    assert "notes.txt" in line or "holds no twin run" in line, line
    assert tree_hash(out) == before


def test_the_root_folder_as_out_is_refused_naming_out(capsys):
    """``--out /`` walked the whole disk and ended on /proc's "Permission denied", naming
    neither --out nor the cause (probe 26's f05)."""
    assert main(["evaluate", "--config", "synthetic", "--out", "/", "--quiet"]) == EXIT_REFUSED
    line = one_line(capsys)
    assert line.startswith("twin: error: --out /: ") and "Permission" not in line, line


@pytest.mark.parametrize("where", ["imported/entry/myrun", "."])
def test_an_out_folder_in_the_cache_is_refused(tmp_path, capsys, where):
    """An --out inside twin's cache was accepted, and deleted without a word with the entry it
    lay in when a later run found that entry damaged (probe 26's f03)."""
    from twin.resources import cache_dir

    out = cache_dir() / where
    cfg = small_config(tmp_path, horizon=3)
    argv = ["evaluate", "--config", str(cfg), "--seeds", "1", "--swarms", "random"]
    assert main([*argv, "--out", str(out), "--no-report", "--quiet"]) == EXIT_REFUSED
    line = one_line(capsys)
    assert f"--out {out}: lies in twin's cache" in line and "outside it" in line, line
    assert not (cache_dir() / "imported" / "entry").exists()


@pytest.mark.parametrize("command", ["evaluate", "run"])
def test_an_out_folder_holding_the_cache_is_refused_naming_it(
    tmp_path, capsys, monkeypatch, command
):
    """$TWIN_CACHE_DIR inside a new --out: twin made its cache there, then refused the folder
    "not empty and holds no twin run", which the user had passed new (probe 28's n02)."""
    out = tmp_path / "newrun"
    monkeypatch.setenv("TWIN_CACHE_DIR", str(out / "cache"))
    cfg = small_config(tmp_path, horizon=3)
    argv = [command, "--config", str(cfg), "--seeds", "1", "--swarms", "random"]
    if command == "run":  # a live run makes its scratch folder in the cache first
        from helpers import small_sumo_scenario

        (tmp_path / "small").mkdir()
        scenario = small_sumo_scenario(tmp_path / "small", horizon=3)
        argv = [command, "--config", str(scenario / "small.toml"), "--swarms", "random"]
    assert main([*argv, "--out", str(out), "--no-report", "--quiet"]) == EXIT_REFUSED
    line = one_line(capsys)
    assert f"--out {out}: holds twin's cache ({out / 'cache'})" in line, line
    assert "$TWIN_CACHE_DIR" in line


def test_a_work_folder_beside_the_caches_own_folders_is_the_users(tmp_path, capsys, monkeypatch):
    """A cache that is a whole scratch disk (``$TWIN_CACHE_DIR=$SCRATCH``, the work in
    ``$SCRATCH/project``) refuses no run there: only the cache itself and its own folders
    are refused (the review of probe 26's fixes)."""
    cfg = small_config(tmp_path, horizon=3)
    monkeypatch.setenv("TWIN_CACHE_DIR", str(tmp_path))
    (tmp_path / "project").mkdir()
    monkeypatch.chdir(tmp_path / "project")
    argv = ["evaluate", "--config", str(cfg), "--seeds", "1", "--swarms", "random"]
    assert main([*argv, "--no-report", "--quiet"]) == 0, capsys.readouterr().err
    assert len(list((tmp_path / "project" / "runs").iterdir())) == 1


def test_a_pretraining_folder_of_the_config_in_use_says_where_to_give_another(
    tmp_path, capsys, monkeypatch
):
    """The folder of the config's ``out`` held by another command: the fix names the key and
    the file (it read "pass another configs/pretrain.toml: out": the review of probe 26's)."""
    monkeypatch.chdir(tmp_path)
    out = tmp_path / "runs" / "pretrain"
    out.mkdir(parents=True)
    with _held_by_another(out):
        assert main(["pretrain", "--quiet"]) == EXIT_REFUSED
        line = one_line(capsys)
    assert "another twin command is writing into this folder now" in line, line
    assert line.endswith(
        "wait for it to end or give another out in configs/pretrain.toml, or --out"
    )
    assert list(out.iterdir()) == []


def test_a_file_system_without_flock_locks_nothing_and_runs(tmp_path, monkeypatch):
    """Some network disks refuse ``flock`` (ENOLCK): the folder is not locked, the command
    runs (it was an internal error; the final review of probe 26's fixes)."""
    import errno
    import fcntl

    from twin.boundary import _state, claim_run_folder

    def no_flock(fd, operation):
        raise OSError(errno.ENOLCK, "No locks available")

    monkeypatch.setattr(fcntl, "flock", no_flock)
    claim_run_folder(tmp_path)
    assert tmp_path.resolve() not in _state["locks"]


def test_a_run_folder_being_written_is_read_as_such_not_as_interrupted(tmp_path, capsys):
    """`twin report` (and every reader) of a folder another command is writing now says so,
    instead of calling it interrupted and advising a rerun the lock would refuse (probe 17's
    P2-08); once the writer has ended, the folder reads as interrupted."""
    out = tmp_path / "run"
    out.mkdir()
    (out / "run.json").write_text('{"partial": true}')
    with _held_by_another(out):
        assert main(["report", str(out), "--no-animation"]) == EXIT_REFUSED
        line = one_line(capsys)
        assert "another twin command is writing into this folder now; wait for it" in line
    assert main(["report", str(out), "--no-animation"]) == EXIT_REFUSED
    assert "incomplete run folder" in one_line(capsys)


def test_a_run_folder_in_use_by_another_command_is_refused(tmp_path: Path, capsys) -> None:
    """Two commands writing into one --out at once would mix their files: while one holds
    the folder (another process), the second is refused in one line and writes nothing; once
    the first has ended, the folder is free again."""
    out = tmp_path / "run"
    out.mkdir()
    with _held_by_another(out):
        cfg = small_config(tmp_path, horizon=3)
        args = ["evaluate", "--config", str(cfg), "--seeds", "1", "--swarms", "random"]
        assert main([*args, "--out", str(out), "--no-report", "--quiet"]) == EXIT_REFUSED
        err = capsys.readouterr().err.strip()
        assert "\n" not in err and "Traceback" not in err
        assert "another twin command is writing into this folder now" in err
        assert list(out.iterdir()) == []
    assert main([*args, "--out", str(out), "--no-report", "--quiet"]) == 0
    assert (out / "manifest.json").is_file()


UNUSABLE_CACHES = {
    "a file": ("cachefile", "twin's cache ($TWIN_CACHE_DIR"),
    "under a file": ("cachefile/sub", "twin's cache ($TWIN_CACHE_DIR"),
    # Path.expanduser's RuntimeError was an internal error (the review of probe 26)
    "no such user's home": ("~no-such-user-of-twin/c", "'~' names no home folder"),
}


@pytest.mark.parametrize("cache", UNUSABLE_CACHES)
def test_an_unusable_cache_is_refused_before_a_report_is_drawn(
    tmp_path, capsys, monkeypatch, cache
):
    """The report's figures keep their font cache in twin's cache: a file in its place is one
    line before the run (never matplotlib's own warnings after it); without a report the run
    needs no cache."""
    where, words = UNUSABLE_CACHES[cache]
    blocker = tmp_path / "cachefile"
    blocker.write_text("")
    monkeypatch.setenv("TWIN_CACHE_DIR", where if where.startswith("~") else str(tmp_path / where))
    config = str(small_config(tmp_path))
    out = tmp_path / "run"
    assert main(["evaluate", "--config", config, "--out", str(out), "--quiet"]) == EXIT_REFUSED
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0 and words in err, err
    assert "matplotlib" not in err.lower() and not out.exists()
    assert main(["evaluate", "--config", config, "--out", str(out), "--quiet", "--no-report"]) == 0
    capsys.readouterr()
    assert main(["report", str(out)]) == EXIT_REFUSED
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0 and words in err, err
    assert not (out / "report").exists()


def test_a_figure_rounded_on_a_save_is_shown_apart_from_the_one_it_contradicts(run_copy, capsys):
    """per_seed.csv rounded to 6 decimals (a spreadsheet's save) is refused, and the line shows
    the two figures with the digits that tell them apart."""
    _edit_table("per_seed.csv", lambda f: f.round(6))(run_copy)
    refresh_manifest(run_copy)
    assert main(["report", str(run_copy), "--no-animation"]) == EXIT_REFUSED
    line = one_line(capsys)
    have, want = re.search(r" = (\S+) for .*, but .* gives (\S+);", line).groups()
    assert have != want and float(have) != float(want), line


def test_a_folder_of_an_earlier_format_reads_back_with_a_notice(run_copy, capsys):
    """A folder an earlier twin wrote (no folder_format: format 1, no bound.npz) reads back,
    saying what it cannot replay; a format later than this twin's is refused."""
    import json

    from twin.runs import FOLDER_FORMAT

    meta = json.loads((run_copy / "run.json").read_text())
    assert meta["folder_format"] == FOLDER_FORMAT
    (run_copy / "bound.npz").unlink()
    (run_copy / "oracle.parquet").unlink()
    as_format_3_wrote(run_copy)
    del meta["folder_format"], meta["starts"]
    (run_copy / "run.json").write_text(json.dumps(meta))
    refresh_manifest(run_copy)
    assert main(["report", str(run_copy), "--no-animation"]) == 0
    err = capsys.readouterr().err
    assert "written by an earlier twin (folder format 1)" in err, err
    # a later folder relabelled: what its format did not have gives it away (probe 18's f13)
    (run_copy / "run.json").write_text(json.dumps({**meta, "folder_format": 1}))
    refresh_manifest(run_copy)
    assert main(["report", str(run_copy), "--no-animation"]) == EXIT_REFUSED
    assert "folder_format = 1, but the folder holds folder_format" in one_line(capsys)
    # folders written between recording starts and folder_format have starts and no format
    (run_copy / "run.json").write_text(json.dumps({**meta, "starts": "random"}))
    refresh_manifest(run_copy)
    assert main(["report", str(run_copy), "--no-animation"]) == 0, capsys.readouterr().err
    capsys.readouterr()
    (run_copy / "oracle.parquet").write_bytes(b"")
    (run_copy / "run.json").write_text(json.dumps(meta))
    refresh_manifest(run_copy)
    assert main(["report", str(run_copy), "--no-animation"]) == EXIT_REFUSED
    assert "no folder_format (format 1), but the folder holds oracle.parquet" in one_line(capsys)
    (run_copy / "oracle.parquet").unlink()
    # the oracle row of a folder of format 1 is not replayed, but its parts still sum to it
    (run_copy / "run.json").write_text(json.dumps(meta))
    _ceiling_scaled("oracle (ceiling)", 1.5)(run_copy)
    refresh_manifest(run_copy)
    assert main(["report", str(run_copy), "--no-animation"]) == EXIT_REFUSED
    assert "swarm 'oracle (ceiling)', but its reward split gives" in one_line(capsys)
    _ceiling_scaled("oracle (ceiling)", 1 / 1.5)(run_copy)
    (run_copy / "oracle.parquet").write_bytes(b"")
    (run_copy / "run.json").write_text(json.dumps({**meta, "folder_format": 2}))
    refresh_manifest(run_copy)
    assert main(["report", str(run_copy), "--no-animation"]) == EXIT_REFUSED
    assert "folder_format = 2, but the folder holds oracle.parquet" in one_line(capsys)
    (run_copy / "oracle.parquet").unlink()
    meta["folder_format"] = FOLDER_FORMAT + 1
    (run_copy / "run.json").write_text(json.dumps(meta))
    refresh_manifest(run_copy)
    assert main(["report", str(run_copy), "--no-animation"]) == EXIT_REFUSED
    line = one_line(capsys)
    assert f"a run folder of format {FOLDER_FORMAT + 1}, written by a later twin" in line


GOOD_POLICY = {
    "checkpoint": "qnet.pt",
    "sha256": "ab" * 32,
    "trained_epochs": 200,
    "layers": [13, 64, 5],
    "state": "paper",
    "coordination": "central",
    "eps": None,
    "outages": [],
    "online": False,
}
FORGED_POLICIES = {
    "epochs below 0": ({"trained_epochs": -5}, "policies.rl.trained_epochs = -5 must be at"),
    "sha256 not hex": ({"sha256": "zz"}, "policies.rl.sha256 = 'zz' is no sha256"),
    "unknown state": ({"state": "bogus"}, "policies.rl.state = 'bogus' is no state variant"),
    "unknown coordination": ({"coordination": "bogus"}, "policies.rl.coordination = 'bogus'"),
    "eps above 1": ({"eps": 5.0}, "policies.rl.eps = 5.0 must be from 0 to 1"),
    "layers of another state": ({"layers": [1, 2]}, "policies.rl.layers = [1, 2] must run from"),
    "layers not ending in 5 actions": ({"layers": [13, 7]}, "to 5 Q-values"),
    "online not true or false": ({"online": "yes"}, 'policies.rl.online = "yes" must be true'),
}


@pytest.mark.parametrize("name", FORGED_POLICIES)
def test_a_forged_learned_policy_record_is_refused(name):
    """run.json's record of a learned swarm has its checkpoint's sha256, epochs, layers that fit
    its state, and a known state and coordination; every learned swarm of a complete run has
    one."""
    from twin.swarms import check_policy_records

    base = {"swarms": ["random", "rl"], "partial": False}
    check_policy_records(Path("run.json"), {**base, "policies": {"rl": GOOD_POLICY}})
    change, words = FORGED_POLICIES[name]
    forged = {**base, "policies": {"rl": {**GOOD_POLICY, **change}}}
    with pytest.raises(UserError, match=re.escape(words)):
        check_policy_records(Path("run.json"), forged)
    with pytest.raises(UserError, match=re.escape("no policies.rl for the swarm")):
        check_policy_records(Path("run.json"), {**base, "policies": {}})
    check_policy_records(Path("run.json"), {**base, "partial": True, "policies": {}})


def test_a_policy_record_its_swarm_cannot_have_is_refused():
    """A record for a swarm that records none (random), and a learned swarm's record that
    contradicts its name (rl-online not online, rl-decentralized central)."""
    from twin.swarms import check_policy_records

    run = {"swarms": ["random", "rl-online", "rl-decentralized"], "partial": True}
    for policies, words in (
        ({"random": {"online": False}}, "policies.random: swarm 'random' records no policy"),
        ({"rl-online": {**GOOD_POLICY, "online": False}}, "policies.rl-online.online = False"),
        (
            {"rl-decentralized": GOOD_POLICY},
            "policies.rl-decentralized.coordination = 'central', but swarm 'rl-decentralized' has",
        ),
    ):
        with pytest.raises(UserError, match=re.escape(words)):
            check_policy_records(Path("run.json"), {**run, "policies": policies})
    good = {"rl-online": {**GOOD_POLICY, "online": True},
            "rl-decentralized": {**GOOD_POLICY, "coordination": "decentralized", "eps": 0.1}}  # fmt: skip
    check_policy_records(Path("run.json"), {**run, "policies": good})


def _tours_record() -> dict:
    from twin.tours import ToursPolicy

    return ToursPolicy().describe()


def _nowcast_record() -> dict:
    return {"weight": 1.0, "quantile_z": 1.64, "meas_var": None, "sighting_count_p": 1.0,
            "history_runs": 3, "history_seeds": [0, 1, 2]}  # fmt: skip


FORGED_PLANNER_RECORDS = {
    "tours per_tour as text": ("tours", {"per_tour": "abc"}, "tours: per_tour = 'abc' must be"),
    "tours per_tour below 1": ("tours", {"per_tour": -5}, "tours: per_tour = -5 must be in 1.."),
    "tours unknown layout": ("tours", {"layout": "nonsense"}, "tours: layout = 'nonsense' must"),
    "tours plans below 0": ("tours", {"plans": -1}, "plans = -1 must be a whole number"),
    "tours option left out": ("tours", {"shift": ...}, "policies.tours: records no shift"),
    "nowcast-gain weight below 0": ("nowcast-gain", {"weight": -1}, "weight = -1 must lie in"),
    "nowcast-gain sighting above 1": (
        "nowcast-gain",
        {"sighting_count_p": 2},
        "sighting_count_p = 2 must be a number in",
    ),
    "nowcast-gain no history runs": ("nowcast-gain", {"history_runs": 0}, "history_runs = 0"),
}


@pytest.mark.parametrize("name", FORGED_PLANNER_RECORDS)
def test_a_forged_planner_record_is_refused(name):
    """A planner's record (its options, as its constructor checks them, and its counts) is read
    back like a learned swarm's; every such swarm of a complete run has one."""
    from twin.swarms import check_policy_records

    swarm, change, words = FORGED_PLANNER_RECORDS[name]
    good = {"tours": _tours_record, "nowcast-gain": _nowcast_record}[swarm]()
    base = {"swarms": ["random", swarm], "partial": False}
    check_policy_records(Path("run.json"), {**base, "policies": {swarm: good}})
    forged = {k: v for k, v in {**good, **change}.items() if v is not ...}
    with pytest.raises(UserError, match=re.escape(words)):
        check_policy_records(Path("run.json"), {**base, "policies": {swarm: forged}})
    with pytest.raises(UserError, match=re.escape(f"no policies.{swarm} for the swarm")):
        check_policy_records(Path("run.json"), {**base, "policies": {}})


def test_a_figure_of_one_seed_has_no_interval(tmp_path, capsys):
    """summary.csv leaves the _ci95 of one seed empty (a 0 would read as certainty), as the
    transfer matrix does; a folder of format 3, which wrote 0 there, still reads back, and a
    0 in a folder of this format is refused."""
    import json

    cfg = small_config(tmp_path, horizon=4)
    out = tmp_path / "one"
    argv = ["evaluate", "--config", str(cfg), "--seeds", "1", "--swarms", "random,rl"]
    assert main([*argv, "--out", str(out), "--no-report", "--quiet"]) == 0
    summary = pd.read_csv(out / "summary.csv")
    spans = [c for c in summary.columns if c.endswith("_ci95")]
    assert spans and summary[spans].isna().all().all(), summary[spans]
    assert pd.read_csv(out / "comparison.csv")["difference_ci95"].isna().all()
    for name in ("summary.csv", "monitoring.csv", "comparison.csv"):  # as format 3 wrote them
        table = pd.read_csv(out / name)
        table[[c for c in table.columns if c.endswith("_ci95")]] = 0.0
        table.to_csv(out / name, index=False)
    refresh_manifest(out)
    assert main(["report", str(out), "--no-animation"]) == EXIT_REFUSED
    assert "summary.csv: R_hat_T_ci95 = 0" in one_line(capsys)
    meta = json.loads((out / "run.json").read_text())
    meta["folder_format"] = 3
    (out / "run.json").write_text(json.dumps(meta))
    refresh_manifest(out)
    assert main(["report", str(out), "--no-animation"]) == 0, capsys.readouterr().err
    # this format's empty intervals relabelled format 3, which wrote 0 there (probe 19's P2-05)
    table = pd.read_csv(out / "summary.csv")
    table[[c for c in table.columns if c.endswith("_ci95")]] = float("nan")
    table.to_csv(out / "summary.csv", index=False)
    refresh_manifest(out)
    assert main(["report", str(out), "--no-animation"]) == EXIT_REFUSED
    assert "summary.csv: R_hat_T_ci95 = nan" in one_line(capsys)


# ----------------------------------------------------------------- records that are no files
def _twin(args: list[str], cwd: Path) -> tuple[int, str]:
    """``python -m twin ARGS`` in a subprocess, stopped after 90 s (a read that blocks on a
    FIFO would hang the test run otherwise)."""
    import subprocess

    root = Path(__file__).resolve().parents[1]
    env = {**os.environ, "PYTHONPATH": str(root)}
    try:
        done = subprocess.run([sys.executable, "-m", "twin", *args], cwd=cwd, env=env,
                              capture_output=True, text=True, timeout=90)  # fmt: skip
    except subprocess.TimeoutExpired:
        pytest.fail(f"twin {' '.join(args)} blocked for 90 s")
    return done.returncode, done.stderr


RECORDS_NO_FILES = {
    "report, manifest.json a FIFO": ("manifest.json", "fifo", ["report", "{run}"]),
    "report, run.json a FIFO": ("run.json", "fifo", ["report", "{run}"]),
    "report, manifest.json linked to /dev/zero": ("manifest.json", "zero", ["report", "{run}"]),
    "history --from, manifest.json a FIFO": (
        "manifest.json", "fifo", ["history", "--from", "{run}", "--out", "{tmp}/h.npz"],
    ),
    "evaluate --out, run.json a FIFO": (
        "run.json", "fifo",
        ["evaluate", "--config", "{config}", "--swarms", "random", "--out", "{run}", "--quiet"],
    ),
    "evaluate --out, manifest.json a FIFO": (
        "manifest.json", "fifo",
        ["evaluate", "--config", "{config}", "--swarms", "random", "--out", "{run}", "--quiet"],
    ),
}  # fmt: skip


@pytest.mark.parametrize("case", list(RECORDS_NO_FILES))
def test_a_record_of_a_run_folder_that_is_no_file_is_refused_without_blocking(
    run_folder, tmp_path, case
):
    """A run folder's manifest.json or run.json replaced by a FIFO (reading it blocks until a
    writer comes, which never does) or linked to /dev/zero (read whole: the memory fills):
    one line naming the file, exit 2, within seconds (probe 12's rf1, rf2)."""
    name, kind, args = RECORDS_NO_FILES[case]
    run = tmp_path / "run"
    shutil.copytree(run_folder, run)
    (run / name).unlink()
    if kind == "fifo":
        os.mkfifo(run / name)
    else:
        (run / name).symlink_to("/dev/zero")
    config = small_config(tmp_path)
    argv = [a.format(run=run, tmp=tmp_path, config=config) for a in args]
    code, err = _twin(argv, tmp_path)
    lines = err.strip().splitlines()
    assert code == 2 and len(lines) == 1 and "Traceback" not in err, err
    assert name in lines[0] or str(run) in lines[0], err
    assert "memory" not in lines[0], err


def test_run_json_records_the_command_line_that_was_run(tmp_path):
    """`twin.cli.main(argv)` from Python (a notebook, a script) records its own arguments in
    run.json, not the process's (a notebook kernel's or pytest's were recorded as the command
    behind the run)."""
    import json
    import shlex

    out = tmp_path / "my run"
    argv = ["evaluate", "--config", str(small_config(tmp_path)), "--swarms", "random",
            "--out", str(out), "--no-report", "--quiet"]  # fmt: skip
    assert main(argv) == 0
    command = json.loads((out / "run.json").read_text())["command"]
    assert shlex.split(command) == ["twin", *argv]


def test_a_python_warning_is_one_notice_line_without_its_source(capfd) -> None:
    """numpy's or a library's warning inside a command: one ``twin: notice:`` line, said once,
    never the file and source line that raised it."""
    import warnings

    def warns(_args) -> int:
        for _ in range(3):
            np.float64(0.0) / np.float64(0.0)  # numpy: invalid value encountered in divide
        warnings.warn("a library's\n  two-line advice", FutureWarning, stacklevel=1)
        return 0

    assert run_command(warns, None) == 0
    err = capfd.readouterr().err.strip().splitlines()
    assert err == [
        "twin: notice: RuntimeWarning: invalid value encountered in scalar divide",
        "twin: notice: FutureWarning: a library's two-line advice",
    ], err


@pytest.mark.parametrize("command", ["replay", "report"])
def test_a_folder_no_run_wrote_is_said_to_be_none(tmp_path, capsys, command):
    """A pretraining's, sweep's or transfer's folder given to replay or report: not a run
    folder, not "an interrupted run" that rerunning its command would mend (probe 15's f25)."""
    folder = tmp_path / "sweep"
    folder.mkdir()
    (folder / "sweep.json").write_text("{}")
    assert main([command, str(folder)]) == EXIT_REFUSED
    err = one_line(capsys)
    assert (
        "not a folder `twin run` or `twin evaluate` wrote" in err or "is this a run folder" in err
    ), err
    assert "interrupted" not in err


def test_an_output_folder_holding_a_hard_link_is_refused(tmp_path):
    """A file of an output folder with another name (a hard link to a file outside): twin
    would write through it (pretraining's log and curve were; probe 15's P2-f02)."""
    from twin import outputs

    victim, out = tmp_path / "victim.csv", tmp_path / "out"
    victim.write_text("keep")
    out.mkdir()
    os.link(victim, out / "train_log.csv")
    with pytest.raises(UserError, match=r"train_log.csv has another name \(a hard link"):
        outputs.check_output_dir(out)
    (out / "train_log.csv").unlink()
    (out / "train_log.csv").write_text("mine")
    assert outputs.check_output_dir(out) == out


@pytest.mark.parametrize("command", ["replay", "report"])
def test_a_file_given_as_a_run_folder_is_said_to_be_a_file(tmp_path, capsys, command):
    """An existing file given for the run folder: "a file, not a run folder" ("no such run
    folder" said an existing path was not there; probe 15's P2-f10)."""
    given = tmp_path / "some.npz"
    given.write_bytes(b"x")
    assert main([command, str(given)]) == EXIT_REFUSED
    assert f"{given}: a file, not a run folder; pass the folder `twin run`" in one_line(capsys)


def test_a_bound_row_past_the_dp_limit_is_refused_not_replayed(run_copy, monkeypatch, capsys):
    """A bound row whose DP would be past what a run computes is refused, not replayed (a
    forged row on a large grid made the read-back allocate the DP)."""
    import twin.ceilings

    monkeypatch.setattr(twin.ceilings, "MAX_DP_BYTES", 0)
    assert main(["report", str(run_copy), "--no-animation"]) == EXIT_REFUSED
    assert "holds a bound (ceiling) row for seed 0, but its DP would hold" in one_line(capsys)


def test_a_learned_policy_record_is_checked_against_its_checkpoint(tmp_path):
    """A record's epochs or layers edited in run.json while its checkpoint is still at the
    recorded path with the recorded sha256: refused, naming the checkpoint's own value (the
    report showed the forged epochs: probe 25's f02). A checkpoint moved or changed since is
    not read (the record is history)."""
    import torch

    from twin.files import file_sha256
    from twin.learning.checkpoint import check_recorded_checkpoints, model_metadata, save_model
    from twin.learning.qnet import QNetwork

    path = tmp_path / "q.pt"
    torch.manual_seed(0)
    save_model(path, QNetwork((13, 16, 5)).state_dict(), model_metadata((13, 16, 5), {}, 0, 250))
    record = {**GOOD_POLICY, "checkpoint": str(path), "sha256": file_sha256(path),
              "trained_epochs": 250, "layers": [13, 16, 5]}  # fmt: skip
    run = tmp_path / "run.json"
    check_recorded_checkpoints(run, {"rl": record})
    for key, forged in (("trained_epochs", 987654), ("layers", [13, 64, 5])):
        with pytest.raises(UserError) as caught:
            check_recorded_checkpoints(run, {"rl": {**record, key: forged}})
        assert str(caught.value).startswith(
            f"{run}: policies.rl.{key} = {forged}, but its checkpoint {path} (the recorded "
            "sha256) has "
        ), caught.value
    other = {**record, "trained_epochs": 987654, "sha256": "ab" * 32}  # another file now
    check_recorded_checkpoints(run, {"rl": other})
    check_recorded_checkpoints(run, {"rl": {**other, "checkpoint": str(tmp_path / "gone.pt")}})
