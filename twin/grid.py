"""The monitoring grid (Def. 1, Ass. 1): cells, obstacles, field of view, feasible moves.

Cell ``(i, j)``: row ``i`` counted from the top (the paper's x axis points down), column ``j``
from the left. Every function here takes the positions of all drones as one ``(N, 2)`` integer
array and answers for all of them with one numpy operation.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property

import numpy as np

#: Action order used everywhere: network output index = action.
ACTIONS: tuple[str, ...] = ("stay", "up", "down", "left", "right")
#: Row/column change of each action, in the order of :data:`ACTIONS`.
ACTION_DELTAS = np.array([[0, 0], [-1, 0], [1, 0], [0, -1], [0, 1]], dtype=np.int64)
N_ACTIONS = len(ACTIONS)


@dataclass(frozen=True, eq=False)
class Grid:
    """An ``nx x ny`` grid with a boolean obstacle mask ``O`` (True = cannot be visited)."""

    obstacles: np.ndarray

    def __post_init__(self) -> None:
        obstacles = np.asarray(self.obstacles, dtype=bool)
        if obstacles.ndim != 2 or min(obstacles.shape) < 1:
            raise ValueError(f"obstacle mask must be a non-empty 2-D array, got {obstacles.shape}")
        obstacles = obstacles.copy()
        obstacles.setflags(write=False)
        object.__setattr__(self, "obstacles", obstacles)
        free = ~obstacles
        free.setflags(write=False)
        object.__setattr__(self, "free", free)

    @classmethod
    def open(cls, nx: int, ny: int) -> Grid:
        """A grid without obstacles."""
        return cls(np.zeros((nx, ny), dtype=bool))

    @property
    def shape(self) -> tuple[int, int]:
        return self.obstacles.shape  # type: ignore[return-value]

    @property
    def nx(self) -> int:
        return self.obstacles.shape[0]

    @property
    def ny(self) -> int:
        return self.obstacles.shape[1]

    @property
    def n_free(self) -> int:
        return int(self.free.sum())

    def free_cells(self) -> np.ndarray:
        """``(n_free, 2)`` array of the free cells in row-major order."""
        return np.argwhere(self.free)

    def inside(self, cells: np.ndarray) -> np.ndarray:
        """Whether each ``(..., 2)`` cell lies on the map."""
        cells = np.asarray(cells)
        return (
            (cells[..., 0] >= 0)
            & (cells[..., 0] < self.nx)
            & (cells[..., 1] >= 0)
            & (cells[..., 1] < self.ny)
        )

    def is_free(self, cells: np.ndarray) -> np.ndarray:
        """Whether each ``(..., 2)`` cell is on the map and not an obstacle."""
        cells = np.asarray(cells)
        ok = self.inside(cells)
        i = np.where(ok, cells[..., 0], 0)
        j = np.where(ok, cells[..., 1], 0)
        return ok & self.free[i, j]

    def field_of_view(self, positions: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Adj(p) of every drone: the cell and its 4 neighbours in action order.

        Returns ``(cells, valid)``: ``cells`` is ``(N, 5, 2)``, clipped onto the map, and
        ``valid`` ``(N, 5)`` says which of them really are on the map.
        """
        flat, valid = self.view_index(positions)
        return np.stack([flat // self.ny, flat % self.ny], axis=-1), valid

    def view_index(self, positions: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Adj(p) as flat indices: the fast form of :meth:`field_of_view`.

        Returns ``(flat, valid)``: ``flat`` ``(N, 5)`` indices into the raveled map (a
        neighbour off the map points at the drone's own cell) and ``valid`` ``(N, 5)``, which
        of them really are on the map.
        """
        positions = np.asarray(positions)
        i, j = positions[:, 0], positions[:, 1]
        valid = np.ones((len(positions), 5), dtype=bool)
        valid[:, 1] = i > 0
        valid[:, 2] = i < self.nx - 1
        valid[:, 3] = j > 0
        valid[:, 4] = j < self.ny - 1
        centre = (i * self.ny + j)[:, None]
        flat = np.where(valid, centre + self._flat_offsets, centre)
        return flat, valid

    @cached_property
    def _flat_offsets(self) -> np.ndarray:
        return ACTION_DELTAS[:, 0] * self.ny + ACTION_DELTAS[:, 1]

    @cached_property
    def free_cumsum_down(self) -> np.ndarray:
        """Free cells counted down each column (prefix sums, for directional means)."""
        return self.free_float.cumsum(axis=0)

    @cached_property
    def free_cumsum_right(self) -> np.ndarray:
        """Free cells counted along each row from the left."""
        return self.free_float.cumsum(axis=1)

    @cached_property
    def free_float(self) -> np.ndarray:
        """The free-cell mask as 0.0 / 1.0, for masking by multiplication."""
        return self.free.astype(np.float64)

    def feasible_actions(self, positions: np.ndarray) -> np.ndarray:
        """``U_d(p)``: ``(N, 5)`` mask of actions that stay on the map and off obstacles."""
        cells = np.asarray(positions)[:, None, :] + ACTION_DELTAS[None, :, :]
        return self.is_free(cells)

    def move(self, positions: np.ndarray, actions: np.ndarray) -> np.ndarray:
        """``p^{k+1} = p^k + u^k``; the caller guarantees the actions are feasible."""
        return np.asarray(positions) + ACTION_DELTAS[np.asarray(actions)]

    def values_in_view(
        self, values: np.ndarray, positions: np.ndarray, view: tuple | None = None
    ) -> np.ndarray:
        """``(N, 5)`` values of a map over each drone's field of view, 0 off the map.

        ``view`` is the :meth:`view_index` of ``positions`` when the caller has it already.
        """
        flat, valid = view if view is not None else self.view_index(positions)
        return np.where(valid, values.ravel()[flat], 0.0)

    def sum_in_view(self, values: np.ndarray, positions: np.ndarray) -> np.ndarray:
        """``(N,)`` sum of a map over each drone's field of view Adj(p)."""
        return self.values_in_view(values, positions).sum(axis=1)
