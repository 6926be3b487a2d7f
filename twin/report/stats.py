"""Mean and 95% interval over seeds, for the report's curves and tables."""

from __future__ import annotations

import numpy as np
import pandas as pd
from scipy import stats


def ci95_half_width(values: np.ndarray, axis: int = 0) -> np.ndarray:
    """Student-t 95% half-width of the mean along ``axis``; 0 with fewer than 2 values."""
    values = np.asarray(values, dtype=np.float64)
    n = values.shape[axis]
    if n < 2:
        return np.zeros(np.delete(values.shape, axis))
    sem = values.std(axis=axis, ddof=1) / np.sqrt(n)
    return stats.t.ppf(0.975, n - 1) * sem


def mean_band(
    series: pd.DataFrame, column: str
) -> dict[str, tuple[np.ndarray, np.ndarray, np.ndarray]]:
    """Per swarm: ``(steps, mean over seeds, 95% half-width)`` of ``column`` at every step."""
    out = {}
    for swarm, rows in series.groupby("swarm", sort=False):
        table = rows.pivot_table(index="step", columns="seed", values=column, aggfunc="first")
        values = table.to_numpy(dtype=np.float64)
        out[str(swarm)] = (
            table.index.to_numpy(),
            values.mean(axis=1),
            ci95_half_width(values, axis=1),
        )
    return out
