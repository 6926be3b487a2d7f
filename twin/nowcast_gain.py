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

import numpy as np
from scipy.special import ndtr

from twin.belief import EXACT_SIGHTINGS, Z90, History, NowcastFilter, SightingModel
from twin.errors import UserError
from twin.grid import ACTION_DELTAS, Grid
from twin.monitoring import DEFAULT_THRESHOLD
from twin.planners import CoordinatedPolicy
from twin.policies import SwarmView
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
        for key, value, lo, hi in (
            ("weight", weight, 0.0, 1e6),
            ("quantile_z", quantile_z, 0.0, 10.0),
            *([("meas_var", meas_var, 1e-12, 1.0)] if meas_var is not None else []),
        ):
            if isinstance(value, bool) or not isinstance(value, int | float | np.floating):
                raise UserError(f"nowcast-gain: {key} = {value!r} must be a number")
            if not lo <= float(value) <= hi:
                raise UserError(f"nowcast-gain: {key} = {value} must lie in [{lo:g}, {hi:g}]")
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
        if h.shape != grid.shape or not np.array_equal(h.obstacles, grid.obstacles):
            raise UserError(
                f"nowcast-gain: the history's grid {h.shape[0]} x {h.shape[1]} (or obstacles) "
                f"differs from the run's {grid.nx} x {grid.ny}; build it from runs of this scenario"
            )
        self.filter = NowcastFilter(h, self.meas_var, self.sighting)
        self.free = grid.free.ravel()

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
        if view.horizon != self.history.horizon:
            raise UserError(
                f"nowcast-gain: the history's horizon T = {self.history.horizon} differs from "
                f"the run's T = {view.horizon}; build it from runs of this scenario"
            )
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


class NowcastEventsPolicy(NowcastGainPolicy):
    """:class:`NowcastGainPolicy` aimed at congestion events: the move to ``p'`` is scored

    ``S(p') = g(p') + w * sum_{c in Adj(p')} e_c``,
    ``e_c = P(T_c^{k+1} >= theta) [That_c < theta] (1 - known_c)``:

    the chance, under the nowcast's prediction of step ``k + 1`` (mean ``That``, std
    ``sigma^-``, normal), that the cell is congested (``theta`` the monitoring threshold) and
    the swarm does not know it yet: its belief is below ``theta`` (a belief at or above it
    already knows the event) and its last sighting of the cell read below ``theta``
    (``known_c``: an event it has seen and not seen end; the filter alone forgets it within a
    step when ``rho`` is small). ``e_c`` is a probability: ``w`` is the visit gain one expected
    unknown event is worth. ``g`` is :class:`NowcastGainPolicy`'s visit gain on ``That``.
    """

    name = "nowcast-events"

    def __init__(
        self,
        history: History | str | Path | None = None,
        weight: float = 1.0,
        threshold: float = DEFAULT_THRESHOLD,
        meas_var: float | None = None,
    ):
        super().__init__(history, weight, DEFAULT_QUANTILE_Z, meas_var)
        if isinstance(threshold, bool) or not isinstance(threshold, int | float | np.floating):
            raise UserError(f"nowcast-events: threshold = {threshold!r} must be a number")
        if not 0.0 < float(threshold) <= 1.0:
            raise UserError(f"nowcast-events: threshold = {threshold} must lie in (0, 1]")
        self.threshold = float(threshold)

    def reset(self, grid: Grid, n_drones: int, rng: np.random.Generator) -> None:
        super().reset(grid, n_drones, rng)
        self.known = np.zeros(grid.nx * grid.ny, dtype=bool)

    def describe(self) -> dict:
        out = super().describe()
        del out["quantile_z"]
        return {**out, "threshold": self.threshold}

    def sight(self, view: SwarmView) -> None:
        super().sight(view)
        flat, valid = view.grid.view_index(view.positions)
        cells = np.unique(flat[valid])
        cells = cells[self.free[cells]]
        seen = np.asarray(view.importance, dtype=np.float64).ravel()[cells]
        self.known[cells] = seen >= self.threshold

    def event_values(self) -> np.ndarray:
        """``(nx*ny,)`` ``e_c``: the chance of an unknown congestion event at step ``k + 1``."""
        mean, prior_var = self.filter.predicted()
        std = np.sqrt(np.maximum(prior_var, 0.0))
        with np.errstate(divide="ignore", invalid="ignore"):
            above = np.where(
                std > 0, ndtr((mean - self.threshold) / np.where(std > 0, std, 1.0)), 0.0
            )
        above = np.where(mean >= self.threshold, 0.0, above)
        return np.where(self.free & ~self.known, above, 0.0)

    def scores(self, view: SwarmView) -> np.ndarray:
        self.sight(view)
        grid, p = view.grid, view.params
        mean, _ = self.filter.predicted()
        fov = grid.view_index(view.positions)
        weight = p.alpha_T * grid.values_in_view(mean, None, fov) + p.alpha_I
        gain = visit_gain(weight, grid.values_in_view(view.idleness, None, fov), p)
        if self.weight == 0.0:
            return gain
        return gain + self.weight * self.view_sums(self.event_values(), view)
