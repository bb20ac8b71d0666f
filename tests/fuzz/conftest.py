"""Every test in this package is a fuzz test: marked ``fuzz`` so that ``make fuzz`` selects it."""

import pathlib

import pytest

_HERE = pathlib.Path(__file__).parent


def pytest_collection_modifyitems(config, items):
    for item in items:
        if _HERE in pathlib.Path(str(item.fspath)).parents:
            item.add_marker(pytest.mark.fuzz)
