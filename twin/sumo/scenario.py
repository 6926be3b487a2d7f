"""A SUMO scenario from a config's ``[traffic] kind = "sumo"`` table, or from swapped-in files.

Keys of ``[traffic]`` (all optional except ``kind``; see configs/shenzhen.toml):

- ``network``: a built-in network (``networks/<name>/spec.toml``), built on first use;
  or ``net`` (+ ``routes``), ``sumocfg``, ``osm``: files, relative to the config file;
- ``cell_m`` (500), ``drone_speed_kmh`` (24): one step = ``cell_m / speed`` of simulated time;
- ``additional``: additional files (vehicle types, signal programs, detectors, polygons) for
  SUMO, besides those of the sumocfg; files may be gzip-compressed, as SUMO reads them; their
  vehicles, flows and persons are demand, as SUMO loads them;
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

import contextlib
import hashlib
import math
import sys
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from twin.clock import clock_label, parse_clock
from twin.config import MFDSettings, SumoSettings
from twin.errors import UserError
from twin.grid import Grid
from twin.sumo.readers import (
    SUMOCFG_ROOTS,
    departure_span,
    naming_the_sumocfg,
    read_sumocfg,
    resolved,
    root_tag,
)

#: SUMO's step (s, its default --step-length): a twin step may not be shorter.
SUMO_STEP_S = 1.0
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


@contextlib.contextmanager
def _named_in(sumocfg: Path | None, files: list[Path]) -> Iterator[None]:
    """A one-line error about one of ``files`` names the ``sumocfg`` that lists it too."""
    try:
        yield
    except UserError as exc:
        message = naming_the_sumocfg(str(exc), sumocfg, files)
        if message == str(exc):
            raise
        raise UserError(message) from exc


def notice(text: str) -> None:
    print(f"twin: notice: {text}", file=sys.stderr)


@dataclass
class SumoInputs:
    """Files and settings that replace the config's SUMO scenario (``twin run`` flags)."""

    net: Path | None = None
    routes: list[Path] | None = None
    sumocfg: Path | None = None
    osm: Path | None = None
    horizon: int | None = None
    begin: str | None = None
    mesoscopic: bool | None = None
    additional: list[Path] | None = None
    cell_m: float | None = None
    drone_speed_kmh: float | None = None

    def as_kwargs(self) -> dict[str, Any]:
        return {k: v for k, v in vars(self).items() if v is not None}


def live_source(
    config,
    index: int = 0,
    traffic_seed: int | None = None,
    separate_process: bool = False,
    **inputs: Any,
):
    """The live source of the ``index``-th seed (:func:`twin.traffic.kinds.build_traffic`):
    SUMO seed ``traffic_seed + index`` (``traffic_seed`` defaults to ``[traffic].seed``), the
    :class:`SumoInputs` given as keywords; with ``separate_process`` SUMO works ahead of the
    swarms in a process of its own (:mod:`twin.sumo.worker`)."""
    base = sumo_settings(config).seed if traffic_seed is None else traffic_seed
    source = sumo_source(config, seed=base + index, **inputs)
    source.separate_process = separate_process
    return source


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
    begin_where = "--begin" if begin else f"{config.path}: [traffic].begin"
    begin_given = begin is not None or (not swapped and "begin" in fields)
    horizon_given = horizon is not None or (not swapped and "horizon" in fields)
    begin = (
        parse_clock(begin, "--begin")
        if begin
        else parse_clock(s.begin, f"{config.path}: [traffic].begin")
    )
    warmup = s.warmup_min * 60.0
    demand = load_spec(resources.network_spec("shenzhen_like"))["demand"]

    sumocfg_path = resolved(s.sumocfg) if s.sumocfg else None
    additional_files = [resolved(a) for a in s.additional]
    window: list[float | None] = [None, None]  # the scenario's own time window
    span = None  # first and last departure of the given demand
    listed: list[Path] = []  # the files of the sumocfg that twin uses (named with it in errors)
    if s.network and not (s.net or sumocfg_path or s.osm):
        built = build_named_network(s.network)
        net_file, route_files, name = built.net_file, [built.trips_file], s.network
        if s.routes:
            route_files = [Path(r) for r in s.routes]
            _check_routes(route_files)
            departure_span(route_files)  # departures SUMO refuses are named here
        _check_additional(additional_files)
        own_window = False
    else:
        if sumocfg_path is not None:
            cfg = read_sumocfg(sumocfg_path, own_net=not s.net)
            # a network given besides the sumocfg replaces its own, as `sumo -c ... -n` does
            net_file, route_files = (Path(s.net) if s.net else cfg.net), cfg.routes
            additional_files = [*cfg.additional, *additional_files]
            listed = [*([] if s.net else [cfg.net]), *([] if s.routes else cfg.routes)]
            listed += cfg.additional
            window = [cfg.begin, cfg.end]
            name = sumocfg_path.name
        elif s.osm:
            osm_path = Path(s.osm)
            net_file = import_osm(osm_path)  # cached
            route_files, name = [], osm_path.name
        else:
            net_file, route_files, name = Path(s.net), [], Path(s.net).name
        if s.routes:
            route_files = [Path(r) for r in s.routes]
        with _named_in(sumocfg_path, listed):
            check_net_file(net_file)
            _check_routes(route_files)
            _check_additional(additional_files)
            # SUMO loads vehicles, flows and persons of additional files as demand too
            span = departure_span([*route_files, *additional_files])
        if span is None and sumocfg_path is not None and not route_files:
            notice(
                f"{sumocfg_path}: names no <route-files>; twin generates a rush-hour demand "
                "(add route files to the config to run your own)"
            )
        elif span is None and route_files:
            notice(
                f"{', '.join(str(r) for r in route_files)}: no vehicle departs in the route "
                "files (vehicle types only?); twin generates a rush-hour demand"
            )
        own_window = span is not None
    if s.end is not None and not swapped:
        window[1] = parse_clock(s.end, f"{config.path}: [traffic].end")
    with _named_in(sumocfg_path, listed):
        check_net_file(net_file)
        lanes = read_lanes(net_file)
    step_s = s.cell_m / (s.drone_speed_kmh / 3.6)
    if step_s < SUMO_STEP_S:
        flags = [f"--drone-speed {drone_speed_kmh:g}" if drone_speed_kmh else ""]
        flags.append(f"--cell-m {cell_m:g}" if cell_m else "")
        where = ", ".join(f for f in flags if f) or f"{config.path}: [traffic]"
        raise UserError(
            f"{where}: a step ({s.cell_m:g} m at {s.drone_speed_kmh:g} km/h) lasts {step_s:.2g} "
            f"s, shorter than SUMO's {SUMO_STEP_S:g} s step; give a lower drone speed or larger "
            "cells"
        )

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
    if begin < warmup:
        raise UserError(
            f"{begin_where} = {clock_label(begin)}: the {warmup / 60:g} min warm-up "
            f"([traffic].warmup_min) would start SUMO before 00:00, which SUMO refuses; give a "
            f"begin of at least {clock_label(warmup)} or a shorter warm-up"
        )

    # The grid: derived from the bounding box, or the config's [grid] nx, ny if it gives them
    # (for the configured network only; a swapped-in network gets its own grid).
    shape = None
    if not (net or sumocfg or osm or cell_m):
        shape = config.explicit_shape()  # set in the file or by an override
    where = f"--cell-m {cell_m:g}" if cell_m else f"{config.path}: [grid]"
    geometry = grid_over(lanes, s.cell_m, shape, where=where)
    obstacles = geometry.obstacles(s.min_lane_km)
    for i, j in getattr(config.grid, "obstacles", []) or []:
        if 0 <= i < geometry.nx and 0 <= j < geometry.ny:
            obstacles[i, j] = True
    if obstacles.all():
        raise UserError(f"{net_file}: no cell of the {geometry.nx} x {geometry.ny} grid has a lane")
    n_free, n_drones = int((~obstacles).sum()), config.swarm.n_drones
    notices = []
    if n_drones <= n_free < MIN_FREE_CELLS_PER_DRONE * n_drones:  # more drones: refused later
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

    if span is None and not s.network:  # no demand given: twin generates it
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
            "sumocfg_files": [str(f) for f in listed],
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
    "SumoInputs",
    "SumoSettings",
    "live_source",
    "parse_clock",
    "sumo_settings",
    "sumo_source",
]
