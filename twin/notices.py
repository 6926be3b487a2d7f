"""Notices (``twin: notice: ...``, the simulation's announcement) held back while a command
may still be refused, so that a refusal is its one error line (:mod:`twin.boundary` prints the
held lines when the command ends well and drops them when it fails).

This module imports nothing of twin: every module may say a notice without an import circle.
"""

from __future__ import annotations

import contextlib
import sys
from typing import Any

#: notices held back until the simulation has started (None: print them at once), or, with
#: ``to_end``, until the command has ended well
_held: dict[str, Any] = {"lines": None, "to_end": False}
#: the notices a command has said (None outside a command): each is said once, not once per seed
_said: dict[str, set[str] | None] = {"lines": None}


def hold_notices(to_end: bool = False) -> None:
    """From now on, hold back :func:`notify`'s lines (notices, the simulation's announcement)
    until :func:`release_notices`: a command refused before its simulation starts prints its
    one error line only. With ``to_end`` (a command writing its results after the run) they
    are held until the command has ended well, whatever simulations start meanwhile (the
    ceilings' oracle): a write that fails is its error's line alone."""
    if _held["lines"] is None:
        _held["lines"] = []
    _held["to_end"] = _held["to_end"] or to_end


def notify(line: str) -> None:
    """Print ``line`` on stderr, or hold it back while :func:`hold_notices` is in force; a
    line the command has said already (the same notice of each seed's scenario) is not
    repeated."""
    said = _said["lines"]
    if said is not None:
        if line in said:
            return
        said.add(line)
    held = _held["lines"]
    if held is not None:
        held.append(line)
    else:
        print(line, file=sys.stderr, flush=True)


def release_notices(final: bool = False) -> None:
    """Print the held lines, in order (the simulation has started), and stop holding; lines
    held ``to_end`` wait for the ``final`` release, when the command has ended well."""
    if _held["to_end"] and not final:
        return
    held, _held["lines"], _held["to_end"] = _held["lines"], None, False
    for line in held or []:
        with contextlib.suppress(Exception):
            print(line, file=sys.stderr, flush=True)


def drop_notices() -> list[str]:
    """Stop holding and return the held lines unprinted (a refusal prints only its error)."""
    held, _held["lines"], _held["to_end"] = _held["lines"], None, False
    return held or []


@contextlib.contextmanager
def once_among(said: set[str]):
    """Within: a notice already in ``said`` is not said again, outside a command too (an env
    builds its scenario again at every episode); a command's own count comes first."""
    if _said["lines"] is not None:
        yield
        return
    _said["lines"] = said
    try:
        yield
    finally:
        _said["lines"] = None


def count_said(on: bool) -> None:
    """From now on (``on``: a command starts) say each notice once; ``False`` when it ends."""
    _said["lines"] = set() if on else None
