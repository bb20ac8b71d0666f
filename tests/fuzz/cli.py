"""The bad-input corpus's one assertion: a CLI given bad input keeps the promise.

:func:`assert_refused` runs a CLI's ``main`` in this process (through ``toolkit.errors.run_cli``, as
``python -m`` does) and checks: exit status 2, exactly one line holding ``error:`` on stderr (argparse's own
usage errors print their usage line before it), no traceback, every input file byte-for-byte unchanged, the
output folder as it was (no partial or temporary file left), and it finished within a time cap (a hang is a
failure, raised from SIGALRM).
"""

from __future__ import annotations

import contextlib
import hashlib
import importlib
import io
import re
import signal
from pathlib import Path
from typing import Sequence

from toolkit.errors import run_cli

CLIS = {"toolkit": "toolkit.__main__", "geometry": "geometry.__main__", "train.data": "train.data.__main__",
        "train.run": "train.run", "apps.redirect": "apps.redirect", "apps.preview": "apps.preview",
        "apps.prepare": "apps.prepare", "apps.demo": "apps.demo",
        **{f"benchmarks.{b}": f"benchmarks.{b}" for b in ("field_switches", "gaussian_model", "gaze_estimator",
                                                           "renderer", "train")}}


class Hang(Exception):
    pass


def _alarm(signum, frame):
    raise Hang()


def _digest(paths: Sequence[Path]) -> dict[str, str]:
    out = {}
    for p in paths:
        files = sorted(q for q in Path(p).rglob("*") if q.is_file()) if Path(p).is_dir() else [Path(p)]
        for f in files:
            out[str(f)] = hashlib.sha256(f.read_bytes()).hexdigest() if f.exists() else "absent"
    return out


def _listing(folder: Path | None) -> list[str]:
    if folder is None or not folder.exists():
        return []
    return sorted(str(p.relative_to(folder)) for p in folder.rglob("*"))


def assert_refused(cli: str, argv: Sequence[str], match: str, *, inputs: Sequence[Path] = (),
                   out_dir: Path | None = None, seconds: int = 60) -> str:
    """Run ``python -m {cli} {argv}`` in-process; assert the promise (module docstring) and that the error line
    matches the regex ``match``. Returns the error line."""
    main = importlib.import_module(CLIS[cli]).main
    before, listing = _digest(inputs), _listing(out_dir)
    err, out = io.StringIO(), io.StringIO()
    previous = signal.signal(signal.SIGALRM, _alarm)
    signal.alarm(seconds)
    try:
        with contextlib.redirect_stderr(err), contextlib.redirect_stdout(out):
            try:
                code = run_cli(main, [str(a) for a in argv])
            except SystemExit as e:  # argparse's usage errors
                code = e.code
    except Hang:
        raise AssertionError(f"{cli} {list(map(str, argv))}: still running after {seconds} s") from None
    finally:
        signal.alarm(0)
        signal.signal(signal.SIGALRM, previous)
    text = err.getvalue()
    lines = [ln for ln in text.splitlines() if "error:" in ln]
    where = f"{cli} {' '.join(map(str, argv))}"
    assert "Traceback" not in text, f"{where}: traceback\n{text}"
    assert code == 2, f"{where}: exit {code}, expected 2\nstderr: {text}"
    assert len(lines) == 1, f"{where}: expected one error line, got\n{text}"
    assert re.search(match, lines[0]), f"{where}: error line {lines[0]!r} does not match {match!r}"
    assert _digest(inputs) == before, f"{where}: an input changed"
    assert _listing(out_dir) == listing, f"{where}: the output folder changed: {_listing(out_dir)}"
    return lines[0]
