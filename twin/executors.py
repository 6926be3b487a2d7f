"""Executors: run a list of tasks (a sweep's cells, a run's seeds) on a local process pool or
on Ray, yielding each one's outcome as it finishes."""

from __future__ import annotations

import logging
import multiprocessing
import os
import threading
from collections.abc import Callable, Iterable, Iterator, Sequence
from concurrent.futures import FIRST_COMPLETED, ProcessPoolExecutor, wait
from concurrent.futures.process import BrokenProcessPool
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
    waiting for them."""
    context = multiprocessing.get_context("spawn")
    pool = ProcessPoolExecutor(
        max_workers=workers,
        mp_context=context,
        initializer=exit_with_parent,
        initargs=(os.getpid(), ignore_sigint),
    )
    pending: dict = {}
    try:
        pending = {pool.submit(fn, *args): n for n, args in enumerate(tasks)}
        while pending:
            done, _ = wait(pending, timeout=1.0, return_when=FIRST_COMPLETED)
            for future in done:
                n = pending.pop(future)
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


def _probe_address(address: str, timeout: float = RAY_PROBE_S) -> None:
    """Refuse (one line) a ``host:port`` Ray address on which nothing answers within
    ``timeout`` seconds; ``auto``/``local`` and addresses without a port are left to Ray."""
    import socket

    rest = address.split("://", 1)[-1]
    host, sep, port = rest.rpartition(":")
    if not sep or not host or not port.isdigit():
        return
    fix = "start the cluster (ray start --head) or give its address: --address HOST:PORT"
    try:
        with socket.create_connection((host.strip("[]"), int(port)), timeout=timeout):
            pass
    except OSError as exc:
        why = "no answer" if isinstance(exc, TimeoutError) else (exc.strerror or str(exc))
        raise UserError(f"Ray address {address}: {why} (waited {timeout:.0f} s); {fix}") from None


def _connect_ray(ray: Any, address: str, timeout: float = RAY_CONNECT_S) -> None:
    """``ray.init(address)``, refused (one line) when the address does not answer or the
    cluster does not let twin join within ``timeout`` seconds."""
    _probe_address(address)
    outcome: dict[str, BaseException | None] = {}

    def join() -> None:
        try:
            ray.init(address=address, log_to_driver=False, logging_level=logging.ERROR)
            outcome["error"] = None
        except BaseException as exc:  # reported in the caller's thread
            outcome["error"] = exc

    thread = threading.Thread(target=join, name="ray-connect", daemon=True)
    thread.start()
    thread.join(timeout)
    fix = "check that the cluster runs (ray status) and that the address is its head's"
    if "error" not in outcome:
        raise UserError(f"Ray address {address}: no cluster joined within {timeout:.0f} s; {fix}")
    error = outcome["error"]
    if error is not None:
        line = " ".join(str(error).split())[:200]
        raise UserError(f"Ray address {address}: {type(error).__name__}: {line}; {fix}")


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
    started = False
    if not ray.is_initialized():
        if address:
            _connect_ray(ray, address)
        else:
            ray.init(
                num_cpus=workers,
                include_dashboard=False,
                log_to_driver=False,
                configure_logging=False,
            )
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


def _ray_executor(
    cells: list[dict], workers: int, address: str | None, fn: Callable
) -> Iterable[Outcome]:
    """Run cells as Ray tasks (:func:`ray_tasks`)."""
    for n, record, error in ray_tasks(fn, [(cell,) for cell in cells], workers, address):
        yield cells[n]["id"], record, None if error is None else _error_line(error)
