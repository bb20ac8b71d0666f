"""apps.redirect on a folder of face crops with a labels CSV, built from the project's own synthetic data."""

import math
import shutil

import cv2
import h5py
import numpy as np
import pytest
import torch

from apps import redirect
from apps.labels_csv import head_rotation
from apps.labels_table import read_labels
from tests.apps.helpers import interrupt_redirect_before_assembly
from toolkit import ToolkitError
from toolkit.errors import run_cli
from toolkit.rotations import pitchyaw_to_vector, so3_exp, vector_to_pitchyaw

HEADER = "image,head_pitch,head_yaw,gaze_pitch,gaze_yaw,code,mask"


def _test_subject(run_dir):
    return sorted((run_dir / "data").glob("*.h5"))[-1]


def write_crops(run_dir, folder, n=3):
    """Rows 0..n-1 of a held-out subject as PNG crops + labels.csv: row 0 with code and mask, row 1 with
    neither (fitted), the others with a code only. Returns the source HDF5 path."""
    src = _test_subject(run_dir)
    folder.mkdir(parents=True, exist_ok=True)
    lines = [HEADER]
    with h5py.File(src) as f:
        for i in range(n):
            cv2.imwrite(str(folder / f"img{i}.png"), f["face_patch"][i])  # stored BGR: imwrite expects BGR
            hp, g = np.degrees(f["face_head_pose"][i]), np.degrees(f["pitchyaw_cam"][i])
            code = mask = ""
            if i != 1:
                np.save(folder / f"code{i}.npy", f["latent_codes"][i])
                code = f"code{i}.npy"
            if i == 0:
                cv2.imwrite(str(folder / "mask0.png"), f["head_mask"][i])
                mask = "mask0.png"
            lines.append(f"img{i}.png,{hp[0]:.6f},{hp[1]:.6f},{g[0]:.6f},{g[1]:.6f},{code},{mask}")
    (folder / "labels.csv").write_text("\n".join(lines) + "\n")
    return src


@pytest.fixture(scope="module")
def crops(tiny_trained_run, tmp_path_factory):
    folder = tmp_path_factory.mktemp("crops")
    return folder, write_crops(tiny_trained_run, folder)


def test_head_rotation_round_trips_the_synthetic_normalized_cameras(tiny_trained_run):
    with h5py.File(_test_subject(tiny_trained_run)) as f:
        R_true = torch.tensor(f["w2c_Rmat"][:]) @ so3_exp(torch.tensor(f["pose"][:, :3]))
        fhp = torch.tensor(f["face_head_pose"][:])
    R = head_rotation(torch.cat([fhp, torch.zeros(len(fhp), 1)], 1))
    assert torch.allclose(R, R_true, atol=1e-5)
    assert torch.allclose(R.transpose(1, 2) @ R, torch.eye(3).expand_as(R), atol=1e-5)
    # Roll turns the head about its own z axis: the face direction is unchanged.
    Rr = head_rotation(torch.tensor([[0.2, -0.3, 0.4]]))
    assert torch.allclose(Rr[0, :, 2], head_rotation(torch.tensor([[0.2, -0.3, 0.0]]))[0, :, 2], atol=1e-6)
    assert not torch.allclose(Rr, head_rotation(torch.tensor([[0.2, -0.3, 0.0]])), atol=1e-3)


def test_head_rotation_stress_extreme_angles():
    """Degenerate (pitch ±90°) and extreme (yaw ±180°, large roll) inputs: orthonormal, finite, det +1,
    finite gradients."""
    pyr = torch.tensor([[math.pi / 2, 0.3, 0.0], [-math.pi / 2, -2.0, 1.0], [0.0, math.pi, 0.0],
                        [1.4, -math.pi, -3.1], [0.0, 0.0, 0.0]], requires_grad=True)
    R = head_rotation(pyr)
    I = torch.eye(3).expand_as(R)
    assert torch.isfinite(R).all() and torch.allclose(R.transpose(1, 2) @ R, I, atol=1e-5)
    assert torch.allclose(torch.linalg.det(R), torch.ones(5), atol=1e-5)
    assert torch.allclose(R[-1], torch.eye(3), atol=1e-6)  # facing the camera, no roll: identity
    R.sum().backward()
    assert torch.isfinite(pyr.grad).all()


def test_csv_input_writes_labelled_redirected_dataset(tiny_trained_run, crops, tmp_path):
    from train.data.dataset import GazeDataset

    folder, src = crops
    out = tmp_path / "out.h5"
    assert redirect.main([str(tiny_trained_run), str(folder / "labels.csv"), str(out), "--gazes", "grid:2x2:20",
                          "--batch", "2", "--fit-steps", "2"]) == 0
    assert not (tmp_path / "out.h5.parts").exists()
    gz = redirect.parse_gazes("grid:2x2:20")
    with h5py.File(out) as o, h5py.File(src) as f:
        n = 3 * 4
        assert o["face_patch"].shape == (n, 64, 64, 3) and o["face_patch"].dtype == np.uint8
        assert o["head_mask"].shape == o["left_eye_mask"].shape == (n, 64, 64)
        assert o["facial_landmarks"].shape == (n, 68, 2) and o["vertice"].shape[0] == n
        assert o["source_row"][:].tolist() == [r for r in range(3) for _ in range(4)]
        assert np.allclose(o["pitchyaw_head"][:], np.tile(gz, (3, 1)))
        for i in range(3):
            rows = slice(4 * i, 4 * i + 4)
            assert np.allclose(o["face_head_pose"][rows], f["face_head_pose"][i], atol=1e-5)
            # World = head frame (pose 0); the head-to-camera rotation is the generator's exactly, and the
            # face centre sits on the optical axis at 0.6 m.
            assert np.allclose(o["pose"][rows], 0)
            R_true = f["w2c_Rmat"][i] @ so3_exp(torch.tensor(f["pose"][i, :3])).numpy()
            R_out = o["w2c_Rmat"][4 * i] @ so3_exp(torch.tensor(o["pose"][4 * i, :3])).numpy()
            assert np.allclose(R_out, R_true, atol=1e-4)
            c = o["facial_landmarks_3d"][4 * i][[36, 39, 42, 45, 48, 54]].mean(0)
            assert np.allclose(o["w2c_Rmat"][4 * i] @ c + o["w2c_Tvec"][4 * i], [0, 0, 0.6], atol=1e-5)
            # Camera-frame gaze label = R · head-frame target gaze.
            g_cam = vector_to_pitchyaw(pitchyaw_to_vector(torch.tensor(gz)) @ torch.tensor(R_out).float().T)
            assert np.allclose(o["pitchyaw_cam"][rows], g_cam.numpy(), atol=1e-4)
            # The normalized camera (0.6 m, 0.26 m crop): landmarks of the run's geometry land on the
            # generator's landmarks of this (different) subject within a few pixels / a centimetre.
            assert np.abs(o["facial_landmarks"][4 * i] - f["facial_landmarks"][i]).mean() < 3.0
            cam_true = f["facial_landmarks_3d"][i] @ f["w2c_Rmat"][i].T + f["w2c_Tvec"][i]
            cam_out = o["facial_landmarks_3d"][4 * i] @ o["w2c_Rmat"][4 * i].T + o["w2c_Tvec"][4 * i]
            assert np.abs(cam_out - cam_true).mean() < 0.01
            K = o["inmat"][4 * i]
            assert np.isclose(K[0, 0], 64 * 0.6 / 0.26, rtol=1e-5) and np.isclose(K[0, 2], 32)
        codes = o["latent_codes"][:]
        assert np.allclose(codes[0], f["latent_codes"][0]) and np.allclose(codes[8], f["latent_codes"][2])
        assert np.isfinite(codes).all() and np.abs(codes[4]).max() > 0  # row 1: fitted from the zero code
        # Row 0's user mask is kept; every image is white outside its mask and not blank inside.
        assert np.array_equal(o["head_mask"][0] > 0, f["head_mask"][0] > 0)
        for k in range(n):
            img, m = o["face_patch"][k], o["head_mask"][k] > 0
            assert m.mean() > 0.1 and (img[~m] == 255).all() and img[m].std() > 1
    assert len(GazeDataset([out])) == 12  # the output passes the loader's schema and range checks


def test_folder_argument_and_resumed_chunks(tiny_trained_run, crops, tmp_path, monkeypatch):
    """A folder holding labels.csv works; finished chunks in OUT.parts are kept, not re-rendered."""
    folder, _ = crops
    out = tmp_path / "o.h5"
    args = [str(tiny_trained_run), str(folder), str(out), "--gazes", "grid:1x2:10", "--batch", "2", "--fit-steps", "1"]
    parts = tmp_path / "o.h5.parts"

    interrupt_redirect_before_assembly(args, monkeypatch)
    # The interrupted run left its settings and chunks: a sentinel in chunk 1 (row 2) proves it is reused as is.
    with np.load(parts / "part_00001.npz") as z:
        chunk1 = {k: z[k] for k in z.files}
    chunk1["face_patch"] = np.zeros_like(chunk1["face_patch"])
    np.savez(parts / "part_00001.npz", **chunk1)
    (parts / "part_00000.npz").unlink()  # and chunk 0 is rendered again
    assert redirect.main(args) == 0
    with h5py.File(out) as h:
        assert h["face_patch"].shape[0] == 6
        assert (h["face_patch"][4:] == 0).all() and (h["face_patch"][:4] != 0).any()


def _csv(folder, text):
    (folder / "labels.csv").write_text(text)
    return folder / "labels.csv"


@pytest.mark.parametrize(
    "case,expect",
    [
        ("missing_image", "line 2, column 'image': .*nope.png: no such file"),
        ("unreadable_image", "line 2, column 'image': .*garbage.png: not a readable image"),
        ("non_square", r"line 2, column 'image': .*wide.png is 32x64 \(width x height\); expected a square crop"),
        ("other_size", "line 3, column 'image': .*small.png is 32x32; the first image is 64x64"),
        ("missing_column", r"missing column\(s\) \['head_yaw'\]"),
        ("nan", "line 2, column 'head_yaw': expected a finite number, got 'nan'"),
        ("not_number", "line 2, column 'gaze_pitch': expected a number, got 'up'"),
        ("out_of_range", r"line 2, column 'head_pitch': expected degrees in \[-90, 90\]"),
        ("yaw_out_of_range", r"line 2, column 'gaze_yaw': expected degrees in \[-180, 180\]"),
        ("unknown_column", r"unknown column\(s\) \['focl'\]"),
        ("bad_code", "line 2, column 'code': .*short.npy: expected 144 numbers"),
        ("no_code_no_gaze", "line 2: no 'code' given.*gaze_pitch and gaze_yaw"),
        ("bad_mask", "line 2, column 'mask': .*mask_small.png is 32x32; expected the image's size 64x64"),
        ("no_csv", "no such labels CSV"),
        ("empty", "no data rows"),
        ("extra_cell", "line 2: 8 cells, the header has 7"),
        ("duplicate_column", r"column\(s\) \['head_yaw'\] appear more than once in the header"),
    ],
)
def test_bad_csv_input_is_one_line_error(tiny_trained_run, crops, tmp_path, capsys, case, expect):
    folder, _ = crops
    d = tmp_path / "in"
    d.mkdir()
    img = cv2.imread(str(folder / "img0.png"))
    cv2.imwrite(str(d / "a.png"), img)
    ok = "a.png,10,-5,3,4,,"
    text = {
        "missing_image": f"{HEADER}\nnope.png,10,-5,3,4,,\n",
        "unreadable_image": f"{HEADER}\ngarbage.png,10,-5,3,4,,\n",
        "non_square": f"{HEADER}\nwide.png,10,-5,3,4,,\n",
        "other_size": f"{HEADER}\n{ok}\nsmall.png,10,-5,3,4,,\n",
        "missing_column": "image,head_pitch\na.png,10\n",
        "nan": f"{HEADER}\na.png,10,nan,3,4,,\n",
        "not_number": f"{HEADER}\na.png,10,-5,up,4,,\n",
        "out_of_range": f"{HEADER}\na.png,100,-5,3,4,,\n",
        "yaw_out_of_range": f"{HEADER}\na.png,10,-5,3,200,,\n",
        "unknown_column": "image,head_pitch,head_yaw,focl\na.png,1,2,3\n",
        "bad_code": f"{HEADER}\na.png,10,-5,3,4,short.npy,\n",
        "no_code_no_gaze": f"{HEADER}\na.png,10,-5,,,,\n",
        "bad_mask": f"{HEADER}\na.png,10,-5,3,4,,mask_small.png\n",
        "empty": f"{HEADER}\n",
        "extra_cell": f"{HEADER}\na.png,10,-5,3,4,,,7\n",  # a shifted row must not lose its last cell silently
        "duplicate_column": "image,head_pitch,head_yaw,head_yaw\na.png,10,5,99\n",
    }.get(case)
    (d / "garbage.png").write_bytes(b"not an image")
    cv2.imwrite(str(d / "wide.png"), np.zeros((64, 32, 3), np.uint8))
    cv2.imwrite(str(d / "small.png"), np.zeros((32, 32, 3), np.uint8))
    cv2.imwrite(str(d / "mask_small.png"), np.zeros((32, 32), np.uint8))
    np.save(d / "short.npy", np.zeros(10, np.float32))
    csv_path = d / "labels.csv" if text is None else _csv(d, text)
    out = tmp_path / "o.h5"
    with pytest.raises(ToolkitError, match=expect):
        read_labels(csv_path)
    assert run_cli(redirect.main, [str(tiny_trained_run), str(csv_path), str(out)]) == 2
    err = capsys.readouterr().err
    assert err.startswith("error: ") and err.count("\n") == 1 and "Traceback" not in err
    assert not out.exists() and not (tmp_path / "o.h5.parts").exists()


def test_focal_and_distance_defaults_and_columns(crops, tmp_path):
    folder, _ = crops
    text = "image,head_pitch,head_yaw,gaze_pitch,gaze_yaw,focal,distance\n" \
           "img0.png,0,0,0,0,,\nimg2.png,0,0,0,0,300,0.5\n"
    p = tmp_path / "l.csv"
    p.write_text(text.replace("img", str(folder / "img")))
    rows, size = read_labels(p, focal=200.0)
    assert size == 64 and rows[0].focal == 200.0 and rows[0].distance == 0.6
    assert rows[1].focal == 300.0 and rows[1].distance == 0.5 and rows[1].code is None
    rows, _ = read_labels(p)
    assert math.isclose(rows[0].focal, 64 * 0.6 / 0.26)
    with pytest.raises(ToolkitError, match="--focal must be a positive number"):
        read_labels(p, focal=-1.0)


def test_code_fitting_compares_the_face_not_the_eyes(tiny_trained_run, crops, tmp_path, monkeypatch):
    """The row without a code is fitted on its image outside its (dilated) visible eyes: they show the
    image's own gaze, which the code must not learn."""
    import torch.nn.functional as F

    import train.evaluation.fitting as evaluate

    folder, _ = crops
    seen = []
    real_fit = evaluate.test_time_fit

    def spy(model, renderer, batch, image, mask, res, steps, **kw):
        with torch.no_grad():
            maps = model(batch["code"], batch["in_pose"], batch["in_gaze_head"], batch["in_viewmat"], batch["K"],
                         res, res, renders=("head", "face", "eyes"))
        up = lambda a: F.interpolate(a, size=(res, res), mode="bilinear", align_corners=False)  # noqa: E731
        eyes = (up(maps["eyes_alpha"]) > 0.5) & (up(maps["face_alpha"]) < 0.5)
        seen.append((mask.clone(), eyes, up(maps["head_alpha"]) > 0.5))
        return real_fit(model, renderer, batch, image, mask, res, steps, **kw)

    monkeypatch.setattr(evaluate, "test_time_fit", spy)
    assert redirect.main([str(tiny_trained_run), str(folder / "labels.csv"), str(tmp_path / "o.h5"),
                          "--gazes", "grid:1x1:0", "--batch", "3", "--fit-steps", "1"]) == 0
    (mask, eyes, head), = seen
    assert mask.shape == eyes.shape == (1, 1, 64, 64)  # only row 1 has no code
    assert eyes.sum() > 0 and (mask[eyes] == 0).all()
    assert (mask <= head.float()).all() and mask.sum() > 0.5 * head.sum() - 4 * eyes.sum()


def test_the_folder_and_its_csv_are_one_input_and_an_edited_input_is_not_resumed(tiny_trained_run, crops, tmp_path,
                                                                                  monkeypatch, capsys):
    """A run interrupted on the folder resumes when given its labels.csv (one input spelt two ways), but not
    after the CSV was edited: the chunks would mix the old rows with the new."""
    folder, _ = crops
    d = tmp_path / "in"
    shutil.copytree(folder, d)
    out = tmp_path / "o.h5"
    opts = [str(out), "--gazes", "grid:1x2:10", "--batch", "2", "--fit-steps", "1"]
    interrupt_redirect_before_assembly([str(tiny_trained_run), str(d), *opts], monkeypatch)
    capsys.readouterr()
    parts = tmp_path / "o.h5.parts"
    (parts / "part_00001.npz").unlink()
    csv_path = d / "labels.csv"
    text = csv_path.read_text()
    lines = text.splitlines()
    cells = lines[1].split(",")
    cells[1] = f"{float(cells[1]) + 1:.6f}"  # row 0's head pitch, one degree up
    csv_path.write_text("\n".join([lines[0], ",".join(cells), *lines[2:]]) + "\n")
    assert run_cli(redirect.main, [str(tiny_trained_run), str(csv_path), *opts]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "other settings (input_stamp differ)" in err[0], err
    csv_path.write_text(text)  # back as it was (a new modification time is no change: the CSV's text is hashed)
    assert redirect.main([str(tiny_trained_run), str(csv_path), *opts]) == 0 and out.is_file()
