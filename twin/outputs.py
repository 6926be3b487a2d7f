"""Output paths checked before any work starts: ``--out`` folders, ``--record`` files, the cache.

Each check refuses, in one line naming the flag and the path, a file in the way of a folder (or
a folder in the way of a file), a parent that cannot be created, a place twin may not write
into, and a disk with less free space than the output is estimated to need (on a file system
that reports no size, such as ``/proc``, a folder made and removed at once tells instead whether
it takes files). Nothing existing is touched.
"""

from __future__ import annotations

import os
import shutil
from collections.abc import Callable
from pathlib import Path

from twin.errors import UserError

#: Free space a run folder needs at least (MB) when no estimate is given.
MIN_FREE_MB = 50


def _existing_ancestor(path: Path) -> Path:
    """The nearest existing folder at or above ``path`` (a file in the way is refused)."""
    probe = path
    while not probe.exists():
        if probe.is_symlink():  # a dangling link: its target is missing
            raise UserError(f"{path}: {probe} is a link to nothing; remove it or use another path")
        parent = probe.parent
        if parent == probe:
            break
        probe = parent
    return probe


def check_output_dir(
    path: str | Path,
    flag: str = "--out",
    need_mb: float = MIN_FREE_MB,
    links_out: bool = False,
    owner: Callable[[Path], None] | None = None,
    in_cache: bool = False,
) -> Path:
    """Refuse an output folder ``path`` twin cannot create or write into (one line naming
    ``flag``), one inside twin's cache (unless ``in_cache``: the cache's own), or one holding a
    symbolic link out of it unless ``links_out`` (the cache's entries may live on another disk;
    a command that writes one new file). ``owner``, the command's own check of what an
    existing folder holds, runs before its tree is walked (a user's project folder is refused
    as not the command's, not for a link in it). It need not exist yet (nothing is created
    here but, on a file system that reports no size, a probe folder removed at once)."""
    path = Path(path)
    _check_name(path, flag)
    if path.exists() and not path.is_dir():
        raise UserError(
            f"{flag} {path}: is a file, not a folder (a file is in the way); move it or pass "
            "another folder"
        )
    base = _existing_ancestor(path)
    if not base.is_dir():
        raise UserError(
            f"{flag} {path}: {base} is a file, not a folder; move it or pass another folder"
        )
    _check_writable(base, path, flag)
    _check_free(base, path, flag, need_mb)
    if not in_cache:
        _check_not_in_cache(path, flag)
    if path.is_dir() and owner is not None:
        owner(path)
    if path.is_dir() and not links_out:
        _check_no_link_out(path, flag)
    return path


def _check_not_in_cache(path: Path, flag: str) -> None:
    """Refuse an output folder that is twin's cache or lies in one of the folders twin keeps
    there (:data:`twin.resources.CACHE_FOLDERS`): the cache rebuilds (deletes) an entry it
    finds damaged, with whatever a user put in it; or one that holds the cache (a
    ``$TWIN_CACHE_DIR`` inside a new ``--out``: twin filled it, then refused it as not new).
    A work folder beside them in a cache that is a whole scratch disk
    (``$TWIN_CACHE_DIR=$SCRATCH``) is the user's."""
    from twin.cache_place import CACHE_FOLDERS, cache_dir

    try:
        cache = cache_dir().resolve()
    except UserError:  # a bad $TWIN_CACHE_DIR is refused by the commands that use it
        return
    try:
        target = path.resolve()
    except (OSError, RuntimeError):  # a link loop: refused when the folder is made
        return
    if target == cache or any(target.is_relative_to(cache / f) for f in CACHE_FOLDERS):
        raise UserError(
            f"{flag} {path}: lies in twin's cache ({cache}), whose entries twin deletes and "
            "rebuilds; pass a folder outside it"
        )
    if cache.is_relative_to(target):  # a run folder holding the cache is neither new nor a run
        raise UserError(
            f"{flag} {path}: holds twin's cache ({cache}); put the cache elsewhere "
            "($TWIN_CACHE_DIR) or pass a folder outside it"
        )


def _resolves_inside(link: Path, root: Path) -> bool:
    """Whether the symbolic link ``link`` leads inside ``root`` (one that cannot be followed,
    a loop or a target twin may not read, does not)."""
    try:
        return link.resolve().is_relative_to(root)
    except (OSError, RuntimeError):
        return False


def _check_no_link_out(path: Path, flag: str) -> None:
    """Refuse an existing output folder holding a symbolic link that leads out of it (a
    ``cells`` or ``rows`` link to elsewhere), or a file with another name (a hard link, which
    may lie anywhere on the disk): twin would write through it, outside the folder. twin makes
    no links; a symbolic link that stays inside the folder is harmless."""
    root = path.resolve()
    for folder, dirs, files in os.walk(path):  # links to folders are listed, never entered
        for name in (*dirs, *files):
            entry = Path(folder, name)
            if entry.is_symlink() and not _resolves_inside(entry, root):
                raise UserError(
                    f"{flag} {path}: {entry} is a symbolic link out of the folder (to "
                    f"{os.readlink(entry)}); twin writes only inside its output folder: remove "
                    "the link or pass another folder"
                )
            if name in files and not entry.is_symlink() and entry.stat().st_nlink > 1:
                raise UserError(
                    f"{flag} {path}: {entry} has another name (a hard link, maybe outside the "
                    "folder), which twin would write through; twin writes only inside its "
                    "output folder: replace it by a copy (cp --remove-destination) or pass "
                    "another folder"
                )


def check_output_file(path: str | Path, flag: str, need_mb: float = 1) -> Path:
    """Refuse an output file ``path`` twin cannot write (one line naming ``flag``): a folder
    in its place, a parent that is a file or cannot be created, no write permission, no space."""
    path = Path(path)
    _check_name(path, flag, deeper=64)
    if path.is_dir():
        raise UserError(f"{flag} {path}: is a folder; give a file name")
    if path.exists() and not os.access(path, os.W_OK):
        raise UserError(
            f"{flag} {path}: the file exists and may not be written; change its permissions "
            "or give another file name"
        )
    base = _existing_ancestor(path.parent)
    if not base.is_dir():
        raise UserError(
            f"{flag} {path}: {base} is a file, not a folder; move it or give another file name"
        )
    _check_writable(base, path, flag)
    _check_free(base, path, flag, need_mb)
    return path


def make_parent(path: str | Path, flag: str) -> Path:
    """Create the missing folders above the output file ``path`` (:func:`check_output_file`
    accepted them as folders that can be created); a failure is one line naming ``flag``."""
    path = Path(path)
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise UserError(
            f"{flag} {path}: cannot create the folder {path.parent} ({exc.strerror}); create "
            "it or give another file name"
        ) from None
    return path


#: The longest path the file system takes (bytes; Linux's PATH_MAX), and the longest name of
#: one folder or file in it (NAME_MAX).
PATH_MAX, NAME_MAX = 4096, 255
#: How much deeper than its output folder twin writes (bytes): ``sumo/seed-<s>/`` and an
#: output's own name, with the suffix of a file being written (:func:`twin.files.atomic_write`).
DEPTH_WRITTEN = 300


def _check_name(path: Path, flag: str, deeper: int = DEPTH_WRITTEN) -> None:
    """Refuse a path that is not valid UTF-8 text (bytes the file system took but twin could
    not write into its JSON and reports, nor print), or too long for the files twin writes
    ``deeper`` bytes below it (or one of its names past :data:`NAME_MAX`)."""
    try:
        str(path).encode("utf-8")
    except UnicodeEncodeError:
        shown = str(path).encode("utf-8", "surrogateescape").decode("utf-8", "backslashreplace")
        raise UserError(
            f"{flag} {shown}: the name is not valid UTF-8; use a name in UTF-8 (e.g. plain "
            "letters, digits, - and _)"
        ) from None
    long_names = [p for p in path.parts if len(p.encode()) > NAME_MAX]
    if long_names:
        raise UserError(
            f"{flag} {path}: a name in it is {len(long_names[0].encode())} bytes long, past the "
            f"{NAME_MAX} the file system takes; pass a shorter path"
        )
    size = len(str(path.absolute()).encode())
    if size + deeper > PATH_MAX:
        raise UserError(
            f"{flag} {path}: the path is {size} bytes long, and twin writes files up to "
            f"{deeper} bytes below it, past the {PATH_MAX} the file system takes; pass a "
            "shorter path"
        )


def _check_writable(base: Path, path: Path, flag: str) -> None:
    if _read_only(base):
        raise UserError(
            f"{flag} {path}: {base} is on a read-only file system; pass a folder you can write to"
        )
    if not os.access(base, os.W_OK | os.X_OK):
        raise UserError(
            f"{flag} {path}: the folder {base} may not be written by you; change its "
            "permissions or pass a folder you can write to"
        )


def _read_only(base: Path) -> bool:
    try:
        return bool(os.statvfs(base).f_flag & os.ST_RDONLY)
    except (OSError, AttributeError):
        return False


def _check_free(base: Path, path: Path, flag: str, need_mb: float) -> None:
    try:
        stats = os.statvfs(base)
        free_mb = shutil.disk_usage(base).free / 1e6
    except (OSError, AttributeError):
        return
    if stats.f_blocks == 0:  # a file system that reports no size (/proc, /sys, some mounts)
        _check_takes_files(base, path, flag)
        return
    if free_mb < need_mb:
        raise UserError(
            f"{flag} {path}: only {free_mb:,.0f} MB free on its disk, about {need_mb:,.0f} MB "
            "needed; free some space or write to another disk"
        )


def _check_takes_files(base: Path, path: Path, flag: str) -> None:
    """On a file system that reports no size, the free-space estimate means nothing: try
    making (and at once removing) a folder in ``base`` instead, and refuse one that takes none
    (``/proc``, ``/sys``)."""
    import tempfile

    try:
        os.rmdir(tempfile.mkdtemp(dir=base, prefix=".twin-probe-"))
    except OSError as exc:
        raise UserError(
            f"{flag} {path}: {base} is on a special file system (it reports no size) that "
            f"takes no new files ({exc.strerror}); pass a folder on a disk"
        ) from None
