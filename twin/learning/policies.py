"""The learned swarms (Sec. III): the pretrained universal Q-function drives every drone.

- ``rl``: central coordination: every drone sends ``q_d = Q(s_d; theta)``, the coordinator
  (:func:`twin.coordinator.coordinate`) picks the joint action with the largest sum of Q and
  all next cells distinct (eq. maxi:op2).
- ``rl-decentralized``: no coordinator: each drone keeps its own idleness map (its own visits
  only) and the last positions it heard of the others, and acts epsilon-greedily on its own
  Q values (eq. eps-greedy).
- ``rl-online``: as ``rl`` (or decentralized with ``decentralized=True``), plus one training
  epoch per step: from the pooled buffers (central) or each drone from its own buffer with its
  own copy of theta (decentralized).

Communication outages (``outages=[(start, stop), ...]``, steps ``start <= k < stop``): while
the coordinator is down, the swarm runs decentralized from the shared map it last had; when it
comes back, the drones' maps merge (each cell takes the smallest idleness any drone holds)
and coordination resumes.

A checkpoint whose state reads the nowcast (``nowcast``, :mod:`twin.states`) needs the run's
history of earlier days (``history``: ``twin run --history FILE`` hands it over); the swarm's
nowcast filter is updated each step on the cells its drones see. It runs with the central
coordinator (``rl``, ``rl-online``); without coordination each drone would need a nowcast of
its own sightings, which it does not keep, so ``decentralized`` and ``outages`` are refused.
"""

from __future__ import annotations

from collections.abc import Sequence
from functools import lru_cache
from pathlib import Path

import numpy as np
import torch

from twin.belief import EXACT_SIGHTINGS, History, SightingModel
from twin.coordinator import coordinate
from twin.errors import UserError
from twin.files import file_sha256, not_a_file
from twin.grid import Grid
from twin.idleness_maps import OwnMaps, SwarmMaps, parse_outages
from twin.learning.checkpoint import checkpoint_state, default_checkpoint, load_qnet
from twin.learning.data import SightedBelief
from twin.learning.online import OnlineLearner
from twin.learning.qnet import QNetwork
from twin.policies import (
    Policy,
    SwarmView,
    Transition,
    flag_option,
    number_option,
    random_feasible,
    whole_option,
)
from twin.states import paper_states, state_variant


@lru_cache(maxsize=4)
def _cached_qnet(path: str, mtime: float) -> tuple[QNetwork, dict]:
    return load_qnet(path)


def shared_qnet(checkpoint: str | Path | None) -> tuple[QNetwork, dict]:
    """Load (once per file version) the network of ``checkpoint``, the shipped one by default."""
    path = Path(checkpoint) if checkpoint is not None else default_checkpoint()
    why = not_a_file(path)
    if why is not None:
        raise UserError(f"checkpoint {path} {why}; run `twin pretrain` or pass checkpoint=<file>")
    return _cached_qnet(str(path.resolve()), path.stat().st_mtime)


def local_drone_states(
    grid: Grid, maps: OwnMaps | np.ndarray, importance: np.ndarray, positions: np.ndarray, others
) -> np.ndarray:
    """:func:`twin.scores.drone_states` with one idleness map per drone: :class:`OwnMaps`
    (read at each drone's view, row and column only) or dense ``(N, nx, ny)``."""
    return paper_states(grid, maps, importance, positions, others)


#: The most steps online learning's replay buffer keeps (each holds every drone's transition,
#: ~120 B per drone: 0.5 GB for 4 drones).
MAX_BUFFER = 1_000_000


class RLPolicy(Policy):
    """A swarm driven by the universal Q-function; see the module docstring for the modes.

    The drones' states are those of the checkpoint's state variant (:mod:`twin.states`,
    ``meta["state"]``; the paper's 13 values for a checkpoint without it).

    Options: ``checkpoint`` (default: the shipped ``data/qnet.pt``), ``state`` (the state
    variant the swarm expects: refused in one line unless it is the checkpoint's), ``history``
    (a :class:`~twin.belief.History` or its file: the nowcast's prior, read only by a
    checkpoint whose state needs it), ``decentralized``
    (never coordinate), ``eps`` (exploration of decentralized drones), ``outages`` (step
    windows without coordinator), ``online`` (learn while patrolling), ``online_iters``
    (gradient steps per step), ``batch_size``, ``gamma``, ``lr``, ``buffer_steps``.
    Inference runs on the threads torch was given by the command (``twin`` sets one).
    """

    name = "rl"

    def __init__(
        self,
        checkpoint: str | Path | None = None,
        state: str | None = None,
        decentralized: bool = False,
        eps: float = 0.1,
        outages: Sequence[Sequence[int]] = (),
        online: bool = False,
        online_iters: int = 1,
        batch_size: int = 32,
        gamma: float = 0.9,
        lr: float = 1e-4,
        buffer_steps: int = 5000,
        history: History | str | Path | None = None,
    ) -> None:
        name = "rl"
        eps = number_option(name, "eps", eps, 0.0, 1.0, 0.05)
        decentralized = flag_option(name, "decentralized", decentralized)
        online = flag_option(name, "online", online)
        learning = {
            "iters": whole_option(name, "online_iters", online_iters, 1, 10_000, 1),
            "batch_size": whole_option(name, "batch_size", batch_size, 1, 1_000_000, 32),
            "gamma": number_option(name, "gamma", gamma, 0.0, 1.0, 0.9),
            "lr": number_option(name, "lr", lr, 0.0, 1.0, 1e-4, low_open=True),
            "buffer_steps": whole_option(name, "buffer_steps", buffer_steps, 1, MAX_BUFFER, 5000),
        }
        self.net, self.meta = shared_qnet(checkpoint)
        self.checkpoint = checkpoint
        path = Path(checkpoint) if checkpoint is not None else default_checkpoint()
        # the file's sha256 as loaded: a file rewritten later is not the network that ran
        self.sha256 = file_sha256(path.resolve())
        self.variant = checkpoint_state(path, self.meta)
        if state is not None and state_variant(state, "swarm option state").name != (
            self.variant.name
        ):
            raise UserError(
                f"checkpoint {path} reads state {self.variant.name!r}, not {state!r} (swarm "
                f"option state); give a checkpoint pretrained with state = {state!r} or drop "
                "the option"
            )
        self.decentralized = decentralized
        self.eps = eps
        self.outages = parse_outages(outages, self.name)
        self.history = None
        self.sighting = EXACT_SIGHTINGS
        if self.variant.needs_belief:
            name = self.variant.name
            if history is None:
                raise UserError(
                    f"checkpoint {path} reads state {name!r}, the nowcast of a history of "
                    "earlier days: give --history FILE (`twin history`) or the swarm option "
                    "history"
                )
            if self.decentralized or self.outages:
                raise UserError(
                    f"checkpoint {path} reads state {name!r}, the swarm's shared nowcast: it "
                    "runs with the coordinator only; drop decentralized and outages (or use rl)"
                )
            self.history = history if isinstance(history, History) else History.load(history)
        self.online = online
        self.learning = learning

    def describe(self) -> dict:
        """What a run folder records about this swarm (JSON)."""
        path = Path(self.checkpoint) if self.checkpoint is not None else default_checkpoint()
        return {
            "checkpoint": str(path),
            "sha256": self.sha256,
            "trained_epochs": self.meta.get("epoch"),
            "layers": self.meta.get("layers"),
            "state": self.variant.name,
            **(
                {
                    "history_runs": self.history.n_runs,
                    "history_seeds": list(self.history.traffic_seeds),
                }
                if self.history is not None
                else {}
            ),
            "coordination": "decentralized" if self.decentralized else "central",
            "eps": self.eps if self.decentralized or self.outages else None,
            "outages": [list(w) for w in self.outages],
            "online": self.online,
        }

    def use_sighting_model(self, sighting: SightingModel) -> None:
        """How the run's sightings are made (the experiment hands its traffic source's): the
        nowcast filter's measurement variance."""
        self.sighting = sighting

    def reset(self, grid: Grid, n_drones: int, rng: np.random.Generator) -> None:
        super().reset(grid, n_drones, rng)
        if self.history is not None and self.outages:  # set by [faults] coordinator_down
            raise UserError(
                f"swarm {self.name}: checkpoint {self.checkpoint} reads state "
                f"{self.variant.name!r}, the swarm's shared nowcast, which runs with the "
                "coordinator only; drop [faults] coordinator_down for this swarm"
            )
        self.maps = SwarmMaps(n_drones, self.decentralized, self.outages)
        self.states = None
        self.belief = self.seen = None
        if self.history is not None:
            h = self.history
            h.check_grid(h.named(self.name), grid.obstacles)
            self.belief = SightedBelief(h, grid, self.sighting)
        self.learner = None
        if self.online:
            self.learner = OnlineLearner(
                self.net,
                n_drones,
                per_drone=self.decentralized,
                rng=np.random.default_rng(rng.integers(2**63)),
                **self.learning,
            )

    @property
    def nets(self):
        return self.learner.nets if self.learner is not None else [self.net]

    def drones_changed(self, before: np.ndarray, after: np.ndarray) -> None:
        """A drone lost or back (:mod:`twin.faults`): the maps, the positions heard and the
        online learner's buffer are rebuilt for the live drones at the next step; own maps held
        during an outage are pooled (merged, then copied to each live drone); the learner's
        network and optimizer are kept."""
        super().drones_changed(before, after)
        n = self.n_drones
        if self.maps.own is not None:
            self.maps.own = OwnMaps(self.maps.own.merged(), n)
        self.maps.n_drones = n
        self.regroup = True
        if self.learner is not None:
            old = self.learner
            self.learner = OnlineLearner(self.net, n, per_drone=self.decentralized, rng=old.rng,
                                         **self.learning)  # fmt: skip
            if len(old.nets) == 1:
                self.learner.nets, self.learner.targets = old.nets, old.targets
                self.learner.optimizers, self.learner.updates = old.optimizers, old.updates

    def observe(self, view: SwarmView) -> np.ndarray:
        """The ``(N, size)`` states of the drones at ``view.k`` (advances the maps)."""
        maps = self.maps
        if getattr(self, "regroup", False):
            maps.heard = view.positions.copy()
            self.regroup = False
        maps.advance(view.k, view.positions, view.idleness, view.grid, view.params,
                     view.recorded_visits())  # fmt: skip
        if self.belief is not None:
            self.history.check_horizon(self.history.named(self.name), view.horizon)
            self.seen = self.belief.at(view.k, view.positions, view.importance)
        return self.local_states(view)

    def local_states(self, view: SwarmView) -> np.ndarray:
        """The states of the drones at ``view.k`` from the maps as they stand."""
        maps = self.maps
        if maps.own is None:
            return self.variant.states(view.grid, maps.shared, view.importance, view.positions,
                                       belief=self.seen)  # fmt: skip
        return self.variant.states(
            view.grid, maps.own, view.importance, view.positions,
            maps.others_centre_of_mass(view.positions),
        )  # fmt: skip

    def q_values(self, states: np.ndarray) -> np.ndarray:
        s = torch.from_numpy(states.astype(np.float32))
        nets = self.nets
        with torch.inference_mode():
            if len(nets) == 1:
                return nets[0](s).double().numpy()
            return (
                torch.stack([net(s[d : d + 1])[0] for d, net in enumerate(nets)]).double().numpy()
            )

    def act(self, view: SwarmView) -> np.ndarray:
        if view.k != self.maps.k:  # (online learning has already observed this step in learn())
            if view.k != self.maps.k + 1:
                raise RuntimeError(f"swarm {self.name} saw step {view.k} after step {self.maps.k}")
            self.states = self.observe(view)
        elif getattr(self, "regroup", False):  # the live drones changed since learn() observed
            self.maps.heard = view.positions.copy()
            self.regroup = False
            self.states = self.local_states(view)
        q = self.q_values(self.states)
        if self.maps.own is None:
            return coordinate(q, view.positions, view.feasible, view.grid)
        best = np.argmax(np.where(view.feasible, q, -np.inf), axis=1)
        explore = self.rng.random(self.n_drones) < self.eps
        return np.where(explore, random_feasible(view.feasible, self.rng), best)

    def learn(self, transition: Transition) -> None:
        if self.learner is None:
            return
        nv = transition.next_view
        states = self.states
        self.states = self.observe(nv)  # as the drones see it; act() at the next step reuses it
        self.learner.step(states, transition.actions, transition.rewards, self.states,
                          nv.feasible)  # fmt: skip


def build_learned_swarm(name: str, **options) -> RLPolicy:
    """The learned swarms of :data:`twin.swarms.SWARMS` by name."""
    defaults = {
        "rl": {},
        "rl-decentralized": {"decentralized": True},
        "rl-online": {"online": True},
    }
    try:
        policy = RLPolicy(**{**defaults[name], **options})
    except UserError as exc:  # an option refused: said of the swarm asked for
        text = str(exc)
        if not text.startswith(f"{RLPolicy.name}: "):
            raise
        raise UserError(f"{name}: {text.removeprefix(f'{RLPolicy.name}: ')}") from None
    policy.name = name
    return policy
