"""Online learning while patrolling (Sec. III-C): one Double DQN epoch per swarm step.

Coordinated, the swarm trains one copy of ``theta`` on batches from the pooled buffers
``U_d B_d``; decentralized, every drone trains its own copy on its own buffer ``B_d``.
"""

from __future__ import annotations

import copy

import numpy as np
import torch

from twin.learning.dqn import sync_target, train_epoch
from twin.learning.qnet import QNetwork
from twin.learning.replay import ReplayBuffer


class OnlineLearner:
    """Private copies of the pretrained network, their buffer and their optimizers."""

    def __init__(self, net: QNetwork, n_drones: int, per_drone: bool, rng: np.random.Generator,
                 buffer_steps: int = 5000, batch_size: int = 32, gamma: float = 0.9,
                 lr: float = 1e-4, iters: int = 1, target_every: int = 100) -> None:  # fmt: skip
        n_nets = n_drones if per_drone else 1
        self.nets = [copy.deepcopy(net) for _ in range(n_nets)]
        self.targets = [copy.deepcopy(net) for _ in range(n_nets)]
        self.optimizers = [torch.optim.Adam(n.parameters(), lr=lr) for n in self.nets]
        self.buffer = ReplayBuffer(buffer_steps, n_drones, state_size=net.layers[0])
        self.rng = rng
        self.batch_size, self.gamma, self.iters = batch_size, gamma, iters
        self.target_every = target_every
        self.updates = 0

    def step(self, states, actions, rewards, next_states, next_feasible) -> None:
        """Store the swarm's transitions, then one epoch per network (once a batch fits)."""
        self.buffer.add(states, actions, rewards, next_states, next_feasible)
        if len(self.buffer) < self.batch_size:
            return
        if len(self.nets) == 1:
            batches = [self.buffer.sample(self.batch_size, self.rng)]
        else:
            batches = [self.buffer.sample(self.batch_size, self.rng, drone=d)
                       for d in range(len(self.nets))]  # fmt: skip
        for net, target, opt, batch in zip(self.nets, self.targets, self.optimizers, batches,
                                           strict=True):  # fmt: skip
            net.train()
            train_epoch(net, target, opt, batch, self.gamma, self.iters)
            net.eval()
        self.updates += 1
        if self.updates % self.target_every == 0:
            for net, target in zip(self.nets, self.targets, strict=True):
                sync_target(net, target)
