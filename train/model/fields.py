"""Conditioned fields of the two-stream Gaussian model: positional encoding, MLPs, face deformation, eye rotation,
eye appearance, and the parametric eyeball colours.

Every field MLP starts with a plain ``nn.Linear`` named ``first`` of width ``hidden``, equal across fields (the
orthogonality loss hooks those of the expression, pose and gaze MLPs; the eye appearance field applies its
``first`` as two matrix products, so hooks on it would not fire), and ends with a zero-initialized linear layer so that at
initialization the face is undeformed and the eyes follow the analytic gaze rotation exactly.
"""

from __future__ import annotations

import math

import torch
import torch.nn as nn

from toolkit.errors import ToolkitError
from toolkit.eyes import gaze_rotation
from toolkit.rotations import so3_exp


def positional_encoding(x: torch.Tensor, num_freqs: int) -> torch.Tensor:
    """[..., d] -> [..., d·(1 + 2·num_freqs)]: x, sin(2^k π x), cos(2^k π x) for k < num_freqs (NeRF)."""
    if num_freqs <= 0:
        return x
    freqs = (2.0 ** torch.arange(num_freqs, device=x.device, dtype=x.dtype)) * math.pi
    xf = x[..., None] * freqs  # [..., d, L]
    return torch.cat([x, torch.sin(xf).flatten(-2), torch.cos(xf).flatten(-2)], -1)


def encoded_dim(d: int, num_freqs: int) -> int:
    return d * (1 + 2 * max(num_freqs, 0))


class FieldMLP(nn.Module):
    """``first`` (Linear in -> hidden) -> ReLU -> [Linear hidden -> hidden -> ReLU] × (depth - 2) -> ``last`` (zero-init)."""

    def __init__(self, in_dim: int, hidden: int, out_dim: int, depth: int = 3):
        super().__init__()
        self.first = nn.Linear(in_dim, hidden)
        self.hidden = nn.ModuleList([nn.Linear(hidden, hidden) for _ in range(max(depth - 2, 0))])
        self.last = nn.Linear(hidden, out_dim)
        nn.init.zeros_(self.last.weight)
        nn.init.zeros_(self.last.bias)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        h = torch.relu(self.first(x))
        for layer in self.hidden:
            h = torch.relu(layer(h))
        return self.last(h)


class FaceDeformationField(nn.Module):
    """Expression (τ) and pose (γ) MLPs on canonical face Gaussians, blended per Gaussian by λτ, λγ.

    Each MLP maps ``[PE(x_can), condition]`` per Gaussian to raw deltas
    ``[Δposition 3, Δfeature D, Δlog-scale 3, Δrotation 3 (quaternion vector part), Δopacity-logit 1]``;
    the expression MLP's condition is τ, the pose MLP's is PE(γ). The blend
    ``Δ = λτ·Δ_expr + λγ·Δ_pose`` lets regions near the landmarks (eyes, brows, mouth) follow the expression
    while far regions (hair, neck) follow the pose, as in GazeGaussian.
    """

    def __init__(self, feature_dim: int, code_dim: int, pose_dim: int, hidden: int, depth: int,
                 pos_freqs: int, pose_freqs: int):
        super().__init__()
        self.feature_dim, self.pos_freqs, self.pose_freqs = feature_dim, pos_freqs, pose_freqs
        self.out_dim = 3 + feature_dim + 3 + 3 + 1
        pe = encoded_dim(3, pos_freqs)
        self.expr_mlp = FieldMLP(pe + code_dim, hidden, self.out_dim, depth)
        self.pose_mlp = FieldMLP(pe + encoded_dim(pose_dim, pose_freqs), hidden, self.out_dim, depth)

    def forward(self, x_norm: torch.Tensor, code: torch.Tensor, pose_norm: torch.Tensor,
                lam_expr: torch.Tensor) -> dict[str, torch.Tensor]:
        """x_norm [N, 3] normalized canonical positions, code [B, C], pose_norm [B, P], lam_expr [N] in [0, 1]
        -> dict of raw deltas, each [B, N, k]: "pos" 3, "feature" D, "log_scale" 3, "rot" 3, "opacity" 1."""
        B, N = code.shape[0], x_norm.shape[0]
        pe = positional_encoding(x_norm, self.pos_freqs)[None].expand(B, N, -1)
        d_expr = self.expr_mlp(torch.cat([pe, code[:, None].expand(B, N, code.shape[1])], -1))
        pose_pe = positional_encoding(pose_norm, self.pose_freqs)
        d_pose = self.pose_mlp(torch.cat([pe, pose_pe[:, None].expand(B, N, pose_pe.shape[1])], -1))
        lam = lam_expr.to(d_expr.dtype)[None, :, None]
        d = lam * d_expr + (1 - lam) * d_pose
        D = self.feature_dim
        return {"pos": d[..., :3], "feature": d[..., 3:3 + D], "log_scale": d[..., 3 + D:6 + D],
                "rot": d[..., 6 + D:9 + D], "opacity": d[..., 9 + D:10 + D]}


class EyeRotationField(nn.Module):
    """Per-eye rigid rotation from the head-frame gaze φ and τ: R_eye = R_residual(φ, τ, eye) · R_gaze(φ).

    Choice: the MLP predicts a **residual** on top of the analytic ``toolkit.eyes.gaze_rotation(φ)``. The
    canonical eye Gaussians look frontally, so the analytic rotation is already the right geometry at step 0
    (the zero-initialized last layer makes the residual the identity); the residual learns what the analytic
    model lacks — the subject's offset between optical and visual axis (kappa) and small per-expression
    changes — and is bounded (``max_residual`` radians per axis-angle component) so it can never replace
    the gaze label's meaning. The eye identity (left/right one-hot) is an input, so each eye gets its own.
    """

    def __init__(self, code_dim: int, hidden: int, depth: int, gaze_freqs: int, max_residual: float = 0.35):
        super().__init__()
        self.gaze_freqs, self.max_residual = gaze_freqs, max_residual
        self.mlp = FieldMLP(encoded_dim(2, gaze_freqs) + code_dim + 2, hidden, 3, depth)

    def forward(self, gaze: torch.Tensor, code: torch.Tensor) -> torch.Tensor:
        """gaze [B, 2] (pitch, yaw) radians, code [B, C] -> [B, 2, 3, 3] rotations (left eye, right eye)."""
        B = gaze.shape[0]
        pe = positional_encoding(gaze / math.pi, self.gaze_freqs)
        eye_id = torch.eye(2, dtype=pe.dtype, device=pe.device)[None].expand(B, 2, 2)
        inp = torch.cat([pe[:, None].expand(B, 2, pe.shape[1]), code[:, None].expand(B, 2, code.shape[1]).to(pe.dtype), eye_id], -1)
        residual = self.max_residual * torch.tanh(self.mlp(inp).float())  # [B, 2, 3] axis-angle
        R_gaze = gaze_rotation(gaze.float())[:, None]  # [B, 1, 3, 3]
        return so3_exp(residual) @ R_gaze


class EyeAppearanceField(nn.Module):
    """Per-identity colours of the eye Gaussians: ``Δfeature(x_eye, τ, eye)`` added to their shared features.

    Without it every face gets the same eyes: the eye Gaussians' features are one set for all identities, so a
    new face's iris colour could come only from the renderer. Each eye Gaussian is located by its canonical
    position in its own eyeball's frame (``x_eye``, in eyeball radii, see ``GaussianModel``: the iris and pupil
    sit on the front cap),
    so the field can colour the iris, the pupil and the sclera differently, from the code τ. A test-time fit
    of the code then recolours the eyes through this low-dimensional map rather than Gaussian by Gaussian.
    """

    def __init__(self, feature_dim: int, code_dim: int, hidden: int, depth: int, pos_freqs: int):
        super().__init__()
        self.pos_freqs = pos_freqs
        self.mlp = FieldMLP(encoded_dim(3, pos_freqs) + 2 + code_dim, hidden, feature_dim, depth)

    def forward(self, x_eye: torch.Tensor, side: torch.Tensor, code: torch.Tensor) -> torch.Tensor:
        """x_eye [N, 3] eyeball-frame positions in eyeball radii, side [N] (0 left, 1 right), code [B, C]
        -> [B, N, feature_dim] raw feature deltas (zero at initialization)."""
        pe = positional_encoding(x_eye, self.pos_freqs)
        where = torch.cat([pe, nn.functional.one_hot(side.long(), 2).to(pe.dtype)], -1)  # [N, P]
        # The first layer split in two: the per-Gaussian half once, the per-code half once per sample.
        w = self.mlp.first.weight
        h = (where @ w[:, :where.shape[1]].T)[None] + (code.to(pe.dtype) @ w[:, where.shape[1]:].T + self.mlp.first.bias)[:, None]
        h = torch.relu(h)
        for layer in self.mlp.hidden:
            h = torch.relu(layer(h))
        return self.mlp.last(h)


class EyeballColours(nn.Module):
    """RGB of the eye Gaussians from a parametric eyeball: a pupil, an iris and a sclera of one colour each,
    bounded by two circles about the eye's optical axis at polar angles ``theta_pupil`` < ``theta_iris``
    (radians), each edge a logistic step of scale ``edge`` radians.

    Why: with a free colour per eye Gaussian, training smears the eye into a ramp from a grey centre to
    skin-coloured edges (the demo model: luminance 0.25 at the axis, 0.55 at the iris edge, 0.7 and pink beyond,
    against the data's 0.03 / 0.2-0.45 / 0.93): the eye Gaussians also paint the lids, and every identity's iris
    size and colour and every misplaced view average into one blur. Here the eyeball can only be an eyeball,
    sharp at any size; a fit can recolour it and resize its iris and pupil (eleven numbers) but never paint an
    iris off its axis. Colours are stored as logits (always in (0, 1)). The edges are kept in order by clamping
    (:meth:`boundaries`): the iris edge to ``[MIN_ANGLE + edge, MAX_ANGLE]``, the pupil edge to
    ``[MIN_ANGLE, iris edge - edge]`` (the pupil gives way when the two meet).
    """

    MIN_ANGLE = 0.02
    MAX_ANGLE = math.pi / 2

    def __init__(self, edge: float = 0.03, pupil=(0.05, 0.05, 0.05), iris=(0.30, 0.25, 0.20),
                 sclera=(0.92, 0.92, 0.92), theta_pupil: float = 0.19, theta_iris: float = 0.50):
        super().__init__()
        if not edge > 0:
            raise ToolkitError(f"EyeballColours: edge must be > 0 radians, got {edge}")
        if not (self.MIN_ANGLE <= theta_pupil <= theta_iris - edge and theta_iris <= self.MAX_ANGLE):
            raise ToolkitError(f"EyeballColours: need {self.MIN_ANGLE} <= theta_pupil <= theta_iris - edge and "
                               f"theta_iris <= pi/2, got {theta_pupil}, {theta_iris} (edge {edge})")
        self.edge = float(edge)
        logit = lambda c: torch.logit(torch.tensor(c, dtype=torch.float32).clamp(1e-3, 1 - 1e-3))  # noqa: E731
        self.pupil, self.iris, self.sclera = (nn.Parameter(logit(c)) for c in (pupil, iris, sclera))
        self.theta_pupil = nn.Parameter(torch.tensor(float(theta_pupil)))
        self.theta_iris = nn.Parameter(torch.tensor(float(theta_iris)))

    def boundaries(self) -> tuple[torch.Tensor, torch.Tensor]:
        """(pupil, iris) edge angles in radians, ordered and within bounds."""
        t_iris = self.theta_iris.clamp(self.MIN_ANGLE + self.edge, self.MAX_ANGLE)
        t_pupil = torch.minimum(self.theta_pupil.clamp(min=self.MIN_ANGLE), t_iris - self.edge)
        return t_pupil, t_iris

    def forward(self, theta: torch.Tensor) -> torch.Tensor:
        """theta [N] polar angles of the Gaussians from the optical axis (radians) -> [N, 3] RGB in (0, 1)."""
        t_pupil, t_iris = self.boundaries()
        outside_iris = torch.sigmoid((theta - t_iris) / self.edge)[:, None]
        outside_pupil = torch.sigmoid((theta - t_pupil) / self.edge)[:, None]
        inner = outside_pupil * torch.sigmoid(self.iris) + (1 - outside_pupil) * torch.sigmoid(self.pupil)
        return outside_iris * torch.sigmoid(self.sclera) + (1 - outside_iris) * inner
