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
  window is its own (``<time>`` of the sumocfg, else the demand's departures) unless set; a
  ``horizon`` the config gives must end by its ``end`` (a flag may take it past, with a notice);
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
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from twin.clock import clock_label, parse_clock
from twin.config import MFDSettings, SumoSettings, with_overrides
from twin.errors import UserError
from twin.grid import Grid
from twin.sumo.readers import (
    AT_BEGIN,
    SUMOCFG_ROOTS,
    VEHICLE_DEMAND,
    check_cache_without_comma,
    check_no_comma,
    departure_span,
    include_cycle,
    naming_the_sumocfg,
    parse_time,
    read_sumocfg,
    resolved,
    root_tag,
    sumo_bool,
)

#: SUMO's step (s, its default --step-length): a twin step may not be shorter.
SUMO_STEP_S = 1.0
#: The longest twin step (s): one drone move per simulated day at most.
MAX_STEP_S = 86400.0

#: Where the window of a demand with an open flow (no end, no number) ends when no end is
#: given: midnight, or its last other departure, or an hour after its (given) begin, whichever
#: is latest.
OPEN_DEMAND_END = 86400.0


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
        _check_includes(path)


def _check_additional(files: list[Path]) -> None:
    """SUMO reads additional files whatever their root (``<additional>``, the older ``<add>``,
    ``<routes>``, ``<polygons>`` ...): twin refuses only a file of another kind."""
    for path in files:
        tag = root_tag(path, "additional file")
        if tag in _OTHER_KINDS:
            raise UserError(f"{path}: not an additional file but {_OTHER_KINDS[tag]}")
        _check_includes(path)


def _check_includes(path: Path) -> None:
    """Refuse (one line) ``<include href>`` files that include each other, on which SUMO
    crashes without a message."""
    cycle = include_cycle(path)
    if cycle is not None:
        chain = " -> ".join(p.name for p in cycle)
        raise UserError(
            f"{path}: its <include href> files include each other ({chain}), which SUMO cannot "
            "load; include each file once, from one side"
        )


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


def suggest_cell_m(
    lanes, cell_m: float, n_drones: int, min_lane_km: float = 0.0, per_drone: int = 0
):
    """Halve ``cell_m`` until the network's grid has ``per_drone`` free cells per drone
    (default :data:`MIN_FREE_CELLS_PER_DRONE`): ``(cell size, free cells)``, or None if no size
    down to ``MIN_SUGGESTED_CELL_M`` does."""
    from twin.sumo.cells import grid_over

    need = (per_drone or MIN_FREE_CELLS_PER_DRONE) * n_drones
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
    """``twin: notice: text`` on stderr; held back while a command holds its notices until its
    simulation starts (:func:`twin.boundary.hold_notices`)."""
    from twin.boundary import notify

    notify(f"twin: notice: {text}")


@dataclass
class SumoInputs:
    """Files that replace the config's SUMO network and demand (``twin run --net`` ...)."""

    net: Path | None = None
    routes: list[Path] | None = None
    sumocfg: Path | None = None
    osm: Path | None = None
    additional: list[Path] | None = None

    def as_kwargs(self) -> dict[str, Any]:
        return {k: v for k, v in vars(self).items() if v is not None}


#: The ``[traffic]`` keys :func:`sumo_source` also takes as keywords, and the flag of each
#: (named in errors; a key set by its flag counts as given even for a swapped-in network).
SETTING_FLAGS = {
    "horizon": "--horizon",
    "begin": "--begin",
    "mesoscopic": "--meso",
    "cell_m": "--cell-m",
    "drone_speed_kmh": "--drone-speed",
}


def live_source(
    config,
    index: int = 0,
    traffic_seed: int | None = None,
    separate_process: bool = False,
    **inputs: Any,
):
    """The live source of the ``index``-th seed (:func:`twin.traffic_kinds.build_traffic`):
    SUMO seed ``traffic_seed + index`` (``traffic_seed`` defaults to ``[traffic].seed``), the
    :class:`SumoInputs` given as keywords; with ``separate_process`` SUMO works ahead of the
    swarms in a process of its own (:mod:`twin.sumo.worker`)."""
    base = sumo_settings(config).seed if traffic_seed is None else traffic_seed
    source = sumo_source(config, seed=base + index, **inputs)
    source.separate_process = separate_process
    return source


@dataclass
class _ScenarioFiles:
    """The files SUMO will load and what they say of the scenario's time window."""

    net_file: Path
    route_files: list[Path]
    additional_files: list[Path]
    name: str  # the scenario's name in messages: the network, sumocfg or OSM file
    sumocfg: Path | None = None
    listed: list[Path] = field(default_factory=list)  # sumocfg files (named with it in errors)
    #: the sumocfg's files by role ("net", "routes", "additional"): a file given by a flag is
    #: never said to be named in the sumocfg, even where the sumocfg names it in another role
    listed_as: dict[str, list[Path]] = field(default_factory=dict)
    window: list[float | None] = field(default_factory=lambda: [None, None])  # <time> of it
    span: tuple[float, float] | None = None  # first and last departure of the given demand
    last_closed: float | None = None  # its last departure but an open flow's (one without end)
    #: those of a built-in network's demand, which sets no window (the config gives it)
    built_span: tuple[float, float] | None = None
    state_time: float | None = None  # the time of the state the sumocfg loads: SUMO starts there
    at_begin: bool = False  # some of the demand departs at SUMO's begin, wherever that is
    #: SUMO reads the route files step by step (``--route-steps`` > 0, its default 200 s),
    #: ignoring what departs before a departure listed above it
    in_order: bool = True

    @property
    def own_window(self) -> bool:
        """Whether the window comes from the files (a network brought with its demand)."""
        return self.span is not None


def _with_inputs(s: SumoSettings, inputs: SumoInputs, keep_end: bool = False) -> SumoSettings:
    """The settings ``s`` with the swapped-in files and flags of ``inputs`` applied (a
    shipped config's ``end`` is its own network's; the user's own config's, ``keep_end``,
    holds for any)."""
    if inputs.net or inputs.sumocfg or inputs.osm:
        s.network, s.net, s.sumocfg, s.osm = None, None, None, None
        s.routes, s.additional = [], []
        s.end = s.end if keep_end else None
    s.net = str(inputs.net) if inputs.net else s.net
    s.sumocfg = str(inputs.sumocfg) if inputs.sumocfg else s.sumocfg
    s.osm = str(inputs.osm) if inputs.osm else s.osm
    s.routes = [str(r) for r in inputs.routes] if inputs.routes else s.routes
    s.additional = [*s.additional, *(str(a) for a in inputs.additional or [])]
    return s


def _scenario_files(s: SumoSettings) -> _ScenarioFiles:
    """Network, route and additional files (a built-in network is built on first use, an OSM
    extract imported), each checked as SUMO would read it, and the given demand's span."""
    from twin.sumo.network import build_named_network, check_net_file, import_osm

    additional_files = [resolved(a) for a in s.additional]
    sumocfg_path = resolved(s.sumocfg) if s.sumocfg else None
    if s.network and not (s.net or sumocfg_path or s.osm):
        built = build_named_network(s.network)
        files = _ScenarioFiles(built.net_file, [built.trips_file], additional_files, s.network)
        if s.routes:
            files.route_files = [Path(r) for r in s.routes]
            _check_routes(files.route_files)
        _check_additional(additional_files)
        # (departures SUMO refuses are named here); the config gives the window, not these
        files.built_span = departure_span(files.route_files)
        return files
    if sumocfg_path is not None:
        cfg = read_sumocfg(sumocfg_path, own_net=not s.net)
        for key in ("random", "mesosim"):  # SUMO refuses another word before it starts
            if sumo_bool(cfg.options.get(key)) is None:
                raise UserError(
                    f"{sumocfg_path}: <{key} value={cfg.options[key]!r}> is no boolean SUMO "
                    "reads; give true or false"
                )
        if sumo_bool(cfg.options.get("random")):
            notice(
                f"{sumocfg_path}: <random value={cfg.options['random']!r}> (a seed from the "
                "clock) is overridden: twin seeds SUMO with --sumo-seed so that runs repeat"
            )
        if cfg.options.get("seed") is not None:
            notice(
                f"{sumocfg_path}: <seed value={cfg.options['seed']!r}> is replaced by twin's "
                "SUMO seed (--sumo-seed, [traffic].seed: one per run seed), so that runs repeat "
                "by it"
            )
        if not s.mesoscopic and sumo_bool(cfg.options.get("mesosim")):
            s.mesoscopic = True  # SUMO runs it so: recorded, and its detectors refused
            notice(
                f"{sumocfg_path}: <mesosim value={cfg.options['mesosim']!r}> runs SUMO's "
                "mesoscopic model, as --meso does"
            )
        step = cfg.options.get("step-length")
        if step is not None:
            seconds = parse_time(step)  # seconds, or SUMO's [D:]HH:MM:SS
            if seconds is None:  # SUMO refuses it too ("Invalid Number Format")
                raise UserError(
                    f"{sumocfg_path}: <step-length value={step!r}> is not a number of seconds; "
                    f"give one such as {SUMO_STEP_S:g} (twin runs steps of {SUMO_STEP_S:g} s "
                    "anyway), or remove it"
                )
            if seconds != SUMO_STEP_S:
                notice(
                    f"{sumocfg_path}: <step-length value={step!r}> is run as SUMO steps of "
                    f"{SUMO_STEP_S:g} s (twin's clock; its other options are kept)"
                )
        # a network given besides the sumocfg replaces its own, as `sumo -c ... -n` does
        files = _ScenarioFiles(
            Path(s.net) if s.net else cfg.net,
            cfg.routes,
            [*cfg.additional, *additional_files],
            sumocfg_path.name,
            sumocfg=sumocfg_path,
            listed=[
                *([] if s.net else [cfg.net]),
                *([] if s.routes else cfg.routes),
                *cfg.additional,
            ],
            listed_as={
                "net": [] if s.net else [cfg.net],
                "routes": [] if s.routes else list(cfg.routes),
                "additional": list(cfg.additional),
            },
            window=[cfg.begin, cfg.end],
            state_time=cfg.state_time,
            in_order=(parse_time(cfg.options.get("route-steps", "200")) or 0.0) > 0,
        )
    elif s.osm:
        osm_path = Path(s.osm)
        files = _ScenarioFiles(import_osm(osm_path), [], additional_files, osm_path.name)
    else:
        files = _ScenarioFiles(Path(s.net), [], additional_files, Path(s.net).name)
    if s.routes:
        files.route_files = [Path(r) for r in s.routes]
    as_ = files.listed_as
    with _named_in(files.sumocfg, as_.get("net", [])):
        check_net_file(files.net_file)
    with _named_in(files.sumocfg, as_.get("routes", [])):
        _check_routes(files.route_files)
    with _named_in(files.sumocfg, as_.get("additional", [])):
        _check_additional(files.additional_files)
    with _named_in(files.sumocfg, [*as_.get("routes", []), *as_.get("additional", [])]):
        # SUMO loads vehicles, flows and persons of additional files as demand too
        departing: dict[str, int] = {}
        closed: list[float] = []
        ignored: list[str] = []
        files.span = departure_span(
            [*files.route_files, *files.additional_files],
            departing,
            start=files.window[0] or 0.0,
            closed=closed,
            in_order=files.route_files if files.in_order else (),
            ignored=ignored,
        )
        if ignored:
            they = (f"{ignored[0]} and {len(ignored) - 1} more depart before a departure listed "
                    "above them, so SUMO ignores them" if len(ignored) > 1 else f"{ignored[0]} "
                    "departs before a departure listed above it, so SUMO ignores it")  # fmt: skip
            notice(
                f"{they} (route files are read in departure order) and so does the window; "
                "sort the file (SUMO's tools/route/sort_routes.py)"
            )
        files.last_closed = closed[0] if closed else None
        files.at_begin = departing.pop(AT_BEGIN, 0) > 0
    if files.span is None and files.sumocfg is not None and not files.route_files:
        notice(
            f"{files.sumocfg}: names no <route-files>; twin generates a rush-hour demand "
            "(add route files to the config to run your own)"
        )
    elif files.span is None and files.route_files:
        notice(
            f"{', '.join(str(r) for r in files.route_files)}: no vehicle departs in the route "
            "files (vehicle types only?); twin generates a rush-hour demand"
        )
    elif files.span is not None and not any(departing.get(t) for t in VEHICLE_DEMAND):
        named = [*files.route_files, *files.additional_files]
        notice(
            f"{', '.join(str(r) for r in named)}: the demand holds persons or containers but no "
            "vehicle, so every cell's traffic stays 0 (no MFD can be fitted); add vehicles, or "
            "leave the demand out and twin generates a rush-hour one"
        )
    if s.mesoscopic:
        _say_meso_parking([*files.route_files, *files.additional_files])
    return files


def _say_meso_parking(paths: list[Path]) -> None:
    """A notice when SUMO's mesoscopic model runs a demand that parks: it tells no vehicle's
    lane or parking, so parked vehicles count as standing traffic."""
    from twin.sumo.readers import may_hold

    stops = (b'parkingArea="', b"parkingArea='", b'parking="true"', b"parking='true'")
    parking = [p for p in paths if may_hold(Path(p), *stops)]  # a stop's, not an area's own
    if parking:
        notice(
            f"{parking[0]}: parks vehicles, but SUMO's mesoscopic model (--meso, or a sumocfg's "
            "mesosim) tells twin no vehicle's lane or parking, so parked vehicles count as "
            "standing traffic (run it microscopic to leave them out)"
        )


def _given(config, key: str, value: float) -> str | None:
    """How the dotted ``key`` was given other than by the config file, with its value: its flag
    (``--cell-m 250``), or another file's key (a sweep's: ``sweep.toml: [parameters].'...' =
    250``); None when the file (or the default) gave it."""
    flag = config.flag_of(key)
    if flag:
        return f"{flag} {value:g}"
    labels = config.set_by([key])
    return f"{labels[0]} = {value:g}" if labels else None


def _step_seconds(s: SumoSettings, config) -> float:
    """Simulated seconds per step, ``cell_m / speed``; not shorter than SUMO's own step and
    not longer than a day."""
    step_s = s.cell_m / (s.drone_speed_kmh / 3.6)
    given = [
        _given(config, f"traffic.{key}", getattr(s, key)) for key in ("drone_speed_kmh", "cell_m")
    ]
    where = ", ".join(g for g in given if g) or f"{config.path}: [traffic]"
    if step_s > MAX_STEP_S:
        raise UserError(
            f"{where}: a step ({s.cell_m:g} m at {s.drone_speed_kmh:g} km/h) lasts {step_s:.3g} "
            f"s, longer than a day ({MAX_STEP_S:g} s) of simulation per drone move; give a "
            "higher drone speed or smaller cells"
        )
    if step_s < SUMO_STEP_S:
        raise UserError(
            f"{where}: a step ({s.cell_m:g} m at {s.drone_speed_kmh:g} km/h) lasts {step_s:.2g} "
            f"s, shorter than SUMO's {SUMO_STEP_S:g} s step; give a lower drone speed or larger "
            "cells"
        )
    from twin.traffic.tape import distinct_reads

    reads = distinct_reads(step_s, s.reads_per_step)
    if reads < s.reads_per_step:  # the same instant read twice would count it twice
        key = ", ".join(config.set_by(["traffic.reads_per_step"])) or (
            f"{config.path}: [traffic].reads_per_step"
            if "reads_per_step" in config.traffic.model_fields_set
            else "[traffic].reads_per_step (the default)"
        )
        notice(
            f"{key} = {s.reads_per_step}: a step of {step_s:.3g} s holds {reads} distinct "
            f"instants of SUMO's {SUMO_STEP_S:g} s steps to read; it is read {reads} time"
            f"{'s' * (reads != 1)} (give fewer reads, or a longer step: larger cells or a "
            "slower drone)"
        )
        s.reads_per_step = reads
    return step_s


#: The keys whose values place a run's last step: its begin, its steps and their length.
WINDOW_KEYS = ("traffic.begin", "traffic.horizon", "traffic.end", "traffic.cell_m",
               "traffic.drone_speed_kmh")  # fmt: skip


def _check_horizon_within_end(
    config, s: SumoSettings, begin: float, step_s: float, end: float, horizon_given: bool
):
    """The config's ``[traffic].end`` bounds the run. Without a horizon, the run takes the
    steps that fit before it (a network without a window of its own took the default horizon,
    past it); none fitting is refused. A given horizon past it: refused in one line when both
    come from the config file (or both from overrides); when an override (a flag, a sweep's
    key) set one side of :data:`WINDOW_KEYS`, the override wins, said in a notice: an
    overridden end bounds the file's horizon, an overridden begin, horizon or step runs past
    the file's end."""
    fits = int((end - begin) / step_s + 1e-9)
    end_by = config.set_by(["traffic.end"])
    others = config.set_by([k for k in WINDOW_KEYS if k != "traffic.end"])
    end_text = f"[traffic].end = {s.end!r}"
    given_end = f"{', '.join(end_by)} ({end_text})" if end_by else f"{config.path}: {end_text}"
    if not horizon_given and fits >= 1:
        s.horizon = fits
        return
    if not horizon_given:
        by = f" (as changed by {', '.join(others)})" if others else ""
        raise UserError(
            f"{given_end} is less than one step ({step_s:g} s) after the begin "
            f"{clock_label(begin)}{by}; give an end at least one step later"
        )
    stop = begin + s.horizon * step_s
    if stop <= end + 1e-6:
        return
    span = f"{s.horizon} steps of {step_s:g} s from {clock_label(begin)} end at {clock_label(stop)}"
    if end_by and not others and fits >= 1:  # the override's end bounds the file's horizon
        notice(f"{given_end}: the run takes the {fits} steps before it ({span} otherwise)")
        s.horizon = fits
        return
    if others and not end_by:  # the override's window runs past the file's end
        notice(f"{', '.join(others)}: {span}, past {given_end}; twin runs the given window")
        return
    fix = f"give a horizon of at most {fits}" if fits >= 1 else "give a later end"
    if not others and not end_by:  # both of the file
        where, given_end = f"{config.path}: [traffic].horizon = {s.horizon}", end_text
    else:  # both of overrides
        where = ", ".join(others)
    raise UserError(f"{where}: {span}, past {given_end}; {fix}, or leave out one of them")


def _time_window(
    s: SumoSettings,
    files: _ScenarioFiles,
    step_s: float,
    begin: float,
    warmup: float,
    begin_given: bool,
    horizon_given: bool,
    begin_where: str,
) -> tuple[float, float, list[float] | None]:
    """``T^0`` (s since midnight), the warm-up (s) and the scenario's own window if it has one;
    sets ``s.horizon`` to what fits the window unless it was given."""  # fmt: skip
    window = None
    if files.own_window:
        w0 = files.window[0] if files.window[0] is not None else files.span[0]
        w1 = files.window[1] if files.window[1] is not None else files.span[1]
        demand_end = files.window[1] is None  # the window ends with the demand
        if demand_end and w1 < w0 and files.state_time is None and not begin_given:
            raise UserError(
                f"{files.sumocfg or files.name}: every departure of its demand falls before "
                f"its <begin> {clock_label(w0)} (the last at {clock_label(w1)}), and SUMO drops "
                "them: every step would be empty; give an earlier <begin> (or a --begin)"
            )  # (SUMO drops what departs before its begin)
        if math.isinf(w1):  # a flow without end: SUMO alone would run on and on
            w1 = max(
                OPEN_DEMAND_END, files.last_closed or 0.0, (begin if begin_given else w0) + 3600.0
            )
        open_flow = files.span is not None and math.isinf(files.span[1])
        if open_flow and files.window[1] is None and not horizon_given:
            notice(
                f"{files.name}: a flow has no end or number, so SUMO would run it for ever; "
                f"twin's window ends at {clock_label(w1)} (give the flow an end or a number, or "
                "a --horizon)"
            )
        if files.state_time is not None:  # a state saved past the last departure: one step
            w1 = max(w1, w0 + step_s)
        window = [w0, w1]
        if not begin_given:
            if w1 - w0 < warmup + step_s:  # too short for the warm-up: half of it warms up
                short = max(0.0, float(math.floor((w1 - w0) / 2)))
                notice(
                    f"{files.name}: the scenario's window {clock_label(w0)} - {clock_label(w1)} "
                    f"is shorter than the {warmup / 60:g} min warm-up plus a step; warm-up cut "
                    f"to {short / 60:.1f} min"
                )
                warmup = short
            # T^0 on a whole second (a window's begin may be fractional): the tape's clock
            # labels, SUMO's begin and the read instants all fall on whole seconds
            begin = float(math.ceil(w0 + warmup - 1e-9))
        if not horizon_given:
            s.horizon = max(1, int((w1 - begin) / step_s + 1e-9))
    if files.state_time is not None and begin < files.state_time - 1e-9:
        raise UserError(
            f"{begin_where} = {clock_label(begin)}: {files.name} loads a state saved at "
            f"{clock_label(files.state_time)}, where SUMO starts; give a begin of at least "
            f"{clock_label(files.state_time)}"
        )
    if files.state_time is not None and begin - warmup < files.state_time - 1e-9:
        notice(  # as at midnight: the warm-up runs from the state on
            f"{begin_where} = {clock_label(begin)}: {files.name} loads a state saved at "
            f"{clock_label(files.state_time)}, where SUMO starts; warm-up cut to "
            f"{(begin - files.state_time) / 60:.1f} min"
        )
        warmup = begin - files.state_time
    if begin < warmup:  # as for a window too short for it: SUMO starts at 00:00
        notice(
            f"{begin_where} = {clock_label(begin)}: the {warmup / 60:g} min warm-up "
            f"([traffic].warmup_min) would start SUMO before 00:00; warm-up cut to "
            f"{begin / 60:.1f} min"
        )
        warmup = begin
    return begin, warmup, window


def _grid_and_notices(
    s: SumoSettings,
    config,
    inputs: SumoInputs,
    files: _ScenarioFiles,
    lanes,
    begin: float,
    step_s: float,
    window_given: bool,
    begin_given: bool = True,
    own_config: bool = False,
):
    """The grid over the network's lanes (the config's ``[grid]`` shape and obstacles for the
    configured network, or for any network with the user's ``own_config``), and the notices
    of a grid too small for the drones or a run that outlasts the demand."""  # fmt: skip
    from twin.sumo.cells import grid_over

    # The grid: derived from the bounding box, or the config's [grid] nx, ny if it gives them
    # (a shipped config's for its own network only: a swapped-in network gets its own grid;
    # the user's own config's for any, like its begin and horizon).
    shape = None
    cell_flag = config.flag_of("traffic.cell_m")
    swapped = bool(inputs.net or inputs.sumocfg or inputs.osm)
    if not cell_flag and (own_config or not swapped):
        shape = config.explicit_shape()  # set in the file or by an override
    where = _given(config, "traffic.cell_m", s.cell_m) or f"{config.path}: [grid]"
    if shape is not None:  # the grid's shape: the file's [grid] nx, ny, or another file's keys
        grid = ", ".join(config.set_by(["grid.nx", "grid.ny"])) or f"{config.path}: [grid] nx, ny"
        cells = _given(config, "traffic.cell_m", s.cell_m)
        where = f"{cells} over {grid}" if cells else grid
    geometry = grid_over(lanes, s.cell_m, shape, where=where)
    obstacles = geometry.obstacles(s.min_lane_km)
    for i, j in getattr(config.grid, "obstacles", []) or []:
        if not (0 <= i < geometry.nx and 0 <= j < geometry.ny):
            raise UserError(
                f"{config.path}: [grid].obstacles has [{i}, {j}], off the {geometry.nx} x "
                f"{geometry.ny} grid over the network ({s.cell_m:g} m cells); give cells on it"
            )
        obstacles[i, j] = True
    if obstacles.all():
        most = float(geometry.lane_km.max(initial=0.0))
        shape = f"{geometry.nx} x {geometry.ny} grid"
        if most <= 0.0:
            raise UserError(f"{files.net_file}: no cell of the {shape} has a lane")
        if most < s.min_lane_km:
            raise UserError(
                f"{config.path}: [traffic].min_lane_km = {s.min_lane_km:g} leaves no cell of the "
                f"{shape} over {files.name} (the most lane in a cell is {most:.3g} km); give a "
                f"min_lane_km below {most:.3g}"
            )
        raise UserError(
            f"{config.path}: [grid].obstacles leave no cell of the {shape} over {files.name} "
            "free; list fewer obstacles"
        )
    n_free, n_drones = int((~obstacles).sum()), config.swarm.n_drones
    if n_drones > n_free:  # the fix names a cell size that fits them, or none does
        from twin.config import check_swarm_fits

        fits = suggest_cell_m(lanes, s.cell_m, n_drones, s.min_lane_km)
        fits = fits or suggest_cell_m(lanes, s.cell_m, n_drones, s.min_lane_km, per_drone=1)
        check_swarm_fits(config, Grid(obstacles), fits or ())
    notices = []
    dropped = config.explicit_shape() if cell_flag and own_config else None  # a shipped one's
    if dropped and dropped != (geometry.nx, geometry.ny):  # is twin's to refit, unsaid
        notices.append(
            f"{config.path}: [grid] nx, ny = {dropped[0]} x {dropped[1]} is for its own "
            f"cell_m; {cell_flag} {s.cell_m:g} fits the grid to the map ({geometry.nx} x "
            f"{geometry.ny}); give [grid] nx, ny for {s.cell_m:g} m cells in the config to "
            "keep a shape of your own"
        )
    if n_drones <= n_free < MIN_FREE_CELLS_PER_DRONE * n_drones:  # more drones: refused later
        better = suggest_cell_m(lanes, s.cell_m, n_drones, s.min_lane_km)
        fewer = max(1, n_free // MIN_FREE_CELLS_PER_DRONE)
        fix = (  # in words of both a command's flags and a sweep's or transfer's keys
            f"try cells of {better[0]:g} m ({better[1]} free cells: --cell-m {better[0]:g}, or "
            f"traffic.cell_m = {better[0]:g})"
            if better
            else f"use fewer drones (--drones {fewer}, or swarm.n_drones = {fewer})"
            if fewer < n_drones
            else "no smaller cell size down to 25 m gives more room"
        )
        notices.append(
            f"{files.name}: {geometry.nx} x {geometry.ny} cells of {s.cell_m:g} m, {n_free} free "
            f"for {n_drones} drones (fewer than {MIN_FREE_CELLS_PER_DRONE} per drone: every "
            f"swarm covers nearly all, the comparison says little); {fix}"
        )
    end = begin + s.horizon * step_s
    own_window = not window_given and files.span is not None and files.state_time is None
    if own_window and end <= files.span[0]:  # the sumocfg's <time> (a given one: see below)
        raise UserError(
            f"{files.name}: its window ({clock_label(begin)} - {clock_label(end)}) ends before "
            f"the first departure ({clock_label(files.span[0])}): every step would be empty; "
            "give a --begin and --horizon within the demand, or fix its <time>"
        )
    if window_given and files.window[1] is not None and begin >= files.window[1]:
        notices.append(  # SUMO alone would stop at its <end>; twin's window replaces it
            f"{files.name}: the run ({clock_label(begin)} - {clock_label(end)}) begins at or "
            f"past the scenario's end ({clock_label(files.window[1])}), where SUMO alone would "
            "stop; twin runs its own window (give a --begin before it to stay within it)"
        )
    span = files.span or files.built_span
    if span is not None and window_given:
        clear = clearing_time(geometry)
        outside = begin >= span[1] + clear or end <= span[0]
        # in the sumocfg's own window (given or derived), its vehicles may still circulate
        in_window = files.window[1] is not None and span[0] <= begin < files.window[1]
        if outside and (not begin_given or in_window):
            notices.append(  # (rerouters keep a loop scenario's vehicles on the road)
                f"{files.name}: the run ({clock_label(begin)} - {clock_label(end)}) begins past "
                f"the last departure ({clock_label(span[1])}) plus {clear / 60:.0f} min to "
                "clear the network: its steps hold only vehicles that are still driving"
            )
        elif outside:
            raise UserError(
                f"{files.name}: the run ({clock_label(begin)} - {clock_label(end)}) lies outside "
                f"the demand (departures {clock_label(span[0])} - "
                f"{clock_label(span[1])}, plus {clear / 60:.0f} min to clear the "
                "network): every step would be empty; give a --begin (and --horizon) within it"
            )
        empty = min(s.horizon, int(max(-1.0, end - span[1] - clear) / step_s))
        if empty >= 1 and not outside:
            notices.append(
                f"{files.name}: the run ends at {clock_label(end)}, past the last departure "
                f"({clock_label(span[1])}) plus {clear / 60:.0f} min to clear the network; "
                f"the last {empty} step{'s' * (empty != 1)} may have no vehicle"
            )
    for text in notices:
        notice(text)
    return geometry, obstacles, notices


def _generated_demand(
    s: SumoSettings,
    files: _ScenarioFiles,
    geometry,
    begin: float,
    warmup: float,
    step_s: float,
    seed: int,
    where: str = "[traffic].demand_scale",
) -> Path:
    """Rush-hour trips for a network brought without demand (:data:`twin.sumo.demand.
    GENERIC_RUSH_HOUR` scaled to its lane-km), built once per network, window and seed in the
    user cache; more than :data:`twin.sumo.demand.MAX_GENERATED_TRIPS` are refused before
    randomTrips runs, naming ``where`` (the key or flag of ``demand_scale``)."""  # fmt: skip
    from twin import resources
    from twin.sumo.demand import (
        FRINGE_MARK,
        GENERIC_RUSH_HOUR,
        MAX_GENERATED_TRIPS,
        expected_trips,
        random_rush_hour_trips,
    )
    from twin.sumo.network import sumo_version

    profile = GENERIC_RUSH_HOUR
    scale = s.demand_scale * float(geometry.lane_km.sum()) / profile["lane_km"]
    span = {
        **{k: v for k, v in profile.items() if k != "lane_km"},
        "begin_s": begin - warmup,
        "end_s": begin + s.horizon * step_s,
        "peak_s": begin - warmup + profile["peak_after_s"],
    }
    net_file = Path(files.net_file)
    trips = expected_trips(span, scale)
    if trips > MAX_GENERATED_TRIPS:
        most = s.demand_scale * MAX_GENERATED_TRIPS / trips
        most = math.floor(most / 10 ** (e := math.floor(math.log10(most)) - 2)) * 10**e
        raise UserError(
            f"{where} = {s.demand_scale:g} asks randomTrips for about {trips:,.0f} trips on "
            f"{files.name} ({clock_label(span['begin_s'])} - {clock_label(span['end_s'])}), "
            f"more than the {MAX_GENERATED_TRIPS:,} twin generates (its memory grows with "
            f"them); give a demand_scale of at most {most:g}"
        )
    key = f"{net_file.stem}-{_digest(net_file, span, scale, seed, sumo_version())}"
    out = resources.build_once(
        resources.cache_dir() / "imported" / key,
        lambda d: random_rush_hour_trips(
            net_file, d / "rush_hour.trips.xml", span, seed=seed, scale=scale
        ),
        verify=lambda d: resources.check_xml_files(d, {"rush_hour.trips.xml": "routes"}),
    )
    if (out / FRINGE_MARK).exists():
        notice(
            f"{files.name}: every edge enters or leaves the network, so the generated trips "
            "start and end on its fringe (randomTrips' --allow-fringe)"
        )
    return out / "rush_hour.trips.xml"


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
    The settings ``horizon`` ... ``drone_speed_kmh`` are ``[traffic]`` keys, set as by their
    flags (:data:`SETTING_FLAGS`, :func:`twin.config.with_overrides`).
    In steps: the settings with the files swapped in, the files, the step, the time window, the
    grid, the generated demand (if none is given), the scenario.
    """
    from twin.sumo.cells import read_lanes
    from twin.sumo.network import check_net_file
    from twin.sumo.source import SumoScenario, SumoTraffic

    settings = {"horizon": horizon, "begin": begin, "mesoscopic": mesoscopic, "cell_m": cell_m,
                "drone_speed_kmh": drone_speed_kmh}  # fmt: skip
    given = {f"traffic.{k}": v for k, v in settings.items() if v is not None}
    if given:
        flags = {f"traffic.{k}": flag for k, flag in SETTING_FLAGS.items()}
        config = with_overrides(config, given, {k: flags[k] for k in given})
    # a begin, end, horizon or grid the user's own config sets holds for files swapped in by
    # flags too; a shipped config's (the built-in network's rush hour) only for its own network
    from twin.resources import shipped

    own = not Path(config.path).resolve().is_relative_to(shipped("configs").resolve())
    inputs = SumoInputs(net=net, routes=routes, sumocfg=sumocfg, osm=osm, additional=additional)
    s = _with_inputs(sumo_settings(config), inputs, keep_end=own)
    fields = config.traffic.model_fields_set
    swapped = bool(net or sumocfg or osm or routes)
    seed = s.seed if seed is None else seed
    begin_flag = config.flag_of("traffic.begin")
    begin_where = begin_flag or f"{config.path}: [traffic].begin"
    begin_given = begin_flag is not None or ((not swapped or own) and "begin" in fields)
    horizon_given = config.flag_of("traffic.horizon") is not None or (
        (not swapped or own) and "horizon" in fields
    )
    t0 = parse_clock(s.begin, begin_where)

    check_cache_without_comma()
    files = _scenario_files(s)
    if s.end is not None and (not swapped or own):  # like its begin and horizon
        files.window[1] = parse_clock(s.end, f"{config.path}: [traffic].end")
        if begin_given and files.window[1] <= t0:
            raise UserError(
                f"{config.path}: [traffic].end = {s.end!r} is not after the begin "
                f"({clock_label(t0)}); give an end after the begin, or leave it out"
            )
    with _named_in(files.sumocfg, files.listed):
        check_net_file(files.net_file)
        lanes = read_lanes(files.net_file)
    step_s = _step_seconds(s, config)
    warmup = float(math.ceil(s.warmup_min * 60.0 - 1e-9))  # SUMO starts on a whole second
    t0, warmup, window = _time_window(
        s, files, step_s, t0, warmup, begin_given, horizon_given, begin_where
    )
    end_given = s.end is not None and (not swapped or own)
    if end_given:  # the config's end bounds its horizon (one that fits, when not given)
        _check_horizon_within_end(config, s, t0, step_s, files.window[1], horizon_given)
    window_given = begin_given or horizon_given or s.end is not None
    if begin_given and files.at_begin:  # SUMO begins at twin's warm-up start: so do they
        files.span = departure_span(
            [*files.route_files, *files.additional_files],
            start=t0 - warmup,
            in_order=files.route_files if files.in_order else (),
        )  # (what SUMO ignores in an unsorted route file left out again)
    geometry, obstacles, notices = _grid_and_notices(
        s, config, inputs, files, lanes, t0, step_s, window_given, begin_given, own_config=own
    )
    route_files = list(files.route_files)
    where = ", ".join(config.set_by(["traffic.demand_scale"])) or (
        f"{config.path}: [traffic].demand_scale"
    )
    if files.span is None and not s.network:  # no demand given: twin generates it
        route_files.append(_generated_demand(s, files, geometry, t0, warmup, step_s, seed, where))
    elif s.demand_scale != 1.0:
        own = (
            "the built-in network's demand is its own (networks/README.md)"
            if s.network
            else f"{files.name} brings its own, which runs as it is (scale it with SUMO's "
            "<scale> in a sumocfg)"
        )
        notice(
            f"{where} = {s.demand_scale:g} scales only the demand twin generates for a network "
            f"without routes; {own}"
        )

    options: tuple[str, ...] = ()
    if files.additional_files:
        for path in files.additional_files:  # a list SUMO splits at commas
            check_no_comma(path)
        options = ("--additional-files", ",".join(str(a) for a in files.additional_files))
    scenario = SumoScenario(
        net_file=Path(files.net_file),
        route_files=[Path(r) for r in route_files],
        begin_s=t0,
        warmup_s=warmup,
        step_s=step_s,
        horizon=s.horizon,
        seed=seed,
        mesoscopic=s.mesoscopic,
        mfd_fit=s.mfd.fit,
        detection_p=s.mfd.detection_p,
        name=files.name,
        sumocfg=files.sumocfg,
        mfd_prior=(s.mfd.a, s.mfd.k_c),
        reads_per_step=s.reads_per_step,
        incidents=list(s.incidents),
        not_for_cars=lanes.not_for_cars,
        sumo_options=options,
        extra={
            "additional_files": [str(a) for a in files.additional_files],
            "sumocfg_files": [str(f) for f in files.listed],
            "window": window,
            "departures": (  # a flow without end: None for the last
                [x if math.isfinite(x) else None for x in files.span] if files.span else None
            ),
            "twin_demand": files.span is None,  # built-in or generated: route errors skipped
            "n_drones": config.swarm.n_drones,
            "n_free": int((~obstacles).sum()),
            "notices": notices,
        },
    )
    scenario.detectors = detector_plan(s.detectors, scenario, geometry, obstacles, config.path)
    if scenario.incidents:  # checked before SUMO starts, against the final window and grid
        from twin.sumo.incidents import check_incidents

        checked = check_incidents(
            scenario.incidents, scenario, geometry, str(config.path), obstacles
        )
        for text in checked:
            notices.append(text)
            notice(text)
    return SumoTraffic(scenario, geometry, Grid(obstacles))


def detector_plan(settings, scenario, geometry, obstacles, where):
    """The detectors a run reads (``[traffic.detectors]``): the scenario's own and the loop
    stations twin places, their cells checked (one-line errors naming the config's field)."""
    from twin.sumo.detectors import (
        DetectorPlan,
        check_cells,
        main_edges,
        place_loops,
        station_cells,
    )

    if scenario.mesoscopic and (settings.scenario or settings.cells or settings.virtual_loops):
        raise UserError(
            f"{where}: [traffic.detectors] with SUMO's mesoscopic model (--meso, or the "
            "sumocfg's mesosim), which has no induction loops or lane-area detectors to read; "
            "run it microscopic, or without [traffic.detectors]"
        )
    if not (settings.cells or settings.virtual_loops):
        return DetectorPlan(scenario=settings.scenario)
    free = ~np.asarray(obstacles, dtype=bool)
    edges = main_edges(scenario.net_file, geometry)
    if settings.cells:
        cells = check_cells(settings.cells, geometry, free, f"{where}: ")
        for i, j in cells:
            if (i, j) not in edges:
                raise UserError(
                    f"{where}: [traffic.detectors].cells: cell [{i}, {j}] holds only junction "
                    "lanes, no edge for a loop; pick another cell"
                )
    else:
        with_edge = free & np.zeros(free.shape, dtype=bool)
        for i, j in edges:
            with_edge[i, j] = free[i, j]
        cells = station_cells(geometry.lane_km, with_edge, settings.virtual_loops)
        if len(cells) < settings.virtual_loops:
            raise UserError(
                f"{where}: [traffic.detectors].virtual_loops = {settings.virtual_loops} exceeds "
                f"the {len(cells)} cells with a road; give at most {len(cells)}"
            )
    return DetectorPlan(scenario=settings.scenario, loops=place_loops(edges, geometry, cells))


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
