"""Property-based fuzzing of what twin reads: random edits of a run folder's files, of a
scenario config and of a sumocfg give exit 0 (or 1: a partial run) or one line and exit 2,
never a traceback, and never a change outside the run folder."""

from __future__ import annotations

import contextlib
import hashlib
import io
import json
import os
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

#: TWIN_FUZZ_EXAMPLES=500 runs that many random examples per test (the default: a fixed,
#: derandomized set, small enough for every test run).
EXAMPLES = int(os.environ.get("TWIN_FUZZ_EXAMPLES", "0"))


def fuzz(examples: int):
    return settings(
        max_examples=EXAMPLES or examples,
        deadline=None,
        suppress_health_check=[HealthCheck.function_scoped_fixture, HealthCheck.too_slow],
        derandomize=not EXAMPLES,
        database=None,
    )


FUZZ = fuzz(40)
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
    if code == 2:  # one line; a live run may have announced its simulation before it
        info = ("twin: notice", "SUMO: ")
        lines = [x for x in err.strip().splitlines() if not x.startswith(info)]
        assert len(lines) == 1 and lines[0].startswith("twin: error"), err


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
    if op != "truncate" and path.suffix in (".parquet", ".csv", ".json", ".npz"):
        edit = {".json": edit_json, ".npz": edit_npz}.get(path.suffix)
        try:
            edit(path, data) if edit else edit_table(path, op, data)
            return
        except Exception:  # a file an earlier edit broke: cut it shorter instead
            pass
    raw = path.read_bytes()
    path.write_bytes(raw[: data.draw(st.integers(0, max(len(raw) - 1, 0)))])


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


@fuzz(25)
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


# --- a live run's folder (replay) and its tape (evaluate --traffic) --------------------------


@pytest.fixture(scope="module")
def sumo_run(sumo_scenario: Path) -> Path:
    """One small `twin run` folder (2 steps, 2 swarms) over the small SUMO scenario."""
    out = sumo_scenario / "run"
    argv = ["run", "--config", str(sumo_scenario / "small.toml"), "--horizon", "2"]
    argv += ["--swarms", "random,greedy", "--out", str(out), "--no-report", "--quiet"]
    code, err = run_twin(argv)
    assert code == 0, err
    return out


def _no_gui(args, swarms, owned=None):
    from twin.errors import UserError

    raise UserError("the GUI is not started in tests")


@fuzz(30)
@given(data=st.data())
def test_damaged_live_run_folder_never_tracebacks(sumo_run: Path, monkeypatch, data) -> None:
    """`twin replay` of a damaged `twin run` folder (the GUI replaced by a refusal, so that an
    intact folder ends with one line too)."""
    monkeypatch.setattr("twin.cli.run.gui_drawer", _no_gui)
    with tempfile.TemporaryDirectory() as tmp:
        parent = Path(tmp)
        run = parent / "run"
        shutil.copytree(sumo_run, run)
        damage(run, data)
        if data.draw(st.integers(0, 5)):
            write_manifest(run, False, None)
        before = tree_hash(parent, skip=run)
        code, err = run_twin(["replay", str(run)])
        assert_clean(code, err)
        assert tree_hash(parent, skip=run) == before


@fuzz(8)
@given(data=st.data())
def test_damaged_live_run_folder_report_never_tracebacks(sumo_run: Path, data) -> None:
    """`twin report` of a damaged `twin run` folder: network.json, mfd.json, the MFD samples
    and the tape besides what a synthetic run has."""
    with tempfile.TemporaryDirectory() as tmp:
        parent = Path(tmp)
        run = parent / "run"
        shutil.copytree(sumo_run, run)
        damage(run, data)
        if data.draw(st.integers(0, 5)):
            write_manifest(run, False, None)
        before = tree_hash(parent, skip=run)
        code, err = run_twin(["report", str(run), "--no-animation"])
        assert_clean(code, err)
        assert tree_hash(parent, skip=run) == before


# network.json of a live run: (dotted key, implausible value, words of the one line)
NETWORK_JSON_CASES = {
    "a negative obstacle count": (("n_obstacles",), -1, "n_obstacles = -1 must be at least 0"),
    "cells of 0 m": (("grid", "cell_m"), 0, "grid.cell_m = 0 must be above 0"),
    "a grid of no rows": (("grid", "nx"), 0, "grid.nx = 0 must be at least 1"),
    "negative lane-km": (("grid", "lane_km_total"), -2.5, "grid.lane_km_total = -2.5"),
}


@pytest.mark.parametrize("case", list(NETWORK_JSON_CASES))
def test_implausible_network_json_is_one_line(sumo_run: Path, tmp_path: Path, case) -> None:
    keys, value, words = NETWORK_JSON_CASES[case]
    run = tmp_path / "run"
    shutil.copytree(sumo_run, run)
    network = json.loads((run / "network.json").read_text())
    node = network
    for key in keys[:-1]:
        node = node[key]
    node[keys[-1]] = value
    (run / "network.json").write_text(json.dumps(network))
    write_manifest(run, False, None)
    before = tree_hash(tmp_path)
    code, err = run_twin(["report", str(run), "--no-animation"])
    assert code == 2 and err.count("\n") == 1 and "Traceback" not in err, err
    assert f"{run / 'network.json'}: {words}" in err, err
    assert tree_hash(tmp_path) == before  # nothing written, the run folder included


def edit_tape(path: Path, data) -> None:
    """An edit of the tape's rows that keeps its twin metadata (or, sometimes, edits that)."""
    import pyarrow as pa
    import pyarrow.parquet as pq

    table = pq.read_table(path)
    meta = dict(table.schema.metadata or {})
    frame = table.to_pandas()
    tmp = path.with_suffix(".edit.parquet")
    frame.to_parquet(tmp, index=False)
    edit_table(tmp, data.draw(st.sampled_from(OPERATIONS[1:6])), data)
    frame = pd.read_parquet(tmp)
    tmp.unlink()
    if b"twin_tape" in meta and data.draw(st.booleans()):
        doc = json.loads(meta[b"twin_tape"])
        key = data.draw(st.sampled_from(sorted(doc)))
        doc[key] = data.draw(JUNK)
        meta[b"twin_tape"] = json.dumps(doc).encode()
    edited = pa.Table.from_pandas(frame, preserve_index=False)
    pq.write_table(edited.replace_schema_metadata(meta), path)


@fuzz(30)
@given(data=st.data())
def test_damaged_tape_never_tracebacks(sumo_run: Path, data) -> None:
    with tempfile.TemporaryDirectory() as tmp:
        folder = Path(tmp)
        tape = folder / "tape.parquet"
        shutil.copy(sumo_run / "tape.parquet", tape)
        if data.draw(st.integers(0, 4)):
            edit_tape(tape, data)
        else:
            raw = tape.read_bytes()
            tape.write_bytes(raw[: data.draw(st.integers(0, len(raw) - 1))])
        run = folder / "run"
        before = tree_hash(folder, skip=run)
        argv = ["evaluate", "--traffic", str(tape), "--swarms", "random,greedy"]
        code, err = run_twin([*argv, "--out", str(run), "--no-report", "--quiet"])
        assert_clean(code, err, allowed=(0, 1, 2))
        assert tree_hash(folder, skip=run) == before


# --- checkpoints ------------------------------------------------------------------------------


def edit_checkpoint(blob: dict, data) -> dict:
    import torch

    part = data.draw(st.sampled_from(["meta", "weights", "top"]))
    if part == "top":
        key = data.draw(st.sampled_from(sorted(blob)))
        blob[key] = data.draw(st.sampled_from([None, [], {}, "x", 3]))
    elif part == "meta":
        key = data.draw(st.sampled_from(sorted(blob["meta"])))
        if data.draw(st.booleans()):
            del blob["meta"][key]
        else:
            blob["meta"][key] = data.draw(
                st.sampled_from([None, [], "x", -1, 2.5, [13, 7, 5], [13, "a", 5], True])
            )
    else:
        key = data.draw(st.sampled_from(sorted(blob["weights"])))
        value = blob["weights"][key]
        blob["weights"][key] = data.draw(
            st.sampled_from(
                [
                    value[..., :-1],
                    value.reshape(-1),
                    torch.full_like(value, float("nan")),
                    value.to(torch.int64),
                    "x",
                ]
            )
        )
        if data.draw(st.booleans()):
            del blob["weights"][key]
    return blob


@pytest.fixture(scope="module")
def checkpoint_blob():
    torch = pytest.importorskip("torch")
    from twin.learning.checkpoint import default_checkpoint

    return torch.load(default_checkpoint(), map_location="cpu", weights_only=True)


@fuzz(30)
@given(data=st.data())
def test_damaged_checkpoint_never_tracebacks(checkpoint_blob, data) -> None:
    import copy

    import torch

    with tempfile.TemporaryDirectory() as tmp:
        folder = Path(tmp)
        path = folder / "qnet.pt"
        if data.draw(st.integers(0, 4)):
            torch.save(edit_checkpoint(copy.deepcopy(checkpoint_blob), data), path)
        else:
            torch.save(checkpoint_blob, path)
            raw = path.read_bytes()
            path.write_bytes(raw[: data.draw(st.integers(0, len(raw) - 1))])
        config = small_config(folder, horizon=4)
        config.write_text(config.read_text() + '\n[swarm_options.rl]\ncheckpoint = "qnet.pt"\n')
        run = folder / "run"
        before = tree_hash(folder, skip=run)
        argv = ["evaluate", "--config", str(config), "--swarms", "rl"]
        code, err = run_twin([*argv, "--out", str(run), "--no-report", "--quiet"])
        assert_clean(code, err, allowed=(0, 1, 2))
        assert tree_hash(folder, skip=run) == before


class _Hostile:
    """A pickle that would create a file when unpickled."""

    def __init__(self, marker: Path) -> None:
        self.marker = marker

    def __reduce__(self):
        return (Path.touch, (self.marker,))


def test_a_hostile_checkpoint_is_refused_in_one_line_and_never_run(tmp_path) -> None:
    import pickle
    import warnings

    marker = tmp_path / "was-run"
    path = tmp_path / "qnet.pt"
    path.write_bytes(pickle.dumps({"meta": {}, "weights": _Hostile(marker)}, protocol=4))
    config = small_config(tmp_path, horizon=4)
    config.write_text(config.read_text() + '\n[swarm_options.rl]\ncheckpoint = "qnet.pt"\n')
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        code, err = run_twin(["evaluate", "--config", str(config), "--swarms", "rl", "--out",
                              str(tmp_path / "run"), "--no-report", "--quiet"])  # fmt: skip
    assert_clean(code, err, allowed=(2,))
    assert "is corrupt or not a torch file (UnpicklingError: Unsupported operand" in err, err
    assert not marker.exists()
    assert [str(w.message)[:80] for w in caught] == []  # torch's own warning is not printed


def test_a_checkpoint_of_a_whole_module_is_one_plain_line(tmp_path) -> None:
    """``torch.save(model)`` pickles the module: refused, saying so, without torch's advice to
    load it unsafely and its terminal colours (probe 27's f01)."""
    import torch

    torch.save(torch.nn.Linear(13, 5), tmp_path / "qnet.pt")
    config = small_config(tmp_path, horizon=4)
    config.write_text(config.read_text() + '\n[swarm_options.rl]\ncheckpoint = "qnet.pt"\n')
    code, err = run_twin(["evaluate", "--config", str(config), "--swarms", "rl", "--out",
                          str(tmp_path / "run"), "--no-report", "--quiet"])  # fmt: skip
    assert_clean(code, err, allowed=(2,))
    assert "holds Python objects beyond tensors" in err and "\x1b" not in err, err
    assert "weights_only" not in err and "trust" not in err, err


def test_layers_far_larger_than_the_weights_are_refused_before_allocation(
    checkpoint_blob, tmp_path
) -> None:
    """meta.layers of 160 GB against the stored few kB: refused by counting, not by torch
    failing to allocate."""
    import copy

    import torch

    from twin.errors import UserError
    from twin.learning.checkpoint import load_qnet

    blob = copy.deepcopy(checkpoint_blob)
    blob["meta"]["layers"] = [13, 200_000, 200_000, 5]
    torch.save(blob, tmp_path / "qnet.pt")
    with pytest.raises(UserError, match=r"needs 40,004,000,005 weights, the file holds"):
        load_qnet(tmp_path / "qnet.pt")
