"""`twin sweep`: the cells equal `twin evaluate`, local pool and Ray agree, a sweep resumes."""

from __future__ import annotations

import json
import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import pandas as pd
import pytest

from twin.cli import main as cli
from twin.errors import UserError
from twin.sweep import done_cells, expand_cells, load_sweep_config, run_sweep

ROOT = Path(__file__).resolve().parents[1]


def scenario_file(tmp: Path, horizon: int = 30, n_drones: int = 3) -> Path:
    """configs/synthetic.toml with a short horizon (a file `twin evaluate` can take as is)."""
    text = (ROOT / "configs" / "synthetic.toml").read_text()
    text = text.replace("horizon = 2000", f"horizon = {horizon}")
    text = text.replace("n_drones = 4", f"n_drones = {n_drones}")
    path = tmp / "scenario.toml"
    path.write_text(text)
    return path


def sweep_file(tmp: Path, seeds: int = 2, parameters: str = "", horizon: int = 30) -> Path:
    scenario = scenario_file(tmp, horizon)
    path = tmp / "sweep.toml"
    path.write_text(
        f"""
[sweep]
name = "t"
swarms = ["random", "greedy", "sweeping"]
seeds = {seeds}

[[scenario]]
name = "syn"
config = "{scenario.name}"

[parameters]
{parameters}
"""
    )
    return path


def numbers(sweep_dir: Path) -> pd.DataFrame:
    frame = pd.read_csv(sweep_dir / "results.csv").drop(columns=["seconds"])
    return frame.sort_values(["cell", "swarm"]).reset_index(drop=True)


def test_cells_equal_twin_evaluate(tmp_path: Path) -> None:
    config = load_sweep_config(sweep_file(tmp_path, seeds=2))
    outcome = run_sweep(config, tmp_path / "sweep", workers=2)
    assert len(outcome.ran) == 2 and not outcome.skipped
    run = tmp_path / "eval"
    args = ["evaluate", "--config", str(tmp_path / "scenario.toml"), "--seeds", "2"]
    args += ["--swarms", "random,greedy,sweeping"]
    assert cli([*args, "--out", str(run), "--no-report", "--quiet", "--no-ceiling"]) == 0
    expected = (
        pd.read_csv(run / "per_seed.csv").sort_values(["seed", "swarm"]).reset_index(drop=True)
    )
    got = numbers(tmp_path / "sweep").sort_values(["seed", "swarm"]).reset_index(drop=True)
    for col in ("R_hat_T", "C_hat_T", "pct_time_max_C", "pct_map_covered"):
        assert got[col].tolist() == pytest.approx(expected[col].tolist(), rel=1e-12, abs=1e-12)
    # the merged summary is the mean over seeds of those rows, with intervals
    summary = pd.read_csv(tmp_path / "sweep" / "summary.csv")
    for swarm, rows in got.groupby("swarm"):
        row = summary[summary["swarm"] == swarm].iloc[0]
        assert row["R_hat_T"] == pytest.approx(rows["R_hat_T"].mean())
        assert row["n_seeds"] == 2 and row["R_hat_T_ci95"] > 0


def test_sweep_report_table_equals_summary(tmp_path: Path) -> None:
    config = load_sweep_config(
        sweep_file(tmp_path, seeds=2, parameters='"swarm.n_drones" = [2, 3]')
    )
    run_sweep(config, tmp_path / "s", workers=2)
    summary = pd.read_csv(tmp_path / "s" / "summary.csv")
    md = (tmp_path / "s" / "report" / "sweep.md").read_text()
    lines = [ln for ln in md.splitlines() if ln.startswith("| syn |")]
    assert len(lines) == len(summary) == 6
    for line, (_, row) in zip(lines, summary.iterrows(), strict=True):
        cells = [c.strip() for c in line.strip("|").split("|")]
        assert int(cells[1]) == row["swarm.n_drones"] and cells[2] == row["swarm"]
        mean, half = (float(x) for x in cells[3].split("±"))
        assert abs(mean - row["R_hat_T"]) <= 5e-5 and abs(half - row["R_hat_T_ci95"]) <= 5e-5
    html = (tmp_path / "s" / "report" / "sweep.html").read_text()
    assert html.count('<img src="data:image/png;base64,') == 2


@pytest.fixture(scope="module")
def swept(tmp_path_factory) -> Path:
    """A finished sweep folder with its report (2 seeds)."""
    tmp = tmp_path_factory.mktemp("swept")
    run_sweep(load_sweep_config(sweep_file(tmp, seeds=2)), tmp / "s", workers=1)
    return tmp / "s"


def _disk_fills_at(monkeypatch, name: str) -> None:
    """The disk fills while the sweep report writes ``name`` (a figure or a page)."""
    import errno

    import matplotlib.figure

    import twin.report.sweep as sweep_report

    def full(path):
        raise OSError(errno.ENOSPC, "No space left on device", str(path))

    real_save, real_write = matplotlib.figure.Figure.savefig, sweep_report.atomic_write

    def savefig(self, path, *args, **kwargs):
        return full(path) if Path(path).name == name else real_save(self, path, *args, **kwargs)

    def atomic_write(path, write):
        return real_write(path, (lambda p: full(p)) if Path(path).name == name else write)

    monkeypatch.setattr(matplotlib.figure.Figure, "savefig", savefig)
    monkeypatch.setattr(sweep_report, "atomic_write", atomic_write)


@pytest.mark.parametrize("earlier", [False, True], ids=["first report", "earlier report"])
@pytest.mark.parametrize("name", ["table2.png", "curves.png", "sweep.html", "sweep.md"])
def test_full_disk_during_the_sweep_report_leaves_no_partial_report(
    swept, tmp_path, monkeypatch, capsys, name, earlier
) -> None:
    """The sweep report is drawn aside and renamed into place, as a run's report: a failure
    mid-way is one line naming the report's file, and leaves the earlier report or none."""
    import shutil

    out = tmp_path / "s"
    shutil.copytree(swept, out)
    if not earlier:
        shutil.rmtree(out / "report")
    before = {p.name: p.read_bytes() for p in (out / "report").iterdir()} if earlier else None
    _disk_fills_at(monkeypatch, name)
    capsys.readouterr()
    argv = ["sweep", "--config", str(swept.parent / "sweep.toml"), "--out", str(out), "--quiet"]
    assert cli(argv) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and err.startswith("twin: error: "), err
    assert f"{out / 'report' / name}: No space left on device" in err and ".tmp" not in err, err
    if earlier:
        assert {p.name: p.read_bytes() for p in (out / "report").iterdir()} == before
    else:
        assert not (out / "report").exists()
    assert not [p for p in out.iterdir() if p.name.startswith(".report")]


def test_a_users_file_in_the_sweep_report_is_refused_and_kept(swept, tmp_path, capsys):
    """A rerun of the sweep draws its report again: a file of the user's in report/ is refused
    in one line and kept (it was deleted with the old report)."""
    import shutil

    out = tmp_path / "s"
    shutil.copytree(swept, out)
    (out / "report" / "notes.txt").write_text("mine")
    capsys.readouterr()
    argv = ["sweep", "--config", str(swept.parent / "sweep.toml"), "--out", str(out), "--quiet"]
    assert cli(argv) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and f"{out / 'report' / 'notes.txt'}: not written by twin" in err
    assert (out / "report" / "notes.txt").read_text() == "mine"
    assert (out / "report" / "sweep.html").is_file()


def tiny_checkpoint(path: Path) -> Path:
    """A small Q-network checkpoint (13 -> 16 -> 5), so the learning swarm runs in seconds."""
    import torch

    from twin.learning.checkpoint import model_metadata, save_model
    from twin.learning.qnet import QNetwork

    torch.manual_seed(0)
    layers = (13, 16, 5)
    save_model(path, QNetwork(layers).state_dict(), model_metadata(layers, {}, seed=0, epoch=0))
    return path


def test_local_pool_and_ray_give_identical_results(tmp_path: Path, capfd) -> None:
    """Baselines and an online-learning swarm (torch) give the same numbers on both executors;
    Ray writes nothing on the terminal (no log or warning lines)."""
    pytest.importorskip("ray", reason="Ray not installed (pip install 'twin[ray]')")
    path = sweep_file(tmp_path, seeds=1, parameters='"swarm.eta" = [0.1, 0.2]')
    tiny_checkpoint(tmp_path / "tiny.pt")
    text = path.read_text().replace('"sweeping"]', '"sweeping", "rl-online"]')
    path.write_text(text + '\n[swarm_options.rl-online]\ncheckpoint = "tiny.pt"\n')
    config = load_sweep_config(path)
    local = run_sweep(config, tmp_path / "local", executor="local", workers=2, report=False)
    capfd.readouterr()
    ray = run_sweep(config, tmp_path / "ray", executor="ray", workers=2, report=False)
    assert capfd.readouterr().err == ""
    assert sorted(local.ran) == sorted(ray.ran) and len(local.ran) == 2
    got = numbers(tmp_path / "local")
    assert set(got["swarm"]) == {"random", "greedy", "sweeping", "rl-online"}
    pd.testing.assert_frame_equal(got, numbers(tmp_path / "ray"))


@pytest.mark.parametrize("cache", ["short", "deep", "relative"])
def test_a_local_ray_leaves_nothing_outside_twin_s_cache(tmp_path: Path, monkeypatch, cache):
    """A local Ray keeps its session in twin's scratch folder and removes it after; when that
    folder is too deep for Ray's socket paths, in Ray's own (under $TMPDIR), removed after as
    well (it was left in /tmp/ray, one more per run: probe 23's f05)."""
    import tempfile

    pytest.importorskip("ray", reason="Ray not installed (pip install 'twin[ray]')")
    from twin.executors import ray_tasks

    short = Path(tempfile.mkdtemp(prefix="t", dir="/tmp"))  # Ray's sockets need short paths
    try:
        system = short / "sys"
        system.mkdir()
        twin_cache = {"short": short / "c", "deep": tmp_path / ("deep" * 12) / "cache",
                      "relative": Path("c")}[cache]  # fmt: skip
        monkeypatch.chdir(short)  # a relative cache: Ray takes no relative folder
        monkeypatch.setenv("TWIN_CACHE_DIR", str(twin_cache))
        monkeypatch.setenv("TMPDIR", str(system))
        monkeypatch.delenv("RAY_TMPDIR", raising=False)
        got = sorted(value for _, value, _ in ray_tasks(lambda x: -x, [(-1,), (-2,)], workers=1))
        assert got == [1, 2]
        assert list(system.iterdir()) == []
        assert not (short / twin_cache / "tmp" / "twin-ray").exists()
    finally:
        shutil.rmtree(short, ignore_errors=True)


def test_a_local_ray_under_folders_too_deep_for_its_sockets_is_one_line(tmp_path, monkeypatch):
    """twin's cache and $TMPDIR both too deep for Ray's socket paths (107 bytes): one line
    naming the cache and how short it must be, not Ray's traceback (probe 23's f06)."""
    from twin.executors import _local_ray_folder

    monkeypatch.setenv("TWIN_CACHE_DIR", str(tmp_path / ("deep" * 12) / "cache"))
    monkeypatch.setenv("TMPDIR", str(tmp_path / ("deep" * 12)))
    with pytest.raises(
        UserError, match=r"set \$TWIN_CACHE_DIR to a folder of at most 30 characters"
    ):
        _local_ray_folder()


def test_restart_runs_only_missing_cells(tmp_path: Path) -> None:
    config = load_sweep_config(sweep_file(tmp_path, seeds=3))
    first = run_sweep(config, tmp_path / "s", workers=2, report=False)
    before = numbers(tmp_path / "s")
    victim = sorted(first.ran)[1]
    (tmp_path / "s" / "cells" / f"{victim}.json").unlink()
    again = run_sweep(config, tmp_path / "s", workers=2, report=False)
    assert again.ran == [victim]
    assert sorted(again.skipped) == sorted(set(first.ran) - {victim})
    pd.testing.assert_frame_equal(numbers(tmp_path / "s"), before)
    nothing = run_sweep(config, tmp_path / "s", workers=2, report=False)
    assert nothing.ran == [] and len(nothing.skipped) == 3


def test_a_resumed_sweep_computes_again_cells_whose_files_changed(tmp_path: Path) -> None:
    """A cell is its scenario file's content, not its name: an edited scenario, a replaced
    tape give new cells (the old numbers were kept, exit 0), equal to a fresh sweep's."""
    from helpers import random_tape

    path = sweep_file(tmp_path, seeds=1)
    random_tape(seed=0, nx=20, ny=30, horizon=30, obstacle=(0, 0)).write(tmp_path / "t.parquet")
    text = path.read_text().replace('config = "scenario.toml"', 'config = "scenario.toml"\n'
                                    '[[scenario]]\nname = "tape"\nconfig = "scenario.toml"\n'
                                    'tape = "t.parquet"')  # fmt: skip
    path.write_text(text)
    first = run_sweep(load_sweep_config(path), tmp_path / "s", workers=1, report=False)
    assert len(first.ran) == 2
    scenario = tmp_path / "scenario.toml"
    scenario.write_text(scenario.read_text().replace("amplitude = 1.0", "amplitude = 0.3", 1))
    random_tape(seed=1, nx=20, ny=30, horizon=30, obstacle=(0, 0)).write(tmp_path / "t.parquet")
    again = run_sweep(load_sweep_config(path), tmp_path / "s", workers=1, report=False)
    assert len(again.ran) == 2 and not again.skipped
    assert not set(again.ran) & set(first.ran)
    run_sweep(load_sweep_config(path), tmp_path / "fresh", workers=1, report=False)
    pd.testing.assert_frame_equal(numbers(tmp_path / "s"), numbers(tmp_path / "fresh"))


def test_a_live_cell_whose_sumo_files_changed_is_not_done(tmp_path: Path) -> None:
    """A finished live cell records the SUMO files it loaded and their hashes (its traffic
    identity); a resumed sweep runs it again when one has changed or gone."""
    from twin.files import file_sha256
    from twin.sweep.store import inputs_changed

    routes = tmp_path / "a.rou.xml"
    routes.write_text("<routes/>")
    entry = {"role": "route file", "path": str(routes), "sha256": file_sha256(routes)}
    record = {"traffic": {"identity": {"files": [entry]}}}
    assert inputs_changed(record) is None
    assert inputs_changed({"traffic": None}) is None  # a synthetic cell: nothing to check
    routes.write_text('<routes><vType id="x"/></routes>')
    assert inputs_changed(record) == f"route file {routes}"
    routes.unlink()
    assert inputs_changed(record) == f"route file {routes}"


def _record(change):
    """A cell JSON edited by ``change(record)``, still well-formed."""

    def damage(data: bytes) -> bytes:
        record = json.loads(data)
        change(record)
        return json.dumps(record).encode()

    return damage


def _frame(change):
    """A cell series edited by ``change(frame)``."""

    def damage(data: bytes) -> bytes:
        import io

        out = io.BytesIO()
        change(pd.read_parquet(io.BytesIO(data))).to_parquet(out, index=False)
        return out.getvalue()

    return damage


def _series(data: bytes) -> bytes:
    import io

    frame = pd.read_parquet(io.BytesIO(data))
    frame["reward"] *= 2
    out = io.BytesIO()
    frame.to_parquet(out, index=False)
    return out.getvalue()


DAMAGED_CELLS = {
    "JSON cut short": (".json", lambda b: b[: len(b) // 2], "not valid JSON"),
    "series cut short": (".parquet", lambda b: b[: len(b) // 2], ".parquet"),
    "series of another kind": (".parquet", lambda b: b"not parquet", ".parquet"),
    "a score edited": (
        ".json",
        _record(lambda r: r["rows"][0].update(R_hat_T=99.0)),
        "has R_hat_T = 99, its series",
    ),
    "a score not a number": (
        ".json",
        _record(lambda r: r["rows"][0].update(R_hat_T="x")),
        "rows' R_hat_T holds 'x', not a number",
    ),
    "another seed": (".json", _record(lambda r: r["cell"].update(seed=7)), "its id"),
    "a swarm's row gone": (".json", _record(lambda r: r["rows"].pop()), "rows of swarms"),
    "rewards of the series changed": (".parquet", _series, "cumulative_reward is not its"),
    # probe 16's f06: other columns were taken as they were
    "coverage text": (".json", _record(lambda r: r["rows"][0].update(C_hat_T="x")),
                      "rows' C_hat_T holds 'x', not a number"),
    "coverage emptied": (".json", _record(lambda r: r["rows"][0].update(C_hat_T=None)),
                         "has C_hat_T = nan, its series give"),
    "coverage edited": (".json", _record(lambda r: r["rows"][0].update(pct_map_covered=1.5)),
                        "has pct_map_covered = 1.5, its series give"),
    "series coverage past 1": (".parquet", _frame(lambda f: f.assign(coverage=5.0)),
                               "coverage holds values outside 0 .. 1"),
    "series rows of another seed added": (
        ".parquet", _frame(lambda f: pd.concat([f, f.assign(seed=7)])), "rows of seeds [0, 7]"),
    "inputs emptied": (".json", _record(lambda r: r["cell"].update(inputs={})),
                       "cell.inputs = {} is not the cell's"),
}  # fmt: skip


@pytest.mark.parametrize("case", list(DAMAGED_CELLS))
def test_a_damaged_cell_is_reported_and_computed_again(tmp_path: Path, capsys, case) -> None:
    """A cell whose files were damaged after it finished is not taken as done: the rerun says
    so in one line and computes it again, with the numbers of the first run."""
    suffix, damage, words = DAMAGED_CELLS[case]
    config = load_sweep_config(sweep_file(tmp_path, seeds=2))
    first = run_sweep(config, tmp_path / "s", workers=1, report=False)
    before = numbers(tmp_path / "s")
    victim = sorted(first.ran)[0]
    path = tmp_path / "s" / "cells" / f"{victim}{suffix}"
    path.write_bytes(damage(path.read_bytes()))
    capsys.readouterr()
    again = run_sweep(config, tmp_path / "s", workers=1, report=False)
    notes = [x for x in capsys.readouterr().err.splitlines() if "damaged" in x]
    assert again.ran == [victim], notes
    assert len(notes) == 1 and f"sweep cell {victim} is damaged" in notes[0], notes
    assert words in notes[0] and notes[0].endswith("computing it again")
    pd.testing.assert_frame_equal(numbers(tmp_path / "s"), before)


def test_a_stray_cell_record_is_left_alone(tmp_path: Path, capsys) -> None:
    """A record in cells/ that is no cell of the sweep is neither read nor merged (it was said
    to be damaged and "computed again", which no cell was; probe 16's f06)."""
    config = load_sweep_config(sweep_file(tmp_path, seeds=1))
    first = run_sweep(config, tmp_path / "s", workers=1, report=False)
    before = numbers(tmp_path / "s")
    (tmp_path / "s" / "cells" / "zzz.json").write_text("{}")
    capsys.readouterr()
    again = run_sweep(config, tmp_path / "s", workers=1, report=False)
    assert again.ran == [] and first.ran
    assert "zzz" not in capsys.readouterr().err
    pd.testing.assert_frame_equal(numbers(tmp_path / "s"), before)


def test_killed_sweep_resumes(tmp_path: Path) -> None:
    path = sweep_file(tmp_path, seeds=6, horizon=400)
    out = tmp_path / "s"
    cmd = [sys.executable, "-m", "twin", "sweep", "--config", str(path), "--out", str(out)]
    proc = subprocess.Popen(
        [*cmd, "--workers", "1", "--quiet", "--no-report"],
        stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, start_new_session=True,
    )  # fmt: skip
    try:
        deadline = time.monotonic() + 90
        while not done_cells(out) and time.monotonic() < deadline and proc.poll() is None:
            time.sleep(0.2)
    finally:
        os.killpg(proc.pid, signal.SIGKILL)  # the sweep and its pool worker, nothing else
        proc.wait()
    finished = done_cells(out)
    assert 1 <= len(finished) < 6, "kill the sweep while cells remain"
    config = load_sweep_config(path)
    resumed = run_sweep(config, out, workers=2, report=False)
    assert set(resumed.skipped) == finished
    assert len(resumed.ran) == 6 - len(finished)
    ids = {c["id"] for c in expand_cells(config, out)}
    assert done_cells(out) == ids
    assert len(pd.read_csv(out / "results.csv")) == 6 * 3


@pytest.mark.parametrize(
    ("text", "message"),
    [
        ('[sweep]\nname = "x"\nswarms = ["nope"]\n', "unknown swarm 'nope'"),
        ('[sweep]\nswarms = ["greedy"]\nseeds = 0\n', "[sweep].seeds = 0 must be at least 1"),
        (  # past SUMO's seeds: it failed in every cell with an OverflowError (probe 19's f03)
            '[sweep]\nswarms = ["greedy"]\nseeds = [9223372036854775808]\n',
            "[sweep].seeds = [9223372036854775808] holds seed 9223372036854775808, out of range; "
            "seeds are whole numbers from 0 to 2147483647",
        ),
        ('[sweep]\nswarms = ["greedy"]\nseeds = [-1]\n', "holds seed -1, out of range"),
        (
            '[sweep]\nswarms = ["greedy"]\nseed = 2147483647\nseeds = 2\n',
            "runs seeds 2147483647 .. 2147483648, past the largest seed 2147483647; give at most 1",
        ),
        (  # the count it suggests is one the sweep's cell limit then takes
            '[sweep]\nswarms = ["greedy"]\nseeds = 4294967296\n',
            "past the largest seed 2147483647; give at most 100000",
        ),
        ('[sweep]\nswarms = ["greedy"]\nseed = 2147483648\n', "[sweep].seed = 2147483648 must be"),
        ('[sweep]\nswarms = ["greedy"]\n', "[[scenario]] is missing"),
        (
            '[sweep]\nswarms = ["greedy"]\nseeds = 100000000\n[[scenario]]\nname = "a"\n'
            'config = "scenario.toml"\n',
            "the sweep expands to 100,000,000 cells (1 scenarios x 1 parameter combinations x "
            "100,000,000 seeds), over the 100,000 one sweep folder holds",
        ),
        (
            '[sweep]\nswarms = ["greedy"]\n[[scenario]]\nname = "a"\nconfig = "missing.toml"\n',
            "does not exist",
        ),
        (  # a folder was said not to exist (probe 27's f02)
            '[sweep]\nswarms = ["greedy"]\n[[scenario]]\nname = "a"\nconfig = "."\n',
            "which is a folder, not a file; fix the path",
        ),
        (
            '[sweep]\nswarms = ["greedy"]\n[[scenario]]\nname = "a"\nconfig = "scenario.toml"\n'
            '[parameters]\n"n_drones" = [1]\n',
            # once, not twice (the review of probe 26)
            "[parameters].'n_drones': overrides reach the grid, swarm, traffic, evaluate tables",
        ),
        (
            '[sweep]\nswarms = ["greedy"]\n[[scenario]]\nname = "a"\nconfig = "scenario.toml"\n'
            '[parameters]\n"swarm.n_drones" = [2, 3, 2]\n',
            "'swarm.n_drones' lists 2 twice",
        ),
        (
            '[sweep]\nswarms = ["greedy"]\n[[scenario]]\nname = "a"\nconfig = "scenario.toml"\n'
            '[parameters]\n"grid.obstacles" = [[[1, 1]], [], [[1, 1]]]\n',
            "'grid.obstacles' lists [[1, 1]] twice",
        ),
        # over a tape, a traffic key changes nothing: every value gave the same rows, labelled
        # as if it did (probe 16's f11)
        (
            '[sweep]\nswarms = ["greedy"]\n[[scenario]]\nname = "t"\nconfig = "scenario.toml"\n'
            'tape = "t.parquet"\n[parameters]\n"traffic.cell_m" = [100.0, 200.0]\n',
            "[parameters].'traffic.cell_m' sets the traffic of [[scenario]] 't', which replays "
            "the tape",
        ),
        (
            '[sweep]\nswarms = ["greedy"]\n[[scenario]]\nname = "t"\nconfig = "scenario.toml"\n'
            'tape = "t.parquet"\n[parameters]\n"grid.obstacles" = [[], [[1, 1]]]\n',
            "[parameters].'grid.obstacles' sets the traffic of [[scenario]] 't'",
        ),
        (
            '[sweep]\nswarms = ["greedy"]\n[[scenario]]\nname = "t"\nconfig = "scenario.toml"\n'
            'tape = "t.parquet"\noverrides = { "traffic.horizon" = 10 }\n',
            "[[scenario]] t.overrides.'traffic.horizon' sets the traffic of [[scenario]] 't'",
        ),
        # keys each cell sets itself: the cells of every value ran alike (probe 18's f10)
        (
            '[sweep]\nswarms = ["greedy"]\n[[scenario]]\nname = "a"\nconfig = "scenario.toml"\n'
            '[parameters]\n"traffic.seed" = [0, 1]\n',
            "[parameters].'traffic.seed' is set by the sweep itself, the seed of each cell's "
            "traffic being its seed ([sweep].seeds); drop it",
        ),
        (
            '[sweep]\nswarms = ["greedy"]\n[[scenario]]\nname = "a"\nconfig = "scenario.toml"\n'
            'overrides = { "evaluate.swarms" = ["random"] }\n',
            "[[scenario]] a.overrides.'evaluate.swarms' is set by the sweep itself, each cell "
            "running [sweep].swarms",
        ),
        (
            '[sweep]\nswarms = ["greedy"]\n[[scenario]]\nname = "a"\nconfig = "scenario.toml"\n'
            '[parameters]\n"evaluate.seed" = [0, 5]\n',
            "[parameters].'evaluate.seed' is set by the sweep itself",
        ),
    ],
)
def test_bad_sweep_configs_are_one_line_errors(tmp_path: Path, text: str, message: str, capsys):
    scenario_file(tmp_path)
    path = tmp_path / "bad.toml"
    path.write_text(text)
    with pytest.raises(UserError, match=None) as info:
        load_sweep_config(path)
    assert message in str(info.value) and str(path) in str(info.value)
    assert cli(["sweep", "--config", str(path), "--out", str(tmp_path / "o")]) == 2
    assert capsys.readouterr().err.count("\n") == 1


def test_missing_ray_is_a_one_line_error(tmp_path: Path, monkeypatch) -> None:
    monkeypatch.setitem(sys.modules, "ray", None)  # import ray -> ImportError
    config = load_sweep_config(sweep_file(tmp_path, seeds=1))
    with pytest.raises(UserError, match=r"pip install 'twin\[ray\]'"):
        run_sweep(config, tmp_path / "s", executor="ray", report=False)


def test_demo_config_expands(tmp_path: Path) -> None:
    config = load_sweep_config(ROOT / "configs" / "sweep-demo.toml")
    cells = expand_cells(config, tmp_path)
    assert len(cells) == len(config.seeds) * 2
    assert len({c["id"] for c in cells}) == len(cells)
    json.dumps(cells)  # plain data, shippable to any executor


def test_list_valued_parameters_are_swept(tmp_path: Path, capsys) -> None:
    """Swept values that are lists (obstacles, start cells) label their cells as JSON text."""
    parameters = (
        '"grid.obstacles" = [[], [[1, 1], [2, 2]]]\n'
        '"swarm.starts" = [[[0, 0], [0, 1], [0, 2]], "random"]'
    )
    path = sweep_file(tmp_path, seeds=1, parameters=parameters, horizon=5)
    out = tmp_path / "s"
    assert cli(["sweep", "--config", str(path), "--out", str(out), "--quiet"]) == 0
    summary = pd.read_csv(out / "summary.csv")
    assert len(summary) == 4 * 3 and (summary["n_seeds"] == 1).all()
    assert set(summary["grid.obstacles"]) == {"[]", "[[1, 1], [2, 2]]"}
    assert set(summary["swarm.starts"]) == {"[[0, 0], [0, 1], [0, 2]]", "random"}
    assert (out / "report" / "sweep.html").is_file()


def test_bad_parameter_value_fails_before_any_cell_runs(tmp_path: Path) -> None:
    config = load_sweep_config(sweep_file(tmp_path, parameters='"swarm.n_drones" = [3, 700]'))
    with pytest.raises(UserError, match=r"n_drones.*700"):
        run_sweep(config, tmp_path / "s", workers=1)
    assert not done_cells(tmp_path / "s")


@pytest.mark.parametrize(
    ("swarm", "table", "said"),
    [
        ("lookahead", "discount = 2.0", "[swarm_options.lookahead]: discount = 2.0 must lie in"),
        ("lookahead", "wieght = 1", "[swarm_options.lookahead] has an option 'wieght'"),
        ("rl-online", "batch_size = 0", "[swarm_options.rl-online]: batch_size = 0 must be in"),
        ("rl", "outages = [[0, 9]]", "[swarm_options.rl].outages has [0, 9] past the horizon "
         "T = 4; end it by 4"),
    ],
)  # fmt: skip
@pytest.mark.parametrize("scenario_too", [False, True])
def test_a_bad_option_of_the_sweeps_own_swarm_options_is_refused_before_any_cell(
    swarm, table, said, scenario_too, tmp_path: Path, capsys
) -> None:
    """A swarm option the sweep file's [swarm_options] gives and the swarm refuses failed every
    cell as it ran, naming neither the file nor its table (the review of probe 26's fixes):
    one line naming both, before any folder is made. Outages past the horizon were refused
    only as a cell ran; with options of the scenario's own for the swarm, the scenario file
    was named for the sweep's value."""
    path = sweep_file(tmp_path, seeds=1, horizon=4)
    if scenario_too:  # a good option of the scenario's for the same swarm
        scenario = tmp_path / "scenario.toml"
        good = {"lookahead": "end_weight = 0.5", "rl-online": "eps = 0.1", "rl": "eps = 0.1"}
        scenario.write_text(scenario.read_text() + f"\n[swarm_options.{swarm}]\n{good[swarm]}\n")
    text = path.read_text().replace('"sweeping"]', f'"{swarm}"]')
    path.write_text(text + f"\n[swarm_options.{swarm}]\n{table}\n")
    out = tmp_path / "s"
    assert cli(["sweep", "--config", str(path), "--out", str(out), "--quiet"]) == 2
    err = capsys.readouterr().err.strip()
    assert "\n" not in err and err.startswith(f"twin: error: {path}: {said}"), err
    assert not out.exists()


def test_a_scenarios_outages_past_the_horizon_name_the_scenario(tmp_path: Path, capsys) -> None:
    """Outages the scenario's [swarm_options] give were blamed on the sweep file when the sweep
    gave any other option for the swarm (the review of probe 27's fixes)."""
    path = sweep_file(tmp_path, seeds=1, horizon=4)
    scenario = tmp_path / "scenario.toml"
    scenario.write_text(scenario.read_text() + "\n[swarm_options.rl]\noutages = [[0, 9]]\n")
    text = path.read_text().replace('"sweeping"]', '"rl"]')
    path.write_text(text + "\n[swarm_options.rl]\neps = 0.2\n")
    out = tmp_path / "s"
    assert cli(["sweep", "--config", str(path), "--out", str(out), "--quiet"]) == 2
    err = capsys.readouterr().err.strip()
    assert "\n" not in err and f"{path}:" not in err, err
    assert f"{scenario}: [swarm_options.rl].outages has [0, 9] past the horizon T = 4" in err, err
    assert not out.exists()


@pytest.mark.parametrize(
    ("parameters", "overrides", "said"),
    [
        ('"swarm.n_drones" = [3, -3]', "", "[parameters].'swarm.n_drones' = -3 must be >= 1"),
        ('"traffic.horizon" = ["x"]', "", "[parameters].'traffic.horizon' = 'x' must be a whole number"),
        ('"swarm.n_drones" = [3]', '{ "swarm.eta" = 7 }', "[[scenario]] syn.overrides.'swarm.eta' = 7 must be"),
    ],
)  # fmt: skip
def test_a_refused_sweep_key_is_named_in_the_sweep_file(
    parameters, overrides, said, tmp_path: Path, capsys
) -> None:
    """A value of the sweep file's ``[parameters]`` or a scenario's ``overrides`` that the
    scenario refuses is named as the sweep file's key, not as an override in the scenario's
    file, which the user did not write it in (probe 24's f01)."""
    path = sweep_file(tmp_path, parameters=parameters)
    if overrides:
        path.write_text(
            path.read_text().replace('config = "', f'overrides = {overrides}\nconfig = "')
        )
    args = ["sweep", "--config", str(path), "--out", str(tmp_path / "s"), "--workers", "1"]
    assert cli(args) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith(f"twin: error: {path}: {said}"), err
    assert f"(scenario 'syn', {tmp_path / 'scenario.toml'})" in err[0], err
    assert not (tmp_path / "s").exists()


def _cell_failing_as_it_runs(cell):
    """A sweep cell's run that fails (in a worker process: a function it can import)."""
    raise UserError(f"cell {cell['id']} failed as it ran")


def test_failing_cells_are_reported_and_rerun(tmp_path: Path, capsys, monkeypatch) -> None:
    """A checkpoint that cannot load is refused before any cell (each cell failed on it); cells
    that fail as they run are listed, and a rerun runs them again."""
    import twin.sweep.runner as runner

    path = sweep_file(tmp_path, seeds=2)
    (tmp_path / "broken.pt").write_bytes(b"not a checkpoint")
    text = path.read_text().replace('"sweeping"]', '"sweeping", "rl"]')
    path.write_text(text + '\n[swarm_options.rl]\ncheckpoint = "broken.pt"\n')
    args = ["sweep", "--config", str(path), "--out", str(tmp_path / "s"), "--workers", "1"]
    assert cli(args) == 2
    err = capsys.readouterr().err
    assert "broken.pt" in err and err.count("\n") == 1 and not (tmp_path / "s").exists()
    tiny_checkpoint(tmp_path / "broken.pt")  # fixed
    monkeypatch.setattr(runner, "run_cell", _cell_failing_as_it_runs)
    assert cli(args) == 2
    err = capsys.readouterr().err
    assert "2 of 2 cells failed" in err and "failed as it ran" in err and err.count("\n") == 1
    assert len(json.loads((tmp_path / "s" / "failed.json").read_text())) == 2
    monkeypatch.undo()
    assert cli(args) == 0
    assert not (tmp_path / "s" / "failed.json").exists()
    assert set(pd.read_csv(tmp_path / "s" / "results.csv")["swarm"]) >= {"rl"}


def test_a_cell_whose_run_did_not_finish_is_failed_not_done(tmp_path: Path, capsys) -> None:
    """A cell whose traffic ends early (a tape short of its horizon) is a failed cell: one
    line naming it, failed.json and the report list it, no row of it in results.csv, and a
    rerun computes it again. A record of such a run left by an earlier version counts as
    neither done nor a result."""
    import dataclasses

    from helpers import random_tape

    from twin.sweep.store import merge

    tape = random_tape(horizon=6)
    keep = tape.steps <= 3  # the traffic stops at step 3 of 6
    short = dataclasses.replace(
        tape, steps=tape.steps[keep], times=tape.times[keep], counts=tape.counts[keep],
        speeds=tape.speeds[keep],
    )  # fmt: skip
    short.write(tmp_path / "short.parquet")
    random_tape(horizon=6).write(tmp_path / "whole.parquet")
    path = sweep_file(tmp_path, seeds=1, horizon=6)
    text = path.read_text().replace(
        'config = "scenario.toml"', 'config = "scenario.toml"\ntape = "short.parquet"'
    )
    text += '\n[[scenario]]\nname = "whole"\nconfig = "scenario.toml"\ntape = "whole.parquet"\n'
    path.write_text(text)
    out = tmp_path / "s"
    args = ["sweep", "--config", str(path), "--out", str(out), "--workers", "1", "--quiet"]
    assert cli(args) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "Traceback" not in err, err
    assert "1 of 2 cells failed (first: syn-s0-" in err
    assert "its run did not finish: traffic source ended after 3 of 6 steps" in err
    failed = json.loads((out / "failed.json").read_text())
    assert list(failed) == [c for c in failed if c.startswith("syn-")] and len(failed) == 1
    assert set(pd.read_csv(out / "results.csv")["scenario"]) == {"whole"}
    assert (
        f"cells FAILED in the last invocation and are not in the tables (failed.json): {next(iter(failed))}"
        in (out / "report" / "sweep.md").read_text()
    )
    assert not (out / "cells" / f"{next(iter(failed))}.json").exists()
    assert cli(args) == 2  # rerun: the failed cell again, the finished one skipped
    assert "1 of 1 cells failed" in capsys.readouterr().err
    # a record of a partial run (as an earlier version wrote them): neither done nor merged
    (done,) = done_cells(out)
    record = json.loads((out / "cells" / f"{done}.json").read_text())
    (out / "cells" / f"{done}.json").write_text(json.dumps({**record, "error": "cut short"}))
    assert done_cells(out) == set()
    results, _ = merge(out, [done])
    assert results.empty


#: (dotted key, the line of configs/synthetic.toml it replaces, the new line) for every key a
#: sweep override can reach in a synthetic scenario.
OVERRIDES = [
    ("grid.nx", "nx = 20", "nx = 12"),
    ("grid.ny", "ny = 30", "ny = 25"),
    ("grid.obstacles", "obstacles = []", "obstacles = [[1, 1], [2, 2]]"),
    ("swarm.n_drones", "n_drones = 3", "n_drones = 2"),
    ("swarm.starts", 'starts = "random"', "starts = [[0, 0], [5, 5], [9, 9]]"),
    ("swarm.eta", "eta = 0.1 ", "eta = 0.3 "),
    ("swarm.delta", "delta = 0.025", "delta = 0.05"),
    ("swarm.alpha_T", "alpha_T = 1.0", "alpha_T = 2.0"),
    ("swarm.alpha_I", "alpha_I = 0.5", "alpha_I = 0.0"),
    ("traffic.horizon", "horizon = 30", "horizon = 25"),
    ("traffic.beta1", "beta1 = 0.7", "beta1 = 0.3"),
    ("traffic.beta2", "beta2 = 5.0", "beta2 = 2.0"),
    ("traffic.z_lo", "z_lo = 0.0", "z_lo = 0.1"),
]
#: swarm options given in the scenario config ([swarm_options]) or by the sweep (the sweep's win)
OPTIONS = [
    ("rl-decentralized", "eps = 0.5", None),
    ("rl-decentralized", "eps = 0.5", {"eps": 0.2}),
    ("rl", "outages = [[5, 12]]", None),
    ("rl-online", "online_iters = 2", {"batch_size": 8}),
    ("lookahead", "horizon = 2", None),
    ("lookahead", "horizon = 2", {"horizon": 3}),
]


def _value(line: str):
    import tomllib

    return next(iter(tomllib.loads(line).values()))


def _cell_rows(tmp: Path, scenario_text: str, overrides: dict, swarms: list[str],
               options: dict) -> pd.DataFrame:  # fmt: skip
    from twin.sweep import run_cell

    scenario = tmp / "scenario.toml"
    scenario.write_text(scenario_text)
    lines = [f"[sweep]\nname = 't'\nswarms = {json.dumps(swarms)}\nseeds = [3]\n"]
    for swarm, table in options.items():
        lines.append(f"[swarm_options.{swarm}]\n" + "".join(
            f"{k} = {json.dumps(v)}\n" for k, v in table.items()))  # fmt: skip
    lines.append(f"[[scenario]]\nname = 'syn'\nconfig = '{scenario.name}'\n")
    lines.append("overrides = {" + ", ".join(
        f'"{k}" = {json.dumps(v)}' for k, v in overrides.items()) + "}\n")  # fmt: skip
    path = tmp / "sweep.toml"
    path.write_text("\n".join(lines))
    cell = expand_cells(load_sweep_config(path), tmp / "sweep")[0]
    return pd.DataFrame(run_cell(cell)["rows"]).set_index("swarm")


def _evaluate_rows(tmp: Path, scenario_text: str, swarms: list[str]) -> pd.DataFrame:
    path = tmp / "equivalent.toml"
    path.write_text(scenario_text)
    out = tmp / "eval"
    args = ["evaluate", "--config", str(path), "--seed", "3", "--swarms", ",".join(swarms)]
    assert cli([*args, "--out", str(out), "--no-report", "--quiet"]) == 0
    return pd.read_csv(out / "per_seed.csv").set_index("swarm")


@pytest.mark.parametrize(("key", "old", "new"), OVERRIDES, ids=[o[0] for o in OVERRIDES])
def test_every_override_gives_a_cell_equal_to_evaluate(tmp_path, key, old, new):
    text = scenario_file(tmp_path, horizon=30).read_text()
    assert old in text, old
    swarms = ["random", "greedy", "visit-gain"]
    got = _cell_rows(tmp_path, text, {key: _value(new)}, swarms, {})
    expected = _evaluate_rows(tmp_path, text.replace(old, new, 1), swarms)
    for col in ("R_hat_T", "C_hat_T", "pct_map_covered", "belief_error"):
        assert got.loc[swarms, col].tolist() == pytest.approx(expected.loc[swarms, col].tolist())


@pytest.mark.parametrize(("swarm", "in_config", "in_sweep"), OPTIONS)
def test_every_swarm_option_gives_a_cell_equal_to_evaluate(tmp_path, swarm, in_config, in_sweep):
    if swarm.startswith("rl"):
        pytest.importorskip("torch")
    text = scenario_file(tmp_path, horizon=30).read_text()
    text += f"\n[swarm_options.{swarm}]\n{in_config}\n"
    got = _cell_rows(tmp_path, text, {}, [swarm], {swarm: in_sweep} if in_sweep else {})
    scenario = text
    if in_sweep:  # the equivalent config states the sweep's value, which wins over the file's
        scenario += "".join(f"{k} = {json.dumps(v)}\n" for k, v in in_sweep.items()
                            if f"{k} =" not in in_config)  # fmt: skip
        for k, v in in_sweep.items():
            scenario = scenario.replace(in_config, f"{k} = {json.dumps(v)}") if (
                in_config.startswith(f"{k} =")) else scenario  # fmt: skip
    expected = _evaluate_rows(tmp_path, scenario, [swarm])
    assert got.loc[swarm, "R_hat_T"] == pytest.approx(expected.loc[swarm, "R_hat_T"], rel=1e-12)


@pytest.mark.parametrize("foreign", ["summary.csv", "results.csv", "mine.txt"])
def test_a_folder_a_sweep_did_not_write_is_refused(tmp_path: Path, capsys, foreign) -> None:
    """--out that holds a user's file (even one named like a sweep's, without sweep.json) is
    refused in one line; the file is left as it was."""
    path = sweep_file(tmp_path, seeds=1, horizon=4)
    out = tmp_path / "userdata"
    out.mkdir()
    (out / "notes.md").write_text("mine\n")
    if foreign != "mine.txt":
        (out / "notes.md").rename(out / foreign)
    before = {p.name: p.read_bytes() for p in out.iterdir()}
    assert cli(["sweep", "--config", str(path), "--out", str(out), "--quiet", "--no-report"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "no twin sweep" in err
    assert {p.name: p.read_bytes() for p in out.iterdir()} == before


@pytest.mark.parametrize("damage", ["{not json", '{"invocations": 3}', "[]"])
def test_a_damaged_sweep_record_is_kept_aside_not_overwritten(tmp_path: Path, capsys, damage):
    """A sweep.json that does not read back is renamed sweep.json.damaged (one notice), the
    sweep resumes with its cells, and a second damage goes to sweep.json.damaged.1."""
    config = load_sweep_config(sweep_file(tmp_path, seeds=1, horizon=4))
    out = tmp_path / "s"
    run_sweep(config, out, workers=1, report=False)
    capsys.readouterr()
    for kept in ("sweep.json.damaged", "sweep.json.damaged.1"):
        (out / "sweep.json").write_text(damage)
        again = run_sweep(config, out, workers=1, report=False)
        assert again.ran == []
        assert (out / kept).read_text() == damage
        err = capsys.readouterr().err
        assert err.count("\n") == 1 and f"kept as {kept}" in err
        assert len(json.loads((out / "sweep.json").read_text())["invocations"]) == 1


def test_a_history_option_is_a_file_of_the_cell(tmp_path: Path) -> None:
    """``[swarm_options.nowcast-gain] history`` is read from the sweep config's folder, like a
    checkpoint, and its content defines the cell: a replaced history gives a new cell (its
    old numbers were kept; probe 13's P2-f01a), a missing one is refused naming the key."""
    path = sweep_file(tmp_path, seeds=1)
    text = path.read_text().replace('"sweeping"]', '"sweeping", "nowcast-gain"]')
    path.write_text(text + '\n[swarm_options.nowcast-gain]\nhistory = "h.npz"\n')
    with pytest.raises(UserError, match=r"\[swarm_options.nowcast-gain\].history = .*h\.npz "
                                        r".*run `twin history` or fix the path"):  # fmt: skip
        load_sweep_config(path)
    history = tmp_path / "h.npz"
    history.write_bytes(b"one history")
    config = load_sweep_config(path)
    assert config.swarm_options["nowcast-gain"]["history"] == str(history.resolve())
    first = [c["id"] for c in expand_cells(config, tmp_path / "s")]
    assert [c["id"] for c in expand_cells(config, tmp_path / "s")] == first
    history.write_bytes(b"another history")
    assert not set(c["id"] for c in expand_cells(config, tmp_path / "s")) & set(first)


@pytest.mark.parametrize("history", [None, b"no history"])
def test_a_swarm_without_a_usable_history_is_refused_before_any_cell(tmp_path, capsys, history):
    """nowcast-gain in a sweep without a history (or with a file that is none) is one line
    before any cell runs; each cell used to run its traffic and then fail."""
    path = sweep_file(tmp_path, seeds=2, horizon=4)
    text = path.read_text().replace('"sweeping"]', '"sweeping", "nowcast-gain"]')
    if history is not None:
        (tmp_path / "h.npz").write_bytes(history)
        text += '\n[swarm_options.nowcast-gain]\nhistory = "h.npz"\n'
    path.write_text(text)
    out = tmp_path / "s"
    assert cli(["sweep", "--config", str(path), "--out", str(out), "--quiet", "--no-report"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "Traceback" not in err, err
    assert "nowcast-gain" in err or "h.npz" in err, err
    assert "cells failed" not in err and not (out / "failed.json").exists(), err  # none ran
    assert not out.exists(), list(out.rglob("*"))  # nothing written for a refused sweep


def test_a_history_of_the_sweeps_swarm_options_is_read_before_any_cell(tmp_path, capsys):
    """The sweep's own ``[swarm_options.nowcast-gain] history``: the check before any cell
    ignored it and refused the sweep, asking for exactly that key (probe 20's f07)."""
    path = sweep_file(tmp_path, seeds=1, horizon=4)
    history = tmp_path / "h.npz"
    assert cli(["history", "--dynamics", str(tmp_path / "scenario.toml"), "--days", "2",
                "--out", str(history)]) == 0  # fmt: skip
    text = path.read_text().replace('"sweeping"]', '"nowcast-gain"]')
    path.write_text(text + '\n[swarm_options.nowcast-gain]\nhistory = "h.npz"\n')
    out = tmp_path / "s"
    capsys.readouterr()
    code = cli(["sweep", "--config", str(path), "--out", str(out), "--quiet", "--no-report"])
    assert code == 0, capsys.readouterr().err
    assert set(pd.read_csv(out / "results.csv")["swarm"]) == {"random", "greedy", "nowcast-gain"}


def test_a_sumocfg_variable_naming_another_file_gives_a_new_cell(tmp_path: Path, monkeypatch):
    """A cell is its sumocfg as SUMO reads it: a ``${VAR}`` that now names another route file
    gives another cell (the old cell's numbers were kept as current; probe 14's f04)."""
    from twin.sweep.cells import cell_inputs

    for name in ("n.net.xml", "a.rou.xml", "b.rou.xml"):
        (tmp_path / name).write_text("<x/>")
    (tmp_path / "c.sumocfg").write_text(
        '<configuration><input><net-file value="n.net.xml"/>'
        '<route-files value="${TWIN_TEST_ROUTES}"/></input></configuration>'
    )
    scenario = tmp_path / "sc.toml"
    scenario.write_text('[traffic]\nkind = "sumo"\nsumocfg = "c.sumocfg"\ncell_m = 200\n')
    monkeypatch.setenv("TWIN_TEST_ROUTES", "a.rou.xml")
    first = cell_inputs(scenario, {}, None)
    assert cell_inputs(scenario, {}, None) == first
    monkeypatch.setenv("TWIN_TEST_ROUTES", "b.rou.xml")
    assert cell_inputs(scenario, {}, None) != first


@pytest.mark.parametrize("link", ["cells", "report", "failed.json"])
def test_a_link_out_of_the_sweep_folder_is_refused(tmp_path: Path, capsys, link) -> None:
    """A link planted in a sweep folder would take the cells' files, the report or the
    failures' record outside it: one line naming the link before any cell runs, nothing
    written through it (probe 14's f05, probe 15's f03 and f06)."""
    path = sweep_file(tmp_path, seeds=1, horizon=4)
    outside, out = tmp_path / "outside", tmp_path / "s"
    outside.mkdir()
    (out / "cells").mkdir(parents=True)  # a sweep's folder, which the link was planted in
    if link == "cells":
        (out / "cells").rmdir()
    (out / link).symlink_to(outside if "." not in link else outside / "victim.txt")
    assert cli(["sweep", "--config", str(path), "--out", str(out), "--quiet"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and f"{out / link} is a symbolic link out of the folder" in err
    assert not any(outside.iterdir())
    assert sorted(p.name for p in out.iterdir()) == sorted({link, "cells"})


def test_the_memory_limit_of_a_sweep_bounds_its_cells(tmp_path: Path, capsys) -> None:
    """``--max-memory-gb`` of a sweep is each cell's limit too (cells used 8 GB whatever it
    said, while a refused cell said to raise it; probe 14's f01); a limit no worker fits in
    says to raise it, not to use at most the one worker given."""
    path = sweep_file(tmp_path, seeds=1, horizon=4)
    args = ["sweep", "--config", str(path), "--quiet", "--no-report", "--workers", "1"]
    assert cli([*args, "--out", str(tmp_path / "a"), "--max-memory-gb", "0.00001"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "raise --max-memory-gb" in err and "at most" not in err, err
    big = tmp_path / "big.toml"  # about 1 GB of maps by twin's estimate
    big.write_text(
        '[grid]\nnx = 6\nny = 3000\n[swarm]\nn_drones = 2\n[traffic]\nkind = "synthetic"\n'
        'horizon = 1600\ndisturbances = [{ kind = "big", i = 2, j = 2, amplitude = 1.0, '
        "sigma = 1.0 }]\n"
    )
    path.write_text(path.read_text().replace('"scenario.toml"', '"big.toml"'))
    assert cli([*args, "--out", str(tmp_path / "b"), "--max-memory-gb", "0.9"]) == 2
    err = capsys.readouterr().err
    assert "over the 0.9 GB limit" in err, err
    assert not list((tmp_path / "b" / "cells").glob("*.parquet"))


def test_a_record_naming_a_device_is_a_changed_file_not_a_hang(tmp_path: Path) -> None:
    """A cell record whose traffic identity names ``/dev/zero`` (or a FIFO) is a file that
    changed: hashing it read forever (probe 15's f07)."""
    from twin.sweep.store import inputs_changed

    fifo = tmp_path / "fifo"
    os.mkfifo(fifo)
    for path in ("/dev/zero", str(fifo)):
        entry = {"role": "route file", "path": path, "sha256": "0" * 64}
        assert inputs_changed({"traffic": {"identity": {"files": [entry]}}}) == f"route file {path}"


def test_a_bad_memory_variable_is_refused_before_any_cell(tmp_path: Path, capsys, monkeypatch):
    """``$TWIN_MAX_MEMORY_GB`` that is no number: one line before the sweep folder is made
    (every cell failed with it, after the sweep started; probe 15's f09)."""
    monkeypatch.setenv("TWIN_MAX_MEMORY_GB", "abc")
    path = sweep_file(tmp_path, seeds=1, horizon=4)
    out = tmp_path / "s"
    assert cli(["sweep", "--config", str(path), "--out", str(out), "--quiet"]) == 2
    err = capsys.readouterr().err
    assert (
        err
        == "twin: error: TWIN_MAX_MEMORY_GB = 'abc' is not a number; give the limit in GB, e.g. 8\n"
    ), err
    assert not out.exists()


def test_a_grid_off_an_incident_in_one_combination_is_refused_before_any_cell(
    tmp_path: Path, capsys
) -> None:
    """A SUMO scenario swept over cell sizes whose incident cell is off the coarser grid: one
    line before any cell runs (the finer cell ran first, then the sweep failed; probe 15's
    f24); a sumocfg that is not there likewise."""
    from helpers import small_sumo_scenario

    folder = small_sumo_scenario(tmp_path, horizon=3)
    text = (folder / "small.toml").read_text()
    (folder / "small.toml").write_text(
        text + '\n[[traffic.incidents]]\nkind = "edge_closed"\ncell = [5, 5]\nstep = 1\n'
        "duration_min = 2.0\n"
    )
    path = folder / "sweep.toml"
    path.write_text(
        '[sweep]\nname = "i"\nswarms = ["random"]\nseeds = 1\n[[scenario]]\nname = "s"\n'
        'config = "small.toml"\n[parameters]\n"traffic.cell_m" = [200.0, 600.0]\n'
    )
    out = folder / "out"
    assert cli(["sweep", "--config", str(path), "--out", str(out), "--quiet", "--no-report"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "incidents[0].cell = [5, 5] is off the" in err, err
    assert not list((out / "cells").glob("*.json"))


def test_a_stopped_pool_starts_no_task_it_had_queued(tmp_path: Path) -> None:
    """A stop (Ctrl-C, SIGTERM) while one worker runs its task: that task ends, no other
    starts (the pool had queued one more than it ran, which kept running after the signal,
    for minutes with SUMO cells; probe 15's f18)."""
    from helpers import slow_marker

    from twin.executors import local_tasks

    tasks = [(str(tmp_path / f"t{n}"), 1.5) for n in range(3)]

    def stop(signum, frame):
        raise KeyboardInterrupt

    previous = signal.signal(signal.SIGALRM, stop)
    try:
        signal.setitimer(signal.ITIMER_REAL, 0.8)  # while the first task runs
        with pytest.raises(KeyboardInterrupt):
            for _ in local_tasks(slow_marker, tasks, workers=1, ignore_sigint=True):
                pass
    finally:
        signal.setitimer(signal.ITIMER_REAL, 0)
        signal.signal(signal.SIGALRM, previous)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["t0"]


def test_a_name_too_long_for_a_file_is_refused_with_the_config(tmp_path: Path) -> None:
    """A sweep or scenario name of 300 letters: refused as the config is read (it failed
    mid-run, "File name too long"; probe 15's f23)."""
    path = sweep_file(tmp_path, seeds=1)
    path.write_text(path.read_text().replace('name = "syn"', f'name = "{"a" * 300}"'))
    with pytest.raises(UserError, match="is 300 characters long; give at most 100"):
        load_sweep_config(path)


@pytest.mark.parametrize("kind", ["fifo", "folder"])
def test_a_failures_record_that_is_no_file_is_refused_before_any_cell(
    tmp_path: Path, capsys, kind
) -> None:
    """``failed.json`` of a sweep folder replaced by a FIFO (the sweep hung after its cells)
    or a folder (an error after them): one line before any cell runs (probe 15's f03)."""
    path = sweep_file(tmp_path, seeds=1, horizon=4)
    out = tmp_path / "s"
    run_sweep(load_sweep_config(path), out, workers=1, report=False)
    (out / "failed.json").unlink(missing_ok=True)
    os.mkfifo(out / "failed.json") if kind == "fifo" else (out / "failed.json").mkdir()
    capsys.readouterr()
    assert cli(["sweep", "--config", str(path), "--out", str(out), "--quiet", "--no-report"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "failed.json is a " in err and "remove it" in err, err


def test_a_limit_no_cell_fits_is_refused_before_any_cell(tmp_path: Path, capsys) -> None:
    """A sweep's memory limit below what its cells take: one line before any cell runs, as
    `twin evaluate` says it (every cell failed with it; probe 15's P2-f07)."""
    path = sweep_file(tmp_path, seeds=2, horizon=4)
    out = tmp_path / "s"
    argv = ["sweep", "--config", str(path), "--out", str(out), "--quiet", "--no-report"]
    assert cli([*argv, "--max-memory-gb", "1e-9"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "1e-09 GB is below what this run takes on any grid" in err
    assert "cells failed" not in err and not list((out / "cells").glob("*.json"))


def test_the_sweep_figures_intervals_stop_where_coverage_and_percentages_do():
    """Two seeds give a t-interval wide enough to reach below 0 % and past 100 %: the figure
    drew it there (probe 19's p2_sweep_rep). The table keeps the interval as computed."""
    import numpy as np

    from twin.report.sweep import figure_table2

    summary = pd.DataFrame(
        {
            "scenario": ["a"],
            "swarm": ["greedy"],
            "n_seeds": [2],
            "R_hat_T": [1.5],
            "R_hat_T_ci95": [4.0],  # a score is >= 0
            "C_hat_T": [0.9],
            "C_hat_T_ci95": [0.5],
            "pct_time_max_C": [20.0],
            "pct_time_max_C_ci95": [127.0],
            "pct_map_covered": [95.0],
            "pct_map_covered_ci95": [3.0],
        }
    )
    fig = figure_table2(summary)
    drawn = {}
    for ax in fig.axes[:4]:
        (errorbar,) = [c for c in ax.containers if c.__class__.__name__ == "ErrorbarContainer"]
        (segment,) = errorbar.lines[2][0].get_segments()
        drawn[ax.get_title()] = tuple(np.round(segment[:, 1], 6))
    assert sorted(drawn.values()) == sorted([(0.0, 5.5), (0.4, 1.0), (0.0, 100.0), (92.0, 98.0)]), (
        drawn
    )


@pytest.mark.parametrize("limited", [True, False])
def test_a_local_ray_that_cannot_start_is_one_line_with_the_fix(
    tmp_path: Path, monkeypatch, limited
) -> None:
    """Ray's node timing out at start (under ``ulimit -v``, as on a cluster's login node) was an
    internal error asking for a bug report (probe 25's f10): one line, Ray's words, the limit
    when one is set, and the fix."""
    import resource

    ray = pytest.importorskip("ray")
    from twin.executors import ray_tasks

    def no_start(**_):
        raise Exception("The current node timed out during startup.\nmore of Ray's words")

    monkeypatch.setenv("TWIN_CACHE_DIR", str(tmp_path / "cache"))
    monkeypatch.setattr(ray, "init", no_start)
    limit = 6_000_000 * 1024 if limited else resource.RLIM_INFINITY
    monkeypatch.setattr(resource, "getrlimit", lambda _: (limit, resource.RLIM_INFINITY))
    with pytest.raises(UserError) as caught:
        list(ray_tasks(abs, [(-1,)], 1))
    said = str(caught.value)
    assert said.startswith(
        "--executor ray: Ray could not start (The current node timed out during startup.)"
    ), said
    if limited:
        assert "at most 5.72 GB of virtual memory (ulimit -v)" in said
        assert said.endswith("lift the limit (ulimit -v unlimited), or use --executor local")
    else:
        assert said.endswith("; use --executor local")
    assert not list((tmp_path / "cache" / "tmp" / "twin-ray").glob("session_*"))


def test_a_sigterm_while_ray_starts_is_a_stop(tmp_path: Path, monkeypatch) -> None:
    """Ray's handler turns a SIGTERM during ``ray.init`` into SystemExit(15): the run exited
    with 15 and a folder of one marker (review); it is twin's stop, as Ctrl-C is."""
    import signal

    ray = pytest.importorskip("ray")
    from twin.executors import ray_tasks

    def terminated(**_):
        raise SystemExit(signal.SIGTERM)

    monkeypatch.setenv("TWIN_CACHE_DIR", str(tmp_path / "cache"))
    monkeypatch.setattr(ray, "init", terminated)
    with pytest.raises(KeyboardInterrupt):
        list(ray_tasks(abs, [(-1,)], 1))
