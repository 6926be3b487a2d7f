"""Fixed detectors: reading loops and lane-area detectors through libsumo, placing virtual
loops, the nowcast fed by detectors, bad detector settings."""

from __future__ import annotations

import itertools
import json
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from twin.belief import (
    DETECTORS_ONLY,
    DetectorCalibration,
    DetectorObservations,
    History,
    error_curve,
    fit_detector_calibration,
    fit_history,
    history_belief,
    nowcast,
)
from twin.grid import Grid


# ----------------------------------------------------------------- nowcast with detectors
def _days(rng, n_days, steps, shape, rho=0.8):
    """Days of importance: a common mean pattern plus an AR(1) deviation per cell."""
    base = rng.uniform(0.1, 0.6, (steps, *shape))
    days = []
    for _ in range(n_days):
        dev = np.zeros((steps, *shape))
        for k in range(1, steps):
            dev[k] = rho * dev[k - 1] + rng.normal(0, 0.06, shape)
        days.append(np.clip(base + dev, 0.0, 1.0))
    return days


@pytest.mark.parametrize("seed", range(6))
def test_nowcast_with_detectors_is_never_worse(seed):
    """Detectors that read the truth with noise of the stated variance: the nowcast with them
    is closer to the truth than without, with drones and without (history only)."""
    rng = np.random.default_rng(seed)
    shape, steps = (8, 10), 40
    obstacles = np.zeros(shape, bool)
    obstacles[0, :3] = True
    grid = Grid(obstacles)
    *earlier, today = _days(rng, 9, steps, shape)
    history = fit_history(earlier, obstacles)
    free = np.flatnonzero(grid.free.ravel())
    cells = np.sort(rng.choice(free, 12, replace=False))
    noise_var = 0.02**2
    flat = today.reshape(steps, -1)
    values = flat[:, cells] + rng.normal(0, np.sqrt(noise_var), (steps, len(cells)))
    values[rng.random(values.shape) < 0.2] = np.nan  # some steps without a reading
    detectors = DetectorObservations(cells, np.clip(values, 0, 1))
    positions = np.stack([rng.integers(0, [8, 10], (2, 2)) for _ in range(steps)])
    curve = {}
    for name, pos, det in (
        ("drones", positions, None),
        ("drones+detectors", positions, detectors),
        ("detectors", positions[:, :0], detectors),
    ):
        mean, _ = nowcast(grid, pos, today, history, 1e-3, 0.0, det, noise_var)
        curve[name] = error_curve(mean, today, grid, 0.1)[1:].mean()
    hist_mean, _ = history_belief(history, steps)
    curve["history"] = error_curve(hist_mean, today, grid, 0.1)[1:].mean()
    assert curve["drones+detectors"] < curve["drones"]
    assert curve["detectors"] < curve["history"]


def test_detectors_shrink_the_stated_uncertainty_of_their_cells_only():
    rng = np.random.default_rng(1)
    obstacles = np.zeros((4, 5), bool)
    grid = Grid(obstacles)
    earlier = _days(rng, 4, 6, (4, 5))
    history = fit_history(earlier, obstacles)
    cells = np.array([3, 11])
    det = DetectorObservations(cells, np.full((6, 2), 0.5))
    nobody = np.zeros((6, 0, 2), np.int64)
    _, std0 = nowcast(grid, nobody, earlier[0], history)
    _, std1 = nowcast(grid, nobody, earlier[0], history, detectors=det)
    others = np.setdiff1d(np.arange(20), cells)
    assert np.all(std1[:, cells] < std0[:, cells])
    np.testing.assert_array_equal(std1[:, others], std0[:, others])


def test_observations_average_a_station_and_leave_gaps():
    obs = DetectorObservations.from_readings(
        [(0, 7, 0.2), (0, 7, 0.4), (2, 7, 0.1), (1, 3, 0.9), (9, 3, 0.5)], horizon=2
    )
    assert list(obs.cells) == [3, 7]
    np.testing.assert_allclose(obs.values[:, 1], [0.3, np.nan, 0.1])
    np.testing.assert_allclose(obs.values[:, 0], [np.nan, 0.9, np.nan])


# ------------------------------------------------------------- stations' calibration
def _biased_stations(rng, day, cells, bias, std):
    """A day's readings of stations at ``cells``: the truth plus each one's bias and noise."""
    flat = day.reshape(len(day), -1)[:, cells]
    return DetectorObservations(cells, flat + bias + rng.normal(0, std, flat.shape))


def test_calibration_recovers_each_stations_bias_and_variance():
    rng = np.random.default_rng(3)
    shape, steps = (6, 7), 60
    days = _days(rng, 8, steps, shape)
    cells = np.array([4, 17, 30])
    bias, std = np.array([-0.08, 0.0, 0.05]), np.array([0.01, 0.04, 0.02])
    c = fit_detector_calibration([(_biased_stations(rng, d, cells, bias, std), d) for d in days])
    np.testing.assert_array_equal(c.cells, cells)
    np.testing.assert_allclose(c.bias, bias, atol=0.006)
    np.testing.assert_allclose(np.sqrt(c.var), std, rtol=0.1)
    assert list(c.n_readings) == [8 * steps] * 3
    lone = DetectorObservations(np.array([5]), np.full((steps, 1), np.nan))
    lone.values[3] = 0.4  # one reading: no variance, left out
    assert fit_detector_calibration([(lone, days[0])]) is None
    b, v = c.at(np.array([4, 5, 30]), 0.003)  # 5: a station the days did not have
    np.testing.assert_allclose(b, [c.bias[0], 0.0, c.bias[2]])
    np.testing.assert_allclose(v, [c.var[0], 0.003, c.var[2]])


@pytest.mark.parametrize("seed", range(4))
def test_calibrated_stations_beat_the_default_error_model(seed):
    """Stations with a bias of their own: the nowcast with the calibration learned on earlier
    days is closer to the truth than with the default variance and no bias, with and without
    drones."""
    rng = np.random.default_rng(seed)
    shape, steps = (8, 10), 40
    obstacles = np.zeros(shape, bool)
    grid = Grid(obstacles)
    *earlier, today = _days(rng, 10, steps, shape)
    cells = np.sort(rng.choice(80, 10, replace=False))
    bias = rng.uniform(-0.1, 0.1, len(cells))
    std = rng.uniform(0.005, 0.05, len(cells))
    calibration = fit_detector_calibration(
        [(_biased_stations(rng, d, cells, bias, std), d) for d in earlier]
    )
    plain = fit_history(earlier, obstacles)
    calibrated = fit_history(earlier, obstacles, detectors=calibration)
    detectors = _biased_stations(rng, today, cells, bias, std)
    positions = np.stack([rng.integers(0, [8, 10], (2, 2)) for _ in range(steps)])
    for pos in (positions, positions[:, :0]):
        error = {}
        for name, history in (("plain", plain), ("calibrated", calibrated)):
            mean, _ = nowcast(grid, pos, today, history, 1e-3, 0.0, detectors, 3e-3)
            error[name] = error_curve(mean, today, grid, 0.1)[1:].mean()
        assert error["calibrated"] < error["plain"]


def test_a_history_keeps_its_calibration_and_refuses_a_broken_one(tmp_path):
    rng = np.random.default_rng(0)
    obstacles = np.zeros((4, 5), bool)
    calibration = DetectorCalibration(
        np.array([2, 9]), np.array([-0.02, 0.03]), np.array([1e-3, 4e-3]), np.array([40, 38])
    )
    history = fit_history(_days(rng, 3, 6, (4, 5)), obstacles, detectors=calibration)
    path = tmp_path / "h.npz"
    history.save(path)
    back = History.load(path).detectors
    for name in ("cells", "bias", "var", "n_readings"):
        np.testing.assert_allclose(getattr(back, name), getattr(calibration, name))
    assert (
        History.load(_saved(fit_history(_days(rng, 3, 6, (4, 5)), obstacles), tmp_path)).detectors
        is None
    )
    with np.load(path) as data:
        arrays = dict(data)
    for edit, needle in (
        (
            {"detector_cells": np.array([2, 20])},
            r"detector_cells\[1\] = 20 is not a cell index in 0 .. 19",
        ),
        ({"detector_cells": np.array([9, 2])}, "not distinct and sorted"),
        ({"detector_bias": np.array([0.0, np.nan])}, r"detector_bias\[1\] = nan"),
        (
            {"detector_var": np.array([0.0, 1e-3])},
            r"detector_var\[0\] = 0.0 is not a number in \(0, 1\]",
        ),
        ({"detector_n_readings": np.array([1, 3])}, r"detector_n_readings\[0\] = 1"),
        ({"detector_var": np.array([1e-3])}, "not of one length"),
        ({"detector_bias": np.array(["a", "b"])}, "not numbers"),
        ({"detector_var": None}, "without detector_var"),
    ):
        broken = {k: v for k, v in (arrays | edit).items() if v is not None}
        bad = tmp_path / "bad.npz"
        np.savez(bad, **broken)
        with pytest.raises(UserError, match=needle) as info:
            History.load(bad)
        assert "\n" not in str(info.value) and str(bad) in str(info.value)


def _saved(history, folder):
    path = folder / "plain.npz"
    history.save(path)
    return path


# ---------------------------------------------------------------- SUMO: placement, reading
libsumo = pytest.importorskip("libsumo")

from helpers import small_sumo_scenario  # noqa: E402

from twin.cli import main as twin_main  # noqa: E402
from twin.config import load_config  # noqa: E402
from twin.errors import UserError  # noqa: E402
from twin.sumo.detectors import (  # noqa: E402
    DetectorPlan,
    DetectorReader,
    main_edges,
    place_loops,
    scenario_reader,
    station_cells,
)
from twin.sumo.scenario import sumo_source  # noqa: E402
from twin.sumo.session import _libsumo  # noqa: E402


@pytest.fixture(scope="module")
def small(tmp_path_factory) -> Path:
    return small_sumo_scenario(tmp_path_factory.mktemp("small"), horizon=6)


def _with_detectors(small: Path, name: str, text: str) -> Path:
    path = small / name
    path.write_text((small / "small.toml").read_text() + "\n[traffic.detectors]\n" + text)
    return path


def test_virtual_loop_placement_is_deterministic_and_on_roads(small):
    source = sumo_source(load_config(small / "small.toml"))
    g = source.geometry
    edges = main_edges(source.scenario.net_file, g)
    with_edge = np.zeros(source.grid.shape, bool)
    for cell in edges:
        with_edge[cell] = source.grid.free[cell]
    cells = station_cells(g.lane_km, with_edge, 6)
    assert cells == station_cells(g.lane_km, with_edge, 6)
    assert len(set(cells)) == 6
    loops = place_loops(edges, g, cells)
    assert loops == place_loops(main_edges(source.scenario.net_file, g), g, cells)
    import sumolib
    from sumolib.geomhelper import positionAtShapeOffset

    net = sumolib.net.readNet(str(source.scenario.net_file))
    for loop in loops:
        assert source.grid.free[loop.cell] and g.lane_km[loop.cell] > 0
        lane = net.getLane(loop.lane)
        assert lane.allows("passenger") and 0 < loop.pos < lane.getLength()
        shape = lane.getShape()
        shape_len = sum(np.hypot(*np.subtract(b, a)) for a, b in itertools.pairwise(shape))
        x, y = positionAtShapeOffset(shape, loop.pos * shape_len / lane.getLength())
        r, c, inside = g.cell_index(np.array([[x, y]]))
        assert inside[0] and (int(r[0]), int(c[0])) == loop.cell
    # the first station is the cell with the most lane-km; no two stations touch while
    # untouched cells remain
    assert g.lane_km[cells[0]] == g.lane_km[with_edge].max()
    touching = [
        (a, b)
        for n, a in enumerate(cells)
        for b in cells[:n]
        if max(abs(a[0] - b[0]), abs(a[1] - b[1])) <= 1
    ]
    assert not touching


def _additional_with_detectors(small: Path, lane: str, length: float) -> Path:
    path = small / "detectors.add.xml"
    path.write_text(
        "<additional>\n"
        f'  <inductionLoop id="own-loop" lane="{lane}" pos="{length / 2:.1f}" period="60" '
        'file="NUL"/>\n'
        f'  <laneAreaDetector id="own-area" lane="{lane}" pos="10" length="{length - 20:.1f}" '
        'period="60" file="area.xml"/>\n'
        "</additional>\n"
    )
    return path


def test_readings_equal_what_libsumo_reports(small):
    """Twin's loops and the scenario's own loop: each reading's vehicle count equals the distinct
    vehicles libsumo reported on the loop at each SUMO step of the interval; the scenario's
    lane-area detector: its count equals what SUMO writes to the detector's own output."""
    loops = load_config(_with_detectors(small, "det.toml", "virtual_loops = 3\n"))
    lane = sumo_source(loops).scenario.detectors.loops[0].lane
    import sumolib

    length = sumolib.net.readNet(str(small / "small.net.xml")).getLane(lane).getLength()
    _additional_with_detectors(small, lane, length)
    text = (
        (small / "small.toml")
        .read_text()
        .replace("[traffic]", '[traffic]\nadditional = ["detectors.add.xml"]')
    )
    (small / "own.toml").write_text(
        text + "\n[traffic.detectors]\nscenario = true\nvirtual_loops = 3\n"
    )
    source = sumo_source(load_config(small / "own.toml"))
    session = source.session(small / "out-read").start()
    try:
        api = _libsumo()
        reader = scenario_reader(source.scenario, source.geometry, api)
        ids = [d.id for d in reader.detectors]
        assert "own-loop" in ids and "own-area" in ids
        assert len(ids) == 2 + len(source.scenario.detectors.loops)
        own = {d.id: d for d in reader.detectors}
        shape = sumolib.net.readNet(str(small / "small.net.xml")).getLane(lane).getShape()
        shape_len = sum(np.hypot(*np.subtract(b, a)) for a, b in itertools.pairwise(shape))
        xy = sumolib.geomhelper.positionAtShapeOffset(shape, shape_len / 2)
        r, c, _ = source.geometry.cell_index(np.array([xy]))
        assert own["own-loop"].cell == (int(r[0]), int(c[0]))
        loops = [d for d in reader.detectors if d.kind == "loop"]
        seen = {d.id: set() for d in loops}
        t = api.simulation.getTime()
        compared, area = 0, {}
        for _, sample in source.sample_times():
            while t < sample - 1e-9:
                t += 1.0
                api.simulationStep(t)
                for d in loops:
                    seen[d.id] |= set(api.inductionloop.getLastStepVehicleIDs(d.id))
            for n, count, _, _ in reader.read():
                d = reader.detectors[n]
                if d.kind == "loop":
                    assert count == len(seen[d.id]), d.id
                    compared += count
                else:
                    area[round(sample)] = count
            seen = {d.id: set() for d in loops}
        assert compared > 0
    finally:
        session.close()
    import xml.etree.ElementTree as ET

    (written,) = (small / "out-read").rglob("area.xml")
    intervals = {
        round(float(e.get("end"))): int(e.get("nVehSeen"))
        for e in ET.parse(written).iter("interval")
    }
    assert area and sum(area.values()) > 0
    assert all(intervals[t] == count for t, count in area.items())


def test_run_with_detectors_writes_them_and_the_reference_row(small, tmp_path):
    base = tmp_path / "days"
    args = ["--no-ceiling", "--no-report", "--quiet"]
    assert twin_main(["run", "--config", str(small / "small.toml"), "--sumo-seed", "20",
                      "--seeds", "2", "--swarms", "random", *args, "--out", str(base)]) == 0  # fmt: skip
    history = tmp_path / "history.npz"
    assert twin_main(["history", "--from", str(base), "--out", str(history)]) == 0
    config = _with_detectors(small, "loops.toml", "virtual_loops = 3\n")
    out = tmp_path / "eval"
    assert twin_main(["run", "--config", str(config), "--swarms", "random,greedy", *args,
                      "--history", str(history), "--out", str(out)]) == 0  # fmt: skip
    readings = pd.read_parquet(out / "detectors.parquet")
    assert readings["virtual"].all() and readings["detector"].nunique() >= 3
    assert readings["step"].min() == 0 and readings["step"].max() == 6
    assert readings["importance"].between(0, 1).all()
    table = pd.read_csv(out / "belief_models.csv")
    pairs = list(zip(table["swarm"], table["model"], strict=True))
    assert (DETECTORS_ONLY, "nowcast") in pairs
    assert ("random", "nowcast+detectors") in pairs and ("greedy", "nowcast+detectors") in pairs


def test_history_of_days_with_detectors_calibrates_their_stations(small, tmp_path, capsys):
    """`twin history` of runs that read detectors keeps each station cell's bias and variance
    of its readings against the replayed truth; the run with that history filters with them.
    A reading off the grid in detectors.parquet is one line."""
    from twin.cli.history import replay_truth
    from twin.runs import write_manifest

    config = _with_detectors(small, "cal.toml", "virtual_loops = 3\n")
    args = ["--no-ceiling", "--no-report", "--quiet"]
    days = tmp_path / "days"
    assert twin_main(["run", "--config", str(config), "--sumo-seed", "20", "--seeds", "2",
                      "--swarms", "random", *args, "--out", str(days)]) == 0  # fmt: skip
    history = tmp_path / "history.npz"
    assert twin_main(["history", "--from", str(days), "--out", str(history)]) == 0
    assert "detector calibration: " in capsys.readouterr().out
    calibration = History.load(history).detectors
    readings = pd.read_parquet(days / "detectors.parquet")
    residuals = {}
    for seed in (0, 1):
        truth, obstacles, _ = replay_truth(days / "tapes" / f"seed-{seed}.parquet")
        ny = obstacles.shape[1]
        rows = readings[readings["seed"] == seed]
        station = rows.groupby(["step", "i", "j"])["importance"].mean().reset_index()
        for k, i, j, v in station.itertuples(index=False):
            residuals.setdefault(i * ny + j, []).append(v - truth[k, i, j])
    assert list(calibration.cells) == sorted(residuals)
    for c, cell in enumerate(calibration.cells):
        r = np.array(residuals[cell])
        assert calibration.bias[c] == pytest.approx(r.mean())
        assert calibration.var[c] == pytest.approx(max(r.var(ddof=1), 1e-6))
    out = tmp_path / "eval"
    assert twin_main(["run", "--config", str(config), "--swarms", "random", *args,
                      "--history", str(history), "--out", str(out)]) == 0  # fmt: skip
    assert (DETECTORS_ONLY, "nowcast") in set(
        pd.read_csv(out / "belief_models.csv")[["swarm", "model"]].itertuples(index=False)
    )
    for edit, words in READING_EDITS:
        edited = readings.copy()
        edit(edited)
        edited.to_parquet(days / "detectors.parquet", index=False)
        write_manifest(days, False, None)  # a damaged file the manifest agrees with
        capsys.readouterr()
        assert twin_main(["history", "--from", str(days), "--out", str(tmp_path / "h2.npz")]) == 2
        err = capsys.readouterr().err
        assert err.count("\n") == 1 and "Traceback" not in err, err
        assert "detectors.parquet: " in err and words in err, err
        assert not (tmp_path / "h2.npz").exists()


def _all(*edits):
    def edit(frame):
        for one in edits:
            one(frame)

    return edit


def _set_all(column, value):
    def edit(frame):
        frame[column] = value

    return edit


#: Edits of a run's detector readings its read-back refuses (a history would learn the
#: stations' biases from them: probe 12's dt1), and words of the refusal.
READING_EDITS = [
    (lambda f: f.__setitem__("i", f["i"].where(f.index != 3, 99)), "seed 0, step"),
    (
        _set_all("occupancy_pct", 500.0),
        "occupancy_pct = 500, not a share of time in %, 0 .. 100",
    ),
    # a broken reading of a scenario's detector (probe 16's f08) is left out when read;
    # forged, refused
    (_set_all("occupancy_pct", -11.57), "occupancy_pct = -11.57, not a share of time in %"),
    (_set_all("speed", -3.0), "speed = -3, not a speed in m/s"),
    (_set_all("importance", 0.99), "but the MFD in effect at that step"),
    (
        lambda f: f.__setitem__("lane", f["lane"].where(f.index != 0, "elsewhere_0")),
        "has more than one lane among its readings",
    ),
    # a column dropped or added (probe 20's P2-f09e)
    (lambda f: f.__delitem__("virtual"), "lacks the column 'virtual'"),
    (_set_all("bogus", 1.0), "holds a column 'bogus', which twin does not write"),
]


@pytest.mark.parametrize(
    ("text", "needle"),
    [
        ("cells = [[0, 99]]", "off the"),
        ("cells = [[1, 1], [1, 1]]", "listed twice"),
        ("virtual_loops = 10000", "exceeds"),
        ("virtual_loops = 2\ncells = [[1, 1]]", "give one of them"),
    ],
)
def test_bad_detector_settings_are_one_line(small, tmp_path, capsys, text, needle):
    config = _with_detectors(small, "bad.toml", text + "\n")
    out = tmp_path / "out"
    code = twin_main(["run", "--config", str(config), "--quiet", "--no-report", "--out", str(out)])
    err = capsys.readouterr().err
    assert code == 2, err
    assert err.count("\n") == 1 and "Traceback" not in err and needle in err, err
    assert "detectors" in err and str(config) in err, err
    assert not (out / "summary.csv").exists()


def _meso_sumocfg(small: Path, word: str = "true") -> Path:
    """A sumocfg of the small scenario that asks SUMO for its mesoscopic model."""
    path = small / "meso.sumocfg"
    path.write_text(
        '<configuration><input><net-file value="small.net.xml"/><route-files '
        f'value="small.trips.xml"/></input><mesoscopic><mesosim value="{word}"/></mesoscopic>'
        "</configuration>"
    )
    return path


@pytest.mark.parametrize("asked", ["--meso", "the sumocfg's mesosim"])
@pytest.mark.parametrize("text", ["virtual_loops = 3", "scenario = true", "cells = [[1, 1]]"])
def test_detectors_under_the_mesoscopic_model_are_refused(small, tmp_path, capsys, text, asked):
    """SUMO's mesoscopic model has no loops to read: refused before SUMO starts, whether the
    flag or the scenario's sumocfg asks for it."""
    config = _with_detectors(small, "meso.toml", text + "\n")
    out = tmp_path / "out"
    how = ["--meso"] if asked == "--meso" else ["--sumocfg", str(_meso_sumocfg(small))]
    code = twin_main(["run", "--config", str(config), *how, "--quiet", "--no-report",
                      "--out", str(out)])  # fmt: skip
    err = capsys.readouterr().err
    assert code == 2 and err.count("\n") == 1 and "Traceback" not in err, err
    assert "[traffic.detectors] with SUMO's mesoscopic model" in err and str(config) in err, err
    assert not out.exists()


@pytest.mark.parametrize("word", ["true", "t"])
def test_a_sumocfg_that_asks_for_the_mesoscopic_model_is_recorded_so(small, tmp_path, capsys, word):
    """SUMO runs a sumocfg's ``mesosim`` as asked; run.json and the tape say mesoscopic. SUMO
    reads ``t`` as true: it ran mesoscopic, recorded as microscopic (a review against SUMO)."""
    out = tmp_path / "out"
    code = twin_main(["run", "--config", str(small / "small.toml"), "--sumocfg",
                      str(_meso_sumocfg(small, word)), "--swarms", "random", "--no-ceiling", "--quiet",
                      "--no-report", "--out", str(out)])  # fmt: skip
    err = capsys.readouterr().err
    assert code == 0, err
    assert "mesosim" in err and "mesoscopic model, as --meso does" in err, err
    assert json.loads((out / "run.json").read_text())["traffic"]["mesoscopic"] is True


def test_a_cell_without_road_is_refused(small):
    """An obstacle cell (listed in [grid].obstacles here) takes no station."""
    text = (
        (small / "small.toml")
        .read_text()
        .replace("[swarm]", "[grid]\nobstacles = [[2, 2]]\n[swarm]")
    )
    (small / "noroad.toml").write_text(text + "\n[traffic.detectors]\ncells = [[2, 2]]\n")
    with pytest.raises(UserError, match=r"cells\[0\] = \[2, 2\] is an obstacle or has no road"):
        sumo_source(load_config(small / "noroad.toml"))


def test_reader_without_plan_reads_nothing(small):
    source = sumo_source(load_config(small / "small.toml"))
    session = source.session().start()
    try:
        assert (
            DetectorReader(
                DetectorPlan(), source.geometry, _libsumo(), begin=0.0, step_s=60.0
            ).detectors
            == []
        )
    finally:
        session.close()


def test_a_broken_occupancy_reading_is_left_out_with_one_notice(capsys):
    """SUMO's API reads an occupancy far below 0 for a loop with a vehicle on it as the
    interval ends (period 1 s: to -60 %): such readings are left out, with one notice naming
    the detector and the true cause (it was recorded and read back as valid, probe 16's f08; the
    notice blamed a period of whole seconds, probe 19's f06)."""
    from types import SimpleNamespace

    from twin.sumo.detectors import LOOP, Detector, DetectorReader

    values = iter([(1, -11.57, 9.0), (2, 5.0, 8.0), (1, -3.0, 9.0)])

    class Loops:
        def getLastIntervalVehicleNumber(self, _):
            self.now = next(values)
            return self.now[0]

        def getLastIntervalOccupancy(self, _):
            return self.now[1]

        def getLastIntervalMeanSpeed(self, _):
            return self.now[2]

    reader = DetectorReader.__new__(DetectorReader)
    reader.api = SimpleNamespace(
        inductionloop=Loops(), simulation=SimpleNamespace(getTime=lambda: 600.0)
    )
    reader.detectors = [Detector("L3", LOOP, "B0B1_0", (0, 0), False)]
    reader._last, reader._broken, reader._first_end, reader._begin = {}, set(), {"L3": 0}, 0.0
    reader._periods, reader._intervals = {}, {}  # no period: read when its values change
    assert [reader.read(), reader.read(), reader.read()] == [[], [(0, 2, 5.0, 8.0)], []]
    notices = [line for line in capsys.readouterr().err.splitlines() if "L3" in line]
    assert len(notices) == 1 and "occupancy of -11.57 % over its last interval" in notices[0]
    assert "miscounting a vehicle on the loop" in notices[0] and "whole seconds" not in notices[0]
    # twin's own loops (a period of one step) dip below 0 too: kept as 0, without a word
    # (probe 16's P2-f08)
    values = iter([(1, -2.1, 9.0)])
    reader.detectors = [Detector("twin-loop-0-0-0", LOOP, "B0B1_0", (0, 0), True)]
    reader._first_end["twin-loop-0-0-0"] = 0.0
    assert reader.read() == [(0, 1, 0.0, 9.0)]
    assert "twin-loop" not in capsys.readouterr().err


def test_scenario_detectors_asked_of_a_scenario_without_any_say_so(small, tmp_path, capsys):
    """[traffic.detectors] scenario = true over files that give no detector: the run goes on
    with a notice that none is read (it ran silently, detectors.parquet empty; probe 17's
    c54)."""
    config = _with_detectors(small, "none.toml", "scenario = true\n")
    out = tmp_path / "out"
    code = twin_main(["run", "--config", str(config), "--swarms", "random", "--no-ceiling",
                      "--quiet", "--no-report", "--out", str(out)])  # fmt: skip
    err = capsys.readouterr().err
    assert code == 0, err
    assert "scenario = true, but the scenario's files give no induction loop" in err, err


def test_no_reading_before_a_detectors_first_interval_ends(tmp_path, monkeypatch, capsys):
    """SUMO gives zeros for a detector whose first interval has not ended: a loop of period 900
    s read 0 vehicles at step 0, recorded as an empty road and fed to the nowcast (probe 19's
    P2-08). Its period comes from its file (``period``, ``freq``; without one SUMO aggregates
    over the whole simulation: never read, with a notice)."""
    from types import SimpleNamespace

    from twin.sumo.detectors import (
        LOOP,
        Detector,
        DetectorPlan,
        DetectorReader,
        LoopSpec,
        detector_periods,
    )

    add = tmp_path / "det.add.xml"
    add.write_text(
        '<additional><inductionLoop id="L900" lane="a_0" pos="5" period="900" file="o.xml"/>'
        '<e2Detector id="A60" lane="a_0" pos="0" length="50" freq="60" file="o.xml"/>'
        '<inductionLoop id="L1" lane="a_0" pos="9" file="o.xml"/></additional>'
    )
    periods = detector_periods([add])
    assert periods == {"L900": 900.0, "A60": 60.0, "L1": float("inf")}
    now = {"t": 300.0}

    class Domain:
        def getIDList(self):
            return ["twin-loop-0-0-0", "L1"]

        def getLaneID(self, _):
            return "a_0"

        def getPosition(self, _):
            return 9.0

        def getLastIntervalVehicleNumber(self, _):
            return 0

        def getLastIntervalOccupancy(self, _):
            return 0.0

        def getLastIntervalMeanSpeed(self, _):
            return -1.0

    api = SimpleNamespace(inductionloop=Domain(), lanearea=Domain(),
                          simulation=SimpleNamespace(getTime=lambda: now["t"]))  # fmt: skip
    monkeypatch.setattr(DetectorReader, "_cell", lambda *_: (0, 0))
    api.lanearea.getIDList = lambda: []
    plan = DetectorPlan(scenario=True, loops=(LoopSpec("twin-loop-0-0-0", "a_0", 3.0, (0, 0)),))
    capsys.readouterr()
    reader = DetectorReader(plan, None, api, begin=300.0, step_s=30.0, periods=periods)
    said = capsys.readouterr().err
    assert "detector 'L1' gives no period: SUMO aggregates such a detector over the whole" in said
    reader.detectors += [  # the scenario's others, as found on the grid
        Detector("L900", LOOP, "a_0", (0, 0), False),
        Detector("A60", "area", "a_0", (0, 0), False),
    ]
    seen = {}
    for t in (300.0, 330.0, 360.0, 390.0, 1200.0):
        now["t"] = t
        seen[t] = sorted(reader.detectors[n].id for n, *_ in reader.read())
    assert seen[300.0] == []  # SUMO begins: no interval has ended
    assert seen[330.0] == ["twin-loop-0-0-0"]
    assert seen[360.0] == ["A60", "twin-loop-0-0-0"]
    assert seen[390.0] == ["twin-loop-0-0-0"]  # A60's interval of 360 s again: not read twice
    # A60's next interval, though it reads the same zeros: told by its period, not its value
    # (an empty interval after another was dropped as the same one: probe 25's u01); L1: never
    assert seen[1200.0] == ["A60", "L900", "twin-loop-0-0-0"]


def test_a_detector_whose_first_period_outlasts_the_run_is_said_unread(
    tmp_path, monkeypatch, capsys
):
    """A scenario loop of period 100000 s in a run that reads until 00:20: none of its
    intervals ends within the run, so twin reads none of it; a notice says so, as for a loop
    without a period (it was silent: probe 23's f12)."""
    from types import SimpleNamespace

    from twin.sumo.detectors import DetectorPlan, DetectorReader, detector_periods

    add = tmp_path / "det.add.xml"
    add.write_text(
        '<additional><inductionLoop id="L9" lane="a_0" pos="5" period="100000" file="o.xml"/>'
        '<inductionLoop id="L60" lane="a_0" pos="9" period="60" file="o.xml"/></additional>'
    )

    class Domain:
        def getIDList(self):
            return ["L9", "L60"]

        def getLaneID(self, _):
            return "a_0"

        def getPosition(self, _):
            return 5.0

    api = SimpleNamespace(inductionloop=Domain(), lanearea=SimpleNamespace(getIDList=list))
    monkeypatch.setattr(DetectorReader, "_cell", lambda *_: (0, 0))
    capsys.readouterr()
    DetectorReader(DetectorPlan(scenario=True), None, api, begin=0.0, step_s=60.0,
                   periods=detector_periods([add]), end=1200.0)  # fmt: skip
    said = capsys.readouterr().err
    assert "detector 'L9' ends its first period after the run's last read (00:20:00)" in said
    assert "L60" not in said
