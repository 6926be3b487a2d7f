"""Executors: run a list of tasks (a sweep's cells, a run's seeds) on a local process pool or
on Ray, yielding each one's outcome as it finishes."""

from __future__ import annotations

import contextlib
import logging
import multiprocessing
import os
import signal
import sys
import threading
from collections.abc import Callable, Iterable, Iterator, Sequence
from concurrent.futures import FIRST_COMPLETED, ProcessPoolExecutor, wait
from concurrent.futures.process import BrokenProcessPool
from pathlib import Path
from typing import Any

from twin.errors import UserError
from twin.processes import exit_with_parent

EXECUTORS = ("local", "ray")


#: What an executor yields per cell: (cell id, result record or None, error message or None).
Outcome = tuple[str, dict[str, Any] | None, str | None]


def _error_line(exc: BaseException) -> str:
    cause = getattr(exc, "cause", None) or exc  # Ray wraps the task's exception
    text = str(cause).strip().splitlines()
    return f"{type(cause).__name__}: {text[0] if text else ''}"


def local_tasks(
    fn: Callable[..., Any],
    tasks: Sequence[tuple],
    workers: int,
    ignore_sigint: bool = False,
    kill_on_close: bool = False,
) -> Iterator[tuple[int, Any, BaseException | None]]:
    """Run ``fn(*tasks[n])`` for every n on a process pool (spawn: one fresh interpreter, hence
    one SUMO, per worker), yielding ``(n, value, None)`` or ``(n, None, exception)`` as each
    finishes. Workers exit when the parent dies (:func:`exit_with_parent`); with
    ``ignore_sigint`` they leave Ctrl-C to the parent. With ``kill_on_close``, a caller that
    stops reading early (an error, a second Ctrl-C) kills the running workers instead of
    waiting for them. At most ``workers`` tasks are handed to the pool at once: the pool
    queues one more than it runs, which a stop (Ctrl-C, SIGTERM) would not cancel."""
    context = multiprocessing.get_context("spawn")
    pool = ProcessPoolExecutor(
        max_workers=workers,
        mp_context=context,
        initializer=exit_with_parent,
        initargs=(os.getpid(), ignore_sigint),
    )
    pending: dict = {}
    waiting = iter(enumerate(tasks))

    def submit_next() -> None:
        for n, args in waiting:
            pending[pool.submit(fn, *args)] = n
            return

    try:
        for _ in range(workers):
            submit_next()
        while pending:
            done, _ = wait(pending, timeout=1.0, return_when=FIRST_COMPLETED)
            for future in done:
                n = pending.pop(future)
                submit_next()  # the freed worker takes the next task at once
                try:
                    yield n, future.result(), None
                except Exception as exc:
                    yield n, None, exc
    finally:
        if pending and kill_on_close:
            for process in list((getattr(pool, "_processes", None) or {}).values()):
                process.kill()
        pool.shutdown(wait=True, cancel_futures=True)


def _local_executor(cells: list[dict], workers: int, fn: Callable) -> Iterable[Outcome]:
    """Run cells (``fn``: :func:`twin.sweep.cells.run_cell`) on a process pool
    (:func:`local_tasks`)."""
    for n, record, error in local_tasks(fn, [(cell,) for cell in cells], workers):
        cid = cells[n]["id"]
        if isinstance(error, BrokenProcessPool):
            raise UserError(
                f"a sweep worker died while running cell {cid} ({error}); finished cells "
                "are saved, rerun the same command to resume"
            ) from None
        yield cid, record, None if error is None else _error_line(error)


#: Seconds to wait for a Ray cluster's address to answer (TCP), then for ``ray.init`` to join.
RAY_PROBE_S, RAY_CONNECT_S = 10.0, 40.0
#: An HTTP/2 client's connection preface and an empty SETTINGS frame (RFC 9113, 3.4 and 6.5):
#: Ray's GCS and its client server speak gRPC, whose servers answer with a SETTINGS frame.
_HTTP2_PREFACE = b"PRI * HTTP/2.0\r\n\r\nSM\r\n\r\n" + bytes([0, 0, 0, 4, 0, 0, 0, 0, 0])
_HTTP2_SETTINGS = 4


def _probe_address(address: str, timeout: float | None = None) -> None:
    """Refuse (one line) a ``host:port`` Ray address on which nothing answers within
    ``timeout`` seconds, or something that does not speak gRPC (Ray's protocol): a web server,
    a silent listener. Checked before ``ray.init``, whose own C++ log lines would otherwise
    surround twin's line while it retries. ``auto``/``local``, addresses without a port and
    clusters with TLS (``RAY_USE_TLS``) are left to Ray. ``timeout``: :data:`RAY_PROBE_S`."""
    import socket

    timeout = RAY_PROBE_S if timeout is None else timeout
    rest = address.split("://", 1)[-1]
    host, sep, port = rest.rpartition(":")
    if not sep or not host or rest.endswith("]"):  # no port ([::1] alone): Ray's default
        return
    fix = "start the cluster (ray start --head) or give its address: --address HOST:PORT"
    if not (port.isascii() and port.isdigit()) or not 0 < int(port) < 65536:
        raise UserError(f"Ray address {address}: port {port!r} is no TCP port (1 .. 65535); {fix}")
    try:
        with socket.create_connection((host.strip("[]"), int(port)), timeout=timeout) as sock:
            if os.environ.get("RAY_USE_TLS", "0").lower() in ("1", "true"):
                return
            answer = _http2_answer(sock, timeout)
    except OSError as exc:
        why = "no answer" if isinstance(exc, TimeoutError) else (exc.strerror or str(exc))
        raise UserError(f"Ray address {address}: {why} (waited {timeout:.0f} s); {fix}") from None
    if answer is not None and len(answer) >= 9 and answer[3] == _HTTP2_SETTINGS:
        return
    if answer is None:
        said = f"said nothing within {timeout:.0f} s"
    elif not answer:
        said = "closed the connection"
    else:
        first = answer.decode("ascii", "replace").splitlines()[0][:60]
        said = f"answered {first!r}"
    raise UserError(
        f"Ray address {address}: something listens there but it is not a Ray cluster (it "
        f"{said}, not gRPC); give the address of the cluster's head (ray status prints it)"
    )


def _http2_answer(sock: Any, timeout: float) -> bytes | None:
    """The first bytes a server sends back to an HTTP/2 connection preface (None: nothing
    within ``timeout`` seconds; empty: it closed the connection)."""
    sock.settimeout(timeout)
    try:
        sock.sendall(_HTTP2_PREFACE)
        return sock.recv(64)
    except TimeoutError:
        return None
    except ConnectionError:
        return b""


#: The file in twin's cache that takes what Ray prints while twin joins a cluster.
RAY_LOG_NAME = "ray-connect.log"


def _connect_ray(ray: Any, address: str, timeout: float = RAY_CONNECT_S) -> None:
    """``ray.init(address)``, refused (one line) when the address does not answer or the
    cluster does not let twin join within ``timeout`` seconds. What Ray's C++ core prints
    meanwhile (its retries, one line a second) goes to :data:`RAY_LOG_NAME` in twin's cache,
    named by the refusal; lines it prints after a join that timed out still reach stderr."""
    _probe_address(address)
    outcome: dict[str, BaseException | None] = {}

    def join() -> None:
        try:
            ray.init(address=address, log_to_driver=False, logging_level=logging.ERROR)
            outcome["error"] = None
        except BaseException as exc:  # reported in the caller's thread
            outcome["error"] = exc

    thread = threading.Thread(target=join, name="ray-connect", daemon=True)
    with _stderr_into_log() as log:
        thread.start()
        thread.join(timeout)
    fix = "check that the cluster runs (ray status) and that the address is its head's"
    said = _read_tail(log)
    if "InvalidAuthToken" in said or "Unauthenticated" in said:
        fix = (
            "the cluster asks for its authentication token: run with RAY_AUTH_MODE=token (and "
            "RAY_AUTH_TOKEN or RAY_AUTH_TOKEN_PATH if the token is not in ~/.ray/auth_token)"
        )
    see = f" (Ray's log: {log})" if said else ""
    if "error" not in outcome:
        raise UserError(
            f"Ray address {address}: no cluster joined within {timeout:.0f} s; {fix}{see}"
        )
    error = outcome["error"]
    if error is not None:
        line = " ".join(str(error).split())[:200]
        raise UserError(f"Ray address {address}: {type(error).__name__}: {line}; {fix}{see}")


@contextlib.contextmanager
def _stderr_into_log() -> Iterator[Path | None]:
    """File descriptor 2 (where Ray's C++ core logs) into :data:`RAY_LOG_NAME` in twin's cache
    while the block runs; yields the log's path (None, and stderr left alone, when the cache
    cannot take it)."""
    from twin.resources import cache_dir

    try:
        path = cache_dir() / RAY_LOG_NAME
        path.parent.mkdir(parents=True, exist_ok=True)
        log = open(path, "wb")  # noqa: SIM115 (closed below, after its descriptor is copied)
    except OSError:
        yield None
        return
    with contextlib.suppress(Exception):
        sys.stderr.flush()
    saved = os.dup(2)
    try:
        os.dup2(log.fileno(), 2)
        log.close()
        yield path
    finally:
        with contextlib.suppress(Exception):
            sys.stderr.flush()
        os.dup2(saved, 2)
        os.close(saved)


def _read_tail(path: Path | None, limit: int = 65536) -> str:
    """The last ``limit`` bytes of ``path`` as text ('' when there is none)."""
    try:
        with open(path, "rb") as fh:  # type: ignore[arg-type]
            fh.seek(max(0, fh.seek(0, 2) - limit))
            return fh.read().decode("utf-8", "replace")
    except (OSError, TypeError):
        return ""


def ray_tasks(
    fn: Callable[..., Any], tasks: Sequence[tuple], workers: int, address: str | None = None
) -> Iterator[tuple[int, Any, BaseException | None]]:
    """Run ``fn(*tasks[n])`` as Ray tasks, one CPU each, on a cluster at ``address`` or a local
    one of ``workers`` CPUs, yielding ``(n, value, None)`` or ``(n, None, exception)`` as each
    finishes; tasks still running when the caller stops reading are cancelled."""
    os.environ.setdefault("RAY_USAGE_STATS_ENABLED", "0")  # offline: never phone home
    try:
        import ray
    except ImportError:
        raise UserError("--executor ray needs Ray: pip install 'twin[ray]'") from None
    # Ray's Python warnings (e.g. on token authentication) stay off the terminal; set after
    # the import, which configures Ray's logger
    logging.getLogger("ray").setLevel(logging.ERROR)
    started, session, temp_dir, own, made = False, None, None, False, False
    if not ray.is_initialized():
        handlers = _signal_handlers()
        if address:
            _connect_ray(ray, address)
        else:
            temp_dir, own = _local_ray_folder()
            made = not temp_dir.exists()
            if own:
                temp_dir.mkdir(exist_ok=True)
            try:
                ray.init(
                    num_cpus=workers,
                    include_dashboard=False,
                    log_to_driver=False,
                    configure_logging=False,
                    **({"_temp_dir": str(temp_dir)} if own else {}),
                )
            except BaseException as exc:  # its half-made session goes with it
                with contextlib.suppress(Exception):
                    ray.shutdown()
                _remove_ray_session(temp_dir, None, own or made)
                _restore_signal_handlers(handlers)
                if isinstance(exc, SystemExit) and exc.code == signal.SIGTERM:
                    raise KeyboardInterrupt from None  # Ray's handler took a SIGTERM: a stop
                if isinstance(exc, Exception) and not isinstance(exc, UserError):
                    raise UserError(ray_start_failure(exc)) from None
                raise
            with contextlib.suppress(Exception):  # removed after the shutdown
                session = Path(ray._private.worker.global_worker.node.get_session_dir_path())
            if session is not None:  # whose it is, for a later scratch sweep
                from twin.resources import HOST_MARK, host_mark

                with contextlib.suppress(OSError):
                    (session / HOST_MARK).write_text(host_mark() + "\n")
        _restore_signal_handlers(handlers)  # Ray's core takes SIGTERM: twin's stop is its own
        started = True
    pending: dict = {}
    try:
        task = ray.remote(num_cpus=1, max_retries=0)(fn)
        pending = {task.remote(*args): n for n, args in enumerate(tasks)}
        while pending:
            done, _ = ray.wait(list(pending), num_returns=1, timeout=1.0)
            for ref in done:
                n = pending.pop(ref)
                try:
                    yield n, ray.get(ref), None
                except Exception as exc:
                    yield n, None, exc
    finally:
        for ref in pending:
            ray.cancel(ref, force=True)
        if started:
            ray.shutdown()
            if session is not None and temp_dir is not None:
                _remove_ray_session(temp_dir, session, own or made)


def _signal_handlers() -> dict[int, Any]:
    """This process's Python handler of SIGTERM (the main thread's to set), which Ray's
    driver takes (it leaves SIGINT's)."""
    if threading.current_thread() is not threading.main_thread():
        return {}
    return {signal.SIGTERM: signal.getsignal(signal.SIGTERM)}


def _restore_signal_handlers(handlers: dict[int, Any]) -> None:
    """Set ``handlers`` again: Ray's driver installs a C++ handler of SIGTERM that prints a
    stack and kills the process, so that a run stopped by ``kill`` (a batch scheduler) wrote
    no partial run."""
    for sig, handler in handlers.items():
        if handler is not None:
            with contextlib.suppress(ValueError, OSError):
                signal.signal(sig, handler)


def ray_start_failure(exc: BaseException) -> str:
    """One line for a local Ray that did not start: its own words, and a virtual-memory limit
    (``ulimit -v``, which Ray's processes outgrow at start) when one is set."""
    import resource

    said = (str(exc).strip().splitlines() or [type(exc).__name__])[0][:200]
    text = f"--executor ray: Ray could not start ({said})"
    with contextlib.suppress(ValueError, OSError):
        limit, _ = resource.getrlimit(resource.RLIMIT_AS)
        if limit != resource.RLIM_INFINITY:
            return (
                f"{text}; this process may use at most {limit / 2**30:.3g} GB of virtual memory "
                "(ulimit -v), which Ray's processes outgrow as they start: lift the limit "
                "(ulimit -v unlimited), or use --executor local"
            )
    return f"{text}; use --executor local"


#: The longest path of a Unix socket (Linux's ``sun_path``, less its final NUL byte).
SOCKET_PATH_MAX = 107
#: What a local Ray adds to its folder for its longest socket path: its session (date, time,
#: microseconds, a process id of up to 7 digits) and ``sockets/plasma_store``.
RAY_SOCKET_TAIL = len("/session_2026-01-01_00-00-00_000000_4194304/sockets/plasma_store")


def _local_ray_folder() -> tuple[Path, bool]:
    """Where a local Ray keeps its sessions, and whether that is twin's own folder
    (``twin-ray`` in twin's scratch folder, :func:`twin.resources.scratch_dir`).

    A Unix socket's path holds at most :data:`SOCKET_PATH_MAX` bytes; when twin's folder is
    too deep for Ray's sockets, Ray's own folder is taken (``$RAY_TMPDIR``, ``$TMPDIR`` or
    ``/tmp``, then ``ray``), the session removed after it (:func:`_remove_ray_session`);
    when both are too deep, refused in one line."""
    from twin.resources import CACHE_ENV, scratch_dir

    own = scratch_dir().absolute() / "twin-ray"  # Ray takes no relative folder
    if len(os.fsencode(own)) + RAY_SOCKET_TAIL <= SOCKET_PATH_MAX:
        return own, True
    theirs = _ray_default_folder()
    if len(os.fsencode(theirs)) + RAY_SOCKET_TAIL <= SOCKET_PATH_MAX:
        return theirs, False
    room = SOCKET_PATH_MAX - RAY_SOCKET_TAIL - len("/tmp/twin-ray")
    raise UserError(
        f"{own}: too deep a folder for a local Ray's sockets (a socket's path holds at most "
        f"{SOCKET_PATH_MAX} bytes), and so is Ray's own {theirs}; set ${CACHE_ENV} to a folder "
        f"of at most {room} characters (twin keeps Ray's sessions in its tmp/twin-ray)"
    )


def _ray_default_folder() -> Path:
    """The folder a local Ray keeps its sessions in when not told one (Ray's own choice)."""
    try:
        from ray._common.utils import get_default_ray_temp_dir
    except ImportError:  # an earlier Ray: its order (RAY_TMPDIR, then TMPDIR on Linux, /tmp)
        for name in ("RAY_TMPDIR", "TMPDIR"):
            if name in os.environ and (name == "RAY_TMPDIR" or sys.platform == "linux"):
                return (Path(os.environ[name]) / "ray").absolute()
        return Path("/tmp/ray")
    return Path(get_default_ray_temp_dir()).absolute()


def _remove_ray_session(folder: Path, session: Path | None, whole: bool) -> None:
    """A local Ray's ``session`` in ``folder`` removed after its shutdown (None: the one of
    this process, if Ray made one before failing), with the ``session_latest`` link when it
    points there; with ``whole`` (twin's folder, or Ray's made by this Ray) the folder too,
    once nothing else is in it. Sessions of killed runs go with a later twin's scratch sweep
    (:data:`twin.resources.SHARED_SCRATCH`)."""
    import shutil

    if session is None:
        mine = sorted(folder.glob(f"session_*_{os.getpid()}")) if folder.is_dir() else []
        session = mine[-1] if mine else None
    if session is not None and session.parent == folder:
        shutil.rmtree(session, ignore_errors=True)
        latest = folder / "session_latest"
        with contextlib.suppress(OSError):
            if latest.is_symlink() and Path(os.readlink(latest)).name == session.name:
                latest.unlink()
    if whole:
        with contextlib.suppress(OSError):
            folder.rmdir()


def _ray_executor(
    cells: list[dict], workers: int, address: str | None, fn: Callable
) -> Iterable[Outcome]:
    """Run cells as Ray tasks (:func:`ray_tasks`)."""
    for n, record, error in ray_tasks(fn, [(cell,) for cell in cells], workers, address):
        yield cells[n]["id"], record, None if error is None else _error_line(error)
