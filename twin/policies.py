"""Swarm policies: the interface every swarm implements and the baselines of Sec. IV-A.

- random: a uniform feasible action per drone;
- greedy: move to the cell of Adj(p) with the largest ``I^k T^k`` (ties broken at random);
- sweeping: boustrophedon drones, greedy drones and random drones (see :func:`sweeping_roles`).

A policy decides for all drones at once from a :class:`SwarmView`. The registry of every swarm
by name is :mod:`twin.swarms`.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from twin.errors import UserError
from twin.grid import ACTION_DELTAS, Grid
from twin.paths import free_paths, largest_free_component
from twin.scores import ScoreParams


@dataclass
class SwarmView:
    """What a swarm's policy sees at step ``k``."""

    k: int
    horizon: int
    grid: Grid
    positions: np.ndarray  # (N, 2) int: P_k
    idleness: np.ndarray  # (nx, ny): the swarm's shared map I^k (after step k's reset)
    importance: np.ndarray  # (nx, ny): T^k; policies read it only inside the field of view
    feasible: np.ndarray  # (N, 5) bool: U_d(p)
    params: ScoreParams
    #: (N,) bool: the drones whose arrival at P_k the swarm recorded (None: all of them); a
    #: scripted fault (:mod:`twin.faults`) can leave a visit unrecorded
    recorded: np.ndarray | None = None
    #: (M, 2) the cells whose visit at P_k the swarm recorded, when the view shows only some of
    #: the drones (a drone lost at k still arrived at P_k); None: read them from the drones
    visits: np.ndarray | None = None

    def recorded_visits(self) -> np.ndarray:
        """The cells the swarm recorded a visit of at ``P_k`` (the idleness resets of Def. 3)."""
        if self.visits is not None:
            return self.visits
        return self.positions if self.recorded is None else self.positions[self.recorded]


@dataclass
class Transition:
    """One step of the swarm, handed to :meth:`Policy.learn` after the move."""

    view: SwarmView
    actions: np.ndarray
    rewards: np.ndarray
    next_view: SwarmView


class Policy:
    """Chooses the actions of every drone of a swarm."""

    name = "policy"
    #: step windows ``[start, stop)`` without the central coordinator (``[faults]``)
    outages: tuple[tuple[int, int], ...] = ()

    def reset(self, grid: Grid, n_drones: int, rng: np.random.Generator) -> None:
        self.grid = grid
        self.n_drones = n_drones
        self.rng = rng

    def act(self, view: SwarmView) -> np.ndarray:
        raise NotImplementedError

    def learn(self, transition: Transition) -> None:
        """Online learning hook; baselines do not learn."""

    def drones_changed(self, before: np.ndarray, after: np.ndarray) -> None:
        """The live drones changed from the ``(N,)`` mask ``before`` to ``after`` (a drone lost
        or back, :mod:`twin.faults`): from now on :meth:`act` sees the ``after`` drones, in
        their order. Policies that keep something per drone override this."""
        self.n_drones = int(after.sum())

    def coordinator_down(self, k: int) -> bool:
        """Whether step ``k`` falls in a window without the central coordinator."""
        return any(start <= k < stop for start, stop in self.outages)


def whole_option(swarm: str, key: str, value, low: int, high: int | None, example) -> int:
    """A swarm option that is a whole number in ``low..high`` (``high`` None: no top), or one
    line naming the swarm, key and value (``true`` is not a number)."""
    if isinstance(value, bool) or not isinstance(value, int | np.integer):
        raise UserError(f"{swarm}: {key} = {value!r} must be an integer; e.g. {example}")
    if value < low or (high is not None and value > high):
        span = f"at least {low}" if high is None else f"in {low}..{high}"
        raise UserError(f"{swarm}: {key} = {value} must be {span}; e.g. {example}")
    return int(value)


def number_option(
    swarm: str,
    key: str,
    value,
    low: float,
    high: float = float("inf"),
    example=None,
    low_open: bool = False,
) -> float:
    """A swarm option that is a number in ``[low, high]`` (``(low, high]`` if ``low_open``;
    no top when ``high`` is infinite), or one line naming the swarm, key and value (``true``
    and ``"0.5"`` are not numbers; NaN lies nowhere, infinity neither)."""
    hint = "" if example is None else f"; e.g. {example}"
    if isinstance(value, bool) or not isinstance(value, int | float | np.integer | np.floating):
        raise UserError(f"{swarm}: {key} = {value!r} must be a number{hint}")
    if np.isinf(value):  # (an open top takes any finite number, not infinity)
        raise UserError(f"{swarm}: {key} = {value} must be a finite number{hint}")
    if not (low < value <= high if low_open else low <= value <= high):
        if high == float("inf"):
            span = f"be {'>' if low_open else '>='} {low:g}"
        else:
            span = f"lie in {'(' if low_open else '['}{low:g}, {high:g}]"
        raise UserError(f"{swarm}: {key} = {value} must {span}{hint}")
    return float(value)


def flag_option(swarm: str, key: str, value) -> bool:
    """A swarm option that is true or false (a string such as ``"false"`` is neither)."""
    if not isinstance(value, bool | np.bool_):
        raise UserError(f"{swarm}: {key} = {value!r} must be true or false")
    return bool(value)


def random_feasible(feasible: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """A uniform feasible action for every row of an ``(N, 5)`` mask."""
    return np.argmax(np.where(feasible, rng.random(feasible.shape), -1.0), axis=1)


def argmax_random_ties(scores: np.ndarray, feasible: np.ndarray, rng: np.random.Generator):
    """Row-wise argmax over feasible actions, ties broken uniformly at random."""
    scores = np.where(feasible, scores, -np.inf)
    best = scores == scores.max(axis=1, keepdims=True)
    return random_feasible(best & feasible, rng)


class RandomPolicy(Policy):
    """Each drone takes a uniform feasible action."""

    name = "random"

    def act(self, view: SwarmView) -> np.ndarray:
        return random_feasible(view.feasible, self.rng)


class GreedyPolicy(Policy):
    """Each drone moves to the cell of its field of view with the largest ``I^k T^k``."""

    name = "greedy"

    def act(self, view: SwarmView) -> np.ndarray:
        grid, fov = view.grid, view.grid.view_index(view.positions)
        seen = grid.values_in_view(view.idleness, None, fov) * grid.values_in_view(
            view.importance, None, fov
        )
        return argmax_random_ties(seen, view.feasible, self.rng)


def boustrophedon_tour(grid: Grid) -> np.ndarray:
    """A walk of adjacent free cells that visits every free cell: rows zig-zag left-right.

    Consecutive cells of the zig-zag order that are not neighbours (an obstacle or a cut in
    between) are joined by a shortest path over free cells. Cells cut off from the largest
    connected free area are left out. Returns ``(L, 2)`` cells.
    """
    reachable = largest_free_component(grid)
    order = []
    for i in range(grid.nx):
        cols = np.flatnonzero(reachable[i])
        order.extend((i, j) for j in (cols if i % 2 == 0 else cols[::-1]))
    order = np.array(order, dtype=np.int64)
    if len(order) <= 1:
        return order
    steps = np.abs(np.diff(order, axis=0)).sum(axis=1)
    if np.all(steps == 1):
        return order
    jumps = np.flatnonzero(steps != 1)
    found = free_paths(grid, order[jumps], order[jumps + 1])
    paths = {int(jumps[k]): path for k, path in found.items()}  # by pair of the order
    tour = [order[0]]
    for n, b in enumerate(order[1:]):
        if steps[n] == 1:
            tour.append(b)
        else:
            tour.extend(paths[n][1:])
    return np.array(tour, dtype=np.int64)


def sweeping_roles(n_drones: int) -> tuple[int, int, int]:
    """How many sweeping, greedy and random drones a sweeping swarm of ``n_drones`` has.

    The paper's swarm of 4 is 1 sweeper, 2 greedy, 1 random. For other sizes a quarter of the
    drones sweep (at least one), a quarter move at random (rounded down), the rest are greedy:
    N=1 -> (1, 0, 0), N=2 -> (1, 1, 0), N=4 -> (1, 2, 1), N=8 -> (2, 4, 2).
    """
    n_sweep = max(1, round(n_drones / 4))
    n_random = n_drones // 4
    return n_sweep, n_drones - n_sweep - n_random, n_random


class SweepingPolicy(Policy):
    """The paper's sweeping swarm: zig-zag sweepers plus greedy and random drones.

    Drones ``0 .. n_sweep-1`` sweep, the next ``n_greedy`` are greedy, the rest random. A
    sweeper walks a boustrophedon tour of all free cells back and forth, starting where the
    tour passes its start cell (a sweeper that starts off the tour acts greedily).
    """

    name = "sweeping"

    def reset(self, grid: Grid, n_drones: int, rng: np.random.Generator) -> None:
        super().reset(grid, n_drones, rng)
        self.n_sweep, self.n_greedy, self.n_random = sweeping_roles(n_drones)
        tour = boustrophedon_tour(grid)
        # back and forth: 0 .. L-1 .. 1, so every move is between neighbours
        self.cycle = np.concatenate([tour, tour[-2:0:-1]]) if len(tour) > 1 else tour
        self.phase: np.ndarray | None = None
        self.greedy = GreedyPolicy()
        self.greedy.reset(grid, n_drones, rng)

    def drones_changed(self, before: np.ndarray, after: np.ndarray) -> None:
        """Roles dealt again among the live drones; sweepers rejoin the tour where they are."""
        self.reset(self.grid, int(after.sum()), self.rng)

    def _start_phase(self, starts: np.ndarray) -> np.ndarray:
        key = self.cycle[:, 0] * self.grid.ny + self.cycle[:, 1]
        phase = np.empty(len(starts), dtype=np.int64)
        for n, (i, j) in enumerate(starts):  # once per run, not on the step path
            hits = np.flatnonzero(key == i * self.grid.ny + j)
            phase[n] = hits[0] if len(hits) else 0
        return phase

    def act(self, view: SwarmView) -> np.ndarray:
        actions = self.greedy.act(view)
        s, g = self.n_sweep, self.n_sweep + self.n_greedy
        actions[g:] = random_feasible(view.feasible[g:], self.rng)
        if s:
            if self.phase is None:
                self.phase = self._start_phase(view.positions[:s])
            nxt = self.cycle[(self.phase + 1) % len(self.cycle)]
            step = nxt - view.positions[:s]
            # the action whose delta equals the step; a sweeper off the tour acts greedily
            match = (ACTION_DELTAS[None, :, :] == step[:, None, :]).all(axis=2)
            on_tour = match.any(axis=1) & (np.abs(step).sum(axis=1) <= 1)
            actions[:s] = np.where(on_tour, match.argmax(axis=1), actions[:s])
            self.phase = np.where(on_tour, self.phase + 1, self.phase) % len(self.cycle)
        return actions
