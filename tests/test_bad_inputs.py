"""Bad input, table-driven: tapes, run folders, --out, memory limits, Markdown escaping.

Each case runs one command in process and asserts the exit code, ONE line on stderr naming the
problem, no traceback, and that no file outside the run's own folder changed (hashes and
mtimes of the whole temporary folder). Plus a fault test: ``kill -9`` of ``twin evaluate`` at
several instants never leaves a folder that claims completeness.
"""

from __future__ import annotations

import hashlib
import json
import os
import shutil
import signal
import subprocess
import sys
import threading
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pandas as pd
import pyarrow as pa
import pyarrow.parquet as pq
import pytest

from twin.cli import main
from twin.runs import MANIFEST, check_run_folder, new_run_dir
from twin.traffic.tape import Tape

SMALL = """
[grid]
nx = 6
ny = 8
[swarm]
n_drones = 2
[traffic]
kind = "synthetic"
horizon = {horizon}
disturbances = [{{ kind = "big", i = 2, j = 2, amplitude = 1.0, sigma = 2.0 }}]
[evaluate]
swarms = ["random", "greedy"]
"""
NX, NY, HORIZON = 3, 4, 6


def good_tape(horizon: int = HORIZON, last: int | None = None) -> Tape:
    """A valid tape: warm-up steps -2, -1, then 0..``last`` (default the horizon)."""
    rng = np.random.default_rng(0)
    steps = np.arange(-2, (horizon if last is None else last) + 1)
    counts = rng.integers(0, 30, (len(steps), NX, NY)).astype(np.int32)
    speeds = np.where(counts > 0, rng.uniform(1, 15, counts.shape), np.nan).astype(np.float32)
    return Tape(
        steps=steps,
        times=25200.0 + 75.0 * steps,
        counts=counts,
        speeds=speeds,
        obstacles=np.zeros((NX, NY), bool),
        lane_km=rng.uniform(0.5, 3.0, (NX, NY)),
        speed_limit=np.full((NX, NY), 13.9),
        horizon=horizon,
        settings={
            "mfd_fit": "online",
            "detection_p": 1.0,
            "seed": 1,
            "mfd_prior": [0.7, 40.0],
            "reads_per_step": 1,
        },
    )


def write_tape(
    path: Path,
    frame: Callable[[pd.DataFrame], pd.DataFrame] = lambda f: f,
    meta: Callable[[dict], dict | bytes | None] = lambda m: m,
) -> Path:
    """A good tape with its row table and metadata passed through ``frame`` and ``meta``."""
    tape = good_tape()
    tape.write(path)
    table = pq.read_table(path)
    raw = table.schema.metadata[b"twin_tape"]
    new_meta = meta(json.loads(raw))
    table = pa.Table.from_pandas(frame(table.to_pandas()), preserve_index=False)
    if new_meta is not None:
        value = new_meta if isinstance(new_meta, bytes) else json.dumps(new_meta).encode()
        table = table.replace_schema_metadata({b"twin_tape": value})
    pq.write_table(table, path)
    return path


def _set(df: pd.DataFrame, column: str, value, where=None) -> pd.DataFrame:
    df = df.copy()
    if where is None:
        where = df["count"] > 0
    idx = df.index[where][0]
    if isinstance(value, float) and df[column].dtype.kind in "iu":
        df[column] = df[column].astype(float)
    df.loc[idx, column] = value
    return df


# name -> (what to do to a good tape, expected words of the one-line message)
TAPE_CASES: dict[str, tuple[Callable[[Path], Path], str]] = {
    "no count column": (lambda p: write_tape(p, lambda f: f.drop(columns="count")), "count"),
    "no speed column": (lambda p: write_tape(p, lambda f: f.drop(columns="speed")), "speed"),
    "no step column": (lambda p: write_tape(p, lambda f: f.drop(columns="step")), "step"),
    "count as float": (
        lambda p: write_tape(p, lambda f: f.assign(count=f["count"] + 0.5)),
        "column count has type float64",
    ),
    "count as text": (
        lambda p: write_tape(p, lambda f: f.assign(count=f["count"].astype(str))),
        "column count has type",
    ),
    "step as float": (
        lambda p: write_tape(p, lambda f: f.assign(step=f["step"] + 0.5)),
        "column step has type",
    ),
    "speed as text": (
        lambda p: write_tape(p, lambda f: f.assign(speed=f["speed"].astype(str))),
        "column speed has type",
    ),
    "i off the grid": (lambda p: write_tape(p, lambda f: _set(f, "i", 7)), "column i = 7"),
    "j negative": (lambda p: write_tape(p, lambda f: _set(f, "j", -1)), "column j = -1"),
    "NaN speed where vehicles are": (
        lambda p: write_tape(p, lambda f: _set(f, "speed", float("nan"))),
        "column speed = nan",
    ),
    "infinite speed": (
        lambda p: write_tape(p, lambda f: _set(f, "speed", float("inf"))),
        "column speed = inf",
    ),
    "negative speed": (
        lambda p: write_tape(p, lambda f: _set(f, "speed", -3.0)),
        "column speed = -3.0",
    ),
    "negative count": (lambda p: write_tape(p, lambda f: _set(f, "count", -4)), "count = -4"),
    "NaN time": (
        lambda p: write_tape(p, lambda f: f.assign(time_s=np.nan)),
        "column time_s = nan",
    ),
    "NaN time in one cell's row": (
        lambda p: write_tape(
            p, lambda f: _set(f, "time_s", float("nan"), (f["step"] == -1) & (f["j"] == 2))
        ),
        "column time_s = nan at step -1, cell (0, 2) is not finite",
    ),
    "another time in one cell's row": (
        lambda p: write_tape(p, lambda f: _set(f, "time_s", 1.0, (f["step"] == 2) & (f["i"] == 1))),
        "column time_s = 1.0 at step 2, cell (1, 0) differs from the step's time 25350.0",
    ),
    "a missing step": (
        lambda p: write_tape(p, lambda f: f[f["step"] != 3]),
        "step 3 missing",
    ),
    "step 0 missing": (lambda p: write_tape(p, lambda f: f[f["step"] != 0]), "step 0 missing"),
    "a cell twice": (
        lambda p: write_tape(p, lambda f: pd.concat([f, f.iloc[[5]]], ignore_index=True)),
        "twice",
    ),
    "a row short": (lambda p: write_tape(p, lambda f: f.drop(index=7)), "has 11 rows"),
    "only warm-up steps": (lambda p: write_tape(p, lambda f: f[f["step"] < 0]), "warm-up"),
    "no rows": (lambda p: write_tape(p, lambda f: f.iloc[:0]), "no rows"),
    "grid of another shape": (lambda p: write_tape(p, meta=lambda m: {**m, "nx": 4}), "4 x 4"),
    "obstacles of another shape": (
        lambda p: write_tape(p, meta=lambda m: {**m, "obstacles": [[0] * NY] * 2}),
        "obstacles has shape (2, 4)",
    ),
    "negative lane-km": (
        lambda p: write_tape(p, meta=lambda m: {**m, "lane_km": [[-1.0] * NY, *m["lane_km"][1:]]}),
        "lane_km = -1.0",
    ),
    **{  # probe 20's f08: a forged limit changed the MFD samples, and the run went on
        f"a speed limit of {value:g} m/s on a free cell": (
            lambda p, value=value: write_tape(
                p, meta=lambda m: {**m, "speed_limit": _zero_at(m["speed_limit"], 1, 2, value)}
            ),
            f"tape metadata speed_limit = {value:g} at cell (1, 2), which its obstacles leave "
            "free, is not a lane speed",
        )
        for value in (0.0, 1e300)
    },
    **{  # probe 20's P2-f08a: text read as a number, true as 1 m/s
        f"{key} {value!r} in the metadata": (
            lambda p, key=key, value=value: write_tape(
                p, meta=lambda m: {**m, key: _zero_at(m[key], 1, 2, value)}
            ),
            f"tape metadata {key} holds {str(value)!r} where {want} belongs",
        )
        for key, value, want in (
            ("speed_limit", "13.9", "a number"),
            ("lane_km", "0.2", "a number"),
            ("speed_limit", True, "a number"),
            ("obstacles", 2, "true or false (1 or 0)"),
        )
    },
    "a speed faster than any vehicle": (
        lambda p: write_tape(p, lambda f: _set(f, "speed", 3e38)),
        "is faster than any road vehicle (over 1000 m/s)",
    ),
    "NaN speed limit": (
        lambda p: write_tape(
            p, meta=lambda m: {**m, "speed_limit": [[float("nan")] * NY, *m["speed_limit"][1:]]}
        ),
        "speed_limit = nan",
    ),
    "horizon 0": (lambda p: write_tape(p, meta=lambda m: {**m, "horizon": 0}), "horizon = 0"),
    "horizon text": (lambda p: write_tape(p, meta=lambda m: {**m, "horizon": "x"}), "horizon"),
    "another version": (
        lambda p: write_tape(p, meta=lambda m: {**m, "version": 9}),
        "tape version = 9",
    ),
    "metadata not JSON": (lambda p: write_tape(p, meta=lambda m: b"{oops"), "not valid JSON"),
    "metadata a list": (lambda p: write_tape(p, meta=lambda m: [1, 2]), "not a table"),
    "no tape metadata": (
        lambda p: (pd.DataFrame({"step": [0]}).to_parquet(p), p)[1],
        "not a twin traffic tape",
    ),
    "truncated parquet": (
        lambda p: (write_tape(p), p.write_bytes(p.read_bytes()[: p.stat().st_size // 2]), p)[2],
        "not a parquet file or truncated",
    ),
    "corrupt footer": (
        lambda p: (write_tape(p), p.write_bytes(p.read_bytes()[:-12] + b"x" * 12), p)[2],
        "not a parquet file",
    ),
    "not parquet at all": (
        lambda p: (p.write_text("step,i,j\n0,0,0\n"), p)[1],
        "not a parquet file",
    ),
    "empty file": (lambda p: (p.write_bytes(b""), p)[1], "not a parquet file"),
    "a folder": (lambda p: (p.mkdir(), p)[1], "is a folder, not a file (a traffic tape"),
    "missing file": (lambda p: p, "no such traffic tape"),
}


def _step_time(f: pd.DataFrame, step: int, time_s: float) -> pd.DataFrame:
    return f.assign(time_s=np.where(f["step"] == step, time_s, f["time_s"]))


def _zero_at(rows: list[list[float]], i: int, j: int, value: float = 0.0) -> list[list[float]]:
    rows = [list(r) for r in rows]
    rows[i][j] = value
    return rows


def _settings(**more) -> Callable[[dict], dict]:
    return lambda m: {**m, "settings": {**m["settings"], **more}}


#: tapes whose rows are well-formed but absurd, or disagree with their metadata
ABSURD_TAPES: dict[str, tuple[Callable[[Path], Path], str]] = {
    "a huge vehicle count": (
        lambda p: write_tape(p, lambda f: _set(f, "count", 2**31 - 1)),
        "column count = 2147483647 at step -2, cell (0, 0) is more vehicles than its",
    ),
    "time going backwards": (
        lambda p: write_tape(p, lambda f: _step_time(f, 2, 25200.0)),
        "column time_s goes from 25275.0 at step 1 to 25200.0 at step 2, not forward",
    ),
    "a time repeated": (
        lambda p: write_tape(p, lambda f: _step_time(f, 2, 25275.0)),
        "column time_s goes from 25275.0 at step 1 to 25275.0 at step 2, not forward",
    ),
    "a whole step duplicated": (
        lambda p: write_tape(p, lambda f: pd.concat([f, f[f["step"] == 3]], ignore_index=True)),
        "step 3 has cell (0, 0) twice",
    ),
    "steps past the horizon": (
        lambda p: write_tape(p, meta=lambda m: {**m, "horizon": 4}),
        "steps go to 6, past the metadata's horizon = 4",
    ),
    "times apart from the step length": (
        lambda p: write_tape(p, meta=_settings(step_s=60.0)),
        "column time_s advances 75 s from step -2 to -1, the metadata's step_s = 60",
    ),
    "more warm-up than recorded": (
        lambda p: write_tape(p, meta=_settings(step_s=75.0, warmup_s=75.0)),
        "steps start at -2, before the metadata's warm-up of 1 steps",
    ),
    **{
        f"observation setting {key} = {value!r}": (
            lambda p, key=key, value=value: write_tape(p, meta=_settings(**{key: value})),
            f"tape metadata {key} = ",
        )
        for key, value in (
            ("mfd_prior", [-1, 0]),
            ("mfd_prior", [0.7, float("nan")]),
            ("mfd_prior", [0.7]),
            ("mfd_prior", "x"),
            ("mfd_prior", [1.5, 40]),
            ("mfd_fit", "bogus"),
            ("detection_p", 0.0),
            ("detection_p", 1.5),
            ("detection_p", "x"),
            ("detection_p", float("nan")),
            ("step_s", -30.0),
            ("step_s", 0),
            ("seed", "0"),  # probe 20's P2-f08b: accepted, run.json's seed then null
            ("seed", -1),
            ("begin", 600),
            ("warmup_s", -1.0),
            ("reads_per_step", 0),
            ("reads_per_step", 1.5),
            ("mfd_prior", [1e-300, 40.0]),
            ("mfd_prior", [0.7, 1e-300]),
            ("mfd_prior", [0.7, 1e300]),
            ("detection_p", 1e-300),
        )
    },
    "a free cell without lanes": (
        lambda p: write_tape(p, meta=lambda m: {**m, "lane_km": _zero_at(m["lane_km"], 1, 2)}),
        "tape metadata lane_km = 0 at cell (1, 2), which its obstacles leave free",
    ),
    **{
        f"observation setting {key} left out": (
            lambda p, key=key: write_tape(
                p,
                meta=lambda m, key=key: {
                    **m,
                    "settings": {k: v for k, v in m["settings"].items() if k != key},
                },
            ),
            f"tape metadata settings lack {key} (a tape records every setting",
        )
        for key in ("reads_per_step", "mfd_prior", "mfd_fit", "detection_p")
    },
    "no settings at all": (
        lambda p: write_tape(p, meta=lambda m: {k: v for k, v in m.items() if k != "settings"}),
        "tape metadata settings lack mfd_fit, mfd_prior, detection_p, reads_per_step",
    ),
    "times shifted against the recorded begin": (
        lambda p: write_tape(
            p, lambda f: f.assign(time_s=f["time_s"] + 7.0), _settings(step_s=75.0, begin="07:00")
        ),
        "column time_s = 25057 at step -2, but the metadata's begin = 07:00 (step 0) and "
        "step_s = 75 put it at 25050",
    ),
    "reads at other offsets than their number gives": (
        lambda p: write_tape(
            p, meta=_settings(step_s=75.0, reads_per_step=1, read_offsets_s=[50.0, 25.0, 0.0])
        ),
        "metadata read_offsets_s = [50.0, 25.0, 0.0], but reads_per_step = 1 reads",
    ),
}
TAPE_CASES.update(ABSURD_TAPES)


def snapshot(root: Path, skip: Path | None = None) -> dict[str, tuple[str, int]]:
    """sha256 and mtime of every file under ``root`` (``skip``: the run's own folder)."""
    out = {}
    for p in sorted(root.rglob("*")):
        if skip is not None and (p == skip or skip in p.parents):
            continue
        if p.is_file():
            out[str(p)] = (hashlib.sha256(p.read_bytes()).hexdigest(), p.stat().st_mtime_ns)
        else:
            out[str(p)] = ("dir", 0)
    return out


def run_case(capsys, root: Path, argv: list[str], out: Path | None, code: int, needle: str):
    """Run ``twin argv``; assert the code, one stderr line with ``needle``, no traceback and
    nothing changed outside ``out``."""
    before = snapshot(root, out)
    got = main(argv)
    captured = capsys.readouterr()
    err = captured.err.strip()
    assert got == code, err
    assert err.count("\n") == 0 and err.startswith("twin: "), err
    assert needle in err, err
    assert "Traceback" not in err + captured.out
    assert snapshot(root, out) == before
    return err


@pytest.fixture
def cfg(tmp_path: Path) -> Path:
    path = tmp_path / "small.toml"
    path.write_text(SMALL.format(horizon=12))
    return path


@pytest.fixture
def tape_cfg(tmp_path: Path) -> Path:
    """The small config on the grid of :func:`good_tape` (another grid is said in a notice)."""
    path = tmp_path / "tape.toml"
    path.write_text(SMALL.format(horizon=12).replace("nx = 6", f"nx = {NX}").replace(
        "ny = 8", f"ny = {NY}"))  # fmt: skip
    return path


@pytest.mark.parametrize("case", list(TAPE_CASES))
def test_bad_tape(tmp_path, capsys, cfg, case):
    make, needle = TAPE_CASES[case]
    tape = make(tmp_path / "tape.parquet")
    out = tmp_path / "out"
    argv = ["evaluate", "--config", str(cfg), "--traffic", str(tape), "--out", str(out)]
    err = run_case(capsys, tmp_path, [*argv, "--quiet", "--no-report"], out, 2, needle)
    assert str(tape) in err
    assert not out.exists()  # refused before anything was written


@pytest.mark.parametrize("command", ["history", "pretrain"])
@pytest.mark.parametrize("case", list(ABSURD_TAPES))
def test_an_absurd_tape_is_refused_by_every_reader(tmp_path, capsys, command, case):
    """`twin history --from TAPE` and `twin pretrain --traffic TAPE` refuse what `twin
    evaluate --traffic TAPE` does (the same reader): one line naming the tape and the field."""
    make, needle = ABSURD_TAPES[case]
    tape = make(tmp_path / "tape.parquet")
    if command == "history":
        good_tape().write(tmp_path / "good.parquet")
        out = tmp_path / "history.npz"
        argv = ["history", "--from", str(tmp_path / "good.parquet"), str(tape), "--out", str(out)]
    else:
        out = tmp_path / "pretrained"
        argv = ["pretrain", "--traffic", str(tape), "--epochs", "1", "--out", str(out), "--quiet"]
    err = run_case(capsys, tmp_path, argv, out, 2, needle)
    assert str(tape) in err
    assert not out.exists()


def test_tape_grid_against_the_config(tmp_path, capsys):
    sumo_cfg = tmp_path / "sumo.toml"
    sumo_cfg.write_text('[grid]\nnx = 5\nny = 5\n[traffic]\nkind = "sumo"\n')
    tape = write_tape(tmp_path / "tape.parquet")
    out = tmp_path / "out"
    argv = ["evaluate", "--config", str(sumo_cfg), "--traffic", str(tape), "--out", str(out)]
    run_case(capsys, tmp_path, [*argv, "--quiet", "--no-report"], out, 2, "differs from")


def test_a_tape_short_of_its_horizon_is_a_partial_run(tmp_path, capsys, tape_cfg):
    """A tape that stops at step 3 of 6 replays 3 steps, exits 1, and says it is partial: on
    stderr, in run.json and manifest.json, and in the first line of the report."""
    tape = tmp_path / "tape.parquet"
    good_tape(last=3).write(tape)
    out = tmp_path / "out"
    argv = ["evaluate", "--config", str(tape_cfg), "--traffic", str(tape), "--out", str(out)]
    run_case(capsys, tmp_path, [*argv, "--quiet", "--no-report"], out, 1, "partial run")
    manifest = check_run_folder(out)
    assert manifest["partial"] and "3 of 6" in manifest["partial_reason"]
    assert json.loads((out / "run.json").read_text())["partial"] is True
    assert main(["report", str(out), "--no-animation"]) == 0
    capsys.readouterr()
    md = (out / "report" / "report.md").read_text().splitlines()
    lede = next(line for line in md[1:] if line.strip())
    assert lede.startswith("PARTIAL RUN (3 of 6 steps)")


@pytest.fixture(scope="module")
def finished_run(tmp_path_factory) -> Path:
    root = tmp_path_factory.mktemp("finished")
    cfg = root / "small.toml"
    cfg.write_text(SMALL.format(horizon=12))
    out = root / "run"
    argv = ["evaluate", "--config", str(cfg), "--out", str(out), "--quiet", "--no-report"]
    assert main(argv) == 0
    return out


def _grow(p: Path) -> None:
    with open(p, "ab") as fh:
        fh.write(b"\n")


# name -> (what to do to a finished run folder, expected words)
FOLDER_CASES: dict[str, tuple[Callable[[Path], None], str]] = {
    "no manifest": (lambda d: (d / MANIFEST).unlink(), "incomplete run folder"),
    "only the start marker": (
        lambda d: (
            [p.unlink() for p in d.iterdir() if p.name != "run.json"]
            and (d / "run.json").write_text(
                json.dumps(
                    {"partial": True, "partial_reason": "interrupted: the run did not finish"}
                )
            )
        ),
        "interrupted",
    ),
    "a file grew": (lambda d: _grow(d / "summary.csv"), "summary.csv has"),
    "a listed file is missing": (
        lambda d: (d / "series.parquet").unlink(),
        "series.parquet listed in manifest.json is missing",
    ),
    "manifest not JSON": (lambda d: (d / MANIFEST).write_text("{"), "not a run manifest"),
    "manifest without files": (lambda d: (d / MANIFEST).write_text("{}"), "not a run manifest"),
    "no run folder": (lambda d: shutil.rmtree(d), "no such run folder"),
    "not a run folder": (
        lambda d: [shutil.rmtree(d), d.mkdir(), (d / "x.txt").write_text("x")],
        "missing series.parquet",
    ),
}


@pytest.mark.parametrize("case", list(FOLDER_CASES))
def test_report_on_a_bad_run_folder(tmp_path, capsys, finished_run, case):
    change, needle = FOLDER_CASES[case]
    run = tmp_path / "run"
    shutil.copytree(finished_run, run)
    change(run)
    run_case(capsys, tmp_path, ["report", str(run), "--no-animation"], None, 2, needle)
    assert not (run / "report").exists()


def _partial_of(args: list[str]) -> Callable[[Path], None]:
    """A folder holding a killed run of ``twin evaluate ARGS`` (its start marker and a file)."""

    def make(out: Path) -> None:
        from twin.cli import build_parser
        from twin.runs import invocation, prepare_run_dir

        prepare_run_dir(out, invocation("evaluate", build_parser().parse_args(args)))
        (out / "series.parquet").write_bytes(b"half")

    return make


def _out_cases(cfg: Path, out: Path) -> dict[str, tuple[Callable[[Path], None], str]]:
    same = ["evaluate", "--config", str(cfg), "--out", str(out)]
    return {
        "a foreign folder": (
            lambda d: [d.mkdir(), (d / "notes.txt").write_text("mine")],
            "holds no twin run",
        ),
        "a file": (lambda d: d.write_text("mine"), "is a file"),
        "a partial run of another command": (
            _partial_of([*same, "--seeds", "3"]),
            "with other options",
        ),
        "a partial run with a foreign file": (
            lambda d: [_partial_of(same)(d), (d / "notes.txt").write_text("mine")],
            "'notes.txt', which twin did not write",
        ),
        "a partial run with a foreign file in tapes/": (
            lambda d: [
                _partial_of(same)(d),
                (d / "tapes").mkdir(),
                (d / "tapes" / "notes.txt").write_text("mine"),
            ],
            "'tapes/notes.txt', which twin did not write",
        ),
        "a partial run with the user's notes in report/": (  # deleted (probe 19's P2-12)
            lambda d: [
                _partial_of(same)(d),
                (d / "report").mkdir(),
                (d / "report" / "report.html").write_text("<html/>"),  # an earlier twin's
                (d / "report" / "mynotes.md").write_text("mine"),
            ],
            "report/mynotes.md: not written by twin; move it out of",
        ),
        "a complete run": (
            lambda d: shutil.copytree(_FINISHED[0], d),
            "already holds a complete run",
        ),
    }


_FINISHED: list[Path] = []
OUT_CASES = [
    "a foreign folder",
    "a file",
    "a partial run of another command",
    "a partial run with a foreign file",
    "a partial run with a foreign file in tapes/",
    "a partial run with the user's notes in report/",
    "a complete run",
]


@pytest.mark.parametrize("case", OUT_CASES)
def test_out_refuses_a_folder_it_does_not_own(tmp_path, capsys, cfg, finished_run, case):
    _FINISHED[:] = [finished_run]
    out = tmp_path / "out"
    make, needle = _out_cases(cfg, out)[case]
    make(out)
    argv = ["evaluate", "--config", str(cfg), "--out", str(out), "--quiet", "--no-report"]
    run_case(capsys, tmp_path, argv, None, 2, needle)  # the folder itself is untouched too


def test_out_replaces_a_partial_run_of_the_same_command(tmp_path, capsys, cfg):
    out = tmp_path / "out"
    argv = ["evaluate", "--config", str(cfg), "--out", str(out)]
    _partial_of(argv)(out)
    (out / ".summary.csv.abc.tmp").write_text("left by a kill")
    assert main([*argv, "--quiet", "--no-report"]) == 0
    check_run_folder(out)
    assert not (out / ".summary.csv.abc.tmp").exists()
    assert pd.read_parquet(out / "series.parquet")["step"].max() == 11


def _memory_cases(tmp_path: Path) -> dict[str, tuple[list[str], dict[str, str], str]]:
    huge = tmp_path / "huge.toml"
    huge.write_text(
        SMALL.format(horizon=2000).replace("nx = 6", "nx = 3000").replace("ny = 8", "ny = 4000")
    )
    return {
        "limit zero": (["--max-memory-gb", "0"], {}, "--max-memory-gb = 0.0"),
        "limit NaN": (["--max-memory-gb", "nan"], {}, "--max-memory-gb = nan"),
        "limit negative": (["--max-memory-gb", "-1"], {}, "not a number > 0"),
        "env limit text": ([], {"TWIN_MAX_MEMORY_GB": "lots"}, "= 'lots' is not a number"),
        "tiny limit": (["--max-memory-gb", "1e-6"], {}, "= 1e-06 GB is below what this run takes"),
        "tiny env limit": ([], {"TWIN_MAX_MEMORY_GB": "1e-6"}, "= 1e-06 GB is below what this"),
        "a huge grid": (["--config", str(huge)], {}, "3000 x 4000 cells x 2000 steps"),
        # probe 26's f02: the seeds, not the limit, are what to change
        "too many seeds": (["--seeds", "1000000"], {}, "1000000 seeds need about"),
    }


MEMORY_CASES = [
    "limit zero", "limit NaN", "limit negative", "env limit text", "tiny limit",
    "tiny env limit", "a huge grid", "too many seeds",
]  # fmt: skip


@pytest.mark.parametrize("case", MEMORY_CASES)
def test_memory_refusal(tmp_path, capsys, monkeypatch, cfg, case):
    extra, env, needle = _memory_cases(tmp_path)[case]
    for key, value in env.items():
        monkeypatch.setenv(key, value)
    out = tmp_path / "out"
    argv = ["evaluate", "--config", str(cfg), *extra, "--out", str(out), "--quiet", "--no-report"]
    run_case(capsys, tmp_path, argv, out, 2, needle)
    assert not out.exists()


@pytest.mark.parametrize("workers", [1, 4])
def test_too_many_seeds_are_refused_with_the_seeds_that_fit(tmp_path, workers):
    """Seeds past the limit on any grid name the seeds that fit this run, on its workers, and
    that many do (the count was the one-worker run's: the review of probe 26's fixes)."""
    import re
    from dataclasses import replace

    from twin.config import load_config
    from twin.errors import UserError
    from twin.experiment import Experiment, check_memory

    cfg = tmp_path / "s.toml"
    cfg.write_text(SMALL.format(horizon=50))
    experiment = Experiment(load_config(cfg), ["random", "greedy"], range(10**6), workers=workers)
    with pytest.raises(UserError, match=r"give at most (\d+) --seeds \(6 x 8 cells") as info:
        check_memory(experiment, (6, 8), 50)
    fit = int(re.search(r"at most (\d+) --seeds", str(info.value)).group(1))
    check_memory(replace(experiment, seeds=range(fit)), (6, 8), 50)
    with pytest.raises(UserError, match=f"{fit + 1} seeds"):
        check_memory(replace(experiment, seeds=range(fit + 1)), (6, 8), 50)


def test_a_huge_sumo_grid_is_refused_with_a_cell_size(tmp_path):
    """The estimate of a live run suggests a coarser cell (thousands of km at 500 m)."""
    from types import SimpleNamespace

    from twin.config import load_config
    from twin.errors import UserError
    from twin.experiment import Experiment, check_memory
    from twin.sumo.source import SumoScenario, SumoTraffic

    class Unstarted(SumoTraffic):  # a live source's scenario and cells, nothing simulated
        def __init__(self):
            self.scenario = SumoScenario(Path("net.xml"), [], warmup_s=900.0, step_s=75.0)
            self.geometry = SimpleNamespace(cell_m=500.0)
            self.horizon = 144

    cfg = tmp_path / "s.toml"
    cfg.write_text(SMALL.format(horizon=144))
    experiment = Experiment(load_config(cfg), ["random", "greedy"], [0])
    source = Unstarted()
    assert source.warmup_steps() == 12
    with pytest.raises(
        UserError, match=r"cells of \d+ m \(--cell-m, \[traffic\]\.cell_m\)"
    ) as info:
        check_memory(experiment, (3000, 4000), 144, source)
    assert "\n" not in str(info.value)
    check_memory(experiment, (20, 30), 144, source)  # the Shenzhen-like grid passes


@pytest.mark.parametrize("evil", ["<script>alert(1)</script>", "a|b](x)`<img src=x>"])
def test_markdown_escapes_what_it_embeds(tmp_path, capsys, cfg, evil):
    """A config path and an --out name with HTML or Markdown syntax appear escaped in
    report.md (and HTML-escaped in report.html)."""
    folder = tmp_path / evil.replace("/", "_")
    folder.mkdir()
    shutil.copy(cfg, folder / "c.toml")
    out = tmp_path / f"run {evil.replace('/', '_')}"
    argv = ["evaluate", "--config", str(folder / "c.toml"), "--out", str(out), "--quiet"]
    assert main(argv) == 0
    capsys.readouterr()
    md = (out / "report" / "report.md").read_text()
    page = (out / "report" / "report.html").read_text()
    assert "<script" not in md and "<img" not in md and "<script>alert" not in page
    assert "&lt;" in md and "run " in md.splitlines()[0]
    assert sum(line.startswith("|") and line.count(" | ") > 1 for line in md.splitlines()) > 3


def test_sweep_markdown_escapes_names(tmp_path):
    from twin.report.document import markdown_table, md_escape

    table = markdown_table(["scenario"], [["<script>x</script>|y"]])
    assert "<script>" not in table and "\\|y" in table
    assert md_escape("a\nb") == "a b"


def test_files_get_the_usual_permissions(tmp_path, capsys, cfg):
    """Run files and report files (HTML, Markdown, matplotlib's PNGs) are 0666 less the
    umask: 0644 under umask 022, not the 0600 of a temporary file."""
    mask = os.umask(0o022)
    try:
        out = tmp_path / "run"
        assert main(["evaluate", "--config", str(cfg), "--out", str(out), "--quiet"]) == 0
    finally:
        os.umask(mask)
    files = [p for p in out.rglob("*") if p.is_file()]
    assert {"manifest.json", "report.md", "report.html", "scores.png"} <= {p.name for p in files}
    assert {p.name: oct(p.stat().st_mode & 0o777) for p in files} == {
        p.name: oct(0o644) for p in files
    }


def test_default_folder_names_are_never_shared(tmp_path):
    """Sixteen threads asking for a folder in the same second each get their own."""
    got: list[Path] = []
    barrier = threading.Barrier(16)

    def claim() -> None:
        barrier.wait()
        got.append(new_run_dir(tmp_path, "evaluate"))

    threads = [threading.Thread(target=claim) for _ in range(16)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert len(set(got)) == 16 and all(p.is_dir() for p in got)


@pytest.mark.parametrize("trigger", ["run.json", "series.parquet", "summary.csv"])
def test_kill_9_never_leaves_a_folder_claiming_completeness(tmp_path, trigger):
    """``kill -9`` of ``twin evaluate`` as soon as ``trigger`` appears: the folder has no
    manifest (or, had the run finished, one that agrees with its files); ``twin report`` says
    in one line that it is incomplete; a rerun with the same --out replaces it (checked once,
    it is the slow part)."""
    cfg = tmp_path / "long.toml"
    cfg.write_text(SMALL.format(horizon=1000))
    out = tmp_path / "run"
    cmd = [sys.executable, "-m", "twin", "evaluate", "--config", str(cfg), "--out", str(out)]
    env = {**os.environ, "PYTHONPATH": str(Path(__file__).resolve().parents[1])}
    proc = subprocess.Popen([*cmd, "--quiet", "--no-report"], env=env,
                            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)  # fmt: skip
    try:
        deadline = time.monotonic() + 60
        while not (out / trigger).exists() and proc.poll() is None:
            assert time.monotonic() < deadline, "the run never wrote " + trigger
            time.sleep(0.002)
        os.kill(proc.pid, signal.SIGKILL)
    finally:
        proc.wait()
    if (out / MANIFEST).exists():  # it finished before the kill: the manifest must hold
        assert trigger != "run.json"  # the start marker comes long before the end
        check_run_folder(out)
        return
    report = subprocess.run([sys.executable, "-m", "twin", "report", str(out)], env=env,
                            capture_output=True, text=True)  # fmt: skip
    assert report.returncode == 2
    lines = report.stderr.strip().splitlines()
    assert len(lines) == 1 and "incomplete run folder" in lines[0], report.stderr
    assert "Traceback" not in report.stderr
    if trigger != "run.json":
        return
    rerun = subprocess.run([*cmd, "--quiet", "--no-report"], env=env, capture_output=True)
    assert rerun.returncode == 0, rerun.stderr
    check_run_folder(out)


def test_a_zero_step_run_is_partial_and_has_nothing_to_report(tmp_path, capsys, tape_cfg):
    tape = tmp_path / "tape.parquet"
    good_tape(last=0).write(tape)  # T^0 only: not one step can run
    out = tmp_path / "out"
    argv = ["evaluate", "--config", str(tape_cfg), "--traffic", str(tape), "--out", str(out)]
    run_case(capsys, tmp_path, [*argv, "--quiet"], out, 1, "0 of 6 steps")
    assert check_run_folder(out)["partial"]
    run_case(capsys, tmp_path, ["report", str(out)], out, 2, "no step ran")


@pytest.fixture(scope="module")
def grid_net(tmp_path_factory) -> Path:
    from twin.sumo.network import generate_grid_scenario

    d = tmp_path_factory.mktemp("net")
    generate_grid_scenario(d, blocks=3, block_m=300, end_s=300, period_s=5.0, seed=1)
    (d / "c.toml").write_text(
        '[swarm]\nn_drones = 2\n[traffic]\nkind = "sumo"\nnet = "small.net.xml"\n'
        'cell_m = 200.0\ndrone_speed_kmh = 12.0\nbegin = "00:01"\nwarmup_min = 1.0\n'
        "horizon = 3\n"
    )
    return d


def test_routes_naming_unknown_edges_are_refused(tmp_path, capsys, grid_net):
    """SUMO refuses to start: one line naming the bad edge, exit 2, no run folder (not a
    zero-step folder claiming success)."""
    routes = tmp_path / "bad.rou.xml"
    routes.write_text('<routes>\n  <trip id="t0" depart="0" from="nowhere" to="x"/>\n</routes>\n')
    out = tmp_path / "out"
    argv = ["run", "--config", str(grid_net / "c.toml"), "--net", str(grid_net / "small.net.xml"),
            "--routes", str(routes), "--out", str(out), "--quiet", "--no-report"]  # fmt: skip
    assert main(argv) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert err[-1].startswith("twin: error:") and "'nowhere'" in err[-1]
    assert not out.exists()


@pytest.mark.parametrize("reader", ["history", "tape", "checkpoint"])
def test_a_pipe_given_as_a_file_twin_seeks_in_is_named_as_a_pipe(tmp_path, reader):
    """``--history <(cat h.npz)``, a tape or a checkpoint through a FIFO: refused as a pipe
    (the file itself is wanted), never as a file that does not exist; nothing blocks on it."""
    import os

    from twin.belief import History
    from twin.errors import UserError
    from twin.traffic.tape import Tape

    fifo = tmp_path / "pipe"
    os.mkfifo(fifo)
    if reader == "checkpoint":
        pytest.importorskip("torch")
        from twin.learning.checkpoint import load_qnet as read
    else:
        read = {"history": History.load, "tape": Tape.read}[reader]
    with pytest.raises(UserError, match="is a pipe or device, not a regular file") as caught:
        read(fifo)
    assert "\n" not in str(caught.value) and "no such" not in str(caught.value)


@pytest.mark.parametrize("flag", ["--sumocfg", "--net", "--routes", "--additional"])
def test_a_sumo_file_given_as_a_pipe_is_named_as_a_pipe(grid_net, tmp_path, capsys, flag):
    """``--routes <(cat r.rou.xml)`` or a FIFO: one line saying it is a pipe (SUMO reads files
    by name, more than once), never "not valid XML" or "no such SUMO config" (probe 12's q12);
    nothing blocks on it."""
    import os

    fifo = tmp_path / "pipe"
    os.mkfifo(fifo)
    argv = ["run", "--config", str(grid_net / "c.toml"), flag, str(fifo),
            "--out", str(tmp_path / "out"), "--quiet", "--no-report"]  # fmt: skip
    if flag in ("--routes", "--additional"):
        argv += ["--net", str(grid_net / "small.net.xml")]
    assert main(argv) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "is a pipe or device, not a regular file" in err[0], err
    assert str(fifo) in err[0]


#: [swarm_options.<swarm>] text -> words of the one line (the config and the table named)
SWARM_OPTION_CASES = {
    "an unknown option": ("lookahead]\nfoo = 1", "[swarm_options.lookahead] has an option 'foo'"),
    "options for a swarm that takes none": ("greedy]\nfoo = 2", "the greedy swarm takes none"),
    "an exhaustive lookahead too long": (
        "lookahead]\nbeam = 0",
        "[swarm_options.lookahead]: horizon = 8 with beam = 0",
    ),
    "an epsilon past 1": (
        "rl-decentralized]\neps = 2",
        "[swarm_options.rl-decentralized]: eps = 2",
    ),
    "an epsilon of text": ('rl-decentralized]\neps = "x"', "eps = 'x' must be a number"),
    "a discount of text": ('lookahead]\ndiscount = "a"', "discount = 'a' must be a number"),
    # the learned swarms' options and lookahead's numbers were not checked: tracebacks once the
    # run had begun, "false" read as true, a string read as a number (the review of probe 26)
    "a batch of 0": ("rl-online]\nbatch_size = 0", "rl-online]: batch_size = 0 must be in 1.."),
    "a negative batch": ("rl-online]\nbatch_size = -5", "batch_size = -5 must be in 1.."),
    "a negative rate": ("rl-online]\nlr = -1.0", "lr = -1.0 must lie in (0, 1]"),
    "negative iterations": ("rl-online]\nonline_iters = -3", "online_iters = -3 must be in"),
    "an empty buffer": ("rl-online]\nbuffer_steps = 0", "buffer_steps = 0 must be in 1.."),
    "a gamma of 50": ("rl-online]\ngamma = 50.0", "gamma = 50.0 must lie in [0, 1]"),
    "a batch of text": ('rl-online]\nbatch_size = "32"', "batch_size = '32' must be an integer"),
    "online as text": ('rl]\nonline = "false"', "online = 'false' must be true or false"),
    "decentralized as text": ('rl]\ndecentralized = "no"', "decentralized = 'no' must be true"),
    "a buffer past memory": (  # a 95 TiB buffer was "out of memory" (probe 26b's g03)
        "rl-online]\nbuffer_steps = 1000000000000",
        "buffer_steps = 1000000000000 must be in 1..1000000",
    ),
    "an outage of text": ('rl]\noutages = [["0", 3]]', "outage window ['0', 3] must be a pair"),
    "an epsilon of true": ("rl-decentralized]\neps = true", "eps = True must be a number"),
    "a discount as a string": ('lookahead]\ndiscount = "0.5"', "discount = '0.5' must be a"),
    "an end weight of true": ("lookahead]\nend_weight = true", "end_weight = True must be a"),
}


def test_an_open_topped_option_refuses_infinity_from_python():
    """A config refuses inf before the swarm sees it; from Python an open top took it (tours'
    ``bonus`` and ``shift``: the final reread of the option checks)."""
    from twin.errors import UserError
    from twin.swarms import make_policy

    for key in ("bonus", "shift", "stretch"):
        with pytest.raises(UserError, match=f"tours: {key} = inf must be a finite number"):
            make_policy("tours", **{key: float("inf")})


@pytest.mark.parametrize("case", list(SWARM_OPTION_CASES))
def test_a_bad_swarm_option_is_one_line_naming_the_table(tmp_path, capsys, case):
    """A swarm's options the swarm refuses: one line naming the config and its
    [swarm_options.<swarm>] (they named neither, showed Python's TypeError text, or were an
    internal error for a string where a number goes: probe 23's so-1)."""
    text, words = SWARM_OPTION_CASES[case]
    swarm = text.split("]")[0]
    cfg = tmp_path / "c.toml"
    cfg.write_text(SMALL.format(horizon=6).replace('["random", "greedy"]', f'["{swarm}"]')
                   + f"[swarm_options.{text}\n")  # fmt: skip
    code = main(["evaluate", "--config", str(cfg), "--no-report", "--quiet",
                 "--out", str(tmp_path / "run")])  # fmt: skip
    err = capsys.readouterr().err.strip()
    assert code == 2 and "\n" not in err and "Traceback" not in err, err
    assert err.startswith(f"twin: error: {cfg}: ") and words in err, err


def test_outages_given_as_an_array_are_step_pairs():
    """A numpy array of windows (the Python API) is read as pairs, as before the check."""
    import numpy as np

    from twin.idleness_maps import parse_outages

    assert parse_outages(np.array([[0, 3], [5, 7]])) == [(0, 3), (5, 7)]


def test_a_swarms_outages_past_the_horizon_are_refused(tmp_path, capsys):
    """``outages`` of a learned swarm past T were taken silently, as [faults]'
    coordinator_down is not (probe 26b's g04); the config that gives them is named."""
    cfg = tmp_path / "c.toml"
    cfg.write_text(SMALL.format(horizon=6).replace('["random", "greedy"]', '["rl"]')
                   + "[swarm_options.rl]\noutages = [[0, 7]]\n")  # fmt: skip
    code = main(["evaluate", "--config", str(cfg), "--no-report", "--quiet", "--no-ceiling",
                 "--out", str(tmp_path / "run")])  # fmt: skip
    err = capsys.readouterr().err.strip()
    assert code == 2 and "\n" not in err, err
    said = f"{cfg}: [swarm_options.rl].outages has [0, 7] past the horizon T = 6; end it by 6"
    assert err == f"twin: error: {said}", err


def test_a_bad_swarm_option_names_the_file_that_gives_it(tmp_path):
    """The config is named for an option it gives, also when a flag or a sweep adds others
    (``--history``: the file was dropped then); an option only the overrides give is not
    blamed on it; a swarm without a table of the config is not said to have one (the
    review of probe 23's fixes)."""
    from twin.config import ConfigError, load_config
    from twin.errors import UserError

    cfg = tmp_path / "c.toml"
    cfg.write_text(SMALL.format(horizon=6) + "[swarm_options.lookahead]\nwieght = 1\n")
    config = load_config(cfg)
    with pytest.raises(
        ConfigError, match=rf"^{cfg}: \[swarm_options.lookahead\] has an option 'wieght'"
    ):
        config.make_swarm("lookahead", horizon=2)
    cfg.write_text(SMALL.format(horizon=6) + "[swarm_options.lookahead]\nhorizon = 2\n")
    with pytest.raises(ConfigError, match=r"^\[swarm_options.lookahead\] has an option 'foo'"):
        load_config(cfg).make_swarm("lookahead", foo=1)
    with pytest.raises(UserError) as info:
        load_config(cfg).make_swarm("nowcast-gain")
    assert not str(info.value).startswith(str(cfg)), info.value


def test_bad_outages_given_beside_the_configs_options_are_not_blamed_on_it(tmp_path):
    """``outages`` a sweep or flag gives, refused by the swarm, were named as the config's
    whenever the config gave the swarm any other option: their message had no ``<swarm>: key
    =`` for the blame to read (the final reread)."""
    from twin.config import load_config
    from twin.errors import UserError

    cfg = tmp_path / "c.toml"
    cfg.write_text(SMALL.format(horizon=6) + "[swarm_options.rl-decentralized]\neps = 0.2\n")
    with pytest.raises(UserError) as info:
        load_config(cfg).make_swarm("rl-decentralized", outages=[[5, 3]])
    said = str(info.value)
    assert str(cfg) not in said and "outage window [5, 3] needs 0 <= start < stop" in said, said
