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
"""

from __future__ import annotations

import copy
from collections.abc import Sequence
from functools import lru_cache
from pathlib import Path

import numpy as np
import torch

from twin.coordinator import coordinate
from twin.errors import UserError
from twin.grid import Grid
from twin.learning.checkpoint import default_checkpoint, load_qnet
from twin.learning.qnet import QNetwork
from twin.learning.replay import ReplayBuffer
from twin.policies import Policy, SwarmView, Transition, random_feasible, register_policy
from twin.scores import drone_states, update_idleness


@lru_cache(maxsize=4)
def _cached_qnet(path: str, mtime: float) -> tuple[QNetwork, dict]:
    return load_qnet(path)


@lru_cache(maxsize=8)
def _file_sha256(path: str, mtime: float) -> str:
    import hashlib

    with open(path, "rb") as f:
        return hashlib.sha256(f.read()).hexdigest()


def shared_qnet(checkpoint: str | Path | None) -> tuple[QNetwork, dict]:
    """Load (once per file version) the network of ``checkpoint``, the shipped one by default."""
    path = Path(checkpoint) if checkpoint is not None else default_checkpoint()
    if not path.is_file():
        raise UserError(
            f"checkpoint {path} does not exist; run `twin pretrain` or pass checkpoint=<file>"
        )
    return _cached_qnet(str(path.resolve()), path.stat().st_mtime)


def local_drone_states(
    grid: Grid, maps: np.ndarray, importance: np.ndarray, positions: np.ndarray, others
) -> np.ndarray:
    """:func:`twin.scores.drone_states` with one idleness map per drone (``(N, nx, ny)``)."""
    return drone_states(grid, maps, importance, positions, others)


def _parse_outages(outages) -> list[tuple[int, int]]:
    windows = []
    for w in outages or ():
        try:
            start, stop = (int(x) for x in w)
        except (TypeError, ValueError):
            raise UserError(
                f"outage window {w!r} must be a pair [start, stop] of step numbers"
            ) from None
        if not 0 <= start < stop:
            raise UserError(f"outage window {w!r} needs 0 <= start < stop")
        windows.append((start, stop))
    return windows


class RLPolicy(Policy):
    """A swarm driven by the universal Q-function; see the module docstring for the modes.

    Options: ``checkpoint`` (default: the shipped ``data/qnet.pt``), ``decentralized``
    (never coordinate), ``eps`` (exploration of decentralized drones), ``outages`` (step
    windows without coordinator), ``online`` (learn while patrolling), ``online_iters``
    (gradient steps per step), ``batch_size``, ``gamma``, ``lr``, ``buffer_steps``.
    """

    name = "rl"

    def __init__(
        self,
        checkpoint: str | Path | None = None,
        decentralized: bool = False,
        eps: float = 0.1,
        outages: Sequence[Sequence[int]] = (),
        online: bool = False,
        online_iters: int = 1,
        batch_size: int = 32,
        gamma: float = 0.9,
        lr: float = 1e-4,
        buffer_steps: int = 5000,
    ) -> None:
        if not 0.0 <= eps <= 1.0:
            raise UserError(f"eps must lie in [0, 1], got {eps}")
        # a swarm's states are a handful of rows: one thread is fastest and leaves the other
        # cores to the simulation and to other work (several threads oversubscribe them)
        torch.set_num_threads(1)
        self.net, self.meta = shared_qnet(checkpoint)
        self.checkpoint = checkpoint
        self.decentralized = bool(decentralized)
        self.eps = float(eps)
        self.outages = _parse_outages(outages)
        self.online = bool(online)
        self.online_iters = int(online_iters)
        self.batch_size, self.gamma, self.lr = int(batch_size), float(gamma), float(lr)
        self.buffer_steps = int(buffer_steps)

    def describe(self) -> dict:
        """What a run folder records about this swarm (JSON)."""
        path = Path(self.checkpoint) if self.checkpoint is not None else default_checkpoint()
        return {
            "checkpoint": str(path),
            "sha256": _file_sha256(str(path.resolve()), path.stat().st_mtime),
            "trained_epochs": self.meta.get("epoch"),
            "layers": self.meta.get("layers"),
            "coordination": "decentralized" if self.decentralized else "central",
            "eps": self.eps if self.decentralized or self.outages else None,
            "outages": [list(w) for w in self.outages],
            "online": self.online,
        }

    # -- episode state ------------------------------------------------------------------
    def reset(self, grid: Grid, n_drones: int, rng: np.random.Generator) -> None:
        super().reset(grid, n_drones, rng)
        self.swarm_map: np.ndarray | None = None  # the coordinator's map (central mode)
        self.local_maps: np.ndarray | None = None  # (N, nx, ny) while decentralized
        self.heard = None  # (N, 2) last positions heard of every drone
        self.was_central = None
        self.states = None
        self.k = -1
        if self.online:
            self.buffer = ReplayBuffer(self.buffer_steps, n_drones)
            # a private copy of theta per swarm (central) or per drone (decentralized)
            n_nets = n_drones if self.decentralized else 1
            self.nets = [copy.deepcopy(self.net) for _ in range(n_nets)]
            self.targets = [copy.deepcopy(self.net) for _ in range(n_nets)]
            self.optimizers = [torch.optim.Adam(n.parameters(), lr=self.lr) for n in self.nets]
            self.train_rng = np.random.default_rng(rng.integers(2**63))
            self.updates = 0
        else:
            self.nets = [self.net]

    def central(self, k: int) -> bool:
        """Whether the coordinator is reachable at step ``k``."""
        if self.decentralized:
            return False
        return not any(start <= k < stop for start, stop in self.outages)

    def _advance_maps(self, view: SwarmView) -> None:
        """Bring the swarm's / drones' idleness maps to step ``view.k``."""
        grid, p = view.grid, view.params
        central = self.central(view.k)
        if self.k < 0:  # step 0: everyone starts from the shared I^0
            self.swarm_map = view.idleness.copy()
            self.heard = view.positions.copy()
            if not central:
                self.local_maps = np.repeat(view.idleness[None], self.n_drones, axis=0)
        elif central:
            if self.local_maps is not None:  # back from an outage: each cell takes the
                # smallest idleness any drone holds, its own visits of this step included
                self.swarm_map = _local_update(self.local_maps, view.positions, grid, p).min(0)
                self.local_maps = None
            else:
                self.swarm_map = update_idleness(
                    self.swarm_map, view.positions, grid, p.eta, p.delta
                )
        else:
            if self.local_maps is None:  # the coordinator just went down
                self.local_maps = np.repeat(self.swarm_map[None], self.n_drones, axis=0)
            self.local_maps = _local_update(self.local_maps, view.positions, grid, p)
        if central:
            self.heard = view.positions.copy()
        self.k = view.k

    def observe(self, view: SwarmView) -> np.ndarray:
        """The ``(N, 13)`` states of the drones at ``view.k`` (advances the maps)."""
        self._advance_maps(view)
        if self.local_maps is None:
            return drone_states(view.grid, self.swarm_map, view.importance, view.positions)
        # each drone: its own map, the centre of mass of the others' last heard positions
        heard, n = self.heard.astype(np.float64), self.n_drones
        others = (heard.sum(axis=0)[None, :] - heard) / (n - 1) if n > 1 else view.positions * 1.0
        return local_drone_states(
            view.grid, self.local_maps, view.importance, view.positions, others
        )

    def q_values(self, states: np.ndarray) -> np.ndarray:
        s = torch.from_numpy(states.astype(np.float32))
        with torch.inference_mode():
            if len(self.nets) == 1:
                return self.nets[0](s).double().numpy()
            return (
                torch.stack([net(s[d : d + 1])[0] for d, net in enumerate(self.nets)])
                .double()
                .numpy()
            )

    def act(self, view: SwarmView) -> np.ndarray:
        if view.k != self.k:  # (online learning has already observed this step in learn())
            if view.k != self.k + 1:
                raise RuntimeError(f"swarm {self.name} saw step {view.k} after step {self.k}")
            self.states = self.observe(view)
        q = self.q_values(self.states)
        if self.local_maps is None:
            return coordinate(q, view.positions, view.feasible, view.grid)
        best = np.argmax(np.where(view.feasible, q, -np.inf), axis=1)
        explore = self.rng.random(self.n_drones) < self.eps
        return np.where(explore, random_feasible(view.feasible, self.rng), best)

    # -- online learning ----------------------------------------------------------------
    def learn(self, transition: Transition) -> None:
        if not self.online:
            return
        from twin.learning.pretrain import train_epoch

        nv = transition.next_view
        states = self.states
        next_states = self.observe(nv)  # as the drones see it (own maps if decentralized)
        self.buffer.add(states, transition.actions, transition.rewards, next_states, nv.feasible)
        self.states = next_states  # act() at the next step reuses them
        if len(self.buffer) < self.batch_size:
            return
        if len(self.nets) == 1:
            batches = [self.buffer.sample(self.batch_size, self.train_rng)]
        else:
            batches = [self.buffer.sample(self.batch_size, self.train_rng, drone=d)
                       for d in range(self.n_drones)]  # fmt: skip
        for net, target, opt, batch in zip(self.nets, self.targets, self.optimizers, batches,
                                           strict=True):  # fmt: skip
            net.train()
            train_epoch(net, target, opt, batch, self.gamma, self.online_iters)
            net.eval()
        self.updates += 1
        if self.updates % 100 == 0:
            for net, target in zip(self.nets, self.targets, strict=True):
                target.load_state_dict(net.state_dict())


def _local_update(maps: np.ndarray, positions: np.ndarray, grid: Grid, p) -> np.ndarray:
    """Def. 3 on every drone's own map with only its own visit: ``(N, nx, ny)``."""
    new = np.where(grid.free, np.minimum(1.0, maps + p.delta), 0.0)
    d = np.arange(len(positions))
    i, j = positions[:, 0], positions[:, 1]
    new[d, i, j] = p.eta * maps[d, i, j]
    return new


def _rl(**options) -> RLPolicy:
    return RLPolicy(**options)


def _rl_decentralized(**options) -> RLPolicy:
    options.setdefault("decentralized", True)
    policy = RLPolicy(**options)
    policy.name = "rl-decentralized"
    return policy


def _rl_online(**options) -> RLPolicy:
    options.setdefault("online", True)
    policy = RLPolicy(**options)
    policy.name = "rl-online"
    return policy


register_policy("rl", _rl)
register_policy("rl-decentralized", _rl_decentralized)
register_policy("rl-online", _rl_online)
