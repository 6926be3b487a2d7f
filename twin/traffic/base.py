"""The traffic-source interface that the patrol loop reads ``T^k`` from.

A source owns the grid it is defined on and yields the importance map of each step, ``T^0``
to ``T^horizon`` (``horizon + 1`` maps: step ``k`` needs ``T^k`` and ``T^{k+1}``). The maps are
yielded in order, so that a live simulation can advance in lockstep with the swarms. Beside
the maps, the interface declares (with defaults) all that the loop and the experiment runner
read of a source: its stage timings and own process, incidents, truth, files for the run folder.
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from collections.abc import Generator, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from twin.grid import Grid
from twin.timing import WAITING_FOR_SOURCE, StageTimer


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
    #: Simulated as the maps are pulled, once per seed, its tape kept (memory estimates).
    live: bool = False
    #: The source's own stages (a simulation's stepping, reads ...), when it times them.
    timer: StageTimer | None = None
    #: The maps are computed in a process of their own, ahead of the loop, which waits for them.
    separate_process: bool = False
    #: The loop's stage while it waits for a source in its own process.
    waiting_stage: str = WAITING_FOR_SOURCE
    #: The name of that process in ``timing.csv``.
    process_name: str = "traffic source"
    #: That process's peak resident memory (MB), as it measured itself when it ended.
    process_peak_mb: float | None = None

    @abstractmethod
    def importance_maps(self) -> Generator[np.ndarray, None, None]:
        """Yield ``horizon + 1`` arrays of shape ``grid.shape``, values in [0, 1]. The loop
        closes the generator when its pass ends (a live simulation stops there)."""

    def metadata(self) -> dict[str, Any]:
        """What a run folder should record about this source (JSON-serialisable)."""
        return {"kind": type(self).__name__, "horizon": self.horizon}

    def detector_observations(self):
        """What fixed detectors read over the run (a :class:`twin.belief.DetectorObservations`);
        ``None`` (the default): the source has no detectors."""
        return None

    def sighting_model(self):
        """How a drone's sighting of this source's maps is made (a
        :class:`twin.belief.SightingModel`, the nowcast's measurement variance); by default the
        drones read the map exactly."""
        from twin.belief import EXACT_SIGHTINGS

        return EXACT_SIGHTINGS

    def truth_map(self) -> np.ndarray | None:
        """The true ``T^k`` of the map last yielded, when the source observes traffic through a
        model that may err and knows the truth; ``None`` (the default): no separate truth."""
        return None

    def clock(self, k: int) -> str | None:
        """A label for step ``k`` in progress bars (a live simulation gives its clock time)."""
        return None

    def process_stages(self) -> dict[str, dict[str, float]]:
        """The stages of the source's own process, run beside the loop, keyed by
        :attr:`process_name`; empty when the maps were computed in the loop's process."""
        if self.separate_process and self.timer is not None:
            return {self.process_name: self.timer.as_dict()}
        return {}

    def incidents_info(self) -> list[dict[str, Any]]:
        """Scheduled incidents as applied so far (scored by monitoring); none by default."""
        return []

    def warmup_steps(self) -> int:
        """Steps simulated before ``T^0`` and kept with the run (memory estimates); 0 here."""
        return 0

    def coarser_hint(self, ratio: float) -> str | None:
        """How to make the grid ``ratio`` times coarser per side in this source's own settings,
        for a run refused for its memory; None: no such setting."""
        return None

    def write_extras(self, run_dir: Path, by_seed: Sequence[tuple[int, TrafficSource]]) -> None:
        """Write the source's own files into the run folder, before ``run.json``: called on the
        first seed's source with ``(seed, source)`` of every seed run; nothing by default."""

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

    def importance_maps(self) -> Generator[np.ndarray, None, None]:
        yield from self.maps

    def metadata(self) -> dict[str, Any]:
        return {"horizon": self.horizon, **self._metadata}
