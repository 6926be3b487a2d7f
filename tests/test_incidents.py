"""Scheduled incidents: config, scoring by hand, and applied in a small SUMO run."""

from __future__ import annotations

import json

import numpy as np
import pytest

from twin.config import load_config
from twin.errors import UserError
from twin.grid import Grid
from twin.monitoring import incident_scores, incident_sightings
from twin.sumo.incidents import onset_and_end_steps


def test_incident_sightings_by_hand():
    grid = Grid(np.zeros((3, 4), bool))
    # one drone, steps 0..4: (0,0) (0,1) (1,1) (2,1) (2,2); view = the cell and its 4 neighbours
    positions = np.array([[[0, 0]], [[0, 1]], [[1, 1]], [[2, 1]], [[2, 2]]])
    incidents = [
        {"cell": [2, 3], "onset_step": 1, "end_step": 4},  # (2,3) next to (2,2) at step 4
        {"cell": [0, 3], "onset_step": 0, "end_step": 4},  # never in view
        {"cell": [1, 1], "onset_step": 3, "end_step": 3},  # (2,1) sees (1,1) at step 3
        {"cell": [0, 0], "onset_step": 2, "end_step": 9},  # seen at 0 and 1: before its onset
    ]
    first, latency = incident_sightings(grid, positions, incidents)
    np.testing.assert_array_equal(first, [4, -1, 3, -1])
    np.testing.assert_array_equal(latency, [3, -1, 0, -1])
    row = incident_scores(first, latency, step_s=75.0)
    assert row["incidents"] == 4 and row["pct_incidents_seen"] == 50.0
    assert row["incident_latency_steps"] == 1.5 and row["incident_latency_min"] == 1.875


def test_incident_times_are_on_sumos_milliseconds_as_read_back():
    """The end is the rounded begin plus the duration, rounded: as the read-back computes it
    from the recorded begin (a begin of a fractional step and an odd duration differed by a
    millisecond, and the run's own folder was refused; the review)."""
    from types import SimpleNamespace

    from twin.sumo.incidents import incident_window

    for step_s, duration in ((12.4138, 0.68596), (53.333333, 1.00000001), (75.0, 2.5)):
        inc = SimpleNamespace(begin=None, step=1, duration_min=duration)
        begin, end = incident_window(inc, 0, 25200.0, step_s)
        assert begin == round(begin, 3) and end == round(begin + 60.0 * duration, 3)


def test_onset_and_end_steps():
    # step k observes (t0 + (k-1) 75, t0 + k 75]: 07:45 -> step 37, 08:15 -> step 60
    assert onset_and_end_steps(2700.0, 4500.0, 0.0, 75.0) == (37, 60)
    assert onset_and_end_steps(10.0, 20.0, 0.0, 75.0) == (1, 1)


def test_incident_config_is_checked(tmp_path):
    path = tmp_path / "c.toml"
    path.write_text(
        '[traffic]\nkind = "sumo"\n[[traffic.incidents]]\nkind = "road_works"\n'
        'edge = "e1"\nbegin = "07:45"\nduration_min = 30\n'
    )
    with pytest.raises(UserError, match="kind"):
        load_config(path)
    path.write_text(
        '[traffic]\nkind = "sumo"\n[[traffic.incidents]]\nkind = "edge_closed"\n'
        'edge = "e1"\ncell = [1, 2]\nbegin = "07:45"\nduration_min = 30\n'
    )
    with pytest.raises(UserError, match="either edge"):
        load_config(path)
    path.write_text(
        '[traffic]\nkind = "sumo"\n[[traffic.incidents]]\nkind = "edge_closed"\n'
        'edge = "e1"\nlane = 1\nbegin = "07:45"\nduration_min = 30\n'
    )
    with pytest.raises(UserError, match='gives lane = 1, which only kind = "lane_closed" reads'):
        load_config(path)
    # shorter than SUMO's step: applied and lifted at one instant, its record then refused
    # by the run's own report (probe 20's f06)
    path.write_text(
        '[traffic]\nkind = "sumo"\n[[traffic.incidents]]\nkind = "edge_closed"\n'
        'edge = "e1"\nbegin = "07:45"\nduration_min = 1e-9\n'
    )
    with pytest.raises(UserError, match=r"duration_min = 1e-09 lasts 6e-08 s, shorter than SUMO"):
        load_config(path)
    # so long that its end in seconds overflows: a partial run of 0 steps (probe 21's f03)
    path.write_text(
        '[traffic]\nkind = "sumo"\n[[traffic.incidents]]\nkind = "edge_closed"\n'
        'edge = "e1"\nbegin = "07:45"\nduration_min = 1e308\n'
    )
    with pytest.raises(UserError, match=r"incidents\[0\]\.duration_min = 1e\+308 must be <= "):
        load_config(path)


# ------------------------------------------------------------------------ on a small SUMO run
INCIDENTS = """
[[traffic.incidents]]
kind = "edge_closed"
cell = [2, 2]
step = 2
duration_min = 4.0
[[traffic.incidents]]
kind = "vehicle_stopped"
cell = [1, 2]
begin = "00:09"
duration_min = 2.0
"""


def test_closure_is_active_in_its_window_and_lifted_after(tmp_path):
    libsumo = pytest.importorskip("libsumo")
    from helpers import small_sumo_scenario
    from test_sumo_small import _patrol

    from twin.sumo.scenario import sumo_source

    small_sumo_scenario(tmp_path, horizon=10)
    with open(tmp_path / "small.toml", "a") as fh:
        fh.write(INCIDENTS)
    source = sumo_source(load_config(tmp_path / "small.toml"))
    maps = source.importance_maps()
    allowed = {}
    schedule = None
    for k, _ in enumerate(maps):  # T^0 at 00:05, one step = 60 s: the closure holds 00:07-00:11
        schedule = source.incident_schedule
        closed = schedule.records[0]
        if closed["edge"] is not None:
            lane = f"{closed['edge']}_0"
            allowed[k] = list(libsumo.lane.getAllowed(lane))
    maps.close()
    assert [k for k, a in allowed.items() if a == ["authority"]] == [2, 3, 4, 5]
    assert allowed[6] != ["authority"] and allowed[10] == allowed[6]
    closed, stopped = schedule.to_json()
    # on at 00:07 = T^2's instant: steps 3..6 observe intervals that meet [00:07, 00:11)
    assert closed["cell"] == [2, 2] and (closed["onset_step"], closed["end_step"]) == (3, 6)
    assert closed["applied_s"] == 420.0 and closed["lifted_s"] == 660.0
    assert stopped["vehicle"] is not None and stopped["lifted_s"] == 660.0
    assert (stopped["onset_step"], stopped["end_step"]) == (5, 6)

    _patrol(source)  # a second run of the same seed resolves the same edge
    assert source.incidents_info()[0]["edge"] == closed["edge"]


def test_run_writes_incidents_json_and_scores_them(tmp_path):
    pytest.importorskip("libsumo")
    from helpers import small_sumo_scenario

    from twin.cli import main as twin_main

    small_sumo_scenario(tmp_path, horizon=10)
    with open(tmp_path / "small.toml", "a") as fh:
        fh.write(INCIDENTS)
    out = tmp_path / "run"
    code = twin_main(
        [
            "run",
            "--config",
            str(tmp_path / "small.toml"),
            "--out",
            str(out),
            "--no-report",
            "--quiet",
        ]
    )
    assert code == 0
    truth = json.loads((out / "incidents.json").read_text())
    assert [r["kind"] for r in truth] == ["edge_closed", "vehicle_stopped"]
    assert all(len(r["cell"]) == 2 and r["duration_min"] > 0 for r in truth)
    import pandas as pd

    summary = pd.read_csv(out / "summary.csv")
    summary = summary[summary["role"] == "swarm"]  # the ceiling rows watch no incident
    assert (summary["incidents"] == 2).all()
    assert summary["pct_incidents_seen"].between(0, 100).all()

    from twin.report import write_report
    from twin.report.document import incident_rows
    from twin.report.load import load_run

    write_report(out, animation=False)
    rf = load_run(out)
    rows = incident_rows(rf)
    assert [r[1] for r in rows] == ["edge_closed", "vehicle_stopped"]
    assert rows[0][3] == "(2, 2)" and rows[0][6] == "3-6"
    markdown = next(out.rglob("*.md")).read_text()
    assert "## Incidents" in markdown and "% incidents seen" in markdown


def test_a_vehicle_to_stop_never_found_on_its_edge_is_recorded_as_never_applied(tmp_path):
    """A stopped vehicle given by its edge, at a time no vehicle drives there (the demand has
    cleared): the run ends with the incident at its edge's cell, never applied (it was an
    internal error after the whole simulation, the results lost)."""
    pytest.importorskip("libsumo")
    from helpers import small_sumo_scenario

    from twin.cli import main as twin_main
    from twin.sumo.incidents import net_edges

    small_sumo_scenario(tmp_path, horizon=40)  # departures end at 00:15, the run at 00:45
    edge = sorted(net_edges(next(tmp_path.glob("*.net.xml"))))[0]
    with open(tmp_path / "small.toml", "a") as fh:
        fh.write(
            f'[[traffic.incidents]]\nkind = "vehicle_stopped"\nedge = "{edge}"\n'
            'begin = "00:40"\nduration_min = 2.0\n'
        )
    out = tmp_path / "run"
    argv = ["run", "--config", str(tmp_path / "small.toml"), "--out", str(out), "--no-report",
            "--quiet", "--swarms", "random", "--no-ceiling"]  # fmt: skip
    assert twin_main(argv) == 0
    (record,) = json.loads((out / "incidents.json").read_text())
    assert record["edge"] == edge and len(record["cell"]) == 2 and record["cell"] != [-1, -1]
    assert record["vehicle"] is None and record["applied_s"] is None
    import pandas as pd

    scores = pd.read_csv(out / "monitoring.csv")  # nothing on the road to see (probe 17's P2-01)
    assert (scores["incidents"] == 0).all() and scores["pct_incidents_seen"].isna().all(), scores
    assert twin_main(["report", str(out), "--no-animation"]) == 0


@pytest.fixture(scope="module")
def incident_run(tmp_path_factory):
    """A small `twin run` with the two incidents above, made once."""
    pytest.importorskip("libsumo")
    from helpers import small_sumo_scenario

    from twin.cli import main as twin_main

    folder = tmp_path_factory.mktemp("incidents")
    small_sumo_scenario(folder, horizon=10)
    with open(folder / "small.toml", "a") as fh:
        fh.write(INCIDENTS)
    argv = ["run", "--config", str(folder / "small.toml"), "--out", str(folder / "run"),
            "--no-report", "--quiet"]  # fmt: skip
    assert twin_main(argv) == 0
    return folder / "run"


def _incidents_edited(change):
    def edit(run):
        incidents = json.loads((run / "incidents.json").read_text())
        (run / "incidents.json").write_text(json.dumps(change(incidents)))

    return edit


def _update(incidents, n, **fields):
    incidents[n].update(fields)
    return incidents


def _shift_onset(incidents):
    incidents[0]["onset_step"] -= 2
    return incidents


# a forged incidents.json -> the words of the one-line refusal
FORGED_INCIDENTS = {
    "onset other than its time": (
        _incidents_edited(_shift_onset),
        "incidents.json: [0].onset_step = 1, but its begin_s and end_s give step 3",
    ),
    "incidents emptied": (
        _incidents_edited(lambda incidents: []),
        "incidents.json: 0 incidents, but run.json's traffic.incidents schedules 2",
    ),
    "a configured cell moved": (
        _incidents_edited(lambda x: _update(x, 1, cell=[0, 2])),
        "incidents.json: [1].cell = [0, 2], but run.json's traffic.incidents[1] schedules [1, 2]",
    ),
    "a longer duration with its end": (
        _incidents_edited(
            lambda x: _update(
                x, 1, duration_min=3.0, end_s=x[1]["end_s"] + 60.0, lifted_s=x[1]["end_s"] + 60.0
            )
        ),
        "incidents.json: [1].end_s = ",
    ),
    "edge moved out of its cell": (
        _incidents_edited(lambda x: _update(x, 0, edge="A0A1")),
        "incidents.json: [0].cell = [2, 2], but edge 'A0A1' of ",
    ),
    "an edge the network lacks": (
        _incidents_edited(lambda x: _update(x, 0, edge="nowhere")),
        'incidents.json: [0].edge = "nowhere" is not an edge of ',
    ),
    "a stopped vehicle that names none": (
        _incidents_edited(lambda x: _update(x, 0, kind="vehicle_stopped")),
        "incidents.json: [0].vehicle = null, but kind vehicle_stopped applied at",
    ),
    "a lane on an edge closure": (
        _incidents_edited(lambda x: _update(x, 0, lane=3)),
        "incidents.json: [0].lane = 3, but kind edge_closed records null",
    ),
    "a lane the edge lacks": (
        _incidents_edited(lambda x: _update(x, 0, kind="lane_closed", lane=9)),
        "incidents.json: [0].lane = 9, but edge ",
    ),
    "applied later than its begin": (
        _incidents_edited(lambda x: _update(x, 0, applied_s=x[0]["begin_s"] + 40.0)),
        "incidents.json: [0].applied_s = ",
    ),
    "an unknown kind": (
        _incidents_edited(lambda x: _update(x, 0, kind="flood")),
        "incidents.json: [0].kind = 'flood' is none of",
    ),
    "not lifted though lifted in the run": (
        _incidents_edited(lambda x: _update(x, 0, lifted_s=None)),
        "incidents.json: [0].lifted_s = null, but an incident to end_s = 660 is lifted at 660,",
    ),
}


@pytest.mark.parametrize("case", list(FORGED_INCIDENTS))
def test_a_forged_incidents_json_is_refused(incident_run, tmp_path, capsys, case):
    import shutil

    from twin.cli import main as twin_main
    from twin.report.load import load_run
    from twin.runs import write_manifest

    run = tmp_path / "run"
    shutil.copytree(incident_run, run)
    load_run(run)  # as written, the incidents read back
    change, words = FORGED_INCIDENTS[case]
    change(run)
    write_manifest(run)
    capsys.readouterr()
    assert twin_main(["report", str(run), "--no-animation"]) == 2
    err = capsys.readouterr().err.strip()
    assert words in err and err.count("\n") == 0 and "Traceback" not in err, err
    assert not (run / "report").exists()


@pytest.fixture(scope="module")
def edge_incident_run(tmp_path_factory):
    """A small `twin run` with one closure of a named edge."""
    pytest.importorskip("libsumo")
    from helpers import small_sumo_scenario

    from twin.cli import main as twin_main

    folder = tmp_path_factory.mktemp("edge-incident")
    small_sumo_scenario(folder, horizon=8)
    with open(folder / "small.toml", "a") as fh:
        fh.write(_incident(where='edge = "B1B2"', when="step = 2", minutes=2.0))
    argv = ["run", "--config", str(folder / "small.toml"), "--out", str(folder / "run"),
            "--no-report", "--quiet", "--swarms", "random,greedy"]  # fmt: skip
    assert twin_main(argv) == 0
    return folder / "run"


def _run_json_edited(change):
    def edit(run):
        meta = json.loads((run / "run.json").read_text())
        change(meta["traffic"])
        (run / "run.json").write_text(json.dumps(meta))

    return edit


# an edge-closure run whose incidents.json or run.json was forged -> the refusal's words
FORGED_SCHEDULE = {
    "the edge swapped for another through its cell": (
        _incidents_edited(lambda x: _update(x, 0, edge="C1B1")),
        'incidents.json: [0].edge = "C1B1", but run.json\'s traffic.incidents[0] schedules "B1B2"',
    ),
    "the schedule left out of run.json": (
        _run_json_edited(lambda traffic: traffic.pop("incidents")),
        "run.json: traffic.incidents (the configured schedule) is missing, but ",
    ),
    # run.json's schedule forged alone: the tape's record of it refuses it first
    "the schedule's edge forged alone": (
        _run_json_edited(lambda traffic: traffic["incidents"][0].update(edge="B2B1")),
        'run.json: traffic.incidents[0].edge = "B2B1", but tape.parquet (seed 0\'s tape) '
        'records "B1B2"',
    ),
    "a schedule that is no incident": (
        _run_json_edited(lambda traffic: traffic["incidents"][0].update(kind="flood")),
        'run.json: traffic.incidents[0].kind = "flood", but tape.parquet (seed 0\'s tape)',
    ),
    # probe 16's f09: an edge's incident moved to another cell, lifted after its end
    "the cell moved off the edge's middle": (
        _incidents_edited(lambda x: _update(x, 0, cell=[x[0]["cell"][0], x[0]["cell"][1] + 1])),
        "but an incident given by its edge 'B1B2' is recorded at the cell of the edge's middle",
    ),
    "lifted long after its end": (
        _incidents_edited(lambda x: _update(x, 0, lifted_s=99999.0)),
        "incidents.json: [0].lifted_s = 99999.0, but an incident to end_s = ",
    ),
    "a second incident scheduled": (
        _run_json_edited(lambda traffic: traffic["incidents"].append(traffic["incidents"][0])),
        "run.json: traffic.incidents = [{",
    ),
}


@pytest.mark.parametrize("case", list(FORGED_SCHEDULE))
def test_incidents_json_holds_the_schedule_run_json_records(
    edge_incident_run, tmp_path, capsys, case
):
    import shutil

    from twin.cli import main as twin_main
    from twin.report.load import load_run
    from twin.runs import write_manifest

    run = tmp_path / "run"
    shutil.copytree(edge_incident_run, run)
    assert json.loads((run / "run.json").read_text())["traffic"]["incidents"][0]["edge"] == "B1B2"
    load_run(run)  # as written, the incidents read back
    change, words = FORGED_SCHEDULE[case]
    change(run)
    write_manifest(run)
    capsys.readouterr()
    assert twin_main(["report", str(run), "--no-animation"]) == 2
    err = capsys.readouterr().err.strip()
    assert words in err and err.count("\n") == 0 and "Traceback" not in err, err
    assert not (run / "report").exists()


# ------------------------------------------------- checked before the run; overlapping closures
def _small(tmp_path, incidents: str):
    from helpers import small_sumo_scenario

    small_sumo_scenario(tmp_path, horizon=10)
    with open(tmp_path / "small.toml", "a") as fh:
        fh.write(incidents)
    return tmp_path / "small.toml"


def _incident(kind="edge_closed", where='edge = "B1B2"', when='begin = "00:07"', minutes=4.0):
    return f'\n[[traffic.incidents]]\nkind = "{kind}"\n{where}\n{when}\nduration_min = {minutes}\n'


# name -> (incidents, words of the one-line error[, a flag]); T^0 = 00:05, 10 steps of 60 s,
# warm-up 5 min
BAD_INCIDENTS = {
    "late in the evening": (_incident(when='begin = "23:00"'), "outside the scenario's window"),
    "after the end": (_incident(when='begin = "00:15"'), "00:00:00 - 00:15:00"),
    "a step past the horizon": (_incident(when="step = 11"), "step = 11 (00:16:00) is outside"),
    "over in the warm-up": (
        _incident(when='begin = "00:01"', minutes=2.0),
        "ends at 00:03:00, by the run's first step T^0 = 00:05:00 (it lies in the warm-up)",
    ),
    "a cell off the grid": (_incident(where="cell = [40, 1]"), "cell = [40, 1] is off the"),
    "a cell without road": (  # a grid larger than the network: its border has no road
        _incident(where="cell = [0, 0]") + "[grid]\nnx = 12\nny = 12\n",
        "cell = [0, 0] has no road; pick a cell on a road",
    ),
    "an unknown edge": (_incident(where='edge = "nowhere"'), "'nowhere' is not a road of"),
    "a lane the edge lacks": (
        _incident(kind="lane_closed", where='edge = "B1B2"\nlane = 5'),
        "edge 'B1B2' has 2 lanes",
    ),
    "a stopped vehicle in the mesoscopic model": (  # it blocked nothing, scored as seen
        _incident(kind="vehicle_stopped"),
        'kind = "vehicle_stopped" with SUMO\'s mesoscopic model',
        "--meso",
    ),
}


@pytest.mark.parametrize("case", list(BAD_INCIDENTS))
def test_incidents_are_checked_before_the_run(tmp_path, capsys, case):
    pytest.importorskip("libsumo")
    from test_bad_inputs import run_case

    incidents, needle, *flags = BAD_INCIDENTS[case]
    cfg = _small(tmp_path, incidents)
    out = tmp_path / "run"
    argv = ["run", "--config", str(cfg), "--out", str(out), "--no-report", "--quiet", *flags]
    err = run_case(capsys, tmp_path, argv, out, 2, needle)
    assert str(cfg) in err and "[traffic].incidents[0]" in err
    assert not out.exists()


@pytest.mark.parametrize(
    "incident",
    [
        _incident(minutes=1.00000001),  # its end falls 0.6 microseconds past a SUMO step
        _incident(kind="vehicle_stopped", when="step = 2", minutes=3.0000001),
    ],
)
def test_an_incident_whose_end_falls_within_a_millisecond_of_a_step_reads_back(
    tmp_path, capsys, incident
):
    """SUMO advances to a time rounded to its milliseconds: an incident ending 0.6 us past a
    step was lifted at that step, and the run's own record then refused as lifted a step too
    early (probe 20's f06, P2-f06a)."""
    pytest.importorskip("libsumo")
    from twin.cli import main as twin_main

    cfg = _small(tmp_path, incident)
    out = tmp_path / "run"
    argv = ["run", "--config", str(cfg), "--out", str(out), "--quiet", "--no-report",
            "--swarms", "greedy", "--no-ceiling"]  # fmt: skip
    assert twin_main(argv) == 0, capsys.readouterr().err
    (record,) = json.loads((out / "incidents.json").read_text())
    assert record["end_s"] == round(record["end_s"], 3) and record["lifted_s"] is not None
    capsys.readouterr()
    assert twin_main(["report", "--no-animation", str(out)]) == 0, capsys.readouterr().err


@pytest.fixture(scope="module")
def walkable(tmp_path_factory):
    """A 3 x 3 grid of 200 m blocks with sidewalks (lane 0 of each road, pedestrians only),
    crossings and walking areas, as `netgenerate --sidewalks.guess --crossings.guess` writes
    it, and a flow of cars over it."""
    pytest.importorskip("libsumo")
    from twin.sumo.tools import binary, run_sumo_program

    d = tmp_path_factory.mktemp("walkable")
    run_sumo_program(
        [binary("netgenerate"), "--grid", "--grid.number", "3", "--grid.length", "200",
         "--sidewalks.guess", "--crossings.guess", "--tls.guess", "true",
         "-o", str(d / "sw.net.xml")],
        what="netgenerate",
    )  # fmt: skip
    (d / "sw.rou.xml").write_text(
        '<routes><flow id="f" begin="0" end="900" period="10" from="A0A1" to="C2C1"/></routes>'
    )
    return d


#: incident on a network with sidewalks -> words of its one-line refusal (None: it runs)
WALKABLE_INCIDENTS = {
    "a walking area": (
        _incident(where='edge = ":B1_w0"'),
        "edge = ':B1_w0' is not a road of",
    ),
    "a crossing": (
        _incident(kind="vehicle_stopped", where='edge = ":B1_c0"'),
        "(a junction's inner lane, crossing or walking area: no road)",
    ),
    "a sidewalk": (
        _incident(kind="lane_closed", where='edge = "A0A1"\nlane = 0'),
        "lane = 0 of edge 'A0A1' is for pedestrians (a sidewalk): closing it holds up no "
        "vehicle; give a lane vehicles use (1)",
    ),
    "the road beside it": (_incident(kind="lane_closed", where='edge = "A0A1"\nlane = 1'), None),
    "a cell's sidewalks": (
        _incident(kind="lane_closed", where="cell = [3, 0]\nlane = 0"),
        "lane = 0: no road of cell = [3, 0] has a lane 0 that carries vehicles (where a road "
        "has a sidewalk, it is lane 0); give lane = 1",
    ),
    "a cell's road": (_incident(kind="lane_closed", where="cell = [3, 0]\nlane = 1"), None),
    "a cell's busiest road": (_incident(where="cell = [3, 0]"), None),
}


@pytest.mark.parametrize("case", list(WALKABLE_INCIDENTS))
def test_an_incident_on_what_carries_no_vehicle_is_refused(walkable, tmp_path, capsys, case):
    """A walking area or crossing was taken as an incident's edge, recorded at cell [-1, -1]
    (a folder the run's own report then refused), and a sidewalk as the lane to close, which
    holds up nothing (probe 20's f05, c39). A cell's incident picks among its roads' lanes
    that carry vehicles."""
    from test_bad_inputs import run_case

    from twin.cli import main as twin_main

    incidents, needle = WALKABLE_INCIDENTS[case]
    cfg = tmp_path / "walk.toml"
    cfg.write_text(
        f'[swarm]\nn_drones = 2\n[traffic]\nkind = "sumo"\nnet = "{walkable / "sw.net.xml"}"\n'
        f'routes = ["{walkable / "sw.rou.xml"}"]\ncell_m = 100.0\nbegin = "00:05"\n'
        f"horizon = 6\nwarmup_min = 2.0\ndrone_speed_kmh = 6.0\n{incidents}"
    )
    out = tmp_path / "run"
    argv = ["run", "--config", str(cfg), "--out", str(out), "--quiet", "--swarms", "greedy",
            "--no-ceiling"]  # fmt: skip
    if needle is not None:
        run_case(capsys, tmp_path, [*argv, "--no-report"], out, 2, needle)
        assert not out.exists()
        return
    assert twin_main(argv) == 0, capsys.readouterr().err
    (record,) = json.loads((out / "incidents.json").read_text())
    assert record["applied_s"] is not None and record["cell"] != [-1, -1], record
    assert record["edge"] is not None and not record["edge"].startswith(":"), record


def test_overlapping_closures_reopen_when_the_last_lifts(tmp_path, capsys):
    """Two closures of edge B1B2 (00:07-00:11, 00:09-00:13) and a lane closure of its lane 0
    inside them: the lane stays closed 00:07-00:13 and then gets back its own permissions (the
    second closure must not restore the "authority" of the first); twin notes the overlaps."""
    libsumo = pytest.importorskip("libsumo")
    from twin.sumo.scenario import sumo_source

    cfg = _small(
        tmp_path,
        _incident(minutes=4.0)
        + _incident(when='begin = "00:09"', minutes=4.0)
        + _incident(kind="lane_closed", where='edge = "B1B2"\nlane = 0', when='begin = "00:08"',
                    minutes=2.0),
    )  # fmt: skip
    source = sumo_source(load_config(cfg))
    err = capsys.readouterr().err
    assert err.count("overlap on edge 'B1B2'") == 3, err
    assert "[traffic].incidents[0] and [1] overlap on edge 'B1B2' from 00:09:00 to 00:11:00" in err
    allowed = {}
    maps = source.importance_maps()
    for k, _ in enumerate(maps):  # T^k at 00:05 + k min
        allowed[k] = {lane: list(libsumo.lane.getAllowed(lane)) for lane in ("B1B2_0", "B1B2_1")}
        if k == 0:
            original = allowed[0]
    maps.close()
    closed = [k for k, a in allowed.items() if a["B1B2_0"] == ["authority"]]
    assert closed == [2, 3, 4, 5, 6, 7]  # 00:07 .. 00:12 (lifted at 00:13 = T^8)
    assert [k for k, a in allowed.items() if a["B1B2_1"] == ["authority"]] == closed
    assert all(allowed[k] == original for k in (0, 1, 8, 9, 10))
    records = source.incidents_info()
    assert [r["lifted_s"] for r in records] == [660.0, 780.0, 600.0]
    assert "lanes" not in records[0]


def test_an_incident_on_an_obstacle_cell_is_said(tmp_path, capsys):
    """A cell-given incident on a cell the config makes an obstacle (a road no drone may fly
    over): it holds up traffic, but no swarm can see it; said in a notice (probe 21's c91)."""
    pytest.importorskip("libsumo")
    from twin.sumo.scenario import sumo_source

    cfg = _small(tmp_path, _incident(where="cell = [2, 2]"))
    cfg.write_text(cfg.read_text().replace("[swarm]", "[grid]\nobstacles = [[2, 2]]\n[swarm]"))
    sumo_source(load_config(cfg)).close()
    err = capsys.readouterr().err
    assert "[traffic].incidents[0].cell = [2, 2] is an obstacle of the grid" in err, err
    (tmp_path / "free").mkdir()
    free = sumo_source(load_config(_small(tmp_path / "free", _incident(where="cell = [2, 2]"))))
    geometry, net = free.geometry, free.scenario.net_file
    free.close()
    assert "is an obstacle" not in capsys.readouterr().err
    # one given by its edge, in that cell: said too (it was not: probe 27e's m04)
    from twin.sumo.incidents import edge_lanes, middle_cell, net_edges

    shapes = edge_lanes(net, set(net_edges(net)))
    edge = next(e for e in sorted(shapes) if middle_cell(shapes[e][1], geometry) == (2, 2))
    (tmp_path / "by-edge").mkdir()
    cfg = _small(tmp_path / "by-edge", _incident(where=f'edge = "{edge}"'))
    cfg.write_text(cfg.read_text().replace("[swarm]", "[grid]\nobstacles = [[2, 2]]\n[swarm]"))
    sumo_source(load_config(cfg)).close()
    err = capsys.readouterr().err
    assert f"[traffic].incidents[0].edge = {edge!r} lies in cell [2, 2], an obstacle" in err, err


def test_route_errors_are_skipped_with_closures_and_twins_own_demand_only(tmp_path):
    """A scenario's own demand is run as SUMO runs it (a route it cannot follow stops it); with
    scheduled closures, which leave routes unfollowable, and in twin's own demand, such a
    vehicle is skipped."""
    pytest.importorskip("libsumo")
    from twin.config import load_config
    from twin.sumo.scenario import sumo_source

    plain = _small(tmp_path, "")
    assert "--ignore-route-errors" not in sumo_source(load_config(plain)).session().command()
    (tmp_path / "closed").mkdir()
    closed = _small(tmp_path / "closed", _incident())
    assert "--ignore-route-errors" in sumo_source(load_config(closed)).session().command()
