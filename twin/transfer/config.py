"""The transfer config (TOML, e.g. ``configs/transfer.toml``) as a pydantic model.

Sections: ``[transfer]`` (name, evaluation seeds, the classical swarms, online learning),
``[schedule]`` (pretraining keys shared by every trained row, ``twin pretrain --help-config``),
``[tapes]`` (the SUMO runs recorded for rows trained on tapes: scenario config, overrides,
seeds), ``[[row]]`` (trained on: name, traffic, init, checkpoint) and ``[[column]]`` (evaluated
on: name, config, overrides, generate). Paths are relative to the config's folder.
"""

from __future__ import annotations

from pathlib import Path
from typing import Annotated, Any, Literal

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
    StrictModel,
    check_config_kind,
    check_name,
    load_config,
    read_toml,
    validation_error,
)
from twin.errors import UserError
from twin.files import not_a_file
from twin.seeds import check_seed_list

#: Seeds that evaluation uses; tapes and validation curves must stay off them.
EVALUATION_SEEDS = range(0, 10)


def _seed_list(seeds: Any, what: str) -> list[int]:
    from twin.sweep.config import MAX_SWEEP_CELLS

    listed = check_seed_list(seeds, what, most=MAX_SWEEP_CELLS)
    if len(listed) > MAX_SWEEP_CELLS:  # before a list of them is made
        raise ValueError(
            f"gives {len(listed):,} seeds, more than the {MAX_SWEEP_CELLS:,} cells the "
            "evaluation sweep holds; give fewer"
        )
    return list(listed)


class TransferSection(StrictModel):
    name: str | None = None  # default: the config file's stem
    seeds: Any = 3  # evaluation seeds per column: a count (0, 1, ...) or a list
    classical: Annotated[list[str], Field(min_length=1)] = Field(
        default_factory=lambda: ["visit-gain", "lookahead", "tours"]
    )
    online: bool = True  # each row also as "rl-online" (learning while patrolling)

    @field_validator("name")
    @classmethod
    def _name(cls, value: str | None) -> str | None:
        return None if value is None else check_name(value)

    @field_validator("seeds", mode="plain")
    @classmethod
    def _seeds(cls, seeds: Any) -> list[int]:
        return _seed_list(seeds, "[0, 1, 2]")

    @field_validator("classical")
    @classmethod
    def _classical(cls, swarms: list[str]) -> list[str]:
        from twin.swarms import available_policies, check_swarm_list, is_learned, needs_history

        check_swarm_list(swarms, lambda: [s for s in available_policies() if not is_learned(s)])
        for swarm in swarms:
            if is_learned(swarm):
                raise ValueError(f"has {swarm!r}, a learned swarm; list classical swarms only")
            if needs_history(swarm):
                raise ValueError(
                    f"has {swarm!r}, which plans on a history of earlier days that a transfer "
                    "does not build for its columns; drop it"
                )
        return swarms


class TapesSection(StrictModel):
    """The earlier days' SUMO runs that rows with ``traffic = "tapes"`` train on."""

    config: ScenarioFile
    overrides: Overrides = Field(default_factory=dict)
    seeds: Any = Field(default_factory=lambda: [100, 101, 102])

    @field_validator("seeds", mode="plain")
    @classmethod
    def _seeds(cls, seeds: Any) -> list[int]:
        seeds = _seed_list(seeds, "[100, 101, 102]")
        used = [s for s in seeds if s in EVALUATION_SEEDS]
        if used:
            raise ValueError(
                f"holds evaluation seed {used[0]}; record tapes from seeds never used for "
                "evaluation, e.g. [100, 101, 102]"
            )
        return seeds


class RowSpec(StrictModel):
    """A row, trained on: a pretraining recipe, or a checkpoint loaded as it is."""

    name: str
    traffic: Literal["paper", "dynamics", "tapes"] = "paper"
    init: str | None = None  # another row's name, or a checkpoint file: fine-tuning
    checkpoint: RelPath | None = None  # load this model instead of training
    schedule: dict[str, Any] = Field(default_factory=dict)  # keys over [schedule] for this row

    @field_validator("name")
    @classmethod
    def _name(cls, value: str) -> str:
        return check_name(value)

    @field_validator("checkpoint")
    @classmethod
    def _checkpoint(cls, path: Path | None) -> Path | None:
        why = None if path is None else not_a_file(path)
        if why is not None:
            raise ValueError(f"names {path}, which {why}; run `twin pretrain` or fix it")
        return path

    @model_validator(mode="after")
    def _loaded_rows_train_nothing(self) -> RowSpec:
        recipe = sorted({"traffic", "init", "schedule"} & self.model_fields_set)
        if self.checkpoint is not None and recipe:
            raise ValueError(
                f"loads its checkpoint as it is, so its {', '.join(recipe)} would train nothing; "
                "drop them, or the checkpoint to train the row"
            )
        return self


class ColumnSpec(StrictModel):
    """A column, evaluated on: a scenario config with overrides; ``generate`` builds a SUMO
    network of another shape (``twin.sumo.network.GENERATED_NETWORKS``) into the cache and
    runs the scenario on it, with demand generated by SUMO's tools."""

    name: str
    config: ScenarioFile
    overrides: Overrides = Field(default_factory=dict)
    generate: str | None = None

    @field_validator("name")
    @classmethod
    def _name(cls, value: str) -> str:
        return check_name(value)

    @field_validator("generate")
    @classmethod
    def _generate(cls, kind: str | None) -> str | None:
        from twin.sumo.network import GENERATED_NETWORKS

        if kind is not None and kind not in GENERATED_NETWORKS:
            raise ValueError(f"is unknown; use one of: {', '.join(GENERATED_NETWORKS)}")
        return kind


#: By what the transfer sets the keys each of its cells (and tapes) set themselves (the
#: sweep's :data:`twin.sweep.config.SET_BY_THE_SWEEP`, whose keys these must be).
TRANSFER_SETS = {
    "traffic.seed": "the traffic of each seed of [transfer].seeds and [tapes].seeds",
    "evaluate.seed": "[transfer].seeds",
    "evaluate.seeds": "[transfer].seeds",
    "evaluate.swarms": "[transfer].classical and the rows' learned swarms",
}


class TransferConfig(StrictModel):
    """A validated transfer config; ``path`` is the file it was read from."""

    transfer: TransferSection = TransferSection()
    schedule: dict[str, Any] = Field(default_factory=dict)
    tapes: TapesSection | None = None
    row: Annotated[list[RowSpec], Field(min_length=1)]
    column: Annotated[list[ColumnSpec], Field(min_length=1)]

    _path: Path = PrivateAttr(default=Path("transfer.toml"))

    @field_validator("schedule")
    @classmethod
    def _schedule(cls, schedule: dict[str, Any]) -> dict[str, Any]:
        return _check_schedule(schedule, "[schedule]")

    @model_validator(mode="after")
    def _across(self, info: ValidationInfo) -> TransferConfig:
        for what, specs in (("row", self.row), ("column", self.column)):
            names = [s.name for s in specs]
            for n, name in enumerate(names):
                if name in names[:n]:
                    raise ValueError(
                        f"[[{what}]] #{n + 1}.name = {name!r} is taken; give distinct names"
                    )
        set_here = [(f"[[column]] {c.name}.overrides", c.overrides) for c in self.column]
        if self.tapes is not None:
            set_here.append(("[tapes].overrides", self.tapes.overrides))
        for where, overrides in set_here:
            for key in overrides:
                if key in TRANSFER_SETS:
                    raise ValueError(
                        f"{where}.{key!r} is set by the transfer itself ({TRANSFER_SETS[key]}); "
                        "drop it"
                    )
        names = [r.name for r in self.row]
        base = Path((info.context or {}).get("path", "transfer.toml")).parent
        for n, row in enumerate(self.row):
            where = f"[[row]] #{n + 1} ({row.name})"
            _check_schedule(row.schedule, f"{where}.schedule")
            if row.traffic == "tapes" and self.tapes is None and row.checkpoint is None:
                raise ValueError(
                    f'{where}.traffic = "tapes" needs a [tapes] section (the SUMO runs to record)'
                )
            if row.init is not None and row.init not in names:
                path = Path(row.init)
                row.init = str(path if path.is_absolute() else (base / path).resolve())
                if not Path(row.init).is_file():
                    raise ValueError(
                        f"{where}.init = {row.init!r} is neither a row nor a checkpoint file; "
                        f"give one of {names} or a qnet.pt"
                    )
            elif row.init is not None and names.index(row.init) >= n:
                raise ValueError(f"{where}.init = {row.init!r} must name a row listed before it")
        return self

    @property
    def path(self) -> Path:
        return self._path

    @property
    def name(self) -> str:
        return self.transfer.name or self.path.stem

    @property
    def seeds(self) -> list[int]:
        return self.transfer.seeds

    def learned_swarms(self) -> list[tuple[str, str, str]]:
        """``(swarm, row, kind)`` of every row's learned swarms: ``rl@<row>`` and, with
        ``online``, ``rl-online@<row>``."""
        kinds = ["rl", "rl-online"] if self.transfer.online else ["rl"]
        return [(f"{kind}@{row.name}", row.name, kind) for row in self.row for kind in kinds]


#: Pretraining keys that the transfer command sets itself, per row.
ROW_KEYS = ("out", "traffic", "tapes", "init")


def _check_schedule(schedule: dict[str, Any], where: str) -> dict[str, Any]:
    from twin.training.pretrain import SCENARIO_KEYS, PretrainConfig

    for key in schedule:
        if key in ROW_KEYS:
            raise ValueError(f"{where}.{key}: set per row ([[row]] traffic, init), not here")
        if key in SCENARIO_KEYS:
            raise ValueError(
                f"{where}.{key} is the scenario's {SCENARIO_KEYS[key]} now; set it as "
                f'scenario_overrides = {{ "{SCENARIO_KEYS[key]}" = ... }}'
            )
        if key not in PretrainConfig.model_fields:
            raise ValueError(
                f"{where}.{key} is not a pretraining key; see `twin pretrain --help-config`"
            )
    return schedule


def row_schedule(config: TransferConfig, row: RowSpec) -> tuple[dict[str, Any], dict[str, str]]:
    """A trained row's pretraining keys, ``[schedule]`` with the row's own ``schedule`` over
    it, and each key's label for errors (``<config>: [schedule].lr``)."""
    overrides = {**config.schedule, **row.schedule}
    labels = {k: f"{config.path}: [schedule].{k}" for k in config.schedule}
    labels |= {k: f"{config.path}: [[row]] {row.name}.schedule.{k}" for k in row.schedule}
    return overrides, labels


def load_transfer_config(path: str | Path) -> TransferConfig:
    """Read and validate a transfer config; every problem is one line naming the key. Each
    trained row's schedule is validated here as pretraining keys (before any tape is
    recorded); its traffic, tapes and init join it when the row trains
    (:func:`twin.transfer.runner.row_pretrain_config`)."""
    from twin.config import with_overrides
    from twin.training.pretrain import PretrainConfig

    path = Path(path)
    data = read_toml(path)
    check_config_kind(path, data, "transfer")
    try:
        config = TransferConfig.model_validate(data, context={"path": path})
    except ValidationError as exc:
        raise validation_error(path, exc, data, TransferConfig) from None
    config._path = path
    defaults = PretrainConfig.from_data(path, {})
    for row in config.row:
        if row.checkpoint is None:
            with_overrides(defaults, *row_schedule(config, row))
    for n, column in enumerate(config.column):
        if column.generate is not None and load_config(column.config).traffic.kind != "sumo":
            raise UserError(
                f"{path}: [[column]] #{n + 1} ({column.name}).generate = {column.generate!r} "
                f"builds a SUMO network, but its config {column.config} has synthetic traffic; "
                "give a SUMO scenario config, or leave generate out"
            )
    return config
