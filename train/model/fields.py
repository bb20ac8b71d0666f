"""Conditioned fields of the two-stream Gaussian model: positional encoding, MLPs, face deformation, eye rotation,
eye appearance (code-driven and gaze-driven), and the parametric eyeball colours.

Every field MLP starts with a plain ``nn.Linear`` named ``first`` of width ``hidden``, equal across fields (the
orthogonality loss hooks those of the expression, pose and gaze MLPs; the MLPs that read a per-Gaussian and a
per-sample input apply their ``first`` as two matrix products, :meth:`FieldMLP.split_forward`, so hooks on them
would not fire), and ends with a zero-initialized linear layer so that at initialization the face is undeformed
and the eyes follow the analytic gaze rotation exactly.
"""

from __future__ import annotations

import math

import torch
import torch.nn as nn

from toolkit.errors import ToolkitError
from toolkit.eyes import gaze_rotation
from toolkit.rotations import so3_exp
from train.model.gaussian_config import FIELD_INPUTS


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
        return self._rest(h)

    def split_forward(self, per_item: torch.Tensor, per_sample: torch.Tensor) -> torch.Tensor:
        """The MLP on ``[per_item, per_sample]`` for every (sample, item) pair: per_item [N, P], per_sample [B, C]
        -> [B, N, out]. The first layer runs as two matrix products, the per-item half once and the per-sample half
        once per sample, instead of on B·N concatenated rows (forward hooks on ``first`` do not fire)."""
        w, p = self.first.weight, per_item.shape[1]
        h = (per_item @ w[:, :p].T)[None] + (per_sample.to(per_item.dtype) @ w[:, p:].T + self.first.bias)[:, None]
        return self._rest(torch.relu(h))

    def _rest(self, h: torch.Tensor) -> torch.Tensor:
        for layer in self.hidden:
            h = torch.relu(layer(h))
        return self.last(h)


class FaceDeformationField(nn.Module):
    """Expression (τ) and pose (γ) MLPs on canonical face Gaussians, blended per Gaussian by λτ, λγ.

    ``field_input="position"``: each MLP maps ``[PE(x_can), condition]`` per Gaussian to raw deltas
    ``[Δposition 3, Δfeature D, Δlog-scale 3, Δrotation 3 (quaternion vector part), Δopacity-logit 1]``.
    ``field_input="feature"`` (GazeGaussian's form, its paper's eq. 2): ``expr_mlp`` / ``pose_mlp`` map
    ``[PE(x_can), condition]`` to Δposition only, and ``expr_attr_mlp`` / ``pose_attr_mlp`` map
    ``[tanh(z₀), condition]``, z₀ the Gaussian's canonical feature, to the other deltas. GazeGaussian's
    ``models/gaussian_model.py`` reads ``pos_embedding(xyz)`` in its deform MLPs (L229-239) and ``tanh(feature)``
    (L134) in its colour and attribute MLPs (L207-226). z₀ is not detached there (L134, L303 trains it through
    those MLPs) nor here: its gradient comes from both the splat and the deltas it conditions.

    The expression MLPs' condition is τ, the pose MLPs' PE(γ). The blend ``Δ = λτ·Δ_expr + λγ·Δ_pose`` lets
    regions near the landmarks (eyes, brows, mouth) follow the expression while far regions (hair, neck) follow
    the pose, as in GazeGaussian.
    """

    def __init__(self, feature_dim: int, code_dim: int, pose_dim: int, hidden: int, depth: int,
                 pos_freqs: int, pose_freqs: int, field_input: str = "position"):
        super().__init__()
        if field_input not in FIELD_INPUTS:
            raise ToolkitError(f"FaceDeformationField: field_input must be one of {list(FIELD_INPUTS)}, got {field_input!r}")
        self.feature_dim, self.pos_freqs, self.pose_freqs = feature_dim, pos_freqs, pose_freqs
        self.field_input = field_input
        self.out_dim = 3 + feature_dim + 3 + 3 + 1
        pe, pose_in = encoded_dim(3, pos_freqs), encoded_dim(pose_dim, pose_freqs)
        moved = self.out_dim if field_input == "position" else 3
        self.expr_mlp = FieldMLP(pe + code_dim, hidden, moved, depth)
        self.pose_mlp = FieldMLP(pe + pose_in, hidden, moved, depth)
        if field_input == "feature":
            self.expr_attr_mlp = FieldMLP(feature_dim + code_dim, hidden, self.out_dim - 3, depth)
            self.pose_attr_mlp = FieldMLP(feature_dim + pose_in, hidden, self.out_dim - 3, depth)

    def forward(self, x_norm: torch.Tensor, code: torch.Tensor, pose_norm: torch.Tensor,
                lam_expr: torch.Tensor, z: torch.Tensor | None = None) -> dict[str, torch.Tensor]:
        """x_norm [N, 3] normalized canonical positions, code [B, C], pose_norm [B, P], lam_expr [N] in [0, 1],
        z [N, D] canonical features (read with ``field_input="feature"`` only)
        -> dict of raw deltas, each [B, N, k]: "pos" 3, "feature" D, "log_scale" 3, "rot" 3, "opacity" 1."""
        B, N = code.shape[0], x_norm.shape[0]
        pe = positional_encoding(x_norm, self.pos_freqs)[None].expand(B, N, -1)
        d_expr = self.expr_mlp(torch.cat([pe, code[:, None].expand(B, N, code.shape[1])], -1))
        pose_pe = positional_encoding(pose_norm, self.pose_freqs)
        d_pose = self.pose_mlp(torch.cat([pe, pose_pe[:, None].expand(B, N, pose_pe.shape[1])], -1))
        if self.field_input == "feature":
            if z is None or z.shape != (N, self.feature_dim):
                raise ToolkitError(f"FaceDeformationField: field_input='feature' needs z [N={N}, {self.feature_dim}], "
                                   f"got {None if z is None else list(z.shape)}")
            zt = torch.tanh(z)  # bounded however large the features grow, as GazeGaussian's L134
            d_expr = torch.cat([d_expr, self.expr_attr_mlp.split_forward(zt, code).to(d_expr.dtype)], -1)
            d_pose = torch.cat([d_pose, self.pose_attr_mlp.split_forward(zt, pose_pe).to(d_pose.dtype)], -1)
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
        return self.mlp.split_forward(where, code)


class EyeGazeAppearanceField(nn.Module):
    """Gaze-driven appearance of the eye Gaussians: from each one's canonical feature z₀ and the gaze φ, raw
    deltas of its feature, log-scale and opacity logit (the G_c, G_κ terms of GazeGaussian's eye branch).

    GazeGaussian's ``models/gaussian_model.py`` feeds ``[tanh(feature), PE(pitchyaw)]`` to its eye colour MLP,
    whose output is added to the colour (L145-149), and to its eye attribute MLP, whose output shifts the
    scale, rotation and opacity (L157-158, L245-256). Rotation is left out here: the eye Gaussians are
    isotropic, so a rotation of one changes nothing. Like the other fields, the last layer starts at zero, so
    at initialization the eyes render exactly as without it.
    """

    def __init__(self, feature_dim: int, hidden: int, depth: int, gaze_freqs: int):
        super().__init__()
        self.feature_dim, self.gaze_freqs = feature_dim, gaze_freqs
        self.mlp = FieldMLP(feature_dim + encoded_dim(2, gaze_freqs), hidden, feature_dim + 2, depth)

    def forward(self, z: torch.Tensor, gaze: torch.Tensor) -> dict[str, torch.Tensor]:
        """z [Ne, D] canonical eye features, gaze [B, 2] (pitch, yaw) radians -> raw deltas "feature"
        [B, Ne, D], "log_scale" [B, Ne], "opacity" [B, Ne] (zero at initialization)."""
        pe = positional_encoding(gaze / math.pi, self.gaze_freqs)
        d = self.mlp.split_forward(torch.tanh(z), pe)  # tanh: GazeGaussian's L134
        D = self.feature_dim
        return {"feature": d[..., :D], "log_scale": d[..., D], "opacity": d[..., D + 1]}


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
