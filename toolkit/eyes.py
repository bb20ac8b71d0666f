"""Eyeballs: sphere fits, gaze rotations and rigid eye redirection of a GaussianScene.

Conventions:
- Part 1 "left eye" is the eye on the *image's* left in a frontal view (iBUG landmarks 36–41, the
  subject's right eye); part 2 "right eye" is landmarks 42–47. This matches GazeGaussian's naming.
- The head frame is OpenCV-like: x towards the image right of a frontal view, y down, z from the face
  into the head, so a frontal gaze is (0, 0, -1) = pitch 0, yaw 0 (ETH-XGaze, see ``toolkit.rotations``).
- Each eye rotates rigidly about **its own** eyeball centre, stored in ``scene.metadata["eyes"]`` as
  ``{"left": {"center": [x, y, z], "radius": r}, "right": {...}}`` (fitted from the Gaussians when absent).
"""

from __future__ import annotations

import math
from typing import Any

import torch

from toolkit.errors import ToolkitError
from toolkit.rotations import matrix_to_quat, quat_multiply

EYE_PARTS = {"left": 1, "right": 2}


def fit_sphere(points: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Least-squares sphere through [M, 3] points -> (centre [3], radius []).

    Solves the linear form |p|^2 = 2 c·p + (r^2 - |c|^2) in float64. Needs >= 4 non-coplanar points.
    """
    if points.shape[0] < 4:
        raise ToolkitError(f"fit_sphere: need at least 4 points, got {points.shape[0]}")
    if not bool(torch.isfinite(points).all()):  # the SVD below would raise LinAlgError on them
        raise ToolkitError("fit_sphere: the points contain NaN/inf")
    p = points.detach().to(torch.float64)
    mu = p.mean(0)
    q = p - mu  # centring keeps the normal equations well conditioned far from the origin
    spread = torch.linalg.svdvals(q)  # lstsq would return a finite but arbitrary sphere for flat points
    if not bool(torch.isfinite(spread).all()) or spread[2] <= 1e-9 * spread[0]:
        raise ToolkitError("fit_sphere: the points do not determine a sphere (coplanar or degenerate)")
    A = torch.cat([2 * q, torch.ones(q.shape[0], 1, dtype=q.dtype)], 1)
    b = (q * q).sum(1, keepdim=True)
    sol = torch.linalg.lstsq(A, b).solution.squeeze(1)
    c = sol[:3]
    r2 = sol[3] + (c * c).sum()
    if not torch.isfinite(sol).all() or r2 <= 0:
        raise ToolkitError("fit_sphere: the points do not determine a sphere (coplanar or degenerate)")
    return (c + mu).to(points.dtype), torch.sqrt(r2).to(points.dtype)


def _stored_eyeball(entry: Any, where: str) -> tuple[list[float], float]:
    """One eye's entry of ``metadata["eyes"]`` -> (centre [3], radius), checked: the scene file is user input."""
    if not isinstance(entry, dict):
        raise ToolkitError(f"{where}: expected a mapping with 'center' and 'radius', got {type(entry).__name__}")
    c, r = entry.get("center"), entry.get("radius")
    ok = (isinstance(c, (list, tuple)) and len(c) == 3
          and all(isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v) for v in c))
    if not ok:
        raise ToolkitError(f"{where}.center: expected 3 finite numbers, got {_short(c)}")
    if isinstance(r, bool) or not isinstance(r, (int, float)) or not (math.isfinite(r) and r > 0):
        raise ToolkitError(f"{where}.radius: expected a finite number > 0, got {_short(r)}")
    return [float(v) for v in c], float(r)


def _short(value: Any, limit: int = 60) -> str:
    text = " ".join(repr(value).split())  # one line, however the file spelled it
    return text if len(text) <= limit else text[:limit] + "..."


def check_eyes_metadata(eyes: Any, where: str = "scene metadata eyes") -> dict[str, tuple[list[float], float]]:
    """``metadata["eyes"]`` checked -> {eye name: (centre, radius)} for the eyes it gives (absent, None or {}:
    none, the spheres are fitted). Anything else is one ToolkitError naming ``where`` and the entry, whether or
    not the scene has that eye's Gaussians: invalid metadata is never taken for missing metadata."""
    if eyes is None:
        return {}
    if not isinstance(eyes, dict):
        raise ToolkitError(f"{where}: expected a mapping of left/right eyeballs, got {type(eyes).__name__}")
    return {name: _stored_eyeball(eyes[name], f"{where}.{name}") for name in EYE_PARTS if name in eyes}


def eyeball_info(scene) -> dict[str, dict[str, torch.Tensor]]:
    """Per-eye {"center": [3], "radius": []} from metadata, else fitted to that eye's Gaussian means.

    Eyes without Gaussians are left out; the result is empty for a scene with no eye Gaussians. Invalid
    ``metadata["eyes"]`` is a ToolkitError naming it (:func:`check_eyes_metadata`), as is an eye whose
    Gaussians do not determine a sphere (:func:`fit_sphere`): neither means "no eye Gaussians".
    """
    stored = check_eyes_metadata(scene.metadata.get("eyes"))
    out = {}
    for name, part in EYE_PARTS.items():
        mask = scene.part == part
        if not bool(mask.any()):
            continue
        if name in stored:
            c, r = (torch.tensor(v, dtype=scene.means.dtype, device=scene.device) for v in stored[name])
        else:
            try:
                c, r = fit_sphere(scene.means[mask])
            except ToolkitError as e:
                raise ToolkitError(f"scene {name} eye: its {int(mask.sum())} Gaussians give no eyeball sphere and "
                                   f"metadata eyes.{name} gives none ({e})") from None
        out[name] = {"center": c, "radius": r}
    return out


def gaze_rotation(pitchyaw: torch.Tensor) -> torch.Tensor:
    """[..., 2] head-frame gaze (pitch, yaw) -> [..., 3, 3] rotation taking the frontal gaze (0, 0, -1) to it.

    R = R_y(yaw) · R_x(-pitch): pitch first about the eye's horizontal axis, then yaw about vertical,
    which keeps the eye's horizontal axis level (no torsion), as Listing-like eye models do.
    """
    p, y = pitchyaw[..., 0], pitchyaw[..., 1]
    cp, sp, cy, sy = torch.cos(-p), torch.sin(-p), torch.cos(y), torch.sin(y)
    o, i = torch.zeros_like(p), torch.ones_like(p)
    Rx = torch.stack([i, o, o, o, cp, -sp, o, sp, cp], -1).reshape(p.shape + (3, 3))
    Ry = torch.stack([cy, o, sy, o, i, o, -sy, o, cy], -1).reshape(p.shape + (3, 3))
    return Ry @ Rx


def rotate_about(means: torch.Tensor, quats: torch.Tensor, R: torch.Tensor, center: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Rigidly rotate Gaussians ([M, 3] means, [M, 4] wxyz quats) by R [3, 3] about ``center`` [3]. An all-zero
    quaternion means the identity (``toolkit.rotations.normalize_quat``) and turns like one."""
    new_means = (means - center) @ R.T + center
    q = matrix_to_quat(R)
    identity = torch.zeros_like(quats)
    identity[..., 0] = 1
    quats = torch.where((quats == 0).all(-1, keepdim=True), identity, quats)
    new_quats = quat_multiply(q.expand_as(quats), quats)
    return new_means, new_quats


def redirect_eyes(scene, pitchyaw: torch.Tensor | tuple[float, float], info=None):
    """A copy of ``scene`` with both eyes rigidly turned to head-frame gaze ``pitchyaw`` (radians).

    The canonical scene is assumed to look frontally (gaze (0, 0)). Returns the new scene; raises
    ``ToolkitError`` when the scene has no eye Gaussians.
    """
    info = eyeball_info(scene) if info is None else info
    if not info:
        raise ToolkitError("scene has no eye Gaussians (part 1 or 2); gaze cannot be changed")
    py = torch.as_tensor(pitchyaw, dtype=scene.means.dtype, device=scene.device)
    if py.shape != (2,) or not bool(torch.isfinite(py).all()):
        raise ToolkitError(f"redirect_eyes: pitchyaw expected two finite angles (pitch, yaw) in radians, got "
                           f"{py.tolist() if py.numel() <= 4 else f'shape {list(py.shape)}'}")
    R = gaze_rotation(py)
    out = scene.clone()
    for name, eye in info.items():
        m = scene.part == EYE_PARTS[name]
        out.means[m], out.quats[m] = rotate_about(scene.means[m], scene.quats[m], R, eye["center"])
    return out
