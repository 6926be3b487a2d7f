"""The one boundary between twin and its user: whatever escapes a command ends here.

:func:`run_command` calls a subcommand and turns every exception that escapes it into ONE line
on stderr and an exit code (:data:`EXIT_CODES`); the full traceback of an unexpected error goes
to ``error.log`` in the command's folder (:func:`set_run_folder`: the run folder, the sweep or
pretraining folder, the folder ``twin report`` renders) or, before there is one, in twin's
cache, and the line names that file.

Exit codes of every ``twin`` command:

- 0: done;
- 1: done, but the run is partial (the traffic ended early, a swarm failed; the files say so)
  or, with ``--record``, the results are written but the video could not be (a warning);
- 2: refused: bad input, a file or folder twin cannot read or write (twin's own
  :class:`~twin.errors.UserError`, and system errors such as a full disk or a read-only
  folder), a missing optional package, the command line itself (argparse);
- 3: an unexpected error in twin (a bug): the line names the log with the traceback;
- 130: interrupted (Ctrl-C); files already written are complete;
- 141: the output went into a pipe whose reader stopped (``twin ... | head``).
"""

from __future__ import annotations

import contextlib
import errno
import os
import signal
import sys
import threading
import traceback
import warnings
from collections.abc import Callable, Iterator
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

from twin.errors import UserError
from twin.notices import (  # noqa: F401 (the notices are part of the boundary's interface)
    count_said,
    drop_notices,
    hold_notices,
    notify,
    release_notices,
)
from twin.processes import interrupt_on_terminate

EXIT_OK, EXIT_PARTIAL, EXIT_REFUSED, EXIT_BUG = 0, 1, 2, 3
EXIT_INTERRUPTED, EXIT_PIPE = 130, 141
EXIT_CODES = {
    EXIT_OK: "done",
    EXIT_PARTIAL: "partial run, or results written but the --record video failed",
    EXIT_REFUSED: "refused: bad input or a file twin cannot read or write",
    EXIT_BUG: "unexpected error in twin (traceback in error.log)",
    EXIT_INTERRUPTED: "interrupted",
    EXIT_PIPE: "output pipe closed",
}
LOG_NAME = "error.log"
#: the longest message printed (a huge value quoted in an exception stays on one screen line)
MAX_MESSAGE = 600

_state: dict[str, Any] = {"run_folder": None, "locks": {}, "argv": None}


def set_command_line(argv: list[str] | None) -> None:
    """The arguments of the command being run (``twin.cli.main(argv)``; None: the process's
    own, ``sys.argv[1:]``)."""
    _state["argv"] = None if argv is None else [str(a) for a in argv]


def command_line() -> str:
    """``twin <arguments>`` of the command being run, as a shell would take it back."""
    import shlex

    argv = _state["argv"] if _state["argv"] is not None else sys.argv[1:]
    return shlex.join(["twin", *argv])


def set_run_folder(path: Path | None) -> None:
    """The folder the current command owns and writes into (None: none yet, and every folder
    :func:`claim_run_folder` locked is released); an unexpected error's traceback goes to its
    ``error.log``."""
    _state["run_folder"] = None if path is None else Path(path)
    if path is None:
        _release_lock()


def claim_run_folder(path: Path, flag: str = "--out", another: str | None = None) -> None:
    """Lock the existing folder ``path`` for the current command (an exclusive ``flock`` on
    the folder itself, held until the command ends, its process exits, or the block of
    :func:`folder_claimed` ends): a second command writing into the same folder at once is
    refused in one line instead of mixing its files with the first's. Claiming a folder
    already held does nothing; a command may hold several (a transfer's folder and its
    sweep's). A file system without ``flock`` (some network disks) locks nothing. ``another``:
    how to give another folder (default: pass another ``flag``)."""
    import fcntl

    path = Path(path)
    if path.resolve() in _state["locks"]:
        return
    fd = os.open(path, os.O_RDONLY | os.O_DIRECTORY)
    try:
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except BlockingIOError:
        os.close(fd)
        raise UserError(
            f"{flag} {path}: another twin command is writing into this folder now; wait for it "
            f"to end or {another or f'pass another {flag}'}"
        ) from None
    except OSError:  # no flock on this file system: nothing to hold
        os.close(fd)
        return
    _state["locks"][path.resolve()] = fd


def written_by_another(path: Path) -> bool:
    """Whether another twin command holds ``path`` (:func:`claim_run_folder`) now: it is
    writing into it."""
    import fcntl

    if Path(path).resolve() in _state["locks"]:
        return False  # this command's own
    try:
        fd = os.open(path, os.O_RDONLY | os.O_DIRECTORY)
    except OSError:
        return False
    try:
        fcntl.flock(fd, fcntl.LOCK_SH | fcntl.LOCK_NB)
    except BlockingIOError:
        return True
    except OSError:
        return False
    finally:
        os.close(fd)
    return False


@contextlib.contextmanager
def folder_claimed(path: Path, flag: str = "--out") -> Iterator[None]:
    """:func:`claim_run_folder` for the block, released after it unless it was held before
    (a command's own folder stays held until the command ends): a function of the Python API
    (a sweep, a transfer) holds its folder only while it writes there."""
    key = Path(path).resolve()
    before = key in _state["locks"]
    claim_run_folder(path, flag)
    try:
        yield
    finally:
        if not before:
            fd = _state["locks"].pop(key, None)
            if fd is not None:
                with contextlib.suppress(OSError):
                    os.close(fd)


def claim_new_folder(path: Path, flag: str = "--out", another: str | None = None) -> bool:
    """Create the output folder ``path`` if need be and lock it (:func:`claim_run_folder`):
    a command whose other checks passed, before it reads or writes anything there. Whether
    this made the folder."""
    path = Path(path)
    made = not path.exists()
    try:
        path.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise UserError(f"{flag} {path}: cannot create the folder ({exc.strerror})") from None
    claim_run_folder(path, flag, another)
    return made


def _release_lock() -> None:
    """Release every folder this command locked."""
    held, _state["locks"] = _state["locks"], {}
    for fd in held.values():
        with contextlib.suppress(OSError):
            os.close(fd)


def run_folder() -> Path | None:
    return _state["run_folder"]


def one_line(text: str) -> str:
    """``text`` on one line (newlines and runs of blanks collapsed), at most
    :data:`MAX_MESSAGE` characters (long paths, then the line, cut in the middle: the reason and
    the fix stay), and printable whatever the terminal's encoding."""
    flat = " ".join(str(text).split())
    if len(flat) > MAX_MESSAGE:  # long words (paths) shortened in the middle first
        flat = " ".join(w if len(w) <= 120 else f"{w[:40]}...{w[-60:]}" for w in flat.split(" "))
    if len(flat) > MAX_MESSAGE:  # then the middle of the line: its end says the fix
        half = (MAX_MESSAGE - 5) // 2
        flat = f"{flat[:half]} ... {flat[-half:]}"
    encoding = getattr(sys.stderr, "encoding", None) or "utf-8"
    return flat.encode(encoding, "backslashreplace").decode(encoding, "replace")


def say(message: str) -> None:
    """Print ``twin: <message>`` as one line on stderr (never raising)."""
    with contextlib.suppress(Exception):
        print(f"twin: {one_line(message)}", file=sys.stderr, flush=True)


#: errno -> what to do about it, for the one-line message of a system error
_FIXES = {
    errno.ENOSPC: "free some space on that disk or write to another disk (--out)",
    errno.EDQUOT: "free some space on that disk or write to another disk (--out)",
    errno.EROFS: "the file system is read-only: write to another folder (--out)",
    errno.EACCES: "you may not write or read there: change the permissions or use another folder",
    errno.EPERM: "you may not write or read there: change the permissions or use another folder",
    errno.ENOENT: "a file or folder is missing: check the path",
    errno.ENOTDIR: "a file stands where a folder is expected: move it or use another path",
    errno.EISDIR: "a folder stands where a file is expected: move it or use another path",
    errno.ENAMETOOLONG: "use a shorter name",
    errno.ELOOP: "a symbolic link points to itself (a loop): fix or remove the link",
    errno.EMFILE: "too many open files: raise the limit (ulimit -n)",
    errno.ENOMEM: "out of memory: use a smaller grid, horizon or fewer seeds",
    errno.EIO: "the disk reported an input/output error: check it",
}


#: the fixes above for a command without ``--out`` (``twin report`` writes into its run folder)
_FIXES_WITHOUT_OUT = {
    errno.ENOSPC: "free some space on that disk",
    errno.EDQUOT: "free some space on that disk (or raise your quota)",
    errno.EROFS: "the file system is read-only: copy the folder to a writable disk",
}


def describe_os_error(exc: OSError, has_out: bool = True) -> str:
    """One line for a system error: the file, what happened and the fix (``--out`` named only
    when the command has that flag: ``has_out``)."""
    name = exc.filename if exc.filename is not None else ""
    if isinstance(name, bytes):
        name = name.decode("utf-8", "backslashreplace")
    what = exc.strerror or str(exc) or type(exc).__name__
    fixes = _FIXES if has_out else {**_FIXES, **_FIXES_WITHOUT_OUT}
    fix = fixes.get(exc.errno or -1, "check the file and the folder")
    where = f"{name}: " if name else ""
    return f"{where}{what}; {fix}"


def log_traceback(exc: BaseException) -> Path | None:
    """Write ``exc``'s traceback to ``error.log`` (the run folder's, else the cache's); the
    log's path, or None when it could not be written."""
    text = "".join(traceback.format_exception(exc))
    stamp = datetime.now(UTC).isoformat(timespec="seconds")
    body = f"{stamp} {command_line()}\n{text}"
    for folder in _log_folders():
        try:
            folder.mkdir(parents=True, exist_ok=True)
            path = folder / LOG_NAME
            # never through a link: an error.log that points elsewhere is not written
            fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_TRUNC | os.O_NOFOLLOW, 0o644)
            with open(fd, "w", encoding="utf-8", errors="backslashreplace") as fh:
                fh.write(body)
            return path
        except (OSError, ValueError):
            continue
    return None


def _log_folders() -> list[Path]:
    folders = []
    run = run_folder()
    if run is not None and run.is_dir() and not run.is_symlink():
        folders.append(run)
    with contextlib.suppress(Exception):
        from twin.resources import cache_dir

        folders.append(cache_dir())
    return folders


def run_command(func: Callable[[Any], int | None], args: Any) -> int:
    """``func(args)`` with every escaping exception turned into one line and an exit code."""
    set_run_folder(None)
    terminate = _terminate_as_interrupt()
    try:
        with warnings.catch_warnings():
            warnings.showwarning = _warning_as_notice
            return int(_notices_held_on_failure(func, args) or 0)
    except UserError as exc:
        say(f"error: {exc}")
        return EXIT_REFUSED
    except KeyboardInterrupt:
        say("interrupted; files already written are complete")
        return EXIT_INTERRUPTED
    except BrokenPipeError:  # output piped into a reader that stopped (`twin ... | head`)
        with contextlib.suppress(OSError, ValueError):
            os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
        return EXIT_PIPE
    except ModuleNotFoundError as exc:
        missing = (exc.name or "").split(".")[0]
        if not missing or missing == "twin":  # twin's own module: a bug
            return _unexpected(exc)
        say(
            f"error: needs the Python package {missing!r}, which is not installed: "
            f"pip install {missing} (or the twin extra that brings it, see the README)"
        )
        return EXIT_REFUSED
    except OSError as exc:
        log = log_traceback(exc)
        say(f"error: {describe_os_error(exc, has_out=hasattr(args, 'out'))}{_see(log)}")
        return EXIT_REFUSED
    except MemoryError as exc:
        log = log_traceback(exc)
        say(f"error: out of memory; use a smaller grid, horizon or fewer seeds{_see(log)}")
        return EXIT_REFUSED
    except UnicodeError as exc:  # a file name or text the file system or terminal cannot encode
        log = log_traceback(exc)
        say(f"error: {exc}; use names and text in UTF-8{_see(log)}")
        return EXIT_REFUSED
    except Exception as exc:
        return _unexpected(exc)
    finally:
        set_run_folder(None)
        if terminate is not None:
            signal.signal(signal.SIGTERM, terminate)


def _warning_as_notice(message, category, filename, lineno, file=None, line=None) -> None:
    """A Python warning (numpy's, a library's) is one notice line, said once, not the source
    line that raised it."""
    text = " ".join(str(message).split())
    notify(f"twin: notice: {category.__name__}: {text[:300]}")


def _terminate_as_interrupt():
    """SIGTERM (``kill``, a batch scheduler, ``timeout``) stops the command as Ctrl-C does:
    a run keeps its finished steps and files already written stay complete. Returns the
    handler to restore (None when SIGTERM was handled by the caller, or off the main
    thread)."""
    if threading.current_thread() is not threading.main_thread():
        return None
    if signal.getsignal(signal.SIGTERM) is not signal.SIG_DFL:
        return None
    return signal.signal(signal.SIGTERM, interrupt_on_terminate)


def _notices_held_on_failure(func: Callable[[Any], int | None], args: Any) -> int | None:
    """``func(args)``; the notices it still holds back are printed when it returns, dropped
    when it fails (its error is the one line)."""
    drop_notices()
    count_said(True)
    try:
        code = func(args)
    except BaseException:
        drop_notices()
        raise
    finally:
        count_said(False)
    release_notices(final=True)
    return code


def _unexpected(exc: BaseException) -> int:
    log = log_traceback(exc)
    where = f"the traceback is in {log}" if log else "no log could be written"
    say(
        f"internal error: {type(exc).__name__}: {exc} ({where}; please report it with the "
        "command that caused it)"
    )
    return EXIT_BUG


def _see(log: Path | None) -> str:
    return f" (details in {log})" if log else ""
