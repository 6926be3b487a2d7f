"""Per-stage timing: every run records where its time went, and the stages cover the
patrol loop."""

from __future__ import annotations

import json
import time

import numpy as np
import pandas as pd
import pytest

from twin.grid import Grid
from twin.patrol import run_patrol
from twin.policies import Policy
from twin.runs import timing_frame, write_run
from twin.scores import ScoreParams
from twin.swarms import make_policy
from twin.timing import (
    OBSERVATION,
    READS,
    SCORING,
    SUMO_STEPPING,
    SUMO_WARMUP,
    TRAFFIC,
    WRITING,
    StageTimer,
    swarm_stage,
)
from twin.traffic.synthetic import Disturbance, SyntheticTraffic


class SlowGreedy(Policy):
    """Greedy that sleeps a known time per decision: its stage must show it."""

    def __init__(self, pause: float):
        self.inner, self.pause = make_policy("greedy"), pause

    def reset(self, grid, n_drones, rng):
        self.inner.reset(grid, n_drones, rng)

    def act(self, view):
        time.sleep(self.pause)
        return self.inner.act(view)


def _synthetic(horizon=12):
    grid = Grid(np.zeros((8, 10), bool))
    return SyntheticTraffic(grid, [Disturbance("big", 2, 3, 1.0, 2.0)], horizon=horizon)


def test_stage_timer_accumulates_in_first_seen_order():
    timer = StageTimer()
    timer.add("b", 1.0)
    with timer.stage("a"):
        pass
    timer.add("b", 0.5, calls=0)
    assert list(timer.seconds) == ["b", "a"]
    assert timer.seconds["b"] == 1.5 and timer.calls["b"] == 1
    assert timer.seconds["a"] >= 0.0 and timer.total() >= 1.5


def test_patrol_stages_cover_the_loop_and_show_a_slow_swarm():
    source = _synthetic()
    swarms = {"random": make_policy("random"), "slow": SlowGreedy(0.01)}
    starts = np.array([[0, 0], [7, 9]])
    result = run_patrol(source, swarms, starts, ScoreParams(), seed=0)
    stages = result.stage_seconds
    assert set(stages) >= {TRAFFIC, swarm_stage("random"), swarm_stage("slow"), SCORING}
    # the slow swarm slept 12 x 10 ms: it is the largest stage and at least that long
    assert stages[swarm_stage("slow")] >= 0.12
    assert max(stages, key=stages.get) == swarm_stage("slow")
    covered = sum(stages.values())
    assert covered <= result.seconds + 1e-6
    assert covered >= 0.9 * result.seconds


def test_timing_csv_is_written_with_the_run(tmp_path):
    source = _synthetic(horizon=6)
    result = run_patrol(
        source, {"greedy": make_policy("greedy")}, np.array([[1, 1]]), ScoreParams(), seed=2
    )
    write_run(tmp_path, [result], {"config": "x"})
    timing = pd.read_csv(tmp_path / "timing.csv")
    assert list(timing.columns) == ["seed", "process", "stage", "seconds", "ms_per_step", "share"]
    assert set(timing["process"]) == {"main"}
    assert set(timing["stage"]) >= {TRAFFIC, swarm_stage("greedy"), SCORING, WRITING}
    assert timing["share"].sum() == pytest.approx(1.0, abs=0.01)
    row = timing.set_index("stage").loc[SCORING]
    assert row["ms_per_step"] == pytest.approx(1000 * row["seconds"] / 6, rel=1e-3, abs=1e-4)
    meta = json.loads((tmp_path / "run.json").read_text())
    assert meta["timings"]["peak_memory_mb"] > 10
    manifest = json.loads((tmp_path / "manifest.json").read_text())
    assert "timing.csv" in manifest["files"]


def test_timing_frame_puts_writing_on_the_first_seed_only():
    source = _synthetic(horizon=3)
    runs = [
        run_patrol(source, {"random": make_policy("random")}, np.array([[0, 0]]), ScoreParams(), s)
        for s in (0, 1)
    ]
    frame = timing_frame(runs, writing_seconds=0.25)
    assert (frame.loc[frame["stage"] == WRITING, "seed"] == 0).all()
    assert frame.groupby("seed")["share"].sum().round(2).tolist() == [1.0, 1.0]


def test_live_sumo_splits_its_time_into_stepping_reads_and_model(tmp_path):
    pytest.importorskip("libsumo")
    from helpers import small_sumo_scenario

    from twin.config import load_config
    from twin.sumo.scenario import sumo_source

    folder = small_sumo_scenario(tmp_path, horizon=4)
    source = sumo_source(load_config(folder / "small.toml"))
    starts = np.argwhere(source.grid.free)[[0, -1]]
    result = run_patrol(source, {"greedy": make_policy("greedy")}, starts, ScoreParams())
    stages = result.stage_seconds
    for stage in (SUMO_WARMUP, SUMO_STEPPING, READS, OBSERVATION):
        assert stages[stage] > 0, stage
    assert TRAFFIC not in stages  # split into the source's own stages
    assert source.timer.calls[SUMO_STEPPING] == 5  # T^0 .. T^4, the warm-up apart
    assert sum(stages.values()) <= result.seconds + 1e-6


def test_sumo_in_its_own_process_gives_the_same_run_and_reports_its_stages(tmp_path):
    """SUMO ahead of the swarms in a child process (twin/sumo/worker.py): the same maps, tape,
    MFD and swarm results as in one process; the loop's traffic stage is the wait for it, and
    the child's own stages come back."""
    pytest.importorskip("libsumo")
    from helpers import small_sumo_scenario

    from twin.config import load_config
    from twin.sumo.scenario import sumo_source
    from twin.timing import WAITING_FOR_SUMO

    folder = small_sumo_scenario(tmp_path, horizon=6)
    config = load_config(folder / "small.toml")
    runs = []
    for separate in (False, True):
        source = sumo_source(config)
        source.separate_process = separate
        starts = np.argwhere(source.grid.free)[[0, -1]]
        swarms = {n: make_policy(n) for n in ("random", "greedy")}
        runs.append((source, run_patrol(source, swarms, starts, ScoreParams(), seed=1)))
    (here, a), (there, b) = runs
    assert np.array_equal(a.importance, b.importance)
    assert np.array_equal(a.positions, b.positions) and np.array_equal(a.rewards, b.rewards)
    assert len(here.snapshots) == len(there.snapshots)
    for x, y in zip(here.snapshots, there.snapshots, strict=True):
        assert x[:2] == y[:2] and np.array_equal(x[2], y[2])
        assert np.array_equal(x[3], y[3], equal_nan=True)
    assert here.vehicles_seen == there.vehicles_seen
    assert here.model.report() == there.model.report()
    assert WAITING_FOR_SUMO in b.stage_seconds and SUMO_STEPPING not in b.stage_seconds
    assert b.extra["process_stages"]["sumo"][SUMO_STEPPING] > 0
    assert a.extra["process_stages"] == {}
    frame = timing_frame([b])
    assert set(frame["process"]) == {"main", "sumo"}


def test_sumo_process_stopped_early_keeps_the_maps_used(tmp_path):
    """A loop stopped after 2 steps (Ctrl-C) keeps exactly the snapshots of the maps it used,
    as SUMO in one process does, and the child process is gone."""
    pytest.importorskip("libsumo")
    import multiprocessing

    from helpers import small_sumo_scenario

    from twin.config import load_config
    from twin.sumo.scenario import sumo_source

    folder = small_sumo_scenario(tmp_path, horizon=8)
    config = load_config(folder / "small.toml")
    kept = []
    for separate in (False, True):
        source = sumo_source(config)
        source.separate_process = separate
        starts = np.argwhere(source.grid.free)[[0, -1]]
        calls = {"n": 0}

        def stop(calls=calls):
            calls["n"] += 1
            return calls["n"] >= 2

        result = run_patrol(
            source, {"greedy": make_policy("greedy")}, starts, ScoreParams(), stop=stop
        )
        assert result.completed_steps == 2 and result.error.startswith("interrupted")
        kept.append([k for k, *_ in source.snapshots])
    assert kept[0] == kept[1]
    assert not multiprocessing.active_children()
