"""Evaluation pairs for gaze redirection.

GazeNeRF protocol: per test subject, inputs 0-99 are paired with a fixed permutation of rows 100-199;
the pairs come from a user-supplied pairing file (:func:`load_pairing`: GazeNeRF's own target list, JSON
``{"subject_stem": [[input_row, target_row], ...]}`` or text lines ``subject input_row target_row``), else
they are generated (:func:`synthetic_pairs`: the first half of a subject's rows with a fixed permutation of the
second half). Each held-out file is evaluated under one of two protocols (:func:`redirection_pairs`):

- a synthetic file (one with the ``subject_params`` attribute): the *target images come from the generator*,
  the subject re-rendered with the input's camera, head pose, expression and light and the target row's gaze,
  an exact gaze-redirection ground truth (:class:`SyntheticRedirectionPairs`);
- any other (real) file: the target is the *stored* target row, its image, camera, head pose and gaze
  (:class:`StoredRedirectionPairs`), as GazeNeRF and GazeGaussian score.
"""

from __future__ import annotations

import os
import re
from pathlib import Path

import numpy as np
import torch

from toolkit.cameras import Camera
from toolkit.errors import ToolkitError, one_line
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


ANY_SUBJECT = "*"
"""The pairing key whose pairs go to every subject the file does not name: GazeNeRF's target list holds one
list for all the held-out subjects."""

_INTEGER = re.compile(r"[+-]?[0-9]+")


def load_pairing(path: str | os.PathLike) -> dict[str, np.ndarray]:
    """Read a pairing file -> {subject stem (or :data:`ANY_SUBJECT`): [P, 2] int64 (input row, target row)}.

    Three forms: JSON ``{"subject_stem": [[input_row, target_row], ...]}``; text lines ``subject input_row
    target_row``; and GazeNeRF's target list, text of integers only, one a line (or all on one line):
    input row i -> target row list[i], for every subject (:data:`ANY_SUBJECT`)."""
    path = check_readable_file(path, "pairing file")
    if path.stat().st_size > MAX_PAIRING_BYTES:
        raise ToolkitError(f"{path}: {path.stat().st_size} bytes; a pairing file is expected under "
                           f"{MAX_PAIRING_BYTES} bytes")
    try:
        text = path.read_text(encoding="utf-8")
    except UnicodeDecodeError as e:
        raise ToolkitError(f"{path}: not a pairing file (not UTF-8 text: byte {e.start})") from None
    try:
        if path.suffix == ".json":
            out = {str(k): v for k, v in parse_json_object(text, f"{path}: the pairing JSON").items()}
        else:
            out = _text_pairing(text)
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
        raise ToolkitError(f"{path}: not a pairing file ({one_line(e)})") from None
    for k, v in pairs.items():
        if (v < 0).any():
            raise ToolkitError(f"{path}: subject '{k}' has negative row indices")
    if not pairs:
        raise ToolkitError(f"{path}: no pairs")
    return pairs


def _text_pairing(text: str) -> dict[str, list]:
    """The text forms of :func:`load_pairing`, told apart by their tokens: integers only is GazeNeRF's target
    list, anything else lines ``subject input_row target_row`` ('#' lines and blank lines skipped in both)."""
    lines = [(ln, line.replace(",", " ").split()) for ln, line in enumerate(text.splitlines(), 1)
             if line.strip() and not line.lstrip().startswith("#")]
    if lines and all(_INTEGER.fullmatch(t) for _, parts in lines for t in parts):
        if len(lines) > 1 and any(len(parts) > 1 for _, parts in lines):
            # Several integers on several lines could be either form (a subject named by a number): refuse.
            raise ValueError("integers only, several on a line: expected GazeNeRF's target list (one integer a "
                             "line, or all on one line) or lines 'subject input_row target_row' (use JSON for a "
                             "subject named by a number)")
        # GazeNeRF's configs/config_files/xgaze_evaluation_target_single_subject.txt (100 lines, a permutation
        # of 100..199; GazeGaussian ships it byte for byte): np.loadtxt'ed at datasets/eth_xgaze.py:280, and
        # the item of input index i loads row target_idx[i] as its target (eth_xgaze.py:358-359), in one
        # loader per held-out subject (utils/metrics_utils.py:110-112, inputs 0..99 unshuffled).
        targets = [int(t) for _, parts in lines for t in parts]
        return {ANY_SUBJECT: [[i, t] for i, t in enumerate(targets)]}
    out: dict[str, list] = {}
    for ln, parts in lines:
        if len(parts) != 3:
            raise ValueError(f"line {ln}: expected 'subject input_row target_row'")
        out.setdefault(parts[0], []).append((int(parts[1]), int(parts[2])))
    return out


def subject_pairing(pairing: dict[str, np.ndarray] | None, stem: str) -> np.ndarray | None:
    """A subject's [P, 2] pairs in a loaded pairing: its own entry, else the pairs for every subject
    (:data:`ANY_SUBJECT`); None without a pairing or when it pairs neither."""
    if pairing is None:
        return None
    return pairing[stem] if stem in pairing else pairing.get(ANY_SUBJECT)


def check_pairing_rows(files: list[Path], pairing: dict[str, np.ndarray] | None, source: str = "the pairing",
                       layout: str = "auto") -> None:
    """Before any work: every held-out subject file has pairs (``pairing``'s, or the generated ones) inside its
    rows. A ToolkitError naming the subject(s), or the file, the pair and the row count; ``source`` names the
    pairing in the message. The files are validated in their ``layout`` (``train.data.layout_files.row_layout``)."""
    from train.data.layout_files import row_layout, validate_file

    if pairing is not None:
        missing = [Path(f).stem for f in files if len(_rows_or_none(pairing, Path(f).stem)) == 0]
        if missing:
            raise ToolkitError(f"the pairing file has no pairs for test subject(s) {missing} "
                               f"(it names {sorted(pairing)[:5]}...)")
    for f in files:
        n = validate_file(f, row_layout(f, layout))["n"]
        rows = subject_pairing(pairing, Path(f).stem)
        if rows is None and n < 2:
            raise ToolkitError(f"{f}: {n} row; the generated pairing (the first half of the rows with a permutation "
                               f"of the second half) needs at least 2 rows: give eval.pairing_file (GazeNeRF's target "
                               f"list, or JSON pairs of this file's rows), or a file with more rows")
        bad = np.flatnonzero((np.asarray(rows) >= n).any(1)) if rows is not None else []
        if len(bad):
            k = int(bad[0])
            raise ToolkitError(f"{f}: pair {k} of {source} (input row {rows[k][0]}, target row {rows[k][1]}) is out "
                               f"of range: the file has {n} rows (0-{n - 1})"
                               + (f"; {len(bad)} of its {len(rows)} pairs are" if len(bad) > 1 else ""))


def _rows_or_none(pairing: dict[str, np.ndarray], stem: str) -> np.ndarray:
    rows = subject_pairing(pairing, stem)
    return np.zeros((0, 2), np.int64) if rows is None else rows


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

    protocol = "synthetic"
    """what :func:`redirection_pairs` and the evaluation's report call this protocol."""

    def __init__(self, path: str | os.PathLike, pairs: np.ndarray | None = None, *, res: int | None = None,
                 seed: int = 0, layout: str = "auto"):
        from train.data.dataset import GazeDataset
        from train.data.subject_params import SubjectParams

        self.data = GazeDataset([path], res=res, layout=layout)
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


class StoredRedirectionPairs(torch.utils.data.Dataset):
    """Input samples of a (real) subject file with their *stored* targets: GazeNeRF's protocol.

    Each item: ``{"input": <GazeDataset sample of the input row>, "target": <GazeDataset sample of the target
    row>, "pair" [2]}``. The target row is the ground truth as it was captured: its image (on white outside its
    head mask, as :class:`train.data.dataset.GazeDataset` composites), masks, landmarks, camera (``viewmat``,
    ``K``), head pose and gaze. A render for it is made at the target's camera, head pose and gaze."""

    protocol = "stored"
    """what :func:`redirection_pairs` and the evaluation's report call this protocol."""

    def __init__(self, path: str | os.PathLike, pairs: np.ndarray | None = None, *, res: int | None = None,
                 seed: int = 0, layout: str = "auto"):
        from train.data.dataset import GazeDataset

        self.data = GazeDataset([path], res=res, layout=layout)
        n = self.data.info[0]["n"]
        self.pairs = check_pairs(synthetic_pairs(n, seed) if pairs is None else pairs, n, str(path))
        self.path = Path(path)

    def __len__(self) -> int:
        return len(self.pairs)

    def __getitem__(self, i: int) -> dict:
        a, b = (int(x) for x in self.pairs[i])
        return {"input": self.data[a], "target": self.data[b], "pair": torch.tensor([a, b])}


def is_synthetic_file(path: str | os.PathLike) -> bool:
    """Whether a subject file was written by the generator (it carries ``subject_params``, from which the
    evaluation re-renders exact targets); real files do not."""
    from toolkit.h5 import open_h5

    with open_h5(path) as f:
        return "subject_params" in f.attrs


def redirection_pairs(path: str | os.PathLike, pairs: np.ndarray | None = None, *, res: int | None = None,
                      seed: int = 0, layout: str = "auto") -> "SyntheticRedirectionPairs | StoredRedirectionPairs":
    """One held-out subject's pairs under its protocol: generator targets for a synthetic file, the stored
    target rows for any other (``pairs`` [P, 2] (input row, target row), or None: :func:`synthetic_pairs`;
    ``layout``: the file's, ``train.data.layouts``)."""
    cls = SyntheticRedirectionPairs if is_synthetic_file(path) else StoredRedirectionPairs
    return cls(path, pairs, res=res, seed=seed, layout=layout)
