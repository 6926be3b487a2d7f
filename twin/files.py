"""Writing files so that a kill at any instant leaves the old file or the new one, never half.

One helper for every writer of twin (run folders, sweep cells, checkpoints, caches).
"""

from __future__ import annotations

import contextlib
import errno
import hashlib
import json
import os
import shutil
import stat
import tempfile
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import numpy as np


def not_a_file(path: str | Path) -> str | None:
    """Why ``path`` cannot be read as a file twin seeks in (an ``.npz``, a parquet tape, a
    checkpoint), or None when it can: it does not exist, is a folder, or is a pipe or device
    (``<(...)``, a FIFO), which cannot be read twice or out of order."""
    path = Path(path)
    if path.is_file():
        return None
    if path.is_dir():
        return "is a folder, not a file"
    if path.exists():
        return "is a pipe or device, not a regular file; give the file itself"
    return "does not exist"


#: The largest record of twin's own folders read whole (a run's JSON files, a sweep's cell
#: records, a training log): a city-scale run's manifest is well under 1 MB.
MAX_RECORD_BYTES = 256 << 20


class NotARecord(OSError):
    """A record twin reads whole is a pipe, a device or a folder, or larger than any twin
    writes (``/dev/zero`` would fill the memory)."""


def read_record(path: str | Path, limit: int = MAX_RECORD_BYTES) -> str:
    """The UTF-8 text of a file twin wrote and reads whole (a run folder's JSON, a sweep's
    records); :class:`NotARecord` when it is no regular file (a FIFO would block forever) or
    larger than ``limit``."""
    path = Path(path)
    why = not_a_file(path)
    if why is None and path.stat().st_size > limit:
        why = f"is {path.stat().st_size:,} bytes, more than any record twin writes"
    if why is not None:
        raise NotARecord(errno.EINVAL, why, str(path))
    return path.read_text(encoding="utf-8")


def atomic_write(path: str | Path, write: Callable[[Path], None]) -> None:
    """Call ``write(tmp)`` on a fresh temporary file beside ``path``, flush it to disk, then
    rename it to ``path``. The file gets the usual permissions (``0666`` less the umask), not
    the ``0600`` of a temporary file; the temporary name is unique, so concurrent writers of
    one path never share it."""
    path = Path(path)
    try:
        fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp")
    except OSError as exc:  # name the file being written, not a temporary name
        exc.filename = str(path)
        raise
    os.close(fd)
    try:
        write(Path(tmp))
        with open(tmp, "rb") as fh:
            os.fsync(fh.fileno())
        os.chmod(tmp, 0o666 & ~_umask())
        os.replace(tmp, path)
    except OSError as exc:
        Path(tmp).unlink(missing_ok=True)
        if exc.filename is None or exc.filename == tmp:  # name the file being written
            exc.filename = str(path)
        raise
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise


@contextlib.contextmanager
def staged_folder(path: str | Path, written: Callable[[str], bool]) -> Iterator[Path]:
    """A fresh temporary folder beside ``path`` to draw a whole folder in (a report); when the
    block ends without error it replaces ``path`` (the old folder is moved aside, then
    deleted), else it is deleted: a failure mid-way (a full disk ...) leaves the previous
    folder, or none, never a partial one. A system error names the file under ``path``, not
    under its temporary copy.

    The folder lists what it holds (:data:`STAGED_LISTING`); an old folder holding anything
    else (a user's notes) is refused before any work, in one line, rather than deleted with
    it. An old folder without that listing (an earlier twin's) may hold the names
    ``written`` accepts."""
    path = Path(path)
    check_staged_folder(path, written)
    try:
        stage = Path(tempfile.mkdtemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp"))
    except OSError as exc:  # name the folder being written, not a temporary name
        exc.filename = str(path)
        raise
    old = None
    try:
        os.chmod(stage, 0o777 & ~_umask())
        yield stage
        names = sorted(p.name for p in stage.iterdir())
        (stage / STAGED_LISTING).write_text("".join(f"{name}\n" for name in names))
        if path.is_dir():
            old = Path(
                tempfile.mkdtemp(dir=path.parent, prefix=f".{path.name}.", suffix=".old.tmp")
            )
            os.replace(path, old / path.name)
        os.replace(stage, path)
    except OSError as exc:
        shutil.rmtree(stage, ignore_errors=True)
        name = str(exc.filename) if exc.filename is not None else str(path)
        exc.filename = name.replace(str(stage), str(path))
        raise
    except BaseException:
        shutil.rmtree(stage, ignore_errors=True)
        raise
    finally:
        if old is not None:
            shutil.rmtree(old, ignore_errors=True)


#: The list of the names a staged folder holds, one per line, written into it.
STAGED_LISTING = ".twin-files"


def check_staged_folder(path: Path, written: Callable[[str], bool]) -> None:
    """Refuse (:class:`UserError`, one line) a folder ``path`` that :func:`staged_folder` would
    replace while it holds what twin did not write there."""
    from twin.errors import UserError

    if not path.is_dir() or path.is_symlink():
        return
    listed = None  # none, or no file (a pipe would block): an earlier twin's folder
    if not_a_file(path / STAGED_LISTING) is None:
        with contextlib.suppress(OSError, UnicodeDecodeError):
            listed = set((path / STAGED_LISTING).read_text(encoding="utf-8").splitlines())
    for entry in sorted(path.iterdir()):
        name = entry.name
        if name == STAGED_LISTING or (name in listed if listed is not None else written(name)):
            continue
        raise UserError(
            f"{entry}: not written by twin; move it out of {path}, which this command "
            "replaces whole"
        )


def _umask() -> int:
    mask = os.umask(0)
    os.umask(mask)
    return mask


def write_json(path: str | Path, data: Any) -> None:
    """JSON (numpy scalars and arrays, paths as plain values), written atomically."""
    text = json.dumps(data, indent=2, default=jsonable) + "\n"
    atomic_write(path, lambda p: p.write_text(text))


def nan_as_null(data: Any) -> Any:
    """``data`` with every float that is not finite (an R^2 of samples in one density bin)
    as None: strict JSON (``null``), which every reader takes, not the ``NaN`` token."""
    if isinstance(data, dict):
        return {k: nan_as_null(v) for k, v in data.items()}
    if isinstance(data, (list, tuple)):
        return [nan_as_null(v) for v in data]
    if isinstance(data, (float, np.floating)) and not np.isfinite(data):
        return None
    return data


def jsonable(value: Any) -> Any:
    if isinstance(value, np.generic):
        return value.item()
    if isinstance(value, np.ndarray):
        return value.tolist()
    if isinstance(value, Path):
        return str(value)
    raise TypeError(f"not JSON serialisable: {type(value).__name__}")


_HASHES: dict[tuple[str, int, int], str] = {}


def rebased(value: Any, old: str | Path, new: str | Path) -> Any:
    """``value`` (JSON data) with every path in the folder ``old`` (a string, or a key) given
    in ``new`` instead: a record of a folder that moved, read as of its new place."""
    old, new = str(old), str(new)
    if old == new:
        return value
    if isinstance(value, dict):
        return {rebased(k, old, new): rebased(v, old, new) for k, v in value.items()}
    if isinstance(value, list):
        return [rebased(v, old, new) for v in value]
    if isinstance(value, str) and value.startswith(f"{old}/"):
        return f"{new}/{value.removeprefix(f'{old}/')}"
    return value


def file_sha256(path: str | Path) -> str:
    """The sha256 of a file, read in blocks; remembered per path, size and modification time
    (a run's seeds hash each input once). A pipe or device (``/dev/zero``, a FIFO named in a
    forged record) is an OSError, never a read that does not end."""
    st = os.stat(path)
    if not stat.S_ISREG(st.st_mode):
        raise OSError(errno.EINVAL, "not a regular file (a pipe, device or folder)", str(path))
    key = (os.path.realpath(path), st.st_size, st.st_mtime_ns)  # the file itself, not its name
    if key not in _HASHES:
        h = hashlib.sha256()
        with open(path, "rb") as fh:
            for block in iter(lambda: fh.read(1 << 20), b""):
                h.update(block)
        _HASHES[key] = h.hexdigest()
    return _HASHES[key]
