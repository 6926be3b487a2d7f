"""Clock times of simulated runs: seconds since midnight <-> "HH:MM[:SS]" labels."""

from __future__ import annotations

import re

from twin.errors import UserError


def clock_label(t: float, seconds: bool = True) -> str:
    """``t`` seconds since midnight as ``HH:MM:SS`` (``HH:MM`` without seconds); past 24 h the
    days come first (``1d 02:15``), so a multi-day run never shows an earlier time later on."""
    t = round(t)
    sign = "-" if t < 0 else ""
    t = abs(t)
    days, hh, mm, ss = t // 86400, t // 3600 % 24, t % 3600 // 60, t % 60
    label = f"{hh:02d}:{mm:02d}:{ss:02d}" if seconds else f"{hh:02d}:{mm:02d}"
    return f"{sign}{days}d {label}" if days else f"{sign}{label}"


#: ``HH:MM[:SS]``, after the days past the first when there are any (``1d 02:15``), as
#: :func:`clock_label` writes it.
_CLOCK = re.compile(r"(?:(\d{1,3})d\s+)?(\d{1,2}):(\d{2})(?::(\d{2}))?")
CLOCK_HINT = 'must be a clock time like "07:00" (or "1d 02:15" on a later day)'


def clock_seconds(text: str) -> float | None:
    """``"07:00"``, ``"07:00:30"`` or ``"1d 02:15"`` -> seconds since the first midnight; None
    when ``text`` is not such a time."""
    m = _CLOCK.fullmatch(str(text).strip())
    if not m or int(m[3]) > 59 or int(m[4] or 0) > 59:
        return None
    days, h, mi, s = int(m[1] or 0), int(m[2]), int(m[3]), int(m[4] or 0)
    return float(days * 86400 + h * 3600 + mi * 60 + s)


def parse_clock(text: str, where: str) -> float:
    """:func:`clock_seconds` of ``text``; ``where`` names the source of a bad value in the
    one-line error."""
    t = clock_seconds(text)
    if t is None:
        raise UserError(f"{where} = {text!r} {CLOCK_HINT}")
    return t
