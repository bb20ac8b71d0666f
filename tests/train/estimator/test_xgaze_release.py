"""ETH-XGaze release files (``train.data.layouts.XGAZE``) feed the estimator stage: ``train.data.patches`` reads
their face patches (BGR -> RGB) and labels (``face_gaze``, ``face_head_pose``) as the native rows of the same
images, the stage trains and scores on them, and every other stage refuses them in one line.

The fixture renders one native synthetic subject and writes its rows as the release does
(xucong-zhang/ETH-XGaze ef9bff0, normalization_example.py): the labels are computed here the release's way from
the native head-frame gaze, head pose and camera, not through ``train.data.layouts``, so the reader is checked
against the native labels of the same rows (frame and sign) and not against itself.
"""

from __future__ import annotations

import contextlib
import io
import json
import shutil

import cv2
import h5py
import numpy as np
import pytest
import torch

from tests.train.data.peer_fixtures import native_vector, rodrigues
from toolkit.errors import ToolkitError, run_cli
from train.data.patches import ReleasePatches, release_layout, release_rows

RES = 32  # rendered patch size (the release's are 224 / 448)
ROWS = 6  # rows per release subject: the rendered subject's 18 views cut in three


def _eth_face_gaze(R_norm_head: np.ndarray, gaze_head: np.ndarray) -> np.ndarray:
    """normalization_example.py L73-75: g = R (gc - face centre), normalized, in the normalized camera;
    L313-315: theta = arcsin(-g[1]), phi = arctan2(-g[0], -g[2])."""
    g = np.einsum("nij,nj->ni", R_norm_head, native_vector(gaze_head))
    g /= np.linalg.norm(g, axis=1, keepdims=True)
    return np.stack([np.arcsin(-g[:, 1]), np.arctan2(-g[:, 0], -g[:, 2])], -1)


def _eth_head_pose(R_norm_head: np.ndarray) -> np.ndarray:
    """normalization_example.py L69 (hR_norm = R hR), L327-331: Zv = hR_norm[:, 2], (asin Zv[1], atan2(Zv[0], Zv[2]))."""
    Z = R_norm_head[:, :, 2]
    return np.stack([np.arcsin(Z[:, 1]), np.arctan2(Z[:, 0], Z[:, 2])], -1)


def write_release(path, rows: dict[str, np.ndarray], *, labels: bool = True) -> None:
    """A release subject file as normalization_example.py L294-331 writes it: int (N, 1) indices (L295-298),
    float64 labels (L305-310), one chunk a row, lzf patches (L302-304), BGR as cv2 read it (L265, L323). No
    facial_landmarks: the published xgaze_224 files hold none (train/data/layouts.py XGAZE); no face_gaze for a
    test subject (data_loader.py L64-66)."""
    n = len(rows["rgb"])
    with h5py.File(path, "w") as f:
        def put(key, data, dtype, lzf=False):
            data = np.asarray(data, dtype)
            f.create_dataset(key, data=data, chunks=(1,) + data.shape[1:], compression="lzf" if lzf else None)

        put("frame_index", rows["frame_index"].reshape(n, 1), np.int64)
        put("cam_index", rows["cam_index"].reshape(n, 1), np.int64)
        put("face_patch", rows["rgb"][..., ::-1], np.uint8, lzf=True)
        put("face_mat_norm", rows["w2c_Rmat"], np.float64)  # the world frame stands in for the original camera
        if labels:
            put("face_gaze", rows["face_gaze"], np.float64)
        put("face_head_pose", rows["face_head_pose"], np.float64)


@pytest.fixture(scope="module")
def release(tmp_path_factory):
    """(folder of release files subject0000-0002, native rows of the same 18 images: ``image`` uint8 [N, 3, R, R]
    RGB and ``label`` [N, 4] as the estimator stage reads the native file, and the stored ``pitchyaw_head``)."""
    from tests.train.helpers import one_frame_subject_file
    from train.data.dataset import GazeDataset
    from train.stages.estimator import _estimator_row

    native_dir = tmp_path_factory.mktemp("native")
    path = one_frame_subject_file(native_dir, subject_seed=11, frame_seed=12, res=RES)
    ds = GazeDataset([path])
    native = [_estimator_row(ds[i]) for i in range(len(ds))]
    with h5py.File(path, "r") as f:
        raw = {k: f[k][()] for k in ("pose", "w2c_Rmat", "pitchyaw_head", "cam_index", "frame_index")}
    R_norm_head = raw["w2c_Rmat"].astype(np.float64) @ rodrigues(raw["pose"][:, :3].astype(np.float64))
    rows = {"rgb": np.stack([r["image"].permute(1, 2, 0).numpy() for r in native]),
            "face_gaze": _eth_face_gaze(R_norm_head, raw["pitchyaw_head"].astype(np.float64)),
            "face_head_pose": _eth_head_pose(R_norm_head), **raw}
    folder = tmp_path_factory.mktemp("xgaze_32") / "train"
    folder.mkdir()
    for s in range(len(native) // ROWS):
        write_release(folder / f"subject{s:04d}.h5", {k: v[s * ROWS:(s + 1) * ROWS] for k, v in rows.items()})
    return {"dir": folder, "rows": rows, "native_path": path,
            "image": torch.stack([r["image"] for r in native]), "label": torch.stack([r["label"] for r in native]),
            "gaze_head": torch.as_tensor(raw["pitchyaw_head"])}


def _files(folder):
    return sorted(folder.glob("*.h5"))


def _one_line(err) -> str:
    text = str(err.value)
    assert "\n" not in text
    return text


# ------------------------------------------------------------------------------------------------ the reader

def test_the_reader_gives_the_native_images_in_rgb_and_the_native_labels(release):
    p = ReleasePatches(_files(release["dir"]), RES)
    assert len(p) == 18 and p.labels.shape == (18, 4) and p.labels.dtype == torch.float32 and p.landmarks is None
    images = torch.stack([p[i]["image"] for i in range(len(p))])
    assert images.dtype == torch.uint8 and images.shape == (18, 3, RES, RES)
    # BGR -> RGB (data_loader.py L130): exactly the native estimator's images; the unflipped patches are not
    assert torch.equal(images, release["image"]) and not torch.equal(images.flip(1), release["image"])
    # face_gaze is the camera-frame gaze with the native sign, face_head_pose the native one (radians)
    assert torch.allclose(p.labels, release["label"], atol=2e-5)
    assert (p.labels[:, :2] - release["gaze_head"]).abs().max() > 0.1  # the frames differ: the check has power
    assert float(release["label"][:, 0].min()) < -0.05 < 0.05 < float(release["label"][:, 0].max())  # both signs
    # resized as the stages resize (area averaging when shrinking)
    small = ReleasePatches(_files(release["dir"])[1:2], 16)
    want = cv2.resize(np.ascontiguousarray(release["rows"]["rgb"][ROWS + 2]), (16, 16), interpolation=cv2.INTER_AREA)
    assert torch.equal(small[2]["image"], torch.from_numpy(want).permute(2, 0, 1))
    assert small.locate(5) == (0, 5)
    p.close()
    small.close()


def test_release_rows_stream_through_a_row_source(release):
    images, labels, lms = release_rows(_files(release["dir"]), RES, workers=2, cache_bytes=4 * 3 * RES * RES)
    try:
        assert lms is None and images.shape == (18, 3, RES, RES) and torch.equal(labels, ReleasePatches(
            _files(release["dir"]), RES).labels)
        idx = torch.randperm(18, generator=torch.Generator().manual_seed(0))
        images.prefetch(idx[:8])
        assert torch.equal(images[idx], release["image"][idx]) and torch.equal(images[3:7], release["image"][3:7])
        assert images.source.cached_bytes <= 4 * 3 * RES * RES  # a bounded cache, not the split in memory
    finally:
        images.source.close()
        images.source.dataset.close()


def test_release_files_are_detected(release):
    assert release_layout(_files(release["dir"])) and release_layout(_files(release["dir"]), "xgaze")
    assert not release_layout([release["native_path"]]) and not release_layout(_files(release["dir"]), "ditgaze")


# ------------------------------------------------------------------------------------------------ the stage

def _context(tmp_path, root, **estimator):
    from train.presets import preset
    from train.stages.pipeline import RunContext

    cfg = preset("tiny")
    cfg.data.root = str(root)
    cfg.data.test_fraction = 0.34  # 3 subjects: the last one held out
    cfg.estimator.crop = "face"
    for k, v in estimator.items():
        setattr(cfg.estimator, k, v)
    run_dir = tmp_path / "run"
    run_dir.mkdir(parents=True, exist_ok=True)
    lines: list[str] = []
    return RunContext(run_dir, cfg, log=lines.append), lines


def _eth_angular_error(pred: np.ndarray, label: np.ndarray) -> np.ndarray:
    """ETH-XGaze utils.py L24-40, L60-75: both (pitch, yaw) as vectors (its sign convention), the angle between."""
    def vec(py):
        return np.stack([np.cos(py[:, 0]) * np.sin(py[:, 1]), np.sin(py[:, 0]), np.cos(py[:, 0]) * np.cos(py[:, 1])], -1)
    a, b = vec(pred), vec(label)
    cos = (a * b).sum(1) / np.linalg.norm(a, axis=1) / np.linalg.norm(b, axis=1)
    return np.degrees(np.arccos(np.clip(cos, -1, 1)))


def test_the_stage_trains_on_release_patches_and_scores_the_held_out_subject(release, tmp_path):
    from toolkit.io import load_checkpoint
    from train.estimator.network import GazeEstimator
    from train.stages.estimator import stage_estimator

    ctx, lines = _context(tmp_path, release["dir"])
    outs = stage_estimator(ctx)
    assert outs == {"loss": "estimator_loss.safetensors", "eval": "estimator_eval.safetensors",
                    "summary": "estimators.json"}
    assert "[estimator] synthetic_subjects ignored: data.root is an external dataset" in lines
    assert any("ETH-XGaze release files: 2 training and 1 scored held-out subject(s); face patches read at 32²"
               in s for s in lines)
    summary = json.loads((ctx.run_dir / "estimators.json").read_text())
    for role in ("loss", "eval"):
        rec = summary[role]
        assert rec["train_images"] == 2 * ROWS and rec["step"] == ctx.config.estimator.steps
        assert 0 <= rec["val_gaze_deg"] <= 180 and 0 <= rec["val_head_deg"] <= 180 and np.isfinite(rec["loss"])
        model = GazeEstimator.load(ctx.run_dir / outs[role])
        assert model.config.input_size == 32 and model.config.crop == (0.0, 1.0, 0.0, 1.0) and not model.config.eyes
        assert load_checkpoint(ctx.run_dir / outs[role])[1]["data_layout"] == "xgaze"
        # The report's held-out error is ETH-XGaze's own metric (trainer.py L125): the estimator's camera-frame
        # gaze on the held-out subject's RGB patches against its stored face_gaze.
        with h5py.File(release["dir"] / "subject0002.h5", "r") as f:
            rgb = torch.from_numpy(f["face_patch"][()][..., ::-1].copy()).permute(0, 3, 1, 2).float() / 255
            face_gaze = f["face_gaze"][()]
        with torch.no_grad():
            pred = model(rgb)[:, :2].double().numpy()
        assert abs(_eth_angular_error(pred, face_gaze).mean() - rec["val_gaze_deg"]) < 1e-3
        assert any(s.startswith(f"[estimator] {role}: 12 training images, held-out gaze error") for s in lines)


def test_held_out_subjects_without_labels_are_not_scored(release, tmp_path):
    """The release's split file names test subjects that data.root (its train/ folder) lacks or that have no
    face_gaze: the stage says so in one line each, trains on the labelled training subjects and scores nothing."""
    from train.stages.estimator import stage_estimator

    folder = tmp_path / "train"
    folder.mkdir()
    for s in ("subject0000", "subject0001"):
        shutil.copy(release["dir"] / f"{s}.h5", folder / f"{s}.h5")
    for s in ("subject0007", "subject0008"):  # copies of subject0002 without labels
        shutil.copy(release["dir"] / "subject0002.h5", folder / f"{s}.h5")
        with h5py.File(folder / f"{s}.h5", "r+") as f:
            del f["face_gaze"]
    (folder / "train_test_split.json").write_text(json.dumps({  # ETH-XGaze data_loader.py L31-42, L64
        "train": ["subject0000.h5", "subject0001.h5", "subject0008.h5"], "test": ["subject0007.h5", "subject0099.h5"],
        "test_person_specific": []}))
    ctx, lines = _context(tmp_path, folder, steps=1)
    stage_estimator(ctx)
    assert any("1 training subject(s) without face_gaze left out" in s and "subject0008" in s for s in lines)
    assert any("held-out subjects not scored: 1 of train_test_split.json's 'test' list not in data.root, 1 without "
               "face_gaze" in s for s in lines)
    assert any("no held-out subject with face_gaze: the estimators train on 2 subjects and are not scored" in s
               for s in lines)
    summary = json.loads((ctx.run_dir / "estimators.json").read_text())
    assert all("val_gaze_deg" not in rec and rec["train_images"] == 2 * ROWS for rec in summary.values())
    assert sum("not scored (no held-out images with gaze labels)" in s for s in lines) == 2


# ------------------------------------------------------------------------------------------------ the CLI

def _cli(argv) -> tuple[int, str]:
    from train import run

    err = io.StringIO()
    with contextlib.redirect_stderr(err), contextlib.redirect_stdout(io.StringIO()):
        code = run_cli(run.main, [str(a) for a in argv])
    return code, err.getvalue()


def test_a_run_trains_its_estimators_on_release_files(release, tmp_path):
    run_dir = tmp_path / "run"
    code, err = _cli(["--preset", "tiny", "--run-dir", run_dir, "--stages", "data,estimator",
                      f"data.root={release['dir']}", "data.layout=xgaze", "estimator.crop=face", "estimator.steps=2"])
    assert code == 0, err
    assert (run_dir / "estimator_loss.safetensors").is_file() and (run_dir / "estimator_eval.safetensors").is_file()
    assert set(json.loads((run_dir / "estimators.json").read_text())) == {"loss", "eval"}


def test_a_run_trains_its_estimators_on_release_files_without_help(release, tmp_path):
    code, err = _cli(["--preset", "tiny", "--run-dir", tmp_path / "run", "--stages", "data,estimator",
                      f"data.root={release['dir']}", "estimator.crop=face", "estimator.steps=2"])
    assert code == 0, err


@pytest.mark.parametrize("stages", ["data,geometry", "data,codec"])
def test_the_other_stages_refuse_release_files_in_one_line(release, tmp_path, stages):
    code, err = _cli(["--preset", "tiny", "--run-dir", tmp_path / "run", "--stages", stages,
                      f"data.root={release['dir']}"])
    lines = [s for s in err.splitlines() if "error:" in s]
    assert code == 2 and len(lines) == 1 and "Traceback" not in err, err
    assert "subject000" in lines[0] and "head_mask" in lines[0] and "w2c_Rmat" in lines[0]


def test_release_files_as_the_eval_data_are_refused_before_any_training(release, tmp_path):
    """eval.data_root is read by the eval stage alone, which cannot score release files (no masks, cameras or codes):
    the config check says so before the first stage, not the eval stage after training."""
    code, err = _cli(["--preset", "tiny", "--run-dir", tmp_path / "run", "--stages", "data",
                      f"eval.data_root={release['dir']}"])
    lines = [s for s in err.splitlines() if "error:" in s]
    assert code == 2 and len(lines) == 1 and "Traceback" not in err, err
    assert lines[0].startswith("error: config key 'eval.data_root': ") and "head_mask" in lines[0]
    assert not (tmp_path / "run" / "data").exists()


def test_inspect_tables_and_draws_release_files_a_test_subject_too(release, tmp_path, capsys):
    """`python -m train.data inspect` on the release: its own table (gaze in native conventions, from face_gaze;
    none for a held-out test subject) and a sheet of the patches as RGB, not a refusal for lacking masks."""
    from train.data.__main__ import main

    folder = tmp_path / "train"
    shutil.copytree(release["dir"], folder)
    with h5py.File(folder / "subject0002.h5", "r+") as f:  # a test subject: labels withheld (README.md L45-46)
        del f["face_gaze"]
    sheet = tmp_path / "sheet.png"
    assert run_cli(main, ["inspect", str(folder), "--sheet", str(sheet), "--n", "6", "--tile", "32"]) == 0
    lines = {ln.split("|")[1].strip(): [c.strip() for c in ln.split("|")[2:-1]]
             for ln in capsys.readouterr().out.splitlines() if ln.startswith("| subject")}
    g = np.degrees(release["rows"]["face_gaze"][:ROWS])  # subject0000's rows, as stored (the native pitch sign)
    assert lines["subject0000.h5"][:5] == ["xgaze", str(ROWS), f"{RES}x{RES}", "6", "1"]
    assert lines["subject0000.h5"][5] == f"{g[:, 0].min():.0f}..{g[:, 0].max():.0f}"
    assert lines["subject0002.h5"][5:7] == ["-", "-"]
    img = cv2.imread(str(sheet))[..., ::-1]
    assert img.shape == (32, 6 * 32, 3)
    first = release["rows"]["rgb"][0].astype(int)  # RES = the tile: drawn as stored, but for its arrow
    coloured = np.abs(first[..., 0] - first[..., 2]) > 30  # where RGB and BGR differ
    assert coloured.sum() > 20
    tile = img[:, :32].astype(int)
    assert np.median(np.abs(tile - first)[coloured]) < 2 < np.median(np.abs(tile - first[..., ::-1])[coloured])


# ------------------------------------------------------------------------------------------------ bad input

def _bad_copy(release, tmp_path, edit):
    folder = tmp_path / "bad"
    shutil.copytree(release["dir"], folder)
    with h5py.File(folder / "subject0001.h5", "r+") as f:
        edit(f)
    return folder


def _replace(key, data):
    def edit(f):
        del f[key]
        f.create_dataset(key, data=data)
    return edit


def _nan_gaze(f):
    f["face_gaze"][3] = [np.nan, 0.1]


BAD = {
    "nan_gaze": (_nan_gaze, r"subject0001.h5: key 'face_gaze' row 3 holds NaN or inf"),
    "gray_patch": (_replace("face_patch", np.zeros((ROWS, RES, RES), np.uint8)), r"subject0001.h5.*'face_patch'"),
    "wide_patch": (_replace("face_patch", np.zeros((ROWS, RES, RES + 8, 3), np.uint8)),
                   r"subject0001.h5: key 'face_patch' has shape \[6, 32, 40, 3\], expected square"),
    "float_patch": (_replace("face_patch", np.zeros((ROWS, RES, RES, 3), np.float32)),
                    r"subject0001.h5: key 'face_patch' has dtype float32, expected uint8"),
    "short_gaze": (_replace("face_gaze", np.zeros((ROWS - 1, 2))),
                   r"subject0001.h5: key 'face_gaze' has shape \[5, 2\], expected \[6, 2\]"),
    "far_gaze": (_replace("face_gaze", np.full((ROWS, 2), 4.0)), r"subject0001.h5: key 'face_gaze' row 0 is"),
}


@pytest.mark.parametrize("case", sorted(BAD))
def test_bad_release_files_are_one_line_naming_file_and_key(release, tmp_path, case):
    edit, match = BAD[case]
    folder = _bad_copy(release, tmp_path, edit)
    with pytest.raises(ToolkitError, match=match) as err:
        ReleasePatches(_files(folder), RES)
    _one_line(err)


def test_the_stage_exits_2_with_one_line_on_a_nan_label(release, tmp_path):
    from train.stages.estimator import stage_estimator

    folder = _bad_copy(release, tmp_path, _nan_gaze)
    ctx, _ = _context(tmp_path, folder)
    err = io.StringIO()
    with contextlib.redirect_stderr(err):
        code = run_cli(lambda argv: stage_estimator(ctx))
    assert code == 2 and err.getvalue().count("\n") == 1, err.getvalue()
    assert err.getvalue().startswith("error: ") and "subject0001.h5: key 'face_gaze' row 3" in err.getvalue()
    assert not (ctx.run_dir / "estimator_loss.safetensors").exists()


def test_a_held_out_file_given_to_the_reader_and_designs_it_cannot_feed_are_one_line(release, tmp_path):
    from train.stages.estimator import stage_estimator

    folder = tmp_path / "test"
    folder.mkdir()
    shutil.copy(release["dir"] / "subject0002.h5", folder / "subject0003.h5")
    with h5py.File(folder / "subject0003.h5", "r+") as f:
        del f["face_gaze"]
    with pytest.raises(ToolkitError, match=r"subject0003.h5: no key 'face_gaze': a held-out subject") as err:
        ReleasePatches([folder / "subject0003.h5"], RES)
    _one_line(err)
    with pytest.raises(ToolkitError, match=r"subject0000.h5: estimator.crop=eyes reads the eyes at each image's "
                                           r"facial_landmarks, which this release file lacks.*estimator.crop=face"):
        stage_estimator(_context(tmp_path, release["dir"], crop="eyes")[0])
    with pytest.raises(ToolkitError, match=r"estimator.crop=eye_band: .*set estimator.crop=face"):
        stage_estimator(_context(tmp_path, release["dir"], crop="eye_band")[0])
    with pytest.raises(ToolkitError, match=r"no training subject has gaze labels"):
        stage_estimator(_context(tmp_path, folder)[0])


def test_the_estimators_trained_at_once_read_the_release_files_themselves(release, tmp_path):
    """With 2 threads the two estimators train in two spawned processes, each reading the release files itself:
    the weights equal those trained in turn on 1 thread."""
    from safetensors.torch import load_file

    from train.stages.estimator import stage_estimator

    weights = []
    for threads in (1, 2):
        ctx, lines = _context(tmp_path / f"t{threads}", release["dir"], steps=2)
        torch.set_num_threads(threads)
        try:
            outs = stage_estimator(ctx)
        finally:
            torch.set_num_threads(1)
        assert any("2 processes" in s for s in lines) == (threads == 2)
        weights.append({role: load_file(ctx.run_dir / outs[role]) for role in ("loss", "eval")})
    for role in ("loss", "eval"):
        a, b = weights[0][role], weights[1][role]
        assert set(a) == set(b) and all(torch.equal(a[k], b[k]) for k in a), role


def test_a_split_file_naming_a_missing_training_subject_is_one_line(release, tmp_path):
    from train.stages.estimator import stage_estimator

    sf = tmp_path / "train_test_split.json"
    sf.write_text(json.dumps({"train": ["subject0000.h5", "subject0042.h5"], "test": ["subject0002.h5"]}))
    ctx, _ = _context(tmp_path, release["dir"])
    ctx.config.data.split_file = str(sf)
    with pytest.raises(ToolkitError, match=r"train_test_split.json: 'train' names subject subject0042, which is not "
                                           r"among the 3 subject files") as err:
        stage_estimator(ctx)
    _one_line(err)
