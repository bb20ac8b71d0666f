"""Pre-training of the two-stream model's fields in the initialization (geometry) stage: ``geometry.pretrain_fields``.

GazeGaussian trains its deformation MLPs in its first stage, with the mesh (``trainer/meshhead_trainer.py``
L51-60: ``shape_deform_mlp``, ``pose_deform_mlp``, ``eye_deform_mlp`` and the colour MLPs at ``lr_net`` 1e-3,
``configs/meshhead_options.py`` L31), and starts the Gaussian model's MLPs from them
(``models/gaze_gaussian.py`` L125-138, ``initialize_with_meshhead``). Its losses (``meshhead_trainer.py`` L109-138):
the rendered colours against the masked image (L1, weight 1), the silhouette (1 − IoU, 0.1), the 3D landmarks
deformed by the expression MLP against each frame's (``loss_def``, MSE, 0.1), the deformations' size
(``loss_offset``, 0.01), plus the SDF's own terms, which this project's SDF fit already has.

Here the mesh is fitted by ``geometry.fit``; what is pre-trained is the model the Gaussian stage trains, on its
own Gaussians (the geometry stage's scene), through its own splat. Per step, on a batch of training rows:

- ``rgb``: L1 of the splatted RGB channels against the target at the splat's size (the Gaussian stage's ``rgb``
  term; the colours start from the images when ``gaussian.rgb_init``, as the Gaussian stage's do);
- ``silhouette``: 1 − soft IoU of the head render's alpha and the head mask;
- ``landmarks``: the 68 landmarks moved with the face stream (each by the softmax(−d² / 2σ²)-weighted mean
  displacement of the face Gaussians around it, σ = :data:`LANDMARK_SIGMA_M`), posed, projected with the row's
  camera, against the row's 2D landmarks: squared distance in image widths. The peer compares 3D landmarks; the
  2D ones are in every layout's rows (a one-camera file has no 3D ones) and are their projections;
- ``offset``: the mean squared displacement of the face Gaussians, in head radii.

Only the fields train (:data:`FIELDS`: the face deformation field, the eye rotation field, and the gaze-driven eye
terms when the model has them); the Gaussians stay as the geometry stage placed them. The eye rotation field
learns from the RGB and silhouette terms, as the peer's ``eye_deform_mlp`` learns from its render.
"""

from __future__ import annotations

import time
from pathlib import Path
from typing import Callable

import torch
import torch.nn.functional as F

from toolkit.errors import ToolkitError
from toolkit.rotations import so3_exp

FIELDS = ("face_field", "eye_field", "eye_gaze_terms")
"""The model's modules pre-trained and saved (those the model has: ``eye_gaze_terms`` is optional)."""
WEIGHTS = {"rgb": 1.0, "silhouette": 0.1, "landmarks": 0.1, "offset": 0.01}
"""The terms' weights: GazeGaussian's (``meshhead_trainer.py`` L138: rgb 1, sil 0.1, def 0.1, offset 0.01)."""
LR = 1e-3
"""Adam learning rate of the fields (GazeGaussian's ``lr_net``)."""
BATCH = 4
"""Training rows per step."""
GRAD_CLIP = 1.0
"""Bound of the gradients' global norm (``meshhead_trainer.py`` L182)."""
LANDMARK_SIGMA_M = 0.005
"""Radius (metres) of the face Gaussians whose displacement moves a landmark."""
FILE = "fields.safetensors"
"""The geometry stage's output file of the pre-trained fields."""
_EPS = 1e-6


def pretrained_modules(model) -> dict[str, torch.nn.Module]:
    """{name: module} of :data:`FIELDS` the model has."""
    return {n: m for n in FIELDS if (m := getattr(model, n, None)) is not None}


def landmark_weights(model, sigma_m: float = LANDMARK_SIGMA_M) -> torch.Tensor:
    """[L, Nf] softmax(−d² / 2σ²) over the face Gaussians, d their canonical distance to each of the model's
    landmarks [L, 3]: each row sums to 1 however far the nearest Gaussian is."""
    d2 = torch.cdist(model.landmarks.float(), model.face_means.detach().float()).square()
    sigma = sigma_m * model.units_per_metre
    return torch.softmax(-d2 / (2 * sigma ** 2), dim=-1)


def project(points: torch.Tensor, pose: torch.Tensor, viewmat: torch.Tensor, K: torch.Tensor) -> torch.Tensor:
    """Head-frame points [B, P, 3] posed (x_world = R(γ[:3]) x + γ[3:]), seen by cameras viewmat [B, 4, 4]
    (world to camera) and K [B, 3, 3] -> pixels [B, P, 2]. Depths are clamped to >= 1e-6 scene units, so a point
    behind the camera stays finite."""
    world = torch.einsum("bij,bpj->bpi", so3_exp(pose[:, :3].float()), points) + pose[:, None, 3:].float()
    cam = torch.einsum("bij,bpj->bpi", viewmat[:, :3, :3].float(), world) + viewmat[:, None, :3, 3].float()
    uvw = torch.einsum("bij,bpj->bpi", K.float(), cam)
    return uvw[..., :2] / uvw[..., 2:].clamp_min(_EPS)


def pretrain_terms(model, b: dict[str, torch.Tensor], lmk_weights: torch.Tensor) -> dict[str, torch.Tensor]:
    """The pre-training's terms on a batch ``b`` (training rows: image [B, 3, R, R], head [B, 1, R, R], code,
    pose, gaze_head, viewmat, K, landmarks [B, 68, 2] pixels) and their weighted sum "total" (scalars)."""
    R = int(b["image"].shape[-1])
    maps = model(b["code"], b["pose"], b["gaze_head"], b["viewmat"], b["K"], R, R, renders=("head",))
    size = maps["rgb"].shape[-2:]
    small = F.interpolate(b["image"], size=size, mode="area")
    mask = F.interpolate(b["head"], size=size, mode="area")
    alpha = maps["head_alpha"]
    inter = (alpha * mask).sum(dim=(1, 2, 3))
    union = (alpha + mask - alpha * mask).sum(dim=(1, 2, 3))
    face = model.face_stream(b["code"], b["pose"])  # the forward's, from the cache
    disp = face["means"] - model.face_means  # [B, Nf, 3]
    moved = model.landmarks + torch.einsum("ln,bnc->blc", lmk_weights, disp)
    px = project(moved, b["pose"], b["viewmat"], b["K"])
    terms = {"rgb": (maps["rgb"] - small).abs().mean(),
             "silhouette": (1 - inter / (union + _EPS)).mean(),
             "landmarks": ((px - b["landmarks"]) / R).square().sum(-1).mean(),
             "offset": (disp / model.norm_scale).square().sum(-1).mean()}
    terms["total"] = sum(WEIGHTS[k] * v for k, v in terms.items())
    return terms


def pretrain_fields(model, data, steps: int, seed: int = 0, log: Callable[[str], None] | None = None) -> dict:
    """Train the model's :data:`FIELDS` for ``steps`` Adam steps on ``data`` (``train.training.trainer``'s
    ``TrainRows`` or ``TrainBatchData``), batches of :data:`BATCH` rows drawn with ``seed``; the other weights are
    left as they are. Returns {"steps", "before", "after"}: the terms on a fixed batch (evenly spaced rows)
    before and after, as floats."""
    if model.landmarks.shape[0] != 68:
        raise ToolkitError(f"geometry.pretrain_fields: the scene has {model.landmarks.shape[0]} landmarks, the "
                           "landmark term needs the 68 the geometry stage stores")
    dev = model.face_means.device
    fields = pretrained_modules(model)
    params = [p for m in fields.values() for p in m.parameters()]
    frozen = [p for p in model.parameters() if p.requires_grad and all(p is not q for q in params)]
    for p in frozen:
        p.requires_grad_(False)
    try:
        n = len(data)
        fixed = data.take(torch.linspace(0, n - 1, min(n, BATCH)).round().long(), dev)
        weights = landmark_weights(model)
        before = _evaluate(model, fixed, weights)
        opt = torch.optim.Adam(params, lr=LR)
        g = torch.Generator().manual_seed(seed)
        for step in range(steps):
            b = data.take(torch.randint(0, n, (BATCH,), generator=g), dev)
            terms = pretrain_terms(model, b, weights)
            opt.zero_grad(set_to_none=True)
            terms["total"].backward()
            torch.nn.utils.clip_grad_norm_(params, GRAD_CLIP)
            opt.step()
            if log is not None and (step + 1) % max(1, steps // 4) == 0:
                log(f"[geometry] fields step {step + 1}/{steps}: total {float(terms['total'].detach()):.4g}")
        after = _evaluate(model, fixed, weights)
    finally:
        for p in frozen:
            p.requires_grad_(True)
        model.clear_cache()
    return {"steps": int(steps), "before": before, "after": after}


def _evaluate(model, b, weights) -> dict[str, float]:
    with torch.no_grad():
        out = {k: float(v) for k, v in pretrain_terms(model, b, weights).items()}
    model.clear_cache()
    return out


def save_fields(model, path: str | Path, info: dict) -> None:
    """Write the model's :data:`FIELDS` (``name.param`` tensors) and ``info`` to ``path`` (safetensors, atomic)."""
    from toolkit.io import save_checkpoint

    state = {f"{n}.{k}": v for n, m in pretrained_modules(model).items() for k, v in m.state_dict().items()}
    save_checkpoint(path, state, {"kind": "pretrained_fields", **info})


def load_fields(model, path: str | Path) -> list[str]:
    """Load :func:`save_fields`' file into the model's fields (each must match exactly); returns their names.
    A ToolkitError names the file when it does not fit the model (written under other ``gaussian`` fields)."""
    from toolkit.io import load_checkpoint

    state, info = load_checkpoint(path)
    if info.get("kind") != "pretrained_fields":
        raise ToolkitError(f"{path}: not a pre-trained fields file (geometry.pretrain_fields)")
    fields = pretrained_modules(model)
    names = sorted({k.split(".", 1)[0] for k in state})
    if names != sorted(fields):
        raise ToolkitError(f"{path}: holds the fields {names}, the model has {sorted(fields)}; re-run the geometry "
                           "stage under this config")
    for name, module in fields.items():
        sub = {k[len(name) + 1:]: v for k, v in state.items() if k.startswith(name + ".")}
        try:
            module.load_state_dict(sub)
        except RuntimeError as e:
            raise ToolkitError(f"{path}: {name} does not fit the model ({str(e).splitlines()[0][:160]}); re-run the "
                               "geometry stage under this config") from None
    model.clear_cache()
    return sorted(fields)


def pretrain_run_fields(ctx, scene_path: Path) -> str:
    """The geometry stage's part: the model the Gaussian stage builds (same seed, same ``gaussian`` fields) on the
    scene at ``scene_path``, its fields pre-trained for ``geometry.pretrain_fields`` steps on the training split
    and saved -> the file's path relative to the run directory."""
    from train.stages.artifacts import RunArtifacts, resolve_device
    from train.training.trainer import build_model, init_rgb, open_split

    cfg = ctx.config
    run = RunArtifacts(ctx)
    device = resolve_device(cfg)
    torch.manual_seed(cfg.seed)  # the Gaussian stage's fresh fields, which the pre-training starts from
    model = build_model(scene_path, cfg.gaussian, device, run.training_code_widths())
    data = open_split(run.split("train"), "all", cfg.data.res, layout=cfg.data.layout)
    try:
        if cfg.gaussian.rgb_init:
            init_rgb(model, data)
        t0 = time.perf_counter()
        result = pretrain_fields(model, data, cfg.geometry.pretrain_fields, cfg.seed, ctx.log)
        result["seconds"] = time.perf_counter() - t0
    finally:
        data.close()
    ctx.log(f"[geometry] fields pre-trained for {result['steps']} steps: total {result['before']['total']:.4g} -> "
            f"{result['after']['total']:.4g}, {result['seconds']:.1f} s")
    rel = f"geometry/{FILE}"
    save_fields(model, ctx.run_dir / rel, result)
    return rel
