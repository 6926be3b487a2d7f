"""Seeds: the range every command, config and run folder keeps to, and a config's list of
them."""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

#: The largest seed (SUMO's seeds are 32-bit signed integers); every seed a command or config
#: takes keeps to 0 .. MAX_SEED (the synthetic generator's seeds derived from them, such as
#: pretraining's episodes, may be larger: numpy takes any).
MAX_SEED = 2**31 - 1


def is_seed(value: Any) -> bool:
    """Whether ``value`` is a seed: a whole number (not a bool) in ``0 .. MAX_SEED``."""
    return isinstance(value, int) and not isinstance(value, bool) and 0 <= value <= MAX_SEED


def check_seed_list(
    seeds: Any, example: str, first: int = 0, most: int | None = None
) -> Sequence[int]:
    """A config's ``seeds``: a count (``first``, ``first + 1``, ...: a range) or a list of
    distinct seeds, all in ``0 .. MAX_SEED``; else a ValueError saying which and how to fix it
    (a count to give no larger than ``most``, the most seeds the caller takes)."""

    def whole(x: Any) -> bool:
        return isinstance(x, int) and not isinstance(x, bool)

    if whole(seeds):
        if seeds < 1:
            raise ValueError("must be at least 1; give a count or a list of seeds")
        if first + seeds - 1 > MAX_SEED:
            raise ValueError(
                f"runs seeds {first} .. {first + seeds - 1}, past the largest seed "
                f"{MAX_SEED}; give at most {min(MAX_SEED - first + 1, most or MAX_SEED + 1)}"
            )
        return range(first, first + seeds)
    if not isinstance(seeds, list) or not seeds or not all(whole(s) for s in seeds):
        raise ValueError(f"must be a count or a non-empty list of whole numbers; e.g. {example}")
    wrong = [s for s in seeds if not is_seed(s)]
    if wrong:
        raise ValueError(
            f"holds seed {wrong[0]}, out of range; seeds are whole numbers from 0 to {MAX_SEED}"
        )
    if len(set(seeds)) != len(seeds):
        raise ValueError("lists a seed twice; list each once")
    return seeds
