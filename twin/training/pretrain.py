"""Pretraining of the universal Q-function (Sec. III-A), one file read top to bottom.

1. hyper-parameters: :class:`PretrainConfig`, every one named once with its default and help;
   the training map, the swarm and the reward's weights are a scenario config's
   (``configs/training-map.toml`` by default);
2. data: episodes of a randomly moving swarm on the training map (:mod:`twin.learning.data`),
   pooled into one replay buffer; or (``collector = "coordinated"``) episodes of the swarm
   being learned, epsilon-greedy, collected every ``collect_every`` epochs into a buffer of
   the last ``episodes``; 1-step transitions, or ``n_step`` returns of each drone's rewards;
3. network: the Table 1 MLP and its target copy, its first layer sized to the state variant
   ``state`` (:mod:`twin.states`: the paper's 13 values by default);
4. the loop (the update itself: :mod:`twin.learning.dqn`): epoch ``m`` samples one batch from the pooled buffers and takes ``N_iter``
   gradient steps on it towards the Double DQN target
   ``Y = r + gamma Q(s', argmax_{u' feasible} Q(s', u'; theta^m); theta^m_-)`` (n-step:
   ``r`` the n-step return, ``gamma^n`` and the state n steps later);
   the target copy is hard-updated every ``target_update_epochs`` epochs;
5. logging (CSV: loss and mean Q), atomic checkpoints every ``checkpoint_every`` epochs, and
   resumption from the last one when the same command is run again.
"""

from __future__ import annotations

import csv
import hashlib
import itertools
import json
import os
import time
from pathlib import Path
from typing import Annotated, Any, ClassVar, Literal

import numpy as np
import torch
from pydantic import (
    BeforeValidator,
    Field,
    PrivateAttr,
    ValidationInfo,
    field_validator,
    model_validator,
)

from twin.belief import DAY_BYTES, History, days_history
from twin.config import (
    ConfigError,
    Overrides,
    ScenarioConfig,
    SourcedConfig,
    make_grid,
    read_with_overrides,
    shipped_config,
    synthetic_config,
    synthetic_source,
    with_overrides,
)
from twin.config import load_config as load_scenario
from twin.errors import UserError
from twin.files import file_sha256, not_a_file
from twin.learning.checkpoint import (
    atomic_save,
    checkpoint_state,
    load_qnet,
    model_metadata,
    read_checkpoint,
    save_model,
)
from twin.learning.data import coordinated_swarm_episode, random_swarm_episode
from twin.learning.dqn import (  # noqa: F401  (double_dqn_target re-exported for tests)
    double_dqn_target,
    flush_subnormals,
    make_optimizer,
    sync_target,
    train_epoch,
)
from twin.learning.qnet import TABLE1_LAYERS, QNetwork
from twin.learning.replay import ReplayBuffer, n_step_transitions
from twin.seeds import MAX_SEED
from twin.states import DEFAULT_STATE, STATE_NAMES, STATE_VARIANTS, UNAVAILABLE, StateVariant
from twin.traffic.dynamic import MAX_DISTURBANCES, dynamics_history
from twin.traffic.synthetic import SyntheticTraffic

PositiveInt = Annotated[int, Field(ge=1)]
PositiveFloat = Annotated[float, Field(gt=0)]

#: The scenario pretraining collects on by default: the paper's training map (Sec. III-A),
#: ``configs/training-map.toml`` (20 x 30, 4 drones, T = 2000, 4 big and 3 small disturbances
#: placed away from the evaluation map's).
TRAINING_MAP = "training-map"

#: Keys that pretraining configs once had and that the scenario declares now: old -> new.
SCENARIO_KEYS = {
    "nx": "grid.nx", "ny": "grid.ny", "n_drones": "swarm.n_drones", "eta": "swarm.eta",
    "delta": "swarm.delta", "alpha_T": "swarm.alpha_T", "alpha_I": "swarm.alpha_I",
    "horizon": "traffic.horizon", "beta1": "traffic.beta1", "beta2": "traffic.beta2",
    "disturbances": "traffic.disturbances",
}  # fmt: skip


def _help(text: str, **bounds: Any) -> Any:
    return Field(description=text, **bounds)


def _scenario_file(value: Any, info: ValidationInfo, default: str = "training-map") -> Path:
    """A scenario config relative to the pretraining config's folder, else a shipped one (the
    field's ``default`` is named in the refusal)."""
    from twin.resources import shipped_config_named

    if not isinstance(value, (str, Path)) or not str(value):
        raise ValueError('must be a scenario config file; e.g. "training-map.toml"')
    base = Path((info.context or {}).get("path", "pretrain.toml")).parent
    path = Path(value) if Path(value).is_absolute() else (base / value).resolve()
    if path.is_file():
        return path
    shipped = shipped_config_named(value)
    if shipped is not None:
        return shipped
    raise ValueError(
        f"names {path}, which does not exist; give a scenario config (relative to this file) "
        f'or a shipped one, e.g. "{default}" (the default)'
    )


def _curve_config_file(value: Any, info: ValidationInfo) -> str:
    """``curve_config``: found as ``scenario`` is (:func:`_scenario_file`)."""
    return str(_scenario_file(value, info, default="synthetic"))


# ----------------------------------------------------------------------------- 1. parameters
class PretrainConfig(SourcedConfig):
    """Every knob of pretraining; a TOML file sets any subset of them (same names). The
    training map, the swarm and the reward's weights are a scenario's (``scenario``, its
    ``[grid]``, ``[swarm]`` and synthetic ``[traffic]``), with ``scenario_overrides`` on top."""

    FILE_TABLES: ClassVar[bool] = False
    KIND: ClassVar[str] = "pretraining"

    seed: int = _help(
        "seed of the data, the network initialisation and the batches",
        default=0,
        ge=0,
        le=MAX_SEED,
    )
    out: str = _help(
        "folder for state.pt, qnet.pt, train_log.csv, snapshots/; relative to the folder twin "
        "runs in (as --out), not to this file",
        default="runs/pretrain",
        min_length=1,
    )
    # data: the training map and the random swarm
    scenario: Annotated[Path, BeforeValidator(_scenario_file)] = _help(
        "scenario config of the training map: its grid, drones (n_drones), idleness and reward "
        "weights (eta, delta, alpha_T, alpha_I) and synthetic traffic (horizon = steps per "
        "episode, disturbances); relative to this file, or a shipped name",
        default=Path(TRAINING_MAP),
        validate_default=True,
    )
    scenario_overrides: Overrides = _help(
        'dotted keys set in the scenario, e.g. { "grid.nx" = 10, "traffic.horizon" = 500 }',
        default_factory=dict,
    )
    # the learning recipe: which traffic the random swarm collects on, where training starts
    traffic: Literal["paper", "dynamics", "tapes"] = _help(
        'training traffic: "paper" (the scenario\'s fixed map, Sec. III-A), "dynamics" '
        "(a fresh map per episode: disturbances that move, grow and fade under a rush-hour "
        'wave, twin/traffic/dynamic.py), "tapes" (recorded SUMO runs, `tapes`; also --traffic)',
        default="paper",
    )
    tapes: list[str] = _help(
        'tape.parquet files of SUMO runs for traffic = "tapes", one per episode in turn',
        default_factory=list,
    )
    dynamics_disturbances: int = _help(
        'disturbances per map for traffic = "dynamics"', default=8, ge=1, le=MAX_DISTURBANCES
    )
    init: str | None = _help(
        "a model checkpoint (qnet.pt) to start from: fine-tuning (default: a fresh network)",
        default=None,
    )
    episodes: PositiveInt = _help(
        'episodes in the replay buffer: collected before training (collector = "random"), '
        'or the last ones kept of those collected while training (collector = "coordinated")',
        default=10,
    )
    collector: Literal["random", "coordinated"] = _help(
        'who collects the data: "random" (the paper: a randomly moving swarm, every episode '
        'before training), "coordinated" (the swarm being learned, rl: the coordinator on the '
        "network's Q values, epsilon-greedy; an episode every `collect_every` epochs)",
        default="random",
    )
    collect_every: PositiveInt = _help(
        'collector = "coordinated": epochs between collected episodes (the first at epoch 0)',
        default=400,
    )
    epsilon_start: float = _help(
        'collector = "coordinated": exploration at epoch 0 (a drone\'s chance to ask for a '
        "uniform feasible action)",
        default=1.0,
        ge=0,
        le=1,
    )
    epsilon_end: float = _help(
        'collector = "coordinated": exploration after `epsilon_decay_epochs`', default=0.05,
        ge=0, le=1,
    )  # fmt: skip
    epsilon_decay_epochs: PositiveInt = _help(
        'collector = "coordinated": epochs over which exploration falls linearly from '
        "epsilon_start to epsilon_end",
        default=10000,
    )
    # network
    state: str = _help(
        "state variant the network reads (twin/states.py): "
        + ", ".join(f'"{n}"' for n in STATE_NAMES)
        + ' ("paper": the 13 values of eq. s; "window": I*T over the 5 x 5 cells around the '
        'drone, 33 values; "nowcast": eq. s plus the nowcast\'s mean and 2 std on the 5 view '
        "cells, 23 values, its history the training map's generator on `history_days` other "
        "days)",
        default=DEFAULT_STATE,
    )
    history_days: int = _help(
        'state = "nowcast": days in the nowcast\'s history (built once per run from the '
        'training traffic\'s generator: for traffic = "dynamics", seeds history_seed, '
        'history_seed + 1, ...; for traffic = "paper", the fixed map, the same every day)',
        default=8,
        ge=2,
    )
    history_seed: int = _help(
        'state = "nowcast", traffic = "dynamics": seed of the history\'s first day (its seeds '
        "must differ from the training episodes')",
        default=1_000_000,
        ge=0,
        le=MAX_SEED,
    )
    layers: list[PositiveInt] = _help(
        "layer sizes, the state's size in and 5 out (Table 1: 13 -> 2048 -> 1024 -> 256 -> 64 "
        "-> 5); unset, Table 1's with the first layer sized to `state`",
        default_factory=lambda: list(TABLE1_LAYERS),
    )
    # learning
    epochs: PositiveInt = _help("N_ep: epochs, each one sampled batch", default=30000)
    iters_per_epoch: PositiveInt = _help(
        "N_iter: gradient steps per epoch on its batch", default=30
    )
    batch_size: PositiveInt = _help("transitions per batch", default=32)
    gamma: float = _help("discount factor", default=0.9, ge=0, lt=1)
    n_step: PositiveInt = _help(
        "n of the n-step returns: each drone's own rewards over n steps (truncated at the "
        "episode's end), bootstrapped with gamma^n (1: the paper's 1-step target)",
        default=1,
        le=100,
    )
    lr: float = _help("Adam learning rate", default=1e-4, gt=0, le=1)
    target_update_epochs: PositiveInt = _help(
        "epochs between hard updates of the target network", default=100
    )
    adam_fused: bool = _help("fused Adam step (one kernel for all parameters)", default=True)
    threads: PositiveInt = _help("torch threads", default=1)
    # output
    log_every: PositiveInt = _help("epochs per CSV log row", default=100)
    checkpoint_every: PositiveInt = _help(
        "epochs between checkpoints (what a kill can lose)", default=1000
    )
    snapshot_every: int = _help("epochs between kept weight snapshots (0: none)", default=0, ge=0)
    # the learning curve: R_hat_T of the "rl" swarm on validation seeds against updates
    curve_every: int = _help(
        "epochs between points of the learning curve, curve.csv (0: no curve)", default=0, ge=0
    )
    curve_seeds: list[Annotated[int, Field(ge=0, le=MAX_SEED)]] = _help(
        "validation seeds of the curve (never the evaluation seeds 0-9)",
        default_factory=lambda: [100, 101],
    )
    curve_config: Annotated[str, BeforeValidator(_curve_config_file)] = _help(
        "scenario config the curve is measured on (a synthetic or a SUMO tape's; relative to "
        "this file, else a shipped one)",
        default="synthetic",
    )
    curve_horizon: PositiveInt = _help("steps of each curve evaluation", default=200)

    _scenario: ScenarioConfig | None = PrivateAttr(default=None)

    # Fields that may change between a run and its resumption without invalidating it.
    RESUMABLE_CHANGES: ClassVar[tuple[str, ...]] = (
        "epochs", "out", "log_every", "checkpoint_every", "snapshot_every",
        "curve_every", "curve_seeds", "curve_config", "curve_horizon",
    )  # fmt: skip

    @classmethod
    def check_data(cls, path: str | Path, data: dict[str, Any]) -> None:
        for old, new in SCENARIO_KEYS.items():
            if old in data:
                value = data[old]
                shown = json.dumps(value) if len(json.dumps(value, default=str)) < 20 else "..."
                raise ConfigError(
                    f"{path}: {old} is the scenario's {new} now; set it in the scenario config "
                    f'(key `scenario`) or as scenario_overrides = {{ "{new}" = {shown} }}'
                )

    @field_validator("state")
    @classmethod
    def _state(cls, state: str) -> str:
        if state in UNAVAILABLE:
            buildable = ", ".join(f'"{n}"' for n in STATE_VARIANTS)
            raise ValueError(f"{UNAVAILABLE[state]}; use one of {buildable}")
        if state not in STATE_VARIANTS:
            raise ValueError(
                "is not a state variant; use one of " + ", ".join(f'"{n}"' for n in STATE_VARIANTS)
            )
        return state

    @field_validator("layers")
    @classmethod
    def _layers(cls, layers: list[int], info: ValidationInfo) -> list[int]:
        if len(layers) < 2 or layers[-1] != TABLE1_LAYERS[-1]:
            raise ValueError(f"must run from the state's size to {TABLE1_LAYERS[-1]} (actions)")
        state = info.data.get("state")
        if state in STATE_VARIANTS and layers[0] != STATE_VARIANTS[state].size:
            size = STATE_VARIANTS[state].size
            raise ValueError(
                f"starts with {layers[0]} but state = {state!r} has {size} values; start "
                f"layers with {size} (or leave layers unset)"
            )
        return layers

    @model_validator(mode="after")
    def _layers_fit_state(self) -> PretrainConfig:
        """Unset ``layers``: Table 1's, the first sized to the state."""
        if "layers" not in self.model_fields_set:
            self.layers = [STATE_VARIANTS[self.state].size, *TABLE1_LAYERS[1:]]
        return self

    @property
    def variant(self) -> StateVariant:
        """The state variant the network reads (:mod:`twin.states`)."""
        return STATE_VARIANTS[self.state]

    @model_validator(mode="after")
    def _history_can_be_built(self) -> PretrainConfig:
        """``state = "nowcast"``: its history needs a generator of days (refused on tapes), of
        seeds that no training episode uses."""
        if not self.variant.needs_belief:
            return self
        if self.traffic == "tapes":
            raise ValueError(
                'state = "nowcast" with traffic = "tapes" needs a history of other SUMO days, '
                'which pretraining does not build; use traffic = "dynamics" or "paper"'
            )
        used = set(history_seeds(self)) & set(training_seeds(self))
        if used:
            raise ValueError(
                f"history_seed = {self.history_seed}: the history's day {min(used)} is also a "
                "training episode's seed; give a history_seed outside the training seeds "
                f"(seed * 100003 + episode), e.g. {self.history_seed + 10**7}"
            )
        return self

    def history_record(self) -> dict[str, Any] | None:
        """What a checkpoint records of the nowcast's history (None: the state reads none)."""
        if not self.variant.needs_belief:
            return None
        generator = "dynamics" if self.traffic == "dynamics" else "the training map (fixed)"
        return {"generator": generator, "days": self.history_days,
                "seeds": history_seeds(self)}  # fmt: skip

    @field_validator("curve_seeds")
    @classmethod
    def _validation_seeds(cls, seeds: list[int]) -> list[int]:
        if any(s < 10 for s in seeds):
            raise ValueError(
                "holds an evaluation seed (0-9); measure the curve on validation seeds, "
                "e.g. [100, 101]"
            )
        return seeds

    @field_validator("init", mode="before")
    @classmethod
    def _init_relative(cls, value: Any, info: ValidationInfo) -> Any:
        return _relative_file(value, info)

    @field_validator("tapes", mode="before")
    @classmethod
    def _tapes_relative(cls, value: Any, info: ValidationInfo) -> Any:
        if isinstance(value, list):
            return [_relative_file(t, info) for t in value]
        return value

    @model_validator(mode="after")
    def _curve_can_be_measured(self) -> PretrainConfig:
        """The curve's scenario is read before training, not after it: a SUMO scenario's
        files, window, grid and incidents as a run checks them before SUMO starts."""
        if self.curve_every and not self.curve_seeds:
            raise ValueError(
                f"curve_every = {self.curve_every} asks for a learning curve, but curve_seeds "
                "= [] gives it no seed; give validation seeds (e.g. curve_seeds = [100, 101]), "
                "or curve_every = 0 for no curve"
            )
        if self.curve_every:
            try:
                _check_curve_scenario(curve_scenario(self))
            except UserError as exc:
                raise ValueError(self._curve_refusal(exc)) from None
        return self

    def _curve_refusal(self, exc: UserError) -> str:
        """Why the curve cannot be measured: the scenario itself, or only its window cut to
        ``curve_horizon`` steps (then the fix is the horizon, not the file)."""
        name = f"curve_config = {self.curve_config!r}"
        try:
            own = load_scenario(shipped_config(self.curve_config))
            _check_curve_scenario(own)
        except UserError:
            return f'{name} cannot measure the curve: {exc} (or give another, e.g. "synthetic")'
        return (
            f"{name} cannot measure the curve over curve_horizon = {self.curve_horizon} "
            f"steps: {exc} (or set curve_horizon = {own.traffic.horizon}, which fits it)"
        )

    @model_validator(mode="after")
    def _exploration_falls(self) -> PretrainConfig:
        if self.epsilon_end > self.epsilon_start:
            raise ValueError(
                f"epsilon_end = {self.epsilon_end:g} is above epsilon_start = "
                f"{self.epsilon_start:g}; exploration falls during training, give "
                "epsilon_end <= epsilon_start"
            )
        return self

    @field_validator("tapes")
    @classmethod
    def _tapes(cls, tapes: list[str], info: ValidationInfo) -> list[str]:
        traffic = info.data.get("traffic")
        if tapes and traffic is not None and traffic != "tapes":
            raise ValueError(
                f'are given, but traffic = "{traffic}" trains on no tape; set traffic = "tapes" '
                "(or drop tapes)"
            )
        for n, tape in enumerate(tapes):
            if not tape.strip():
                raise ValueError(f"has an empty name (entry {n + 1}); remove it")
            if Path(tape).is_dir():
                inside = Path(tape) / "tape.parquet"
                hint = f" ({inside})" if inside.is_file() else ""
                raise ValueError(f"names {tape}, a folder; give its tape.parquet files{hint}")
            if not Path(tape).is_file():
                raise ValueError(f"names {tape}, which does not exist; give tape.parquet files")
        return tapes

    @model_validator(mode="after")
    def _tapes_given(self, info: ValidationInfo) -> PretrainConfig:
        if self.traffic == "tapes" and not self.tapes:
            raise ValueError(
                '[tapes] is empty; traffic = "tapes" needs tape files (or --traffic TAPE)'
            )
        self._scenario = training_scenario(
            self.scenario,
            self.scenario_overrides,
            Path((info.context or {}).get("path", "pretrain.toml")),
        )
        return self

    @property
    def training_map(self) -> ScenarioConfig:
        """The scenario of the training map, its overrides applied (validated on load)."""
        if self._scenario is None:  # built by model_copy: the scenario is the same
            self._scenario = training_scenario(self.scenario, self.scenario_overrides)
        return self._scenario

    @property
    def nx(self) -> int:
        return self.training_map.grid.nx

    @property
    def ny(self) -> int:
        return self.training_map.grid.ny

    @property
    def n_drones(self) -> int:
        return self.training_map.swarm.n_drones

    @property
    def horizon(self) -> int:
        """Steps per random-swarm episode on a synthetic map (tapes: their own)."""
        return self.training_map.traffic.horizon

    def training_dict(self) -> dict[str, Any]:
        """The config as plain python types (stored in every checkpoint): the settings that
        shape training, the scenario's among them by their old flat names (nx, ny, horizon,
        ..., eta ...) in their old order, so that checkpoints of the same settings compare
        equal whichever file declared them. The scenario's keys that older pretraining could
        not set (obstacles, z_lo, z_hi) and the state variant follow when they are not their
        defaults."""
        own = self.model_dump(exclude={"scenario", "scenario_overrides", "state"})
        s = self.training_map
        t = synthetic_config(s)
        values = {
            **own,
            "nx": s.grid.nx, "ny": s.grid.ny, "horizon": t.horizon, "beta1": t.beta1,
            "beta2": t.beta2, "disturbances": [d.model_dump() for d in t.disturbances],
            "n_drones": s.swarm.n_drones, "eta": s.swarm.eta, "delta": s.swarm.delta,
            "alpha_T": s.swarm.alpha_T, "alpha_I": s.swarm.alpha_I,
        }  # fmt: skip
        record = {k: values.pop(k) for k in TRAINING_KEYS}
        record.update(values)  # none today: a new key of the config's own
        if s.grid.obstacles:
            record["obstacles"] = s.grid.obstacles
        if t.z_lo != 0.0:
            record["z_lo"] = t.z_lo
        if t.z_hi is not None:
            record["z_hi"] = t.z_hi
        if self.state != DEFAULT_STATE:
            record["state"] = self.state
        if self.variant.needs_belief:
            record["history_days"] = self.history_days
            record["history_seed"] = self.history_seed
        return record


#: The keys of :meth:`PretrainConfig.training_dict`, in the order checkpoints store them.
TRAINING_KEYS = (
    "seed", "out", "nx", "ny", "horizon", "beta1", "beta2", "disturbances", "n_drones",
    "traffic", "tapes", "dynamics_disturbances", "init", "episodes", "eta", "delta", "alpha_T",
    "alpha_I", "layers", "epochs", "iters_per_epoch", "batch_size", "gamma", "lr",
    "target_update_epochs", "adam_fused", "threads", "log_every", "checkpoint_every",
    "snapshot_every", "curve_every", "curve_seeds", "curve_config", "curve_horizon",
)  # fmt: skip


def _relative_file(value: Any, info: ValidationInfo) -> Any:
    """A file named in a pretraining config, relative to the config's folder (a flag's is
    made absolute by the command line first)."""
    if not isinstance(value, str) or not value or info.context is None:
        return value
    path = Path(value)
    return value if path.is_absolute() else str(Path(info.context["path"]).resolve().parent / path)


def training_scenario(
    path: Path, overrides: dict[str, Any], where: Path = Path("pretrain.toml")
) -> ScenarioConfig:
    """The scenario config at ``path`` with ``overrides`` (a pretraining config's
    ``scenario_overrides``, named in errors as keys of ``where``), refused (one line) unless
    pretraining can collect on it: synthetic traffic, random starts, no scripted faults."""
    labels = {key: f"{where}: scenario_overrides {key!r}" for key in overrides}
    kind = overrides.get("traffic.kind", "synthetic")
    if kind != "synthetic":  # named before the synthetic keys it leaves unknown are blamed
        raise ConfigError(
            f"{labels['traffic.kind']} = {kind!r}: pretraining collects on a synthetic map; "
            "remove it, or train on tapes of SUMO runs (--traffic TAPE)"
        )
    if overrides.get("swarm.starts", "random") != "random":
        raise ConfigError(
            f"{labels['swarm.starts']} gives start cells; the random swarm starts on random "
            'cells in every episode: remove it (or set it to "random")'
        )
    config = with_overrides(load_scenario(path), overrides, labels)
    fix = f"{where}: scenario = {path}"
    if config.traffic.kind != "synthetic":
        raise ConfigError(
            f'{fix} has [traffic] kind = "{config.traffic.kind}"; pretraining collects on a '
            "synthetic map: name a synthetic scenario, or train on tapes of SUMO runs "
            "(--traffic TAPE)"
        )
    if config.swarm.starts != "random":
        raise ConfigError(
            f"{fix} gives [swarm].starts; the random swarm starts on random cells in every "
            'episode: set "swarm.starts" = "random" in scenario_overrides'
        )
    if config.fault_plan() is not None:
        raise ConfigError(
            f"{fix} scripts faults ([faults]); pretraining collects without faults: name a "
            "scenario without them"
        )
    return config


#: Command-line flags that override config keys.
FLAGS = {"out": "--out", "epochs": "--epochs", "tapes": "--traffic", "init": "--init"}


def load_config(path: str | Path, **overrides: Any) -> PretrainConfig:
    """Read and validate a pretraining TOML file; ``overrides`` (from flags, :data:`FLAGS`)
    that are not None are set by :func:`twin.config.with_overrides`, named by their flag in
    an error. Every problem is one :class:`UserError` line."""
    given = {k: v for k, v in overrides.items() if v is not None}
    if given.get("tapes"):  # --traffic TAPE [TAPE ...]
        given["traffic"] = "tapes"
    flags = {k: FLAGS.get(k, FLAGS["tapes"] if k == "traffic" else f"--{k}") for k in given}
    return read_with_overrides(PretrainConfig, path, given, flags)


# ----------------------------------------------------------------------------- memory
def transition_bytes(state_size: int) -> int:
    """Bytes per stored transition: the buffer's state, next state, action, reward and feasible
    mask (121 B for the paper's 13 values), and the copies the buffer's digest makes of them
    (69 B)."""
    return (8 * state_size + 17) + (4 * state_size + 17)


#: Copies of the network's float32 parameters: online, target, gradient, Adam's two moments,
#: and the copies a checkpoint holds while it is written.
PARAMETER_COPIES = 9


def estimate_pretrain_memory(cfg: PretrainConfig) -> dict[str, float]:
    """Bytes pretraining needs, roughly and from above, per part: the replay buffer (plus one
    episode being recorded), the network (:data:`PARAMETER_COPIES` copies of its parameters),
    a batch's activations and gradients, and the training map (its kernels and the blocks the
    importance scale is searched in), besides the interpreter with torch itself."""
    from twin.experiment import PROCESS_BYTES

    layers = [int(n) for n in cfg.layers]
    params = sum(a * b + b for a, b in itertools.pairwise(layers))
    cells = cfg.nx * cfg.ny
    history = cfg.history_days * (cfg.horizon + 1) * cells * DAY_BYTES
    return {
        "buffer": float(
            (cfg.episodes + 1) * cfg.horizon * cfg.n_drones * transition_bytes(cfg.variant.size)
        ),
        "network": float(params * 4 * PARAMETER_COPIES),
        "batch": float(cfg.batch_size * (sum(layers) * 4 * 8 + 200)),
        "map": float(
            cells * 8 * (len(synthetic_config(cfg.training_map).disturbances) + 3 * 256 + 16)
        ),
        "history": float(history if cfg.variant.needs_belief else 0),
        "interpreter": PROCESS_BYTES,
    }


#: The keys that size each part of the estimate, for the refusal's hint.
MEMORY_FIELDS = {
    "buffer": "episodes, traffic.horizon or swarm.n_drones",
    "network": "layers",
    "batch": "batch_size or layers",
    "map": "grid.nx, grid.ny",
    "history": "history_days, traffic.horizon or grid.nx, grid.ny",
    "interpreter": None,  # only the limit can change
}


def check_pretrain_memory(
    cfg: PretrainConfig, where: str = "pretraining config", limit_gb: float | None = None
) -> None:
    """Refuse (one line naming the key) a pretraining past the memory limit (``limit_gb``,
    else ``$TWIN_MAX_MEMORY_GB``, else 8 GB) before anything is allocated."""
    from twin.experiment import MEMORY_ENV, memory_limit_gb
    from twin.resources import check_grid_size

    check_grid_size(cfg.nx, cfg.ny, f"{where}: grid.nx, grid.ny", "use a smaller training map")
    limit = memory_limit_gb(limit_gb)
    parts = estimate_pretrain_memory(cfg)
    need = sum(parts.values())
    if need <= limit * 1e9:
        return
    part = max(parts, key=lambda k: parts[k])
    lower = f"lower {MEMORY_FIELDS[part]}, or " if MEMORY_FIELDS[part] else ""
    raise UserError(
        f"{where}: pretraining needs about {need / 1e9:,.1f} GB ({part}: "
        f"{parts[part] / 1e9:,.1f} GB), over the {limit:g} GB limit; {lower}raise "
        f"--max-memory-gb / ${MEMORY_ENV}"
    )


# ----------------------------------------------------------------------------- 2. data
def training_source(cfg: PretrainConfig) -> SyntheticTraffic:
    """The training map: the scenario's synthetic traffic (by default the paper's, an open
    20 x 30 grid with 4 big + 3 small disturbances, ``configs/training-map.toml``)."""
    return synthetic_source(cfg.training_map)


def episode_sources(cfg: PretrainConfig, count: int | None = None) -> list:
    """The traffic of each of ``count`` episodes (default ``episodes``): see
    :func:`episode_source`."""
    source = episode_source(cfg)
    return [source(e) for e in range(cfg.episodes if count is None else count)]


def episode_source(cfg: PretrainConfig):
    """A function from an episode's index to its traffic, by the recipe's ``traffic``: the one
    paper map for all, a fresh dynamic map per episode (seeded by ``seed`` and the episode,
    made when asked for), or the tapes in turn."""
    if cfg.traffic == "dynamics":
        from twin.traffic.dynamic import DynamicTraffic

        grid = make_grid(cfg.training_map)
        return lambda e: DynamicTraffic(
            grid, cfg.horizon, cfg.dynamics_disturbances, seed=cfg.seed * 100003 + e
        )
    if cfg.traffic == "tapes":
        from twin.traffic.tape import TapeTraffic

        tapes = [TapeTraffic.from_file(t) for t in cfg.tapes]
        for path, tape in zip(cfg.tapes, tapes, strict=True):
            tape.check_complete("pretraining")
            if cfg.n_drones > tape.grid.n_free:  # random starts need a free cell per drone
                free = tape.grid.n_free
                raise UserError(
                    f"{path}: its {tape.grid.nx} x {tape.grid.ny} grid has {free} free "
                    f"cell{'s' * (free != 1)} for the {cfg.n_drones} drones of the training "
                    f'map; give scenario_overrides = {{ "swarm.n_drones" = {free} }} (or a '
                    "tape of a larger grid)"
                )
        return lambda e: tapes[e % len(tapes)]
    source = training_source(cfg)
    return lambda e: source


def training_seeds(cfg: PretrainConfig) -> list[int]:
    """The dynamic generator's seeds of the training episodes (traffic = "dynamics"; none
    otherwise): ``seed * 100003 + e`` for every episode ``e`` collected."""
    if cfg.traffic != "dynamics":
        return []
    count = cfg.episodes if cfg.collector == "random" else cfg.epochs // cfg.collect_every + 1
    return [cfg.seed * 100003 + e for e in range(count)]


def history_seeds(cfg: PretrainConfig) -> list[int]:
    """The seeds of the nowcast history's days (traffic = "dynamics"; the fixed map of
    traffic = "paper" has none: every day is the same)."""
    if cfg.traffic != "dynamics":
        return []
    return list(range(cfg.history_seed, cfg.history_seed + cfg.history_days))


def training_history(cfg: PretrainConfig) -> History | None:
    """The nowcast's history of a ``state = "nowcast"`` run (None for other states): the
    training traffic's generator on ``history_days`` other days, on the training map's grid
    and horizon. The dynamic generator's days differ (seeds :func:`history_seeds`); the paper's
    fixed map is the same every day, so its history is that map with no spread (the filter's
    variance floor)."""
    if not cfg.variant.needs_belief:
        return None
    if cfg.traffic == "dynamics":
        grid = make_grid(cfg.training_map)
        return dynamics_history(grid, cfg.horizon, history_seeds(cfg), cfg.dynamics_disturbances)
    return days_history([training_source(cfg)] * cfg.history_days)


def add_episode(buffer: ReplayBuffer, ep, cfg: PretrainConfig) -> None:
    """One episode into the buffer: its 1-step transitions (``n_step = 1``), or its n-step
    transitions with their discounts (:func:`twin.learning.replay.n_step_transitions`)."""
    if cfg.n_step == 1:
        buffer.add_steps(ep.states, ep.actions, ep.rewards, ep.next_states, ep.next_feasible)
        return
    returns, next_states, next_feasible, discounts = n_step_transitions(
        ep.rewards, ep.next_states, ep.next_feasible, cfg.gamma, cfg.n_step
    )
    buffer.add_steps(ep.states, ep.actions, returns, next_states, next_feasible, discounts)


def collect_buffer(
    cfg: PretrainConfig, progress: bool = False, history: History | None = None
) -> ReplayBuffer:
    """``episodes`` random-swarm episodes, pooled; a function of the config alone (seeded).
    ``history``: the nowcast's (:func:`training_history`), for a state that reads it."""
    sources = episode_sources(cfg)
    params = cfg.training_map.params
    buffer = ReplayBuffer(sum(s.horizon for s in sources), cfg.n_drones,
                          state_size=cfg.variant.size, discounted=cfg.n_step > 1)  # fmt: skip
    episodes = range(cfg.episodes)
    if progress:
        from tqdm.auto import tqdm

        episodes = tqdm(episodes, desc="random swarm", unit="episode", leave=False)
    for e in episodes:
        rng = np.random.default_rng([cfg.seed, 1, e])
        ep = random_swarm_episode(sources[e], cfg.n_drones, params, rng, cfg.variant, history)
        add_episode(buffer, ep, cfg)
    return buffer


class CoordinatedCollector:
    """The data of ``collector = "coordinated"``: an episode of the swarm being learned every
    ``collect_every`` epochs (the first at epoch 0), epsilon-greedy on a linear schedule, into
    a ring buffer of the last ``episodes`` episodes. Episode ``e`` is seeded by ``seed`` and
    ``e`` and driven by the network as it stands, so a run is a function of its config."""

    def __init__(self, cfg: PretrainConfig, history: History | None = None) -> None:
        self.cfg = cfg
        self.history = history
        self.source = episode_source(cfg)
        self.params = cfg.training_map.params
        horizons = [self.source(e).horizon for e in range(len(cfg.tapes))] or [cfg.horizon]
        self.buffer = ReplayBuffer(cfg.episodes * max(horizons), cfg.n_drones,
                                   state_size=cfg.variant.size,
                                   discounted=cfg.n_step > 1)  # fmt: skip

    def epsilon(self, epoch: int) -> float:
        """Linear from ``epsilon_start`` at epoch 0 to ``epsilon_end`` at
        ``epsilon_decay_epochs``, constant after."""
        cfg = self.cfg
        if epoch >= cfg.epsilon_decay_epochs:
            return cfg.epsilon_end
        frac = epoch / cfg.epsilon_decay_epochs
        return cfg.epsilon_start + frac * (cfg.epsilon_end - cfg.epsilon_start)

    def due(self, epoch: int) -> bool:
        return epoch % self.cfg.collect_every == 0

    def collect(self, epoch: int, net: QNetwork) -> None:
        """The episode due at ``epoch``, driven by ``net``, into the buffer."""
        cfg = self.cfg
        e = epoch // cfg.collect_every
        rng = np.random.default_rng([cfg.seed, 3, e])
        ep = coordinated_swarm_episode(
            self.source(e),
            cfg.n_drones,
            self.params,
            rng,
            net,
            self.epsilon(epoch),
            cfg.variant,
            self.history,
        )
        add_episode(self.buffer, ep, cfg)


BUFFER_FIELDS = ("states", "actions", "rewards", "next_states", "next_feasible", "discounts")


def buffer_arrays(buffer: ReplayBuffer) -> dict[str, Any]:
    """The buffer's contents as tensors (for a checkpoint read with ``weights_only``)."""
    blob: dict[str, Any] = {"cursor": buffer.cursor, "steps": buffer.steps}
    for name in BUFFER_FIELDS:
        arr = getattr(buffer, name)
        if arr is not None:
            blob[name] = torch.from_numpy(np.ascontiguousarray(arr[: buffer.steps]))
    return blob


def restore_buffer(buffer: ReplayBuffer, blob: dict[str, Any]) -> None:
    """Put :func:`buffer_arrays`'s contents back into ``buffer``."""
    steps = int(blob["steps"])
    for name in BUFFER_FIELDS:
        if getattr(buffer, name) is not None:
            getattr(buffer, name)[:steps] = blob[name].numpy()
    buffer.cursor, buffer.steps = int(blob["cursor"]), steps


def buffer_digest(buffer: ReplayBuffer) -> str:
    """Short hash of the buffer's contents: a resumed run must train on the same data."""
    h = hashlib.sha256()
    arrays = [buffer.states, buffer.actions, buffer.rewards, buffer.next_feasible]
    for arr in arrays + ([buffer.discounts] if buffer.discounts is not None else []):
        h.update(np.ascontiguousarray(arr[: buffer.steps]).tobytes())
    return h.hexdigest()[:16]


# ----------------------------------------------------------------------------- 4. the loop
LOG_COLUMNS = ("epoch", "updates", "loss", "mean_q", "wall_s", "updates_per_s")


def pretrain(
    cfg: PretrainConfig, progress: bool = True, max_memory_gb: float | None = None
) -> Path:
    """Train (or resume) as configured; returns the path of the final model checkpoint.
    ``max_memory_gb``: the memory limit (else ``$TWIN_MAX_MEMORY_GB``, else 8 GB)."""
    out = Path(cfg.out)
    state_path, model_path, log_path = out / "state.pt", out / "qnet.pt", out / "train_log.csv"
    check_pretrain_memory(cfg, limit_gb=max_memory_gb)
    check_out_folder(cfg, "out")
    flush_subnormals()  # before the threads start: they keep the flag they start with
    try:
        return _pretrain(cfg, progress, out, state_path, model_path, log_path)
    finally:
        torch.set_flush_denormal(False)  # the process's default again


def training_threads(cfg: PretrainConfig) -> int:
    """torch's threads: ``threads``, at most the CPUs this process may use (more only slow
    training, and each one's stack takes memory: 100000 ran out of it), said in a notice. The
    config keeps its value, so a checkpoint of a larger machine resumes on a smaller one."""
    from twin.notices import notify

    try:
        cpus = len(os.sched_getaffinity(0))
    except (AttributeError, OSError):  # not on Linux
        cpus = os.cpu_count() or 1
    if cfg.threads <= cpus:
        return cfg.threads
    notify(
        f"twin: notice: threads = {cfg.threads}, but this machine gives twin {cpus} CPUs: "
        f"training on {cpus} threads"
    )
    return cpus


def _pretrain(cfg, progress, out, state_path, model_path, log_path) -> Path:
    """:func:`pretrain`'s work, with subnormals flushed: collect, train, checkpoint."""
    torch.set_num_threads(training_threads(cfg))
    torch.manual_seed(cfg.seed)

    history = training_history(cfg)  # the nowcast's, built once per run (None: not read)
    collector = CoordinatedCollector(cfg, history) if cfg.collector == "coordinated" else None
    collect_start = time.perf_counter()
    if collector is None:
        buffer = collect_buffer(cfg, progress=progress, history=history)
        digest = buffer_digest(buffer)
    else:  # collected while training; a checkpoint holds the buffer as it stands
        buffer, digest = collector.buffer, None
    collect_s = time.perf_counter() - collect_start
    kept = buffer if collector is not None else None  # saved by a checkpoint, then restored

    net = QNetwork(cfg.layers)
    target = QNetwork(cfg.layers)
    sync_target(net, target)
    optimizer = make_optimizer(net, cfg.lr, cfg.adam_fused)
    batch_rng = np.random.default_rng([cfg.seed, 2])
    epoch, wall = 0, 0.0

    if state_path.exists():
        epoch, wall = _resume(state_path, cfg, digest, net, target, optimizer, batch_rng, kept)
        _truncate_log(log_path, epoch)
    elif cfg.init is not None:  # fine-tuning: start from the given network's weights
        load_initial_weights(cfg, net)
        sync_target(net, target)
    if epoch == 0 and cfg.curve_every:  # the curve's first point: the starting network
        meta = checkpoint_meta(cfg, 0)
        meta["wall_s"] = 0.0
        save_model(out / "snapshots" / f"qnet_e{0:07d}.pt", net.state_dict(), meta)
    if epoch == 0:
        log_path.parent.mkdir(parents=True, exist_ok=True)
        with open(log_path, "w", newline="") as f:
            csv.writer(f).writerow(LOG_COLUMNS)

    bar = None
    if progress:
        from tqdm.auto import tqdm

        bar = tqdm(total=cfg.epochs, initial=epoch, desc="pretrain", unit="epoch",
                   dynamic_ncols=True)  # fmt: skip
    t_start, logged_wall, logged_epoch = time.perf_counter() - wall, wall, epoch
    saved = epoch if state_path.exists() else None  # the last good checkpoint's epoch
    losses, qs = [], []
    try:
        while epoch < cfg.epochs:
            if collector is not None and collector.due(epoch):
                collector.collect(epoch, net)
            batch = buffer.sample(cfg.batch_size, batch_rng)
            loss, mean_q = train_epoch(
                net, target, optimizer, batch, cfg.gamma, cfg.iters_per_epoch
            )
            losses.append(loss)
            qs.append(mean_q)
            epoch += 1
            if epoch % cfg.target_update_epochs == 0:
                sync_target(net, target)
            log = epoch % cfg.log_every == 0 or epoch == cfg.epochs
            save = epoch % cfg.checkpoint_every == 0 or epoch == cfg.epochs
            snapshot = (cfg.snapshot_every and epoch % cfg.snapshot_every == 0) or (
                cfg.curve_every and epoch % cfg.curve_every == 0
            )
            if log or save or snapshot:  # never log or write a diverged network
                _check_finite(cfg, net, losses, epoch, state_path, saved)
            if log:
                wall = time.perf_counter() - t_start
                rate = (epoch - logged_epoch) * cfg.iters_per_epoch / max(wall - logged_wall, 1e-9)
                row = (epoch, epoch * cfg.iters_per_epoch, float(torch.stack(losses).mean()),
                       float(torch.stack(qs).mean()), round(wall, 2), round(rate, 2))  # fmt: skip
                with open(log_path, "a", newline="") as f:
                    csv.writer(f).writerow(row)
                if bar is not None:
                    bar.set_postfix(loss=f"{row[2]:.4g}", q=f"{row[3]:.3g}", ups=f"{rate:.0f}")
                losses, qs, logged_wall, logged_epoch = [], [], wall, epoch
            if save:
                wall = time.perf_counter() - t_start
                if kept is not None:
                    digest = buffer_digest(buffer)
                _save_state(state_path, cfg, digest, net, target, optimizer, batch_rng, epoch,
                            wall, kept)  # fmt: skip
                saved = epoch
            if snapshot:
                meta = checkpoint_meta(cfg, epoch)
                meta["wall_s"] = round(time.perf_counter() - t_start, 2)
                save_model(out / "snapshots" / f"qnet_e{epoch:07d}.pt", net.state_dict(), meta)
            if bar is not None:
                bar.update(1)
    finally:
        if bar is not None:
            bar.close()
    meta = checkpoint_meta(cfg, epoch)
    meta["wall_s"] = round(time.perf_counter() - t_start, 1)
    meta["buffer_digest"] = digest if kept is None else buffer_digest(buffer)
    meta["collect_s"] = round(collect_s, 1)  # the data collected before the loop (random)
    save_model(model_path, net.state_dict(), meta)
    if cfg.curve_every:
        write_curve(cfg, out)
    write_provenance(cfg, out, meta)
    return model_path


#: The keys of a recipe's schedule that its provenance lists.
SCHEDULE_KEYS = (
    "episodes", "horizon", "n_drones", "epochs", "iters_per_epoch", "batch_size", "gamma", "lr",
    "target_update_epochs", "layers", "n_step", "collector",
)  # fmt: skip


def checkpoint_meta(cfg: PretrainConfig, epoch: int) -> dict[str, Any]:
    """The metadata of a checkpoint of ``cfg`` at ``epoch`` (with the nowcast's history)."""
    return model_metadata(cfg.layers, cfg.training_dict(), cfg.seed, epoch, cfg.state,
                          history=cfg.history_record())  # fmt: skip


def _tape_shape(path: str | Path) -> dict[str, Any] | None:
    """A tape's grid and steps, from its footer (None when it cannot be read)."""
    from twin.traffic.tape import tape_footer

    meta = tape_footer(path)
    try:  # it trained: a footer fails to read only if the file changed since
        return {"grid": [int(meta["nx"]), int(meta["ny"])], "horizon": int(meta["horizon"])}
    except (TypeError, KeyError, ValueError):
        return None


def write_provenance(cfg: PretrainConfig, out: Path, meta: dict[str, Any]) -> Path:
    """``provenance.json`` beside ``qnet.pt``: the command, the recipe, the seeds, the schedule,
    the wall time, the inputs' hashes and the learning curve (if measured)."""
    import json

    from twin.boundary import command_line
    from twin.files import atomic_write

    training = cfg.training_dict()
    curve_path = out / "curve.csv"
    curve = []
    if curve_path.exists():
        with open(curve_path, newline="") as f:
            curve = [
                {k: float(v) if k in ("R_hat_T", "wall_s") else int(v) for k, v in row.items()}
                for row in csv.DictReader(f)
            ]
    record = {
        "command": command_line(),
        "recipe": {
            "traffic": cfg.traffic,
            "tapes": {t: file_sha256(t) for t in cfg.tapes},
            "dynamics_disturbances": cfg.dynamics_disturbances
            if cfg.traffic == "dynamics"
            else None,
            "init": {"path": cfg.init, "sha256": file_sha256(cfg.init)} if cfg.init else None,
            "scenario": {
                "path": str(cfg.scenario),
                "sha256": file_sha256(cfg.scenario),
                "overrides": cfg.scenario_overrides,
            },
            # what the episodes ran on: each tape's own grid and steps (the scenario's grid and
            # schedule.horizon then apply to the curve's scenario only), else the scenario's
            "episodes": {"from": "tapes", "tapes": {t: _tape_shape(t) for t in cfg.tapes}}
            if cfg.traffic == "tapes"
            else {"from": "scenario", "horizon": training.get("horizon")},
            "state": cfg.variant.summary,
            **({"history": cfg.history_record()} if cfg.variant.needs_belief else {}),
            "collector": cfg.collector,
            "n_step": cfg.n_step,
            "gamma": cfg.gamma,
            "exploration": {
                "collect_every": cfg.collect_every,
                "epsilon_start": cfg.epsilon_start,
                "epsilon_end": cfg.epsilon_end,
                "epsilon_decay_epochs": cfg.epsilon_decay_epochs,
            }
            if cfg.collector == "coordinated"
            else None,
        },
        "seeds": {
            "training": cfg.seed,
            "validation_curve": cfg.curve_seeds if cfg.curve_every else [],
        },
        "schedule": {k: training[k] for k in SCHEDULE_KEYS},
        "updates": cfg.epochs * cfg.iters_per_epoch,
        "wall_s": meta.get("wall_s"),
        "collect_s": meta.get("collect_s"),
        "qnet_sha256": file_sha256(out / "qnet.pt"),
        "buffer_digest": meta.get("buffer_digest"),
        "curve": {"config": cfg.curve_config, "horizon": cfg.curve_horizon, "points": curve},
        "config": training,
    }
    path = out / "provenance.json"
    text = json.dumps(record, indent=1, default=str)
    atomic_write(path, lambda tmp: tmp.write_text(text))
    return path


def initial_network(cfg: PretrainConfig) -> QNetwork:
    """The network of ``cfg.init``; refused (one line) when its state variant or its layers
    differ from ``cfg``'s, or its weights do not load."""
    meta = read_checkpoint(cfg.init)["meta"]
    state = checkpoint_state(cfg.init, meta).name
    check_initial_fit(cfg, f"init = {cfg.init}", state, meta.get("layers"))
    loaded, _ = load_qnet(cfg.init)  # its weights checked against its layers (one line)
    return loaded


def check_initial_fit(cfg: PretrainConfig, where: str, state: str, layers) -> None:
    """A start (a checkpoint, or a row trained before) reads ``cfg``'s state with its layers."""
    if state != cfg.state:
        raise UserError(
            f"{where}: it reads state {state!r}, this pretraining state = "
            f'{cfg.state!r}; give a checkpoint of the same state or set `state = "{state}"`'
        )
    if layers != list(cfg.layers):
        raise UserError(
            f"{where}: its layers {layers} differ from `layers` {list(cfg.layers)}; "
            "give a checkpoint of the same network or set `layers` to match"
        )


def load_initial_weights(cfg: PretrainConfig, net: QNetwork) -> None:
    """The weights of ``cfg.init`` into ``net`` (:func:`initial_network`)."""
    net.load_state_dict(initial_network(cfg).state_dict())


# ----------------------------------------------------------------------------- 6. the curve
CURVE_COLUMNS = ("epoch", "updates", "seed", "R_hat_T", "wall_s")


def curve_scenario(cfg: PretrainConfig):
    """The scenario config the curve is measured on, at ``curve_horizon`` steps."""
    config = load_scenario(shipped_config(cfg.curve_config))
    return with_overrides(config, {"traffic.horizon": cfg.curve_horizon}, {})


def _check_curve_scenario(config: ScenarioConfig) -> None:
    """A SUMO scenario's files, window, grid and incidents, as a run checks them before SUMO
    starts (synthetic scenarios are checked on load)."""
    if config.traffic.kind == "sumo":
        from twin.sumo.scenario import sumo_source

        sumo_source(config)


def write_curve(cfg: PretrainConfig, out: Path) -> Path:
    """``curve.csv``: R_hat_T of the "rl" swarm driven by each curve snapshot (every
    ``curve_every`` epochs, and the final model) on the validation seeds ``curve_seeds``; a
    nowcast state's swarm reads the history of ``history_days`` days of the dynamic generator
    on the curve map's grid (seeds from ``history_seed``)."""
    from twin.experiment import Experiment, run_experiment
    from twin.metrics import table2

    config = curve_scenario(cfg)
    points = sorted(
        e
        for e in (int(f.name[6:-3]) for f in (out / "snapshots").glob("qnet_e*.pt"))
        if e % cfg.curve_every == 0 and e <= cfg.epochs
    )
    files = [(e, out / "snapshots" / f"qnet_e{e:07d}.pt") for e in points]
    if cfg.epochs not in points:
        files.append((cfg.epochs, out / "qnet.pt"))
    options = {}
    if cfg.variant.needs_belief:  # the curve map's history: the dynamic generator's days
        options["history"] = dynamics_history(
            make_grid(config), cfg.curve_horizon, range(cfg.history_seed,
            cfg.history_seed + cfg.history_days), cfg.dynamics_disturbances,
        )  # fmt: skip
    rows = []
    for epoch, path in files:
        wall = read_checkpoint(path)["meta"].get("wall_s")
        experiment = Experiment(
            config, swarms=["rl"], seeds=cfg.curve_seeds,
            swarm_options={"rl": {"checkpoint": path, **options}}, keep_importance=False,
        )  # fmt: skip
        for result in run_experiment(experiment).results:
            value = float(table2(result, config.params)["R_hat_T"].iloc[0])
            rows.append((epoch, epoch * cfg.iters_per_epoch, result.seed, value, wall))
    path = out / "curve.csv"
    with open(path, "w", newline="") as f:
        writer = csv.writer(f)
        writer.writerow(CURVE_COLUMNS)
        writer.writerows(rows)
    return path


def _check_finite(cfg, net, losses, epoch, state_path, saved) -> None:
    """Stop with one line when the loss since the last check or a weight is not finite; the
    last checkpoint (``saved``: its epoch, None if none) is left as it is."""
    loss_ok = bool(torch.isfinite(torch.stack(losses)).all()) if losses else True
    if loss_ok and all(bool(torch.isfinite(p).all()) for p in net.parameters()):
        return
    what = "loss" if not loss_ok else "weights"
    kept = (
        f"the last good checkpoint {state_path} (epoch {saved}) is kept"
        if saved is not None
        else "no checkpoint was written"
    )
    raise UserError(
        f"{Path(cfg.out)}: lr = {cfg.lr:g}: training diverged by epoch {epoch} (non-finite "
        f"{what}); {kept}; lower `lr` or the reward weights and start afresh in another `out`"
    )


# ----------------------------------------------------------------------------- 5. checkpoints
def _save_state(path, cfg, digest, net, target, optimizer, batch_rng, epoch, wall,
                buffer=None) -> None:  # fmt: skip
    """The training state; ``buffer``: replay data collected while training, saved whole."""
    meta = checkpoint_meta(cfg, epoch)
    data = {"seed": cfg.seed, "digest": digest}
    if buffer is not None:
        data["data"] = buffer_arrays(buffer)
    atomic_save(
        {
            "meta": meta,
            "weights": net.state_dict(),
            "target": target.state_dict(),
            "optimizer": optimizer.state_dict(),
            "batch_rng": batch_rng.bit_generator.state,
            "torch_rng": torch.get_rng_state(),
            "buffer": data,
            "epoch": epoch,
            "wall_s": wall,
        },
        path,
    )


#: What pretraining writes into its folder (and the boundary's error.log).
PRETRAIN_FILES = frozenset(
    {"state.pt", "qnet.pt", "train_log.csv", "snapshots", "error.log", "curve.csv",
     "provenance.json"}
)  # fmt: skip


def check_out_folder(cfg: PretrainConfig, flag: str = "--out") -> None:
    """Refuse (one line naming ``flag``) an ``out`` folder that is not empty and not this
    pretraining's own: a file twin did not write, a model or log without the checkpoint
    ``state.pt`` to resume from, or a checkpoint of other settings. A folder of this config's
    checkpoint (an interrupted or finished run) is resumed by :func:`pretrain`."""
    out = Path(cfg.out)
    if not out.is_dir():
        return
    entries = list(out.iterdir())
    fix = "pass a new or empty folder (or delete this one to start afresh)"
    foreign = sorted(e.name for e in entries if not written_by_pretraining(e))
    if foreign:
        raise UserError(
            f"{flag} {out}: holds {foreign[0]!r}, which `twin pretrain` did not write; {fix}"
        )
    snapshots = out / "snapshots"
    if snapshots.exists():
        odd = [e.name for e in _entries(snapshots) if not _snapshot_name(e)]
        if not snapshots.is_dir() or snapshots.is_symlink() or odd:
            what = repr(f"snapshots/{odd[0]}") if odd else "snapshots, not a folder of its own,"
            raise UserError(
                f"{flag} {out}: holds {what} which `twin pretrain` did not write; {fix}"
            )
    log = out / "train_log.csv"
    if log.exists() and not _own_log(log):
        raise UserError(
            f"{flag} {out}: train_log.csv is not a pretraining log of twin (its header is not "
            f"{','.join(LOG_COLUMNS)}); {fix}"
        )
    state = out / "state.pt"
    if state.exists():
        _check_settings(state, cfg)
    elif (out / "qnet.pt").exists():
        raise UserError(
            f"{flag} {out}: holds qnet.pt but no checkpoint state.pt of the run that wrote it, "
            f"so it would be overwritten; {fix}"
        )


def written_by_pretraining(entry: Path) -> bool:
    """Whether ``entry`` of a pretraining folder is one pretraining writes
    (:data:`PRETRAIN_FILES`, or a temporary file of its atomic writes)."""
    return entry.name in PRETRAIN_FILES or _temp(entry)


def _temp(entry: Path) -> bool:
    return entry.name.startswith(".") and entry.name.endswith(".tmp") and entry.is_file()


def _entries(folder: Path) -> list[Path]:
    return list(folder.iterdir()) if folder.is_dir() and not folder.is_symlink() else []


def _snapshot_name(entry: Path) -> bool:
    name = entry.name
    return _temp(entry) or (
        name.startswith("qnet_e") and name.endswith(".pt") and name[6:-3].isdigit()
    )


def _own_log(path: Path) -> bool:
    if not_a_file(path) is not None:  # a FIFO would block forever
        return False
    try:
        with open(path, newline="", encoding="utf-8") as f:
            header = next(csv.reader(f), [])
    except (OSError, UnicodeError, csv.Error):
        return False
    return tuple(header) == LOG_COLUMNS


def _check_settings(path: Path, cfg: PretrainConfig) -> dict[str, Any]:
    """The checkpoint at ``path``, refused unless it was written with ``cfg``'s settings."""
    blob = read_checkpoint(path, f"delete {path.parent} or set another `out` to start afresh")
    saved = blob["meta"].get("config")
    if not isinstance(saved, dict) or not isinstance(blob.get("buffer"), dict):
        raise UserError(
            f"{path}: meta.config or buffer is missing or not a table (a damaged checkpoint); "
            f"delete {path.parent} or set another `out` to start afresh"
        )
    now = cfg.training_dict()
    defaults = PretrainConfig().training_dict()  # keys a checkpoint of older code lacks
    changed = [
        k for k in now if k not in cfg.RESUMABLE_CHANGES and saved.get(k, defaults.get(k)) != now[k]
    ]
    if changed:
        raise UserError(
            f"{path} was written by a run with other settings ({', '.join(changed)}); "
            f"delete {path.parent} or set another `out` to start afresh"
        )
    epoch = blob.get("epoch")
    if isinstance(epoch, int) and epoch > cfg.epochs:  # its model would be labelled cfg.epochs
        given = cfg.flag_of("epochs") or "epochs ="
        raise UserError(
            f"{path}: its run trained {epoch} epochs, past {given} {cfg.epochs}; give at least "
            f"{epoch} epochs to resume it, or delete {path.parent} (or set another `out`) to "
            f"train {cfg.epochs} afresh"
        )
    return blob


def _resume(path, cfg, digest, net, target, optimizer, batch_rng, buffer=None):
    """Load the state at ``path`` into the training objects; returns (epoch, wall_s).
    ``buffer``: replay data collected while training, restored from the state."""
    blob = _check_settings(path, cfg)
    if buffer is not None:
        try:
            restore_buffer(buffer, blob["buffer"]["data"])
        except (KeyError, TypeError, ValueError, AttributeError) as exc:
            raise UserError(
                f"{path} is incomplete ({type(exc).__name__}); delete {path.parent} or set "
                "another `out` to start afresh"
            ) from None
        digest = buffer_digest(buffer)
    if blob["buffer"].get("digest") != digest:
        tapes = f" ({', '.join(map(str, cfg.tapes))} or its scenario)" if cfg.tapes else ""
        raise UserError(
            f"{path}: the replay data differ from the saved run's: its traffic{tapes} changed "
            f"since; delete {path.parent} or set another `out` to start afresh"
        )
    try:
        net.load_state_dict(blob["weights"])
        target.load_state_dict(blob["target"])
        optimizer.load_state_dict(blob["optimizer"])
        batch_rng.bit_generator.state = blob["batch_rng"]
        torch.set_rng_state(blob["torch_rng"])
        return int(blob["epoch"]), float(blob["wall_s"])
    except (KeyError, TypeError, ValueError, RuntimeError, AttributeError, IndexError) as exc:
        raise UserError(f"{path} is incomplete ({type(exc).__name__}); delete it") from None


def _truncate_log(path: Path, epoch: int) -> None:
    """Drop log rows written after the checkpoint we resume from."""
    if not path.exists():
        return
    with open(path, newline="") as f:
        rows = list(csv.reader(f))
    kept = rows[:1]
    for n, row in enumerate(rows[1:], start=2):
        if not row:
            continue
        try:
            row_epoch = int(row[0])
        except ValueError:
            raise UserError(
                f"{path}: row {n} starts with {row[0]!r}, not an epoch number; delete the row "
                "(or the file, to start its log afresh)"
            ) from None
        if row_epoch <= epoch:
            kept.append(row)
    with open(path, "w", newline="") as f:
        csv.writer(f).writerows(kept or [LOG_COLUMNS])
