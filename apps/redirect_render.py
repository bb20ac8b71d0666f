"""``apps.redirect``'s rendering: every (input row, target gaze) pair of a chunk -> arrays of the output
schema (docs/data.md)."""

from __future__ import annotations

import contextlib
from typing import Callable

import numpy as np
import torch

from toolkit.errors import ToolkitError
from toolkit.rotations import so3_exp

RENDER_BATCH = 32
"""Gazes of one input row rendered in one forward pass: a long gaze list (random:2000:35) is rendered in
slices of this many, so memory does not grow with it."""

OUTPUT_KEYS = ("face_patch", "head_mask", "pitchyaw_head", "pitchyaw_cam", "pose", "w2c_Rmat", "w2c_Tvec", "inmat",
               "latent_codes", "face_head_pose", "cam_index", "frame_index", "source_row", "left_eye_mask",
               "right_eye_mask", "facial_landmarks", "facial_landmarks_3d", "scale", "vertice")
"""The datasets of the output file (docs/data.md), plus ``source_row``."""


def render_gazes(model, renderer, code: torch.Tensor, pose: torch.Tensor, gz: torch.Tensor, V: torch.Tensor,
                 K: torch.Tensor, res: int, steps: int) -> torch.Tensor:
    """One input row at G gazes -> [G, 3, res, res] images, ``RENDER_BATCH`` gazes at a time; ``code``
    [G, C], ``pose`` [G, 6], ``gz`` [G, 2], ``V`` [G, 4, 4], ``K`` [G, 3, 3]. A diffusion renderer's
    starting noise is drawn for all G at once (its ``seed=0`` stream), so the images do not depend on the
    slicing."""
    G, noise, out = gz.shape[0], None, []
    for a in range(0, G, RENDER_BATCH):
        s = slice(a, min(a + RENDER_BATCH, G))
        maps = model(code[s], pose[s], gz[s], V[s], K[s], res, res, renders=("head",))
        if hasattr(renderer, "diffusion"):
            if noise is None:
                shape = renderer.latent_shape(maps["head"])
                noise = torch.randn((G, *shape[1:]), generator=torch.Generator().manual_seed(0))
            out.append(renderer.render(maps["head"], code[s], gaze=gz[s], pose=pose[s], steps=steps, noise=noise[s]))
        else:
            out.append(renderer.render(maps["head"], code[s], gaze=gz[s], pose=pose[s]))
    return torch.cat(out)


def render_chunk(model, renderer, items: list[dict], rows: list[int], gazes: np.ndarray, res: int, steps: int,
                 device, fit: Callable[[dict, torch.Tensor], torch.Tensor] | None = None) -> dict:
    """Render every (row, gaze) pair of the input ``items`` (``GazeDataset`` items or
    ``LabelsCsvSource.items``; ``rows`` their input row numbers) -> arrays of the output schema.

    ``fit`` (``TrainedRun.row_fitter``): fit each row before rendering its gazes, from the trained weights
    each time."""
    from train.evaluation.fitting import restored_weights

    out: dict[str, list] = {k: [] for k in OUTPUT_KEYS}
    G = gazes.shape[0]
    gz = torch.from_numpy(gazes).float().to(device)
    for it, r in zip(items, rows):
        rep = lambda k, it=it: torch.as_tensor(it[k]).float()[None].expand(G, *torch.as_tensor(it[k]).shape).to(device)  # noqa: E731
        code, pose, V, K = rep("latent_code"), rep("pose"), rep("viewmat"), rep("K")
        with restored_weights(model, renderer) if fit is not None else contextlib.nullcontext():
            if fit is not None:
                code = fit(it, gz).expand(G, -1)
                if not torch.isfinite(code).all():
                    raise ToolkitError(f"--fit-weights: the fit of input row {r} diverged (non-finite code); try "
                                       "fewer --fit-steps or a lower eval.tta_renderer_lr")
            with torch.no_grad():
                img = render_gazes(model, renderer, code, pose, gz, V, K, res, steps)
        if not torch.isfinite(img).all():  # NaN would be written as black pixels
            raise ToolkitError(f"input row {r}: the render is not finite (a non-finite code or a diverged fit?)")
        _append_row(out, it, r, img, code, pose, V, K, gazes, gz, res, device)
    return {k: np.concatenate(v) for k, v in out.items()}


def _append_row(out: dict[str, list], it: dict, r: int, img: torch.Tensor, code: torch.Tensor, pose: torch.Tensor,
                V: torch.Tensor, K: torch.Tensor, gazes: np.ndarray, gz: torch.Tensor, res: int, device) -> None:
    """Append one input row's G renders ``img`` [G, 3, res, res] (composited on white outside the row's head
    mask) and their labels to ``out``'s lists."""
    from toolkit.rotations import pitchyaw_to_vector, vector_to_pitchyaw

    G = gazes.shape[0]
    mask = torch.as_tensor(it["head_mask"]).float().to(device)
    img = img * mask + (1 - mask)
    R = V[:, :3, :3] @ so3_exp(pose[:, :3])
    cam_gaze = vector_to_pitchyaw(torch.einsum("bij,bj->bi", R, pitchyaw_to_vector(gz)))
    bgr = (img.clamp(0, 1).permute(0, 2, 3, 1).cpu().numpy()[..., ::-1] * 255).round().astype(np.uint8)
    out["face_patch"].append(bgr)
    out["head_mask"].append(np.repeat((mask[0].cpu().numpy() > 0.5).astype(np.uint8)[None] * 255, G, 0))
    out["pitchyaw_head"].append(gazes)
    out["pitchyaw_cam"].append(cam_gaze.cpu().numpy())
    out["pose"].append(pose.cpu().numpy())
    out["w2c_Rmat"].append(V[:, :3, :3].cpu().numpy())
    out["w2c_Tvec"].append(V[:, :3, 3].cpu().numpy())
    out["inmat"].append(K.cpu().numpy())
    out["latent_codes"].append(code.cpu().numpy())
    out["face_head_pose"].append(np.repeat(np.asarray(it["face_head_pose"], np.float32)[None], G, 0))
    out["cam_index"].append(np.full((G, 1), int(it["cam_index"]), np.int32))  # the schema's [N, 1] int32 (docs/data.md)
    out["frame_index"].append(np.full((G, 1), int(it["frame_index"]), np.int32))
    out["source_row"].append(np.full(G, r, np.int64))
    # Gaze does not move the lids, landmarks or mesh of the synthetic subjects: the input's stay valid.
    for key, src in (("left_eye_mask", "left_eye_mask"), ("right_eye_mask", "right_eye_mask")):
        m = (np.asarray(it[src]).reshape(res, res) > 0.5).astype(np.uint8) * 255
        out[key].append(np.repeat(m[None], G, 0))
    for key, src in (("facial_landmarks", "landmarks"), ("facial_landmarks_3d", "landmarks_3d"),
                     ("scale", "scale"), ("vertice", "vertice")):
        a = np.asarray(it[src], np.float32)
        out[key].append(np.repeat(a[None], G, 0))
