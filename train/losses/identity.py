"""ArcFace identity similarity, the gaze-redirection metric of GazeNeRF and GazeGaussian: the cosine similarity of
face-recognition embeddings of a render and its target, in plain torch for the evaluation metrics.

This module owns insightface's ArcFace backbone (:class:`IResNet`: iresnet18/34/50/100), the five-point alignment
onto ArcFace's 112x112 template (:func:`align_faces`), the similarity itself (:class:`IdentitySimilarity`) and the
reading of the backbone's weight file (:func:`load_identity_model`).

Conventions: images are [B, 3, H, W] RGB, nominally in [0, 1], finite, of any size (the alignment resamples them
to 112x112). Landmarks are [B, 68, 2] iBUG-68 points (x, y) in pixels of those images, pixel centres at integers
((0, 0) is the centre of the top-left pixel: OpenCV's, dlib's and face_alignment's convention, and the one
insightface's template assumes with ``cv2.warpAffine``). The aligned crop is scaled to ArcFace's input range
inside, x -> (255 x - 127.5) / 127.5 = 2x - 1, as insightface's ``arcface_torch/inference.py`` does.

Pretrained weights cannot be downloaded here: the user passes insightface's ``backbone.pth`` for the chosen
architecture (e.g. ``ms1mv3_arcface_r50_fp16/backbone.pth`` for the default ``"iresnet50"``), read with
``weights_only=True``, or the same tensors as ``.safetensors``.
"""

from __future__ import annotations

import os
import re

import torch
import torch.nn as nn
import torch.nn.functional as F

from toolkit.errors import ToolkitError
from toolkit.io import check_readable_file, load_state_dict_file

# Blocks per stage of insightface's ``recognition/arcface_torch/backbones/iresnet.py`` architectures.
IRESNET_LAYERS = {
    "iresnet18": (2, 2, 2, 2),
    "iresnet34": (3, 4, 6, 3),
    "iresnet50": (3, 4, 14, 3),
    "iresnet100": (3, 13, 30, 3),
}
STAGE_CHANNELS = (64, 128, 256, 512)
EMBEDDING_DIM = 512
ARCFACE_SIZE = 112
FC_SPATIAL = 7  # 112 after four stride-2 stages
BN_EPS = 1e-5  # every BatchNorm of the reference, 2d and 1d
# insightface's ``face_align.arcface_dst``: left eye, right eye, nose tip, left and right mouth corners (x, y),
# in pixels of the 112x112 crop ("left" is the image's left, the subject's right eye).
ARCFACE_TEMPLATE = (
    (38.2946, 51.6963),
    (73.5318, 51.5014),
    (56.0252, 71.7366),
    (41.5493, 92.3655),
    (70.7299, 92.2041),
)
EMBED_EPS = 1e-8  # floor of the embedding norm, so an all-zero embedding gives similarity 0, not NaN
TEMPLATE_SPREAD = 23.2  # the template's RMS distance to its centroid, in px
MIN_LANDMARK_SPREAD = 1e-3  # pixels: RMS distance of the five points to their centroid below this is degenerate
# Far-off landmarks put the sampling grid anywhere; beyond +-3 (normalized) every bilinear tap is outside the image
# already, so clamping changes nothing but keeps grid_sample's index arithmetic in range.
GRID_LIMIT = 3.0


# ----------------------------------------------------------------------------- backbone
def _bn2d(c: int) -> nn.BatchNorm2d:
    return nn.BatchNorm2d(c, eps=BN_EPS)


class IBasicBlock(nn.Module):
    """insightface's pre-activation residual block: BN, conv3x3, BN, PReLU, conv3x3 (carrying the stride), BN,
    plus the (downsampled) input. No ReLU after the sum."""

    def __init__(self, inplanes: int, planes: int, stride: int = 1):
        super().__init__()
        self.bn1 = _bn2d(inplanes)
        self.conv1 = nn.Conv2d(inplanes, planes, 3, stride=1, padding=1, bias=False)
        self.bn2 = _bn2d(planes)
        self.prelu = nn.PReLU(planes)
        self.conv2 = nn.Conv2d(planes, planes, 3, stride=stride, padding=1, bias=False)
        self.bn3 = _bn2d(planes)
        self.downsample = None
        if stride != 1 or inplanes != planes:
            self.downsample = nn.Sequential(nn.Conv2d(inplanes, planes, 1, stride=stride, bias=False), _bn2d(planes))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        out = self.bn3(self.conv2(self.prelu(self.bn2(self.conv1(self.bn1(x))))))
        return out + (x if self.downsample is None else self.downsample(x))


class IResNet(nn.Module):
    """insightface's ArcFace backbone; ``forward(x [B, 3, 112, 112] scaled to [-1, 1])`` -> [B, 512] embeddings.

    Module and state-dict names match ``arcface_torch/backbones/iresnet.py`` exactly, so its ``backbone.pth`` loads
    unchanged: ``conv1`` (3x3, stride 1), ``bn1``, ``prelu``, ``layer1..4`` of :class:`IBasicBlock` (each stage's
    first block has stride 2 and a ``downsample``), ``bn2``, ``dropout``, ``fc`` (512*7*7 -> 512) and ``features``
    (BatchNorm1d; the reference freezes its weight at 1). Built directly it holds untrained weights.
    """

    def __init__(self, arch: str = "iresnet50"):
        super().__init__()
        if arch not in IRESNET_LAYERS:
            raise ToolkitError(f"identity: unknown arch {arch!r}; expected one of {', '.join(IRESNET_LAYERS)}")
        self.arch = arch
        self.conv1 = nn.Conv2d(3, STAGE_CHANNELS[0], 3, stride=1, padding=1, bias=False)
        self.bn1 = _bn2d(STAGE_CHANNELS[0])
        self.prelu = nn.PReLU(STAGE_CHANNELS[0])
        inplanes = STAGE_CHANNELS[0]
        for i, (planes, blocks) in enumerate(zip(STAGE_CHANNELS, IRESNET_LAYERS[arch])):
            stage = [IBasicBlock(inplanes, planes, stride=2)] + [IBasicBlock(planes, planes) for _ in range(blocks - 1)]
            self.add_module(f"layer{i + 1}", nn.Sequential(*stage))
            inplanes = planes
        self.bn2 = _bn2d(STAGE_CHANNELS[-1])
        self.dropout = nn.Dropout(p=0.0)  # the reference's default; an identity at evaluation anyway
        self.fc = nn.Linear(STAGE_CHANNELS[-1] * FC_SPATIAL * FC_SPATIAL, EMBEDDING_DIM)
        self.features = nn.BatchNorm1d(EMBEDDING_DIM, eps=BN_EPS)
        nn.init.constant_(self.features.weight, 1.0)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        x = self.prelu(self.bn1(self.conv1(x)))
        x = self.layer4(self.layer3(self.layer2(self.layer1(x))))
        x = self.dropout(torch.flatten(self.bn2(x), 1))
        return self.features(self.fc(x))

    def load_insightface_state_dict(self, state: dict, source: str = "state dict") -> None:
        """Copy an insightface-layout state dict (plain, or nested under ``"state_dict"``, ``"model"`` or
        ``"state_dict_backbone"``; ``"module."`` prefixes stripped); names the first mismatch. ``num_batches_tracked``
        may be absent; any other missing, misshapen, non-finite or surplus backbone tensor is an error (a deeper
        architecture's file would otherwise load silently into a shallower one)."""
        state = _unwrap_state_dict(state)
        own = self.state_dict()
        found = _block_counts(state)
        hint = ""
        if found in IRESNET_LAYERS.values():
            name = next(a for a, layers in IRESNET_LAYERS.items() if layers == found)
            if name != self.arch:
                hint = f"; the file's blocks per stage {found} are {name}'s, pass arch={name!r}"
        picked = {}
        for name, ref in own.items():
            src = state.get(name)
            if name.endswith("num_batches_tracked"):
                ok = isinstance(src, torch.Tensor) and src.numel() == 1
                picked[name] = src.reshape(ref.shape).to(ref.dtype) if ok else ref
                continue
            if src is None:
                raise ToolkitError(f"{source}: missing tensor {name!r}; expected insightface's {self.arch} ArcFace "
                                   f"backbone state dict (backbone.pth){hint}")
            if not isinstance(src, torch.Tensor) or tuple(src.shape) != tuple(ref.shape):
                got = list(src.shape) if isinstance(src, torch.Tensor) else type(src).__name__
                raise ToolkitError(f"{source}: tensor {name!r} has shape {got}, expected {list(ref.shape)} "
                                   f"({self.arch}){hint}")
            if not src.is_floating_point() or not bool(torch.isfinite(src).all()):
                raise ToolkitError(f"{source}: tensor {name!r} must be finite floating-point values")
            picked[name] = src.to(ref.dtype)
        roots = {name.split(".")[0] for name in own}
        surplus = sorted(k for k in state if k.split(".")[0] in roots and k not in own)
        if surplus:
            raise ToolkitError(f"{source}: unexpected tensor {surplus[0]!r} (and {len(surplus) - 1} more) for "
                               f"{self.arch}{hint}")
        self.load_state_dict(picked)


def _unwrap_state_dict(state: dict) -> dict:
    for key in ("state_dict", "model", "state_dict_backbone"):
        if isinstance(state.get(key), dict):
            state = state[key]
            break
    return {(k[len("module."):] if isinstance(k, str) and k.startswith("module.") else k): v for k, v in state.items()}


def _block_counts(state: dict) -> tuple[int, ...]:
    """Blocks per stage in an insightface state dict, from its ``layerN.M.`` names (0 for an absent stage)."""
    counts = [0, 0, 0, 0]
    for k in state:
        m = re.match(r"layer([1-4])\.(\d+)\.", k) if isinstance(k, str) else None
        if m:
            s = int(m.group(1)) - 1
            counts[s] = max(counts[s], int(m.group(2)) + 1)
    return tuple(counts)


# ----------------------------------------------------------------------------- alignment
def five_point_landmarks(landmarks: torch.Tensor) -> torch.Tensor:
    """iBUG-68 [B, 68, 2] -> ArcFace's five points [B, 5, 2] in the template's order: the eye centres (means of
    36-41 and 42-47, the image's left eye first), the nose tip (30) and the mouth corners (48, 54)."""
    return torch.stack([landmarks[:, 36:42].mean(1), landmarks[:, 42:48].mean(1), landmarks[:, 30],
                        landmarks[:, 48], landmarks[:, 54]], dim=1)


def arcface_transform(landmarks: torch.Tensor) -> torch.Tensor:
    """[B, 68, 2] iBUG-68 landmarks -> [B, 2, 3] float64 similarity transforms (image pixels -> 112x112 crop pixels).

    The least-squares similarity (rotation, uniform scale, translation; no reflection) taking the five points onto
    :data:`ARCFACE_TEMPLATE`: Umeyama's solution, as insightface's ``estimate_norm`` gets from skimage. In 2D it
    is linear least squares in (a, b, tx, ty) for [[a, -b], [b, a]] x + t, solved here in closed form (no SVD, so
    gradients to the landmarks stay finite). Raises a ToolkitError where the points are degenerate.
    """
    src = five_point_landmarks(landmarks.to(torch.float64))
    dst = torch.tensor(ARCFACE_TEMPLATE, dtype=torch.float64, device=src.device).expand_as(src)
    src_mean, dst_mean = src.mean(1, keepdim=True), dst.mean(1, keepdim=True)
    p, q = src - src_mean, dst - dst_mean
    var = (p ** 2).sum((1, 2))
    spread = (var / 5).sqrt()
    bad = torch.nonzero(spread < MIN_LANDMARK_SPREAD).flatten()
    if len(bad):
        i = int(bad[0])
        raise ToolkitError(f"identity: landmarks of batch entry {i} are degenerate: the five ArcFace points (eye "
                           f"centres, nose tip, mouth corners) spread {float(spread[i]):.3g} px, expected at least "
                           f"{MIN_LANDMARK_SPREAD} px")
    a = (p * q).sum((1, 2)) / var
    b = (p[..., 0] * q[..., 1] - p[..., 1] * q[..., 0]).sum(1) / var
    scale = torch.sqrt(a ** 2 + b ** 2)
    bad = torch.nonzero(scale * spread < 1e-6 * TEMPLATE_SPREAD).flatten()
    if len(bad):
        raise ToolkitError(f"identity: landmarks of batch entry {int(bad[0])} do not fit a face: the best similarity "
                           f"onto the ArcFace template collapses them to a point")
    rot = torch.stack([torch.stack([a, -b], -1), torch.stack([b, a], -1)], -2)  # [B, 2, 2]
    t = dst_mean.squeeze(1) - (rot @ src_mean.transpose(1, 2)).squeeze(-1)
    return torch.cat([rot, t.unsqueeze(-1)], -1)


def align_faces(images: torch.Tensor, landmarks: torch.Tensor) -> torch.Tensor:
    """Warp [B, 3, H, W] images in [0, 1] to ArcFace's [B, 3, 112, 112] crops by :func:`arcface_transform` of
    their [B, 68, 2] landmarks.

    Bilinear, like insightface's ``cv2.warpAffine`` (no antialiasing when shrinking a large face). Outside the
    image is white (1.0), not black, because the evaluation composites renders and targets on white. Gradients
    reach the images (and the landmarks). Output in the images' dtype.
    """
    _check_images(images)
    _check_landmarks(landmarks, images.shape[0])
    if images.shape[0] == 0:
        return images.new_ones(0, 3, ARCFACE_SIZE, ARCFACE_SIZE)
    h, w = images.shape[-2:]
    m = arcface_transform(landmarks)  # crop pixel = m @ [image pixel, 1]
    rot, t = m[..., :2], m[..., 2:]
    # The inverse similarity: crop pixel -> image pixel, [[a, b], [-b, a]] / (a^2 + b^2).
    inv_rot = rot.transpose(1, 2) / (rot[:, 0, 0] ** 2 + rot[:, 1, 0] ** 2).view(-1, 1, 1)
    inv = torch.cat([inv_rot, -inv_rot @ t], -1)
    # grid_sample's normalized coordinates (align_corners=False): u = (2 px + 1) / size - 1.
    s = ARCFACE_SIZE
    from_crop = torch.tensor([[s / 2, 0, (s - 1) / 2], [0, s / 2, (s - 1) / 2], [0, 0, 1]],
                             dtype=torch.float64, device=m.device)
    to_image = torch.tensor([[2 / w, 0, 1 / w - 1], [0, 2 / h, 1 / h - 1]], dtype=torch.float64, device=m.device)
    inv3 = torch.cat([inv, inv.new_tensor([0, 0, 1]).expand(inv.shape[0], 1, 3)], 1)
    theta = to_image @ inv3 @ from_crop
    grid = F.affine_grid(theta.to(images.dtype), [images.shape[0], 3, s, s], align_corners=False)
    grid = grid.clamp(-GRID_LIMIT, GRID_LIMIT)
    # Bilinear sampling is linear, so sampling (x - 1) with zero padding and adding 1 pads with white exactly.
    return F.grid_sample(images - 1, grid, mode="bilinear", padding_mode="zeros", align_corners=False) + 1


# ----------------------------------------------------------------------------- similarity
class IdentitySimilarity(nn.Module):
    """Frozen ArcFace identity similarity; ``forward(a, b, landmarks)`` -> [B] cosine similarities in [-1, 1].

    Both images are aligned with the same landmarks (in the evaluation the render and its target share the view
    and the face), embedded by ``backbone`` and compared. Built directly it wraps an untrained ``IResNet(arch)``;
    use :func:`load_identity_model` for the real metric. Always in eval mode (``train()`` is a no-op: BatchNorm
    must use its running statistics, or a batch's entries would depend on each other). Parameters never require
    grad, but gradients reach the images. Computes in the backbone's dtype (float32 unless converted).
    """

    def __init__(self, backbone: IResNet | None = None, arch: str = "iresnet50"):
        super().__init__()
        self.backbone = backbone if backbone is not None else IResNet(arch)
        self.eval()
        self.requires_grad_(False)

    def train(self, mode: bool = True) -> IdentitySimilarity:
        return super().train(False)

    @classmethod
    def from_file(cls, path: str | os.PathLike, arch: str = "iresnet50") -> IdentitySimilarity:
        """The metric with insightface's ``backbone.pth`` (or a ``.safetensors`` copy) for ``arch``."""
        backbone = IResNet(arch)
        path = check_readable_file(path, "ArcFace backbone weights file")
        backbone.load_insightface_state_dict(load_state_dict_file(path), source=str(path))
        return cls(backbone)

    def embed(self, aligned: torch.Tensor) -> torch.Tensor:
        """Aligned [B, 3, 112, 112] crops in [0, 1] -> [B, 512] embeddings (not normalized)."""
        x = aligned.to(self.backbone.conv1.weight.dtype)
        return self.backbone((x * 255 - 127.5) / 127.5)

    def forward(self, a: torch.Tensor, b: torch.Tensor, landmarks: torch.Tensor) -> torch.Tensor:
        """Images a, b [B, 3, H, W] (finite, in [0, 1]) and their shared landmarks [B, 68, 2] -> [B] similarities."""
        _check_images(a, b)
        _check_landmarks(landmarks, a.shape[0])
        dtype = self.backbone.conv1.weight.dtype
        if a.shape[0] == 0:
            return a.new_zeros(0, dtype=dtype)
        crops = align_faces(torch.cat([a, b]).to(dtype), torch.cat([landmarks, landmarks]))
        ea, eb = F.normalize(self.embed(crops), dim=1, eps=EMBED_EPS).chunk(2)
        # Rounding can put the dot product of unit vectors a hair past 1.
        return (ea * eb).sum(1).clamp(-1.0, 1.0)


def load_identity_model(path: str | os.PathLike, arch: str = "iresnet50") -> IdentitySimilarity:
    """:meth:`IdentitySimilarity.from_file`: the frozen metric from a local insightface ``backbone.pth``."""
    return IdentitySimilarity.from_file(path, arch)


# ----------------------------------------------------------------------------- input checks
def _check_images(*images: torch.Tensor) -> None:
    names = ("a", "b") if len(images) == 2 else ("images",)
    for name, x in zip(names, images):
        if not isinstance(x, torch.Tensor) or x.dim() != 4 or x.shape[1] != 3 or min(x.shape[-2:]) < 1:
            got = list(x.shape) if isinstance(x, torch.Tensor) else type(x).__name__
            raise ToolkitError(f"identity: input {name} must be a [B, 3, H, W] image tensor, got {got}")
        if not x.is_floating_point():
            raise ToolkitError(f"identity: input {name} must be floating-point in [0, 1], got {x.dtype}")
    if len(images) == 2 and images[0].shape != images[1].shape:
        raise ToolkitError(f"identity: inputs must have one shape, got {list(images[0].shape)} and "
                           f"{list(images[1].shape)}")
    for name, x in zip(names, images):
        if not bool(torch.isfinite(x).all()):
            raise ToolkitError(f"identity: input {name} contains NaN or inf")


def _check_landmarks(landmarks: torch.Tensor, batch: int) -> None:
    if not isinstance(landmarks, torch.Tensor) or tuple(landmarks.shape) != (batch, 68, 2):
        got = list(landmarks.shape) if isinstance(landmarks, torch.Tensor) else type(landmarks).__name__
        raise ToolkitError(f"identity: landmarks must be a [B, 68, 2] tensor of iBUG-68 (x, y) pixel coordinates "
                           f"with B = {batch}, got {got}")
    if landmarks.is_complex() or landmarks.dtype == torch.bool:
        raise ToolkitError(f"identity: landmarks must be real pixel coordinates, got {landmarks.dtype}")
    if landmarks.is_floating_point() and not bool(torch.isfinite(landmarks).all()):
        raise ToolkitError("identity: landmarks contain NaN or inf")
