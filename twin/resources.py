"""Where twin's shipped files and its per-user cache are: the one place that knows.

Shipped with the package, read through :mod:`importlib.resources`:

- scenario and pretraining configs ``configs/<name>.toml``,
- built-in network specs ``networks/<name>/spec.toml``,
- the pretrained Q-network ``data/qnet.pt``.

In the repository these folders stay at the top (``configs/``, ``networks/``, ``data/``);
``twin/configs``, ``twin/networks`` and ``twin/data`` are symlinks to them. An editable install
reads them through the links; a wheel copies the linked files into ``twin/`` as package data
(``[tool.setuptools.package-data]`` in pyproject.toml), so the same relative paths hold in both,
including a config's ``../data/qnet.pt``.

Everything twin generates (network builds, generated demand, imported OSM networks) goes to the
per-user cache :func:`cache_dir`, never into the installed package or the source tree.
"""

from __future__ import annotations

import contextlib
import os
import re
import shutil
import tempfile
import xml.etree.ElementTree as ET
from collections.abc import Callable
from importlib import resources
from pathlib import Path

from twin.cache_place import CACHE_ENV, CACHE_FOLDERS, cache_dir  # noqa: F401 (where it lies)
from twin.errors import UserError


def package_root() -> Path:
    """The installed ``twin`` package folder (a plain folder: twin is not run from a zip)."""
    root = resources.files("twin")
    if not isinstance(root, Path):  # pragma: no cover - zipped installs are not supported
        raise UserError(f"twin is installed in an archive ({root}); install it with pip")
    return root


def shipped(*parts: str) -> Path:
    """The path of a shipped file, e.g. ``shipped("configs", "synthetic.toml")``."""
    return package_root().joinpath(*parts)


def shipped_config_names() -> list[str]:
    """Names of the shipped configs (``synthetic`` for ``configs/synthetic.toml``)."""
    return sorted(p.stem for p in shipped("configs").glob("*.toml"))


def shipped_config(given: str | Path) -> Path:
    """The config file ``given`` names: a path that exists wins; otherwise a shipped config
    given as ``synthetic``, ``synthetic.toml`` or ``configs/synthetic.toml``."""
    path = Path(given)
    if path.exists():
        return path
    if path.is_symlink():  # a link to nothing, or a loop of links
        raise UserError(f"{given}: a symbolic link to no file or a loop; fix or remove the link")
    candidate = shipped_config_named(path)
    if candidate is not None:
        return candidate
    names = ", ".join(shipped_config_names()) or "none"
    raise UserError(
        f"{given}: config file not found; give the path of a TOML file or a shipped config "
        f"({names})"
    )


def shipped_config_named(given: str | Path) -> Path | None:
    """The shipped config ``given`` names (``synthetic``, ``synthetic.toml`` or
    ``configs/synthetic.toml``), None when it names none."""
    path = Path(given)
    if path.parent in (Path("."), Path("configs")):
        name = path.name if path.suffix == ".toml" else f"{path.name}.toml"
        candidate = shipped("configs", name)
        if candidate.is_file():
            return candidate
    return None


def network_names() -> list[str]:
    """The built-in networks: shipped folders ``networks/<name>/`` holding a ``spec.toml``."""
    return sorted(p.parent.name for p in shipped("networks").glob("*/spec.toml"))


def network_spec(name: str) -> Path:
    """The shipped spec ``networks/<name>/spec.toml`` of a built-in network."""
    known = network_names()
    if name not in known:  # a plain name: never a path out of the networks folder
        raise UserError(
            f"unknown network {name!r}; built-in networks: {', '.join(known) or 'none'}"
        )
    return shipped("networks", name, "spec.toml")


def shipped_checkpoint() -> Path:
    """The shipped, pretrained Q-network ``data/qnet.pt``."""
    return shipped("data", "qnet.pt")


#: How old (days) a scratch entry of a process that was killed (``kill -9``) may grow before a
#: later twin removes it.
SCRATCH_DAYS = 2
#: The scratch folders this process has swept of stale entries.
_SWEPT: set[Path] = set()
#: The start of every scratch entry's name: only such entries are twin's to remove.
SCRATCH_PREFIX = "twin-"
#: Scratch folders that processes share (a local Ray's, :mod:`twin.executors`): never removed
#: whole; each folder in them named ``..._<pid>`` goes once that process has ended, when it
#: holds :data:`HOST_MARK` of this host (a cache may be shared by machines, whose processes
#: this one cannot see), else once it is :data:`SCRATCH_DAYS` old.
SHARED_SCRATCH = ("twin-ray",)
#: The file in a shared scratch entry that says which host (and process namespace) made it.
HOST_MARK = "twin-host"


def host_mark() -> str:
    """This host and process namespace, as :data:`HOST_MARK` records them."""
    import socket

    try:
        space = os.readlink("/proc/self/ns/pid")
    except OSError:
        space = ""
    return f"{socket.gethostname()} {space}".strip()


def _sweep_shared(folder: Path, old: float) -> None:
    """Remove the entries of the shared scratch ``folder`` whose process (the number ending
    their name) has ended (one of this host's) or that are older than ``old`` (another's),
    and links that lead nowhere."""
    import re
    import shutil

    here = host_mark()
    for entry in sorted(folder.iterdir(), key=Path.is_symlink):  # links once their targets
        try:
            if entry.is_symlink():
                if not entry.exists():
                    entry.unlink()
                continue
            pid = re.search(r"_(\d+)$", entry.name)
            if pid is None or not entry.is_dir():
                continue
            mark = entry / HOST_MARK
            mine = mark.is_file() and mark.read_text().strip() == here
            if (mine and not _alive(int(pid[1]))) or (not mine and entry.stat().st_mtime < old):
                shutil.rmtree(entry, ignore_errors=True)
        except OSError:
            continue


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except (PermissionError, OverflowError, ValueError):
        return True
    return True


def scratch_dir() -> Path:
    """twin's scratch folder, ``<cache>/tmp``: the temporary files of a command (SUMO's
    messages, a GUI's frames, the word to stop a parallel run) live there, never in the
    system's temporary folder (twin writes only into its run folder and its cache). Entries a
    killed process left behind are removed after :data:`SCRATCH_DAYS` days: twin's own, named
    :data:`SCRATCH_PREFIX`..., never another file that happens to lie there."""
    import shutil
    import time

    folder = cache_dir() / "tmp"
    if folder in _SWEPT and folder.is_dir():  # once per process (an env makes a scratch file
        return folder  # at every episode)
    check_cache("its scratch files live in its tmp/")
    if folder.is_symlink():  # twin writes only into its run folder and its cache
        raise UserError(
            f"{folder}: twin's scratch folder is a link (to {os.readlink(folder)}), and twin "
            f"writes only into its cache (${CACHE_ENV}), not through a link; remove the link, "
            "twin makes its own tmp/"
        )
    try:
        folder.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        what = "a file" if folder.exists() and not folder.is_dir() else (exc.strerror or exc)
        raise UserError(
            f"{folder}: twin's scratch folder (in its cache, ${CACHE_ENV}) cannot be made "
            f"({what}); move that out of the way, or set ${CACHE_ENV} to another folder"
        ) from None
    if folder in _SWEPT:
        return folder
    _SWEPT.add(folder)
    old = time.time() - SCRATCH_DAYS * 86400
    for entry in folder.iterdir():
        if not entry.name.startswith(SCRATCH_PREFIX):
            continue
        try:
            if entry.name in SHARED_SCRATCH and entry.is_dir() and not entry.is_symlink():
                _sweep_shared(entry, old)
            elif entry.lstat().st_mtime < old:
                if entry.is_dir() and not entry.is_symlink():
                    shutil.rmtree(entry, ignore_errors=True)
                else:
                    entry.unlink()
        except OSError:
            continue
    return folder


def check_cache(why: str) -> Path:
    """Refuse (one line) a cache twin cannot write in (a file in its place, a read-only
    disk) before work that needs it starts; ``why`` says what needs it."""
    from twin.outputs import check_output_dir

    return check_output_dir(
        cache_dir(), f"twin's cache (${CACHE_ENV}; {why})", links_out=True, in_cache=True
    )


#: The most cells a grid may have: 25 million (a 5000 x 5000 grid), whose maps alone need GBs
#: per swarm and step; checked before any array of that size is allocated.
MAX_CELLS = 25_000_000
#: The cell sizes twin accepts (m): a drone's view is a cell, from a street corner to a region.
MIN_CELL_M, MAX_CELL_M = 1.0, 100_000.0


def check_grid_size(nx: int, ny: int, where: str, fix: str) -> None:
    """Refuse (one line) a grid of more than :data:`MAX_CELLS` cells before it is allocated;
    ``where`` names its source, ``fix`` says what to change."""
    cells = int(nx) * int(ny)
    if cells > MAX_CELLS:
        raise UserError(
            f"{where}: a {nx} x {ny} grid has {cells:,} cells, over the {MAX_CELLS:,} twin "
            f"handles (about {cells * 8 / 1e9:,.0f} GB per map and step); {fix}"
        )


def check_cell_size(cell_m: float, where: str) -> None:
    """Refuse (one line) a cell size outside ``MIN_CELL_M .. MAX_CELL_M`` (or not a number)."""
    try:
        value = float(cell_m)
    except (TypeError, ValueError):
        value = float("nan")
    if not (MIN_CELL_M <= value <= MAX_CELL_M):
        raise UserError(
            f"{where}: cell size {cell_m} m is outside {MIN_CELL_M:g} .. {MAX_CELL_M:g} m; give "
            "the side of one drone's view in metres, e.g. 500"
        )


class BrokenEntry(Exception):
    """A cache entry that fails its check (a missing, empty or unparseable file)."""


#: The file in a cache entry that records the sha256 of each of the entry's other files.
SEAL = ".twin-seal.json"


def _entry_files(folder: Path) -> list[Path]:
    return sorted(p for p in folder.rglob("*") if p.is_file() and p.name != SEAL)


#: The comments SUMO's tools put at the head of what they write: the time and the command
#: line, with the temporary folder of the build in it (randomTrips' route file holds two:
#: its own and duarouter's).
_GENERATOR_COMMENT = re.compile(
    rb"\A(<\?xml[^>]*\?>\s*)?(?:<!-- generated on .*?-->\s*)+", re.DOTALL
)


def strip_generator_comments(folder: Path) -> None:
    """Drop the "generated on" comment from the head of each XML file of a build, so that two
    builds of one entry are the same bytes (and a run's recorded sha256 of a cached input still
    holds after the cache is rebuilt)."""
    for path in _entry_files(folder):
        if not path.name.endswith(".xml"):
            continue
        data = path.read_bytes()
        stripped = _GENERATOR_COMMENT.sub(rb"\1", data, count=1)
        if stripped != data:
            path.write_bytes(stripped)


def write_seal(folder: Path) -> None:
    """Record the sha256 of every file of a built cache entry (before it is committed)."""
    import json

    from twin.files import file_sha256

    sums = {p.relative_to(folder).as_posix(): file_sha256(p) for p in _entry_files(folder)}
    (folder / SEAL).write_text(json.dumps(sums, indent=1))


def check_seal(folder: Path) -> None:
    """Raise :class:`BrokenEntry` when a file the entry's seal lists is gone or changed (or the
    entry has no seal: it was not committed by this version of twin)."""
    import json

    from twin.files import file_sha256, read_record

    try:
        sums = json.loads(read_record(folder / SEAL))
    except (OSError, ValueError) as exc:
        raise BrokenEntry(
            f"{SEAL}, the record of its files, is missing (an earlier twin built it) or damaged"
        ) from exc
    if not isinstance(sums, dict) or not sums:
        raise BrokenEntry(f"{SEAL}, the record of its files, is damaged")
    for name, digest in sums.items():
        path = folder / str(name)
        if not path.is_file() or file_sha256(path) != digest:
            raise BrokenEntry(f"{name} changed since it was built")


def build_once(
    target: Path,
    make: Callable[[Path], None],
    force: bool = False,
    verify: Callable[[Path], None] | None = None,
) -> Path:
    """The folder ``target``, made by ``make(folder)`` unless it exists already.

    ``make`` fills a fresh temporary folder beside ``target`` that is then renamed into place
    in one step, so a reader never sees a half-built folder and two processes building the same
    ``target`` at once both end up with one complete copy (the loser's is deleted). ``force``
    replaces an existing ``target``.

    ``verify(folder)`` raises :class:`BrokenEntry` (or OSError) when an entry is not usable (a
    file missing, empty or unparseable): a new build is checked before it is renamed in (a
    broken build is a one-line :class:`UserError`); an existing entry that fails the check
    (deleted or damaged files) is reported in one line on stderr and rebuilt. A committed entry
    holds the sha256 of each of its files (:data:`SEAL`): an entry whose files changed since,
    even into other well-formed files, is rebuilt the same way. An entry without a seal (built
    by an earlier twin, or its seal removed) is built again beside it and kept, then sealed, only
    when its files are those of the new build (SUMO's "generated on" comments aside), so runs
    recorded on an earlier twin's entry still replay; otherwise it is reported and replaced.
    """
    unsealed = False
    if target.is_dir() and not force:
        try:
            if verify is not None:
                verify(target)
            if (target / SEAL).exists():
                check_seal(target)
                return target
            unsealed = True
        except (BrokenEntry, OSError) as exc:
            from twin.notices import notify

            notify(f"twin: notice: cache entry {target} is broken ({_reason(exc)}); rebuilding it")
            force = True
    from twin.outputs import check_output_dir

    if target.exists() and not target.is_dir():  # a file where the entry's folder belongs
        from twin.notices import notify

        notify(f"twin: notice: cache entry {target} is a file, not a folder; rebuilding it")
        target.unlink()
    check_output_dir(
        target.parent, f"the cache (${CACHE_ENV} moves it)", links_out=True, in_cache=True
    )
    target.parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=f".{target.name}.tmp-", dir=target.parent))
    try:
        make(tmp)
        if verify is not None:
            try:
                verify(tmp)
            except (BrokenEntry, OSError) as exc:
                raise UserError(
                    f"{target}: the build produced a broken entry ({_reason(exc)}); nothing "
                    "was cached, see the message of the tool above or report it"
                ) from None
        strip_generator_comments(tmp)
        if unsealed:
            differs = _differing_file(target, tmp)
            if differs is None:  # an earlier twin's entry, as this one builds it: kept
                write_seal(target)
                return target
            from twin.notices import notify

            notify(
                f"twin: notice: cache entry {target} has no {SEAL} (the record of its files) "
                f"and {differs} differs from a fresh build; replacing it"
            )
            force = True
        write_seal(tmp)
        if force and target.is_dir():
            old = Path(tempfile.mkdtemp(prefix=f".{target.name}.old-", dir=target.parent))
            with contextlib.suppress(FileNotFoundError):  # removed meanwhile
                target.rename(old / "x")
            shutil.rmtree(old, ignore_errors=True)
        try:
            tmp.rename(target)
        except OSError:
            if not target.is_dir():
                raise
            # another process finished the same build first: use its copy
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    return target


def _differing_file(entry: Path, build: Path) -> str | None:
    """The first file (relative name) in which ``entry`` and a fresh ``build`` of it differ,
    SUMO's "generated on" comments aside; None when they hold the same files."""
    names = {p.relative_to(entry).as_posix() for p in _entry_files(entry)}
    built = {p.relative_to(build).as_posix() for p in _entry_files(build)}
    extra = sorted(names ^ built)
    if extra:
        return extra[0]
    for name in sorted(names):
        data = (entry / name).read_bytes()
        if name.endswith(".xml"):
            data = _GENERATOR_COMMENT.sub(rb"\1", data, count=1)
        if data != (build / name).read_bytes():
            return name
    return None


def _reason(exc: BaseException) -> str:
    if isinstance(exc, OSError) and exc.strerror:
        return f"{exc.filename or ''}: {exc.strerror}".lstrip(": ")
    return str(exc) or type(exc).__name__


def check_xml_files(folder: Path, files: dict[str, str]) -> None:
    """:class:`BrokenEntry` unless each ``files`` name (relative to ``folder``) is present,
    non-empty and a whole XML document with the given root element (checked by its first
    element and its closing tag, without parsing it all)."""
    for name, root in files.items():
        path = Path(folder) / name
        if not path.is_file():
            raise BrokenEntry(f"{name} is missing")
        size = path.stat().st_size
        if size == 0:
            raise BrokenEntry(f"{name} is empty")
        with open(path, "rb") as fh:
            try:
                start = next(ET.iterparse(fh, events=("start",)))[1].tag
            except (ET.ParseError, StopIteration):
                start = None
            fh.seek(max(0, size - 256))
            tail = fh.read()
        if start != root:
            raise BrokenEntry(f"{name} is not a SUMO <{root}> file")
        end = rb"(</%s>|<%s\b[^<>]*/>)" % (root.encode(), root.encode())
        # comments and instructions may follow it (each matched one way: no backtracking)
        after = rb"(?:\s|<!--(?:(?!-->).)*-->|<\?(?:(?!\?>).)*\?>)*$"
        closed = re.search(end + after, tail, re.DOTALL)
        if closed is None:
            raise BrokenEntry(f"{name} is cut short (no closing </{root}>)")
