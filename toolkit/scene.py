"""``GaussianScene``: the one Gaussian scene format every module reads and writes.

Fields are stored **pre-activation**, as in the graphdeco 3DGS PLY:

- ``means``       [N, 3] float, world units given by ``metadata["units"]``.
- ``quats``       [N, 4] float, **wxyz**, raw (any norm; normalized on use, zero -> identity).
- ``log_scales``  [N, 3] float, ``scales = exp(log_scales)``.
- ``opacity_logits`` [N] float, ``opacities = sigmoid(opacity_logits)``.
- ``features``    [N, D] float, any D: RGB in [0, 1] (``metadata["feature_kind"] == "rgb"``) or neural.
- ``sh``          optional [N, K, 3] float spherical-harmonic coefficients (K = (degree + 1)^2).
- ``part``        [N] int8: 0 face, 1 left eye, 2 right eye (the subject's left and right).
- ``metadata``    free-form JSON-able dict; ``format_version`` is managed here.

Storage: :meth:`GaussianScene.save` / :meth:`GaussianScene.load` (safetensors + JSON metadata, versioned)
and :meth:`GaussianScene.to_ply` / :meth:`GaussianScene.from_ply` (graphdeco layout, see ``toolkit.ply``).
"""

from __future__ import annotations

import math
import os
from dataclasses import dataclass, field
from typing import Any, Sequence

import torch

from toolkit.errors import ToolkitError
from toolkit.eyes import check_eyes_metadata
from toolkit.io import MAX_JSON_DEPTH, check_device, json_depth, load_tensors, save_tensors
from toolkit.ply import read_gaussian_ply, write_gaussian_ply
from toolkit.rotations import normalize_quat

FORMAT_NAME = "ditgaze.gaussian_scene"
FORMAT_VERSION = 1

PART_FACE, PART_LEFT_EYE, PART_RIGHT_EYE = 0, 1, 2
PART_NAMES = {PART_FACE: "face", PART_LEFT_EYE: "left_eye", PART_RIGHT_EYE: "right_eye"}

_FLOAT_FIELDS = ("means", "quats", "log_scales", "opacity_logits", "features")
# What every consumer computes in; float8 and other exotic safetensors dtypes load, but are refused by name.
_FLOAT_DTYPES = (torch.float16, torch.bfloat16, torch.float32, torch.float64)


@dataclass
class GaussianScene:
    """A set of N 3D Gaussians with per-Gaussian features and part labels (fields in the module doc)."""

    means: torch.Tensor
    quats: torch.Tensor
    log_scales: torch.Tensor
    opacity_logits: torch.Tensor
    features: torch.Tensor
    part: torch.Tensor | None = None
    sh: torch.Tensor | None = None
    metadata: dict[str, Any] = field(default_factory=dict)

    def __post_init__(self) -> None:
        for name in _FLOAT_FIELDS:  # shapes and values are validate()'s; an array or list fails here, by name
            if not isinstance(getattr(self, name), torch.Tensor):
                raise ToolkitError(f"GaussianScene: {name} must be a torch tensor, got {type(getattr(self, name)).__name__}"
                                   " (torch.as_tensor converts arrays)")
        if self.part is None:
            self.part = torch.zeros(self.means.shape[0] if self.means.dim() else 0, dtype=torch.int8,
                                    device=self.means.device)

    # ------------------------------------------------------------------ activated views
    @property
    def num_gaussians(self) -> int:
        return int(self.means.shape[0])

    def __len__(self) -> int:
        return self.num_gaussians

    @property
    def scales(self) -> torch.Tensor:
        """[N, 3] activated scales (standard deviations along the local axes)."""
        return torch.exp(self.log_scales)

    @property
    def opacities(self) -> torch.Tensor:
        """[N] activated opacities in (0, 1)."""
        return torch.sigmoid(self.opacity_logits)

    @property
    def unit_quats(self) -> torch.Tensor:
        """[N, 4] unit wxyz quaternions."""
        return normalize_quat(self.quats)

    @property
    def sh_degree(self) -> int | None:
        if self.sh is None:
            return None
        return int(round(math.sqrt(self.sh.shape[1]))) - 1

    @property
    def device(self) -> torch.device:
        return self.means.device

    # ------------------------------------------------------------------ validation
    def validate(self) -> "GaussianScene":
        """Raise one ``ToolkitError`` naming the first bad field (shape, dtype, NaN/inf, N mismatch)."""
        if not isinstance(self.means, torch.Tensor) or self.means.dim() != 2 or self.means.shape[1] != 3:
            raise ToolkitError(f"GaussianScene.means: expected shape [N, 3], got {_shape(self.means)}")
        n = self.means.shape[0]
        expected = {
            "quats": (n, 4),
            "log_scales": (n, 3),
            "opacity_logits": (n,),
            "part": (n,),
        }
        for name, shape in expected.items():
            t = getattr(self, name)
            if not isinstance(t, torch.Tensor) or tuple(t.shape) != shape:
                raise ToolkitError(
                    f"GaussianScene.{name}: expected shape {list(shape)} (N={n} from means), got {_shape(t)}"
                )
        if not isinstance(self.features, torch.Tensor) or self.features.dim() != 2 or self.features.shape[0] != n:
            raise ToolkitError(f"GaussianScene.features: expected shape [N={n}, D], got {_shape(self.features)}")
        if self.sh is not None:
            k = self.sh.shape[1] if self.sh.dim() == 3 else -1
            if (self.sh.dim() != 3 or self.sh.shape[0] != n or self.sh.shape[2] != 3
                    or int(round(math.sqrt(max(k, 0)))) ** 2 != k or k < 1):
                raise ToolkitError(
                    f"GaussianScene.sh: expected shape [N={n}, K=(degree+1)^2, 3], got {_shape(self.sh)}"
                )
        for name in _FLOAT_FIELDS + (("sh",) if self.sh is not None else ()):
            t = getattr(self, name)
            if t.dtype not in _FLOAT_DTYPES:
                raise ToolkitError(f"GaussianScene.{name}: expected a floating-point tensor (float16, bfloat16, "
                                   f"float32 or float64), got {t.dtype}")
            if t.numel() and not bool(torch.isfinite(t).all()):
                bad = int((~torch.isfinite(t)).any(dim=-1).sum()) if t.dim() > 1 else int((~torch.isfinite(t)).sum())
                raise ToolkitError(f"GaussianScene.{name}: {bad} Gaussian(s) have NaN or inf values")
        if self.part.dtype != torch.int8:
            raise ToolkitError(f"GaussianScene.part: expected int8 labels, got {self.part.dtype}")
        if n and bool(((self.part < 0) | (self.part > 2)).any()):
            raise ToolkitError("GaussianScene.part: labels must be 0 (face), 1 (left eye) or 2 (right eye)")
        devices = {getattr(self, f).device for f in _FLOAT_FIELDS + ("part",)}
        if len(devices) > 1:
            raise ToolkitError(f"GaussianScene: fields live on different devices {sorted(map(str, devices))}")
        _check_metadata(self.metadata)
        return self

    # ------------------------------------------------------------------ construction and selection
    @classmethod
    def from_activated(
        cls,
        means: torch.Tensor,
        scales: torch.Tensor,
        opacities: torch.Tensor,
        features: torch.Tensor,
        quats: torch.Tensor | None = None,
        part: torch.Tensor | None = None,
        metadata: dict[str, Any] | None = None,
        eps: float = 1e-8,
    ) -> "GaussianScene":
        """Build a scene from activated scales/opacities (inverted here with clamped log/logit)."""
        n = means.shape[0]
        if quats is None:
            quats = torch.zeros(n, 4, dtype=means.dtype, device=means.device)
            quats[:, 0] = 1
        # 1 - eps must differ from 1 in the opacities' own precision, or an opacity of 1 inverts to +inf.
        e = max(eps, torch.finfo(opacities.dtype).eps) if opacities.is_floating_point() else eps
        o = opacities.clamp(e, 1 - e)
        # The floor must be a positive number in the scales' precision (float16 rounds 1e-8 to 0: log gives -inf).
        floor = max(eps, torch.finfo(scales.dtype).tiny) if scales.is_floating_point() else eps
        return cls(
            means=means,
            quats=quats,
            log_scales=torch.log(scales.clamp_min(floor)),
            opacity_logits=torch.log(o) - torch.log1p(-o),
            features=features,
            part=part.to(torch.int8) if part is not None else None,
            metadata=dict(metadata or {}),
        )

    def _map(self, fn) -> "GaussianScene":
        return GaussianScene(
            means=fn(self.means), quats=fn(self.quats), log_scales=fn(self.log_scales),
            opacity_logits=fn(self.opacity_logits), features=fn(self.features), part=fn(self.part),
            sh=None if self.sh is None else fn(self.sh), metadata=_deepcopy_meta(self.metadata),
        )

    def select(self, mask: torch.Tensor) -> "GaussianScene":
        """A new scene with the Gaussians picked by a boolean mask [N] or an index tensor."""
        mask = torch.as_tensor(mask, device=self.device)
        if mask.dtype == torch.bool and tuple(mask.shape) != (self.num_gaussians,):
            raise ToolkitError(f"select: boolean mask must have shape [{self.num_gaussians}], got {list(mask.shape)}")
        return self._map(lambda t: t[mask])

    def part_mask(self, *parts: int) -> torch.Tensor:
        """[N] bool: Gaussians whose label is one of ``parts``."""
        m = torch.zeros_like(self.part, dtype=torch.bool)
        for p in parts:
            m |= self.part == p
        return m

    def to(self, device: torch.device | str) -> "GaussianScene":
        return self._map(lambda t: t.to(device))

    def clone(self) -> "GaussianScene":
        return self._map(lambda t: t.clone())

    def detach(self) -> "GaussianScene":
        return self._map(lambda t: t.detach())

    @staticmethod
    def cat(scenes: Sequence["GaussianScene"]) -> "GaussianScene":
        """Concatenate scenes with equal feature width; metadata of the first wins (eye info merged)."""
        if not scenes:
            raise ToolkitError("GaussianScene.cat: need at least one scene")
        d = {s.features.shape[1] for s in scenes}
        if len(d) != 1:
            raise ToolkitError(f"GaussianScene.cat: feature widths differ {sorted(d)}")
        has_sh = {s.sh is not None for s in scenes}
        if len(has_sh) != 1:
            raise ToolkitError("GaussianScene.cat: either all scenes have SH coefficients or none")
        if True in has_sh and len({s.sh.shape[1] for s in scenes}) != 1:
            raise ToolkitError("GaussianScene.cat: SH degrees differ")
        meta = _deepcopy_meta(scenes[0].metadata)
        for s in scenes[1:]:
            for k, v in s.metadata.items():
                meta.setdefault(k, v)
        return GaussianScene(
            means=torch.cat([s.means for s in scenes]),
            quats=torch.cat([s.quats for s in scenes]),
            log_scales=torch.cat([s.log_scales for s in scenes]),
            opacity_logits=torch.cat([s.opacity_logits for s in scenes]),
            features=torch.cat([s.features for s in scenes]),
            part=torch.cat([s.part for s in scenes]),
            sh=torch.cat([s.sh for s in scenes]) if True in has_sh else None,
            metadata=meta,
        )

    # ------------------------------------------------------------------ storage
    def tensors(self) -> dict[str, torch.Tensor]:
        out = {name: getattr(self, name) for name in _FLOAT_FIELDS + ("part",)}
        if self.sh is not None:
            out["sh"] = self.sh
        return out

    def save(self, path: str | os.PathLike) -> None:
        """Write as safetensors (atomic) with the metadata and the format version in the header."""
        self.validate()
        meta = dict(self.metadata)
        meta["format"] = FORMAT_NAME
        meta["format_version"] = FORMAT_VERSION
        save_tensors(path, self.tensors(), meta)

    @classmethod
    def load(cls, path: str | os.PathLike, device: str | torch.device = "cpu") -> "GaussianScene":
        """Read a scene written by :meth:`save`; a newer or foreign format is a clear error."""
        tensors, meta = load_tensors(path, device)
        if meta.get("format") != FORMAT_NAME:
            raise ToolkitError(f"{path}: not a GaussianScene file (format={meta.get('format')!r})")
        version = meta.get("format_version")
        if isinstance(version, bool) or not isinstance(version, int) or not 1 <= version <= FORMAT_VERSION:
            raise ToolkitError(
                f"{path}: scene format version {version!r} is not supported (this toolkit reads 1..{FORMAT_VERSION});"
                " upgrade ditgaze to read it"
            )
        missing = [k for k in _FLOAT_FIELDS + ("part",) if k not in tensors]
        if missing:
            raise ToolkitError(f"{path}: missing tensor(s) {missing}")
        scene = cls(**{k: tensors[k] for k in _FLOAT_FIELDS}, part=tensors["part"], sh=tensors.get("sh"),
                    metadata={k: v for k, v in meta.items() if k not in ("format", "format_version")})
        return scene._validated_from(path)

    def _validated_from(self, path: str | os.PathLike) -> "GaussianScene":
        """``validate()``, its error prefixed with the file the scene came from."""
        try:
            return self.validate()
        except ToolkitError as e:
            raise ToolkitError(f"{path}: {e}") from None

    def to_ply(self, path: str | os.PathLike) -> None:
        """Write the graphdeco 3DGS PLY layout (see ``toolkit.ply``), atomically."""
        self.validate()
        write_gaussian_ply(path, self.tensors(), self.metadata)

    @classmethod
    def from_ply(cls, path: str | os.PathLike, device: str | torch.device = "cpu") -> "GaussianScene":
        """Read a 3DGS PLY written by this toolkit or by other 3DGS tools."""
        check_device(device)
        tensors, meta = read_gaussian_ply(path)
        return cls(**tensors, metadata=meta)._validated_from(path).to(device)

    @classmethod
    def read(cls, path: str | os.PathLike, device: str | torch.device = "cpu") -> "GaussianScene":
        """Load ``.safetensors`` or ``.ply`` by extension."""
        ext = os.path.splitext(str(path))[1].lower()
        if ext == ".ply":
            return cls.from_ply(path, device)
        if ext == ".safetensors":
            return cls.load(path, device)
        raise ToolkitError(f"{path}: unknown scene extension {ext!r}; expected .safetensors or .ply")

    def summary(self) -> str:
        counts = {PART_NAMES[p]: int((self.part == p).sum()) for p in PART_NAMES}
        lines = [
            f"Gaussians: {self.num_gaussians}  ({', '.join(f'{k} {v}' for k, v in counts.items())})",
            f"features: D={self.features.shape[1]} ({self.metadata.get('feature_kind', 'unspecified')})"
            + (f", SH degree {self.sh_degree}" if self.sh is not None else ""),
        ]
        if self.num_gaussians:
            lo, hi = self.means.min(0).values.tolist(), self.means.max(0).values.tolist()
            lines.append("bbox: " + " ".join(f"[{a:.4g}, {b:.4g}]" for a, b in zip(lo, hi))
                         + f" {self.metadata.get('units', '')}".rstrip())
            s = self.scales
            lines.append(f"scales: min {s.min():.3g} median {s.median():.3g} max {s.max():.3g}; "
                         f"opacity mean {self.opacities.mean():.3f}")
        return "\n".join(lines)


def _check_metadata(meta: Any) -> None:
    """The metadata a file can carry and every reader takes back: a JSON object of bounded depth (as
    ``toolkit.io.parse_json_object`` reads it) whose ``eyes`` entry, if any, is valid (``toolkit.eyes``)."""
    if not isinstance(meta, dict):
        raise ToolkitError(f"GaussianScene.metadata: expected a dict, got {type(meta).__name__}")
    if json_depth(meta) > MAX_JSON_DEPTH:
        raise ToolkitError(f"GaussianScene.metadata: nested deeper than {MAX_JSON_DEPTH} levels")
    check_eyes_metadata(meta.get("eyes"), "GaussianScene.metadata.eyes")


def _shape(t: Any) -> str:
    return str(list(t.shape)) if isinstance(t, torch.Tensor) else type(t).__name__


def _deepcopy_meta(meta: dict[str, Any]) -> dict[str, Any]:
    import copy

    return copy.deepcopy(meta)
