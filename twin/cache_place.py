"""Where twin's cache lies: ``$TWIN_CACHE_DIR``, else the user cache folder platformdirs gives,
and the folders twin keeps there. What the cache holds and how entries are built is
:mod:`twin.resources`; output folders are checked against this place by :mod:`twin.outputs`.
"""

from __future__ import annotations

import os
from pathlib import Path

from twin.errors import UserError

#: Environment variable that moves the cache (tests point it at a temporary folder).
CACHE_ENV = "TWIN_CACHE_DIR"
#: The folders twin keeps in its cache (built networks and demands, scratch files, the
#: GUI's, matplotlib's and torch's own caches); no output folder may lie in them.
CACHE_FOLDERS = ("networks", "imported", "generated", "tmp", "sumo-gui", "matplotlib", "torch")


def cache_dir() -> Path:
    """The per-user cache: ``$TWIN_CACHE_DIR`` if set, else platformdirs' user cache for twin."""
    given = os.environ.get(CACHE_ENV, "").strip()
    if given:
        try:
            return Path(given).expanduser()
        except RuntimeError:  # "~user/..." of no such user, or no home to expand
            raise UserError(
                f"${CACHE_ENV} = {given!r}: its '~' names no home folder on this machine; give "
                "an absolute folder"
            ) from None
    import platformdirs

    return Path(platformdirs.user_cache_dir("twin", appauthor=False))
