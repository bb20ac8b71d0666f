"""The orthogonality loss of DiT-Gaze: gaze, head pose and expression features kept apart.

Forward hooks on the **first linear layer** of the gaze MLP, the pose MLP and the expression MLP;
``L = w1·|cos(v_gaze, v_expr)| + w2·|cos(v_pose, v_expr)|`` averaged over the batch, in float32 even under
autocast.
"""

from __future__ import annotations

import torch
import torch.nn as nn
import torch.nn.functional as F

from toolkit.errors import ToolkitError
from train.losses.precision import no_autocast


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
        with no_autocast(layer.weight.device):
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
