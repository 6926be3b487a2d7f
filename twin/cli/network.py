"""``twin network``: build the built-in networks (plain XML -> netconvert -> demand), import OSM."""

from __future__ import annotations

import argparse
import time

from twin.cli import path_arg


def add_parser(subparsers) -> None:
    p = subparsers.add_parser(
        "network",
        help="build a built-in SUMO network and its demand, or import an OSM extract",
        description="Build a built-in network (a shipped networks/<name>/spec.toml) with "
        "netconvert (from the eclipse-sumo wheel), with its rush-hour demand, into the user "
        "cache (TWIN_CACHE_DIR to move it); or convert an OpenStreetMap extract with options "
        "suited to city networks.",
    )
    sub = p.add_subparsers(title="actions", metavar="ACTION")
    b = sub.add_parser("build", help="build a built-in network (e.g. shenzhen_like)")
    b.add_argument("name", nargs="?", default="shenzhen_like", help="network name")
    b.add_argument("--force", action="store_true", help="rebuild even if up to date")
    b.set_defaults(func=main_build)
    o = sub.add_parser("import-osm", help="convert an OSM extract into a SUMO network")
    o.add_argument("osm", type=path_arg, help="the .osm file")
    o.add_argument("--out", type=path_arg, default=None, help="folder (default: the user cache)")
    o.set_defaults(func=main_osm)
    p.set_defaults(func=lambda args: (p.print_help(), 2)[1])


def main_build(args: argparse.Namespace) -> int:
    from twin.sumo.network import build_named_network

    t0 = time.perf_counter()
    built = build_named_network(args.name, force=args.force)
    n_trips = sum(1 for line in built.trips_file.open() if "<trip " in line)
    print(f"network: {built.net_file}")
    print(f"demand:  {built.trips_file} ({n_trips} trips)")
    print(f"built in {time.perf_counter() - t0:.1f} s")
    return 0


def main_osm(args: argparse.Namespace) -> int:
    from twin.sumo.network import import_osm
    from twin.sumo.readers import missing

    if not args.osm.exists():
        raise missing(args.osm, "OSM file")
    print(f"network: {import_osm(args.osm, args.out)}")
    return 0
