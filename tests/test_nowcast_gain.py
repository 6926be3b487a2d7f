"""The nowcast-gain swarm (twin.nowcast_gain): its score by hand, its filter equal to the
nowcast belief model's, collision-free, deterministic, refused without a history."""

import numpy as np
import pytest

from twin.belief import Z90, History, NowcastFilter, fit_history, nowcast
from twin.errors import UserError
from twin.grid import ACTION_DELTAS, Grid
from twin.nowcast_gain import NowcastGainPolicy, information_values
from twin.patrol import random_starts, run_patrol
from twin.policies import SwarmView
from twin.scores import ScoreParams
from twin.swarms import make_policy, needs_history
from twin.traffic.dynamic import DynamicTraffic

PARAMS = ScoreParams()


def flat_history(nx=3, ny=4, horizon=5, mean=0.2, var=4e-4, rho=0.0) -> History:
    shape = (horizon + 1, nx, ny)
    return History(
        np.full(shape, mean), np.full(shape, var), np.full((nx, ny), rho),
        np.zeros((nx, ny), bool), n_runs=3,
    )  # fmt: skip


def view_at(grid, positions, idleness, importance, k=0, horizon=5) -> SwarmView:
    positions = np.asarray(positions)
    return SwarmView(
        k=k,
        horizon=horizon,
        grid=grid,
        positions=positions,
        idleness=idleness,
        importance=importance,
        feasible=grid.feasible_actions(positions),
        params=PARAMS,
    )


def test_score_by_hand():
    """One drone at (1, 1) of a 3 x 4 map, rho = 0, history mean 0.2 everywhere; step 1's
    variance 9e-4 at (0, 2), 4e-4 elsewhere; the drone sees its view at the mean."""
    h = flat_history()
    var = h.var.copy()
    var[1, 0, 2] = 9e-4
    h = History(h.mean, var, h.rho, h.obstacles, 3)
    grid = Grid(np.zeros((3, 4), bool))
    idleness = np.full((3, 4), 0.5)
    policy = NowcastGainPolicy(h, weight=2.0, meas_var=1e-3)
    policy.reset(grid, 1, np.random.default_rng(0))
    scores = policy.scores(view_at(grid, [(1, 1)], idleness, np.full((3, 4), 0.2)))

    # the visit gain: (alpha_T * 0.2 + alpha_I) * (min(1, 0.5 + 0.025) - 0.1 * 0.5)
    gain = (1.0 * 0.2 + 0.5) * (0.525 - 0.05)
    # rho = 0: the prior of step 1 is the history's variance, the sighting's info lasts 1 step
    v_low = min(1.0, 0.2 + Z90 * 0.02) * 4e-4**2 / (4e-4 + 1e-3)
    v_high = min(1.0, 0.2 + Z90 * 0.03) * 9e-4**2 / (9e-4 + 1e-3)
    typical = (11 * v_low + v_high) / 12
    # the view of each reached cell: right -> (1, 2) sees (0, 2); up -> (0, 1) sees (0, 2)
    view_cells = {0: 5, 1: 4, 2: 4, 3: 4, 4: 5}  # cells of Adj(p') on the map
    high = {0: 0, 1: 1, 2: 0, 3: 0, 4: 1}  # of which (0, 2)
    for u in range(5):
        info = ((view_cells[u] - high[u]) * v_low + high[u] * v_high) / (5 * typical)
        assert scores[0, u] == pytest.approx(gain + 2.0 * info, rel=1e-12)
    assert np.argmax(scores[0]) in (1, 4)  # towards the uncertain cell


def test_information_lasts_by_rho_squared():
    """Summed over the steps left: ``sum_{j<L} rho^(2j)``, 1 when rho = 0."""
    one = information_values(np.array([0.5]), np.array([1e-3]), np.array([0.0]), 1e-3, 10)
    assert one[0] == pytest.approx(0.5 * 1e-6 / 2e-3)
    half = information_values(np.array([0.5]), np.array([1e-3]), np.array([0.5]), 1e-3, 3)
    assert half[0] == pytest.approx(one[0] * (1 + 0.25 + 0.0625))


def maps_of(grid, horizon, seed):
    return np.stack(list(DynamicTraffic(grid, horizon, seed=seed).importance_maps()))


def synthetic_case(horizon=30, n=4, seed=0):
    """A 9 x 11 map with a few obstacles, a history of 3 other days, the day to run."""
    rng = np.random.default_rng(seed)
    obstacles = rng.random((9, 11)) < 0.1
    grid = Grid(obstacles)
    history = fit_history([maps_of(grid, horizon, s) for s in (11, 12, 13)], obstacles)
    truth = maps_of(grid, horizon, 0)
    starts = random_starts(grid, n, rng)
    return grid, history, truth, starts


class Recording(NowcastGainPolicy):
    """Keeps its filter's mean and std after each step's sightings."""

    def reset(self, grid, n_drones, rng):
        super().reset(grid, n_drones, rng)
        self.kept = []

    def sight(self, view):
        super().sight(view)
        self.kept.append((self.filter.mean(), self.filter.std()))


def patrol(policy, grid, truth, starts, seed=0):
    from twin.traffic.base import RecordedTraffic

    return run_patrol(RecordedTraffic(grid, truth), {"nowcast-gain": policy}, starts, PARAMS, seed)


def test_its_filter_is_the_nowcast_belief_model():
    grid, history, truth, starts = synthetic_case()
    policy = Recording(history)
    result = patrol(policy, grid, truth, starts)
    mean, std = nowcast(grid, result.positions[0], result.importance, history)
    kept_mean = np.stack([m for m, _ in policy.kept])
    kept_std = np.stack([s for _, s in policy.kept])
    steps = len(kept_mean)  # k = 0 .. T-1: the swarm acts before every move
    assert steps == truth.shape[0] - 1
    np.testing.assert_allclose(kept_mean, mean[:steps], rtol=0, atol=1e-6)
    np.testing.assert_allclose(kept_std, std[:steps], rtol=1e-6)


def test_no_two_drones_on_one_cell_and_feasible():
    grid, history, truth, starts = synthetic_case(n=8, seed=3)
    result = patrol(NowcastGainPolicy(history, weight=5.0), grid, truth, starts, seed=3)
    pos = result.positions[0]
    for k in range(pos.shape[0]):
        flat = pos[k, :, 0] * grid.ny + pos[k, :, 1]
        assert len(np.unique(flat)) == len(flat)
        assert grid.free[pos[k, :, 0], pos[k, :, 1]].all()
    step = np.abs(np.diff(pos, axis=0)).sum(axis=2)
    assert (step <= 1).all()


def test_crowded_scene_uses_the_coordinator():
    """Four drones around the one cell whose idleness has recovered all score it best; the
    coordinator sends one of them there and keeps the cells distinct."""
    grid = Grid(np.zeros((5, 5), bool))
    policy = NowcastGainPolicy(flat_history(5, 5, horizon=5), weight=1.0)
    policy.reset(grid, 4, np.random.default_rng(0))
    positions = np.array([(1, 2), (3, 2), (2, 1), (2, 3)])
    idleness = np.zeros((5, 5))
    idleness[2, 2] = 1.0
    view = view_at(grid, positions, idleness, np.full((5, 5), 0.2))
    scores = policy.scores(view)
    assert (np.argmax(scores, axis=1) == [2, 1, 4, 3]).all()  # each alone would take (2, 2)
    actions = policy.act(view)
    after = positions + ACTION_DELTAS[actions]
    assert len({tuple(p) for p in after}) == 4
    assert (2, 2) in {tuple(p) for p in after}


def test_deterministic_under_the_seed():
    grid, history, truth, starts = synthetic_case()
    a = patrol(NowcastGainPolicy(history), grid, truth, starts, seed=5)
    b = patrol(NowcastGainPolicy(history), grid, truth, starts, seed=5)
    np.testing.assert_array_equal(a.positions, b.positions)
    np.testing.assert_array_equal(a.rewards, b.rewards)


def test_weight_zero_is_visit_gain_on_the_predicted_importance():
    grid, history, truth, starts = synthetic_case()
    policy = NowcastGainPolicy(history, weight=0.0)
    policy.reset(grid, len(starts), np.random.default_rng(0))
    view = view_at(grid, starts, np.ones(grid.shape), truth[0], horizon=history.horizon)
    scores = policy.scores(view)
    f = NowcastFilter(history)
    f.advance(0)
    flat, valid = grid.view_index(starts)
    cells = np.unique(flat[valid])
    cells = cells[grid.free.ravel()[cells]]
    f.observe(cells, truth[0].ravel()[cells])
    mean, _ = f.predicted()
    reached = starts[:, None, :] + ACTION_DELTAS[None]
    inside = grid.is_free(reached)
    at = np.where(inside, reached[..., 0] * grid.ny + reached[..., 1], 0)
    expected = (mean[at] + 0.5) * (1.0 - 0.1)  # I = 1: min(1, 1 + delta) - eta
    np.testing.assert_allclose(scores[inside], expected[inside], rtol=1e-12)


def test_refused_without_a_history_in_one_line():
    assert needs_history("nowcast-gain") and not needs_history("visit-gain")
    with pytest.raises(UserError, match="--history FILE") as exc:
        make_policy("nowcast-gain")
    assert "\n" not in str(exc.value)


def test_a_history_of_another_grid_is_refused():
    policy = NowcastGainPolicy(flat_history(3, 4))
    with pytest.raises(UserError, match="differs from the run's 4 x 4"):
        policy.reset(Grid(np.zeros((4, 4), bool)), 1, np.random.default_rng(0))


@pytest.mark.parametrize("key, value", [("weight", -1.0), ("quantile_z", "x"), ("meas_var", 0.0)])
def test_bad_options_are_refused(key, value):
    with pytest.raises(UserError, match=key):
        NowcastGainPolicy(flat_history(), **{key: value})


def test_belief_maps_of_a_run_and_a_damaged_file(tmp_path):
    """belief_maps of a patrol: the swarm's nowcast at the snapshot steps; the report's reader
    takes it back and refuses a damaged one in one line."""
    from twin.belief import belief_maps
    from twin.report.load import read_belief_maps

    grid, history, truth, starts = synthetic_case()
    result = patrol(NowcastGainPolicy(history), grid, truth, starts)
    maps = belief_maps(result, history)
    mean, std = nowcast(grid, result.positions[0], result.importance, history)
    at = maps["steps"]
    assert at.min() >= 1 and at.max() <= truth.shape[0] - 1
    np.testing.assert_allclose(maps["mean"][0], mean[at].reshape(len(at), *grid.shape), atol=1e-6)
    np.testing.assert_allclose(maps["std"][0], std[at].reshape(len(at), *grid.shape), rtol=1e-6)
    path = tmp_path / "belief_maps.npz"
    np.savez(path, **maps)
    back = read_belief_maps(path, grid.shape)
    assert back["swarms"] == ["nowcast-gain"] and back["known_at"].shape[0] == 1
    with pytest.raises(UserError, match="truth has shape") as exc:
        read_belief_maps(path, (grid.nx + 1, grid.ny))
    assert "\n" not in str(exc.value)
    path.write_bytes(b"PK\x03\x04 not really")
    with pytest.raises(UserError, match=r"not a readable belief_maps\.npz"):
        read_belief_maps(path, grid.shape)


def test_filter_predicts_through_steps_without_sightings():
    history = synthetic_case()[1]
    a, b = NowcastFilter(history), NowcastFilter(history)
    for f in (a, b):
        f.advance(0)
        f.observe(np.array([5, 6]), np.array([0.9, 0.8]))
    a.advance(3)
    for k in (1, 2, 3):
        b.advance(k)
    np.testing.assert_array_equal(a.mean(), b.mean())
    np.testing.assert_array_equal(a.std(), b.std())
    with pytest.raises(ValueError, match="back"):
        a.advance(2)


def test_history_from_the_config_relative_to_it(tmp_path):
    from twin.config import load_config

    flat_history().save(tmp_path / "h.npz")
    (tmp_path / "c.toml").write_text(
        '[swarm_options.nowcast-gain]\nhistory = "h.npz"\nweight = 0.5\n'
    )
    policy = load_config(tmp_path / "c.toml").make_swarm("nowcast-gain")
    assert policy.weight == 0.5 and policy.history.n_runs == 3
    (tmp_path / "d.toml").write_text('[swarm_options.nowcast-gain]\nhistory = "none.npz"\n')
    with pytest.raises(UserError, match=r"none\.npz: no such history file"):
        load_config(tmp_path / "d.toml").make_swarm("nowcast-gain")


def test_a_run_hands_its_sighting_model_to_the_swarm_and_the_belief_table(tmp_path):
    """A tape whose drones see each vehicle with probability 0.7: the run's sighting model (its
    detection probability, lane-km, MFD prior and reads) reaches the swarm's filter and the
    result the belief table scores."""
    from helpers import random_tape

    from twin.belief import SIGHTING_VAR_FLOOR, run_sensing
    from twin.config import load_config
    from twin.experiment import Experiment, run_experiment
    from twin.traffic.tape import TapeTraffic

    tape = random_tape(seed=2, nx=4, ny=5, warmup=2, horizon=6, obstacle=(1, 1))
    tape.settings["detection_p"] = 0.7
    tape.write(tmp_path / "tape.parquet")
    model = TapeTraffic.from_file(tmp_path / "tape.parquet").sighting_model()
    assert model.count_p == 0.7 and model.k_c == 40.0 and model.reads == 1
    np.testing.assert_array_equal(model.lane_km, tape.lane_km.ravel())
    assert (model.variance(np.full(20, 0.5), np.arange(20))[tape.lane_km.ravel() > 0] > (
        100 * SIGHTING_VAR_FLOOR
    )).all()  # fmt: skip

    history = flat_history(4, 5, horizon=6)
    obstacles = np.zeros((4, 5), bool)
    obstacles[1, 1] = True
    # a history of SUMO days (clocked), as a tape's swarm's own history must be
    history = History(history.mean, history.var, history.rho, obstacles, 3, step_s=60.0)
    (tmp_path / "c.toml").write_text("[swarm]\nn_drones = 2\n")
    experiment = Experiment(
        load_config(tmp_path / "c.toml"),
        ["nowcast-gain"],
        [0],
        tape=tmp_path / "tape.parquet",
        swarm_options={"nowcast-gain": {"history": history}},
    )
    out = run_experiment(experiment)
    assert out.policies["nowcast-gain"]["sighting_count_p"] == 0.7
    sighting, recorded = run_sensing(out.results[0])
    assert recorded is None and (sighting.count_p, sighting.reads) == (0.7, 1)
    np.testing.assert_array_equal(sighting.lane_km, model.lane_km)


def test_history_flag_over_a_swarm_option_is_said(tmp_path, capsys):
    """``--history`` replaces a swarm's own ``[swarm_options.<swarm>].history`` of the config:
    said in a notice naming both (probe 20's c32), not silently; a swarm without one is not
    named."""
    import dataclasses

    from twin.cli.recording import hand_history
    from twin.config import load_config
    from twin.experiment import Experiment

    history = dataclasses.replace(flat_history(), path=str(tmp_path / "b.npz"))
    (tmp_path / "c.toml").write_text(
        '[swarm_options.nowcast-gain]\nhistory = "a.npz"\nweight = 0.5\n'
    )
    experiment = Experiment(load_config(tmp_path / "c.toml"), ["nowcast-gain", "random"], [0])
    hand_history(experiment, history)
    err = capsys.readouterr().err
    assert err.count("\n") == 1, err
    assert f"--history {tmp_path / 'b.npz'} replaces [swarm_options.nowcast-gain].history = " in err
    assert "'a.npz'" in err
    assert experiment.swarm_options["nowcast-gain"] == {"history": history}
    (tmp_path / "e.toml").write_text('[swarm_options.nowcast-gain]\nhistory = "b.npz"\n')
    experiment = Experiment(load_config(tmp_path / "e.toml"), ["nowcast-gain"], [0])
    hand_history(experiment, history)  # the same file: nothing replaced
    assert capsys.readouterr().err == ""
    (tmp_path / "d.toml").write_text("[swarm]\nn_drones = 2\n")
    experiment = Experiment(load_config(tmp_path / "d.toml"), ["nowcast-gain"], [0])
    hand_history(experiment, history)
    assert capsys.readouterr().err == ""
