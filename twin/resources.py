"""Where twin's shipped files and its per-user cache are: the one place that knows.

Shipped with the package, read through :mod:`importlib.resources`:

- scenario and pretraining configs ``configs/<name>.toml``,
- built-in network specs ``networks/<name>/spec.toml``,
- the pretrained Q-network ``data/qnet.pt``.

In the repository these folders stay at the top (``configs/``, ``networks/``, ``data/``);
``twin/configs``, ``twin/networks`` and ``twin/data`` are symlinks to them. An editable install
reads them through the links; a wheel copies the linked files into ``twin/`` as package data
(``[tool.setuptools.package-data]`` in pyproject.toml), so the same relative paths hold in both,
including a config's ``../data/qnet.pt``.

Everything twin generates (network builds, generated demand, imported OSM networks) goes to the
per-user cache :func:`cache_dir`, never into the installed package or the source tree.
"""

from __future__ import annotations

import contextlib
import os
import shutil
import tempfile
from collections.abc import Callable
from importlib import resources
from pathlib import Path

from twin.errors import UserError

#: Environment variable that moves the cache (tests point it at a temporary folder).
CACHE_ENV = "TWIN_CACHE_DIR"


def package_root() -> Path:
    """The installed ``twin`` package folder (a plain folder: twin is not run from a zip)."""
    root = resources.files("twin")
    if not isinstance(root, Path):  # pragma: no cover - zipped installs are not supported
        raise UserError(f"twin is installed in an archive ({root}); install it with pip")
    return root


def shipped(*parts: str) -> Path:
    """The path of a shipped file, e.g. ``shipped("configs", "synthetic.toml")``."""
    return package_root().joinpath(*parts)


def shipped_config_names() -> list[str]:
    """Names of the shipped configs (``synthetic`` for ``configs/synthetic.toml``)."""
    return sorted(p.stem for p in shipped("configs").glob("*.toml"))


def shipped_config(given: str | Path) -> Path:
    """The config file ``given`` names: a path that exists wins; otherwise a shipped config
    given as ``synthetic``, ``synthetic.toml`` or ``configs/synthetic.toml``."""
    path = Path(given)
    if path.exists():
        return path
    if path.parent in (Path("."), Path("configs")):
        name = path.name if path.suffix == ".toml" else f"{path.name}.toml"
        candidate = shipped("configs", name)
        if candidate.is_file():
            return candidate
    names = ", ".join(shipped_config_names()) or "none"
    raise UserError(
        f"{given}: config file not found; give the path of a TOML file or a shipped config "
        f"({names})"
    )


def network_names() -> list[str]:
    """The built-in networks: shipped folders ``networks/<name>/`` holding a ``spec.toml``."""
    return sorted(p.parent.name for p in shipped("networks").glob("*/spec.toml"))


def network_spec(name: str) -> Path:
    """The shipped spec ``networks/<name>/spec.toml`` of a built-in network."""
    path = shipped("networks", name, "spec.toml")
    if not path.is_file():
        known = ", ".join(network_names()) or "none"
        raise UserError(f"unknown network {name!r} (no {path}); built-in networks: {known}")
    return path


def shipped_checkpoint() -> Path:
    """The shipped, pretrained Q-network ``data/qnet.pt``."""
    return shipped("data", "qnet.pt")


def cache_dir() -> Path:
    """The per-user cache: ``$TWIN_CACHE_DIR`` if set, else platformdirs' user cache for twin."""
    given = os.environ.get(CACHE_ENV, "").strip()
    if given:
        return Path(given).expanduser()
    import platformdirs

    return Path(platformdirs.user_cache_dir("twin", appauthor=False))


def build_once(target: Path, make: Callable[[Path], None], force: bool = False) -> Path:
    """The folder ``target``, made by ``make(folder)`` unless it exists already.

    ``make`` fills a fresh temporary folder beside ``target`` that is then renamed into place
    in one step, so a reader never sees a half-built folder and two processes building the same
    ``target`` at once both end up with one complete copy (the loser's is deleted). ``force``
    replaces an existing ``target``.
    """
    if target.is_dir() and not force:
        return target
    target.parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=f".{target.name}.tmp-", dir=target.parent))
    try:
        make(tmp)
        if force and target.is_dir():
            old = Path(tempfile.mkdtemp(prefix=f".{target.name}.old-", dir=target.parent))
            with contextlib.suppress(FileNotFoundError):  # removed meanwhile
                target.rename(old / "x")
            shutil.rmtree(old, ignore_errors=True)
        try:
            tmp.rename(target)
        except OSError:
            if not target.is_dir():
                raise
            # another process finished the same build first: use its copy
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    return target
