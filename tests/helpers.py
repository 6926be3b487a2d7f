"""Small builders shared by several test modules."""

from __future__ import annotations

import os
import shutil

import numpy as np
import pytest

from twin.traffic.tape import Tape

#: sumo-gui (``--gui``, ``twin replay``) needs a display: Xvfb or DISPLAY, else skipped
needs_display = pytest.mark.skipif(
    shutil.which("Xvfb") is None and not os.environ.get("DISPLAY"),
    reason="sumo-gui needs a display: install Xvfb (apt-get install xvfb) or set DISPLAY",
)


def random_tape(seed=0, nx=3, ny=4, warmup=2, horizon=5, obstacle=(0, 0)) -> Tape:
    """A tape of random counts and speeds on an ``nx x ny`` grid with one obstacle cell."""
    rng = np.random.default_rng(seed)
    steps = np.arange(-warmup, horizon + 1)
    counts = rng.integers(0, 40, (len(steps), nx, ny)).astype(np.int32)
    speeds = np.where(counts > 0, rng.uniform(0, 15, counts.shape), np.nan).astype(np.float32)
    obstacles = np.zeros((nx, ny), bool)
    obstacles[obstacle] = True
    counts[:, obstacle[0], obstacle[1]] = 0
    speeds[:, obstacle[0], obstacle[1]] = np.nan
    return Tape(
        steps=steps,
        times=25200.0 + 75.0 * steps,
        counts=counts,
        speeds=speeds,
        obstacles=obstacles,
        lane_km=rng.uniform(0.5, 3.0, (nx, ny)) * ~obstacles,
        speed_limit=np.where(obstacles, 0.0, 13.9),
        horizon=horizon,
        settings={
            "mfd_fit": "online",
            "detection_p": 1.0,
            "seed": 4,
            "mfd_prior": [0.7, 40.0],
            "reads_per_step": 1,
        },
    )


def cut_tape(tape: Tape, last: int) -> Tape:
    """``tape`` as a run that stopped after step ``last`` leaves it (its horizon unchanged)."""
    import dataclasses

    keep = tape.steps <= last
    return dataclasses.replace(tape, steps=tape.steps[keep], times=tape.times[keep],
                               counts=tape.counts[keep], speeds=tape.speeds[keep])  # fmt: skip


SMALL_SUMO_CONFIG = """
[swarm]
n_drones = 2
[traffic]
kind = "sumo"
net = "small.net.xml"
routes = ["small.trips.xml"]
cell_m = 200.0
drone_speed_kmh = 12.0   # one step = 60 s
begin = "00:05"
warmup_min = 5.0
horizon = {horizon}
seed = 3
[evaluate]
swarms = ["random", "greedy", "sweeping"]
"""


def small_sumo_scenario(folder, horizon: int = 10):
    """A 5 x 5 signalised grid of 300 m blocks with 15 min of random trips, and its scenario
    config ``small.toml`` (2 drones, 200 m cells, one step = 60 s from 00:05)."""
    from twin.sumo.network import generate_grid_scenario

    generate_grid_scenario(folder, blocks=5, block_m=300, end_s=900, period_s=1.5, seed=5)
    (folder / "small.toml").write_text(SMALL_SUMO_CONFIG.format(horizon=horizon))
    return folder


def slow_marker(path: str, seconds: float) -> str:
    """A pool task: wait ``seconds``, then leave the file ``path`` (it ran)."""
    import time
    from pathlib import Path

    time.sleep(seconds)
    Path(path).write_text("ran")
    return path
