"""`twin transfer`: a tiny matrix end to end (2 rows, a synthetic and a small SUMO column, 2
seeds, a few updates), the same numbers on a local pool as one after another, a rerun that
reuses every checkpoint and cell, and bad transfer configs as one-line errors."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
import torch
from helpers import small_sumo_scenario

from twin.cli import main as cli
from twin.errors import UserError
from twin.metrics import ci95_halfwidth
from twin.transfer.config import load_transfer_config
from twin.transfer.runner import run_transfer

ROOT = Path(__file__).resolve().parents[1]

SCHEDULE = """
[schedule]
episodes = 1
scenario_overrides = { "traffic.horizon" = 40 }
epochs = 12
target_update_epochs = 4
log_every = 4
checkpoint_every = 4
curve_every = 6
curve_horizon = 10
"""


def tiny_config(tmp: Path, sumo: bool = True) -> Path:
    """2 rows (the paper recipe, then fine-tuned on a small SUMO scenario's tapes) x the
    synthetic map and (``sumo``) that SUMO scenario, seeds 0 and 1."""
    small_sumo_scenario(tmp, horizon=5)
    synthetic = ROOT / "configs" / "synthetic.toml"
    text = f"""
[transfer]
name = "tiny"
seeds = [0, 1]
classical = ["visit-gain", "greedy-coordinated"]
{SCHEDULE}
[tapes]
config = "small.toml"
seeds = [100, 101]

[[row]]
name = "paper"

[[row]]
name = "paper+tapes"
traffic = "tapes"
init = "paper"

[[column]]
name = "synthetic"
config = "{synthetic}"
overrides = {{ "traffic.horizon" = 12, "swarm.n_drones" = 2 }}
"""
    if sumo:
        text += '\n[[column]]\nname = "small"\nconfig = "small.toml"\n'
    path = tmp / "transfer.toml"
    path.write_text(text)
    return path


def test_tiny_matrix_end_to_end_and_pool_equals_sequential(tmp_path: Path, capsys) -> None:
    config = load_transfer_config(tiny_config(tmp_path))
    sequential, pool = tmp_path / "seq", tmp_path / "pool"
    report = run_transfer(config, sequential, workers=1)
    run_transfer(config, pool, workers=2)

    a, b = pd.read_csv(sequential / "matrix.csv"), pd.read_csv(pool / "matrix.csv")
    pd.testing.assert_frame_equal(a, b)
    # every row x learned swarm x column, paired over both seeds
    assert len(a) == 2 * 2 * 2 and set(a["n_seeds"]) == {2}
    assert set(a["evaluated_on"]) == {"synthetic", "small"}
    # the cells recomputed from the per-seed results
    results = pd.read_csv(sequential / "sweep" / "results.csv")
    for line in a.itertuples(index=False):
        col = results[results["scenario"] == line.evaluated_on]
        means = col[col["swarm"].isin(["visit-gain", "greedy-coordinated"])].groupby("swarm")
        assert line.best_classical == means["R_hat_T"].mean().idxmax()
        by_seed = col.pivot_table(index="seed", columns="swarm", values="R_hat_T")
        diff = (by_seed[line.swarm] - by_seed[line.best_classical]).to_numpy()
        assert line.difference == pytest.approx(diff.mean())
        assert line.difference_ci95 == pytest.approx(ci95_halfwidth(diff))
        oracle = col[col["swarm"] == "oracle (ceiling)"]["R_hat_T"].mean()
        share = (line.R_learned - line.R_best_classical) / (oracle - line.R_best_classical)
        assert line.gap_closed_oracle == pytest.approx(share)
        seen = col[col["swarm"] == line.swarm]["pct_events_seen"].mean()  # NaN: no event
        assert line.pct_events_seen == pytest.approx(seen, nan_ok=True)
    assert np.isfinite(a[a["evaluated_on"] == "synthetic"]["pct_events_seen"]).all()
    # the checkpoints hold the same weights, each with its provenance beside it
    for row in ("paper", "paper+tapes"):
        w1, w2 = (torch.load(d / "rows" / row / "qnet.pt")["weights"] for d in (sequential, pool))
        assert all(torch.equal(w1[k], w2[k]) for k in w1)
        p1 = json.loads((sequential / "rows" / row / "provenance.json").read_text())
        assert {"command", "recipe", "seeds", "schedule", "wall_s", "curve"} <= set(p1)
        assert all(p["seed"] >= 100 for p in p1["curve"]["points"])  # validation seeds only
    tuned = json.loads((sequential / "rows" / "paper+tapes" / "provenance.json").read_text())
    assert tuned["recipe"]["traffic"] == "tapes" and len(tuned["recipe"]["tapes"]) == 2
    assert tuned["recipe"]["init"]["path"].endswith("rows/paper/qnet.pt")
    html = report.read_text()
    assert "heatmap" in html and (sequential / "report" / "heatmap.png").stat().st_size > 0

    def rerun_does_nothing(folder: Path, row: str) -> None:
        """A rerun into ``folder`` trains no row (``row``'s model untouched) and runs no cell."""
        model = folder / "rows" / row / "qnet.pt"
        stamp = model.stat().st_mtime_ns
        run_transfer(config, folder, workers=1)
        assert model.stat().st_mtime_ns == stamp
        manifest = json.loads((folder / "sweep" / "sweep.json").read_text())
        assert manifest["invocations"][-1]["ran"] == 0

    rerun_does_nothing(sequential, "paper")
    # a folder moved is still its own (its rows' provenance named the old folder, and every
    # row was trained again: probe 26b's g02)
    pool.rename(tmp_path / "moved")
    rerun_does_nothing(tmp_path / "moved", "paper+tapes")
    model = sequential / "rows" / "paper" / "qnet.pt"
    stamp = model.stat().st_mtime_ns

    # the tapes' route file edited: the tapes are recorded again, the row fine-tuned on them
    # trained again, the SUMO column's cells run again; the paper row stays (probe 13's P2-f01b:
    # tapes, row and matrix were kept, exit 0)
    from twin.files import file_sha256

    trips = tmp_path / "small.trips.xml"  # its first trip dropped
    lines = trips.read_text().splitlines()
    trips.write_text("\n".join(line for line in lines if 'id="0"' not in line) + "\n")
    tuned_model = sequential / "rows" / "paper+tapes" / "qnet.pt"
    before = file_sha256(tuned_model)
    capsys.readouterr()
    run_transfer(config, sequential, workers=1)
    said = "row paper+tapes: its tapes, start or scenario changed since it was trained; training"
    assert said in capsys.readouterr().err
    assert model.stat().st_mtime_ns == stamp
    tuned = json.loads((sequential / "rows" / "paper+tapes" / "provenance.json").read_text())
    assert tuned["recipe"]["tapes"] == {t: file_sha256(t) for t in tuned["recipe"]["tapes"]}
    assert tuned["qnet_sha256"] == file_sha256(tuned_model) != before
    manifest = json.loads((sequential / "sweep" / "sweep.json").read_text())
    assert manifest["invocations"][-1]["ran"] >= 2  # the small column's cells (and the row's)
    # a row's model deleted: said so (the notice blamed changed settings: probe 27's f03)
    (tmp_path / "moved" / "rows" / "paper" / "qnet.pt").unlink()
    run_transfer(config, tmp_path / "moved", workers=1)
    err = capsys.readouterr().err
    assert "row paper: its model qnet.pt is missing; training it again" in err, err


def test_ray_gives_the_local_numbers(tmp_path: Path) -> None:
    pytest.importorskip("ray")
    config = load_transfer_config(tiny_config(tmp_path, sumo=False))
    run_transfer(config, tmp_path / "local", workers=2)
    run_transfer(config, tmp_path / "ray", executor="ray", workers=2)
    pd.testing.assert_frame_equal(
        pd.read_csv(tmp_path / "local" / "matrix.csv"), pd.read_csv(tmp_path / "ray" / "matrix.csv")
    )


GOOD = """
[transfer]
seeds = [0]
[[row]]
name = "paper"
[[column]]
name = "synthetic"
config = "{synthetic}"
"""

BAD = [
    ("[transfer]\nseeds = [0]\nbogus = 1\n", "bogus"),
    ('[transfer]\nclassical = ["rl"]\n', "learned swarm"),
    ('[transfer]\nclassical = ["nope"]\n', "unknown swarm 'nope'"),
    ("[transfer]\nseeds = 0\n", "seeds"),
    ("[transfer]\nseeds = [2147483648]\n", "[transfer].seeds = [2147483648] holds seed 2147483648"),
    ("[transfer]\nseeds = 1000000\n", "more than the 100,000 cells"),
    (
        "[transfer]\nseeds = 10000000000\n",
        "[transfer].seeds = 10000000000 runs seeds 0 .. 9999999999",
    ),
    ('[tapes]\nconfig = "{synthetic}"\nseeds = [-5]\n', "holds seed -5, out of range"),
    ("[schedule]\nepocs = 3\n", "epocs is not a pretraining key"),
    ('[schedule]\nout = "x"\n', "set per row"),
    ("[schedule]\nlr = -1.0\n", "[schedule].lr = -1.0 must be > 0"),
    ("[schedule]\nhorizon = 40\n", 'scenario_overrides = { "traffic.horizon" = ... }'),
    ('[schedule]\nscenario_overrides = {{ "grid.nx" = 0 }}\n', "'grid.nx' = 0 must be >= 1"),
    ('[[row]]\nname = "x"\nschedule = {{ epochs = 0 }}\n', "[[row]] x.schedule.epochs = 0"),
    ('[tapes]\nconfig = "{synthetic}"\nseeds = [3]\n', "evaluation seed 3"),
    ('[[row]]\nname = "tuned"\ninit = "later"\n', "neither a row nor a checkpoint"),
    ('[[row]]\nname = "t"\ntraffic = "tapes"\n', "needs a [tapes] section"),
    ('[[row]]\nname = "paper"\n', "is taken"),
    ('[[row]]\nname = "x"\ntraffic = "weather"\n', "traffic"),
    ('[[row]]\nname = "x"\ncheckpoint = "missing.pt"\n', "does not exist"),
    ('[[row]]\nname = "x"\ncheckpoint = "{data}"\n', "which is a folder, not a file"),
    ('[[column]]\nname = "c"\nconfig = "nowhere.toml"\n', "does not exist"),
    ('[[column]]\nname = "c"\nconfig = "{synthetic}"\ngenerate = "moon"\n', "spider"),
    ('[[column]]\nname = "c"\nconfig = "{synthetic}"\noverrides = {{ "x" = 1 }}\n', "dotted"),
    ('[[row]]\nname = "a/b"\n', "plain name"),
    (
        '[[column]]\nname = "g"\nconfig = "{synthetic}"\ngenerate = "spider"\n',
        "builds a SUMO network, but its config",
    ),
    (
        '[[row]]\nname = "x"\ncheckpoint = "{qnet}"\ntraffic = "dynamics"\n',
        "loads its checkpoint as it is, so its traffic would train nothing",
    ),
    # keys the transfer sets itself: the override changed nothing (probe 18's P2-03, P2-04)
    (
        '[[column]]\nname = "c"\nconfig = "{synthetic}"\noverrides = {{ "evaluate.seed" = 5 }}\n',
        "bad.toml: [[column]] c.overrides.'evaluate.seed' is set by the transfer itself "
        "([transfer].seeds); drop it",
    ),
    (
        '[tapes]\nconfig = "{synthetic}"\noverrides = {{ "traffic.seed" = 3 }}\n',
        "bad.toml: [tapes].overrides.'traffic.seed' is set by the transfer itself",
    ),
    # a swarm that plans on a history: the transfer builds none (probe 18's P2-07)
    ('[transfer]\nclassical = ["nowcast-gain"]\n', "'nowcast-gain', which plans on a history"),
]


@pytest.mark.parametrize(("extra", "message"), BAD)
def test_bad_transfer_configs_are_one_line_errors(tmp_path: Path, extra: str, message, capsys):
    synthetic = ROOT / "configs" / "synthetic.toml"
    text = GOOD.format(synthetic=synthetic)
    extra = extra.format(synthetic=synthetic, qnet=ROOT / "data" / "qnet.pt", data=ROOT / "data")
    if extra.startswith("[transfer]"):  # replaces the section
        text = text.replace("[transfer]\nseeds = [0]\n", "")
    path = tmp_path / "bad.toml"
    path.write_text(extra + text if extra.startswith("[transfer]") else text + extra)
    with pytest.raises(UserError) as info:
        load_transfer_config(path)
    assert message in str(info.value) and str(path) in str(info.value)
    assert cli(["transfer", "--config", str(path), "--out", str(tmp_path / "o")]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "Traceback" not in err
    assert not (tmp_path / "o").exists()


def test_a_row_checkpoint_that_cannot_load_is_refused_before_any_stage(tmp_path, capsys):
    """A row's checkpoint is loaded before the tapes and rows start: a broken one is the
    command's one line, nothing said before it and no folder made."""
    torch = pytest.importorskip("torch")
    from twin.learning.checkpoint import model_metadata, save_model
    from twin.learning.qnet import QNetwork

    weights = QNetwork([13, 16, 5]).state_dict()
    weights = {k: v * torch.nan for k, v in weights.items()}
    broken = tmp_path / "broken.pt"
    save_model(broken, weights, model_metadata([13, 16, 5], {}, 0, 1))
    path = tmp_path / "t.toml"
    synthetic = ROOT / "configs" / "synthetic.toml"
    path.write_text(
        GOOD.format(synthetic=synthetic) + f'[[row]]\nname = "loaded"\ncheckpoint = "{broken}"\n'
    )
    assert cli(["transfer", "--config", str(path), "--out", str(tmp_path / "o")]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "broken.pt" in err and "non-finite" in err, err
    assert not (tmp_path / "o").exists()


@pytest.mark.parametrize(
    ("rows", "words"),
    [
        ('[[row]]\nname = "tuned"\ninit = "{small}"\n', "small.pt: its layers [13, 16, 5]"),
        (
            '[[row]]\nname = "a"\nschedule = {{ layers = [13, 8, 5] }}\n'
            '[[row]]\nname = "b"\ninit = "a"\n',
            "[[row]] b.init = a: its layers [13, 8, 5] differ",
        ),
        (
            '[[row]]\nname = "a"\ncheckpoint = "{small}"\n[[row]]\nname = "b"\ninit = "a"\n',
            "[[row]] b.init = a: its layers [13, 16, 5] differ",
        ),
    ],
)
def test_a_fine_tuning_start_that_does_not_fit_is_refused_before_any_stage(
    tmp_path, capsys, rows, words
):
    """A row's init (a checkpoint, a loaded row, a row trained before it) whose layers differ
    from the row's is the command's one line before the tapes and rows start, no folder made
    (it was refused when that row's training began, after the stage lines)."""
    pytest.importorskip("torch")
    from twin.learning.checkpoint import model_metadata, save_model
    from twin.learning.qnet import QNetwork

    small = tmp_path / "small.pt"
    save_model(small, QNetwork([13, 16, 5]).state_dict(), model_metadata([13, 16, 5], {}, 0, 1))
    path = tmp_path / "t.toml"
    synthetic = ROOT / "configs" / "synthetic.toml"
    path.write_text(GOOD.format(synthetic=synthetic) + rows.format(small=small))
    assert cli(["transfer", "--config", str(path), "--out", str(tmp_path / "o")]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and words in err and str(path) in err, err
    assert not (tmp_path / "o").exists()


@pytest.mark.parametrize(
    ("rows", "words"),
    [
        (
            '[schedule]\nstate = "nowcast"\nhistory_seed = 10000000\n'
            '[[row]]\nname = "dyn"\ntraffic = "dynamics"\n',
            "[[row]] paper trains state 'nowcast' ([schedule].state): a nowcast",
        ),
        (
            '[[row]]\nname = "loaded"\ncheckpoint = "{nowcast}"\n',
            "whose network reads state 'nowcast': a nowcast",
        ),
    ],
)
def test_a_row_of_a_nowcast_state_is_refused_before_any_stage(tmp_path, capsys, rows, words):
    """A row whose network reads the nowcast (a trained row's schedule, a loaded checkpoint)
    needs a history of each column's scenario, which a transfer does not build: the command's
    one line before any row is trained (every cell failed after the training, with a fix the
    command does not take)."""
    pytest.importorskip("torch")
    from twin.learning.checkpoint import model_metadata, save_model
    from twin.learning.qnet import QNetwork

    nowcast = tmp_path / "nowcast.pt"
    meta = model_metadata([23, 8, 5], {}, 0, 1, state="nowcast")
    save_model(nowcast, QNetwork([23, 8, 5]).state_dict(), meta)
    path = tmp_path / "t.toml"
    synthetic = ROOT / "configs" / "synthetic.toml"
    path.write_text(GOOD.format(synthetic=synthetic) + rows.format(nowcast=nowcast))
    assert cli(["transfer", "--config", str(path), "--out", str(tmp_path / "o")]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and words in err and str(path) in err, err
    assert not (tmp_path / "o").exists()


def test_the_transfer_sets_the_keys_a_sweep_sets_itself() -> None:
    from twin.sweep.config import SET_BY_THE_SWEEP
    from twin.transfer.config import TRANSFER_SETS

    assert set(TRANSFER_SETS) == set(SET_BY_THE_SWEEP)


def test_a_foreign_out_folder_is_refused(tmp_path: Path, capsys) -> None:
    path = tmp_path / "t.toml"
    path.write_text(GOOD.format(synthetic=ROOT / "configs" / "synthetic.toml"))
    (tmp_path / "o").mkdir()
    (tmp_path / "o" / "mine.txt").write_text("keep")
    assert cli(["transfer", "--config", str(path), "--out", str(tmp_path / "o")]) == 2
    assert "mine.txt" in capsys.readouterr().err


def test_the_shipped_transfer_config_loads() -> None:
    config = load_transfer_config(ROOT / "configs" / "transfer.toml")
    assert [r.name for r in config.row] == ["paper", "dynamics", "tapes", "paper+tapes"]
    assert [c.name for c in config.column] == ["synthetic", "shenzhen", "spider"]
    assert not set(config.tapes.seeds) & set(config.seeds)


def test_learned_swarms_take_labels_and_classical_ones_do_not() -> None:
    from twin.swarms import check_swarm_name, is_learned, make_policy

    check_swarm_name("rl@paper+tapes")
    assert is_learned("rl-online@dynamics") and not is_learned("lookahead")
    for bad, words in [("lookahead@x", "only learned"), ("rl@", "label"), ("rl@a/b", "label"),
                       ("nope@x", "unknown swarm")]:  # fmt: skip
        with pytest.raises(UserError, match=words):
            check_swarm_name(bad)
    policy = make_policy("rl@shipped", checkpoint=ROOT / "data" / "qnet.pt")
    assert policy.name == "rl@shipped" and not policy.online


def test_the_full_transfer_config_is_the_short_one_at_full_size() -> None:
    short = load_transfer_config(ROOT / "configs" / "transfer.toml")
    full = load_transfer_config(ROOT / "configs" / "transfer-full.toml")
    assert full.seeds == list(range(10))
    assert [r.name for r in full.row] == [r.name for r in short.row]
    assert [c.name for c in full.column] == [c.name for c in short.column]
    assert full.schedule["epochs"] > short.schedule["epochs"]


@pytest.mark.parametrize(
    ("seeds", "shown"),
    [
        ([0], "-0.500 (one seed: no interval)"),
        ([0, 1], "-0.500 ± 0.000"),  # two seeds that agree: a real interval of width 0
    ],
)
def test_one_seed_gives_no_interval(seeds, shown) -> None:
    """A one-seed difference is no 95% interval: NaN in matrix.csv, said in the table and the
    verdict (it read "-0.500 ± 0.000")."""
    from twin.transfer.matrix import format_matrix, transfer_matrix, verdict

    rows = [
        {"scenario": "syn", "seed": s, "swarm": swarm, "R_hat_T": value, "role": "swarm"}
        for s in seeds
        for swarm, value in (("greedy", 1.0), ("rl@paper", 0.5))
    ]
    config = load_transfer_config(ROOT / "configs" / "transfer.toml")
    config.column = [type(config.column[0]).model_construct(name="syn")]
    config.transfer.classical = ["greedy"]
    config.row = [type(config.row[0]).model_construct(name="paper")]
    matrix = transfer_matrix(pd.DataFrame(rows), config)
    assert list(matrix["n_seeds"]) == [len(seeds)]
    assert np.isnan(matrix["difference_ci95"].iloc[0]) == (len(seeds) == 1)
    assert shown in format_matrix(matrix) and shown in verdict(matrix)


@pytest.mark.parametrize("link", ["rows", "sweep", "rows/paper", "tapes", "report"])
def test_a_link_out_of_the_transfer_folder_is_refused(tmp_path: Path, capsys, link) -> None:
    """``rows`` or ``sweep`` links planted in a transfer folder would take checkpoints and
    cells outside it: one line naming the link, nothing written through it (probe 14's
    f06)."""
    path = tmp_path / "t.toml"
    path.write_text(GOOD.format(synthetic=ROOT / "configs" / "synthetic.toml"))
    out, outside = tmp_path / "o", tmp_path / "outside"
    outside.mkdir()
    (out / link).parent.mkdir(parents=True)
    (out / link).symlink_to(outside)
    assert cli(["transfer", "--config", str(path), "--out", str(out), "--quiet"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and f"{out / link} is a symbolic link out of the folder" in err
    assert not any(outside.iterdir())


def test_a_tape_of_another_seed_copied_over_a_tape_is_recorded_again(tmp_path, capsys):
    """A transfer's tape replaced by another seed's tape of the same scenario is not its tape:
    it is recorded again, with a notice (the row was trained on the foreign tape, exit 0;
    probe 15's f27); the tape itself holds."""
    from twin.transfer.runner import record_tape, tape_still_holds

    small_sumo_scenario(tmp_path, horizon=3)
    tasks = [
        {"config": str(tmp_path / "small.toml"), "overrides": {}, "seed": seed,
         "path": str(tmp_path / f"seed-{seed}.parquet")}
        for seed in (100, 101)
    ]  # fmt: skip
    for task in tasks:
        record_tape(task)
    assert tape_still_holds(tasks[0]) and capsys.readouterr().err == ""
    shutil.copy(tasks[1]["path"], tasks[0]["path"])
    assert not tape_still_holds(tasks[0])
    err = capsys.readouterr().err
    assert "it was recorded with seed = 101, not its scenario's 100; recording it again" in err
    # the same seed on another grid (same step): not its tape either (probe 15's P2-f08)
    coarse = {**tasks[0], "overrides": {"traffic.cell_m": 300.0, "traffic.drone_speed_kmh": 18.0},
              "path": str(tmp_path / "coarse.parquet")}  # fmt: skip
    record_tape(coarse)
    shutil.copy(coarse["path"], tasks[0]["path"])
    assert not tape_still_holds(tasks[0])
    assert "it was recorded with identity.cell_m = 300.0, not its scenario's 200.0" in (
        capsys.readouterr().err
    )


def test_tapes_too_small_for_the_rows_drones_are_refused_before_any_stage(tmp_path, capsys):
    """A ``[tapes]`` scenario whose grid has fewer free cells than the drones a tapes row
    trains: one line naming the fix before any tape is recorded (it was an internal error
    after recording them; probe 17's f04)."""
    config = tiny_config(tmp_path, sumo=False)
    config.write_text(
        config.read_text().replace(
            "seeds = [100, 101]",
            'seeds = [100, 101]\noverrides = { "traffic.cell_m" = 1500, "swarm.n_drones" = 1 }',
        )
    )
    out = tmp_path / "o"
    assert cli(["transfer", "--config", str(config), "--out", str(out)]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1, err
    assert "[[row]] paper+tapes trains 4 drones on tapes of small.toml, whose grid has 1 " in err
    assert 'give [schedule] scenario_overrides = { "swarm.n_drones" = 1 }' in err, err
    assert not out.exists()


@pytest.mark.parametrize(
    ("old", "new", "said"),
    [
        ('"swarm.n_drones" = 2 }', '"swarm.n_drones" = 0 }', "[[column]] synthetic.overrides.'swarm.n_drones' = 0 must be >= 1"),
        ('"swarm.n_drones" = 2 }', '"swarm.n_drones" = 2, "grid.nx" = "x" }', "[[column]] synthetic.overrides.'grid.nx' = 'x' must be a whole number"),
        ("seeds = [100, 101]", 'seeds = [100, 101]\noverrides = { "traffic.cell_m" = -5 }', "[tapes].overrides.'traffic.cell_m' = -5 must be > 0"),
    ],
)  # fmt: skip
def test_a_refused_column_or_tapes_override_is_named_before_any_stage(
    old, new, said, tmp_path, capsys
):
    """A value a column's (or the tapes') scenario refuses: one line naming the transfer
    file's key before any tape is recorded or row trained (a column's was found after the rows
    trained, and named as an override of the scenario's file: probe 24's f02)."""
    config = tiny_config(tmp_path, sumo=False)
    config.write_text(config.read_text().replace(old, new))
    out = tmp_path / "o"
    assert cli(["transfer", "--config", str(config), "--out", str(out)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith(f"twin: error: {config}: {said}"), err
    assert not out.exists()


def test_tapes_of_a_synthetic_scenario_are_refused_before_any_stage(tmp_path, capsys):
    """``[tapes] config`` naming a synthetic scenario: one line before any stage (it was an
    internal error while recording, a synthetic source has no tape; probe 16's f05)."""
    config = tiny_config(tmp_path, sumo=False)
    synthetic = ROOT / "configs" / "synthetic.toml"
    config.write_text(
        config.read_text().replace('config = "small.toml"', f'config = "{synthetic}"')
    )
    out = tmp_path / "o"
    assert cli(["transfer", "--config", str(config), "--out", str(out)]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "its traffic is 'synthetic', not a SUMO scenario" in err, err
    assert not out.exists()


def test_a_row_trained_again_keeps_the_users_files(tmp_path: Path) -> None:
    """A row folder to train again is cleared of what pretraining wrote only; a file twin did
    not write is refused in one line and nothing is removed (the folder was deleted whole;
    probe 17's P2-06)."""
    from twin.transfer.runner import clear_row_folder

    row = tmp_path / "rows" / "dyn"
    (row / "snapshots").mkdir(parents=True)
    for name in ("qnet.pt", "state.pt", "train_log.csv", "provenance.json", ".qnet.pt.tmp"):
        (row / name).write_text("twin's")
    (row / "snapshots" / "epoch_10.pt").write_text("twin's")
    (row / "plots").mkdir()
    (row / "plots" / "a.png").write_text("mine")
    with pytest.raises(UserError, match=r"row dyn: must be trained again .* holds 'plots', "
                                        "which twin did not write; move it out") as info:  # fmt: skip
        clear_row_folder(row)
    assert "\n" not in str(info.value)
    assert (row / "plots" / "a.png").read_text() == "mine" and (row / "qnet.pt").exists()
    (row / "plots" / "a.png").unlink()
    (row / "plots").rmdir()
    clear_row_folder(row)
    assert list(row.iterdir()) == []


def test_the_columns_are_checked_against_the_memory_limit_given(tmp_path, capsys):
    """The columns' check before any stage takes ``--max-memory-gb`` as the evaluation does (it
    checked against the default 8 GB, refusing a transfer the limit allowed)."""
    from twin.errors import UserError
    from twin.transfer.config import load_transfer_config
    from twin.transfer.runner import check_columns

    config = tiny_config(tmp_path, sumo=False)
    big = '"traffic.horizon" = 100000, "grid.nx" = 200, "grid.ny" = 300'  # maps of 24 GB
    config.write_text(config.read_text().replace('"traffic.horizon" = 12', big))
    transfer = load_transfer_config(config)
    with pytest.raises(UserError, match="GB"):
        check_columns(transfer)
    check_columns(transfer, max_memory_gb=10000.0)
