"""Road networks: the built-in ``shenzhen_like`` layout, OSM import, and checks on given files.

A built-in network is a spec file ``networks/<name>/spec.toml``, shipped with the package.
Building it writes plain XML nodes and edges, runs netconvert from the eclipse-sumo wheel and
writes the rush-hour demand, all in the user cache under
``networks/<name>/<hash of spec, generator and SUMO version>/`` (:mod:`twin.resources`); a build
is reused while that hash is unchanged.
"""

from __future__ import annotations

import contextlib
import hashlib
import json
import re
import tomllib
import xml.etree.ElementTree as ET
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from twin import resources
from twin.errors import UserError
from twin.files import not_a_file, read_record
from twin.sumo.readers import (
    check_cache_without_comma,
    check_no_comma,
    missing,
    open_xml,
    reencoded,
    root_tag,
)
from twin.sumo.tools import binary, run_sumo_program

#: Bump when the generator's output changes for the same spec (forces a rebuild).
GENERATOR_VERSION = 4

#: netconvert options for city networks imported from OpenStreetMap.
OSM_OPTIONS = [
    "--geometry.remove",
    "--roundabouts.guess",
    "--ramps.guess",
    "--junctions.join",
    "--tls.guess-signals",
    "--tls.discard-simple",
    "--tls.join",
    "--remove-edges.isolated",
    "--keep-edges.by-vclass",
    "passenger",
    "--remove-edges.by-type",
    "highway.track,highway.services,highway.unsurfaced,highway.path,highway.footway",
    "--no-turnarounds.except-deadend",
    "--output.street-names",
]

# Edge priority of each road kind (netconvert uses it for right of way).
_PRIORITY = {"expressway": 13, "boulevard": 12, "arterial": 10, "secondary": 5}


@dataclass(frozen=True)
class BuiltNetwork:
    """The files of a built network."""

    name: str
    net_file: Path
    trips_file: Path
    spec: dict[str, Any]


def network_names() -> list[str]:
    """Built-in networks: the shipped folders ``networks/<name>/`` that hold a ``spec.toml``."""
    return resources.network_names()


def load_spec(path: Path) -> dict[str, Any]:
    """Read and check a network spec (TOML)."""
    try:
        spec = tomllib.loads(path.read_text())
    except FileNotFoundError as exc:
        raise UserError(f"{path}: no such network spec") from exc
    except tomllib.TOMLDecodeError as exc:
        raise UserError(f"{path}: not valid TOML ({exc})") from exc
    except RecursionError:
        raise UserError(f"{path}: not valid TOML for twin (nested too deep)") from None
    for key in ("lattice", "secondary", "demand", "districts"):
        if key not in spec:
            raise UserError(f"{path}: missing section [{key}]")
    for road in spec.get("roads", []):
        if road.get("kind") not in _PRIORITY or road.get("axis") not in ("ew", "ns"):
            raise UserError(
                f"{path}: road {road.get('name')!r} needs kind in {sorted(_PRIORITY)} and "
                "axis 'ew' or 'ns'"
            )
    return spec


def sumo_version() -> str:
    """The installed eclipse-sumo version (a new SUMO may convert the same spec differently)."""
    from importlib import metadata

    try:
        return metadata.version("eclipse-sumo")
    except metadata.PackageNotFoundError:  # pragma: no cover - depends on the install
        return "unknown"


def _spec_hash(spec_path: Path) -> str:
    data = spec_path.read_bytes() + f"generator={GENERATOR_VERSION};sumo={sumo_version()}".encode()
    return hashlib.sha256(data).hexdigest()[:16]


def build_dir(name: str) -> Path:
    """Where the built-in network ``name`` is (or will be) built in the cache."""
    return resources.cache_dir() / "networks" / name / _spec_hash(resources.network_spec(name))


def build_named_network(name: str, force: bool = False, progress: bool = False) -> BuiltNetwork:
    """Build (or reuse) the built-in network ``name``: plain XML -> netconvert -> demand.

    Safe when several processes build it at once (:func:`twin.resources.build_once`).
    """
    from twin.sumo.demand import write_spec_demand

    check_cache_without_comma()
    spec_path = resources.network_spec(name)
    spec = load_spec(spec_path)
    digest = _spec_hash(spec_path)

    def make(out: Path) -> None:
        nod, edg = write_plain_xml(spec, out / name)
        run_sumo_program(
            [
                binary("netconvert"),
                "--node-files", str(nod),
                "--edge-files", str(edg),
                "--output-file", str(out / f"{name}.net.xml"),
                "--offset.disable-normalization", "true",
                "--remove-edges.isolated", "true",
                "--tls.default-type", "static",
                "--junctions.corner-detail", "0",
                "--no-internal-links", "true",  # a third faster in SUMO; cells are 500 m anyway
                "--no-warnings", "true",
            ],
            what=f"netconvert on {edg}",
        )  # fmt: skip
        write_spec_demand(
            out / f"{name}.net.xml", spec, out / f"{name}.trips.xml", seed=int(spec.get("seed", 0))
        )
        stamp = {"spec_hash": digest, "generator": GENERATOR_VERSION, "sumo": sumo_version()}
        (out / "build.json").write_text(json.dumps(stamp))

    def verify(out: Path) -> None:
        resources.check_xml_files(out, {f"{name}.net.xml": "net", f"{name}.trips.xml": "routes"})
        try:
            stamp = json.loads(read_record(out / "build.json"))
        except (OSError, ValueError) as exc:
            raise resources.BrokenEntry("build.json is missing or not JSON") from exc
        if not isinstance(stamp, dict) or stamp.get("spec_hash") != digest:
            raise resources.BrokenEntry("build.json does not match the spec")

    out = resources.build_once(build_dir(name), make, force=force, verify=verify)
    return BuiltNetwork(name, out / f"{name}.net.xml", out / f"{name}.trips.xml", spec)


def write_plain_xml(spec: dict[str, Any], stem: Path) -> tuple[Path, Path]:
    """Write ``<stem>.nod.xml`` and ``<stem>.edg.xml`` from a spec's lattice, roads and voids.

    Nodes sit on a lattice; a node inside a void (water, hill, park) is dropped with its edges.
    On an expressway's line only the nodes where a south-north arterial meets it remain (ramps);
    the secondary streets that cross it pass under without a junction.
    """
    from shapely.geometry import LineString, Point, Polygon

    lat = spec["lattice"]
    sp, off = float(lat["spacing_m"]), float(lat["offset_m"])
    xs = [off + sp * c for c in range(int(lat["x_lines"]))]
    ys = [off + sp * r for r in range(int(lat["y_lines"]))]
    voids = [Polygon(v["polygon"]) for v in spec.get("voids", [])]
    roads = spec.get("roads", [])
    sec = spec["secondary"]

    def road_at(axis: str, at: float, pos: float) -> dict[str, Any] | None:
        for road in roads:
            lo, hi = road.get("span_m", [float("-inf"), float("inf")])
            if road["axis"] == axis and abs(road["at_m"] - at) < 1e-6 and lo <= pos <= hi:
                return road
        return None

    def in_void(x: float, y: float) -> bool:
        return any(v.intersects(Point(x, y)) for v in voids)

    ns_arterial = {x for x in xs if any(road_at("ns", x, y) for y in ys)}
    # Which lattice nodes exist: not in a void; on an expressway line only at ramps.
    nodes: dict[tuple[int, int], tuple[float, float]] = {}
    bypassed: set[tuple[int, int]] = set()
    for c, x in enumerate(xs):
        for r, y in enumerate(ys):
            if in_void(x, y):
                continue
            road = road_at("ew", y, x)
            if road and road["kind"] == "expressway" and x not in ns_arterial:
                bypassed.add((c, r))
                continue
            nodes[(c, r)] = (x, y)

    def node_id(c: int, r: int) -> str:
        return f"n{c}_{r}"

    edges: list[dict[str, Any]] = []

    def add_line(cells: list[tuple[int, int]], axis: str) -> None:
        """Connect consecutive existing nodes along one lattice line, across bypassed nodes."""
        prev: tuple[int, int] | None = None
        for cr in cells:
            if cr in nodes:
                if prev is not None:
                    a, b = nodes[prev], nodes[cr]
                    if not any(v.intersects(LineString([a, b])) for v in voids):
                        mid = ((a[0] + b[0]) / 2, (a[1] + b[1]) / 2)
                        at, pos = (mid[1], mid[0]) if axis == "ew" else (mid[0], mid[1])
                        road = road_at(axis, at, pos)
                        edges.append({"a": prev, "b": cr, "road": road})
                prev = cr
            elif cr not in bypassed:
                prev = None

    for r in range(len(ys)):
        add_line([(c, r) for c in range(len(xs))], "ew")
    for c in range(len(xs)):
        add_line([(c, r) for r in range(len(ys))], "ns")

    degree: dict[tuple[int, int], int] = {}
    major: set[tuple[int, int]] = set()
    for e in edges:
        for end in (e["a"], e["b"]):
            degree[end] = degree.get(end, 0) + 1
            if e["road"] is not None:
                major.add(end)

    nod = ET.Element("nodes")
    for cr, (x, y) in nodes.items():
        if cr not in degree:
            continue
        kind = "traffic_light" if cr in major and degree[cr] >= 3 else "priority"
        ET.SubElement(nod, "node", id=node_id(*cr), x=f"{x:.1f}", y=f"{y:.1f}", type=kind)
    edg = ET.Element("edges")
    for e in edges:
        road = e["road"]
        kind = road["kind"] if road else "secondary"
        lanes = int(road["lanes"]) if road else int(sec["lanes"])
        speed = float(road["speed_kmh"]) if road else float(sec["speed_kmh"])
        named = {"name": road["name"]} if road else {}
        for a, b in ((e["a"], e["b"]), (e["b"], e["a"])):
            ET.SubElement(
                edg,
                "edge",
                id=f"{node_id(*a)}-{node_id(*b)}",
                attrib={"from": node_id(*a), "to": node_id(*b), **named},
                priority=str(_PRIORITY[kind]),
                numLanes=str(lanes),
                speed=f"{speed / 3.6:.3f}",
                type=kind,
            )
    nod_path, edg_path = stem.with_suffix(".nod.xml"), stem.with_suffix(".edg.xml")
    ET.indent(nod)
    ET.indent(edg)
    ET.ElementTree(nod).write(nod_path, encoding="unicode", xml_declaration=True)
    ET.ElementTree(edg).write(edg_path, encoding="unicode", xml_declaration=True)
    return nod_path, edg_path


def imported_dir(osm_file: Path) -> Path:
    """Where an OSM extract's converted network is cached: ``imported/<stem>-<hash>/``."""
    digest = hashlib.sha256(Path(osm_file).read_bytes() + sumo_version().encode()).hexdigest()
    return resources.cache_dir() / "imported" / f"{Path(osm_file).stem}-{digest[:16]}"


#: Compressions netconvert does not read, by their first bytes: (magic, name, command).
_PACKED_OSM = (
    (b"BZh", "a bzip2", "bunzip2 -k"),
    (b"\xfd7zXZ\x00", "an xz", "unxz -k"),
    (b"PK\x03\x04", "a zip", "unzip"),
    (b"\x28\xb5\x2f\xfd", "a zstd", "unzstd"),
)


#: The coordinates netconvert projects (WGS84 degrees).
LAT_RANGE, LON_RANGE = (-90.0, 90.0), (-180.0, 180.0)


def _osm_refusal(osm_file: Path, message: str) -> UserError:
    """netconvert's refusal of an OSM extract as one line naming the node and the fix: a node
    it cannot project (a latitude of 95), a node's attribute it cannot read, or none left."""
    unprojected = re.search(r"Unable to project coordinates for junction '([^']*)'", message)
    if unprojected:
        node = unprojected[1]
        lat, lon = _osm_node_position(osm_file, node)
        where = f" at lat = {lat}, lon = {lon}" if lat is not None else ""
        return UserError(
            f"{osm_file}: netconvert cannot project node {node}{where}; a node's lat must lie "
            f"in [{LAT_RANGE[0]:g}, {LAT_RANGE[1]:g}] and its lon in [{LON_RANGE[0]:g}, "
            f"{LON_RANGE[1]:g}]: fix or remove the node"
        )
    attribute = re.search(r"Error: (Attribute '[^']*'[^\n]* node '[^']*'[^\n]*)", message)
    if attribute:
        return UserError(f"{osm_file}: {attribute[1].rstrip('.')}; fix that node's attribute")
    if "No nodes loaded" in message:  # nodes of no street way are dropped as they are read
        return UserError(
            f"{osm_file}: no road is left after conversion: no node lies on a street way twin "
            "imports (a way of two or more nodes, tagged highway=..., for cars), or none has a "
            f"numeric lat in [{LAT_RANGE[0]:g}, {LAT_RANGE[1]:g}] and lon in "
            f"[{LON_RANGE[0]:g}, {LON_RANGE[1]:g}]; give an extract with streets"
        )
    return UserError(message)


def _osm_node_position(osm_file: Path, node: str) -> tuple[str | None, str | None]:
    """The lat and lon (as written) of the node ``node`` of an OSM extract, or Nones."""
    from twin.sumo.readers import open_xml

    with contextlib.suppress(ET.ParseError, OSError), open_xml(osm_file) as fh:
        for _, element in ET.iterparse(fh):
            if element.tag == "node" and element.get("id") == node:
                return element.get("lat"), element.get("lon")
            element.clear()
    return None, None


def osm_network_name(osm_file: Path) -> str:
    """The network file an OSM extract converts to: its name without the extract's suffixes
    (``.gz``, ``.xml``, ``.osm``) and ``.net.xml`` after it (``a.b.osm`` -> ``a.b.net.xml``,
    not ``a.net.xml``, which ``a.c.osm`` would give too)."""
    name = osm_file.name
    for suffix in (".gz", ".xml", ".osm"):
        if name.lower().endswith(suffix) and len(name) > len(suffix):
            name = name[: -len(suffix)]
    return f"{name}.net.xml"


def import_osm(osm_file: Path, out_dir: Path | None = None) -> Path:
    """Convert an OpenStreetMap extract into a SUMO network with city-network options, into
    ``out_dir`` or (by default) the cache, reusing a cached conversion."""
    osm_file = Path(osm_file)
    if not osm_file.exists():
        raise missing(osm_file, "OSM file")
    why = not_a_file(osm_file)  # a folder, a pipe or a device: netconvert reads a file by name
    if why is not None:
        raise UserError(f"{osm_file}: {why} (an OSM extract: .osm, or .osm.gz)")
    head = b""
    with contextlib.suppress(OSError), open(osm_file, "rb") as fh:
        head = fh.read(16)
    if head[4:15] == b"\x0a\x09OSMHeader":  # a PBF file's first blob
        raise UserError(
            f"{osm_file}: an OSM PBF extract, which netconvert does not read; convert it to "
            f"XML (osmium cat {osm_file.name} -o {osm_file.stem}.osm) and give the .osm"
        )
    for magic, what, command in _PACKED_OSM:  # bzip2: how OSM extracts are downloaded
        if head.startswith(magic):
            raise UserError(
                f"{osm_file}: {what}-compressed extract, which netconvert does not read; "
                f"decompress it ({command} {osm_file.name}) and give the .osm (gzip works too)"
            )
    check_no_comma(osm_file, "netconvert")
    if out_dir is None:  # the network is for SUMO, which splits its path at commas
        check_cache_without_comma()
    else:
        check_no_comma(out_dir)
    name = osm_network_name(osm_file)

    no_road = UserError(
        f"{osm_file}: no road is left after conversion (twin keeps the roads passenger cars "
        "may use, drops tracks, paths, service roads and isolated edges); give an extract with "
        "streets, or convert it with your own netconvert options and pass the network with --net"
    )

    def make(out: Path, file_name: str = name) -> None:
        try:
            run_sumo_program(
                [binary("netconvert"), "--osm-files", str(osm_file), "--output-file",
                 str(out / file_name), *OSM_OPTIONS, "--no-warnings", "true"],
                what=f"netconvert on {osm_file}",
            )  # fmt: skip
        except UserError as exc:
            if "No edges loaded" in str(exc):  # every way dropped as it was read
                raise no_road from None
            raise _osm_refusal(osm_file, str(exc)) from None
        if not has_roads(out / file_name):  # every edge removed after reading (isolated)
            raise no_road

    def verify(folder: Path) -> None:  # an empty conversion cached by an earlier twin
        resources.check_xml_files(folder, {name: "net"})
        if not has_roads(folder / name):
            raise resources.BrokenEntry(f"{name} holds no road")

    if out_dir is None:
        return resources.build_once(imported_dir(osm_file), make, verify=verify) / name
    from twin.outputs import check_output_dir

    out_dir = check_output_dir(out_dir, "--out", links_out=True)  # writes one new file there
    target = out_dir / name
    if target.exists() or target.is_symlink():
        raise UserError(
            f"--out {out_dir}: {name} exists there; twin never overwrites a file: give "
            "another folder, or move that file away"
        )
    created = not out_dir.exists()
    out_dir.mkdir(parents=True, exist_ok=True)
    partial = f".{name}.tmp"  # a failed conversion leaves no half network under the name
    try:
        make(out_dir, partial)
        (out_dir / partial).replace(target)
    finally:
        (out_dir / partial).unlink(missing_ok=True)
        if created and not target.exists():  # nor the folder it made for it
            with contextlib.suppress(OSError):
                out_dir.rmdir()
    return target


def has_roads(net_file: Path) -> bool:
    """Whether a network holds an edge that is not inside a junction (read up to the first)."""
    with open(net_file, "rb") as fh:
        for _, elem in ET.iterparse(fh, events=("start",)):
            if elem.tag == "edge" and elem.get("function") != "internal":
                return True
    return False


def check_net_file(net_file: Path) -> None:
    """One-line error unless ``net_file`` is a readable SUMO network (gzip-compressed or not)."""
    net_file = Path(net_file)
    tag = root_tag(net_file, "network file")
    if tag != "net":
        raise UserError(f"{net_file}: not a SUMO network (root element <{tag}>, want <net>)")
    with open_xml(net_file) as fh:
        if reencoded(fh):  # SUMO reads it; sumolib, which twin reads networks with, not
            raise UserError(
                f"{net_file}: a network in an encoding other than it declares, or in UTF-32 "
                "or a multi-byte one, which SUMO reads but twin's network reader (sumolib) "
                f"does not; write it as UTF-8 (netconvert -s {net_file.name} -o FILE)"
            )


def generate_grid_scenario(
    out_dir: Path, blocks: int, block_m: float, end_s: float, period_s: float, seed: int
) -> tuple[Path, Path]:
    """A small signalised grid network (netgenerate) with uniform random trips (randomTrips),
    for tests, benchmarks and quick tries. Returns ``(net_file, trips_file)`` in ``out_dir``."""
    from twin.sumo.tools import tool

    net, trips = out_dir / "small.net.xml", out_dir / "small.trips.xml"
    run_sumo_program(
        [binary("netgenerate"), "--grid", "--grid.number", str(blocks),
         "--grid.length", str(block_m), "--default.lanenumber", "2", "--tls.guess", "true",
         "--no-internal-links", "true", "-o", str(net)],
        what="netgenerate",
    )  # fmt: skip
    run_sumo_program(
        [tool("randomTrips.py"), "-n", str(net), "-o", str(trips),
         "-r", str(out_dir / "small.rou.xml"), "-b", "0", "-e", str(end_s),
         "-p", str(period_s), "--seed", str(seed), "--validate"],
        what="randomTrips",
    )  # fmt: skip
    return net, trips


#: Networks of other shapes than the built-in one, generated by netgenerate (no download):
#: name -> netgenerate options. Demand is generated for them as for any network given without
#: routes (randomTrips over the scenario's window, twin/sumo/demand.py).
GENERATED_NETWORKS: dict[str, list[str]] = {
    # a radial city: 6 arms, 5 rings 400 m apart (4 km across), signals at the junctions
    "spider": ["--spider", "--spider.arm-number", "6", "--spider.circle-number", "5",
               "--spider.space-radius", "400", "--spider.omit-center", "true"],
}  # fmt: skip


def generated_network(kind: str) -> Path:
    """Build (or reuse) the netgenerate network ``kind`` of :data:`GENERATED_NETWORKS` in the
    user cache (``generated/<kind>-<hash>/``); returns its ``.net.xml``."""
    if kind not in GENERATED_NETWORKS:
        raise UserError(
            f"generated network {kind!r} is unknown; choose from {', '.join(GENERATED_NETWORKS)}"
        )
    options = [*GENERATED_NETWORKS[kind], "--default.lanenumber", "2", "--tls.guess", "true",
               "--no-internal-links", "true"]  # fmt: skip
    digest = hashlib.sha256(json.dumps([options, sumo_version()]).encode()).hexdigest()[:16]
    name = f"{kind}.net.xml"

    def make(out: Path) -> None:
        run_sumo_program(
            [binary("netgenerate"), *options, "-o", str(out / name)], what="netgenerate"
        )

    verify = lambda d: resources.check_xml_files(d, {name: "net"})  # noqa: E731
    where = resources.cache_dir() / "generated" / f"{kind}-{digest}"
    return resources.build_once(where, make, verify=verify) / name
