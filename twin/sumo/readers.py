"""Readers of SUMO's XML files: compressed or not, the root element, a ``.sumocfg``'s files,
options and time window, the span of a demand's departures."""

from __future__ import annotations

import codecs
import errno
import functools
import gzip
import io
import math
import os
import re
import xml.etree.ElementTree as ET
from collections.abc import Collection
from dataclasses import dataclass, field
from datetime import UTC, datetime
from pathlib import Path
from typing import IO

from twin.errors import UserError
from twin.files import not_a_file
from twin.notices import notify
from twin.sumo.options import canonical


def open_xml(path: Path) -> IO[bytes]:
    """A SUMO XML file for reading, gzip-compressed or not (SUMO reads both; told by content),
    in an encoding Python's XML parser reads as SUMO's does (:func:`_as_sumo_reads`)."""
    path = Path(path)
    fh = open(path, "rb")  # noqa: SIM115 (the caller closes it)
    try:
        if fh.read(2) == b"\x1f\x8b":
            fh.close()
            fh = gzip.open(path, "rb")  # noqa: SIM115 (the caller closes it)
        fh.seek(0)
        return _as_sumo_reads(path, fh)
    except BaseException:
        fh.close()
        raise


#: The starts of UTF-32 text (with and without a byte-order mark), which SUMO's parser
#: (Xerces) senses and Python's (expat) does not read.
_UTF32_STARTS = {
    b"\xff\xfe\x00\x00": "utf-32",
    b"\x00\x00\xfe\xff": "utf-32",
    b"<\x00\x00\x00": "utf-32-le",
    b"\x00\x00\x00<": "utf-32-be",
}
#: Multi-byte encodings SUMO's parser (Xerces) knows by names Python does not.
_UCS = re.compile(r"(ISO-10646-)?UCS-?[24]", re.IGNORECASE)
#: An XML declaration's encoding, in a file of ASCII-compatible bytes.
_DECLARED = re.compile(rb"""\A(\xef\xbb\xbf)?(<\?xml\s[^>]*?encoding\s*=\s*["'])([^"']*)(["'])""")


def _as_sumo_reads(path: Path, fh: IO[bytes]) -> IO[bytes]:
    """``fh`` as SUMO reads it: UTF-32 text given as UTF-8; a declared encoding that
    contradicts ASCII-compatible bytes (UTF-16, UTF-32, UTF-7: SUMO warns and reads what it
    senses, and for UCS-2/UCS-4) declared as UTF-8; an unknown encoding refused in one line,
    as by SUMO."""
    head = fh.read(1024)
    utf32 = _UTF32_STARTS.get(head[:4])
    if utf32 is not None:
        return _transcoded(path, fh, head, utf32)
    declared = _DECLARED.match(head)
    if declared is not None:
        name = declared[3].decode("ascii", "replace")
        try:
            info = codecs.lookup(name)
            codec = info.name if info._is_text_encoding else None  # not base64, rot13 ...
        except LookupError:
            codec = "utf-32" if _UCS.fullmatch(name) else None  # Xerces' names Python lacks
        if codec is None:
            raise UserError(
                f"{path}: its XML declaration names the encoding {name!r}, which twin does not "
                "know (SUMO refuses an encoding it does not know too); declare the file's "
                'encoding (e.g. encoding="UTF-8")'
            ) from None
        if codec.startswith(("utf-16", "utf-32", "utf-7")):  # bytes are ASCII-compatible
            head = head[: declared.start(3)] + b"UTF-8" + head[declared.end(3) :]
            return io.BufferedReader(_Joined(head, fh))
        if not _expat_reads(name):  # a multi-byte encoding (Shift_JIS, GB2312 ...)
            return _transcoded(path, fh, head, codec)
    fh.seek(0)
    return fh


def _transcoded(path: Path, fh: IO[bytes], head: bytes, codec: str) -> IO[bytes]:
    """The file ``head`` + the rest of ``fh``, in ``codec``, as UTF-8 declared so: read whole
    (such files are rare)."""
    try:
        text = (head + fh.read()).decode(codec).removeprefix("\ufeff")
    except (UnicodeError, LookupError) as exc:
        raise UserError(f"{path}: not valid XML (not {codec} text: {exc})") from None
    finally:
        fh.close()
    text = re.sub(r"""\A(<\?xml\s[^>]*?encoding\s*=\s*["'])[^"']*""", r"\g<1>UTF-8", text)
    return io.BytesIO(text.encode("utf-8"))


@functools.lru_cache(maxsize=64)
def _expat_reads(encoding: str) -> bool:
    """Whether Python's XML parser reads a file declared in ``encoding`` (expat reads UTF-8,
    UTF-16 and single-byte encodings, not multi-byte ones)."""
    from xml.parsers import expat

    try:
        expat.ParserCreate().Parse(
            f'<?xml version="1.0" encoding="{encoding}"?><a/>'.encode(), True
        )
    except (ValueError, LookupError, expat.ExpatError):
        return False
    return True


def reencoded(stream: IO[bytes]) -> bool:
    """Whether a stream of :func:`open_xml` gives other bytes than the file's (an encoding
    rewritten or transcoded for Python's XML parser)."""
    return isinstance(stream, io.BytesIO) or isinstance(getattr(stream, "raw", None), _Joined)


class _Joined(io.RawIOBase):
    """``head``, then the rest of ``rest``: a file whose first bytes were rewritten."""

    def __init__(self, head: bytes, rest: IO[bytes]):
        self._head, self._rest = head, rest

    def readable(self) -> bool:
        return True

    def readinto(self, buffer) -> int:
        if self._head:
            n = min(len(buffer), len(self._head))
            buffer[:n], self._head = self._head[:n], self._head[n:]
            return n
        data = self._rest.read(len(buffer))
        buffer[: len(data)] = data
        return len(data)

    def close(self) -> None:
        self._rest.close()
        super().close()


def link_loop(path: Path, named_in: Path | None = None) -> str:
    """The one-line message for a file that is a symbolic link loop."""
    where = f" (named in {named_in})" if named_in is not None else ""
    return f"{path}{where}: a symbolic link loop; fix or remove the link"


def resolved(path: Path, named_in: Path | None = None) -> Path:
    """``path`` made absolute as SUMO reads it (:func:`as_given`: a file named through a link
    reads its own relative names from the link's folder); a symbolic link loop, a pipe or a
    device is a one-line error (``named_in``: the config that names the file)."""
    if not Path(path).is_dir():
        check_regular(path)
    try:
        Path(path).resolve()  # a loop is refused here
    except (RuntimeError, OSError) as exc:  # Python 3.11 raises RuntimeError for a loop
        raise UserError(link_loop(path, named_in)) from exc
    return as_given(path)


def as_given(path: Path) -> Path:
    """``path`` absolute without following its links, as SUMO takes a file name (it joins a
    config's folder and a relative name as text): ``..`` is folded into its folder, except
    after a link, where the system resolves it in the link's target."""
    whole = Path.cwd() / path
    out = Path(whole.anchor)
    for part in whole.parts[1:]:
        if part != "..":
            out = out / part
        elif out.is_symlink():
            return whole  # only the system knows where it leads
        else:
            out = out.parent
    return out


def missing(path: Path, what: str) -> UserError:
    """The one-line error for a file that is not there: a symbolic link loop, or no file."""
    try:
        os.stat(path)
    except OSError as exc:
        if exc.errno == errno.ELOOP:
            return UserError(link_loop(path))
    return UserError(f"{path}: no such {what}")


def check_no_comma(path: Path | str, program: str = "SUMO") -> None:
    """Refuse (one line) a file that twin hands ``program`` by its full path when the path
    holds a comma: SUMO's programs split file lists at commas."""
    if "," in str(path):
        raise UserError(
            f"{path}: {program} splits file names at commas, and twin gives it this one by its "
            "full path; rename the folder or file without the comma"
        )


def check_cache_without_comma() -> None:
    """twin hands SUMO files of its cache (built networks, generated demand, its loops) by their
    full paths, which SUMO splits at commas: a cache folder with a comma is refused before any
    of them is made, naming the variable that sets it."""
    from twin.resources import CACHE_ENV, cache_dir

    folder = cache_dir()
    if "," in str(folder):
        raise UserError(
            f"twin's cache {folder} (${CACHE_ENV}) has a comma in its path, and SUMO splits the "
            f"names of the cache's files twin gives it at commas; set {CACHE_ENV} to a folder "
            "without one"
        )


def local_name(elem: ET.Element) -> str:
    """An element's name without its namespace (``{uri}edgeData`` -> ``edgeData``), as SUMO
    matches names; ``""`` for a comment or processing instruction."""
    tag = elem.tag
    return tag.rpartition("}")[2] if isinstance(tag, str) else ""


def check_regular(path: Path) -> None:
    """One line for a SUMO file given as a pipe or a device (``<(cat a.sumocfg)``, a FIFO):
    SUMO reads its files more than once and by name, not as streams."""
    why = not_a_file(path)
    if why is not None and Path(path).exists():
        raise UserError(f"{path}: {why} (SUMO reads files, not streams)")


def root_tag(path: Path, what: str) -> str:
    """The root element of a SUMO XML file (compressed or not), without its namespace;
    one-line errors."""
    path = Path(path)
    if not path.exists():
        raise missing(path, what)
    check_regular(path)
    try:
        with open_xml(path) as fh:
            return local_name(next(ET.iterparse(fh, events=("start",)))[1])
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
    #: the time of the state its ``load-state`` loads: SUMO starts there, whatever the begin
    state_time: float | None = None

    def files(self) -> list[Path]:
        """The network, route and additional files it names."""
        return [self.net, *self.routes, *self.additional]


def naming_the_sumocfg(message: str, sumocfg: Path | None, files: list[Path]) -> str:
    """``message``, when it begins with one of ``files`` (those ``sumocfg`` lists), with the
    sumocfg named after the file: the user sees where the file comes from."""
    if sumocfg is None or str(sumocfg) in message:
        return message
    for path in files:
        if message.startswith(f"{path}:"):
            rest = message[len(str(path)) :]
            missing = any(w in rest for w in ("no such", "does not exist", "is a folder"))
            unset = _unset_variables(sumocfg) if missing else []  # the likely cause
            where = f", where ${{{unset[0]}}} is not set and reads as empty" if unset else ""
            return f"{path} (named in {sumocfg}{where}){rest}"
    return message


def _unset_variables(sumocfg: Path) -> list[str]:
    """The environment variables (``${NAME}``) a SUMO config's file options name that are not
    set."""
    try:
        with open_xml(sumocfg) as fh:
            root = ET.parse(fh).getroot()
    except (ET.ParseError, OSError, EOFError, UserError):
        return []
    files = [elem for elem in root.iter() if canonical(local_name(elem)).endswith("-files")
             or canonical(local_name(elem)) == "net-file"]  # fmt: skip
    values = [v for elem in files for v in (*elem.attrib.values(), elem.text or "")]
    names = {n for v in values for n in _VARIABLE.findall(v)}
    return sorted(n for n in names if n not in os.environ)


def file_list(value: str | None, base: Path, named_in: Path | None = None) -> list[Path]:
    """The files of a comma-separated SUMO option, resolved against ``base`` (``named_in``: the
    config that lists them, named in errors; an empty name among them, which SUMO cannot read
    ("Cannot read file ''"), is refused there in one line)."""
    items = (value or "").split(",")
    if named_in is not None and len(items) > 1 and any(not v.strip() for v in items):
        raise UserError(
            f"{named_in}: the file list {value!r} names an empty file (a comma too many), which "
            "SUMO cannot read; remove the extra comma"
        )
    return [resolved(base / v.strip(), named_in) for v in items if v.strip()]


def _strtod_reads_all(value: str) -> bool:
    """Whether SUMO's number reader (``strtod``, then nothing after it) can read all of
    ``value`` where Python's does: not past "_", a trailing space or a non-ASCII digit
    ("1_0", "10 ", "１０")."""
    return "_" not in value and value == value.rstrip() and value.isascii()


def sumo_number(value: str | None) -> float | None:
    """A number as SUMO's reader takes it (``strtod`` with nothing after it, or C's hexadecimal
    form "0xe10"), finite; None otherwise."""
    if value is None or not _strtod_reads_all(value):
        return None
    try:
        t = float(value)
    except ValueError:
        try:
            t = float.fromhex(value) if _HEX.fullmatch(value.strip()) else math.nan
        except (ValueError, OverflowError):
            t = math.nan
    return t if math.isfinite(t) else None


def parse_time(value: str | None) -> float | None:
    """A SUMO time value: seconds (:func:`sumo_number`: "3600", "3600.5", "0xe10") or a clock
    ("1:00:00", "1:07:00:00"); None if neither (also for NaN and infinite values, which SUMO
    refuses too)."""
    if value is None:
        return None
    value = str(value)
    if not _strtod_reads_all(value):
        return None
    t = sumo_number(value)
    if t is not None:
        return t
    parts = value.strip().split(":")
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


_EXP_PERIOD = re.compile(r"exp\((.+)\)")
_HEX = re.compile(r"[+-]?0[xX][0-9a-fA-F]+(\.[0-9a-fA-F]*)?([pP][+-]?\d+)?")

#: SUMO's words for true and false, in any case (``StringUtils::toBool``).
_TRUE, _FALSE = ("1", "yes", "true", "on", "x", "t"), ("0", "no", "false", "off", "-", "f")


def sumo_bool(value: str | None, default: bool = False) -> bool | None:
    """A SUMO boolean option's value as SUMO reads it (``t``, ``x``, ``on``, ... are true;
    ``f``, ``-``, ``off``, ... false); ``default`` when unset; None when SUMO refuses it."""
    if value is None:
        return default
    word = value.lower()  # (SUMO does not strip spaces off it)
    return True if word in _TRUE else False if word in _FALSE else None


#: Roots of a SUMO simulation config: ``<configuration>``, and ``<sumoConfiguration>`` as
#: ``sumo -C`` (``--save-configuration``) writes it.
SUMOCFG_ROOTS = ("configuration", "sumoConfiguration")


_VARIABLE = re.compile(r"\$\{(.+?)\}")


def substitute_environment(value: str) -> str:
    """An option value as SUMO reads it: ``${NAME}`` replaced by the environment variable
    (empty when unset), ``${PID}`` by the process id, ``${LOCALTIME}``/``${UTC}`` by the
    time, and a leading ``~`` (of the value or of a list item) by ``${HOME}``
    (SUMO's ``StringUtils::substituteEnvironment``)."""
    if "$" not in value and "~" not in value:
        return value
    now = datetime.now(UTC)
    s = value.replace("${LOCALTIME}", now.astimezone().strftime("%Y-%m-%d-%H-%M-%S.%f"), 1)
    s = s.replace("${UTC}", now.strftime("%Y-%m-%d-%H-%M-%S.%f"), 1)
    s = s.replace("${PID}", str(os.getpid()), 1)
    if s.startswith("~"):
        s = "${HOME}" + s[1:]
    s = s.replace(",~", ",${HOME}")
    for name in _VARIABLE.findall(s):
        if name not in os.environ:  # said once per command (twin.notices)
            notify(
                f"twin: notice: a SUMO option names ${{{name}}}, which is not set: SUMO reads it "
                f"as empty; set {name}, or write the value out"
            )
    return _VARIABLE.sub(lambda m: os.environ.get(m.group(1), ""), s)


def sumocfg_options(root: ET.Element, path: Path) -> tuple[dict[str, str], dict[str, str]]:
    """The options the SUMO config ``path`` sets, as SUMO reads them: any element with a
    ``value`` attribute (or its short form ``v``) or, without children, a text, whether in a
    section (``<input><net-file value="..."/></input>``) or right under the root, named by any
    of SUMO's synonyms (:func:`twin.sumo.options.canonical`): canonical name -> value
    (environment variables substituted, :func:`substitute_environment`), and canonical name ->
    the name the config wrote. An empty value is skipped, as SUMO skips it; an option set twice,
    or emptied by an unset variable where SUMO needs a value, is refused, as SUMO refuses it."""
    options: dict[str, str] = {}
    written: dict[str, str] = {}
    for elem in root.iter():
        name = local_name(elem)
        if elem is root or not name:
            continue
        given = [v for v in (elem.get("value"), elem.get("v")) if v]
        if len(elem) == 0 and elem.text is not None and elem.text.strip():
            given.append(elem.text.strip())
        if not given:
            continue
        key, value = canonical(name), given[0]
        if key in options or len(given) > 1:
            twice = (f"<{written[key]}> and <{name}> both set option {key}" if key in options
                     else f"<{name}> sets option {key} twice")  # fmt: skip
            first, second = (options[key], value) if key in options else given[:2]
            raise UserError(
                f"{path}: {twice} ({first!r}, {second!r}), which SUMO refuses ('probably "
                "defined twice'); keep one"
            )
        options[key], written[key] = substitute_environment(value), name
        if not options[key] and _refused_empty(key):
            names = ", ".join(f"${{{n}}}" for n in sorted(set(_VARIABLE.findall(value))))
            raise UserError(
                f"{path}: <{name} value={value!r}> is empty ({names} unset or empty), which SUMO "
                "refuses; set it, or write the value out"
            )
    return options, written


#: Options SUMO refuses as empty (a ``${VAR}`` not set): its file lists but the route files,
#: numbers, times and switches twin reads; outputs are matched by their name.
_NOT_EMPTY = ("net-file", "additional-files", "weight-files", "begin", "end", "step-length",
              "route-steps", "seed", "random", "mesosim", "version")  # fmt: skip


def _refused_empty(key: str) -> bool:
    return key in _NOT_EMPTY or key.endswith("-output")


#: Options that make SUMO write a file (beside the user's files) and quit without simulating.
_SAVE_AND_QUIT = ("save-configuration", "save-template", "save-schema")
#: Switches that make SUMO print something and quit without simulating.
_PRINT_AND_QUIT = ("help", "version")
#: Options that make SUMO wait for a client on a socket before it simulates.
_WAIT_FOR_CLIENT = ("remote-port",)


def read_sumocfg(path: Path, own_net: bool = True) -> SumoConfigFile:
    """Net, route and additional files of a ``.sumocfg`` (relative to its folder, as SUMO reads
    them), its ``<time>`` window, if it gives one, and all its options. Without ``own_net``
    (a network given besides it replaces its own, as with ``sumo -c ... -n``) its
    ``<net-file>`` is not checked."""
    check_regular(path)
    path = resolved(path) if Path(path).exists() else Path(path)
    tag = root_tag(path, "SUMO config")  # SUMO reads a config's options under any root
    with open(path, "rb") as fh:
        compressed = fh.read(2) == b"\x1f\x8b"
    if compressed:  # SUMO reads compressed network, route and additional files, not configs
        raise UserError(
            f"{path}: a gzip-compressed config, which SUMO does not read; decompress it "
            f"(gunzip -k {path.name}), its files may stay compressed"
        )
    try:
        with open_xml(path) as fh:
            root = ET.parse(fh).getroot()
    except (ET.ParseError, OSError, EOFError) as exc:
        raise UserError(f"{path}: not valid XML ({exc})") from exc
    options, written = sumocfg_options(root, path)

    def value(name: str) -> str | None:
        return options.get(name) or None

    net = file_list(value("net-file"), path.parent, path)
    if not own_net:
        net = net[:1] or [Path()]
    if not net:
        if tag not in SUMOCFG_ROOTS:  # a data file given for a config, most likely
            what = tag[: -len("Configuration")] if tag.endswith("Configuration") else f"<{tag}>"
            raise UserError(
                f"{path}: a {what} file that names no network, not a SUMO simulation config; "
                "give a .sumocfg (as `sumo -C` writes) or the network with --net"
            )
        raise UserError(
            f"{path}: names no network; add <net-file value=...> to its <input> (twin needs "
            "the network to lay its grid)"
        )
    for name in _SAVE_AND_QUIT:
        if options.get(name):
            raise UserError(
                f"{path}: <{written[name]} value={options[name]!r}> makes SUMO write that file "
                "and quit instead of simulating; remove it (twin runs the simulation)"
            )
    for name in _WAIT_FOR_CLIENT:  # a port of 0 (SUMO's default) opens no server
        if options.get(name, "").strip() not in ("", "0"):
            raise UserError(
                f"{path}: <{written[name]} value={options[name]!r}> makes SUMO wait for a TraCI "
                "client instead of simulating; remove it (twin drives SUMO itself)"
            )
    for name in _PRINT_AND_QUIT:
        said = sumo_bool(options.get(name))
        if said is None and name == "version":
            raise UserError(
                f"{path}: <{written[name]} value={options[name]!r}> is no boolean SUMO reads; "
                "give true or false"
            )
        if said is not False:  # (help takes a topic too)
            raise UserError(
                f"{path}: <{written[name]} value={options[name]!r}> makes SUMO print its {name} "
                "and quit instead of simulating; remove it"
            )
    if len(set(net)) < len(net):
        raise UserError(
            f"{path}: <{written['net-file']} value={value('net-file')!r}> names a network twice, "
            "which SUMO refuses (each junction would exist twice); name it once"
        )
    if len(net) > 1:
        raise UserError(
            f"{path}: <{written['net-file']} value={value('net-file')!r}> names {len(net)} "
            "networks; "
            "twin lays its grid over one: merge them (netconvert -s a.net.xml,b.net.xml -o "
            "merged.net.xml) and name that"
        )
    window = []
    for key in ("begin", "end"):
        text = value(key)
        t = parse_time(text)
        if text is not None and t is None:
            raise UserError(
                f"{path}: <{written[key]} value={text!r}> is not a finite time SUMO reads; give "
                "seconds (e.g. 3600) or a clock (1:00:00), with no spaces or underscores"
            )
        if key == "end" and t is not None and t < 0:  # SUMO's default -1: no end
            t = None
        if key == "begin" and t is not None and t < 0:
            raise UserError(
                f"{path}: <{written[key]} value={text!r}> is negative, which SUMO refuses; give seconds "
                "from 0 (e.g. 3600) or a clock (1:00:00)"
            )
        window.append(t)
    if None not in window and window[1] <= window[0]:
        raise UserError(
            f"{path}: <{written['end']} value={value('end')!r}> is not after "
            f"<{written['begin']} value={value('begin')!r}>; give an end after the begin"
        )
    states = file_list(value("load-state"), path.parent, path)
    state = saved_state_time(states[0], path) if states else None
    if state is not None and (window[0] is None or window[0] < state):
        window[0] = state  # SUMO's clock starts at the state's time
        if window[1] is not None and window[1] <= state:
            raise UserError(
                f"{path}: <{written['end']} value={value('end')!r}> is not after the time "
                f"{state:g} s of the state its <{written['load-state']}> loads; give a later end"
            )
    return SumoConfigFile(
        net=net[0],
        routes=file_list(value("route-files"), path.parent, path),
        additional=file_list(value("additional-files"), path.parent, path),
        begin=window[0],
        end=window[1],
        options=options,
        path=path,
        state_time=state,
    )


def saved_state_time(path: Path, named_in: Path) -> float:
    """The time of a state SUMO saved (``--save-state.files``): its root's ``time``; a binary
    state (``.sbx``), which twin cannot read, is a one-line error."""
    where = f"{path} (named in {named_in}'s load-state)"
    if path.name.endswith(".sbx"):
        raise UserError(
            f"{where}: a binary saved state, whose time twin cannot read; save the state as XML "
            "(--save-state.suffix .xml) and load that"
        )
    if not path.is_file():
        raise UserError(f"{where}: {'does not exist' if not path.exists() else 'not a file'}")
    try:
        with open_xml(path) as fh:
            root = next(ET.iterparse(fh, events=("start",)))[1]
    except (ET.ParseError, OSError, EOFError, StopIteration) as exc:
        raise UserError(f"{where}: not valid XML ({exc or 'empty file'})") from None
    t = parse_time(root.get("time"))
    if local_name(root) != "snapshot" or t is None or t < 0:
        raise UserError(
            f"{where}: not a state SUMO saved (a <snapshot> with its time); give the file "
            "SUMO's --save-state.files wrote"
        )
    return t


#: Elements that put vehicles on the road, and the attribute of their departure.
_DEPARTING = {
    "vehicle": "depart",
    "trip": "depart",
    "person": "depart",
    "container": "depart",
    "flow": "begin",
    "personFlow": "begin",
    "containerFlow": "begin",
}


def _drives(person: ET.Element) -> bool:
    """Whether a person (or person flow) may travel in a vehicle of its own: a ``<personTrip>``
    whose ``modes`` hold ``car``, ``bicycle`` or ``taxi`` (``randomTrips.py --persontrips``
    with ``modes="car"``)."""
    return any(
        local_name(step) == "personTrip" and _DRIVING_MODES & set(step.get("modes", "").split())
        for step in person
    )


def _check_departure(path: Path, elem: ET.Element, key: str, start: float = 0.0) -> float | None:
    """The departure time of ``elem``: ``start`` (the simulation's begin) for SUMO's word
    "begin", None for its other words such as "triggered" or "now"; a negative, NaN or infinite
    time, which SUMO refuses, is a one-line error naming the file."""
    text = elem.get(key)
    if text is None:
        return None
    if text.strip() == "begin":
        return start
    if text.strip() in _DEPART_WORDS:
        return None
    t = parse_time(text)
    if t is None or t < 0:
        what = "negative" if t is not None else "not a time SUMO reads"
        raise UserError(
            f"{path}: <{local_name(elem)} id={elem.get('id')!r} {key}={text!r}>: the time is {what}, "
            "which SUMO refuses; give seconds from 0 (e.g. 3600) or a clock (1:00:00), with no "
            "spaces after it"
        )
    return t


#: SUMO's departures that are no time: at a person's or container's boarding, at once, split
#: off another vehicle ("begin", the simulation's begin, is read as that time).
_DEPART_WORDS = ("triggered", "containerTriggered", "now", "split")


#: The key of :func:`departure_span`'s ``counts`` that counts departures at the simulation's
#: begin (``start``), wherever SUMO begins.
AT_BEGIN = "at the simulation's begin"

#: :func:`departure_span`'s count of persons (and person flows) whose ``<personTrip>`` may
#: drive (``modes`` with ``car``, ``bicycle`` or ``taxi``): SUMO puts their vehicles on roads.
DRIVING_PERSONS = "persons driving"

#: The departing elements that put vehicles on the roads (persons walk unless they drive,
#: containers wait).
VEHICLE_DEMAND = ("vehicle", "trip", "flow", DRIVING_PERSONS)

#: A ``<personTrip modes>`` that SUMO may route by road in a vehicle: the person's own car or
#: bicycle, or a taxi.
_DRIVING_MODES = frozenset(("car", "bicycle", "taxi"))


def departure_span(
    route_files: list[Path],
    counts: dict[str, int] | None = None,
    start: float = 0.0,
    closed: list[float] | None = None,
    in_order: Collection[Path] = (),
    ignored: list[str] | None = None,
) -> tuple[float, float] | None:
    """First and last numeric departure of the demand (``depart`` of vehicles, trips and persons,
    ``begin`` .. ``end`` of flows, person and container flows, those of their ``<interval>`` or
    ``start``, the simulation's begin, when a flow gives none, as SUMO reads them; the last is
    ``math.inf`` when a flow has no end); None when the files hold no vehicle (e.g. only vTypes).
    ``counts``, when given, gets the number of departing elements of each tag, of those
    departing at ``start`` (:data:`AT_BEGIN`) and of persons who may drive
    (:data:`DRIVING_PERSONS`); ``closed``, when given, the last departure
    that is not an open flow's. Files pulled in with ``<include href>`` count, as SUMO loads
    them. Of the files ``in_order`` (route files SUMO reads step by step, ``--route-steps``), an
    element departing before one listed above it is left out, as SUMO ignores it ("Route file
    should be sorted by departure time"; one departing at "begin" departs when SUMO reads it, a
    public transport vehicle, with a ``line``, sets no order for the next; a file with
    ``<include>``s, which SUMO reads where they stand, is taken whole); ``ignored``, when given,
    gets ``"<file>: '<id>'"`` of each."""
    first = last = None
    counts = {} if counts is None else counts
    read: list[Path] = []
    ordered: set[Path] = set()  # files read in departure order
    for path in route_files:
        included = included_files(Path(path))
        for p in (Path(path), *included):
            if p not in read and (p == Path(path) or p.is_file()):
                read.append(p)
        if Path(path) in in_order and not included:
            ordered.add(Path(path))
    for path in read:
        intervals: list[tuple[float, float | None]] = []  # the <interval>s a flow lies in
        latest = -math.inf if path in ordered else None  # the last departure SUMO took of it
        try:
            with open_xml(path) as fh:
                for event, elem in ET.iterparse(fh, events=("start", "end")):
                    tag = local_name(elem)
                    if tag == "interval":
                        if event == "start":
                            intervals.append(_interval(path, elem, start))
                        else:
                            intervals.pop()
                        continue
                    if event == "start":
                        continue
                    key = _DEPARTING.get(tag)
                    t = _check_departure(path, elem, key, start) if key else None
                    flow = tag.endswith(("flow", "Flow"))  # flow, personFlow, ...
                    if flow and elem.get("begin") is None:  # SUMO: the interval's, else its own
                        t = intervals[-1][0] if intervals else start
                    if latest is not None and t is not None:
                        if (elem.get(key) or "").strip() == "begin":
                            t = max(t, latest)  # departs as SUMO's reader reaches it
                        elif t < latest:  # SUMO ignores it, with a warning
                            if ignored is not None:
                                ignored.append(f"{path}: {elem.get('id') or tag!r}")
                            t = None
                        elif elem.get("line") is None:  # (public transport sets no order)
                            latest = t
                    if (
                        key
                        and t is not None
                        and (
                            (elem.get(key) or "").strip() == "begin"
                            or (flow and elem.get("begin") is None and not intervals)
                        )
                    ):
                        counts[AT_BEGIN] = counts.get(AT_BEGIN, 0) + 1
                    if t is not None:
                        counts[tag] = counts.get(tag, 0) + 1
                        if tag in ("person", "personFlow") and _drives(elem):
                            counts[DRIVING_PERSONS] = counts.get(DRIVING_PERSONS, 0) + 1
                        end = t
                        if flow:
                            end = _flow_end(elem, t, intervals[-1][1] if intervals else None)
                        first = t if first is None else min(first, t)
                        last = end if last is None else max(last, end)
                        if closed is not None and math.isfinite(end):
                            closed[:] = [max([*closed, end])]
                    if tag in _DEPARTING or tag in ("route", "vType"):
                        elem.clear()
        except (ET.ParseError, OSError, EOFError) as exc:
            raise UserError(f"{path}: not valid XML ({exc})") from exc
    return None if first is None else (first, last)


def _interval(path: Path, elem: ET.Element, start: float) -> tuple[float, float | None]:
    """A route file's ``<interval begin end>``: the begin and end of the flows inside it that
    give none (SUMO's defaults for them)."""
    begin = _check_departure(path, elem, "begin", start)
    return (0.0 if begin is None else begin), parse_time(elem.get("end"))


def _flow_end(elem: ET.Element, begin: float, interval_end: float | None = None) -> float:
    """When a flow's departures end: its ``end`` (the last of ``number`` spread over
    ``begin``..``end`` without a period or rate), else its last of ``number`` departures: one at
    ``begin`` and then one every ``period``/``headway`` or at ``vehsPerHour``
    (``personsPerHour``, ``containersPerHour``, ``perHour``); when they are random
    (``probability`` per second, ``period="exp(rate)"``), the time ``number`` of their gaps take
    plus three standard deviations (rarely exceeded); spread over its
    ``<interval>`` without a period (as SUMO 1.28 departs them), no later than its end, else
    that end; never (``math.inf``) for an open flow, which SUMO (1.2x) runs as long as it
    runs."""
    end = parse_time(elem.get("end"))
    number = sumo_number(elem.get("number"))  # None: SUMO will say what is wrong with it
    step = parse_time(elem.get("period")) or parse_time(elem.get("headway"))
    for rate in ("vehsPerHour", "personsPerHour", "containersPerHour", "perHour"):
        per_hour = parse_time(elem.get(rate))
        if step is None and per_hour:
            step = 3600.0 / per_hour
    random_period = _EXP_PERIOD.fullmatch(elem.get("period", "").strip())
    per_second = parse_time(random_period[1] if random_period else elem.get("probability"))
    spread_until = end if end is not None else interval_end  # without a period: spread there
    spread = number is not None and number >= 1 and step is None and per_second is None
    if spread and spread_until is not None:
        return max(begin, begin + (number - 1) * (spread_until - begin) / number)
    if end is not None:
        return end
    gaps = None if number is None else number - 1  # the first departs at begin
    if step is None and per_second is not None and per_second > 0 and number is not None:
        # the first departs after a gap too; the n-th at a mean of n gaps, sd sqrt(n) gaps
        step, gaps = 1.0 / per_second, number + 3.0 * math.sqrt(max(number, 0.0))
    if gaps is not None and step is not None:
        last = begin + max(gaps, 0.0) * step
        return last if interval_end is None else max(begin, min(last, interval_end))
    return math.inf if interval_end is None else max(begin, interval_end)


def may_hold(path: Path, *words: bytes) -> bool:
    """Whether an XML file's bytes may hold one of ``words`` (element names: never character
    references), read once: they do, or its encoding is not ASCII-compatible (UTF-16, UTF-32);
    False for a file that cannot be read."""
    return bool(words_held(path, *words, first=True))


def words_held(path: Path, *words: bytes, first: bool = False) -> set[bytes]:
    """Which of ``words`` an XML file's bytes may hold, read once in 16 MB pieces (up to the
    ``first`` piece holding one, or until each is found): all of them when its encoding is not ASCII-compatible (UTF-16,
    UTF-32); none for a file that cannot be read."""
    tail, keep, found = b"", max(len(w) for w in words), set()
    try:
        with open_xml(path) as fh:
            while chunk := fh.read(1 << 24):
                if not tail and (
                    chunk.startswith((b"\xff\xfe", b"\xfe\xff")) or b"\x00" in chunk[:4]
                ):
                    return set(words)
                found.update(word for word in words if word in tail + chunk)
                if (first and found) or len(found) == len(words):
                    break
                tail = chunk[-keep:]
    except (OSError, EOFError):
        pass
    return found


def include_cycle(path: Path) -> list[Path] | None:
    """The files of an ``<include href>`` chain from ``path`` that comes back to a file on it
    (``a -> b -> a``: SUMO crashes on it without a message), else None."""

    def hrefs(current: Path) -> list[Path]:
        if not may_hold(current, b"include"):  # a large route file is not parsed for nothing
            return []
        try:
            with open_xml(current) as fh:
                root = ET.parse(fh).getroot()
        except (ET.ParseError, OSError, EOFError, UserError):
            return []
        found = [e.get("href") for e in root.iter() if local_name(e) == "include"]
        return [as_given(current.parent / h) for h in found if h]

    done: set[str] = set()  # files whose includes hold no cycle: each searched once
    real = os.path.realpath  # a file's identity (names through links grow around a cycle)

    def walk(chain: list[Path]) -> list[Path] | None:
        on_chain = {real(p) for p in chain}
        for child in dict.fromkeys(hrefs(chain[-1])):
            if real(child) in on_chain:
                return [*chain, child]
            if real(child) not in done and len(chain) < 50 and (cycle := walk([*chain, child])):
                return cycle
        done.add(real(chain[-1]))
        return None

    return walk([as_given(Path(path))])


def included_files(path: Path) -> list[Path]:
    """The files an additional file pulls in with ``<include href="...">`` (relative to the
    including file, as SUMO reads them), and theirs in turn; a file SUMO could not read or a
    cycle ends the search there (SUMO says what is wrong with it)."""
    found: list[Path] = []
    todo, seen = [Path(path)], {os.path.realpath(path)}  # by identity: a link's names grow
    while todo:
        current = todo.pop(0)
        if not may_hold(current, b"include"):  # a large route file is not parsed for nothing
            continue
        try:
            with open_xml(current) as fh:
                root = ET.parse(fh).getroot()
                hrefs = [e.get("href") for e in root.iter() if local_name(e) == "include"]
        except (ET.ParseError, OSError, EOFError, UserError):
            continue
        for href in hrefs:
            if not href:
                continue
            child = as_given(current.parent / href)
            if os.path.realpath(child) not in seen:
                seen.add(os.path.realpath(child))
                found.append(child)
                todo.append(child)
    return found
