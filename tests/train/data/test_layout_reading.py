"""GazeDataset reads the peers' files in native conventions (train.data.layouts): a GazeGaussian file's gaze
sign and 3D frame are converted when its labels are read; layouts without what the stages need are one line."""

from __future__ import annotations

import numpy as np
import pytest

from tests.train.data.peer_fixtures import (
    native_truth,
    write_ditgaze,
    write_gazegaussian,
    write_gazenerf,
    write_xgaze,
)
from toolkit.errors import ToolkitError
from train.data.dataset import GazeDataset


@pytest.fixture(scope="module")
def truth():
    return native_truth(n_frames=2, n_cams=3, seed=4)


@pytest.mark.parametrize("gazenerf_keys", [True, False])
def test_a_gazegaussian_file_reads_as_native(tmp_path, truth, gazenerf_keys):
    path = tmp_path / "xgaze_subject0003.h5"
    write_gazegaussian(path, truth, gazenerf_keys=gazenerf_keys)
    ds = GazeDataset([path], layout="auto" if gazenerf_keys else "gazegaussian")
    assert ds.layouts[0] == "gazegaussian" and len(ds) == 6
    r = truth.rows
    for i in range(len(ds)):
        s = ds[i]
        np.testing.assert_allclose(s["pitchyaw_head"].numpy(), r["pitchyaw_head"][i], atol=1e-6)  # sign restored
        # world frame, with the head's scale folded in (train.data.dataset.fold_head_scale)
        np.testing.assert_allclose(s["landmarks_3d"].numpy(), r["facial_landmarks_3d"][i] / r["scale"][i, 0], atol=1e-5)
        assert int(s["cam_index"]) == r["cam_index"][i]
        assert int(s["frame_index"]) == (r["frame_index"][i] if gazenerf_keys else i)
        assert s["scale"].shape == (1,) and float(s["scale"]) == 1.0 and r["scale"][i, 0] != 1


def test_a_native_file_reads_unchanged(tmp_path, truth):
    path = write_ditgaze(tmp_path / "subject0000.h5", truth)
    ds = GazeDataset([path])
    assert ds.layouts[0] == "ditgaze"
    np.testing.assert_array_equal(ds.read_row(0, 2)["pitchyaw_head"], truth.rows["pitchyaw_head"][2])


def test_the_release_layout_the_stages_cannot_use_is_one_line(tmp_path, truth):
    xg = tmp_path / "subject0002.h5"
    write_xgaze(xg, truth)
    with pytest.raises(ToolkitError, match=r"subject0002.h5: a xgaze file .* has no .*head_mask") as err:
        GazeDataset([xg])
    assert "\n" not in str(err.value) and "vertice" not in str(err.value)  # the mesh: with_mesh readers only


def test_a_gazenerf_file_reads_but_has_no_mesh(tmp_path, truth):
    """GazeNeRF's files (no pose, scale or 3D keys) are read, converted whole (tests/train/data/
    test_gazenerf_files.py); a reader asking for the mesh, which nothing makes up, is one line."""
    nerf = tmp_path / "xgaze_subject0001.h5"
    write_gazenerf(nerf, truth)
    ds = GazeDataset([nerf])
    assert ds.layouts == ["gazenerf"] and ds[0]["latent_code"].shape == (179,)
    with pytest.raises(ToolkitError, match=r"xgaze_subject0001.h5: with_mesh: a gazenerf file has no key 'vertice'"):
        GazeDataset([nerf], with_mesh=True)


def test_a_named_layout_that_contradicts_the_file_is_one_line(tmp_path, truth):
    path = write_ditgaze(tmp_path / "subject0000.h5", truth)
    with pytest.raises(ToolkitError, match=r"subject0000.h5: data.layout=gazegaussian") as err:
        GazeDataset([path], layout="gazegaussian")
    assert "\n" not in str(err.value)
    with pytest.raises(ToolkitError, match=r"layout"):
        GazeDataset([path], layout="nerfie")


def test_inspect_prints_the_layout_and_reads_gaze_natively(tmp_path, truth, capsys):
    from train.data.__main__ import main

    path = tmp_path / "xgaze_subject0003.h5"
    write_gazegaussian(path, truth)
    assert main(["inspect", str(path), "--sheet", str(tmp_path / "sheet.png"), "--n", "2", "--tile", "32"]) == 0
    out = capsys.readouterr().out
    assert "| xgaze_subject0003.h5 | gazegaussian |" in out
    assert "layout gazegaussian: " in out and "pitch = asin(+g_y)" in out
    g = np.degrees(truth.rows["pitchyaw_head"][:, 0])
    assert f"{g.min():.0f}..{g.max():.0f}" in out  # the native pitch range, not its mirror
