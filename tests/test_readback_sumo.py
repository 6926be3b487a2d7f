"""A live SUMO run folder read back: figures and inputs its tapes, network and config contradict
are refused in one line (exit 2, no traceback, nothing written outside the folder)."""

from __future__ import annotations

import json
import shutil
from collections.abc import Callable
from pathlib import Path

import pyarrow as pa
import pyarrow.parquet as pq
import pytest

pytest.importorskip("libsumo")

from helpers import needs_display, small_sumo_scenario
from test_boundary import forge_per_seed, one_line, refresh_manifest, tree_hash

from twin.boundary import EXIT_REFUSED
from twin.cli import main


@pytest.fixture(scope="module")
def sumo_run(tmp_path_factory) -> Path:
    """A small finished `twin run` of 2 seeds and 2 swarms (``tapes/`` holds both tapes)."""
    folder = small_sumo_scenario(tmp_path_factory.mktemp("sumo-readback"), horizon=6)
    out = folder / "run"
    argv = ["run", "--config", str(folder / "small.toml"), "--swarms", "random,greedy",
            "--seeds", "2", "--no-ceiling", "--no-report", "--quiet", "--out", str(out)]  # fmt: skip
    assert main(argv) == 0
    return out


@pytest.fixture()
def sumo_copy(sumo_run: Path, tmp_path: Path) -> Path:
    out = tmp_path / "work" / "run"
    shutil.copytree(sumo_run, out)
    shutil.copytree(sumo_run.parent, tmp_path / "work" / "scenario", ignore=lambda d, n: ["run"])
    return out


def _edit_tape(name: str, edit: Callable) -> Callable[[Path], None]:
    """Rewrite the tape ``name`` with its rows edited by ``edit(frame)`` (metadata kept)."""

    def damage(run: Path) -> None:
        table = pq.read_table(run / name)
        frame = table.to_pandas()
        edit(frame)
        out = pa.Table.from_pandas(frame, schema=table.schema, preserve_index=False)
        pq.write_table(out.replace_schema_metadata(table.schema.metadata), run / name)

    return damage


def _triple_counts(frame) -> None:
    frame.loc[frame["step"] >= 0, "count"] *= 3


def _run_json(edit: Callable[[dict], None]) -> Callable[[Path], None]:
    def damage(run: Path) -> None:
        record = json.loads((run / "run.json").read_text())
        edit(record)
        (run / "run.json").write_text(json.dumps(record, indent=1))

    return damage


def _mfd_json(edit: Callable[[dict], None]) -> Callable[[Path], None]:
    def damage(run: Path) -> None:
        record = json.loads((run / "mfd.json").read_text())
        edit(record)
        (run / "mfd.json").write_text(json.dumps(record, indent=2))

    return damage


#: name -> (damage, words the one line holds, commands that refuse it)
SUMO_READ_BACK: dict[str, tuple[Callable[[Path], None], str, tuple[str, ...]]] = {
    "first seed's copy in tapes/ is not tape.parquet": (
        _edit_tape("tapes/seed-0.parquet", _triple_counts),
        "tapes/seed-0.parquet: count = ",
        ("report", "history"),
    ),
    "a later seed's tape contradicts its scores": (
        _edit_tape("tapes/seed-1.parquet", _triple_counts),
        "but trajectories.parquet and tapes/seed-1.parquet give",
        ("report", "history"),
    ),
    "a later seed's paper accounting is forged consistently": (  # probe 23's f02
        lambda run: forge_per_seed(run, 1, "random", "R_hat_T_paper", 0.05),
        "per_seed.csv: R_hat_T_paper = ",
        ("report",),
    ),
    "run.json begins at another time than the tape": (
        _run_json(lambda r: r["traffic"].update(begin="00:06:00")),
        'run.json: traffic.begin = "00:06:00", but tape.parquet (seed 0\'s tape) records '
        '"00:05:00"',
        ("report",),
    ),
    "run.json names another scenario than the tape": (
        _run_json(lambda r: r["traffic"].update(name="other.sumocfg")),
        'run.json: traffic.name = "other.sumocfg", but tape.parquet (seed 0\'s tape) records ',
        ("report",),
    ),
    "run.json reads fewer times a step than the tape": (
        _run_json(lambda r: r["traffic"].update(reads_per_step=1, read_offsets_s=[0.0])),
        "run.json: traffic.reads_per_step = 1, but tape.parquet (seed 0's tape) records 3",
        ("report",),
    ),
    "a later seed's reads in run.json are not its tape's": (
        _run_json(lambda r: r["traffic_by_seed"][1].update(read_offsets_s=[30.0, 15.0, 0.0])),
        "run.json: traffic_by_seed[1].read_offsets_s[0] = 30.0, but tapes/seed-1.parquet",
        ("report",),
    ),
    "mfd.json's rejected fit is not the samples' fit": (
        _mfd_json(lambda m: m["rejected_fit"].update(a=0.5)),
        "mfd.json: rejected_fit.a = 0.5, but tape.parquet replayed through its MFD gives 0.",
        ("report",),
    ),
    "run.json's monitoring step is not its traffic's": (
        _run_json(lambda r: r["monitoring"].update(step_s=99.0)),
        "run.json: monitoring.step_s = 99.0, but traffic.step_s = ",
        ("report",),
    ),
    "run.json's versions name another SUMO than its traffic's identity": (
        _run_json(lambda r: r["versions"].update({"eclipse-sumo": "1.0"})),
        "run.json: versions.eclipse-sumo = 1.0, but traffic.identity.sumo = ",
        ("report",),
    ),
    "run.json's network sha256 is not its network file's": (
        _run_json(lambda r: r["traffic"]["identity"].update(net_sha256="0" * 64)),
        "run.json: traffic.identity.net_sha256 = 0000000000000000..., but its files record",
        ("report",),
    ),
    "mfd.json leaves out the fit the run rejected": (
        _mfd_json(lambda m: m.pop("rejected_fit")),
        'mfd.json: rejected_fit = null, but tape.parquet replayed through its MFD gives {"a": ',
        ("report",),
    ),
}


@pytest.mark.parametrize("name", list(SUMO_READ_BACK))
def test_contradicted_sumo_run_is_one_line(name, sumo_copy: Path, capsys) -> None:
    damage, words, commands = SUMO_READ_BACK[name]
    damage(sumo_copy)
    refresh_manifest(sumo_copy)
    parent = sumo_copy.parent
    before = tree_hash(parent, skip=sumo_copy)
    for command in commands:
        argv = {
            "report": ["report", str(sumo_copy), "--no-animation"],
            "replay": ["replay", str(sumo_copy), "--out", str(parent / "replayed")],
            "history": ["history", "--from", str(sumo_copy), "--out", str(parent / "h.npz")],
        }[command]
        assert main(argv) == EXIT_REFUSED, command
        line = one_line(capsys)
        assert words in line, (command, line)
        assert not (sumo_copy / "report").exists()
        assert tree_hash(parent, skip=sumo_copy) == before


def test_the_intact_sumo_run_reads_back(sumo_copy: Path, capsys) -> None:
    from twin.report.load import load_run

    assert load_run(sumo_copy).run["seeds"] == [0, 1]
    out = sumo_copy.parent / "h.npz"
    assert main(["history", "--from", str(sumo_copy), "--out", str(out)]) == 0
    assert out.is_file()


@needs_display
@pytest.mark.parametrize("seed", [0, 1])
def test_replay_checks_each_step_against_the_tape_as_read_back(
    seed, sumo_copy: Path, capsys, monkeypatch
) -> None:
    # the read-back replays every seed's tape once; the per-step check uses those maps
    import twin.cli.replay

    def replayed_again(*args):
        raise AssertionError("the tape was replayed a second time")

    monkeypatch.setattr(twin.cli.replay, "recorded_importance", replayed_again)
    assert main(["replay", str(sumo_copy), "--seed", str(seed)]) == 0
    captured = capsys.readouterr()
    assert f"replayed 6 steps of seed {seed}" in captured.out, captured.out + captured.err
    assert "Traceback" not in captured.err


def test_a_run_whose_fit_quality_is_undefined_reads_back(tmp_path, monkeypatch, capsys):
    """An R^2 that samples cannot give (one density bin, constant speed: SUMO's DRT demo) is
    written as null, which JSON and the read-back take: the run's own folder was refused by
    its report ("r2 = NaN must be ... a number"; probe 15's f11)."""
    import twin.mfd

    fit_quality = twin.mfd.fit_quality
    monkeypatch.setattr(
        twin.mfd, "fit_quality", lambda *a, **k: {**fit_quality(*a, **k), "r2": float("nan")}
    )
    folder = small_sumo_scenario(tmp_path, horizon=3)
    out = tmp_path / "run"
    argv = ["run", "--config", str(folder / "small.toml"), "--swarms", "random", "--no-ceiling",
            "--quiet", "--out", str(out)]  # fmt: skip
    assert main(argv) == 0, capsys.readouterr().err
    assert json.loads((out / "mfd.json").read_text())["r2"] is None
    assert main(["report", str(out), "--no-animation"]) == 0, capsys.readouterr().err
