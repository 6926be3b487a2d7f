"""SUMO's configured outputs, sent into the run folder instead of beside the scenario's files.

A scenario may ask SUMO for outputs: a sumocfg's ``<output>`` and ``<report>`` sections
(``tripinfo-output``, ``summary-output``, ``fcd-output``, ``log``, ``save-state.files`` ...), and
additional files whose elements write files (detectors' ``file=``, ``edgeData``/``laneData``
``file=``, a calibrator's ``output=``, a ``timedEvent``'s ``dest=``), and vehicle types or
vehicles whose device parameters name files (``<param key="device.ssm.file" value=...>``, in
additional or route files). SUMO would write them next to the user's files; twin writes only
into its run folder, so when it starts SUMO it

- passes a command-line override for every output option the sumocfg sets, pointing into the
  output folder (``RUN/sumo/``) with the same base name;
- loads, instead of an additional file that writes outputs, a copy in the output folder whose
  outputs point into that folder and whose other relative paths (``<include href>``, a
  rerouter's definitions, images) are made absolute so they resolve as before (the same for a
  route file whose device parameters name files, and a network whose traffic lights' programs
  do: an actuated light's detector ``file``).

A file that declares entities in its own DTD is loaded as such a copy too, its entities
expanded: SUMO's program reads them, libsumo does not.

An output the sumocfg sends to ``stdout`` or ``stderr`` (``-``) goes to ``RUN/sumo/<option>.xml``
instead, one of an additional file's elements to ``RUN/sumo/<element>-<id>.xml``
(``edgeData-ed1.xml``; a parameter's to ``<key>.xml``), all listed in run.json's
``traffic.sumo_outputs``: twin's tables and its one-line errors are on those streams.

SSM devices equipped without a file (``device.ssm.probability``, a vehicle type's
``has.ssm.device``) would write one ``ssm_<vehicle>.xml`` per vehicle into SUMO's working
folder: twin then names their file, ``RUN/sumo/ssm.xml``.

Files are named by their base name; two outputs of the same base name from different folders
get ``-2``, ``-3`` ... One output file shared by several detectors stays shared. Every path
handed to SUMO is absolute: SUMO reads an additional file's outputs relative to that file, so a
relative run folder would put them in ``RUN/sumo/RUN/sumo/``.

SUMO prepends ``output-prefix`` to the last part of every output's path (and inserts
``output-suffix`` before its extension), so a prefix with a folder part (``../escape_``,
``/tmp/x_``) would move all outputs out of the folder; an ``output-prefix`` or ``output-suffix``
the sumocfg sets is overridden by its last part only (``escape_``, ``x_``; SUMO's ``TIME``
placeholder kept), which names the files but keeps them in ``RUN/sumo/``.
"""

from __future__ import annotations

import contextlib
import hashlib
import itertools
import os
import re
import xml.etree.ElementTree as ET
from pathlib import Path

from twin.errors import UserError
from twin.notices import notify
from twin.sumo.options import output_options
from twin.sumo.readers import (
    as_given,
    file_list,
    included_files,
    local_name,
    may_hold,
    open_xml,
    read_sumocfg,
    words_held,
)

#: SUMO's own messages while it runs (its warnings are off; errors such as a vehicle that
#: cannot depart), kept in this file of SUMO's output folder instead of twin's stderr
#: (:mod:`twin.sumo.worker`); an output of the scenario's by that name is named apart.
MESSAGES_NAME = "sumo-messages.log"
#: The later seeds' output folders beside the first seed's outputs (``sumo/seed-<s>/``,
#: :func:`twin.experiment.build_source`): an output of the scenario's by such a name is named
#: apart.
SEED_FOLDER = re.compile(r"seed-\d+")
#: Options that add to every output's name (kept to their name part, :func:`name_part`).
NAMING_OPTIONS = ("output-prefix", "output-suffix")
NAMING_FLAGS = tuple(f"--{name}" for name in NAMING_OPTIONS)
#: Options whose value is a list of files.
_FILE_LISTS = {"save-state.files"}
#: Output names SUMO writes to its process's streams (twin's own: sent to a file instead), by
#: its names for them or the system's (a path resolved would name where twin's streams go).
_STREAMS = {"stdout", "stderr", "-", "/dev/stdout", "/dev/stderr", "/dev/fd/1", "/dev/fd/2",
            "/proc/self/fd/1", "/proc/self/fd/2"}  # fmt: skip
#: Output names SUMO does not take as files, as it spells them (``Nul`` is a file).
_NOT_FILES = {"", "nul", "NUL", "/dev/null", *_STREAMS}

#: Elements of additional files that write files, and the attribute naming the file.
OUTPUT_ELEMENTS = {
    **{
        tag: "file"
        for tag in (
            "e1Detector", "inductionLoop", "instantInductionLoop", "e2Detector",
            "laneAreaDetector", "e3Detector", "entryExitDetector", "edgeData", "laneData",
            "meandata-edge", "meandata-lane", "edgeRelations", "tazRelations", "routeProbe",
            "vTypeProbe",
        )
    },
    "calibrator": "output",
    "timedEvent": "dest",
}  # fmt: skip
#: Device parameters of vehicle types and vehicles that name output files (``<param key=...>``).
DEVICE_OUTPUTS = frozenset(
    (
        "device.ssm.file", "device.toc.file", "device.rerouting.output",
        "device.taxi.dispatch-algorithm.output", "device.taxi.idle-algorithm.output",
    )
)  # fmt: skip
#: Parameters of a traffic light's program (``<tlLogic>`` of a network or an additional file)
#: that name output files: an actuated, delay-based or NEMA light's detector output.
PROGRAM_OUTPUTS = frozenset(("file",))
#: An entity declared in a file's own DTD (``<!DOCTYPE routes [<!ENTITY e "...">]>``), which
#: libsumo cannot read: the file is loaded as a copy with its entities expanded.
ENTITY = b"<!ENTITY"
#: Attributes of additional files that name input files (made absolute in a rewritten copy).
INPUT_ATTRIBUTES = ("href", "file", "imgFile", "osgFile")

ET.register_namespace("xsi", "http://www.w3.org/2001/XMLSchema-instance")


def _is_file(value: str) -> bool:
    v = value.strip()
    if v in _NOT_FILES:
        return False
    host, _, port = v.rpartition(":")  # a socket host:port
    return not (host and port.isdigit() and "/" not in v)


class OutputPlan:
    """Where each output goes in ``out_dir`` (created on first use) and the copies written."""

    def __init__(self, out_dir: Path):
        self.out_dir = Path(os.path.abspath(out_dir))
        self.targets: dict[Path, Path] = {}
        self.copies: dict[Path, Path] = {}
        self._names: set[str] = {MESSAGES_NAME}
        #: SSM devices may be equipped (a ``device.ssm.*`` option or parameter): without a
        #: file, SUMO writes one ``ssm_<vehicle>.xml`` per vehicle into its working folder
        self.ssm_devices = False
        #: the files twin made for outputs sent to a stream, by made name (SUMO prefixes them)
        self.made: dict[str, Path] = {}

    def _fresh(self, name: str) -> Path:
        name = literal(name)
        stem, dot, suffix = name.partition(".")
        for n in itertools.count(1):
            candidate = name if n == 1 else f"{stem}-{n}{dot}{suffix}"
            if candidate not in self._names and not SEED_FOLDER.fullmatch(candidate):
                self._names.add(candidate)
                self.out_dir.mkdir(parents=True, exist_ok=True)
                return self.out_dir / candidate
        raise AssertionError  # pragma: no cover

    def stream_file(self, name: str) -> Path:
        """The file of the outputs the scenario sends to a stream under one made ``name``
        (:func:`_stream_file`: an element's, or a parameter's, which every vehicle giving it
        shares, as they share the stream), named apart from the outputs named before."""
        if name not in self.made:
            self.made[name] = self._fresh(name)
        return self.made[name]

    def own_file(self, name: str) -> Path:
        """A file of twin's own in ``out_dir`` (its virtual loops), named apart from the
        scenario's outputs (one named ``twin-loops.add.xml`` keeps its name)."""
        return self._fresh(name)

    def target(self, original: Path) -> Path:
        """The file in ``out_dir`` that replaces the output ``original`` (same base name)."""
        original = _absolute(original)
        if original not in self.targets:
            self.targets[original] = self._fresh(original.name)
        return self.targets[original]

    def additional(self, path: Path) -> Path:
        """``path``, or a rewritten copy in ``out_dir`` if it (or a file it includes) writes
        outputs."""
        path = _absolute(path)
        if path in self.copies:
            return self.copies[path]
        self.copies[path] = path  # (an include cycle ends here)
        try:
            with open_xml(path) as fh:
                tree = ET.parse(fh)
        except (ET.ParseError, OSError, EOFError):
            return path  # SUMO will say what is wrong with it
        # entities declared in the file's own DTD: SUMO's program expands them, libsumo
        # refuses them ("entity not found"); the copy holds them expanded
        root, base, changed = tree.getroot(), path.parent, may_hold(path, ENTITY)
        program_outputs = {
            id(param)
            for program in root.iter()
            if local_name(program) == "tlLogic"
            for param in program
            if local_name(param) == "param" and param.get("key") in PROGRAM_OUTPUTS
        }
        streams: list[tuple[ET.Element, str, str]] = []  # outputs sent to stdout or stderr
        for elem in root.iter():
            tag = local_name(elem)
            attr = OUTPUT_ELEMENTS.get(tag)
            if tag == "param" and (
                elem.get("key") in DEVICE_OUTPUTS or id(elem) in program_outputs
            ):
                attr = "value"
            if tag == "param" and _names_ssm(elem.get("key")):
                self.ssm_devices = True
            value = elem.get(attr) if attr else None
            if value is not None and value.strip() in _STREAMS:  # twin's tables are there
                streams.append((elem, attr, tag))
            elif value is not None and _is_file(value):
                elem.set(attr, str(self.target(base / value)))
                changed = True
        for elem, attr, tag in streams:  # after the file's own names: those keep theirs
            elem.set(attr, str(self.stream_file(_stream_file(elem, tag))))
            changed = True
        for elem in root.iter():
            href = elem.get("href") if local_name(elem) == "include" else None
            if href and self.additional(base / href) != _absolute(base / href):
                changed = True
        if changed:
            for elem in root.iter():
                tag = local_name(elem)
                if not tag:
                    continue
                for name in INPUT_ATTRIBUTES:
                    value = elem.get(name)
                    if value is None or name == OUTPUT_ELEMENTS.get(tag):
                        continue
                    if name == "href" and tag == "include":
                        elem.set(name, str(self.additional(base / value)))
                    elif _is_file(value) and not Path(value).is_absolute():
                        elem.set(name, str(_absolute(base / value)))
            for elem in root.iter():  # SUMO reads names as written: no ns0: prefixes
                if local_name(elem):
                    elem.tag = local_name(elem)
            name = path.name[:-3] if path.name.endswith(".gz") else path.name
            copy = self._fresh(name)
            ET.indent(tree)
            tree.write(copy, encoding="UTF-8", xml_declaration=True)
            self.copies[path] = copy
        return self.copies[path]

    def network(self, path: Path) -> Path:
        """``path``, or a rewritten copy in ``out_dir`` if a traffic light's program in it names
        an output file (:data:`PROGRAM_OUTPUTS`). A network is parsed only when its bytes hold
        both ``tlLogic`` and ``param`` (one pass over its bytes decides)."""
        held = words_held(path, ENTITY, b"tlLogic", b"param")
        if ENTITY in held or ({b"tlLogic", b"param"} <= held and _program_output(path)):
            return self.additional(path)
        return path

    def routes(self, path: Path) -> Path:
        """``path``, or a rewritten copy in ``out_dir`` if device parameters in it or in a file
        it includes name output files. Route files may be large: one is parsed only when its
        bytes, or an included file's, hold ``param`` (an element's name is never a character
        reference), or always when its encoding is not ASCII-compatible (UTF-16, UTF-32)."""
        for file in (path, *included_files(path)):
            if may_hold(file, b"param", ENTITY):  # one pass over a large route file
                return self.additional(path)
        return path

    def device_defaults(self, options: tuple[str, ...]) -> tuple[str, ...]:
        """``options`` with SSM's output file in ``out_dir`` when SSM devices may be equipped
        and no option names their file (one file for every vehicle, instead of one per
        vehicle in SUMO's working folder)."""
        ssm = self.ssm_devices or any(
            o.startswith("--device.ssm.") and not o.endswith(".input-file") for o in options
        )
        if not ssm or "--device.ssm.file" in options:
            return options
        return (*options, "--device.ssm.file", str(self.target(self.out_dir / "ssm.xml")))


#: The longest name twin makes up for an output (file systems take 255 bytes): a longer one
#: keeps its start and a digest of the whole.
MAX_MADE_NAME = 100


def _stream_file(elem: ET.Element, tag: str) -> str:
    """The file in the output folder of an element that sends its output to ``stdout`` or
    ``stderr``: ``<tag>-<id>.xml`` (``edgeData-ed1.xml``), a parameter's ``<key>.xml``."""
    name = elem.get("key") if tag == "param" else f"{tag}-{elem.get('id', '')}".rstrip("-")
    name = re.sub(r"[^\w.-]", "_", name or tag)
    return _shortened(name, MAX_MADE_NAME) + ".xml"  # a 300-character id: SUMO takes it


def _shortened(text: str, most: int) -> str:
    """``text``, or, past ``most`` bytes, its start and a digest of the whole in ``most``."""
    if len(text.encode()) <= most:
        return text
    digest = hashlib.sha256(text.encode()).hexdigest()[:8]
    return f"{text.encode()[: most - 9].decode(errors='ignore')}-{digest}"


def _program_output(path: Path) -> bool:
    """Whether a traffic light's program in the XML file ``path`` names an output file, read
    as a stream (a network may be large)."""
    program = 0
    try:
        with open_xml(path) as fh:
            for event, elem in ET.iterparse(fh, events=("start", "end")):
                tag = local_name(elem)
                if tag == "tlLogic":
                    program += 1 if event == "start" else -1
                elif (
                    event == "start"
                    and program
                    and tag == "param"
                    and elem.get("key") in PROGRAM_OUTPUTS
                    and _is_file(elem.get("value", ""))
                ):
                    return True
                if event == "end" and not program:
                    elem.clear()
    except (ET.ParseError, OSError, EOFError):
        return False  # SUMO will say what is wrong with it
    return False


def _names_ssm(key: str | None) -> bool:
    """A device parameter that may equip SSM devices (``has.ssm.device``, ``device.ssm.*``)."""
    return bool(key) and (key == "has.ssm.device" or key.startswith("device.ssm."))


def name_part(value: str) -> str:
    """The part of an ``output-prefix`` (``output-suffix``) that names files, without its folders
    (SUMO splits at the last ``/`` or ``\\``): ``../escape_`` -> ``escape_``."""
    return literal(re.split(r"[\\/]", value)[-1])


def literal(name: str) -> str:
    """A file name SUMO reads as it is: ``$`` (SUMO substitutes ``${NAME}`` on the command
    line too, :func:`twin.sumo.readers.substitute_environment`) and ``,`` (a list of files)
    replaced by ``_``."""
    return name.replace("$", "_").replace(",", "_")


def _absolute(path: Path) -> Path:
    """``path`` absolute, its links followed where they lead somewhere (a link loop stays as it
    is, for SUMO to refuse or, for an output, to be replaced)."""
    try:
        return Path(path).resolve()
    except (RuntimeError, OSError):  # Python 3.11 raises RuntimeError for a loop
        return Path(os.path.abspath(path))


def redirect_outputs(
    sumocfg: Path | None, options: tuple[str, ...], out_dir: Path
) -> tuple[tuple[str, ...], OutputPlan]:
    """``options`` with additional files that write outputs replaced by rewritten copies, plus
    an override of every output option of ``sumocfg``, all pointing into ``out_dir``; an
    ``output-prefix`` or ``output-suffix`` (of ``sumocfg`` or ``options``) keeps only its name
    part."""
    plan = OutputPlan(out_dir)
    extra: list[str] = []
    out = list(options)
    if sumocfg is not None:
        cfg = read_sumocfg(sumocfg, own_net=False)  # its outputs only
        for name in NAMING_OPTIONS:
            value = cfg.options.get(name)
            if value and f"--{name}" not in out:
                extra += [f"--{name}", name_part(value)]
        base = as_given(sumocfg).parent  # as SUMO: a config named through a link writes beside it
        plan.ssm_devices = any(k.startswith("device.ssm.") for k in cfg.options)
        given = {k: v for k, v in cfg.options.items() if k in output_options()}
        state_times = any(cfg.options.get(k) for k in ("save-state.times", "save-state.period"))
        if state_times and not given.get("save-state.files") and "save-state.prefix" not in given:
            given["save-state.prefix"] = "state"  # SUMO's default prefix, in its working folder
        streams = [name for name, value in given.items() if value.strip() in _STREAMS]
        for name, value in given.items():
            if name in streams:  # twin's tables and errors are there: after the others' names
                continue
            if name in _FILE_LISTS:
                files = file_list(value, base)
                if files:
                    extra += [f"--{name}", ",".join(str(plan.target(f)) for f in files)]
            elif _is_file(value):
                extra += [f"--{name}", str(plan.target(base / value.strip()))]
        for name in streams:  # a file of its own, named apart from the outputs' own names
            extra += [f"--{name}", str(plan.stream_file(f"{name}.xml"))]
    for i in range(len(out) - 1):
        if out[i] in ("--additional-files", "-a"):
            files = [Path(v) for v in out[i + 1].split(",") if v]
            out[i + 1] = ",".join(str(plan.additional(f)) for f in files)
            copied = [f for f in files if plan.additional(f) != _absolute(f)]
            if copied and "," in str(plan.out_dir):
                raise UserError(
                    f"{plan.out_dir}: SUMO splits file names at commas and reads twin's copy of "
                    f"{copied[0].name} (its outputs sent here) from this folder; give --out a "
                    "folder without a comma"
                )
        elif out[i] in {f"--{name}" for name in NAMING_OPTIONS}:
            out[i + 1] = name_part(out[i + 1])
    return (*out, *extra), plan


#: What SUMO's ``TIME`` placeholder in an output's name becomes, at most (bytes).
TIME_PLACEHOLDER_BYTES = 24


def naming_that_fits(options: tuple[str, ...], plan: OutputPlan) -> tuple[str, ...]:
    """``options`` with an ``output-prefix``/``output-suffix`` shortened (its start and a
    digest, said in a notice) when, around a name twin made for a stream's output, it would
    make a file name longer than file systems take: SUMO alone names no file for a stream, so
    a scenario with a long prefix runs there. Called once every file is planned."""
    from twin.outputs import NAME_MAX

    if not plan.made:
        return options
    out = list(options)
    at = {out[i]: i + 1 for i in range(len(out) - 1) if out[i] in NAMING_FLAGS}

    def size(value: str) -> int:  # SUMO's TIME placeholder expands
        return len(value.encode()) + value.count("TIME") * TIME_PLACEHOLDER_BYTES

    room = NAME_MAX - max(len(p.name.encode()) for p in plan.made.values())
    if not at or sum(size(out[i]) for i in at.values()) <= room:
        return options
    share = max(room // len(at), 16)
    for flag, i in at.items():
        if size(out[i]) > share:
            value, out[i] = out[i], _shortened(out[i].replace("TIME", ""), share)
            notify(
                f"twin: notice: {flag.removeprefix('--')} {value[:40]!r}... is too long for the "
                f"files of outputs sent to a stream; {out[i]!r} names the outputs instead"
            )
    return tuple(out)


def check_output_dir(out_dir: Path) -> None:
    """One-line error if ``out_dir`` cannot be made."""
    try:
        Path(out_dir).mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise UserError(f"{out_dir}: cannot create SUMO's output folder ({exc.strerror})") from exc


def remove_empty(out_dir: Path) -> None:
    with contextlib.suppress(OSError):
        Path(out_dir).rmdir()
