"""benchmarks/common.py's plot writer: atomic like every other output."""

import os

import pytest

from benchmarks.common import save_plot
from toolkit.errors import ToolkitError


def test_plot_is_written_whole_with_the_umask_mode(tmp_path):
    mask = os.umask(0)
    os.umask(mask)
    out = save_plot(tmp_path / "p.png", {"a": ([1, 2, 3], [3, 1, 2])}, xlabel="x", ylabel="y", title="t")
    assert out.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n" and out.stat().st_mode & 0o777 == 0o666 & ~mask
    assert sorted(tmp_path.iterdir()) == [out]  # no temporary file left beside it


def test_plot_into_an_unwritable_place_is_a_clear_error(tmp_path):
    (tmp_path / "afile").write_text("")
    with pytest.raises(ToolkitError, match="cannot write here"):
        save_plot(tmp_path / "afile" / "p.png", {"a": ([1, 2], [1, 2])}, xlabel="x", ylabel="y", title="t")
    assert sorted(tmp_path.iterdir()) == [tmp_path / "afile"]
