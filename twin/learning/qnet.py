"""The universal Q-function of Sec. III-A, Table 1: one MLP shared by every drone.

``Q(s, .; theta)``: the state values in (13 for the paper's state; the first layer is sized to
the state variant, :mod:`twin.states`), one Q value per action out, in the action order of
:data:`twin.grid.ACTIONS` (network output index = action).
"""

from __future__ import annotations

import itertools
from collections.abc import Sequence

import torch
from torch import nn

from twin.grid import N_ACTIONS
from twin.scores import STATE_SIZE

#: Table 1: 13 -> 2048 -> 1024 -> 256 -> 64 -> 5, ReLU between layers, linear output.
TABLE1_LAYERS: tuple[int, ...] = (STATE_SIZE, 2048, 1024, 256, 64, N_ACTIONS)


class QNetwork(nn.Module):
    """Fully connected ReLU network with a linear output layer; sizes from ``layers`` (the
    first: the state variant's size)."""

    def __init__(self, layers: Sequence[int] = TABLE1_LAYERS) -> None:
        super().__init__()
        layers = tuple(int(n) for n in layers)
        if len(layers) < 2 or min(layers) < 1 or layers[-1] != N_ACTIONS:
            raise ValueError(
                f"layer sizes must run from the state's size to {N_ACTIONS}, got {list(layers)}"
            )
        self.layers = layers
        modules: list[nn.Module] = []
        for n_in, n_out in itertools.pairwise(layers[:-1]):
            modules += [nn.Linear(n_in, n_out), nn.ReLU()]
        modules.append(nn.Linear(layers[-2], layers[-1]))
        self.net = nn.Sequential(*modules)

    def forward(self, states: torch.Tensor) -> torch.Tensor:
        """``(B, state size)`` states -> ``(B, 5)`` Q values."""
        return self.net(states)


def masked_argmax(q: torch.Tensor, feasible: torch.Tensor) -> torch.Tensor:
    """Index of the largest Q value among the feasible actions (``stay`` is always feasible)."""
    return q.masked_fill(~feasible, float("-inf")).argmax(dim=1)


def n_parameters(net: nn.Module) -> int:
    return sum(p.numel() for p in net.parameters())
