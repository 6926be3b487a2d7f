"""Rush-hour demand: time-varying trips toward business districts, two vehicle classes.

For a built-in network the spec's ``[demand]`` and ``[[districts]]`` give a departure rate
``lambda(t) = base + peak * exp(-(t - t_peak)^2 / (2 w^2))`` and where trips start and end:
residential zones, the network's boundary (external traffic) and random edges (ride-hailing
pick-ups, background traffic), toward a central, a western and an eastern business district.
For a network not written for twin, :func:`random_rush_hour_trips` uses SUMO's randomTrips.py
with the same time profile and validates the trips with duarouter (``--validate``).

Trips carry only origin and destination edges; SUMO routes them at insertion and reroutes a
share of them while driving. Same seed, same trips.
"""

from __future__ import annotations

import re
import xml.etree.ElementTree as ET
from pathlib import Path
from typing import Any

import numpy as np

from twin.errors import UserError
from twin.sumo.tools import run_sumo_program, tool

#: Vehicle classes of the rush-hour demand (SUMO vTypes).
VTYPES = {
    "private": {"vClass": "passenger", "color": "0.2,0.4,1", "speedFactor": "normc(1,0.1,0.2,2)"},
    "ridehail": {"vClass": "passenger", "color": "1,0.8,0", "speedFactor": "normc(1.05,0.1,0.2,2)"},
}


#: The rush-hour profile of demand generated for a network brought without demand, for a
#: network of ``lane_km`` lane-km (scaled to the network's own): off-peak and peak trips per
#: hour, the peak ``peak_after_s`` after the demand begins (at the warm-up's start), with a
#: Gaussian spread of ``peak_width_s``. The numbers are those of the built-in network's demand
#: (``networks/shenzhen_like/spec.toml``, 1350 lane-km): a morning peak 1 h 45 min into a 3.5 h
#: window.
GENERIC_RUSH_HOUR = {
    "lane_km": 1350.0,
    "base_rate_per_h": 1200.0,
    "peak_rate_per_h": 16000.0,
    "peak_after_s": 6300.0,
    "peak_width_s": 2400.0,
}


def departure_rate(t: np.ndarray, demand: dict[str, Any]) -> np.ndarray:
    """Trips per second at time ``t`` (s since midnight): base plus a Gaussian peak."""
    base = float(demand["base_rate_per_h"]) / 3600.0
    peak = float(demand["peak_rate_per_h"]) / 3600.0
    t0, w = float(demand["peak_s"]), float(demand["peak_width_s"])
    return base + peak * np.exp(-0.5 * ((t - t0) / w) ** 2)


def departure_times(demand: dict[str, Any], rng: np.random.Generator) -> np.ndarray:
    """Sorted departure times of an inhomogeneous Poisson process with :func:`departure_rate`."""
    begin, end = float(demand["begin_s"]), float(demand["end_s"])
    edges = np.arange(begin, end, 60.0)
    counts = rng.poisson(departure_rate(edges + 30.0, demand) * 60.0)
    times = np.repeat(edges, counts) + rng.uniform(0.0, 60.0, counts.sum())
    return np.sort(np.round(times, 1))


def _passenger_edges(net_file: Path) -> tuple[list[str], np.ndarray, np.ndarray, np.ndarray]:
    """Ids, mid points ``(E, 2)``, lengths and 'enters from the boundary' flags of the
    passenger-car edges of a network."""
    import sumolib

    net = sumolib.net.readNet(str(net_file))
    (xmin, ymin), (xmax, ymax) = net.getBBoxXY()
    ids, mids, lengths, entering = [], [], [], []
    for edge in net.getEdges(withInternal=False):
        if not edge.allows("passenger"):
            continue
        (x0, y0), (x1, y1) = edge.getFromNode().getCoord(), edge.getToNode().getCoord()
        on_border = min(x0 - xmin, xmax - x0, y0 - ymin, ymax - y0) < 1.0
        inward = min(x1 - xmin, xmax - x1, y1 - ymin, ymax - y1) >= 1.0
        ids.append(edge.getID())
        mids.append(((x0 + x1) / 2, (y0 + y1) / 2))
        lengths.append(edge.getLength())
        entering.append(on_border and inward)
    return ids, np.array(mids), np.array(lengths), np.array(entering)


def write_spec_demand(net_file: Path, spec: dict[str, Any], out: Path, seed: int) -> int:
    """Write the rush-hour trips of a built-in network's spec; returns the number of trips."""
    rng = np.random.default_rng(seed)
    demand = spec["demand"]
    ids, mids, lengths, entering = _passenger_edges(net_file)
    n_edges = len(ids)

    def zone_weights(district: dict[str, Any]) -> np.ndarray:
        d = np.linalg.norm(mids - np.asarray(district["center"], dtype=float), axis=1)
        w = np.where(d <= float(district["radius_m"]), lengths, 0.0)
        return w / w.sum() if w.sum() > 0 else w

    business = [d for d in spec["districts"] if d["kind"] == "business"]
    homes = [d for d in spec["districts"] if d["kind"] == "residential"]
    biz_w = np.array([d["weight"] for d in business], dtype=float)
    home_w = np.array([d["weight"] for d in homes], dtype=float)
    biz_edges = [zone_weights(d) for d in business]
    home_edges = [zone_weights(d) for d in homes]
    uniform = lengths / lengths.sum()
    external = entering / entering.sum() if entering.any() else uniform

    times = departure_times(demand, rng)
    n = len(times)
    is_ridehail = rng.random(n) < float(demand["ridehail_share"])
    kind = rng.random(n)
    ext_share = float(demand["external_share"])
    bg_share = float(demand["background_share"])
    root = ET.Element("routes")
    for name, attrs in VTYPES.items():
        ET.SubElement(root, "vType", id=name, **attrs)
    for v in range(n):
        if kind[v] < bg_share:
            origin_w, dest_w = uniform, uniform
        else:
            dest_w = biz_edges[rng.choice(len(business), p=biz_w / biz_w.sum())]
            if is_ridehail[v]:
                origin_w = uniform  # ride-hailing picks up anywhere
            elif kind[v] < bg_share + ext_share:
                origin_w = external
            else:
                origin_w = home_edges[rng.choice(len(homes), p=home_w / home_w.sum())]
        o = rng.choice(n_edges, p=origin_w)
        d = rng.choice(n_edges, p=dest_w)
        if o == d:
            d = (d + 1) % n_edges
        ET.SubElement(
            root,
            "trip",
            id=f"{'rh' if is_ridehail[v] else 'pv'}{v}",
            type="ridehail" if is_ridehail[v] else "private",
            depart=f"{times[v]:.1f}",
            attrib={"from": ids[o], "to": ids[d]},
            departLane="best",
            departSpeed="max",
            departPos="random",
        )
    ET.indent(root)
    ET.ElementTree(root).write(out, encoding="unicode", xml_declaration=True)
    return n


#: Beside generated trips: they start and end on the network's fringe (randomTrips'
#: ``--allow-fringe``), said in a notice at every run on them.
FRINGE_MARK = "allow-fringe.txt"
#: randomTrips' words for a network it cannot make trips on (as against running out of time
#: or memory, where a smaller demand_scale helps).
NO_TRIPS = re.compile(r"no valid edges|couldn't be generated|could not be generated", re.I)
#: The most trips twin asks randomTrips for (the built-in network's rush hour is about a tenth
#: of this): randomTrips and duarouter hold every trip in memory.
MAX_GENERATED_TRIPS = 1_000_000


def insertion_rates(demand: dict[str, Any], scale: float) -> np.ndarray:
    """Trips per hour in each 15-minute piece of the window (randomTrips' insertion rates):
    :func:`departure_rate` at the piece's middle times ``scale``, at least one."""
    begin, end = float(demand["begin_s"]), float(demand["end_s"])
    pieces = np.arange(begin, end, 900.0) + 450.0
    return np.maximum(departure_rate(pieces, demand) * 3600.0 * scale, 1.0)


def expected_trips(demand: dict[str, Any], scale: float) -> float:
    """About how many trips :func:`random_rush_hour_trips` generates (randomTrips divides the
    window into equal parts, one per rate)."""
    rates = insertion_rates(demand, scale)
    begin, end = float(demand["begin_s"]), float(demand["end_s"])
    return float(rates.sum() * (end - begin) / len(rates) / 3600.0) if len(rates) else 0.0


def random_rush_hour_trips(
    net_file: Path, out: Path, demand: dict[str, Any], seed: int, scale: float = 1.0
) -> Path:
    """Rush-hour trips for any network with randomTrips.py (+ duarouter via ``--validate``).

    The departure rate follows :func:`departure_rate` in 15-minute pieces (randomTrips'
    list of insertion rates); ``scale`` multiplies it, e.g. per lane-km of a small network.
    """
    begin, end = float(demand["begin_s"]), float(demand["end_s"])
    rates = insertion_rates(demand, scale)
    args = [tool("randomTrips.py"), "-n", str(net_file), "-o", str(out),
         # --validate routes the trips with duarouter; keep its route file beside `out`
         # instead of routes.rou.xml in the working directory
         "-r", str(out.with_name(out.stem.removesuffix(".trips") + ".validated.rou.xml")),
         "-b", f"{begin:.0f}", "-e", f"{end:.0f}", "--seed", str(seed),
         "--insertion-rate", *[f"{r:.1f}" for r in rates],
         "--fringe-factor", "5", "--min-distance", "500", "--validate",
         "--vehicle-class", "passenger", "--trip-attributes",
         'departLane="best" departSpeed="max" departPos="random"']  # fmt: skip
    what = f"randomTrips.py on {net_file}"
    fix = "; twin cannot generate demand on it: give your own (--routes, or a sumocfg's routes)"
    try:
        try:
            run_sumo_program(args, what=what)
        except UserError as exc:
            if "--allow-fringe" not in str(exc):
                raise
            # every edge enters or leaves the network (a single road): trips may start and end
            # there, or there is no demand at all
            run_sumo_program([*args, "--allow-fringe"], what=what)
            out.with_name(FRINGE_MARK).write_text("randomTrips.py ran with --allow-fringe\n")
    except UserError as exc:  # randomTrips' own words name no fix twin's user can take
        if not NO_TRIPS.search(str(exc)):
            raise
        raise UserError(f"{exc}{fix}") from None
    if not any(e.tag == "trip" for _, e in ET.iterparse(out)):  # --validate dropped them all
        raise UserError(
            f"{what}: none of its trips (500 m or longer, between roads cars may use) can be "
            f"driven, so the network's roads are not connected for such trips{fix}"
        )
    return out
