"""The two-stream Gaussian model of DiT-Gaze (GazeGaussian's, with its eye-rotation bugs fixed).

Face stream: canonical face Gaussians (part 0) deformed by :class:`train.model.fields.FaceDeformationField`
(code τ [B, code_dim] = identity ++ expression, the data's widths, and head pose γ [B, 6]), blended per Gaussian by
``λτ = clamp((far − d) / (far − near), 0, 1)``, ``λγ = 1 − λτ`` where d is the distance from the canonical
Gaussian to the nearest 3D landmark; ``near`` / ``far`` are given in **metres** and converted with the scene's
``metadata["units"]`` (m, cm or mm).

Eye stream: canonical eye Gaussians (parts 1 and 2, isotropic: one log-scale each) rotated rigidly per eye
by :class:`train.model.fields.EyeRotationField` about **that eye's own eyeball centre** from
``scene.metadata["eyes"]`` (``toolkit.eyes.eyeball_info``); left and right eyes use their own Gaussians and
centres. Gaze φ [B, 2] is (pitch, yaw) in the head frame. Their features are shared by every identity, or,
with ``eye_appearance``, shifted per code by :class:`train.model.fields.EyeAppearanceField`; with ``eye_field_terms``
their features, scales and opacities also follow the gaze (:class:`train.model.fields.EyeGazeAppearanceField`); with
``eyeball_colours`` their RGB channels come from a parametric pupil / iris / sclera
(:class:`train.model.fields.EyeballColours`). The face field reads each Gaussian's position, or with
``field_input="feature"`` its canonical feature for every delta but Δposition (GazeGaussian's form).

Then the rigid head transform ``x_world = R(γ[:3]) x + γ[3:]`` (γ[:3] axis-angle radians, γ[3:] translation in
scene units), optional per-image camera offsets, and splatting with ``render.splat.rasterize`` into
``feature_dim``-channel maps (default 32) at ``render_scale`` (default 1/4) of the output size, for the whole
head, the face only and the eyes only. Channels 0..2 are also an RGB image (white background; the other
channels have background 0).

Skipping work: the face stream's output is cached on its inputs (effective code, pose, parameter versions,
grad/autocast mode), so changing only the gaze reuses it; renders not listed in ``renders`` are not made.
Under grad mode a cache hit shares the autograd graph of the first call: sum the losses and call backward
once per step (the cache is invalidated automatically when the optimizer updates the parameters).

The configuration is :class:`train.model.gaussian_config.GaussianModelConfig`; scenes and checkpoint files in
and out go through :mod:`train.model.gaussian_io`.
"""

from __future__ import annotations

import math
from typing import Callable, Sequence

import torch
import torch.nn as nn

from toolkit.cameras import resize_intrinsics
from toolkit.errors import ToolkitError
from toolkit.rotations import matrix_to_quat, normalize_quat, quat_multiply, so3_exp
from toolkit.scene import GaussianScene
from train.model.fields import (
    EyeAppearanceField,
    EyeballColours,
    EyeGazeAppearanceField,
    EyeRotationField,
    FaceDeformationField,
)
from train.model.gaussian_config import GaussianModelConfig
from train.model.gaussian_io import checkpoint_metadata, posed_scene, read_checkpoint, streams_from_scene

RENDERS = ("head", "face", "eyes")


class GaussianModel(nn.Module):
    """Two-stream Gaussian head. Build with :meth:`from_scene`; call :meth:`forward` to render feature maps."""

    def __init__(self, config: GaussianModelConfig, face: dict[str, torch.Tensor], eyes: dict[str, torch.Tensor],
                 eye_centers: torch.Tensor, landmarks: torch.Tensor, units_per_metre: float = 1.0,
                 rasterizer: Callable | None = None):
        super().__init__()
        cfg = self.config = config
        cfg.validate()
        self.face_means = nn.Parameter(face["means"].float().clone())
        self.face_quats = nn.Parameter(face["quats"].float().clone())
        self.face_log_scales = nn.Parameter(face["log_scales"].float().clone())
        self.face_opacity_logits = nn.Parameter(face["opacity_logits"].float().clone())
        self.face_features = nn.Parameter(face["features"].float().clone())
        self.eye_means = nn.Parameter(eyes["means"].float().clone())
        self.eye_log_scales = nn.Parameter(eyes["log_scales"].float().clone())  # [Ne] isotropic
        self.eye_opacity_logits = nn.Parameter(eyes["opacity_logits"].float().clone())
        self.eye_features = nn.Parameter(eyes["features"].float().clone())
        self.register_buffer("eye_side", eyes["side"].long().clone())  # [Ne] 0 = left eye, 1 = right eye
        self.register_buffer("eye_centers", eye_centers.float().clone())  # [2, 3]
        self.register_buffer("landmarks", landmarks.float().clone())  # [L, 3]
        all_means = torch.cat([face["means"], eyes["means"]]).float()
        center = all_means.mean(0)
        self.register_buffer("norm_center", center)
        self.register_buffer("norm_scale", (all_means - center).norm(dim=-1).max().clamp_min(1e-6))
        self.units_per_metre = float(units_per_metre)
        d2 = torch.cdist(eye_centers.float(), face["means"].float()).square()  # [2, Nf]
        sigma = cfg.socket_sigma_m * self.units_per_metre
        # softmax: well defined however far the nearest face Gaussian is (no empty neighbourhood).
        self.register_buffer("socket_weights", torch.softmax(-d2 / (2 * sigma ** 2), dim=-1))
        self.face_field = FaceDeformationField(cfg.feature_dim, cfg.code_dim, cfg.pose_dim, cfg.hidden, cfg.depth,
                                               cfg.pos_freqs, cfg.pose_freqs, cfg.field_input)
        self.eye_field = EyeRotationField(cfg.code_dim, cfg.hidden, cfg.depth, cfg.gaze_freqs, cfg.max_eye_residual)
        if cfg.eye_appearance:
            self.eye_appearance = EyeAppearanceField(cfg.feature_dim, cfg.code_dim, cfg.hidden, cfg.depth,
                                                     cfg.pos_freqs)
            # Each eye's largest Gaussian distance from its centre at construction (the front cap reaches the
            # eyeball's radius): the field's positions are in these units.
            r = (eyes["means"].float() - eye_centers.float()[eyes["side"].long()]).norm(dim=-1)
            radius = torch.stack([r[eyes["side"] == k].max() if bool((eyes["side"] == k).any()) else r.new_tensor(1.0)
                                  for k in (0, 1)])
            self.register_buffer("eye_radius", radius.clamp_min(1e-6))
        else:
            self.eye_appearance = None
        self.eyeball_colours = EyeballColours() if cfg.eyeball_colours else None
        self.eye_gaze_terms = (EyeGazeAppearanceField(cfg.feature_dim, cfg.hidden, cfg.depth, cfg.gaze_freqs)
                               if cfg.eye_field_terms else None)
        if cfg.num_images > 0:
            self.image_codes = nn.Embedding(cfg.num_images, cfg.code_dim)
            self.camera_offsets = nn.Embedding(cfg.num_images, 6)
            nn.init.zeros_(self.image_codes.weight)
            nn.init.zeros_(self.camera_offsets.weight)
        else:
            self.image_codes = self.camera_offsets = None
        self._rasterizer = rasterizer
        self._face_cache: tuple | None = None
        self.cache_hits = 0
        self.cache_misses = 0

    # ------------------------------------------------------------------ construction
    @classmethod
    def from_scene(cls, scene: GaussianScene, config: GaussianModelConfig | None = None,
                   landmarks: torch.Tensor | None = None, rasterizer: Callable | None = None) -> "GaussianModel":
        """Initialize from a GaussianScene with part labels and eyeball centres (``metadata["eyes"]``).

        Features are lifted to ``config.feature_dim``: the scene's first min(D, feature_dim) channels are
        copied (RGB scenes fill channels 0..2), the rest start at 0. Landmarks [L, 3] come from the argument,
        else ``scene.metadata["landmarks"]``, else the two eyeball centres (then only the eye region is
        expression-driven; pass landmarks for brows/mouth).
        """
        cfg = config or GaussianModelConfig()
        cfg.validate()  # before the streams are built at its sizes
        if landmarks is not None and not bool(torch.isfinite(torch.as_tensor(landmarks)).all()):
            raise ToolkitError("GaussianModel.from_scene: landmarks contain NaN/inf")
        return cls(cfg, *streams_from_scene(scene, cfg, landmarks), rasterizer)

    # ------------------------------------------------------------------ helpers
    @property
    def num_face(self) -> int:
        return int(self.face_means.shape[0])

    @property
    def num_eye(self) -> int:
        return int(self.eye_means.shape[0])

    def orthogonality_layers(self) -> tuple[nn.Linear, nn.Linear, nn.Linear]:
        """(gaze MLP first layer, pose MLP first layer, expression MLP first layer) for ``OrthogonalityLoss``."""
        return self.eye_field.mlp.first, self.face_field.pose_mlp.first, self.face_field.expr_mlp.first

    def expression_weights(self) -> torch.Tensor:
        """[Nf] λτ of each face Gaussian from its canonical distance to the nearest landmark."""
        with torch.no_grad():
            d = torch.cdist(self.face_means.detach().float(), self.landmarks).min(1).values / self.units_per_metre
            return ((self.config.far_m - d) / (self.config.far_m - self.config.near_m)).clamp(0, 1)

    def effective_code(self, code: torch.Tensor, image_index: torch.Tensor | None) -> torch.Tensor:
        if image_index is None:
            return code
        if self.image_codes is None:
            raise ToolkitError("image_index given but the model has no per-image codes (config.num_images = 0)")
        return code + self.image_codes(image_index.long())

    def _check_image_index(self, image_index: torch.Tensor | None, B: int) -> None:
        """ToolkitError unless ``image_index`` is None or [B] indices of this model's per-image codes."""
        if image_index is None:
            return
        if self.image_codes is None:
            raise ToolkitError("image_index given but the model has no per-image codes (config.num_images = 0)")
        n = self.config.num_images
        if image_index.shape != (B,):
            raise ToolkitError(f"image_index: expected [B={B}] training-image indices, got {list(image_index.shape)}")
        bad = (image_index < 0) | (image_index >= n)
        if bool(bad.any()):
            raise ToolkitError(f"image_index: expected indices in [0, {n}) (config.num_images = {n}), got "
                               f"{image_index[bad].tolist()[:8]}")

    def clear_cache(self) -> None:
        self._face_cache = None

    def _check_inputs(self, code, pose, gaze=None) -> None:
        cfg = self.config
        if code.dim() != 2 or code.shape[1] != cfg.code_dim:
            raise ToolkitError(f"code: expected [B, {cfg.code_dim}] ({cfg.identity_dim} identity + {cfg.expression_dim} "
                               f"expression, the widths of the data the model was built for), got {list(code.shape)}")
        B = code.shape[0]
        if pose.shape != (B, cfg.pose_dim):
            raise ToolkitError(f"pose: expected [B={B}, {cfg.pose_dim}], got {list(pose.shape)}")
        if gaze is not None and gaze.shape != (B, 2):
            raise ToolkitError(f"gaze: expected [B={B}, 2] (pitch, yaw), got {list(gaze.shape)}")

    # ------------------------------------------------------------------ streams
    def _face_params(self) -> list[torch.Tensor]:
        ps = [self.face_means, self.face_quats, self.face_log_scales, self.face_opacity_logits, self.face_features]
        ps += list(self.face_field.parameters())
        if self.image_codes is not None:
            ps.append(self.image_codes.weight)
        return ps

    def face_stream(self, code: torch.Tensor, pose: torch.Tensor) -> dict[str, torch.Tensor]:
        """Deformed face Gaussians in the head frame (before the rigid head transform), cached on the inputs.

        code [B, C] (effective), pose [B, 6] -> {"means" [B, Nf, 3], "quats" [B, Nf, 4], "scales" [B, Nf, 3],
        "opacities" [B, Nf], "features" [B, Nf, D]}.
        """
        cfg = self.config
        key = (tuple(p._version for p in self._face_params()), torch.is_grad_enabled(),
               torch.is_autocast_enabled("cpu"), torch.get_autocast_dtype("cpu"),
               torch.is_autocast_enabled("cuda") if code.is_cuda else False)
        if cfg.cache_face and self._face_cache is not None:
            k, c, p, out = self._face_cache
            if k == key and c.shape == code.shape and p.shape == pose.shape and c.device == code.device \
                    and torch.equal(c, code.detach()) and torch.equal(p, pose.detach()):
                self.cache_hits += 1
                return out
        self.cache_misses += 1
        x_norm = (self.face_means - self.norm_center) / self.norm_scale
        pose_norm = torch.cat([pose[:, :3] / math.pi, pose[:, 3:] / self.norm_scale], -1)
        d = self.face_field(x_norm, code, pose_norm, self.expression_weights(), self.face_features)
        d = {k: v.float() for k, v in d.items()}
        means = self.face_means + cfg.max_offset * self.norm_scale * torch.tanh(d["pos"])
        dq = torch.cat([torch.ones_like(d["rot"][..., :1]), 0.5 * d["rot"]], -1)
        quats = quat_multiply(normalize_quat(dq), normalize_quat(self.face_quats).expand_as(dq))
        scales = torch.exp(self.face_log_scales + cfg.max_log_scale_delta * torch.tanh(d["log_scale"]))
        opacities = torch.sigmoid(self.face_opacity_logits + cfg.max_opacity_delta * torch.tanh(d["opacity"][..., 0]))
        features = self.face_features + cfg.max_feature_delta * torch.tanh(d["feature"])
        out = {"means": means, "quats": quats, "scales": scales, "opacities": opacities, "features": features}
        if cfg.cache_face:
            self._face_cache = (key, code.detach().clone(), pose.detach().clone(), out)
        return out

    def socket_shift(self, face: dict[str, torch.Tensor]) -> torch.Tensor:
        """[B, 2, 3] head-frame displacement of each eye socket (left, right) by the deformed face stream
        ``face`` (:meth:`face_stream` output): the ``socket_weights``-weighted mean Δposition."""
        return torch.einsum("en,bnc->bec", self.socket_weights, face["means"] - self.face_means)

    def eye_polar_angles(self) -> torch.Tensor:
        """[Ne] angle (radians) of each canonical eye Gaussian from its eye's optical axis (-z, the canonical
        gaze) about that eye's centre; atan2 rather than acos, exact near the axis. Detached: the colours it
        selects never pull the Gaussians along the eyeball."""
        d = (self.eye_means.detach() - self.eye_centers[self.eye_side]).float()
        return torch.atan2(d[:, :2].norm(dim=-1), -d[:, 2])

    def eye_stream(self, code: torch.Tensor, gaze: torch.Tensor, shift: torch.Tensor | None = None) -> dict[str, torch.Tensor]:
        """Eye Gaussians rotated per eye about their own centres, head frame.

        code [B, C], gaze [B, 2], shift [B, 2, 3] or None (a translation per eye, applied after the rotation
        with the centre: :meth:`socket_shift`) -> {"means" [B, Ne, 3], "quats" [B, Ne, 4], "scales" [B, Ne, 3],
        "opacities" [B, Ne], "features" [B, Ne, D], "rotations" [B, 2, 3, 3] (left, right)}.
        """
        B = code.shape[0]
        R = self.eye_field(gaze.float(), code)  # [B, 2, 3, 3]
        Rg = R[:, self.eye_side]  # [B, Ne, 3, 3]: each Gaussian takes its own eye's rotation
        c = self.eye_centers[self.eye_side]  # [Ne, 3]: ... and its own eye's centre
        means = torch.einsum("bnij,bnj->bni", Rg, (self.eye_means - c).expand(B, -1, -1)) + c
        if shift is not None:
            means = means + shift.to(means.dtype)[:, self.eye_side]
        quats = matrix_to_quat(R)[:, self.eye_side]  # eye Gaussians are isotropic: canonical rotation = identity
        ne = self.num_eye
        scales = torch.exp(self.eye_log_scales)[None, :, None].expand(B, ne, 3)
        opacities = torch.sigmoid(self.eye_opacity_logits)[None].expand(B, ne)
        features = self.eye_features[None].expand(B, ne, -1)
        if self.eye_appearance is not None:
            # Detached: a colour loss recolours the eyes through the field but never moves their Gaussians.
            x_eye = (self.eye_means.detach() - c) / self.eye_radius[self.eye_side, None]
            d = self.eye_appearance(x_eye, self.eye_side, code).float()
            features = features + self.config.max_feature_delta * torch.tanh(d)
        if self.eye_gaze_terms is not None:
            scales, opacities, features = self._gaze_terms(gaze, features)
        if self.eyeball_colours is not None:
            rgb = self.eyeball_colours(self.eye_polar_angles()).to(features.dtype)
            features = torch.cat([rgb[None].expand(B, -1, -1), features[..., 3:]], -1)
        return {"means": means, "quats": quats, "scales": scales, "opacities": opacities, "features": features,
                "rotations": R}

    def _gaze_terms(self, gaze: torch.Tensor, features: torch.Tensor) -> tuple[torch.Tensor, ...]:
        """(scales [B, Ne, 3], opacities [B, Ne], features [B, Ne, D]) of the eye Gaussians with the bounded
        gaze-driven deltas of ``eye_gaze_terms`` (config ``eye_field_terms``) applied; ``features`` [B, Ne, D]
        are the eye features before them."""
        cfg, ne = self.config, self.num_eye
        t = {k: v.float() for k, v in self.eye_gaze_terms(self.eye_features, gaze.float()).items()}
        log_scales = self.eye_log_scales + cfg.max_log_scale_delta * torch.tanh(t["log_scale"])
        scales = torch.exp(log_scales)[..., None].expand(-1, ne, 3)
        opacities = torch.sigmoid(self.eye_opacity_logits + cfg.max_opacity_delta * torch.tanh(t["opacity"]))
        return scales, opacities, features + cfg.max_feature_delta * torch.tanh(t["feature"])

    def gaussians(self, code: torch.Tensor, pose: torch.Tensor, gaze: torch.Tensor,
                  image_index: torch.Tensor | None = None) -> dict[str, dict[str, torch.Tensor]]:
        """Both streams after the rigid head transform (world frame): {"face": {...}, "eyes": {...}}."""
        self._check_inputs(code, pose, gaze)
        self._check_image_index(image_index, code.shape[0])
        code = self.effective_code(code, image_index)
        face = self.face_stream(code, pose)
        return {"face": self._posed(face, pose), "eyes": self._posed(self._eyes(code, gaze, face), pose)}

    def _eyes(self, code: torch.Tensor, gaze: torch.Tensor, face: dict[str, torch.Tensor] | None) -> dict[str, torch.Tensor]:
        """The eye stream, moved with the sockets of ``face`` when ``config.eyes_follow_face``."""
        if not self.config.eyes_follow_face:
            return self.eye_stream(code, gaze)
        return self.eye_stream(code, gaze, self.socket_shift(face))

    # ------------------------------------------------------------------ rendering
    def _rasterize(self):
        if self._rasterizer is None:
            from render.splat import rasterize

            self._rasterizer = rasterize
        return self._rasterizer

    def camera_viewmats(self, viewmats: torch.Tensor, image_index: torch.Tensor | None) -> torch.Tensor:
        """[B, 4, 4] world-to-camera with the per-image learnable offsets applied (viewmat · T(offset))."""
        if image_index is None or self.camera_offsets is None:
            return viewmats
        off = self.camera_offsets(image_index.long())  # [B, 6] axis-angle + translation
        T = torch.eye(4, dtype=viewmats.dtype, device=viewmats.device).repeat(off.shape[0], 1, 1)
        T[:, :3, :3] = so3_exp(off[:, :3])
        T[:, :3, 3] = off[:, 3:]
        return viewmats @ T

    def forward(self, code: torch.Tensor, pose: torch.Tensor, gaze: torch.Tensor, viewmats: torch.Tensor,
                Ks: torch.Tensor, width: int, height: int, *, image_index: torch.Tensor | None = None,
                renders: Sequence[str] = RENDERS) -> dict[str, torch.Tensor]:
        """Render feature maps.

        Args:
            code [B, code_dim] τ; pose [B, 6] γ; gaze [B, 2] head-frame (pitch, yaw) radians;
            viewmats [B, 4, 4] world-to-camera; Ks [B, 3, 3] for the **output** size ``width`` × ``height``;
            image_index [B] long (auto-decoder codes/offsets) or None; renders: subset of ("head", "face", "eyes").
        Returns:
            for each requested name r: ``r`` [B, D, h, w] feature map and ``r + "_alpha"`` [B, 1, h, w], where
            h, w = round(render_scale · height), round(render_scale · width); plus "rgb" [B, 3, h, w] =
            head[:, :3] when "head" is rendered.
        """
        bad = [r for r in renders if r not in RENDERS]
        if bad:
            raise ToolkitError(f"renders: unknown name(s) {bad}; expected a subset of {list(RENDERS)}")
        B = code.shape[0]
        if viewmats.shape != (B, 4, 4) or Ks.shape != (B, 3, 3):
            raise ToolkitError(f"viewmats/Ks: expected [B={B}, 4, 4] and [B, 3, 3], got {list(viewmats.shape)} and {list(Ks.shape)}")
        if B < 1 and renders:
            raise ToolkitError(f"code: expected at least one camera to render (B >= 1), got {list(code.shape)}")
        if not (width >= 1 and height >= 1):
            raise ToolkitError(f"width/height: expected an output size >= 1 pixel each, got {width!r} x {height!r}")
        self._check_image_index(image_index, B)
        w = max(1, round(width * self.config.render_scale))
        h = max(1, round(height * self.config.render_scale))
        Ks_r = resize_intrinsics(Ks.float(), width, height, w, h)
        vm = self.camera_viewmats(viewmats.float(), image_index)
        need_face = any(r in renders for r in ("head", "face"))
        need_eyes = any(r in renders for r in ("head", "eyes"))
        if not (need_face or need_eyes):
            return {}
        self._check_inputs(code, pose, gaze)
        ce = self.effective_code(code, image_index)
        # Evaluate only the streams some requested render needs.
        g = {}
        # Eyes that follow the face need the face stream (cached) even for an eyes-only render.
        face = self.face_stream(ce, pose) if need_face or self.config.eyes_follow_face else None
        if need_face:
            g["face"] = self._posed(face, pose)
        if need_eyes:
            g["eyes"] = self._posed(self._eyes(ce, gaze, face), pose)
        bg = torch.zeros(self.config.feature_dim, device=vm.device)
        bg[:3] = 1.0
        out: dict[str, torch.Tensor] = {}
        for r in renders:
            parts = [g["face"], g["eyes"]] if r == "head" else [g[r]]
            # Sample b's posed Gaussians go to camera b: the whole batch is one rasterize call (one tile sweep).
            cat = {k: torch.cat([p[k].float() for p in parts], 1) for k in ("means", "quats", "scales", "opacities",
                                                                             "features")}
            # Splatting runs in float32 even under autocast: depth sorting, conics and transmittance
            # products lose too much in bf16, and the splatter's kernels expect one dtype.
            with torch.autocast(device_type=vm.device.type, enabled=False):
                img, alpha, _ = self._rasterize()(cat["means"], cat["quats"], cat["scales"], cat["opacities"],
                                                  cat["features"], vm, Ks_r, w, h, backgrounds=bg)
            out[r] = img.permute(0, 3, 1, 2)
            out[r + "_alpha"] = alpha.permute(0, 3, 1, 2)
        if "head" in out:
            out["rgb"] = out["head"][:, :3]
        return out

    def _posed(self, s: dict[str, torch.Tensor], pose: torch.Tensor) -> dict[str, torch.Tensor]:
        Rh = so3_exp(pose[:, :3].float())
        out = dict(s)
        out["means"] = torch.einsum("bij,bnj->bni", Rh, s["means"]) + pose[:, None, 3:].float()
        out["quats"] = quat_multiply(matrix_to_quat(Rh)[:, None].expand_as(s["quats"]), s["quats"])
        return out

    # ------------------------------------------------------------------ storage
    def save(self, path, info: dict | None = None) -> None:
        """Write all parameters and buffers (safetensors) with the config as JSON metadata (atomic)."""
        from toolkit.io import save_checkpoint

        save_checkpoint(path, self.state_dict(), checkpoint_metadata(self.config, self.units_per_metre, info))

    @classmethod
    def load(cls, path, device: str | torch.device = "cpu", rasterizer: Callable | None = None) -> "GaussianModel":
        """Rebuild a model written by :meth:`save`; foreign or incompatible files raise ``ToolkitError``."""
        raw, face, eyes, state, units_per_metre = read_checkpoint(path)
        try:
            model = cls(GaussianModelConfig(**raw), face, eyes, state["eye_centers"], state["landmarks"],
                        units_per_metre, rasterizer)
        except (TypeError, ValueError, RuntimeError, ToolkitError) as e:  # a config value out of range, say
            raise ToolkitError(f"{path}: cannot build the model from its config and tensors "
                               f"({str(e).splitlines()[0][:160]})") from None
        # Checkpoints written before socket_weights existed: the buffer recomputed from their means.
        state.setdefault("socket_weights", model.socket_weights)
        try:
            result = model.load_state_dict(state, strict=False)
        except RuntimeError as e:  # a shape mismatch: its first detail line names the tensor
            detail = [ln.strip() for ln in str(e).splitlines() if ln.strip()][1:2] or [str(e)]
            raise ToolkitError(f"{path}: tensors do not match the stored config ({detail[0][:160]})") from None
        if result.missing_keys or result.unexpected_keys:
            raise ToolkitError(f"{path}: tensors do not match the stored config (missing {result.missing_keys[:4]}, "
                               f"unexpected {result.unexpected_keys[:4]})")
        return model.to(device)

    # ------------------------------------------------------------------ export
    def export_scene(self, code: torch.Tensor, pose: torch.Tensor, gaze: torch.Tensor, index: int = 0) -> GaussianScene:
        """Sample ``index`` of a batch as a world-frame GaussianScene (neural features, part labels), for previews."""
        with torch.no_grad():
            g = self.gaussians(code, pose, gaze)
        return posed_scene(g["face"], g["eyes"], self.eye_side, index, self.units_per_metre, self.config)
