"""A run reads its subjects in their layout: the peers' split file decides the split, the geometry stage sees
a GazeGaussian file's views as the native file's, and a named ``data.layout`` that the keys contradict is one
line before any work."""

from __future__ import annotations

import json

import numpy as np
import pytest

from tests.fuzz.cli import assert_refused
from tests.train.data.peer_fixtures import native_truth, write_ditgaze, write_native_folder
from train.data.__main__ import main as data_main
from train.data.dataset import find_subject_files, split_files


@pytest.fixture(scope="module")
def native(tmp_path_factory):
    return write_native_folder(tmp_path_factory.mktemp("native"), first_seed=20)


@pytest.fixture(scope="module")
def gazegaussian(native, tmp_path_factory):
    out = tmp_path_factory.mktemp("gg") / "gg"
    assert data_main(["export", str(native), str(out)]) == 0
    return out


def test_the_peers_split_file_decides_the_split(gazegaussian):
    # GazeGaussian dataloader/eth_xgaze.py L103-118, L163: held-out names under "val", "subjectNNNN.h5" for the
    # file xgaze_subjectNNNN.h5; the exported folder has only that split file.
    assert not (gazegaussian / "split.json").exists()
    files = find_subject_files([gazegaussian])
    assert [f.name for f in split_files(files, "test")] == ["xgaze_subject0002.h5"]
    assert [f.name for f in split_files(files, "train", layout="gazegaussian")] == \
        ["xgaze_subject0000.h5", "xgaze_subject0001.h5"]


def test_a_split_naming_a_missing_subject_is_one_line(gazegaussian, tmp_path):
    sf = tmp_path / "train_test_split.json"
    sf.write_text(json.dumps({"train": ["subject0000.h5"], "val": ["subject0042.h5"]}))
    files = find_subject_files([gazegaussian])
    with pytest.raises(Exception, match=r"'val' names subject subject0042, which is not among the 3"):
        split_files(files, "test", sf)
    # a native split file given for peer files: its form is the layout's, so its keys are named
    sf.write_text(json.dumps({"train": ["subject0000.h5"], "test": ["subject0002.h5"]}))
    with pytest.raises(Exception, match=r"no key 'val', expected the gazegaussian form"):
        split_files(files, "test", sf)


def test_the_geometry_stage_reads_a_gazegaussian_file_as_the_native_one(native, gazegaussian):
    from geometry.fit_dataset import read_subject
    from train.stages.geometry import subject_views_in_layout

    want = read_subject(native / "subject0001.h5")
    got = subject_views_in_layout(gazegaussian / "xgaze_subject0001.h5")
    assert bool((got["masks"] == want["masks"]).all())
    np.testing.assert_allclose(got["viewmats"].numpy(), want["viewmats"].numpy(), atol=2e-5)
    np.testing.assert_allclose(got["landmarks"].numpy(), want["landmarks"].numpy(), atol=2e-6)
    # read as if native, the same file's landmarks land in the wrong frame (GazeGaussian stores (p - t) R^T's inverse)
    naive = read_subject(gazegaussian / "xgaze_subject0001.h5")
    assert float((naive["landmarks"] - want["landmarks"]).abs().max()) > 0.05


def test_a_named_layout_the_keys_contradict_is_refused_before_any_work(native, gazegaussian, tmp_path):
    run = tmp_path / "run"
    # GazeNeRF dataset_pre_processing.py L258-381 writes c2w_* and inv_inmat, which native files lack
    assert_refused("train.run", ["--preset", "tiny", "--run-dir", run, f"data.root={native}", "data.layout=gazenerf"],
                   r"subject0000\.h5: data\.layout=gazenerf requires keys \['c2w_Rmat', 'c2w_Tvec', 'inv_inmat'",
                   inputs=[native])
    assert not run.exists()
    # GazeGaussian indexes cam_index[idx, :] (dataloader/eth_xgaze.py L442): a 1-D index contradicts it
    assert_refused("train.run", ["--preset", "tiny", "--run-dir", run, f"data.root={native}",
                                 "data.layout=gazegaussian"],
                   r"data\.layout=gazegaussian: key 'cam_index' \[6\] \(expected N,1\)", inputs=[native])
    assert not run.exists()
    # An exported GazeGaussian file keeps GazeNeRF's c2w_* and inv_inmat (train.data.export): named native, its gaze
    # pitch would be read with the wrong sign
    assert_refused("train.data", ["inspect", gazegaussian / "xgaze_subject0000.h5", "--layout", "ditgaze"],
                   r"data\.layout=ditgaze: the file has \['c2w_Rmat', 'c2w_Tvec', 'inv_inmat'\], keys only other "
                   r"layouts write \(it is a gazegaussian file\)", inputs=[gazegaussian])
    assert_refused("train.run", ["--preset", "tiny", "--run-dir", run, f"data.root={native}",
                                 f"data.split_file={tmp_path / 'none.json'}"],
                   r"data\.split_file.*no such file", inputs=[native])
    assert not run.exists()


def test_cross_dataset_evaluation_scores_another_datasets_held_out_subjects(tiny_run, gazegaussian, tmp_path):
    """eval.data_root: a run trained on the synthetic data evaluated on a GazeGaussian folder's held-out subjects
    ('val' of its train_test_split.json), against their stored targets; the report names both datasets."""
    import shutil

    import torch

    from train import run

    d = tmp_path / "run"
    shutil.copytree(tiny_run, d)
    old = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        assert run.main(["--run-dir", str(d), "--stages", "eval", f"eval.data_root={gazegaussian}",
                         "eval.pairs_per_subject=2", "eval.tta_steps=0"]) == 0
    finally:
        torch.set_num_threads(old)
    metrics = json.loads((d / "metrics.json").read_text())
    assert [r["subject"] for r in metrics["per_subject"]] == ["xgaze_subject0002.h5"]
    assert metrics["protocol"].startswith("GazeNeRF: stored targets")
    assert metrics["datasets"] == {"train": "synthetic (generated by the data stage)",
                                   "eval": "gg (gazegaussian layout)"}
    assert "evaluated on gg (gazegaussian layout)" in (d / "report.md").read_text()
    assert_refused("train.run", ["--run-dir", d, "--stages", "eval", f"eval.data_root={tmp_path / 'none'}"],
                   r"eval\.data_root.*no such folder")


def test_split_files_name_the_subject_without_the_datasets_prefix(gazegaussian, tmp_path):
    """GazeNeRF names an MPIIFaceGaze file mpii_subject0000.h5 (dataset_pre_processing.py L496) and a
    ColumbiaGaze one columbia_subject0001.h5 (L844), and lists the subject alone, every one under 'val'
    (data/mpii_face_gaze/train_test_split.json, data/columbia/train_test_split.json)."""
    import shutil

    folder = tmp_path / "mpii"
    folder.mkdir()
    for i in range(3):
        shutil.copy(gazegaussian / f"xgaze_subject000{i}.h5", folder / f"mpii_subject000{i}.h5")
    (folder / "train_test_split.json").write_text(json.dumps(
        {"train": [], "val": ["subject0000.h5", "subject0001.h5", "subject0002.h5"]}))
    files = find_subject_files([folder])
    assert [f.name for f in split_files(files, "test")] == [f"mpii_subject000{i}.h5" for i in range(3)]
    shutil.copy(gazegaussian / "xgaze_subject0000.h5", folder / "subject0000.h5")
    with pytest.raises(Exception, match=r"the files mpii_subject0000\.h5 and subject0000\.h5 are both subject subject0000"):
        split_files(find_subject_files([folder]), "test")


def test_the_other_datasets_pairing_lists_are_read_verbatim(tmp_path):
    """GazeNeRF's cross-dataset lists differ in length: configs/config_files/columbia_evaluation_target_single_subject.txt
    holds 52 targets in 52..103, mpii_... 50 in 50..99 (one integer a line, input row i -> target row list[i])."""
    from train.data.pairing import check_pairing_rows, load_pairing, subject_pairing

    targets = np.random.default_rng(0).permutation(np.arange(52, 104))
    path = tmp_path / "columbia_evaluation_target_single_subject.txt"
    path.write_text("".join(f"{t}\n" for t in targets))
    pairs = subject_pairing(load_pairing(path), "columbia_subject0001")
    assert pairs.shape == (52, 2) and (pairs[:, 0] == np.arange(52)).all() and (pairs[:, 1] == targets).all()
    short = tmp_path / "columbia_subject0001.h5"
    write_ditgaze(short, native_truth(n_frames=10, n_cams=10, seed=3))  # 100 rows: target 103 is past the end
    with pytest.raises(Exception, match=r"columbia_subject0001"):
        check_pairing_rows([short], load_pairing(path), "the pairing file")
