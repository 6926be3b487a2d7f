"""A small real SUMO scenario (netgenerate grid of about 2 km, 15 min simulated): per-cell
counts against an independent count, tape replay against the live run, bad files."""

from __future__ import annotations

import json
import xml.etree.ElementTree as ET
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

pytest.importorskip("libsumo")

from helpers import small_sumo_scenario

from twin.cli import main as twin_main
from twin.config import load_config
from twin.errors import UserError
from twin.patrol import run_patrol
from twin.scores import ScoreParams
from twin.sumo.scenario import sumo_source
from twin.sumo.session import SumoRunError, SumoSession
from twin.sumo.tools import binary, run_sumo_program
from twin.swarms import make_policy
from twin.traffic.tape import Tape, TapeTraffic


@pytest.fixture(scope="module")
def small(tmp_path_factory) -> Path:
    """A 5 x 5 signalised grid of 300 m blocks with 15 min of random trips."""
    return small_sumo_scenario(tmp_path_factory.mktemp("small"), horizon=10)


def _fcd_counts(fcd: Path, source, times: list[float]) -> dict[float, np.ndarray]:
    """Vehicles per cell from SUMO's own FCD output, binned with shapely boxes (independent of
    the source's numpy binning)."""
    from shapely.geometry import Point, box

    g = source.geometry
    boxes = {
        (i, j): box(
            g.x0 + j * g.cell_m,
            g.y_top - (i + 1) * g.cell_m,
            g.x0 + (j + 1) * g.cell_m,
            g.y_top - i * g.cell_m,
        )
        for i in range(g.nx)
        for j in range(g.ny)
    }
    wanted = {round(t, 1) for t in times}
    out = {}
    for _, elem in ET.iterparse(fcd, events=("end",)):
        if elem.tag == "timestep" and round(float(elem.get("time")), 1) in wanted:
            counts = np.zeros((g.nx, g.ny), dtype=int)
            for veh in elem.iter("vehicle"):
                p = Point(float(veh.get("x")), float(veh.get("y")))
                hits = [c for c, b in boxes.items() if b.covers(p)]
                i, j = min(hits)  # a point on a border: the cell the floor rule picks
                counts[i, j] += 1
            out[round(float(elem.get("time")), 1)] = counts
            elem.clear()
    return out


def _patrol(source, seed=0):
    swarms = {n: make_policy(n) for n in ("random", "greedy", "sweeping")}
    starts = np.argwhere(source.grid.free)[[0, -1]]
    return run_patrol(source, swarms, starts, ScoreParams(), seed=seed)


def test_counts_equal_an_independent_count_and_replay_equals_live(small, tmp_path):
    config = load_config(small / "small.toml")
    source = sumo_source(config)
    fcd = tmp_path / "fcd.xml"
    source.scenario.sumo_options = ("--fcd-output", str(fcd))
    source.scenario.reads_per_step = 1  # one instant per step (more: tests/test_sumo_observe.py)
    live = _patrol(source)
    assert live.error is None and live.completed_steps == 10
    times = [t for _, t, _, _ in source.snapshots]
    # SUMO labels an FCD timestep with the time at the start of the step that produced it:
    # the state read after simulationStep(t) is the FCD timestep t - 1 s (step length 1 s).
    independent = _fcd_counts(fcd, source, [t - 1.0 for t in times])
    assert len(independent) == len(times)
    total = 0
    for _, t, counts, _ in source.snapshots:
        np.testing.assert_array_equal(counts, independent[round(t - 1.0, 1)])
        total += counts.sum()
    assert total > 100  # the scenario has traffic to count

    path = tmp_path / "tape.parquet"
    source.tape().write(path)
    replay = _patrol(TapeTraffic.from_file(path))
    np.testing.assert_array_equal(replay.importance, live.importance)
    np.testing.assert_array_equal(replay.positions, live.positions)
    np.testing.assert_array_equal(replay.rewards, live.rewards)
    assert live.importance[1:].max() > 0  # the MFD sees congestion somewhere


def test_same_seed_same_traffic_and_sessions_run_one_after_another(small):
    config = load_config(small / "small.toml")
    a, b = sumo_source(config), sumo_source(config)
    maps_a = np.stack(list(a.importance_maps()))
    maps_b = np.stack(list(b.importance_maps()))
    np.testing.assert_array_equal(maps_a, maps_b)
    assert SumoSession._active is None


def test_sumo_failure_mid_run_keeps_partial_results(small, tmp_path, monkeypatch):
    from twin.config import SumoSettings

    calls = {"n": 0}
    original = SumoSession.advance_to
    reads = SumoSettings().reads_per_step  # one advance per read instant

    def failing(self, t):
        calls["n"] += 1
        if calls["n"] > 7 * reads:  # 4 warm-up snapshots, T^0, then 2 steps
            raise SumoRunError(f"SUMO failed before t = {t:g} s: simulated crash")
        original(self, t)

    monkeypatch.setattr(SumoSession, "advance_to", failing)
    out = tmp_path / "run"
    code = twin_main(["run", "--config", str(small / "small.toml"), "--out", str(out),
                      "--no-report", "--quiet"])  # fmt: skip
    assert code == 1
    assert SumoSession._active is None
    tape = Tape.read(out / "tape.parquet")
    assert tape.steps.max() == 2
    import pandas as pd

    series = pd.read_parquet(out / "series.parquet")
    assert series["step"].max() == 1


@pytest.mark.parametrize("after_steps", [0, 2])
def test_memory_running_out_is_one_line_or_a_partial_run_saying_so(
    small, tmp_path, monkeypatch, capsys, after_steps
):
    """Out of memory in the warm-up (a city of 1 s steps) was a partial run of 0 steps whose
    reason read "MemoryError: " (probe 28's n01); later it is a partial run saying it."""
    from twin.config import SumoSettings

    calls = {"n": 0}
    original = SumoSession.advance_to
    reads = SumoSettings().reads_per_step

    def failing(self, t):
        calls["n"] += 1
        if calls["n"] > (5 + after_steps) * reads:  # 4 warm-up snapshots, T^0, then steps
            raise MemoryError()
        original(self, t)

    monkeypatch.setattr(SumoSession, "advance_to", failing)
    out = tmp_path / "run"
    code = twin_main(["run", "--config", str(small / "small.toml"), "--out", str(out),
                      "--no-report", "--quiet"])  # fmt: skip
    assert SumoSession._active is None
    err = capsys.readouterr().err
    if after_steps == 0:
        assert code == 2
        lines = [line for line in err.splitlines() if "error" in line]
        assert len(lines) == 1 and "out of memory; use a smaller grid" in lines[0]
        assert not (out / "series.parquet").exists()  # no partial run of 0 steps
    else:
        assert code == 1
        reason = json.loads((out / "run.json").read_text())["partial_reason"]
        assert "out of memory (MemoryError)" in reason, reason


def test_a_swarms_own_failure_is_no_partial_run_of_the_simulation(
    small, tmp_path, monkeypatch, capsys
):
    """A swarm that fails (rl-online's optimizer on a torch cache it cannot make) is not the
    simulation crashing: one line, not a partial run of no seed that ended in an internal
    KeyError (probe 26's f06)."""
    from twin.policies import RandomPolicy

    def failing(self, grid, n_drones, rng):
        raise NotADirectoryError(20, "Not a directory", "/a/file/t")

    monkeypatch.setattr(RandomPolicy, "reset", failing)
    out = tmp_path / "run"
    code = twin_main(["run", "--config", str(small / "small.toml"), "--out", str(out),
                      "--swarms", "greedy,random", "--no-report", "--quiet"])  # fmt: skip
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2 and "/a/file/t: Not a directory" in err[-1], err
    assert "internal error" not in err[-1] and SumoSession._active is None


def test_a_swarm_failing_mid_run_keeps_the_steps_done(small, tmp_path, monkeypatch, capsys):
    """A swarm that fails after some steps (memory, torch) keeps the run's steps as a partial
    run, as a simulation crash does; only a failure before the first step is raised (the final
    review of probe 26's fixes)."""
    from twin.policies import RandomPolicy

    act = RandomPolicy.act

    def failing(self, view):
        if view.k == 2:
            raise MemoryError("simulated")
        return act(self, view)

    monkeypatch.setattr(RandomPolicy, "act", failing)
    out = tmp_path / "run"
    code = twin_main(["run", "--config", str(small / "small.toml"), "--out", str(out),
                      "--swarms", "greedy,random", "--no-report", "--quiet"])  # fmt: skip
    assert code == 1, capsys.readouterr().err
    assert pd.read_parquet(out / "series.parquet")["step"].max() == 1


def test_bad_files_give_one_line_errors(small, tmp_path, capsys):
    cfg = str(small / "small.toml")
    broken = tmp_path / "broken.net.xml"
    broken.write_text("<net><edge")
    not_net = tmp_path / "routes_as.net.xml"
    not_net.write_text("<routes/>")
    cases = [
        (["--net", str(tmp_path / "missing.net.xml")], "missing.net.xml"),
        (["--net", str(broken)], "broken.net.xml"),
        (["--net", str(not_net)], "routes_as.net.xml"),
        (["--net", str(small / "small.net.xml"), "--routes", str(broken)], "broken.net.xml"),
        (["--sumocfg", str(tmp_path / "nope.sumocfg")], "nope.sumocfg"),
    ]
    for extra, name in cases:
        code = twin_main(["run", "--config", cfg, "--quiet", "--out", str(tmp_path / "x"), *extra])
        err = capsys.readouterr().err.strip().splitlines()
        assert code == 2
        assert len(err) == 1 and err[0].startswith("twin: error:") and name in err[0]
    with pytest.raises(UserError, match="not a parquet file"):
        Tape.read(broken)


def test_swapped_network_without_routes_gets_generated_demand(small, tmp_path, monkeypatch):
    """A network not written for twin (netgenerate --spider), demand from randomTrips, generated
    into the cache once and reused."""
    monkeypatch.setenv("TWIN_CACHE_DIR", str(tmp_path / "cache"))
    net = tmp_path / "spider.net.xml"
    run_sumo_program(
        [binary("netgenerate"), "--spider", "--spider.arm-number", "5",
         "--spider.circle-number", "4", "--spider.space-radius", "250",
         "--no-internal-links", "true", "-o", str(net)],
        what="netgenerate",
    )  # fmt: skip
    config = load_config(small / "small.toml")
    source = sumo_source(config, net=net, horizon=6)
    result = _patrol(source)
    assert result.completed_steps == 6
    assert source.snapshots[-1][2].sum() > 0
    (demand,) = (tmp_path / "cache" / "imported").glob("spider*/rush_hour.trips.xml")
    stamp = demand.stat().st_mtime_ns
    sumo_source(config, net=net, horizon=6)
    assert demand.stat().st_mtime_ns == stamp  # reused, not regenerated


OSM = """<?xml version="1.0" encoding="UTF-8"?>
<osm version="0.6" generator="hand">
  <bounds minlat="22.540" minlon="114.050" maxlat="22.550" maxlon="114.060"/>
  <node id="1" lat="22.541" lon="114.051"/><node id="2" lat="22.541" lon="114.055"/>
  <node id="3" lat="22.541" lon="114.059"/><node id="4" lat="22.545" lon="114.055"/>
  <node id="5" lat="22.537" lon="114.055"/><node id="6" lat="22.549" lon="114.055"/>
  <way id="10"><nd ref="1"/><nd ref="2"/><nd ref="3"/><tag k="highway" v="primary"/></way>
  <way id="11"><nd ref="5"/><nd ref="2"/><nd ref="4"/><nd ref="6"/>
    <tag k="highway" v="secondary"/></way>
</osm>
"""


def test_an_osm_extracts_network_is_named_after_all_its_name():
    """``a.b.osm`` and ``a.c.osm`` both became ``a.net.xml``, ``.x.osm`` became ``.net.xml``
    (probe 26b's v01)."""
    from twin.sumo.network import osm_network_name

    names = ["tiny.osm", "map.osm.gz", "map.osm.xml", "a.b.osm", "a.c.OSM", ".x.osm", "plain"]
    assert [osm_network_name(Path(n)) for n in names] == [
        "tiny.net.xml", "map.net.xml", "map.net.xml", "a.b.net.xml", "a.c.net.xml",
        ".x.net.xml", "plain.net.xml",
    ]  # fmt: skip


def test_osm_import_and_sumocfg(small, tmp_path, monkeypatch):  # writes only under tmp_path
    from twin.sumo.network import import_osm

    monkeypatch.setenv("TWIN_CACHE_DIR", str(tmp_path / "cache"))
    osm = tmp_path / "tiny.osm"
    osm.write_text(OSM)
    net = import_osm(osm, tmp_path / "osm")
    assert net.exists() and "<edge" in net.read_text()
    net.write_text("mine")  # a file twin did not write is never replaced
    with pytest.raises(UserError, match=r"tiny\.net\.xml exists there; twin never overwrites"):
        import_osm(osm, tmp_path / "osm")
    assert net.read_text() == "mine" and sorted(p.name for p in net.parent.iterdir()) == [
        "tiny.net.xml"
    ]
    cached = import_osm(osm)  # by default into the cache, converted once
    assert cached.parent.parent == tmp_path / "cache" / "imported"
    stamp = cached.stat().st_mtime_ns
    assert "<edge" in cached.read_text() and import_osm(osm) == cached
    assert cached.stat().st_mtime_ns == stamp
    cfg = tmp_path / "small.sumocfg"
    cfg.write_text(
        f'<configuration><input><net-file value="{small / "small.net.xml"}"/>'
        f'<route-files value="{small / "small.trips.xml"}"/></input></configuration>'
    )
    config = load_config(small / "small.toml")
    source = sumo_source(config, sumocfg=cfg, horizon=3)
    assert _patrol(source).completed_steps == 3


def test_an_osm_extract_without_streets_is_one_line_naming_it(tmp_path, monkeypatch, capsys):
    """An extract whose ways twin's city options all drop (tracks, service roads): no empty
    network with exit 0, no error naming the cache's file; and a cached empty conversion of
    an earlier twin is rebuilt, then refused alike."""
    from twin.cli import main
    from twin.sumo.network import imported_dir

    monkeypatch.setenv("TWIN_CACHE_DIR", str(tmp_path / "cache"))
    tracks = tmp_path / "tracks.osm"  # every way dropped as netconvert reads it
    tracks.write_text(OSM.replace('"primary"', '"track"').replace('"secondary"', '"service"'))
    osm = tmp_path / "isolated.osm"  # one one-way road: removed as isolated (exit 0, no edge)
    osm.write_text(OSM.replace('v="primary"/>', 'v="primary"/><tag k="oneway" v="yes"/>')
                   .replace('v="secondary"', 'v="track"'))  # fmt: skip
    for extract in (tracks, osm):
        out = tmp_path / f"net-{extract.stem}"
        assert main(["network", "import-osm", str(extract), "--out", str(out)]) == 2
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and err[0].startswith(f"twin: error: {extract}: no road is"), err
        assert not list(out.glob("*"))  # no half network left behind
    stale = imported_dir(osm)  # an earlier twin cached an empty conversion
    stale.mkdir(parents=True)
    (stale / "isolated.net.xml").write_text('<?xml version="1.0"?>\n<net version="1.20"></net>\n')
    argv = ["run", "--osm", str(osm), "--horizon", "2", "--out", str(tmp_path / "run")]
    assert main(argv) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert err[-1].startswith(f"twin: error: {osm}: no road is left"), err
    assert not (tmp_path / "run").exists()


@pytest.mark.parametrize(
    ("node", "said"),
    [
        ('lat="95.0" lon="114.051"', "netconvert cannot project node 1 at lat = 95.0, lon = 114.051; a node's lat must lie in [-90, 90] and its lon in [-180, 180]: fix or remove the node"),
        ('lat="22.541" lon="200"', "netconvert cannot project node 1 at lat = 22.541, lon = 200; "),
        ('lat="x" lon="114.051"', "Attribute 'lat' in definition of node '1' Invalid Number Format (double) x; fix that node's attribute"),
        ('lon="114.051"', "Attribute 'lat' is missing in definition of node '1'; fix that node's attribute"),
    ],
)  # fmt: skip
def test_an_osm_node_netconvert_cannot_place_is_named_with_the_fix(node, said, tmp_path, capsys):
    """A node at a latitude of 95 (or unreadable) is one line naming the extract, the node,
    its coordinates and the range they must lie in, not netconvert's bare "Unable to project
    coordinates for junction '1'" (probe 24's f04)."""
    from twin.cli import main

    osm = tmp_path / "bad.osm"
    osm.write_text(OSM.replace('lat="22.541" lon="114.051"', node, 1))
    assert main(["network", "import-osm", str(osm), "--out", str(tmp_path / "net")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith(f"twin: error: {osm}: {said}"), err


def test_an_osm_extract_of_nodes_and_no_street_is_no_road(tmp_path, capsys):
    """Nodes but no street way (buildings only): netconvert's "No nodes loaded" (the file
    holds nodes) was passed on with no fix (probe 25's f05)."""
    from twin.cli import main

    osm = tmp_path / "nohw.osm"
    osm.write_text(OSM.replace('k="highway" v="primary"', 'k="building" v="yes"')
                   .replace('k="highway" v="secondary"', 'k="building" v="yes"'))  # fmt: skip
    assert main(["network", "import-osm", str(osm), "--out", str(tmp_path / "net")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith(
        f"twin: error: {osm}: no road is left after conversion: no node lies on a street way"
    ), err
    assert err[0].endswith("give an extract with streets"), err


@pytest.mark.parametrize("given", ["folder", "/dev/null"])
def test_an_osm_flag_on_a_folder_or_device_is_one_line(given, tmp_path, capsys):
    """``--osm`` on a folder or a device: one line, as the other file flags say it (a device
    reached netconvert, "invalid document structure"; a folder was an error with a log: probe
    25's f05)."""
    from twin.cli import main

    osm = tmp_path / "d.osm" if given == "folder" else Path(given)
    if given == "folder":
        osm.mkdir()
    out = tmp_path / "run"
    assert main(["run", "--osm", str(osm), "--horizon", "2", "--out", str(out)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith(f"twin: error: {osm}: is a "), err
    assert err[0].endswith("(an OSM extract: .osm, or .osm.gz)") and not out.exists()


def test_import_osm_out_on_a_file_is_the_out_line(tmp_path, capsys):
    """``--out`` naming a file is refused as every command's ``--out`` is, before netconvert
    runs (it was the system's bare "File exists"; probe 14's f07)."""
    from twin.cli import main

    osm, taken = tmp_path / "a.osm", tmp_path / "taken.toml"
    osm.write_text(OSM)
    taken.write_text("keep")
    assert main(["network", "import-osm", str(osm), "--out", str(taken)]) == 2
    err = capsys.readouterr().err.strip()
    assert err == (f"twin: error: --out {taken}: is a file, not a folder (a file is in the "
                   "way); move it or pass another folder"), err  # fmt: skip
    assert taken.read_text() == "keep"


def test_import_osm_refuses_a_bzip2_extract_and_an_unwritable_out(tmp_path, capsys):
    """An extract as OSM downloads come (.osm.bz2), which netconvert does not read: one line
    saying so and how to decompress it (netconvert's "invalid multi-byte sequence" before);
    an --out on a file system that takes no files is the --out line, and a refused import
    leaves no folder of its own behind (probe 15's f15, f16)."""
    import bz2

    from twin.cli import main

    packed = tmp_path / "a.osm.bz2"
    packed.write_bytes(bz2.compress(OSM.encode()))
    assert main(["network", "import-osm", str(packed), "--out", str(tmp_path / "n")]) == 2
    err = capsys.readouterr().err.strip()
    assert err == (f"twin: error: {packed}: a bzip2-compressed extract, which netconvert does "
                   "not read; decompress it (bunzip2 -k a.osm.bz2) and give the .osm (gzip "
                   "works too)"), err  # fmt: skip
    import lzma
    import zipfile

    xz, zipped = tmp_path / "a.osm.xz", tmp_path / "a.osm.zip"
    xz.write_bytes(lzma.compress(OSM.encode()))
    with zipfile.ZipFile(zipped, "w") as archive:
        archive.writestr("a.osm", OSM)
    zst, pbf = tmp_path / "a.osm.zst", tmp_path / "a.osm.pbf"
    zst.write_bytes(b"\x28\xb5\x2f\xfd" + b"\0" * 12)
    pbf.write_bytes(b"\0\0\0\x0d\x0a\x09OSMHeader\x18\x10")  # a PBF's first blob header
    for path, what in ((xz, "an xz"), (zipped, "a zip"), (zst, "a zstd")):
        assert main(["network", "import-osm", str(path), "--out", str(tmp_path / "n")]) == 2
        err = capsys.readouterr().err.strip()
        assert f"{path}: {what}-compressed extract" in err, err
    assert main(["network", "import-osm", str(pbf), "--out", str(tmp_path / "n")]) == 2
    assert "an OSM PBF extract, which netconvert does not read" in capsys.readouterr().err
    comma = tmp_path / "my osm,v2"
    comma.mkdir()
    (comma / "a.osm").write_text(OSM)
    assert main(["network", "import-osm", str(comma / "a.osm"), "--out", str(tmp_path / "n")]) == 2
    assert "netconvert splits file names at commas" in capsys.readouterr().err
    osm = tmp_path / "a.osm"
    osm.write_text(OSM)
    assert main(["network", "import-osm", str(osm), "--out", "/proc/twin-x"]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("twin: error: --out /proc/twin-x: ") and "\n" not in err, err
    tracks = tmp_path / "tracks.osm"
    tracks.write_text(OSM.replace('"primary"', '"track"').replace('"secondary"', '"service"'))
    assert main(["network", "import-osm", str(tracks), "--out", str(tmp_path / "new")]) == 2
    assert not (tmp_path / "new").exists()


def test_the_sumo_line_gives_the_warm_up_start_sumo_begins_at(capsys):
    """A warm-up of 895 s at steps of 30 s: SUMO begins at 0 s, and the line says so (it gave
    the start of 29 whole steps, 00:00:25; probe 19's f07)."""
    from types import SimpleNamespace

    from twin.cli.run import _announce
    from twin.clock import clock_label
    from twin.sumo.source import SumoScenario

    s = SumoScenario(Path("g8.net.xml"), [], begin_s=895.0, warmup_s=895.0, step_s=30.0,
                     horizon=10, name="g8.net.xml")  # fmt: skip
    source = SimpleNamespace(
        scenario=s,
        grid=SimpleNamespace(nx=8, ny=8, n_free=64),
        geometry=SimpleNamespace(cell_m=200.0),
        clock=lambda k: clock_label(s.begin_s + k * s.step_s),
    )
    _announce(source)
    err = capsys.readouterr().err
    assert "00:00:00 warm-up, 00:14:55 - 00:19:55, step 30 s" in err, err
