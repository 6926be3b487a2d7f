"""Fixed detectors: the scenario's induction loops and lane-area detectors, or virtual loops.

Which detectors (``[traffic.detectors]``): those the scenario's additional files define
(``<inductionLoop>``/``<e1Detector>``, ``<laneAreaDetector>``/``<e2Detector>``, found through
libsumo once SUMO has loaded them), and loop stations that twin places itself, written as an
additional file of ``<inductionLoop>`` elements with an aggregation period of one step:

- at the listed ``cells``, or
- at ``virtual_loops = N`` cells chosen by a deterministic rule from the network alone
  (:func:`station_cells`): free cells by decreasing lane-km (ties: row, then column), each
  taken unless it touches (8-neighbourhood) a cell taken before, until N are chosen; if fewer
  than N remain, the skipped ones follow in the same order.

A station is one loop on every passenger lane (on a network without any, every vehicle lane)
of the cell's main edge (the normal edge with the longest lane length inside the cell; ties by
edge id), at the middle of that lane's stretch in the cell.

Reading: at every sample time each detector's last completed aggregation interval is read
(vehicles counted, occupancy, mean speed: three calls, no subscriptions, no per-SUMO-step
work). Twin's own loops aggregate over exactly one step. A scenario detector aggregates over
its file's period; its reading is passed on once per interval, the interval told by that period
from SUMO's begin, so a period longer than a step gives fewer readings, never the same one twice
(a detector whose period twin cannot read, none in its files, is passed on when its reading
differs from the previous one: an interval that repeats the previous one exactly, mostly when
nothing passes, is lost). Density from occupancy, ``k = occ / L`` with ``L`` the effective
vehicle length (:data:`twin.mfd.VEHICLE_LENGTH_M`), per lane-km as the cells' density, then the
importance of :class:`twin.mfd.MFD` in effect at that step (the same mapping as the cells').
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path
from xml.sax.saxutils import quoteattr

import numpy as np

from twin.clock import clock_label
from twin.errors import UserError

#: Columns of ``detectors.parquet``: each fixed detector's reading at each sample time.
DETECTOR_COLUMNS = ["seed", "step", "detector", "kind", "virtual", "lane", "i", "j", "vehicles",
                    "occupancy_pct", "speed", "importance"]  # fmt: skip

#: Prefix of the ids of the loops twin places (told apart from the scenario's own).
VIRTUAL_PREFIX = "twin-loop-"
LOOP = "loop"
AREA = "area"


@dataclass(frozen=True)
class LoopSpec:
    """One loop twin places: id, lane, position along the lane (m), cell."""

    id: str
    lane: str
    pos: float
    cell: tuple[int, int]


@dataclass(frozen=True)
class DetectorPlan:
    """What a run reads: the scenario's detectors (``scenario``) and twin's loops."""

    scenario: bool = False
    loops: tuple[LoopSpec, ...] = ()

    @property
    def active(self) -> bool:
        return self.scenario or bool(self.loops)


@dataclass(frozen=True)
class Detector:
    """A detector being read: id, kind (loop or area), lane, cell, placed by twin or not."""

    id: str
    kind: str
    lane: str
    cell: tuple[int, int]
    virtual: bool


def station_cells(lane_km: np.ndarray, free: np.ndarray, n: int) -> list[tuple[int, int]]:
    """``n`` cells for loop stations by the rule of the module docstring (deterministic)."""
    nx, ny = lane_km.shape
    cells = [(int(i), int(j)) for i, j in np.argwhere(free & (lane_km > 0))]
    cells.sort(key=lambda c: (-float(lane_km[c]), c[0], c[1]))
    taken: list[tuple[int, int]] = []
    blocked = np.zeros((nx, ny), dtype=bool)
    skipped = []
    for i, j in cells:
        if len(taken) == n:
            break
        if blocked[i, j]:
            skipped.append((i, j))
            continue
        taken.append((i, j))
        blocked[max(i - 1, 0) : i + 2, max(j - 1, 0) : j + 2] = True
    return taken + skipped[: max(n - len(taken), 0)]


def check_cells(cells, geometry, free: np.ndarray, where: str) -> list[tuple[int, int]]:
    """The listed station cells, refused (one line) off the grid, without road or twice."""
    out: list[tuple[int, int]] = []
    for n, (i, j) in enumerate(cells):
        field = f"{where}[traffic.detectors].cells[{n}] = [{i}, {j}]"
        if not (0 <= i < geometry.nx and 0 <= j < geometry.ny):
            raise UserError(
                f"{field} is off the {geometry.nx} x {geometry.ny} grid; give "
                f"0 <= i < {geometry.nx}, 0 <= j < {geometry.ny}"
            )
        if geometry.lane_km[i, j] <= 0 or not free[i, j]:
            raise UserError(
                f"{field} is an obstacle or has no road; pick a free cell on a road (see the "
                "report's map)"
            )
        if (i, j) in out:
            raise UserError(f"{field} is listed twice; give each cell once")
        out.append((int(i), int(j)))
    return out


def _cell_box(geometry, cell: tuple[int, int]):
    from shapely.geometry import box

    x0 = geometry.x0 + cell[1] * geometry.cell_m
    y1 = geometry.y_top - cell[0] * geometry.cell_m
    return box(x0, y1 - geometry.cell_m, x0 + geometry.cell_m, y1)


def main_edges(net_file: Path, geometry) -> dict[tuple[int, int], list]:
    """Per cell, the passenger lanes (sumolib) of its main edge: the normal edge with the most
    lane length inside the cell, ties by edge id. Cells with junction lanes only are absent. A
    network without car lanes gives the lanes of its other vehicles, as its traffic."""
    import sumolib
    from shapely.geometry import LineString

    from twin.sumo.cells import traffic_lanes

    net = sumolib.net.readNet(str(net_file))
    counted = traffic_lanes(net)
    best: dict[tuple[int, int], tuple[float, str, list]] = {}
    quarter = geometry.cell_m / 4
    for edge in sorted(net.getEdges(), key=lambda e: e.getID()):
        lanes = [lane for lane in edge.getLanes() if counted(lane)]
        if not lanes:
            continue
        line = LineString(lanes[0].getShape())
        steps = max(int(line.length / quarter), 1)
        pts = np.array(
            [line.interpolate(t, normalized=True).coords[0] for t in np.linspace(0, 1, steps + 1)]
        )
        rows, cols, inside = geometry.cell_index(pts)
        touched = {(int(r), int(c)) for r, c, ok in zip(rows, cols, inside, strict=True) if ok}
        for cell in touched:
            box = _cell_box(geometry, cell)
            length = sum(LineString(lane.getShape()).intersection(box).length for lane in lanes)
            if length > 0 and (cell not in best or length > best[cell][0]):
                best[cell] = (length, edge.getID(), lanes)
    return {cell: lanes for cell, (_, _, lanes) in best.items()}


def place_loops(edges: dict, geometry, cells: list[tuple[int, int]]) -> tuple[LoopSpec, ...]:
    """One station per cell (each a key of :func:`main_edges`' ``edges``): a loop on every
    lane :func:`main_edges` gives of the cell's main edge, at the middle of the lane's stretch in the cell."""
    from shapely.geometry import LineString

    specs = []
    for cell in cells:
        box = _cell_box(geometry, cell)
        for lane in edges[cell]:
            line = LineString(lane.getShape())
            pieces = list(getattr(part := line.intersection(box), "geoms", [part]))
            piece = max(pieces, key=lambda g: g.length)
            along = line.project(piece.interpolate(0.5, normalized=True))
            pos = along * lane.getLength() / line.length if line.length > 0 else 0.0
            pos = float(min(max(pos, 0.1), max(lane.getLength() - 0.1, 0.1)))
            loop_id = f"{VIRTUAL_PREFIX}{cell[0]}-{cell[1]}-{lane.getIndex()}"
            specs.append(LoopSpec(loop_id, lane.getID(), round(pos, 2), cell))
    return tuple(specs)


def write_loops(specs: tuple[LoopSpec, ...], path: Path, period_s: float) -> Path:
    """The additional file of twin's loops (aggregation period one step, output discarded)."""
    lines = ["<additional>"]
    for s in specs:
        lines.append(
            f'    <inductionLoop id={quoteattr(s.id)} lane={quoteattr(s.lane)} pos="{s.pos:.2f}" '
            f'period="{period_s:g}" file="NUL"/>'
        )
    lines.append("</additional>\n")
    Path(path).write_text("\n".join(lines))
    return Path(path)


def with_additional(options: tuple[str, ...], extra: Path) -> tuple[str, ...]:
    """SUMO ``options`` with ``extra`` added to the ``--additional-files`` list (or a new one)."""
    out = list(options)
    for i in range(len(out) - 1):
        if out[i] in ("--additional-files", "-a"):
            out[i + 1] = ",".join([*[v for v in out[i + 1].split(",") if v], str(extra)])
            return tuple(out)
    return (*out, "--additional-files", str(extra))


#: The detectors of an additional file twin reads (old and new names), by SUMO's element name.
DETECTOR_ELEMENTS = ("inductionLoop", "e1Detector", "laneAreaDetector", "e2Detector")
#: SUMO's aggregation period of a detector that gives none: the whole simulation (SUMO 1.2x),
#: so no interval of it ends within a run.
DEFAULT_PERIOD_S = math.inf


def detector_periods(files: list[Path]) -> dict[str, float]:
    """The aggregation period (s) of each detector the scenario's additional files define
    (``period``, or its old name ``freq``; the whole simulation when absent, as SUMO
    aggregates it), files they include too: a detector's first interval ends one period after
    SUMO begins."""
    import xml.etree.ElementTree as ET

    from twin.sumo.readers import included_files, local_name, open_xml, parse_time

    periods: dict[str, float] = {}
    for path in [p for f in files for p in (Path(f), *included_files(Path(f)))]:
        try:
            with open_xml(path) as fh:
                for _, elem in ET.iterparse(fh, events=("end",)):
                    if local_name(elem) in DETECTOR_ELEMENTS and elem.get("id") is not None:
                        given = parse_time(elem.get("period", elem.get("freq")))
                        periods[elem.get("id")] = given if given and given > 0 else (
                            DEFAULT_PERIOD_S)  # fmt: skip
        except (ET.ParseError, OSError, EOFError):
            continue  # read and refused before SUMO started; nothing more to learn here
    return periods


#: The lowest occupancy (%) a reading of the scenario's detectors keeps. SUMO's last-interval
#: occupancy through its API (``getLastIntervalOccupancy``) miscounts a vehicle on the loop when
#: an interval ends, where SUMO's own file output does not: at times it lags an interval or
#: goes below 0, by about the vehicle's time on the loop over the period (twin's own loops, of
#: a period of one step, to -2 %; a loop of period 1 s, to -60 %). A dip to this floor is kept
#: as 0 (the importance of a density at or below 0 is 0 alike); a reading further below is
#: broken and left out.
OCCUPANCY_FLOOR = -1.0


def scenario_reader(scenario, geometry, api) -> DetectorReader:
    """The :class:`DetectorReader` of a live scenario (:class:`twin.sumo.source.SumoScenario`):
    its detectors' periods from its additional files, its first interval from SUMO's begin."""
    periods = detector_periods(scenario.extra.get("additional_files", []))
    last = scenario.begin_s + scenario.horizon * scenario.step_s  # T^horizon's read
    return DetectorReader(scenario.detectors, geometry, api, begin=scenario.sim_begin,
                          step_s=scenario.step_s, periods=periods, end=last)  # fmt: skip


class DetectorReader:
    """The detectors of an open SUMO session, their cells, and their readings per sample time:
    none of a detector before its first interval has ended (``begin``, SUMO's begin, plus its
    period: ``periods`` of the scenario's, ``step_s`` of twin's loops), whose zeros measure
    nothing."""

    def __init__(
        self,
        plan: DetectorPlan,
        geometry,
        api,
        *,
        begin: float,
        step_s: float,
        periods: dict[str, float] | None = None,
        end: float = math.inf,
    ):
        self.api = api
        self._first_end = {s.id: begin + step_s for s in plan.loops}
        for det_id, period in (periods or {}).items():
            self._first_end.setdefault(det_id, begin + period)
        self._begin = begin
        virtual = {s.id: s for s in plan.loops}
        found: list[Detector] = []
        loop_ids = list(api.inductionloop.getIDList())
        area_ids = list(api.lanearea.getIDList()) if plan.scenario else []
        for det_id in loop_ids:
            if det_id in virtual:
                found.append(
                    Detector(det_id, LOOP, virtual[det_id].lane, virtual[det_id].cell, True)
                )
            elif plan.scenario:
                lane = api.inductionloop.getLaneID(det_id)
                cell = self._cell(geometry, lane, api.inductionloop.getPosition(det_id))
                if cell is not None:
                    found.append(Detector(det_id, LOOP, lane, cell, False))
        for det_id in area_ids:
            lane = api.lanearea.getLaneID(det_id)
            mid = api.lanearea.getPosition(det_id) + api.lanearea.getLength(det_id) / 2.0
            cell = self._cell(geometry, lane, mid)
            if cell is not None:
                found.append(Detector(det_id, AREA, lane, cell, False))
        if plan.scenario and not any(not d.virtual for d in found):
            from twin.boundary import notify

            own = [d for d in loop_ids if d not in virtual] + area_ids
            where = "on the grid " if own else ""
            notify(
                "twin: notice: [traffic.detectors] scenario = true, but the scenario's files "
                f"give no induction loop or lane-area detector {where}(e1/e2 in its additional "
                "files): no detector of the scenario is read"
            )
        self.detectors = found
        first_end = {d.id: self._first_end.get(d.id, begin) for d in found if not d.virtual}
        unread = [i for i, t in first_end.items() if t == math.inf]
        late = [i for i, t in first_end.items() if end < t < math.inf]  # the run ends first
        if late:
            from twin.boundary import notify

            notify(
                f"twin: notice: the scenario's detector{'s' * (len(late) > 1)} "
                f"{', '.join(repr(i) for i in late[:3])}{' ...' * (len(late) > 3)} end{'s' * (len(late) == 1)} "
                f"{'their' if len(late) > 1 else 'its'} first period after the run's last read "
                f"({clock_label(end)}): twin reads none of {'them' if len(late) > 1 else 'it'}; "
                "give a shorter period (e.g. twin's step)"
            )
        if unread:
            from twin.boundary import notify

            notify(
                f"twin: notice: the scenario's detector{'s' * (len(unread) > 1)} "
                f"{', '.join(repr(i) for i in unread[:3])}{' ...' * (len(unread) > 3)} "
                f"give{'s' * (len(unread) == 1)} no period: SUMO aggregates such a detector over the whole simulation, so none of "
                "its readings ends within the run and twin reads none; give it a period (e.g. "
                "twin's step)"
            )
        self._last: dict[str, tuple] = {}
        self._periods = dict(periods or {})  # a scenario detector's, from its file
        self._intervals: dict[str, int] = {}  # the completed intervals it was last read at
        self._broken: set[str] = set()

    def _cell(self, geometry, lane: str, pos: float) -> tuple[int, int] | None:
        edge = self.api.lane.getEdgeID(lane)
        index = int(lane.rsplit("_", 1)[1])
        length = self.api.lane.getLength(lane)
        x, y = self.api.simulation.convert2D(edge, min(max(pos, 0.0), length), index)
        r, c, inside = geometry.cell_index(np.array([[x, y]]))
        return (int(r[0]), int(c[0])) if inside[0] else None

    def _say_broken(self, detector: Detector, occupancy: float) -> None:
        """One notice per detector of the scenario whose reading SUMO gave broken (left out)."""
        if detector.id in self._broken:
            return
        self._broken.add(detector.id)
        from twin.boundary import notify

        notify(
            f"twin: notice: the scenario's detector {detector.id!r} (lane {detector.lane}) read "
            f"an occupancy of {occupancy:.4g} % over its last interval, SUMO's value through its "
            "API miscounting a vehicle on the loop as the interval ended (its file output does "
            f"not): its readings below {OCCUPANCY_FLOOR:g} % are left out; a longer period, "
            "e.g. twin's step, makes them rarer"
        )

    def read(self) -> list[tuple[int, int, float, float]]:
        """``(index, vehicles, occupancy %, mean speed m/s)`` of each detector whose last
        completed interval is new (twin's loops: always; speed NaN when nothing passed)."""
        rows = []
        now = float(self.api.simulation.getTime())
        for n, d in enumerate(self.detectors):
            if now < self._first_end.get(d.id, self._begin + DEFAULT_PERIOD_S) - 1e-6:
                continue  # its first interval has not ended: SUMO gives zeros, not a reading
            period = self._periods.get(d.id)
            known = not d.virtual and period is not None  # its interval is told by its period
            if known:  # (asked before SUMO is: an interval read already costs no call)
                done = math.floor((now - self._begin) / period + 1e-6)
                if self._intervals.get(d.id) == done:
                    continue
                self._intervals[d.id] = done
            dom = self.api.inductionloop if d.kind == LOOP else self.api.lanearea
            reading = (
                int(dom.getLastIntervalVehicleNumber(d.id)),
                float(dom.getLastIntervalOccupancy(d.id)),
                float(dom.getLastIntervalMeanSpeed(d.id)),
            )
            if not d.virtual and not known and self._last.get(d.id) == reading:
                continue
            self._last[d.id] = reading
            count, occupancy, speed = reading
            if occupancy < OCCUPANCY_FLOOR and not d.virtual:
                self._say_broken(d, occupancy)
                continue
            occupancy = max(occupancy, 0.0)  # a dip below 0: no vehicle time (importance 0)
            rows.append((n, count, occupancy, speed if speed >= 0 else float("nan")))
        return rows
