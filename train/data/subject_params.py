"""The parameters of a procedural subject: identity and expression vectors, the 144-d latent code they map to
(and back, exactly), random expressions, and :class:`SubjectParams`, an identity with the colours and the
analytic head (:class:`toolkit.procedural.DemoHeadShape`) it defines. ``train.data.synthetic`` meshes and
renders subjects from them.
"""

from __future__ import annotations

import json
from dataclasses import dataclass, replace

import numpy as np
import torch

from toolkit.errors import ToolkitError
from toolkit.procedural import DemoHeadShape

IDENTITY_NAMES = (
    "head_width", "head_height", "head_depth", "nose_height", "nose_width", "brow_height", "chin_height",
    "eye_spacing", "eye_size", "eye_height", "iris_size", "lid_height", "skin_lightness", "skin_redness",
    "iris_blueness", "iris_lightness", "hair_lightness", "hair_redness", "mouth_width", "mouth_height",
    "lip_redness", "pupil_size",
)
"""Identity parameters, each normalized to [-1, 1] (0 = the average subject, close to the demo head)."""

EXPRESSION_NAMES = ("mouth_open", "smile", "brow_raise", "eyelid")
"""Expression parameters: mouth_open, eyelid in [0, 1]; smile, brow_raise in [-1, 1]; 0 = neutral."""

EXPRESSION_RANGES = ((0.0, 1.0), (-1.0, 1.0), (-1.0, 1.0), (0.0, 1.0))
ID_CODE_DIM, EXPR_CODE_DIM = 80, 64
_EMBED_SEED = 20240605  # fixes the latent-code embedding forever: changing it changes every file's codes


def _orthonormal_embedding(rows: int, cols: int, seed: int) -> np.ndarray:
    q, _ = np.linalg.qr(np.random.default_rng(seed).standard_normal((rows, cols)))
    return q.astype(np.float32)  # [rows, cols] with orthonormal columns: code = W p, p = W^T code


_W_ID = _orthonormal_embedding(ID_CODE_DIM, len(IDENTITY_NAMES), _EMBED_SEED)
_W_EXPR = _orthonormal_embedding(EXPR_CODE_DIM, len(EXPRESSION_NAMES), _EMBED_SEED + 1)


def latent_code(identity: np.ndarray, expression: np.ndarray) -> np.ndarray:
    """[..., 22] identity + [..., 4] expression -> [..., 144] code (80 identity dims, then 64 expression).

    A fixed linear map with orthonormal columns, so the parameters are recovered exactly by
    :func:`params_from_code`.
    """
    identity = np.asarray(identity, np.float32)
    expression = np.asarray(expression, np.float32)
    return np.concatenate([identity @ _W_ID.T, expression @ _W_EXPR.T], -1)


def params_from_code(code: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Inverse of :func:`latent_code`: [..., 144] -> ([..., 22] identity, [..., 4] expression). Only the
    generator's codes (80 identity + 64 expression dims) hold these parameters: a code of another width (a peer
    layout's, GazeNeRF's 100 + 79) is a ToolkitError."""
    code = np.asarray(code, np.float32)
    if code.shape[-1:] != (ID_CODE_DIM + EXPR_CODE_DIM,):
        raise ToolkitError(f"params_from_code: expected a synthetic subject's code of {ID_CODE_DIM} identity + "
                           f"{EXPR_CODE_DIM} expression dims, got shape {list(code.shape)}")
    return code[..., :ID_CODE_DIM] @ _W_ID, code[..., ID_CODE_DIM:ID_CODE_DIM + EXPR_CODE_DIM] @ _W_EXPR


def check_expression(expression, name: str = "expression") -> np.ndarray:
    e = np.asarray(expression, np.float32)
    if e.shape[-1:] != (len(EXPRESSION_NAMES),) or not np.isfinite(e).all():
        raise ToolkitError(f"{name}: expected finite [..., {len(EXPRESSION_NAMES)}] {EXPRESSION_NAMES}, "
                           f"got shape {list(e.shape)}")
    for k, (lo, hi) in enumerate(EXPRESSION_RANGES):
        if (e[..., k] < lo - 1e-6).any() or (e[..., k] > hi + 1e-6).any():
            raise ToolkitError(f"{name}: {EXPRESSION_NAMES[k]} must lie in [{lo}, {hi}]")
    return e


def sample_expression(rng: np.random.Generator, n: int) -> np.ndarray:
    """[n, 4] random expressions: half with an open mouth, mostly open eyes."""
    mouth = rng.uniform(0, 1, n) ** 1.5 * (rng.uniform(0, 1, n) < 0.5)
    smile = rng.uniform(-0.6, 1.0, n)
    brow = rng.uniform(-0.8, 0.8, n)
    lid = rng.uniform(0, 0.5, n)
    return np.stack([mouth, smile, brow, lid], -1).astype(np.float32)


@dataclass(frozen=True)
class SubjectParams:
    """A subject's identity: ``identity`` [22] in [-1, 1] (names in IDENTITY_NAMES), its seed, and its eyes'
    ``kappa`` (pitch, yaw) in radians: the optical axis (where the eyeball's iris points) relative to the visual
    axis (the gaze label), yaw temporal in each eye (mirrored between the eyes), as real eyes' angle κ (about 5°
    horizontally); (0, 0): the eyes point where the subject looks."""

    identity: tuple[float, ...] = tuple(0.0 for _ in IDENTITY_NAMES)
    seed: int = 0
    kappa: tuple[float, float] = (0.0, 0.0)

    def __post_init__(self):
        u = np.asarray(self.identity, np.float64)
        if u.shape != (len(IDENTITY_NAMES),) or not np.isfinite(u).all() or np.abs(u).max() > 1 + 1e-6:
            raise ToolkitError(f"SubjectParams.identity: expected {len(IDENTITY_NAMES)} finite values in [-1, 1]")
        k = np.asarray(self.kappa, np.float64)
        if k.shape != (2,) or not np.isfinite(k).all() or np.abs(k).max() > 0.5:
            raise ToolkitError(f"SubjectParams.kappa: expected (pitch, yaw) radians within ±0.5, got {self.kappa}")

    @classmethod
    def sample(cls, seed: int, kappa_deg: float = 0.0) -> "SubjectParams":
        """A random identity, deterministic in ``seed``; with ``kappa_deg`` > 0 a random κ of its own stream:
        yaw ``kappa_deg`` × (1 + 0.3 N(0, 1)) degrees, pitch 0.3 ``kappa_deg`` N(0, 1) (real eyes: about 5 ± 2°
        horizontally, smaller vertically). The identity does not depend on ``kappa_deg``."""
        rng = np.random.default_rng([seed, 7])
        identity = tuple(float(x) for x in rng.uniform(-1, 1, len(IDENTITY_NAMES)))
        if not kappa_deg:
            return cls(identity, int(seed))
        z = np.random.default_rng([seed, 11]).standard_normal(2)
        kappa = np.radians([0.3 * kappa_deg * z[0], kappa_deg * (1 + 0.3 * z[1])])
        return cls(identity, int(seed), tuple(float(x) for x in np.clip(kappa, -0.5, 0.5)))

    def vector(self) -> np.ndarray:
        return np.asarray(self.identity, np.float32)

    def to_json(self) -> str:
        d = {"identity": list(self.identity), "seed": self.seed, "names": list(IDENTITY_NAMES)}
        if any(self.kappa):  # written only when set: files without κ stay as they were
            d["kappa"] = list(self.kappa)
        return json.dumps(d)

    @classmethod
    def from_json(cls, text: str) -> "SubjectParams":
        try:
            d = json.loads(text)
            return cls(tuple(float(x) for x in d["identity"]), int(d.get("seed", 0)),
                       tuple(float(x) for x in d.get("kappa", (0.0, 0.0))))
        except (ValueError, KeyError, TypeError) as e:
            raise ToolkitError(f"subject params: not a SubjectParams JSON ({e})") from e

    def _u(self, name: str) -> float:
        return float(self.identity[IDENTITY_NAMES.index(name)])

    def colors(self) -> dict[str, np.ndarray]:
        """Albedos of skin, hair, lips, iris from the identity."""
        u = self._u
        skin = np.array([0.86, 0.66, 0.55]) * (1 + 0.18 * u("skin_lightness")) + np.array([0.04, -0.02, -0.03]) * u(
            "skin_redness")
        hair = np.array([0.20, 0.13, 0.08]) * (1 + 0.8 * max(u("hair_lightness"), -0.6)) + np.array(
            [0.08, 0.02, -0.02]) * u("hair_redness")
        lips = skin * np.array([0.85, 0.52, 0.52]) * (1 + 0.1 * u("lip_redness"))
        blue = 0.5 * (u("iris_blueness") + 1)
        iris = ((1 - blue) * np.array([0.34, 0.21, 0.10]) + blue * np.array([0.25, 0.42, 0.58])) * (
            1 + 0.35 * u("iris_lightness"))
        clip = lambda c: np.clip(c, 0.02, 0.98).astype(np.float32)  # noqa: E731
        return {"skin": clip(skin), "hair": clip(hair), "lips": clip(lips), "iris": clip(iris)}

    def shape(self, expression=None) -> DemoHeadShape:
        """The analytic head of this identity with ``expression`` [4] (default neutral)."""
        u = self._u
        e = np.zeros(len(EXPRESSION_NAMES)) if expression is None else check_expression(expression)
        base = DemoHeadShape(
            semi_axes=(0.075 + 0.006 * u("head_width"), 0.10 + 0.008 * u("head_height"),
                       0.09 + 0.006 * u("head_depth")),
            eye_offset_x=0.031 + 0.003 * u("eye_spacing"),
            eye_y=-0.005 + 0.003 * u("eye_height"),
            eye_radius=0.012 + 0.0007 * u("eye_size"),
            nose_height=0.024 + 0.007 * u("nose_height"),
            nose_width=0.09 + 0.02 * u("nose_width"),
            brow_height=0.006 + 0.003 * u("brow_height"),
            brow_y=-0.30,
            chin_height=0.008 + 0.005 * u("chin_height"),
            skin=tuple(float(x) for x in self.colors()["skin"]),
            iris=tuple(float(x) for x in self.colors()["iris"]),
            mouth_width=0.024 + 0.003 * u("mouth_width"),
            mouth_y=0.062 + 0.004 * u("mouth_height"),
        )
        # Seat the eyeballs so their fronts lie 1.5 mm behind the closed skin: hidden unless the lids open.
        ex, ey = base.eye_offset_x, base.eye_y
        d = base.dirs_from_base_xy(torch.tensor([[ex, ey]], dtype=torch.float64))
        z_skin = float(base.surface_points(d)[0, 2])
        return replace(
            base,
            eye_z=z_skin + base.eye_radius + 0.0015,
            eye_opening=(0.0135 + 0.0012 * u("eye_size"), 0.0052 + 0.0009 * u("lid_height")),
            mouth_open=float(e[0]), smile=float(e[1]), brow_raise=float(e[2]), eyelid=float(e[3]),
        )
