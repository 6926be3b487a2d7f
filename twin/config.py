"""Scenario configs: TOML files validated on load.

A config has the sections ``[grid]``, ``[swarm]``, ``[traffic]`` and ``[evaluate]`` (see
``configs/synthetic.toml``). Every problem is reported as one :class:`UserError` line that
names the file, the key and the fix. Traffic kinds other than ``synthetic`` (``sumo``) keep
their table as given; their own module validates it.
"""

from __future__ import annotations

import dataclasses
import tomllib
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from twin.errors import UserError
from twin.grid import Grid
from twin.resources import shipped_config as shipped_config  # re-export (moved there)
from twin.scores import ScoreParams


@dataclass
class GridConfig:
    nx: int = 20
    ny: int = 30
    obstacles: list = field(default_factory=list)  # [[i, j], ...]


@dataclass
class SwarmConfig:
    n_drones: int = 4
    starts: Any = "random"  # "random" or [[i, j], ...]
    eta: float = 0.1
    delta: float = 0.025
    alpha_T: float = 1.0
    alpha_I: float = 0.5


@dataclass
class DisturbanceConfig:
    kind: str = "big"
    i: float = 0.0
    j: float = 0.0
    amplitude: float = 1.0
    sigma: float = 1.0


@dataclass
class SyntheticConfig:
    kind: str = "synthetic"
    horizon: int = 2000
    beta1: float = 0.7
    beta2: float = 5.0
    z_lo: float = 0.0
    z_hi: float | None = None
    disturbances: list = field(default_factory=list)


@dataclass
class EvaluateConfig:
    swarms: list = field(default_factory=lambda: ["random", "greedy", "sweeping"])
    seeds: int = 1
    seed: int = 0


@dataclass
class ScenarioConfig:
    path: Path
    grid: GridConfig
    swarm: SwarmConfig
    traffic: dict[str, Any]
    evaluate: EvaluateConfig
    #: ``[swarm_options.<name>]``: keyword options of ``make_policy(name, ...)``
    swarm_options: dict[str, dict[str, Any]] = field(default_factory=dict)

    def make_swarm(self, name: str):
        """The swarm ``name`` with this config's options for it."""
        from twin.policies import make_policy

        options = dict(self.swarm_options.get(name, {}))
        if isinstance(options.get("checkpoint"), str):  # relative to the config, as in sweeps
            options["checkpoint"] = self.path.parent / options["checkpoint"]
        try:
            return make_policy(name, **options)
        except TypeError as exc:
            raise _fail(
                self.path,
                f"[swarm_options.{name}]",
                f"has an option the swarm does not take ({exc})",
            ) from None

    @property
    def params(self) -> ScoreParams:
        s = self.swarm
        return ScoreParams(eta=s.eta, delta=s.delta, alpha_T=s.alpha_T, alpha_I=s.alpha_I)


class ConfigError(UserError):
    pass


def _fail(path: Path, key: str, problem: str) -> ConfigError:
    return ConfigError(f"{path}: {key} {problem}")


def _typed(path: Path, key: str, value: Any, kind: Any) -> Any:
    """Check ``value`` against a dataclass field type (int, float, str, list, optional)."""
    if kind in ("float", float, "float | None"):
        if kind == "float | None" and value is None:
            return None
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise _fail(path, key, f"must be a number, got {value!r}")
        return float(value)
    if kind in ("int", int):
        if isinstance(value, bool) or not isinstance(value, int):
            raise _fail(path, key, f"must be a whole number, got {value!r}")
        return value
    if kind in ("str", str):
        if not isinstance(value, str):
            raise _fail(path, key, f"must be a string, got {value!r}")
        return value
    if kind in ("list", list):
        if not isinstance(value, list):
            raise _fail(path, key, f"must be a list, got {value!r}")
        return value
    return value


def build_section(path: Path, section: str, table: Any, cls: type) -> Any:
    """Build dataclass ``cls`` from a TOML table, rejecting unknown keys and wrong types."""
    if not isinstance(table, dict):
        raise _fail(path, f"[{section}]", "must be a table")
    fields = {f.name: f for f in dataclasses.fields(cls)}
    for key in table:
        if key not in fields:
            raise _fail(
                path,
                f"[{section}].{key}",
                f"is not a known key; use one of: {', '.join(fields)}",
            )
    values = {k: _typed(path, f"[{section}].{k}", v, fields[k].type) for k, v in table.items()}
    return cls(**values)


def _cell_list(path: Path, key: str, value: Any) -> np.ndarray:
    cells = np.asarray(value, dtype=object)
    if len(value) == 0:
        return np.zeros((0, 2), dtype=np.int64)
    ok = (
        cells.ndim == 2
        and cells.shape[1] == 2
        and all(isinstance(x, int) and not isinstance(x, bool) for x in cells.ravel())
    )
    if not ok:
        raise _fail(path, key, "must be a list of [row, column] pairs of whole numbers")
    return cells.astype(np.int64)


def read_toml(path: str | Path) -> dict[str, Any]:
    path = Path(path)
    try:
        with open(path, "rb") as fh:
            return tomllib.load(fh)
    except FileNotFoundError:
        raise UserError(f"{path}: config file not found; check the path") from None
    except IsADirectoryError:
        raise UserError(f"{path}: is a folder, not a config file") from None
    except PermissionError:
        raise UserError(f"{path}: config file is not readable (permission denied)") from None
    except tomllib.TOMLDecodeError as exc:
        raise UserError(f"{path}: not valid TOML ({exc})") from None
    except UnicodeDecodeError:
        raise UserError(f"{path}: not a text file; expected a TOML config") from None


def load_config(path: str | Path) -> ScenarioConfig:
    """Read and validate a scenario config."""
    path = Path(path)
    return config_from_data(path, read_toml(path))


def config_from_data(path: Path, data: dict[str, Any]) -> ScenarioConfig:
    """Validate the tables of a scenario config read from ``path`` (perhaps with overrides)."""
    known = {"grid", "swarm", "traffic", "evaluate", "swarm_options"}
    for key in data:
        if key not in known:
            raise _fail(
                path, f"[{key}]", f"is not a known section; use: {', '.join(sorted(known))}"
            )
    grid = build_section(path, "grid", data.get("grid", {}), GridConfig)
    swarm = build_section(path, "swarm", data.get("swarm", {}), SwarmConfig)
    evaluate = build_section(path, "evaluate", data.get("evaluate", {}), EvaluateConfig)
    traffic = data.get("traffic", {"kind": "synthetic"})
    if not isinstance(traffic, dict):
        raise _fail(path, "[traffic]", "must be a table")
    traffic.setdefault("kind", "synthetic")
    options = data.get("swarm_options", {})
    if not isinstance(options, dict) or not all(isinstance(v, dict) for v in options.values()):
        raise _fail(
            path, "[swarm_options]", "must hold one table per swarm, e.g. [swarm_options.rl]"
        )
    config = ScenarioConfig(path, grid, swarm, traffic, evaluate, options)
    validate(config)
    return config


def validate(config: ScenarioConfig) -> None:
    path, s, g, e = config.path, config.swarm, config.grid, config.evaluate
    for key in ("eta", "delta"):
        value = getattr(s, key)
        if not 0.0 < value < 1.0:
            raise _fail(path, f"[swarm].{key}", f"= {value} must lie in (0, 1), e.g. 0.1 or 0.025")
    for key in ("alpha_T", "alpha_I"):
        if getattr(s, key) < 0:
            raise _fail(path, f"[swarm].{key}", "must be >= 0")
    if s.n_drones < 1:
        raise _fail(path, "[swarm].n_drones", f"= {s.n_drones} must be at least 1")
    if e.seeds < 1:
        raise _fail(path, "[evaluate].seeds", f"= {e.seeds} must be at least 1")
    if not e.swarms or not all(isinstance(x, str) for x in e.swarms):
        raise _fail(path, "[evaluate].swarms", "must be a non-empty list of swarm names")
    if config.traffic["kind"] == "synthetic":
        if g.nx < 1 or g.ny < 1:
            raise _fail(path, "[grid].nx/ny", f"= {g.nx} x {g.ny} must both be at least 1")
        traffic = synthetic_config(config)
        if traffic.horizon < 1:
            raise _fail(path, "[traffic].horizon", f"= {traffic.horizon} must be at least 1")
        grid = make_grid(config)
        check_swarm_fits(config, grid)


def make_grid(config: ScenarioConfig) -> Grid:
    """The grid of a config with explicit cells (synthetic scenarios)."""
    path, g = config.path, config.grid
    obstacles = np.zeros((g.nx, g.ny), dtype=bool)
    cells = _cell_list(path, "[grid].obstacles", g.obstacles)
    if len(cells):
        inside = (cells >= 0).all(axis=1) & (cells < [g.nx, g.ny]).all(axis=1)
        if not inside.all():
            bad = cells[~inside][0].tolist()
            raise _fail(path, "[grid].obstacles", f"has {bad} off the {g.nx} x {g.ny} map")
        obstacles[cells[:, 0], cells[:, 1]] = True
    if obstacles.all():
        raise _fail(path, "[grid].obstacles", "cover every cell; leave at least one free cell")
    return Grid(obstacles)


def check_swarm_fits(config: ScenarioConfig, grid: Grid) -> None:
    """Enough free cells for the drones; explicit starts on distinct free cells of the map."""
    path, s = config.path, config.swarm
    if s.n_drones > grid.n_free:
        raise _fail(
            path,
            "[swarm].n_drones",
            f"= {s.n_drones} exceeds the {grid.n_free} free cells; use fewer drones",
        )
    if isinstance(s.starts, str):
        if s.starts != "random":
            raise _fail(path, "[swarm].starts", 'must be "random" or a list of [row, column] cells')
        return
    starts = _cell_list(path, "[swarm].starts", s.starts)
    if len(starts) != s.n_drones:
        raise _fail(
            path,
            "[swarm].starts",
            f"lists {len(starts)} cells for {s.n_drones} drones; give one each",
        )
    for cell in starts:
        if not grid.inside(cell):
            raise _fail(
                path, "[swarm].starts", f"has {cell.tolist()} off the {grid.nx} x {grid.ny} map"
            )
        if grid.obstacles[cell[0], cell[1]]:
            raise _fail(
                path,
                "[swarm].starts",
                f"has {cell.tolist()} on an obstacle; move it to a free cell",
            )
    if len({tuple(c) for c in starts.tolist()}) != len(starts):
        raise _fail(path, "[swarm].starts", "puts two drones on one cell; give distinct cells")


def start_positions(config: ScenarioConfig, grid: Grid, rng: np.random.Generator) -> np.ndarray:
    from twin.patrol import random_starts

    if isinstance(config.swarm.starts, str):
        return random_starts(grid, config.swarm.n_drones, rng)
    return _cell_list(config.path, "[swarm].starts", config.swarm.starts)


def synthetic_config(config: ScenarioConfig) -> SyntheticConfig:
    path = config.path
    traffic = build_section(path, "traffic", config.traffic, SyntheticConfig)
    for n, table in enumerate(traffic.disturbances):
        d = build_section(path, f"traffic.disturbances[{n}]", table, DisturbanceConfig)
        if d.kind not in ("big", "small"):
            raise _fail(
                path, f"[traffic.disturbances[{n}]].kind", f'= {d.kind!r} must be "big" or "small"'
            )
        if d.sigma <= 0:
            raise _fail(path, f"[traffic.disturbances[{n}]].sigma", "must be > 0")
    if traffic.beta1 <= 0 or traffic.beta2 <= 0:
        raise _fail(path, "[traffic].beta1/beta2", "must be > 0")
    if traffic.z_hi is not None and traffic.z_hi <= traffic.z_lo:
        raise _fail(path, "[traffic].z_hi", f"= {traffic.z_hi} must exceed z_lo = {traffic.z_lo}")
    return traffic


def synthetic_source(config: ScenarioConfig, grid: Grid | None = None):
    """The :class:`SyntheticTraffic` a synthetic config describes."""
    from twin.traffic.synthetic import Disturbance, SyntheticTraffic

    t = synthetic_config(config)
    grid = grid or make_grid(config)
    disturbances = [
        Disturbance(
            **dataclasses.asdict(
                build_section(config.path, "traffic.disturbances", d, DisturbanceConfig)
            )
        )
        for d in t.disturbances
    ]
    return SyntheticTraffic(grid, disturbances, t.horizon, t.beta1, t.beta2, t.z_lo, t.z_hi)
