"""Bounds on what a user-controlled size may cost, checked before the work.

Every count, size or loop length a user gives (a flag, a config key, a count declared in a file's header) goes
through one of these checks first, so a typo such as ``--samples 1e11`` or a 7 KB file declaring 20 M rows is
one ``ToolkitError`` naming the flag or field, never a ``MemoryError``, an allocation traceback or a hang.

- :func:`check_count` -- an integer in a declared range (``what`` says its unit).
- :func:`check_allocation` -- the bytes an operation would allocate, against :func:`memory_budget`.
- :func:`check_declared_size` -- the bytes a file's header declares, against the bytes the file holds.

The memory budget is half the machine's physical memory, or ``DITGAZE_MEMORY_GB`` (GiB) when set.
"""

from __future__ import annotations

import math
import os
from pathlib import Path

from toolkit.errors import ToolkitError

GIB = 1 << 30


def memory_budget() -> int:
    """Bytes one operation may allocate: ``DITGAZE_MEMORY_GB`` GiB when set, else half the physical memory."""
    env = os.environ.get("DITGAZE_MEMORY_GB", "").strip()
    if env:
        try:
            gb = float(env)
        except ValueError:
            gb = math.nan
        if not (math.isfinite(gb) and 0 < gb <= 1 << 20):
            raise ToolkitError(f"DITGAZE_MEMORY_GB: expected a number of GiB in (0, 1048576], got {env!r}")
        return int(gb * GIB)
    try:
        return os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES") // 2
    except (ValueError, OSError, AttributeError):  # not POSIX: assume a small machine
        return 4 * GIB


def _size(n: float) -> str:
    return f"{n / GIB:.3g} GiB" if n >= GIB / 10 else f"{n / (1 << 20):.3g} MiB"


def check_allocation(nbytes: float, what: str, hint: str = "") -> None:
    """Raise unless ``nbytes`` (what ``what`` would allocate) fits :func:`memory_budget`; ``hint`` says how to
    ask for less ("lower --samples")."""
    budget = memory_budget()
    if not (nbytes <= budget):  # NaN fails too
        more = f"; {hint}" if hint else ""
        raise ToolkitError(f"{what} would allocate {_size(nbytes)}, more than the memory budget of {_size(budget)} "
                           f"(half the machine's memory, or DITGAZE_MEMORY_GB){more}")


def is_finite_number(value: object) -> bool:
    """Whether ``value`` is a finite real number (a Python or numpy scalar, a one-element tensor); False for
    anything ``math.isfinite`` cannot read."""
    try:
        return math.isfinite(value)
    except (TypeError, ValueError, RuntimeError):
        return False


def check_count(value: object, name: str, low: int, high: int, what: str = "a count") -> int:
    """``value`` as an int in ``[low, high]``, else "{name}: expected {what} in [low, high], got {value}".
    Accepts ints and integral floats (``1e3``); refuses bools, NaN, infinities and fractions."""
    ok = isinstance(value, (int, float)) and not isinstance(value, bool)
    if ok and isinstance(value, float):
        ok = math.isfinite(value) and value.is_integer()
    if not ok or not low <= value <= high:
        raise ToolkitError(f"{name}: expected {what} in [{low}, {high}], got {value!r}")
    return int(value)


def check_declared_size(path: str | os.PathLike, declared_bytes: float, what: str) -> None:
    """Raise unless a file holds at least the ``declared_bytes`` its header promises for ``what`` (a file that
    declares 20 M rows in 7 KB is truncated or forged: refuse it before allocating for them)."""
    size = Path(path).stat().st_size
    if not (declared_bytes <= size):
        raise ToolkitError(f"{path}: {what} needs {declared_bytes:.0f} bytes but the file holds {size} "
                           f"(truncated, or a count in its header is wrong)")
