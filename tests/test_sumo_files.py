"""SUMO's files as SUMO reads and writes them, SUMO's configured outputs kept in the run folder.

Accepted forms (each read as SUMO reads it): ``<sumoConfiguration>`` as ``sumo -C`` writes it
and ``<configuration>``; option values as ``value=`` attributes or as element text; additional
files with an ``<add>`` root, route files of any root SUMO takes; gzip-compressed files. Refused
(exit 2, one line naming the file and the fix, no traceback, nothing changed outside the run
folder, no run folder left): NaN or infinite times, a config of another SUMO program, a config
without a network, a network given as a route file, a ``<save-configuration>`` or ``<help>``
(SUMO would write or print it and quit). And a public-style scenario whose sumocfg asks for
outputs (trip info, summary, log, detectors of an additional file) runs from its sumocfg alone:
every output lands in ``RUN/sumo/``, listed in the manifest, and the scenario folder hashes the
same before and after, also with a relative ``--out``, an ``output-prefix`` (``-suffix``) that
names folders, and device outputs named by vehicle types.
"""

from __future__ import annotations

import gzip
import hashlib
import json
import re
import shutil
import subprocess
import xml.etree.ElementTree as ET
from pathlib import Path

import pandas as pd
import pytest

pytest.importorskip("libsumo")

from twin.cli import main
from twin.errors import UserError
from twin.runs import check_run_folder
from twin.sumo.outputs import MESSAGES_NAME
from twin.sumo.readers import departure_span, read_sumocfg
from twin.sumo.tools import binary, run_sumo_program

CONFIG = """
[swarm]
n_drones = 2
[traffic]
kind = "sumo"
cell_m = 200.0
drone_speed_kmh = 12.0   # one step = 60 s
warmup_min = 1.0
[evaluate]
swarms = ["random", "greedy"]
"""
DETECTORS = """<additional>
    <inductionLoop id="loop" lane="{lane}" pos="20" period="60" file="out/loops.xml"/>
    <e1Detector id="loop2" lane="{lane}" pos="40" freq="60" file="out/loops.xml"/>
    <laneAreaDetector id="area" lane="{lane}" pos="10" endPos="100" period="60"
                      file="area.xml"/>
    <edgeData id="ed" period="120" file="edges.xml"/>
    <laneData id="ld" period="120" file="../scenario/out/lanes.xml"/>
</additional>
"""
OUTPUTS = """<output>
        <tripinfo-output value="out/tripinfo.xml"/>
        <summary-output value="summary.xml"/>
        <statistic-output value="stats.xml"/>
    </output>
    <report>
        <log value="sumo.log"/>
        <error-log value="errors.log"/>
    </report>"""


def tree_hash(root: Path) -> dict[str, str]:
    """sha256 of every file under ``root`` and the list of its folders (the whole tree)."""
    out = {}
    for p in sorted(root.rglob("*")):
        rel = p.relative_to(root).as_posix()
        out[rel] = hashlib.sha256(p.read_bytes()).hexdigest() if p.is_file() else "dir"
    return out


@pytest.fixture(scope="module")
def scenario(tmp_path_factory) -> Path:
    """``scenario/``: a 3 x 3 signalised grid, 10 min of random trips, a detector file, a
    sumocfg with outputs; ``config.toml`` beside it."""
    from twin.sumo.network import generate_grid_scenario

    root = tmp_path_factory.mktemp("files")
    d = root / "scenario"
    d.mkdir()
    net, trips = generate_grid_scenario(d, blocks=3, block_m=300, end_s=600, period_s=4.0, seed=2)
    (d / "small.rou.xml").unlink()  # keep the trips: SUMO routes them on loading
    (d / "out").mkdir()  # SUMO writes into existing folders only
    with open(net, "rb") as fh:
        lane = next(
            lane.get("id")
            for lane in ET.parse(fh).getroot().iter("lane")
            if not lane.get("id").startswith(":") and float(lane.get("length")) > 150
        )
    (d / "detectors.add.xml").write_text(DETECTORS.format(lane=lane))
    (d / "public.sumocfg").write_text(
        f"""<?xml version="1.0" encoding="UTF-8"?>
<configuration>
    <input>
        <net-file value="{net.name}"/>
        <route-files value="{trips.name}"/>
        <additional-files value="detectors.add.xml"/>
    </input>
    {OUTPUTS}
</configuration>
"""
    )
    (root / "config.toml").write_text(CONFIG)
    return root


def _run(root: Path, out: Path, *args: str) -> int:
    return main(["run", "--config", str(root / "config.toml"), "--quiet", "--no-report",
                 "--out", str(out), *args])  # fmt: skip


def test_configured_outputs_go_into_the_run_folder(scenario, capsys):
    before = tree_hash(scenario / "scenario")
    out = scenario / "run-outputs"
    code = _run(scenario, out, "--sumocfg", str(scenario / "scenario" / "public.sumocfg"),
                "--seeds", "2")  # fmt: skip
    err = capsys.readouterr().err
    assert code == 0, err
    assert tree_hash(scenario / "scenario") == before  # nothing written beside its files
    sumo = out / "sumo"
    names = {p.name for p in sumo.iterdir() if p.is_file()}
    want = {"tripinfo.xml", "summary.xml", "stats.xml", "sumo.log", "errors.log", "loops.xml",
            "area.xml", "edges.xml", "lanes.xml", "detectors.add.xml"}  # fmt: skip
    assert names == want
    for name in ("tripinfo.xml", "summary.xml", "loops.xml", "area.xml", "edges.xml"):
        with open(sumo / name, "rb") as fh:
            assert len(ET.parse(fh).getroot()) > 0, name  # SUMO wrote and closed it
    with open(sumo / "loops.xml", "rb") as fh:  # one file shared by two detectors, as given
        assert {i.get("id") for i in ET.parse(fh).getroot().iter("interval")} == {"loop", "loop2"}
    seed = json.loads((out / "run.json").read_text())["seeds"][1]
    assert {p.name for p in (sumo / f"seed-{seed}").iterdir()} == want  # the second simulation
    manifest = check_run_folder(out)
    assert {f"sumo/{n}" for n in want} <= set(manifest["files"])
    assert {f"sumo/seed-{seed}/{n}" for n in want} <= set(manifest["files"])
    run = json.loads((out / "run.json").read_text())
    assert set(run["traffic"]["sumo_outputs"]) == want


def test_sumo_writes_nothing_when_the_run_is_refused(scenario, capsys):
    """A bad additional file on top of the scenario: SUMO refuses to start, no run folder."""
    bad = scenario / "bad.add.xml"
    bad.write_text('<additional><vType id="x" vClass="flyingcar"/></additional>')
    before = tree_hash(scenario / "scenario")
    out = scenario / "run-refused"
    code = _run(scenario, out, "--sumocfg", str(scenario / "scenario" / "public.sumocfg"),
                "--additional", str(bad))  # fmt: skip
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2 and "flyingcar" in err[-1] and "Traceback" not in "".join(err)
    assert not out.exists()
    assert tree_hash(scenario / "scenario") == before


def test_sumo_refusing_a_rewritten_file_names_the_users_file(scenario, tmp_path, capsys):
    """A detector on a lane the network lacks: SUMO refuses twin's copy of the file, the one
    line names the user's file (the copy went with the refused run's folder)."""
    bad = tmp_path / "bad-detector.add.xml"
    bad.write_text(
        '<additional><e1Detector id="d" lane="nowhere_0" pos="1" freq="60" file="d.xml"/>'
        "</additional>"
    )
    out = tmp_path / "run"
    code = _run(scenario, out, "--sumocfg", str(scenario / "scenario" / "public.sumocfg"),
                "--additional", str(bad))  # fmt: skip
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2 and err[-1].startswith("twin: error:"), err
    assert str(bad) in err[-1] and "nowhere_0" in err[-1] and str(out) not in err[-1]
    assert not out.exists() and sorted(p.name for p in tmp_path.iterdir()) == [bad.name]


def test_a_file_given_twice_is_named_with_the_repeat_to_drop(scenario, tmp_path, capsys):
    """An additional file given twice (by --additional twice, or by the sumocfg and
    --additional): SUMO refuses its ids as taken; the line says the file is loaded twice and to
    drop the repeat (it quoted SUMO alone: probe 24)."""
    types = tmp_path / "types.add.xml"
    types.write_text('<additional><vType id="car2" maxSpeed="20"/></additional>')
    cfg = scenario / "scenario" / "public.sumocfg"
    for n, given in enumerate(
        (["--additional", str(types), "--additional", str(types)], ["--additional", str(types)])
    ):
        text = _cfg(NET_AND_TRIPS + '<input><additional-files value="types.add.xml"/></input>')
        case = _write_case(scenario, tmp_path / f"case{n}", text, {}) if n else cfg
        if n:
            (case.parent / "types.add.xml").symlink_to(types)
        out = tmp_path / f"run{n}"
        code = _run(scenario, out, "--sumocfg", str(case), *given)
        err = capsys.readouterr().err.strip().splitlines()
        assert code == 2 and "with the id 'car2' exists; types.add.xml is given twice" in err[-1]
        assert err[-1].endswith("so SUMO loads it twice: drop the repeat"), err
        assert not out.exists()
    single = _run(scenario, tmp_path / "once", "--sumocfg", str(cfg), "--additional", str(types))
    assert single == 0, capsys.readouterr().err  # once is fine


def test_sumo_refusing_a_file_of_the_sumocfg_names_both(scenario, tmp_path, capsys):
    """SUMO refuses, when it starts, an additional file the sumocfg lists: the error line
    names that file and the sumocfg."""
    text = _cfg(NET_AND_TRIPS + '<input><additional-files value="t.add.xml"/></input>')
    bad = {"t.add.xml": '<additional><vType id="x" vClass="nonsense"/></additional>'}
    cfg = _write_case(scenario, tmp_path / "case", text, bad)
    out = tmp_path / "run"
    code = _run(scenario, out, "--sumocfg", str(cfg))
    captured = capsys.readouterr()
    err = captured.err.strip().splitlines()
    assert code == 2 and err[-1].startswith("twin: error:"), err
    assert f"{cfg.parent / 't.add.xml'} (named in {cfg}): SUMO refuses it" in err[-1], err
    assert "Traceback" not in captured.err + captured.out and not out.exists()


def test_a_sumocfg_written_by_sumo_itself(scenario, tmp_path, capsys):
    """``sumo -C`` writes ``<sumoConfiguration>`` with relative paths; twin runs it as is."""
    d = tmp_path / "generated"
    d.mkdir()
    for name in ("small.net.xml", "small.trips.xml"):
        shutil.copy(scenario / "scenario" / name, d / name)
    cfg = d / "generated.sumocfg"
    run_sumo_program(
        [binary("sumo"), "-n", str(d / "small.net.xml"), "-r", str(d / "small.trips.xml"),
         "--tripinfo-output", str(d / "trips.out.xml"), "--begin", "0", "--end", "600",
         "--save-configuration.relative", "true", "-C", str(cfg)],
        what="sumo -C",
    )  # fmt: skip
    root = ET.parse(cfg).getroot()
    assert root.tag == "sumoConfiguration"
    assert root.find("input/net-file").get("value") == "small.net.xml"
    before = tree_hash(d)
    out = tmp_path / "run"
    code = _run(scenario, out, "--sumocfg", str(cfg))
    err = capsys.readouterr().err
    assert code == 0, err
    assert tree_hash(d) == before
    assert (out / "sumo" / "trips.out.xml").stat().st_size > 0
    run = json.loads((out / "run.json").read_text())
    assert run["traffic"]["begin"] == "00:01:00"  # the config's window: 0 + 1 min warm-up


def _cfg(body: str, root: str = "configuration") -> str:
    return f"<{root}>{body}</{root}>"


NET_AND_TRIPS = (
    '<input><net-file value="small.net.xml"/><route-files value="small.trips.xml"/></input>'
)

# name -> (sumocfg text, files to write beside it {name: text | bytes}, expected begin, end)
ACCEPTED = {
    "<sumoConfiguration> root": (_cfg(NET_AND_TRIPS, "sumoConfiguration"), {}, None, None),
    # SUMO reads a config's options under any root (`sumo -c` runs both)
    "a <foo> root": (_cfg(NET_AND_TRIPS, "foo"), {}, None, None),
    "a <netconvertConfiguration> root of SUMO's options": (
        _cfg(NET_AND_TRIPS, "netconvertConfiguration"), {}, None, None),
    "values as element text": (
        _cfg("<input><net-file>small.net.xml</net-file>"
             "<route-files>small.trips.xml</route-files></input>"
             "<time><begin>60</begin><end>0:08:00</end></time>"),
        {}, 60.0, 480.0,
    ),
    "an <add> root and gzip": (
        _cfg('<input><net-file value="small.net.xml"/><route-files value="t.rou.xml.gz"/>'
             '<additional-files value="types.add.xml"/></input>'),
        {"types.add.xml": '<add><vType id="car" vClass="passenger"/></add>',
         "t.rou.xml.gz": "GZ:small.trips.xml"},
        None, None,
    ),
    "no route files (twin generates demand)": (
        _cfg('<input><net-file value="small.net.xml"/></input>'
             '<time><begin value="0"/><end value="600"/></time>'),
        {}, 0.0, 600.0,
    ),
    "demand only in an additional file": (
        _cfg('<input><net-file value="small.net.xml"/>'
             '<additional-files value="types.add.xml,trips.add.xml"/></input>'),
        {"types.add.xml": '<add><vType id="car" vClass="passenger"/></add>',
         "trips.add.xml": "ADD:small.trips.xml"},
        None, None,
    ),
    "options right under the root, no sections": (
        _cfg('<net-file value="small.net.xml"/><route-files value="small.trips.xml"/>'
             '<begin value="60"/><end value="480"/>', "sumoConfiguration"),
        {}, 60.0, 480.0,
    ),
    "SUMO's no-end -1": (
        _cfg(NET_AND_TRIPS + '<time><begin value="0"/><end value="-1"/></time>'),
        {}, 0.0, None,
    ),
    "remote port 0, SUMO's default: no TraCI server": (
        _cfg(NET_AND_TRIPS + '<traci_server><remote-port value="0"/></traci_server>'),
        {}, None, None,
    ),
    # SUMO skips an empty value (then reads the element's text); each was taken as the value,
    # which dropped the routes, the network or the end (a review against SUMO 1.28)
    "empty values, which SUMO skips": (
        _cfg('<input><net-file value="small.net.xml"/><net-file value=""/><route-files value="">'
             'small.trips.xml</route-files><route-files value=""/></input>'
             '<time><begin value="60"/><end value="480"/><end value=""/></time>'),
        {}, 60.0, 480.0,
    ),
    "a plain option an unset variable empties, which SUMO takes": (
        _cfg(NET_AND_TRIPS + '<output><output-prefix value="${TWIN_TEST_NEVER_SET}"/></output>'
             '<time><begin value="60"/><end value="480"/></time>'),
        {}, 60.0, 480.0,
    ),
    "C's hexadecimal times, and SUMO's false words for help": (
        _cfg(NET_AND_TRIPS + '<time><begin value="0x3c"/><end value="0x1E0"/></time>'
             '<report><help value="f"/><version value="-"/></report>'),
        {}, 60.0, 480.0,
    ),
}  # fmt: skip


def _write_case(scenario: Path, d: Path, text: str, files: dict[str, str]) -> Path:
    d.mkdir()
    for name in ("small.net.xml", "small.trips.xml"):
        shutil.copy(scenario / "scenario" / name, d / name)
    for name, body in files.items():
        if body.startswith("GZ:"):
            (d / name).write_bytes(gzip.compress((d / body[3:]).read_bytes()))
        elif body.startswith("ADD:"):  # a route file's demand in an additional file
            routes = (d / body[4:]).read_text()
            (d / name).write_text(
                routes.replace("<routes", "<additional").replace("</routes>", "</additional>")
            )
        elif body.startswith("LATE:"):  # a route file's demand 2000 s later
            routes = (d / body[5:]).read_text()
            shift = lambda m: f'depart="{float(m.group(1)) + 2000:.2f}"'  # noqa: E731
            (d / name).write_text(re.sub(r'depart="([0-9.]+)"', shift, routes))
        elif body.startswith("LINK:"):
            (d / name).symlink_to(d / body[5:])
        else:
            (d / name).write_text(body)
    if text.startswith("GZ:"):
        (d / "case.sumocfg").write_bytes(gzip.compress(text[3:].encode()))
    else:
        (d / "case.sumocfg").write_text(text)
    return d / "case.sumocfg"


@pytest.mark.parametrize("case", list(ACCEPTED))
def test_accepted_sumocfg_forms(scenario, tmp_path, capsys, case):
    from twin.config import load_config
    from twin.sumo.scenario import sumo_source

    text, files, begin, end = ACCEPTED[case]
    cfg = _write_case(scenario, tmp_path / "case", text, files)
    read = read_sumocfg(cfg)
    assert read.net == (tmp_path / "case" / "small.net.xml").resolve()
    assert (read.begin, read.end) == (begin, end)
    source = sumo_source(load_config(scenario / "config.toml"), sumocfg=cfg)
    assert source.horizon >= 1
    err = capsys.readouterr().err
    assert ("names no <route-files>; twin generates" in err) == ("no route files" in case), err
    if "additional" in case:  # SUMO loads its vehicles as demand: the window is theirs
        assert not source.scenario.route_files
        trips = scenario / "scenario" / "small.trips.xml"
        assert source.scenario.extra["departures"] == list(departure_span([trips]))
    else:
        assert source.scenario.route_files


def test_a_net_given_besides_the_sumocfg_replaces_its_own(scenario, tmp_path, capsys):
    """As with ``sumo -c case.sumocfg -n small.net.xml``: the sumocfg's own <net-file> (here
    named twice, which SUMO alone would refuse) is not read."""
    text = _cfg('<input><net-file value="small.net.xml,small.net.xml"/>'
                '<route-files value="small.trips.xml"/></input>')  # fmt: skip
    cfg = _write_case(scenario, tmp_path / "case", text, {})
    net = scenario / "scenario" / "small.net.xml"
    out = tmp_path / "run"
    code = _run(scenario, out, "--sumocfg", str(cfg), "--net", str(net), "--horizon", "2")
    err = capsys.readouterr().err
    assert code == 0, err
    assert json.loads((out / "run.json").read_text())["traffic"]["net_file"] == str(net)


def test_gzip_additional_with_outputs_is_rewritten(scenario, tmp_path):
    """A compressed detector file whose outputs are redirected: the copy is plain XML in the
    output folder, other relative paths in it made absolute (they resolve as before)."""
    from twin.sumo.outputs import redirect_outputs

    d = tmp_path / "gz"
    d.mkdir()
    add = d / "det.add.xml.gz"
    add.write_bytes(gzip.compress(
        b'<additional><include href="types.xml"/>'
        b'<e1Detector id="a" lane="x_0" pos="1" freq="60" file="a.xml"/>'
        b'<poly id="p" shape="0,0 1,1" imgFile="img/p.png"/></additional>'
    ))  # fmt: skip
    (d / "types.xml").write_text('<additional><vType id="t"/></additional>')
    options, _ = redirect_outputs(None, ("--additional-files", str(add)), tmp_path / "o")
    copy = Path(options[1])
    assert copy == tmp_path / "o" / "det.add.xml"
    root = ET.parse(copy).getroot()
    assert root.find("e1Detector").get("file") == str(tmp_path / "o" / "a.xml")
    assert root.find("include").get("href") == str(d / "types.xml")  # no output: the original
    assert root.find("poly").get("imgFile") == str(d / "img" / "p.png")
    untouched, _ = redirect_outputs(None, ("-a", str(d / "types.xml")), tmp_path / "o2")
    assert untouched[1] == str(d / "types.xml") and not (tmp_path / "o2").exists()


def test_an_output_named_like_sumos_messages_is_named_apart(tmp_path):
    """A scenario output named ``sumo-messages.log`` (a sumocfg's ``<log>``, a detector's
    file) goes to ``sumo-messages-2.log``: twin's file of SUMO's messages, moved in when SUMO
    ends, would replace it (probe 21's c37)."""
    from twin.sumo.outputs import MESSAGES_NAME, redirect_outputs

    (tmp_path / "s").mkdir()
    cfg = tmp_path / "s" / "a.sumocfg"
    cfg.write_text(f'<configuration><report><log value="{MESSAGES_NAME}"/></report>'
                   "</configuration>")  # fmt: skip
    options, _ = redirect_outputs(cfg, (), tmp_path / "o")
    assert options == ("--log", str(tmp_path / "o" / "sumo-messages-2.log"))


def test_a_streams_file_is_named_apart_from_the_scenarios_own_names(tmp_path):
    """An output sent to stdout gets a file of its own, after the scenario's outputs keep their
    names: ``<tripinfo-output value="stdout"/>`` beside ``<summary-output
    value="tripinfo-output.xml"/>`` shared one file, interleaved (probe 21's P2-04); an
    element's id too long for a file name is shortened with a digest (P2-01)."""
    from twin.sumo.outputs import MAX_MADE_NAME, redirect_outputs

    (tmp_path / "s").mkdir()
    cfg = tmp_path / "s" / "a.sumocfg"
    cfg.write_text('<configuration><output><tripinfo-output value="stdout"/>'
                   '<summary-output value="tripinfo-output.xml"/></output></configuration>')  # fmt: skip
    options, _ = redirect_outputs(cfg, (), tmp_path / "o")
    given = dict(zip(options[::2], options[1::2], strict=True))
    assert Path(given["--summary-output"]).name == "tripinfo-output.xml"
    assert Path(given["--tripinfo-output"]).name == "tripinfo-output-2.xml"
    add = tmp_path / "s" / "a.add.xml"
    add.write_text(f'<additional><laneData id="{"x" * 300}" file="stdout" period="60"/>'
                   '<edgeData id="e" file="edgeData-e.xml" period="60"/>'
                   '<edgeData id="e" file="-" period="60"/></additional>')  # fmt: skip
    options, _ = redirect_outputs(None, ("-a", str(add)), tmp_path / "o2")
    files = {e.get("id")[:3]: Path(e.get("file")).name for e in ET.parse(options[1]).getroot()}
    assert len(files["xxx"]) <= MAX_MADE_NAME + 4 and files["xxx"].startswith("laneData-xxx")
    assert (files["e"], len(files)) == ("edgeData-e-2.xml", 2)  # the stream's, after the own


def test_a_long_output_prefix_is_shortened_for_a_streams_file(tmp_path, capsys):
    """A 240-character ``output-prefix`` with an output sent to stdout: SUMO alone names no
    file, twin's file for the stream would pass 255 bytes with the prefix (probe 21's P2-05):
    the prefix is shortened with a digest, said in a notice; a short one is kept."""
    from twin.outputs import NAME_MAX
    from twin.sumo.outputs import naming_that_fits, redirect_outputs

    (tmp_path / "s").mkdir()
    cfg = tmp_path / "s" / "a.sumocfg"
    for prefix, kept in (("p" * 240, False), ("run1_", True)):
        cfg.write_text(f'<configuration><output><output-prefix value="{prefix}"/>'
                       '<tripinfo-output value="stdout"/></output></configuration>')  # fmt: skip
        options, plan = redirect_outputs(cfg, (), tmp_path / "o" / prefix[:5])
        given = dict(zip(*[iter(naming_that_fits(options, plan))] * 2, strict=True))
        name = given["--output-prefix"] + Path(given["--tripinfo-output"]).name
        assert len(name.encode()) <= NAME_MAX
        assert (given["--output-prefix"] == prefix) == kept
        assert ("output-prefix 'pppp" in capsys.readouterr().err) != kept
    # a route file's stream, planned after the sumocfg's options: counted too (the review)
    routes = tmp_path / "s" / "r.rou.xml"
    routes.write_text('<routes><vType id="t"><param key="device.ssm.file" value="stdout"/>'
                      "</vType></routes>")  # fmt: skip
    cfg.write_text(f'<configuration><output><output-prefix value="{"q" * 240}"/></output>'
                   "</configuration>")  # fmt: skip
    options, plan = redirect_outputs(cfg, (), tmp_path / "o3")
    made = Path(ET.parse(plan.routes(routes)).getroot()[0][0].get("value")).name
    given = dict(zip(*[iter(naming_that_fits(options, plan))] * 2, strict=True))
    assert len((given["--output-prefix"] + made).encode()) <= NAME_MAX


@pytest.mark.parametrize("stream", ["/dev/stdout", "/dev/stderr", "/proc/self/fd/1"])
def test_an_output_sent_to_a_streams_device_is_named_as_a_stream(tmp_path, stream):
    """``/dev/stdout`` (``/dev/stderr``, ``/proc/self/fd/1``) is SUMO's stream too: its file is
    named as a stream's, not after where twin's own streams point (the file the user's shell
    redirected twin to, twin's temporary log of SUMO's messages: probe 22's f01)."""
    from twin.sumo.outputs import redirect_outputs

    (tmp_path / "s").mkdir()
    cfg = tmp_path / "s" / "a.sumocfg"
    cfg.write_text(f'<configuration><output><tripinfo-output value="{stream}"/></output>'
                   "</configuration>")  # fmt: skip
    add = tmp_path / "s" / "a.add.xml"
    add.write_text(f'<additional><edgeData id="e" file="{stream}" period="60"/></additional>')
    options, _ = redirect_outputs(cfg, ("-a", str(add)), tmp_path / "o")
    given = dict(zip(options[::2], options[1::2], strict=True))
    assert Path(given["--tripinfo-output"]).name == "tripinfo-output.xml"
    edge = ET.parse(given["-a"]).getroot()[0]
    assert Path(edge.get("file")).name == "edgeData-e.xml"


def test_a_parameter_every_vehicle_sends_to_a_stream_shares_one_file(tmp_path):
    """``<param key="device.ssm.file" value="stdout"/>`` in each of many vehicles: one file for
    them all, as they share the stream (each had a file of its own: thousands of open files;
    the review)."""
    from twin.sumo.outputs import redirect_outputs

    routes = tmp_path / "r.rou.xml"
    vehicle = (
        '<vehicle id="v{n}" depart="0"><param key="device.ssm.file" value="stdout"/></vehicle>'
    )
    routes.write_text("<routes>" + "".join(vehicle.format(n=n) for n in range(50)) + "</routes>")
    _, plan = redirect_outputs(None, (), tmp_path / "o")
    copy = ET.parse(plan.routes(routes)).getroot()
    files = {p.get("value") for p in copy.iter("param")}
    assert len(files) == 1 and Path(files.pop()).name == "device.ssm.file.xml"


def test_an_output_named_like_a_later_seeds_folder_is_named_apart(tmp_path):
    """An output named ``seed-1`` would take the folder of seed 1's outputs (``sumo/seed-1/``):
    seed 1 failed on it (FileExistsError) and was left out (probe 21's f08); it is named
    ``seed-1-2``, while ``seed-1.xml`` or ``seeds`` keep their names."""
    from twin.sumo.outputs import OutputPlan

    plan = OutputPlan(tmp_path / "o")
    names = [plan.target(tmp_path / n).name for n in ("seed-1", "seed-1.xml", "seeds", "seed-x")]
    assert names == ["seed-1-2", "seed-1.xml", "seeds", "seed-x"]


def _detector_case(scenario: Path, d: Path, output: str = "") -> Path:
    """A sumocfg in ``d`` with an induction loop writing ``det.xml`` and ``output`` options."""
    with open(scenario / "scenario" / "detectors.add.xml", "rb") as fh:
        lane = ET.parse(fh).getroot().find("inductionLoop").get("lane")
    detector = f'<e1Detector id="d" lane="{lane}" pos="20" freq="60" file="det.xml"/>'
    cfg = _cfg(
        '<input><net-file value="small.net.xml"/><route-files value="small.trips.xml"/>'
        f'<additional-files value="det.add.xml"/></input>{f"<output>{output}</output>" if output else ""}'
    )
    return _write_case(scenario, d, cfg, {"det.add.xml": f"<additional>{detector}</additional>"})


def test_relative_out_keeps_detector_outputs_in_the_run_folder(
    scenario, tmp_path, capsys, monkeypatch
):
    """``--out run1`` from the scenario's folder: SUMO reads the rewritten additional file's
    outputs relative to that copy, so twin gives them absolute (not ``run1/sumo/run1/...``)."""
    cfg = _detector_case(scenario, tmp_path / "case")
    before = tree_hash(tmp_path / "case")
    monkeypatch.chdir(tmp_path / "case")
    code = _run(scenario, Path("run1"), "--sumocfg", cfg.name)
    err = capsys.readouterr().err
    assert code == 0, err
    sumo = tmp_path / "case" / "run1" / "sumo"
    written = sorted(p.relative_to(sumo).as_posix() for p in sumo.rglob("*"))
    assert written == ["det.add.xml", "det.xml"]
    with open(sumo / "det.xml", "rb") as fh:
        assert len(ET.parse(fh).getroot()) > 0
    after = {k: v for k, v in tree_hash(tmp_path / "case").items() if not k.startswith("run1")}
    assert after == before
    assert {"sumo/det.xml", "sumo/det.add.xml"} <= set(check_run_folder(sumo.parent)["files"])


SSM_TYPE = (
    '<vType id="DEFAULT_VEHTYPE"><param key="has.ssm.device" value="true"/>'
    '<param key="device.ssm.file" value="../ssm.xml"/></vType>'
)


@pytest.mark.parametrize("where", ["additional file", "route file"])
def test_device_outputs_of_vehicle_types_go_into_the_run_folder(scenario, tmp_path, capsys, where):
    """A vehicle type whose SSM device writes ``../ssm.xml`` (in an additional or a route
    file): twin loads a rewritten copy, the output lands in ``RUN/sumo/ssm.xml``."""
    root = tmp_path / "root"
    root.mkdir()
    cfg = _detector_case(scenario, root / "case")
    if where == "additional file":
        (root / "case" / "det.add.xml").write_text(f"<additional>{SSM_TYPE}</additional>")
    else:
        trips = root / "case" / "small.trips.xml"
        text = trips.read_text()
        trips.write_text(text.replace("<trip ", SSM_TYPE + "<trip ", 1))
    before = tree_hash(root)
    out = tmp_path / "run"
    code = _run(scenario, out, "--sumocfg", str(cfg))
    err = capsys.readouterr().err
    assert code == 0, err
    assert tree_hash(root) == before
    with open(out / "sumo" / "ssm.xml", "rb") as fh:
        assert ET.parse(fh).getroot().tag == "SSMLog"
    want = ["det.add.xml", "ssm.xml"]
    if where == "route file":  # the detector of _detector_case too
        want = ["det.add.xml", "det.xml", "small.trips.xml", "ssm.xml"]
    run = json.loads((out / "run.json").read_text())
    # SUMO's own messages (its warnings of SSM devices without measures) aside
    assert sorted(o for o in run["traffic"]["sumo_outputs"] if o != MESSAGES_NAME) == want


def _utf16_routes_with_ssm(d: Path) -> None:
    """``small.trips.xml`` again in UTF-16, with a vehicle type whose SSM device writes a file."""
    trips = d / "small.trips.xml"
    text = trips.read_text().replace("<trip ", SSM_TYPE.replace("../ssm", "ssm") + "<trip ", 1)
    text = text.replace('encoding="UTF-8"', 'encoding="UTF-16"')
    trips.write_bytes(text.encode("utf-16"))


def _included_ssm_type(d: Path) -> None:
    """``small.trips.xml`` includes ``types.xml``, whose vehicle type writes an SSM file."""
    (d / "types.xml").write_text(f"<routes>{SSM_TYPE.replace('../ssm', 'ssm')}</routes>")
    trips = d / "small.trips.xml"
    text = trips.read_text()
    start = text.index(">", text.index("<routes")) + 1
    trips.write_text(text[:start] + '<include href="types.xml"/>' + text[start:])


def _ssm_type_without_file(d: Path) -> None:
    """``small.trips.xml``'s default vehicle type has an SSM device and names no file (SUMO
    would write one ``ssm_<vehicle>.xml`` per vehicle into its working folder)."""
    trips = d / "small.trips.xml"
    text = trips.read_text()
    start = text.index(">", text.index("<routes")) + 1
    kind = '<vType id="DEFAULT_VEHTYPE"><param key="has.ssm.device" value="true"/></vType>'
    trips.write_text(text[:start] + kind + text[start:])


def _actuated(program: ET.Element, output: str) -> str:
    """``program`` (a ``<tlLogic>``) as an actuated light whose detectors write ``output``."""
    program.set("type", "actuated")
    for phase in program.iter("phase"):  # a green phase of variable length has detectors
        if "G" in phase.get("state", "") or "g" in phase.get("state", ""):
            phase.set("minDur", "5")
            phase.set("maxDur", "50")
    for key, value in (("freq", "60"), ("file", output)):
        param = ET.Element("param", key=key, value=value)
        program.insert(0, param)
    return ET.tostring(program, encoding="unicode")


def _actuated_program_in_additional(d: Path) -> None:
    """tls.add.xml (no other output) loads another program of the first light: actuated,
    writing its detectors' output to ``tlsdet.xml`` (SUMO: beside tls.add.xml)."""
    with open(d / "small.net.xml", "rb") as fh:
        program = ET.parse(fh).getroot().find("tlLogic")
    program.set("programID", "actuated")
    (d / "tls.add.xml").write_text(f"<additional>{_actuated(program, 'tlsdet.xml')}</additional>")
    cfg = d / "case.sumocfg"
    cfg.write_text(cfg.read_text().replace('"det.add.xml"', '"det.add.xml,tls.add.xml"'))


def _actuated_program_in_network(d: Path) -> None:
    """The network's first light is actuated and writes ``netdet.xml`` (SUMO: beside the
    network file)."""
    net = d / "small.net.xml"
    text = net.read_text()
    start = text.index("<tlLogic ")
    end = text.index("</tlLogic>", start) + len("</tlLogic>")
    program = ET.fromstring(text[start:end])
    net.write_text(text[:start] + _actuated(program, "netdet.xml") + text[end:])


def _environment_variables(d: Path) -> None:
    """The sumocfg names its network through ``${TWIN_TEST_NET}`` and prefixes its outputs
    with ``${TWIN_TEST_PREFIX}`` = ``../../escape_`` (SUMO substitutes both)."""
    cfg = d / "case.sumocfg"
    text = cfg.read_text().replace('"small.net.xml"', '"${TWIN_TEST_NET}"')
    cfg.write_text(
        text.replace(
            "</input>", '</input><output><output-prefix value="${TWIN_TEST_PREFIX}"/></output>'
        )
    )


def _entity_in_routes(d: Path) -> None:
    """small.trips.xml declares an entity in its own DTD and uses it for a trip's origin:
    SUMO's program expands it, libsumo refuses it ("entity 'e1' not found")."""
    trips = d / "small.trips.xml"
    text = trips.read_text()
    origin = re.search(r'<trip [^>]*from="([^"]+)"', text).group(1)
    start = text.index("<routes")
    text = text[:start] + f'<!DOCTYPE routes [<!ENTITY e1 "{origin}">]>\n' + text[start:]
    trips.write_text(text.replace(f'from="{origin}"', 'from="&e1;"', 1))


# name -> (output options of the sumocfg, how to change the case's files, what RUN/sumo/ holds)
ESCAPES = {
    "a route file with an entity of its own DTD (read as a copy, entities expanded)": (
        "",
        _entity_in_routes,
        ["det.add.xml", "det.xml", "small.trips.xml"],
    ),
    "an actuated light's detector output in an additional file": (
        "",
        _actuated_program_in_additional,
        ["det.add.xml", "det.xml", "tls.add.xml", "tlsdet.xml"],
    ),
    "an actuated light's detector output in the network": (
        "",
        _actuated_program_in_network,
        ["det.add.xml", "det.xml", "netdet.xml", "small.net.xml"],
    ),
    "environment variables in the sumocfg": (
        "",
        _environment_variables,
        ["det.add.xml", "escape_det.xml"],
    ),
    "SSM's file named by a device option (SUMO types it a string, not a file)": (
        '<device.ssm.probability value="1"/><device.ssm.file value="ssm.out.xml"/>',
        None,
        ["det.add.xml", "det.xml", "ssm.out.xml"],
    ),
    "SSM devices of a device option without a file": (
        '<device.ssm.probability value="1"/>',
        None,
        ["det.add.xml", "det.xml", "ssm.xml"],
    ),
    "SSM devices of a vehicle type without a file": (
        "",
        _ssm_type_without_file,
        ["det.add.xml", "det.xml", "ssm.xml"],
    ),
    "outputs named by SUMO's synonyms": (
        '<statistics-output value="stats.xml"/><log-file value="sumo.log"/>'
        '<tripinfo v="trips.out.xml"/>',
        None,
        ["det.add.xml", "det.xml", "stats.xml", "sumo.log", "trips.out.xml"],
    ),
    "an additional file in SUMO's namespace": (
        "",
        lambda d: (d / "det.add.xml").write_text(
            (d / "det.add.xml")
            .read_text()
            .replace(
                "<additional>", '<additional xmlns="http://sumo.dlr.de/xsd/additional_file.xsd">'
            )
            .replace("</e1Detector>", "")
            .replace("/>", '/><edgeData id="e" file="ed.xml"/>', 1)
        ),
        ["det.add.xml", "det.xml", "ed.xml"],
    ),
    "a route file including a vehicle type with a device output": (
        "",
        _included_ssm_type,
        ["det.add.xml", "det.xml", "small.trips.xml", "ssm.xml", "types.xml"],
    ),
    "a UTF-16 route file with a device output": (
        "",
        _utf16_routes_with_ssm,
        ["det.add.xml", "det.xml", "small.trips.xml", "ssm.xml"],
    ),
}


@pytest.mark.parametrize("case", list(ESCAPES))
def test_outputs_in_every_form_sumo_reads_go_into_the_run_folder(
    scenario, tmp_path, capsys, monkeypatch, case
):
    """Outputs named as SUMO also reads them (an option's synonym, an element in SUMO's XML
    namespace, a device parameter in a UTF-16 file, SSM devices with or without a file) land
    in RUN/sumo/, never beside the scenario's files nor in the working folder."""
    output, change, want = ESCAPES[case]
    cfg = _detector_case(scenario, tmp_path / "case", output)
    monkeypatch.setenv("TWIN_TEST_NET", str(tmp_path / "case" / "small.net.xml"))
    monkeypatch.setenv("TWIN_TEST_PREFIX", "../../escape_")
    if change is not None:
        change(tmp_path / "case")
    before = tree_hash(tmp_path / "case")
    (tmp_path / "cwd").mkdir()
    monkeypatch.chdir(tmp_path / "cwd")
    out = tmp_path / "run"
    code = _run(scenario, out, "--sumocfg", str(cfg))
    err = capsys.readouterr().err
    assert code == 0, err
    assert tree_hash(tmp_path / "case") == before
    assert list((tmp_path / "cwd").iterdir()) == []
    written = sorted(p.name for p in (out / "sumo").iterdir() if p.name != MESSAGES_NAME)
    assert written == want  # SUMO's own messages (its warnings) aside


@pytest.mark.parametrize("stream", ["stdout", "stderr", "-"])
def test_an_output_sent_to_a_stream_goes_to_a_file_in_the_run_folder(
    scenario, tmp_path, capfd, stream
):
    """``<fcd-output value="stdout"/>``: SUMO would write its XML into twin's tables (stdout)
    or among its notices and errors (stderr); it goes to RUN/sumo/fcd-output.xml."""
    cfg = _detector_case(scenario, tmp_path / "case", f'<fcd-output value="{stream}"/>')
    out = tmp_path / "run"
    code = _run(scenario, out, "--sumocfg", str(cfg))
    captured = capfd.readouterr()
    assert code == 0, captured.err
    assert "<fcd-export" not in captured.out + captured.err
    assert "<fcd-export" in (out / "sumo" / "fcd-output.xml").read_text()
    run = json.loads((out / "run.json").read_text())
    assert "fcd-output.xml" in run["traffic"]["sumo_outputs"]


def test_an_additional_files_outputs_sent_to_streams_go_to_files_in_the_run_folder(
    scenario, tmp_path, capfd
):
    """``<edgeData file="stdout"/>`` (``stderr``, ``-``) in an additional file: SUMO would write
    its XML into twin's tables or among its messages; each goes to RUN/sumo/<element>-<id>.xml
    (they flooded stdout and sumo-messages.log: probe 21's f05)."""
    cfg = _detector_case(scenario, tmp_path / "case")
    streams = ('<edgeData id="ed1" file="stdout" period="120"/><edgeData id="ed2" file="stderr" '
               'period="120"/><laneData id="l/d" file="-" period="120"/>'
               # a file of the name a stream's output takes: each keeps its own
               '<laneData id="named" file="edgeData-ed1.xml" period="120"/>')  # fmt: skip
    add = cfg.parent / "det.add.xml"
    add.write_text(add.read_text().replace("</additional>", streams + "</additional>"))
    before = tree_hash(tmp_path / "case")
    out = tmp_path / "run"
    code = _run(scenario, out, "--sumocfg", str(cfg))
    captured = capfd.readouterr()
    assert code == 0, captured.err
    assert "<edge " not in captured.out + captured.err and "<lane " not in captured.out
    # the named file keeps its name, the stream's takes -2
    for name, row in [("edgeData-ed1-2.xml", "<edge "), ("edgeData-ed2.xml", "<edge "),
                      ("laneData-l_d.xml", "<lane "), ("edgeData-ed1.xml", "<lane ")]:  # fmt: skip
        assert row in (out / "sumo" / name).read_text(), name
        assert name in json.loads((out / "run.json").read_text())["traffic"]["sumo_outputs"]
    log = out / "sumo" / "sumo-messages.log"
    assert not log.exists() or "<edge " not in log.read_text()
    assert tree_hash(tmp_path / "case") == before


@pytest.mark.parametrize("option", ["save-config", "C", "save-configuration"])
def test_save_configuration_by_any_name_is_refused_before_sumo_starts(
    scenario, tmp_path, capsys, option
):
    cfg = _detector_case(scenario, tmp_path / "case")
    text = cfg.read_text().replace("</input>", f'</input><configuration><{option} '
                                   'value="saved.sumocfg"/></configuration>')  # fmt: skip
    cfg.write_text(text)
    before = tree_hash(tmp_path / "case")
    code = _run(scenario, tmp_path / "run", "--sumocfg", str(cfg))
    err = capsys.readouterr().err
    assert code == 2 and err.count("\n") == 1 and "Traceback" not in err, err
    assert f"<{option} value='saved.sumocfg'> makes SUMO write that file and quit" in err, err
    assert tree_hash(tmp_path / "case") == before and not (tmp_path / "run").exists()


@pytest.mark.parametrize("role", ["route-files", "additional-files"])
def test_files_that_include_each_other_are_refused_before_sumo(scenario, tmp_path, capsys, role):
    """``a.xml`` includes ``b.xml``, which includes ``a.xml``: SUMO crashes on it without a
    message; twin names the chain in one line before SUMO starts."""
    root = "routes" if role == "route-files" else "additional"
    files = {"a.xml": f'<{root}><include href="b.xml"/></{root}>',
             "b.xml": f'<{root}><include href="a.xml"/></{root}>'}  # fmt: skip
    input_ = '<net-file value="small.net.xml"/><route-files value="small.trips.xml"/>'
    if role == "route-files":
        input_ = '<net-file value="small.net.xml"/><route-files value="small.trips.xml,a.xml"/>'
    else:
        input_ += '<additional-files value="a.xml"/>'
    cfg = _write_case(scenario, tmp_path / "case", _cfg(f"<input>{input_}</input>"), files)
    out = tmp_path / "run"
    code = _run(scenario, out, "--sumocfg", str(cfg))
    err = capsys.readouterr().err
    assert code == 2 and err.count("\n") == 1 and "Traceback" not in err, err
    assert "include each other (a.xml -> b.xml -> a.xml)" in err, err
    assert not out.exists()


def test_a_config_seeding_sumo_from_the_clock_still_repeats(scenario, tmp_path, capsys):
    """``<random value="true"/>`` (SUMO's seed from the clock) is overridden with a notice:
    two runs of one SUMO seed record the same traffic."""
    cfg = _detector_case(scenario, tmp_path / "case")
    cfg.write_text(cfg.read_text().replace("</input>", '</input><random_number><random '
                                           'value="true"/></random_number>'))  # fmt: skip
    tapes = []
    for name in ("a", "b"):
        assert _run(scenario, tmp_path / name, "--sumocfg", str(cfg)) == 0
        err = capsys.readouterr().err
        assert "<random value='true'> (a seed from the clock) is overridden" in err, err
        tapes.append(pd.read_parquet(tmp_path / name / "tape.parquet"))
    pd.testing.assert_frame_equal(tapes[0], tapes[1])


def test_a_config_seed_replaced_by_twins_is_said(scenario, tmp_path, capsys):
    """``<seed value="42"/>``: twin seeds SUMO itself (one seed per run seed) and says so."""
    cfg = _detector_case(scenario, tmp_path / "case")
    cfg.write_text(cfg.read_text().replace("</input>", '</input><random_number><seed '
                                           'value="42"/></random_number>'))  # fmt: skip
    assert _run(scenario, tmp_path / "run", "--sumocfg", str(cfg)) == 0
    err = capsys.readouterr().err
    assert "<seed value='42'> is replaced by twin's SUMO seed" in err, err


def test_a_step_length_that_is_no_number_is_refused_as_sumo_does(scenario, tmp_path, capsys):
    """``<step-length value="abc"/>``, which SUMO refuses, ran silently (the review of probe
    26); a number other than twin's step is run at twin's with a notice."""
    cfg = _detector_case(scenario, tmp_path / "case")
    text = cfg.read_text()
    cfg.write_text(text.replace("</input>", '</input><time><step-length value="abc"/></time>'))
    out = tmp_path / "run"
    assert _run(scenario, out, "--sumocfg", str(cfg)) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "<step-length value='abc'> is not a number" in err, err
    assert str(cfg) in err and not out.exists()
    cfg.write_text(text.replace("</input>", '</input><time><step-length value="0.5"/></time>'))
    assert _run(scenario, out, "--sumocfg", str(cfg)) == 0
    assert "<step-length value='0.5'> is run as SUMO steps of 1 s" in capsys.readouterr().err
    # SUMO's clock form is a time SUMO takes (the review of probe 26's fixes)
    cfg.write_text(text.replace("</input>", '</input><time><step-length value="0:00:01"/></time>'))
    assert _run(scenario, tmp_path / "clock", "--sumocfg", str(cfg)) == 0
    assert "step-length" not in capsys.readouterr().err


TIME = r"\d{4}(-\d\d){5}"  # SUMO replaces TIME in a prefix or suffix by the date and time
# <option value> of the sumocfg ({root}: the folder holding the scenario's folder) -> the pattern
# of the names SUMO writes in RUN/sumo/ for det.xml and trips.xml (NAME: det or trips)
NAMINGS = {
    '<output-prefix value="../escape_"/>': r"escape_NAME\.xml",
    '<output-prefix value="../../escape_"/>': r"escape_NAME\.xml",
    '<output-prefix value="{root}/abs_"/>': r"abs_NAME\.xml",
    '<output-prefix value="sub/TIME_"/>': TIME + r"_NAME\.xml",
    '<output-prefix value=".."/>': r"\.\.NAME\.xml",
    '<output-suffix value="/../../escape"/>': r"NAMEescape\.xml",
    '<output-suffix value="_TIME"/>': r"NAME_" + TIME + r"\.xml",
}


@pytest.mark.parametrize("naming", list(NAMINGS))
def test_output_prefix_and_suffix_keep_outputs_in_the_run_folder(
    scenario, tmp_path, capsys, naming
):
    """SUMO puts ``output-prefix`` before every output's name, folders included (and
    ``output-suffix`` before its extension); twin keeps only their name part, so the outputs
    stay in ``RUN/sumo/``, named as the sumocfg asks."""
    import re

    root = tmp_path / "root"
    root.mkdir()
    output = naming.format(root=root) + '<tripinfo-output value="trips.xml"/>'
    cfg = _detector_case(scenario, root / "case", output)
    before = tree_hash(root)
    out = tmp_path / "run"
    code = _run(scenario, out, "--sumocfg", str(cfg))
    err = capsys.readouterr().err
    assert code == 0, err
    assert tree_hash(root) == before  # the scenario's folder and the one above it as they were
    assert sorted(p.name for p in tmp_path.iterdir()) == ["root", "run"]
    names = sorted(p.relative_to(out / "sumo").as_posix() for p in (out / "sumo").rglob("*"))
    assert len(names) == 3 and "det.add.xml" in names, names
    for written in ("det", "trips"):
        pattern = NAMINGS[naming].replace("NAME", written)
        assert any(re.fullmatch(pattern, n) for n in names), names
    manifest = check_run_folder(out)
    assert {f"sumo/{n}" for n in names} <= set(manifest["files"])
    run = json.loads((out / "run.json").read_text())
    assert sorted(run["traffic"]["sumo_outputs"]) == names


def test_outputs_and_includes_that_are_link_loops_are_rewritten(tmp_path):
    """An output file or an include that is a symbolic link loop: the output goes into the
    output folder as any other, the include is left for SUMO to refuse (no internal error)."""
    from twin.sumo.outputs import redirect_outputs

    d = tmp_path / "loops"
    d.mkdir()
    (d / "a.xml").symlink_to(d / "b.xml")
    (d / "b.xml").symlink_to(d / "a.xml")
    add = d / "det.add.xml"
    add.write_text('<additional><include href="a.xml"/>'
                   '<e1Detector id="d" lane="x_0" pos="1" freq="60" file="b.xml"/></additional>')  # fmt: skip
    options, _ = redirect_outputs(None, ("--additional-files", str(add)), tmp_path / "o")
    root = ET.parse(options[1]).getroot()
    assert root.find("e1Detector").get("file") == str(tmp_path / "o" / "b.xml")
    assert root.find("include").get("href") == str(d / "a.xml")


# name -> (sumocfg text, files beside it, words of the one-line error)
REFUSED = {
    "NaN end": (_cfg(NET_AND_TRIPS + '<time><end value="nan"/></time>'), {},
                "<end value='nan'> is not a finite time"),
    "infinite begin": (_cfg(NET_AND_TRIPS + '<time><begin value="inf"/></time>'), {},
                       "<begin value='inf'> is not a finite time"),
    "NaN clock": (_cfg(NET_AND_TRIPS + "<time><end>1:nan:00</end></time>"), {},
                  "is not a finite time"),
    "its window ends before the first departure": (  # every step was empty, exit 0
        _cfg('<input><net-file value="small.net.xml"/><route-files value="late.trips.xml"/>'
             '</input><time><begin value="0"/><end value="600"/></time>'),
        {"late.trips.xml": "LATE:small.trips.xml"},
        "its window (00:01:00 - 00:10:00) ends before the first departure (00:33:20)",
    ),
    "end before begin": (
        _cfg(NET_AND_TRIPS + '<time><begin value="600"/><end value="60"/></time>'), {},
        "is not after <begin",
    ),
    "a route file given as config": (_cfg('<vehicle id="v" depart="0"/>', "routes"), {},
                                     "a <routes> file that names no network, not a SUMO"),
    "a netconvert config": (_cfg('<input><osm-files value="a.osm"/></input>',
                                 "netconvertConfiguration"), {},
                            "a netconvert file that names no network, not a SUMO"),
    "no network": (_cfg('<input><route-files value="small.trips.xml"/></input>'), {},
                   "names no network; add <net-file value=...>"),
    "a network as route file": (
        _cfg('<input><net-file value="small.net.xml"/><route-files value="small.net.xml"/>'
             "</input>"),
        {}, "not a route file but a SUMO network; pass it as --net",
    ),
    "a sumocfg as additional": (
        _cfg(NET_AND_TRIPS + '<input><additional-files value="x.sumocfg"/></input>'),
        {"x.sumocfg": _cfg(NET_AND_TRIPS)}, "not an additional file but a SUMO config",
    ),
    "a save-configuration": (
        _cfg(NET_AND_TRIPS + '<configuration><save-configuration value="../saved.sumocfg"/>'
             "</configuration>"),
        {}, "<save-configuration value='../saved.sumocfg'> makes SUMO write that file and quit",
    ),
    "a save-template": (
        _cfg(NET_AND_TRIPS + "<configuration><save-template>t.xml</save-template></configuration>"),
        {}, "<save-template value='t.xml'> makes SUMO write that file and quit",
    ),
    "a remote port": (_cfg(NET_AND_TRIPS + '<remote-port value="8813"/>'), {},
                      "<remote-port value='8813'> makes SUMO wait for a TraCI client"),
    "a help switch": (_cfg(NET_AND_TRIPS + '<report><help value="true"/></report>'), {},
                      "<help value='true'> makes SUMO print its help and quit"),
    "a help switch in SUMO's short word": (_cfg(NET_AND_TRIPS + '<help value="T"/>'), {},
                                           "<help value='T'> makes SUMO print its help"),
    "an option set twice": (
        _cfg(NET_AND_TRIPS + '<input><route-files value="small.trips.xml"/></input>'), {},
        "<route-files> and <route-files> both set option route-files ('small.trips.xml', "
        "'small.trips.xml'), which SUMO refuses ('probably defined twice'); keep one",
    ),
    "a mesosim that is no boolean": (_cfg(NET_AND_TRIPS + '<mesosim value="maybe"/>'), {},
                                     "<mesosim value='maybe'> is no boolean SUMO reads"),
    "a boolean with a space, which SUMO does not strip": (
        _cfg(NET_AND_TRIPS + '<mesosim value=" true"/>'), {},
        "<mesosim value=' true'> is no boolean SUMO reads",
    ),
    "a version switch that is no boolean": (_cfg(NET_AND_TRIPS + '<version value="no!"/>'), {},
                                            "<version value='no!'> is no boolean SUMO reads"),
    "a begin past every departure": (  # SUMO drops them all: it ran empty (probe 27c's h04)
        _cfg(NET_AND_TRIPS + '<time><begin value="7200"/></time>'), {},
        "every departure of its demand falls before its <begin> 02:00:00",
    ),
    "a help topic": (_cfg(NET_AND_TRIPS + '<help value="input"/>'), {},
                     "<help value='input'> makes SUMO print its help and quit"),
    "a departure with a space after it": (
        _cfg('<input><net-file value="small.net.xml"/><route-files value="s.rou.xml"/></input>'),
        {"s.rou.xml": '<routes><trip id="t" depart="0:00:10 " from="a" to="b"/></routes>'},
        "<trip id='t' depart='0:00:10 '>: the time is not a time SUMO reads",
    ),
    "an option's value and text both": (
        _cfg('<input><net-file value="small.net.xml">small.net.xml</net-file><route-files '
             'value="small.trips.xml"/></input>'), {},
        "<net-file> sets option net-file twice ('small.net.xml', 'small.net.xml'), which SUMO "
        "refuses",
    ),
    "a value made empty by an unset variable": (
        _cfg('<input><net-file value="${TWIN_TEST_NEVER_SET}"/><route-files '
             'value="small.trips.xml"/></input>'), {},
        "<net-file value='${TWIN_TEST_NEVER_SET}'> is empty (${TWIN_TEST_NEVER_SET} unset or "
        "empty), which SUMO refuses; set it",
    ),
    "an end that SUMO's number reader refuses": (
        _cfg(NET_AND_TRIPS + '<time><end value="2_400"/></time>'), {},
        "<end value='2_400'> is not a finite time",
    ),
    "an end with a space after it": (_cfg(NET_AND_TRIPS + '<time><end value="2400 "/></time>'),
                                     {}, "<end value='2400 '> is not a finite time"),
    "an end in full-width digits": (  # SUMO: "Cannot parse option 'end'"; Python reads them
        _cfg(NET_AND_TRIPS + '<time><end value="２４００"/></time>'), {},
        "<end value='２４００'> is not a finite time",
    ),
    "a departure in full-width digits": (
        _cfg('<input><net-file value="small.net.xml"/><route-files value="w.rou.xml"/></input>'),
        {"w.rou.xml": '<routes><trip id="t" depart="１０" from="a" to="b"/></routes>'},
        "<trip id='t' depart='１０'>: the time is not a time SUMO reads",
    ),
    "an option's value and its short form both": (
        _cfg('<input><net-file value="small.net.xml" v="small.net.xml"/><route-files '
             'value="small.trips.xml"/></input>'), {},
        "<net-file> sets option net-file twice",
    ),
    "not XML": ("<configuration><input>", {}, "not valid XML"),
    "a negative begin": (_cfg(NET_AND_TRIPS + '<time><begin value="-60"/></time>'), {},
                         "<begin value='-60'> is negative, which SUMO refuses"),
    "a NaN departure": (
        _cfg('<input><net-file value="small.net.xml"/><route-files value="n.rou.xml"/></input>'),
        {"n.rou.xml": '<routes><trip id="t" depart="nan" from="a" to="b"/></routes>'},
        "n.rou.xml (named in {case}/case.sumocfg): <trip id='t' depart='nan'>: the time is not a time SUMO reads",
    ),
    "an infinite departure": (
        _cfg('<input><net-file value="small.net.xml"/><route-files value="i.rou.xml"/></input>'),
        {"i.rou.xml": '<routes><vehicle id="v" depart="inf" route="r"/></routes>'},
        "i.rou.xml (named in {case}/case.sumocfg): <vehicle id='v' depart='inf'>: the time is not a time SUMO reads",
    ),
    "a flow beginning before 0": (
        _cfg('<input><net-file value="small.net.xml"/><route-files value="f.rou.xml"/></input>'),
        {"f.rou.xml": '<routes><flow id="f" begin="-50" end="60" period="5" from="a" to="b"/>'
                      "</routes>"},
        "f.rou.xml (named in {case}/case.sumocfg): <flow id='f' begin='-50'>: the time is negative",
    ),
    "the network twice": (
        _cfg('<input><net-file value="small.net.xml,small.net.xml"/>'
             '<route-files value="small.trips.xml"/></input>'),
        {}, "names a network twice, which SUMO refuses",
    ),
    "two networks": (
        _cfg('<input><net-file value="small.net.xml, b.net.xml"/>'
             '<route-files value="small.trips.xml"/></input>'),
        {"b.net.xml": "<net/>"}, "names 2 networks; twin lays its grid over one: merge them",
    ),
    "a missing route file": (
        _cfg('<input><net-file value="small.net.xml"/><route-files value="no.rou.xml"/></input>'),
        {}, "{case}/no.rou.xml (named in {case}/case.sumocfg): no such route file",
    ),
    "a route file not XML": (
        _cfg('<input><net-file value="small.net.xml"/><route-files value="x.rou.xml"/></input>'),
        {"x.rou.xml": "<routes><trip"},
        "{case}/x.rou.xml (named in {case}/case.sumocfg): not valid XML",
    ),
    "a route file as network": (
        _cfg('<input><net-file value="small.trips.xml"/></input>'), {},
        "{case}/small.trips.xml (named in {case}/case.sumocfg): not a SUMO network",
    ),
    "a link loop as route file": (
        _cfg('<input><net-file value="small.net.xml"/><route-files value="a.rou.xml"/></input>'),
        {"a.rou.xml": "LINK:b.rou.xml", "b.rou.xml": "LINK:a.rou.xml"},
        "a.rou.xml (named in {case}/case.sumocfg): a symbolic link loop",
    ),
    "a link loop as network": (
        _cfg('<input><net-file value="a.net.xml"/><route-files value="small.trips.xml"/></input>'),
        {"a.net.xml": "LINK:b.net.xml", "b.net.xml": "LINK:a.net.xml"},
        "a.net.xml (named in {case}/case.sumocfg): a symbolic link loop",
    ),
    "a link loop as additional": (
        _cfg(NET_AND_TRIPS + '<input><additional-files value="a.add.xml"/></input>'),
        {"a.add.xml": "LINK:b.add.xml", "b.add.xml": "LINK:a.add.xml"},
        "a.add.xml (named in {case}/case.sumocfg): a symbolic link loop",
    ),
    "a compressed sumocfg": ("GZ:" + _cfg(NET_AND_TRIPS), {},
                             "a gzip-compressed config, which SUMO does not read; decompress"),
}  # fmt: skip


@pytest.mark.parametrize("case", list(REFUSED))
def test_refused_sumocfg(scenario, tmp_path, capsys, case):
    text, files, needle = REFUSED[case]
    cfg = _write_case(scenario, tmp_path / "case", text, files)
    before = tree_hash(tmp_path)
    out = tmp_path / "run"
    code = _run(scenario, out, "--sumocfg", str(cfg))
    captured = capsys.readouterr()
    err = captured.err.strip()
    assert code == 2, err
    assert "\n" not in err and err.startswith("twin: error:"), err
    assert needle.replace("{case}", str(tmp_path / "case")) in err, err
    assert "Traceback" not in err + captured.out
    assert not out.exists()
    assert tree_hash(tmp_path) == before
    if case.startswith(("NaN", "infinite")):
        with pytest.raises(UserError, match="finite time"):
            read_sumocfg(cfg)


# name -> (flags of `twin run`, words of the one-line error); {cfg}: the scenario's sumocfg,
# {net}: its network, {tmp}: a folder holding two loops of symbolic links, loop.xml and
# loop.sumocfg, and early.rou.xml, a trip departing at -5 s
PUBLIC = ["--sumocfg", "{cfg}"]
REFUSED_FLAGS = {
    "more drones than free cells": ([*PUBLIC, "--drones", "1000"], "--drones 1000 exceeds the"),
    "drones past any disk": ([*PUBLIC, "--drones", "99999999999"], "--drones 99999999999 exceeds"),
    "a cell size too large": ([*PUBLIC, "--cell-m", "1e9"], "--cell-m 1e+09: cell size"),
    "a cell size too small": ([*PUBLIC, "--cell-m", "0.5"], "--cell-m 0.5: cell size"),
    "a negative drone speed": ([*PUBLIC, "--drone-speed", "-3"], "--drone-speed = -3.0 must be > 0"),
    "a step shorter than SUMO's": ([*PUBLIC, "--drone-speed", "1e9"],
                                   "--drone-speed 1e+09: a step (200 m at 1e+09 km/h) lasts"),
    "a begin that is no clock": ([*PUBLIC, "--begin", "x"], "--begin = 'x' must be a clock"),
    "a negative departure": (["--net", "{net}", "--routes", "{tmp}/early.rou.xml"],
                             "{tmp}/early.rou.xml: <trip id='t' depart='-5'>: the time is"),
    "a link loop as sumocfg": (["--sumocfg", "{tmp}/loop.sumocfg"],
                               "{tmp}/loop.sumocfg: a symbolic link loop"),
    "a link loop as net": (["--net", "{tmp}/loop.xml"], "{tmp}/loop.xml: a symbolic link loop"),
    "a link loop as routes": (["--net", "{net}", "--routes", "{tmp}/loop.xml"],
                              "{tmp}/loop.xml: a symbolic link loop"),
    "a link loop as additional": ([*PUBLIC, "--additional", "{tmp}/loop.xml"],
                                  "{tmp}/loop.xml: a symbolic link loop"),
}  # fmt: skip


@pytest.mark.parametrize("case", list(REFUSED_FLAGS))
def test_refused_flags_name_the_flag_or_file(scenario, tmp_path, capsys, case):
    flags, needle = REFUSED_FLAGS[case]
    for loop in ("loop.xml", "loop.sumocfg"):
        (tmp_path / f"other-{loop}").symlink_to(tmp_path / loop)
        (tmp_path / loop).symlink_to(tmp_path / f"other-{loop}")
    (tmp_path / "early.rou.xml").write_text(
        '<routes><trip id="t" depart="-5" from="a" to="b"/></routes>'
    )
    names = {"cfg": scenario / "scenario" / "public.sumocfg", "tmp": tmp_path,
             "net": scenario / "scenario" / "small.net.xml"}  # fmt: skip
    out = tmp_path / "run"
    code = _run(scenario, out, *(f.format(**names) for f in flags))
    captured = capsys.readouterr()
    err = captured.err.strip()
    assert code == 2, err
    assert "\n" not in err and err.startswith("twin: error:"), err
    assert needle.format(**names) in err and "config.toml" not in err, err
    assert "Traceback" not in err + captured.out
    assert not out.exists()


def test_a_run_wholly_after_the_demand_is_refused(scenario, tmp_path, capsys):
    """A begin a day after the demand: every step would be empty, so the run is refused in one
    line (a run partly past the demand gets a notice instead, test_sumo_inputs)."""
    d = scenario / "scenario"
    code = _run(scenario, tmp_path / "run", "--net", str(d / "small.net.xml"), "--routes",
                str(d / "small.trips.xml"), "--begin", "25:00", "--horizon", "3",
                "--swarms", "random", "--no-ceiling")  # fmt: skip
    err = capsys.readouterr().err
    assert code == 2 and err.count("\n") == 1, err
    assert "lies outside the demand" in err and "every step would be empty" in err
    assert not (tmp_path / "run").exists()


# name -> (flags of `twin run`, words of the one-line error). Each run is given a horizon past
# its demand, so a notice (and the SUMO announcement) would come before the simulation starts:
# they are held back until it has, and a refusal prints its one error line only. {tmp}: a
# folder with bad.rou.xml (a trip from an unknown edge), bogus.sumocfg (an option SUMO does not
# know), copy.trips.xml (the scenario's trips again: duplicate vehicle ids)
HELD_BACK = {
    "a route over an unknown edge": (["--net", "{net}", "--routes", "{tmp}/bad.rou.xml"],
                                     "bad.rou.xml: SUMO refuses it: "),
    "an option SUMO does not know": (["--sumocfg", "{tmp}/bogus.sumocfg"],
                                     "bogus.sumocfg: SUMO refuses it: No option with the name"),
    "duplicate vehicle ids": (["--net", "{net}", "--routes", "{trips}", "--routes",
                               "{tmp}/copy.trips.xml"], "already exists"),
    "an additional file twice": ([*PUBLIC, "--additional", "{detectors}"], "SUMO refuses it"),
    "more drones than free cells": (["--net", "{net}", "--routes", "{trips}", "--drones",
                                     "100000"], "--drones 100000 exceeds the"),
}  # fmt: skip


def _held_back_names(scenario: Path, tmp_path: Path) -> dict[str, Path]:
    d = scenario / "scenario"
    (tmp_path / "bad.rou.xml").write_text(
        '<routes><trip id="x" depart="0" from="nosuchedge" to="nosuchedge"/></routes>'
    )
    (tmp_path / "bogus.sumocfg").write_text(
        f'<configuration><input><net-file value="{d / "small.net.xml"}"/><route-files '
        f'value="{d / "small.trips.xml"}"/></input><bogus-option value="1"/></configuration>'
    )
    shutil.copy(d / "small.trips.xml", tmp_path / "copy.trips.xml")
    return {"cfg": d / "public.sumocfg", "tmp": tmp_path, "net": d / "small.net.xml",
            "trips": d / "small.trips.xml", "detectors": d / "detectors.add.xml"}  # fmt: skip


@pytest.mark.parametrize("case", list(HELD_BACK))
def test_a_refusal_after_notices_is_one_line(scenario, tmp_path, capsys, case):
    flags, needle = HELD_BACK[case]
    names = _held_back_names(scenario, tmp_path)
    out = tmp_path / "run"
    code = _run(scenario, out, "--horizon", "200", *(f.format(**names) for f in flags))
    captured = capsys.readouterr()
    err = captured.err.strip()
    assert code == 2, err
    assert "\n" not in err and err.startswith("twin: error:"), err
    assert needle in err and "Traceback" not in err + captured.out, err
    assert not out.exists()


def test_notices_come_before_the_results_of_a_run_that_starts(scenario, tmp_path, capsys):
    names = _held_back_names(scenario, tmp_path)
    out = tmp_path / "run"
    code = _run(scenario, out, "--horizon", "200", "--net", str(names["net"]), "--routes",
                str(names["trips"]))  # fmt: skip
    err = capsys.readouterr().err.splitlines()
    assert code == 0, err
    notices = [x for x in err if x.startswith("twin: notice:")]
    assert any("past the last departure" in x for x in notices), err
    assert err[: len(notices) + 1] == [*notices, err[len(notices)]], err  # notices first
    assert err[len(notices)].startswith("SUMO: small.net.xml (seed "), err


def test_included_files_are_found_through_nested_includes_and_cycles(tmp_path):
    """The files an additional file includes (and theirs) are part of the run's identity."""
    from twin.sumo.readers import included_files

    (tmp_path / "sub").mkdir()
    (tmp_path / "a.add.xml").write_text('<additional><include href="sub/b.add.xml"/></additional>')
    (tmp_path / "sub" / "b.add.xml").write_text(
        '<additional><include href="../a.add.xml"/><include href="c.add.xml"/></additional>'
    )
    (tmp_path / "sub" / "c.add.xml").write_text("<additional/>")
    found = included_files(tmp_path / "a.add.xml")
    assert [p.name for p in found] == ["b.add.xml", "c.add.xml"]


def test_an_include_cycle_through_a_linked_folder_is_one(tmp_path):
    """``L/c`` a link to ``real/cfg``, whose ``a.xml`` includes ``../cfg/a.xml``: read as SUMO
    reads it (``..`` in the link's target), the names grew round the cycle, which went unseen
    and gave hundreds of "included files" (the review of probe 27's fixes)."""
    from twin.sumo.readers import include_cycle, included_files

    (tmp_path / "real" / "cfg").mkdir(parents=True)
    (tmp_path / "L").mkdir()
    (tmp_path / "real" / "cfg" / "a.xml").write_text(
        '<additional><include href="../cfg/a.xml"/></additional>'
    )
    (tmp_path / "L" / "c").symlink_to(tmp_path / "real" / "cfg")
    start = tmp_path / "L" / "c" / "a.xml"
    assert len(included_files(start)) <= 1
    cycle = include_cycle(start)
    assert cycle is not None and len(cycle) == 2


def test_a_run_in_the_scenarios_own_window_past_its_departures_gets_a_notice(
    scenario, tmp_path, capsys
):
    """A sumocfg whose own window runs long past its departures (a looping scenario's rerouters
    keep its vehicles on the road): the run, begun in that window after the warm-up, is not
    refused as empty (twin cannot tell); a notice says it starts past the last departure."""
    d = scenario / "scenario"
    cfg = tmp_path / "loop.sumocfg"
    cfg.write_text(
        f'<configuration><input><net-file value="{d / "small.net.xml"}"/><route-files '
        f'value="{d / "small.trips.xml"}"/></input><time><begin value="0"/><end '
        'value="100000"/></time></configuration>'
    )
    config = tmp_path / "late.toml"  # a warm-up past the 10 min of departures and their clearing
    config.write_text(CONFIG.replace("warmup_min = 1.0", "warmup_min = 40.0"))
    code = main(["run", "--config", str(config), "--sumocfg", str(cfg), "--horizon", "2",
                 "--swarms", "random", "--no-ceiling", "--quiet", "--no-report", "--out",
                 str(tmp_path / "run")])  # fmt: skip
    err = capsys.readouterr().err
    assert code == 0, err
    assert "begins past the last departure" in err, err
    code = main(["run", "--config", str(config), "--sumocfg", str(cfg), "--horizon", "2",
                 "--begin", "05:00", "--swarms", "random", "--no-ceiling", "--quiet",
                 "--no-report", "--out", str(tmp_path / "run-begun")])  # fmt: skip
    err = capsys.readouterr().err
    assert code == 0 and "begins past the last departure" in err, err  # a begin in its window


def test_a_begin_past_the_sumocfgs_end_gets_a_notice(scenario, tmp_path, capsys):
    """A --begin at or past the sumocfg's <end>, where SUMO alone would stop: twin runs its own
    window and says so (before, silently)."""
    d = scenario / "scenario"
    cfg = tmp_path / "short.sumocfg"
    cfg.write_text(
        f'<configuration><input><net-file value="{d / "small.net.xml"}"/><route-files '
        f'value="{d / "small.trips.xml"}"/></input><time><begin value="0"/><end '
        'value="300"/></time></configuration>'
    )
    config = tmp_path / "twin.toml"
    config.write_text(CONFIG)
    argv = ["run", "--config", str(config), "--sumocfg", str(cfg), "--horizon",
            "2", "--swarms", "random", "--no-ceiling", "--quiet", "--no-report"]  # fmt: skip
    code = main([*argv, "--begin", "00:06", "--out", str(tmp_path / "late")])
    err = capsys.readouterr().err
    assert code == 0, err
    assert "past the scenario's end (00:05:00)" in err, err
    code = main([*argv, "--begin", "00:02", "--out", str(tmp_path / "within")])
    err = capsys.readouterr().err
    assert code == 0 and "past the scenario's end" not in err, err


def test_a_min_lane_km_above_every_cell_names_the_key_not_the_network(scenario, tmp_path, capsys):
    """[traffic].min_lane_km above every cell's lane-km: one line naming the key and the most
    lane a cell has (it said the network had no lane; probe 17's f09)."""
    d = scenario / "scenario"
    config = tmp_path / "c.toml"
    config.write_text(
        CONFIG.replace("warmup_min = 1.0", f'warmup_min = 1.0\nmin_lane_km = 1e6\nnet = '
                       f'"{d / "small.net.xml"}"\nroutes = ["{d / "small.trips.xml"}"]')
    )  # fmt: skip
    code = main(["run", "--config", str(config), "--horizon", "2", "--swarms", "random",
                 "--no-ceiling", "--quiet", "--no-report", "--out", str(tmp_path / "o")])  # fmt: skip
    err = capsys.readouterr().err
    assert code == 2 and err.count("\n") == 1, err
    assert "[traffic].min_lane_km = 1e+06 leaves no cell of the" in err, err
    assert "give a min_lane_km below" in err and "has a lane" not in err, err


@pytest.fixture(scope="module")
def saved_state(scenario, tmp_path_factory) -> Path:
    """``state/``: the scenario's network and trips, a state SUMO saved at 300 s (with SUMO's
    default options) and a sumocfg that loads it."""
    import subprocess

    d = tmp_path_factory.mktemp("state")
    for name in ("small.net.xml", "small.trips.xml"):
        shutil.copy(scenario / "scenario" / name, d / name)
    cfg = _cfg('<input><net-file value="small.net.xml"/><route-files value="small.trips.xml"/>'
               "</input>")  # fmt: skip
    (d / "plain.sumocfg").write_text(cfg)
    subprocess.run([binary("sumo"), "-c", str(d / "plain.sumocfg"), "--end", "700",
                    "--save-state.times", "300,650", "--save-state.files",
                    f"{d / 'st300.xml'},{d / 'st650.xml'}", "--no-step-log", "true"],
                   check=True, capture_output=True)  # fmt: skip
    (d / "state.sumocfg").write_text(
        cfg.replace("</input>", '<load-state value="st300.xml"/></input>')
    )
    return d


def test_a_sumocfg_loading_a_saved_state_runs_from_the_state_s_time(
    scenario, saved_state, tmp_path, capsys
):
    """``<load-state>``: SUMO's clock starts at the state's time whatever the begin, so the
    scenario's window does too; every snapshot is read after it, none is the state frozen
    and relabelled as earlier steps (probe 12's a04). twin's rerouting defaults leave the
    state's own speeds alone (another count crashed libsumo)."""
    before = tree_hash(saved_state)
    out = tmp_path / "run"
    code = _run(scenario, out, "--sumocfg", str(saved_state / "state.sumocfg"))
    err = capsys.readouterr().err
    assert code == 0, err
    assert tree_hash(saved_state) == before
    tape = pd.read_parquet(out / "tape.parquet")
    times = tape.groupby("step")["time_s"].first()
    assert times.min() > 300 and times.is_monotonic_increasing
    assert tape.groupby("step")["count"].sum().nunique() > 1  # the traffic moves


def test_a_begin_after_a_saved_state_cuts_the_warm_up_to_it(
    scenario, saved_state, tmp_path, capsys
):
    """``--begin`` 30 s after the state's time with a 1 min warm-up: the warm-up runs from the
    state on (cut to 0.5 min, with a notice), as it is at midnight; a state saved past the last
    departure runs its one step (its window ended before it began: probe 12's P2-ls)."""
    out = tmp_path / "run"
    code = _run(scenario, out, "--sumocfg", str(saved_state / "state.sumocfg"), "--begin",
                "00:05:30", "--horizon", "2")  # fmt: skip
    err = capsys.readouterr().err
    assert code == 0, err
    assert "loads a state saved at 00:05:00, where SUMO starts; warm-up cut to 0.5 min" in err
    late = tmp_path / "late.sumocfg"
    late.write_text((saved_state / "state.sumocfg").read_text().replace("st300", "st650"))
    shutil.copy(saved_state / "st650.xml", tmp_path)
    for name in ("small.net.xml", "small.trips.xml"):
        shutil.copy(saved_state / name, tmp_path)
    code = _run(scenario, tmp_path / "late", "--sumocfg", str(late))
    err = capsys.readouterr().err
    assert code == 0, err
    assert "window 00:10:50 - 00:11:50" in err, err  # not 00:10:50 - 00:09:58


def _binary_state(d: Path) -> list[str]:
    (d / "st300.xml").rename(d / "st300.sbx")
    cfg = d / "state.sumocfg"
    cfg.write_text(cfg.read_text().replace("st300.xml", "st300.sbx"))
    return []


def _not_a_state(d: Path) -> list[str]:
    (d / "st300.xml").write_text("<routes/>")
    return []


@pytest.mark.parametrize(
    ("change", "words"),
    [
        (lambda d: ["--begin", "00:04:00"], "loads a state saved at 00:05:00, where SUMO starts"),
        (_binary_state, "a binary saved state, whose time twin cannot read"),
        (_not_a_state, "not a state SUMO saved"),
    ],
    ids=["begin before the state", "binary state", "not a state"],
)
def test_a_saved_state_twin_cannot_honour_is_one_line(
    scenario, saved_state, tmp_path, capsys, change, words
):
    d = tmp_path / "state"
    shutil.copytree(saved_state, d)
    code = _run(scenario, tmp_path / "run", "--sumocfg", str(d / "state.sumocfg"), *change(d))
    err = capsys.readouterr().err
    assert code == 2 and err.count("\n") == 1 and words in err, err


def test_sumo_s_own_demo_runs_with_its_messages_kept_out_of_twin_s_lines(
    scenario, tmp_path, capfd, monkeypatch
):
    """SUMO's demo fokr_bs_demo (shipped in the eclipse-sumo wheel: cars, bicycles,
    pedestrians, 0.05 s steps) run with its sumocfg alone: SUMO's errors while it runs (at
    twin's 1 s steps some vehicles cannot depart) go to RUN/sumo/sumo-messages.log with one
    notice, never as raw lines among twin's (probe 12's g01); its folder stays as it was."""
    import sumo

    demo = Path(sumo.__file__).parent / "tools" / "game"
    d = tmp_path / "demo"
    d.mkdir()
    shutil.copytree(demo / "fokr_bs_demo", d / "fokr_bs_demo")
    shutil.copy(demo / "fokr_bs_demo.sumocfg", d)
    before = tree_hash(d)
    (tmp_path / "cwd").mkdir()
    monkeypatch.chdir(tmp_path / "cwd")
    out = tmp_path / "run"
    code = main(["run", "--sumocfg", str(d / "fokr_bs_demo.sumocfg"), "--cell-m", "100",
                 "--horizon", "2", "--swarms", "random", "--quiet", "--no-report",
                 "--no-ceiling", "--out", str(out)])  # fmt: skip
    err = capfd.readouterr().err
    assert code == 0, err
    assert not [line for line in err.splitlines() if not line.startswith(("twin:", "SUMO:"))]
    log = out / "sumo" / "sumo-messages.log"
    assert "SUMO reported" in err and str(log) in err
    assert "will not be able to depart" in log.read_text()
    assert tree_hash(d) == before and list((tmp_path / "cwd").iterdir()) == []
    assert "sumo/sumo-messages.log" in check_run_folder(out)["files"]


def test_what_a_verbose_sumo_prints_goes_to_its_messages_not_twin_s_stdout(
    scenario, tmp_path, capfd
):
    """A sumocfg asking SUMO to be verbose and print its statistics: SUMO's lines go to
    RUN/sumo/sumo-messages.log, not among twin's on stdout (they leaked: probe 23's f01)."""
    cfg = _detector_case(scenario, tmp_path / "case")
    cfg.write_text(cfg.read_text().replace("</configuration>", '<report><verbose value="true"/>'
                   '<duration-log.statistics value="true"/></report></configuration>'))  # fmt: skip
    out = tmp_path / "run"
    code = _run(scenario, out, "--sumocfg", str(cfg))
    captured = capfd.readouterr()
    assert code == 0, captured.err
    assert "Loading net-file" not in captured.out + captured.err, captured.out
    assert "Statistics" not in captured.out + captured.err
    said = (out / "sumo" / "sumo-messages.log").read_text()
    assert "Loading net-file" in said and "Statistics" in said


def test_a_run_with_its_stdout_closed_completes(tmp_path):
    """``twin run ... >&-``: Python's stdout is None then; the SUMO child's start flushed it
    and failed, a partial run of no step (the review of probe 23's f01 fix)."""
    import os
    import sys

    from helpers import small_sumo_scenario

    folder = small_sumo_scenario(tmp_path, horizon=3)
    out = tmp_path / "run"
    argv = [sys.executable, "-m", "twin", "run", "--config", str(folder / "small.toml"),
            "--swarms", "random", "--no-ceiling", "--no-report", "--quiet", "--out", str(out)]  # fmt: skip
    done = subprocess.run(argv, preexec_fn=lambda: os.close(1), stderr=subprocess.PIPE,
                          text=True, check=False, timeout=300)  # fmt: skip
    assert done.returncode == 0, done.stderr
    assert (out / "manifest.json").is_file()


def test_a_refusal_after_a_warning_quotes_the_error(scenario, tmp_path, capsys):
    """SUMO warns (a deprecated vehicle shape), then refuses to start (a vehicle type defined
    twice: the additional file again by --routes), its error in libsumo's exception: the line
    quotes the error, not the warning
    (SUMO's own process writes its warnings now: probe 24's f05)."""
    cfg = _detector_case(scenario, tmp_path / "case")
    add = cfg.parent / "det.add.xml"
    add.write_text(add.read_text().replace(
        "<additional>", '<additional><vType id="LKW" guiShape="transport"/><vType id="PKW"/>'))  # fmt: skip
    code = _run(scenario, tmp_path / "run", "--sumocfg", str(cfg), "--routes", str(add))
    err = capsys.readouterr().err.strip()
    assert code == 2 and "\n" not in err, err
    assert "Another vehicle type (or distribution) with the id 'LKW' exists" in err, err
    assert "deprecated" not in err


def test_demand_sumo_ignores_with_a_warning_is_told(scenario, tmp_path, capfd):
    """A route file SUMO loads only in part (a flow after a later person: "Route file should
    be sorted by departure time, ignoring 'f1'!"): a notice quotes SUMO's warning and names
    RUN/sumo/sumo-messages.log, which keeps it (twin ran SUMO without warnings, so the flow
    was dropped without a word: probe 23's f03)."""
    cfg = _detector_case(scenario, tmp_path / "case")
    with open(cfg.parent / "small.trips.xml", "rb") as fh:
        trip = ET.parse(fh).getroot().find("trip")
    edge, to = trip.get("from"), trip.get("to")
    flows = "".join(f'<flow id="f{n}" from="{edge}" to="{to}" begin="100" end="500" '
                    'period="10"/>' for n in range(1, 26))  # fmt: skip
    (cfg.parent / "late.rou.xml").write_text(
        f'<routes><person id="p0" depart="300"><walk from="{edge}" to="{to}"/></person>'
        f"{flows}</routes>"
    )
    cfg.write_text(cfg.read_text().replace('value="small.trips.xml"',
                                           'value="small.trips.xml,late.rou.xml"'))  # fmt: skip
    out = tmp_path / "run"
    code = _run(scenario, out, "--sumocfg", str(cfg))
    err = capfd.readouterr().err
    assert code == 0, err
    log = out / "sumo" / "sumo-messages.log"
    notice = [line for line in err.splitlines() if "SUMO warned that it ignored something" in line]
    assert len(notice) == 1 and "ignoring 'f1'" in notice[0] and str(log) in notice[0], err
    assert "(25 warnings;" in notice[0], notice  # past 20, SUMO counts them: all counted
    assert "ignoring 'f1'" in log.read_text()


def _one_edge_net(d: Path, length_m: float) -> Path:
    """A network of one two-lane edge of ``length_m``, built by netconvert from plain XML."""
    (d / "one.nod.xml").write_text(
        f'<nodes><node id="a" x="0" y="0"/><node id="b" x="{length_m:g}" y="0"/></nodes>'
    )
    (d / "one.edg.xml").write_text(
        '<edges><edge id="e" from="a" to="b" numLanes="2" speed="13.9"/></edges>'
    )
    subprocess.run([binary("netconvert"), "-n", str(d / "one.nod.xml"), "-e",
                    str(d / "one.edg.xml"), "-o", str(d / "one.net.xml")], check=True,
                   capture_output=True)  # fmt: skip
    return d / "one.net.xml"


def test_a_network_randomtrips_cannot_use_is_one_line_with_a_fix(tmp_path, capsys):
    """One 3 m edge: randomTrips finds no edge for its trips; the line says twin cannot
    generate demand there and to give routes (randomTrips' words alone named no fix: probe
    23's P2-f01)."""
    net = _one_edge_net(tmp_path, 3.0)
    code = main(["run", "--net", str(net), "--cell-m", "200", "--drones", "1", "--swarms",
                 "random", "--horizon", "4", "--no-ceiling", "--no-report", "--quiet",
                 "--out", str(tmp_path / "run")])  # fmt: skip
    err = capsys.readouterr().err.strip()
    assert code == 2 and "\n" not in err, err
    assert err.startswith("twin: error: randomTrips.py on") and "one.net.xml" in err, err
    assert err.endswith("give your own (--routes, or a sumocfg's routes)"), err


def test_a_network_whose_generated_trips_all_fail_to_route_is_one_line(tmp_path, capsys):
    """Two 3 x 3 grids of 200 m blocks, 3 km apart: randomTrips' trips of 500 m or more all go
    from one to the other, and its --validate drops every one; the run had no demand and only
    said its importance was 0 (probe 26's f01)."""
    nodes, edges = [], []
    for part, x0 in (("L", 0), ("R", 3000)):
        for a in range(3):
            for b in range(3):
                nodes.append(f'<node id="{part}{a}{b}" x="{x0 + 200 * a}" y="{200 * b}"/>')
                for da, db, tag in ((1, 0, "x"), (0, 1, "y")):
                    if a + da < 3 and b + db < 3:
                        there = f"{part}{a + da}{b + db}"
                        edges.append(f'<edge id="{part}{a}{b}{tag}" from="{part}{a}{b}" '
                                     f'to="{there}" numLanes="1" speed="13"/>')  # fmt: skip
                        edges.append(f'<edge id="{part}{a}{b}{tag}r" from="{there}" '
                                     f'to="{part}{a}{b}" numLanes="1" speed="13"/>')  # fmt: skip
    (tmp_path / "two.nod.xml").write_text("<nodes>" + "".join(nodes) + "</nodes>")
    (tmp_path / "two.edg.xml").write_text("<edges>" + "".join(edges) + "</edges>")
    net = tmp_path / "two.net.xml"
    subprocess.run([binary("netconvert"), "-n", str(tmp_path / "two.nod.xml"), "-e",
                    str(tmp_path / "two.edg.xml"), "-o", str(net)], check=True,
                   capture_output=True)  # fmt: skip
    code = main(["run", "--net", str(net), "--cell-m", "100", "--drones", "1", "--swarms",
                 "random", "--horizon", "4", "--no-ceiling", "--no-report", "--quiet",
                 "--out", str(tmp_path / "run")])  # fmt: skip
    err = capsys.readouterr().err.strip()
    assert code == 2 and "\n" not in err, err
    assert "two.net.xml: none of its trips (500 m or longer" in err, err
    assert err.endswith("give your own (--routes, or a sumocfg's routes)"), err
    assert not (tmp_path / "run").exists()


def test_demand_is_generated_on_a_network_of_fringe_edges_only(tmp_path, capsys):
    """A network whose only road enters and leaves it (one edge): randomTrips finds no inner
    edge and advised its own --allow-fringe, which twin's user cannot give; twin gives it,
    with a notice (probe 23's f04)."""
    net = _one_edge_net(tmp_path, 1000.0)
    code = main(["run", "--net", str(net), "--cell-m", "200", "--drones", "2", "--swarms",
                 "random", "--horizon", "4", "--no-ceiling", "--no-report", "--quiet",
                 "--out", str(tmp_path / "run")])  # fmt: skip
    err = capsys.readouterr().err
    assert code == 0, err
    assert "start and end on its fringe" in err and "one.net.xml" in err, err
    assert pd.read_parquet(tmp_path / "run" / "tape.parquet")["count"].sum() > 0


def test_a_command_that_keeps_no_sumo_outputs_says_so(scenario, tmp_path, capsys):
    """A simulation without a run folder (a sweep's cell, a transfer's, an env's) cannot keep
    the outputs the scenario's files ask SUMO for: one notice names them (they vanished
    silently: probe 11's sw20); nothing is written beside the scenario's files."""
    from twin.config import load_config
    from twin.sumo.scenario import sumo_source

    cfg = _detector_case(scenario, tmp_path / "case", '<tripinfo-output value="trips.out.xml"/>')
    before = tree_hash(tmp_path / "case")
    source = sumo_source(load_config(scenario / "config.toml"), sumocfg=cfg)
    maps = source.importance_maps()
    next(maps)
    maps.close()
    err = capsys.readouterr().err
    assert "(det.xml, trips.out.xml) are not kept by this command" in err, err
    assert tree_hash(tmp_path / "case") == before


@pytest.mark.parametrize(
    "window",
    ['<begin value="100.25"/>', '<begin value="0"/><end value="119"/>'],
    ids=["fractional begin", "odd window: half of it warms up"],
)
def test_a_window_off_whole_seconds_gives_a_folder_that_reads_back(
    scenario, tmp_path, capsys, window
):
    """A sumocfg's begin of 100.25 s, or a window of 119 s whose half warms up: T^0 falls on a
    whole second, so the tape's clock labels agree with its times and the run's own read-back
    accepts its folder (it refused it as a corrupt tape: probe 12's t01)."""
    cfg = _write_case(
        scenario, tmp_path / "case", _cfg(NET_AND_TRIPS + f"<time>{window}</time>"), {}
    )
    out = tmp_path / "run"
    assert _run(scenario, out, "--sumocfg", str(cfg), "--horizon", "1") == 0, (
        capsys.readouterr().err
    )
    assert main(["report", str(out), "--no-animation"]) == 0, capsys.readouterr().err
    times = pd.read_parquet(out / "tape.parquet")["time_s"]
    assert (times == times.round()).all()


def test_a_begin_whose_warm_up_would_start_before_midnight_cuts_it(scenario, tmp_path, capsys):
    """``--begin 00:00:30`` with a 1 min warm-up: cut to 30 s with a notice, as a window too
    short for the warm-up is (the same begin twin picks itself was refused)."""
    cfg = _write_case(scenario, tmp_path / "case", _cfg(NET_AND_TRIPS), {})
    out = tmp_path / "run"
    code = _run(scenario, out, "--sumocfg", str(cfg), "--begin", "00:00:30", "--horizon", "2")
    err = capsys.readouterr().err
    assert code == 0, err
    assert "would start SUMO before 00:00; warm-up cut to 0.5 min" in err
    assert json.loads((out / "run.json").read_text())["traffic"]["warmup_s"] == 30


def test_a_sumocfg_named_through_a_link_reads_its_files_beside_the_link(scenario, tmp_path, capsys):
    """As ``sumo -c other/public.sumocfg`` (a link to ``real/``): its relative names are read
    from ``other/``, the link's folder, not the target's (twin ran ``real/``'s files, exit 0),
    and without them there the run is refused, as SUMO refuses it."""
    real, other = tmp_path / "real", tmp_path / "other"
    shutil.copytree(scenario / "scenario", real)
    other.mkdir()
    (other / "public.sumocfg").symlink_to("../real/public.sumocfg")
    argv = ("--sumocfg", str(other / "public.sumocfg"), "--horizon", "2")
    assert _run(scenario, tmp_path / "refused", *argv) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and str(other / "small.net.xml") in err[0], err
    for name in ("small.net.xml", "small.trips.xml", "detectors.add.xml"):
        shutil.copy(real / name, other / name)
    (other / "out").mkdir()
    assert _run(scenario, tmp_path / "run", *argv) == 0, capsys.readouterr().err
    identity = json.loads((tmp_path / "run" / "run.json").read_text())["traffic"]["identity"]
    loaded = {Path(f["path"]).name: Path(f["path"]).parent for f in identity["files"]}
    assert loaded["small.trips.xml"] == other and loaded["small.net.xml"] == other
    assert loaded["public.sumocfg"] == other


def test_a_flow_without_begin_refused_at_twins_begin_says_so(tmp_path):
    """SUMO begins a flow without begin at its own begin, which twin sets before the window: a
    flow ending before it is refused by SUMO, and the line says where twin starts SUMO and the
    fix (probe 27c's h02)."""
    from twin.sumo.session import SumoSession

    routes = tmp_path / "r.rou.xml"
    routes.write_text('<routes><flow id="fnb" end="1200" period="60" from="a" to="b"/></routes>')
    session = SumoSession(net_file=tmp_path / "n.net.xml", route_files=[routes], begin=1500.0)
    said = str(session.refusal("Error: Flow 'fnb' ends before its begin time."))
    assert "\n" not in said and "twin starts SUMO at 00:25:00" in said, said
    assert "give the flow a begin, or a --begin" in said, said


def test_a_sumocfg_in_a_linked_folder_records_the_files_sumo_reads(scenario, tmp_path, capsys):
    """``L/c`` a link to ``real/cfg``, whose sumocfg names ``../net/...``: SUMO reads
    ``real/net/`` (the system resolves ``..`` in the link's target); run.json hashed
    ``L/net/``'s files, so a sweep kept a stale cell when the real route file changed (probe
    27's f07)."""
    from twin.files import file_sha256

    real, decoy = tmp_path / "real", tmp_path / "L"
    for folder in (real / "net", real / "cfg", decoy / "net"):
        folder.mkdir(parents=True)
    for name in ("small.net.xml", "small.trips.xml"):
        shutil.copy(scenario / "scenario" / name, real / "net" / name)
        shutil.copy(scenario / "scenario" / name, decoy / "net" / name)
    (decoy / "net" / "small.trips.xml").write_text(
        (real / "net" / "small.trips.xml").read_text().replace("<routes", "<!-- other -->\n<routes")
    )
    (real / "cfg" / "x.sumocfg").write_text(
        '<configuration><input><net-file value="../net/small.net.xml"/><route-files '
        'value="../net/small.trips.xml"/></input></configuration>'
    )
    (decoy / "c").symlink_to(real / "cfg")
    out = tmp_path / "run"
    assert _run(scenario, out, "--sumocfg", str(decoy / "c" / "x.sumocfg"), "--horizon", "2") == 0
    identity = json.loads((out / "run.json").read_text())["traffic"]["identity"]
    hashes = {f["role"]: f["sha256"] for f in identity["files"]}
    assert hashes["route file"] == file_sha256(real / "net" / "small.trips.xml")
    assert hashes["route file"] != file_sha256(decoy / "net" / "small.trips.xml")


@pytest.mark.parametrize(
    ("value", "kept"),
    [("Nul", True), ("nUL", True), ("Stdout", True), ("nul", False), ("NUL", False),
     ("/dev/null", False)],
)  # fmt: skip
def test_only_the_null_names_sumo_knows_are_not_outputs(tmp_path, value, kept):
    """SUMO takes ``nul`` and ``NUL`` (exactly) for no file: ``Nul`` is a file it writes, so
    twin sends it into the run folder (it was left beside the scenario; probe 15's f02)."""
    from twin.sumo.outputs import redirect_outputs

    cfg = tmp_path / "c.sumocfg"
    cfg.write_text(
        '<configuration><input><net-file value="n.net.xml"/></input><output>'
        f'<tripinfo-output value="{value}"/></output></configuration>'
    )
    options, _ = redirect_outputs(cfg, (), tmp_path / "o")
    if kept:
        assert list(options) == ["--tripinfo-output", str(tmp_path / "o" / value)]
    else:
        assert list(options) == []


def test_a_comma_in_a_scenario_path_is_one_line(tmp_path):
    """SUMO splits file names at commas and twin gives it full paths: a folder named
    ``my scen,v2`` is refused naming the comma (SUMO's error named a path the user never
    gave; probe 15's f17)."""
    from twin.sumo.session import SumoSession

    folder = tmp_path / "my scen,v2"
    session = SumoSession(net_file=folder / "a.net.xml", route_files=[], begin=0.0, end=10.0)
    with pytest.raises(UserError, match=r"my scen,v2/a\.net\.xml: SUMO splits file names at "
                                        r"commas.*rename the folder or file"):  # fmt: skip
        session.command()


def test_twins_loops_file_is_named_apart_from_a_scenario_output(tmp_path):
    """A scenario output named ``twin-loops.add.xml``: twin's virtual loops take another name
    (SUMO truncated twin's file to write the output, then read it back as an additional
    file; probe 15's f22)."""
    from twin.sumo.outputs import OutputPlan

    plan = OutputPlan(tmp_path / "o")
    taken = plan.target(tmp_path / "twin-loops.add.xml")
    own = plan.own_file("twin-loops.add.xml")
    assert taken.name == "twin-loops.add.xml" and own.name == "twin-loops-2.add.xml"


def test_a_comma_in_the_folder_of_a_rewritten_additional_is_one_line(tmp_path):
    """An additional file whose outputs twin sends into the run folder is read by SUMO from
    there: a run folder named with a comma is refused naming it (SUMO split the copy's path,
    "my run: no such file"; probe 15's P2-f01)."""
    from twin.sumo.outputs import redirect_outputs

    add = tmp_path / "det.add.xml"
    add.write_text(
        '<additional><e1Detector id="a" lane="x_0" pos="1" freq="60" file="a.xml"/></additional>'
    )
    with pytest.raises(UserError, match=r"my run,2/sumo: SUMO splits file names at commas and "
                                        r"reads twin's copy of det.add.xml"):  # fmt: skip
        redirect_outputs(None, ("--additional-files", str(add)), tmp_path / "my run,2" / "sumo")


def test_a_comma_in_an_additional_files_path_is_one_line(tmp_path, capsys):
    """``--additional`` under a folder whose name holds a comma: refused naming it (SUMO split
    the path: ".../my scen: no such file"; probe 15's P2-f05)."""
    from helpers import small_sumo_scenario

    from twin.cli import main

    (tmp_path / "s").mkdir()
    folder = small_sumo_scenario(tmp_path / "s", horizon=2)
    odd = tmp_path / "my scen,v2"
    odd.mkdir()
    (odd / "a.add.xml").write_text("<additional/>")
    argv = ["run", "--config", str(folder / "small.toml"), "--additional", str(odd / "a.add.xml"),
            "--swarms", "random", "--no-ceiling", "--no-report", "--quiet",
            "--out", str(tmp_path / "run")]  # fmt: skip
    assert main(argv) == 2
    err = capsys.readouterr().err.strip().splitlines()[-1]
    assert err.startswith(f"twin: error: {odd / 'a.add.xml'}: SUMO splits file names at commas"), (
        err
    )


ROADSIDE = 'roadsideCapacity="30"/>'
#: a parking lot: spaces of its own, away from the road (a cell of no lane may hold them)
LOT = (
    ">"
    + "".join(f'<space x="{400 + 5 * n}" y="{100 + n % 3}"/>' for n in range(10))
    + "</parkingArea>"
)


@pytest.mark.parametrize(
    ("stop", "spaces", "counted"),
    [
        ('<stop parkingArea="pa" duration="20000"/>', ROADSIDE, 1),  # a parking area's roadside
        ('<stop parkingArea="pa" duration="20000"/>', LOT, 1),
        ('<stop lane="B1C1_0" endPos="150" parking="true" duration="20000"/>', ROADSIDE, 1),
        # an area onRoad="true": its cars stand on the lane, and SUMO's lane counts hold them
        ('<stop parkingArea="pa" duration="20000"/>', 'onRoad="true" ' + ROADSIDE, 6),
    ],
)  # fmt: skip
def test_parked_vehicles_are_not_traffic_but_stopped_ones_are(stop, spaces, counted, tmp_path):
    """A vehicle parked off its lane (a parking area, a ``parking="true"`` stop) is not on the
    road: it was counted as a standing vehicle, so 25 parked cars made their cell the most
    congested of the city (probe 25's f01), and a lot's spaces off the roads put more vehicles
    in a cell than its lanes hold, so that twin refused its own tape (f06). One stopped on its
    lane (a bus at its stop, a jam) still is."""
    from twin.sumo.session import SumoSession
    from twin.sumo.tools import binary, run_sumo_program

    run_sumo_program(
        [binary("netgenerate"), "--grid", "--grid.number", "4", "--grid.length", "300",
         "--default.lanenumber", "1", "-o", str(tmp_path / "g.net.xml")],
        what="netgenerate",
    )  # fmt: skip
    (tmp_path / "p.add.xml").write_text(
        '<additional><parkingArea id="pa" lane="B1C1_0" startPos="20" endPos="280" '
        f"{spaces}</additional>"
    )
    on_lane = '<stop lane="B1C1_0" endPos="150" duration="20000"/>'
    (tmp_path / "r.rou.xml").write_text(
        f'<routes><flow id="parked" begin="0" end="100" number="5" from="A1B1" to="C1D1">{stop}'
        f'</flow><flow id="held" begin="200" end="300" number="1" from="A1B1" to="C1D1">'
        f"{on_lane}</flow></routes>"
    )
    session = SumoSession(
        net_file=tmp_path / "g.net.xml", route_files=[tmp_path / "r.rou.xml"],
        additional_files=[tmp_path / "p.add.xml"], begin=0.0, end=3600.0,
    )  # fmt: skip
    with session:
        session.advance_to(900.0)
        xy, speed = session.vehicles()
        assert session.n_running() == 6  # all in the simulation, parked or not
        assert len(xy) == counted and (speed == 0.0).all()  # those on their lanes are traffic


def test_vehicles_on_lanes_cars_may_not_use_are_not_car_traffic(tmp_path):
    """Bicycles on a bike-only lane were counted as cars of their cell, against the car lanes'
    lane-km and speed limits: a bike street read as congested with no car on it (probe 25's
    f09). The cars beside them are counted."""
    from twin.sumo.cells import read_lanes
    from twin.sumo.session import SumoSession
    from twin.sumo.tools import binary, run_sumo_program

    net = tmp_path / "b.net.xml"
    run_sumo_program(
        [binary("netgenerate"), "--grid", "--grid.number", "4", "--grid.length", "300",
         "--default.lanenumber", "1", "--bikelanes.guess", "true", "-o", str(net)],
        what="netgenerate",
    )  # fmt: skip
    lanes = read_lanes(net)
    assert "A0A1_0" in lanes.not_for_cars and "A0A1_1" not in lanes.not_for_cars
    (tmp_path / "b.rou.xml").write_text(
        '<routes><vType id="bike" vClass="bicycle"/><vType id="car" vClass="passenger"/>'
        '<flow id="bk" type="bike" begin="0" end="600" period="3" from="A0A1" to="A2A3"/>'
        '<flow id="cars" type="car" begin="0" end="600" period="30" from="A0A1" to="A2A3"/>'
        "</routes>"
    )
    session = SumoSession(net_file=net, route_files=[tmp_path / "b.rou.xml"], end=3600.0)
    with session:
        session.advance_to(300.0)
        everyone = len(session.vehicles()[0])
        xy, _ = session.vehicles(lanes.not_for_cars)
        cars = [v for v in _libsumo_vehicles() if v.startswith("cars")]
        assert everyone > len(cars) > 0
        assert len(xy) == len(cars)  # the bicycles on their own lane left out


def _libsumo_vehicles() -> list[str]:
    from twin.sumo.session import _libsumo

    return list(_libsumo().vehicle.getIDList())


def test_a_lane_allowing_all_is_a_car_lane(tmp_path):
    """sumolib reads ``allow="all"`` as one class named "all": such a lane was taken for one
    cars may not use, and its cars left out of the counts."""
    from twin.sumo.cells import read_lanes
    from twin.sumo.tools import binary, run_sumo_program

    net = tmp_path / "g.net.xml"
    run_sumo_program(
        [binary("netgenerate"), "--grid", "--grid.number", "3", "--grid.length", "200",
         "-o", str(net)],
        what="netgenerate",
    )  # fmt: skip
    before = read_lanes(net)
    text = net.read_text().replace('<lane id="A0A1_0"', '<lane id="A0A1_0" allow="all"')
    assert 'allow="all"' in text
    net.write_text(text)
    after = read_lanes(net)
    assert len(after.shapes) == len(before.shapes) and not after.not_for_cars


def test_a_network_without_car_lanes_counts_its_other_vehicles(tmp_path, capsys):
    """SUMO runs a freight network (lanes for trucks alone) with its trucks: twin refused it
    for having no passenger lane (a review against SUMO 1.28). Its lanes are the grid's, its
    trucks the traffic, with a notice; a network of sidewalks alone is refused in one line."""
    from twin.sumo.cells import grid_over, read_lanes
    from twin.sumo.detectors import main_edges
    from twin.sumo.session import SumoSession
    from twin.sumo.tools import binary, run_sumo_program

    net = tmp_path / "t.net.xml"
    run_sumo_program(
        [binary("netgenerate"), "--grid", "--grid.number", "3", "--grid.length", "200",
         "--default.allow", "truck", "-o", str(net)],
        what="netgenerate",
    )  # fmt: skip
    lanes = read_lanes(net)
    err = capsys.readouterr().err
    assert "no lane lets passenger cars drive" in err and "(truck)" in err, err
    assert lanes.shapes and not lanes.not_for_cars
    stations = main_edges(net, grid_over(lanes, 200.0))  # detectors on the trucks' lanes
    assert stations and all(lane.allows("truck") for cell in stations.values() for lane in cell)
    (tmp_path / "t.rou.xml").write_text(
        '<routes><vType id="lorry" vClass="truck"/><flow id="f" type="lorry" begin="0" '
        'end="300" period="10" from="A0A1" to="C2C1"/></routes>'
    )
    session = SumoSession(net_file=net, route_files=[tmp_path / "t.rou.xml"], end=3600.0)
    with session:
        session.advance_to(200.0)
        xy, _ = session.vehicles(lanes.not_for_cars)
        assert len(xy) == len(_libsumo_vehicles()) > 0
    walk = tmp_path / "w.net.xml"
    walk.write_text(net.read_text().replace('allow="truck"', 'allow="pedestrian"'))
    with pytest.raises(UserError, match="the network has no lane that vehicles may use"):
        read_lanes(walk)


def test_parking_under_meso_is_said_to_count(tmp_path, capsys):
    """Under --meso SUMO tells no lane or parking, so parked vehicles count as traffic (a full
    lot read as importance 0.999, silently: probe 25b's u02): a notice says so."""
    from twin.sumo.scenario import _say_meso_parking

    routes, plain = tmp_path / "p.rou.xml", tmp_path / "q.rou.xml"
    routes.write_text(
        '<routes><flow id="p" begin="0" end="100" number="3" from="a" to="b">'
        '<stop parkingArea="pa" duration="20000"/></flow></routes>'
    )
    plain.write_text(
        '<routes><flow id="q" begin="0" end="100" number="3" from="a" to="b"/></routes>'
    )
    _say_meso_parking([plain])
    assert "parks vehicles" not in capsys.readouterr().err
    _say_meso_parking([plain, routes])
    err = capsys.readouterr().err
    assert f"{routes}: parks vehicles, but SUMO's mesoscopic model (--meso, or a sumocfg's " in err
    areas = tmp_path / "a.add.xml"  # parking areas alone park nobody
    areas.write_text(
        '<additional><parkingArea id="pa" lane="a_0" startPos="0" endPos="9"/></additional>'
    )
    _say_meso_parking([plain, areas])
    assert "parks vehicles" not in capsys.readouterr().err


def test_with_a_begin_given_what_sumo_ignores_stays_out_of_the_demand(scenario, tmp_path):
    """A begin given and demand departing at "begin" make twin read the demand again from
    twin's start: that second reading counted the flow SUMO ignores in an unsorted route file
    (the final reread of the departure-order rule)."""
    from twin.config import load_config
    from twin.sumo.scenario import sumo_source

    routes = tmp_path / "unsorted.rou.xml"
    routes.write_text(
        '<routes><trip id="b" depart="begin" from="A0A1" to="B1B2"/>'
        '<trip id="v" depart="3600" from="A0A1" to="B1B2"/>'
        '<flow id="f" begin="50" end="9000" period="60" from="A0A1" to="B1B2"/></routes>'
    )
    source = sumo_source(load_config(scenario / "config.toml"), routes=[routes], begin="00:50",
                         net=scenario / "scenario" / "small.net.xml", horizon=2)  # fmt: skip
    try:
        assert source.scenario.extra["departures"][1] == 3600.0
    finally:
        source.close()
