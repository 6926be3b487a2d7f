"""The traffic tape without SUMO: round trip, replay through the MFD model, bad files."""

from __future__ import annotations

import numpy as np
import pytest
from helpers import random_tape
from hypothesis import given, settings
from hypothesis import strategies as st

from twin.errors import UserError
from twin.mfd import MFD, MFDImportance
from twin.traffic.tape import Tape, TapeTraffic

_tape = random_tape  # a 3 x 4 grid, cell (0, 0) an obstacle, 2 warm-up steps, T = 5


def test_round_trip_keeps_every_value(tmp_path):
    tape = _tape()
    path = tmp_path / "tape.parquet"
    tape.write(path)
    back = Tape.read(path)
    np.testing.assert_array_equal(back.steps, tape.steps)
    np.testing.assert_array_equal(back.counts, tape.counts)
    np.testing.assert_array_equal(back.speeds, tape.speeds)
    np.testing.assert_array_equal(back.obstacles, tape.obstacles)
    np.testing.assert_array_equal(back.lane_km, tape.lane_km)
    assert back.horizon == tape.horizon and back.settings == tape.settings


def test_replay_feeds_the_observation_model_in_order(tmp_path):
    tape = _tape(seed=1)
    path = tmp_path / "tape.parquet"
    tape.write(path)
    source = TapeTraffic.from_file(path)
    maps = list(source.importance_maps())
    assert len(maps) == source.horizon + 1 == 6
    model = MFDImportance(~tape.obstacles, tape.lane_km, tape.speed_limit, "online", MFD(), 1.0, 4)
    expected = [
        model.observe(int(k), c, s.astype(float))
        for k, c, s in zip(tape.steps, tape.counts, tape.speeds, strict=True)
    ][2:]
    for got, want in zip(maps, expected, strict=True):
        np.testing.assert_array_equal(got, want)
    assert (np.stack(maps)[:, 0, 0] == 0).all()
    assert source.clock(0) == "07:00:00" and source.clock(4) == "07:05:00"


def test_detection_override_changes_what_the_drones_see(tmp_path):
    tape = _tape(seed=2)
    exact = np.stack(list(TapeTraffic(tape).importance_maps()))
    blurred = np.stack(list(TapeTraffic(tape, detection_p=0.5).importance_maps()))
    assert not np.array_equal(exact, blurred)


def test_bad_tapes_give_user_errors(tmp_path):
    with pytest.raises(UserError, match="no such traffic tape"):
        Tape.read(tmp_path / "missing.parquet")
    junk = tmp_path / "junk.parquet"
    junk.write_text("not parquet")
    with pytest.raises(UserError, match="not a parquet file"):
        Tape.read(junk)
    import pandas as pd

    plain = tmp_path / "plain.parquet"
    pd.DataFrame({"a": [1]}).to_parquet(plain)
    with pytest.raises(UserError, match="not a twin traffic tape"):
        Tape.read(plain)


@settings(max_examples=15, deadline=None)
@given(
    nx=st.integers(1, 4),
    ny=st.integers(1, 4),
    warmup=st.integers(0, 3),
    horizon=st.integers(1, 5),
    seed=st.integers(0, 2**16),
)
def test_every_valid_tape_passes_its_checks(tmp_path_factory, nx, ny, warmup, horizon, seed):
    """The checks on read refuse nothing a tape's own writer produces."""
    tape = _tape(seed, nx, ny, warmup, horizon)
    path = tmp_path_factory.mktemp("t") / "tape.parquet"
    tape.write(path)
    back = Tape.read(path, shape=(nx, ny))
    np.testing.assert_array_equal(back.counts, tape.counts)
    assert TapeTraffic(back).horizon == horizon


def test_a_short_tape_replays_partially(tmp_path):
    """A tape cut before its horizon (a SUMO run that stopped) yields fewer maps than
    ``horizon + 1``: the patrol sees the source end and reports a partial run."""
    tape = _tape(horizon=5)
    keep = tape.steps <= 2
    tape.steps, tape.times = tape.steps[keep], tape.times[keep]
    tape.counts, tape.speeds = tape.counts[keep], tape.speeds[keep]
    path = tmp_path / "tape.parquet"
    tape.write(path)
    source = TapeTraffic.from_file(path)
    assert source.horizon == 5 and len(list(source.importance_maps())) == 3


@pytest.mark.parametrize(
    ("config_text", "said"),
    [
        ('[traffic]\nkind = "sumo"\nhorizon = 5\n', []),
        ('[traffic]\nkind = "sumo"\n', []),  # nothing set: nothing to replace
        ('[traffic]\nkind = "sumo"\nhorizon = 144\n',
         ["its T = 5 replaces c.toml's [traffic].horizon = 144"]),
        ('[grid]\nnx = 20\nny = 30\n[traffic]\nkind = "synthetic"\nhorizon = 2000\n', []),
        (
            '[traffic]\nkind = "sumo"\n[[traffic.incidents]]\nkind = "edge_closed"\n'
            'cell = [0, 1]\nstep = 1\nduration_min = 5\n',
            ["c.toml's 1 [[traffic.incidents]] are not applied (a tape replays recorded "
             "vehicles: run them live with `twin run`)"],
        ),
    ],
)  # fmt: skip
def test_a_replay_says_what_of_the_config_it_sets_aside(tmp_path, capsys, config_text, said):
    """`twin evaluate --traffic`: the tape's horizon replaces a SUMO config's own, and its
    incidents meet no recorded vehicle: said in one notice, nothing said when equal or for a
    synthetic config (whose traffic the tape replaces whole, as --traffic says)."""
    from twin.config import load_config

    config = tmp_path / "c.toml"
    config.write_text(config_text)
    path = tmp_path / "tape.parquet"
    _tape().write(path)
    source = TapeTraffic.from_file(path, load_config(config))
    assert source.horizon == 5 and source.grid.shape == (3, 4)
    err = capsys.readouterr().err.strip()
    assert err == (f"twin: notice: {path}: {'; '.join(said)}" if said else "")


def test_a_replay_says_its_runs_incidents_are_not_scored(tmp_path, capsys):
    """A tape of a run with incidents: their effect is in the vehicles, but `twin evaluate
    --traffic` scores no incident; said in the notice (it was silent: probe 19)."""
    tape = _tape()
    tape.settings["incidents"] = [{"kind": "edge_closed", "cell": [0, 1], "step": 1}] * 2
    path = tmp_path / "tape.parquet"
    tape.write(path)
    from twin.config import load_config

    config = tmp_path / "c.toml"
    config.write_text('[grid]\nnx = 3\nny = 4\n[traffic]\nkind = "synthetic"\n')
    TapeTraffic.from_file(path, load_config(config))
    err = capsys.readouterr().err.strip()
    assert err == (
        f"twin: notice: {path}: the 2 incidents of its run are in its vehicles, but not "
        "scored as incidents here (their detection and incidents.json come with `twin run`)"
    ), err


def test_a_tapes_footer_reads_without_its_rows_and_none_when_damaged(tmp_path):
    from twin.traffic.tape import tape_footer

    path = tmp_path / "tape.parquet"
    random_tape(seed=0, nx=4, ny=3, warmup=2, horizon=6).write(path)
    meta = tape_footer(path)
    assert (meta["nx"], meta["ny"], meta["horizon"]) == (4, 3, 6)
    path.write_bytes(path.read_bytes()[:-20])  # truncated: its footer is gone
    assert tape_footer(path) is None
    assert tape_footer(tmp_path / "missing.parquet") is None
