"""Synthetic traffic with dynamics: disturbances that move, grow and fade, under a rush-hour
wave; a training map for learned swarms that the paper's fixed map (Sec. III-A) does not give.

Each disturbance ``s`` is a Gaussian bump (as in the paper's ``z^k``) whose centre drifts in a
straight line, ``c_s(k) = c_s + v_s k``, reflected at the map's edges, and whose amplitude rises
and falls once, ``A_s(k) = a_s sin(pi (k - k_on) / d_s)`` for ``k_on <= k < k_on + d_s`` (0
otherwise). Every map is scaled by the rush-hour wave
``w(k) = w_0 + (1 - w_0) exp(-(k / T - peak)^2 / (2 width^2))``. The map is normalised per
Def. 2 with ``z_hi`` the largest ``z`` over the map and the horizon. All of it follows from
one seed.
"""

from __future__ import annotations

from collections.abc import Generator, Sequence
from typing import Any

import numpy as np

from twin.belief import History, days_history
from twin.grid import Grid
from twin.traffic.base import TrafficSource, normalise_importance

#: The rush-hour wave: base level, peak (fraction of the horizon) and width (same unit).
WAVE_BASE, WAVE_PEAK, WAVE_WIDTH = 0.3, 0.45, 0.18
#: The most disturbances a day may hold (8 by default): past this the map is one flat jam.
MAX_DISTURBANCES = 10_000
#: Cell values one batch of disturbances' bumps may take while ``z^k`` is summed.
BUMP_BATCH_VALUES = 1 << 22


class DynamicTraffic(TrafficSource):
    """``n_disturbances`` moving, growing and fading Gaussian disturbances drawn from ``seed``."""

    def __init__(self, grid: Grid, horizon: int, n_disturbances: int = 8, seed: int = 0) -> None:
        self.grid = grid
        self.horizon = int(horizon)
        self.seed = int(seed)
        rng = np.random.default_rng([self.seed, 7])
        nx, ny = grid.shape
        n = int(n_disturbances)
        if not 1 <= n <= MAX_DISTURBANCES:
            raise ValueError(f"n_disturbances = {n}: give 1 to {MAX_DISTURBANCES}")
        big = rng.random(n) < 0.4
        self.centres = rng.uniform([0, 0], [nx - 1, ny - 1], size=(n, 2))
        # a big jam drifts slowly, a small one may cross a quarter of the map over the run
        speed = np.where(big, 0.05, 0.25) * max(nx, ny) / max(self.horizon, 1)
        angle = rng.uniform(0, 2 * np.pi, n)
        self.velocities = speed[:, None] * np.stack([np.cos(angle), np.sin(angle)], axis=1)
        self.sigmas = np.where(big, rng.uniform(2.0, 3.5, n), rng.uniform(0.8, 1.5, n))
        self.amplitudes = np.where(big, 1.0, 0.5) * rng.uniform(0.7, 1.0, n)
        span = max(self.horizon, 1)
        self.durations = np.maximum(2.0, rng.uniform(0.2, 0.8, n) * span)
        self.onsets = rng.uniform(-0.3, 0.9, n) * span
        self._z = np.stack([self.z(k) for k in range(self.horizon + 1)])
        free_z = np.where(grid.free, self._z, 0.0)
        self.z_lo, self.z_hi = 0.0, max(float(free_z.max()), 1e-9)

    def wave(self, k: int) -> float:
        """The rush-hour scale ``w(k)`` of step ``k``."""
        x = k / max(self.horizon, 1)
        return WAVE_BASE + (1 - WAVE_BASE) * float(
            np.exp(-((x - WAVE_PEAK) ** 2) / (2 * WAVE_WIDTH**2))
        )

    def centres_at(self, k: int) -> np.ndarray:
        """Every disturbance's centre at step ``k``, reflected at the map's edges."""
        nx, ny = self.grid.shape
        size = np.array([max(nx - 1, 1), max(ny - 1, 1)], dtype=float)
        raw = np.mod(self.centres + self.velocities * k, 2 * size)
        return np.where(raw > size, 2 * size - raw, raw)

    def z(self, k: int) -> np.ndarray:
        """The raw traffic variable ``z^k`` over the map."""
        phase = (k - self.onsets) / self.durations
        amp = np.where((phase >= 0) & (phase < 1), self.amplitudes * np.sin(np.pi * phase), 0.0)
        ii, jj = np.indices(self.grid.shape, dtype=np.float64)
        c = self.centres_at(k)
        z = np.zeros(self.grid.shape)
        batch = max(1, BUMP_BATCH_VALUES // ii.size)  # the bumps of many take memory
        for b in range(0, len(amp), batch):
            cb, sb = c[b : b + batch], self.sigmas[b : b + batch]
            d2 = (ii[None] - cb[:, 0, None, None]) ** 2 + (jj[None] - cb[:, 1, None, None]) ** 2
            z += np.tensordot(amp[b : b + batch], np.exp(-d2 / (2 * sb[:, None, None] ** 2)), 1)
        return self.wave(k) * z

    def importance(self, k: int) -> np.ndarray:
        """``T^k`` (Def. 2)."""
        return normalise_importance(self._z[k], self.grid, self.z_lo, self.z_hi)

    def importance_maps(self) -> Generator[np.ndarray, None, None]:
        for k in range(self.horizon + 1):
            yield self.importance(k)

    def metadata(self) -> dict[str, Any]:
        return {
            "kind": "dynamic",
            "horizon": self.horizon,
            "seed": self.seed,
            "disturbances": len(self.amplitudes),
            "z_hi": self.z_hi,
        }


def dynamics_history(
    grid: Grid, horizon: int, seeds: Sequence[int], disturbances: int = 8
) -> History:
    """The :class:`~twin.belief.History` of the dynamic generator's days (one
    :class:`DynamicTraffic` per seed in ``seeds``) on ``grid`` over ``horizon`` steps."""
    days = [DynamicTraffic(grid, horizon, disturbances, seed=int(s)) for s in seeds]
    return days_history(days, [int(s) for s in seeds], [f"dynamics seed {int(s)}" for s in seeds])
