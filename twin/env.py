"""The swarm as an RL environment: a PettingZoo parallel env and a Gymnasium joint-swarm env.

Any :class:`twin.traffic.base.TrafficSource` drives it (synthetic, a replayed tape, live SUMO).
The environment owns no dynamics of its own: it advances with :func:`twin.swarm.step`, the step
of the patrol loop, so a policy scores the same here as in ``run_patrol``.

- agents ``drone_0 .. drone_{N-1}``; per agent the observation is a dict with ``observation``,
  the 13 values of eq. (s) (:data:`twin.scores.STATE_LAYOUT`; another state variant of
  :mod:`twin.states` with ``state=``), and ``action_mask``, the feasible
  actions ``U_d(p)`` as 0/1 (PettingZoo's convention);
- actions ``Discrete(5)`` in the order of :data:`twin.grid.ACTIONS`: 0 stay, 1 up, 2 down,
  3 left, 4 right; an infeasible action raises :class:`twin.swarm.InfeasibleActionError`, an
  unknown agent name, an action that is not a whole number in 0..4 (in either env: ``1.0`` is
  not an action), a fractional or off-grid start, an ``n_drones`` that is not a whole number
  in 1..free cells or disagrees with ``starts``, a reset seed that is not a whole number >= 0
  :class:`EnvInputError` (both :class:`~twin.errors.UserError` and ``ValueError``); ``step()``
  before ``reset()`` or after the episode ended, and any call after ``close()``, raise
  :class:`EnvCallOrderError` (a UserError, Gymnasium's ``ResetNeeded``, a ``RuntimeError``),
  saying what to call first; ``close()`` twice does nothing the second time;
- reward per drone: the headline reward :func:`twin.scores.rewards_on_arrival`, the gain of
  the cell the drone visits (split evenly among drones on one cell), so the drones' rewards sum
  to the swarm's ``R^k``; the infos carry its parts ``reward_importance`` (alpha_T) and
  ``reward_idleness`` (alpha_I), and ``reward_paper``, Def. 4 as printed (gameable by
  overlapping views and stacking, for comparison only);
- no termination; truncation after ``horizon`` steps.

``reset(seed=s)`` draws the start cells as ``twin.patrol.random_starts(grid, N,
np.random.default_rng(s))``, unless fixed ``starts`` were given. A source built by a factory is
rebuilt on every reset after the first (a live SUMO run restarts cleanly, on the same traffic
day: its SUMO seed is the factory's); ``close`` closes it.
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path
from typing import Any, ClassVar, Literal

import numpy as np
from pydantic import ValidationError

try:
    import gymnasium
    from gymnasium import spaces
    from pettingzoo import ParallelEnv
except ImportError:  # pragma: no cover - depends on the install
    raise ImportError("twin.env needs gymnasium and pettingzoo: pip install 'twin[env]'") from None

from twin.config import SwarmConfig, validation_error
from twin.errors import UserError
from twin.grid import N_ACTIONS
from twin.notices import once_among
from twin.scores import ScoreParams
from twin.states import DEFAULT_STATE, state_variant
from twin.swarm import (
    InfeasibleActionError,
    StepOutcome,
    SwarmState,
    check_actions,
    initial_state,
    random_starts,
    step,
)
from twin.traffic.base import TrafficSource

SourceLike = TrafficSource | Callable[[], TrafficSource]


class EnvInputError(UserError, ValueError):
    """A bad argument to an env (agent name, action, start cell, reward parameter, source,
    option): one line naming it."""


class EnvCallOrderError(UserError, gymnasium.error.ResetNeeded, RuntimeError):
    """A call out of order (``step()`` before ``reset()`` or after the episode ended, any
    call but ``close()`` after ``close()``): one line saying what to call first. Gymnasium's
    ``ResetNeeded`` (what its order-enforcing wrapper raises) and a ``RuntimeError``."""


def _check_order(env: SwarmParallelEnv, call: str) -> None:
    """Refuse ``call`` (``"step()"``, ``"reset()"``) on a closed env, and a step outside an
    episode."""
    if env._closed:
        raise EnvCallOrderError(f"{call} after close(): the env is closed; make a new one")
    if call != "step()":
        return
    if env.swarm is None:
        raise EnvCallOrderError("step() before reset(): call env.reset() first")
    if env.swarm.k >= env.horizon:
        raise EnvCallOrderError(
            f"step() after the episode ended (truncated after {env.horizon} steps): call "
            "env.reset() to start a new episode"
        )


def _action(agent: str, value: Any) -> int:
    """One agent's action as an int in ``0 .. N_ACTIONS - 1`` (numpy integers accepted)."""
    if isinstance(value, np.ndarray) and value.shape == ():
        value = value.item()
    if isinstance(value, (bool, np.bool_)) or not isinstance(value, (int, np.integer)):
        raise EnvInputError(
            f"{agent}: action {value!r} is not a whole number; give 0 .. {N_ACTIONS - 1} "
            "(0 stay, 1 up, 2 down, 3 left, 4 right)"
        )
    if not 0 <= int(value) < N_ACTIONS:
        raise EnvInputError(f"{agent}: action {value} is out of range 0 .. {N_ACTIONS - 1}")
    return int(value)


def _whole(name: str, value: Any) -> int:
    """``value`` as an int (numpy integers accepted), else :class:`EnvInputError`."""
    if isinstance(value, np.ndarray) and value.shape == ():
        value = value.item()
    if isinstance(value, (bool, np.bool_)) or not isinstance(value, (int, np.integer)):
        raise EnvInputError(f"{name} = {value!r} is not a whole number; give e.g. 4")
    return int(value)


def _seed(seed: Any) -> int:
    """A reset seed: a whole number >= 0."""
    seed = _whole("seed", seed)
    if seed < 0:
        raise EnvInputError(f"seed = {seed} is negative; give a whole number >= 0 (or None)")
    return seed


def _params(params: Any) -> ScoreParams:
    """``params`` as :class:`ScoreParams` with every value in ``[swarm]``'s range (checked by
    :class:`twin.config.SwarmConfig`: Def. 3's ``eta, delta`` in (0, 1), Def. 4's weights in
    [0, 1e6], not both 0); else one line naming it."""
    if params is None:
        return ScoreParams()
    if not isinstance(params, ScoreParams):
        raise EnvInputError(
            f"params = {params!r} is not a ScoreParams; give "
            "twin.scores.ScoreParams(eta=..., delta=..., alpha_T=..., alpha_I=...)"
        )
    names = ("eta", "delta", "alpha_T", "alpha_I")
    values = {name: getattr(params, name) for name in names}
    values = {  # numpy's numbers and bools as Python's (a bool is then refused)
        name: v.item() if isinstance(v, (np.integer, np.floating, np.bool_)) else v
        for name, v in values.items()
    }
    for name, v in values.items():  # a Decimal, complex or array would pass as a float
        if (isinstance(v, (int, float, str)) and not isinstance(v, bool)) or v is None:
            continue
        raise EnvInputError(
            f"params.{name} = {v!r} must be a number (a Python or numpy int or float); give "
            f"e.g. {getattr(ScoreParams(), name)!r}"
        )
    try:
        SwarmConfig.model_validate(values)
    except ValidationError as exc:
        labels = {name: f"params.{name}" for name in names}
        line = validation_error("params", exc, values, SwarmConfig, sections=False, labels=labels)
        raise EnvInputError(str(line)) from None
    return params


def _built_source(source: Any, where: str) -> TrafficSource:
    """``source`` when it is a traffic source, else one line naming ``where``."""
    if not isinstance(source, TrafficSource):
        raise EnvInputError(
            f"{where} is {type(source).__name__}, not a traffic source; give a "
            "twin.traffic.base.TrafficSource or a callable that returns one"
        )
    return source


class SwarmParallelEnv(ParallelEnv):
    """PettingZoo ``ParallelEnv``: one agent per drone over a traffic source."""

    metadata: ClassVar[dict] = {
        "name": "twin_swarm_v0",
        "render_modes": [],
        "is_parallelizable": True,
    }
    render_mode = None  # none: watch a run with `twin run --gui` or `twin replay --gui`

    def __init__(
        self,
        source: SourceLike,
        n_drones: int | None = None,
        params: ScoreParams | None = None,
        starts: np.ndarray | None = None,
        state: str = DEFAULT_STATE,
    ) -> None:
        """``source`` is a traffic source or a callable that builds one (``source_factory``).

        Give ``n_drones`` (random starts drawn at each reset) or fixed ``starts`` ``(N, 2)``.
        ``state`` names the observations' state variant (:mod:`twin.states`); ``nowcast`` is
        refused: the envs carry no history for its belief.
        """
        try:
            self.variant = state_variant(state)
        except UserError as exc:  # the env's own error type, a ValueError too
            raise EnvInputError(str(exc)) from None
        if self.variant.needs_belief:
            raise EnvInputError(
                f"state = {state!r} reads the nowcast of a history of earlier days, which the "
                'envs do not carry; use state = "paper" or "window" (or `twin pretrain`)'
            )
        self.params = _params(params)
        if not isinstance(source, TrafficSource) and not callable(source):
            _built_source(source, "source")
        self._factory = None if isinstance(source, TrafficSource) else source
        self._said: set[str] = set()  # the notices said, each once per env
        with once_among(self._said):
            self.source: TrafficSource = (
                source if self._factory is None else _built_source(self._factory(), "source()")
            )
        self.grid, self.horizon = self.source.grid, self.source.horizon
        self._starts = None if starts is None else self._check_starts(starts)
        if n_drones is not None:
            n_drones = _whole("n_drones", n_drones)
        if self._starts is not None:
            if n_drones is not None and n_drones != len(self._starts):
                raise EnvInputError(
                    f"n_drones = {n_drones} but starts gives {len(self._starts)} cells; give one "
                    "start cell per drone, or only one of n_drones and starts"
                )
            n_drones = len(self._starts)
        if n_drones is None or n_drones < 1 or n_drones > self.grid.n_free:
            raise EnvInputError(
                f"n_drones = {n_drones}: need 1 .. {self.grid.n_free} drones (the free cells)"
            )
        self.n_drones = int(n_drones)
        self.possible_agents = [f"drone_{d}" for d in range(self.n_drones)]
        self.agents: list[str] = []
        self._observation_spaces = {
            a: spaces.Dict(
                {
                    "observation": spaces.Box(0.0, 1.0, (self.variant.size,), np.float32),
                    "action_mask": spaces.MultiBinary(N_ACTIONS),
                }
            )
            for a in self.possible_agents
        }
        self._action_spaces = {a: spaces.Discrete(N_ACTIONS) for a in self.possible_agents}
        self._rng = np.random.default_rng()
        self._maps = None
        self._used = False
        self._closed = False
        self.swarm: SwarmState | None = None

    def observation_space(self, agent: str) -> spaces.Space:
        return self._observation_spaces[self._agent(agent)]

    def action_space(self, agent: str) -> spaces.Space:
        return self._action_spaces[self._agent(agent)]

    def _agent(self, agent: Any) -> str:
        if not isinstance(agent, str) or agent not in self._action_spaces:
            raise EnvInputError(
                f"agent {agent!r} is not one of this env's agents "
                f"(drone_0 .. drone_{self.n_drones - 1}); use env.possible_agents"
            )
        return agent

    def reset(self, seed: int | None = None, options: dict | None = None):
        """A new episode; ``options`` are accepted and not used (PettingZoo's API test passes
        arbitrary ones): starts and drones are set when the env is made."""
        _check_order(self, "reset()")
        if seed is not None:
            self._rng = np.random.default_rng(_seed(seed))
        self._restart(self._rng)
        obs = self._observations()
        return obs, {a: {} for a in self.agents}

    def step(self, actions: dict[str, int]):
        _check_order(self, "step()")
        if not isinstance(actions, dict):
            raise EnvInputError(
                f"actions must be a dict {{agent: action}}, got {type(actions).__name__}"
            )
        unknown = [a for a in actions if a not in self.agents]
        if unknown:
            live = f"drone_0 .. drone_{self.n_drones - 1}" if self.agents else "none: call reset()"
            raise EnvInputError(
                f"action for {unknown[0]!r}, which is not a live agent ({live}); "
                "give one action per agent of env.agents"
            )
        missing = [a for a in self.agents if a not in actions]
        if missing:
            raise EnvInputError(f"no action for {', '.join(missing)}; give one per live agent")
        out = self._advance(np.array([_action(a, actions[a]) for a in self.agents]))
        agents = self.agents
        done = self.swarm.k >= self.horizon
        obs = self._observations()
        rewards = {a: float(out.rewards[d]) for d, a in enumerate(agents)}
        infos = {
            a: {
                "reward_importance": float(out.importance[d]),
                "reward_idleness": float(out.idleness[d]),
                "reward_paper": float(out.paper[d]),
            }
            for d, a in enumerate(agents)
        }
        if done:
            self.agents = []
        return (
            obs,
            rewards,
            dict.fromkeys(agents, False),
            dict.fromkeys(agents, done),
            infos,
        )

    def render(self) -> None:
        """Nothing to render (``render_modes`` is empty): a warning and None, as Gymnasium's
        environments do without a render mode."""
        _no_render()

    def close(self) -> None:
        """Close the traffic source (a live simulation ends); a second call does nothing."""
        if self._closed:
            return
        self._closed = True
        with once_among(self._said):  # a forked simulation's notices come as it ends
            self._close_maps()
        self.source.close()

    # shared with SwarmGymEnv -------------------------------------------------------------

    def _restart(self, rng: np.random.Generator) -> None:
        """Start a new episode on a fresh pass of the source; the start cells from ``rng``."""
        with once_among(self._said):  # a scenario's notices once, not at every episode
            self._close_maps()  # (a forked simulation's come as it ends)
            if self._used and self._factory is not None:
                self.source.close()
                self.source = _built_source(self._factory(), "source()")
                if self.source.grid.shape != self.grid.shape or self.source.horizon != self.horizon:
                    raise EnvInputError(
                        "source() built a source with another grid or horizon than its first; "
                        "make the factory build the same scenario at every call"
                    )
                self.grid = self.source.grid
            self._used = True
            self._maps = self.source.importance_maps()
            first = self._next_map()
        starts = self._starts
        if starts is None:
            starts = random_starts(self.grid, self.n_drones, rng)
        self.swarm = initial_state(self.grid, starts, first)
        self.agents = list(self.possible_agents)

    def _advance(self, actions: np.ndarray) -> StepOutcome:
        _check_order(self, "step()")
        actions = check_actions(self.swarm, actions)  # before the source moves on
        self.swarm, out = step(self.swarm, actions, self._next_map(), self.grid, self.params)
        if self.swarm.k >= self.horizon:
            with once_among(self._said):  # the simulation's notices come as it ends
                self._close_maps()
        return out

    def _next_map(self) -> np.ndarray:
        try:
            return next(self._maps)
        except StopIteration:
            k = -1 if self.swarm is None else self.swarm.k
            raise RuntimeError(
                f"traffic source ended after {k + 1} of {self.horizon + 1} maps"
            ) from None

    def _close_maps(self) -> None:
        if self._maps is not None:
            self._maps.close()  # a live source closes its simulation here
            self._maps = None

    def _states(self) -> np.ndarray:
        s = self.swarm
        states = self.variant.states(self.grid, s.idleness, s.importance, s.positions)
        return states.astype(np.float32)

    def _observations(self) -> dict[str, dict[str, np.ndarray]]:
        if not self.agents:
            return {}
        states, masks = self._states(), self.swarm.feasible.astype(np.int8)
        return {
            a: {"observation": states[d], "action_mask": masks[d]}
            for d, a in enumerate(self.agents)
        }

    def _check_starts(self, starts) -> np.ndarray:
        cells = np.asarray(starts, dtype=object).ravel()
        if any(isinstance(v, (bool, np.bool_)) for v in cells):  # as n_drones = True is no count
            raise EnvInputError(
                "starts must be (N, 2) whole-number cells (i, j), not True/False; e.g. "
                "[[0, 0], [1, 2]]"
            )
        if any(isinstance(v, (str, bytes, np.str_)) for v in cells):  # as n_drones = "3" is none
            raise EnvInputError(
                "starts must be (N, 2) whole-number cells (i, j), not text; e.g. [[0, 0], [1, 2]]"
            )
        try:
            raw = np.asarray(starts, dtype=np.float64)
        except (TypeError, ValueError):
            raise EnvInputError(
                "starts must be (N, 2) whole-number cells (i, j), e.g. [[0, 0], [1, 2]]"
            ) from None
        if raw.ndim != 2 or raw.shape[1] != 2 or not len(raw):
            raise EnvInputError(f"starts must be (N, 2) cells, got shape {raw.shape}")
        whole = np.isfinite(raw) & (raw == np.round(raw))
        if not whole.all():
            d = int(np.flatnonzero(~whole.all(axis=1))[0])
            raise EnvInputError(
                f"starts[{d}] = {raw[d].tolist()} is not a cell; give whole numbers (i, j)"
            )
        nx, ny = self.grid.shape
        inside = (raw[:, 0] >= 0) & (raw[:, 0] < nx) & (raw[:, 1] >= 0) & (raw[:, 1] < ny)
        if not inside.all():
            d = int(np.flatnonzero(~inside)[0])
            i, j = (f"{v:.0f}" if abs(v) < 1e15 else f"{v:g}" for v in raw[d])  # not 301 digits
            raise EnvInputError(
                f"starts[{d}] = ({i}, {j}) is off the {nx} x {ny} grid; every start must be a "
                "free cell on the map"
            )
        starts = raw.astype(np.int64)
        free = self.grid.is_free(starts)
        if not free.all():
            d = int(np.flatnonzero(~free)[0])
            i, j = (int(v) for v in starts[d])
            where = "an obstacle" if self.grid.inside(starts[d]) else f"off the {nx} x {ny} grid"
            raise EnvInputError(
                f"starts[{d}] = ({i}, {j}) is {where}; every start must be a free cell on the map"
            )
        if len({tuple(c) for c in starts.tolist()}) != len(starts):
            raise EnvInputError("starts: two drones on one cell; give distinct cells")
        return starts


class SwarmGymEnv(gymnasium.Env):
    """The joint swarm as one Gymnasium agent: ``MultiDiscrete([5] * N)`` actions, ``(N, S)``
    observations (S = 13 for the paper state), reward ``R^k`` (Def. 4, summed over drones);
    ``info["action_mask"]`` is the ``(N, 5)`` feasible mask.

    ``infeasible="stay"`` turns an infeasible action into "stay" (for algorithms that cannot
    mask actions); the default raises.
    """

    metadata: ClassVar[dict] = {"render_modes": []}

    def __init__(
        self,
        source: SourceLike,
        n_drones: int | None = None,
        params: ScoreParams | None = None,
        starts: np.ndarray | None = None,
        infeasible: Literal["raise", "stay"] = "raise",
        state: str = DEFAULT_STATE,
    ) -> None:
        if infeasible not in ("raise", "stay"):
            raise EnvInputError(f'infeasible = {infeasible!r}: use "raise" or "stay"')
        self.swarm_env = SwarmParallelEnv(source, n_drones, params, starts, state)
        n = self.swarm_env.n_drones
        self.infeasible = infeasible
        self.action_space = spaces.MultiDiscrete([N_ACTIONS] * n)
        size = self.swarm_env.variant.size
        self.observation_space = spaces.Box(0.0, 1.0, (n, size), np.float32)

    def reset(self, *, seed: int | None = None, options: dict | None = None):
        _check_order(self.swarm_env, "reset()")
        super().reset(
            seed=None if seed is None else _seed(seed)
        )  # np_random from seed: the stream of default_rng(seed)
        self.swarm_env._restart(self.np_random)
        return self.swarm_env._states(), self._info()

    def step(self, action):
        env = self.swarm_env
        _check_order(env, "step()")
        action = _joint_action(action, env.n_drones)
        if self.infeasible == "stay" and env.swarm is not None and action.shape == (env.n_drones,):
            ok = env.swarm.feasible[np.arange(env.n_drones), action]
            action = np.where(ok, action, 0)
        try:
            out = env._advance(action)
        except InfeasibleActionError as error:  # a MultiDiscrete sample can be one
            raise InfeasibleActionError(
                f"{error}; choose among info['action_mask'], or make the env with "
                'infeasible="stay" (for algorithms that cannot mask actions, and for '
                "Gymnasium's check_env)"
            ) from None
        info = self._info()
        info.update(
            rewards=out.rewards.copy(),
            reward_importance=float(out.importance.sum()),
            reward_idleness=float(out.idleness.sum()),
            reward_paper=float(out.paper.sum()),
        )
        truncated = env.swarm.k >= env.horizon
        return env._states(), float(out.rewards.sum()), False, truncated, info

    def _info(self) -> dict[str, Any]:
        return {"action_mask": self.swarm_env.swarm.feasible.astype(np.int8)}

    def render(self) -> None:
        """Nothing to render (``render_modes`` is empty): a warning and None."""
        _no_render()

    def close(self) -> None:
        self.swarm_env.close()


def _no_render() -> None:
    import warnings

    warnings.warn(
        "twin's environments have no render mode (metadata render_modes = []); to watch a "
        "swarm, run `twin run --gui` or `twin replay --gui` on a run folder",
        UserWarning,
        stacklevel=3,
    )


def _joint_action(action: Any, n: int) -> np.ndarray:
    """The joint action as ``(n,)`` int64, refused (one line) when not ``n`` integers (floats
    such as ``1.0`` are refused, as by the parallel env)."""
    try:
        raw = np.asarray(action)
    except (TypeError, ValueError):
        raw = np.asarray(None)
    if raw.shape != (n,) or not np.issubdtype(raw.dtype, np.integer):
        raise EnvInputError(
            f"action must be {n} whole numbers 0 .. {N_ACTIONS - 1} (one per drone), got "
            f"{raw.dtype} of shape {raw.shape}"
        )
    out = (raw < 0) | (raw >= N_ACTIONS)
    if out.any():
        d = int(np.flatnonzero(out)[0])
        raise EnvInputError(
            f"drone {d}: action {raw[d]} is out of range 0 .. {N_ACTIONS - 1} (0 stay, 1 up, "
            "2 down, 3 left, 4 right)"
        )
    return raw.astype(np.int64)


#: The keywords ``make_env`` passes to the env's constructor (the joint env also takes
#: ``infeasible``).
ENV_OPTIONS = ("n_drones", "params", "starts", "state")


def make_env(
    config: str | Path,
    *,
    tape: str | Path | None = None,
    joint: bool = False,
    **options,
) -> SwarmParallelEnv | SwarmGymEnv:
    """The env of a scenario config (a path, or a shipped config's name such as ``"synthetic"``):
    its traffic (synthetic, live SUMO, or ``tape`` replayed), drone count and reward weights.

    ``joint=True`` gives the Gymnasium joint-swarm env; ``options`` go to the env's constructor.
    """
    from twin.config import load_config, shipped_config
    from twin.experiment import Experiment, build_source, check_memory, is_live, planned_shape

    if not isinstance(config, (str, Path)):
        raise EnvInputError(
            f"make_env({config!r}): give a scenario config's path or a shipped config's name "
            'such as "synthetic"'
        )
    if not isinstance(joint, (bool, np.bool_)):  # "no" would be read as True
        raise EnvInputError(
            f"make_env(joint={joint!r}): give True (the Gymnasium joint-swarm env) or False (the "
            "PettingZoo parallel env)"
        )
    allowed = (*ENV_OPTIONS, "infeasible") if joint else ENV_OPTIONS
    unknown = sorted(set(options) - set(allowed))
    if unknown:
        raise EnvInputError(
            f"make_env({unknown[0]}=...) is not an option"
            + (" of the parallel env" if unknown[0] == "infeasible" else "")
            + "; give "
            + ", ".join(allowed)
            + ", tape or joint"
        )

    if tape is not None and (not isinstance(tape, (str, Path)) or str(tape) == ""):
        raise EnvInputError(
            f"make_env(tape={tape!r}): give a tape.parquet's path, or leave tape out for the "
            "config's own traffic"
        )
    path = Path(config)
    if not path.exists() and path.suffix != ".toml":
        path = shipped_config(f"configs/{config}.toml")
    cfg = load_config(path)
    if cfg.faults.plan().active:  # an env drove every drone as if none were lost
        raise EnvInputError(
            f"{cfg.path}: [faults] scripts lost drones, a coordinator down or missed "
            "sightings, which the environments do not apply (the agent drives every drone, "
            "every step); remove [faults], or score faults with `twin evaluate`"
        )
    experiment = Experiment(cfg, swarms=(), seeds=(0,), tape=None if tape is None else Path(tape))
    if is_live(experiment):

        def source() -> TrafficSource:  # a fresh simulation at every reset
            return build_source(experiment)

    else:
        try:  # the maps an env records, estimated before any is made (as `twin evaluate`)
            check_memory(experiment, *planned_shape(experiment))
        except UserError as exc:
            raise EnvInputError(str(exc)) from None
        source = build_source(experiment)
        if tape is not None:
            try:  # an episode runs every step of the tape's horizon
                source.check_complete("an env")
            except UserError as exc:
                raise EnvInputError(str(exc)) from None
    options.setdefault("params", cfg.params)
    if not isinstance(cfg.swarm.starts, str):
        options.setdefault("starts", cfg.swarm.starts)
    if "starts" not in options:
        options.setdefault("n_drones", cfg.swarm.n_drones)
    return (SwarmGymEnv if joint else SwarmParallelEnv)(source, **options)
