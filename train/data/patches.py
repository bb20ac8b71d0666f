"""The ETH-XGaze release's subject files (``train.data.layouts.XGAZE``: ``xgaze_224`` / ``xgaze_448``) read row by
row for the gaze estimator: each row's normalized face patch as RGB uint8, resized, with its labels (``face_gaze``
and ``face_head_pose``) in native conventions and, where the file has them, its landmarks.

The release holds no masks, cameras or codes, so :func:`train.data.layout_files.row_layout` refuses its files for every
stage that renders or poses heads; the estimator stage reads them here instead. What the release's files are
(xucong-zhang/ETH-XGaze ef9bff0):

- ``face_patch`` is BGR: normalization_example.py L265 reads the frame with ``cv2.imread``, L66 warps it into the
  normalized camera and L323 stores it; data_loader.py L130 and demo.py L159 flip it (``[:, :, [2, 1, 0]]``,
  "from BGR to RGB") before the network. Square (roiSize, L30; L302-304), uint8.
- It is the whole input of ETH-XGaze's own baseline: data_loader.py L129-137 reads ``face_patch`` and
  ``face_gaze`` only, model.py L5-19 regresses (pitch, yaw) from it with a ResNet-50, trainer.py L123-128 trains
  it with an L1 loss and scores it by angular error (L125, utils.py L60-75). No landmark crop is involved.
- ``face_gaze`` is the gaze (pitch, yaw) in the normalized camera, pitch = asin(-g_y) (normalization_example.py
  L73-75, L313-315), the native ``pitchyaw_cam`` convention (``layouts.XGAZE.renames``); ``face_head_pose`` is the
  face direction in the same camera (L327-331), the native ``face_head_pose``.
- The held-out test subjects have no ``face_gaze`` (data_loader.py L64-66 reads them with ``is_load_label=False``;
  README.md L45-46: their labels are scored on the leaderboard only).

Every read goes through ``toolkit.h5``'s bounded reader; a :class:`ReleasePatches` checks its files when it is
built (the layout's keys and shapes, ``face_patch``'s dtype and size, finite labels in range): each failure is
one ToolkitError naming the file and key.
"""

from __future__ import annotations

import os
import threading
from pathlib import Path
from typing import Any, Sequence

import numpy as np
import torch

from toolkit.errors import ToolkitError, one_line
from toolkit.h5 import READ_ERRORS, has_key, open_h5
from train.data.layouts import XGAZE

LABEL_KEY = "face_gaze"
"""The release's gaze label, which its held-out test subjects lack."""


def release_layout(files: Sequence[str | os.PathLike], layout: str = "auto") -> bool:
    """Whether a run's subject ``files`` are ETH-XGaze release files: ``layout`` ``xgaze``, or ``auto`` and the
    first file's keys fit that layout alone (``train.data.layouts.detect_layout``; a file no layout fits, or several,
    is left to the readers, whose message names what is wrong)."""
    if layout != "auto":
        return layout == XGAZE.name
    from train.data.layouts import describe_file, detect_layout

    if not files:
        return False
    try:
        return detect_layout(*describe_file(files[0])) is XGAZE
    except ToolkitError:
        return False


def has_labels(path: str | os.PathLike) -> bool:
    """Whether a release file holds gaze labels (``face_gaze``; the release's test subjects do not)."""
    with open_h5(path) as f:
        return has_key(path, f, LABEL_KEY)


def has_landmarks(path: str | os.PathLike) -> bool:
    """Whether a release file holds ``facial_landmarks`` (normalization_example.py L299 writes them; the
    published xgaze_224 / xgaze_448 files do not)."""
    with open_h5(path) as f:
        return has_key(path, f, "facial_landmarks")


def _patch_dataset(path, f):
    """The file's ``face_patch`` dataset, checked: [N, H, H, 3] uint8 (normalization_example.py L302-304), N >= 1,
    H in [8, 16384], a row read bounded (its bytes, and the HDF5 chunks it spans)."""
    from toolkit.h5 import MAX_ROW_CHUNKS, chunk_count, h5_dataset, row_nbytes
    from toolkit.limits import check_allocation

    ds = h5_dataset(path, f, "face_patch")
    shape = tuple(ds.shape)
    if len(shape) != 4 or shape[3] != 3 or shape[1] != shape[2] or not 8 <= shape[1] <= 16384 or shape[0] < 1:
        raise ToolkitError(f"{path}: key 'face_patch' has shape {list(shape)}, expected square BGR patches [N, H, H, 3] "
                           f"with N >= 1 and H in [8, 16384] (normalization_example.py L30, L302-304)")
    if ds.dtype != np.uint8:
        raise ToolkitError(f"{path}: key 'face_patch' has dtype {ds.dtype}, expected uint8 images "
                           f"(normalization_example.py L302-304)")
    check_allocation(row_nbytes(ds), f"{path}: key 'face_patch': reading one row")
    if chunk_count(ds, whole=False) > MAX_ROW_CHUNKS:
        raise ToolkitError(f"{path}: key 'face_patch' stores one row in {chunk_count(ds, whole=False)} HDF5 chunks, "
                           f"more than {MAX_ROW_CHUNKS}; rewrite the file with larger chunks")
    return ds


def _read_rows(path, f, key: str, n: int, trailing: tuple) -> np.ndarray:
    """The whole per-row key ``key`` (bounded read), checked: [n, *trailing] floats, all finite."""
    from toolkit.h5 import read_array

    a = read_array(path, f, key)
    if a.shape != (n, *trailing):
        want = ", ".join(map(str, (n, *trailing)))
        raise ToolkitError(f"{path}: key '{key}' has shape {list(a.shape)}, expected [{want}] for the file's {n} "
                           f"face patches")
    if a.dtype.kind not in "fiu":
        raise ToolkitError(f"{path}: key '{key}' has dtype {a.dtype}, expected floats")
    bad = np.flatnonzero(~np.isfinite(a.reshape(n, -1)).all(1))
    if len(bad):
        raise ToolkitError(f"{path}: key '{key}' row {int(bad[0])} holds NaN or inf"
                           + (f" ({len(bad)} rows do)" if len(bad) > 1 else ""))
    return a


def _check_angles(path, key: str, a: np.ndarray) -> None:
    far = np.flatnonzero((np.abs(a[:, 0]) > np.pi / 2 + 1e-4) | (np.abs(a[:, 1]) > np.pi + 1e-4))
    if len(far):
        raise ToolkitError(f"{path}: key '{key}' row {int(far[0])} is {a[far[0]].tolist()}, expected (pitch, yaw) "
                           f"radians with |pitch| <= pi/2 and |yaw| <= pi")


def _read_file(path: Path, res: int, landmarks: bool) -> tuple[int, np.ndarray, np.ndarray | None]:
    """One release file checked and its per-row labels read: (rows, labels [N, 4] float32 (camera-frame gaze,
    head pose; native conventions), landmarks [N, 68, 2] float32 pixels of the res x res image or None). Every
    failure is one ToolkitError naming the file and key."""
    s = release_summary(path)
    if s["gaze"] is None:
        raise ToolkitError(f"{path}: no key '{LABEL_KEY}': a held-out subject of the release (its labels are "
                           f"withheld, ETH-XGaze README.md L45-46) cannot be trained on or scored")
    n, size, lm = s["n"], s["size"], None
    if landmarks:
        if not s["landmarks"]:
            raise ToolkitError(f"{path}: no key 'facial_landmarks', which the eye-patch estimator reads")
        with open_h5(path) as f:
            lm = _read_rows(path, f, "facial_landmarks", n, (68, 2))
        if (lm < -size).any() or (lm > 2 * size).any():
            raise ToolkitError(f"{path}: key 'facial_landmarks' lies far outside the {size}x{size} patch "
                               f"(pixels expected)")
        lm = lm.astype(np.float32) * np.float32(res / size)
    labels = np.concatenate([s["gaze"], s["head_pose"]], 1).astype(np.float32)
    return n, labels, lm


def release_summary(path: str | os.PathLike) -> dict[str, Any]:
    """One release file checked as :class:`ReleasePatches` checks it, a test subject's too, and summarized:
    ``{"n", "size" (patch side, pixels), "gaze" [N, 2] native ``pitchyaw_cam`` radians or None (a held-out test
    subject), "head_pose" [N, 2] radians, "cameras", "frames" (distinct indices), "landmarks" (bool)}``."""
    from toolkit.h5 import read_array
    from train.data.layout_conversion import to_native
    from train.data.layouts import check_layout, describe_file

    keys, shapes = describe_file(path)
    check_layout(XGAZE, keys, shapes, str(path))
    with open_h5(path) as f:
        n, size = (int(x) for x in _patch_dataset(path, f).shape[:2])
        rows = {k: _read_rows(path, f, k, n, (2,)) for k in (LABEL_KEY, "face_head_pose") if has_key(path, f, k)}
        for k, a in rows.items():
            _check_angles(path, k, a)
        distinct = {k: int(np.unique(read_array(path, f, k)).size) for k in ("cam_index", "frame_index")}
        landmarks = has_key(path, f, "facial_landmarks")
    native = to_native(XGAZE, rows)  # face_gaze -> pitchyaw_cam (the same sign)
    return {"n": n, "size": size, "gaze": native.get("pitchyaw_cam"), "head_pose": native["face_head_pose"],
            "cameras": distinct["cam_index"], "frames": distinct["frame_index"], "landmarks": landmarks}


def read_patches(path: str | os.PathLike, rows: Sequence[int]) -> np.ndarray:
    """Rows of a release file's ``face_patch`` as stored: [len(rows), H, H, 3] uint8 BGR, one bounded read each."""
    from toolkit.h5 import read_selection

    with open_h5(path) as f:
        ds = _patch_dataset(path, f)
        return np.stack([read_selection(path, "face_patch", ds, int(r)) for r in rows])


class ReleasePatches(torch.utils.data.Dataset):
    """The rows of ETH-XGaze release files, for the gaze estimator.

    Args:
        files: release subject files (every one with ``face_gaze``: :func:`has_labels`).
        res: the square size the patches are resized to (``cv2.INTER_AREA`` when shrinking, as
            ``train.data.dataset.resize_image``).
        landmarks: also read ``facial_landmarks`` (scaled to ``res``), which eye-patch estimators need.

    Built: every file is checked (the layout's keys and shapes, ``face_patch``'s dtype and size, finite labels in
    range) and its labels read, a few bytes a row: :attr:`labels` [N, 4] float32 (``face_gaze`` as the native ``pitchyaw_cam``, then ``face_head_pose``:
    the ``[B, 4]`` the estimator reads), :attr:`landmarks` [N, 68, 2] or None. An item is read when asked for:
    ``{"image": uint8 [3, res, res] RGB}``, one bounded HDF5 row read; handles are opened once per file (per
    process) and shared by the reading threads.
    """

    def __init__(self, files: Sequence[str | os.PathLike], res: int, *, landmarks: bool = False):
        self.files = [Path(f) for f in files]
        if not self.files:
            raise ToolkitError("ReleasePatches: no subject files given")
        if not 8 <= int(res) <= 4096:
            raise ToolkitError(f"res: expected an integer in [8, 4096], got {res}")
        self.res = int(res)
        counts, labels, lms = [], [], []
        for path in self.files:
            n, lab, lm = _read_file(path, self.res, landmarks)
            counts.append(n)
            labels.append(lab)
            lms.append(lm)
        self.counts = counts
        self.starts = np.concatenate([[0], np.cumsum(counts)])
        self.labels = torch.from_numpy(np.concatenate(labels))
        self.landmarks = torch.from_numpy(np.concatenate(lms)) if landmarks else None
        self._handles: dict[int, Any] = {}
        self._lock = threading.Lock()
        self._pid = os.getpid()

    def __len__(self) -> int:
        return int(self.starts[-1])

    def locate(self, i: int) -> tuple[int, int]:
        """(file index, row in that file) of item ``i``."""
        k = int(np.searchsorted(self.starts, i, side="right")) - 1
        return k, int(i - self.starts[k])

    def _patches(self, k: int):
        """File ``k``'s ``face_patch`` dataset, its file opened once (per process; h5py serializes the threads)."""
        import h5py

        from toolkit.h5 import h5_dataset

        with self._lock:
            if self._pid != os.getpid():  # forked: never reuse the parent's handles
                self._handles, self._pid = {}, os.getpid()
            got = self._handles.get(k)
            if got is None:
                path = self.files[k]
                try:
                    f = h5py.File(path, "r")
                except READ_ERRORS as e:
                    raise ToolkitError(f"{path}: cannot open ({one_line(e, None)})") from e
                got = self._handles[k] = (f, h5_dataset(path, f, "face_patch"))
            return got[1]

    def read_patch(self, i: int) -> np.ndarray:
        """Item ``i``'s stored patch, as the file holds it: [H, W, 3] uint8 BGR."""
        from toolkit.h5 import read_selection

        k, row = self.locate(i)
        return read_selection(self.files[k], "face_patch", self._patches(k), row)

    def __getitem__(self, i: int) -> dict[str, torch.Tensor]:
        if not -len(self) <= i < len(self):
            raise IndexError(i)
        from train.data.dataset import resize_image

        rgb = np.ascontiguousarray(self.read_patch(i % len(self))[..., ::-1])  # stored BGR
        img = resize_image(rgb, self.res)
        return {"image": torch.from_numpy(np.ascontiguousarray(img.transpose(2, 0, 1)))}

    def close(self) -> None:
        with self._lock:
            for f, _ in self._handles.values():
                f.close()
            self._handles = {}

    def __getstate__(self):
        state = self.__dict__.copy()
        state["_handles"], state["_lock"] = {}, None
        return state

    def __setstate__(self, state):
        self.__dict__.update(state)
        self._lock = threading.Lock()


def _image_row(item: dict[str, torch.Tensor]) -> dict[str, torch.Tensor]:
    return item


def release_rows(files: Sequence[str | os.PathLike], res: int, *, landmarks: bool = False, workers: int = 0,
                 cache_bytes: int | None = None) -> tuple:
    """(images, labels [N, 4], landmarks [N, 68, 2] or None) of release ``files`` for the gaze estimator: the
    images a :class:`train.data.rows.RowImages` of uint8 [N, 3, res, res] read from the files when a batch
    indexes them (through a :class:`train.data.rows.RowSource` with ``workers`` reading threads and a cache of
    ``cache_bytes``, default ``DEFAULT_CACHE_BYTES``), the labels read up front. Unlike the native rows, no pass
    over the images is made up front: the release holds over a million patches."""
    from train.data.rows import DEFAULT_CACHE_BYTES, RowImages, RowSource

    patches = ReleasePatches(files, res, landmarks=landmarks)
    source = RowSource(patches, _image_row, cache_bytes=DEFAULT_CACHE_BYTES if cache_bytes is None else cache_bytes,
                       workers=workers)
    return RowImages(source, "image", (3, patches.res, patches.res), torch.uint8), patches.labels, patches.landmarks
