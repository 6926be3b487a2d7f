"""``twin replay`` checks that it would show the recorded run: the network file (sha256), the
cell size, the grid, SUMO's and twin's versions recorded in ``run.json``, and trajectory cells
on the grid. Each refusal: exit 2, one line naming what differs, no traceback, nothing changed
(the run folder included). The checks come before sumo-gui is needed."""

from __future__ import annotations

import importlib
import json
import subprocess
import sys
from collections.abc import Callable
from pathlib import Path

import pandas as pd
import pytest

pytest.importorskip("libsumo")

from helpers import needs_display
from test_bad_inputs import run_case, snapshot

from twin.cli import main
from twin.runs import write_manifest

CONFIG = """
[swarm]
n_drones = 1
[traffic]
kind = "sumo"
net = "small.net.xml"
routes = ["small.trips.xml"]
cell_m = 200.0
drone_speed_kmh = 12.0
begin = "00:01"
warmup_min = 1.0
horizon = 3
[evaluate]
swarms = ["random", "greedy"]
"""


@pytest.fixture
def recorded(tmp_path, capsys) -> Path:
    from twin.sumo.network import generate_grid_scenario

    generate_grid_scenario(tmp_path, blocks=3, block_m=300, end_s=300, period_s=5.0, seed=1)
    (tmp_path / "c.toml").write_text(CONFIG)
    run = tmp_path / "run"
    argv = ["run", "--config", str(tmp_path / "c.toml"), "--out", str(run), "--no-report",
            "--quiet"]  # fmt: skip
    assert main(argv) == 0
    capsys.readouterr()
    return run


def _edit_run_json(change: Callable[[dict], None]) -> Callable[[Path], None]:
    """Change run.json as another twin might have written it (the manifest agrees)."""

    def edit(run: Path) -> None:
        meta = json.loads((run / "run.json").read_text())
        change(meta)
        (run / "run.json").write_text(json.dumps(meta))
        write_manifest(run)

    return edit


def _off_grid(run: Path) -> None:
    path = run / "trajectories.parquet"
    rows = pd.read_parquet(path)
    rows.loc[rows.index[5], "i"] = 99
    rows.to_parquet(path, index=False)
    write_manifest(run)


def _rename_swarm(old: str, new: str) -> Callable[[Path], None]:
    """Rows of a recorded swarm under another name (the manifest agrees)."""

    def edit(run: Path) -> None:
        path = run / "trajectories.parquet"
        rows = pd.read_parquet(path)
        rows["swarm"] = rows["swarm"].replace(old, new)
        rows.to_parquet(path, index=False)
        write_manifest(run)

    return edit


def _drop_swarm(run: Path) -> None:
    path = run / "trajectories.parquet"
    rows = pd.read_parquet(path)
    rows[rows["swarm"] != "random"].to_parquet(path, index=False)
    write_manifest(run)


def _add_swarm(run: Path) -> None:
    path = run / "trajectories.parquet"
    rows = pd.read_parquet(path)
    extra = rows[rows["swarm"] == "greedy"].assign(swarm="foo")
    pd.concat([rows, extra]).to_parquet(path, index=False)
    write_manifest(run)


def _edit_net(run: Path) -> None:
    with open(run.parent / "small.net.xml", "a") as fh:
        fh.write("<!-- edited after the run -->\n")


def _edit_routes(run: Path) -> None:
    with open(run.parent / "small.trips.xml", "a") as fh:
        fh.write("<!-- fewer vehicles since the run -->\n")


def _edit_recorded_route_hash(run: Path) -> None:
    def change(meta: dict) -> None:
        for f in meta["traffic"]["identity"]["files"]:
            if f["role"] == "route file":
                f["sha256"] = "0" * 64

    _edit_run_json(change)(run)


def _maps_rewritten(run: Path) -> None:
    """importance.npz with every free cell at 0.9 (the manifest agrees)."""
    import numpy as np

    with np.load(run / "importance.npz") as npz:
        data = dict(npz)
    data["importance"] = (
        np.where(data["obstacles"], 0.0, 0.9)
        .astype(np.float32)[None]
        .repeat(len(data["importance"]), axis=0)
    )
    np.savez(run / "importance.npz", **data)
    write_manifest(run)


def _tape_counts_scaled(run: Path) -> None:
    """tape.parquet with every count ten times what SUMO had, its metadata kept."""
    import pyarrow as pa
    import pyarrow.parquet as pq

    table = pq.read_table(run / "tape.parquet")
    at = table.schema.get_field_index("count")
    counts = pa.compute.multiply(table.column("count"), pa.scalar(10, table.column("count").type))
    pq.write_table(table.set_column(at, table.schema.field(at), counts), run / "tape.parquet")
    write_manifest(run)


def _tape_of_sumo_seed(seed: int) -> Callable[[Path], None]:
    """tape.parquet as if SUMO had run with another seed (its metadata says so)."""

    def edit(run: Path) -> None:
        import pyarrow.parquet as pq

        table = pq.read_table(run / "tape.parquet")
        meta = dict(table.schema.metadata)
        tape = json.loads(meta[b"twin_tape"])
        tape["settings"]["seed"] = seed
        meta[b"twin_tape"] = json.dumps(tape).encode()
        pq.write_table(table.replace_schema_metadata(meta), run / "tape.parquet")
        write_manifest(run)

    return edit


def _edit_table(name: str, change: Callable[[pd.DataFrame], pd.DataFrame]) -> Callable:
    """A table of the run changed (the manifest agrees)."""

    def edit(run: Path) -> None:
        change(pd.read_parquet(run / name)).to_parquet(run / name, index=False)
        write_manifest(run)

    return edit


def _removed(name: str) -> Callable[[Path], None]:
    """A file of the run removed (the manifest agrees)."""

    def edit(run: Path) -> None:
        (run / name).unlink()
        write_manifest(run)

    return edit


def _edit_json(name: str, change: Callable[[dict], None]) -> Callable[[Path], None]:
    """A JSON file of the run changed in place (the manifest agrees)."""

    def edit(run: Path) -> None:
        data = json.loads((run / name).read_text())
        change(data)
        (run / name).write_text(json.dumps(data))
        write_manifest(run)

    return edit


def _additional_never_loaded(run: Path) -> None:
    """run.json names an additional file the run never loaded (a vType, harmless to SUMO)."""
    extra = run.parent / "extra.add.xml"
    extra.write_text('<additional><vType id="extra"/></additional>\n')
    _edit_run_json(lambda m: m["invocation"]["options"].update(additional=[str(extra)]))(run)


# name -> (what to change, monkeypatched (module, attribute, value) or None, expected words)
CASES = {
    "additional file the run never loaded": (
        _additional_never_loaded,
        None,
        "extra.add.xml: this additional file is not one the run loaded",
    ),
    "network edited": (_edit_net, None, "the network file (sha256) was"),
    "other twin": (None, ("twin", "__version__", "9.9.9"), "the twin version was 0.1.0, now 9.9.9"),
    "other SUMO": (
        None,
        ("twin.sumo.network", "sumo_version", lambda: "0.0.1"),
        "the SUMO version was",
    ),
    "other cell size": (
        _edit_run_json(lambda m: m["traffic"]["identity"].update(cell_m=100.0)),
        None,
        "grid.cell_m = 200, but run.json has traffic.identity.cell_m = 100",
    ),
    "other grid": (
        _edit_run_json(lambda m: m["traffic"]["identity"].update(grid=[9, 9])),
        None,
        "traffic.identity.grid = [9, 9], but grid is",
    ),
    "identity files emptied": (
        _edit_run_json(lambda m: m["traffic"]["identity"].update(files=[])),
        None,
        "traffic.identity.files records no network",
    ),
    "identity files without the route file": (
        _edit_run_json(
            lambda m: m["traffic"]["identity"].update(
                files=[f for f in m["traffic"]["identity"]["files"] if f["role"] != "route file"]
            )
        ),
        None,
        "traffic.identity.files records the route files [], but traffic.route_files are",
    ),
    "cell off the grid": (_off_grid, None, "on cell (99, "),
    "swarm renamed in trajectories": (
        _rename_swarm("random", "foo"),
        None,
        "summary.csv: no row for swarm 'foo', which trajectories.parquet holds",
    ),
    "swarm missing from trajectories": (
        _drop_swarm,
        None,
        "trajectories.parquet: no rows for swarm 'random' (summary.csv), seed 0",
    ),
    "unknown swarm in trajectories": (
        _add_swarm,
        None,
        "summary.csv: no row for swarm 'foo', which trajectories.parquet holds",
    ),
    "route file edited": (
        _edit_routes,
        None,
        "small.trips.xml: the route file changed since the run (sha256 ",
    ),
    "recorded folder not absolute": (
        _edit_run_json(lambda m: m["invocation"].update(cwd="somewhere")),
        None,
        "invocation.cwd = 'somewhere' is no absolute folder",
    ),
    "no drones recorded": (
        _edit_run_json(lambda m: m.update(n_drones=0)),
        None,
        "n_drones = 0 must be at least 1",
    ),
    "negative horizon recorded": (
        _edit_run_json(lambda m: m["traffic"].update(horizon=-4)),
        None,
        "traffic.horizon = -4 must be at least 1",
    ),
    "cell size 0 recorded": (
        _edit_run_json(lambda m: m["traffic"]["identity"].update(cell_m=0)),
        None,
        "traffic.identity.cell_m = 0 must be above 0",
    ),
    "maps other than the tape's": (
        _maps_rewritten,
        None,
        "importance.npz: importance at step 0, cell (",
    ),
    "tape other than the maps": (
        _tape_counts_scaled,
        None,
        "but tape.parquet replayed through its MFD gives",
    ),
    "MFD samples other than the tape's": (
        _edit_table("mfd_samples.parquet", lambda f: f.assign(count=f["count"] * 10)),
        None,
        "mfd_samples.parquet: count = ",
    ),
    # a live run's file removed with its manifest entry: its checks would go unsaid
    **{
        f"{name} removed": (
            _removed(name),
            None,
            f"{name} is missing, which a live SUMO run writes",
        )
        for name in ("tape.parquet", "mfd_samples.parquet", "network.json", "mfd.json")
    },
    # probe 20's P2-f09e
    "MFD samples without their speed limits": (
        _edit_table("mfd_samples.parquet", lambda f: f.drop(columns="speed_limit")),
        None,
        "mfd_samples.parquet: lacks the column 'speed_limit', which twin writes",
    ),
    "MFD samples with a column twin does not write": (
        _edit_table("mfd_samples.parquet", lambda f: f.assign(bogus=1.0)),
        None,
        "mfd_samples.parquet: holds a column 'bogus', which twin does not write",
    ),
    "MFD fit of more samples than the tape's": (
        _edit_json("mfd.json", lambda m: m.update(n_samples=m["n_samples"] + 5)),
        None,
        "mfd.json: n_samples = ",
    ),
    "network placed elsewhere than the tape's": (
        _edit_json("network.json", lambda m: m["grid"].update(x0=m["grid"]["x0"] + 5000.0)),
        None,
        "network.json: grid.x0 = ",
    ),
    "tape of another SUMO seed": (
        _tape_of_sumo_seed(7),
        None,
        "tape.parquet: recorded with SUMO seed 7, but run.json has seed 0 run with SUMO seed",
    ),
    "route hash differs": (
        _edit_recorded_route_hash,
        None,
        "the route file changed since the run (sha256 000000000000...",
    ),
}


@pytest.mark.parametrize("case", list(CASES))
def test_replay_refuses_another_scenario(recorded, tmp_path, capsys, monkeypatch, case):
    change, patch, needle = CASES[case]
    if change is not None:
        change(recorded)
    if patch is not None:
        module, name, value = patch
        monkeypatch.setattr(importlib.import_module(module), name, value)
    err = run_case(capsys, tmp_path, ["replay", str(recorded)], None, 2, needle)
    assert "\n" not in err


def test_a_recorded_run_reads_back_whole(recorded, capsys):
    """The live run's maps are its tape's replay, its scores its trajectories' over them."""
    from twin.report.load import load_run

    load_run(recorded)
    assert main(["report", str(recorded), "--no-animation"]) == 0


def test_run_json_records_the_identity(recorded):
    from twin.sumo.network import sumo_version

    identity = json.loads((recorded / "run.json").read_text())["traffic"]["identity"]
    import hashlib

    net = recorded.parent / "small.net.xml"
    assert identity["net_sha256"] == hashlib.sha256(net.read_bytes()).hexdigest()
    assert identity["cell_m"] == 200.0 and identity["sumo"] == sumo_version()
    run = json.loads((recorded / "run.json").read_text())
    assert identity["grid"] == [run["grid"]["nx"], run["grid"]["ny"]]


def test_run_json_records_every_input_file(recorded):
    import hashlib

    identity = json.loads((recorded / "run.json").read_text())["traffic"]["identity"]
    files = {f["role"]: f for f in identity["files"]}
    assert set(files) == {"network", "route file"}
    for f in identity["files"]:
        assert f["sha256"] == hashlib.sha256(Path(f["path"]).read_bytes()).hexdigest()
    assert Path(files["route file"]["path"]).name == "small.trips.xml"


@pytest.mark.parametrize("recorded_files", ["x", [1], {"role": "route file"}])
def test_file_hashes_of_the_wrong_type_are_refused(tmp_path, recorded_files):
    """A damaged identity must not switch the check off."""
    from twin.cli.replay import check_input_files
    from twin.errors import UserError

    with pytest.raises(UserError, match="is not a list of files"):
        check_input_files(tmp_path, recorded_files, None)


@pytest.mark.parametrize("recorded_files", [None, [], [{"role": "route file"}]])
def test_runs_without_file_hashes_are_not_refused(tmp_path, recorded_files):
    """Older run folders record no file hashes: unknown, not a mismatch."""
    from twin.cli.replay import check_input_files

    path = tmp_path / "r.xml"
    path.write_text("<routes/>")

    class Source:
        def input_files(self):
            return [("route file", path)]

    check_input_files(tmp_path, recorded_files, Source())


# flags of `twin replay` -> words of the one-line error; checked before the scenario loads
REPLAY_FLAGS = {
    "a video of another format": (["--record", "{tmp}/x.avi"], "give a .mp4 or .gif file name"),
    "a video that exists": (["--record", "{tmp}/existing.mp4"], "--record never overwrites"),
    "a swarm not in the run": (["--gui-swarms", "lookahead"], "'lookahead' is not among"),
    # the report is drawn afresh: a video in it was lost (probe 16's f13)
    "a video in the run's report": (["--record", "{run}/report/x.gif"], "the run's report"),
    "a swarm twice": (["--gui-swarms", "random,random"], "'random' is named twice"),
}


@pytest.mark.parametrize("case", list(REPLAY_FLAGS))
def test_replay_flags_are_checked_before_the_scenario_loads(
    recorded, tmp_path, capsys, monkeypatch, case
):
    import twin.experiment

    def no_scenario(*args, **kwargs):
        raise AssertionError("the scenario was loaded before the flags were checked")

    monkeypatch.setattr(twin.experiment, "build_source", no_scenario)
    (tmp_path / "existing.mp4").write_bytes(b"")
    flags, needle = REPLAY_FLAGS[case]
    argv = ["replay", str(recorded), *(f.format(tmp=tmp_path, run=recorded) for f in flags)]
    err = run_case(capsys, tmp_path, argv, None, 2, needle)
    assert "\n" not in err


@pytest.fixture
def recorded_relative(tmp_path, capsys, monkeypatch) -> Path:
    """A run made from the scenario's folder with relative paths (config, network, routes)."""
    from twin.sumo.network import generate_grid_scenario

    scenario = tmp_path / "scenario"
    scenario.mkdir()
    generate_grid_scenario(scenario, blocks=3, block_m=300, end_s=300, period_s=5.0, seed=1)
    (scenario / "c.toml").write_text(CONFIG)
    monkeypatch.chdir(scenario)
    run = tmp_path / "run"
    argv = ["run", "--config", "c.toml", "--net", "small.net.xml", "--routes", "small.trips.xml",
            "--out", str(run), "--no-report", "--quiet"]  # fmt: skip
    assert main(argv) == 0
    capsys.readouterr()
    return run


def _decoy_folder(tmp_path: Path, same_config: bool = False) -> Path:
    """Another folder holding files of the same names: another scenario (the same network,
    other trips; another cell size unless ``same_config``)."""
    import shutil

    elsewhere = tmp_path / "elsewhere"
    shutil.copytree(tmp_path / "scenario", elsewhere)
    if not same_config:
        (elsewhere / "c.toml").write_text(CONFIG.replace("cell_m = 200.0", "cell_m = 100.0"))
    with open(elsewhere / "small.trips.xml", "a") as fh:
        fh.write("<!-- another day's trips -->\n")
    return elsewhere


def test_an_older_run_replayed_among_other_files_is_refused(
    recorded_relative, tmp_path, capsys, monkeypatch
):
    """A run that records no folder reads relative paths from the current one: a route file
    of another scenario there is not the run's (its sha256 differs from the recorded one)."""
    _edit_run_json(lambda m: m["invocation"].pop("cwd"))(recorded_relative)
    elsewhere = _decoy_folder(tmp_path, same_config=True)
    monkeypatch.chdir(elsewhere)
    needle = "small.trips.xml: this route file is not one the run loaded"
    err = run_case(capsys, tmp_path, ["replay", str(recorded_relative)], None, 2, needle)
    assert str(elsewhere / "small.trips.xml") in err


@needs_display
def test_replay_reads_relative_paths_from_the_folder_the_run_was_made_in(
    recorded_relative, tmp_path, capsys, monkeypatch
):
    from twin.cli.replay import run_arguments

    scenario = tmp_path / "scenario"
    monkeypatch.chdir(_decoy_folder(tmp_path))
    args = run_arguments(recorded_relative)
    assert args.config == scenario / "c.toml" and args.net == scenario / "small.net.xml"
    assert args.routes == [scenario / "small.trips.xml"]
    before = snapshot(tmp_path, recorded_relative)
    assert main(["replay", str(recorded_relative)]) == 0
    captured = capsys.readouterr()
    assert "replayed 3 steps of seed 0" in captured.out
    assert "error" not in captured.err and "Traceback" not in captured.err
    assert snapshot(tmp_path, recorded_relative) == before


def test_replay_from_elsewhere_refuses_a_file_gone_from_the_runs_folder(
    recorded_relative, tmp_path, capsys, monkeypatch
):
    scenario = tmp_path / "scenario"
    (scenario / "small.trips.xml").unlink()
    monkeypatch.chdir(_decoy_folder(tmp_path))
    (tmp_path / "elsewhere" / "small.trips.xml").write_text("<routes/>")
    err = run_case(capsys, tmp_path, ["replay", str(recorded_relative)], None, 2, "small.trips")
    assert str(scenario / "small.trips.xml") in err


def test_a_shipped_config_named_relatively_stays_the_shipped_one(tmp_path, monkeypatch):
    """A run of ``--config configs/shenzhen.toml`` from a folder without that file used the
    shipped config; replayed from a folder that has one, it still does."""
    from twin.cli.replay import _from_folder
    from twin.resources import shipped

    (tmp_path / "configs").mkdir()
    (tmp_path / "configs" / "shenzhen.toml").write_text("[grid]\nnx = 2\n")
    monkeypatch.chdir(tmp_path)
    made_in = tmp_path / "where-the-run-was-made"
    got = _from_folder("config", Path("configs/shenzhen.toml"), made_in)
    assert got == shipped("configs", "shenzhen.toml") and got.is_file()


def test_replay_refuses_a_changed_file_that_a_route_file_includes(tmp_path, capsys):
    """A route file that only includes the trips: the included file is part of the run's
    identity, as the route file itself is."""
    from twin.sumo.network import generate_grid_scenario

    generate_grid_scenario(tmp_path, blocks=3, block_m=300, end_s=300, period_s=5.0, seed=1)
    (tmp_path / "inc.rou.xml").write_text('<routes><include href="small.trips.xml"/></routes>')
    (tmp_path / "c.toml").write_text(CONFIG.replace('"small.trips.xml"', '"inc.rou.xml"'))
    run = tmp_path / "run"
    argv = ["run", "--config", str(tmp_path / "c.toml"), "--out", str(run), "--no-report",
            "--quiet"]  # fmt: skip
    assert main(argv) == 0
    capsys.readouterr()
    roles = {
        f["role"]
        for f in json.loads((run / "run.json").read_text())["traffic"]["identity"]["files"]
    }
    assert "included file" in roles
    _edit_routes(run)
    run_case(capsys, tmp_path, ["replay", str(run)], None, 2,
             "small.trips.xml: the included file changed since the run (sha256 ")  # fmt: skip


def test_replay_refuses_a_changed_saved_state_the_sumocfg_loads(tmp_path, capsys):
    """A sumocfg's <load-state> file is an input like the network: changed, replay refuses."""
    from twin.sumo.network import generate_grid_scenario
    from twin.sumo.tools import binary, run_sumo_program

    generate_grid_scenario(tmp_path, blocks=3, block_m=300, end_s=300, period_s=5.0, seed=1)
    run_sumo_program(
        [binary("sumo"), "-n", str(tmp_path / "small.net.xml"), "-r",
         str(tmp_path / "small.trips.xml"), "--save-state.times", "60", "--save-state.files",
         str(tmp_path / "state.xml"), "--end", "61", "--no-step-log", "true"],
        what="sumo",
    )  # fmt: skip
    (tmp_path / "c.sumocfg").write_text(
        '<configuration><input><net-file value="small.net.xml"/>'
        '<route-files value="small.trips.xml"/><load-state value="state.xml"/></input>'
        '<time><begin value="60"/><end value="300"/></time></configuration>'
    )
    run = tmp_path / "run"
    argv = ["run", "--sumocfg", str(tmp_path / "c.sumocfg"), "--cell-m", "200", "--drones", "1",
            "--swarms", "random", "--no-ceiling", "--out", str(run), "--no-report", "--quiet"]  # fmt: skip
    # in a process of its own, as a user runs it: SUMO's process is forked from one that has
    # not run libsumo (this test process has), whose teardown after a loaded state can crash
    done = subprocess.run(
        [sys.executable, "-m", "twin", *argv], capture_output=True, text=True, timeout=600
    )
    assert done.returncode == 0, done.stderr
    files = json.loads((run / "run.json").read_text())["traffic"]["identity"]["files"]
    assert "load-state" in {f["role"] for f in files}
    with open(tmp_path / "state.xml", "a") as fh:
        fh.write("<!-- another day -->\n")
    run_case(capsys, tmp_path, ["replay", str(run)], None, 2,
             "state.xml: the load-state changed since the run (sha256 ")  # fmt: skip


@needs_display
def test_replay_refuses_traffic_other_than_the_recorded_one(recorded, tmp_path, capsys):
    """run.json and the tape's record of the scenario edited alike to name another route
    file, with that file's sha256 (a determined forgery that every hash check and every
    cross-check of the folder passes): the replayed simulation is compared step by step
    with the run's tape, and the first step that differs is refused in one line."""
    import hashlib
    import re

    trips = (tmp_path / "small.trips.xml").read_text()
    fewer = re.sub(r"(<trip [^>]*/>\s*)(<trip [^>]*/>)", r"\1", trips)  # every other trip
    assert fewer != trips
    other = tmp_path / "other.trips.xml"
    other.write_text(fewer)
    config = tmp_path / "c.toml"
    config.write_text(config.read_text().replace("small.trips.xml", "other.trips.xml"))

    def forge(meta: dict) -> None:
        for entry in meta["traffic"]["identity"]["files"]:
            if entry["role"] == "route file":
                entry["path"] = str(other)
                entry["sha256"] = hashlib.sha256(other.read_bytes()).hexdigest()
        meta["traffic"]["route_files"] = [str(other)]

    def forge_tape(run: Path) -> None:  # the tape's record of the scenario, alike
        import pyarrow.parquet as pq

        table = pq.read_table(run / "tape.parquet")
        meta = dict(table.schema.metadata)
        tape = json.loads(meta[b"twin_tape"])
        tape["settings"]["route_files"] = [str(other)]
        for entry in tape["settings"]["identity"]["files"]:
            if entry["role"] == "route file":
                entry["path"] = str(other)
                entry["sha256"] = hashlib.sha256(other.read_bytes()).hexdigest()
        meta[b"twin_tape"] = json.dumps(tape).encode()
        pq.write_table(table.replace_schema_metadata(meta), run / "tape.parquet")
        write_manifest(run)

    _edit_run_json(forge)(recorded)
    forge_tape(recorded)
    run_case(capsys, tmp_path, ["replay", str(recorded)], None, 2,
             "tape.parquet: the replayed simulation's importance at step ")  # fmt: skip
