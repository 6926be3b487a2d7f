"""Lane-to-cell geometry: the monitoring grid laid over a SUMO network (Def. 1 on a network).

The grid covers the bounding box of the network's passenger-car lanes at the configured cell
size, centred on it; row 0 is the northern edge, column 0 the western one. Each lane's centre
line is cut by the cells (shapely) to give every cell its lane-km and its length-weighted speed
limit; a cell with no drivable lane (less than ``min_lane_km``) is an obstacle. Vehicles are
binned into cells by their position, so one numpy pass gives all per-cell counts and speeds.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from twin.errors import UserError


@dataclass(frozen=True, eq=False)
class CellGeometry:
    """Grid placement and per-cell road supply of a network."""

    x0: float  # western edge of column 0 (m, network coordinates)
    y_top: float  # northern edge of row 0
    cell_m: float
    nx: int
    ny: int
    lane_km: np.ndarray  # (nx, ny) lane length inside each cell, km
    speed_limit: np.ndarray  # (nx, ny) length-weighted lane speed limit, m/s (0 without lanes)
    bbox: tuple[float, float, float, float]  # xmin, ymin, xmax, ymax of the lanes

    def obstacles(self, min_lane_km: float = 0.0) -> np.ndarray:
        """Cells without drivable lane: no lane, or less than ``min_lane_km`` of it."""
        return (self.lane_km <= 0.0) | (self.lane_km < min_lane_km)

    def cell_index(self, xy: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Rows, columns and on-grid mask of points ``(n, 2)``."""
        xy = np.asarray(xy, dtype=float).reshape(-1, 2)
        col = np.floor((xy[:, 0] - self.x0) / self.cell_m).astype(np.int64)
        row = np.floor((self.y_top - xy[:, 1]) / self.cell_m).astype(np.int64)
        inside = (row >= 0) & (row < self.nx) & (col >= 0) & (col < self.ny)
        return row, col, inside

    def count_and_speed(self, xy: np.ndarray, speed: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Vehicles per cell ``(nx, ny)`` int and their mean speed (m/s, NaN where empty).

        The mean of the instantaneous speeds of the vehicles inside a cell is the space-mean
        speed of Edie's definitions for a region of the cell's lanes over an instant.
        """
        row, col, inside = self.cell_index(xy)
        flat = row[inside] * self.ny + col[inside]
        size = self.nx * self.ny
        count = np.bincount(flat, minlength=size)
        total = np.bincount(flat, weights=np.asarray(speed, float)[inside], minlength=size)
        with np.errstate(invalid="ignore", divide="ignore"):
            mean = np.where(count > 0, total / np.maximum(count, 1), np.nan)
        return count.reshape(self.nx, self.ny), mean.reshape(self.nx, self.ny)

    def cell_center(self, i: np.ndarray, j: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        return self.x0 + (np.asarray(j) + 0.5) * self.cell_m, self.y_top - (
            np.asarray(i) + 0.5
        ) * self.cell_m

    def to_json(self) -> dict[str, Any]:
        """Grid placement (``network.json``); the arrays go to the tape."""
        return {
            "x0": self.x0,
            "y_top": self.y_top,
            "cell_m": self.cell_m,
            "nx": self.nx,
            "ny": self.ny,
            "bbox": list(self.bbox),
            "lane_km_total": round(float(self.lane_km.sum()), 3),
        }


@dataclass(frozen=True)
class Lanes:
    """Centre lines ``(x, y)`` arrays and speed limits (m/s) of the lanes cars may use."""

    shapes: list[np.ndarray]
    speeds: np.ndarray
    #: lanes some vehicles use but cars may not (bike lanes, bus lanes, rails): a vehicle on
    #: one is not car traffic, whose lanes give the cells' lane-km and speed limits
    not_for_cars: frozenset[str] = frozenset()


def for_cars(lane) -> bool:
    """Whether passenger cars may use a (sumolib) lane; sumolib reads allow="all" as a class."""
    allowed = lane.getPermissions()
    return "passenger" in allowed or "all" in allowed


def for_vehicles(lane) -> bool:
    """Whether some vehicle may use a (sumolib) lane: a sidewalk carries none."""
    return bool(lane.getPermissions() - {"pedestrian"})


def traffic_lanes(net) -> Callable[[Any], bool]:
    """Which lanes of a (sumolib) network carry its counted traffic: those of passenger cars,
    or, on a network without any, those of every other vehicle (:func:`read_lanes`)."""
    has_cars = any(for_cars(lane) for edge in net.getEdges() for lane in edge.getLanes())
    return for_cars if has_cars else for_vehicles


def read_lanes(net_file: Path) -> Lanes:
    """Passenger-car lanes of a network, junction-internal lanes included (cars stand there);
    a network without any (a freight or bus network, which SUMO runs as well) gives its lanes
    of every other vehicle class, with a notice."""
    import sumolib

    try:
        net = sumolib.net.readNet(str(net_file), withInternal=True)
    except Exception as exc:  # sumolib raises SAX errors and others on a broken file
        raise UserError(f"{net_file}: cannot read the network ({exc})") from exc
    cars, others = ([], [], []), ([], [], [])  # (shapes, speeds, ids)
    classes: set[str] = set()
    for edge in net.getEdges(withInternal=True):
        for lane in edge.getLanes():
            if for_cars(lane):
                kept = cars
            elif for_vehicles(lane):
                kept = others
                classes |= lane.getPermissions() - {"pedestrian"}
            else:
                continue
            kept[0].append(np.asarray(lane.getShape(), dtype=float))
            kept[1].append(lane.getSpeed())
            kept[2].append(lane.getID())
    if cars[0]:
        return Lanes(cars[0], np.asarray(cars[1], dtype=float), frozenset(others[2]))
    if not others[0]:
        raise UserError(f"{net_file}: the network has no lane that vehicles may use")
    from twin.notices import notify

    notify(
        f"twin: notice: {net_file}: no lane lets passenger cars drive; twin counts the "
        f"vehicles of its other lanes ({', '.join(sorted(classes))}) as its traffic"
    )
    return Lanes(others[0], np.asarray(others[1], dtype=float))


def grid_over(
    lanes: Lanes, cell_m: float, shape: tuple[int, int] | None = None, where: str = "network"
) -> CellGeometry:
    """Lay a grid of ``cell_m`` cells over the lanes' bounding box, centred on it.

    ``shape`` (rows, columns) asks for a given grid; it must cover the bounding box.
    """
    from shapely.geometry import LineString
    from shapely.geometry import box as make_box

    from twin.resources import check_cell_size, check_grid_size

    check_cell_size(cell_m, where)
    pts = np.concatenate(lanes.shapes)
    xmin, ymin = pts.min(axis=0)
    xmax, ymax = pts.max(axis=0)
    need = (max(1, math.ceil((ymax - ymin) / cell_m)), max(1, math.ceil((xmax - xmin) / cell_m)))
    nx, ny = shape if shape is not None else need
    if nx < need[0] or ny < need[1]:
        raise UserError(
            f"{where}: a {nx} x {ny} grid of {cell_m:g} m cells cannot cover the network "
            f"({xmax - xmin:.0f} m x {ymax - ymin:.0f} m needs {need[0]} x {need[1]}); "
            "use a larger grid or cell size"
        )
    check_grid_size(
        nx, ny, where, f"use larger cells than {cell_m:g} m ([traffic].cell_m, --cell-m)"
    )
    x0 = (xmin + xmax) / 2 - ny * cell_m / 2
    y_top = (ymin + ymax) / 2 + nx * cell_m / 2
    lane_m = np.zeros((nx, ny))
    speed_m = np.zeros((nx, ny))
    for shape_xy, speed in zip(lanes.shapes, lanes.speeds, strict=True):
        if len(shape_xy) < 2:
            continue
        line = LineString(shape_xy)
        c0, c1 = (np.floor((np.array([shape_xy[:, 0].min(), shape_xy[:, 0].max()]) - x0) / cell_m)
                  .astype(int).clip(0, ny - 1))  # fmt: skip
        r0, r1 = (np.floor((y_top - np.array([shape_xy[:, 1].max(), shape_xy[:, 1].min()])) / cell_m)
                  .astype(int).clip(0, nx - 1))  # fmt: skip
        if r0 == r1 and c0 == c1:
            lane_m[r0, c0] += line.length
            speed_m[r0, c0] += line.length * speed
            continue
        for r in range(r0, r1 + 1):
            for c in range(c0, c1 + 1):
                cell = make_box(
                    x0 + c * cell_m,
                    y_top - (r + 1) * cell_m,
                    x0 + (c + 1) * cell_m,
                    y_top - r * cell_m,
                )
                length = line.intersection(cell).length
                lane_m[r, c] += length
                speed_m[r, c] += length * speed
    with np.errstate(invalid="ignore", divide="ignore"):
        limit = np.where(lane_m > 0, speed_m / np.maximum(lane_m, 1e-9), 0.0)
    return CellGeometry(
        x0=float(x0),
        y_top=float(y_top),
        cell_m=float(cell_m),
        nx=int(nx),
        ny=int(ny),
        lane_km=lane_m / 1000.0,
        speed_limit=limit,
        bbox=(float(xmin), float(ymin), float(xmax), float(ymax)),
    )
