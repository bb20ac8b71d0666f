"""Initial RGB channels of the two-stream model's Gaussians, read off the training images.

The geometry stage gives the Gaussians the SDF network's features, whose first three channels are not colours;
the splatted ``rgb`` map then starts far from any face and a short run cannot pull it there. 3DGS starts its
Gaussians from the colours of the SfM points; we have posed images instead, so each Gaussian gets the mean of
the pixels it is seen in, **weighted by its blending weight** ``w_ip = alpha_ip T_ip`` in the splat:

    rgb_i = sum_p m_p w_ip I_p / sum_p m_p w_ip        (over all images; m the head mask)

This handles occlusion and coverage exactly as the splatter renders. The weights come from one backward pass:
for a render ``C_p = sum_i f_i w_ip`` with features ``f = 0``, the gradient of ``sum_p m_p <C_p, I_p>`` with
respect to ``f_i`` is ``sum_p m_p w_ip I_p`` and that of ``sum_p m_p C_p`` is ``sum_p m_p w_ip``. Images are
used at the model's render resolution (``render_scale``), area-downsampled as the stage's ``rgb`` loss sees them;
eye Gaussians are rotated to each image's gaze first, so the iris colour lands on the iris Gaussians. Gaussians
no image sees keep the mean colour of the seen ones.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F

from toolkit.cameras import resize_intrinsics

_EPS = 1e-8


def rgb_from_images(model, images: torch.Tensor, masks: torch.Tensor, code: torch.Tensor, pose: torch.Tensor,
                    gaze: torch.Tensor, viewmats: torch.Tensor, Ks: torch.Tensor,
                    render_scale: float | None = None) -> dict[str, torch.Tensor]:
    """Blending-weighted mean colours of the model's Gaussians over the images.

    Args:
        model: :class:`train.model.gaussian_model.GaussianModel`.
        images [B, 3, H, W] in [0, 1]; masks [B, 1, H, W] head masks; code [B, code_dim]; pose [B, 6];
        gaze [B, 2] head frame; viewmats [B, 4, 4]; Ks [B, 3, 3] for the H x W images.
        render_scale: the resolution to read the images at, as a fraction of H x W (default: the model's).
    Returns:
        {"face": [Nf, 3], "eyes": [Ne, 3]} colours and {"face_weight": [Nf], "eyes_weight": [Ne]} summed weights
        (0: never seen; such Gaussians get the mean colour of the seen ones).
    """
    B, _, H, W = images.shape
    scale = model.config.render_scale if render_scale is None else render_scale
    w, h = max(1, round(W * scale)), max(1, round(H * scale))
    small = F.interpolate(images.float(), size=(h, w), mode="area")
    small_mask = F.interpolate(masks.float(), size=(h, w), mode="area")
    Ks_r = resize_intrinsics(Ks.float(), W, H, w, h)
    with torch.no_grad():
        g = model.gaussians(code.float(), pose.float(), gaze.float())
    n_face = g["face"]["means"].shape[1]
    parts = (g["face"], g["eyes"])
    acc = torch.zeros(n_face + g["eyes"]["means"].shape[1], 4, device=images.device)
    rasterize = model._rasterize()
    for b in range(B):
        cat = {k: torch.cat([p[k][b].float() for p in parts]) for k in ("means", "quats", "scales", "opacities")}
        feats = torch.zeros(cat["means"].shape[0], 4, device=images.device, requires_grad=True)
        with torch.enable_grad():
            img, _, _ = rasterize(cat["means"], cat["quats"], cat["scales"], cat["opacities"], feats,
                                  viewmats[b:b + 1].float(), Ks_r[b:b + 1], w, h,
                                  backgrounds=torch.zeros(4, device=images.device))
            m = small_mask[b].permute(1, 2, 0)  # [h, w, 1]
            target = torch.cat([small[b].permute(1, 2, 0), torch.ones_like(m)], -1)  # [h, w, 4]: colour, weight
            (grad,) = torch.autograd.grad((img[0] * m * target).sum(), feats)
        acc += grad
    weight = acc[:, 3]
    seen = weight > 1e-4
    rgb = acc[:, :3] / (weight[:, None] + _EPS)
    fallback = rgb[seen].mean(0) if bool(seen.any()) else torch.full((3,), 0.5, device=images.device)
    rgb = torch.where(seen[:, None], rgb, fallback).clamp(0, 1)
    return {"face": rgb[:n_face], "eyes": rgb[n_face:], "face_weight": weight[:n_face], "eyes_weight": weight[n_face:]}


@torch.no_grad()
def init_rgb_from_images(model, images, masks, code, pose, gaze, viewmats, Ks, *, max_images: int = 64) -> float:
    """Set channels 0..2 of the face and eye features to :func:`rgb_from_images` of (up to ``max_images``,
    evenly spaced) images, which may stay on the CPU; returns the fraction of Gaussians some image saw.

    The eye Gaussians' colours are read at the images' full resolution: at the model's 1/4 an eye is ~3 pixels
    wide and its iris less than one, so every eye Gaussian would get the same sclera-iris-lid mixture. A model
    with ``eyeball_colours`` keeps its eye features as they are (their RGB is never drawn)."""
    n = images.shape[0]
    idx = torch.linspace(0, n - 1, min(n, max_images)).round().long().unique()
    dev = model.face_features.device
    pick = lambda x: x[idx.to(x.device)].to(dev)  # noqa: E731  (the subset only goes to the model's device)
    args = [pick(x) for x in (images, masks, code, pose, gaze, viewmats, Ks)]
    out = rgb_from_images(model, *args)
    # A parametric eyeball (``eyeball_colours``) draws the eyes' RGB itself: their free RGB columns go unused,
    # so neither the full-resolution eye pass nor their colours are needed.
    free_eyes = getattr(model, "eyeball_colours", None) is None
    eyes = out if model.config.render_scale == 1 or not free_eyes else rgb_from_images(model, *args, render_scale=1.0)
    model.face_features[:, :3] = out["face"].to(model.face_features)
    if free_eyes:
        model.eye_features[:, :3] = eyes["eyes"].to(model.eye_features)
    out["eyes_weight"] = eyes["eyes_weight"]
    model.clear_cache()
    seen = torch.cat([out["face_weight"], out["eyes_weight"]]) > 1e-4
    return float(seen.float().mean())
