"""Where the canonical tensors of the Gaussian model (:class:`train.model.gaussian_model.GaussianModel`) come
from and go to: a part-labelled :class:`toolkit.scene.GaussianScene` (split into the face and eye streams),
a safetensors checkpoint (its metadata and the checks a stored file must pass), and a posed scene for previews.

The streams, as the model's constructor takes them: ``face`` {"means" [Nf, 3], "quats" [Nf, 4], "log_scales"
[Nf, 3], "opacity_logits" [Nf], "features" [Nf, D]}; ``eyes`` {"means" [Ne, 3], "log_scales" [Ne] (isotropic),
"opacity_logits" [Ne], "features" [Ne, D], "side" [Ne] (0 = left, 1 = right)}; ``eye_centers`` [2, 3] (left,
right); ``landmarks`` [L, 3].
"""

from __future__ import annotations

from dataclasses import asdict

import torch

from toolkit.errors import ToolkitError
from toolkit.eyes import EYE_PARTS, eyeball_info
from toolkit.rotations import normalize_quat
from toolkit.scene import PART_FACE, GaussianScene
from train.model.gaussian_config import UNITS_PER_METRE, GaussianModelConfig

CHECKPOINT_KIND = "ditgaze.gaussian_model"
FACE_TENSORS = ("face_means", "face_quats", "face_log_scales", "face_opacity_logits", "face_features")
EYE_TENSORS = ("eye_means", "eye_log_scales", "eye_opacity_logits", "eye_features")

Streams = dict[str, torch.Tensor]


def streams_from_scene(scene: GaussianScene, cfg: GaussianModelConfig, landmarks: torch.Tensor | None
                       ) -> tuple[Streams, Streams, torch.Tensor, torch.Tensor, float]:
    """``(face, eyes, eye_centers, landmarks, units_per_metre)`` of a scene with part labels and eyeball centres
    (``metadata["eyes"]``); see :meth:`train.model.gaussian_model.GaussianModel.from_scene`."""
    scene = scene.detach().to("cpu")
    scene.validate()
    units = scene.metadata.get("units", "m")
    if units not in UNITS_PER_METRE:
        raise ToolkitError(f"scene.metadata['units']: expected one of {sorted(UNITS_PER_METRE)}, got {units!r}")
    face_mask = scene.part == PART_FACE
    if not bool(face_mask.any()):
        raise ToolkitError("scene: has no face Gaussians (part 0); the face stream needs some")
    info = eyeball_info(scene)
    missing = [n for n in EYE_PARTS if n not in info]
    if missing:
        raise ToolkitError(f"scene: has no Gaussians for eye(s) {missing} (parts 1 = left, 2 = right)")

    def lift(f: torch.Tensor) -> torch.Tensor:
        out = torch.zeros(f.shape[0], cfg.feature_dim, dtype=torch.float32)
        k = min(f.shape[1], cfg.feature_dim)
        out[:, :k] = f[:, :k]
        return out

    face = {"means": scene.means[face_mask], "quats": normalize_quat(scene.quats[face_mask]),
            "log_scales": scene.log_scales[face_mask], "opacity_logits": scene.opacity_logits[face_mask],
            "features": lift(scene.features[face_mask])}
    eye_mask = ~face_mask
    eye_part = scene.part[eye_mask].long()
    eyes = {"means": scene.means[eye_mask], "log_scales": scene.log_scales[eye_mask].mean(-1),
            "opacity_logits": scene.opacity_logits[eye_mask], "features": lift(scene.features[eye_mask]),
            "side": (eye_part == EYE_PARTS["right"]).long()}
    centers = torch.stack([info["left"]["center"], info["right"]["center"]]).float()
    if landmarks is None and "landmarks" in scene.metadata:
        landmarks = torch.tensor(scene.metadata["landmarks"], dtype=torch.float32)
    if landmarks is None:
        landmarks = centers
    landmarks = torch.as_tensor(landmarks, dtype=torch.float32)
    if landmarks.dim() != 2 or landmarks.shape[1] != 3 or landmarks.shape[0] < 1:
        raise ToolkitError(f"landmarks: expected shape [L, 3], got {list(landmarks.shape)}")
    return face, eyes, centers, landmarks, UNITS_PER_METRE[units]


def checkpoint_metadata(config: GaussianModelConfig, units_per_metre: float, info: dict | None) -> dict:
    """The JSON metadata a model checkpoint carries: its kind, the config, the scene units, then ``info``."""
    meta = {"kind": CHECKPOINT_KIND, "version": 1, "config": asdict(config), "units_per_metre": units_per_metre}
    meta.update(info or {})
    return meta


def read_checkpoint(path) -> tuple[dict, Streams, Streams, dict[str, torch.Tensor], float]:
    """``(raw config dict, face, eyes, state, units_per_metre)`` of a file written by
    :meth:`train.model.gaussian_model.GaussianModel.save`, its kind, config keys, tensor names and shapes
    checked; ``state`` (all stored tensors) also holds ``eye_centers`` and ``landmarks``."""
    from toolkit.io import load_checkpoint

    state, info = load_checkpoint(path)
    if info.get("kind") != CHECKPOINT_KIND:
        raise ToolkitError(f"{path}: not a Gaussian model checkpoint (kind={info.get('kind')!r})")
    raw = info.get("config")
    if isinstance(raw, dict) and "code_dim" in raw:  # written before the code's widths were stored: 80 + 64
        raw = dict(raw)
        old = raw.pop("code_dim")
        base = GaussianModelConfig()
        if old != raw.get("identity_dim", base.identity_dim) + raw.get("expression_dim", base.expression_dim):
            raise ToolkitError(f"{path}: config code_dim={old!r} disagrees with its identity and expression widths")
    if not isinstance(raw, dict) or set(raw) - set(GaussianModelConfig.__dataclass_fields__):
        raise ToolkitError(f"{path}: missing or unknown Gaussian model config fields")
    need = [*FACE_TENSORS, *EYE_TENSORS, "eye_side", "eye_centers", "landmarks"]
    missing = [k for k in need if k not in state]
    if missing:
        raise ToolkitError(f"{path}: missing tensor(s) {missing}")
    _check_stored_shapes(path, state)
    face = {k[5:]: state[k] for k in FACE_TENSORS}
    eyes = {k[4:]: state[k] for k in EYE_TENSORS}
    eyes["side"] = state["eye_side"]
    return raw, face, eyes, state, float(info.get("units_per_metre", 1.0))


def _check_stored_shapes(path, state: dict[str, torch.Tensor]) -> None:
    """The stored Gaussians agree with each other: the face tensors share one count Nf, the eye tensors and
    ``eye_side`` one count Ne, ``eye_centers`` is [2, 3] and ``landmarks`` [L, 3]."""
    def rows(keys, trailing):
        n = None
        for k, tail in zip(keys, trailing, strict=True):
            t = state[k]
            ok = t.dim() == 1 + len(tail) and all(a is None or a == b for a, b in zip(tail, t.shape[1:]))
            if not ok or (n is not None and t.shape[0] != n):
                want = "[" + ", ".join(["N"] + ["*" if a is None else str(a) for a in tail]) + "]"
                raise ToolkitError(f"{path}: tensor '{k}' has shape {list(t.shape)}, expected {want}"
                                   + (f" with N = {n}" if n is not None else ""))
            n = t.shape[0]

    rows(list(FACE_TENSORS), [(3,), (4,), (3,), (), (None,)])
    rows([*EYE_TENSORS, "eye_side"], [(3,), (), (), (None,), ()])  # eye Gaussians are isotropic: one log-scale each
    for k, shape in (("eye_centers", (2, 3)), ("landmarks", (None, 3))):
        t = state[k]
        if t.dim() != 2 or any(a is not None and a != b for a, b in zip(shape, t.shape)):
            raise ToolkitError(f"{path}: tensor '{k}' has shape {list(t.shape)}, expected "
                               f"[{', '.join('*' if a is None else str(a) for a in shape)}]")


def posed_scene(face: Streams, eyes: Streams, eye_side: torch.Tensor, index: int, units_per_metre: float,
                config: GaussianModelConfig) -> GaussianScene:
    """Sample ``index`` of posed batched streams (``GaussianModel.gaussians`` output: "means" [B, N, 3],
    "quats", "scales", "opacities", "features") as one world-frame scene with part labels (face 0, eyes 1, 2)."""
    part = torch.cat([torch.zeros(face["means"].shape[1], dtype=torch.int8), (eye_side + 1).to(torch.int8).cpu()])
    return GaussianScene.from_activated(
        means=torch.cat([face["means"][index], eyes["means"][index]]).cpu(),
        scales=torch.cat([face["scales"][index], eyes["scales"][index]]).cpu(),
        opacities=torch.cat([face["opacities"][index], eyes["opacities"][index]]).cpu(),
        features=torch.cat([face["features"][index], eyes["features"][index]]).cpu(),
        quats=torch.cat([face["quats"][index], eyes["quats"][index]]).cpu(),
        part=part,
        metadata={"units": {v: k for k, v in UNITS_PER_METRE.items()}[units_per_metre],
                  "feature_kind": "neural", "source": "train.model.gaussian_model.GaussianModel.export_scene",
                  "config": asdict(config)},
    )
