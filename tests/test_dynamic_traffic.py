"""Synthetic traffic with dynamics: maps in [0, 1] per Def. 2, disturbances that move, grow and
fade under a rush-hour wave, the same maps from the same seed."""

from __future__ import annotations

import numpy as np

from twin.grid import Grid
from twin.traffic.dynamic import DynamicTraffic


def maps(source: DynamicTraffic) -> np.ndarray:
    return np.stack(list(source.importance_maps()))


def test_maps_are_importance_maps_and_follow_the_seed() -> None:
    grid = Grid.open(10, 12)
    a = maps(DynamicTraffic(grid, 50, 5, seed=3))
    assert a.shape == (51, 10, 12)
    assert a.min() >= 0 and a.max() == 1.0  # z_hi is the largest z over map and horizon
    assert np.array_equal(a, maps(DynamicTraffic(grid, 50, 5, seed=3)))
    assert not np.array_equal(a, maps(DynamicTraffic(grid, 50, 5, seed=4)))


def test_disturbances_move_and_stay_on_the_map() -> None:
    source = DynamicTraffic(Grid.open(8, 8), 200, 6, seed=0)
    start, later = source.centres_at(0), source.centres_at(150)
    assert not np.allclose(start, later)
    for k in range(0, 201, 10):
        c = source.centres_at(k)
        assert (c >= 0).all() and (c <= 7).all()


def test_a_disturbance_grows_and_fades() -> None:
    source = DynamicTraffic(Grid.open(6, 6), 100, 1, seed=1)
    z = np.array([source.z(k).sum() for k in range(101)])
    on = np.flatnonzero(z > 0)
    assert len(on) > 2 and z[0] >= 0
    peak = int(np.argmax(z))
    # rises to one peak, then fades (a sine envelope times the wave)
    assert peak in range(on[0], on[-1] + 1)
    assert z[on[-1]] < z[peak] and z[on[0]] <= z[peak]


def test_the_rush_hour_wave_peaks_inside_the_horizon() -> None:
    source = DynamicTraffic(Grid.open(4, 4), 100, 1, seed=0)
    wave = [source.wave(k) for k in range(101)]
    assert 30 < int(np.argmax(wave)) < 60 and min(wave) > 0


def test_many_disturbances_sum_in_batches_to_the_same_map(monkeypatch):
    """``z^k`` summed over batches of disturbances (bounded memory, whatever their number) is
    the sum over all of them at once."""
    import twin.traffic.dynamic as dynamic

    grid = Grid.open(9, 7)
    whole = dynamic.DynamicTraffic(grid, 12, n_disturbances=40, seed=3)
    monkeypatch.setattr(dynamic, "BUMP_BATCH_VALUES", 2 * 9 * 7)  # batches of 2
    batched = dynamic.DynamicTraffic(grid, 12, n_disturbances=40, seed=3)
    np.testing.assert_allclose(batched._z, whole._z, rtol=1e-12, atol=1e-15)


def test_history_of_too_many_disturbances_is_one_line(tmp_path, capsys):
    """``twin history --dynamics --disturbances 1e8`` is refused before any work, naming the
    flag (it ran out of memory, blaming the grid: probe 23's f10)."""
    from twin.cli import main

    config = tmp_path / "nc.toml"
    config.write_text(
        '[grid]\nnx = 6\nny = 7\n[traffic]\nkind = "synthetic"\nhorizon = 20\n'
        'disturbances = [{ kind = "big", i = 3, j = 4, amplitude = 1.0, sigma = 2.0 }]\n'
    )
    argv = ["history", "--dynamics", str(config), "--days", "3", "--disturbances",
            "100000000", "--out", str(tmp_path / "h.npz")]  # fmt: skip
    assert main(argv) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("twin: error: --disturbances 100000000: give at most 10000")
    assert "\n" not in err and not (tmp_path / "h.npz").exists()
