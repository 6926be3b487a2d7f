"""Pretraining speed of the Table 1 Q-network: the Double DQN update's share of the dense rate
of its own layer shapes, beside a plain loop.

Measured in one process, on the same thread count (``--threads``, default 2), in ``--rounds``
interleaved rounds (each implementation and the plain matmuls timed in every round, call by
call; the medians of the per-call times are reported):

- ``plain``: a reference update as a single-file DQN writes it: every gradient step computes
  its Double DQN target, default ``torch.optim.Adam``, no tricks;
- ``ours``: :func:`twin.training.pretrain.train_epoch` (fused Adam; the target once per epoch),
  for the shipped schedule (N_iter = 1) and the paper's (N_iter = 30);
- ``own shapes``: the matmuls the update itself needs, timed as plain ``torch.mm`` calls of
  the same shapes on random data: for each layer ``n_in -> n_out`` at batch 32 the forward
  ``(32, n_in) @ (n_in, n_out)``, the weight gradient ``(n_out, 32) @ (32, n_in)`` and, for
  every layer but the first (the states need no gradient), the input gradient
  ``(32, n_out) @ (n_out, n_in)``; each set called back to back (warm caches), as a dense
  rate is measured, while the update's own matmuls find the weights after Adam's pass.

The share of an update is ``T_dense / T_update``: ``T_dense`` is the time those plain matmuls
take for one gradient step (forward + both gradients) plus ``2 / N_iter`` forward passes (the
online and target networks on the next states, once per epoch), ``T_update`` the measured time
per gradient step. It equals the update's FLOP rate over the dense FLOP rate of the same
matmuls. The remainder is what is not a matmul: Adam, bias and ReLU passes, the loss, the
allocator and Python.

Float32 subnormals are flushed to zero for every loop alike, as ``twin pretrain`` does
(``--keep-subnormals`` keeps them). On a machine shared with other jobs the share on 2 threads
follows their load: every parallel region of the update waits for the second thread.

Prints updates/s, the ratio ours / plain, GFLOP/s, the share, and the projected wall time of
the paper's schedule (30000 epochs x 30 updates, batch 32). First checks that ours with one
update per epoch and the plain loop reach the same weights from the same start (exit 1
otherwise). ``--quick`` uses a small network and short timings.

    python benchmarks/bench_learning.py [--quick] [--threads 2] [--rounds 10] [--seconds 10]
"""

from __future__ import annotations

import argparse
import itertools
import sys
import time

import numpy as np
import torch
import torch.nn.functional as F

from twin.learning.qnet import TABLE1_LAYERS, QNetwork, masked_argmax
from twin.learning.replay import ReplayBuffer
from twin.training.pretrain import flush_subnormals, make_optimizer, train_epoch

BATCH = 32
PAPER_UPDATES = 30000 * 30


def synthetic_buffer(rng: np.random.Generator, steps: int = 5000) -> ReplayBuffer:
    buffer = ReplayBuffer(steps, 4, state_size=13)
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


def own_shape_matmuls(layers) -> tuple[list, list]:
    """The plain matmuls of one gradient step at batch 32, in nn.Linear's layouts (weights
    ``(n_out, n_in)`` row-major), into preallocated outputs: the forward ones, and the
    backward ones (weight gradients, and input gradients for all layers but the first)."""
    forward, backward = [], []
    for i, (n_in, n_out) in enumerate(itertools.pairwise(layers)):
        w, x, dz = torch.randn(n_out, n_in), torch.randn(BATCH, n_in), torch.randn(BATCH, n_out)
        z, dw, dx = torch.empty(BATCH, n_out), torch.empty(n_out, n_in), torch.empty(BATCH, n_in)
        forward.append(lambda x=x, w=w, z=z: torch.mm(x, w.t(), out=z))
        backward.append(lambda dz=dz, x=x, dw=dw: torch.mm(dz.t(), x, out=dw))
        if i > 0:
            backward.append(lambda dz=dz, w=w, dx=dx: torch.mm(dz, w, out=dx))
    return forward, backward


def call_seconds(call) -> float:
    t0 = time.perf_counter()
    call()
    return time.perf_counter() - t0


def matmul_flops(layers, iters: int) -> float:
    """FLOPs of the matmuls per gradient step: forward, weight gradient and input gradient
    (none for the first layer), plus the two forward passes of the target once per epoch."""
    macs = [a * b for a, b in itertools.pairwise(layers)]
    forward = 2 * BATCH * sum(macs)
    backward = 2 * BATCH * (2 * sum(macs) - macs[0])
    return forward * (1 + 2 / iters) + backward


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    p.add_argument("--quick", action="store_true", help="small network, short timings")
    p.add_argument("--threads", type=int, default=2)
    p.add_argument("--seconds", type=float, default=None, help="seconds per implementation")
    p.add_argument("--keep-subnormals", action="store_true", help="no flush_subnormals()")
    p.add_argument("--rounds", type=int, default=None, help="interleaved rounds (default 10)")
    args = p.parse_args()
    if not args.keep_subnormals:
        flush_subnormals()  # as twin pretrain does, for every loop alike; before the threads start
    torch.set_num_threads(args.threads)
    torch.manual_seed(0)
    seconds = args.seconds or (0.5 if args.quick else 10.0)
    rounds = args.rounds or (2 if args.quick else 10)
    layers = [13, 256, 128, 5] if args.quick else list(TABLE1_LAYERS)
    rng = np.random.default_rng(0)
    buffer = synthetic_buffer(rng)
    disagree = updates_disagree(layers, buffer)
    if disagree:
        sys.exit(f"bench_learning: ours and the plain loop disagree: {disagree}")

    def fresh(fused: bool):
        net, target = QNetwork(layers), QNetwork(layers)
        return net, target, make_optimizer(net, 1e-4, fused)

    plain_net = fresh(False)
    ours = {iters: fresh(True) for iters in (1, 30)}
    forward, backward = own_shape_matmuls(layers)
    steps = {
        "plain": (lambda: plain_update(*plain_net, buffer.sample(BATCH, rng)), 1),
        **{
            iters: (lambda i=iters: train_epoch(*ours[i], buffer.sample(BATCH, rng), 0.9, i), iters)
            for iters in ours
        },
    }
    for step, _ in steps.values():  # warm-up
        step()
    # Interleaved rounds: in each, every implementation and the plain matmuls (each set of them
    # called back to back, so warm, as a dense rate is measured) for seconds / rounds; the
    # medians of the per-call times over all rounds.
    times: dict = {name: [] for name in (*steps, "forward", "backward")}
    calls = {name: (step, per_call) for name, (step, per_call) in steps.items()}
    calls["forward"] = (lambda: [c() for c in forward], 1)
    calls["backward"] = (lambda: [c() for c in backward], 1)
    for _ in range(rounds):
        for name, (call, per_call) in calls.items():
            t_end = time.perf_counter() + seconds / rounds
            while True:
                times[name].append(call_seconds(call) / per_call)
                if time.perf_counter() > t_end:
                    break
    med = {name: float(np.median(t)) for name, t in times.items()}

    def dense_seconds(iters: int) -> float:
        return med["forward"] * (1 + 2 / iters) + med["backward"]

    print(f"Table 1 network {layers}, batch {BATCH}, {args.threads} thread(s), "
          f"{rounds} interleaved rounds of {seconds / rounds:.2g} s each, medians per call")  # fmt: skip
    print(f"own layer shapes as plain matmuls: "
          f"{matmul_flops(layers, 10**9) / dense_seconds(10**9) / 1e9:.1f} GFLOP/s (forward "
          f"{med['forward'] * 1e3:.2f} ms, gradients {med['backward'] * 1e3:.2f} ms per step)")  # fmt: skip
    print(f"{'loop':44s} {'updates/s':>10s} {'x plain':>8s} {'GFLOP/s':>8s} {'of own shapes':>14s}")
    rows = [("plain loop (default Adam, target every step)", "plain", 1)]
    rows += [(f"ours (fused Adam), N_iter = {i}", i, i) for i in ours]
    for label, name, iters in rows:
        rate = 1 / med[name]
        gflops = rate * matmul_flops(layers, iters) / 1e9
        print(f"{label:44s} {rate:10.1f} {med['plain'] / med[name]:8.2f} {gflops:8.1f} "
              f"{dense_seconds(iters) / med[name]:14.1%}")  # fmt: skip
    print(f"paper schedule (30000 x 30 = {PAPER_UPDATES} updates): ours "
          f"{PAPER_UPDATES * med[30] / 3600:.2f} h, plain {PAPER_UPDATES * med['plain'] / 3600:.2f} h")  # fmt: skip


if __name__ == "__main__":
    main()
