"""A coordinated classical swarm that plans on its own nowcast (:mod:`twin.belief`).

The swarm carries the per-cell Kalman filter of the ``nowcast`` belief model, fed by a history
of earlier days and by its own sightings only (the cells of its drones' fields of view, as
they see them): never the true map of the current run. At every step it scores the move of
each drone by what the visit is expected to be worth, the headline score's visit gain plus
the uncertainty the sighting removes, and lets the exact coordinator choose the joint action
(eq. maxi:op2: no two drones on one cell).
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from twin.belief import EXACT_SIGHTINGS, Z90, History, NowcastFilter, SightingModel
from twin.errors import UserError
from twin.grid import ACTION_DELTAS, Grid
from twin.planners import CoordinatedPolicy
from twin.policies import SwarmView, number_option
from twin.scores import visit_gain

#: Default weight of the information term against the visit gain (see
#: :class:`NowcastGainPolicy`): chosen on validation SUMO seeds 100 and 101 of the default rush
#: hour (docs/beliefs.md) as the weight with the lowest nowcast belief error among those that
#: keep R_hat_T at 90% of visit-gain's or more, with the filter's sighting model (exact counts).
DEFAULT_INFO_WEIGHT = 0.05
#: Default width, in standard deviations, of the importance quantile the information term uses
#: (1.645: the upper end of the nowcast's 90% interval).
DEFAULT_QUANTILE_Z = Z90
#: Cells in a field of view (the scale of the normalised information term).
VIEW_CELLS = 5

NEEDS_HISTORY = (
    "swarm 'nowcast-gain' plans on the nowcast of a history of earlier days: give --history "
    "FILE (built by `twin history`) or [swarm_options.nowcast-gain].history"
)


def information_values(
    quantile: np.ndarray,
    prior_var: np.ndarray,
    rho: np.ndarray,
    meas_var: float | np.ndarray,
    steps_left: int,
) -> np.ndarray:
    """Per cell, the importance-weighted variance a sighting at the next step removes, over
    the steps it lasts: ``Tq (P^- - P^+) (1 - rho^(2 L)) / (1 - rho^2)``.

    ``P^- - P^+ = P^-^2 / (P^- + meas_var)`` is the Kalman reduction of the prior variance
    ``P^-`` (``meas_var`` per cell or one for all); what it tells of the deviation fades by
    ``rho^2`` per step (the filter's prediction), so it is summed over the ``L = steps_left``
    steps up to the horizon (``sum_{j < L} rho^(2j)``: 1 when ``rho = 0``); ``Tq`` is the
    believed importance (a quantile of the nowcast).
    """
    removed = prior_var * prior_var / (prior_var + meas_var)
    rho2 = rho * rho
    steps = max(int(steps_left), 1)
    lasting = np.where(
        rho2 < 1.0, (1.0 - rho2**steps) / np.maximum(1.0 - rho2, 1e-12), float(steps)
    )
    return quantile * removed * lasting


def check_options(weight: Any, quantile_z: Any, meas_var: Any) -> None:
    """The nowcast-gain swarm's options: numbers, each within its range."""
    for key, value, lo, hi in (
        ("weight", weight, 0.0, 1e6),
        ("quantile_z", quantile_z, 0.0, 10.0),
        *([("meas_var", meas_var, 1e-12, 1.0)] if meas_var is not None else []),
    ):
        number_option("nowcast-gain", key, value, lo, hi)


class NowcastGainPolicy(CoordinatedPolicy):
    """Each drone's move to ``p'`` is scored by the expected value of visiting ``p'``:

    ``S(p') = g(p') + w * sum_{c in Adj(p')} v_c / (5 vbar)``

    - ``g(p') = (alpha_T That(p') + alpha_I) (min(1, I^k + delta) - eta I^k)`` at ``p'``: the
      visit gain of the headline score (Def. 3 idleness, Def. 4 read on arrival, each visited
      cell paid once), with ``That`` the nowcast's prediction of ``T^{k+1}`` (the reward uses
      ``T^{k+1}``; visit-gain uses the last seen ``T^k``);
    - ``v_c`` (:func:`information_values`): a quantile of the believed importance,
      ``Tq = min(1, That + z sigma^-)``, times the variance the sighting of ``c`` at step
      ``k + 1`` removes from the nowcast (prior minus posterior), summed over the steps the
      information lasts (``rho^2`` decay);
    - ``vbar``: the mean of ``v`` over the free cells at this step, so the information term is
      about ``w`` for a view of average worth: ``w`` trades the headline score against what
      the swarm learns, whatever the history's scale of variance.

    Joint action: the exact coordinator on the summed scores (no two drones on one cell).
    Two drones whose views overlap are both credited the shared cells' information (the
    coordinator keeps their cells distinct, not their views). With ``w = 0`` it is visit-gain
    planning on the nowcast's predicted importance.

    Knows at run time only: the history (earlier days), its own sightings ``T^k`` inside the
    fields of view, its idleness map. Its filter is the ``nowcast`` belief model's (the belief
    table scores that model on the swarm's trajectory: the same numbers). Without a history it
    refuses to be built (one line): planning on a nowcast that has no prior would be another
    swarm.
    """

    name = "nowcast-gain"

    def __init__(
        self,
        history: History | str | Path | None = None,
        weight: float = DEFAULT_INFO_WEIGHT,
        quantile_z: float = DEFAULT_QUANTILE_Z,
        meas_var: float | None = None,
    ):
        if history is None:
            raise UserError(NEEDS_HISTORY)
        if not isinstance(history, History):
            history = History.load(Path(history))
        check_options(weight, quantile_z, meas_var)
        self.history = history
        self.weight = float(weight)
        self.quantile_z = float(quantile_z)
        self.meas_var = None if meas_var is None else float(meas_var)
        self.sighting = EXACT_SIGHTINGS

    def use_sighting_model(self, sighting: SightingModel) -> None:
        """How the run's sightings are made (the experiment hands its traffic source's): the
        filter's measurement variance when no ``meas_var`` is given."""
        self.sighting = sighting

    def reset(self, grid: Grid, n_drones: int, rng: np.random.Generator) -> None:
        super().reset(grid, n_drones, rng)
        h = self.history
        h.check_grid(h.named(self.name), grid.obstacles)
        self.filter = NowcastFilter(h, self.meas_var, self.sighting)
        self.free = grid.free.ravel()

    @staticmethod
    def check_record(record: dict) -> None:
        """run.json's record of a nowcast-gain swarm (:meth:`describe`): its options as the
        constructor checks them, a sighting probability in [0, 1] and its history's runs (at
        least 1) and traffic seeds."""
        keys = ["weight", "quantile_z", "meas_var", "history_runs", "history_seeds"]
        missing = [k for k in keys if k not in record]
        if missing:
            raise UserError(f"records no {missing[0]}")
        check_options(record["weight"], record["quantile_z"], record["meas_var"])
        p = record.get("sighting_count_p", 1.0)  # recorded since sighting models
        runs, seeds = record["history_runs"], record["history_seeds"]
        if isinstance(p, bool) or not isinstance(p, int | float) or not 0 <= p <= 1:
            raise UserError(f"sighting_count_p = {str(p)[:40]} must be a number in [0, 1]")
        if isinstance(runs, bool) or not isinstance(runs, int) or runs < 1:
            raise UserError(f"history_runs = {str(runs)[:40]} must be a whole number of at least 1")
        if not isinstance(seeds, list) or not all(
            isinstance(s, int) and not isinstance(s, bool) for s in seeds
        ):
            raise UserError(f"history_seeds = {str(seeds)[:40]} must be a list of seeds")

    def describe(self) -> dict:
        return {
            "weight": self.weight,
            "quantile_z": self.quantile_z,
            "meas_var": self.meas_var,  # None: the sighting model's
            "sighting_count_p": self.sighting.count_p,
            "history_runs": self.history.n_runs,
            "history_seeds": list(self.history.traffic_seeds),
        }

    def sight(self, view: SwarmView) -> None:
        """Advance the filter to step ``k`` and update it on the cells the drones see."""
        self.history.check_horizon(self.history.named(self.name), view.horizon)
        grid = view.grid
        self.filter.advance(view.k)
        flat, valid = grid.view_index(view.positions)
        cells = np.unique(flat[valid])
        cells = cells[self.free[cells]]
        self.filter.observe(cells, np.asarray(view.importance, dtype=np.float64).ravel()[cells])

    def scores(self, view: SwarmView) -> np.ndarray:
        self.sight(view)
        grid, p = view.grid, view.params
        mean, prior_var = self.filter.predicted()
        quantile = np.minimum(1.0, mean + self.quantile_z * np.sqrt(prior_var))
        cells = np.arange(len(mean))
        meas_var = self.filter.measurement_variance(mean, cells)
        values = information_values(
            quantile, prior_var, self.filter.rho, meas_var, view.horizon - view.k
        )
        values = np.where(self.free, values, 0.0)
        fov = grid.view_index(view.positions)  # the cells each action leads to
        weight = p.alpha_T * grid.values_in_view(mean, None, fov) + p.alpha_I
        gain = visit_gain(weight, grid.values_in_view(view.idleness, None, fov), p)
        if self.weight == 0.0:
            return gain
        typical = values[self.free].mean() if self.free.any() else 0.0
        if typical <= 0.0:
            return gain
        info = self.view_sums(values / (VIEW_CELLS * typical), view)
        return gain + self.weight * info

    def view_sums(self, values: np.ndarray, view: SwarmView) -> np.ndarray:
        """``(N, 5)``: for each drone and action, the sum of ``values`` (flat) over the field of
        view of the cell the action leads to (off-map cells count 0; infeasible actions are
        masked by the coordinator)."""
        grid = view.grid
        padded = np.pad(values.reshape(grid.shape), 2)
        sums = np.zeros(padded.shape)
        for di, dj in ((0, 0), (-1, 0), (1, 0), (0, -1), (0, 1)):
            sums += np.roll(padded, (-di, -dj), axis=(0, 1))
        pos = np.asarray(view.positions, dtype=np.int64)
        cells = pos[:, None, :] + ACTION_DELTAS[None, :, :] + 2  # padded coordinates
        return sums[cells[..., 0], cells[..., 1]]
