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


def parse_clock(text: str, where: str) -> float:
    """``"07:00"`` or ``"07:00:30"`` -> seconds since midnight; ``where`` names the source of a
    bad value in the one-line error."""
    m = re.fullmatch(r"(\d{1,2}):(\d{2})(?::(\d{2}))?", str(text).strip())
    if not m or int(m[2]) > 59 or int(m[3] or 0) > 59:
        raise UserError(f'{where} = {text!r} must be a clock time like "07:00"')
    h, mi, s = int(m[1]), int(m[2]), int(m[3] or 0)
    return float(h * 3600 + mi * 60 + s)
