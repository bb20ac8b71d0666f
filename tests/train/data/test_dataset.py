"""HDF5 schema validation and GazeDataset: lazy reads, resize, white compositing, splits, bad files."""

from __future__ import annotations

import json
import pickle
import shutil

import h5py
import numpy as np
import pytest
import torch

from toolkit.errors import ToolkitError
from train.data.dataset import GazeDataset, split_files
from train.data.format import REQUIRED, validate_subject_file, write_subject_h5


def _copy_rows(path):
    with h5py.File(path, "r") as f:
        return {k: f[k][()] for k in f.keys()}, dict(f.attrs)


def _write(tmp_path, name, rows, attrs=None):
    subject_keys = ("neutral_vertice", "mesh_faces", "eyeball_centers", "eyeball_radii", "identity_params")
    per_row = {k: v for k, v in rows.items() if k not in subject_keys}
    subj = {k: v for k, v in rows.items() if k in subject_keys}
    return write_subject_h5(tmp_path / name, per_row, subject=subj, attrs=attrs, compression=None)


def test_validate_good_file(subject_file):
    info = validate_subject_file(subject_file)
    assert info["n"] == 36 and info["height"] == info["width"] == 96
    assert {"pitchyaw_cam", "expression_params", "light_dir"} <= set(info["optional"])
    assert "neutral_vertice" in info["subject_keys"] and "subject_params" in info["attrs"]


def test_dataset_samples(subject_file):
    ds = GazeDataset([subject_file])
    assert len(ds) == 36
    s = ds[5]
    assert s["image"].shape == (3, 96, 96) and s["image"].dtype == torch.float32
    assert s["head_mask"].shape == (1, 96, 96) and s["landmarks"].shape == (68, 2)
    assert s["latent_code"].shape == (144,) and s["pose"].shape == (6,) and s["scale"].shape == (1,)
    assert "pitchyaw_cam" in s and "vertice" not in s
    # Composited on white outside the head mask; BGR stored -> RGB returned.
    out = s["head_mask"][0] < 0.5
    assert torch.all(s["image"][:, out] == 1.0)
    with h5py.File(subject_file, "r") as f:
        bgr = f["face_patch"][5]
    inside = ~out.numpy()  # anti-aliased edge pixels outside the mask are the only ones composited
    np.testing.assert_allclose(s["image"].numpy().transpose(1, 2, 0)[inside], bgr[..., ::-1][inside] / 255.0, atol=1e-6)
    # viewmat is the stored extrinsics; K projects the 3D landmarks onto the 2D ones.
    pc = s["landmarks_3d"] @ s["viewmat"][:3, :3].T + s["viewmat"][:3, 3]
    uv = pc @ s["K"].T
    torch.testing.assert_close(uv[:, :2] / uv[:, 2:], s["landmarks"], atol=2e-3, rtol=0)
    with pytest.raises(IndexError):
        ds[36]


def test_dataset_resize_and_mesh(subject_file):
    ds = GazeDataset(subject_file, res=48, with_mesh=True)
    s = ds[3]
    assert s["image"].shape == (3, 48, 48) and s["left_eye_mask"].shape == (1, 48, 48)
    assert s["vertice"].shape[1] == 3
    pc = s["landmarks_3d"] @ s["w2c_R"].T + s["w2c_T"]
    uv = pc @ s["K"].T
    torch.testing.assert_close(uv[:, :2] / uv[:, 2:], s["landmarks"], atol=2e-3, rtol=0)
    big = GazeDataset(subject_file, res=96)[3]
    # Area-averaged masks keep the covered fraction.
    assert abs(float(s["head_mask"].mean()) - float(big["head_mask"].mean())) < 0.01


def test_one_handle_per_worker(subject_file):
    ds = GazeDataset(subject_file)
    ds[0]
    assert len(ds._handles) == 1
    clone = pickle.loads(pickle.dumps(ds))  # what a spawned DataLoader worker receives
    assert clone._handles == {}
    torch.testing.assert_close(clone[1]["image"], ds[1]["image"])
    ds._pid = -1  # as after a fork: the parent's handle must not be reused
    ds[2]
    assert ds._pid > 0 and len(ds._handles) == 1
    loader = torch.utils.data.DataLoader(ds, batch_size=6, num_workers=2)
    n = sum(b["image"].shape[0] for b in loader)
    assert n == 36
    ds.close()


def test_splits(tmp_path, subject_file):
    for k in range(4):
        shutil.copy(subject_file, tmp_path / f"subject{k:04d}.h5")
    files = sorted(tmp_path.glob("*.h5"))
    assert [f.name for f in split_files(files, "test")] == ["subject0003.h5"]
    assert len(split_files(files, "train")) == 3
    (tmp_path / "split.json").write_text(json.dumps({"train": ["subject0000", "subject0002"], "test": ["subject0001.h5"]}))
    assert [f.name for f in split_files(files, "test")] == ["subject0001.h5"]
    ds = GazeDataset(tmp_path, split="train")
    assert len(ds) == 72 and int(ds[40]["subject"]) == 1
    with pytest.raises(ToolkitError, match="split: expected one of"):
        GazeDataset(tmp_path, split="val")
    (tmp_path / "split.json").write_text("{not json")
    with pytest.raises(ToolkitError, match="split.json"):
        GazeDataset(tmp_path, split="train")


def test_files_with_one_dimensional_indices_still_read(tmp_path, subject_file):
    rows, _ = _copy_rows(subject_file)  # the generator writes (N, 1); files written before it wrote (N,)
    assert rows["cam_index"].shape == (36, 1)
    rows["cam_index"], rows["frame_index"] = rows["cam_index"].reshape(-1), rows["frame_index"].reshape(-1)
    old = GazeDataset(_write(tmp_path, "old.h5", rows))
    new = GazeDataset(subject_file)
    assert [int(old[i]["cam_index"]) for i in (0, 20)] == [int(new[i]["cam_index"]) for i in (0, 20)] == [0, 2]


def test_optional_keys_are_optional(tmp_path, subject_file):
    rows, attrs = _copy_rows(subject_file)
    for k in ("pitchyaw_cam", "expression_params", "light_dir", "neutral_vertice"):
        rows.pop(k)
    rows["cam_index"] = rows["cam_index"].reshape(-1, 1).astype(np.uint8)  # GazeNeRF-style (N, 1) uint8
    rows["scale"] = rows["scale"][:, 0]  # (N,) is accepted too
    p = _write(tmp_path, "real_like.h5", rows)
    s = GazeDataset(p)[0]
    assert s["image"].shape == (3, 96, 96)
    assert int(GazeDataset(p)[20]["cam_index"]) == 2 and s["scale"].shape == (1,)
    # Without it, the camera-frame gaze is the head-frame gaze turned by w2c ∘ pose: the generator's label.
    full = GazeDataset(subject_file)
    for i in (0, 20):
        assert torch.allclose(GazeDataset(p)[i]["pitchyaw_cam"], full[i]["pitchyaw_cam"], atol=1e-5)


@pytest.mark.parametrize("scale", [0.9, 1.1])
def test_a_scaled_head_reads_as_the_unit_scale_head_it_images(tmp_path, subject_file, scale):
    """The same scene scaled by s about the world origin (cameras, head translation, 3D landmarks and vertices
    times s, head scale s) makes the same images; GazeDataset folds s back into the world frame, so every stage
    that poses the head rigidly receives the unit-scale sample."""
    rows, _ = _copy_rows(subject_file)
    rows["w2c_Tvec"] = rows["w2c_Tvec"] * scale
    rows["pose"] = rows["pose"].copy()
    rows["pose"][:, 3:] *= scale
    rows["facial_landmarks_3d"] = rows["facial_landmarks_3d"] * scale
    rows["vertice"] = rows["vertice"] * scale
    rows["scale"] = np.full_like(rows["scale"], scale)
    scaled, unit = GazeDataset(_write(tmp_path, "scaled.h5", rows), with_mesh=True), GazeDataset(subject_file,
                                                                                               with_mesh=True)
    for i in (0, 7, 20):
        a, b = scaled[i], unit[i]
        assert float(a["scale"]) == 1.0
        for key in ("image", "viewmat", "pose", "landmarks_3d", "vertice", "pitchyaw_cam", "K"):
            torch.testing.assert_close(a[key], b[key], atol=2e-6, rtol=1e-5, msg=key)
    # A row of scale 1 is read as it is stored.
    assert torch.equal(unit[3]["viewmat"][:3, 3], torch.as_tensor(unit.read_row(0, 3)["w2c_Tvec"]))


@pytest.mark.parametrize(
    "edit,match",
    [
        (lambda r: r.pop("w2c_Tvec"), "missing key 'w2c_Tvec'"),
        (lambda r: r.__setitem__("facial_landmarks", r["facial_landmarks"][:, :60]), "'facial_landmarks' has shape"),
        (lambda r: r.__setitem__("head_mask", r["head_mask"][:, :50]), "'head_mask' has H = 50"),
        (lambda r: r.__setitem__("face_patch", r["face_patch"].astype(np.float32)), "'face_patch' has dtype float32"),
        (lambda r: r.__setitem__("face_patch", r["face_patch"].astype(np.uint16)), "'face_patch' has dtype uint16"),
        (lambda r: r.__setitem__("pitchyaw_head", r["pitchyaw_head"] + 4.0), "'pitchyaw_head' is out of range"),
        (lambda r: r["pose"].__setitem__((0, 0), np.nan), "'pose' contains NaN"),
        (lambda r: r.__setitem__("w2c_Rmat", r["w2c_Rmat"] * 2), "'w2c_Rmat' is not a rotation"),
        (lambda r: r["inmat"].__setitem__((1, 0, 0), -5.0), "'inmat' has non-positive focal"),
        (lambda r: r["cam_index"].__setitem__(0, -1), "'cam_index' has negative"),
        (lambda r: r.__setitem__("scale", np.zeros_like(r["scale"])), "'scale' has non-positive"),
        (lambda r: r.__setitem__("facial_landmarks", r["facial_landmarks"] * 100), "far outside"),
        (lambda r: r.__setitem__("latent_codes", r["latent_codes"][:, :80]), "'latent_codes' has shape"),
    ],
)
def test_schema_violations_name_file_and_key(tmp_path, subject_file, edit, match):
    rows, _ = _copy_rows(subject_file)
    edit(rows)
    p = tmp_path / "bad.h5"
    with h5py.File(p, "w") as f:  # written raw: the writer itself refuses some of these
        for k, v in rows.items():
            f.create_dataset(k, data=v)
    with pytest.raises(ToolkitError, match=match) as e:
        GazeDataset(p)
    assert "bad.h5" in str(e.value)


def test_a_group_where_rows_belong_is_one_clear_error(tmp_path, subject_file):
    rows, _ = _copy_rows(subject_file)
    p = tmp_path / "grouped.h5"
    with h5py.File(p, "w") as f:
        for k, v in rows.items():
            if k == "pose":
                f.create_group("pose").create_dataset("x", data=v)
            else:
                f.create_dataset(k, data=v)
    with pytest.raises(ToolkitError, match=r"grouped\.h5: key 'pose' is a Group, expected a dataset of rows"):
        GazeDataset(p)


def test_row_count_mismatch_and_empty_subject(tmp_path, subject_file):
    rows, _ = _copy_rows(subject_file)
    p = tmp_path / "short.h5"
    with h5py.File(p, "w") as f:
        for k, v in rows.items():
            f.create_dataset(k, data=v[:10] if k == "pose" else v)
    with pytest.raises(ToolkitError, match="'pose' has 10 rows, face_patch has 36"):
        validate_subject_file(p)
    p = tmp_path / "empty.h5"
    with h5py.File(p, "w") as f:
        for k, v in rows.items():
            f.create_dataset(k, data=v[:0])
    with pytest.raises(ToolkitError, match="empty subject"):
        validate_subject_file(p)
    with pytest.raises(ToolkitError, match="missing keys"):
        write_subject_h5(tmp_path / "x.h5", {"face_patch": rows["face_patch"]})
    assert not (tmp_path / "x.h5").exists()


def test_truncated_and_garbage_files(tmp_path, subject_file):
    data = subject_file.read_bytes()
    (tmp_path / "trunc.h5").write_bytes(data[: len(data) // 3])
    with pytest.raises(ToolkitError, match="trunc.h5.*(truncated|corrupt)"):
        GazeDataset(tmp_path / "trunc.h5")
    (tmp_path / "junk.h5").write_bytes(b"\x89HDF\r\n not really")
    with pytest.raises(ToolkitError, match="junk.h5: not a readable HDF5 file"):
        validate_subject_file(tmp_path / "junk.h5")
    with pytest.raises(ToolkitError, match="no such file"):
        GazeDataset(tmp_path / "missing.h5")
    empty_dir = tmp_path / "none"
    empty_dir.mkdir()
    with pytest.raises(ToolkitError, match="no \\*.h5 subject files"):
        GazeDataset(empty_dir)


def test_every_required_key_is_checked(tmp_path, subject_file):
    rows, _ = _copy_rows(subject_file)
    for key in REQUIRED:
        p = tmp_path / f"no_{key}.h5"
        with h5py.File(p, "w") as f:
            for k, v in rows.items():
                if k != key:
                    f.create_dataset(k, data=v)
        with pytest.raises(ToolkitError, match=f"missing key '{key}'"):
            validate_subject_file(p)
