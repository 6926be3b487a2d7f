"""The lifecycle of one in-process SUMO simulation through libsumo: start, advance, read, close.

libsumo runs at most one simulation per process, so a session is exclusive: starting a second
one while the first is open is an error, and :meth:`SumoSession.close` (also called on leaving a
``with`` block and at interpreter exit) frees the slot for the next one.

Bulk reads happen only at sample times: :meth:`SumoSession.vehicles` asks every running vehicle
for its position and speed. No subscriptions are set, because SUMO evaluates subscriptions at
every simulation step even when they are read only every 75 s (see benchmarks/bench_sumo.py).
"""

from __future__ import annotations

import atexit
import contextlib
import io
import itertools
import os
import re
import stat
import subprocess
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, ClassVar
from xml.sax.saxutils import escape as xml_escape

import numpy as np

from twin.errors import UserError
from twin.sumo.readers import missing

#: SUMO options that keep a congested run moving in rush hour:
#: a vehicle blocked for 300 s jumps ahead (teleport), a vehicle that cannot enter the network
#: for 15 min is dropped, a share of vehicles reroute around congestion every 5 min (each one
#: a scenario's sumocfg sets is its own, :func:`filled_in_options`).
ANTI_GRIDLOCK_OPTIONS = (
    "--time-to-teleport", "300",
    "--max-depart-delay", "900",
    "--ignore-junction-blocker", "60",
    "--device.rerouting.probability", "0.3",
    "--device.rerouting.period", "300",
    "--device.rerouting.adaptation-steps", "18",
)  # fmt: skip


#: SUMO's own defaults for checking XML inputs against the schema they declare, given
#: explicitly: the sumo binary checks route and additional files that declare one (a misspelt
#: attribute is refused), libsumo only when told (such a file ran, the attribute ignored).
XML_VALIDATION = ("--xml-validation", "local", "--xml-validation.routes", "local")


def filled_in_options(sumocfg: Path | None) -> tuple[str, ...]:
    """:data:`ANTI_GRIDLOCK_OPTIONS` and :data:`XML_VALIDATION` but those a scenario's sumocfg
    sets itself: its own settings (no teleports, no rerouting, no validation ...) are kept,
    twin's only fill in where it says nothing. Route files follow the sumocfg's
    ``xml-validation`` when it sets no ``xml-validation.routes``, as the sumo binary reads them
    (``never`` checks neither; libsumo kept checking routes)."""
    defaults = (*ANTI_GRIDLOCK_OPTIONS, *XML_VALIDATION)
    if sumocfg is None:
        return defaults
    from twin.sumo.readers import read_sumocfg

    options = read_sumocfg(sumocfg, own_net=False).options
    own = set(options)
    if "load-state" in own:  # the state holds rerouting's speeds: another count crashes SUMO
        own.add("device.rerouting.adaptation-steps")
    general = options.get("xml-validation")
    if general and "xml-validation.routes" not in own:
        defaults = (*ANTI_GRIDLOCK_OPTIONS, "--xml-validation.routes", general)
    pairs = zip(defaults[::2], defaults[1::2], strict=True)
    return tuple(part for flag, value in pairs if flag[2:] not in own for part in (flag, value))


#: Warnings of one kind SUMO writes before it only counts them (``--aggregate-warnings``).
AGGREGATE_AFTER = 20


class SumoRunError(RuntimeError):
    """SUMO failed while running (not on start): what was recorded so far is still valid.
    ``reason``: SUMO's own words."""

    def __init__(self, message: str, reason: str = "") -> None:
        super().__init__(message)
        self.reason = reason or message


def _libsumo():
    """The API of the open session: traci when it runs under sumo-gui (``gui`` set), else
    libsumo (imported silencing its print about the pyarrow version). Both have the same calls."""
    active = SumoSession._active
    if active is not None and active.gui is not None:
        import traci

        return traci
    with contextlib.redirect_stdout(io.StringIO()):
        import libsumo
    return libsumo


@dataclass
class SumoSession:
    """One SUMO run: network, demand files, time window, seed and options."""

    net_file: Path
    route_files: Sequence[Path] = ()
    begin: float = 0.0
    end: float = 3600.0
    seed: int = 0
    step_length: float = 1.0
    mesoscopic: bool = False
    extra_options: Sequence[str] = (*ANTI_GRIDLOCK_OPTIONS, *XML_VALIDATION)
    additional_files: Sequence[Path] = ()
    config_file: Path | None = None
    #: skip a vehicle whose route cannot be followed (twin's own demand, which is its to keep
    #: moving, or a run with scheduled closures); a scenario's own demand is otherwise taken as
    #: SUMO takes it: such a vehicle stops SUMO
    ignore_route_errors: bool = True
    #: run under sumo-gui through traci (a :class:`twin.sumo.gui.GuiSettings`); None: libsumo.
    #: The simulation is the same, so are the results.
    gui: Any = None
    #: let SUMO write its warnings (a SUMO child whose messages go to ``sumo-messages.log``:
    #: :mod:`twin.sumo.worker`); elsewhere they would crowd twin's stderr
    warnings: bool = False
    started: bool = field(default=False, init=False)
    #: sumo-gui's error log in twin's scratch folder, removed when the session closes
    _scratch: Path | None = field(default=None, init=False, repr=False)
    _classes: dict[str, str] = field(default_factory=dict, init=False, repr=False)  # vClass by id

    _active: ClassVar[SumoSession | None] = None

    def command(self) -> list[str]:
        """The SUMO command line this session starts (its files by absolute paths: one holding
        a comma, which SUMO splits file lists at, is refused in one line)."""
        from twin.sumo.readers import check_no_comma

        for path in (self.config_file, self.net_file, *self.route_files, *self.additional_files):
            if path is not None:
                check_no_comma(path)
        cmd = ["sumo"]
        if self.config_file is not None:
            cmd += ["--configuration-file", str(self.config_file)]
        cmd += [
            "--net-file", str(self.net_file),
            "--begin", f"{self.begin:g}",
            "--end", f"{self.end:g}",
            "--seed", str(self.seed),
            "--random", "false",  # a config's clock seed would make runs unrepeatable
            "--step-length", f"{self.step_length:g}",
            "--no-step-log", "true",
            # a warning of a kind past 20 is counted, not written (a city's teleports)
            *(["--aggregate-warnings", str(AGGREGATE_AFTER)] if self.warnings
              else ["--no-warnings", "true"]),
            "--duration-log.disable", "true",
            "--threads", "1",
        ]  # fmt: skip
        if self.ignore_route_errors:
            cmd += ["--ignore-route-errors", "true"]
        if self.route_files:
            cmd += ["--route-files", ",".join(str(p) for p in self.route_files)]
        if self.additional_files:
            cmd += ["--additional-files", ",".join(str(p) for p in self.additional_files)]
        if self.mesoscopic:
            cmd += ["--mesosim", "true", "--meso-junction-control", "true"]
        return cmd + list(self.extra_options)

    def additionals(self) -> list[Path]:
        """The additional files SUMO loads, from the field and from ``extra_options``."""
        files = [Path(p) for p in self.additional_files]
        options = list(self.extra_options)
        for flag, value in itertools.pairwise(options):
            if flag in ("--additional-files", "-a"):
                files += [Path(v) for v in value.split(",") if v]
        return files

    def input_files(self) -> list[Path]:
        """The files SUMO reads: sumocfg, network, routes, additionals."""
        named = (self.config_file, self.net_file, *self.route_files, *self.additionals())
        return [Path(p) for p in named if p is not None]

    def read_files(self) -> list[Path]:
        """:meth:`input_files` with, after each, the files it pulls in with ``<include
        href>`` (a refused object may be defined there)."""
        from twin.sumo.readers import included_files, may_hold

        out = []
        for path in self.input_files():
            out.append(path)
            if path.suffix != ".sumocfg" and may_hold(path, b"include"):
                out += included_files(path)
        return out

    def file_of(self, message: str) -> Path | str | None:
        """The input file a message of SUMO's names or concerns, None when none is told."""
        return sumo_refusal(message, self.read_files(), fallback=False)[0]

    def refusal(self, message: str, when: str = "") -> UserError:
        """SUMO's refusal (``message``) as one line naming the file it concerns
        (:func:`sumo_refusal`, an included file too); ``when`` says when SUMO gave it, if not
        on start."""
        where, reason = sumo_refusal(message, self.read_files())
        loaded = [os.path.realpath(p) for p in self.input_files() if p.suffix != ".sumocfg"]
        if isinstance(where, Path) and loaded.count(os.path.realpath(where)) > 1:
            reason = (  # its ids taken by itself: the sumocfg, flags or keys name it twice
                f"{reason.rstrip('.')}; {where.name} is given twice (by the sumocfg, --routes, "
                "--additional or [traffic] keys), so SUMO loads it twice: drop the repeat"
            )
        if "ends before its begin time" in reason and self.begin > 0:  # a flow without begin
            from twin.clock import clock_label

            reason = (  # (SUMO says so too of a flow whose own begin is past its end)
                f"{reason.rstrip('.')}: if it gives no begin, it begins where twin starts SUMO, "
                f"and twin starts SUMO at {clock_label(self.begin)} (the window's start less the "
                "warm-up); give the flow a begin, or a --begin"
            )
        return UserError(f"{where}: SUMO refuses it{when}: {reason}")

    def start(self) -> SumoSession:
        if SumoSession._active is not None:
            raise RuntimeError(
                "a SUMO session is already open in this process (libsumo allows one)"
            )
        files = self.input_files()
        for path in files:
            if not Path(path).exists():
                raise missing(path, "file")
        if self.gui is not None:
            self._start_gui(files)
            return self
        libsumo = _libsumo()
        stderr = _capture_fd2()
        try:
            libsumo.start(self.command())
        except Exception as exc:  # libsumo raises its own TraCI exception types
            said = stderr.text()  # its warnings come first; its error may be the exception's
            has_error = re.search(r"^Error:", said, re.MULTILINE)
            message = said if has_error or not str(exc) else f"Error: {exc}\n{said}"
            with contextlib.suppress(Exception):
                libsumo.close()
            raise self.refusal(message) from None
        else:
            said = stderr.text()  # errors SUMO went on after while loading: kept as SUMO's
        finally:
            stderr.restore()
        if said:  # messages, like those it writes while running (sumo/sumo-messages.log)
            with contextlib.suppress(OSError):
                os.write(2, said.encode())
        SumoSession._active = self
        self.started = True
        return self

    def _start_gui(self, files: list[Path]) -> None:
        """Start sumo-gui through traci with the same options (see :mod:`twin.sumo.gui`); its
        refusal to start is one line with its reason and file, as libsumo's is."""
        import traci
        from sumolib.miscutils import getFreeSocketPort

        cmd = [self.gui.binary(), *self.command()[1:], *self.gui.sumo_options(self.mesoscopic)]
        log = _error_log(cmd)  # sumo-gui says why it quits there (and in its window), not on
        owned = None  # stderr
        if log is None:
            from twin.resources import scratch_dir

            log = owned = scratch_dir() / f"twin-gui-errors-{os.getpid()}.txt"
            cmd += ["--error-log", str(log)]
        stderr = _ChildStderr()
        try:
            with (
                self.gui.environment(),  # its saved settings in twin's cache, not in ~
                contextlib.redirect_stdout(io.StringIO()),  # traci's "Retrying in 1 seconds"
            ):
                # a port of its own: traci then gives up when sumo-gui quits, instead of
                # starting it again on other ports for a minute
                traci.start(cmd, port=getFreeSocketPort(), stdout=subprocess.DEVNULL)
        except Exception as exc:  # traci raises FatalTraCIError, TraCIException or OSError
            stderr.child_started()
            with contextlib.suppress(Exception):
                traci.close()
            said = stderr.text(wait=True)
            with contextlib.suppress(OSError):
                said += log.read_text(errors="replace")
            if owned is not None:
                owned.unlink(missing_ok=True)
            if "Error" in said:
                where, reason = sumo_refusal(said, self.read_files())
                raise UserError(f"{where}: sumo-gui refuses it: {reason}") from None
            raise UserError(f"--gui: sumo-gui did not start ({_first_line(str(exc))})") from None
        except BaseException:  # Ctrl-C while it starts: twin's stderr back, its log gone
            stderr.child_started()
            if owned is not None:
                owned.unlink(missing_ok=True)
            raise
        stderr.child_started()
        stderr.pass_on()  # its messages from here on go to twin's stderr, as libsumo's do
        self._scratch = owned  # removed when the session closes
        SumoSession._active = self
        self.started = True

    @property
    def time(self) -> float:
        return float(_libsumo().simulation.getTime())

    def advance_to(self, t: float) -> None:
        """Run the simulation up to time ``t`` (s) in one call (no per-step Python work)."""
        mark = _stderr_size() if self.gui is None else None
        try:
            _libsumo().simulationStep(t)
        except Exception as exc:
            said = _first_line(str(exc))
            cause = _error_written_since(mark, said)  # "vehicle cannot be created": SUMO's why
            said = f"{cause} ({said})" if cause else said
            raise SumoRunError(f"SUMO failed before t = {t:g} s: {said}", said) from exc

    def vehicles(self, not_for_cars: frozenset[str] = frozenset()) -> tuple[np.ndarray, np.ndarray]:
        """Positions ``(n, 2)`` (m, network coordinates) and speeds ``(n,)`` (m/s) of the
        vehicles on the road now; vehicles off it are left out: in a teleport, or parked off
        their lane (in a parking area, but one ``onRoad``, or at a stop with ``parking="true"``;
        SUMO's own lane counts leave them out too), or on a lane of ``not_for_cars`` (a bike or
        bus lane, a rail: not the car lanes whose lane-km and speed limits the cells have)."""
        veh = _libsumo().vehicle
        ids = veh.getIDList()
        xy = np.array([veh.getPosition(v) for v in ids], dtype=float).reshape(-1, 2)
        speed = np.array([veh.getSpeed(v) for v in ids], dtype=float)
        on_road = xy[:, 0] > -1e9  # libsumo's INVALID_DOUBLE_VALUE for teleporting vehicles
        if self.mesoscopic:  # SUMO's meso model tells neither lanes nor parking: all count
            # to the micrometre: its vehicles stand at segment ends, often on a cell border, and
            # sumo-gui places them 1e-14 m off libsumo (a --gui run or replay counted another
            # cell)
            return np.round(xy[on_road], 6), speed[on_road]
        if not_for_cars:  # (only networks with such lanes ask, and only of vehicles not cars)
            classes = self._classes
            for n, v in enumerate(ids):
                if (c := classes.get(v)) is None:
                    c = classes[v] = veh.getVehicleClass(v)
                if c != "passenger" and veh.getLaneID(v) in not_for_cars:
                    on_road[n] = False
            if len(classes) > 4 * len(ids) + 1000:  # those that left, forgotten now and then
                self._classes = {v: classes[v] for v in ids if v in classes}
        for n in np.flatnonzero(speed < HALTING_SPEED):  # a parked vehicle stands (slows to 0
            if veh.getLaneID(ids[n]) == "":  # as it parks): off its lane, as SUMO's lane counts
                on_road[n] = False  # leave it (one of an onRoad="true" area stays on it)
        return xy[on_road], speed[on_road]

    def n_running(self) -> int:
        return int(_libsumo().vehicle.getIDCount())

    def close(self) -> None:
        if self.started:
            with contextlib.suppress(Exception):
                _libsumo().close()
            self.started = False
        if self._scratch is not None:
            self._scratch.unlink(missing_ok=True)
            self._scratch = None
        if SumoSession._active is self:
            SumoSession._active = None

    def __enter__(self) -> SumoSession:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.close()


#: SUMO's halting speed (m/s): a vehicle parking has slowed below it.
HALTING_SPEED = 0.1

#: The elements that define an object SUMO names by its kind at the start of a refusal
#: ("Vehicle 'v' has no valid route"): its own file is named, not another holding the id.
OBJECT_ELEMENTS = {
    "vehicle": ("vehicle", "trip", "flow"),
    "person": ("person", "personFlow"),
    "container": ("container", "containerFlow"),
}


def sumo_refusal(
    text: str, files: list[Path], fallback: bool = True
) -> tuple[Path | str | None, str]:
    """The file SUMO refused and its reason, from what SUMO wrote on failing to start.

    SUMO names the file of an XML error (``In file '...'``, ``At line/column``); for other
    errors (an unknown vehicle class, edge, type, traffic light ...) the file is the first one
    that names the object SUMO quotes (or puts in parentheses), else the sumocfg or network
    (None without ``fallback``: no file is named).
    """
    reason = re.sub(r"^Error:\s*", "", _first_line(text))
    lines = [line.strip() for line in text.splitlines()]
    named = [m for line in lines if (m := re.match(r"In file '(.+)'", line))]
    place = [m for line in lines if (m := re.match(r"At line/column (\d+)/(\d+)", line))]
    if named:
        where: Path | str = Path(named[0][1])
        if place:
            reason += f" (line {place[0][1]}, column {place[0][2]})"
        return where, reason
    # the object SUMO names: quoted ('nolane_0'), or in parentheses ("to save (B1)")
    quoted = re.findall(r"'([^']+)'", reason) + re.findall(r"\(([^()\s]+)\)", reason)
    quoted += [t[1:] for t in quoted if t.startswith("!") and len(t) > 1]  # '!v': v's route
    quoted += [e for t in quoted if (e := xml_escape(t, {'"': "&quot;"})) != t]  # as written
    for path in files:
        if any(Path(token).name == Path(path).name for token in quoted):
            return path, reason
    # the object a refusal is about, named by its kind first ("Vehicle 'bad' has no valid
    # route ... edge 'A0A1'"): the file defining one of that kind (a flow's vehicle
    # 'f.0' is the flow 'f''s)
    subject = re.match(r"(?:The )?([A-Za-z]+) '([^']+)'", reason)
    kind = subject[1].lower() if subject else ""
    if kind in OBJECT_ELEMENTS:
        name = subject[2]
        ids = [name, *([name.rsplit(".", 1)[0]] if re.search(r"\.\d+$", name) else [])]
        ids += [e for i in ids if (e := xml_escape(i, {'"': "&quot;"})) != i]  # as written
        tags, names = "|".join(OBJECT_ELEMENTS[kind]), "|".join(re.escape(i) for i in ids)
        pattern = rf'<(?:{tags})\s[^>]*\bid\s*=\s*"(?:{names})"'
        for path in reversed(files):
            if path.suffix != ".sumocfg" and re.search(pattern, _text_of(path)):
                return path, reason
    for path in reversed(files):  # additionals and routes before the network
        if quoted and path.suffix != ".sumocfg" and _mentions(path, quoted):
            return path, reason
    # an element SUMO names by its kind ("... in definition of a interval."): the file with one
    element = re.search(r"definition of (?:an? )?([A-Za-z_][\w-]*)", reason)
    lacking = re.search(r"[Aa]ttribute '([A-Za-z_][\w:.-]*)' is missing", reason)
    holders = [
        p for p in reversed(files)
        if element and p.suffix != ".sumocfg" and _mentions(p, [element[1]], "<")
    ]  # fmt: skip
    for path in holders:  # the one whose element lacks the attribute, else the first
        if lacking is None or _lacks(path, element[1], lacking[1]):
            return path, reason
    if holders:
        return holders[0], reason
    # an attribute SUMO finds wrong ("Invalid ... Attribute accel.", "length must be ..."): the
    # file that gives it
    attribute = re.search(r"[Aa]ttribute '?([A-Za-z_][\w:-]*(?:\.[\w:-]+)*)'?", reason) or (
        re.match(r"([A-Za-z_][\w:-]*) must be ", reason)  # "length must be greater than 0"
    )
    wrong = attribute is not None and "missing" not in reason
    givers = [
        p for p in reversed(files)
        if wrong and p.suffix != ".sumocfg" and _mentions(p, [attribute[1]], "=")
    ]  # fmt: skip
    if givers:  # the one whose value breaks the bound SUMO names, else the first to give it
        bad = _value_below_bound(reason)
        if bad is not None:
            for path in givers:
                if _mentions(path, [rf'{re.escape(attribute[1])}\s*=\s*"{bad}'], "re"):
                    return path, reason
        return givers[0], reason
    return ((files[0] if files else "SUMO") if fallback else None), reason


def _lacks(path: Path, element: str, attribute: str) -> bool:
    """Whether an XML file holds an ``element`` start tag without ``attribute``."""
    data = _text_of(path)
    tags = re.finditer(rf"<{re.escape(element)}(?:\s[^>]*)?>", data)
    return any(not re.search(rf"\s{re.escape(attribute)}\s*=", m[0]) for m in tags)


def _value_below_bound(reason: str) -> str | None:
    """A pattern of the values a "... must be greater than 0" refusal names (negative or 0;
    negative for "equal or greater than 0"), None for another refusal."""
    if re.search(r"must be (equal or )?greater than 0", reason, re.IGNORECASE) is None:
        return None
    if re.search(r"equal or greater", reason, re.IGNORECASE):
        return r"\s*-"
    return r"\s*(-|0*\.?0*\s*\")"


def _mentions(path: Path, tokens: list[str], as_: str = "value") -> bool:
    """Whether a (perhaps gzip-compressed) XML file gives one of ``tokens`` as a value (or, with
    ``as_="<"``, holds an element of that name; with ``as_="="``, an attribute)."""
    data = _text_of(path)
    if as_ == "<":
        return any(re.search(rf"<{re.escape(t)}[\s/>]", data) for t in tokens)
    if as_ == "=":
        return any(re.search(rf"\s{re.escape(t)}\s*=", data) for t in tokens)
    if as_ == "re":  # tokens are patterns, matched after whitespace
        return any(re.search(rf"\s{t}", data) for t in tokens)
    return any(f'"{t}"' in data for t in tokens)


def _text_of(path: Path) -> str:
    """The first 64 MB of a (perhaps gzip-compressed) file as text; "" when unreadable."""
    import gzip

    try:
        with open(path, "rb") as fh:
            gz = fh.read(2) == b"\x1f\x8b"
        opener = gzip.open if gz else open
        with opener(path, "rb") as fh:
            return fh.read(64 << 20).decode(errors="replace")
    except (OSError, EOFError):
        return ""


def _stderr_size() -> int | None:
    """The size of the file behind stderr (a worker's SUMO messages), None when stderr is no
    file (a terminal, a pipe)."""
    try:
        info = os.fstat(2)
    except OSError:
        return None
    return info.st_size if stat.S_ISREG(info.st_mode) else None


def _error_written_since(mark: int | None, said: str) -> str | None:
    """SUMO's first ``Error:`` line written to stderr since ``mark`` (:func:`_stderr_size`
    before the call that failed) other than the error libsumo raised (``said``): the cause
    SUMO wrote ("Invalid vehicle id 'q&r'") of the one it raised ("vehicle cannot be
    created"). Read through ``/proc/self/fd/2`` (Linux); None elsewhere, or without a file."""
    if mark is None:
        return None
    try:
        with open("/proc/self/fd/2", "rb") as fh:
            fh.seek(mark)
            lines = fh.read(65536).decode(errors="replace").splitlines()
    except OSError:
        return None
    errors = [x[len("Error:") :].strip() for x in lines if x.startswith("Error:")]
    errors = [x for x in errors if x and x != said]
    return errors[0] if errors else None


def _first_line(text: str) -> str:
    """SUMO's first ``Error:`` line (else the first naming an error, else the first line):
    never a warning it wrote before its error."""
    lines = [line.strip() for line in text.splitlines() if line.strip()]
    for line in lines:
        if line.startswith("Error:"):
            return line
    for line in lines:
        if "error" in line.lower() and not line.startswith("Warning:"):
            return line
    return lines[0] if lines else "unknown error"


def _error_log(cmd: list[str]) -> Path | None:
    """The file a SUMO command line writes its errors to (``--error-log``, else ``--log``)."""
    for names in (("--error-log",), ("--log", "-l")):
        for flag, value in itertools.pairwise(cmd):
            if flag in names:
                return Path(value)
    return None


class _ChildStderr:
    """The stderr of a process started while it exists (sumo-gui), through a pipe: held while
    the process starts, so that its refusal becomes twin's one line, then passed on to twin's
    stderr as it comes."""

    def __init__(self) -> None:
        import threading

        self._read, write = os.pipe()
        self._saved = os.dup(2)
        os.dup2(write, 2)  # a process started now writes into the pipe
        os.close(write)
        self._held: list[bytes] = []
        self._passing = False
        self._restored = False
        self._lock = threading.Lock()
        self._thread = threading.Thread(target=self._pump, daemon=True)
        self._thread.start()

    def _pump(self) -> None:
        with os.fdopen(self._read, "rb", buffering=0) as fh:
            while chunk := fh.read(4096):
                with self._lock:
                    if self._passing:
                        os.write(self._saved, chunk)
                    else:
                        self._held.append(chunk)

    def child_started(self) -> None:
        """twin's own stderr back; the child keeps the pipe."""
        if not self._restored:
            os.dup2(self._saved, 2)
            self._restored = True

    def text(self, wait: bool = False) -> str:
        """What was held; ``wait``: until the child closed its end (at most 5 s)."""
        if wait:
            self._thread.join(timeout=5.0)
        with self._lock:
            return b"".join(self._held).decode(errors="replace")

    def pass_on(self) -> None:
        with self._lock:
            for chunk in self._held:
                os.write(self._saved, chunk)
            self._held.clear()
            self._passing = True


class _capture_fd2:
    """Capture what the C++ side of libsumo writes to file descriptor 2 (stderr)."""

    def __init__(self) -> None:
        import tempfile

        from twin.resources import scratch_dir

        # in the cache's scratch folder, as twin's every temporary file (never $TMPDIR)
        self._file = tempfile.TemporaryFile(mode="w+b", dir=scratch_dir())  # noqa: SIM115
        self._saved = os.dup(2)
        os.dup2(self._file.fileno(), 2)
        self._restored = False

    def text(self) -> str:
        self._file.seek(0)
        return self._file.read().decode(errors="replace")

    def restore(self) -> None:
        if not self._restored:
            os.dup2(self._saved, 2)
            os.close(self._saved)
            self._file.close()
            self._restored = True


@atexit.register
def _close_open_session() -> None:
    if SumoSession._active is not None:
        SumoSession._active.close()
