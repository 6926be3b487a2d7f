"""Formations as adversarial tests of the headline score.

Drones flying as a pack see the same cells. Def. 4 as printed pays each of them its whole field
of view, so a pack is paid several times for one visit; the headline score pays each visited
cell once. Two hand-coded packs (neither is a swarm twin ships) must beat the visit-gain rule on
the paper's column, which shows the loophole, and lose to it on the headline, which closes it.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from twin.config import load_config, start_positions, synthetic_source
from twin.grid import ACTION_DELTAS
from twin.metrics import table2
from twin.patrol import run_patrol
from twin.planners import VisitGainPolicy
from twin.policies import Policy, SwarmView
from twin.scores import visit_gain
from twin.traffic.base import RecordedTraffic

CONFIG = Path(__file__).resolve().parents[1] / "configs" / "synthetic.toml"
STAY, UP, DOWN, LEFT, RIGHT = range(5)


class LineSweep(Policy):
    """A 1 x 4 line (one row, four adjacent columns) sweeping broadside, blind to traffic: down
    to the last row, four columns sideways, up to the first row, and so on."""

    def reset(self, grid, n_drones, rng):
        super().reset(grid, n_drones, rng)
        self.vertical, self.sideways, self.shift = DOWN, RIGHT, 0

    def act(self, view: SwarmView) -> np.ndarray:
        feasible = view.feasible
        if self.shift == 0 and feasible[:, self.vertical].all():
            return np.full(len(feasible), self.vertical)
        if self.shift == 0:
            self.shift = 4
            self.vertical = UP if self.vertical == DOWN else DOWN
        if not feasible[:, self.sideways].all():
            self.sideways = LEFT if self.sideways == RIGHT else RIGHT
        self.shift -= 1
        return np.full(len(feasible), self.sideways)


class BlockGreedy(Policy):
    """A 2 x 2 block moved as one: the move whose four cells have the largest summed visit gain
    (``I^k``, and ``T^k`` as seen from the block)."""

    def act(self, view: SwarmView) -> np.ndarray:
        p = view.params
        best, best_move = -np.inf, STAY
        for move in self.rng.permutation(5):
            if not view.feasible[:, move].all():
                continue
            cells = view.positions + ACTION_DELTAS[move]
            i, j = cells[:, 0], cells[:, 1]
            weight = p.alpha_T * view.importance[i, j] + p.alpha_I
            gain = visit_gain(weight, view.idleness[i, j], p).sum()
            if gain > best:
                best, best_move = gain, move
        return np.full(len(view.positions), best_move)


SEEDS = range(3)


@pytest.fixture(scope="module")
def scores():
    config = load_config(CONFIG)
    source = RecordedTraffic.from_source(synthetic_source(config))
    nx, ny = source.grid.shape
    rows = []
    for seed in SEEDS:
        rng = np.random.default_rng(seed)
        i, j = int(rng.integers(0, nx - 1)), int(rng.integers(0, ny - 3))
        packs = {
            "line": (LineSweep(), np.array([[i, j + d] for d in range(4)])),
            "block": (BlockGreedy(), np.array([[i, j], [i, j + 1], [i + 1, j], [i + 1, j + 1]])),
            "visit-gain": (VisitGainPolicy(), start_positions(config, source.grid, rng)),
        }
        for name, (policy, starts) in packs.items():
            result = run_patrol(source, {name: policy}, starts, config.params, seed=seed)
            rows.append(table2(result, config.params).assign(seed=seed))
    return pd.concat(rows).groupby("swarm")[["R_hat_T", "R_hat_T_paper"]].mean()


@pytest.mark.parametrize("pack", ["line", "block"])
def test_a_pack_games_the_papers_column(scores, pack):
    assert scores.loc[pack, "R_hat_T_paper"] > scores.loc["visit-gain", "R_hat_T_paper"]


@pytest.mark.parametrize("pack", ["line", "block"])
def test_a_pack_never_beats_visit_gain_on_the_headline(scores, pack):
    assert scores.loc[pack, "R_hat_T"] < scores.loc["visit-gain", "R_hat_T"]
