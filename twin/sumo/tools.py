"""Where SUMO's binaries and tools live (the eclipse-sumo wheel), and how to call them.

Users never set ``SUMO_HOME``: it is taken from the wheel and passed to subprocesses only.
"""

from __future__ import annotations

import os
import subprocess
import sys
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


def _env() -> dict[str, str]:
    env = dict(os.environ)
    env.setdefault("SUMO_HOME", str(sumo_home()))
    return env


def run_sumo_program(args: list[str], what: str, timeout: float = 600.0) -> str:
    """Run a SUMO binary or tool (``args[0]`` a name from :func:`binary` or a ``.py`` tool).

    Raises :class:`UserError` with SUMO's first error line when it fails; returns stdout.
    """
    cmd = [sys.executable, *args] if args[0].endswith(".py") else args
    try:
        proc = subprocess.run(
            cmd, capture_output=True, text=True, env=_env(), timeout=timeout, check=False
        )
    except subprocess.TimeoutExpired as exc:
        raise UserError(f"{what}: {Path(args[0]).name} took longer than {timeout:.0f} s") from exc
    if proc.returncode != 0:
        raise UserError(f"{what}: {first_error(proc.stderr + proc.stdout)}")
    return proc.stdout


def first_error(text: str) -> str:
    """The first line of SUMO's output that reports an error (or the last line)."""
    lines = [line.strip() for line in text.splitlines() if line.strip()]
    for line in lines:
        if line.lower().startswith(("error", "quitting")) or "error:" in line.lower():
            return line
    return lines[-1] if lines else "failed without a message"
