"""Helpers for twin's child processes (sweep workers, SUMO's own process)."""

from __future__ import annotations

import os
import signal
import sys
import threading
import time

#: Seconds between two checks of a child process that its parent is alive.
PARENT_POLL_S = 0.5
#: Set while a run was asked to stop (a first Ctrl-C or SIGTERM, :func:`twin.experiment.
#: stop_on_interrupt`): work that has no step to finish first (a SUMO tool building the
#: scenario) stops at once.
STOP_ASKED = threading.Event()


def peak_memory_mb() -> float | None:
    """This process's peak resident memory so far (MB), where the OS tells it."""
    try:
        import resource
    except ImportError:  # not on Windows
        return None
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    return round(peak / (1024.0 * 1024.0 if sys.platform == "darwin" else 1024.0), 1)


def interrupt_on_terminate(signum, frame) -> None:
    """A SIGTERM handler (``kill``, a batch scheduler's stop, ``timeout``): stop as Ctrl-C
    does, so the files already written stay complete."""
    raise KeyboardInterrupt


def leave_stops_to_parent() -> None:
    """Ignore Ctrl-C and SIGTERM, which may reach the whole process group: the parent
    decides (it stops or kills this process)."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    signal.signal(signal.SIGTERM, signal.SIG_IGN)


def exit_with_parent(parent: int, ignore_sigint: bool = False) -> None:
    """End this process when ``parent`` dies, even by ``kill -9`` (no cleanup runs there). On
    Linux the kernel sends SIGKILL on the parent's death (``PR_SET_PDEATHSIG``); everywhere a
    daemon thread checks ``os.getppid()`` twice a second. With ``ignore_sigint`` the process
    ignores Ctrl-C and SIGTERM (:func:`leave_stops_to_parent`)."""
    if ignore_sigint:
        leave_stops_to_parent()
    if sys.platform.startswith("linux"):
        try:
            import ctypes

            libc = ctypes.CDLL(None, use_errno=True)
            libc.prctl(1, signal.SIGKILL, 0, 0, 0)  # PR_SET_PDEATHSIG = 1
        except (OSError, AttributeError):
            pass
    if os.getppid() != parent:  # the parent died before the line above took effect
        os._exit(1)

    def watch() -> None:
        while os.getppid() == parent:
            time.sleep(PARENT_POLL_S)
        os._exit(1)

    threading.Thread(target=watch, name="twin-parent-watch", daemon=True).start()
