"""Mean and 95% interval over seeds, for the report's curves and tables."""

from __future__ import annotations

import numpy as np
import pandas as pd

from twin.metrics import ci95_halfwidth


def ci95_half_width(values: np.ndarray, axis: int = 0) -> np.ndarray:
    """:func:`twin.metrics.ci95_halfwidth` along ``axis`` (the report's bands over seeds)."""
    return np.apply_along_axis(ci95_halfwidth, axis, np.asarray(values, dtype=np.float64))


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
