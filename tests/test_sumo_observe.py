"""Observations over the step (several reads per step) and the MFD on thin data."""

from __future__ import annotations

import numpy as np
import pytest

from twin.mfd import MFD, MIN_FIT_SAMPLES, MFDImportance, OnlineMFD


def test_thin_data_keeps_the_prior_and_says_why():
    online = OnlineMFD(prior=MFD(0.7, 40.0))
    count = np.array([3, 5, 8])
    online.add(count, np.array([2.0, 30.0, 60.0]), np.array([0.2, 0.1, 0.05]))
    mfd, used, why = online.choose()
    assert (mfd, used) == (MFD(0.7, 40.0), "prior") and "3 samples" in why


def test_negative_r2_keeps_the_prior_enough_good_data_uses_the_fit():
    rng = np.random.default_rng(0)
    n = 4 * MIN_FIT_SAMPLES
    density = rng.uniform(0.0, 100.0, n)
    # speeds that rise with density: no Underwood curve explains them better than their mean
    bad = OnlineMFD()
    bad.add(np.ones(n), density, 0.1 + 0.008 * density)
    mfd, used, why = bad.choose()
    assert used == "prior" and mfd == bad.prior and "R2" in why
    assert bad.data_r2(bad.fit()) < 0.0
    good = OnlineMFD()
    good.add(
        np.full(n, 50),
        density,  # 40 000 vehicles: the prior weighs little
        MFD(0.5, 25.0).speed_ratio(density) + rng.normal(0, 0.01, n),
    )
    mfd, used, _ = good.choose()
    assert used == "fit" and abs(mfd.k_c - 25.0) < 2.0 and good.data_r2(mfd) > 0.9


def test_report_says_which_mfd_was_used():
    free = np.ones((2, 2), bool)
    model = MFDImportance(free, np.ones((2, 2)), np.full((2, 2), 14.0))
    model.observe(0, np.array([[1, 2], [3, 4]]), np.full((2, 2), 10.0))
    report = model.report()
    assert report["used"] == "prior" and "samples" in report["why"]
    assert (report["a"], report["k_c"]) == (MFD().a, MFD().k_c)


def test_reads_divide_the_count_into_a_mean_density():
    free = np.ones((1, 2), bool)
    lane_km = np.array([[1.0, 2.0]])
    one = MFDImportance(free, lane_km, np.full((1, 2), 14.0), fit="fixed")
    three = MFDImportance(free, lane_km, np.full((1, 2), 14.0), fit="fixed", reads=3)
    mean_counts = np.array([[10, 4]])
    np.testing.assert_allclose(
        three.observe(0, 3 * mean_counts, np.full((1, 2), 5.0)),
        one.observe(0, mean_counts, np.full((1, 2), 5.0)),
    )
    np.testing.assert_allclose(three.samples()["density"], [10.0, 2.0])


# ------------------------------------------------------------------------ on a small SUMO run
def test_averaged_count_equals_an_average_of_fcd_and_replay_equals_live(tmp_path):
    pytest.importorskip("libsumo")
    from helpers import small_sumo_scenario
    from test_sumo_small import _fcd_counts, _patrol

    from twin.config import load_config
    from twin.sumo.scenario import sumo_source
    from twin.traffic.tape import TapeTraffic

    small_sumo_scenario(tmp_path, horizon=10)
    source = sumo_source(load_config(tmp_path / "small.toml"))
    s = source.scenario
    s.reads_per_step = 3
    fcd = tmp_path / "fcd.xml"
    s.sumo_options = ("--fcd-output", str(fcd))
    live = _patrol(source)
    assert live.error is None and s.read_offsets() == [40.0, 20.0, 0.0]  # 60 s steps
    instants = [
        max(t - o, s.sim_begin + 1.0) for _, t, _, _ in source.snapshots for o in s.read_offsets()
    ]
    # the state after simulationStep(t) is SUMO's FCD timestep t - 1 s (step length 1 s)
    fcd_counts = _fcd_counts(fcd, source, [t - 1.0 for t in instants])
    total = 0
    for _, t, counts, _ in source.snapshots:
        at = [round(max(t - o, s.sim_begin + 1.0) - 1.0, 1) for o in s.read_offsets()]
        independent = sum(fcd_counts[a] for a in at)  # vehicle-instants = 3 x the mean count
        np.testing.assert_array_equal(counts, independent)
        total += counts.sum()
    assert total > 300

    path = tmp_path / "tape.parquet"
    source.tape().write(path)
    replay_source = TapeTraffic.from_file(path)
    replay = _patrol(replay_source)
    assert replay_source.model().reads == 3
    np.testing.assert_array_equal(replay.importance, live.importance)
    np.testing.assert_array_equal(replay.positions, live.positions)
    assert source.model.report()["reads_per_step"] == 3
