"""Scripted faults (``[faults]``, twin/faults.py): lost drones, the coordinator down, missed
sightings; their validation, the fault-free twin, the degradation table and the report."""

from __future__ import annotations

import hashlib
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from twin.config import load_config
from twin.faults import DroneLoss, FaultPlan, LiveDrones
from twin.grid import Grid
from twin.patrol import run_patrol
from twin.policies import Policy
from twin.scores import ScoreParams, initial_idleness, reward_parts, update_idleness
from twin.swarms import make_policy
from twin.traffic.base import RecordedTraffic

ROOT = Path(__file__).resolve().parents[1]
DATA = ROOT / "tests" / "data"
CLASSICAL = ["random", "greedy", "sweeping", "greedy-coordinated", "visit-gain", "lookahead",
             "tours"]  # fmt: skip
PARAMS = ScoreParams()


class Spy(Policy):
    """A swarm that records what its policy is shown at each step."""

    def __init__(self, inner: Policy) -> None:
        self.inner, self.name, self.seen = inner, inner.name, {}

    def reset(self, grid, n_drones, rng):
        super().reset(grid, n_drones, rng)
        self.inner.reset(grid, n_drones, rng)

    def act(self, view):
        self.seen[view.k] = view.positions.copy()
        return self.inner.act(view)

    def learn(self, transition):
        self.inner.learn(transition)

    def drones_changed(self, before, after):
        super().drones_changed(before, after)
        self.inner.drones_changed(before, after)

    def __setattr__(self, key, value):  # coordinator outages reach the policy spied on
        if key == "outages":
            self.inner.outages = value
        object.__setattr__(self, key, value)


def float32_maps(nx: int, ny: int, horizon: int, seed: int) -> np.ndarray:
    """Importance maps exactly representable in float32 (the run records them so)."""
    rng = np.random.default_rng(seed)
    return rng.random((horizon + 1, nx, ny)).astype(np.float32).astype(np.float64)


@st.composite
def fault_plans(draw):
    n = draw(st.integers(2, 5))
    horizon = draw(st.integers(6, 24))
    losses, used = [], {}
    for _ in range(draw(st.integers(1, 4))):
        d = draw(st.integers(0, n - 1))
        step = draw(st.integers(1, horizon - 1))
        back = draw(st.none() | st.integers(step + 1, horizon + 2))
        stop = horizon + 10 if back is None else back
        if any(step < b and a < stop for a, b in used.get(d, [])):
            continue  # one drone, overlapping windows: refused by the config
        used.setdefault(d, []).append((step, stop))
        losses.append(DroneLoss(d, step, back))
    down = ()
    if draw(st.booleans()):
        a = draw(st.integers(0, horizon - 1))
        down = ((a, draw(st.integers(a + 1, horizon))),)
    p = draw(st.sampled_from([1.0, 0.7]))
    plan = FaultPlan(tuple(losses), down, p)
    if not plan.live_steps(horizon + 1, n).any(axis=1).all():
        plan = FaultPlan(tuple(losses[:-1]) or (), down, p) if len(losses) > 1 else FaultPlan()
        if not plan.live_steps(horizon + 1, n).any(axis=1).all():
            plan = FaultPlan((), down, p)
    return n, horizon, plan


@settings(max_examples=40, deadline=None)
@given(fault_plans(), st.sampled_from(CLASSICAL), st.integers(0, 2**16))
def test_lost_drones_never_move_see_or_score_and_are_never_planned_for(case, swarm, seed):
    n, horizon, plan = case
    obstacles = np.zeros((5, 6), dtype=bool)
    obstacles[2, 2] = True
    grid = Grid(obstacles)
    maps = float32_maps(5, 6, horizon, seed)
    starts = grid.free_cells()[np.random.default_rng(seed).choice(grid.n_free, n, replace=False)]
    spy = Spy(make_policy(swarm))
    result = run_patrol(RecordedTraffic(grid, maps), {swarm: spy}, starts, PARAMS, seed,
                        faults=plan)  # fmt: skip
    pos = result.positions[0]
    live = plan.live_steps(horizon + 1, n)
    for k in range(horizon):
        lost = ~live[k]
        assert (pos[k + 1][lost] == pos[k][lost]).all(), f"a lost drone moved at step {k}"
        # the policy and its coordinator saw the live drones alone, in their order
        assert np.array_equal(spy.seen[k], pos[k][live[k]])
    # every step's score is the visit gains of the recorded arrivals alone (Def. 3, Def. 4)
    recorded = plan.recorded(seed, horizon + 1, n)
    idle = initial_idleness(grid)
    for k in range(horizon):
        rec = np.ones(n, bool) if recorded is None else recorded[k + 1, :, 0]
        assert not rec[~live[k]].any(), "a drone lost at step k is paid for its arrival"
        expected = reward_parts(grid, PARAMS, idle, maps[k], maps[k + 1], pos[k][rec],
                                pos[k + 1][rec]).total.sum() if rec.any() else 0.0  # fmt: skip
        assert result.rewards[0, k] == pytest.approx(expected, abs=1e-12)
        idle = update_idleness(idle, pos[k + 1][rec], grid, PARAMS.eta, PARAMS.delta)


def test_a_drone_back_resumes_from_where_it_was_lost_and_moves_again():
    grid = Grid(np.zeros((6, 6), dtype=bool))
    maps = float32_maps(6, 6, 30, 1)
    plan = FaultPlan((DroneLoss(0, 5, 15),))
    starts = np.array([[0, 0], [5, 5]])
    result = run_patrol(RecordedTraffic(grid, maps), {"random": make_policy("random")}, starts,
                        PARAMS, 3, faults=plan)  # fmt: skip
    pos = result.positions[0, :, 0]
    assert (pos[5:16] == pos[5]).all()
    assert (pos[16:] != pos[15]).any(axis=1).any()


def test_the_coordinator_down_leaves_collisions_unresolved_and_is_up_again_after():
    # two drones side by side in a corridor, both wanting the same cell; the coordinator keeps
    # them apart (distinct cells) while it is up; down, each takes its own best move
    grid = Grid(np.zeros((1, 3), dtype=bool))
    maps = np.zeros((11, 1, 3))
    maps[:, 0, 1] = 1.0
    starts = np.array([[0, 0], [0, 2]])
    shared = {}
    for name, plan in (("up", FaultPlan()), ("down", FaultPlan((), ((0, 10),)))):
        result = run_patrol(RecordedTraffic(grid, maps), {"visit-gain": make_policy("visit-gain")},
                            starts, PARAMS, 0, faults=plan)  # fmt: skip
        pos = result.positions[0]
        shared[name] = any((pos[k, 0] == pos[k, 1]).all() for k in range(1, len(pos)))
    assert not shared["up"] and shared["down"]


@pytest.mark.slow
def test_learned_swarms_run_with_drones_lost_back_and_the_coordinator_down():
    pytest.importorskip("torch")
    grid = Grid(np.zeros((6, 8), dtype=bool))
    maps = float32_maps(6, 8, 40, 2)
    plan = FaultPlan((DroneLoss(1, 10, 25), DroneLoss(2, 12)), ((15, 20),), 0.8)
    starts = np.array([[0, 0], [5, 7], [2, 3], [4, 1]])
    swarms = {name: make_policy(name) for name in ("rl", "rl-online", "rl-decentralized")}
    result = run_patrol(RecordedTraffic(grid, maps), swarms, starts, PARAMS, 0, faults=plan)
    live = plan.live_steps(41, 4)
    for s in range(3):
        pos = result.positions[s]
        for k in range(40):
            assert (pos[k + 1][~live[k]] == pos[k][~live[k]]).all()
    assert swarms["rl"].outages == ((15, 20),)


@pytest.mark.parametrize("losses", [(), (DroneLoss(1, 6, 14),)])
def test_the_learned_swarms_map_misses_the_sightings_the_swarm_missed(losses):
    pytest.importorskip("torch")
    grid = Grid(np.zeros((5, 6), dtype=bool))
    maps = float32_maps(5, 6, 20, 3)
    policy = make_policy("rl")
    checked = []
    act = policy.act

    def checking_act(view):
        actions = act(view)
        assert np.array_equal(policy.maps.shared, view.idleness)  # the swarm's own map
        checked.append(view.k)
        return actions

    policy.act = checking_act
    plan = FaultPlan(losses, (), 0.5)
    starts = np.array([[0, 0], [4, 5], [2, 2]])
    run_patrol(RecordedTraffic(grid, maps), {"rl": policy}, starts, PARAMS, 1, faults=plan)
    assert checked == list(range(20))


def test_the_fault_free_twin_is_the_same_swarm_run_without_faults():
    config = load_config(DATA / "regression-small.toml")
    grid = Grid(np.zeros((8, 10), dtype=bool))
    maps = float32_maps(8, 10, 40, 5)
    starts = np.array([[0, 0], [7, 9], [3, 3], [5, 1]])
    plan = FaultPlan((DroneLoss(1, 10),))
    faulted = run_patrol(RecordedTraffic(grid, maps), {n: make_policy(n) for n in CLASSICAL},
                         starts, config.params, 4, faults=plan,
                         fault_free={n: make_policy(n) for n in CLASSICAL})  # fmt: skip
    plain = run_patrol(RecordedTraffic(grid, maps), {n: make_policy(n) for n in CLASSICAL},
                       starts, config.params, 4)  # fmt: skip
    twin = faulted.fault_free
    assert twin.swarms == plain.swarms == faulted.swarms
    assert np.array_equal(twin.positions, plain.positions)
    assert np.array_equal(twin.rewards, plain.rewards)
    assert not np.array_equal(faulted.rewards, plain.rewards)
    # before the loss at step 10 the swarms are their twins: the moves of steps 0..9 count
    assert np.array_equal(faulted.rewards[:, :10], plain.rewards[:, :10])
    assert np.array_equal(faulted.positions[:, :11], plain.positions[:, :11])


# ------------------------------------------------------------------------------ regression
def run_hashes(config_path: Path, swarms: list[str]) -> dict[str, str]:
    from twin.experiment import Experiment, run_experiment

    out = run_experiment(Experiment(load_config(config_path), swarms, [0, 1]))
    hashes = {}
    for r in out.results:
        assert r.fault_free is None
        for s, name in enumerate(r.swarms):
            h = hashlib.sha256()
            for arr in (r.rewards[s], r.positions[s], r.coverage[s], r.visited_share[s]):
                h.update(np.ascontiguousarray(arr).tobytes())
            hashes[f"{r.seed}/{name}"] = h.hexdigest()
    return hashes


@pytest.mark.parametrize(
    ("faults", "swarms"),
    [
        ("[faults]\n", CLASSICAL),
        ("[faults]\ndetection_p = 1.0\ncoordinator_down = []\ndrone_loss = []\n", CLASSICAL),
        pytest.param("[faults]\n", ["rl", "rl-online"], marks=pytest.mark.slow),
    ],
)
def test_a_fault_free_faults_table_changes_nothing(tmp_path, faults, swarms):
    # rewards, positions, coverage and visited share of every swarm, byte for byte, as with no
    # [faults] table at all (that the fault machinery leaves the swarms' moves alone is the
    # twin test above: a faulted run's fault-free twin equals the plain run)
    path = tmp_path / "scenario.toml"
    path.write_text((DATA / "regression-small.toml").read_text() + faults)
    assert run_hashes(path, swarms) == run_hashes(DATA / "regression-small.toml", swarms)


# ------------------------------------------------------------------------------ bad configs
SMALL = """
[grid]
nx = 6
ny = 6
[swarm]
n_drones = 3
[traffic]
kind = "synthetic"
horizon = 40
disturbances = [{ kind = "big", i = 2, j = 2, amplitude = 1.0, sigma = 2.0 }]
"""


@pytest.mark.parametrize(
    ("faults", "message"),
    [
        ("drone_loss = [{ drone = 3, step = 5 }]",
         "[faults].drone_loss[0].drone = 3 is not one of the 3 drones; give 0 .. 2"),
        ("drone_loss = [{ drone = 0, step = 40 }]",
         "[faults].drone_loss[0].step = 40 is outside the horizon T = 40; give 1 .. 39"),
        ("drone_loss = [{ drone = 0, step = 5, back = 41 }]",
         "[faults].drone_loss[0].back = 41 is outside the horizon"),
        ("drone_loss = [{ drone = 0, step = 0 }]", "[faults].drone_loss[0].step = 0 must be >= 1"),
        ("drone_loss = [{ drone = 0, step = 9, back = 9 }]",
         "[faults].drone_loss[0].back = 9 must come after step = 9"),
        ("drone_loss = [{ drone = 1, step = 5, back = 20 }, { drone = 1, step = 10 }]",
         "[faults].drone_loss[0] and [1] lose drone 1 in overlapping windows"),
        ("drone_loss = [{ drone = 0, step = 5 }, { drone = 1, step = 5 }, { drone = 2, step = 6 }]",
         "[faults].drone_loss leaves no drone flying at step 6"),
        ("drone_loss = [{ drone = 0 }]", "[faults].drone_loss[0].step is missing"),
        ('drone_loss = [{ drone = "0", step = 3 }]', "drone = '0' must be a whole number"),
        ("detection_p = 0.0", "[faults].detection_p = 0.0 must be > 0"),
        ("detection_p = 1.2", "[faults].detection_p = 1.2 must be <= 1"),
        ("coordinator_down = [[9, 3]]", "[faults].coordinator_down has [9, 3]; give windows"),
        (  # one outage split into phases of one state (probe 19's f11)
            "coordinator_down = [[7, 10], [5, 8]]",
            "[faults].coordinator_down has [5, 8] and [7, 10], which overlap; give one window "
            "[5, 10], or separate them",
        ),
        ("coordinator_down = [[30, 50]]", "[faults].coordinator_down has [30, 50] past the horizon"),
        ("lost = 1", "[faults].lost is not a known key; use one of: drone_loss"),
    ],
)  # fmt: skip
def test_bad_fault_configs_are_one_line_refusals(tmp_path, capsys, faults, message):
    from twin.cli import main

    path = tmp_path / "bad.toml"
    path.write_text(SMALL + "[faults]\n" + faults + "\n")
    code = main(["evaluate", "--config", str(path), "--out", str(tmp_path / "out")])
    err = capsys.readouterr().err.strip()
    assert code == 2
    assert len(err.splitlines()) == 1 and message in err and "bad.toml" in err, err
    assert not (tmp_path / "out").exists()


def test_outages_given_twice_are_refused(tmp_path, capsys):
    from twin.cli import main

    path = tmp_path / "bad.toml"
    path.write_text(SMALL + "[swarm_options.rl]\noutages = [[1, 3]]\n[faults]\n"
                    "coordinator_down = [[5, 9]]\n")  # fmt: skip
    assert main(["evaluate", "--config", str(path), "--out", str(tmp_path / "out")]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "keep [faults].coordinator_down alone" in err


# ------------------------------------------------------------------------------ run folder
@pytest.mark.slow
def test_evaluate_with_faults_writes_the_degradation_table_and_the_report(tmp_path):
    from twin.cli import main
    from twin.report.load import load_run

    path = tmp_path / "faults.toml"
    path.write_text(SMALL + "[faults]\ndrone_loss = [{ drone = 1, step = 10 }, "
                    "{ drone = 2, step = 10, back = 25 }]\ndetection_p = 0.9\n")  # fmt: skip
    out = tmp_path / "run"
    code = main(["evaluate", "--config", str(path), "--out", str(out), "--seeds", "2",
                 "--swarms", "random,greedy,visit-gain,tours", "--ceiling", "--quiet"])  # fmt: skip
    assert code == 0
    rf = load_run(out)
    deg = rf.degradation
    assert list(deg["label"].unique()) == [
        "no drone lost, sightings at p = 0.9", "2 of 3 drones lost, sightings at p = 0.9",
        "1 of 3 drones lost, sightings at p = 0.9", "whole run",
    ]  # fmt: skip
    assert len(deg) == 2 * 4 * 4
    # lost drones cost score while they are lost (a swarm of one drone against three)
    lost = deg[deg["label"] == "2 of 3 drones lost, sightings at p = 0.9"]
    assert (lost["R_hat"] < lost["R_hat_fault_free"]).all()
    assert rf.run["faults"]["detection_p"] == 0.9
    md = (out / "report" / "report.md").read_text()
    assert "Faults: degradation against the fault-free twin" in md
    assert (out / "report" / "surviving.png").exists()
    assert "oracle (ceiling)" in set(rf.summary["swarm"])
    # the report's idleness replay follows the recorded visits: it matches the run's coverage
    assert "their coverage matches series.parquet" in md


@pytest.mark.slow
def test_a_small_sumo_scenario_with_a_drone_loss_runs(tmp_path):
    pytest.importorskip("libsumo")
    from helpers import small_sumo_scenario

    from twin.cli import main
    from twin.report.load import load_run

    folder = small_sumo_scenario(tmp_path, horizon=10)
    config = folder / "small.toml"
    config.write_text(config.read_text() + "\n[faults]\ndrone_loss = [{ drone = 1, step = 3, "
                      "back = 7 }]\n")  # fmt: skip
    out = tmp_path / "run"
    assert main(["run", "--config", str(config), "--out", str(out), "--quiet"]) == 0
    rf = load_run(out)
    pos = rf.positions("greedy")
    assert (pos[3:8, 1] == pos[3, 1]).all()
    assert set(rf.degradation["label"]) == {"no drone lost", "1 of 2 drones lost", "whole run"}


def test_the_shipped_drone_loss_config_loses_two_of_four_drones_at_t_3_and_one_is_back_at_2t_3():
    config = load_config(ROOT / "configs" / "drone-loss.toml")
    horizon, plan = config.traffic.horizon, config.fault_plan()
    assert config.swarm.n_drones == 4
    assert [(a, b, label) for a, b, label in plan.phases(horizon, 4)] == [
        (0, horizon // 3, "no drone lost"),
        (horizon // 3, 2 * horizon // 3, "2 of 4 drones lost"),
        (2 * horizon // 3, horizon, "1 of 4 drones lost"),
    ]
    assert set(config.evaluate.swarms) >= set(CLASSICAL) | {"rl", "rl-online"}


def test_live_drones_wrapper_names_the_swarm():
    policy = LiveDrones(make_policy("greedy"), FaultPlan((DroneLoss(0, 1),)))
    assert policy.name == "greedy"


# ------------------------------------------------------------------- forged degradation tables
@pytest.fixture(scope="module")
def faulted(tmp_path_factory) -> Path:
    """A finished evaluation of two seeds under a drone loss, a coordinator outage and missed
    sightings: its degradation.csv and fault_free.parquet."""
    from twin.cli import main

    base = tmp_path_factory.mktemp("faulted")
    path = base / "faults.toml"
    path.write_text(SMALL + "[faults]\ndrone_loss = [{ drone = 1, step = 10, back = 20 }]\n"
                    "coordinator_down = [[25, 30]]\ndetection_p = 0.9\n")  # fmt: skip
    out = base / "run"
    code = main(["evaluate", "--config", str(path), "--out", str(out), "--seeds", "2",
                 "--swarms", "random,greedy,visit-gain", "--no-ceiling", "--no-report",
                 "--quiet"])  # fmt: skip
    assert code == 0
    return out


def _table_edit(**row_0):
    def edit(run: Path) -> None:
        import pandas as pd

        table = pd.read_csv(run / "degradation.csv")
        for column, value in row_0.items():
            table[column] = table[column].astype(object)
            table.loc[0, column] = value
        table.to_csv(run / "degradation.csv", index=False)

    return edit


def _drop_column(run: Path, column: str) -> None:
    import pandas as pd

    table = pd.read_csv(run / "degradation.csv")
    table.drop(columns=column).to_csv(run / "degradation.csv", index=False)


def _add_column(run: Path) -> None:
    import pandas as pd

    table = pd.read_csv(run / "degradation.csv")
    table.assign(bogus=1.0).to_csv(run / "degradation.csv", index=False)


def _twin_edit(change):
    def edit(run: Path) -> None:
        import pandas as pd

        frame = pd.read_parquet(run / "fault_free.parquet")
        change(frame)
        frame.to_parquet(run / "fault_free.parquet", index=False)

    return edit


def _moved(frame, step: int, di: int) -> None:
    """Drone 0 of the first swarm and seed moved by ``di`` cells at ``step``."""
    at = (frame["seed"] == 0) & (frame["swarm"] == "random") & (frame["drone"] == 0)
    at &= frame["step"] == step
    frame.loc[at, "i"] = (frame.loc[at, "i"] + di) % 6


#: Forgeries of a degradation table twin can tell from the folder (probe 15's P2-f04): each
#: name -> (edit of the run folder, words of the one-line refusal).
DEGRADATION_FORGERIES = {
    "R_hat_fault_free": (_table_edit(R_hat_fault_free=50.0),
                         "R_hat_fault_free = 50 for seed 0, swarm 'random', phase 1"),
    "events": (_table_edit(events=3), "events = 3 for seed 0, swarm 'random', phase 1"),
    "latency": (_table_edit(latency_median_steps=999.0), "latency_median_steps = 999"),
    "congested observed": (_table_edit(pct_congested_observed=99.0),
                           "pct_congested_observed = 99"),
    "seen by the twin": (_table_edit(pct_events_seen_fault_free=0.0),
                         "pct_events_seen_fault_free = 0"),
    "label": (_table_edit(label="all drones lost"), "label = 'all drones lost'"),
    **{  # an internal error (KeyError) in the report (probe 20's P2-f09b)
        f"{column} dropped": (
            lambda run, column=column: _drop_column(run, column),
            f"degradation.csv: no column {column!r}",
        )
        for column in ("pct_events_seen_fault_free", "latency_median_steps_fault_free",
                       "pct_congested_observed")
    },
    "a column added": (  # probe 20's P2-f09e
        lambda run: _table_edit()(run) or _add_column(run),
        "degradation.csv: holds a column 'bogus', which twin does not write",
    ),
    "twin's cells missing": (lambda run: (run / "fault_free.parquet").unlink(),
                             "fault_free.parquet) are missing"),
    "twin teleports": (_twin_edit(lambda f: _moved(f, 5, 3)), "fault_free.parquet: swarm"),
    "twin starts elsewhere": (_twin_edit(lambda f: _moved(f, 0, 1)), "does not start where"),
}  # fmt: skip


@pytest.mark.slow
@pytest.mark.parametrize("name", list(DEGRADATION_FORGERIES))
def test_forged_degradation_tables_are_refused(faulted, tmp_path, capsys, name):
    """Every column of degradation.csv is recomputed on read-back: the faulted ones from the
    trajectories, the fault-free twin's from fault_free.parquet replayed over the maps (they
    were trusted; probe 15's P2-f04)."""
    import shutil

    from test_boundary import refresh_manifest

    from twin.cli import main

    edit, words = DEGRADATION_FORGERIES[name]
    run = tmp_path / "run"
    shutil.copytree(faulted, run)
    edit(run)
    refresh_manifest(run)
    capsys.readouterr()
    assert main(["report", str(run), "--no-animation"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and words in err, err


@pytest.mark.slow
def test_an_unforged_degradation_table_reads_back(faulted, capsys):
    from twin.cli import main

    assert main(["report", str(faulted), "--no-animation"]) == 0, capsys.readouterr().err


@pytest.mark.slow
def test_a_degradation_table_of_an_earlier_format_reads_back_with_a_notice(
    faulted, tmp_path, capsys
):
    """A folder of format 2 kept no fault-free twin: its faulted columns are recomputed, the
    twin's are not, and a notice says so."""
    import json
    import shutil

    from test_boundary import refresh_manifest

    from twin.cli import main

    run = tmp_path / "run"
    shutil.copytree(faulted, run)
    (run / "fault_free.parquet").unlink()
    meta = json.loads((run / "run.json").read_text())
    meta["folder_format"] = 2
    (run / "run.json").write_text(json.dumps(meta))
    refresh_manifest(run)
    capsys.readouterr()
    assert main(["report", str(run), "--no-animation"]) == 0
    assert "its fault-free twin are not replayed" in capsys.readouterr().err
    _table_edit(events=3)(run)
    refresh_manifest(run)
    assert main(["report", str(run), "--no-animation"]) == 2
    assert "events = 3 for seed 0" in capsys.readouterr().err
