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
    """``Y = r + gamma Q(s', argmax_{u' in U(s')} Q(s', u'; theta); theta_-)``; ``gamma`` a
    number, or a ``(B,)`` tensor of per-transition discounts (``gamma^m`` of n-step returns)."""
    with torch.no_grad():
        best = masked_argmax(net(next_states), next_feasible)
        return rewards + gamma * target(next_states).gather(1, best[:, None]).squeeze(1)


def flush_subnormals() -> bool:
    """Float32 values below 1.2e-38 (subnormals) read and written as zero on this thread and the
    threads torch starts after it (call it before the first parallel op). Adam's first moment
    of a weight whose gradient stays zero (a dead ReLU unit) decays by beta1 a step into that
    range, where every operation on it costs about 100 times a normal one: the paper schedule's
    update ran 2.3x slower after 1000 updates. Such a moment moves its weight by at most
    ``lr * 1.2e-38 / eps``, far below a float32 step of any weight, so the weights stay the same
    bit for bit (checked over 990 updates of the paper schedule). Returns False where the CPU
    cannot."""
    return torch.set_flush_denormal(True)


def train_epoch(net, target, optimizer, batch: Batch, gamma: float, iters: int):
    """One epoch: the batch's Double DQN targets, then ``iters`` gradient steps on
    ``L = mean (Y - Q(s, u; theta))^2``. Returns the last loss and mean Q (tensors).
    A batch of n-step transitions bootstraps with its own discounts ``gamma^m``."""
    s, a, r, s1, feasible1 = to_tensors(batch)
    if batch.discounts is not None:
        gamma = torch.from_numpy(batch.discounts)
    y = double_dqn_target(net, target, r, s1, feasible1, gamma)
    a = a[:, None]
    linears = [m for m in net.net if isinstance(m, nn.Linear)]
    for _ in range(iters):
        loss, q = gradient(linears, s, a, y)
        adam_step(optimizer)
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


def adam_step(optimizer: torch.optim.Optimizer) -> None:
    """``optimizer.step()``; for a fused Adam over float32 CPU parameters, from its second step on,
    one ``_fused_adam_`` call over flat buffers that hold the parameters, their gradients and
    both moments (the tensors the network and the optimizer state see are views into them)
    instead of one call per tensor: the same element-wise update, bit for bit, with one
    parallel region instead of one per tensor. The optimizer's state and ``state_dict`` keep
    their per-parameter form; state replaced from outside (``load_state_dict``) is flattened
    anew at the next step."""
    flat = _flat_adam(optimizer)
    if flat is None:
        optimizer.step()
        return
    (group,) = optimizer.param_groups
    params, grads, exp_avgs, exp_avg_sqs, steps = flat
    torch._foreach_add_(steps, 1)
    torch._fused_adam_([params], [grads], [exp_avgs], [exp_avg_sqs], [], [steps[0]],
                       amsgrad=False, lr=group["lr"], beta1=group["betas"][0],
                       beta2=group["betas"][1], weight_decay=group["weight_decay"],
                       eps=group["eps"], maximize=False, grad_scale=None,
                       found_inf=None)  # fmt: skip


def _flat_adam(optimizer) -> tuple | None:
    """The flat buffers of :func:`adam_step`, (re)built when the views are not in place;
    None where the flat step does not apply (then ``optimizer.step()`` runs)."""
    if not isinstance(optimizer, torch.optim.Adam) or len(optimizer.param_groups) != 1:
        return None
    group = optimizer.param_groups[0]
    params = group["params"]
    if (not group["fused"] or group["amsgrad"] or group["maximize"] or group["capturable"]
            or group["differentiable"] or group.get("decoupled_weight_decay")
            or optimizer._optimizer_step_pre_hooks or optimizer._optimizer_step_post_hooks
            or any(p.grad is None or p.dtype != torch.float32 or p.device.type != "cpu"
                   or len(optimizer.state[p]) != 3 for p in params)):  # fmt: skip
        return None  # first step (state not created yet) or not a plain fused Adam
    flat = getattr(optimizer, "_twin_flat", None)
    if flat is not None and _views_in_place(optimizer, params, flat):
        return flat
    steps = [optimizer.state[p]["step"] for p in params]
    if any(not torch.equal(t, steps[0]) for t in steps):
        return None
    n = sum(p.numel() for p in params)
    buffers = [torch.empty(n) for _ in range(4)]  # params, grads, exp_avg, exp_avg_sq
    offset = 0
    with torch.no_grad():
        for p in params:
            state, size = optimizer.state[p], p.numel()
            views = [b[offset : offset + size].view_as(p) for b in buffers]
            for view, src in zip(views, (p, p.grad, state["exp_avg"], state["exp_avg_sq"]),
                                 strict=True):  # fmt: skip
                view.copy_(src)
            p.data, p.grad = views[0], views[1]
            state["exp_avg"], state["exp_avg_sq"] = views[2], views[3]
            offset += size
    optimizer._twin_flat = (*buffers, steps)
    return optimizer._twin_flat


def _views_in_place(optimizer, params, flat) -> bool:
    """Whether every parameter, gradient, moment and step is still the one in ``flat``."""
    offset = 0
    for p, step in zip(params, flat[4], strict=True):
        state = optimizer.state[p]
        if state["step"] is not step:
            return False
        for buffer, t in zip(flat[:4], (p, p.grad, state["exp_avg"], state["exp_avg_sq"]),
                             strict=True):  # fmt: skip
            if t.data_ptr() != buffer.data_ptr() + 4 * offset:
                return False
        offset += p.numel()
    return True


def sync_target(net: QNetwork, target: QNetwork) -> None:
    """Hard update of the target network: ``theta_- <- theta``."""
    target.load_state_dict(net.state_dict())
