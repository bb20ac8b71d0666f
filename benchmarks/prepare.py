"""``python -m apps.prepare`` throughput (photos/s at 0.3, 1 and 12 megapixels) against landmark and head-pose error
on synthetic renders (docs/photos.md).

    .venv/bin/python benchmarks/prepare.py                 # 3 sizes x 5 repeats, 10 synthetic subjects
    .venv/bin/python benchmarks/prepare.py --repeats 2 --subjects 4

Part 1, speed: skimage's astronaut resized to 0.3, 1 and 12 megapixels (4:3), written as JPEG (quality 95), each
prepared end to end as the app does (decode, detect, mesh, pose, normalize at 512², masks with the person
segmenter, gaze; not the HDF5 writing), median of ``--repeats`` after a warm-up. Target: >= 5 photos/s at 1 MP.

Part 2, accuracy: ``--subjects`` procedural subjects rendered by a plain photo camera (640x480, focal 1.2 x 640,
random head pose yaw ±25°, pitch ±15°, roll ±8°, gaze ±25°); mediapipe's iBUG-68 landmarks against the
generator's exact ones (pixels, by region; the jaw is approximate by construction), the head rotation error (°)
of PnP with the average head model, the head scale the iris sets (the renders' is 1, their irises vary ±10%),
the normalized crop's eye-centre error against the generator's normalized view (pixels at 512², with the iris
scale and with ``--scale 1``), the iris-geometry gaze error (°) and the head-mask IoU against the generator's.
"""

from __future__ import annotations

import math
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from benchmarks.common import OUT_DIR, count, format_table, machine_info, save_plot  # noqa: E402
from toolkit.errors import CliParser, run_cli  # noqa: E402


def synthetic_photo(seed: int, *, width: int = 640, height: int = 480, focal: float | None = None,
                    head_rotation=(0.0, 0.0, 0.0), translation=(0.0, 0.0, 0.65), gaze=(0.0, 0.0),
                    subject=None) -> dict:
    """A procedural subject rendered by a plain camera at the origin (world = the photo camera's frame).

    ``head_rotation`` (pitch, yaw, roll) radians composed yaw · pitch · roll as the generator's poses, metres
    ``translation``, head-frame ``gaze`` (pitch, yaw). Returns ``bgr`` [H, W, 3] uint8, ``K`` [3, 3],
    ``landmarks`` [68, 2] exact (u = 0 left edge), ``iris`` [2, 2] the pupil centres' projections, ``pose`` [6],
    ``R`` [3, 3], ``gaze`` [2], ``subject``, ``head_mask``/``left_eye_mask`` [H, W] bool, ``camera``."""
    import torch

    from apps.photo.gaze import pitchyaw_vector
    from toolkit.cameras import Camera
    from toolkit.rotations import so3_exp, so3_log
    from train.data.poses import pose_matrix
    from train.data.subject_params import SubjectParams
    from train.data.synthetic import build_subject, render_views

    subject = subject or build_subject(SubjectParams.sample(seed))
    f = focal or 1.2 * max(width, height)
    K = np.array([[f, 0, width / 2], [0, f, height / 2], [0, 0, 1.0]])
    cam = Camera(torch.from_numpy(K).float(), torch.eye(4), width, height)
    p, y, r = (float(a) for a in head_rotation)
    R = so3_exp(torch.tensor([0.0, y, 0])) @ so3_exp(torch.tensor([p, 0.0, 0])) @ so3_exp(torch.tensor([0, 0, r]))
    pose = np.r_[so3_log(R).numpy(), np.asarray(translation, np.float64)]
    out = render_views(subject, np.asarray(gaze), pose, np.zeros(4), [cam])
    Rm, t = pose_matrix(pose)
    pupils = subject.eye_centers + subject.eye_radius * pitchyaw_vector(np.asarray(gaze, np.float64))
    pc = pupils @ Rm.T + t
    iris = pc[:, :2] / pc[:, 2:] * f + K[:2, 2]
    rgb = np.clip(np.rint(out["rgb"][0] * 255), 0, 255).astype(np.uint8)
    return {"bgr": np.ascontiguousarray(rgb[..., ::-1]), "K": K, "landmarks": out["landmarks_2d"][0].astype(np.float64),
            "iris": iris, "pose": pose, "R": Rm, "gaze": np.asarray(gaze, np.float64), "subject": subject,
            "head_mask": out["head_mask"][0], "left_eye_mask": out["left_eye_mask"][0], "camera": cam}


def generator_view(photo: dict, size: int, distance: float = 0.6, crop: float = 0.26) -> dict:
    """The generator's own normalized view of a :func:`synthetic_photo`'s head: the photo camera aimed at the face
    centre by ``train.data.generate``'s rule (``frame_cameras``), rendered; ``render_views``'s outputs."""
    from train.data.poses import normalized_camera, pose_matrix
    from train.data.synthetic import render_views

    R, t = pose_matrix(photo["pose"])
    cam = normalized_camera(photo["camera"], R @ photo["subject"].face_center + t, R, size, distance=distance,
                            crop=crop)
    out = render_views(photo["subject"], photo["gaze"], photo["pose"], np.zeros(4), [cam])
    return {k: v[0] for k, v in out.items()}


SIZES_MP = (0.3, 1.0, 12.0)


def prepare_one(path: Path, finder, target, out: Path) -> int:
    """One photo as the app prepares it (decode, faces, rows, sheet strips, the HDF5 file); returns its faces."""
    from apps.photo.images import load_photo
    from apps.photo.rows import photo_rows, write_rows
    from apps.photo.sheet import sheet_strip

    photo = load_photo(path)
    rows, _ = photo_rows(photo, finder, target)
    for r in rows:
        sheet_strip(path.name, photo.bgr, r.source_landmarks, r.arrays)
    write_rows(out, rows, target, {"source": "benchmarks/prepare.py"})
    return len(rows)


def speed_rows(finder, target, repeats: int, tmp: Path) -> list[dict]:
    import cv2
    from skimage import data

    from benchmarks.common import timeit

    rows = []
    for mp in SIZES_MP:
        side = round(math.sqrt(mp * 1e6))  # square, as the astronaut: no distortion of the face
        path = tmp / f"astronaut_{side}.jpg"
        big = cv2.resize(data.astronaut(), (side, side), interpolation=cv2.INTER_CUBIC)
        cv2.imwrite(str(path), big[..., ::-1], [cv2.IMWRITE_JPEG_QUALITY, 95])
        s = timeit(lambda p=path: prepare_one(p, finder, target, tmp / "out.h5"), repeats=repeats, warmup=1)
        rows.append({"megapixels": round(side * side / 1e6, 2), "photo": f"{side}x{side}", "s / photo": s,
                     "photos / s": 1.0 / s})
    return rows


def accuracy_rows(finder, n_subjects: int, size: int = 512) -> tuple[list[dict], dict]:
    """Per-subject errors of mediapipe's landmarks and of the prepared rows on synthetic renders (module doc)."""
    from apps.photo.face_model import default_target
    from apps.photo.gaze import pitchyaw_vector
    from apps.photo.landmarks68 import ibug68
    from apps.photo.rows import FaceObservation, prepare_face

    target = default_target(size)
    rng = np.random.default_rng(0)
    out = []
    for seed in range(n_subjects):
        rot = rng.uniform(-1, 1, 3) * np.radians([15, 25, 8])
        gaze = rng.uniform(-1, 1, 2) * np.radians(25)
        ph = synthetic_photo(seed, head_rotation=rot, translation=(*rng.uniform(-0.05, 0.05, 2), 0.65), gaze=gaze)
        faces, _ = finder.faces(np.ascontiguousarray(ph["bgr"][..., ::-1]))
        if not faces:
            out.append({"subject": seed, "found": 0})
            continue
        lm = ibug68(faces[0].points)
        err = np.linalg.norm(lm - ph["landmarks"], axis=1)
        row = prepare_face(ph["bgr"], FaceObservation.from_mesh(faces[0].points), ph["K"], target, person=finder.person)
        a, view = row.arrays, generator_view(ph, size)
        unit = prepare_face(ph["bgr"], FaceObservation.from_mesh(faces[0].points), ph["K"], target, scale=1.0).arrays
        R_gen = view["w2c_R"].astype(np.float64) @ ph["R"]
        cos = (np.trace(a["w2c_Rmat"].astype(np.float64).T @ R_gen) - 1) / 2
        eyes, eyes_unit = ([np.linalg.norm(r["facial_landmarks"][s].mean(0) - view["landmarks_2d"][s].mean(0))
                            for s in (slice(36, 42), slice(42, 48))] for r in (a, unit))
        g = float(np.degrees(np.arccos(np.clip(pitchyaw_vector(a["pitchyaw_head"]) @ pitchyaw_vector(gaze), -1, 1))))
        head, truth = a["head_mask"] > 0, view["head_mask"]
        out.append({"subject": seed, "found": 1, "landmarks px": float(err.mean()), "jaw px": float(err[:17].mean()),
                    "eyes px": float(err[36:48].mean()), "mouth px": float(err[48:].mean()),
                    "face width px": float(np.ptp(ph["landmarks"][:, 0])),
                    "head pose deg": float(np.degrees(np.arccos(np.clip(cos, -1, 1)))),
                    "iris scale": float(a["scale"][0]), "crop eye centres px": float(np.mean(eyes)),
                    "crop eye centres px, --scale 1": float(np.mean(eyes_unit)), "gaze deg": g,
                    "head mask IoU": float((head & truth).sum() / max((head | truth).sum(), 1))})
    return out


def main(argv=None) -> int:
    import tempfile

    from apps.photo.face_model import default_target
    from apps.photo.faces import FaceFinder

    ap = CliParser(description=__doc__.split("\n")[0])
    ap.add_argument("--repeats", type=count("--repeats"), default=5)
    ap.add_argument("--subjects", type=count("--subjects"), default=10)
    args = ap.parse_args(argv)
    print(machine_info())
    with FaceFinder() as finder, tempfile.TemporaryDirectory() as tmp:
        speed = speed_rows(finder, default_target(512), args.repeats, Path(tmp))
        acc = accuracy_rows(finder, args.subjects)
    print("\nSpeed (skimage's astronaut, 512² crops, one face, the whole app but the contact sheet's PNG):")
    print(format_table(speed))
    found = [r for r in acc if r["found"]]
    print(f"\nAccuracy on {len(acc)} synthetic renders ({len(found)} faces found), mean (max):")
    keys = [k for k in (found[0] if found else {}) if k not in ("subject", "found", "face width px")]
    summary = [{"metric": k, "mean": float(np.mean([r[k] for r in found])), "max": float(np.max([r[k] for r in found]))}
               for k in keys]
    print(format_table(summary))
    if found:
        print(f"(faces {np.mean([r['face width px'] for r in found]):.0f} px wide in the 640x480 renders)")
    path = save_plot(OUT_DIR / "prepare.png", {"photos / s": ([r["megapixels"] for r in speed],
                                                              [r["photos / s"] for r in speed])},
                     xlabel="photo megapixels", ylabel="photos / s", logx=True,
                     title=f"apps.prepare throughput; synthetic landmark error "
                           f"{summary[0]['mean'] if summary else float('nan'):.1f} px")
    print(f"wrote {path}")
    return 0


if __name__ == "__main__":
    sys.exit(run_cli(main))
