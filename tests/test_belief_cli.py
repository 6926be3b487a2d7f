"""``twin history`` and ``twin run --history`` on a small real SUMO scenario."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

pytest.importorskip("libsumo")

from helpers import small_sumo_scenario

from twin.belief import NO_DRONES, History
from twin.cli import main as twin_main
from twin.errors import UserError

ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def small(tmp_path_factory) -> Path:
    return small_sumo_scenario(tmp_path_factory.mktemp("small"), horizon=8)


@pytest.fixture(scope="module")
def history(small, tmp_path_factory) -> Path:
    """A history from SUMO seeds 10 and 11 (never the evaluated seed 3)."""
    base = tmp_path_factory.mktemp("history")
    code = twin_main(
        ["run", "--config", str(small / "small.toml"), "--sumo-seed", "10", "--seeds", "2",
         "--swarms", "random", "--no-ceiling", "--no-report", "--quiet",
         "--out", str(base / "days")]
    )  # fmt: skip
    assert code == 0
    out = base / "history.npz"
    assert twin_main(["history", "--from", str(base / "days"), "--out", str(out)]) == 0
    return out


def run_args(small, out, *extra):
    return ["run", "--config", str(small / "small.toml"), "--swarms", "random,greedy",
            "--no-ceiling", "--no-report", "--quiet", "--out", str(out), *extra]  # fmt: skip


def test_history_then_run_writes_the_belief_table(small, history, tmp_path, capsys):
    h = History.load(history)
    assert h.n_runs == 2 and h.horizon == 8 and h.traffic_seeds == (10, 11)
    assert h.step_s == pytest.approx(60.0) and h.begin == "00:05:00"
    capsys.readouterr()
    out = tmp_path / "eval"
    assert twin_main(run_args(small, out, "--history", str(history))) == 0
    printed = capsys.readouterr().out
    assert "Belief models" in printed and "nowcast" in printed
    table = pd.read_csv(out / "belief_models.csv")
    assert list(zip(table["swarm"], table["model"], strict=True)) == [
        (NO_DRONES, "history"),
        ("random", "last-seen"),
        ("random", "nowcast"),
        ("greedy", "last-seen"),
        ("greedy", "nowcast"),
    ]
    manifest = json.loads((out / "manifest.json").read_text())
    assert "belief_models.csv" in manifest["files"]
    # last-seen is the monitoring table's belief error
    monitoring = pd.read_csv(out / "monitoring.csv").set_index("swarm")
    last = table[table["model"] == "last-seen"].set_index("swarm")
    for swarm in ("random", "greedy"):
        assert last.loc[swarm, "belief_error"] == pytest.approx(
            monitoring.loc[swarm, "belief_error"], rel=1e-12
        )
    assert table.loc[table["model"] != "last-seen", "calibration_90"].between(0, 1).all()
    assert np.isfinite(table["false_alarms_per_hour"]).all()
    assert twin_main(["report", str(out), "--no-animation"]) == 0
    report = (out / "report" / "report.md").read_text()
    assert "## Belief models" in report and "| (no drones) | history |" in report
    # the run's tape replayed without SUMO gives the same belief table
    replay = tmp_path / "replay"
    code = twin_main(
        ["evaluate", "--config", str(small / "small.toml"), "--traffic", str(out / "tape.parquet"),
         "--swarms", "random,greedy", "--no-ceiling", "--no-report", "--quiet",
         "--history", str(history), "--out", str(replay)]
    )  # fmt: skip
    assert code == 0
    pd.testing.assert_frame_equal(pd.read_csv(replay / "belief_models.csv"), table)


def test_without_history_no_belief_file(small, tmp_path):
    out = tmp_path / "plain"
    assert twin_main(run_args(small, out)) == 0
    assert not (out / "belief_models.csv").exists()


def test_mismatched_history_is_one_line_and_exit_2(small, history, tmp_path, capsys):
    cases = [
        (["--horizon", "6"], "horizon T = 8 differs from the run's T = 6"),
        (["--sumo-seed", "11"], "traffic seed 11"),
        (["--begin", "00:06"], "starts at 00:05:00"),
    ]
    for extra, text in cases:
        out = tmp_path / f"bad{len(extra[1])}{extra[0]}"
        code = twin_main(run_args(small, out, "--history", str(history), *extra))
        err = capsys.readouterr().err.strip()
        assert code == 2, err
        assert "Traceback" not in err
        err = err.splitlines()[-1]  # after the line announcing the simulation
        assert err.startswith("twin: error: ") and text in err and str(history) in err
        assert not out.exists()  # the refused run leaves no folder
    broken = tmp_path / "broken.npz"
    broken.write_bytes(b"PK\x03\x04 not really")
    code = twin_main(run_args(small, tmp_path / "b", "--history", str(broken)))
    err = capsys.readouterr().err.strip()
    assert code == 2 and str(broken) in err and "\n" not in err


def test_a_mismatched_history_is_named_by_its_file_in_the_workers_too(
    small, history, tmp_path, capsys
):
    """With --workers the sources are built in the workers, where the swarms find the history
    of another horizon: their refusal names the file and the fix, as the check before SUMO
    does (it named the swarm alone)."""
    out = tmp_path / "w"
    argv = run_args(small, out, "--history", str(history), "--horizon", "6")
    code = twin_main([*argv, "--swarms", "nowcast-gain", "--seeds", "2", "--workers", "2"])
    err = capsys.readouterr().err.strip()
    assert code == 2 and "Traceback" not in err, err
    err = err.splitlines()[-1]
    assert f"{history}" in err and "horizon T = 8 differs from the run's T = 6" in err, err
    assert "build the history from runs of the same scenario and options" in err


def test_nowcast_gain_runs_on_the_history_and_is_scored_by_the_belief_table(
    small, history, tmp_path, capsys
):
    """The swarm that plans on the nowcast gets ``--history``; its rows are in the belief
    table, its drones never share a cell; the tape replayed gives the same run."""
    out = tmp_path / "nowcast"
    args = ["run", "--config", str(small / "small.toml"), "--swarms", "visit-gain,nowcast-gain",
            "--no-ceiling", "--no-report", "--quiet", "--out", str(out), "--history", str(history)]  # fmt: skip
    assert twin_main(args) == 0
    table = pd.read_csv(out / "belief_models.csv")
    rows = table[table["swarm"] == "nowcast-gain"]
    assert list(rows["model"]) == ["last-seen", "nowcast"]
    assert rows["belief_error"].notna().all()
    traj = pd.read_parquet(out / "trajectories.parquet")
    mine = traj[traj["swarm"] == "nowcast-gain"]
    assert not mine.duplicated(["seed", "step", "i", "j"]).any()  # no two drones on one cell
    run = json.loads((out / "run.json").read_text())
    assert run["policies"]["nowcast-gain"]["history_seeds"] == [10, 11]
    with np.load(out / "belief_maps.npz") as maps:
        assert json.loads(str(maps["swarms"])) == ["visit-gain", "nowcast-gain"]
        assert maps["mean"].shape == (2, len(maps["steps"]), *maps["truth"].shape[1:])
        known = maps["known_at"]
        assert ((known == -1) | (known >= maps["event_onset"])).all()
    known_share = 100.0 * (known >= 0).mean(axis=1) if known.shape[1] else None
    if known_share is not None:  # the timeline's marks are the belief table's % known
        nowcast_rows = table[table["model"] == "nowcast"].set_index("swarm")
        for s, swarm in enumerate(["visit-gain", "nowcast-gain"]):
            assert known_share[s] == pytest.approx(nowcast_rows.loc[swarm, "pct_events_known"])
    assert twin_main(["report", str(out), "--no-animation"]) == 0
    report = (out / "report" / "report.md").read_text()
    assert "Believed against true importance (nowcast)" in report
    assert (out / "report" / "belief_maps.png").exists()
    assert (out / "report" / "belief_timeline.png").exists()
    replay = tmp_path / "replay"
    code = twin_main(
        ["evaluate", "--config", str(small / "small.toml"), "--traffic", str(out / "tape.parquet"),
         "--swarms", "visit-gain,nowcast-gain", "--no-ceiling", "--no-report", "--quiet",
         "--history", str(history), "--out", str(replay)]
    )  # fmt: skip
    assert code == 0
    pd.testing.assert_frame_equal(pd.read_csv(replay / "belief_models.csv"), table)


def test_nowcast_gain_without_history_is_one_line_and_exit_2(small, tmp_path, capsys):
    out = tmp_path / "refused"
    code = twin_main(["run", "--config", str(small / "small.toml"), "--swarms", "nowcast-gain",
                      "--no-ceiling", "--no-report", "--quiet", "--out", str(out)])  # fmt: skip
    err = capsys.readouterr().err.strip()
    assert code == 2 and "Traceback" not in err
    assert err.splitlines()[-1].startswith("twin: error: ") and "--history FILE" in err
    assert not out.exists()


def test_history_needs_two_distinct_simulations(small, history, tmp_path, capsys):
    days = history.parent / "days"
    one = days / "tapes" / "seed-0.parquet"
    code = twin_main(["history", "--from", str(one), "--out", str(tmp_path / "h.npz")])
    err = capsys.readouterr().err.strip()
    assert code == 2 and "at least 2" in err and "\n" not in err
    code = twin_main(["history", "--from", str(one), str(one), "--out", str(tmp_path / "h.npz")])
    err = capsys.readouterr().err.strip()
    assert code == 2 and "SUMO seed 10 again" in err
    code = twin_main(["history", "--from", str(tmp_path), "--out", str(tmp_path / "h.npz")])
    err = capsys.readouterr().err.strip()
    assert code == 2 and "no tape.parquet" in err
    assert not (tmp_path / "h.npz").exists()


def test_history_never_overwrites_a_file(history, tmp_path, capsys):
    days = history.parent / "days"
    mine = tmp_path / "mine.npz"
    mine.write_bytes(b"keep")
    code = twin_main(["history", "--from", str(days), "--out", str(mine)])
    err = capsys.readouterr().err.strip()
    assert code == 2 and "exists; give a new file name" in err and "\n" not in err
    assert mine.read_bytes() == b"keep"


def test_history_out_into_missing_folders_creates_them(history, tmp_path, capsys):
    """--out's missing folders are created (the check before the work accepted them), and the
    written file is the one named, never a temporary name."""
    days = history.parent / "days"
    out = tmp_path / "new" / "sub" / "h.npz"
    assert twin_main(["history", "--from", str(days), "--out", str(out)]) == 0
    assert f"written: {out}" in capsys.readouterr().out
    assert History.load(out).n_runs == 2
    assert sorted(p.name for p in out.parent.iterdir()) == ["h.npz"]


@pytest.mark.parametrize("dtype", ["complex64", "U12"])
def test_a_history_of_other_than_real_numbers_is_refused(history, tmp_path, dtype):
    with np.load(history) as data:
        arrays = dict(data)
    arrays["mean"] = arrays["mean"].astype(dtype)
    bad = tmp_path / "bad.npz"
    np.savez(bad, **arrays)
    with pytest.raises(UserError, match=r"mean holds .* not real numbers"):
        History.load(bad)


@pytest.mark.parametrize(
    ("edit", "words"),
    [
        ({"n_runs": 1}, r"traffic_seeds = \[10, 11\] are not distinct seeds of its n_runs = 1"),
        ({"n_runs": 0}, r"n_runs = 0 is not a whole number >= 1"),
        ({"n_runs": "2"}, r"n_runs = '2' is not a whole number"),
        ({"traffic_seeds": [10, 10]}, r"traffic_seeds = \[10, 10\] are not distinct"),
        ({"traffic_seeds": [-5, 11]}, r"traffic_seeds holds -5, not a SUMO seed"),
        ({"traffic_seeds": [10, 2**70]}, r"traffic_seeds holds 1180591620717411303424, not a"),
        ({"sources": ["a"]}, r"sources = \['a'\] do not name its n_runs = 2 days"),
        ({"sources": []}, r"sources = \[\] do not name its n_runs = 2 days"),
    ],
)
def test_a_history_whose_info_contradicts_itself_is_refused(history, tmp_path, edit, words):
    """Its days, their seeds and their sources are counted alike (a history built from two
    SUMO seeds says n_runs = 2, two distinct seeds, two sources)."""
    import json

    with np.load(history) as data:
        arrays = dict(data)
    info = json.loads(str(arrays["info"]))
    assert info["n_runs"] == 2 and info["traffic_seeds"] == [10, 11] and len(info["sources"]) == 2
    arrays["info"] = np.array(json.dumps({**info, **edit}))
    bad = tmp_path / "bad.npz"
    np.savez(bad, **arrays)
    with pytest.raises(UserError, match=words) as caught:
        History.load(bad)
    assert "\n" not in str(caught.value)


def test_a_history_whose_days_seeds_are_unknown_says_what_it_cannot_check(
    history, tmp_path, capsys
):
    """`twin history` records each day's SUMO seed: a file naming its days (sources) without
    all their seeds is refused; one of unnamed days without seeds (built in memory) says, on
    a run, that nothing keeps an evaluated day out of it (probe 20's f01: an emptied list
    passed silently)."""
    import json

    with np.load(history) as data:
        arrays = dict(data)
    info = json.loads(str(arrays["info"]))
    edits = {"partly": {"traffic_seeds": [11]}, "unnamed": {"traffic_seeds": [], "sources": []}}
    for name, edit in edits.items():
        arrays["info"] = np.array(json.dumps({**info, **edit}))
        np.savez(tmp_path / f"{name}.npz", **arrays)
    with pytest.raises(UserError, match=r"traffic_seeds = \[11\] do not give the seed of each"):
        History.load(tmp_path / "partly.npz")
    for path, said in ((history, False), (tmp_path / "unnamed.npz", True)):
        h = History.load(path)
        h.check_matches(path, h.obstacles, h.horizon, traffic_seeds=[0])
        err = capsys.readouterr().err
        assert ("2 of the history's 2 days have no recorded SUMO seed" in err) == said, err


def test_a_history_of_sumo_days_is_refused_for_synthetic_traffic(history, tmp_path, capsys):
    out = tmp_path / "out"
    code = twin_main(["evaluate", "--config", "synthetic", "--history", str(history), "--seeds",
                      "1", "--swarms", "random", "--quiet", "--no-report", "--out", str(out)])  # fmt: skip
    err = capsys.readouterr().err
    assert code == 2 and err.count("\n") == 1 and "Traceback" not in err, err
    assert "a history of SUMO days (from 00:05:00) for synthetic traffic" in err, err
    assert not out.exists()


def test_history_out_is_claimed_for_one_command_and_freed_on_a_refusal(history, tmp_path, capsys):
    """Two `twin history` into one --out at once: the file is claimed (created and locked)
    before the work, so the second is refused rather than both ending well; a claim left by a
    killed command is taken over; a refusal after the claim leaves no file."""
    import os

    from twin.cli.history import _claim

    out = tmp_path / "h.npz"
    held = _claim(out)
    assert held is not None and out.exists()
    with pytest.raises(UserError, match="another command is writing it now"):
        _claim(out)
    os.close(held)  # the command was killed: its empty claim is taken over, not in the way
    os.close(_claim(out))
    out.write_bytes(b"a history")
    with pytest.raises(UserError, match="exists; give a new file name"):
        _claim(out)
    one_day = history.parent / "days" / "tape.parquet"
    lonely = tmp_path / "lonely.npz"
    assert twin_main(["history", "--from", str(one_day), "--out", str(lonely)]) == 2
    assert "a history needs at least 2" in capsys.readouterr().err
    assert not lonely.exists()


def test_a_history_of_generated_days_is_refused_for_a_sumo_run(small, tmp_path, capsys):
    """A history of generated days (`twin history --dynamics`, no clock) for a SUMO run of the
    same grid size: refused in one line, as the converse is (it ran the synthetic days as
    the network's prior: probe 12's h01)."""
    config = tmp_path / "generated.toml"
    config.write_text(
        (ROOT / "configs" / "synthetic.toml").read_text().replace("horizon = 2000", "horizon = 8")
    )
    days = tmp_path / "generated.npz"
    assert twin_main(["history", "--dynamics", str(config), "--days", "2", "--seed", "5",
                      "--out", str(days)]) == 0  # fmt: skip
    capsys.readouterr()
    out = tmp_path / "out"
    assert twin_main(run_args(small, out, "--history", str(days))) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "a history of generated days" in err, err
    assert not out.exists()


@pytest.fixture(scope="module")
def believed(small, history, tmp_path_factory) -> Path:
    """A finished run with the history: its belief_maps.npz and belief_models.csv."""
    out = tmp_path_factory.mktemp("believed") / "run"
    assert twin_main(run_args(small, out, "--history", str(history))) == 0
    return out


def _maps_edit(key: str, value):
    def edit(maps: dict) -> None:
        maps[key] = value(maps[key]) if callable(value) else value

    return edit


def _row_edit(swarm: str, model: str, **values):
    def edit(table: pd.DataFrame) -> pd.DataFrame:
        at = (table["swarm"] == swarm) & (table["model"] == model)
        for column, value in values.items():
            table[column] = table[column].astype(object)
            table.loc[at, column] = value
        return table

    return edit


#: Forgeries of belief_maps.npz and belief_models.csv the report refuses, each a value twin
#: can tell is wrong (probe 15's f13): name -> (file, edit, words of the one-line error).
BELIEF_FORGERIES = {
    "truth above 1": ("belief_maps.npz", _maps_edit("truth", lambda a: a * 0 + 2.0),
                      "truth holds values outside 0 .. 1"),
    "negative std": ("belief_maps.npz", _maps_edit("std", lambda a: a * 0 - 1.0),
                     "std holds negative values"),
    "steps past T": ("belief_maps.npz", _maps_edit("steps", lambda a: a + 99),
                     "are not rising steps within 0 .. "),
    "swarm not run": ("belief_maps.npz", _maps_edit("swarms", np.array('["a", "b"]')),
                      "swarms: swarm 'a' has no row in summary.csv"),
    "seed not run": ("belief_maps.npz", _maps_edit("seed", np.array(77)),
                     "seed = 77 has no results"),
    "threshold NaN": ("belief_maps.npz", _maps_edit("threshold", np.array(np.nan)),
                      "threshold = nan, not in (0, 1]"),
    "unknown model": ("belief_models.csv", lambda t: t.assign(model="psychic"),
                      "model 'psychic' is none of twin's belief models"),
    "more seeds than run": ("belief_models.csv", lambda t: t.assign(n_seeds=7),
                            "n_seeds = 7 for swarm"),
    "history row removed": ("belief_models.csv", lambda t: t[t["swarm"] != NO_DRONES],
                            "model 'history' is missing"),
    # the numbers the folder determines (probe 15's P2-f04)
    "last-seen error": ("belief_models.csv", _row_edit("random", "last-seen", belief_error=0.9),
                        "belief_error = 0.9, but summary.csv's belief_error"),
    "one row's events": ("belief_models.csv", _row_edit("random", "nowcast", events=77),
                         "the rows count different events"),
    "every row's events": ("belief_models.csv", lambda t: t.assign(events=t["events"] + 5),
                           "but events.parquet holds"),
    "minutes": ("belief_models.csv", lambda t: t.assign(latency_median_min=999.0),
                "latency_median_min = 999, but the row's steps and step_s"),
    "alarm rate": ("belief_models.csv", lambda t: t.assign(false_alarms_per_hour=1e9),
                   "false_alarms_per_hour = 1e+09, but the row's steps"),
    "a swarm's nowcast removed": (
        "belief_models.csv",
        lambda t: t[~((t["swarm"] == "greedy") & (t["model"] == "nowcast"))],
        "swarm 'greedy' has the models ['last-seen']"),
    "events known": ("belief_models.csv",
                     _row_edit("random", "nowcast", pct_events_known=33.25),
                     "pct_events_known = 33.25, but belief_maps.npz's known_at gives"),
    # the models replayed with the run's history (probe 16's P2-b1, P2-b2)
    "a nowcast's error": ("belief_models.csv", _row_edit("random", "nowcast", belief_error=0.3),
                          "belief_error = 0.3 for swarm 'random', model 'nowcast', but the "
                          "models replayed with the run's history give"),
    "the history's calibration": ("belief_models.csv",
                                  _row_edit(NO_DRONES, "history", calibration_90=0.123),
                                  "calibration_90 = 0.123 for swarm '(no drones)', model "
                                  "'history', but the models replayed"),
    # a column dropped: the report left it out (probe 20's P2-f09c)
    **{f"{column} dropped": ("belief_models.csv", lambda t, c=column: t.drop(columns=c),
                             f"belief_models.csv: no column {column!r}")
       for column in ("calibration_90", "false_alarms_per_hour", "n_seeds")},
    "truth halved": ("belief_maps.npz", _maps_edit("truth", lambda a: a * 0.5),
                     "but the nowcast replayed with the run's history gives"),
    "nowcast std zero": ("belief_maps.npz", _maps_edit("std", lambda a: a * 0),
                         "std[0, 0, 0, 0] = 0, but the nowcast replayed"),
}  # fmt: skip


@pytest.mark.parametrize("name", list(BELIEF_FORGERIES))
def test_forged_belief_files_are_refused(believed, tmp_path, capsys, name):
    import shutil

    from test_boundary import refresh_manifest

    file, edit, words = BELIEF_FORGERIES[name]
    run = tmp_path / "run"
    shutil.copytree(believed, run)
    if file.endswith(".npz"):
        with np.load(run / file) as npz:
            maps = {k: npz[k] for k in npz.files}
        edit(maps)
        np.savez(run / file, **maps)
    else:
        edit(pd.read_csv(run / file)).to_csv(run / file, index=False)
    refresh_manifest(run)
    capsys.readouterr()
    assert twin_main(["report", str(run), "--no-animation"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and file in err and words in err, err


def test_the_unforged_belief_files_read_back(believed, capsys):
    assert twin_main(["report", str(believed), "--no-animation"]) == 0, capsys.readouterr().err


def test_history_days_past_the_memory_limit_are_refused_before_any(tmp_path, capsys):
    """``twin history --dynamics`` on a grid whose days do not fit the limit: one line with
    the estimate before any day is computed (it allocated, then died or said "out of
    memory"; probe 15's f10)."""
    config = tmp_path / "big.toml"
    config.write_text(
        '[grid]\nnx = 2000\nny = 2000\n[traffic]\nkind = "synthetic"\nhorizon = 2000\n'
        'disturbances = [{ kind = "big", i = 2, j = 2, amplitude = 1.0, sigma = 1.0 }]\n'
    )
    out = tmp_path / "h.npz"
    argv = ["history", "--dynamics", str(config), "--days", "2", "--out", str(out)]
    assert twin_main([*argv, "--max-memory-gb", "1"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "2 days of 2000 x 2000 cells x 2001 maps need about" in err
    assert "over the 1 GB limit" in err and not out.exists()


@pytest.mark.parametrize(
    ("key", "value", "words"),
    [("step_s", "abc", "step_s = 'abc' is not a step in seconds > 0"),
     ("step_s", [1, 2], "step_s = '[1, 2]' is not a step"),
     ("begin", 25200.0, "begin = '25200.0' is not a clock time")],
)  # fmt: skip
def test_a_history_with_forged_info_is_refused(history, tmp_path, key, value, words):
    """A history whose info names a step or a start of the wrong kind: one line (it was used
    as if valid; probe 15's f12)."""
    with np.load(history) as npz:
        arrays = {k: npz[k] for k in npz.files}
    info = json.loads(str(arrays["info"]))
    info[key] = value
    arrays["info"] = np.array(json.dumps(info))
    forged = tmp_path / "forged.npz"
    np.savez(forged, **arrays)
    with pytest.raises(UserError, match=words.replace("[", r"\[").replace("(", r"\(")):
        History.load(forged)


def test_a_history_seed_clash_advises_seeds_past_both(small, history, tmp_path, capsys):
    """The advised fix of a history built on a seed the run evaluates names seeds past both
    (it named the clashing seed again; probe 15's f20)."""
    code = twin_main(
        run_args(small, tmp_path / "o", "--history", str(history), "--sumo-seed", "11")
    )
    err = capsys.readouterr().err.strip().splitlines()[-1]
    assert (
        code == 2 and "(for a run of --sumo-seed s and --seeds n, from --sumo-seed s+n on)" in err
    ), err


def test_a_history_from_tapes_past_the_memory_limit_is_refused(
    history, tmp_path, capsys, monkeypatch
):
    """``twin history --from`` estimates its tapes' memory before replaying them, and refuses
    a limit that is no number (both were ignored; probe 15's P2-f03)."""
    days = history.parent / "days"
    argv = ["history", "--from", str(days), "--out", str(tmp_path / "h.npz")]
    assert twin_main([*argv, "--max-memory-gb", "0.00001"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "--from: 2 tapes of " in err and "over the 1e-05 GB" in err
    monkeypatch.setenv("TWIN_MAX_MEMORY_GB", "abc")
    assert twin_main(argv) == 2
    err = capsys.readouterr().err
    assert (
        err
        == "twin: error: TWIN_MAX_MEMORY_GB = 'abc' is not a number; give the limit in GB, e.g. 8\n"
    )
    assert not (tmp_path / "h.npz").exists()


def test_belief_rates_of_a_timed_run_read_back_and_forged_ones_do_not(tmp_path):
    """Minutes and rates of belief_models.csv are its steps (k = 0 .. T) over step_s: a table
    twin writes for a run of 60 s steps, with events and false alarms, agrees with the check,
    and one alarm more per hour does not (the read-back of probe 15's P2-f04)."""
    from twin.belief import belief_table, summarize
    from twin.config import load_config
    from twin.experiment import Experiment, run_experiment
    from twin.report.derived import Primary
    from twin.report.load import check_belief_scores, load_run

    config = tmp_path / "s.toml"
    config.write_text(
        '[grid]\nnx = 8\nny = 8\n[swarm]\nn_drones = 3\n[traffic]\nkind = "synthetic"\n'
        'horizon = 40\ndisturbances = [{ kind = "big", i = 3, j = 3, amplitude = 1.0, '
        'sigma = 2.0 }, { kind = "small", i = 6, j = 6, amplitude = 0.5, sigma = 1.0 }]\n'
    )
    history = tmp_path / "h.npz"
    assert twin_main(["history", "--dynamics", str(config), "--days", "3", "--out",
                      str(history)]) == 0  # fmt: skip
    run = tmp_path / "run"
    assert twin_main(["evaluate", "--config", str(config), "--history", str(history), "--seeds",
                      "2", "--swarms", "random,greedy", "--no-report", "--quiet", "--out",
                      str(run)]) == 0  # fmt: skip
    outcome = run_experiment(Experiment(load_config(config), swarms=["random", "greedy"],
                                        seeds=[0, 1]))  # fmt: skip
    frames = [belief_table(r, History.load(history), step_s=60.0) for r in outcome.results]
    table = summarize(pd.concat(frames, ignore_index=True))
    assert (table["false_alarms"] > 0).any() and (table["events"] > 0).all()
    rf = load_run(run)
    timed = {**rf.run, "traffic": {**rf.run["traffic"], "step_s": 60.0}}
    primary = Primary(run, rf.series, rf.trajectories, rf.events, rf.obstacles, timed,
                      ["random", "greedy"], summary=rf.summary)  # fmt: skip
    check_belief_scores(run, table, primary, rf.belief_maps)
    forged = table.assign(false_alarms_per_hour=table["false_alarms_per_hour"] + 1.0)
    with pytest.raises(UserError, match="false_alarms_per_hour = "):
        check_belief_scores(run, forged, primary, rf.belief_maps)


def test_a_stray_tape_in_a_run_folder_is_no_day_of_its_history(history, tmp_path, capsys):
    """A tape planted in a run folder's tapes/ under a seed the run does not have: one line,
    no history (it became a day of it; probe 16's f15)."""
    import shutil

    days = tmp_path / "days"
    shutil.copytree(history.parent / "days", days)
    planted = days / "tapes" / "seed-7.parquet"
    shutil.copy(sorted((days / "tapes").glob("seed-*.parquet"))[0], planted)
    out = tmp_path / "h.npz"
    capsys.readouterr()
    assert twin_main(["history", "--from", str(days), "--out", str(out)]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and f"{planted}: no tape of the run's seeds" in err, err
    assert not out.exists()


def test_a_later_seeds_tape_removed_with_its_manifest_entry_is_refused(history, tmp_path, capsys):
    """A live run of two seeds keeps each seed's tape in tapes/: one removed with its manifest
    entry left the later seed's maps unreplayed, silently; it is refused in one line."""
    import shutil

    from test_boundary import refresh_manifest

    days = tmp_path / "days"
    shutil.copytree(history.parent / "days", days)
    (days / "tapes" / "seed-1.parquet").unlink()
    refresh_manifest(days)
    capsys.readouterr()
    assert twin_main(["report", str(days), "--no-animation"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1, err
    assert "tapes/seed-1.parquet is missing, which a live SUMO run writes" in err, err
    assert not (days / "report").exists()


def test_beliefs_whose_history_is_gone_are_not_replayed_and_say_so(believed, tmp_path, capsys):
    """A run folder whose history file changed since: its belief models read back with a
    notice that they are not replayed (ranges and relations checked), not refused."""
    import shutil

    from test_boundary import refresh_manifest

    run = tmp_path / "run"
    shutil.copytree(believed, run)
    meta = json.loads((run / "run.json").read_text())
    assert Path(meta["history"]["path"]).is_file() and len(meta["history"]["sha256"]) == 64
    meta["history"]["sha256"] = "0" * 64
    (run / "run.json").write_text(json.dumps(meta))
    refresh_manifest(run)
    capsys.readouterr()
    assert twin_main(["report", str(run), "--no-animation"]) == 0
    err = capsys.readouterr().err
    assert "belief_models.csv and belief_maps.npz not replayed (the history " in err, err


@pytest.mark.parametrize(
    ("record", "folder_format", "words"),
    [
        ([1], 4, "history must be an object"),
        ({"path": 3}, 4, "history.path = 3 must be text"),
        (None, 4, "history = null names no history file and its sha256"),
        ({"path": "h.npz"}, 4, 'history = {"path": "h.npz"} names no history file'),
        ({"path": "h.npz", "sha256": "0" * 64}, 4, "history.path = 'h.npz' is not an absolute"),
        (None, 3, None),  # an earlier twin's folder: a notice, not a refusal
    ],
)
def test_a_history_record_that_names_no_file_is_refused_in_a_current_folder(
    believed, tmp_path, capsys, record, folder_format, words
):
    """run.json's ``history`` edited alone (the file still there) turned the belief replay off
    with a notice blaming an earlier twin (probe 19's f02): a folder of format 4 records it."""
    import shutil

    from test_boundary import as_format_3_wrote, refresh_manifest

    run = tmp_path / "run"
    shutil.copytree(believed, run)
    meta = json.loads((run / "run.json").read_text())
    meta["history"], meta["folder_format"] = record, folder_format
    if folder_format < 4:
        as_format_3_wrote(run)
    (run / "run.json").write_text(json.dumps(meta))
    refresh_manifest(run)
    capsys.readouterr()
    code = twin_main(["report", str(run), "--no-animation"])
    err = capsys.readouterr().err
    if words is None:
        assert code == 0 and "not replayed (run.json records no history file" in err, err
    else:
        assert code == 2 and err.count("\n") == 1 and words in err, err
        assert str(run / "run.json") in err, err


def test_beliefs_and_maps_of_a_run_on_a_tape_are_replayed_with_its_tape(
    believed, history, small, tmp_path, capsys
):
    """`twin evaluate --traffic TAPE --history H`: run.json names the tape and its sha256, and
    the read-back replays its maps and, with them, the belief models (probe 17's f05: forged
    belief rows were accepted with a notice that the tape was not replayed). A tape changed
    since: read back with that notice."""
    import shutil

    from test_boundary import refresh_manifest

    tape = tmp_path / "tape.parquet"
    shutil.copy(believed / "tape.parquet", tape)
    out = tmp_path / "on-tape"
    argv = ["evaluate", "--config", str(small / "small.toml"), "--traffic", str(tape),
            "--swarms", "visit-gain", "--no-ceiling", "--no-report", "--quiet", "--history",
            str(history), "--out", str(out)]  # fmt: skip
    assert twin_main(argv) == 0
    record = json.loads((out / "run.json").read_text())["traffic"]["tape_file"]
    assert record["path"] == str(tape.resolve()) and len(record["sha256"]) == 64
    capsys.readouterr()
    assert twin_main(["report", str(out), "--no-animation"]) == 0
    assert "not replayed" not in capsys.readouterr().err

    def forged(edit) -> str:
        run = tmp_path / "forged"
        shutil.rmtree(run, ignore_errors=True)
        shutil.copytree(out, run)
        edit(run)
        refresh_manifest(run)
        capsys.readouterr()
        code = twin_main(["report", str(run), "--no-animation"])
        return f"{code} {capsys.readouterr().err}"

    def belief_error(run):
        table = pd.read_csv(run / "belief_models.csv")
        table.loc[table["model"] == "nowcast", "belief_error"] *= 0.5
        table.to_csv(run / "belief_models.csv", index=False)

    def importance(run):
        with np.load(run / "importance.npz") as npz:
            maps = {k: npz[k] for k in npz.files}
        maps["importance"][3, 1, 1] = 0.5 * maps["importance"][3, 1, 1] + 0.25
        np.savez_compressed(run / "importance.npz", **maps)

    said = forged(belief_error)
    assert said.startswith("2 ") and "belief_error = " in said, said
    assert "the models replayed with the run's history gives" in said, said
    said = forged(importance)
    assert said.startswith("2 ") and "importance.npz: importance at step 3, cell (1, 1)" in said
    assert "(the tape run.json names) replayed through its MFD gives" in said, said
    with open(tape, "ab") as fh:  # the tape changed since: the models are not replayed
        fh.write(b" ")
    said = forged(belief_error)
    assert said.startswith("0 ") and "not replayed (seed " in said, said


def test_a_swarms_own_history_holding_the_evaluated_day_is_refused(small, history, tmp_path,
                                                                    capsys):  # fmt: skip
    """nowcast-gain's ``[swarm_options.nowcast-gain].history`` built from the SUMO seed the run
    evaluates on: it planned on a prior holding its own day; the same file as ``--history`` is
    refused (probe 20's P2-f07a)."""
    config = small / "own.toml"  # beside the scenario files it names
    config.write_text(
        (small / "small.toml")
        .read_text()
        .replace(
            "[traffic]", f'[swarm_options.nowcast-gain]\nhistory = "{history}"\n\n[traffic]', 1
        )
    )
    out = tmp_path / "own"
    argv = ["run", "--config", str(config), "--swarms", "random,nowcast-gain", "--no-ceiling",
            "--no-report", "--quiet", "--out", str(out)]  # fmt: skip
    assert twin_main([*argv, "--sumo-seed", "10"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "Traceback" not in err, err
    assert f"{history}: history built from traffic seed 10, which this run evaluates on" in err
    assert twin_main([*argv, "--sumo-seed", "3"]) == 0, capsys.readouterr().err


def test_a_history_of_days_on_other_network_files_says_so(history, tmp_path, capsys):
    """Days of other demand make a history; days whose network files differ were taken
    without a word, their cells paired by position (probe 28's z02)."""
    import json

    import pyarrow.parquet as pq

    tapes = history.parent / "days" / "tapes"
    a, b = tapes / "seed-0.parquet", tmp_path / "other-network.parquet"
    table = pq.read_table(tapes / "seed-1.parquet")
    meta = json.loads(table.schema.metadata[b"twin_tape"])
    meta["settings"]["identity"]["net_sha256"] = "f" * 64  # another network file
    pq.write_table(table.replace_schema_metadata({b"twin_tape": json.dumps(meta).encode()}), b)
    assert twin_main(["history", "--from", str(a), str(b), "--out", str(tmp_path / "h.npz")]) == 0
    notices = [x for x in capsys.readouterr().err.splitlines() if "another network" in x]
    assert len(notices) == 1 and notices[0].startswith(f"twin: notice: {b} ran on"), notices
    assert twin_main(["history", "--from", str(a), str(tapes / "seed-1.parquet"), "--out",
                      str(tmp_path / "h2.npz")]) == 0  # fmt: skip
    assert "another network" not in capsys.readouterr().err
