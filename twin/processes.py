"""Helpers for twin's child processes (sweep workers, SUMO's own process)."""

from __future__ import annotations

import os
import signal
import sys
import threading
import time

#: Seconds between two checks of a child process that its parent is alive.
PARENT_POLL_S = 0.5


def exit_with_parent(parent: int, ignore_sigint: bool = False) -> None:
    """End this process when ``parent`` dies, even by ``kill -9`` (no cleanup runs there). On
    Linux the kernel sends SIGKILL on the parent's death (``PR_SET_PDEATHSIG``); everywhere a
    daemon thread checks ``os.getppid()`` twice a second. With ``ignore_sigint`` the process
    ignores Ctrl-C, which reaches the whole terminal's process group: the parent decides."""
    if ignore_sigint:
        signal.signal(signal.SIGINT, signal.SIG_IGN)
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
