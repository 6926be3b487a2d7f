"""A SUMO scenario from a config's ``[traffic] kind = "sumo"`` table, or from swapped-in files.

Keys of ``[traffic]`` (all optional except ``kind``; see configs/shenzhen.toml):

- ``network``: a built-in network (``networks/<name>/spec.toml``), built on first use;
  or ``net`` (+ ``routes``), ``sumocfg``, ``osm``: files, relative to the config file;
- ``cell_m`` (500), ``drone_speed_kmh`` (24): one step = ``cell_m / speed`` of simulated time;
- ``begin`` ("07:00", time of ``T^0``), ``horizon`` (144), ``warmup_min`` (30), ``seed`` (0);
- ``mesoscopic`` (false), ``min_lane_km`` (0: a cell is an obstacle only without any lane),
  ``demand_scale`` (1.0, demand generated for networks without routes);
- ``[traffic.mfd]``: ``fit`` ("online" | "fixed"), ``a``, ``k_c`` (the fixed or prior MFD),
  ``detection_p`` (1.0).

Networks without demand get a rush-hour demand from SUMO's randomTrips.py (+ duarouter),
scaled to the network's lane-km, cached in the user cache (``imported/``, :mod:`twin.resources`).
"""

from __future__ import annotations

import hashlib
import re
import xml.etree.ElementTree as ET
from pathlib import Path
from typing import Any

from twin.config import MFDSettings, SumoSettings
from twin.errors import UserError
from twin.grid import Grid

#: Peak demand of the built-in network per lane-km (trips/h), used to scale generated demand.
SHENZHEN_LANE_KM = 1350.0


def parse_clock(text: str, where: str) -> float:
    """'07:00' or '07:00:30' -> seconds since midnight."""
    m = re.fullmatch(r"(\d{1,2}):(\d{2})(?::(\d{2}))?", str(text).strip())
    if not m:
        raise UserError(f'{where} = {text!r} must be a clock time like "07:00"')
    h, mi, s = int(m[1]), int(m[2]), int(m[3] or 0)
    return float(h * 3600 + mi * 60 + s)


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


def read_sumocfg(path: Path) -> tuple[Path, list[Path]]:
    """Net file and route files named in a ``.sumocfg`` (relative to it)."""
    if not path.exists():
        raise UserError(f"{path}: no such SUMO config")
    try:
        root = ET.parse(path).getroot()
    except ET.ParseError as exc:
        raise UserError(f"{path}: not valid XML ({exc})") from exc
    net = root.find(".//net-file")
    if net is None or not net.get("value"):
        raise UserError(f"{path}: names no <net-file value=...>; add one")
    routes = root.find(".//route-files")
    route_files = []
    if routes is not None and routes.get("value"):
        route_files = [path.parent / r.strip() for r in routes.get("value").split(",") if r.strip()]
    return path.parent / net.get("value"), route_files


def earliest_depart(route_files: list[Path]) -> float | None:
    """The earliest numeric departure (``depart`` of vehicles/trips, ``begin`` of flows)."""
    first = None
    for path in route_files:
        try:
            for _, elem in ET.iterparse(path, events=("end",)):
                value = elem.get("depart") if elem.tag in ("vehicle", "trip") else None
                value = elem.get("begin") if elem.tag == "flow" else value
                if value is not None:
                    try:
                        t = float(value)
                    except ValueError:
                        t = None
                    if t is not None:
                        first = t if first is None else min(first, t)
                elem.clear()
        except ET.ParseError as exc:
            raise UserError(f"{path}: not valid XML ({exc})") from exc
        except FileNotFoundError as exc:
            raise UserError(f"{path}: no such route file") from exc
    return first


def _check_routes(route_files: list[Path]) -> None:
    for path in route_files:
        if not Path(path).exists():
            raise UserError(f"{path}: no such route file")
        try:
            tag = next(ET.iterparse(path, events=("start",)))[1].tag
        except ET.ParseError as exc:
            raise UserError(f"{path}: not valid XML ({exc})") from exc
        if tag not in ("routes", "additional"):
            raise UserError(f"{path}: not a SUMO route file (root <{tag}>, want <routes>)")


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
):
    """The live :class:`SumoTraffic` of a config; the file arguments swap the network in."""
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
    swapped = bool(net or sumocfg or osm or routes)
    if net or sumocfg or osm:
        s.network, s.net, s.sumocfg, s.osm = None, None, None, None
        s.routes = []
    s.net = str(net) if net else s.net
    s.sumocfg = str(sumocfg) if sumocfg else s.sumocfg
    s.osm = str(osm) if osm else s.osm
    s.routes = [str(r) for r in routes] if routes else s.routes
    if horizon is not None:
        s.horizon = horizon
    if mesoscopic is not None:
        s.mesoscopic = mesoscopic
    seed = s.seed if seed is None else seed
    begin_given = begin is not None or (not swapped and "begin" in config.traffic.model_fields_set)
    begin = parse_clock(begin or s.begin, f"{config.path}: [traffic].begin")
    warmup = s.warmup_min * 60.0
    demand = load_spec(resources.network_spec("shenzhen_like"))["demand"]

    sumocfg_path = Path(s.sumocfg) if s.sumocfg else None
    if s.network and not (s.net or sumocfg_path or s.osm):
        built = build_named_network(s.network)
        net_file, route_files, name = built.net_file, [built.trips_file], s.network
        if s.routes:
            route_files = [Path(r) for r in s.routes]
    else:
        if sumocfg_path is not None:
            net_file, route_files = read_sumocfg(sumocfg_path)
            name = sumocfg_path.name
        elif s.osm:
            osm_path = Path(s.osm)
            net_file = import_osm(osm_path)  # cached
            route_files, name = [], osm_path.name
        else:
            net_file, route_files, name = Path(s.net), [], Path(s.net).name
        if s.routes:
            route_files = [Path(r) for r in s.routes]
        _check_routes(route_files)
        if route_files:
            first = earliest_depart(route_files)
            if first is not None and not begin_given:
                begin = first + warmup
    check_net_file(net_file)
    lanes = read_lanes(net_file)

    # The grid: derived from the bounding box, or the config's [grid] nx, ny if it gives them
    # (for the configured network only; a swapped-in network gets its own grid).
    shape = None
    if not (net or sumocfg or osm):
        shape = config.explicit_shape()  # set in the file or by an override
    geometry = grid_over(lanes, s.cell_m, shape, where=f"{config.path}: [grid]")
    obstacles = geometry.obstacles(s.min_lane_km)
    for i, j in getattr(config.grid, "obstacles", []) or []:
        if 0 <= i < geometry.nx and 0 <= j < geometry.ny:
            obstacles[i, j] = True
    if obstacles.all():
        raise UserError(f"{net_file}: no cell of the {geometry.nx} x {geometry.ny} grid has a lane")

    if not route_files:
        lane_km = float(geometry.lane_km.sum())
        scale = s.demand_scale * lane_km / SHENZHEN_LANE_KM
        window = {**demand, "begin_s": begin - warmup, "end_s": begin + s.horizon * s.step_s}
        window["peak_s"] = window["begin_s"] + (demand["peak_s"] - demand["begin_s"])
        key = (
            f"{Path(net_file).stem}-{_digest(Path(net_file), window, scale, seed, sumo_version())}"
        )
        out = resources.build_once(
            resources.cache_dir() / "imported" / key,
            lambda d: random_rush_hour_trips(
                Path(net_file), d / "rush_hour.trips.xml", window, seed=seed, scale=scale
            ),
        )
        route_files = [out / "rush_hour.trips.xml"]

    scenario = SumoScenario(
        net_file=Path(net_file),
        route_files=[Path(r) for r in route_files],
        begin_s=begin,
        warmup_s=warmup,
        step_s=s.step_s,
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
    )
    return SumoTraffic(scenario, geometry, Grid(obstacles))


__all__ = ["MFDSettings", "SumoSettings", "parse_clock", "sumo_settings", "sumo_source"]
