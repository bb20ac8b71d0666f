"""geometry tests keep the tet-grid disk cache in one temporary folder per test run, not in ~/.cache."""

from __future__ import annotations

import pytest


@pytest.fixture(autouse=True, scope="package")
def _tet_cache(tmp_path_factory):
    mp = pytest.MonkeyPatch()
    mp.setenv("DITGAZE_CACHE", str(tmp_path_factory.mktemp("ditgaze_cache")))
    yield
    mp.undo()
