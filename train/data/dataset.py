"""GazeDataset: one loader for real (GazeGaussian-preprocessed ETH-XGaze) and synthetic subject files.

The schema of every file is validated when the dataset is built (a missing key or a wrong shape names
the file and key); samples are then read lazily, one HDF5 handle per file per worker process (handles
are reopened after a fork, so DataLoader workers never share one), resized, and composited on white
outside the head mask.
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any, Sequence

import numpy as np
import torch

from toolkit.errors import ToolkitError, one_line
from toolkit.h5 import READ_ERRORS, has_key, read_array, read_selection
from train.data.format import OPTIONAL
from train.data.layout_conversion import mesh_to_native, to_native
from train.data.layout_files import check_frames, native_keys, row_layout, validate_file
from train.data.layouts import DITGAZE, agreed_code_widths

SPLITS = ("all", "train", "test")


APPLEDOUBLE_MAGIC = b"\x00\x05\x16\x07"
"""The first bytes of a macOS AppleDouble file (``._NAME``), which macOS writes beside every file it copies to a
non-Mac volume or share: ``._subject0000.h5`` holds Finder metadata, not HDF5."""


def _appledouble(p: Path) -> bool:
    if not p.name.startswith("._"):
        return False
    try:
        with open(p, "rb") as fh:
            return fh.read(4) == APPLEDOUBLE_MAGIC
    except OSError:
        return False


def find_subject_files(paths: str | os.PathLike | Sequence[str | os.PathLike]) -> list[Path]:
    """Files from a list of files and/or folders (a folder contributes its ``*.h5``, sorted, but for the
    AppleDouble ``._*.h5`` files macOS leaves beside them)."""
    if isinstance(paths, (str, os.PathLike)):
        paths = [paths]
    files: list[Path] = []
    for p in map(Path, paths):
        if p.is_dir():
            found = sorted(q for q in p.glob("*.h5") if not _appledouble(q))
            unlisted = sorted(q.name for q in p.iterdir() if q.suffix.lower() in (".h5", ".hdf5")
                              and q.suffix != ".h5" and not _appledouble(q))
            if unlisted:  # left out, the dataset would lack these subjects unseen
                raise ToolkitError(f"{p}: {unlisted[0]}" + (f" (and {len(unlisted) - 1} more)" if unlisted[1:] else "")
                                   + ": subject files are listed by the suffix .h5 (lower case); rename it")
            if not found:
                raise ToolkitError(f"{p}: no *.h5 subject files in this folder")
            files += found
        elif p.exists():
            files.append(p)
        else:
            raise ToolkitError(f"{p}: no such file or folder")
    if not files:
        raise ToolkitError("no subject files given")
    return files


def held_out_count(n_subjects: int, test_fraction: float) -> int:
    """How many of ``n_subjects`` (the last ones) are held out: ``test_fraction`` of them, at least one when
    there are two or more. The one rule for :func:`split_files` and the ``split.json`` the generator writes."""
    return max(1, round(test_fraction * n_subjects)) if n_subjects > 1 else 0


SPLIT_FILE_NAMES = ("split.json", "train_test_split.json")
"""The split files looked for beside the subject files, in this order: the native one, then the peers'."""
DATASET_PREFIXES = ("xgaze_", "mpii_", "columbia_", "gaze_capture_")
"""The prefixes GazeNeRF's preprocessing puts before a subject's name, one per dataset (dataset_pre_processing.py
L123, L496, L844; datasets/gaze_capture.py L246), while its split files name the subject alone
(data/*/train_test_split.json): a split entry names the file with or without one."""


def subject_key(stem: str) -> str:
    """A subject file's stem without its dataset prefix (:data:`DATASET_PREFIXES`): what split files name."""
    return next((stem[len(p):] for p in DATASET_PREFIXES if stem.startswith(p)), stem)


def check_no_other_dataset(out: str | os.PathLike, names: list[str], flag: str, writer: str) -> None:
    """The folder ``out`` (``flag`` on the command line) holds no subject or split file besides ``names``, the
    files ``writer`` is about to replace: what else is there would join its dataset (split "all", a folder read
    whole) unseen."""
    out = Path(out)
    if not out.is_dir():
        return
    others = sorted(p.name for p in out.iterdir() if p.name not in names and not p.name.startswith(".")
                    and (p.suffix.lower() in (".h5", ".hdf5") or p.name in SPLIT_FILE_NAMES))
    if others:
        raise ToolkitError(f"{flag} {out}: holds {len(others)} other dataset file(s) ({', '.join(others[:3])}"
                           f"{', ...' if len(others) > 3 else ''}), which would mix with this {writer}; expected a new or "
                           f"empty folder, or an earlier {writer} of the same subjects")


def split_files(files: list[Path], split: str, split_file: str | os.PathLike | None = None,
                test_fraction: float = 0.25, layout: str = "auto") -> list[Path]:
    """Select a split. A split file decides: ``split_file``, else ``split.json`` or ``train_test_split.json``
    beside the files, read in the form of ``layout`` (``train.data.layout_files.read_split_file``; ``split.json``
    is always the native form, another file takes the form of the files' layout, ``auto``: detected from the
    first file). Every subject it names for ``split`` must be among ``files``. Without a split file, the last
    ``test_fraction`` of the sorted files (at least one when there are two or more) are the test subjects."""
    from train.data.layout_files import read_split_file, row_layout
    from train.data.layouts import DITGAZE

    if split not in SPLITS:
        raise ToolkitError(f"split: expected one of {SPLITS}, got {split!r}")
    if split == "all":
        return files
    beside = [files[0].parent / name for name in SPLIT_FILE_NAMES if (files[0].parent / name).exists()]
    sf = Path(split_file) if split_file else (beside[0] if beside else None)
    if sf is not None:
        form = DITGAZE if sf.name == SPLIT_FILE_NAMES[0] and layout == "auto" else row_layout(files[0], layout)
        train, held = read_split_file(sf, form)
        names = {subject_key(n) for n in (train if split == "train" else held)}
        by_key: dict[str, Path] = {}
        for f in files:
            if by_key.setdefault(subject_key(f.stem), f) != f:
                raise ToolkitError(f"{sf}: the files {by_key[subject_key(f.stem)].name} and {f.name} are both "
                                   f"subject {subject_key(f.stem)}; keep one dataset's files in a folder")
        missing = sorted(names - set(by_key))
        if missing:
            key = form.split.train_key if split == "train" else form.split.held_out_key
            raise ToolkitError(f"{sf}: '{key}' names subject {missing[0]}, which is not among the {len(files)} "
                               f"subject files given (file {missing[0]}.h5 expected, or with a dataset prefix "
                               f"such as {DATASET_PREFIXES[0]})")
        if not names:
            raise ToolkitError(f"{sf}: split '{split}' selects none of the {len(files)} given files")
        return [f for f in files if subject_key(f.stem) in names]
    files = sorted(files)
    n_test = held_out_count(len(files), test_fraction)
    chosen = files[len(files) - n_test:] if split == "test" else files[: len(files) - n_test]
    if not chosen:
        raise ToolkitError(f"split '{split}' is empty for {len(files)} file(s); pass a split file")
    return chosen


def resize_image(img: np.ndarray, res: int, *, nearest: bool = False) -> np.ndarray:
    """[H, W, C] or [H, W] -> res × res (area averaging when shrinking, bilinear when growing)."""
    import cv2

    if img.shape[0] == res and img.shape[1] == res:
        return img
    interp = cv2.INTER_NEAREST if nearest else (cv2.INTER_AREA if img.shape[0] > res else cv2.INTER_LINEAR)
    return cv2.resize(img, (res, res), interpolation=interp)


ROW_READ_KEYS = ("face_patch", "head_mask", "left_eye_mask", "right_eye_mask", "vertice")
"""Keys read one row at a time (images, then the mesh, read only ``with_mesh``); the others are read whole per
file and kept."""
LABEL_KEYS = ("facial_landmarks", "facial_landmarks_3d", "latent_codes", "pose", "scale", "w2c_Rmat", "w2c_Tvec",
              "inmat", "pitchyaw_head", "face_head_pose", "cam_index", "frame_index")
"""The small per-row keys every sample carries."""


def fold_head_scale(r: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
    """A row whose head ``scale`` s is not 1, rewritten with s folded into the world frame: every world length
    divided by s (``w2c_Tvec``, the pose's translation, ``facial_landmarks_3d``, ``vertice``) and ``scale`` 1.
    x_world = s R x_head + t becomes x_world / s = R x_head + t / s, and the camera, its translation divided by
    s too, sees the same scene scaled by 1 / s: the same image, the same gaze, the same landmarks (a perspective
    projection does not change under a uniform scaling of the camera frame). So every stage that poses the head
    rigidly reads scaled heads as unit-scale ones. A row of scale 1 is returned as it is."""
    s = np.float32(np.reshape(r["scale"], -1)[0])
    if s == 1:
        return r
    r = dict(r)
    r["w2c_Tvec"] = r["w2c_Tvec"] / s
    r["pose"] = np.concatenate([r["pose"][:3], r["pose"][3:] / s]).astype(r["pose"].dtype)
    for key in ("facial_landmarks_3d", "vertice"):
        if key in r:
            r[key] = r[key] / s
    r["scale"] = np.ones_like(r["scale"])
    return r


class GazeDataset(torch.utils.data.Dataset):
    """Samples of subject files as dicts of torch tensors.

    Args:
        paths: files and/or folders of ``*.h5`` subject files.
        split: "all", "train" or "test" (see :func:`split_files`).
        res: output resolution (square); None keeps the stored one. Landmarks and K are rescaled.
        composite: put white outside the head mask (the stored images may have any background).
        with_mesh: also return ``vertice`` [V, 3] (world frame; large).

    Each sample: ``image`` [3, R, R] float32 RGB in [0, 1]; ``head_mask``, ``left_eye_mask``,
    ``right_eye_mask`` [1, R, R] float32 in {0, 1} (soft at resized edges); ``landmarks`` [68, 2] pixels of
    the R × R image; ``landmarks_3d`` [68, 3] (none for a one-camera GazeNeRF file); ``K`` [3, 3] (for R × R);
    ``w2c_R`` [3, 3]; ``w2c_T`` [3];
    ``viewmat`` [4, 4]; ``pitchyaw_head`` [2]; ``face_head_pose`` [2]; ``pose`` [6]; ``scale`` [1];
    ``latent_code`` [I + E] (identity then expression: 80 + 64 for native files, the layout's widths for the
    peers', :meth:`code_widths`); ``cam_index``, ``frame_index``, ``subject``, ``row`` int64 scalars (a scaled
    head's scale folded into the world frame: :func:`fold_head_scale`, ``scale`` then 1);
    ``pitchyaw_cam`` [2] (the file's, else the head-frame gaze turned by w2c ∘ pose); and, where the file has
    them, ``expression_params`` [4], ``light_dir`` [3], ``latent_texture``, ``latent_illumination`` (GazeNeRF's
    other code slices, never fed to the model).

    A peer layout's label keys are converted to the native conventions once per file, whole
    (``train.data.layout_conversion.to_native``: GazeNeRF's 3D landmarks are triangulated across a frame's cameras);
    native files are read as stored.
    """

    def __init__(self, paths, split: str = "all", res: int | None = None, *, composite: bool = True,
                 with_mesh: bool = False, split_file=None, test_fraction: float = 0.25, layout: str = "auto"):
        self.files = split_files(find_subject_files(paths), split, split_file, test_fraction)
        if res is not None and not 8 <= int(res) <= 4096:
            raise ToolkitError(f"res: expected an integer in [8, 4096], got {res}")
        self.res = None if res is None else int(res)
        self.composite, self.with_mesh = composite, with_mesh
        # Layout names, not Layout objects: a dataset is pickled into DataLoader workers.
        self.layouts = [row_layout(f, layout).name for f in self.files]
        if with_mesh:  # nothing makes up a mesh a layout does not store (GazeNeRF's files)
            for f, name in zip(self.files, self.layouts):
                if "vertice" not in native_keys(name):
                    raise ToolkitError(f"{f}: with_mesh: a {name} file has no key 'vertice' (the per-row head mesh)")
        self.info = [validate_file(f, name) for f, name in zip(self.files, self.layouts)]
        for f, name in zip(self.files, self.layouts):  # GazeNeRF's: every frame seen by two cameras, before any work
            check_frames(f, name)
        from toolkit.limits import check_allocation

        check_allocation(16 * sum(i["n"] for i in self.info), f"the row index of {len(self.files)} subject files")
        self.index = np.concatenate([np.stack([np.full(i["n"], k), np.arange(i["n"])], 1) for k, i in enumerate(self.info)])
        self._handles: dict[int, Any] = {}
        self._label_cache: dict[int, dict[str, np.ndarray]] = {}
        self._pid = os.getpid()

    def __len__(self) -> int:
        return len(self.index)

    def _file(self, k: int):
        import h5py

        if self._pid != os.getpid():  # forked into a worker: never reuse the parent's handles
            self._handles, self._pid = {}, os.getpid()
        h = self._handles.get(k)
        if h is None:
            try:
                h = self._handles[k] = h5py.File(self.files[k], "r")
            except READ_ERRORS as e:
                raise ToolkitError(f"{self.files[k]}: cannot open ({one_line(e, None)})") from e
        return h

    def close(self) -> None:
        for h in self._handles.values():
            h.close()
        self._handles = {}

    def __getstate__(self):
        state = self.__dict__.copy()
        state["_handles"], state["_label_cache"] = {}, {}
        return state

    def code_widths(self) -> tuple[int, int]:
        """(identity, expression) widths of every sample's ``latent_code``: its files' layouts', which must agree
        (else one line naming two files and their widths)."""
        return agreed_code_widths(list(zip(self.files, self.layouts)))

    def _labels(self, k: int, f) -> dict[str, np.ndarray]:
        """File ``k``'s small per-row keys (:data:`LABEL_KEYS` and the optional ones it has), read whole once
        (validation bounded them; a few KB a row) and, for a peer layout, converted to native conventions whole
        (``to_native``): a row then reads only its images, as h5py's per-call cost dominates reading ~20 small
        keys one row at a time, and GazeNeRF's 3D landmarks need every camera of a frame."""
        cached = self._label_cache.get(k)
        if cached is None:
            keys = [*LABEL_KEYS, *(o for o in self.info[k]["optional"] if o in OPTIONAL)]
            if self.layouts[k] == DITGAZE.name:
                cached = {key: read_array(self.files[k], f, key) for key in keys}
            else:  # a peer layout stores some keys under other conventions, and may lack some (to_native makes them)
                stored = {key: read_array(self.files[k], f, key) for key in keys if has_key(self.files[k], f, key)}
                cached = to_native(self.layouts[k], stored, where=str(self.files[k]))
                # a GazeGaussian file may lack frame_index: each row its own frame
                cached.setdefault("frame_index", np.arange(self.info[k]["n"], dtype=np.int32))
            self._label_cache[k] = cached
        return cached

    def frame_indices(self, k: int) -> np.ndarray:
        """[n] int: the frame of each row of file ``k``, from its labels alone (no image is read)."""
        return np.asarray(self._labels(k, self._file(k))["frame_index"]).reshape(-1)

    def read_row(self, k: int, row: int) -> dict[str, np.ndarray]:
        """Raw arrays of one row of file ``k`` (no resizing), for tools that need the stored data."""
        f = self._file(k)
        # copies: callers may edit a row in place
        out = {key: labels[row].copy() for key, labels in self._labels(k, f).items()}
        for key in ROW_READ_KEYS if self.with_mesh else ROW_READ_KEYS[:-1]:
            # The file was validated when the dataset was built: its keys resolve inside it, one row fits memory.
            try:
                ds = f[key]
            except READ_ERRORS as e:
                raise ToolkitError(f"{self.files[k]}: key '{key}' cannot be opened (changed since it was checked?): "
                                   f"{one_line(e, None)}") from e
            out[key] = read_selection(self.files[k], key, ds, row)
        if "vertice" in out and not np.isfinite(out["vertice"]).all():  # too large to check whole up front
            raise ToolkitError(f"{self.files[k]}: key 'vertice' row {row} contains NaN or inf")
        if "vertice" in out and self.layouts[k] != DITGAZE.name:
            out["vertice"] = mesh_to_native(self.layouts[k], out["vertice"], out["w2c_Rmat"], out["w2c_Tvec"])
        return out

    def __getitem__(self, i: int) -> dict[str, torch.Tensor]:
        if not -len(self) <= i < len(self):
            raise IndexError(i)
        k, row = (int(x) for x in self.index[i])
        r = fold_head_scale(self.read_row(k, row))
        H, W = r["face_patch"].shape[:2]
        img = r["face_patch"][..., ::-1].astype(np.float32) / 255.0  # stored BGR
        masks = {m: r[m].astype(np.float32) / 255.0 for m in ("head_mask", "left_eye_mask", "right_eye_mask")}
        res = self.res or H
        if self.composite:
            a = masks["head_mask"][..., None]
            img = img * a + (1 - a)
        img = resize_image(img, res)
        masks = {m: resize_image(v, res) for m, v in masks.items()}
        sx, sy = res / W, res / H
        lm = r["facial_landmarks"].astype(np.float32) * np.array([sx, sy], np.float32)
        K = r["inmat"].astype(np.float32).copy()
        K[0] *= sx
        K[1] *= sy
        V = np.eye(4, dtype=np.float32)
        V[:3, :3], V[:3, 3] = r["w2c_Rmat"], r["w2c_Tvec"]
        t = lambda a: torch.from_numpy(np.ascontiguousarray(a, dtype=np.float32))  # noqa: E731
        out = {
            "image": t(img.transpose(2, 0, 1)),
            **{m: t(v[None]) for m, v in masks.items()},
            "landmarks": t(lm),
            # absent where a file cannot give them (a one-camera GazeNeRF file: train.data.triangulation.single_camera)
            **({"landmarks_3d": t(r["facial_landmarks_3d"])} if "facial_landmarks_3d" in r else {}),
            "K": t(K),
            "w2c_R": t(r["w2c_Rmat"]),
            "w2c_T": t(r["w2c_Tvec"]),
            "viewmat": t(V),
            "pitchyaw_head": t(r["pitchyaw_head"]),
            "face_head_pose": t(r["face_head_pose"]),
            "pose": t(r["pose"]),
            "scale": t(np.reshape(r["scale"], (1,))),
            "latent_code": t(r["latent_codes"]),
            "cam_index": torch.tensor(int(np.reshape(r["cam_index"], -1)[0])),
            "frame_index": torch.tensor(int(np.reshape(r["frame_index"], -1)[0])),
            "subject": torch.tensor(k),
            "row": torch.tensor(row),
        }
        for o in ("pitchyaw_cam", "expression_params", "light_dir", "latent_texture", "latent_illumination"):
            if o in r:
                out[o] = t(r[o])
        if "pitchyaw_cam" not in out:  # optional in the format: the head-frame gaze seen from this camera
            from train.losses import gaze_to_camera, head_to_camera_rotation

            R = head_to_camera_rotation(out["viewmat"][None], out["pose"][None])
            out["pitchyaw_cam"] = gaze_to_camera(out["pitchyaw_head"][None], R)[0]
        if self.with_mesh:
            out["vertice"] = t(r["vertice"])
        return out
