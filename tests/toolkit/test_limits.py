"""The shared bounds: counts, allocations against the memory budget, sizes a file's header declares."""

import math

import pytest

from toolkit.errors import ToolkitError
from toolkit.limits import GIB, check_allocation, check_count, check_declared_size, memory_budget


@pytest.mark.parametrize("value", [0, 11, -1, 1.5, math.nan, math.inf, True, "3", None, 2**64])
def test_check_count_refuses_what_is_not_an_integer_in_range(value):
    with pytest.raises(ToolkitError, match=r"^--views: expected a count in \[1, 10\], got "):
        check_count(value, "--views", 1, 10)


@pytest.mark.parametrize("value, expected", [(1, 1), (10, 10), (3.0, 3), (1e1, 10)])
def test_check_count_accepts_integral_values(value, expected):
    out = check_count(value, "--views", 1, 10)
    assert out == expected and type(out) is int


def test_memory_budget_reads_the_environment(monkeypatch):
    monkeypatch.setenv("DITGAZE_MEMORY_GB", "2")
    assert memory_budget() == 2 * GIB
    check_allocation(2 * GIB, "x")
    with pytest.raises(ToolkitError, match=r"^--samples 1e11 would allocate 2.* GiB, more than .*; lower --samples$"):
        check_allocation(2 * GIB + 1, "--samples 1e11", "lower --samples")
    with pytest.raises(ToolkitError, match="would allocate"):
        check_allocation(math.nan, "x")
    for bad in ("abc", "0", "-1", "nan", "inf"):
        monkeypatch.setenv("DITGAZE_MEMORY_GB", bad)
        with pytest.raises(ToolkitError, match="^DITGAZE_MEMORY_GB: expected"):
            memory_budget()


def test_memory_budget_default_is_half_the_machine(monkeypatch):
    monkeypatch.delenv("DITGAZE_MEMORY_GB", raising=False)
    assert 0 < memory_budget() < 1 << 50


def test_check_declared_size(tmp_path):
    p = tmp_path / "f.bin"
    p.write_bytes(b"x" * 100)
    check_declared_size(p, 100, "the rows")
    with pytest.raises(ToolkitError, match=r"f.bin: the rows needs 101 bytes but the file holds 100"):
        check_declared_size(p, 101, "the rows")
