"""Synthetic traffic of the paper's Sec. IV: Gaussian big and small disturbances.

``z^k(i, j) = sum_s A_s(k) exp(-((i - i_s)^2 + (j - j_s)^2) / (2 sigma_s^2))`` with
``A_big(k) = a exp(-k / (beta1 T))`` (slowly dissipating jams, accidents) and
``A_small(k) = a max(0, sin(2 pi beta2 k / T))`` (periodic: signals, signs).
"""

from __future__ import annotations

from collections.abc import Generator, Sequence
from dataclasses import asdict, dataclass
from typing import Any, Literal

import numpy as np

from twin.grid import Grid
from twin.traffic.base import TrafficSource, normalise_importance


@dataclass(frozen=True)
class Disturbance:
    """One Gaussian disturbance centred on cell ``(i, j)``."""

    kind: Literal["big", "small"]
    i: float
    j: float
    amplitude: float
    sigma: float

    def amplitudes(self, steps: np.ndarray, horizon: int, beta1: float, beta2: float) -> np.ndarray:
        """``A_s(k)`` for every ``k`` in ``steps``."""
        if self.kind == "big":  # a tiny beta1 overflows -k / (beta1 T) to -inf: A is then 0
            with np.errstate(over="ignore", divide="ignore"):
                return self.amplitude * np.exp(-steps / (beta1 * horizon))
        return self.amplitude * np.maximum(0.0, np.sin(2.0 * np.pi * beta2 * steps / horizon))


class SyntheticTraffic(TrafficSource):
    """Importance maps from Gaussian disturbances, normalised per Def. 2.

    ``z_hi`` defaults to the largest ``z`` over the map and the horizon, ``z_lo`` to 0.
    """

    def __init__(
        self,
        grid: Grid,
        disturbances: Sequence[Disturbance],
        horizon: int,
        beta1: float = 0.7,
        beta2: float = 5.0,
        z_lo: float = 0.0,
        z_hi: float | None = None,
    ) -> None:
        self.grid = grid
        self.disturbances = tuple(disturbances)
        self.horizon = int(horizon)
        self.beta1, self.beta2 = float(beta1), float(beta2)
        steps = np.arange(self.horizon + 1, dtype=np.float64)
        ii, jj = np.indices(grid.shape, dtype=np.float64)
        if self.disturbances:
            # (S, nx, ny) spatial kernels and (S, T+1) amplitudes: z = A^T K, one tensordot.
            self._kernels = np.stack(
                [
                    np.exp(-((ii - d.i) ** 2 + (jj - d.j) ** 2) / (2.0 * d.sigma**2))
                    for d in self.disturbances
                ]
            )
            self._amplitudes = np.stack(
                [
                    d.amplitudes(steps, self.horizon, self.beta1, self.beta2)
                    for d in self.disturbances
                ]
            )
        else:
            self._kernels = np.zeros((0, *grid.shape))
            self._amplitudes = np.zeros((0, self.horizon + 1))
        self.z_lo = float(z_lo)
        self.z_hi = float(z_hi) if z_hi is not None else self._largest_z()

    def _largest_z(self) -> float:
        if not self.disturbances:
            return 1.0
        peak = self.peak_z()
        return peak if peak > self.z_lo else self.z_lo + 1.0

    def peak_z(self) -> float:
        """The largest ``z`` on a free cell over the horizon (0 without disturbances)."""
        return self._z_range()[1]

    def low_z(self) -> float:
        """The smallest ``z`` on a free cell over the horizon (0 without disturbances)."""
        return self._z_range()[0]

    def _z_range(self) -> tuple[float, float]:
        if getattr(self, "_range", None) is None:
            low, peak = np.inf, 0.0
            for start in range(0, self.horizon + 1, 256):
                amplitudes = self._amplitudes[:, start : start + 256].T
                block = np.tensordot(amplitudes, self._kernels, axes=1)
                peak = max(peak, float(np.where(self.grid.free, block, 0.0).max(initial=0.0)))
                low = min(low, float(np.where(self.grid.free, block, np.inf).min(initial=np.inf)))
            self._range = (0.0 if np.isinf(low) else low, peak)
        return self._range

    def z(self, k: int) -> np.ndarray:
        """The raw traffic variable ``z^k`` over the map."""
        return np.tensordot(self._amplitudes[:, k], self._kernels, axes=1)

    def importance(self, k: int) -> np.ndarray:
        """``T^k`` (Def. 2)."""
        return normalise_importance(self.z(k), self.grid, self.z_lo, self.z_hi)

    def importance_maps(self) -> Generator[np.ndarray, None, None]:
        for k in range(self.horizon + 1):
            yield self.importance(k)

    def metadata(self) -> dict[str, Any]:
        return {
            "kind": "synthetic",
            "horizon": self.horizon,
            "beta1": self.beta1,
            "beta2": self.beta2,
            "z_lo": self.z_lo,
            "z_hi": self.z_hi,
            "disturbances": [asdict(d) for d in self.disturbances],
        }
