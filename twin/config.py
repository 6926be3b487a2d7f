"""Scenario configs: TOML files validated on load by pydantic models.

A config has the sections ``[grid]``, ``[swarm]``, ``[traffic]``, ``[evaluate]`` and
``[swarm_options.<swarm>]`` (see ``configs/synthetic.toml``). ``[traffic]`` is a tagged union on
``kind``: ``"synthetic"`` (:class:`SyntheticConfig`) or ``"sumo"`` (:class:`SumoSettings`).
Types are strict (no ``"500"`` for a number, no ``"false"`` for a bool), numbers finite, unknown
keys refused. Every problem is reported as one :class:`ConfigError` line naming the file, the
key, the value and the fix (:func:`validation_error` serves every config kind: scenario, sweep,
pretraining). Command-line flags, sweep keys and a transfer's schedule change a config
(:class:`SourcedConfig`: a scenario, a pretraining) by one path, dotted keys applied to its
tables and validated by the same models (:func:`with_overrides`); an error then names the flag
or the key.
"""

from __future__ import annotations

import codecs
import copy
import itertools
import math
import re
import sys
import tomllib
import types
import typing
from collections.abc import Iterable, Mapping
from pathlib import Path
from typing import Annotated, Any, ClassVar, Literal, Self, TypeVar

import numpy as np
from pydantic import (
    AfterValidator,
    BaseModel,
    BeforeValidator,
    ConfigDict,
    Field,
    PrivateAttr,
    ValidationError,
    ValidationInfo,
    field_validator,
    model_validator,
)

from twin.clock import CLOCK_HINT, clock_seconds
from twin.errors import UserError
from twin.files import not_a_file
from twin.grid import Grid
from twin.mfd import SETTING_RANGES as MFD_SETTING_RANGES
from twin.resources import shipped_config as shipped_config  # re-export (moved there)
from twin.scores import ScoreParams
from twin.seeds import MAX_SEED
from twin.swarms import base_name, check_swarm_name, make_policy


class ConfigError(UserError):
    pass


#: Each kind of config file: what it is called, the command that reads it, and whether a
#: file's top level holds what only that kind has (a file given to another command is named
#: as what it is, not by its first unknown key).
CONFIG_KINDS: dict[str, tuple[str, str, Any]] = {
    "scenario": (
        "a scenario config",
        "twin run --config",
        lambda d: any(isinstance(d.get(k), dict) for k in ("grid", "swarm", "traffic", "faults")),
    ),
    "sweep": ("a sweep config", "twin sweep --config", lambda d: isinstance(d.get("sweep"), dict)),
    "transfer": (
        "a transfer config",
        "twin transfer --config",
        lambda d: isinstance(d.get("transfer"), dict) or isinstance(d.get("row"), list),
    ),
    "pretraining": (
        "a pretraining config",
        "twin pretrain --config",
        lambda d: any(k in d for k in ("epochs", "episodes", "batch_size", "lr", "gamma")),
    ),
}


def check_config_kind(path: str | Path, data: Mapping[str, Any], kind: str) -> None:
    """Refuse a file of another kind than ``kind`` (:data:`CONFIG_KINDS`) in one line naming
    what it is and the command that reads it; a file that looks like none is left to the
    model's own checks."""
    name, _, looks = CONFIG_KINDS[kind]
    if looks(data):
        return
    for other, (other_name, command, other_looks) in CONFIG_KINDS.items():
        if other != kind and other_looks(data):
            raise ConfigError(
                f"{path}: is {other_name}, not {name} (`{command} {path}` reads it); give "
                f"{name} here"
            )


class StrictModel(BaseModel):
    """Base of every config table: strict types, finite numbers, no unknown keys."""

    model_config = ConfigDict(strict=True, extra="forbid", allow_inf_nan=False)


class SourcedConfig(StrictModel):
    """A config that keeps the tables it was validated from (:meth:`from_data`), so that
    dotted-key overrides can be set in them and validated again (:func:`with_overrides`)."""

    #: the file's top level holds tables (``[grid]``...) or plain keys (pretraining)
    FILE_TABLES: ClassVar[bool] = True
    #: its kind of config file (:data:`CONFIG_KINDS`)
    KIND: ClassVar[str] = "scenario"

    _path: Path = PrivateAttr(default=Path("config.toml"))
    _tables: dict[str, Any] | None = PrivateAttr(default=None)  # as read, overrides applied
    _flags: dict[str, str] = PrivateAttr(default_factory=dict)  # dotted key -> its flag
    #: dotted key -> the flag or other file's key that set it (named in later errors)
    _labels: dict[str, str] = PrivateAttr(default_factory=dict)

    @classmethod
    def from_data(
        cls,
        path: str | Path,
        data: dict[str, Any],
        labels: Mapping[str, str] | None = None,
        flags: Mapping[str, str] | None = None,
    ) -> Self:
        """Validate the tables read from ``path`` (paths in them are relative to it);
        ``labels`` names the flag or key that set a dotted key, named in an error instead of
        the file; ``flags`` the command-line flags among them (:func:`with_overrides`)."""
        check_config_kind(path, data, cls.KIND)
        cls.check_data(path, data)
        try:
            config = cls.model_validate(data, context={"path": Path(path)})
        except ValidationError as exc:
            error = validation_error(path, exc, data, cls, sections=cls.FILE_TABLES, labels=labels)
            raise _naming_changes(error, labels) from None
        config._path = Path(path)
        config._tables = copy.deepcopy(data)
        config._flags = dict(flags or {})
        config._labels = dict(labels or {})
        try:
            config.check()
        except UserError as exc:  # a check across tables: name what changed the file too
            raise _naming_changes(exc, labels) from None
        return config

    @classmethod
    def check_data(cls, path: str | Path, data: dict[str, Any]) -> None:
        """Checks of the tables before the models see them (e.g. a key that moved)."""

    def check(self) -> None:
        """Checks after the models, across tables (e.g. the drones fit the grid)."""

    @property
    def path(self) -> Path:
        return self._path

    def flag_of(self, key: str) -> str | None:
        """The command-line flag that set the dotted ``key`` (:func:`with_overrides`), or None
        when the file (or a sweep key, or the default) did."""
        return self._flags.get(key)

    def set_by(self, keys: Iterable[str]) -> list[str]:
        """The flags or other files' keys (a sweep's) that set any of the dotted ``keys``
        (sorted; empty when the file, or the defaults, set them all)."""
        keys = set(keys)
        return sorted({label for key, label in self._labels.items() if key in keys})


def _naming_changes(exc: UserError, labels: Mapping[str, str] | None) -> UserError:
    """``exc`` about a file that flags or another file's keys (``labels``) changed, with them
    named when it names none (a check of a whole table blames the file, which the user may
    not edit: a shipped training map)."""
    shown = sorted(set((labels or {}).values()))
    if not shown or any(label in str(exc) for label in shown):
        return exc
    return type(exc)(f"{exc} (the config as changed by {', '.join(shown)})")


def _relative(value: Any, info: ValidationInfo) -> Any:
    """A path relative to the folder of the config being read (``context["path"]``)."""
    if not isinstance(value, (str, Path)):
        raise ValueError("must be a file name (a string)")
    p = Path(value)
    base = Path((info.context or {}).get("path", "config.toml")).parent
    return p if p.is_absolute() else (base / p).resolve()


def _existing(path: Path) -> Path:
    why = not_a_file(path)
    if why is not None:  # (a pipe's reason names its fix)
        raise ValueError(f"names {path}, which {why}" + ("" if ";" in why else "; fix the path"))
    return path


C = TypeVar("C", bound=SourcedConfig)

#: The tables of a scenario config that dotted-key overrides reach.
SECTIONS = ("grid", "swarm", "traffic", "evaluate")


def check_dotted(key: str) -> str:
    parts = key.split(".")
    if len(parts) < 2 or parts[0] not in SECTIONS or "" in parts:
        raise ValueError(
            f"key {key!r}: overrides reach the {', '.join(SECTIONS)} tables of a scenario "
            "config, by dotted keys; e.g. 'swarm.n_drones'"
        )
    return key


def _dotted_keys(overrides: dict[str, Any]) -> dict[str, Any]:
    for key in overrides:
        check_dotted(key)
    return overrides


#: a path relative to the folder of the config that names it
RelPath = Annotated[Path, BeforeValidator(_relative)]
#: a scenario config file, relative to the config that names it, that exists
ScenarioFile = Annotated[RelPath, AfterValidator(_existing)]
#: dotted-key overrides of a scenario config (``{"swarm.n_drones": 2}``)
Overrides = Annotated[dict[str, Any], AfterValidator(_dotted_keys)]


#: A ``[row, column]`` cell of the grid.
Cell = Annotated[list[int], Field(min_length=2, max_length=2)]
Count = Annotated[int, Field(ge=1)]
#: The most steps a run may have: ten million (the memory estimate refuses far fewer on any
#: real grid; beyond it arrays cannot even be shaped).
MAX_HORIZON = 10_000_000
Horizon = Annotated[int, Field(ge=1, le=MAX_HORIZON)]
#: The largest reward weight (Def. 4): sums of a run's rewards stay finite.
MAX_WEIGHT = 1e6
Weight = Annotated[float, Field(ge=0, le=MAX_WEIGHT)]
Seed = Annotated[int, Field(ge=0, le=MAX_SEED)]


Unit = Annotated[float, Field(gt=0, lt=1)]

_NAME = re.compile(r"[A-Za-z0-9_][A-Za-z0-9_.+=-]*")
#: The longest name: file names built from it (a cell's id, a row's folder) stay well under
#: the 255 bytes file systems allow.
MAX_NAME = 100


def check_name(value: str) -> str:
    """A name that is safe as (part of) a file name inside a folder: no ``/``, ``..``, spaces,
    at most :data:`MAX_NAME` characters."""
    if not _NAME.fullmatch(value) or ".." in value:
        raise ValueError(
            "must be a plain name of letters, digits, '-', '_', '.' (no '/', '..' or spaces); "
            'e.g. "rush-hour"'
        )
    if len(value) > MAX_NAME:
        raise ValueError(
            f"is {len(value)} characters long; give at most {MAX_NAME} (it names files)"
        )
    return value


def check_clock(text: str) -> str:
    """A clock time ``HH:MM`` or ``HH:MM:SS``, after ``Nd`` on a later day."""
    if clock_seconds(text) is None:
        raise ValueError(CLOCK_HINT)
    return text


def _cells(value: Any) -> Any:
    ok = isinstance(value, list) and all(
        isinstance(c, list)
        and len(c) == 2
        and all(isinstance(x, int) and not isinstance(x, bool) for x in c)
        for c in value
    )
    if not ok:
        raise ValueError("must be a list of [row, column] pairs of whole numbers")
    return value


# --------------------------------------------------------------------------------- sections
class GridConfig(StrictModel):
    nx: Count = 20
    ny: Count = 30
    obstacles: list[Cell] = []  # [[i, j], ...]


class SwarmConfig(StrictModel):
    n_drones: Count = 4
    starts: Any = "random"  # "random" or [[i, j], ...]
    eta: Unit = 0.1
    #: at least 1e-9: a smaller recovery is 0 in the steps' arithmetic (and no run is that long)
    delta: Annotated[float, Field(ge=1e-9, lt=1)] = 0.025
    alpha_T: Weight = 1.0
    alpha_I: Weight = 0.5

    @field_validator("starts", mode="plain")
    @classmethod
    def _starts(cls, value: Any) -> Any:
        if isinstance(value, str):
            if value != "random":
                raise ValueError('must be "random" or a list of [row, column] cells')
            return value
        return _cells(value)

    @field_validator("alpha_I")
    @classmethod
    def _some_weight(cls, value: float, info) -> float:
        if value == 0 and info.data.get("alpha_T") == 0:
            raise ValueError("and alpha_T are both 0: every reward would be 0; give one above 0")
        return value


class DisturbanceConfig(StrictModel):
    kind: Literal["big", "small"] = "big"
    i: float = 0.0
    j: float = 0.0
    amplitude: float = 1.0
    sigma: Annotated[float, Field(ge=1e-3, le=1e6)] = 1.0  # cells (its square must not overflow)


#: The largest beta2 (periods of a small disturbance over the horizon): the phase 2 pi beta2 k/T
#: of A_small is then computed to about 1e-7 rad (its rounding, ulp(2 pi beta2)); past it
#: the floats' sines are no longer the formula's (at 1e307 the phase overflows).
MAX_BETA2 = 1e8


class SyntheticConfig(StrictModel):
    kind: Literal["synthetic"] = "synthetic"
    horizon: Horizon = 2000
    beta1: Annotated[float, Field(gt=0)] = 0.7
    beta2: Annotated[float, Field(gt=0, le=MAX_BETA2)] = 5.0
    z_lo: float = 0.0
    z_hi: float | None = None
    disturbances: list[DisturbanceConfig] = []

    @field_validator("z_hi")
    @classmethod
    def _z_hi(cls, value: float | None, info) -> float | None:
        z_lo = info.data.get("z_lo")
        if value is not None and z_lo is not None and value <= z_lo:
            raise ValueError(f"must exceed z_lo = {z_lo}")
        return value


def _setting_range(name: str) -> Any:
    low, high = MFD_SETTING_RANGES[name]
    return Annotated[float, Field(ge=low, le=high)]


class MFDSettings(StrictModel):
    """``[traffic.mfd]``: the MFD's form ``v(k) = a v_lim exp(-k / k_c)`` (prior, or fixed)
    and the share of vehicles a drone sees, in :data:`twin.mfd.SETTING_RANGES`."""

    fit: Literal["online", "fixed"] = "online"
    a: _setting_range("a") = 0.7
    k_c: _setting_range("k_c") = 40.0
    detection_p: _setting_range("detection_p") = 1.0


#: The longest incident (minutes, about 1900 years): one past a run's end lasts to its end.
MAX_INCIDENT_MIN = 1e9


class IncidentSettings(StrictModel):
    """``[[traffic.incidents]]``: a lane or edge closed, or a vehicle stopped, for a while.

    Where: ``edge`` (a SUMO edge id, with ``lane`` its lane index for "lane_closed") or ``cell``
    ([i, j]): twin takes the edge of that cell with the most vehicles at the onset. When:
    ``begin`` (clock time) or ``step`` (k of ``T^k``), for ``duration_min`` minutes.
    """

    kind: Literal["lane_closed", "edge_closed", "vehicle_stopped"]
    edge: str | None = None
    lane: Annotated[int, Field(ge=0)] = 0
    cell: Cell | None = None
    begin: str | None = None
    step: Annotated[int, Field(ge=0)] | None = None
    # at most MAX_INCIDENT_MIN: its end stays a time on SUMO's clock (1e308 min overflowed)
    duration_min: Annotated[float, Field(gt=0, le=MAX_INCIDENT_MIN)]

    @field_validator("begin")
    @classmethod
    def _begin(cls, value: str | None) -> str | None:
        return None if value is None else check_clock(value)

    @field_validator("duration_min")
    @classmethod
    def _a_sumo_step_at_least(cls, value: float, info: ValidationInfo) -> float:
        recorded = (info.context or {}).get("recorded")  # an earlier twin's run took one
        if value * 60.0 < 1.0 and not recorded:  # applied and lifted on SUMO's steps
            raise ValueError(
                f"lasts {value * 60.0:.12g} s, shorter than SUMO's 1 s step, on which incidents "
                "are applied and lifted; give at least 1/60 (1 s)"
            )
        return value

    @model_validator(mode="after")
    def _one_place_one_time(self) -> IncidentSettings:
        if (self.edge is None) == (self.cell is None):
            raise ValueError('needs either edge = "<edge id>" or cell = [i, j], not both')
        if (self.begin is None) == (self.step is None):
            raise ValueError('needs either begin = "HH:MM" or step = <k>, not both')
        if self.lane != 0 and self.kind != "lane_closed":  # (a dumped config holds lane = 0)
            raise ValueError(
                f'gives lane = {self.lane}, which only kind = "lane_closed" reads (a {self.kind} '
                'takes every lane); leave lane out, or use kind = "lane_closed"'
            )
        return self


class DetectorSettings(StrictModel):
    """``[traffic.detectors]``: fixed detectors the twin reads (:mod:`twin.sumo.detectors`).

    ``scenario``: the induction loops and lane-area detectors of the scenario's additional
    files; ``virtual_loops``: that many loop stations placed by the documented rule;
    ``cells``: loop stations at these cells instead (not both).
    """

    scenario: bool = False
    virtual_loops: Annotated[int, Field(ge=0, le=10000)] = 0
    cells: list[Cell] = []

    @model_validator(mode="after")
    def _one_placement(self) -> DetectorSettings:
        if self.virtual_loops and self.cells:
            raise ValueError("gives both virtual_loops and cells; give one of them")
        return self


class SumoSettings(StrictModel):
    """``[traffic] kind = "sumo"``; see :mod:`twin.sumo.scenario` for the meaning of each key."""

    kind: Literal["sumo"] = "sumo"
    network: str | None = "shenzhen_like"
    net: str | None = None
    routes: Any = []  # a route file or a list of them
    additional: Any = []  # additional file(s) for SUMO: vehicle types, signals, detectors, ...
    sumocfg: str | None = None
    osm: str | None = None
    cell_m: Annotated[float, Field(gt=0)] = 500.0
    drone_speed_kmh: Annotated[float, Field(gt=0)] = 24.0
    begin: str = "07:00"
    end: str | None = None  # end of the scenario's window (clock); default: its demand's
    horizon: Horizon = 144
    warmup_min: Annotated[float, Field(ge=0)] = 30.0
    seed: Seed = 0
    mesoscopic: bool = False
    min_lane_km: Annotated[float, Field(ge=0)] = 0.0
    demand_scale: Annotated[float, Field(gt=0)] = 1.0
    reads_per_step: Annotated[int, Field(ge=1, le=75)] = 3
    mfd: MFDSettings = MFDSettings()
    incidents: list[IncidentSettings] = []
    detectors: DetectorSettings = DetectorSettings()

    @field_validator("network")
    @classmethod
    def _network(cls, value: str | None) -> str | None:
        if value is None:
            return None
        from twin.resources import network_names

        known = network_names()
        if check_name(value) not in known:
            raise ValueError(f"is not a built-in network; use one of: {', '.join(known)}")
        return value

    @model_validator(mode="after")
    def _one_source_of_files(self) -> SumoSettings:
        if self.osm is not None and (self.net is not None or self.sumocfg is not None):
            raise ValueError(
                "[traffic].osm with net or sumocfg: give osm alone (twin imports it), or net "
                "and/or sumocfg"
            )
        return self

    @field_validator("begin")
    @classmethod
    def _begin(cls, value: str) -> str:
        return check_clock(value)

    @field_validator("end")
    @classmethod
    def _end(cls, value: str | None) -> str | None:
        return None if value is None else check_clock(value)

    @field_validator("routes", "additional", mode="plain")
    @classmethod
    def _routes(cls, value: Any) -> list[str]:
        value = [value] if isinstance(value, str) else value
        if not isinstance(value, list) or not all(isinstance(r, str) for r in value):
            raise ValueError("must be a file or a list of them")
        empty = [n for n, r in enumerate(value) if not r.strip()]
        if empty:
            raise ValueError(f"has an empty file name (entry {empty[0] + 1}); remove it")
        return value

    @field_validator("net", "sumocfg", "osm")
    @classmethod
    def _file(cls, value: str | None) -> str | None:
        if value is not None and not value.strip():
            raise ValueError("is an empty file name; give a file or leave the key out")
        return value

    @property
    def step_s(self) -> float:
        return self.cell_m / (self.drone_speed_kmh / 3.6)


class EvaluateConfig(StrictModel):
    swarms: Annotated[list[str], Field(min_length=1)] = ["random", "greedy", "sweeping"]
    seeds: Count = 1
    seed: Seed = 0

    @field_validator("swarms")
    @classmethod
    def _swarms(cls, swarms: list[str]) -> list[str]:
        from twin.swarms import check_swarm_list

        check_swarm_list(swarms)
        return swarms


class DroneLossConfig(StrictModel):
    """``[[faults.drone_loss]]``: drone ``drone`` (0-based) lost at ``step``, back at ``back``."""

    drone: Annotated[int, Field(ge=0, description="the lost drone, 0 .. n_drones - 1")]
    step: Annotated[int, Field(ge=1, description="first step without it, 1 .. T - 1")]
    back: Annotated[int, Field(ge=1)] | None = Field(
        None, description="first step with it again (left out: lost to the end)"
    )


class FaultsConfig(StrictModel):
    """``[faults]``: scripted faults applied to every swarm (see :mod:`twin.faults`)."""

    drone_loss: list[DroneLossConfig] = Field(
        [], description="drones lost for steps step <= k < back: they neither move, see nor score"
    )
    coordinator_down: list[Annotated[list[int], Field(min_length=2, max_length=2)]] = Field(
        [], description="[[start, stop], ...]: steps start <= k < stop without the coordinator"
    )
    detection_p: Annotated[float, Field(gt=0, le=1)] = Field(
        1.0, description="chance that a drone's sighting of a cell is recorded (seeded)"
    )
    compare: bool = Field(
        True, description="run each swarm's fault-free twin beside it (the degradation table)"
    )

    @field_validator("coordinator_down")
    @classmethod
    def _windows(cls, value: list[list[int]]) -> list[list[int]]:
        for start, stop in value:
            if not 0 <= start < stop:
                raise ValueError(
                    f"[faults].coordinator_down has [{start}, {stop}]; give windows "
                    "[start, stop] with 0 <= start < stop"
                )
        ordered = sorted(value)
        for (a, b), (c, d) in itertools.pairwise(ordered):
            if c < b:  # one outage given twice would be split into phases of one state
                raise ValueError(
                    f"[faults].coordinator_down has [{a}, {b}] and [{c}, {d}], which overlap; "
                    f"give one window [{a}, {max(b, d)}], or separate them"
                )
        return value

    def plan(self):
        """The :class:`twin.faults.FaultPlan` of this table."""
        from twin.faults import DroneLoss, FaultPlan

        return FaultPlan(
            drone_loss=tuple(DroneLoss(d.drone, d.step, d.back) for d in self.drone_loss),
            coordinator_down=tuple((a, b) for a, b in self.coordinator_down),
            detection_p=self.detection_p,
        )


TrafficConfig = Annotated[SyntheticConfig | SumoSettings, Field(discriminator="kind")]


def _finite_options(options: dict[str, dict[str, Any]]) -> dict[str, dict[str, Any]]:
    """Options of registered swarms only (a table for an unknown swarm would be silently
    unused), and finite numbers."""
    for name in options:
        try:
            check_swarm_name(name)
        except UserError as exc:
            raise ValueError(f"[swarm_options.{name}]: {exc}") from None
    for name, table in options.items():
        for key, value in table.items():
            if isinstance(value, float) and not math.isfinite(value):
                raise ValueError(
                    f"[swarm_options.{name}].{key} = {value} must be finite; give a number"
                )
    return options


class ScenarioConfig(SourcedConfig):
    """A scenario config; ``path`` is the file it was read from (paths in it are relative)."""

    grid: GridConfig = GridConfig()
    swarm: SwarmConfig = SwarmConfig()
    traffic: TrafficConfig = SyntheticConfig()
    evaluate: EvaluateConfig = EvaluateConfig()
    #: ``[swarm_options.<name>]``: keyword options of ``make_policy(name, ...)``
    swarm_options: dict[str, dict[str, Any]] = {}
    faults: FaultsConfig = FaultsConfig()

    @model_validator(mode="before")
    @classmethod
    def _default_kind(cls, data: Any) -> Any:
        if isinstance(data, dict) and isinstance(data.get("traffic"), dict):
            data = {**data, "traffic": {"kind": "synthetic", **data["traffic"]}}
        return data

    @model_validator(mode="after")
    def _sumo_grid(self) -> ScenarioConfig:
        given = {"nx", "ny"} & self.grid.model_fields_set
        if self.traffic.kind == "sumo" and len(given) == 1:
            raise ValueError("[grid] gives one of nx, ny; give both (or neither, to fit the map)")
        _finite_options(self.swarm_options)
        if self.faults.coordinator_down:
            for name, options in self.swarm_options.items():
                if "outages" in options:
                    raise ValueError(
                        f"[swarm_options.{name}].outages and [faults].coordinator_down both "
                        "give coordinator outages; keep [faults].coordinator_down alone"
                    )
        return self

    def fault_plan(self):
        """The scenario's :class:`twin.faults.FaultPlan`, or None when it scripts no fault."""
        plan = self.faults.plan()
        return plan if plan.active else None

    def check(self) -> None:
        validate(self)

    def explicit_shape(self) -> tuple[int, int] | None:
        """``[grid] nx, ny`` if the config (or an override) sets them, else None."""
        if {"nx", "ny"} <= self.grid.model_fields_set:
            return self.grid.nx, self.grid.ny
        return None

    def make_swarm(self, name: str, **overrides: Any):
        """The swarm ``name`` with this config's options for it, ``overrides`` on top (a
        sweep's, a flag's). Options the swarm refuses are one line naming the table, and this
        config when it gives them (:meth:`_refused_option`)."""
        own = self.swarm_options.get(name, {})
        options = {**own, **overrides}
        for key in ("checkpoint", "history"):  # relative to the config, as in sweeps
            if isinstance(options.get(key), str):
                options[key] = self.path.parent / options[key]
        try:
            return make_policy(name, **options)
        except (TypeError, ValueError) as exc:  # an unknown option, or a value of a wrong type
            if not options:
                raise
            raise self._refused_option(name, own, overrides, exc) from None
        except UserError as exc:  # a value the swarm refuses, said where the config gives it
            text = str(exc)
            said = re.match(rf"{re.escape(base_name(name))}: (\w+) = ", text)
            theirs = said is not None and said[1] in overrides  # the value the overrides give
            if not own or theirs or str(self.path) in text or text.startswith("[swarm_options"):
                raise
            for lead in (f"{base_name(name)}: ", "swarm option "):  # said by the table now
                text = text.removeprefix(lead)
            raise UserError(f"{self.path}: [swarm_options.{name}]: {text}") from None

    def _refused_option(self, name: str, own: dict, overrides: dict, exc: Exception):
        """The :class:`ConfigError` of options the swarm ``name`` does not take or cannot use:
        naming this config for a key it gives (not one ``overrides`` gives)."""
        text = str(exc)
        word = re.search(r"unexpected keyword argument '([^']+)'", text)
        keys = [word[1]] if word else list({**own, **overrides})
        mine = any(k in own and k not in overrides for k in keys)
        table = f"{self.path}: [swarm_options.{name}]" if mine else f"[swarm_options.{name}]"
        if word:
            return ConfigError(f"{table} has an option {word[1]!r} the {name} swarm does not "
                               "take; remove it")  # fmt: skip
        if "takes no arguments" in text:
            return ConfigError(f"{table} gives options, but the {name} swarm takes none; "
                               "remove them")  # fmt: skip
        given = ", ".join(f"{k} = {v!r}" for k, v in {**own, **overrides}.items())
        return ConfigError(
            f"{table}: the {name} swarm cannot use a value of {given} ({text}); give each the "
            "type of its default (a number, a whole number, true or false, a string)"
        )

    @property
    def params(self) -> ScoreParams:
        s = self.swarm
        return ScoreParams(eta=s.eta, delta=s.delta, alpha_T=s.alpha_T, alpha_I=s.alpha_I)


def config_help() -> str:
    """Every table and key of a scenario config with its default (and meaning, where the model
    states one): what ``--help-config`` prints."""
    from pydantic_core import PydanticUndefined

    lines: list[str] = []

    def table(path: str, model: type[BaseModel], array: bool = False, note: str = "") -> None:
        lines.append((f"[[{path}]]" if array else f"[{path}]") + note)
        nested = []
        for name, f in model.model_fields.items():
            inner = _models(f.annotation)
            if inner:
                nested.append((f"{path}.{name}", inner[0], _is_array(f.annotation)))
                continue
            if f.default is PydanticUndefined and f.default_factory is None:
                text = "(required)"
            else:
                default = f.get_default(call_default_factory=True)
                text = "(none)" if default is None else _toml(default)
            text = text if len(text) <= 30 else text[:27] + "..."
            lines.append(f"  {name:18s} {text:30s} {f.description or ''}".rstrip())
        for args in nested:
            table(*args)

    for section, f in ScenarioConfig.model_fields.items():
        if section == "traffic":
            for model in _models(f.annotation):
                table(
                    "traffic", model, note=f"  (kind = {_toml(model.model_fields['kind'].default)})"
                )
        elif section == "swarm_options":
            lines.append("[swarm_options.<swarm>]")
            lines.append("  <option> = <value>  keyword options of that swarm (docs/guide.md)")
        else:
            table(section, _models(f.annotation)[0])
    return "\n".join(lines)


# --------------------------------------------------------------------------- error messages
def _fail(path: Path, key: str, problem: str) -> ConfigError:
    return ConfigError(f"{path}: {key} {problem}")


_TYPES = {
    "int_type": "a whole number",
    "float_type": "a number",
    "bool_type": "true or false",
    "string_type": "a string",
    "list_type": "a list",
    "dict_type": "a table",
    "model_type": "a table",
    "model_attributes_type": "a table",
}


def _models(annotation: Any) -> list[type[BaseModel]]:
    """The model classes an annotation can hold (through Annotated, unions, lists, dicts)."""
    origin = typing.get_origin(annotation)
    if isinstance(annotation, type) and issubclass(annotation, BaseModel):
        return [annotation]
    if origin is Annotated:
        return _models(typing.get_args(annotation)[0])
    if origin in (typing.Union, types.UnionType, list, dict):
        return [m for arg in typing.get_args(annotation) for m in _models(arg)]
    return []


def _inner(model: type[BaseModel], loc: tuple) -> list[type[BaseModel]]:
    """The model classes that can hold the keys below ``loc``."""
    owners = [model]
    for part in loc:
        if not isinstance(part, str):
            continue
        hits = [m for m in owners if part in m.model_fields]
        if hits:
            owners = _models(hits[0].model_fields[part].annotation)
        else:  # a union's tag narrows to its member; a dict key keeps the owners
            tagged = [m for m in owners if m.model_fields.get("kind") and
                      m.model_fields["kind"].default == part]  # fmt: skip
            owners = tagged or owners
    return owners


def _is_array(annotation: Any) -> bool:
    """A list of tables (``[[name]]`` in TOML)."""
    while typing.get_origin(annotation) is Annotated:
        annotation = typing.get_args(annotation)[0]
    return typing.get_origin(annotation) is list and bool(_models(annotation))


def _field(model: type[BaseModel], loc: tuple) -> Any:
    if not loc or not isinstance(loc[-1], str):
        return None
    hits = [m for m in _inner(model, loc[:-1]) if loc[-1] in m.model_fields]
    return hits[0].model_fields[loc[-1]] if hits else None


def key_name(loc: tuple, data: Any, sections: bool = True, arrays: tuple = ()) -> str:
    """``[section.sub].key[n].leaf`` from an error location (tables in brackets)."""
    if not loc:
        return "the file"
    rest = list(loc)
    if not sections:
        return str(rest.pop(0)) + "".join(_part(p) for p in rest)
    head = [rest.pop(0)]
    node = data.get(head[0]) if isinstance(data, dict) else None
    if head[0] in arrays and not rest:
        return f"[[{head[0]}]]"
    if isinstance(node, list) and rest and isinstance(rest[0], int):
        return f"[[{head[0]}]] #{rest.pop(0) + 1}" + "".join(_part(p) for p in rest)
    while len(rest) > 1 and isinstance(node, dict) and isinstance(node.get(rest[0]), dict):
        node = node[rest[0]]
        head.append(rest.pop(0))
    return f"[{'.'.join(map(str, head))}]" + "".join(_part(p) for p in rest)


def _part(p: Any) -> str:
    if isinstance(p, int):
        return f"[{p}]"
    return f".{p!r}" if "." in p else f".{p}"  # a dotted key is one key


def _short(value: Any) -> str:
    text = repr(value)
    return text if len(text) <= 60 else text[:57] + "..."


def _problem(err: dict[str, Any]) -> str:
    kind, ctx, value = err["type"], err.get("ctx", {}), err.get("input")
    if kind == "finite_number":
        return f"= {_short(value)} must be a finite number"
    if kind in _TYPES:
        return f"= {_short(value)} must be {_TYPES[kind]}"
    bounds = {"greater_than": ">", "greater_than_equal": ">=", "less_than": "<",
              "less_than_equal": "<="}  # fmt: skip
    if kind in bounds:
        limit = next(iter(ctx.values()))
        return f"= {_short(value)} must be {bounds[kind]} {limit}"
    if kind == "literal_error":
        return f"= {_short(value)} must be {ctx.get('expected')}"
    if kind == "union_tag_invalid":
        return f"= {_short(ctx.get('tag'))} must be one of {ctx.get('expected_tags')}"
    if kind == "union_tag_not_found":
        return "needs a kind"
    if kind == "too_short" and ctx.get("min_length") == 1:
        return f"= {_short(value)} must not be empty"
    if kind in ("too_short", "too_long"):
        return f"= {_short(value)} must have {_length(ctx)} items"
    if kind == "value_error":
        msg = str(ctx.get("error", err["msg"])).removeprefix("Value error, ")
        return msg if msg.startswith("[") else f"= {_short(value)} {msg}"
    return f"= {_short(value)}: {err['msg'][0].lower()}{err['msg'][1:]}"


def _length(ctx: dict[str, Any]) -> str:
    lo, hi = ctx.get("min_length"), ctx.get("max_length")
    if lo is not None and hi is not None and lo == hi:
        return f"exactly {lo}"
    return f"at least {lo}" if lo is not None else f"at most {hi}"


def check_message(err: dict[str, Any]) -> str:
    """The message a validator raised, without pydantic's "Value error, " before it."""
    return str(err.get("ctx", {}).get("error", err["msg"])).removeprefix("Value error, ")


def validation_error(
    source: Any,
    exc: ValidationError,
    data: Any,
    model: type[BaseModel],
    sections: bool = True,
    labels: Mapping[str, str] | None = None,
) -> ConfigError:
    """The first error of ``exc`` as one line: ``<file>: <key> = <value> <problem>; <fix>``.

    ``sections``: the file's top level holds tables (scenario, sweep) or plain keys (pretrain);
    ``labels`` maps a dotted key to the flag or sweep key that overrode it
    (``<label> = <value> <problem>``).
    """
    err = exc.errors(include_url=False)[0]
    loc = tuple(err["loc"])
    tags = ("synthetic", "sumo")
    if err["type"] == "union_tag_invalid":
        loc = (*loc, "kind")
    kind = err["type"]
    field = _field(model, loc)
    arrays = tuple(k for k, f in model.model_fields.items() if _is_array(f.annotation))
    if kind == "extra_forbidden":
        known = [k for m in _inner(model, loc[:-1]) for k in m.model_fields]
        # pydantic puts a union's tag in the location; the file has no such level
        loc = tuple(
            p for n, p in enumerate(loc) if not (n == 1 and loc[0] == "traffic" and p in tags)
        )
        where = key_name(loc, data, sections, arrays)
        what = "section" if sections and len(loc) == 1 else "key"
        label = _labelled(labels, loc)
        if label:
            known = ", ".join(dict.fromkeys(known))
            return ConfigError(f"{label} is not a known key; use one of: {known}")
        return ConfigError(
            f"{source}: {where} is not a known {what}; use one of: {', '.join(dict.fromkeys(known))}"
        )
    loc = tuple(p for n, p in enumerate(loc) if not (n == 1 and loc[0] == "traffic" and p in tags))
    where = key_name(loc, data, sections, arrays)
    at = _labelled(labels, loc) or f"{source}: {where}"  # the flag or key, else the file's key
    if kind == "missing":
        return ConfigError(f"{at} is missing; add it")
    if kind == "value_error" and not loc:  # a check of the whole file names its keys itself
        return ConfigError(f"{source}: {check_message(err)}")
    problem = _problem(err)
    if problem.startswith("["):  # a check across keys names its keys itself
        return ConfigError(f"{source}: {problem}")
    if kind == "value_error" and "; " in problem:  # the check gave its own fix
        return ConfigError(f"{at} {problem}")
    fix = "fix the value"
    if field is not None and field.default is not None and not isinstance(field.default, BaseModel):
        default = field.default
        if isinstance(default, (bool, int, float, str)) or (
            isinstance(default, list) and 0 < len(repr(default)) < 40 and default
        ):
            fix = f"e.g. {_toml(default)} (the default)"
    if kind in ("dict_type", "model_type", "model_attributes_type"):
        dotted = ".".join(p for p in loc if isinstance(p, str))
        fix = f"write it as a table, [{dotted}] or {{ key = value }}"
    return ConfigError(f"{at} {problem}; {fix}")


def _labelled(labels: Mapping[str, str] | None, loc: tuple) -> str | None:
    """The label of the longest overridden dotted key that ``loc`` lies in, with the rest of
    ``loc`` after it (``--drones``; ``override 'traffic.mfd'.a``); None when the file's."""
    for n in range(len(loc), 0, -1):
        label = (labels or {}).get(".".join(str(p) for p in loc[:n]))
        if label:
            return label + "".join(_part(p) for p in loc[n:])
    return None


def _toml(value: Any) -> str:
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, str):
        return f'"{value}"'
    if isinstance(value, list):
        return "[" + ", ".join(_toml(v) for v in value) + "]"
    return repr(value)


# ------------------------------------------------------------------------------- reading
#: The largest config twin reads (a sweep's or transfer's tables are a few kB).
MAX_CONFIG_BYTES = 16 * 2**20


def read_toml(path: str | Path) -> dict[str, Any]:
    """The tables of the TOML file ``path``; a UTF-8 byte order mark at its start (as editors
    on Windows write it, and TOML does not allow) is skipped."""
    path = Path(path)
    try:
        with open(path, "rb") as fh:
            raw = fh.read(MAX_CONFIG_BYTES + 1)  # /dev/zero, a huge file: never read whole
        if len(raw) > MAX_CONFIG_BYTES:
            raise UserError(
                f"{path}: over {MAX_CONFIG_BYTES // 2**20} MB, larger than any config; give the "
                "scenario's TOML file"
            )
        return tomllib.loads(raw.removeprefix(codecs.BOM_UTF8).decode("utf-8"))
    except FileNotFoundError:
        raise UserError(f"{path}: config file not found; check the path") from None
    except IsADirectoryError:
        raise UserError(f"{path}: is a folder, not a config file") from None
    except PermissionError:
        raise UserError(f"{path}: config file is not readable (permission denied)") from None
    except tomllib.TOMLDecodeError as exc:
        raise UserError(f"{path}: not valid TOML ({exc})") from None
    except RecursionError:  # arrays or tables nested thousands deep: no config's shape
        raise UserError(
            f"{path}: not valid TOML for twin (nested deeper than Python reads); give the "
            "scenario's TOML file"
        ) from None
    except UnicodeDecodeError:
        raise UserError(f"{path}: not a text file; expected a TOML config") from None


def load_config(path: str | Path) -> ScenarioConfig:
    """Read and validate a scenario config."""
    path = Path(path)
    return config_from_data(path, read_toml(path))


def config_from_data(
    path: Path,
    data: dict[str, Any],
    labels: Mapping[str, str] | None = None,
    flags: Mapping[str, str] | None = None,
) -> ScenarioConfig:
    """Validate the tables of a scenario config read from ``path``
    (:meth:`SourcedConfig.from_data`)."""
    return ScenarioConfig.from_data(path, data, labels, flags)


def with_overrides(
    config: C,
    overrides: Mapping[str, Any],
    flags: Mapping[str, str] | None = None,
    labels: Mapping[str, str] | None = None,
) -> C:
    """``config`` with dotted-key ``overrides`` (``{"swarm.n_drones": 2}``) set in its tables
    and validated again by the same models: the one path by which command-line flags, sweep
    keys and a transfer's schedule change a config (a scenario, a pretraining). ``flags``
    names the command-line flag (or the key of another file) that set a key
    (``{"swarm.n_drones": "--drones"}``): a one-line error names it instead of the file, and
    :meth:`SourcedConfig.flag_of` tells it later; ``labels`` names keys that another file set
    (a sweep's ``[parameters]``) in errors and :meth:`SourcedConfig.set_by`, without making them
    flags; other keys are named as overrides. The tables are those the config was validated
    from: change a config by this function, not by ``model_copy``."""
    flags = {**config._flags, **(flags or {})}
    if config._tables is None:  # built in code, not read from a file
        data = config.model_dump(exclude_unset=True)
    else:
        data = copy.deepcopy(config._tables)
    named = set_dotted(data, overrides, {**(labels or {}), **flags}, config.path)
    return type(config).from_data(config.path, data, named, flags)


def read_with_overrides(
    cls: type[C],
    path: str | Path,
    overrides: Mapping[str, Any],
    flags: Mapping[str, str] | None = None,
) -> C:
    """The config of class ``cls`` read from ``path`` with ``overrides`` set in its tables
    before one validation (:func:`with_overrides` validates the file alone first): a value the
    file lacks may come from a flag (``traffic = "tapes"`` in the file, ``--traffic TAPE``)."""
    flags = dict(flags or {})
    data = read_toml(path)
    check_config_kind(path, data, cls.KIND)  # the file's own kind, before flags set keys
    named = set_dotted(data, overrides, flags, Path(path))
    return cls.from_data(path, data, named, flags)


def set_dotted(
    data: dict[str, Any], overrides: Mapping[str, Any], flags: Mapping[str, str], path: Path
) -> dict[str, str]:
    """Set each dotted key of ``overrides`` in the tables ``data`` (in place); returns every
    key's label for errors: its flag, else ``<path>: override '<key>'``."""
    named = dict(flags)
    for key, value in overrides.items():
        label = flags.get(key) or f"{path}: override {key!r}"
        node = data
        *parents, last = key.split(".")
        for part in parents:
            node = node.setdefault(part, {})
            if not isinstance(node, dict):
                raise UserError(f"{label} goes through {part!r}, which is not a table")
        node[last] = value
        named[key] = label
    return named


def validate(config: ScenarioConfig) -> None:
    """The checks that need the grid (synthetic scenarios); the rest is in the models."""
    if config.traffic.kind == "synthetic":
        check_swarm_fits(config, make_grid(config))
        check_disturbances(config)


#: How far (in sigmas) a disturbance's centre may lie off the map: beyond, its kernel is below
#: exp(-12.5) ~ 4e-6 on every cell.
DISTURBANCE_REACH = 5.0
#: The widest disturbance, in map sides: wider, its kernel varies by under 0.5% over the map.
FLAT_SIGMAS = 10.0


def check_disturbances(config: ScenarioConfig) -> None:
    """Each disturbance of a synthetic config reaches the map: one centred more than
    :data:`DISTURBANCE_REACH` sigmas from its nearest cell would add nothing to any cell (a
    centre just off the map, reaching in, is kept: a sweep may shrink the grid)."""
    g = config.grid
    for n, d in enumerate(config.traffic.disturbances):
        if d.sigma > FLAT_SIGMAS * max(g.nx, g.ny):
            raise _fail(
                config.path,
                f"[traffic].disturbances[{n}].sigma",
                f"= {d.sigma:g} cells is more than {FLAT_SIGMAS:g} x the {g.nx} x {g.ny} map's "
                "side: the disturbance is flat over the map (it changes no cell against "
                f"another); give at most {FLAT_SIGMAS * max(g.nx, g.ny):g}",
            )
        gap = math.hypot(d.i - min(max(d.i, 0), g.nx - 1), d.j - min(max(d.j, 0), g.ny - 1))
        if gap > DISTURBANCE_REACH * d.sigma:
            raise _fail(
                config.path,
                f"[traffic].disturbances[{n}]",
                f"is centred at (i, j) = ({d.i:g}, {d.j:g}), {gap:.3g} cells off the "
                f"{g.nx} x {g.ny} map (more than {DISTURBANCE_REACH:g} x sigma = "
                f"{DISTURBANCE_REACH * d.sigma:g}): it reaches no cell; centre it on the map",
            )
    check_faults(config, config.swarm.n_drones, config.traffic.horizon)


# ------------------------------------------------------------------------- grid and swarm
def _cell_list(value: list) -> np.ndarray:
    if len(value) == 0:
        return np.zeros((0, 2), dtype=np.int64)
    return np.asarray(value, dtype=np.int64).reshape(-1, 2)


def make_grid(config: ScenarioConfig) -> Grid:
    """The grid of a config with explicit cells (synthetic scenarios)."""
    from twin.resources import check_grid_size

    path, g = config.path, config.grid
    where = config.flag_of("grid.nx") or config.flag_of("grid.ny") or f"{path}: [grid]"
    check_grid_size(g.nx, g.ny, where, "give fewer cells (nx, ny)")
    obstacles = np.zeros((g.nx, g.ny), dtype=bool)
    cells = _cell_list(g.obstacles)
    if len(cells):
        inside = (cells >= 0).all(axis=1) & (cells < [g.nx, g.ny]).all(axis=1)
        if not inside.all():
            bad = cells[~inside][0].tolist()
            raise _fail(path, "[grid].obstacles", f"has {bad} off the {g.nx} x {g.ny} map")
        obstacles[cells[:, 0], cells[:, 1]] = True
    if obstacles.all():
        raise _fail(path, "[grid].obstacles", "cover every cell; leave at least one free cell")
    return Grid(obstacles)


def check_faults(config: ScenarioConfig, n_drones: int, horizon: int) -> None:
    """The ``[faults]`` table against the swarm and the horizon: drones in range, steps inside
    ``1 .. T - 1``, no two loss windows of one drone overlapping, a live drone at every step."""
    path, f = config.path, config.faults
    for n, loss in enumerate(f.drone_loss):
        key = f"[faults].drone_loss[{n}]"
        if loss.back is not None and loss.back <= loss.step:
            raise _fail(path, f"{key}.back", f"= {loss.back} must come after step = {loss.step}; "
                        "give a later step, or leave back out (lost to the end)")  # fmt: skip
        if loss.drone >= n_drones:
            raise _fail(path, f"{key}.drone", f"= {loss.drone} is not one of the {n_drones} "
                        f"drones; give 0 .. {n_drones - 1}")  # fmt: skip
        for name, value in (("step", loss.step), ("back", loss.back)):
            if value is not None and value >= horizon:
                raise _fail(path, f"{key}.{name}", f"= {value} is outside the horizon "
                            f"T = {horizon}; give 1 .. {horizon - 1}")  # fmt: skip
    for a in range(len(f.drone_loss)):
        for b in range(a + 1, len(f.drone_loss)):
            x, y = f.drone_loss[a], f.drone_loss[b]
            x_end = horizon if x.back is None else x.back
            y_end = horizon if y.back is None else y.back
            if x.drone == y.drone and x.step < y_end and y.step < x_end:
                raise _fail(path, f"[faults].drone_loss[{a}] and [{b}]",
                            f"lose drone {x.drone} in overlapping windows; give one window, "
                            "or separate them")  # fmt: skip
    for start, stop in f.coordinator_down:
        if stop > horizon:
            raise _fail(path, "[faults].coordinator_down", f"has [{start}, {stop}] past the "
                        f"horizon T = {horizon}; end it by {horizon}")  # fmt: skip
    plan = f.plan()
    live = plan.live_steps(horizon, n_drones).any(axis=1)
    if not live.all():
        k = int(np.flatnonzero(~live)[0])
        raise _fail(path, "[faults].drone_loss", f"leaves no drone flying at step {k}; keep "
                    "at least one drone live")  # fmt: skip


def check_swarm_fits(
    config: ScenarioConfig, grid: Grid, fits: tuple[float, int] | tuple[()] | None = None
) -> None:
    """Enough free cells for the drones; explicit starts on distinct free cells of the map.
    The command-line flag that set the number of drones, if one did, is named instead of the
    config file. ``fits``: on a network, the cell size that gives the drones room and its free
    cells (:func:`twin.sumo.scenario.suggest_cell_m`; ``()``: no size does), named as the fix."""
    path, s = config.path, config.swarm
    drones_flag = config.flag_of("swarm.n_drones")
    if s.n_drones > grid.n_free and drones_flag:
        raise ConfigError(
            f"{drones_flag} {s.n_drones} exceeds the {grid.n_free} free cells of the "
            f"{grid.shape[0]} x {grid.shape[1]} grid; give at most {grid.n_free}"
        )
    drones = "drone" if grid.n_free == 1 else "drones"
    fewer = f"at most {grid.n_free} {drones} with --drones {grid.n_free}"
    if fits:
        smaller = f"--cell-m {fits[0]:g} ({fits[1]} free cells), or {fewer}"
    elif fits is not None:
        smaller = f"{fewer} (no cell size down to 25 m gives them room)"
    else:
        smaller = None
    cell_flag = config.flag_of("traffic.cell_m")
    if s.n_drones > grid.n_free and cell_flag:
        raise ConfigError(
            f"{cell_flag} {config.traffic.cell_m:g} leaves {grid.n_free} free cells of the "
            f"{grid.shape[0]} x {grid.shape[1]} grid for the {s.n_drones} drones of {path} "
            f"([swarm].n_drones); give {smaller or 'smaller cells, or fewer drones with --drones'}"
        )
    if s.n_drones > grid.n_free and config.traffic.kind == "sumo":  # a network's cells
        from twin.resources import shipped

        cell = config.traffic.cell_m
        own = not Path(path).resolve().is_relative_to(shipped("configs").resolve())
        source = f"[traffic].cell_m and [swarm].n_drones of {path}" if own else "twin's defaults"
        raise ConfigError(
            f"{grid.n_free} free cells of {cell:g} m for {s.n_drones} drones ({source}); give "
            f"{smaller or f'smaller cells with --cell-m (e.g. {cell / 4:g}), or {fewer}'}"
        )
    if s.n_drones > grid.n_free:
        raise _fail(
            path,
            "[swarm].n_drones",
            f"= {s.n_drones} exceeds the {grid.n_free} free cells; use fewer drones",
        )
    if isinstance(s.starts, str):
        return
    starts = _cell_list(s.starts)
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
    return _cell_list(config.swarm.starts)


# ------------------------------------------------------------------------------- traffic
def synthetic_config(config: ScenarioConfig) -> SyntheticConfig:
    if not isinstance(config.traffic, SyntheticConfig):
        raise _fail(config.path, "[traffic].kind", f"= {config.traffic.kind!r} is not synthetic")
    return config.traffic


#: The least importance a synthetic map's largest z may be given by a ``z_hi`` (Def. 2): a
#: map whose cells all lie below it is a flat one.
MIN_PEAK_IMPORTANCE = 1e-6


def synthetic_source(config: ScenarioConfig, grid: Grid | None = None):
    """The :class:`SyntheticTraffic` a synthetic config describes."""
    from twin.traffic.synthetic import Disturbance, SyntheticTraffic

    t = synthetic_config(config)
    grid = grid or make_grid(config)
    disturbances = [Disturbance(**d.model_dump()) for d in t.disturbances]
    if not disturbances:
        raise _naming_changes(_fail(
            config.path,
            "[traffic].disturbances",
            "is empty: the map has no z^k (Sec. IV) and every importance would be 0; add a "
            '[[traffic.disturbances]] (kind = "big", i, j, amplitude, sigma)',
        ), config._labels)  # fmt: skip
    reach = sum(abs(d.amplitude) for d in disturbances) + abs(t.z_lo) + abs(t.z_hi or 0.0)
    if not math.isfinite(reach):  # |z| <= the sum of amplitudes (Gaussian kernels <= 1): then
        # every z, z - z_lo and z_hi - z_lo of Def. 2 is finite too
        raise _naming_changes(_fail(
            config.path,
            "[traffic].disturbances",
            "have amplitudes that, with z_lo and z_hi, add up past the largest number a map "
            f"can hold ({sys.float_info.max:.3g}); give amplitudes, z_lo and z_hi whose sizes "
            "add up to less",
        ), config._labels)  # fmt: skip
    source = SyntheticTraffic(grid, disturbances, t.horizon, t.beta1, t.beta2, t.z_lo, t.z_hi)
    if source.peak_z() <= t.z_lo:
        raise _naming_changes(_fail(
            config.path,
            "[traffic].z_lo",
            f"= {t.z_lo:g} is not below the largest z of the map over the horizon "
            f"({source.peak_z():.3g}): every importance would be 0; give a z_lo below it",
        ), config._labels)  # fmt: skip
    if t.z_hi is not None:  # Def. 2 divides by z_hi - z_lo
        peak, span = source.peak_z(), t.z_hi - t.z_lo
        why = (
            "so close to z_lo that Def. 2's (z - z_lo) / (z_hi - z_lo) overflows"
            if not math.isfinite(reach / span)
            else f"so far above the map's largest z ({peak:.3g}) that every importance is "
            f"below {MIN_PEAK_IMPORTANCE:g}"
            if (peak - t.z_lo) / span < MIN_PEAK_IMPORTANCE
            else f"at or below every z of the map (the smallest is {source.low_z():.3g}), so "
            "every importance would be 1"
            if t.z_hi <= source.low_z()
            else None
        )
        if why is not None:
            raise _naming_changes(_fail(
                config.path,
                "[traffic].z_hi",
                f"= {t.z_hi:g} lies {why}; give a z_hi near the largest z, or leave it out (the "
                "largest z of the map)",
            ), config._labels)  # fmt: skip
    return source
