"""Wall time per stage of a run: where a step's time goes (SUMO, reads, each swarm, scoring).

Every run records it (``timing.csv`` in the run folder, a table in the report), so that a stage
that grows faster than the work is seen at once. Stages are accumulated with
:meth:`StageTimer.stage` (a context manager) or :meth:`StageTimer.add`; the order in which stages
first appear is kept, so tables read in the order of the step.
"""

from __future__ import annotations

import time
from collections.abc import Iterator, Mapping
from contextlib import contextmanager

#: Stage names shared by the patrol loop and the traffic sources.
SUMO_WARMUP = "SUMO warm-up (stepping, reads, model)"
SUMO_STEPPING = "SUMO stepping"
READS = "reads and binning"
OBSERVATION = "observation model (MFD)"
DETECTOR_READS = "fixed detectors (reads)"
TRAFFIC = "traffic source"
TRAFFIC_OTHER = "traffic source (other)"
WAITING_FOR_SOURCE = "waiting for the traffic source (its own process)"
WAITING_FOR_SUMO = "waiting for SUMO (its own process)"
SCORING = "step and scoring"
RECORDING = "recording"
WRITING = "monitoring and writing"
LIVE_VIEW = "live view (sumo-gui drawing, screenshots)"


def swarm_stage(name: str) -> str:
    """The stage of one swarm's decision (and online learning, if any)."""
    return f"swarm {name}"


class StageTimer:
    """Seconds and calls per named stage, accumulated."""

    def __init__(self) -> None:
        self.seconds: dict[str, float] = {}
        self.calls: dict[str, int] = {}

    def add(self, name: str, seconds: float, calls: int = 1) -> None:
        self.seconds[name] = self.seconds.get(name, 0.0) + seconds
        self.calls[name] = self.calls.get(name, 0) + calls

    @contextmanager
    def stage(self, name: str) -> Iterator[None]:
        t0 = time.perf_counter()
        try:
            yield
        finally:
            self.add(name, time.perf_counter() - t0)

    def merge(self, other: StageTimer | Mapping[str, float]) -> None:
        seconds = other.seconds if isinstance(other, StageTimer) else other
        calls = other.calls if isinstance(other, StageTimer) else {}
        for name, s in seconds.items():
            self.add(name, s, calls.get(name, 1))

    def total(self) -> float:
        return sum(self.seconds.values())

    def as_dict(self) -> dict[str, float]:
        return dict(self.seconds)


def largest_stages(stages: Mapping[str, float], n: int = 4) -> str:
    """``"SUMO stepping 80.1 s (71%), swarm lookahead 9.0 s (8%), ..."``: the ``n`` largest."""
    total = sum(stages.values()) or 1.0
    top = sorted(stages.items(), key=lambda kv: -kv[1])[:n]
    return ", ".join(f"{name} {s:.1f} s ({100 * s / total:.0f}%)" for name, s in top)
