"""`twin evaluate` on good and bad input: a run folder, or one line and exit code 2."""

import subprocess
import sys

import pandas as pd
import pytest

from twin.cli import main

SMALL = """
[grid]
nx = 6
ny = 8
obstacles = [[0, 0], [3, 4]]
[swarm]
n_drones = 3
{starts}
eta = {eta}
[traffic]
kind = "synthetic"
horizon = 40
disturbances = [{{ kind = "big", i = 2, j = 2, amplitude = 1.0, sigma = 2.0 }}]
[evaluate]
swarms = ["random", "greedy", "sweeping"]
"""


def write(tmp_path, name="c.toml", starts="", eta=0.1, extra=""):
    path = tmp_path / name
    path.write_text(SMALL.format(starts=starts, eta=eta) + extra)
    return path


def test_evaluate_writes_the_run_folder(tmp_path, capsys):
    cfg = write(tmp_path)
    out = tmp_path / "run"
    assert (
        main(
            [
                "evaluate",
                "--config",
                str(cfg),
                "--seeds",
                "3",
                "--out",
                str(out),
                "--no-report",
                "--quiet",
            ]
        )
        == 0
    )
    printed = capsys.readouterr().out
    assert "R_hat_T" in printed and "greedy" in printed
    summary = pd.read_csv(out / "summary.csv")
    per_seed = pd.read_csv(out / "per_seed.csv")
    series = pd.read_parquet(out / "series.parquet")
    ceilings = ["oracle (ceiling)", "bound (ceiling)"]
    assert list(summary.swarm) == ["random", "greedy", "sweeping", *ceilings]
    assert list(summary.role) == ["swarm"] * 3 + ["ceiling"] * 2
    assert (summary.n_seeds == 3).all() and len(per_seed) == 9 + 2 * 3
    assert len(series) == 3 * 3 * 40
    # the summary is the mean of the per-seed rows, which are the means of the series
    g = series[series.seed == 0].groupby("swarm", sort=False)["reward"].mean()
    swarms = per_seed[(per_seed.seed == 0) & (per_seed.role == "swarm")]
    assert swarms.set_index("swarm").R_hat_T.to_dict() == pytest.approx(g.to_dict())
    assert summary.set_index("swarm").R_hat_T.to_dict() == pytest.approx(
        per_seed.groupby("swarm").R_hat_T.mean().to_dict()
    )
    for name in ("trajectories.parquet", "importance.npz", "run.json"):
        assert (out / name).exists()


def test_refuses_to_overwrite_a_run(tmp_path):
    cfg = write(tmp_path)
    out = tmp_path / "run"
    args = ["evaluate", "--config", str(cfg), "--out", str(out), "--no-report", "--quiet"]
    assert main(args) == 0
    before = (out / "summary.csv").read_bytes()
    assert main(args) == 2
    assert (out / "summary.csv").read_bytes() == before


@pytest.mark.parametrize(
    ("kwargs", "needle"),
    [
        ({"eta": 1.5}, "[swarm].eta"),
        ({"eta": 0}, "[swarm].eta"),
        ({"starts": "starts = [[0, 0], [1, 1], [2, 2]]"}, "obstacle"),
        ({"starts": "starts = [[9, 0], [1, 1], [2, 2]]"}, "off the 6 x 8 map"),
        ({"starts": "starts = [[1, 1], [1, 1], [2, 2]]"}, "two drones on one cell"),
        ({"starts": "starts = [[1, 1]]"}, "1 cells for 3 drones"),
        ({"starts": "colour = 1"}, "[swarm].colour"),
        ({"extra": "[oops]\n"}, "[oops]"),
    ],
)
def test_bad_config_gets_one_line(tmp_path, capsys, kwargs, needle):
    cfg = write(tmp_path, **kwargs)
    assert main(["evaluate", "--config", str(cfg), "--out", str(tmp_path / "o"), "--quiet"]) == 2
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0 and needle in err and str(cfg) in err
    assert not (tmp_path / "o" / "summary.csv").exists()


def test_more_drones_than_free_cells(tmp_path, capsys):
    cfg = tmp_path / "tiny.toml"
    cfg.write_text("[grid]\nnx = 2\nny = 2\nobstacles = [[0, 0], [1, 1]]\n[swarm]\nn_drones = 3\n")
    assert main(["evaluate", "--config", str(cfg), "--quiet"]) == 2
    assert "exceeds the 2 free cells" in capsys.readouterr().err


def test_grid_without_free_cells(tmp_path, capsys):
    cfg = tmp_path / "full.toml"
    cfg.write_text("[grid]\nnx = 1\nny = 2\nobstacles = [[0, 0], [0, 1]]\n")
    assert main(["evaluate", "--config", str(cfg), "--quiet"]) == 2
    assert "leave at least one free cell" in capsys.readouterr().err


@pytest.mark.parametrize("kind", ["missing", "folder", "binary", "not-toml"])
def test_unreadable_config(tmp_path, capsys, kind):
    path = tmp_path / "x.toml"
    if kind == "folder":
        path.mkdir()
    elif kind == "binary":
        path.write_bytes(b"\xff\xfe\x00\x01")
    elif kind == "not-toml":
        path.write_text("this is = = not toml")
    assert main(["evaluate", "--config", str(path), "--quiet"]) == 2
    err = capsys.readouterr().err
    assert str(path) in err and err.count("\n") == 1


def test_unknown_swarm(tmp_path, capsys):
    assert main(["evaluate", "--config", str(write(tmp_path)), "--swarms", "greedy,bogus"]) == 2
    assert "bogus" in capsys.readouterr().err


def test_console_script_help_and_no_traceback(tmp_path):
    out = subprocess.run(
        [sys.executable, "-m", "twin", "evaluate", "--help"], capture_output=True, text=True
    )
    assert out.returncode == 0 and "--seeds" in out.stdout
    bad = subprocess.run(
        [sys.executable, "-m", "twin", "evaluate", "--config", str(tmp_path / "none.toml")],
        capture_output=True,
        text=True,
    )
    assert bad.returncode == 2 and "Traceback" not in bad.stderr and "not found" in bad.stderr


def test_swarm_options_reach_the_swarm_and_bad_ones_get_one_line(tmp_path, capsys):
    cfg = write(tmp_path, extra="[swarm_options.rl-decentralized]\neps = 0.5\n")
    out = tmp_path / "run"
    args = ["evaluate", "--config", str(cfg), "--swarms", "rl-decentralized", "--out", str(out)]
    assert main([*args, "--no-report", "--quiet"]) == 0
    import json

    described = json.loads((out / "run.json").read_text())["policies"]["rl-decentralized"]
    assert described["eps"] == 0.5
    bad = write(tmp_path, name="bad.toml", extra="[swarm_options.greedy]\nspeed = 3\n")
    assert main(["evaluate", "--config", str(bad), "--quiet", "--out", str(tmp_path / "b")]) == 2
    assert "[swarm_options.greedy]" in capsys.readouterr().err
    # options of a swarm that does not exist would be silently unused: refused
    for name in ("nosuch", "greedy@x"):
        bad = write(tmp_path, name="bad.toml", extra=f'[swarm_options."{name}"]\nweight = 1\n')
        out = tmp_path / f"b-{name}"
        assert main(["evaluate", "--config", str(bad), "--quiet", "--out", str(out)]) == 2
        err = capsys.readouterr().err.strip()
        assert "\n" not in err and f"[swarm_options.{name}]:" in err and "swarm" in err
        assert not out.exists()


def test_a_runs_tape_replays_with_the_runs_swarm(tmp_path, capsys):
    """``twin evaluate --traffic RUN/tape.parquet`` without --config replays with the run's
    swarm (its run.json: drones, starts, weights), said in a notice: the README's "same swarm
    results" (it used synthetic.toml's 4 drones silently; probe 15's f28)."""
    from helpers import small_sumo_scenario

    (tmp_path / "s").mkdir()
    folder = small_sumo_scenario(tmp_path / "s", horizon=4)
    run = tmp_path / "run"
    common = ["--swarms", "random,greedy", "--no-ceiling", "--no-report", "--quiet"]
    assert main(["run", "--config", str(folder / "small.toml"), *common, "--out", str(run)]) == 0
    capsys.readouterr()
    assert (
        main(
            [
                "evaluate",
                "--traffic",
                str(run / "tape.parquet"),
                *common[:-1],  # not --quiet: the table's title names the tape
                "--out",
                str(tmp_path / "ev"),
            ]
        )
        == 0
    )
    said = capsys.readouterr()
    assert "the swarm of" in said.err
    # titled by the tape, not by synthetic.toml, whose traffic it did not use (probe 25's f04)
    assert f"Table 2 analog (the tape {run / 'tape.parquet'}, 1 seed from 0" in said.out, said.out
    live = pd.read_csv(run / "per_seed.csv").set_index("swarm")["R_hat_T"]
    replayed = pd.read_csv(tmp_path / "ev" / "per_seed.csv").set_index("swarm")["R_hat_T"]
    assert replayed.to_dict() == pytest.approx(live.to_dict(), rel=1e-12)


def test_a_tape_out_of_its_run_folder_says_whose_swarm_replays_it(tmp_path, capsys):
    """A tape copied away from its run.json replays with the config's swarm: said in a
    notice, as when the run.json is another run's (it was silent: probe 26's u05)."""
    import shutil

    run, _ = _small_sumo_run(tmp_path, capsys, "--drones", "2")
    tape = tmp_path / "copied.parquet"
    shutil.copy(run / "tape.parquet", tape)
    argv = ["evaluate", "--traffic", str(tape), "--swarms", "random", "--no-ceiling"]
    assert main([*argv, "--no-report", "--out", str(tmp_path / "ev")]) == 0
    err = capsys.readouterr().err
    assert f"no run.json beside {tape} (not in its run folder), so synthetic.toml's swarm" in err


def test_a_synthetic_configs_grid_set_aside_by_a_tape_is_said(tmp_path, capsys):
    """``--traffic TAPE --config C``: C's explicit [grid] gave way to the tape's silently, and
    its starts were then refused as off "the 7 x 7 map" (probe 26b's g05)."""
    run, _ = _small_sumo_run(tmp_path, capsys, "--drones", "2")  # a grid other than 6 x 8
    cfg = tmp_path / "c.toml"
    cfg.write_text(
        '[grid]\nnx = 6\nny = 8\n[swarm]\nn_drones = 2\n[traffic]\nkind = "synthetic"\n'
        "horizon = 30\n"
    )
    argv = ["evaluate", "--traffic", str(run / "tape.parquet"), "--config", str(cfg)]
    assert main([*argv, "--swarms", "random", "--no-ceiling", "--no-report", "--out",
                 str(tmp_path / "ev")]) == 0  # fmt: skip
    err = capsys.readouterr().err
    assert "grid replaces c.toml's [grid] of 6 x 8" in err, err


def _small_sumo_run(tmp_path, capsys, *extra):
    """A `twin run` of a small SUMO scenario (4 steps) in ``tmp_path/run``, and the display
    and swarm flags it took."""
    from helpers import small_sumo_scenario

    (tmp_path / "s").mkdir()
    folder = small_sumo_scenario(tmp_path / "s", horizon=4)
    run = tmp_path / "run"
    common = ["--swarms", "random", "--no-ceiling", "--no-report", "--quiet"]
    argv = ["run", "--config", str(folder / "small.toml"), *extra, *common]
    assert main([*argv, "--out", str(run)]) == 0
    capsys.readouterr()
    return run, common


def test_a_damaged_or_foreign_run_json_beside_a_tape_is_not_taken_silently(tmp_path, capsys):
    """The run.json of a tape's run folder is read back before its swarm replays the tape: a
    damaged one is one line naming it (it was skipped silently, and the default config's
    swarm replayed the tape); one whose folder does not list the tape is not its run's, and
    the config's swarm replays it, said in a notice (probe 18's f11)."""
    import json
    import shutil

    from twin.runs import write_manifest

    run, common = _small_sumo_run(tmp_path, capsys, "--drones", "2")
    meta = json.loads((run / "run.json").read_text())
    (run / "run.json").write_text(json.dumps({**meta, "params": "eta=0.1"}))
    write_manifest(run, False, None)
    tape = str(run / "tape.parquet")
    assert main(["evaluate", "--traffic", tape, *common, "--out", str(tmp_path / "ev")]) == 2
    err = capsys.readouterr().err.strip()
    assert "\n" not in err and f"{run / 'run.json'}: params" in err, err
    assert not (tmp_path / "ev").exists()
    lone = tmp_path / "lone"
    lone.mkdir()
    shutil.copy(run / "tape.parquet", lone / "tape.parquet")
    (lone / "run.json").write_text(json.dumps(meta))
    (lone / "manifest.json").write_text(json.dumps({"partial": False, "files": {}}))
    argv = ["evaluate", "--traffic", str(lone / "tape.parquet"), *common]
    assert main([*argv, "--out", str(tmp_path / "ev2")]) == 0
    err = capsys.readouterr().err
    assert "does not list tape.parquet: not the tape of the run" in err, err
    (lone / "manifest.json").unlink()  # as an interrupted run leaves its folder
    other = {**meta, "grid": {**meta["grid"], "nx": 2, "ny": 2}}  # another run's, whole
    other["traffic"] = {**meta["traffic"], "identity": {**meta["traffic"]["identity"],
                                                        "grid": [2, 2]}}  # fmt: skip
    (lone / "run.json").write_text(json.dumps(other))
    assert main([*argv, "--out", str(tmp_path / "ev3")]) == 0, capsys.readouterr().err
    err = capsys.readouterr().err
    assert "gives a grid of 2 x 2, the tape" in err and "not the tape of its run" in err, err
    other = {**meta, "traffic": {**meta["traffic"], "seed": 9}}  # another day, same grid
    (lone / "run.json").write_text(json.dumps(other))
    assert main([*argv, "--out", str(tmp_path / "ev4")]) == 0, capsys.readouterr().err
    err = capsys.readouterr().err
    assert "records another traffic than the tape's" in err, err
    (lone / "run.json").write_text(json.dumps(meta))  # its own run's: its swarm replays it
    assert main([*argv, "--out", str(tmp_path / "ev5")]) == 0, capsys.readouterr().err
    assert "the swarm of" in capsys.readouterr().err


def test_a_later_seeds_tape_replays_with_that_seed(tmp_path, capsys):
    """``--traffic RUN/tapes/seed-1.parquet`` without --seed replays with the run's seed 1
    (its swarms' random choices), giving the run's seed-1 rows; --seed still chooses another
    (it replayed with seed 0, another result; probe 17's p2-c30)."""
    run, common = _small_sumo_run(tmp_path, capsys, "--seeds", "2")
    tape = str(run / "tapes" / "seed-1.parquet")
    assert main(["evaluate", "--traffic", tape, *common, "--out", str(tmp_path / "ev")]) == 0
    assert "score weights, seed 1)" in capsys.readouterr().err
    live = pd.read_csv(run / "per_seed.csv")
    replayed = pd.read_csv(tmp_path / "ev" / "per_seed.csv")
    assert replayed["seed"].tolist() == [1]
    want = live[live["seed"] == 1].set_index("swarm")["R_hat_T"].to_dict()
    assert replayed.set_index("swarm")["R_hat_T"].to_dict() == pytest.approx(want, rel=1e-12)
    argv = ["evaluate", "--traffic", tape, "--seed", "0", *common, "--out", str(tmp_path / "e0")]
    assert main(argv) == 0
    assert pd.read_csv(tmp_path / "e0" / "per_seed.csv")["seed"].tolist() == [0]
    # the notice names the seeds that ran, not the run's (probe 23's f11)
    assert "score weights, seed 0 by --seed; the run had 1)" in capsys.readouterr().err
    argv = ["evaluate", "--traffic", tape, "--seeds", "2", *common, "--out", str(tmp_path / "e2")]
    assert main(argv) == 0
    assert "score weights, seeds 1 to 2)" in capsys.readouterr().err


def test_a_runs_faults_are_said_not_replayed_with_its_tape(tmp_path, capsys):
    """A run with [faults] replayed from its tape without its config: a notice that its faults
    are not replayed (the numbers differed silently; probe 15's P2-f09)."""
    from helpers import small_sumo_scenario

    (tmp_path / "s").mkdir()
    folder = small_sumo_scenario(tmp_path / "s", horizon=4)
    config = folder / "small.toml"
    config.write_text(config.read_text() + "\n[faults]\ndrone_loss = [{ drone = 1, step = 2 }]\n")
    run = tmp_path / "run"
    common = ["--swarms", "random", "--no-ceiling", "--no-report", "--quiet"]
    assert main(["run", "--config", str(config), *common, "--out", str(run)]) == 0
    capsys.readouterr()
    argv = [
        "evaluate",
        "--traffic",
        str(run / "tape.parquet"),
        *common,
        "--out",
        str(tmp_path / "e"),
    ]
    assert main(argv) == 0
    err = capsys.readouterr().err
    assert "[swarm_options] and [faults] are not replayed (this run had [faults]" in err, err


def test_a_runs_tapes_swapped_between_seeds_are_refused(tmp_path, capsys):
    """``tapes/seed-0.parquet`` and ``tapes/seed-1.parquet`` swapped (the manifest made to
    agree): replaying ``seed-1`` would run seed 1's swarm on seed 0's day and give other
    figures than the run's, with exit 0; refused in one line (probe 24's f06)."""
    from test_boundary import refresh_manifest

    run, common = _small_sumo_run(tmp_path, capsys, "--seeds", "2")
    tapes = run / "tapes"
    (tapes / "seed-0.parquet").rename(tapes / "swap.parquet")
    (tapes / "seed-1.parquet").rename(tapes / "seed-0.parquet")
    (tapes / "swap.parquet").rename(tapes / "seed-1.parquet")
    refresh_manifest(run)
    tape = str(tapes / "seed-1.parquet")
    code = main(["evaluate", "--traffic", tape, *common, "--out", str(tmp_path / "ev")])
    err = capsys.readouterr().err.strip()
    assert code == 2 and "\n" not in err, err
    assert "seed-1.parquet: records seed 0's traffic in" in err and "not that of seed 1" in err
    assert not (tmp_path / "ev").exists()
