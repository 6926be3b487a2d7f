"""A SUMO scenario from a config's ``[traffic] kind = "sumo"`` table, or from swapped-in files.

Keys of ``[traffic]`` (all optional except ``kind``; see configs/shenzhen.toml):

- ``network``: a built-in network (``networks/<name>/spec.toml``), built on first use;
  or ``net`` (+ ``routes``), ``sumocfg``, ``osm``: files, relative to the config file;
- ``cell_m`` (500), ``drone_speed_kmh`` (24): one step = ``cell_m / speed`` of simulated time;
- ``additional``: additional files (vehicle types, signal programs, detectors, polygons) for
  SUMO, besides those of the sumocfg; files may be gzip-compressed, as SUMO reads them;
- ``begin`` ("07:00", time of ``T^0``), ``horizon`` (144), ``warmup_min`` (30), ``seed`` (0);
  ``end`` (a clock time): the end of the scenario's window. For a network given as files, the
  window is its own (``<time>`` of the sumocfg, else the demand's departures) unless set;
- ``mesoscopic`` (false), ``min_lane_km`` (0: a cell is an obstacle only without any lane),
  ``demand_scale`` (1.0, demand generated for networks without routes);
- ``[traffic.mfd]``: ``fit`` ("online" | "fixed"), ``a``, ``k_c`` (the fixed or prior MFD),
  ``detection_p`` (1.0).

Networks without demand get a rush-hour demand from SUMO's randomTrips.py (+ duarouter),
scaled to the network's lane-km, cached in the user cache (``imported/``, :mod:`twin.resources`).
"""

from __future__ import annotations

import gzip
import hashlib
import math
import sys
import xml.etree.ElementTree as ET
from dataclasses import dataclass, field
from pathlib import Path
from typing import IO, Any

from twin.clock import clock_label, parse_clock
from twin.config import MFDSettings, SumoSettings
from twin.errors import UserError
from twin.grid import Grid

#: Peak demand of the built-in network per lane-km (trips/h), used to scale generated demand.
SHENZHEN_LANE_KM = 1350.0


def sumo_settings(config) -> SumoSettings:
    """The SUMO settings of a scenario config (validated with it), file paths resolved against
    the config's folder; a copy the caller may change."""
    if not isinstance(config.traffic, SumoSettings):
        raise UserError(f"{config.path}: [traffic].kind = {config.traffic.kind!r} is not sumo")
    s = config.traffic.model_copy(deep=True)
    base = Path(config.path).resolve().parent
    for key in ("net", "sumocfg", "osm"):
        if getattr(s, key) is not None:
            setattr(s, key, str(base / getattr(s, key)))
    s.routes = [str(base / r) for r in s.routes]
    s.additional = [str(base / a) for a in s.additional]
    if s.net or s.sumocfg or s.osm:
        s.network = None
    return s


def _digest(*parts: Any) -> str:
    h = hashlib.sha256()
    for p in parts:
        if isinstance(p, Path) and p.exists():
            h.update(p.read_bytes())
        else:
            h.update(repr(p).encode())
    return h.hexdigest()[:12]


def open_xml(path: Path) -> IO[bytes]:
    """A SUMO XML file for reading, gzip-compressed or not (SUMO reads both; told by content)."""
    path = Path(path)
    fh = open(path, "rb")  # noqa: SIM115 (the caller closes it)
    if fh.read(2) == b"\x1f\x8b":
        fh.close()
        return gzip.open(path, "rb")
    fh.seek(0)
    return fh


def root_tag(path: Path, what: str) -> str:
    """The root element of a SUMO XML file (compressed or not); one-line errors."""
    path = Path(path)
    if not path.exists():
        raise UserError(f"{path}: no such {what}")
    try:
        with open_xml(path) as fh:
            return next(ET.iterparse(fh, events=("start",)))[1].tag
    except (ET.ParseError, OSError, EOFError, StopIteration) as exc:
        raise UserError(f"{path}: not valid XML ({exc or 'empty file'})") from exc


@dataclass
class SumoConfigFile:
    """What twin takes from a ``.sumocfg``: files (resolved against its folder) and window."""

    net: Path
    routes: list[Path]
    additional: list[Path]
    begin: float | None = None
    end: float | None = None
    #: every option the file sets (element name -> value, as written), e.g. its outputs
    options: dict[str, str] = field(default_factory=dict)
    path: Path | None = None


def _file_list(value: str | None, base: Path) -> list[Path]:
    return [(base / v.strip()).resolve() for v in (value or "").split(",") if v.strip()]


def parse_time(value: str | None) -> float | None:
    """A SUMO time value: seconds ("3600", "3600.5") or a clock ("1:00:00"); None if neither
    (also for NaN and infinite values, which SUMO refuses too)."""
    if value is None:
        return None
    try:
        t = float(value)
    except ValueError:
        pass
    else:
        return t if math.isfinite(t) else None
    parts = str(value).strip().split(":")
    try:
        numbers = [float(x) for x in parts]
    except ValueError:
        return None
    if len(parts) not in (3, 4) or not all(math.isfinite(x) for x in numbers):
        return None
    total = 0.0
    for x, unit in zip(reversed(numbers), (1, 60, 3600, 86400), strict=False):
        total += x * unit
    return total


#: Roots of a SUMO simulation config: ``<configuration>``, and ``<sumoConfiguration>`` as
#: ``sumo -C`` (``--save-configuration``) writes it.
SUMOCFG_ROOTS = ("configuration", "sumoConfiguration")


def sumocfg_options(root: ET.Element) -> dict[str, str]:
    """The options a SUMO config sets: ``<section><name value="..."/></section>`` or, as SUMO
    also reads, ``<name>...</name>``; element name -> value (the last one wins, as in SUMO)."""
    options: dict[str, str] = {}
    for section in root:
        if not isinstance(section.tag, str):
            continue
        for elem in section:
            if not isinstance(elem.tag, str):
                continue
            value = elem.get("value")
            if value is None and elem.text is not None and elem.text.strip():
                value = elem.text.strip()
            if value is not None:
                options[elem.tag] = value
    return options


def read_sumocfg(path: Path) -> SumoConfigFile:
    """Net, route and additional files of a ``.sumocfg`` (relative to its folder, as SUMO reads
    them), its ``<time>`` window, if it gives one, and all its options."""
    path = Path(path).resolve() if Path(path).exists() else Path(path)
    tag = root_tag(path, "SUMO config")
    if tag not in SUMOCFG_ROOTS:
        what = (
            f"a {tag[: -len('Configuration')]} config"
            if tag.endswith("Configuration")
            else (f"root <{tag}>")
        )
        raise UserError(
            f"{path}: not a SUMO simulation config ({what}); give a .sumocfg with a "
            "<configuration> or <sumoConfiguration> root (as `sumo -C` writes)"
        )
    with open(path, "rb") as fh:
        compressed = fh.read(2) == b"\x1f\x8b"
    if compressed:  # SUMO reads compressed network, route and additional files, not configs
        raise UserError(
            f"{path}: a gzip-compressed config, which SUMO does not read; decompress it "
            f"(gunzip -k {path.name}), its files may stay compressed"
        )
    try:
        with open(path, "rb") as fh:
            root = ET.parse(fh).getroot()
    except (ET.ParseError, OSError, EOFError) as exc:
        raise UserError(f"{path}: not valid XML ({exc})") from exc
    options = sumocfg_options(root)

    def value(*names: str) -> str | None:
        for name in names:
            if options.get(name):
                return options[name]
        return None

    net = _file_list(value("net-file", "n"), path.parent)
    if not net:
        raise UserError(
            f"{path}: names no network; add <net-file value=...> to its <input> (twin needs "
            "the network to lay its grid)"
        )
    window = []
    for key in ("begin", "end"):
        text = value(key, "b" if key == "begin" else "e")
        t = parse_time(text)
        if text is not None and t is None:
            raise UserError(
                f"{path}: <{key} value={text!r}> is not a finite time; give seconds "
                "(e.g. 3600) or a clock (1:00:00)"
            )
        if key == "end" and t is not None and t < 0:  # SUMO's default -1: no end
            t = None
        window.append(t)
    if None not in window and window[1] <= window[0]:
        raise UserError(
            f"{path}: <end value={value('end', 'e')!r}> is not after <begin "
            f"value={value('begin', 'b')!r}>; give an end after the begin"
        )
    return SumoConfigFile(
        net=net[0],
        routes=_file_list(value("route-files", "r"), path.parent),
        additional=_file_list(value("additional-files", "a"), path.parent),
        begin=window[0],
        end=window[1],
        options=options,
        path=path,
    )


#: Elements that put vehicles on the road, and the attribute of their departure.
_DEPARTING = {"vehicle": "depart", "trip": "depart", "person": "depart", "flow": "begin"}


def departure_span(route_files: list[Path]) -> tuple[float, float] | None:
    """First and last numeric departure of the demand (``depart`` of vehicles, trips and persons,
    ``begin`` .. ``end`` of flows); None when the files hold no vehicle (e.g. only vTypes)."""
    first = last = None
    for path in route_files:
        try:
            with open_xml(path) as fh:
                for _, elem in ET.iterparse(fh, events=("end",)):
                    key = _DEPARTING.get(elem.tag)
                    t = parse_time(elem.get(key)) if key else None
                    if t is not None:
                        end = t
                        if elem.tag == "flow":
                            end = _flow_end(elem, t)
                        first = t if first is None else min(first, t)
                        last = end if last is None else max(last, end)
                    if elem.tag in _DEPARTING or elem.tag in ("route", "vType"):
                        elem.clear()
        except (ET.ParseError, OSError, EOFError) as exc:
            raise UserError(f"{path}: not valid XML ({exc})") from exc
    return None if first is None else (first, last)


def _flow_end(elem: ET.Element, begin: float) -> float:
    end = parse_time(elem.get("end"))
    if end is not None:
        return end
    number = elem.get("number")
    step = parse_time(elem.get("period")) or parse_time(elem.get("headway"))
    if number is not None and step is not None:
        return begin + float(number) * step
    return begin + 3600.0  # SUMO's default flow end is its --end; assume an hour


#: Roots of SUMO files that are not demand nor additional files, and what to do instead.
_OTHER_KINDS = {
    "net": "a SUMO network; pass it as --net (or net = ... in [traffic])",
    "osm": "an OpenStreetMap extract; pass it as --osm",
    **{r: "a SUMO config; pass it as --sumocfg" for r in SUMOCFG_ROOTS},
}


def _check_routes(route_files: list[Path]) -> None:
    """SUMO reads route files whatever their root (``<routes>`` as SUMO writes them): twin
    refuses only a file of another kind (network, config, OSM), which SUMO would misread."""
    for path in route_files:
        tag = root_tag(path, "route file")
        if tag in _OTHER_KINDS:
            raise UserError(f"{path}: not a route file but {_OTHER_KINDS[tag]}")


def _check_additional(files: list[Path]) -> None:
    """SUMO reads additional files whatever their root (``<additional>``, the older ``<add>``,
    ``<routes>``, ``<polygons>`` ...): twin refuses only a file of another kind."""
    for path in files:
        tag = root_tag(path, "additional file")
        if tag in _OTHER_KINDS:
            raise UserError(f"{path}: not an additional file but {_OTHER_KINDS[tag]}")


#: Fewer free cells per drone than this, and every swarm covers nearly all cells: the comparison
#: says little, so twin says so and suggests a smaller cell.
MIN_FREE_CELLS_PER_DRONE = 10
#: The smallest cell size twin suggests (m): below it a step is only a few seconds.
MIN_SUGGESTED_CELL_M = 25.0


def clearing_time(geometry) -> float:
    """Time (s) the network needs to empty after the last departure, estimated from its size:
    the lanes' bounding-box diagonal at 5 m/s (18 km/h, a congested city average), kept within
    15 - 30 min."""
    xmin, ymin, xmax, ymax = geometry.bbox
    return float(min(1800.0, max(900.0, math.hypot(xmax - xmin, ymax - ymin) / 5.0)))


def suggest_cell_m(lanes, cell_m: float, n_drones: int, min_lane_km: float = 0.0):
    """Halve ``cell_m`` until the network's grid has ``MIN_FREE_CELLS_PER_DRONE`` free cells per
    drone: ``(cell size, free cells)``, or None if no size down to ``MIN_SUGGESTED_CELL_M`` does."""
    from twin.sumo.cells import grid_over

    need = MIN_FREE_CELLS_PER_DRONE * n_drones
    size = cell_m / 2
    while size >= MIN_SUGGESTED_CELL_M:
        free = int((~grid_over(lanes, size).obstacles(min_lane_km)).sum())
        if free >= need:
            return size, free
        size /= 2
    return None


def notice(text: str) -> None:
    print(f"twin: notice: {text}", file=sys.stderr)


def sumo_source(
    config,
    seed: int | None = None,
    net: Path | None = None,
    routes: list[Path] | None = None,
    sumocfg: Path | None = None,
    osm: Path | None = None,
    horizon: int | None = None,
    mesoscopic: bool | None = None,
    begin: str | None = None,
    additional: list[Path] | None = None,
    cell_m: float | None = None,
    drone_speed_kmh: float | None = None,
):
    """The live :class:`SumoTraffic` of a config; the file arguments swap the network in.

    The time window of a network brought as files is the scenario's own: ``<time>`` of the
    sumocfg, else the span of the demand's departures; the warm-up is taken inside it (``T^0`` =
    window begin + warm-up) and the horizon is what fits, unless ``begin``/``horizon`` are given.
    """
    from twin import resources
    from twin.sumo.cells import grid_over, read_lanes
    from twin.sumo.demand import random_rush_hour_trips
    from twin.sumo.network import (
        build_named_network,
        check_net_file,
        import_osm,
        load_spec,
        sumo_version,
    )
    from twin.sumo.source import SumoScenario, SumoTraffic

    s = sumo_settings(config)
    fields = config.traffic.model_fields_set
    swapped = bool(net or sumocfg or osm or routes)
    if net or sumocfg or osm:
        s.network, s.net, s.sumocfg, s.osm = None, None, None, None
        s.routes, s.additional = [], []
        s.end = None
    s.net = str(net) if net else s.net
    s.sumocfg = str(sumocfg) if sumocfg else s.sumocfg
    s.osm = str(osm) if osm else s.osm
    s.routes = [str(r) for r in routes] if routes else s.routes
    s.additional = [*s.additional, *(str(a) for a in additional or [])]
    if horizon is not None:
        s.horizon = horizon
    if mesoscopic is not None:
        s.mesoscopic = mesoscopic
    if cell_m is not None:
        s.cell_m = cell_m
    if drone_speed_kmh is not None:
        s.drone_speed_kmh = drone_speed_kmh
    seed = s.seed if seed is None else seed
    begin_given = begin is not None or (not swapped and "begin" in fields)
    horizon_given = horizon is not None or (not swapped and "horizon" in fields)
    begin = parse_clock(begin or s.begin, f"{config.path}: [traffic].begin")
    warmup = s.warmup_min * 60.0
    demand = load_spec(resources.network_spec("shenzhen_like"))["demand"]

    sumocfg_path = Path(s.sumocfg).resolve() if s.sumocfg else None
    additional_files = [Path(a).resolve() for a in s.additional]
    window: list[float | None] = [None, None]  # the scenario's own time window
    span = None  # first and last departure of the given demand
    if s.network and not (s.net or sumocfg_path or s.osm):
        built = build_named_network(s.network)
        net_file, route_files, name = built.net_file, [built.trips_file], s.network
        if s.routes:
            route_files = [Path(r) for r in s.routes]
        own_window = False
    else:
        if sumocfg_path is not None:
            cfg = read_sumocfg(sumocfg_path)
            net_file, route_files = cfg.net, cfg.routes
            additional_files = [*cfg.additional, *additional_files]
            window = [cfg.begin, cfg.end]
            name = sumocfg_path.name
            if not route_files and not s.routes:
                notice(
                    f"{sumocfg_path}: names no <route-files>; twin generates a rush-hour demand "
                    "(add route files to the config to run your own)"
                )
        elif s.osm:
            osm_path = Path(s.osm)
            net_file = import_osm(osm_path)  # cached
            route_files, name = [], osm_path.name
        else:
            net_file, route_files, name = Path(s.net), [], Path(s.net).name
        if s.routes:
            route_files = [Path(r) for r in s.routes]
        _check_routes(route_files)
        span = departure_span(route_files) if route_files else None
        if route_files and span is None:
            notice(
                f"{', '.join(str(r) for r in route_files)}: no vehicle departs in the route "
                "files (vehicle types only?); twin generates a rush-hour demand"
            )
        own_window = span is not None
    _check_additional(additional_files)
    if s.end is not None and not swapped:
        window[1] = parse_clock(s.end, f"{config.path}: [traffic].end")
    check_net_file(net_file)
    lanes = read_lanes(net_file)
    step_s = s.cell_m / (s.drone_speed_kmh / 3.6)

    if own_window:
        w0 = window[0] if window[0] is not None else span[0]
        w1 = window[1] if window[1] is not None else span[1]
        if not begin_given:
            if w1 - w0 < warmup + step_s:  # too short for the warm-up: half of it warms up
                short = max(0.0, (w1 - w0) / 2)
                notice(
                    f"{name}: the scenario's window {clock_label(w0)} - {clock_label(w1)} is shorter than "
                    f"the {warmup / 60:g} min warm-up plus a step; warm-up cut to "
                    f"{short / 60:.1f} min"
                )
                warmup = short
            begin = w0 + warmup
        if not horizon_given:
            s.horizon = max(1, int((w1 - begin) / step_s + 1e-9))

    # The grid: derived from the bounding box, or the config's [grid] nx, ny if it gives them
    # (for the configured network only; a swapped-in network gets its own grid).
    shape = None
    if not (net or sumocfg or osm or cell_m):
        shape = config.explicit_shape()  # set in the file or by an override
    geometry = grid_over(lanes, s.cell_m, shape, where=f"{config.path}: [grid]")
    obstacles = geometry.obstacles(s.min_lane_km)
    for i, j in getattr(config.grid, "obstacles", []) or []:
        if 0 <= i < geometry.nx and 0 <= j < geometry.ny:
            obstacles[i, j] = True
    if obstacles.all():
        raise UserError(f"{net_file}: no cell of the {geometry.nx} x {geometry.ny} grid has a lane")
    n_free, n_drones = int((~obstacles).sum()), config.swarm.n_drones
    notices = []
    if n_free < MIN_FREE_CELLS_PER_DRONE * n_drones:
        better = suggest_cell_m(lanes, s.cell_m, n_drones, s.min_lane_km)
        fix = (
            f"try --cell-m {better[0]:g} ({better[1]} free cells)"
            if better
            else f"use fewer drones (--drones {max(1, n_free // MIN_FREE_CELLS_PER_DRONE)})"
        )
        notices.append(
            f"{name}: {geometry.nx} x {geometry.ny} cells of {s.cell_m:g} m, {n_free} free for "
            f"{n_drones} drones (fewer than {MIN_FREE_CELLS_PER_DRONE} per drone: every swarm "
            f"covers nearly all, the comparison says little); {fix}"
        )
    if span is not None and (begin_given or horizon_given):
        clear = clearing_time(geometry)
        end = begin + s.horizon * step_s
        if end > span[1] + clear:
            notices.append(
                f"{name}: the run ends at {clock_label(end)}, past the last departure "
                f"({clock_label(span[1])}) plus {clear / 60:.0f} min to clear the network; the last "
                f"{int((end - span[1] - clear) / step_s)} steps may have no vehicle"
            )
    for text in notices:
        notice(text)

    if not route_files or (span is None and not s.network):
        lane_km = float(geometry.lane_km.sum())
        scale = s.demand_scale * lane_km / SHENZHEN_LANE_KM
        span_gen = {**demand, "begin_s": begin - warmup, "end_s": begin + s.horizon * step_s}
        span_gen["peak_s"] = span_gen["begin_s"] + (demand["peak_s"] - demand["begin_s"])
        key = (
            f"{Path(net_file).stem}-"
            f"{_digest(Path(net_file), span_gen, scale, seed, sumo_version())}"
        )
        out = resources.build_once(
            resources.cache_dir() / "imported" / key,
            lambda d: random_rush_hour_trips(
                Path(net_file), d / "rush_hour.trips.xml", span_gen, seed=seed, scale=scale
            ),
            verify=lambda d: resources.check_xml_files(d, {"rush_hour.trips.xml": "routes"}),
        )
        route_files = [*route_files, out / "rush_hour.trips.xml"]

    options: tuple[str, ...] = ()
    if additional_files:
        options = ("--additional-files", ",".join(str(a) for a in additional_files))
    scenario = SumoScenario(
        net_file=Path(net_file),
        route_files=[Path(r) for r in route_files],
        begin_s=begin,
        warmup_s=warmup,
        step_s=step_s,
        horizon=s.horizon,
        seed=seed,
        mesoscopic=s.mesoscopic,
        mfd_fit=s.mfd.fit,
        detection_p=s.mfd.detection_p,
        name=name,
        sumocfg=sumocfg_path,
        mfd_prior=(s.mfd.a, s.mfd.k_c),
        reads_per_step=s.reads_per_step,
        incidents=list(s.incidents),
        sumo_options=options,
        extra={
            "additional_files": [str(a) for a in additional_files],
            "window": [w0, w1] if own_window else None,
            "departures": list(span) if span else None,
            "n_drones": n_drones,
            "n_free": n_free,
            "notices": notices,
        },
    )
    if scenario.incidents:  # checked before SUMO starts, against the final window and grid
        from twin.sumo.incidents import check_incidents

        for text in check_incidents(scenario.incidents, scenario, geometry, str(config.path)):
            notices.append(text)
            notice(text)
    return SumoTraffic(scenario, geometry, Grid(obstacles))


__all__ = [
    "MIN_FREE_CELLS_PER_DRONE",
    "MFDSettings",
    "SumoSettings",
    "parse_clock",
    "read_sumocfg",
    "sumo_settings",
    "sumo_source",
]
