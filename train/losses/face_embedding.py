"""An offline face embedding for identity drift: dlib's face-recognition ResNet on faces aligned with the
toolkit's own landmarks.

The network is dlib's ``dlib_face_recognition_resnet_model_v1.dat`` (a ResNet-29 metric-learning model, 128-d
embeddings; Davis King, released to the public domain), shipped in the PyPI package ``face-recognition-models``
and run by ``dlib`` (``dlib-bin`` wheels, CPU only): the optional extra ``identity``. Nothing is downloaded at
run time. dlib's 68-point *landmark predictor* is never used (its training data, iBUG 300-W, is for
non-commercial use): each face is aligned on the iBUG-68 landmarks the caller gives (the dataset's, or a
photo's from ``apps.photo.landmarks68``), which dlib's ``get_face_chip_details`` maps onto its template exactly
as it maps its own predictor's points.

Distances are Euclidean between embeddings; dlib's model was trained so that two photos of one person lie
within :data:`SAME_PERSON_DISTANCE` (0.6; 99.38 % on LFW with that threshold, dlib's release notes). Images
are [B, 3, H, W] RGB in [0, 1]; landmarks [B, 68, 2] (x, y) pixels, pixel centres at integers (dlib's and
OpenCV's convention, as :mod:`train.losses.identity`).
"""

from __future__ import annotations

import importlib.util
from pathlib import Path

import numpy as np
import torch

from toolkit.errors import ToolkitError

MODEL_FILE = "dlib_face_recognition_resnet_model_v1.dat"
"""The network's file inside the ``face_recognition_models`` package (its ``models/`` folder)."""
EMBEDDING_DIM = 128
SAME_PERSON_DISTANCE = 0.6
"""dlib's threshold: embeddings of one person's photos lie closer than this (Euclidean)."""
CHIP_PADDING = 0.25
"""dlib's default margin around the aligned 150x150 face chip, as a fraction of the face's size."""
MIN_LANDMARK_SPREAD = 1e-3
"""Pixels: landmarks whose RMS distance to their centroid is below this give no alignment (an error)."""
MAX_LANDMARK_PX = 1e6
"""Pixels: landmarks farther than this from the origin are refused (dlib's points are integers)."""
IDENTITY_EXTRA = ("identity drift needs the optional extra 'identity' (dlib and its face-recognition model): "
                  "pip install 'ditgaze[identity]'")


def _model_path() -> Path:
    """The network file, found without importing ``face_recognition_models`` (its ``__init__`` imports
    ``pkg_resources``, which recent setuptools no longer ship)."""
    spec = importlib.util.find_spec("face_recognition_models")
    roots = list(spec.submodule_search_locations or []) if spec is not None else []
    for root in roots:
        path = Path(root) / "models" / MODEL_FILE
        if path.is_file():
            return path
    raise ToolkitError(f"{IDENTITY_EXTRA} ({MODEL_FILE} not found)")


class FaceEmbedding:
    """dlib's face-recognition network: ``embed(images [B, 3, H, W], landmarks [B, 68, 2])`` -> [B, 128]
    float32 embeddings; ``distance(a, lm_a, b, lm_b)`` -> [B] Euclidean distances of pairs. Not differentiable
    (a metric, run by dlib on the CPU). A ToolkitError naming the extra when dlib or the model is missing."""

    def __init__(self, model_path: str | Path | None = None):
        try:
            import dlib
        except ImportError as e:
            raise ToolkitError(f"{IDENTITY_EXTRA} ({e.__class__.__name__}: {str(e)[:80]})") from None
        path = Path(model_path) if model_path else _model_path()
        if not path.is_file():
            raise ToolkitError(f"face embedding: model file {path} not found")
        self._dlib = dlib
        self._net = dlib.face_recognition_model_v1(str(path))

    def embed(self, images: torch.Tensor, landmarks: torch.Tensor) -> torch.Tensor:
        """[B, 3, H, W] images in [0, 1] (clamped, quantized to 8 bits as dlib reads them) and their iBUG-68
        landmarks [B, 68, 2] -> [B, 128] embeddings (float32, on the images' device)."""
        _check_inputs(images, landmarks)
        rgb = (images.detach().float().clamp(0, 1) * 255).round().to(torch.uint8).permute(0, 2, 3, 1).cpu().numpy()
        pts = landmarks.detach().double().cpu().numpy()
        out = np.zeros((images.shape[0], EMBEDDING_DIM), np.float32)
        for i in range(images.shape[0]):
            shape = self._shape(pts[i])
            out[i] = np.asarray(self._net.compute_face_descriptor(np.ascontiguousarray(rgb[i]), shape,
                                                                  num_jitters=0, padding=CHIP_PADDING))
        return torch.from_numpy(out).to(images.device)

    def distance(self, a: torch.Tensor, landmarks_a: torch.Tensor, b: torch.Tensor,
                 landmarks_b: torch.Tensor) -> torch.Tensor:
        """[B] Euclidean distances between the embeddings of images ``a`` and ``b`` [B, 3, H, W], each aligned
        on its own landmarks [B, 68, 2]: under :data:`SAME_PERSON_DISTANCE`, dlib reads one person."""
        if a.shape[0] != b.shape[0]:
            raise ToolkitError(f"face embedding: {a.shape[0]} images against {b.shape[0]}; expected pairs")
        return torch.linalg.vector_norm(self.embed(a, landmarks_a) - self.embed(b, landmarks_b), dim=1)

    def _shape(self, pts: np.ndarray):
        """dlib's ``full_object_detection`` of one face's [68, 2] landmarks (its box: the points' bounds)."""
        dlib = self._dlib
        lo, hi = np.floor(pts.min(0)).astype(int), np.ceil(pts.max(0)).astype(int)
        rect = dlib.rectangle(int(lo[0]), int(lo[1]), int(hi[0]), int(hi[1]))
        return dlib.full_object_detection(rect, [dlib.point(int(round(x)), int(round(y))) for x, y in pts])


def _check_inputs(images: torch.Tensor, landmarks: torch.Tensor) -> None:
    if images.ndim != 4 or images.shape[1] != 3 or min(images.shape[2:]) < 1:
        raise ToolkitError(f"face embedding: images must be [B, 3, H, W], got {list(images.shape)}")
    if landmarks.shape != (images.shape[0], 68, 2):
        raise ToolkitError(f"face embedding: landmarks must be [{images.shape[0]}, 68, 2] (iBUG-68 pixels), "
                           f"got {list(landmarks.shape)}")
    if not (torch.isfinite(images).all() and torch.isfinite(landmarks).all()):
        raise ToolkitError("face embedding: images and landmarks must be finite")
    if landmarks.numel() and float(landmarks.abs().max()) > MAX_LANDMARK_PX:
        raise ToolkitError(f"face embedding: landmarks must lie within {MAX_LANDMARK_PX:g} px of the image")
    if landmarks.shape[0]:
        spread = (landmarks - landmarks.mean(1, keepdim=True)).square().sum(-1).mean(1).sqrt()
        if bool((spread < MIN_LANDMARK_SPREAD).any()):
            raise ToolkitError(f"face embedding: landmarks spread under {MIN_LANDMARK_SPREAD} px: no face to align")


def load_face_embedding(log=print) -> FaceEmbedding | None:
    """The embedding when the extra ``identity`` is installed, else None after one log line saying so (the
    evaluation then reports identity drift as n/a)."""
    try:
        return FaceEmbedding()
    except ToolkitError as err:
        log(f"[eval] identity drift: n/a ({err})")
        return None
