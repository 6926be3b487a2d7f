"""The MFD observation model (twin/mfd.py): fit, online fit, importance, detection."""

from __future__ import annotations

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from twin.mfd import (
    MFD,
    MFDImportance,
    OnlineMFD,
    density_from_counts,
    detected_counts,
    fit_quality,
    fit_underwood,
)


def _samples(rng, n=4000, a=0.6, k_c=35.0, noise=0.03):
    density = rng.uniform(0.0, 120.0, n)
    ratio = a * np.exp(-density / k_c) + rng.normal(0.0, noise, n)
    return density, np.clip(ratio, 0.0, None)


def test_fit_recovers_underwood_parameters():
    rng = np.random.default_rng(0)
    density, ratio = _samples(rng)
    mfd = fit_underwood(density, ratio, np.ones_like(density))
    assert abs(mfd.a - 0.6) < 0.02 and abs(mfd.k_c - 35.0) < 2.0
    limit = np.full_like(density, 50 / 3.6)
    quality = fit_quality(mfd, density, ratio * limit, limit)
    assert quality["r2"] > 0.9 and quality["rmse_kmh"] < 2.0


def test_online_fit_on_binned_sums_matches_the_batch_fit():
    rng = np.random.default_rng(1)
    density, ratio = _samples(rng, n=6000)
    online = OnlineMFD(bin_width=1.0, prior_weight=0.0)
    for part in np.array_split(np.arange(len(density)), 6):
        online.add(np.ones(len(part), int), density[part], ratio[part])
    fitted = online.fit()
    batch = fit_underwood(density, ratio, np.ones_like(density))
    assert abs(fitted.a - batch.a) < 0.02 and abs(fitted.k_c - batch.k_c) < 2.0


def test_thin_data_keeps_the_prior():
    prior = MFD(0.7, 40.0)
    assert fit_underwood(np.array([1.0]), np.array([0.5]), np.array([1.0]), prior) == prior
    assert OnlineMFD(prior=prior).fit() == prior


@settings(max_examples=50, deadline=None)
@given(
    a=st.floats(0.1, 1.2),
    k_c=st.floats(3.0, 300.0),
    density=st.lists(st.floats(0.0, 1e4), min_size=1, max_size=20),
)
def test_importance_lies_in_unit_interval_zero_when_empty_and_grows_with_density(a, k_c, density):
    mfd = MFD(a, k_c)
    d = np.sort(np.asarray(density))
    t = mfd.importance(d)
    assert ((t >= 0) & (t <= 1)).all()
    assert np.all(np.diff(t) >= -1e-12)
    assert mfd.importance(np.zeros(1))[0] == 0.0


def test_detection_thins_counts_and_density_corrects_for_it():
    rng = np.random.default_rng(2)
    counts = np.full(20000, 10)
    np.testing.assert_array_equal(detected_counts(counts, 1.0, rng), counts)
    seen = detected_counts(counts, 0.5, rng)
    assert (seen <= counts).all() and abs(seen.mean() - 5.0) < 0.1
    lane_km = np.full(20000, 2.0)
    assert abs(density_from_counts(seen, lane_km, 0.5).mean() - 5.0) < 0.1
    assert density_from_counts(np.array([3]), np.array([0.0]))[0] == 0.0


def test_observation_uses_only_earlier_snapshots_and_obstacles_are_zero():
    rng = np.random.default_rng(3)
    free = np.ones((4, 5), bool)
    free[0, 0] = False
    lane_km = np.full((4, 5), 1.0)
    limit = np.full((4, 5), 14.0)
    model = MFDImportance(free, lane_km, limit, fit="online", mfd=MFD(0.7, 40.0))
    first = model.observe(0, rng.integers(0, 30, (4, 5)), np.full((4, 5), 5.0))
    # the first snapshot is seen through the prior
    expected = np.where(free, MFD(0.7, 40.0).importance(np.zeros((4, 5))), 0)
    assert first[0, 0] == 0.0 and expected[0, 0] == 0.0
    assert model.mfd == MFD(0.7, 40.0) and model.used == "prior"  # 19 samples: too thin
    for k in range(1, 30):  # enough snapshots on a curve of its own: the fit takes over
        count = rng.integers(0, 60, (4, 5))
        model.observe(k, count, limit * MFD(0.5, 20.0).speed_ratio(count / lane_km))
    assert model.used == "fit" and model.mfd != MFD(0.7, 40.0)
    fixed = MFDImportance(free, lane_km, limit, fit="fixed", mfd=MFD(0.7, 40.0))
    fixed.observe(0, rng.integers(0, 30, (4, 5)), np.full((4, 5), 5.0))
    assert fixed.mfd == MFD(0.7, 40.0)
    report = model.report()
    assert report["n_samples"] > 0 and "r2" in report and "rmse_kmh" in report


def test_prior_pseudo_samples_hold_k_c_until_dense_data_arrives():
    rng = np.random.default_rng(4)
    low = rng.uniform(0.0, 3.0, 500)  # a morning's first snapshots: flat, uninformative
    ratio = 0.75 + rng.normal(0, 0.05, 500)
    bare, held = OnlineMFD(prior_weight=0.0), OnlineMFD()
    for m in (bare, held):
        m.add(np.ones(500, int), low, ratio)
    assert abs(held.fit().k_c - 40.0) < abs(bare.fit().k_c - 40.0)
    density, r = _samples(rng, n=20000, a=0.6, k_c=20.0, noise=0.02)
    held.add(np.full(len(density), 5), density, r)
    assert abs(held.fit().k_c - 20.0) < 1.0  # plenty of data outweighs the prior


def test_samples_of_a_run_without_vehicles_keep_their_columns() -> None:
    """No cell ever held a vehicle: the samples are empty but keep the columns and types of a
    run that had some, so mfd_samples.parquet reads back like any other."""
    free = np.ones((2, 2), dtype=bool)
    lane_km, limit = np.ones((2, 2)), np.full((2, 2), 14.0)
    empty = MFDImportance(free, lane_km, limit)
    empty.observe(0, np.zeros((2, 2)), np.zeros((2, 2)))
    busy = MFDImportance(free, lane_km, limit)
    busy.observe(0, np.full((2, 2), 3), np.full((2, 2), 9.0))
    got, want = empty.samples(), busy.samples()
    assert list(got) == list(want) and all(len(v) == 0 for v in got.values())
    assert {k: v.dtype for k, v in got.items()} == {k: v.dtype for k, v in want.items()}
    assert empty.report()["n_samples"] == 0
