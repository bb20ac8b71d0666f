"""toolkit.host: the allocator settings apply on glibc, do nothing elsewhere, and change no result."""

from __future__ import annotations

import platform
import subprocess
import sys
from pathlib import Path

import pytest

from toolkit import host


def test_keep_freed_memory_applies_on_glibc_and_is_a_no_op_elsewhere(monkeypatch):
    # Applied to this pytest process too, for the rest of the test run: harmless (train.run applies it anyway).
    if sys.platform.startswith("linux") and platform.libc_ver()[0] == "glibc":
        assert host.keep_freed_memory() is True
    monkeypatch.setattr(host.sys, "platform", "darwin")
    assert host.keep_freed_memory() is False


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="glibc allocator settings")
def test_results_are_bitwise_the_same_with_the_settings():
    # A fresh interpreter each, so the first one's allocator is the untouched default.
    code = ("import sys, torch; from toolkit.host import keep_freed_memory\n"
            "applied = keep_freed_memory() if sys.argv[1] == '1' else None\n"
            "torch.manual_seed(0); torch.set_num_threads(1)\n"
            "x = torch.randn(64, 3, 96, 96, requires_grad=True); w = torch.randn(16, 3, 3, 3, requires_grad=True)\n"
            "y = torch.nn.functional.conv2d(x, w).relu().square().mean(); y.backward()\n"
            "print(applied, y.item().hex(), float(x.grad.abs().sum()).hex(), float(w.grad.sum()).hex())")
    out = [subprocess.run([sys.executable, "-c", code, flag], capture_output=True, text=True, check=True,
                          cwd=Path(__file__).resolve().parents[2]).stdout
           for flag in ("0", "1")]
    plain, tuned = (o.split(" ", 1) for o in out)
    assert plain[0] == "None" and tuned[0] in ("True", "False")
    if platform.libc_ver()[0] == "glibc":
        assert tuned[0] == "True"  # the settings did take effect in the tuned process
    # A smoke test: the same numbers with and without (only where memory comes from changes).
    assert plain[1] == tuned[1] and plain[1].strip()
