"""Where SUMO's binaries and tools live (the eclipse-sumo wheel), and how to call them.

Users never set ``SUMO_HOME``: it is taken from the wheel and passed to subprocesses only.
"""

from __future__ import annotations

import contextlib
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

from twin.errors import UserError


def sumo_home() -> Path:
    """The ``SUMO_HOME`` of the installed eclipse-sumo wheel."""
    try:
        from sumo import SUMO_HOME
    except ImportError as exc:  # pragma: no cover - depends on the install
        raise UserError("SUMO is not installed: pip install eclipse-sumo libsumo") from exc
    return Path(SUMO_HOME)


def binary(name: str) -> str:
    """Path of a SUMO binary (``netconvert``, ``netgenerate``, ``duarouter``, ``sumo``)."""
    path = sumo_home() / "bin" / name
    if not path.exists():  # pragma: no cover - depends on the install
        raise UserError(f"SUMO binary {name!r} not found in {path.parent}")
    return str(path)


def tool(name: str) -> str:
    """Path of a script in SUMO's tools dir, e.g. ``randomTrips.py``."""
    path = sumo_home() / "tools" / name
    if not path.exists():  # pragma: no cover - depends on the install
        raise UserError(f"SUMO tool {name!r} not found in {path.parent}")
    return str(path)


#: Seconds between two looks at a running SUMO program (finished? asked to stop?).
POLL_S = 0.2


def _env() -> dict[str, str]:
    env = dict(os.environ)
    env.setdefault("SUMO_HOME", str(sumo_home()))
    return env


def run_sumo_program(args: list[str], what: str, timeout: float = 600.0) -> str:
    """Run a SUMO binary or tool (``args[0]`` a name from :func:`binary` or a ``.py`` tool).

    Raises :class:`UserError` with SUMO's first error line when it fails; returns stdout. The
    program runs in a session of its own: a terminal's Ctrl-C reaches twin alone, which stops
    it (and what it started, duarouter under randomTrips) at once, as a stop asked before it
    started does (:data:`twin.processes.STOP_ASKED`): :class:`KeyboardInterrupt`.
    """
    from twin.processes import STOP_ASKED

    cmd = [sys.executable, *args] if args[0].endswith(".py") else args
    if STOP_ASKED.is_set():
        raise KeyboardInterrupt
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                            env=_env(), start_new_session=True)  # fmt: skip
    deadline = time.monotonic() + timeout
    try:
        while True:
            try:
                out, err = proc.communicate(timeout=POLL_S)
                break
            except subprocess.TimeoutExpired:
                if STOP_ASKED.is_set():
                    raise KeyboardInterrupt from None
                if time.monotonic() > deadline:
                    raise UserError(
                        f"{what}: {Path(args[0]).name} took longer than {timeout:.0f} s; give it "
                        "less to do (a smaller network, window or demand_scale)"
                    ) from None
    finally:
        if proc.poll() is None:  # stopped, or out of time: the program and its children
            with contextlib.suppress(OSError):
                os.killpg(proc.pid, signal.SIGKILL)
            proc.communicate()
    if proc.returncode != 0:
        raise UserError(f"{what}: {first_error(err + out)}")
    return out


def first_error(text: str) -> str:
    """The first line of SUMO's output that reports an error (or the last line)."""
    lines = [line.strip() for line in text.splitlines() if line.strip()]
    for line in lines:
        if line.lower().startswith(("error", "quitting")) or "error:" in line.lower():
            return line
    return lines[-1] if lines else "failed without a message"
