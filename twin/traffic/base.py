"""The traffic-source interface that the patrol loop reads ``T^k`` from.

A source owns the grid it is defined on and yields the importance map of each step, ``T^0``
to ``T^horizon`` (``horizon + 1`` maps: step ``k`` needs ``T^k`` and ``T^{k+1}``). The maps are
yielded in order, so that a live simulation can advance in lockstep with the swarms.
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from collections.abc import Iterator
from typing import Any

import numpy as np

from twin.grid import Grid


def normalise_importance(z: np.ndarray, grid: Grid, z_lo: float, z_hi: float) -> np.ndarray:
    """Def. 2: ``T = clip((z - z_lo) / (z_hi - z_lo), 0, 1)`` on free cells, 0 on obstacles."""
    span = z_hi - z_lo
    t = np.clip((z - z_lo) / span, 0.0, 1.0) if span > 0 else np.zeros_like(z, dtype=float)
    return np.where(grid.free, t, 0.0)


class TrafficSource(ABC):
    """Yields the importance map of every step on :attr:`grid`."""

    grid: Grid
    horizon: int
    #: A live simulation sets this: a failure mid-run then keeps the steps recorded so far.
    keeps_partial_results: bool = False

    @abstractmethod
    def importance_maps(self) -> Iterator[np.ndarray]:
        """Yield ``horizon + 1`` arrays of shape ``grid.shape``, values in [0, 1]."""

    def metadata(self) -> dict[str, Any]:
        """What a run folder should record about this source (JSON-serialisable)."""
        return {"kind": type(self).__name__, "horizon": self.horizon}

    def truth_map(self) -> np.ndarray | None:
        """The true ``T^k`` of the map last yielded, when the source observes traffic through a
        model that may err and knows the truth; ``None`` (the default): no separate truth."""
        return None

    def clock(self, k: int) -> str | None:
        """A label for step ``k`` in progress bars (a live simulation gives its clock time)."""
        return None

    def close(self) -> None:
        """Release what the source holds (a simulation, files)."""


class RecordedTraffic(TrafficSource):
    """Importance maps held in memory: a synthetic source computed once, or a replayed tape."""

    def __init__(self, grid: Grid, maps: np.ndarray, metadata: dict[str, Any] | None = None):
        maps = np.asarray(maps)
        if maps.ndim != 3 or maps.shape[1:] != grid.shape or len(maps) < 2:
            raise ValueError(f"need (T+1, {grid.nx}, {grid.ny}) maps with T >= 1, got {maps.shape}")
        self.grid = grid
        self.maps = maps
        self.horizon = len(maps) - 1
        self._metadata = dict(metadata or {})

    @classmethod
    def from_source(cls, source: TrafficSource) -> RecordedTraffic:
        maps = np.stack(list(source.importance_maps()))
        return cls(source.grid, maps, source.metadata())

    def importance_maps(self) -> Iterator[np.ndarray]:
        yield from self.maps

    def metadata(self) -> dict[str, Any]:
        return {"horizon": self.horizon, **self._metadata}
