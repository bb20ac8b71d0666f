"""The configuration of the two-stream Gaussian model (:class:`train.model.gaussian_model.GaussianModel`):
sizes of its fields, bounds of their outputs, the optional eye features, and the checks a config must pass."""

from __future__ import annotations

import numbers
from dataclasses import dataclass

from toolkit.errors import ToolkitError
from toolkit.limits import is_finite_number

UNITS_PER_METRE = {"m": 1.0, "cm": 100.0, "mm": 1000.0}
"""Scene units (``scene.metadata["units"]``) per metre: the config's distances are in metres."""

FIELD_INPUTS = ("position", "feature")
"""Values of :attr:`GaussianModelConfig.field_input`."""


@dataclass
class GaussianModelConfig:
    """Two-stream Gaussian model configuration (all MLP first layers share ``hidden`` for the orthogonality loss)."""

    feature_dim: int = 32
    """channels of the splatted feature maps; the first three are RGB."""
    identity_dim: int = 80
    expression_dim: int = 64
    """the widths of the code τ's identity and expression parts (τ = identity ++ expression, :attr:`code_dim`
    wide): the training data's (``train.data.layouts.code_widths``: 80 + 64 for native files, 100 + 79 for
    GazeNeRF's), stored with the model so that a trained run reloads at them."""
    pose_dim: int = 6
    """head pose γ: axis-angle (3, radians) + translation (3, scene units)."""
    hidden: int = 128
    depth: int = 3
    pos_freqs: int = 4
    pose_freqs: int = 4
    gaze_freqs: int = 4
    near_m: float = 0.02
    """distance to the nearest landmark (metres) below which λτ = 1."""
    far_m: float = 0.05
    """distance (metres) above which λτ = 0 (the pose MLP alone deforms)."""
    max_offset: float = 0.1
    """largest Δposition per axis, as a fraction of the head radius."""
    max_log_scale_delta: float = 1.0
    max_opacity_delta: float = 4.0
    max_feature_delta: float = 1.0
    max_eye_residual: float = 0.35
    """bound (radians per axis-angle component) of the learned residual eye rotation."""
    eyes_follow_face: bool = False
    """translate each eyeball (its Gaussians and its rotation centre) by the face field's displacement of its
    socket: the softmax(-d² / 2σ²)-weighted mean Δposition of the face Gaussians at canonical distance d from
    the eye centre (σ = ``socket_sigma_m``). The canonical eyes sit where the geometry subject's eyes were;
    with this the eyes of another identity move with the lids and sockets the code puts on its face, and a
    fit of the face region alone (eyes masked out) still places them."""
    socket_sigma_m: float = 0.01
    eye_appearance: bool = False
    """give the eye Gaussians per-identity features: :class:`train.model.fields.EyeAppearanceField` adds a bounded
    (``max_feature_delta``) code-conditioned delta to their shared features, so a new face's code can carry its
    iris colour; off, every identity gets the same eyes."""
    eyeball_colours: bool = False
    """the eye Gaussians' RGB channels (0..2) from :class:`train.model.fields.EyeballColours`, a pupil, an iris and a
    sclera by each Gaussian's polar angle from its eye's canonical optical axis (-z), instead of a free colour
    per Gaussian; their other channels stay free. Excludes ``eye_appearance`` (both would set the eye colours)."""
    field_input: str = "position"
    """what the face field's MLPs read per Gaussian beside their condition (τ or PE(γ)): ``position``, PE(x) for
    every delta; ``feature``, GazeGaussian's form: PE(x) for Δposition, tanh(z₀) (the Gaussian's canonical
    feature, ``face_features``) for Δfeature, Δlog-scale, Δrotation and Δopacity
    (:class:`train.model.fields.FaceDeformationField`)."""
    eye_field_terms: bool = False
    """gaze-driven deltas of the eye Gaussians' features, log-scales and opacities from their canonical features
    and the gaze (:class:`train.model.fields.EyeGazeAppearanceField`), bounded like the face field's
    (``max_feature_delta``, ``max_log_scale_delta``, ``max_opacity_delta``); zero at initialization. Added after
    ``eye_appearance``'s delta; with ``eyeball_colours`` the RGB channels stay parametric and the term moves the
    other channels, the scales and the opacities."""
    render_scale: float = 0.25
    num_images: int = 0
    """> 0 adds per-training-image learnable codes and camera offsets (auto-decoder)."""
    cache_face: bool = True

    @property
    def code_dim(self) -> int:
        """The width of the code τ: identity + expression."""
        return self.identity_dim + self.expression_dim

    def code_parts(self, code):
        """(identity, expression) parts of codes [..., code_dim] (arrays or tensors), at the stored widths."""
        return code[..., :self.identity_dim], code[..., self.identity_dim:self.code_dim]

    def validate(self) -> None:
        """ToolkitError on values no model can be built with (the cross-field rules included)."""
        for name in ("identity_dim", "expression_dim"):
            v = getattr(self, name)
            if not isinstance(v, int) or isinstance(v, bool) or v < 1:
                raise ToolkitError(f"GaussianModelConfig.{name}: expected a code width >= 1, got {v!r}")
        for name, low, what in (("feature_dim", 3, "a channel count >= 3 (the first three are RGB)"),
                                ("hidden", 1, "a layer width >= 1"), ("depth", 1, "a layer count >= 1"),
                                ("pos_freqs", 0, "a frequency count >= 0"), ("pose_freqs", 0, "a frequency count >= 0"),
                                ("gaze_freqs", 0, "a frequency count >= 0"),
                                ("num_images", 0, "an image count >= 0 (0: no per-image codes)")):
            v = getattr(self, name)
            if not isinstance(v, numbers.Integral) or isinstance(v, bool) or v < low:
                raise ToolkitError(f"GaussianModelConfig.{name}: expected {what}, got {v!r}")
        if self.pose_dim != 6 or isinstance(self.pose_dim, bool):
            raise ToolkitError(f"GaussianModelConfig.pose_dim: expected 6 (axis-angle 3 + translation 3), "
                               f"got {self.pose_dim!r}")
        for name in ("near_m", "far_m", "socket_sigma_m", "max_offset", "max_log_scale_delta", "max_opacity_delta",
                     "max_feature_delta", "max_eye_residual"):
            v = getattr(self, name)
            if isinstance(v, bool) or not is_finite_number(v):
                raise ToolkitError(f"GaussianModelConfig.{name}: expected a finite number, got {v!r}")
        for name in ("max_offset", "max_log_scale_delta", "max_opacity_delta", "max_feature_delta", "max_eye_residual"):
            if getattr(self, name) < 0:
                raise ToolkitError(f"GaussianModelConfig.{name}: expected a bound >= 0, got {getattr(self, name)!r}")
        if self.near_m < 0 or self.far_m <= self.near_m:
            raise ToolkitError(f"GaussianModelConfig: need 0 <= near_m < far_m, got near_m={self.near_m}, far_m={self.far_m}")
        if not 0 < self.render_scale <= 1:
            raise ToolkitError(f"GaussianModelConfig.render_scale: expected (0, 1], got {self.render_scale}")
        if self.socket_sigma_m <= 0:
            raise ToolkitError(f"GaussianModelConfig.socket_sigma_m: expected > 0 metres, got {self.socket_sigma_m}")
        if self.field_input not in FIELD_INPUTS:
            raise ToolkitError(f"GaussianModelConfig.field_input: expected one of {list(FIELD_INPUTS)}, "
                               f"got {self.field_input!r}")
        if self.eyeball_colours and self.eye_appearance:
            raise ToolkitError("GaussianModelConfig: eyeball_colours and eye_appearance both set the eye Gaussians' "
                               "colours; enable one of them")
