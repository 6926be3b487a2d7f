"""Scheduled incidents applied to a live SUMO run through libsumo, kept as ground truth.

``[[traffic.incidents]]`` (:class:`twin.config.IncidentSettings`) names a kind, a place and a
time. Where: an ``edge`` id, or a ``cell`` (i, j) from which twin takes, at the onset, the edge
with the most vehicles among the edges whose middle lies in the cell (ties: the smallest id).
How, at the onset and lifted at the end:

- ``lane_closed``: lane ``lane`` of the edge allows only the "authority" class
  (``lane.setAllowed``); the lane's permissions are restored after;
- ``edge_closed``: every lane of the edge, alike;
- ``vehicle_stopped``: the vehicle on the edge with the smallest id is held at speed 0
  (``vehicle.setSpeed``), released after (waits until a vehicle is on the edge).

A swarm's drones see an incident at step k when one's field of view covers its cell while it
lasts (:func:`twin.monitoring.incident_sightings`). Step k observes ``(t_{k-1}, t_k]``, so the
incident is on at the steps whose interval meets ``[begin, end)``.
"""

from __future__ import annotations

import itertools
import math
from typing import Any

import numpy as np

from twin.clock import clock_label, parse_clock
from twin.errors import UserError
from twin.sumo.readers import open_xml

#: The one vehicle class a closed lane still allows.
CLOSED_TO = ["authority"]


def _libsumo():
    from twin.sumo.session import _libsumo

    return _libsumo()


def onset_and_end_steps(begin: float, end: float, t0: float, step_s: float) -> tuple[int, int]:
    """First and last step k whose interval ``(t0 + (k-1) step, t0 + k step]`` meets
    ``[begin, end)``."""
    first = math.floor((begin - t0) / step_s + 1e-9) + 1
    last = math.ceil((end - t0) / step_s - 1e-9)
    return max(first, 0), max(last, first)


def incident_window(
    inc, n: int, begin_s: float, step_s: float, ms: bool = True
) -> tuple[float, float]:
    """``[begin, end)`` (s) of incident ``n`` (its ``begin`` clock, or ``T^step``), on SUMO's
    clock of whole milliseconds, to which it rounds the times it is advanced to (``ms``
    False: unrounded, as twin recorded them before)."""
    if inc.begin is not None:
        begin = parse_clock(inc.begin, f"[traffic].incidents[{n}].begin")
    else:
        begin = begin_s + inc.step * step_s
    if not ms:
        return begin, begin + 60.0 * inc.duration_min
    begin = round(begin, 3)
    return begin, round(begin + 60.0 * inc.duration_min, 3)


def configured_schedule(incidents: list[Any]) -> list[dict[str, Any]]:
    """``[[traffic.incidents]]`` as configured (run.json ``traffic.incidents``): what an
    ``incidents.json`` of the run must hold, read back by
    :func:`twin.report.derived.check_incident_schedule`."""
    return [inc.model_dump(mode="json") for inc in incidents]


#: Edge functions that are no road: a junction's inner lanes, its crossings and walking areas.
NOT_ROADS = ("internal", "crossing", "walkingarea")


def for_vehicles(allow: str | None, disallow: str | None = None) -> bool:
    """Whether a lane of these SUMO permissions carries vehicles: not one for pedestrians
    alone (``allow="pedestrian"``, a sidewalk) nor closed to all."""
    if allow is not None:
        return bool(set(allow.split()) - {"pedestrian"})
    return (disallow or "").strip() != "all"


def net_edges(net_file) -> dict[str, list[bool]]:
    """The roads of a network (edges but a junction's internal ones, crossings and walking
    areas): per lane, by index, whether it carries vehicles (:func:`for_vehicles`)."""
    import xml.etree.ElementTree as ET

    edges: dict[str, list[bool]] = {}
    with open_xml(net_file) as fh:
        for _, elem in ET.iterparse(fh, events=("end",)):
            if elem.tag == "edge":
                if elem.get("function") not in NOT_ROADS and elem.get("id"):
                    lanes = sorted(elem.findall("lane"), key=lambda la: int(la.get("index", 0)))
                    edges[elem.get("id")] = [
                        for_vehicles(la.get("allow"), la.get("disallow")) for la in lanes
                    ]
                elem.clear()
    return edges


def edge_lanes(net_file, wanted: set[str]) -> dict[str, tuple[int, np.ndarray]]:
    """Of the non-internal edges ``wanted`` of a network: their number of lanes and the shape
    ``(n, 2)`` of their lane 0 (an edge the network lacks is left out)."""
    import xml.etree.ElementTree as ET

    out: dict[str, tuple[int, np.ndarray]] = {}
    with open_xml(net_file) as fh:
        for _, elem in ET.iterparse(fh, events=("end",)):
            if elem.tag != "edge":
                continue
            if elem.get("function") != "internal" and elem.get("id") in wanted:
                lanes = elem.findall("lane")
                first = next((la for la in lanes if la.get("index") == "0"), None)
                points = (first.get("shape") or "").split() if first is not None else []
                shape = np.array([[float(v) for v in p.split(",")[:2]] for p in points])
                out[elem.get("id")] = (len(lanes), shape.reshape(-1, 2))
            elem.clear()
    return out


def edge_cells(shape: np.ndarray, geometry) -> set[tuple[int, int]]:
    """The cells (i, j) of ``geometry`` (:class:`twin.sumo.cells.CellGeometry`, or any with
    its ``cell_index``) that a lane of ``shape`` passes through, sampled as
    :meth:`IncidentSchedule._edge_cells` samples it (its middle and every 10 m)."""
    if not len(shape):
        return set()
    points = np.vstack([_midpoint(shape), _along(shape, 10.0)])
    row, col, inside = geometry.cell_index(points)
    return {(int(r), int(c)) for r, c, ok in zip(row, col, inside, strict=True) if ok}


def middle_cell(shape: np.ndarray, geometry) -> tuple[int, int]:
    """The cell of a lane's middle (:meth:`IncidentSchedule._edge_cells`), where an incident
    given by its edge is recorded; ``(-1, -1)`` off the grid."""
    row, col, inside = geometry.cell_index(np.array([_midpoint(shape)]))
    return (int(row[0]), int(col[0])) if inside[0] else (-1, -1)


def cell_roads(net_file, geometry) -> dict[tuple[int, int], list[tuple[str, list[bool]]]]:
    """Per cell: the roads whose lane 0 passes through it (as :meth:`IncidentSchedule.
    _edge_cells` finds them in the running simulation), each with its lanes' vehicle flags
    (:func:`net_edges`): the candidates of an incident given by its cell."""
    roads = net_edges(net_file)
    out: dict[tuple[int, int], list[tuple[str, list[bool]]]] = {}
    for edge, (_, shape) in edge_lanes(net_file, set(roads)).items():
        if edge.startswith(":"):
            continue
        for cell in edge_cells(shape, geometry):
            out.setdefault(cell, []).append((edge, roads[edge]))
    return out


def _check_cell_roads(field: str, inc, cell: tuple[int, int], roads) -> None:
    """Refuse an incident given by its cell whose roads there carry no vehicle on what it
    would act on: the lane it closes (a sidewalk, lane 0 where a road has one), else any."""
    usable = sorted({k for _, lanes in roads for k, ok in enumerate(lanes) if ok})
    place = f"cell = [{cell[0]}, {cell[1]}]"
    if not roads:
        raise UserError(
            f"{field}.{place}: no road runs through it (lanes only touch it); pick a cell on "
            "a road (see the report's map) or give an edge"
        )
    if not usable:
        raise UserError(
            f"{field}.{place}: its roads carry no vehicle (footpaths), so the incident would "
            "hold up nothing; pick a cell on a road (see the report's map)"
        )
    if inc.kind == "lane_closed" and inc.lane not in usable:
        raise UserError(
            f"{field}.lane = {inc.lane}: no road of {place} has a lane {inc.lane} that carries "
            f"vehicles (where a road has a sidewalk, it is lane 0); give lane = "
            f"{', '.join(map(str, usable))}"
        )


def check_incidents(
    incidents: list[Any], scenario, geometry, where: str = "", obstacles=None
) -> list[str]:
    """Refuse (one line) an incident outside the scenario's simulated window (warm-up
    included) or over before its first step ``T^0``, on a cell off the grid or without a road,
    on an edge or lane the network lacks, a stopped vehicle in the mesoscopic model;
    return notices for incidents that overlap in time on one edge or cell (they are applied
    together: a lane reopens when the last incident closing it lifts), and for one on a cell
    of the road that is an obstacle of the grid (``obstacles``: no drone may see it)."""
    prefix = f"{where}: " if where else ""
    edges = net_edges(scenario.net_file) if any(i.edge is not None for i in incidents) else {}
    named = {i.edge for i in incidents if i.edge is not None}  # their lane 0, read once
    shapes = edge_lanes(scenario.net_file, named) if named and obstacles is not None else {}
    by_cell = cell_roads(scenario.net_file, geometry) if any(i.cell for i in incidents) else {}
    lo, hi = scenario.sim_begin, scenario.sim_end
    places, unseen = [], []
    for n, inc in enumerate(incidents):
        field = f"{prefix}[traffic].incidents[{n}]"
        if inc.kind == "vehicle_stopped" and scenario.mesoscopic:
            raise UserError(
                f'{field}.kind = "vehicle_stopped" with SUMO\'s mesoscopic model (--meso, or the '
                "sumocfg's mesosim), whose queues a stopped vehicle does not block; run it "
                'microscopic, or close the edge or a lane instead (kind = "edge_closed")'
            )
        begin, end = incident_window(inc, n, scenario.begin_s, scenario.step_s)
        if not lo - 1e-6 <= begin < hi - 1e-6:  # (step times carry rounding errors)
            given = f"begin = {inc.begin!r}" if inc.begin is not None else f"step = {inc.step}"
            raise UserError(
                f"{field}.{given} ({clock_label(begin)}) is outside the scenario's window "
                f"{clock_label(lo)} - {clock_label(hi)} (warm-up included); give a time inside it"
            )
        if end <= scenario.begin_s + 1e-6:
            raise UserError(
                f"{field} ends at {clock_label(end)}, by the run's first step T^0 = "
                f"{clock_label(scenario.begin_s)} (it lies in the warm-up): no drone could see "
                "it; give a begin or duration that reaches past T^0"
            )
        if inc.cell is not None:
            i, j = inc.cell
            if not (0 <= i < geometry.nx and 0 <= j < geometry.ny):
                raise UserError(
                    f"{field}.cell = [{i}, {j}] is off the {geometry.nx} x {geometry.ny} grid; "
                    f"give 0 <= i < {geometry.nx}, 0 <= j < {geometry.ny}"
                )
            if geometry.lane_km[i, j] <= 0:
                raise UserError(
                    f"{field}.cell = [{i}, {j}] has no road; pick a cell on a road (see the "
                    "report's map) or give an edge"
                )
            _check_cell_roads(field, inc, (i, j), by_cell.get((i, j), []))
            place = f"cell [{i}, {j}]"
            if obstacles is not None and obstacles[i, j]:
                unseen.append(
                    f"{field}.cell = [{i}, {j}] is an obstacle of the grid ([grid].obstacles, or "
                    "less road than [traffic].min_lane_km): the incident holds up traffic, but no "
                    "drone can fly there to see it"
                )
        else:
            if inc.edge not in edges:
                junction = " (a junction's inner lane, crossing or walking area: no road)"
                raise UserError(
                    f"{field}.edge = {inc.edge!r} is not a road of {scenario.net_file}"
                    f"{junction if inc.edge.startswith(':') else ''}; give an edge id of the "
                    "net file, or a cell = [i, j]"
                )
            lanes = edges[inc.edge]
            if inc.kind == "lane_closed" and inc.lane >= len(lanes):
                raise UserError(
                    f"{field}.lane = {inc.lane}: edge {inc.edge!r} has {len(lanes)} lanes "
                    f"(0 is the rightmost); give a lane below {len(lanes)}"
                )
            usable = [k for k, ok in enumerate(lanes) if ok]
            if not usable:
                raise UserError(
                    f"{field}.edge = {inc.edge!r} carries no vehicle (its lanes are for "
                    "pedestrians), so the incident would hold up nothing; give a road's edge"
                )
            if inc.kind == "lane_closed" and not lanes[inc.lane]:
                raise UserError(
                    f"{field}.lane = {inc.lane} of edge {inc.edge!r} is for pedestrians (a "
                    "sidewalk): closing it holds up no vehicle; give a lane vehicles use "
                    f"({', '.join(map(str, usable))})"
                )
            place = f"edge {inc.edge!r}"
            shape = shapes.get(inc.edge, (0, ()))[1]
            seen_at = middle_cell(shape, geometry) if len(shape) else (-1, -1)  # as the run does
            if obstacles is not None and min(seen_at) >= 0 and obstacles[seen_at]:
                unseen.append(
                    f"{field}.edge = {inc.edge!r} lies in cell [{seen_at[0]}, {seen_at[1]}], an "
                    "obstacle of the grid ([grid].obstacles, or less road than "
                    "[traffic].min_lane_km): the incident holds up traffic, but no drone can "
                    "fly there to see it"
                )
        places.append((place, begin, end))
    notices = unseen
    for (a, (pa, ba, ea)), (b, (pb, bb, eb)) in itertools.combinations(enumerate(places), 2):
        if pa == pb and ba < eb and bb < ea:
            notices.append(
                f"{prefix}[traffic].incidents[{a}] and [{b}] overlap on {pa} from "
                f"{clock_label(max(ba, bb))} to {clock_label(min(ea, eb))}; both apply, and a "
                "closed lane reopens only when the last incident on it lifts"
            )
    return notices


def holds_up_vehicles(lanes: list[bool], inc) -> bool:
    """Whether incident ``inc`` on an edge of these lanes (:func:`net_edges`' flags) acts on
    one that carries vehicles: its lane, for a closed lane, else any of the edge's."""
    if inc.kind == "lane_closed":
        return inc.lane < len(lanes) and lanes[inc.lane]
    return any(lanes)


class IncidentSchedule:
    """The incidents of one run: applied as SUMO is advanced, recorded for ``incidents.json``."""

    def __init__(self, incidents: list[Any], geometry, scenario, grid=None):

        self.geometry = geometry
        self.records: list[dict[str, Any]] = []
        self.events: list[tuple[float, int, str]] = []  # (time, incident, "on" | "off")
        self._settings = list(incidents)
        self._edges: dict[str, tuple[tuple[int, int], set[tuple[int, int]]]] | None = None
        self._net_file = scenario.net_file
        self._roads: dict[str, list[bool]] | None = None  # lanes that carry vehicles, by edge
        #: closed lanes: how many incidents close each, and its permissions before the first
        self._closed: dict[str, tuple[int, tuple[list[str], list[str]]]] = {}
        #: held vehicles: how many incidents hold each
        self._held: dict[str, int] = {}
        for n, inc in enumerate(self._settings):
            begin, end = incident_window(inc, n, scenario.begin_s, scenario.step_s)
            onset, last = onset_and_end_steps(begin, end, scenario.begin_s, scenario.step_s)
            self.records.append(
                {
                    "kind": inc.kind,
                    "edge": inc.edge,
                    "lane": inc.lane if inc.kind == "lane_closed" else None,
                    "cell": list(inc.cell) if inc.cell is not None else None,
                    "begin": clock_label(begin),
                    "begin_s": begin,
                    "end_s": end,
                    "duration_min": inc.duration_min,
                    "onset_step": onset,
                    "end_step": min(last, scenario.horizon),
                    "vehicle": None,
                    "applied_s": None,
                    "lifted_s": None,
                }
            )
            self.events += [(begin, n, "on"), (end, n, "off")]
        self.events.sort()

    def advance_to(self, session, t: float) -> None:
        """Advance ``session`` to ``t``, applying the incident events due on the way."""
        while self.events and self.events[0][0] <= t:
            when, n, what = self.events.pop(0)
            if when > session.time:
                session.advance_to(when)
            if what == "on":
                self._start(n, session)
            else:
                self._stop(n, session)
        if t > session.time:
            session.advance_to(t)

    # ------------------------------------------------------------------------------ libsumo
    def _edge_cells(self) -> dict[str, tuple[tuple[int, int], set[tuple[int, int]]]]:
        """Per (non-internal) edge: the cell of its middle and every cell its first lane
        passes through (points every 10 m along the lane's shape)."""
        if self._edges is None:
            ls = _libsumo()
            self._edges = {}
            for e in (e for e in ls.edge.getIDList() if not e.startswith(":")):
                shape = ls.lane.getShape(f"{e}_0")
                points = np.vstack([_midpoint(shape), _along(shape, 10.0)])
                row, col, inside = self.geometry.cell_index(points)
                if not inside[0]:
                    continue
                cells = {(int(r), int(c)) for r, c, ok in zip(row, col, inside, strict=True) if ok}
                self._edges[e] = ((int(row[0]), int(col[0])), cells)
        return self._edges

    def _place(self, n: int) -> str | None:
        """The incident's edge (resolved now for a cell), or None while no vehicle to stop."""
        ls, inc, rec = _libsumo(), self._settings[n], self.records[n]
        where = f"[traffic].incidents[{n}]"
        cells = self._edge_cells()
        if inc.edge is not None:
            if inc.edge not in cells and inc.edge not in ls.edge.getIDList():
                raise UserError(
                    f"{where}.edge = {inc.edge!r} is not an edge of the network; "
                    "give an edge id of the net file, or a cell = [i, j]"
                )
            candidates = [inc.edge]
            if rec["cell"] is None:  # known before any vehicle is: the cell of its middle
                rec["cell"] = list(cells[inc.edge][0]) if inc.edge in cells else [-1, -1]
        else:
            cell = tuple(inc.cell)
            candidates = sorted(e for e, (_, through) in cells.items() if cell in through)
            # a cell's footpaths and sidewalks are no candidates
            if self._roads is None:  # as the check before the run read them
                self._roads = net_edges(self._net_file)
            candidates = [e for e in candidates if holds_up_vehicles(self._roads.get(e, []), inc)]
            if not candidates:
                lane = f" whose lane {inc.lane}" if inc.kind == "lane_closed" else " that"
                raise UserError(
                    f"{where}.cell = {list(cell)} has no road{lane} carries vehicles (where a "
                    "road has a sidewalk, it is lane 0); pick a cell on a road (see the "
                    "report's map)" + (" or another lane" if inc.kind == "lane_closed" else "")
                )
        if inc.kind == "lane_closed" and ls.edge.getLaneNumber(candidates[0]) <= inc.lane:
            raise UserError(
                f"{where}.lane = {inc.lane}: edge {candidates[0]!r} has "
                f"{ls.edge.getLaneNumber(candidates[0])} lanes (0 is the rightmost)"
            )
        busy = [(ls.edge.getLastStepVehicleNumber(e), e) for e in candidates]
        if inc.kind == "vehicle_stopped":
            busy = [b for b in busy if b[0] > 0]
            if not busy:
                return None
        edge = max(busy, key=lambda b: b[0])[1]  # the first, smallest id, among equals
        rec["edge"] = edge
        if rec["cell"] is None:
            rec["cell"] = list(cells[edge][0]) if edge in cells else [-1, -1]
        return edge

    def _lanes(self, n: int, edge: str) -> list[str]:
        inc = self._settings[n]
        if inc.kind == "lane_closed":
            return [f"{edge}_{inc.lane}"]
        return [f"{edge}_{i}" for i in range(_libsumo().edge.getLaneNumber(edge))]

    def _start(self, n: int, session) -> None:
        ls, rec = _libsumo(), self.records[n]
        edge = self._place(n)
        if edge is None:  # no vehicle to stop yet: try again in 10 s while the incident lasts
            if session.time + 10.0 < rec["end_s"]:
                self.events.append((session.time + 10.0, n, "on"))
                self.events.sort()
            return
        if rec["kind"] == "vehicle_stopped":
            vehicle = sorted(ls.edge.getLastStepVehicleIDs(edge))[0]
            ls.vehicle.setSpeed(vehicle, 0.0)
            self._held[vehicle] = self._held.get(vehicle, 0) + 1
            rec["vehicle"] = vehicle
        else:
            lanes = self._lanes(n, edge)
            for lane in lanes:
                count, saved = self._closed.get(lane, (0, None))
                if count == 0:  # the first incident on this lane keeps its own permissions
                    saved = (list(ls.lane.getAllowed(lane)), list(ls.lane.getDisallowed(lane)))
                    ls.lane.setAllowed(lane, CLOSED_TO)
                self._closed[lane] = (count + 1, saved)
            rec["lanes"] = lanes
        rec["applied_s"] = session.time

    def _stop(self, n: int, session) -> None:
        """Lift incident ``n``; a lane (a vehicle) closed (held) by several overlapping
        incidents reopens (drives on) only when the last of them lifts, with the permissions
        it had before the first."""
        ls, rec = _libsumo(), self.records[n]
        if rec["applied_s"] is None:
            return
        if rec["kind"] == "vehicle_stopped":
            vehicle = rec["vehicle"]
            self._held[vehicle] -= 1
            if self._held[vehicle] == 0:
                del self._held[vehicle]
                if vehicle in ls.vehicle.getIDList():
                    ls.vehicle.setSpeed(vehicle, -1.0)  # back to its own driving
        else:
            for lane in rec.pop("lanes"):
                count, (allowed, disallowed) = self._closed[lane]
                if count > 1:
                    self._closed[lane] = (count - 1, (allowed, disallowed))
                    continue
                del self._closed[lane]
                if allowed:
                    ls.lane.setAllowed(lane, allowed)
                else:
                    ls.lane.setDisallowed(lane, disallowed)
        rec["lifted_s"] = session.time

    def to_json(self) -> list[dict[str, Any]]:
        """Ground truth for ``incidents.json``: what, where (edge, cell i, j), when, how long."""
        return [{k: v for k, v in r.items() if k != "lanes"} for r in self.records]


def _along(shape, every_m: float) -> np.ndarray:
    """Points every ``every_m`` metres along a polyline (its vertices included)."""
    xy = np.asarray(shape, dtype=float).reshape(-1, 2)
    out = [xy]
    for a, b in itertools.pairwise(xy):
        n = int(np.hypot(*(b - a)) // every_m)
        if n:
            t = np.arange(1, n + 1)[:, None] / (n + 1)
            out.append(a + t * (b - a))
    return np.vstack(out)


def _midpoint(shape) -> tuple[float, float]:
    xy = np.asarray(shape, dtype=float).reshape(-1, 2)
    if len(xy) == 1:
        return float(xy[0, 0]), float(xy[0, 1])
    seg = np.hypot(*np.diff(xy, axis=0).T)
    cum = np.concatenate([[0.0], np.cumsum(seg)])
    half = cum[-1] / 2
    i = min(int(np.searchsorted(cum, half, side="right")) - 1, len(seg) - 1)
    f = (half - cum[i]) / seg[i] if seg[i] > 0 else 0.0
    p = xy[i] + f * (xy[i + 1] - xy[i])
    return float(p[0]), float(p[1])
