"""The Double DQN update (Sec. III-A), in one place for pretraining and online learning.

``Y = r + gamma Q(s', argmax_{u' in U(s')} Q(s', u'; theta); theta_-)`` with the argmax over the
feasible actions of the next state only, and ``L = mean (Y - Q(s, u; theta))^2``.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import nn

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
    linears = [m for m in net.net if isinstance(m, nn.Linear)]
    for _ in range(iters):
        loss, q = gradient(linears, s, a, y)
        optimizer.step()
    return loss, q.mean()


@torch.no_grad()
def gradient(linears: list[nn.Linear], s, a, y) -> tuple[torch.Tensor, torch.Tensor]:
    """``dL/dtheta`` of ``L = mean (Y - Q(s, a; theta))^2`` into the parameters' ``.grad``,
    written in place (no allocation of the weight-sized gradients); returns ``L`` and
    ``Q(s, a)``. The same kernels autograd runs for ``QNetwork``'s ``addmm``/``relu`` layers,
    ``gather`` and ``mse_loss``, in the same order, so the gradients are bit for bit the same
    as ``loss.backward()``'s (``tests/test_learning_components.py``)."""
    hidden, x = [s], s
    for i, lin in enumerate(linears):
        z = torch.addmm(lin.bias, x, lin.weight.t())
        if i < len(linears) - 1:
            x = torch.relu(z)
            hidden.append(x)
    q = z.gather(1, a).squeeze(1)
    loss = F.mse_loss(q, y)
    # mse_loss backward: 2 / n (q - y); gather backward: scattered into zeros
    dz = torch.zeros_like(z).scatter_(1, a, ((q - y) * (2 / q.numel()))[:, None])
    for i in reversed(range(len(linears))):
        lin = linears[i]
        for p in (lin.weight, lin.bias):
            if p.grad is None:
                p.grad = torch.empty_like(p)
        torch.mm(dz.t(), hidden[i], out=lin.weight.grad)
        torch.sum(dz, 0, out=lin.bias.grad)
        if i > 0:
            dz = torch.ops.aten.threshold_backward(dz.mm(lin.weight), hidden[i], 0)
    return loss, q


def sync_target(net: QNetwork, target: QNetwork) -> None:
    """Hard update of the target network: ``theta_- <- theta``."""
    target.load_state_dict(net.state_dict())
