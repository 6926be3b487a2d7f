"""Property-based fuzzing of what twin reads: random edits of a run folder's files, of a
scenario config and of a sumocfg give exit 0 (or 1: a partial run) or one line and exit 2,
never a traceback, and never a change outside the run folder."""

from __future__ import annotations

import contextlib
import hashlib
import io
import json
import shutil
import tempfile
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

hypothesis = pytest.importorskip("hypothesis")
from hypothesis import HealthCheck, given, settings  # noqa: E402
from hypothesis import strategies as st  # noqa: E402

from twin.cli import main  # noqa: E402
from twin.resources import shipped_config  # noqa: E402
from twin.runs import write_manifest  # noqa: E402

FUZZ = settings(
    max_examples=40,
    deadline=None,
    suppress_health_check=[HealthCheck.function_scoped_fixture, HealthCheck.too_slow],
    derandomize=True,
)
SYNTHETIC = shipped_config("configs/synthetic.toml")


def tree_hash(folder: Path, skip: Path | None = None) -> str:
    digest = hashlib.sha256()
    for p in sorted(folder.rglob("*")):
        if skip is not None and (p == skip or skip in p.parents):
            continue
        digest.update(str(p.relative_to(folder)).encode())
        if p.is_file() and not p.is_symlink():
            digest.update(p.read_bytes())
    return digest.hexdigest()


def run_twin(argv: list[str]) -> tuple[int, str]:
    """``twin argv`` in this process: its exit code and stderr."""
    err = io.StringIO()
    with contextlib.redirect_stderr(err), contextlib.redirect_stdout(io.StringIO()):
        try:
            code = main(argv)
        except SystemExit as stop:
            code = stop.code
    return int(code or 0), err.getvalue()


def assert_clean(code: int, err: str, allowed=(0, 2)) -> None:
    assert "Traceback" not in err, err
    assert code in allowed, err
    if code == 2:
        lines = [x for x in err.strip().splitlines() if not x.startswith("twin: notice")]
        assert len(lines) == 1, err


def small_config(folder: Path, horizon: int = 10) -> Path:
    path = folder / "small.toml"
    path.write_text(SYNTHETIC.read_text().replace("horizon = 2000", f"horizon = {horizon}"))
    return path


@pytest.fixture(scope="module")
def run_folder(tmp_path_factory) -> Path:
    """One small `twin evaluate` run folder (2 seeds, 2 swarms), copied per example."""
    root = tmp_path_factory.mktemp("fuzz-run")
    out = root / "run"
    argv = ["evaluate", "--config", str(small_config(root)), "--swarms", "random,greedy"]
    code, err = run_twin([*argv, "--seeds", "2", "--out", str(out), "--no-report", "--quiet"])
    assert code == 0, err
    return out


# --- run folders ----------------------------------------------------------------------------

OPERATIONS = ("truncate", "delete_rows", "duplicate_rows", "nan", "string", "drop_column", "edit")
JUNK = st.sampled_from(["x", "", -1, 0, 1.5, -1e308, 1e308, None, [], {}, True, "NaN", [1, "a"]])


def edit_table(path: Path, op: str, data) -> None:
    frame = pd.read_parquet(path) if path.suffix == ".parquet" else pd.read_csv(path)
    if frame.empty:
        return
    column = data.draw(st.sampled_from(list(frame.columns)))
    row = data.draw(st.integers(0, len(frame) - 1))
    if op == "delete_rows":
        n = data.draw(st.integers(1, len(frame)))
        frame = frame.drop(frame.index[row : row + n])
    elif op == "duplicate_rows":
        frame = pd.concat([frame, frame.iloc[[row]]])
    elif op == "drop_column":
        frame = frame.drop(columns=[column])
    else:
        value = (
            float("nan")
            if op == "nan"
            else data.draw(st.sampled_from(["x", "", "1e999", "-5", "drone"]))
            if op == "string"
            else data.draw(st.sampled_from([-1, 10**6, 0.5, float("inf"), -(10**9)]))
        )
        frame[column] = frame[column].astype(object)
        frame.loc[frame.index[row], column] = value
    if path.suffix == ".parquet":
        try:
            frame.to_parquet(path, index=False)
        except Exception:  # a mixed column parquet cannot hold: as text
            frame.astype(str).to_parquet(path, index=False)
    else:
        frame.to_csv(path, index=False)


def edit_json(path: Path, data) -> None:
    doc = json.loads(path.read_text())
    node, depth = doc, 0
    while isinstance(node, (dict, list)) and node and depth < 4:
        keys = list(node) if isinstance(node, dict) else list(range(len(node)))
        key = data.draw(st.sampled_from(keys))
        child = node[key]
        if isinstance(child, (dict, list)) and child and data.draw(st.booleans()):
            node, depth = child, depth + 1
            continue
        if data.draw(st.booleans()) and isinstance(node, dict):
            del node[key]
        else:
            node[key] = data.draw(JUNK)
        break
    path.write_text(json.dumps(doc))


def edit_npz(path: Path, data) -> None:
    with np.load(path) as npz:
        arrays = dict(npz)
    key = data.draw(st.sampled_from(sorted(arrays)))
    a = arrays[key]
    choice = data.draw(st.integers(0, 5))
    arrays[key] = [
        a[:1],
        a.reshape(-1),
        a.astype(str),
        np.full(a.shape, np.nan),
        a[..., :-1],
        np.ones_like(a),
    ][choice]
    if data.draw(st.booleans()):
        del arrays[data.draw(st.sampled_from(sorted(arrays)))]
    np.savez(path, **arrays)


def damage(run: Path, data) -> None:
    files = sorted(p for p in run.rglob("*") if p.is_file() and p.name not in ("manifest.json",))
    path = data.draw(st.sampled_from(files))
    op = data.draw(st.sampled_from(OPERATIONS))
    if op == "truncate" or path.suffix not in (".parquet", ".csv", ".json", ".npz"):
        raw = path.read_bytes()
        path.write_bytes(raw[: data.draw(st.integers(0, max(len(raw) - 1, 0)))])
    elif path.suffix in (".parquet", ".csv"):
        edit_table(path, op, data)
    elif path.suffix == ".json":
        edit_json(path, data)
    else:
        edit_npz(path, data)


@FUZZ
@given(data=st.data())
def test_damaged_run_folder_never_tracebacks(run_folder: Path, data) -> None:
    with tempfile.TemporaryDirectory() as tmp:
        parent = Path(tmp)
        (parent / "neighbour.txt").write_text("not twin's")
        run = parent / "run"
        shutil.copytree(run_folder, run)
        for _ in range(data.draw(st.integers(1, 2))):
            damage(run, data)
        if data.draw(st.integers(0, 5)):  # mostly: the manifest agrees, the content must be checked
            write_manifest(run, False, None)
        command = data.draw(st.sampled_from(["report", "report", "replay"]))
        before = tree_hash(parent, skip=run)
        argv = [command, str(run)] + (["--no-animation"] if command == "report" else [])
        code, err = run_twin(argv)
        assert_clean(code, err)
        assert tree_hash(parent, skip=run) == before


# --- scenario configs -----------------------------------------------------------------------

VALUES = st.sampled_from(
    ['"x"', "-1", "0", "1e309", "-1e309", "nan", "inf", "[]", "{}", "true", "1.5", "99999999",
     '"random"', "[[0, 0]]", "[[99, 99]]", '[["a", 1]]', "2000"]
)  # fmt: skip


@FUZZ
@given(data=st.data())
def test_damaged_scenario_config_never_tracebacks(data) -> None:
    with tempfile.TemporaryDirectory() as tmp:
        folder = Path(tmp)
        lines = small_config(folder, horizon=8).read_text().splitlines()
        for _ in range(data.draw(st.integers(1, 3))):
            n = data.draw(st.integers(0, len(lines) - 1))
            op = data.draw(st.sampled_from(["value", "delete", "duplicate", "truncate"]))
            if op == "value" and "=" in lines[n]:
                key = lines[n].split("=", 1)[0]
                lines[n] = f"{key}= {data.draw(VALUES)}"
            elif op == "delete":
                del lines[n]
            elif op == "duplicate":
                lines.insert(n, lines[n])
            elif op == "truncate":
                lines = [*lines[:n], lines[n][: len(lines[n]) // 2]]
        config = folder / "small.toml"
        config.write_text("\n".join(lines) + "\n")
        run = folder / "run"
        before = tree_hash(folder, skip=run)
        argv = ["evaluate", "--config", str(config), "--swarms", "random,greedy"]
        code, err = run_twin([*argv, "--out", str(run), "--no-report", "--quiet"])
        assert_clean(code, err, allowed=(0, 1, 2))
        assert tree_hash(folder, skip=run) == before


# --- sumocfg ----------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def sumo_scenario(tmp_path_factory) -> Path:
    pytest.importorskip("libsumo")
    from helpers import small_sumo_scenario

    folder = small_sumo_scenario(tmp_path_factory.mktemp("fuzz-sumo"), horizon=2)
    (folder / "small.sumocfg").write_text(
        '<configuration>\n  <input>\n    <net-file value="small.net.xml"/>\n'
        '    <route-files value="small.trips.xml"/>\n  </input>\n'
        '  <time>\n    <begin value="0"/>\n    <end value="900"/>\n  </time>\n'
        "</configuration>\n"
    )
    return folder


SUMOCFG_EDITS = st.sampled_from(
    [
        ("small.net.xml", "missing.net.xml"),
        ("small.net.xml", ""),
        ("small.trips.xml", "small.net.xml"),
        ("small.trips.xml", "nope.xml"),
        ('<begin value="0"/>', '<begin value="x"/>'),
        ('<begin value="0"/>', '<begin value="-100"/>'),
        ('<end value="900"/>', '<end value="0"/>'),
        ('<end value="900"/>', '<end value="1e20"/>'),
        ("</configuration>", ""),
        ("<input>", "<inptu>"),
        ("<configuration>", "<configuration><additional-files value='gone.add.xml'/>"),
        ('value="small.trips.xml"', 'value="small.trips.xml,small.trips.xml"'),
        ("<time>", "<time><step-length value='0'/>"),
        ("<time>", "<time><step-length value='abc'/>"),
        ("<", "&"),
    ]
)


@settings(
    max_examples=25,
    deadline=None,
    suppress_health_check=[HealthCheck.function_scoped_fixture, HealthCheck.too_slow],
    derandomize=True,
)
@given(data=st.data())
def test_damaged_sumocfg_never_tracebacks(sumo_scenario: Path, data) -> None:
    with tempfile.TemporaryDirectory() as tmp:
        folder = Path(tmp)
        for name in ("small.net.xml", "small.trips.xml", "small.sumocfg"):
            shutil.copy(sumo_scenario / name, folder / name)
        cfg = folder / "small.sumocfg"
        text = cfg.read_text()
        for old, new in data.draw(st.lists(SUMOCFG_EDITS, min_size=1, max_size=2)):
            text = text.replace(old, new, 1)
        if data.draw(st.booleans()):
            text = text[: data.draw(st.integers(0, len(text)))]
        cfg.write_text(text)
        run = folder / "run"
        before = tree_hash(folder, skip=run)
        argv = ["run", "--sumocfg", str(cfg), "--horizon", "2", "--cell-m", "400"]
        argv += ["--drones", "1", "--swarms", "random", "--out", str(run), "--no-report"]
        code, err = run_twin([*argv, "--quiet"])
        assert_clean(code, err, allowed=(0, 1, 2))
        assert tree_hash(folder, skip=run) == before
