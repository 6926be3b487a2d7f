"""Faults scripted in a scenario's ``[faults]`` table, applied to every swarm of a run.

- **Drone loss** (``[[faults.drone_loss]]``: ``drone``, ``step``, optional ``back``): the
  drone is lost for the steps ``step <= k < back`` (to the end without ``back``). A lost drone
  neither moves, sees nor scores: it stays on the cell where it was lost, the swarm's policy
  and coordinator plan for the live drones only, its arrivals are not paid and do not reset
  idleness (Def. 3, Def. 4), and monitoring counts none of its sightings. Back at ``back``, it
  resumes from that cell.
- **Coordinator down** (``coordinator_down = [[start, stop], ...]``): steps ``start <= k <
  stop`` without the central coordinator (eq. maxi:op2). The learned swarms switch to their
  outage mode (own idleness maps, epsilon-greedy; :mod:`twin.idleness_maps`); the classical
  swarms that use the coordinator let each drone take its own best-scored move, collisions
  unresolved; swarms without a coordinator (random, greedy, sweeping) are unaffected.
- **Detection probability** (``detection_p`` < 1): each (drone, step, cell of its field of
  view) sighting is recorded with probability p, drawn from the run's seed (the same draws for
  every swarm). An unrecorded sighting of the drone's own cell is a visit the swarm does not
  know of (no idleness reset, no pay); an unrecorded sighting of any cell of the view is not a
  sighting for monitoring. The traffic (ground truth) is untouched.

A drone is live at step ``k`` when no loss window holds it: it then acts at ``k``, and its
arrival and sighting at ``P_{k+1}`` count when the draw records them. So a drone lost at ``s``
still arrives at ``P_s`` (its last move), and one back at ``b`` first counts at ``P_{b+1}``:
each phase's scores come from the moves made in it. The fault-free twin of each swarm runs in the
same pass over the same traffic (:func:`twin.patrol.run_patrol`), so each phase of the run
(between two changes of the faults) can be compared with the same swarm without faults.
"""

from __future__ import annotations

import itertools
import zlib
from dataclasses import dataclass, field

import numpy as np

from twin.grid import Grid
from twin.policies import Policy, SwarmView, Transition

#: Index of the "stay" action (:data:`twin.grid.ACTIONS`): what a lost drone does.
STAY = 0


@dataclass(frozen=True)
class DroneLoss:
    """Drone ``drone`` lost for the steps ``step <= k < back`` (``back`` None: to the end)."""

    drone: int
    step: int
    back: int | None = None

    def holds(self, k: int) -> bool:
        return self.step <= k and (self.back is None or k < self.back)


@dataclass(frozen=True)
class FaultPlan:
    """The faults of a run; :meth:`active` is False for a plan that changes nothing."""

    drone_loss: tuple[DroneLoss, ...] = ()
    coordinator_down: tuple[tuple[int, int], ...] = ()
    detection_p: float = 1.0
    _cache: dict = field(default_factory=dict, compare=False, repr=False)

    @property
    def active(self) -> bool:
        return bool(self.drone_loss or self.coordinator_down or self.detection_p < 1.0)

    def live(self, k: int, n_drones: int) -> np.ndarray:
        """``(N,)`` bool: the drones live at step ``k``."""
        live = np.ones(n_drones, dtype=bool)
        for loss in self.drone_loss:
            if loss.holds(k) and loss.drone < n_drones:
                live[loss.drone] = False
        return live

    def live_steps(self, steps: int, n_drones: int) -> np.ndarray:
        """``(steps, N)`` bool: :meth:`live` at ``k = 0 .. steps - 1``."""
        live = np.ones((steps, n_drones), dtype=bool)
        for loss in self.drone_loss:
            if loss.drone < n_drones:
                stop = steps if loss.back is None else min(loss.back, steps)
                live[loss.step : stop, loss.drone] = False
        return live

    def flown_steps(self, steps: int, n_drones: int) -> np.ndarray:
        """``(steps, N)`` bool: the drones that flew to ``P_k``, live at step ``k - 1`` (at
        ``k = 0``: live at 0). Their arrival and sighting at ``P_k`` count; a drone lost at
        ``s`` still arrives at ``P_s``, a drone back at ``b`` first counts at ``P_{b+1}``."""
        live = self.live_steps(steps, n_drones)
        return np.concatenate([live[:1], live[:-1]]) if steps else live

    def detected(self, seed: int, steps: int, n_drones: int) -> np.ndarray | None:
        """``(steps, N, 5)`` bool: which sightings of the fields of view are recorded (None:
        all of them, p = 1). Drawn from ``seed`` alone: the same for every swarm."""
        if self.detection_p >= 1.0:
            return None
        key = (seed, steps, n_drones)
        if key not in self._cache:
            rng = np.random.default_rng([seed, zlib.crc32(b"detection")])
            self._cache[key] = rng.random((steps, n_drones, 5)) < self.detection_p
        return self._cache[key]

    def recorded(self, seed: int, steps: int, n_drones: int) -> np.ndarray | None:
        """``(steps, N, 5)`` bool: the sightings that count (a drone that flew to its cell, a
        recorded draw); None when every sighting counts."""
        if not self.drone_loss and self.detection_p >= 1.0:
            return None
        live = self.flown_steps(steps, n_drones)[:, :, None]
        detected = self.detected(seed, steps, n_drones)
        return np.broadcast_to(live, (steps, n_drones, 5)) & (
            True if detected is None else detected
        )

    def down(self, k: int) -> bool:
        """Whether the coordinator is down at step ``k``."""
        return any(start <= k < stop for start, stop in self.coordinator_down)

    def change_points(self, horizon: int) -> list[int]:
        """Steps in ``1 .. horizon - 1`` at which a fault starts or ends."""
        points = set()
        for loss in self.drone_loss:
            points.add(loss.step)
            if loss.back is not None:
                points.add(loss.back)
        for start, stop in self.coordinator_down:
            points.update((start, stop))
        return sorted(p for p in points if 0 < p < horizon)

    def phases(self, horizon: int, n_drones: int) -> list[tuple[int, int, str]]:
        """The run cut at every change of the faults: ``(start, stop, label)`` over the steps
        ``start <= k < stop`` of ``0 .. horizon - 1`` (the label says what holds in it)."""
        cuts = [0, *self.change_points(horizon), horizon]
        phases = []
        for start, stop in itertools.pairwise(cuts):
            lost = int((~self.live(start, n_drones)).sum())
            parts = []
            if lost:
                parts.append(f"{lost} of {n_drones} drones lost")
            if self.down(start):
                parts.append("coordinator down")
            if not parts:
                quiet = self.coordinator_down and not self.drone_loss
                parts.append("coordinator up" if quiet else "no drone lost")
            if self.detection_p < 1.0:
                parts.append(f"sightings at p = {self.detection_p:g}")
            phases.append((start, stop, ", ".join(parts)))
        return phases

    def describe(self) -> dict:
        """What ``run.json`` records of the faults (JSON)."""
        return {
            "drone_loss": [
                {"drone": d.drone, "step": d.step, "back": d.back} for d in self.drone_loss
            ],
            "coordinator_down": [list(w) for w in self.coordinator_down],
            "detection_p": self.detection_p,
        }

    @classmethod
    def from_record(cls, record: dict | None) -> FaultPlan | None:
        """The plan :meth:`describe` wrote (None when the run had none)."""
        if not record:
            return None
        return cls(
            drone_loss=tuple(DroneLoss(**d) for d in record.get("drone_loss", [])),
            coordinator_down=tuple(tuple(w) for w in record.get("coordinator_down", [])),
            detection_p=float(record.get("detection_p", 1.0)),
        )


def recorded_arrivals(
    plan: FaultPlan | None, seed: int, k: int, n_drones: int, horizon: int
) -> np.ndarray | None:
    """``(N,)`` bool: the drones whose arrival at ``P_k`` (``k >= 1``) is recorded (live at
    ``k - 1``, :meth:`FaultPlan.flown_steps`; own-cell sighting drawn); None when every
    arrival is."""
    if plan is None or (not plan.drone_loss and plan.detection_p >= 1.0):
        return None
    rec = plan.live(k - 1, n_drones)
    detected = plan.detected(seed, horizon + 1, n_drones)
    if detected is not None:
        rec &= detected[k, :, STAY]  # slot 0 of the field of view is the drone's own cell
    return rec


def live_view(view: SwarmView, live: np.ndarray) -> SwarmView:
    """The view of the live drones alone."""
    return SwarmView(
        k=view.k,
        horizon=view.horizon,
        grid=view.grid,
        positions=view.positions[live],
        idleness=view.idleness,
        importance=view.importance,
        feasible=view.feasible[live],
        params=view.params,
        recorded=None if view.recorded is None else view.recorded[live],
        visits=view.recorded_visits(),
    )


class LiveDrones(Policy):
    """A swarm's policy run on its live drones only: lost drones stay where they are and the
    policy (its coordinator included) sees and plans for the others. When the set of live
    drones changes, the policy is told by :meth:`Policy.drones_changed`."""

    def __init__(self, inner: Policy, plan: FaultPlan) -> None:
        self.inner = inner
        self.plan = plan
        self.name = inner.name

    def reset(self, grid: Grid, n_drones: int, rng: np.random.Generator) -> None:
        super().reset(grid, n_drones, rng)
        self.live = self.plan.live(0, n_drones)
        self.inner.reset(grid, int(self.live.sum()), rng)

    def act(self, view: SwarmView) -> np.ndarray:
        live = self.plan.live(view.k, self.n_drones)
        if not np.array_equal(live, self.live):
            self.inner.drones_changed(self.live, live)
            self.live = live
        actions = np.full(self.n_drones, STAY, dtype=np.int64)
        if live.any():
            actions[live] = np.asarray(self.inner.act(live_view(view, live)), dtype=np.int64)
        return actions

    def learn(self, transition: Transition) -> None:
        live = self.live
        if not live.any():
            return
        self.inner.learn(
            Transition(
                live_view(transition.view, live),
                transition.actions[live],
                transition.rewards[live],
                live_view(transition.next_view, live),
            )
        )


#: Columns of ``degradation.csv``: one row per seed, swarm and phase of the faults.
DEGRADATION_COLUMNS = (
    "seed", "swarm", "phase", "label", "start", "stop", "R_hat", "R_hat_fault_free",
    "events", "pct_events_seen", "pct_events_seen_fault_free", "latency_median_steps",
    "latency_median_steps_fault_free", "pct_congested_observed",
    "pct_congested_observed_fault_free",
)  # fmt: skip


def phase_events(events, start: int, stop: int):
    """The congestion events that last into the steps ``start <= k < stop``, cut to them (an
    event under way at ``start`` counts from ``start``)."""
    onset = events["onset"].to_numpy()
    end = onset + events["duration"].to_numpy()
    cut_onset, cut_end = np.maximum(onset, start), np.minimum(end, stop)
    keep = cut_end > cut_onset
    return events[keep].assign(onset=cut_onset[keep], duration=(cut_end - cut_onset)[keep])


def degradation_frame(result, events):
    """``degradation.csv``'s rows of one seed's result and its fault-free twin
    (``result.fault_free``: same traffic, same seed), :func:`degradation_table`."""
    twin = result.fault_free
    return degradation_table(
        result.seed, result.swarms, result.grid, result.faults, events,
        result.positions, result.rewards, twin.positions, twin.rewards,
    )  # fmt: skip


def degradation_table(
    seed, swarms, grid, plan, events, positions, rewards, free_positions, free_rewards
):
    """Per swarm and phase of the faults (:meth:`FaultPlan.phases`, then the whole run), under
    the faults (``positions`` ``(S, T+1, N, 2)``, ``rewards`` ``(S, T)``) and in the fault-free
    twin (``free_positions``, ``free_rewards``; a NaN reward: not known):

    - ``R_hat``: the mean score per step ``R^k`` over the phase's steps;
    - the congestion events (``events``, :func:`twin.monitoring.congestion_events`) that last
      into the phase, cut to it: the share seen in the phase, the median latency from the
      event's start in the phase to its first sighting that counts, and the share of their
      cell-steps in view.

    ``twin report`` recomputes the table with it from the run folder (:mod:`twin.report.load`)."""
    import pandas as pd

    from twin.monitoring import event_sightings, sightings

    steps = rewards.shape[1]
    n_steps, n_drones = positions.shape[1], positions.shape[2]
    phases = plan.phases(steps, n_drones) if steps else []
    if len(phases) > 1:
        phases.append((0, steps, "whole run"))
    recorded = plan.recorded(seed, n_steps, n_drones)
    rows = []
    for s, swarm in enumerate(swarms):
        keys = {
            "": sightings(grid, positions[s], recorded),
            "_fault_free": sightings(grid, free_positions[s]),
        }
        for p, (start, stop, label) in enumerate(phases):
            cut = phase_events(events, start, stop)
            row = {"seed": seed, "swarm": swarm, "phase": p + 1, "label": label,
                   "start": start, "stop": stop,
                   "R_hat": float(rewards[s, start:stop].mean()),
                   "R_hat_fault_free": float(free_rewards[s, start:stop].mean()),
                   "events": len(cut)}  # fmt: skip
            for suffix, k in keys.items():
                first, seen_steps = event_sightings(cut, k, n_steps, grid.ny)
                seen = first >= 0
                latency = (first - cut["onset"].to_numpy())[seen]
                row[f"pct_events_seen{suffix}"] = 100.0 * seen.mean() if len(seen) else np.nan
                row[f"latency_median_steps{suffix}"] = (
                    float(np.median(latency)) if len(latency) else np.nan
                )
                total = cut["duration"].sum()
                row[f"pct_congested_observed{suffix}"] = (
                    100.0 * seen_steps.sum() / total if total else np.nan
                )
            rows.append(row)
    return pd.DataFrame(rows, columns=list(DEGRADATION_COLUMNS))


def format_degradation(frame) -> str:
    """What ``twin evaluate`` and ``twin run`` print of ``degradation.csv``: per swarm and
    phase, ``R_hat`` with the faults / fault-free (change %), means over seeds."""
    keys = ["swarm", "phase", "label", "start", "stop"]
    means = frame.groupby(keys, sort=False).mean(numeric_only=True).reset_index()
    table = {}
    for _, r in means.iterrows():
        change = 100.0 * (r["R_hat"] - r["R_hat_fault_free"]) / r["R_hat_fault_free"]
        column = f"{r['label']} ({int(r['start'])}-{int(r['stop'])})"
        cell = f"{r['R_hat']:.3f} / {r['R_hat_fault_free']:.3f} ({change:+.1f}%)"
        table.setdefault(r["swarm"], {})[column] = cell
    import pandas as pd

    text = pd.DataFrame.from_dict(table, orient="index").to_string()
    seeds = ", ".join(str(s) for s in sorted(set(frame["seed"])))
    return (
        f"Faults: R_hat per phase with the faults / fault-free twin (change), seeds {seeds}; "
        "monitoring per phase in degradation.csv and the report:\n" + text
    )
