"""State variants: what one drone's Q-network input holds, by name (numpy only).

Every variant builds the ``(N, size)`` states of the drones from what the swarm knows, the
inputs of the paper's 13-value state (eq. s): the grid, the idleness map (the swarm's
``(nx, ny)``, one per drone ``(N, nx, ny)``, or the sparse
:class:`~twin.idleness_maps.OwnMaps` of the decentralized mode), the importance map ``T^k``,
the drones' cells and, optionally, each drone's view of the others' centre of mass. A
checkpoint records the variant it was trained on (``meta["state"]``); the learned swarms build
that variant's states.

- ``paper`` (the default): the 13 values of eq. (s), :func:`twin.scores.drone_states`.
- ``window``: the same quantities over a wider window: ``I*T`` on the 5 x 5 cells around the
  drone instead of its field of view (33 values).
- ``nowcast``: the paper's 13 values plus the nowcast belief's mean and std on the drone's 5
  view cells (23 values). The nowcast (:mod:`twin.belief` ``NowcastFilter``) fuses the
  swarm's sightings with a history of earlier days; its builder takes that belief
  (``belief=(mean, std)``, flat ``(nx*ny,)``, as the filter gives them). Pretraining builds
  the history from the training map's generator on other days (docs/beliefs.md); a learned
  swarm whose checkpoint reads it needs the run's history (``--history``).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from twin.errors import UserError
from twin.grid import Grid
from twin.scores import (
    STATE_LAYOUT,
    assemble_states,
    directional_idleness,
    directional_means,
    drone_states,
    others_centre_of_mass,
)

#: Half-width of the ``window`` variant's square: 2 gives the 5 x 5 cells around the drone.
WINDOW_RADIUS = 2
#: The view cells' names in :func:`twin.grid.Grid.view_index`'s order.
VIEW_CELLS = ("centre", "up", "down", "left", "right")

Builder = Callable[..., np.ndarray]


@dataclass(frozen=True)
class StateVariant:
    """A named state: its values' names in order (``layout``) and the function that builds
    ``(N, len(layout))`` states as ``build(grid, idleness, importance, positions, others)``,
    with a last argument ``belief`` when ``needs_belief``."""

    name: str
    layout: tuple[str, ...]
    build: Builder
    summary: str
    #: the builder also reads the nowcast belief ``(mean, std)`` (:mod:`twin.belief`)
    needs_belief: bool = False

    @property
    def size(self) -> int:
        return len(self.layout)

    def states(
        self,
        grid: Grid,
        idleness,
        importance: np.ndarray,
        positions: np.ndarray,
        others: np.ndarray | None = None,
        belief: tuple[np.ndarray, np.ndarray] | None = None,
    ) -> np.ndarray:
        """The ``(N, size)`` states; ``idleness`` a map, a map per drone, or ``OwnMaps``;
        ``belief`` the nowcast's ``(mean, std)`` per flat cell (read only by a variant that
        ``needs_belief``, which refuses to build without it)."""
        if not self.needs_belief:
            return self.build(grid, idleness, importance, positions, others)
        if belief is None:
            raise ValueError(f"state {self.name!r} needs the nowcast belief (mean, std)")
        return self.build(grid, idleness, importance, positions, others, belief)


def paper_states(
    grid: Grid, idleness, importance: np.ndarray, positions: np.ndarray, others=None
) -> np.ndarray:
    """The 13 values of eq. (s), laid out as :data:`twin.scores.STATE_LAYOUT`: ``i/nx, j/ny``;
    ``I*T`` on the field of view (centre, up, down, left, right; 0 off the map); the mean
    idleness of the free cells strictly below, above, left and right of the drone (0 if none);
    the others' centre of mass over ``(nx, ny)``. ``idleness``: the swarm's map, a dense map
    per drone, or :class:`~twin.idleness_maps.OwnMaps` (read at each drone's view, row and
    column only)."""
    if isinstance(idleness, np.ndarray):
        return drone_states(grid, idleness, importance, positions, others)
    view = grid.view_index(positions)
    flat, valid = view
    idle_seen = np.where(valid, idleness.at(flat), 0.0)
    rows, cols = idleness.rows_and_columns(positions)
    directional = directional_means(rows, cols, grid, positions)
    return assemble_states(grid, importance, positions, view, idle_seen, directional, others)


def window_index(grid: Grid, positions: np.ndarray, radius: int = WINDOW_RADIUS):
    """The ``(2r+1)^2`` cells around each drone as flat indices, row by row (``di`` from
    ``-r`` to ``r``, ``dj`` from ``-r`` to ``r`` within a row): ``(flat, valid)`` ``(N, W)``,
    a cell off the map pointing at the drone's own cell and marked invalid."""
    offsets = np.arange(-radius, radius + 1)
    di, dj = np.repeat(offsets, len(offsets)), np.tile(offsets, len(offsets))
    i = positions[:, 0:1] + di[None, :]
    j = positions[:, 1:2] + dj[None, :]
    valid = (i >= 0) & (i < grid.nx) & (j >= 0) & (j < grid.ny)
    centre = (positions[:, 0] * grid.ny + positions[:, 1])[:, None]
    return np.where(valid, i * grid.ny + j, centre), valid


def window_states(
    grid: Grid, idleness, importance: np.ndarray, positions: np.ndarray, others=None
) -> np.ndarray:
    """``window``: eq. (s)'s quantities with ``I*T`` read over the 5 x 5 cells around the
    drone (:func:`window_index`'s order; 0 off the map and on obstacles, as eq. (s) has 0 off
    the map and an obstacle's idleness is 0) instead of its 5-cell field of view. Values:
    ``i/nx, j/ny``; 25 ``I*T``; the four directional mean idlenesses of eq. (s); the others'
    centre of mass over ``(nx, ny)``. All in [0, 1]."""
    positions = np.asarray(positions)
    flat, valid = window_index(grid, positions)
    if isinstance(idleness, np.ndarray) and idleness.ndim == 2:
        idle = idleness.ravel()[flat]
        directional = directional_idleness(idleness, grid, positions)
    elif isinstance(idleness, np.ndarray):
        idle = idleness.reshape(len(idleness), -1)[np.arange(len(positions))[:, None], flat]
        directional = directional_idleness(idleness, grid, positions)
    else:
        idle = idleness.at(flat)
        rows, cols = idleness.rows_and_columns(positions)
        directional = directional_means(rows, cols, grid, positions)
    seen = np.where(valid, idle * importance.ravel()[flat] * grid.free_float.ravel()[flat], 0.0)
    scale = np.array([grid.nx, grid.ny], dtype=np.float64)
    cm = others_centre_of_mass(positions) if others is None else others
    return np.concatenate([positions / scale, seen, directional, cm / scale], axis=1)


def _window_layout(radius: int = WINDOW_RADIUS) -> tuple[str, ...]:
    offsets = range(-radius, radius + 1)
    cells = tuple(f"IT[{di:+d},{dj:+d}]" for di in offsets for dj in offsets)
    return (*STATE_LAYOUT[:2], *cells, *STATE_LAYOUT[7:])


def nowcast_states(
    grid: Grid,
    idleness,
    importance: np.ndarray,
    positions: np.ndarray,
    others,
    belief: tuple[np.ndarray, np.ndarray],
) -> np.ndarray:
    """``nowcast``: the 13 values of eq. (s) (:func:`paper_states`), then the nowcast's mean
    on the drone's 5 view cells (:data:`VIEW_CELLS` order), then its std there scaled as
    ``min(1, 2 std)``; 0 off the map and on obstacles. ``belief``: ``(mean, std)``, flat
    ``(nx*ny,)``. The mean is an importance, in [0, 1]; an importance in [0, 1] has a std of
    at most 1/2 (Popoviciu's bound), so ``2 std`` lies in [0, 1] for any belief that knows
    the value's range (the filter's prior is the history's spread of such values; the clip
    guards the rest). All 23 values in [0, 1]."""
    positions = np.asarray(positions)
    mean, std = (np.asarray(a, dtype=np.float64).ravel() for a in belief)
    flat, valid = grid.view_index(positions)
    seen = valid & grid.free.ravel()[flat]
    m = np.where(seen, np.clip(mean[flat], 0.0, 1.0), 0.0)
    s = np.where(seen, np.clip(2.0 * std[flat], 0.0, 1.0), 0.0)
    paper = paper_states(grid, idleness, importance, positions, others)
    return np.concatenate([paper, m, s], axis=1)


#: ``nowcast``'s values: eq. (s)'s, then the belief's mean and scaled std per view cell.
NOWCAST_LAYOUT: tuple[str, ...] = (
    *STATE_LAYOUT,
    *(f"mean_{c}" for c in VIEW_CELLS),
    *(f"2std_{c}" for c in VIEW_CELLS),
)

#: Variants that can be named but not built, with the reason (one line each); none today.
UNAVAILABLE: dict[str, str] = {}

STATE_VARIANTS: dict[str, StateVariant] = {
    v.name: v
    for v in (
        StateVariant("paper", STATE_LAYOUT, paper_states, "the paper's 13 values (eq. s)"),
        StateVariant(
            "window",
            _window_layout(),
            window_states,
            "eq. (s) with I*T over the 5 x 5 cells around the drone (33 values)",
        ),
        StateVariant(
            "nowcast",
            NOWCAST_LAYOUT,
            nowcast_states,
            "eq. (s) plus the nowcast's mean and 2 std on the 5 view cells (23 values)",
            needs_belief=True,
        ),
    )
}
#: The variant every checkpoint without ``meta["state"]`` was trained on.
DEFAULT_STATE = "paper"
#: Every name a config may give (the buildable ones and the refused ones).
STATE_NAMES: tuple[str, ...] = (*STATE_VARIANTS, *UNAVAILABLE)


def state_variant(name: str, where: str = "state") -> StateVariant:
    """The variant called ``name``; anything else is one :class:`UserError` line naming
    ``where``."""
    known = ", ".join(repr(n) for n in STATE_VARIANTS)
    if not isinstance(name, str):  # a list or a dict cannot even be looked up
        raise UserError(f"{where} = {name!r} is not a state variant's name; use one of {known}")
    if name in STATE_VARIANTS:
        return STATE_VARIANTS[name]
    if name in UNAVAILABLE:
        raise UserError(f"{where} = {name!r} {UNAVAILABLE[name]}; use one of {known}")
    raise UserError(f"{where} = {name!r} is not a state variant; use one of {known}")
