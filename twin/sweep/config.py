"""The sweep config (TOML, e.g. ``configs/sweep-demo.toml``) as a pydantic model.

Sections: ``[sweep]`` (name, swarms, seeds, seed), ``[[scenario]]`` (name, config, overrides,
tape; paths relative to the sweep config), ``[parameters]`` (dotted keys into a scenario config
to non-empty lists of values) and ``[swarm_options.<swarm>]``. Names become file names in the
sweep folder, so they are plain (no ``/``, no ``..``).
"""

from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Annotated, Any

from pydantic import (
    Field,
    PrivateAttr,
    ValidationError,
    ValidationInfo,
    field_validator,
    model_validator,
)

from twin.config import (
    Overrides,
    RelPath,
    ScenarioFile,
    Seed,
    StrictModel,
    check_config_kind,
    check_dotted,
    check_name,
    read_toml,
    validation_error,
)
from twin.files import not_a_file
from twin.seeds import check_seed_list

#: Swarm options that name a file, and how such a file is made: a sweep resolves them against
#: its own folder, and each cell's id hashes their content (:func:`twin.sweep.cells.cell_id`).
OPTION_FILES = {"checkpoint": "run `twin pretrain`", "history": "run `twin history`"}


class SweepSection(StrictModel):
    name: str | None = None  # default: the config file's stem
    swarms: Annotated[list[str], Field(min_length=1)]
    seed: Seed = 0  # the first seed of a count (before seeds: its check reads it)
    seeds: Any = 1  # a count (seeds seed, seed + 1, ...) or a list of seeds
    #: each cell also runs the ceilings (oracle, bound) on its true maps: rows with role ceiling
    ceilings: bool = False

    @field_validator("name")
    @classmethod
    def _name(cls, value: str | None) -> str | None:
        return None if value is None else check_name(value)

    @field_validator("swarms")
    @classmethod
    def _swarms(cls, swarms: list[str]) -> list[str]:
        from twin.swarms import check_swarm_list

        check_swarm_list(swarms)
        return swarms

    @field_validator("seeds", mode="plain")
    @classmethod
    def _seeds(cls, seeds: Any, info: ValidationInfo) -> Any:
        first = info.data.get("seed", 0)
        listed = check_seed_list(seeds, "3", first=first, most=MAX_SWEEP_CELLS)
        return seeds if isinstance(seeds, int) else listed


#: The most cells one sweep may expand to (each is a file in its folder and a run).
MAX_SWEEP_CELLS = 100_000


#: The traffic keys a tape's replay reads from its scenario config
#: (:meth:`twin.traffic.tape.TapeTraffic.from_file`); it keeps its own for the others.
TAPE_TRAFFIC_KEYS = ("traffic.mfd.detection_p",)


class ScenarioSpec(StrictModel):
    """One scenario of a sweep: a scenario config file and overrides of its keys."""

    name: str
    config: ScenarioFile
    overrides: Overrides = Field(default_factory=dict)
    tape: RelPath | None = None  # replay a recorded traffic tape instead of the config's traffic

    @field_validator("name")
    @classmethod
    def _name(cls, value: str) -> str:
        return check_name(value)


def _same_value(value: Any) -> Any:
    """What makes two swept values the same cell: equal numbers (2 and 2.0), equal text,
    equal lists or tables."""
    if isinstance(value, (list, dict)):
        return ("json", json.dumps(value, sort_keys=True))
    return value


#: Scenario keys each cell sets itself (a value swept or overridden there would change
#: nothing), and by what.
SET_BY_THE_SWEEP = {
    "traffic.seed": "the seed of each cell's traffic being its seed ([sweep].seeds)",
    "evaluate.seed": "each cell running one of [sweep].seeds",
    "evaluate.seeds": "each cell running one of [sweep].seeds",
    "evaluate.swarms": "each cell running [sweep].swarms",
}


class SweepConfig(StrictModel):
    """A validated sweep config; ``path`` is the file it was read from."""

    sweep: SweepSection
    scenario: Annotated[list[ScenarioSpec], Field(min_length=1)]
    parameters: dict[str, Annotated[list[Any], Field(min_length=1)]] = Field(default_factory=dict)
    swarm_options: dict[str, dict[str, Any]] = Field(default_factory=dict)

    _path: Path = PrivateAttr(default=Path("sweep.toml"))
    #: how the file that holds the scenarios names one (a transfer's are its ``[[column]]``)
    _scenario_table: str = PrivateAttr(default="[[scenario]]")
    #: a folder whose files the cells name relative to it in their ids (a transfer's: its rows'
    #: checkpoints), so that the folder moved keeps its cells; None: paths as given
    _home: Path | None = PrivateAttr(default=None)

    @field_validator("parameters")
    @classmethod
    def _parameters(cls, parameters: dict[str, list[Any]]) -> dict[str, list[Any]]:
        for key in parameters:
            try:
                check_dotted(key)
            except ValueError as exc:
                raise ValueError(
                    f"[parameters].{key!r} {exc}".replace(f" key {key!r}:", ":")
                ) from None
            seen: list[Any] = []
            for value in parameters[key]:
                same = _same_value(value)
                if same in seen:
                    shown = json.dumps(value) if not isinstance(value, str) else repr(value)
                    raise ValueError(
                        f"[parameters].{key!r} lists {shown} twice; list each value once "
                        "(every value is a cell for every seed)"
                    )
                seen.append(same)
        return parameters

    @model_validator(mode="after")
    def _across(self, info: ValidationInfo) -> SweepConfig:
        names = [s.name for s in self.scenario]
        for n, name in enumerate(names):
            if name in names[:n]:
                raise ValueError(
                    f"[[scenario]] #{n + 1}.name = {name!r} is taken; give distinct names"
                )
        seeds = self.sweep.seeds if isinstance(self.sweep.seeds, int) else len(self.sweep.seeds)
        combinations = math.prod(len(v) for v in self.parameters.values())
        cells = len(self.scenario) * combinations * seeds
        if cells > MAX_SWEEP_CELLS:
            raise ValueError(
                f"the sweep expands to {cells:,} cells ({len(self.scenario)} scenarios x "
                f"{combinations:,} parameter combinations x {seeds:,} seeds), over the "
                f"{MAX_SWEEP_CELLS:,} one sweep folder holds; sweep fewer seeds or values"
            )
        for where, key in [(f"[parameters].{k!r}", k) for k in self.parameters] + [
            (f"[[scenario]] {spec.name}.overrides.{k!r}", k)
            for spec in self.scenario
            for k in spec.overrides
        ]:
            if key in SET_BY_THE_SWEEP:
                raise ValueError(
                    f"{where} is set by the sweep itself, {SET_BY_THE_SWEEP[key]}; drop it"
                )
        for spec in self.scenario:
            if spec.tape is None:
                continue
            swept = [(f"[parameters].{k!r}", k) for k in self.parameters]
            set_here = [(f"[[scenario]] {spec.name}.overrides.{k!r}", k) for k in spec.overrides]
            for where, key in swept + set_here:
                if (key.startswith("traffic.") and key not in TAPE_TRAFFIC_KEYS) or (
                    key == "grid.obstacles"
                ):
                    raise ValueError(
                        f"{where} sets the traffic of [[scenario]] {spec.name!r}, which replays "
                        f"the tape {spec.tape}: a tape keeps its own traffic (cells and their "
                        "obstacles, window, demand), so it would change nothing; sweep it over "
                        "a live scenario (no tape), or drop it"
                    )
        base = Path((info.context or {}).get("path", "sweep.toml")).parent
        for swarm, table in self.swarm_options.items():
            if swarm not in self.sweep.swarms:
                raise ValueError(
                    f"[swarm_options.{swarm}] names a swarm not in [sweep].swarms "
                    f"{self.sweep.swarms}; add it there or drop the table"
                )
            for key, make in OPTION_FILES.items():  # relative to the sweep config
                if key not in table:
                    continue
                where = f"[swarm_options.{swarm}].{key}"
                if not isinstance(table[key], str):
                    raise ValueError(f"{where} = {table[key]!r} must be a file name")
                path = Path(table[key])
                table[key] = str(path if path.is_absolute() else (base / path).resolve())
                why = not_a_file(table[key])
                if why is not None:
                    raise ValueError(f"{where} = {table[key]} {why}; {make} or fix the path")
        return self

    @property
    def path(self) -> Path:
        return self._path

    @property
    def name(self) -> str:
        return self.sweep.name or self.path.stem

    @property
    def swarms(self) -> list[str]:
        return self.sweep.swarms

    @property
    def seeds(self) -> list[int]:
        s = self.sweep
        return list(range(s.seed, s.seed + s.seeds)) if isinstance(s.seeds, int) else s.seeds

    @property
    def scenarios(self) -> list[ScenarioSpec]:
        return self.scenario


def load_sweep_config(path: str | Path) -> SweepConfig:
    """Read and validate a sweep config; every problem is one line naming the key."""
    path = Path(path)
    data = read_toml(path)
    check_config_kind(path, data, "sweep")
    try:
        config = SweepConfig.model_validate(data, context={"path": path})
    except ValidationError as exc:
        raise validation_error(path, exc, data, SweepConfig) from None
    config._path = path
    return config
