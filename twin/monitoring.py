"""Monitoring against ground truth, computed after a run from a :class:`PatrolResult`.

A twin knows the truth, so it can score what a traffic monitor is for (project notes,
"Monitoring against ground truth"):

- **Belief map** of a swarm: for each cell the last value its drones observed in their field of
  view Adj(p) (Def. 2: the cell and its 4 neighbours), through the observation model, i.e. the
  ``importance`` the drones saw. A cell not yet seen counts as 0, "believed free-flowing" (the
  operator's default assumption; idleness 1 already says it is unknown). The belief error at
  step k is the importance-weighted mean absolute error over free cells,
  ``sum w |B^k - T_true^k| / sum w`` with ``w = max(T_true^k, floor)``: congested cells weigh
  most, and the floor keeps a stale "congested" belief on a now free cell from costing nothing.
  On an all-zero truth every weight is the floor, so the error is the plain MAE.
- **Congestion events**: maximal runs of steps in which a free cell's true importance stays
  ``>= threshold``. Default 0.5: under the MFD observation model ``T = 1 - v / (a v_lim)`` the
  cell's MFD speed has fallen to half its free-flow value ``a v_lim``. A swarm *sees* an event
  when a drone's field of view covers the cell at a step while the event lasts; its latency is
  the first such step minus the onset.
- **Incidents** (scheduled in SUMO, :mod:`twin.sumo.incidents`): ground-truth events with a
  cell and the steps ``onset .. end`` they last; scored like congestion events
  (:func:`incident_sightings`): share seen while they last, latency from onset to first sighting.
- **Coverage reference** ``C_hat_T`` of drones that jump, each step, to the N freshest
  distinct free cells (Def. 3 and Def. 5 rules). Not a bound: a visit removes
  ``min(1, I + delta) - eta I``, which is largest just below ``I = 1 - delta``, so swarms that
  pace their revisits can exceed it slightly (the synthetic map's lookahead: 0.1105 against
  0.1104).

Steps: the drones stand on ``P_k`` and see ``T^k`` for k = 0..T. Run averages use k = 1..T (the
steps the swarm chose), like ``C_hat_T``; events are found over k = 0..T.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import pandas as pd

from twin.grid import Grid
from twin.scores import coverage, initial_idleness, update_idleness

#: Default event threshold: MFD speed at half its free-flow value (T = 1 - v / (a v_lim)).
DEFAULT_THRESHOLD = 0.5
#: Default floor of the belief-error weights.
DEFAULT_WEIGHT_FLOOR = 0.05

EVENT_COLUMNS = ("i", "j", "onset", "duration", "peak")


@dataclass(frozen=True)
class MonitorSettings:
    """Event threshold on true importance, shortest event counted (steps), weight floor."""

    threshold: float = DEFAULT_THRESHOLD
    min_duration: int = 1
    weight_floor: float = DEFAULT_WEIGHT_FLOOR

    def __post_init__(self) -> None:
        if not 0.0 < self.threshold <= 1.0:
            raise ValueError(f"threshold = {self.threshold} must lie in (0, 1]")
        if self.min_duration < 1:
            raise ValueError(f"min_duration = {self.min_duration} must be >= 1")
        if self.weight_floor <= 0.0:
            raise ValueError(f"weight_floor = {self.weight_floor} must be > 0")


def sightings(grid: Grid, positions: np.ndarray, recorded: np.ndarray | None = None) -> np.ndarray:
    """Sorted unique keys ``cell * (T+1) + k`` of every (free cell, step) in some drone's view.

    ``positions`` is one swarm's ``(T+1, N, 2)``; ``cell`` is the flat index ``i * ny + j``.
    ``recorded`` ``(T+1, N, 5)`` bool: the sightings that count (scripted faults,
    :meth:`twin.faults.FaultPlan.recorded`); None: all.
    """
    steps, n_drones, _ = positions.shape
    flat, valid = grid.view_index(positions.reshape(-1, 2))
    k = np.repeat(np.arange(steps), n_drones)[:, None]
    keys = flat * steps + k
    keep = valid & grid.free.ravel()[flat]
    if recorded is not None:
        keep &= recorded[:steps].reshape(-1, 5)
    return np.unique(keys[keep])


def incident_sightings(
    grid: Grid, positions: np.ndarray, incidents: list[dict], recorded: np.ndarray | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """First step at which a drone's field of view covers each incident's cell while it lasts
    (-1 when never) and the latency from onset (-1 when not seen), per incident.

    ``incidents``: dicts with ``cell`` [i, j], ``onset_step`` and ``end_step`` (inclusive);
    ``positions``: one swarm's ``(T+1, N, 2)``.
    """
    steps = positions.shape[0]
    keys = sightings(grid, positions, recorded)
    first = np.full(len(incidents), -1, dtype=np.int64)
    for n, inc in enumerate(incidents):
        i, j = inc["cell"]
        lo, hi = int(inc["onset_step"]), min(int(inc["end_step"]), steps - 1)
        if not (0 <= i < grid.nx and 0 <= j < grid.ny) or lo > hi:
            continue
        base = (i * grid.ny + j) * steps
        at = np.searchsorted(keys, base + lo)
        if at < len(keys) and keys[at] <= base + hi:
            first[n] = keys[at] - base
    onset = np.array([int(inc["onset_step"]) for inc in incidents], dtype=np.int64)
    return first, np.where(first >= 0, first - onset, -1)


def applied_incidents(incidents: list[dict]) -> list[dict]:
    """The incidents that took place: a stopped vehicle never found (``applied_s`` null) left
    nothing on the road for a drone to see, so it is no incident to be seen or missed."""
    return [inc for inc in incidents if inc.get("applied_s", 0.0) is not None]


def incident_scores(first_seen: np.ndarray, latency: np.ndarray, step_s: float | None) -> dict:
    """The incident columns of one swarm: count, % seen, mean latency (steps, minutes)."""
    seen = first_seen >= 0
    lat = latency[seen]
    row = {
        "incidents": len(first_seen),
        "pct_incidents_seen": 100.0 * seen.mean() if len(seen) else np.nan,
        "incident_latency_steps": float(lat.mean()) if len(lat) else np.nan,
    }
    if step_s:
        row["incident_latency_min"] = row["incident_latency_steps"] * step_s / 60.0
    return row


def belief_error_curve(
    grid: Grid,
    positions: np.ndarray,
    observed: np.ndarray,
    truth: np.ndarray,
    floor: float = DEFAULT_WEIGHT_FLOOR,
    recorded: np.ndarray | None = None,
) -> np.ndarray:
    """``(T+1,)`` importance-weighted MAE of the swarm's belief map against the truth, per step.

    ``positions`` ``(T+1, N, 2)``; ``observed`` and ``truth`` ``(T+1, nx, ny)``; ``recorded``
    as in :func:`sightings`. One numpy pass over the cells per step.
    """
    steps = positions.shape[0]
    free = grid.free.ravel()
    belief = np.zeros(grid.nx * grid.ny)
    out = np.empty(steps)
    for k in range(steps):
        flat, valid = grid.view_index(positions[k])
        cells = flat[valid if recorded is None else valid & recorded[k]]
        belief[cells] = observed[k].ravel()[cells]
        true = truth[k].ravel()
        w = np.maximum(true, floor)[free]
        out[k] = float((w * np.abs(belief[free] - true[free])).sum() / w.sum())
    return out


def congestion_events(
    truth: np.ndarray, grid: Grid, threshold: float = DEFAULT_THRESHOLD, min_duration: int = 1
) -> pd.DataFrame:
    """Maximal runs of steps with ``truth >= threshold`` on a free cell, at least
    ``min_duration`` steps long: columns i, j, onset, duration, peak; sorted by onset, cell."""
    steps = truth.shape[0]
    series = truth.reshape(steps, -1).T  # (cells, T+1)
    hot = (series >= threshold) & grid.free.ravel()[:, None]
    padded = np.zeros((hot.shape[0], steps + 2), dtype=np.int8)
    padded[:, 1:-1] = hot
    edges = np.diff(padded, axis=1)
    cell, onset = np.nonzero(edges == 1)  # row-major: by cell, then time
    _, end = np.nonzero(edges == -1)  # one past the last hot step, paired in the same order
    duration = end - onset
    keep = duration >= min_duration
    cell, onset, end, duration = cell[keep], onset[keep], end[keep], duration[keep]
    if len(cell):
        flat = np.append(series.ravel(), 0.0)
        bounds = np.stack([cell * steps + onset, cell * steps + end], axis=1).ravel()
        peak = np.maximum.reduceat(flat, bounds)[::2]
    else:
        peak = np.zeros(0)
    frame = pd.DataFrame(
        {
            "i": cell // grid.ny,
            "j": cell % grid.ny,
            "onset": onset,
            "duration": duration,
            "peak": peak.astype(np.float64),
        }
    )
    return frame.sort_values(["onset", "i", "j"], kind="stable", ignore_index=True)


def event_sightings(
    events: pd.DataFrame, keys: np.ndarray, steps: int, ny: int
) -> tuple[np.ndarray, np.ndarray]:
    """Per event: first step its cell was in view while it lasted (-1 if never), and the number
    of its steps in view. ``keys`` from :func:`sightings` with ``steps = T+1``."""
    cell = events["i"].to_numpy(np.int64) * ny + events["j"].to_numpy(np.int64)
    start = cell * steps + events["onset"].to_numpy(np.int64)
    stop = start + events["duration"].to_numpy(np.int64)
    lo = np.searchsorted(keys, start, side="left")
    hi = np.searchsorted(keys, stop, side="left")
    seen = hi > lo
    if not len(keys):
        return np.full(len(cell), -1, np.int64), np.zeros(len(cell), np.int64)
    first = np.where(seen, keys[np.minimum(lo, len(keys) - 1)] - cell * steps, -1)
    return first.astype(np.int64), (hi - lo).astype(np.int64)


def ceiling_coverage(
    grid: Grid, n_drones: int, eta: float, delta: float, horizon: int
) -> np.ndarray:
    """``(T,)`` coverage ``C^1 .. C^T`` (Def. 5) of the jumping oracle.

    Each step the N drones go to the N free cells of highest idleness ``I^k`` (ties by flat
    index), then Def. 3 updates the map. Visiting cell c removes ``min(1, I + delta) - eta I``,
    which grows with ``I`` up to ``1 - delta`` and falls after it, so this is a reference, not
    a bound: it ignores that drones move one cell per step, and swarms that pace their
    revisits can exceed it slightly.
    """
    free_idx = np.flatnonzero(grid.free.ravel())
    n = min(n_drones, len(free_idx))
    idle = initial_idleness(grid)
    out = np.empty(horizon)
    for k in range(horizon):
        values = idle.ravel()[free_idx]
        if n < len(values):
            nth = np.partition(values, len(values) - n)[len(values) - n]
            above = np.flatnonzero(values > nth)
            ties = np.flatnonzero(values == nth)[: n - len(above)]
            chosen = free_idx[np.concatenate([above, ties])]
        else:
            chosen = free_idx
        cells = np.stack([chosen // grid.ny, chosen % grid.ny], axis=1)
        idle = update_idleness(idle, cells, grid, eta, delta)
        out[k] = coverage(idle, grid)
    return out


@dataclass
class RunMonitoring:
    """Monitoring of every swarm of one run (one seed)."""

    swarms: list[str]
    seed: int
    events: pd.DataFrame  # EVENT_COLUMNS
    belief_error: np.ndarray  # (S, T+1)
    first_seen: np.ndarray  # (S, E) step, -1 when not seen while the event lasted
    steps_seen: np.ndarray  # (S, E) steps of the event with its cell in view
    incidents: list[dict] | None = None  # the scheduled incidents applied (ground truth)
    incident_first_seen: np.ndarray | None = None  # (S, I) step, -1 when not seen
    incident_latency: np.ndarray | None = None  # (S, I) steps, -1 when not seen

    def table(self, step_s: float | None = None) -> pd.DataFrame:
        """One row per swarm: the monitoring columns (latency in minutes when ``step_s``)."""
        durations = self.events["duration"].to_numpy()
        onset = self.events["onset"].to_numpy()
        rows = []
        for s, swarm in enumerate(self.swarms):
            seen = self.first_seen[s] >= 0
            latency = (self.first_seen[s] - onset)[seen]
            row = {
                "swarm": swarm,
                "belief_error": _mean(self.belief_error[s, 1:]),
                "events": len(durations),
                "pct_events_seen": 100.0 * seen.mean() if len(seen) else np.nan,
                "latency_median_steps": float(np.median(latency)) if len(latency) else np.nan,
                "latency_p90_steps": float(np.percentile(latency, 90)) if len(latency) else np.nan,
                "pct_congested_observed": (
                    100.0 * self.steps_seen[s].sum() / durations.sum() if len(durations) else np.nan
                ),
            }
            if step_s:
                row["latency_median_min"] = row["latency_median_steps"] * step_s / 60.0
                row["latency_p90_min"] = row["latency_p90_steps"] * step_s / 60.0
            if self.incidents is not None:  # (none applied: 0 incidents)
                row |= incident_scores(
                    self.incident_first_seen[s], self.incident_latency[s], step_s
                )
            rows.append(row)
        return pd.DataFrame(rows)

    def events_frame(self) -> pd.DataFrame:
        """Long format: one row per (event, swarm) with seen, first_seen and latency_steps."""
        n_events = len(self.events)
        base = self.events.assign(seed=self.seed, event=np.arange(n_events))
        parts = []
        for s, swarm in enumerate(self.swarms):
            first = self.first_seen[s]
            parts.append(
                base.assign(
                    swarm=swarm,
                    seen=first >= 0,
                    first_seen=first,
                    latency_steps=np.where(first >= 0, first - base["onset"].to_numpy(), -1),
                )
            )
        columns = ["seed", "event", *EVENT_COLUMNS, "swarm", "seen", "first_seen", "latency_steps"]
        if not parts:
            return pd.DataFrame(columns=columns)
        return pd.concat(parts, ignore_index=True)[columns]


def _mean(values: np.ndarray) -> float:
    return float(values.mean()) if len(values) else np.nan


def monitor_run(result, settings: MonitorSettings | None = None) -> RunMonitoring:
    """The monitoring of every swarm of ``result`` (a PatrolResult that kept its importance).

    The truth is ``result.truth`` when the run recorded one, else what the drones observed.
    """
    settings = settings or MonitorSettings()
    observed = result.importance
    if observed is None:
        raise ValueError("monitoring needs the run's importance maps (keep_importance=True)")
    truth = result.truth
    truth = observed if truth is None else truth
    grid = result.grid
    positions = result.positions
    steps = positions.shape[1]
    observed, truth = observed[:steps], truth[:steps]
    events = congestion_events(truth, grid, settings.threshold, settings.min_duration)
    n_swarms = len(result.swarms)
    belief = np.zeros((n_swarms, steps))
    first = np.zeros((n_swarms, len(events)), dtype=np.int64)
    seen_steps = np.zeros((n_swarms, len(events)), dtype=np.int64)
    faults = getattr(result, "faults", None)
    recorded = None
    if faults is not None:
        recorded = faults.recorded(result.seed, steps, positions.shape[2])
    for s in range(n_swarms):
        belief[s] = belief_error_curve(
            grid, positions[s], observed, truth, settings.weight_floor, recorded
        )
        keys = sightings(grid, positions[s], recorded)
        first[s], seen_steps[s] = event_sightings(events, keys, steps, grid.ny)
    scheduled = (getattr(result, "extra", None) or {}).get("incidents") or None
    incidents = None if scheduled is None else applied_incidents(scheduled)
    inc_first = inc_latency = None
    if incidents is not None:
        pairs = [
            incident_sightings(grid, positions[s], incidents, recorded) for s in range(n_swarms)
        ]
        inc_first = np.array([p[0] for p in pairs]).reshape(n_swarms, len(incidents))
        inc_latency = np.array([p[1] for p in pairs]).reshape(n_swarms, len(incidents))
    return RunMonitoring(
        list(result.swarms),
        result.seed,
        events,
        belief,
        first,
        seen_steps,
        incidents,
        inc_first,
        inc_latency,
    )
