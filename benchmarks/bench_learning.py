"""Pretraining speed of the Table 1 Q-network, against a plain loop and the matmul ceiling.

Measured in one process, on the same thread count:
- ``plain``: a reference update as a single-file DQN writes it: every gradient step computes
  its Double DQN target, default ``torch.optim.Adam``, no tricks;
- ``ours``: :func:`twin.learning.pretrain.train_epoch` (fused Adam; the target once per epoch),
  for the shipped schedule (N_iter = 1) and the paper's (N_iter = 30);
- ``ceiling``: a large dense fp32 matmul and one of the update's own shape (32 x 2048 x 1024),
  in GFLOP/s; the fraction of the ceiling is the update's FLOP rate over the large matmul's.

Prints updates/s, the ratio ours / plain, GFLOP/s and the projected wall time of the paper's
schedule (30000 epochs x 30 updates, batch 32). First checks that ours with one update per
epoch and the plain loop reach the same weights from the same start (exit 1 otherwise).
``--quick`` uses a small network and short timings.

    python benchmarks/bench_learning.py [--quick] [--threads 1] [--seconds 10]
"""

from __future__ import annotations

import argparse
import itertools
import sys
import time

import numpy as np
import torch
import torch.nn.functional as F

from twin.learning.pretrain import make_optimizer, train_epoch
from twin.learning.qnet import TABLE1_LAYERS, QNetwork, masked_argmax
from twin.learning.replay import ReplayBuffer

BATCH = 32
PAPER_UPDATES = 30000 * 30


def synthetic_buffer(rng: np.random.Generator, steps: int = 5000) -> ReplayBuffer:
    buffer = ReplayBuffer(steps, 4)
    feasible = rng.random((steps, 4, 5)) < 0.8
    feasible[..., 0] = True
    buffer.add_steps(rng.random((steps, 4, 13), dtype=np.float32), rng.integers(0, 5, (steps, 4)),
                     rng.random((steps, 4), dtype=np.float32),
                     rng.random((steps, 4, 13), dtype=np.float32), feasible)  # fmt: skip
    return buffer


def plain_update(net, target, optimizer, batch, gamma=0.9):
    """One gradient step as a single-file DQN writes it."""
    s = torch.tensor(batch.states)
    a = torch.tensor(batch.actions)
    r = torch.tensor(batch.rewards)
    s1 = torch.tensor(batch.next_states)
    f1 = torch.tensor(batch.next_feasible)
    with torch.no_grad():
        best = masked_argmax(net(s1), f1)
        y = r + gamma * target(s1).gather(1, best[:, None]).squeeze(1)
    q = net(s).gather(1, a[:, None]).squeeze(1)
    loss = F.mse_loss(q, y)
    optimizer.zero_grad()
    loss.backward()
    optimizer.step()


def updates_disagree(layers, buffer: ReplayBuffer, epochs: int = 5) -> str:
    """With one update per epoch, ours (fused Adam, target per epoch) and the plain loop are
    the same algorithm: from the same weights and batches they must reach the same weights."""
    torch.manual_seed(1)
    start, start_target = QNetwork(layers), QNetwork(layers)
    nets = []
    for fused in (False, True):
        net, target = QNetwork(layers), QNetwork(layers)
        net.load_state_dict(start.state_dict())
        target.load_state_dict(start_target.state_dict())
        nets.append((net, target, make_optimizer(net, 1e-3, fused)))
    batches = [buffer.sample(BATCH, np.random.default_rng([7, e])) for e in range(epochs)]
    for batch in batches:
        plain_update(*nets[0], batch)
        train_epoch(*nets[1], batch, 0.9, 1)
    for (name, a), b in zip(nets[0][0].named_parameters(), nets[1][0].parameters(), strict=True):
        if not torch.allclose(a, b, rtol=1e-4, atol=1e-6):
            return f"{name} after {epochs} updates (max difference {(a - b).abs().max():.2e})"
    return ""


def updates_per_second(step, updates_per_call: int, seconds: float) -> float:
    step()  # warm-up
    n, t0 = 0, time.perf_counter()
    while time.perf_counter() - t0 < seconds:
        step()
        n += updates_per_call
    return n / (time.perf_counter() - t0)


def matmul_gflops(m: int, k: int, n: int, seconds: float) -> float:
    a, b = torch.randn(m, k), torch.randn(k, n)
    torch.mm(a, b)
    reps, t0 = 0, time.perf_counter()
    while time.perf_counter() - t0 < seconds:
        torch.mm(a, b)
        reps += 1
    return 2.0 * m * k * n * reps / (time.perf_counter() - t0) / 1e9


def flops_per_update(layers, iters: int) -> float:
    """Forward + backward (3 matmuls per layer) per step, plus the target's two forward
    passes once per epoch."""
    macs = sum(a * b for a, b in itertools.pairwise(layers))
    return 2 * BATCH * macs * (3 + 2 / iters)


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    p.add_argument("--quick", action="store_true", help="small network, short timings")
    p.add_argument("--threads", type=int, default=1)
    p.add_argument("--seconds", type=float, default=None, help="seconds per measurement")
    args = p.parse_args()
    torch.set_num_threads(args.threads)
    torch.manual_seed(0)
    seconds = args.seconds or (0.5 if args.quick else 10.0)
    layers = [13, 256, 128, 5] if args.quick else list(TABLE1_LAYERS)
    rng = np.random.default_rng(0)
    buffer = synthetic_buffer(rng)
    disagree = updates_disagree(layers, buffer)
    if disagree:
        sys.exit(f"bench_learning: ours and the plain loop disagree: {disagree}")

    def fresh(fused: bool):
        net, target = QNetwork(layers), QNetwork(layers)
        return net, target, make_optimizer(net, 1e-4, fused)

    net, target, opt = fresh(False)
    plain = updates_per_second(
        lambda: plain_update(net, target, opt, buffer.sample(BATCH, rng)), 1, seconds
    )
    rows = [("plain loop (default Adam, target every step)", 1, plain)]
    for iters in (1, 30):
        net, target, opt = fresh(True)
        rate = updates_per_second(
            lambda: train_epoch(net, target, opt, buffer.sample(BATCH, rng), 0.9, iters),  # noqa: B023
            iters, seconds,
        )  # fmt: skip
        rows.append((f"ours (fused Adam), N_iter = {iters}", iters, rate))
    big = matmul_gflops(2048, 2048, 2048, seconds)
    own = matmul_gflops(BATCH, 2048, 1024, seconds)

    print(f"Table 1 network {layers}, batch {BATCH}, {args.threads} thread(s)")
    print(f"dense fp32 matmul: 2048^3 {big:.1f} GFLOP/s; 32 x 2048 x 1024 {own:.1f} GFLOP/s")
    print(f"{'loop':48s} {'updates/s':>10s} {'x plain':>8s} {'GFLOP/s':>8s} {'of ceiling':>10s}")
    for name, iters, rate in rows:
        gflops = rate * flops_per_update(layers, iters) / 1e9
        print(f"{name:48s} {rate:10.1f} {rate / plain:8.2f} {gflops:8.1f} {gflops / big:10.1%}")
    paper = rows[2][2]
    print(f"paper schedule (30000 x 30 = {PAPER_UPDATES} updates): ours "
          f"{PAPER_UPDATES / paper / 3600:.2f} h, plain {PAPER_UPDATES / plain / 3600:.2f} h")  # fmt: skip


if __name__ == "__main__":
    main()
