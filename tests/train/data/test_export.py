"""``python -m train.data export --layout gazegaussian``: files GazeGaussian's loader reads with correct
geometry, and that read back as the native labels."""

from __future__ import annotations

import json

import h5py
import numpy as np
import pytest

from tests.fuzz.cli import assert_refused
from tests.train.data.peer_fixtures import write_native_folder
from train.data.__main__ import main
from train.data.dataset import GazeDataset


@pytest.fixture(scope="module")
def src(tmp_path_factory):
    return write_native_folder(tmp_path_factory.mktemp("native"), first_seed=10)


@pytest.fixture(scope="module")
def exported(src, tmp_path_factory):
    out = tmp_path_factory.mktemp("gg") / "gg"
    assert main(["export", str(src), str(out)]) == 0
    return out


def test_names_shapes_and_split_are_gazegaussians(exported):
    assert sorted(p.name for p in exported.glob("*.h5")) == [f"xgaze_subject000{i}.h5" for i in range(3)]
    split = json.loads((exported / "train_test_split.json").read_text())
    # GazeGaussian configs/dataset/eth_xgaze/train_test_split.json L84-100: "subjectNNNN.h5", held out under "val"
    assert split["train"] == ["subject0000.h5", "subject0001.h5"] and split["val"] == ["subject0002.h5"]
    with h5py.File(exported / "xgaze_subject0000.h5") as f:
        # dataloader/eth_xgaze.py L442 cam_index[idx, :], L480 scale[idx, :]: 2-D
        assert f["cam_index"].shape == (6, 1) and f["scale"].shape == (6, 1) and f["frame_index"].shape == (6, 1)


def test_gazegaussians_loader_geometry_reprojects(exported):
    """GazeGaussian dataloader/eth_xgaze.py L440: ldms_3d = (ldms_3d - w2c_Tvec) @ w2c_Rmat^T, then L464-472
    renders that frame through w2c and inmat: the 3D landmarks must land on the stored 2D ones."""
    with h5py.File(exported / "xgaze_subject0001.h5") as f:
        p, R, t = f["facial_landmarks_3d"][:].astype(np.float64), f["w2c_Rmat"][:], f["w2c_Tvec"][:]
        K, uv = f["inmat"][:], f["facial_landmarks"][:]
    q = np.einsum("nkj,nij->nki", p - t[:, None], R)  # (p - t) @ R^T
    cam = np.einsum("nij,nkj->nki", R, q) + t[:, None]
    proj = np.einsum("nij,nkj->nki", K, cam)
    err = np.linalg.norm(proj[..., :2] / proj[..., 2:] - uv, axis=-1)
    assert err.max() < 1.5, err.max()


def test_the_round_trip_gives_back_the_native_labels(src, exported):
    for i in range(3):
        a = GazeDataset([src / f"subject000{i}.h5"])
        b = GazeDataset([exported / f"xgaze_subject000{i}.h5"])
        assert b.layouts == ["gazegaussian"] and len(a) == len(b)
        for row in range(len(a)):
            x, y = a[row], b[row]
            np.testing.assert_allclose(y["pitchyaw_head"], x["pitchyaw_head"], atol=1e-4)
            np.testing.assert_allclose(y["landmarks_3d"], x["landmarks_3d"], atol=1e-5)
            for k in ("image", "head_mask", "pose", "scale", "viewmat", "K", "latent_code"):
                np.testing.assert_allclose(y[k], x[k], atol=1e-6, err_msg=k)
            assert int(y["cam_index"]) == int(x["cam_index"]) and int(y["frame_index"]) == int(x["frame_index"])


def test_bad_exports_are_one_line(src, exported, tmp_path):
    assert_refused("train.data", ["export", src, src], r"is the input dataset", inputs=[src])
    assert_refused("train.data", ["export", exported, tmp_path / "again"],
                   r"export reads this project's own files; this one is gazegaussian", inputs=[exported],
                   out_dir=tmp_path)
    assert_refused("train.data", ["export", src, tmp_path / "x", "--layout", "gazenerf"], r"invalid choice",
                   out_dir=tmp_path)
