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


def parse_outages(
    outages: Sequence[Sequence[int]] | None, swarm: str | None = None
) -> list[tuple[int, int]]:
    """Step windows ``[start, stop)`` without coordinator, checked; a swarm's option
    (``swarm``) is refused as its options are (``<swarm>: outages = ...``)."""
    lead = "" if swarm is None else f"{swarm}: outages = {outages!r}: "
    windows = []
    for w in () if outages is None else outages:
        pair = list(w) if isinstance(w, list | tuple | np.ndarray) else []
        if len(pair) != 2 or not all(
            isinstance(x, int | np.integer) and not isinstance(x, bool) for x in pair
        ):  # "3" and 1.5 are no step numbers
            raise UserError(
                f"{lead}outage window {w!r} must be a pair [start, stop] of step numbers"
            )
        start, stop = (int(x) for x in pair)
        if not 0 <= start < stop:
            raise UserError(f"{lead}outage window {w!r} needs 0 <= start < stop")
        windows.append((start, stop))
    return windows


def own_visits_update(maps: np.ndarray, positions: np.ndarray, grid: Grid, p) -> np.ndarray:
    """Def. 3 on every drone's own map ``(N, nx, ny)`` with only that drone's visit (dense:
    the reference for :class:`OwnMaps`)."""
    new = np.where(grid.free, np.minimum(1.0, maps + p.delta), 0.0)
    d = np.arange(len(positions))
    i, j = positions[:, 0], positions[:, 1]
    new[d, i, j] = p.eta * maps[d, i, j]
    return new


class OwnMaps:
    """Every drone's own idleness map (Def. 3 with its own visits only), stored sparsely.

    All maps start equal and recover alike, so drone ``d``'s map is one common map ``base``
    (recovered every step, visited by nobody) except at the cells ``d`` itself visited; only
    those cells are kept per drone, and dropped again once they equal ``base`` (they then
    evolve alike). A step costs O(cells + kept cells) instead of O(N cells), and every value
    is the one :func:`own_visits_update` gives, bit for bit: the same operations per cell.
    """

    def __init__(self, start: np.ndarray, n_drones: int) -> None:
        self.n_drones = n_drones
        self.shape = start.shape
        self.base = start.copy()
        n_cells = start.size
        #: (N, cells) index into ``cell``/``drone``/``value`` of drone d's own value, else -1
        self.index = np.full(
            (n_drones, n_cells), -1, dtype=np.int32 if n_drones * n_cells < 2**31 else np.int64
        )
        self.cell = np.empty(0, np.intp)
        self.drone = np.empty(0, np.intp)
        self.value = np.empty(0, np.float64)

    def at(self, flat: np.ndarray) -> np.ndarray:
        """Drone ``d``'s value at flat cells ``flat[d]`` (``flat``: ``(N, ...)``)."""
        d = np.arange(self.n_drones).reshape((-1,) + (1,) * (flat.ndim - 1))
        k = self.index[d, flat]
        own = k >= 0
        out = self.base.ravel()[flat]
        out[own] = self.value[k[own]]
        return out

    def advance(self, positions: np.ndarray, grid: Grid, p) -> None:
        """One step: every map recovers, each drone resets its own cell (Def. 3)."""
        i, j = positions[:, 0], positions[:, 1]
        flat = i * self.shape[1] + j
        old = self.at(flat)  # before recovery: the visit keeps eta * I
        self.base = np.where(grid.free, np.minimum(1.0, self.base + p.delta), 0.0)
        self.value = np.where(
            grid.free.ravel()[self.cell], np.minimum(1.0, self.value + p.delta), 0.0
        )
        d = np.arange(self.n_drones)
        k = self.index[d, flat]
        seen = k >= 0
        self.value[k[seen]] = p.eta * old[seen]
        fresh = ~seen
        if fresh.any():
            self.index[d[fresh], flat[fresh]] = len(self.value) + np.arange(fresh.sum())
            self.cell = np.concatenate([self.cell, flat[fresh]])
            self.drone = np.concatenate([self.drone, d[fresh]])
            self.value = np.concatenate([self.value, p.eta * old[fresh]])
        same = self.value == self.base.ravel()[self.cell]
        if same.any():  # equal to the common map: from now on they evolve alike
            self.index[self.drone[same], self.cell[same]] = -1
            keep = ~same
            self.cell, self.drone, self.value = self.cell[keep], self.drone[keep], self.value[keep]
            self.index[self.drone, self.cell] = np.arange(len(self.value))

    def rows_and_columns(self, positions: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Drone ``d``'s map along its row ``(N, ny)`` and its column ``(N, nx)``."""
        d = np.arange(self.n_drones)
        i, j = positions[:, 0], positions[:, 1]
        index = self.index.reshape((self.n_drones, *self.shape))
        out = []
        for k, line in ((index[d, i, :], self.base[i, :]), (index[d, :, j], self.base[:, j].T)):
            own = k >= 0
            line = np.ascontiguousarray(line)
            line[own] = self.value[k[own]]
            out.append(line)
        return out[0], out[1]

    def merged(self) -> np.ndarray:
        """Each cell's smallest idleness over the drones' maps."""
        out = self.base.copy()
        flat = out.ravel()
        if self.n_drones > 0:
            everyone = np.bincount(self.cell, minlength=flat.size) == self.n_drones
            flat[everyone] = np.inf  # no drone holds the common value there
        np.minimum.at(flat, self.cell, self.value)
        return out

    def dense(self) -> np.ndarray:
        """The ``(N, nx, ny)`` maps in full (for inspection; O(N cells))."""
        out = np.repeat(self.base[None], self.n_drones, axis=0)
        out.reshape(self.n_drones, -1)[self.drone, self.cell] = self.value
        return out


class SwarmMaps:
    """The shared map (coordinated) or the drones' own maps (outage), advanced step by step."""

    def __init__(self, n_drones: int, decentralized: bool = False, outages=()) -> None:
        self.n_drones = n_drones
        self.decentralized = decentralized
        self.outages = parse_outages(outages)
        self.shared: np.ndarray | None = None  # the coordinator's map
        self.own: OwnMaps | None = None  # the drones' own maps while the coordinator is down
        self.heard: np.ndarray | None = None  # (N, 2) last positions heard of every drone
        self.k = -1

    def central(self, k: int) -> bool:
        """Whether the coordinator is reachable at step ``k``."""
        if self.decentralized:
            return False
        return not any(start <= k < stop for start, stop in self.outages)

    def advance(self, k: int, positions: np.ndarray, shared_map: np.ndarray, grid: Grid,
                params: ScoreParams, visits: np.ndarray | None = None) -> None:  # fmt: skip
        """Bring the maps to step ``k``, the drones now at ``positions``. At ``k = 0`` every
        map starts from ``shared_map`` (``I^0``). ``visits``: the cells whose visit the swarm
        recorded (scripted faults, :mod:`twin.faults`); None: the drones' cells."""
        visits = positions if visits is None else visits
        central = self.central(k)
        if self.k < 0:
            self.shared = shared_map.copy()
            self.heard = positions.copy()
            if not central:
                self.own = OwnMaps(shared_map, self.n_drones)
        elif central:
            if self.own is not None:  # back from an outage: merge, this step's visits included
                self.own.advance(positions, grid, params)
                self.shared = self.own.merged()
                self.own = None
            else:
                self.shared = update_idleness(self.shared, visits, grid, params.eta, params.delta)
        else:
            if self.own is None:  # the coordinator just went down
                self.own = OwnMaps(self.shared, self.n_drones)
            self.own.advance(positions, grid, params)
        if central:
            self.heard = positions.copy()
        self.k = k

    @property
    def local(self) -> np.ndarray | None:
        """The drones' own maps ``(N, nx, ny)`` in full while the coordinator is down, else
        None (built on each call: for inspection, not for the step)."""
        return None if self.own is None else self.own.dense()

    def others_centre_of_mass(self, positions: np.ndarray) -> np.ndarray:
        """Each drone's view of the others' centre of mass, from the positions it last heard."""
        n = self.n_drones
        if n == 1:
            return positions.astype(np.float64)
        heard = self.heard.astype(np.float64)
        return (heard.sum(axis=0)[None, :] - heard) / (n - 1)
