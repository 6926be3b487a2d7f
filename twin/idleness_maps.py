"""The idleness maps a swarm decides on, with its coordinator or without (Def. 3, Sec. III-B).

While the coordinator is reachable the swarm shares one map, updated with every drone's visit.
During a communication outage (steps ``start <= k < stop``) each drone keeps its own copy,
updated with its own visits only, and remembers the positions it last heard of the others.
When the coordinator comes back the copies merge: each cell takes the smallest idleness any
drone holds. A decentralized swarm is one whose outage never ends.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from twin.errors import UserError
from twin.grid import Grid
from twin.scores import ScoreParams, update_idleness


def parse_outages(outages: Sequence[Sequence[int]] | None) -> list[tuple[int, int]]:
    """Step windows ``[start, stop)`` without coordinator, checked."""
    windows = []
    for w in outages or ():
        try:
            start, stop = (int(x) for x in w)
        except (TypeError, ValueError):
            raise UserError(
                f"outage window {w!r} must be a pair [start, stop] of step numbers"
            ) from None
        if not 0 <= start < stop:
            raise UserError(f"outage window {w!r} needs 0 <= start < stop")
        windows.append((start, stop))
    return windows


def own_visits_update(maps: np.ndarray, positions: np.ndarray, grid: Grid, p) -> np.ndarray:
    """Def. 3 on every drone's own map ``(N, nx, ny)`` with only that drone's visit."""
    new = np.where(grid.free, np.minimum(1.0, maps + p.delta), 0.0)
    d = np.arange(len(positions))
    i, j = positions[:, 0], positions[:, 1]
    new[d, i, j] = p.eta * maps[d, i, j]
    return new


class SwarmMaps:
    """The shared map (coordinated) or the drones' own maps (outage), advanced step by step."""

    def __init__(self, n_drones: int, decentralized: bool = False, outages=()) -> None:
        self.n_drones = n_drones
        self.decentralized = decentralized
        self.outages = parse_outages(outages)
        self.shared: np.ndarray | None = None  # the coordinator's map
        self.local: np.ndarray | None = None  # (N, nx, ny) while the coordinator is down
        self.heard: np.ndarray | None = None  # (N, 2) last positions heard of every drone
        self.k = -1

    def central(self, k: int) -> bool:
        """Whether the coordinator is reachable at step ``k``."""
        if self.decentralized:
            return False
        return not any(start <= k < stop for start, stop in self.outages)

    def advance(self, k: int, positions: np.ndarray, shared_map: np.ndarray, grid: Grid,
                params: ScoreParams) -> None:  # fmt: skip
        """Bring the maps to step ``k``, the drones now at ``positions``. At ``k = 0`` every
        map starts from ``shared_map`` (``I^0``)."""
        central = self.central(k)
        if self.k < 0:
            self.shared = shared_map.copy()
            self.heard = positions.copy()
            if not central:
                self.local = np.repeat(shared_map[None], self.n_drones, axis=0)
        elif central:
            if self.local is not None:  # back from an outage: merge, this step's visits included
                self.shared = own_visits_update(self.local, positions, grid, params).min(0)
                self.local = None
            else:
                self.shared = update_idleness(
                    self.shared, positions, grid, params.eta, params.delta
                )
        else:
            if self.local is None:  # the coordinator just went down
                self.local = np.repeat(self.shared[None], self.n_drones, axis=0)
            self.local = own_visits_update(self.local, positions, grid, params)
        if central:
            self.heard = positions.copy()
        self.k = k

    def others_centre_of_mass(self, positions: np.ndarray) -> np.ndarray:
        """Each drone's view of the others' centre of mass, from the positions it last heard."""
        n = self.n_drones
        if n == 1:
            return positions.astype(np.float64)
        heard = self.heard.astype(np.float64)
        return (heard.sum(axis=0)[None, :] - heard) / (n - 1)
