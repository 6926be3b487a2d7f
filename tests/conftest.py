"""Shared test setup: twin's cache (network builds, generated demand) in a temporary folder."""

from __future__ import annotations

import pytest

from twin.resources import CACHE_ENV


@pytest.fixture(scope="session", autouse=True)
def _twin_cache(tmp_path_factory):
    """Every test, and every subprocess a test starts, builds into one fresh cache folder."""
    with pytest.MonkeyPatch.context() as mp:
        mp.setenv(CACHE_ENV, str(tmp_path_factory.mktemp("twin-cache")))
        yield
