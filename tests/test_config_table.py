"""Every config key's bad values (wrong type, non-finite, out of range, unknown key) through the
CLI: exit code 2 and one line naming the file and the key, never a traceback, nothing run."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest

import twin.config
import twin.resources
import twin.sumo.scenario
import twin.sweep
import twin.training.pretrain
from twin.cli import main
from twin.config import load_config

# --- base files: each valid as is; a case replaces (or adds) one key --------------------------
SYNTHETIC = {
    "grid": {"nx": "6", "ny": "8", "obstacles": "[[0, 0]]"},
    "swarm": {
        "n_drones": "2",
        "starts": '"random"',
        "eta": "0.1",
        "delta": "0.025",
        "alpha_T": "1.0",
        "alpha_I": "0.5",
    },
    "traffic": {
        "kind": '"synthetic"',
        "horizon": "5",
        "beta1": "0.7",
        "beta2": "5.0",
        "z_lo": "0.0",
        "z_hi": "2.0",
        "disturbances": '[{ kind = "big", i = 2, j = 2, amplitude = 1.0, sigma = 2.0 }]',
    },
    "evaluate": {"swarms": '["greedy"]', "seeds": "1", "seed": "0"},
    "swarm_options.greedy": {},
}
SUMO = {
    "grid": {"nx": "20", "ny": "30"},
    "swarm": {"n_drones": "2"},
    "traffic": {
        "kind": '"sumo"',
        "network": '"shenzhen_like"',
        "cell_m": "500.0",
        "drone_speed_kmh": "24.0",
        "begin": '"07:00"',
        "horizon": "2",
        "warmup_min": "1.0",
        "seed": "0",
        "mesoscopic": "false",
        "min_lane_km": "0.0",
        "demand_scale": "1.0",
    },
    "traffic.mfd": {"fit": '"online"', "a": "0.7", "k_c": "40.0", "detection_p": "1.0"},
    "traffic.detectors": {"scenario": "false", "virtual_loops": "0"},
    "evaluate": {"swarms": '["greedy"]'},
}
SWEEP = {
    "sweep": {"name": '"t"', "swarms": '["greedy"]', "seeds": "2", "seed": "0"},
    "scenario": {
        "name": '"a"',
        "config": '"scenario.toml"',
        "overrides": '{ "traffic.horizon" = 5 }',
    },
    "parameters": {'"swarm.n_drones"': "[1, 2]"},
}
PRETRAIN = {
    "": {
        "seed": "0",
        "out": '"runs/x"',
        "episodes": "1",
        "layers": "[13, 8, 5]",
        "epochs": "1",
        "iters_per_epoch": "1",
        "batch_size": "2",
        "gamma": "0.9",
        "lr": "0.001",
        "target_update_epochs": "1",
        "adam_fused": "false",
        "threads": "1",
        "log_every": "1",
        "checkpoint_every": "1",
        "snapshot_every": "0",
    },
}

NUMBER = ['"1.0"', "nan", "inf", "-inf", "true"]  # every float key refuses these
WHOLE = ['"1"', "1.5", "nan", "true"]  # every int key refuses these


def toml_text(base: dict, section: str, key: str, value: str | None) -> str:
    """``base`` as TOML with ``[section].key = value`` (``None``: the key removed)."""
    lines = []
    for name, table in base.items():
        table = dict(table)
        if name == section:
            if value is None:
                table.pop(key, None)
            else:
                table[key] = value
        if name == "scenario":
            lines.append("[[scenario]]")
        elif name:
            lines.append(f"[{name}]")
        lines += [f"{k} = {v}" for k, v in table.items()]
    if section not in base:  # a new section
        lines += [f"[{section}]", f"{key} = {value}"]
    return "\n".join(lines) + "\n"


def cases(base: dict, table: dict[tuple[str, str], list[str]]) -> list:
    out = []
    for (section, key), values in table.items():
        for value in values:
            out.append(pytest.param(section, key, value, id=f"{section}.{key}={value}"))
    for section in base:
        out.append(pytest.param(section, "colour", "1", id=f"{section}.unknown"))
    return out


SYNTHETIC_BAD = {
    ("grid", "nx"): [*WHOLE, "0", "-1"],
    ("grid", "ny"): [*WHOLE, "0"],
    ("grid", "obstacles"): ['"x"', "[[1]]", '[["a", 1]]', "[[9, 9]]", "[[1, 2, 3]]"],
    ("swarm", "n_drones"): [*WHOLE, "0", "-2", "100"],
    ("swarm", "starts"): [
        '"corner"',
        "3",
        "[[1]]",
        "[[0, 0], [1, 1]]",
        "[[1, 1], [1, 1]]",
        "[[1, 1], [60, 1]]",
        "[[1, 1]]",
    ],
    ("swarm", "eta"): [*NUMBER, "0", "1", "1.5", "-0.1"],
    ("swarm", "delta"): [*NUMBER, "0.0", "1.0", "1e-320"],
    ("swarm", "alpha_T"): [*NUMBER, "-0.1", "1e308", "2e6"],
    ("swarm", "alpha_I"): [*NUMBER, "-1", "1e308"],
    ("traffic", "kind"): ['"tape"', "3"],
    ("traffic", "horizon"): [*WHOLE, "0", "-5", "100000000000000000000", "9223372036854775807"],
    ("traffic", "beta1"): [*NUMBER, "0", "-1.0"],
    ("traffic", "beta2"): [*NUMBER, "0", "3e307", "1e308"],  # 2 pi beta2 past the floats
    ("traffic", "z_lo"): [*NUMBER, "3.0"],
    ("traffic", "z_hi"): [*NUMBER, "-1.0", "0.0", "1e-320", "1e308", "1e-15"],  # flat maps
    ("traffic", "disturbances"): [
        "3",
        '["big"]',
        '[{ kind = "huge" }]',
        "[{ sigma = 0.0 }]",
        "[{ sigma = nan }]",
        "[{ sigma = 1e-300 }]",
        "[{ amplitude = inf }]",
        "[{ amplitude = 1e308 }, { amplitude = 1e308 }]",  # finite each, NaN maps together
        "[{ amplitude = 1.7e308 }, { amplitude = 1.7e307 }]",
        '[{ i = "1" }]',
        "[{ j = nan }]",
        "[{ colour = 1 }]",
    ],
    ("evaluate", "swarms"): [
        "[]",
        '"greedy"',
        "[1]",
        '["greedy", ""]',
        '["greedy", " "]',
        '["greedy", "greedy"]',
        '["nope"]',
    ],
    ("evaluate", "seeds"): [*WHOLE, "0"],
    ("evaluate", "seed"): [*WHOLE, "-1"],
    ("swarm_options.greedy", "speed"): ["3"],
    ("swarm_options.rl", "eps"): ["nan", "inf"],
    ("oops", "x"): ["1"],
}


def _needle(section: str, key: str, value: str) -> str:
    if section == "oops":
        return "[oops]"
    if section.startswith("swarm_options"):
        return f"[{section}]"
    if (section, key, value) == ("traffic", "z_lo", "3.0"):
        return "[traffic].z_hi"  # the base's z_hi = 2.0 no longer exceeds it
    return f"[{section}].{key}"


@pytest.mark.parametrize(("section", "key", "value"), cases(SYNTHETIC, SYNTHETIC_BAD))
def test_bad_synthetic_scenario(tmp_path, capsys, section, key, value):
    path = tmp_path / "bad.toml"
    path.write_text(toml_text(SYNTHETIC, section, key, value))
    out = tmp_path / "out"
    code = main(["evaluate", "--config", str(path), "--out", str(out), "--quiet", "--no-report"])
    _one_line(capsys, code, path, _needle(section, key, value))
    assert not (out / "summary.csv").exists()


SUMO_BAD = {
    ("traffic", "network"): ["3", "true", '"../../etc"', '"a/b"', '"atlantis"'],
    ("traffic", "net"): ["3", '""'],
    ("traffic", "routes"): ["3", "[1]", '""', '["a.rou.xml", ""]'],
    ("traffic", "additional"): ['[" "]'],
    ("traffic", "sumocfg"): ["true", '" "'],
    ("traffic", "osm"): ["1.0", '""'],
    ("traffic", "cell_m"): [*NUMBER, '"500"', "0", "-1.0"],
    ("traffic", "drone_speed_kmh"): [*NUMBER, "0"],
    ("traffic", "begin"): ['"07:75"', '"7"', "700", '"seven"'],
    ("traffic", "horizon"): [*WHOLE, '"144"', "0", "100000000000000000000"],
    ("traffic", "warmup_min"): [*NUMBER, "-1.0"],
    ("traffic", "seed"): [*WHOLE, "-1"],
    ("traffic", "mesoscopic"): ['"false"', '"true"', "0", "1"],
    ("traffic", "min_lane_km"): [*NUMBER, "-0.5"],
    ("traffic", "demand_scale"): [*NUMBER, "0", "-2.0"],
    ("traffic.mfd", "fit"): ['"x"', "1"],
    ("traffic.mfd", "a"): [*NUMBER, "0", "1.5", "1e-300"],
    ("traffic.mfd", "k_c"): [*NUMBER, '"40"', "0", "1e-300", "1e300"],
    ("traffic.mfd", "detection_p"): [*NUMBER, "0", "1.5", "1e-300"],
    ("traffic.detectors", "scenario"): ['"yes"', "1"],
    ("traffic.detectors", "virtual_loops"): [*WHOLE, "-1", "100000"],
    ("traffic.detectors", "cells"): ['"x"', "[[1]]", '[["a", 1]]', "[[1, 2, 3]]"],
    ("swarm", "eta"): ["nan", "2"],
}


@pytest.mark.parametrize(("section", "key", "value"), cases(SUMO, SUMO_BAD))
def test_bad_sumo_scenario_fails_before_sumo_starts(
    tmp_path, capsys, monkeypatch, section, key, value
):
    def no_sumo(*args, **kwargs):
        raise AssertionError("SUMO started on a bad config")

    monkeypatch.setattr(twin.sumo.scenario, "sumo_source", no_sumo)
    path = tmp_path / "bad.toml"
    path.write_text(toml_text(SUMO, section, key, value))
    out = tmp_path / "out"
    code = main(["run", "--config", str(path), "--horizon", "1", "--out", str(out), "--quiet"])
    _one_line(capsys, code, path, f"[{section}].{key}")
    assert not out.exists()


def test_sumo_grid_needs_both_sides(tmp_path, capsys):
    path = tmp_path / "bad.toml"
    path.write_text(toml_text(SUMO, "grid", "ny", None))
    _one_line(capsys, main(["run", "--config", str(path), "--horizon", "1"]), path, "[grid]")


SWEEP_BAD = {
    ("sweep", "name"): ['"../x"', '"a/b"', '".."', '""', '".hidden"', "3"],
    ("sweep", "swarms"): [
        "[]",
        '["nope"]',
        '"greedy"',
        '["greedy", "greedy"]',
        "[1]",
        '["", "greedy"]',
    ],
    ("sweep", "seeds"): ["0", "-1", "[]", "[1, 1]", "[-1]", "2.5", "true", '"3"', "nan"],
    ("sweep", "seed"): [*WHOLE, "-1"],
    ("scenario", "name"): ['"../evil"', '"a/b"', '".."', '"a\\\\b"', "3"],
    ("scenario", "config"): ['"missing.toml"', "3"],
    ("scenario", "overrides"): ['{ "colour" = 1 }', "3", '{ "traffic" = 1 }'],
    ("scenario", "tape"): ["3"],
    ("parameters", '"n_drones"'): ["[1]"],
    ("parameters", '"swarm.n_drones"'): ["[]", "3"],
    ("swarm_options.rl", "checkpoint"): ['"nope.pt"'],
    ("swarm_options.greedy", "checkpoint"): ['"nope.pt"', "3"],
}


def _sweep_needle(section: str, key: str) -> str:
    if section == "scenario":
        return f"[[scenario]] #1.{key}"
    if section == "parameters":
        return "[parameters]"
    if section.startswith("swarm_options"):
        return f"[{section}]"
    return f"[{section}].{key}"


@pytest.mark.parametrize(("section", "key", "value"), cases(SWEEP, SWEEP_BAD))
def test_bad_sweep(tmp_path, capsys, monkeypatch, section, key, value):
    def no_run(*args, **kwargs):
        raise AssertionError("a bad sweep ran")

    monkeypatch.setattr(twin.sweep, "run_sweep", no_run)
    (tmp_path / "scenario.toml").write_text(toml_text(SYNTHETIC, "grid", "nx", "6"))
    path = tmp_path / "bad.toml"
    path.write_text(toml_text(SWEEP, section, key, value))
    code = main(["sweep", "--config", str(path), "--out", str(tmp_path / "out")])
    needle = _sweep_needle(section, key) if key != "colour" else f"{section}]"
    _one_line(capsys, code, path, needle)


@pytest.mark.parametrize("missing", ["sweep", "scenario"])
def test_sweep_sections_are_required(tmp_path, capsys, missing):
    base = {k: v for k, v in SWEEP.items() if k != missing}
    (tmp_path / "scenario.toml").write_text(toml_text(SYNTHETIC, "grid", "nx", "6"))
    path = tmp_path / "bad.toml"
    path.write_text(toml_text(base, "sweep" if missing != "sweep" else "parameters", "x", None))
    _one_line(capsys, main(["sweep", "--config", str(path)]), path, missing)


PRETRAIN_BAD = {
    ("", "seed"): [*WHOLE, "-1"],
    ("", "out"): ["3", '""'],
    ("", "episodes"): ["0", '"1"'],
    ("", "scenario"): ["3", '"nowhere.toml"', '""'],
    ("", "scenario_overrides"): ["3", "{ nx = 6 }", '{ "grid" = 6 }'],
    ("", "layers"): ["[12, 5]", "[13, 0, 5]", '"x"', "[13, 8.5, 5]"],
    ("", "epochs"): [*WHOLE, '"many"', "0"],
    ("", "iters_per_epoch"): ["0", "1.5"],
    ("", "batch_size"): ["0", "-3"],
    ("", "gamma"): [*NUMBER, "1.0", "-0.1"],
    ("", "lr"): [*NUMBER, "0", "-1.0", "2.0"],
    ("", "target_update_epochs"): ["0"],
    ("", "adam_fused"): ['"false"', "1"],
    ("", "threads"): ["0", '"2"'],
    ("", "log_every"): ["0"],
    ("", "checkpoint_every"): ["0"],
    ("", "snapshot_every"): ["-1", "nan"],
    ("", "tapes"): ['[""]', '[" "]', '["nowhere.parquet"]'],
}


@pytest.mark.parametrize(("section", "key", "value"), cases(PRETRAIN, PRETRAIN_BAD))
def test_bad_pretrain(tmp_path, capsys, monkeypatch, section, key, value):
    def no_training(*args, **kwargs):
        raise AssertionError("a bad config trained")

    monkeypatch.setattr(twin.training.pretrain, "pretrain", no_training)
    path = tmp_path / "bad.toml"
    path.write_text(toml_text(PRETRAIN, section, key, value))
    _one_line(capsys, main(["pretrain", "--config", str(path), "--quiet"]), path, key)


#: The scenario's keys that a pretraining config sets through scenario_overrides.
PRETRAIN_SCENARIO = {
    "grid.nx": "6",
    "grid.ny": "8",
    "traffic.horizon": "5",
    "traffic.beta1": "0.7",
    "traffic.beta2": "5.0",
    "traffic.disturbances": '[{ kind = "big", i = 2, j = 2, amplitude = 1.0, sigma = 2.0 }]',
    "swarm.n_drones": "2",
    "swarm.eta": "0.1",
    "swarm.delta": "0.025",
    "swarm.alpha_T": "1.0",
    "swarm.alpha_I": "0.5",
}
PRETRAIN_SCENARIO_BAD = {
    "grid.nx": [*WHOLE, "0"],
    "grid.ny": ["0"],
    "traffic.horizon": [*WHOLE, "0"],
    "traffic.beta1": [*NUMBER, "0"],
    "traffic.beta2": [*NUMBER, "-1.0"],
    "traffic.disturbances": ["3", '[{ kind = "x" }]', "[{ sigma = nan }]", "[{ i = inf }]"],
    "swarm.n_drones": [*WHOLE, "0", "49"],
    "swarm.eta": [*NUMBER, "0", "1"],
    "swarm.delta": [*NUMBER, "1.5"],
    "swarm.alpha_T": [*NUMBER, "-1.0"],
    "swarm.alpha_I": [*NUMBER, "-0.5"],
    "grid.colour": ["1"],
}


def pretrain_text(key: str | None = None, value: str | None = None) -> str:
    """The pretraining base with ``scenario_overrides`` of the scenario's keys (``key`` set to
    ``value``)."""
    table = {**PRETRAIN_SCENARIO, **({key: value} if key else {})}
    inline = ", ".join(f'"{k}" = {v}' for k, v in table.items())
    return toml_text(PRETRAIN, "", "scenario_overrides", f"{{ {inline} }}")


@pytest.mark.parametrize(
    ("key", "value"),
    [pytest.param(k, v, id=f"{k}={v}") for k, vs in PRETRAIN_SCENARIO_BAD.items() for v in vs],
)
def test_bad_pretrain_scenario_override(tmp_path, capsys, monkeypatch, key, value):
    """A bad value of the scenario's key in a pretraining config: one line naming the
    pretraining file and the override, not the scenario file."""
    monkeypatch.setattr(twin.training.pretrain, "pretrain", None)
    path = tmp_path / "bad.toml"
    path.write_text(pretrain_text(key, value))
    code = main(["pretrain", "--config", str(path), "--quiet"])
    _one_line(capsys, code, path, f"scenario_overrides {key!r}")


@pytest.mark.parametrize(("old", "new"), list(twin.training.pretrain.SCENARIO_KEYS.items()))
def test_a_pretraining_key_now_the_scenarios_names_its_new_key(tmp_path, capsys, old, new):
    path = tmp_path / "old.toml"
    path.write_text(toml_text(PRETRAIN, "", old, "6"))
    code = main(["pretrain", "--config", str(path), "--quiet"])
    _one_line(capsys, code, path, f'scenario_overrides = {{ "{new}" = 6 }}')


def test_bases_are_valid(tmp_path, monkeypatch):
    """The table's base files pass: each case fails because of its one change."""
    from twin.sweep import load_sweep_config
    from twin.training.pretrain import load_config as load_pretrain

    for name, base in (("syn.toml", SYNTHETIC), ("sumo.toml", SUMO)):
        (tmp_path / name).write_text(toml_text(base, "grid", "nx", base["grid"]["nx"]))
        load_config(tmp_path / name)
    (tmp_path / "scenario.toml").write_text(toml_text(SYNTHETIC, "grid", "nx", "6"))
    (tmp_path / "sweep.toml").write_text(toml_text(SWEEP, "sweep", "seed", "0"))
    load_sweep_config(tmp_path / "sweep.toml")
    (tmp_path / "pre.toml").write_text(pretrain_text())
    assert load_pretrain(tmp_path / "pre.toml").training_map.grid.nx == 6


BOM = b"\xef\xbb\xbf"  # the UTF-8 byte order mark editors on Windows put first


@pytest.mark.parametrize("kind", ["scenario", "sweep", "pretrain"])
def test_a_byte_order_mark_is_read_past(tmp_path, kind):
    """TOML forbids the mark; twin reads the file as the same file without it."""
    from twin.sweep import load_sweep_config
    from twin.training.pretrain import load_config as load_pretrain

    def both(name: str, text: str) -> tuple[Path, Path]:
        (tmp_path / "plain").mkdir(exist_ok=True)
        (tmp_path / "bom").mkdir(exist_ok=True)
        (tmp_path / "plain" / name).write_text(text)
        (tmp_path / "bom" / name).write_bytes(BOM + text.encode())
        return tmp_path / "plain" / name, tmp_path / "bom" / name

    scenario = toml_text(SYNTHETIC, "grid", "nx", "6")
    plain, bom = both("scenario.toml", scenario)
    if kind == "sweep":
        plain, bom = both("sweep.toml", toml_text(SWEEP, "sweep", "seed", "0"))
    load = {"scenario": load_config, "sweep": load_sweep_config, "pretrain": load_pretrain}[kind]
    if kind == "pretrain":
        plain, bom = both("pre.toml", pretrain_text())
    got = repr(load(bom).model_dump(exclude={"path"}))  # the sweep names its scenario's path
    assert got.replace(str(bom.parent), str(plain.parent)) == repr(
        load(plain).model_dump(exclude={"path"})
    )


def test_a_bad_key_after_a_byte_order_mark_is_one_line(tmp_path, capsys):
    path = tmp_path / "bad.toml"
    path.write_bytes(BOM + toml_text(SYNTHETIC, "swarm", "eta", "nan").encode())
    code = main(["evaluate", "--config", str(path), "--quiet", "--no-report"])
    _one_line(capsys, code, path, "[swarm].eta")


def _one_line(capsys, code: int, path: Path, needle: str) -> None:
    err = capsys.readouterr().err
    assert code == 2, err
    assert err.count("\n") == 1 and err.startswith("twin: error: "), err
    assert str(path) in err and needle in err, err
    assert "Traceback" not in err


@pytest.mark.parametrize(
    ("command", "text"),
    [
        (["evaluate"], "[swarm]\neta = nan\n"),
        (["run", "--horizon", "1"], '[traffic]\nkind = "sumo"\nmesoscopic = "false"\n'),
        (["pretrain"], "lr = inf\n"),
        (["sweep"], '[sweep]\nswarms = ["greedy"]\n[[scenario]]\nname = "../up"\nconfig = "x"\n'),
    ],
)
def test_python_m_twin_exits_2_without_traceback(tmp_path, command, text):
    path = tmp_path / "bad.toml"
    path.write_text(text)
    cmd = [sys.executable, "-m", "twin", command[0], "--config", str(path), *command[1:]]
    proc = subprocess.run(cmd, capture_output=True, text=True, timeout=120)
    assert proc.returncode == 2 and proc.stderr.count("\n") == 1, proc.stderr
    assert "Traceback" not in proc.stderr and str(path) in proc.stderr


def test_sweep_grid_override_reaches_the_sumo_grid():
    """A sweep's ``grid.nx`` override on a SUMO scenario is the grid's size (it used to be
    dropped: the SUMO scenario re-read the file to learn whether nx, ny were given)."""
    from twin.sweep import scenario_config

    root = Path(__file__).resolve().parents[1]
    config = scenario_config(root / "configs" / "shenzhen.toml", {"grid.nx": 25})
    assert config.explicit_shape() == (25, 30)
    assert load_config(root / "configs" / "shenzhen.toml").explicit_shape() == (20, 30)


def test_overrides_that_break_a_check_across_tables_are_named(tmp_path, capsys, monkeypatch):
    """A pretraining's ``scenario_overrides`` that shrink the map below the shipped training
    map's disturbances: the error names the user's file and keys, not only the shipped file
    (which the user does not edit; probe 14's f03)."""
    monkeypatch.setattr(twin.training.pretrain, "pretrain", None)
    path = tmp_path / "small.toml"
    path.write_text(
        toml_text(PRETRAIN, "", "scenario_overrides", '{ "grid.nx" = 6, "grid.ny" = 6 }')
    )
    code = main(["pretrain", "--config", str(path), "--quiet"])
    _one_line(capsys, code, path, "cells off the 6 x 6 map")


@pytest.mark.parametrize(
    ("overrides", "words"),
    [('{ "traffic.kind" = "sumo" }', "scenario_overrides 'traffic.kind' = 'sumo': pretraining collects on a synthetic map"),
     ('{ "swarm.starts" = [[0, 0], [1, 1]] }', "scenario_overrides 'swarm.starts' gives start cells")],
)  # fmt: skip
def test_a_pretraining_override_is_blamed_not_the_shipped_map(tmp_path, capsys, overrides, words):
    """The user's override named, not a valid key of the shipped training map it made
    unknown, nor the map as giving what the override gave (probe 15's f26)."""
    path = tmp_path / "o.toml"
    path.write_text(toml_text(PRETRAIN, "", "scenario_overrides", overrides))
    code = main(["pretrain", "--config", str(path), "--quiet"])
    _one_line(capsys, code, path, words)
    assert "training-map.toml" not in capsys.readouterr().err


@pytest.mark.parametrize(
    "overrides", ['{ "traffic.disturbances" = [] }', '{ "traffic.z_lo" = 5.0 }']
)
def test_an_override_that_empties_the_training_map_is_named(tmp_path, capsys, overrides):
    """A map made empty by an override (no disturbance, z_lo above every z): the error names
    the user's key beside the shipped map (probe 15's P2-f11)."""
    path = tmp_path / "o.toml"
    path.write_text(toml_text(PRETRAIN, "", "scenario_overrides", overrides))
    code = main(["pretrain", "--config", str(path), "--quiet"])
    key = overrides.split('"')[1]
    _one_line(capsys, code, path, f"(the config as changed by {path}: scenario_overrides '{key}')")


SHIPPED_OF_KIND = {
    "scenario": "synthetic",
    "sweep": "sweep-demo",
    "transfer": "transfer",
    "pretraining": "pretrain",
}
COMMAND_OF_KIND = {
    "scenario": ["evaluate"],
    "sweep": ["sweep"],
    "transfer": ["transfer"],
    "pretraining": ["pretrain"],
}


@pytest.mark.parametrize(
    ("given", "wanted"),
    [(g, w) for g in SHIPPED_OF_KIND for w in COMMAND_OF_KIND if g != w],
)
def test_a_config_of_another_kind_is_named_as_what_it_is(tmp_path, capsys, given, wanted):
    """A shipped config given to a command of another kind: named as what it is and the
    command that reads it, not by its first key the command does not know ("[seed] is not a
    known section" for a pretraining config given to `twin evaluate` or `make_env`)."""
    path = tmp_path / f"{given}.toml"
    path.write_text(
        twin.resources.shipped_config(SHIPPED_OF_KIND[given]).read_text()
    )  # its relative paths are never read: the kind is told first
    code = main([*COMMAND_OF_KIND[wanted], "--config", str(path)])
    _one_line(capsys, code, path, f"is a {given} config, not a {wanted} config")
    assert not any(p for p in tmp_path.iterdir() if p != path)


def test_a_config_of_another_kind_is_named_so_whatever_the_flags_set(tmp_path, capsys):
    """A flag setting a key of the command's kind (--epochs) made a scenario config look like
    a pretraining one, and the message named its first wrong key (the review)."""
    path = tmp_path / "synthetic.toml"
    path.write_text(twin.resources.shipped_config("synthetic").read_text())
    code = main(["pretrain", "--config", str(path), "--epochs", "3"])
    _one_line(capsys, code, path, "is a scenario config, not a pretraining config")


def test_make_env_names_a_pretraining_config_as_what_it_is():
    from twin.env import make_env

    with pytest.raises(twin.config.ConfigError, match="is a pretraining config, not a scenario"):
        make_env("pretrain")
