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


def _tree(folder):
    """{relative path: bytes} of every file under ``folder`` (hidden ones too)."""
    return {str(p.relative_to(folder)): p.read_bytes() for p in sorted(folder.rglob("*")) if p.is_file()}


def test_a_bad_source_file_leaves_the_output_folder_as_it_was(src, tmp_path):
    """Every source is checked before anything is written: an earlier export in OUT_DIR stays whole, a new
    OUT_DIR is not made."""
    import shutil

    bad = tmp_path / "bad"
    shutil.copytree(src, bad)
    with h5py.File(bad / "subject0001.h5", "r+") as f:
        f["pitchyaw_head"][2, 0] = np.nan
    earlier = tmp_path / "earlier"
    assert main(["export", str(src), str(earlier)]) == 0
    before = _tree(earlier)
    for out in (earlier, tmp_path / "new"):
        assert_refused("train.data", ["export", bad, out], r"subject0001\.h5.*pitchyaw_head", inputs=[bad])
    assert _tree(earlier) == before and not (tmp_path / "new").exists()


def test_a_failure_mid_export_writes_nothing(src, tmp_path, monkeypatch):
    """A write that fails on the second file (a full disk) leaves OUT_DIR without any exported file, and no
    staging folder; the error names OUT_DIR's file, not the staging one."""
    from toolkit.errors import ToolkitError
    from train.data import export as export_module

    calls = []

    def write_then_fill_the_disk(path, rows):
        calls.append(path)
        if len(calls) == 2:
            raise ToolkitError(f"{path}: no space left on device; nothing was written (the partial file was removed)")
        real_write(path, rows)

    real_write = export_module._write_peer
    monkeypatch.setattr(export_module, "_write_peer", write_then_fill_the_disk)
    out = tmp_path / "out"
    with pytest.raises(ToolkitError, match=rf"^{out}/xgaze_subject0001\.h5: no space left on device"):
        export_module.export(src, out)
    assert not out.exists()  # the folder it made too


def test_ctrl_c_mid_export_leaves_an_earlier_export_whole(src, tmp_path, monkeypatch):
    from train.data import export as export_module

    out = tmp_path / "out"
    assert main(["export", str(src), str(out)]) == 0
    before = _tree(out)
    real_write, calls = export_module._write_peer, []

    def write_then_interrupt(path, rows):
        calls.append(path)
        if len(calls) == 2:
            raise KeyboardInterrupt
        real_write(path, rows)

    monkeypatch.setattr(export_module, "_write_peer", write_then_interrupt)
    with pytest.raises(KeyboardInterrupt):
        export_module.export(src, out)
    assert _tree(out) == before  # no staging folder left, no file replaced


def test_an_output_folder_holding_another_dataset_is_refused_and_an_earlier_export_replaced(src, tmp_path):
    out = tmp_path / "out"
    out.mkdir()
    (out / "subject0042.h5").write_bytes(b"")
    assert_refused("train.data", ["export", src, out], r"OUT_DIR .*out: holds 1 other dataset file\(s\) "
                   r"\(subject0042\.h5\), which would mix with this export", inputs=[src])
    (out / "subject0042.h5").unlink()
    assert main(["export", str(src), str(out)]) == 0
    first = _tree(out)
    assert main(["export", str(src), str(out)]) == 0  # the same subjects again: replaced, nothing else there
    assert _tree(out).keys() == first.keys()


def test_the_split_is_the_sources_and_a_subject_it_leaves_out_stays_out(src, tmp_path):
    import shutil

    partial = tmp_path / "partial"
    shutil.copytree(src, partial)
    (partial / "split.json").write_text(json.dumps({"train": ["subject0000"], "test": ["subject0002"]}))
    main(["export", str(partial), str(tmp_path / "gg")])
    split = json.loads((tmp_path / "gg" / "train_test_split.json").read_text())
    assert split["train"] == ["subject0000.h5"] and split["val"] == ["subject0002.h5"]
    assert GazeDataset([tmp_path / "gg"], split="train").files == [tmp_path / "gg" / "xgaze_subject0000.h5"]


def test_a_ditgaze_export_is_a_whole_copy_in_the_current_form(tmp_path):
    """Attributes (what makes a subject synthetic: the evaluation re-renders its targets), subject arrays and every
    row kept; indices [N, 1]; split.json in the native form."""
    from train.data.pairing import is_synthetic_file

    synth = tmp_path / "synth"
    assert main(["synth", "--subjects", "2", "--frames", "2", "--res", "32", "--out", str(synth)]) == 0
    assert main(["export", str(synth), str(tmp_path / "copy"), "--layout", "ditgaze"]) == 0
    assert json.loads((tmp_path / "copy" / "split.json").read_text()) == json.loads((synth / "split.json").read_text())
    for name in ("subject0000.h5", "subject0001.h5"):
        assert is_synthetic_file(tmp_path / "copy" / name)
        with h5py.File(synth / name) as a, h5py.File(tmp_path / "copy" / name) as b:
            assert dict(a.attrs).keys() == dict(b.attrs).keys()
            assert all(np.array_equal(a.attrs[k], b.attrs[k]) for k in a.attrs)
            assert set(a) == set(b) and b["cam_index"].shape == (len(b["face_patch"]), 1)
            for k in a:
                np.testing.assert_array_equal(np.asarray(a[k]).reshape(b[k].shape), b[k][()], err_msg=k)
