"""The Double DQN update (Sec. III-A), in one place for pretraining and online learning.

``Y = r + gamma Q(s', argmax_{u' in U(s')} Q(s', u'; theta); theta_-)`` with the argmax over the
feasible actions of the next state only, and ``L = mean (Y - Q(s, u; theta))^2``.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F

from twin.learning.qnet import QNetwork, masked_argmax
from twin.learning.replay import Batch


def make_optimizer(net: QNetwork, lr: float, fused: bool) -> torch.optim.Adam:
    return torch.optim.Adam(net.parameters(), lr=lr, fused=fused or None)


def to_tensors(batch: Batch) -> tuple[torch.Tensor, ...]:
    return (torch.from_numpy(batch.states), torch.from_numpy(batch.actions),
            torch.from_numpy(batch.rewards), torch.from_numpy(batch.next_states),
            torch.from_numpy(batch.next_feasible))  # fmt: skip


def double_dqn_target(net, target, rewards, next_states, next_feasible, gamma):
    """``Y = r + gamma Q(s', argmax_{u' in U(s')} Q(s', u'; theta); theta_-)``."""
    with torch.no_grad():
        best = masked_argmax(net(next_states), next_feasible)
        return rewards + gamma * target(next_states).gather(1, best[:, None]).squeeze(1)


def train_epoch(net, target, optimizer, batch: Batch, gamma: float, iters: int):
    """One epoch: the batch's Double DQN targets, then ``iters`` gradient steps on
    ``L = mean (Y - Q(s, u; theta))^2``. Returns the last loss and mean Q (tensors)."""
    s, a, r, s1, feasible1 = to_tensors(batch)
    y = double_dqn_target(net, target, r, s1, feasible1, gamma)
    a = a[:, None]
    for _ in range(iters):
        q = net(s).gather(1, a).squeeze(1)
        loss = F.mse_loss(q, y)
        optimizer.zero_grad(set_to_none=True)
        loss.backward()
        optimizer.step()
    return loss.detach(), q.detach().mean()


def sync_target(net: QNetwork, target: QNetwork) -> None:
    """Hard update of the target network: ``theta_- <- theta``."""
    target.load_state_dict(net.state_dict())
