"""The contact sheet of a prepare run: per face, the photo with its detected landmarks, the normalized crop with
its landmarks, iris centres and gaze, and the crop with its masks (head green, image-left eye blue, image-right
eye red). Written atomically as a PNG."""

from __future__ import annotations

import os

import numpy as np

TILE = 256
MAX_FACES = 24
"""Faces shown; the sheet says how many more there were."""


def _pt(p: np.ndarray, k: float = 1.0) -> tuple[int, int]:
    """u = 0 left-edge pixels (scaled by ``k``) -> OpenCV's integer-centre drawing coordinates."""
    return int(round(p[0] * k - 0.5)), int(round(p[1] * k - 0.5))


def _photo_tile(bgr: np.ndarray, landmarks: np.ndarray, box: np.ndarray) -> np.ndarray:
    import cv2

    h, w = bgr.shape[:2]
    k = TILE / max(h, w)
    small = cv2.resize(bgr, (max(1, round(w * k)), max(1, round(h * k))), interpolation=cv2.INTER_AREA)
    tile = np.full((TILE, TILE, 3), 40, np.uint8)
    tile[: small.shape[0], : small.shape[1]] = small
    cv2.rectangle(tile, _pt(box[:2], k), _pt(box[2:], k), (0, 200, 255), 1)
    for p in landmarks:
        cv2.circle(tile, _pt(p, k), 1, (0, 255, 255), -1)
    return tile


def _crop_tiles(row: dict) -> tuple[np.ndarray, np.ndarray]:
    import cv2

    from apps.photo.gaze import pitchyaw_vector

    crop = row["face_patch"]
    k = TILE / crop.shape[0]
    a = cv2.resize(crop, (TILE, TILE), interpolation=cv2.INTER_AREA if k < 1 else cv2.INTER_LINEAR)
    for p in row["facial_landmarks"]:
        cv2.circle(a, _pt(p, k), 1, (0, 255, 255), -1)
    g = pitchyaw_vector(row["pitchyaw_cam"])
    for c in row["iris_centers"]:
        if (c >= 0).all():
            cv2.circle(a, _pt(c, k), 2, (255, 0, 255), -1)
            cv2.arrowedLine(a, _pt(c, k), _pt(c + 0.2 * crop.shape[0] * g[:2], k), (0, 0, 255), 2,
                            tipLength=0.2)
    b = cv2.resize(crop, (TILE, TILE), interpolation=cv2.INTER_AREA if k < 1 else cv2.INTER_LINEAR).astype(np.float32)
    for key, color in (("head_mask", (0, 200, 0)), ("left_eye_mask", (255, 80, 0)), ("right_eye_mask", (0, 0, 255))):
        m = cv2.resize(row[key], (TILE, TILE), interpolation=cv2.INTER_NEAREST)[..., None] / 255.0
        b = b * (1 - 0.45 * m) + 0.45 * m * np.array(color, np.float32)
    return a, np.clip(b, 0, 255).astype(np.uint8)


def sheet_strip(name: str, photo: np.ndarray, source_landmarks: np.ndarray, row: dict) -> np.ndarray:
    """One face's strip [18 + TILE, 3·TILE, 3] uint8 BGR: a caption, then the photo ([H, W, 3] BGR) with the
    landmarks ``source_landmarks`` [68, 2] (photo pixels), the crop with its labels, the crop with its masks
    (``row``: one row's arrays, apps.photo.rows). Made as each face is done: the sheet keeps no photo."""
    import cv2

    crop_a, crop_b = _crop_tiles(row)
    tiles = np.concatenate([_photo_tile(photo, source_landmarks, row["face_box"]), crop_a, crop_b], 1)
    label = np.full((18, tiles.shape[1], 3), 255, np.uint8)
    py, hp = np.degrees(row["pitchyaw_head"]), np.degrees(row["face_head_pose"])
    text = (f"{name[:40]}  head {hp[0]:+.0f}/{hp[1]:+.0f}  gaze {py[0]:+.0f}/{py[1]:+.0f} (head frame)  "
            f"scale {float(row['scale'][0]):.2f}")
    cv2.putText(label, text, (4, 13), cv2.FONT_HERSHEY_SIMPLEX, 0.4, (0, 0, 0), 1, cv2.LINE_AA)
    return np.concatenate([label, tiles], 0)


def write_contact_sheet(path: str | os.PathLike, strips: list[np.ndarray], total: int) -> None:
    """The first :data:`MAX_FACES` ``strips`` (:func:`sheet_strip`) stacked, with a line for the ``total`` −
    shown faces left out, written as a PNG atomically."""
    import cv2

    from toolkit.io import atomic_write_bytes

    blocks = list(strips[:MAX_FACES])
    if total > len(blocks):
        more = np.full((18, 3 * TILE, 3), 255, np.uint8)
        cv2.putText(more, f"... and {total - len(blocks)} more faces", (4, 13), cv2.FONT_HERSHEY_SIMPLEX, 0.4,
                    (0, 0, 0), 1, cv2.LINE_AA)
        blocks.append(more)
    ok, buf = cv2.imencode(".png", np.concatenate(blocks, 0))
    if not ok:
        raise OSError(f"PNG encoding failed for {path}")
    atomic_write_bytes(path, buf.tobytes())
