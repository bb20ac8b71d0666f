"""train.allocator: glibc's thresholds set once, exported to children, and left alone when the user chose."""

import os
import subprocess
import sys

import pytest

from train import allocator

PROBE = ("import os, json; from train.allocator import keep_large_blocks; first = keep_large_blocks(); "
         "second = keep_large_blocks(); print(json.dumps([first, second, "
         "{k: os.environ.get(k) for k in ('MALLOC_MMAP_THRESHOLD_', 'MALLOC_TRIM_THRESHOLD_')}]))")


def _probe(**env):
    import json

    base = {k: v for k, v in os.environ.items() if k not in allocator.ENV and k != allocator.OPT_OUT}
    out = subprocess.run([sys.executable, "-c", PROBE], env={**base, **env}, capture_output=True, text=True,
                         check=True, cwd=os.path.dirname(os.path.dirname(os.path.dirname(__file__))))
    return json.loads(out.stdout.strip().splitlines()[-1])


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="glibc on Linux only")
def test_thresholds_are_set_once_and_exported_for_spawned_workers():
    first, second, env = _probe()
    if not first:
        pytest.skip("this C library has no mallopt thresholds (not glibc)")
    assert second is False  # the exported settings now stand
    assert env == {k: str(v) for k, v in allocator.ENV.items()}


def test_the_users_settings_and_the_opt_out_are_respected():
    first, _, env = _probe(MALLOC_MMAP_THRESHOLD_="1048576")
    assert first is False and env["MALLOC_MMAP_THRESHOLD_"] == "1048576" and env["MALLOC_TRIM_THRESHOLD_"] is None
    first, _, env = _probe(**{allocator.OPT_OUT: "0"})
    assert first is False and env == {k: None for k in allocator.ENV}
