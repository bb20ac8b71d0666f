"""Faces in a photo: mediapipe's face detector, then its 478-point face mesh on each face, at full resolution.

The backend is mediapipe 0.10.21's legacy ``solutions`` (Apache-2.0; the models ship inside the wheel, nothing is
downloaded): ``FaceDetection`` (the full-range model) finds the faces on the photo downscaled to
:data:`DETECT_SIDE`; each face is then cut from the **full-resolution** photo as a square of
:data:`CROP_MARGIN` × its box, resized to :data:`MESH_SIDE`, and ``FaceMesh(refine_landmarks=True)`` fits its
478 points (iris centres 468 / 473 included), mapped back to photo pixels. ``SelfieSegmentation`` gives the
person mask the head mask is refined with (:mod:`apps.photo.masks`). The import is lazy: without the optional
extra ``photos`` a ToolkitError says how to install it.

mediapipe's C++ side logs to file descriptor 2 (absl / glog, TF Lite INFO lines); :func:`quiet_fd2` sends that
to /dev/null around every call so none of it reaches the user's terminal.
"""

from __future__ import annotations

import contextlib
import math
import os
from dataclasses import dataclass

import numpy as np

from toolkit.errors import ToolkitError

PHOTOS_EXTRA = ("reading faces from photos needs the optional extra 'photos' (mediapipe 0.10.21): run `make setup`, or "
                "`pip install -e '.[photos]' && pip install --no-deps mediapipe==0.10.21`")

DETECT_SIDE = 1024
"""Longest side of the photo the detector sees (it resizes to 192² inside: larger only costs time)."""
MESH_SIDE = 320
"""Side of the face crop the mesh is fitted on (its landmark model reads the face at 192² or 256²)."""
CROP_MARGIN = 2.0
"""Side of that crop / the detector's box side: the mesh's own short-range detector wants the face at ~half."""
MIN_DETECTION = 0.5
"""Detector and mesh confidence thresholds."""
TILE_SIDE = 768
"""Side of the tiles a photo where the whole-photo detector finds no face is searched in: the detector finds a
face down to ~6% of the longer side of what it sees (a 92-pixel face in a 1600² image, not in an 1800² or a
2000 × 512 one), so a face of the pipeline's least width (64 pixels) is ~8% of a tile. Faces in a panorama or
a large group photo (each a few per cent of the photo's width) are found this way."""
TILE_OVERLAP_NMS = 0.3
"""Two detections (of overlapping tiles) are one face when their boxes overlap by this IoU, or the smaller lies
this much inside the larger."""


@contextlib.contextmanager
def quiet_fd2():
    """Send file descriptor 2 to /dev/null for the block (mediapipe's C++ log lines), restoring it after."""
    import sys

    with contextlib.suppress(AttributeError, ValueError, OSError):
        sys.stderr.flush()
    saved = os.dup(2)
    devnull = os.open(os.devnull, os.O_WRONLY)
    try:
        os.dup2(devnull, 2)
        yield
    finally:
        os.dup2(saved, 2)
        os.close(saved)
        os.close(devnull)


def import_mediapipe():
    """mediapipe's ``solutions`` module, imported quietly; a ToolkitError naming the extra when missing."""
    os.environ.setdefault("GLOG_minloglevel", "2")
    os.environ.setdefault("TF_CPP_MIN_LOG_LEVEL", "3")
    try:
        with quiet_fd2():
            from mediapipe.python import solutions
    except ImportError as e:
        raise ToolkitError(f"{PHOTOS_EXTRA} ({e.__class__.__name__}: {str(e)[:80]})") from None
    with contextlib.suppress(ImportError):
        from absl import logging as absl_logging

        absl_logging.set_verbosity(absl_logging.ERROR)
    return solutions


@dataclass
class MeshFace:
    """One face found in a photo: ``points`` [478, 3] float64, (u, v) in photo pixels (u = 0 the left edge) and
    mediapipe's relative depth z in pixels; ``box`` [4] the detector's box (x0, y0, x1, y1) in photo pixels;
    ``score`` the detector's confidence."""

    points: np.ndarray
    box: np.ndarray
    score: float

    @property
    def width(self) -> float:
        """Face width in photo pixels: the extent of the mesh along x."""
        return float(np.ptp(self.points[:, 0]))


def _square_crop(rgb: np.ndarray, center: np.ndarray, side: float, roll: float,
                 out: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """An ``out`` × ``out`` crop of the square of ``side`` pixels around ``center`` [2], turned by ``roll``
    radians (so a face rolled by it comes out upright), area-averaged when it shrinks by more than 1.5; outside
    the photo is black. Returns (crop, A [2, 2], b [2]) with photo point p = A q + b for a crop point q (both
    u = 0 left-edge pixels)."""
    import cv2

    s = side / out
    c, si = np.cos(roll), np.sin(roll)
    A = s * np.array([[c, -si], [si, c]])
    b = np.asarray(center, np.float64) - A @ np.array([out / 2, out / 2])
    k = np.ones(2)
    if s > 1.5:  # shrink first, so the warp does not alias
        n = int(s)
        small = cv2.resize(rgb, (max(1, rgb.shape[1] // n), max(1, rgb.shape[0] // n)), interpolation=cv2.INTER_AREA)
        k = np.array([rgb.shape[1] / small.shape[1], rgb.shape[0] / small.shape[0]])  # edges map to edges
        rgb = small
    # crop (OpenCV integer-centre pixels) -> source: src_cv = (A (q_cv + 0.5) + b) / k - 0.5
    M = np.concatenate([A / k[:, None], ((A @ np.full(2, 0.5) + b) / k - 0.5)[:, None]], 1)
    crop = cv2.warpAffine(rgb, M, (out, out), flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP,
                          borderMode=cv2.BORDER_CONSTANT)
    return crop, A, b


def _tile_starts(n: int, side: int) -> list[int]:
    """Offsets of tiles of ``side`` along ``n`` pixels at half-tile strides, the last flush with the end."""
    if n <= side:
        return [0]
    return list(range(0, n - side, side // 2)) + [n - side]


def _overlap(a: np.ndarray, b: np.ndarray) -> float:
    """max(IoU, intersection / the smaller area) of two boxes (x0, y0, x1, y1)."""
    iw = max(0.0, min(a[2], b[2]) - max(a[0], b[0]))
    ih = max(0.0, min(a[3], b[3]) - max(a[1], b[1]))
    inter = iw * ih
    area = lambda q: max(1e-9, (q[2] - q[0]) * (q[3] - q[1]))  # noqa: E731
    return max(inter / (area(a) + area(b) - inter), inter / min(area(a), area(b)))


class FaceFinder:
    """mediapipe's detector, face mesh and selfie segmenter, built once and reused for every photo (a context
    manager: ``with FaceFinder() as ff: faces = ff.faces(rgb)``)."""

    def __init__(self, max_faces: int = 16):
        sol = import_mediapipe()
        with quiet_fd2():
            self._detector = sol.face_detection.FaceDetection(model_selection=1, min_detection_confidence=MIN_DETECTION)
            self._mesh = sol.face_mesh.FaceMesh(static_image_mode=True, max_num_faces=1, refine_landmarks=True,
                                                min_detection_confidence=MIN_DETECTION)
            self._segmenter = sol.selfie_segmentation.SelfieSegmentation(model_selection=0)
            # The graphs open their models on worker threads, which log as they do: one call of each, still
            # quiet, waits for that.
            blank = np.zeros((MESH_SIDE, MESH_SIDE, 3), np.uint8)
            for m in (self._detector, self._mesh, self._segmenter):
                m.process(blank)
        self.max_faces = max_faces

    def __enter__(self) -> "FaceFinder":
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def close(self) -> None:
        with quiet_fd2():
            for m in (self._detector, self._mesh, self._segmenter):
                with contextlib.suppress(Exception):  # a graph already closed: nothing to release
                    m.close()

    def detect(self, rgb: np.ndarray, quarter_turns: int = 0) -> list[tuple[np.ndarray, float, float]]:
        """[H, W, 3] uint8 RGB -> [(box [4] x0, y0, x1, y1 photo pixels, score, roll radians from the eyes)],
        largest first; the detector sees the photo turned by ``quarter_turns`` × 90° (counter-clockwise), its
        results mapped back."""
        import cv2

        H, W = rgb.shape[:2]
        k = max(1.0, max(H, W) / DETECT_SIDE)
        size = (max(1, round(W / k)), max(1, round(H / k)))  # a sliver of a photo keeps one pixel across
        small = rgb if k == 1 else cv2.resize(rgb, size, interpolation=cv2.INTER_AREA)
        small = np.ascontiguousarray(np.rot90(small, quarter_turns))
        h, w = small.shape[:2]
        # A turned image's point (u, v) in the unturned one (scaled): np.rot90 by one quarter turn puts the unturned
        # point (x, y) at (y, width - x), and the turned image's height is the unturned width, so x = h - v.
        back = {0: lambda u, v: (u, v), 1: lambda u, v: (h - v, u), 2: lambda u, v: (w - u, h - v),
                3: lambda u, v: (v, w - u)}[quarter_turns % 4]
        sx, sy = W / small.shape[1 - quarter_turns % 2], H / small.shape[quarter_turns % 2]
        photo = lambda u, v: np.array(back(u, v)) * (sx, sy)  # noqa: E731
        with quiet_fd2():
            res = self._detector.process(small)
        boxes = []
        for d in res.detections or []:
            b = d.location_data.relative_bounding_box
            corners = np.array([photo(x * w, y * h) for x in (b.xmin, b.xmin + b.width) for y in (b.ymin, b.ymin + b.height)])
            kp = d.location_data.relative_keypoints  # 0, 1: the image-left and image-right eye of an upright face
            eyes = [photo(kp[i].x * w, kp[i].y * h) for i in (0, 1)] if len(kp) >= 2 else None
            roll = 0.0 if eyes is None else math.atan2(*(eyes[1] - eyes[0])[::-1])
            boxes.append((np.concatenate([corners.min(0), corners.max(0)]), float(d.score[0]) if d.score else 0.0, roll))
        boxes.sort(key=lambda bs: -(bs[0][2] - bs[0][0]) * (bs[0][3] - bs[0][1]))
        return boxes[: self.max_faces]

    def detect_tiled(self, rgb: np.ndarray, side: int = TILE_SIDE) -> list[tuple[np.ndarray, float, float]]:
        """As :meth:`detect`, on overlapping tiles: squares of ``side``, ``2 side``, ... (while smaller than the
        photo's longer side) at half-tile strides, so that every face up to half a tile lies whole in one tile at
        some level. A detection touching a tile's edge inside the photo is left to the tile that holds it whole;
        the same face seen in several tiles is kept once (its best score)."""
        H, W = rgb.shape[:2]
        found = []
        while side < max(H, W):
            margin = 0.02 * side
            for y0 in _tile_starts(H, side):
                for x0 in _tile_starts(W, side):
                    tile = np.ascontiguousarray(rgb[y0:y0 + side, x0:x0 + side])
                    th, tw = tile.shape[:2]
                    for box, score, roll in self.detect(tile):
                        if ((x0 > 0 and box[0] < margin) or (y0 > 0 and box[1] < margin)
                                or (x0 + tw < W and box[2] > tw - margin) or (y0 + th < H and box[3] > th - margin)):
                            continue  # cut by the tile: whole in an overlapping one
                        found.append((box + np.array([x0, y0, x0, y0], np.float64), score, roll))
            side *= 2
        kept: list[tuple[np.ndarray, float, float]] = []
        for d in sorted(found, key=lambda d: -d[1]):
            if all(_overlap(d[0], k[0]) < TILE_OVERLAP_NMS for k in kept):
                kept.append(d)
        kept.sort(key=lambda bs: -(bs[0][2] - bs[0][0]) * (bs[0][3] - bs[0][1]))
        return kept[: self.max_faces]

    def mesh(self, rgb: np.ndarray, box: np.ndarray, roll: float = 0.0) -> np.ndarray | None:
        """The 478 mesh points [478, 3] (photo pixels; z mediapipe's relative depth) of the face in ``box``, cut
        out turned upright by ``roll``; None when the mesh finds no face there (a profile, an occluded face)."""
        side = CROP_MARGIN * max(box[2] - box[0], box[3] - box[1])
        crop, A, b = _square_crop(rgb, 0.5 * (box[:2] + box[2:]), side, roll, MESH_SIDE)
        with quiet_fd2():
            res = self._mesh.process(crop)
        if not res.multi_face_landmarks:
            return None
        # mediapipe's normalized coordinates: 0 and 1 are the crop's edges, so x * MESH_SIDE is u from its left edge
        lm = np.array([[p.x, p.y, p.z] for p in res.multi_face_landmarks[0].landmark], np.float64) * MESH_SIDE
        return np.concatenate([lm[:, :2] @ A.T + b, lm[:, 2:] * (side / MESH_SIDE)], 1)

    def faces(self, rgb: np.ndarray) -> tuple[list[MeshFace], int]:
        """Every face of a photo ([H, W, 3] uint8 RGB) with its mesh, largest first, and how many detected faces
        the mesh could not fit. Each face's crop is turned upright by the roll of its eyes. A photo where the
        detector finds none is tried turned by 90°, 270° and 180°, then in tiles (:meth:`detect_tiled`: faces too
        small for the whole photo's detector, as in a panorama or a group photo; also when the mesh fits none of
        the whole photo's detections); a face seen by the mesh but not the detector (a close-up filling the photo)
        by a last try on the whole photo."""
        boxes = self.detect(rgb)
        for turns in (1, 3, 2):  # a photo on its side (no or a wrong EXIF orientation): the detector wants upright
            boxes = boxes or self.detect(rgb, turns)
        found, unfitted = self._fitted(rgb, boxes)
        if not found:  # none, or none the mesh fits (a false detection on a turned pass): the faces may be small
            found, unfitted_in_tiles = self._fitted(rgb, self.detect_tiled(rgb))
            unfitted = max(unfitted, unfitted_in_tiles)  # the same face may be detected both ways: counted once
        if not found and not boxes:  # no detection on the whole photo, no fit in tiles: a close-up, too big for it
            H, W = rgb.shape[:2]
            box = np.array([W / 2 - 0.25 * max(W, H), H / 2 - 0.25 * max(W, H),
                            W / 2 + 0.25 * max(W, H), H / 2 + 0.25 * max(W, H)])
            pts = self.mesh(rgb, box)
            if pts is not None:
                found = [MeshFace(pts, box, 0.0)]
        return found, unfitted

    def _fitted(self, rgb: np.ndarray, boxes: list[tuple[np.ndarray, float, float]]) -> tuple[list[MeshFace], int]:
        """The detections the mesh fits, as faces, and how many scored detections it did not fit."""
        found, unfitted = [], 0
        for box, score, roll in boxes:
            pts = self.mesh(rgb, box, roll)
            if pts is None:
                unfitted += score > 0
                continue
            found.append(MeshFace(pts, box, score))
        return found, unfitted

    def person(self, rgb: np.ndarray) -> np.ndarray:
        """[H, W, 3] uint8 RGB -> [H, W] float32 in [0, 1]: how likely each pixel shows a person."""
        with quiet_fd2():
            res = self._segmenter.process(np.ascontiguousarray(rgb))
        return np.asarray(res.segmentation_mask, np.float32)
