"""Belief models (twin/belief.py): last-seen, history, the nowcast filter, their scores."""

from __future__ import annotations

import json

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from twin.belief import (
    NO_DRONES,
    SIGHTING_VAR_FLOOR,
    VAR_FLOOR,
    History,
    SightingModel,
    belief_scores,
    belief_table,
    fit_history,
    history_belief,
    last_seen,
    nowcast,
    summarize,
)
from twin.errors import UserError
from twin.grid import Grid
from twin.monitoring import belief_error_curve
from twin.patrol import PatrolResult


def days(n, steps=40, nx=4, ny=5, rho=0.9, sd=0.15, seed=0):
    """``n`` days of maps: a shared daily pattern plus AR(1) deviations, clipped to [0, 1]."""
    rng = np.random.default_rng(seed)
    k = np.arange(steps)[:, None, None]
    base = 0.4 + 0.3 * np.sin(k / 8.0 + np.arange(nx)[:, None] + np.arange(ny)[None, :])
    out = []
    for _ in range(n):
        d = np.zeros((steps, nx, ny))
        d[0] = rng.normal(0, sd, (nx, ny))
        for t in range(1, steps):
            d[t] = rho * d[t - 1] + rng.normal(0, sd * np.sqrt(1 - rho**2), (nx, ny))
        out.append(np.clip(base + d, 0.0, 1.0))
    return out


def walk(grid, steps, n_drones, seed):
    """Random positions on free cells (not necessarily adjacent: the filter does not care)."""
    rng = np.random.default_rng(seed)
    free = np.argwhere(grid.free)
    return free[rng.integers(0, len(free), (steps, n_drones))]


def make_result(grid, positions, importance, swarms, truth=None, seed=0) -> PatrolResult:
    n_swarms, steps = positions.shape[:2]
    zeros = np.zeros((n_swarms, steps - 1))
    return PatrolResult(
        swarms=list(swarms),
        grid=grid,
        seed=seed,
        rewards=zeros,
        reward_importance=zeros,
        reward_idleness=zeros,
        reward_paper=zeros,
        coverage=zeros,
        visited_share=zeros,
        positions=np.asarray(positions, dtype=np.int64),
        importance=np.asarray(importance, dtype=np.float32),
        truth=None if truth is None else np.asarray(truth, dtype=np.float32),
    )


def test_last_seen_reproduces_the_monitoring_belief_error_exactly():
    rng = np.random.default_rng(3)
    obstacles = rng.random((5, 6)) < 0.2
    grid = Grid(obstacles)
    steps = 30
    positions = walk(grid, steps, 3, 1)
    observed = rng.random((steps, 5, 6))
    truth = np.clip(observed + rng.normal(0, 0.1, observed.shape), 0, 1)
    mean, std = last_seen(grid, positions, observed)
    expected = belief_error_curve(grid, positions, observed, truth, 0.05)
    from twin.belief import error_curve

    assert np.array_equal(error_curve(mean, truth, grid, 0.05), expected)
    assert np.isnan(std).all()
    assert np.isnan(belief_scores(mean, std, truth, grid)["calibration_90"])


def test_nowcast_beats_history_with_exact_observations():
    earlier = days(6, seed=1)
    history = fit_history(earlier, np.zeros((4, 5), bool))
    today = days(1, seed=99)[0]
    grid = Grid.open(4, 5)
    positions = walk(grid, today.shape[0], 1, 2)
    h_mean, h_std = history_belief(history)
    n_mean, n_std = nowcast(grid, positions, today, history, meas_var=1e-8)
    h = belief_scores(h_mean, h_std, today, grid)
    n = belief_scores(n_mean, n_std, today, grid)
    assert n["belief_error"] < 0.8 * h["belief_error"]
    # a cell in view is known exactly
    flat, valid = grid.view_index(positions[10])
    cells = np.unique(flat[valid])
    assert np.allclose(n_mean[10, cells], today[10].ravel()[cells], atol=1e-4)
    assert (n_std[10, cells] < 1e-3).all()


def test_variance_shrinks_on_observation_and_grows_back_to_the_history_variance():
    grid = Grid.open(1, 9)
    steps = 40
    history = History(
        mean=np.full((steps, 1, 9), 0.3),
        var=np.full((steps, 1, 9), 0.04),
        rho=np.full((1, 9), 0.8),
        obstacles=np.zeros((1, 9), bool),
        n_runs=5,
    )
    positions = np.zeros((steps, 1, 2), np.int64)  # the drone sees cells 0, 1 ...
    positions[5] = [0, 7]  # ... but cells 6, 7, 8 at step 5 only
    observed = np.full((steps, 1, 9), 0.9)
    mean, std = nowcast(grid, positions, observed, history, meas_var=1e-3)
    far = 8
    assert std[4, far] == pytest.approx(0.2)  # the prior: the history's std
    assert std[5, far] < 0.05  # observed
    assert mean[5, far] > 0.85
    later = std[5:, far]
    assert (np.diff(later) > 0).all()  # grows back ...
    assert later[-1] == pytest.approx(0.2, abs=1e-3)  # ... towards the history's std
    assert mean[-1, far] == pytest.approx(0.3, abs=1e-3)  # and the mean to the history's
    assert mean[5 + 1, far] == pytest.approx(0.3 + 0.8 * (mean[5, far] - 0.3))


def test_fit_history_recovers_the_autocorrelation_and_variance():
    maps = days(30, steps=120, nx=3, ny=3, rho=0.85, sd=0.1, seed=4)
    history = fit_history(maps, np.zeros((3, 3), bool))
    assert history.n_runs == 30 and history.horizon == 119
    assert np.median(history.rho) == pytest.approx(0.85, abs=0.05)
    assert np.median(history.var) == pytest.approx(0.01, rel=0.3)
    single = fit_history(maps[:1], np.zeros((3, 3), bool))
    assert (single.var == 0).all()


def test_history_file_roundtrip_and_mismatches(tmp_path):
    obstacles = np.zeros((4, 5), bool)
    obstacles[0, 0] = True
    history = fit_history(days(3), obstacles, 75.0, "07:00:00", (100, 101, 102), ["a", "b", "c"])
    path = tmp_path / "history.npz"
    history.save(path)
    back = History.load(path)
    assert np.allclose(back.mean, history.mean, atol=1e-6)
    assert back.traffic_seeds == (100, 101, 102) and back.step_s == 75.0 and back.n_runs == 3
    back.check_matches(path, obstacles, 39, 75.0, "07:00:00", (0, 1))
    cases = [
        ((np.zeros((4, 6), bool), 39, 75.0, None, ()), "grid 4 x 5 differs"),
        ((np.zeros((4, 5), bool), 39, 75.0, None, ()), "obstacles differ"),
        ((obstacles, 20, 75.0, None, ()), "horizon T = 39 differs from the run's T = 20"),
        ((obstacles, 39, 60.0, None, ()), "step 75 s differs"),
        ((obstacles, 39, 75.0, "08:00:00", ()), "starts at 07:00:00"),
        ((obstacles, 39, 75.0, None, (101,)), "traffic seed 101"),
    ]
    for args, text in cases:
        with pytest.raises(UserError, match=text) as info:
            back.check_matches(path, *args)
        assert str(path) in str(info.value) and "\n" not in str(info.value)
    (tmp_path / "bad.npz").write_bytes(b"not a zip")
    with pytest.raises(UserError, match="not a readable"):
        History.load(tmp_path / "bad.npz")
    with pytest.raises(UserError, match="no such history"):
        History.load(tmp_path / "missing.npz")
    with np.load(path) as data:
        arrays = dict(data)
    info = json.loads(str(arrays["info"]))
    for seeds in ("missing", None, [100, "101"], [100.0], [True], "100"):
        edited = {k: v for k, v in info.items() if k != "traffic_seeds"}
        if seeds != "missing":
            edited["traffic_seeds"] = seeds
        np.savez(tmp_path / "seeds.npz", **(arrays | {"info": np.array(json.dumps(edited))}))
        with pytest.raises(UserError, match=r"traffic_seeds = .* is not a list of the SUMO seeds"):
            History.load(tmp_path / "seeds.npz")


def test_belief_table_has_every_swarm_and_model_and_the_history_row():
    maps = days(4, steps=20)
    grid = Grid.open(4, 5)
    history = fit_history(maps[:3], grid.obstacles)
    positions = np.stack([walk(grid, 20, 2, s) for s in (0, 1)])
    result = make_result(grid, positions, maps[3], ["a", "b"], seed=7)
    table = belief_table(result, history, step_s=60.0)
    assert list(zip(table["swarm"], table["model"], strict=True)) == [
        (NO_DRONES, "history"),
        ("a", "last-seen"),
        ("a", "nowcast"),
        ("b", "last-seen"),
        ("b", "nowcast"),
    ]
    assert (table["seed"] == 7).all()
    assert table["events"].nunique() == 1
    assert table.loc[table["model"] == "last-seen", "calibration_90"].isna().all()
    assert table.loc[table["model"] != "last-seen", "calibration_90"].between(0, 1).all()
    assert (table["latency_median_min"].dropna() >= 0).all()
    summary = summarize(table)
    assert len(summary) == 5 and (summary["n_seeds"] == 1).all()
    spatial = belief_table(result, history, step_s=60.0, spatial=True)
    assert spatial["model"].tolist().count("nowcast-spatial") == 2


def test_false_alarms_count_onset_runs_per_hour():
    grid = Grid.open(1, 2)
    truth = np.zeros((6, 1, 2))
    mean = np.zeros((6, 2))
    mean[[1, 2, 4], 0] = 0.9  # two runs on cell 0
    mean[3, 1] = 0.7  # one on cell 1
    row = belief_scores(mean, np.zeros_like(mean), truth, grid, step_s=600.0)
    assert row["false_alarms"] == 3
    assert row["false_alarms_per_hour"] == pytest.approx(3.0)  # 6 steps of 10 min
    assert row["events"] == 0 and np.isnan(row["pct_events_known"])


def test_events_known_and_latency():
    grid = Grid.open(1, 3)
    truth = np.zeros((8, 1, 3))
    truth[2:6, 0, 2] = 0.8  # one event, onset 2, 4 steps
    mean = np.zeros((8, 3))
    mean[4:, 2] = 0.6  # known from step 4
    row = belief_scores(mean, np.zeros_like(mean), truth, grid)
    assert row["events"] == 1 and row["pct_events_known"] == 100.0
    assert row["latency_median_steps"] == 2.0
    assert row["false_alarms"] == 1  # steps 6, 7 after the event: one onset


@settings(max_examples=40, deadline=None)
@given(
    st.integers(1, 4),
    st.integers(1, 5),
    st.integers(2, 12),
    st.integers(1, 3),
    st.integers(0, 10_000),
    st.floats(1e-6, 0.1),
)
def test_beliefs_stay_in_range(nx, ny, steps, n_days, seed, meas_var):
    rng = np.random.default_rng(seed)
    obstacles = rng.random((nx, ny)) < 0.3
    obstacles.flat[0] = False
    grid = Grid(obstacles)
    maps = [rng.random((steps, nx, ny)) ** 3 for _ in range(n_days)]
    history = fit_history(maps, obstacles)
    assert ((history.rho >= 0) & (history.rho <= 1)).all()
    truth = rng.random((steps, nx, ny))
    positions = walk(grid, steps, 2, seed)
    for mean, std in (
        history_belief(history),
        nowcast(grid, positions, truth, history, meas_var),
    ):
        assert ((mean >= 0) & (mean <= 1)).all()
        assert (std >= 0).all() and (std >= np.sqrt(VAR_FLOOR) * 0).all()
        row = belief_scores(mean, std, truth, grid, step_s=75.0)
        assert 0.0 <= row["calibration_90"] <= 1.0
        assert row["belief_error"] >= 0
        known = row["pct_events_known"]
        assert np.isnan(known) or 0 <= known <= 100


def test_spatial_coupling_moves_unobserved_neighbours_only():
    grid = Grid.open(1, 9)
    steps = 5
    history = History(
        mean=np.full((steps, 1, 9), 0.3),
        var=np.full((steps, 1, 9), 0.04),
        rho=np.full((1, 9), 0.8),
        obstacles=np.zeros((1, 9), bool),
        n_runs=5,
        neighbour_corr=0.6,
    )
    positions = np.zeros((steps, 1, 2), np.int64)  # sees cells 0, 1; cell 2 is a neighbour
    observed = np.full((steps, 1, 9), 0.9)
    plain, plain_std = nowcast(grid, positions, observed, history)
    coupled, coupled_std = nowcast(grid, positions, observed, history, coupling=0.6)
    assert np.array_equal(plain[:, :2], coupled[:, :2])  # observed cells: unchanged
    assert (coupled[:, 2] > plain[:, 2] + 0.05).all()  # the neighbour leans to the sighting
    assert (coupled_std[:, 2] < plain_std[:, 2]).all()
    assert np.array_equal(plain[:, 3:], coupled[:, 3:])  # farther cells: untouched
    assert nowcast(grid, positions, observed, history, coupling=0.0)[0].tolist() == plain.tolist()


def test_fit_history_neighbour_correlation():
    rng = np.random.default_rng(0)
    shared = rng.normal(0, 0.1, (20, 30, 1, 1))  # one deviation for the whole map per day-step
    maps = list(np.clip(0.5 + shared + rng.normal(0, 0.02, (20, 30, 3, 3)), 0, 1))
    assert fit_history(maps, np.zeros((3, 3), bool)).neighbour_corr > 0.9
    independent = list(rng.random((20, 30, 3, 3)))
    assert fit_history(independent, np.zeros((3, 3), bool)).neighbour_corr < 0.1


def scenario_history(steps, nx=1, ny=9, var=1.7e-4, rho=0.1):
    """A flat history with the default scenario's typical variance per cell and step."""
    return History(
        mean=np.full((steps, nx, ny), 0.1),
        var=np.full((steps, nx, ny), var),
        rho=np.full((nx, ny), rho),
        obstacles=np.zeros((nx, ny), bool),
        n_runs=3,
    )


def test_an_exact_sighting_collapses_the_uncertainty_of_the_seen_cell():
    """By default a drone counts every vehicle of a cell: it reads the true importance, and the
    nowcast of the cells it sees is that reading, with a std of the numeric floor."""
    grid = Grid.open(1, 9)
    steps = 6
    history = scenario_history(steps)
    positions = np.zeros((steps, 1, 2), np.int64)  # sees cells 0 and 1 at every step
    observed = np.random.default_rng(0).uniform(0.0, 0.9, (steps, 1, 9))
    mean, std = nowcast(grid, positions, observed, history)
    seen, unseen = [0, 1], [4, 8]
    innovation = np.abs(observed[:, 0, seen] - 0.1)
    assert (np.abs(mean[:, seen] - observed[:, 0, seen]) <= 0.01 * innovation + 1e-12).all()
    assert (std[:, seen] <= np.sqrt(SIGHTING_VAR_FLOOR)).all()
    assert np.allclose(std[:, unseen], np.sqrt(1.7e-4)) and np.allclose(mean[:, unseen], 0.1)
    # the variance 1e-3 the filter used before: a first sighting moves it ~15% of the way
    old, _ = nowcast(grid, positions, observed, history, meas_var=1e-3)
    assert (np.abs(old[0, seen] - 0.1) < 0.2 * innovation[0]).all()


def test_a_thinned_count_has_the_binomial_variance_and_keeps_some_uncertainty():
    """Each vehicle seen with probability p: the importance the count gives varies as the
    sighting model says (Monte Carlo of the MFD observation model's thinning), and one sighting
    leaves the seen cell part of its uncertainty."""
    from twin.mfd import MFD, density_from_counts

    p, reads, lane_km = 0.6, 3, 1.2
    model = SightingModel(p, np.full(9, lane_km), MFD().k_c, reads)
    rng = np.random.default_rng(1)
    for vehicles in (40, 120, 300):  # vehicle-instants over the reads
        true = MFD().importance(density_from_counts(vehicles, lane_km, reads))
        seen = rng.binomial(vehicles, p, 100_000)
        sampled = MFD().importance(density_from_counts(seen, lane_km, p * reads))
        stated = model.variance(np.array([true]), np.array([0]))[0] - SIGHTING_VAR_FLOOR
        assert stated == pytest.approx(sampled.var(), rel=0.1)
    assert SightingModel().variance(np.array([0.3]), np.array([0]))[0] == SIGHTING_VAR_FLOOR

    grid = Grid.open(1, 9)
    steps = 3
    history = scenario_history(steps, var=0.01)
    positions = np.zeros((steps, 1, 2), np.int64)
    observed = np.full((steps, 1, 9), 0.5)
    _, exact = nowcast(grid, positions, observed, history)
    _, thinned = nowcast(grid, positions, observed, history, sighting=model)
    stated = model.variance(np.array([0.5]), np.array([0]))[0]
    assert stated > 100 * SIGHTING_VAR_FLOOR
    assert (thinned[1:, :2] > 10 * exact[1:, :2]).all()  # some uncertainty kept ...
    assert (thinned[1:, :2] < 0.5 * np.sqrt(0.01)).all()  # ... less than the prior's
    with pytest.raises(ValueError, match="lane_km"):
        SightingModel(0.5)


def test_a_sighting_lost_to_a_fault_updates_nothing():
    """A sighting the faults did not record is no measurement; the belief table scores what
    was recorded, and its last-seen belief is monitoring's."""
    from twin.faults import FaultPlan

    grid = Grid.open(1, 9)
    steps = 5
    history = scenario_history(steps)
    positions = np.zeros((steps, 1, 2), np.int64)
    observed = np.full((steps, 1, 9), 0.6)
    recorded = np.ones((steps, 1, 5), bool)
    recorded[3] = False  # nothing recorded at step 3
    mean, std = nowcast(grid, positions, observed, history, recorded=recorded)
    rho2 = 0.1**2
    prior = np.sqrt(rho2 * std[2, 0] ** 2 + (1 - rho2) * 1.7e-4)
    assert std[3, 0] == pytest.approx(prior) and std[3, 0] > 10 * std[2, 0]
    assert mean[3, 0] == pytest.approx(0.1 + 0.1 * (mean[2, 0] - 0.1))
    assert std[4, 0] <= np.sqrt(SIGHTING_VAR_FLOOR)

    rng = np.random.default_rng(5)
    maps = days(4, steps=30)
    grid = Grid.open(4, 5)
    history = fit_history(maps[:3], grid.obstacles)
    positions = walk(grid, 30, 2, 3)[None]
    result = make_result(grid, positions, maps[3], ["a"], seed=int(rng.integers(100)))
    result.faults = FaultPlan(detection_p=0.4)
    kept = result.faults.recorded(result.seed, 30, 2)
    table = belief_table(result, history).set_index("model")
    expected = belief_error_curve(grid, positions[0], maps[3], maps[3], 0.05, kept)[1:].mean()
    assert table.loc["last-seen", "belief_error"] == pytest.approx(expected)
    mean, std = nowcast(grid, positions[0], maps[3], history, recorded=kept)
    assert table.loc["nowcast", "belief_error"] == pytest.approx(
        belief_scores(mean, std, maps[3], grid)["belief_error"]
    )
    result.faults = None
    assert (
        belief_table(result, history).set_index("model").loc["nowcast", "belief_error"]
        < (table.loc["nowcast", "belief_error"])
    )


def test_a_history_file_missing_an_array_names_it(tmp_path):
    """A history .npz without its ``rho`` array: one line naming the array (numpy's own
    words were pasted inside quotes: probe 24's f07)."""
    from twin.errors import UserError

    path = tmp_path / "h.npz"
    np.savez(path, mean=np.zeros((2, 2, 2)), var=np.zeros((2, 2, 2)),
             obstacles=np.zeros((2, 2), bool), info=np.array("{}"))  # fmt: skip
    with pytest.raises(UserError, match=r"h\.npz: not a twin history \(no array 'rho'\)"):
        History.load(path)
