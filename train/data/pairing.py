"""Evaluation pairs for gaze redirection.

GazeNeRF protocol: per test subject, inputs 0-99 are paired with a fixed permutation of rows 100-199;
the pairs come from a user-supplied pairing file (JSON ``{"subject_stem": [[input_row, target_row], ...]}``
or text lines ``subject input_row target_row``). For synthetic subjects the pairing is generated
deterministically (:func:`synthetic_pairs`) and the *target images come from the generator*: the
subject is re-rendered with the input's camera, head pose, expression and light and the target row's
gaze, an exact gaze-redirection ground truth (:class:`SyntheticRedirectionPairs`).
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import torch

from toolkit.cameras import Camera
from toolkit.errors import ToolkitError
from toolkit.io import atomic_write_json, check_readable_file, parse_json_object

MAX_PAIRING_BYTES = 64 << 20
"""Largest pairing file read: GazeNeRF's protocol lists 100 pairs a subject; 64 MiB holds millions."""


def gazenerf_pairs(n: int = 100, seed: int = 0) -> np.ndarray:
    """[n, 2]: inputs 0..n-1 paired with a fixed permutation of n..2n-1."""
    perm = np.random.default_rng(seed).permutation(n)
    return np.stack([np.arange(n), n + perm], 1).astype(np.int64)


def synthetic_pairs(n_rows: int, seed: int = 0) -> np.ndarray:
    """GazeNeRF-style pairs for a subject of ``n_rows`` rows: first half -> permuted second half."""
    if n_rows < 2:
        raise ToolkitError(f"synthetic_pairs: a subject needs at least 2 rows, got {n_rows}")
    return gazenerf_pairs(n_rows // 2, seed)


def load_pairing(path: str | os.PathLike) -> dict[str, np.ndarray]:
    """Read a pairing file -> {subject stem: [P, 2] int64 (input row, target row)}."""
    path = check_readable_file(path, "pairing file")
    if path.stat().st_size > MAX_PAIRING_BYTES:
        raise ToolkitError(f"{path}: {path.stat().st_size} bytes; a pairing file is expected under "
                           f"{MAX_PAIRING_BYTES} bytes")
    try:
        text = path.read_text(encoding="utf-8")
    except UnicodeDecodeError as e:
        raise ToolkitError(f"{path}: not a pairing file (not UTF-8 text: byte {e.start})") from None
    out: dict[str, list] = {}
    try:
        if path.suffix == ".json":
            out = {str(k): v for k, v in parse_json_object(text, f"{path}: the pairing JSON").items()}
        else:
            for ln, line in enumerate(text.splitlines(), 1):
                if not line.strip() or line.lstrip().startswith("#"):
                    continue
                parts = line.replace(",", " ").split()
                if len(parts) != 3:
                    raise ValueError(f"line {ln}: expected 'subject input_row target_row'")
                out.setdefault(parts[0], []).append((int(parts[1]), int(parts[2])))
        pairs = {}
        for k, v in out.items():
            a = np.asarray(v)
            if a.size == 0:  # a subject without pairs, as save_pairing writes it
                a = np.zeros((0, 2), np.int64)
            if a.ndim != 2 or a.shape[1] != 2 or (a.size and (a.dtype.kind not in "iu" or a.max() >= 2**62)):
                raise ValueError(f"subject '{k}': expected a list of [input_row, target_row] integer pairs below 2^62, "
                                 f"got an array of shape {list(a.shape)} and dtype {a.dtype}")
            pairs[k] = a.astype(np.int64)
    except (ValueError, TypeError, OverflowError) as e:  # a ragged list, a string row, an integer past int64
        raise ToolkitError(f"{path}: not a pairing file ({' '.join(str(e).split())[:200]})") from None
    for k, v in pairs.items():
        if (v < 0).any():
            raise ToolkitError(f"{path}: subject '{k}' has negative row indices")
    if not pairs:
        raise ToolkitError(f"{path}: no pairs")
    return pairs


def save_pairing(path: str | os.PathLike, pairs: dict[str, np.ndarray]) -> None:
    atomic_write_json(path, {k: np.asarray(v).tolist() for k, v in pairs.items()})


def check_pairs(pairs: np.ndarray, n_rows: int, where: str) -> np.ndarray:
    pairs = np.asarray(pairs, np.int64)
    if pairs.ndim != 2 or pairs.shape[1] != 2:
        raise ToolkitError(f"{where}: pairs must be [P, 2], got {list(pairs.shape)}")
    if (pairs < 0).any() or (pairs >= n_rows).any():
        raise ToolkitError(f"{where}: pair rows must be in [0, {n_rows - 1}]")
    return pairs


class SyntheticRedirectionPairs(torch.utils.data.Dataset):
    """Input samples of a synthetic subject file with generator-rendered redirection targets.

    Each item: ``{"input": <GazeDataset sample>, "target": {"image" [3, R, R], "head_mask",
    "left_eye_mask", "right_eye_mask" [1, R, R], "pitchyaw_head" [2], "pitchyaw_cam" [2]}, "pair" [2]}``.
    The target is the input's view (camera, head pose, expression, light) with the target row's gaze.
    Targets are rendered with OpenGL: use DataLoader(multiprocessing_context="spawn") for workers.
    """

    def __init__(self, path: str | os.PathLike, pairs: np.ndarray | None = None, *, res: int | None = None,
                 seed: int = 0):
        from train.data.dataset import GazeDataset
        from train.data.subject_params import SubjectParams

        self.data = GazeDataset([path], res=res)
        info = self.data.info[0]
        if "subject_params" not in info["attrs"]:
            raise ToolkitError(f"{path}: not a synthetic subject file (no 'subject_params' attribute); "
                               "use a pairing file and stored targets for real data")
        self.params = SubjectParams.from_json(info["attrs"]["subject_params"])
        self.ambient = float(info["attrs"].get("ambient", 0.45))
        self.pairs = check_pairs(synthetic_pairs(info["n"], seed) if pairs is None else pairs, info["n"], str(path))
        self.path = Path(path)
        self._subject = None

    def __len__(self) -> int:
        return len(self.pairs)

    @property
    def subject(self):
        if self._subject is None:
            from train.data.synthetic import build_subject

            self._subject = build_subject(self.params)
        return self._subject

    def __getitem__(self, i: int) -> dict:
        a, b = (int(x) for x in self.pairs[i])
        target = self.render_target(a, np.asarray(self.data._file(0)["pitchyaw_head"][b], np.float64))
        return {"input": self.data[self._flat(a)], "target": target, "pair": torch.tensor([a, b])}

    def render_target(self, row: int, target_gaze) -> dict:
        """Ground truth for input ``row`` turned to head-frame ``target_gaze`` [2] (radians): the item's
        ``"target"`` dict, rendered by the generator at the row's view, pose, expression and light."""
        from train.data.dataset import resize_image
        from train.data.generate import rgb_to_u8
        from train.data.synthetic import render_views

        raw = self.data.read_row(0, int(row))
        target_gaze = np.asarray(target_gaze, np.float64)
        H, W = raw["face_patch"].shape[:2]
        V = np.eye(4, dtype=np.float32)
        V[:3, :3], V[:3, 3] = raw["w2c_Rmat"], raw["w2c_Tvec"]
        cam = Camera(torch.from_numpy(raw["inmat"].astype(np.float32)), torch.from_numpy(V), W, H)
        expr = raw.get("expression_params")
        if expr is None:
            from train.data.subject_params import params_from_code

            expr = params_from_code(raw["latent_codes"])[1]
        out = render_views(self.subject, target_gaze, raw["pose"], np.clip(expr, [0, -1, -1, 0], [1, 1, 1, 1]), [cam],
                           scale=float(np.reshape(raw["scale"], -1)[0]), light_dirs=raw.get("light_dir"),
                           ambient=self.ambient)
        res = self.data.res or H
        t = lambda x: torch.from_numpy(np.ascontiguousarray(x, dtype=np.float32))  # noqa: E731
        # Quantize like the stored images so input and target share one pipeline.
        rgb = rgb_to_u8(out["rgb"][0]) / 255.0
        if self.data.composite:  # as GazeDataset does the input: white outside the (centre-sample) head mask
            rgb = np.where(out["head_mask"][0][..., None], rgb, 1.0)
        target = {"image": t(resize_image(rgb.astype(np.float32), res).transpose(2, 0, 1))}
        for m in ("head_mask", "left_eye_mask", "right_eye_mask"):
            target[m] = t(resize_image(out[m][0].astype(np.float32), res)[None])
        target["pitchyaw_head"] = t(out["pitchyaw_head"][0])
        target["pitchyaw_cam"] = t(out["pitchyaw_cam"][0])
        return target

    def _flat(self, row: int) -> int:
        return row  # one file: flat index = row
