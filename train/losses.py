"""Losses of DiT-Gaze: region image loss, gaze loss, orthogonality loss.

- :class:`ImageLoss` — per region (``head``, ``face``, ``eyes``; masks from the data), both images are put on
  a white background outside the region, then ``λ_L1·L1 + λ_SSIM·(1 − SSIM) + λ_P·perceptual``. L1 and SSIM
  are averaged over the region's pixels only, so a small region (the eyes) is not drowned by its background.
  The perceptual term uses the project's own VGG16 (``train.vgg``) with a local torchvision-layout state dict;
  with no weights file the term is disabled and logged once.
- :class:`GazeLoss` — a frozen gaze estimator ψ; angular error (degrees) between ψ(render) and ψ(target image),
  or between ψ(render) and a given gaze (weak supervision with the sampled intermediate gaze).
- :class:`OrthogonalityLoss` — forward hooks on the **first linear layer** of the gaze MLP, the pose MLP and the
  expression MLP; ``L = w1·|cos(v_gaze, v_expr)| + w2·|cos(v_pose, v_expr)|`` averaged over the batch.

All losses compute in float32 even under autocast (SSIM and cosines lose too much in bf16).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field

import torch
import torch.nn as nn
import torch.nn.functional as F

from toolkit.errors import ToolkitError
from toolkit.rotations import angular_error_deg
from train.metrics import composite_on_white  # noqa: F401  (re-exported: the loss and the metrics composite alike)

log = logging.getLogger(__name__)
REGIONS = ("head", "face", "eyes")
_EPS = 1e-6
_perceptual_off_logged = False


def _fp32(x: torch.Tensor) -> torch.Tensor:
    return x.float() if x.dtype != torch.float32 else x


def _no_autocast(device: torch.device):
    return torch.autocast(device_type=device.type, enabled=False)


# ----------------------------------------------------------------------------- image loss
@dataclass
class ImageLossConfig:
    """Weights of the per-region image loss."""

    lambda_l1: float = 1.0
    """weight of the masked L1 term."""
    lambda_ssim: float = 0.2
    """weight of (1 − SSIM) (SSIM from kornia, ``ssim_window`` Gaussian window)."""
    lambda_perceptual: float = 0.1
    """weight of the VGG16 perceptual term (ignored when ``vgg_path`` is None)."""
    ssim_window: int = 11
    vgg_path: str | None = None
    """local torchvision-layout VGG16 state dict (.pth/.pt/.safetensors); None disables the perceptual term."""
    region_weights: dict[str, float] = field(default_factory=lambda: {"head": 1.0, "face": 1.0, "eyes": 1.0})


class ImageLoss(nn.Module):
    """Region image loss. ``forward(pred, target, masks, weights=None) -> (total [], logs {name: float})``.

    Args of forward:
        pred: [B, 3, h, w] RGB in [0, 1], or a dict region -> [B, 3, h, w] (e.g. the face-only render for
            ``face``); h, w may be smaller than the target's (a 1/4-resolution RGB head): target and mask are
            then area-downsampled to the prediction's size.
        target: [B, 3, H, W] RGB in [0, 1] with a white background.
        masks: dict region -> [B, 1, H, W] (or [B, H, W]) in [0, 1]; a region with weight 0 is skipped.
        weights: optional per-region weights overriding ``config.region_weights``.
    """

    def __init__(self, config: ImageLossConfig | None = None):
        super().__init__()
        self.config = cfg = config or ImageLossConfig()
        if cfg.ssim_window < 3 or cfg.ssim_window % 2 == 0:
            raise ToolkitError(f"ImageLossConfig.ssim_window: expected an odd integer >= 3, got {cfg.ssim_window}")
        self.vgg = None
        if cfg.vgg_path is not None and cfg.lambda_perceptual > 0:
            from train.vgg import load_vgg16

            self.vgg = load_vgg16(cfg.vgg_path)
        elif cfg.lambda_perceptual > 0:
            global _perceptual_off_logged
            if not _perceptual_off_logged:
                log.warning("perceptual loss disabled: no VGG16 weights given (ImageLossConfig.vgg_path); "
                            "pass a local torchvision-layout VGG16 state dict to enable it")
                _perceptual_off_logged = True

    @property
    def perceptual_enabled(self) -> bool:
        return self.vgg is not None

    def train(self, mode: bool = True) -> "ImageLoss":
        super().train(mode)
        if self.vgg is not None:
            self.vgg.eval()  # frozen: never switch to training behaviour
        return self

    def region_loss(self, pred: torch.Tensor, target: torch.Tensor, mask: torch.Tensor) -> dict[str, torch.Tensor]:
        """One region: {"l1", "ssim" (= 1 − SSIM), "perceptual", "total"} scalars (float32)."""
        cfg = self.config
        with _no_autocast(pred.device):
            pred, target, mask = _fp32(pred), _fp32(target), _fp32(mask)
            if mask.dim() == 3:
                mask = mask[:, None]
            if pred.dim() != 4 or pred.shape[1] != 3:
                raise ToolkitError(f"ImageLoss: pred must be [B, 3, H, W], got {list(pred.shape)}")
            if target.dim() != 4 or target.shape[:2] != pred.shape[:2]:
                raise ToolkitError(f"ImageLoss: target must be [B={pred.shape[0]}, 3, H, W], got {list(target.shape)}")
            if mask.dim() != 4 or mask.shape[0] != pred.shape[0] or mask.shape[1] != 1 or mask.shape[2:] != target.shape[2:]:
                raise ToolkitError(f"ImageLoss: mask must be [B, 1, {target.shape[2]}, {target.shape[3]}], got {list(mask.shape)}")
            if pred.shape[2:] != target.shape[2:]:
                target = F.interpolate(target, size=pred.shape[2:], mode="area")
                mask = F.interpolate(mask, size=pred.shape[2:], mode="area")
            mask = mask.clamp(0, 1)
            a, b = composite_on_white(pred, mask), composite_on_white(target, mask)
            area = mask.sum(dim=(1, 2, 3))  # [B]
            l1 = ((a - b).abs() * mask).sum(dim=(1, 2, 3)) / (3 * area + _EPS)
            out = {"l1": l1.mean()}
            zero = pred.new_zeros(())
            if cfg.lambda_ssim > 0:
                win = min(cfg.ssim_window, _largest_odd(min(pred.shape[2:])))
                if win >= 3:
                    smap = _ssim_map(a, b, win).mean(1, keepdim=True)  # [B, 1, H, W]
                    ssim = (smap * mask).sum(dim=(1, 2, 3)) / (area + _EPS)
                    # Empty regions contribute 0 rather than 1 − 0.
                    out["ssim"] = torch.where(area > _EPS, 1 - ssim, torch.zeros_like(ssim)).mean()
                else:
                    out["ssim"] = zero
            else:
                out["ssim"] = zero
            if self.vgg is not None and cfg.lambda_perceptual > 0:
                from train.vgg import perceptual_distance

                out["perceptual"] = perceptual_distance(self.vgg, a, b)
            else:
                out["perceptual"] = zero
            out["total"] = cfg.lambda_l1 * out["l1"] + cfg.lambda_ssim * out["ssim"] + cfg.lambda_perceptual * out["perceptual"]
        return out

    def forward(self, pred, target: torch.Tensor, masks: dict[str, torch.Tensor],
                weights: dict[str, float] | None = None) -> tuple[torch.Tensor, dict[str, float]]:
        w = dict(self.config.region_weights)
        w.update(weights or {})
        unknown = set(w) - set(REGIONS)
        if unknown:
            raise ToolkitError(f"ImageLoss: unknown region(s) {sorted(unknown)}; expected {list(REGIONS)}")
        total = None
        logs: dict[str, float] = {}
        for region in REGIONS:
            if w.get(region, 0.0) == 0.0:
                continue
            if region not in masks:
                raise ToolkitError(f"ImageLoss: masks has no {region!r} entry (weight {w[region]}); got {sorted(masks)}")
            p = pred.get(region) if isinstance(pred, dict) else pred
            if p is None:
                raise ToolkitError(f"ImageLoss: pred has no {region!r} image; got {sorted(pred)}")
            parts = self.region_loss(p, target, masks[region])
            for k, v in parts.items():
                logs[f"{region}/{k}"] = float(v.detach())
            term = w[region] * parts["total"]
            total = term if total is None else total + term
        if total is None:
            total = target.new_zeros((), dtype=torch.float32)
        logs["image/total"] = float(total.detach())
        return total, logs


def _largest_odd(n: int) -> int:
    return n if n % 2 == 1 else n - 1


def _ssim_map(a: torch.Tensor, b: torch.Tensor, window: int) -> torch.Tensor:
    """[B, C, H, W] SSIM map (kornia, Gaussian window, max value 1)."""
    import kornia

    return kornia.metrics.ssim(a, b, window, max_val=1.0)


# ----------------------------------------------------------------------------- gaze loss
class GazeLoss(nn.Module):
    """Angular error in degrees between a frozen estimator's gaze on the render and on the target.

    ``forward(render [B, 3, H, W], target_image=None, target_gaze=None [B, 2] pitch/yaw) -> [] mean degrees``;
    exactly one target must be given. The estimator (``estimator(images) -> [B, >=2]`` with gaze pitch/yaw
    first, e.g. :class:`train.gaze_estimator.GazeEstimator`) is frozen: eval mode, no parameter gradients;
    gradients flow through the render only.
    """

    def __init__(self, estimator: nn.Module):
        super().__init__()
        self.estimator = estimator.eval()
        for p in self.estimator.parameters():
            p.requires_grad_(False)

    def train(self, mode: bool = True) -> "GazeLoss":
        super().train(mode)
        self.estimator.eval()
        return self

    def forward(self, render: torch.Tensor, target_image: torch.Tensor | None = None,
                target_gaze: torch.Tensor | None = None, reduction: str = "mean",
                landmarks: torch.Tensor | None = None) -> torch.Tensor:
        """``landmarks`` [B, 68, 2] (pixels of the target, which the render shares) are passed on to
        estimators that read eye patches."""
        if (target_image is None) == (target_gaze is None):
            raise ToolkitError("GazeLoss: give exactly one of target_image or target_gaze")
        est = self.estimator if landmarks is None else (lambda x: self.estimator(x, _fp32(landmarks)))
        with _no_autocast(render.device):
            pred = est(_fp32(render))[:, :2]
            if target_image is not None:
                with torch.no_grad():
                    target = est(_fp32(target_image))[:, :2]
            else:
                target = _fp32(target_gaze).to(pred.device)
                if target.shape != pred.shape:
                    raise ToolkitError(f"GazeLoss: target_gaze must be [B={pred.shape[0]}, 2], got {list(target.shape)}")
            err = angular_error_deg(pred, target.detach())
        if reduction == "none":
            return err
        return err.mean()


def head_to_camera_rotation(viewmat: torch.Tensor, pose: torch.Tensor) -> torch.Tensor:
    """[B, 3, 3] rotation from the head frame to the camera frame (w2c ∘ pose), for world-to-camera
    ``viewmat`` [B, 4, 4] and head ``pose`` [B, 6] (axis-angle rotation first): the ``R`` of :func:`gaze_to_camera`."""
    from toolkit.rotations import so3_exp

    return viewmat[:, :3, :3] @ so3_exp(pose[:, :3])


def gaze_to_camera(pitchyaw: torch.Tensor, R: torch.Tensor) -> torch.Tensor:
    """Head-frame gaze [B, 2] -> camera-frame gaze [B, 2] for head-to-camera rotations R [B, 3, 3].

    The sampled intermediate gaze φ lives in the head frame, while an estimator trained on camera-frame labels
    (``pitchyaw_cam``) predicts camera-frame gaze: convert φ with this before ``GazeLoss(target_gaze=...)``.
    """
    from toolkit.rotations import pitchyaw_to_vector, vector_to_pitchyaw

    return vector_to_pitchyaw(torch.einsum("bij,bj->bi", R, pitchyaw_to_vector(pitchyaw)))


# ----------------------------------------------------------------------------- orthogonality loss
class OrthogonalityLoss:
    """Disentangling regularizer on the first linear layers of the gaze, pose and expression MLPs.

    ``L = w1·|cos(v_gaze, v_expr)| + w2·|cos(v_pose, v_expr)|``, averaged over the batch.

    Pooling: each MLP's first layer sees per-Gaussian (or per-eye) inputs ``[B, ..., in]``; its output is
    pooled per sample by the **mean over all Gaussians / eyes**, giving ``v [B, width]``. Because the layer is
    affine, mean(W x + b) = W mean(x) + b, so the hook stores only the mean input (cheap: [B, in]) and the
    pooled output is recomputed from it with the layer's current weights when the loss is evaluated.

    Gradient: the stored inputs are detached, so the loss trains exactly the three first layers (weight and
    bias) and nothing upstream (codes, canonical Gaussians, encoders) nor downstream (deeper layers): it
    shapes how the layers embed their conditions rather than moving the conditions themselves. The layers
    need equal output widths (the cosines compare vectors in the same space).

    Use: ``ortho = OrthogonalityLoss(gaze_layer, pose_layer, expr_layer)``; run the model forward (hooks
    fire); ``loss = ortho()``; ``ortho.remove()`` when done. A missing capture raises ``ToolkitError``.
    """

    def __init__(self, gaze_layer: nn.Linear, pose_layer: nn.Linear, expr_layer: nn.Linear,
                 w1: float = 1.0, w2: float = 1.0, eps: float = 1e-8):
        layers = {"gaze": gaze_layer, "pose": pose_layer, "expr": expr_layer}
        for name, layer in layers.items():
            if not isinstance(layer, nn.Linear):
                raise ToolkitError(f"OrthogonalityLoss: {name} layer must be an nn.Linear, got {type(layer).__name__}")
        widths = {n: l.out_features for n, l in layers.items()}
        if len(set(widths.values())) != 1:
            raise ToolkitError(f"OrthogonalityLoss: first-layer widths must be equal, got {widths}")
        self.layers = layers
        self.w1, self.w2, self.eps = float(w1), float(w2), float(eps)
        self.inputs: dict[str, torch.Tensor] = {}
        self._handles = [layer.register_forward_hook(self._hook(name)) for name, layer in layers.items()]

    def _hook(self, name: str):
        def hook(module, args, output):
            x = args[0].detach()
            if x.dim() < 2:
                raise ToolkitError(f"OrthogonalityLoss: {name} layer input must be [B, ..., in], got {list(x.shape)}")
            x = x.float().reshape(x.shape[0], -1, x.shape[-1]).mean(1)  # [B, in]: mean over Gaussians / eyes
            self.inputs[name] = x
        return hook

    def pooled(self, name: str) -> torch.Tensor:
        """[B, width] pooled first-layer output of ``name`` ("gaze", "pose", "expr") from the last forward."""
        if name not in self.inputs:
            raise ToolkitError(f"OrthogonalityLoss: no {name!r} activation captured; run the model forward first")
        layer = self.layers[name]
        with _no_autocast(layer.weight.device):
            return F.linear(self.inputs[name], layer.weight.float(), None if layer.bias is None else layer.bias.float())

    def cosines(self) -> tuple[torch.Tensor, torch.Tensor]:
        """([B] cos(v_gaze, v_expr), [B] cos(v_pose, v_expr))."""
        g, p, e = self.pooled("gaze"), self.pooled("pose"), self.pooled("expr")
        if not (g.shape[0] == p.shape[0] == e.shape[0]):
            raise ToolkitError(f"OrthogonalityLoss: batch sizes differ (gaze {g.shape[0]}, pose {p.shape[0]}, expr {e.shape[0]})")
        return _cos(g, e, self.eps), _cos(p, e, self.eps)

    def __call__(self) -> torch.Tensor:
        c1, c2 = self.cosines()
        return (self.w1 * c1.abs() + self.w2 * c2.abs()).mean()

    def clear(self) -> None:
        self.inputs.clear()

    def remove(self) -> None:
        for h in self._handles:
            h.remove()
        self._handles.clear()
        self.inputs.clear()


def _cos(a: torch.Tensor, b: torch.Tensor, eps: float) -> torch.Tensor:
    # sqrt(|a|^2 + eps) keeps the gradient finite when an activation vector is exactly zero.
    na = torch.sqrt((a * a).sum(-1) + eps)
    nb = torch.sqrt((b * b).sum(-1) + eps)
    return (a * b).sum(-1) / (na * nb)

