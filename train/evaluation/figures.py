"""The evaluation's figures: image grids, the worst pairs' eye views (``eyes.png``) and gaze sweeps."""

from __future__ import annotations

from typing import Any

import numpy as np
import torch
import torch.nn.functional as F

from toolkit.errors import ToolkitError
from train.estimator.crops import eye_patches
from train.evaluation.pairs import render_pairs
from train.losses.metrics import composite_on_white


def image_grid(rows: list[torch.Tensor], labels: list[str] | None = None) -> np.ndarray:
    """Rows of [K, 3, H, W] images -> one uint8 [rows·H, K·W, 3] grid (labels drawn with OpenCV)."""
    import cv2

    k = max(r.shape[0] for r in rows)
    H, W = rows[0].shape[-2:]
    grid = np.ones((len(rows) * H, k * W, 3), np.uint8) * 255
    for i, r in enumerate(rows):
        for j in range(r.shape[0]):
            img = (r[j].clamp(0, 1).permute(1, 2, 0).numpy() * 255).round().astype(np.uint8)
            grid[i * H:(i + 1) * H, j * W:(j + 1) * W] = img
        if labels:
            cv2.putText(grid, labels[i], (3, i * H + 12), cv2.FONT_HERSHEY_SIMPLEX, 0.35, (0, 0, 0), 1, cv2.LINE_AA)
    return grid


WORST_EYE_PAIRS = 6
"""How many pairs, those with the largest gaze errors, the eval keeps eye views of (``eyes.png``)."""
EYE_VIEW_HW = (48, 80)
"""(h, w) of each eye's view in ``eyes.png``: the window the eye-patch estimators read (2 x 1.2 eye widths)."""


def worst_eye_views(subject: str, indices: list[int], gaze_err: torch.Tensor, inp: torch.Tensor, tgt: torch.Tensor,
                    out: torch.Tensor, landmarks: torch.Tensor, *,
                    input_landmarks: torch.Tensor | None = None) -> list[dict[str, Any]]:
    """The eye views of a subject's :data:`WORST_EYE_PAIRS` worst pairs (by ``gaze_err`` [B]): for each, its
    subject, pair index, gaze error and ``views``, uint8 [3 (input, target, render), 3, h, 2 w], both eyes side
    by side as the estimator reads them (:func:`train.estimator.crops.eye_patches` at the target's
    ``landmarks`` [B, 68, 2], which the render shares; the input's own ``input_landmarks`` where its view
    differs, as a stored target's does, else the same). Kept per subject, so the overall worst are among what a
    whole evaluation keeps, at a few kB a pair."""
    keep = torch.argsort(gaze_err.cpu(), descending=True)[:WORST_EYE_PAIRS].tolist()
    if not keep:
        return []
    B = inp.shape[0]
    with torch.no_grad():
        lm_in = landmarks if input_landmarks is None else input_landmarks
        lm = torch.cat([lm_in.float(), landmarks.float(), landmarks.float()])
        p = eye_patches(torch.cat([inp, tgt, out]).float(), lm, EYE_VIEW_HW)
    views = torch.cat([p[:, :3], p[:, 3:]], -1).view(3, B, 3, EYE_VIEW_HW[0], 2 * EYE_VIEW_HW[1]).transpose(0, 1)
    views = (views.clamp(0, 1) * 255).round().to(torch.uint8).cpu()
    # Clones: a view would keep the whole subject's buffer alive.
    return [{"subject": subject, "pair": indices[i], "gaze_error_deg": float(gaze_err[i]), "views": views[i].clone()}
            for i in keep]


def eye_views_grid(worst: list[dict[str, Any]]) -> np.ndarray:
    """uint8 [H, W, 3] image: one row per pair of ``worst`` (:func:`worst_eye_views` records), its input,
    target and render eye views side by side, labelled with the pair and its gaze error. The gaze metric reads
    these windows only; a render that the loss estimator was fitted to can read the right gaze from eyes that
    do not look like the target's (docs/results.md, 2026-11-23)."""
    if not worst:
        raise ToolkitError("eye_views_grid: no pairs to show")
    gap = lambda v: F.pad(v, (0, 6), value=1.0)  # noqa: E731  (white between input, target and render)
    strips = [torch.cat([gap(v) for v in r["views"].float() / 255], -1) for r in worst]  # [3, h, 3 * (2w + 6)]
    # A white band above each strip holds its label (image_grid writes at a row's top left).
    rows = [torch.cat([torch.ones(3, 14, v.shape[-1]), v], 1)[None] for v in strips]
    return image_grid(rows,
                      [f"{r['subject']} pair {r['pair']}: gaze error {r['gaze_error_deg']:.1f} deg "
                       "(input | target | render)" for r in worst])


def sweep_gazes(n: int) -> torch.Tensor:
    """``n`` head-frame gazes [n, 2] (pitch, yaw radians) on a circle of ±20° pitch and ±26° yaw: the gaze
    sweep of the report's figure and of the demo's video."""
    if n < 1:
        raise ToolkitError(f"sweep_gazes: expected >= 1 gazes, got {n}")
    t = torch.linspace(0, 2 * torch.pi, n + 1)[:-1]
    return torch.stack([0.35 * torch.sin(t), 0.45 * torch.cos(t)], -1)


@torch.no_grad()
def model_gaze_sweep(model, renderer, item: dict, gazes: torch.Tensor, res: int, steps: int = 1,
                     device="cpu") -> torch.Tensor:
    """Render one input view (a dataset item) at each head-frame gaze [G, 2] -> [G, 3, res, res] on white."""
    G = gazes.shape[0]
    rep = lambda k: torch.as_tensor(item[k]).float()[None].expand(G, *torch.as_tensor(item[k]).shape).to(device)  # noqa: E731
    batch = {"code": rep("latent_code"), "pose": rep("pose"), "viewmat": rep("viewmat"), "K": rep("K"),
             "gaze_head": gazes.float().to(device)}
    out = render_pairs(model, renderer, batch, res, steps)
    mask = torch.as_tensor(item["head_mask"]).float().to(device)[None]
    return composite_on_white(out, mask.expand(G, *mask.shape[1:])).cpu()
