"""GazeNeRF's evaluation gaze estimator, read from its published checkpoint and fed as GazeNeRF feeds it.

GazeNeRF (github AlessandroRuzzi/GazeNeRF) scores redirected images with an ETH-XGaze ResNet-50 gaze estimator
(:class:`train.estimator.resnet50.XGazeGazeNetwork`). The facts this module follows, by file and line of that
repository (commit eb0a5f1) and of ETH-XGaze's baseline (xucong-zhang/ETH-XGaze, commit ef9bff0):

- **Network**: ``gaze_network()`` of ``gaze_estimation/xgaze_baseline_resnet.py:6-22`` (``evaluate_metrics.py:12,
  132``): ResNet-50 trunk -> pooled 2048 -> ``Linear(2048, 4)``; outputs [:, :2] gaze, [:, 2:] head pose.
- **Checkpoint**: ``configs/config_models/epoch_7_resnet_correct_ckpt.pth.tar`` (``evaluate_metrics.py:131``),
  read with ``torch.load`` and loaded strictly from its ``"model_state"`` entry (``evaluate_metrics.py:134-136``),
  no ``module.`` prefix; the container is ETH-XGaze's trainer's ``{"epoch", "model_state", "optim_state",
  "scheule_state"}`` (ETH-XGaze ``trainer.py:97-103``). ETH-XGaze's own ``epoch_24_ckpt.pth.tar`` (``demo.py:150-157``)
  has the same layout with a 2-output ``gaze_fc`` (``model.py:10-12``); it loads too.
- **Input**: the image as uint8, ``(x * 255).astype(np.uint8)`` (truncation; ``utils/metrics_utils.py:266-269,
  301-303``), re-normalized by ``utils.gaze_estimation_utils.normalize`` to a 224 x 224 face patch of a virtual
  camera with focal 960 px at 600 mm from the face centre (``utils/gaze_estimation_utils.py:84-86, 105-111``;
  ``img_dim = 224`` at ``evaluate_metrics.py:117``), warped bilinearly (``cv2.warpPerspective``, line 132), the
  face centre being the mean of the eye-corner mean and the nose-corner mean (landmarks 36, 39, 42, 45 and 31, 35;
  lines 62-65, 92-97). Then ``ToTensor`` (/255) and ``Normalize`` with ImageNet's mean and std, then
  ``Resize(224)``, a no-op on a 224 patch (``utils/metrics_utils.py:30-37``, applied at lines 278-283, 310-313).
- **Colour**: RGB. GazeNeRF's loader turns the stored BGR into RGB (``datasets/eth_xgaze.py:330-332``), its
  renders are RGB, and nothing between swaps channels; ETH-XGaze trains on RGB too (``data_loader.py:129-131``).
- **Output**: radians, in the convention of ETH-XGaze's ``face_gaze`` labels that the baseline regresses
  (ETH-XGaze ``data_loader.py:135``; GazeNeRF publishes no training code for its 4-output variant, whose
  outputs are the ``face_gaze`` and ``face_head_pose`` pair): pitch = asin(-g_y), yaw = atan2(-g_x, -g_z) in
  the normalized camera, this project's convention (``toolkit.rotations``; ETH-XGaze ``demo.py:36-37`` draws
  positive pitch upwards). No sign change is applied. GazeNeRF compares readings only by angle
  (``utils/metrics_utils.py:85-95``), which no convention shared by both readings changes.

What cannot be reproduced without GazeNeRF's own inputs: its warp comes from a PnP fit of ETH-XGaze's generic
face model to six landmarks with its dataset's camera matrix (``utils/gaze_estimation_utils.py:6-17, 59-72``).
On an already normalized image (this project's: 0.26 m wide at 0.6 m, no roll) that warp is a scale and a shift
about the peer's face centre; :func:`gazenerf_preprocess` applies it for a face at the normalized distance, so a
face the generic model fits nearer or farther is cropped a few per cent tighter or looser than GazeNeRF would.
"""

from __future__ import annotations

import os

import torch
import torch.nn as nn
import torch.nn.functional as F

from toolkit.errors import ToolkitError
from toolkit.io import load_foreign_torch_checkpoint, nonfinite_tensors
from train.estimator.resnet50 import RESNET50_FEATURES, XGazeGazeNetwork

PEER_SIZE = 224
"""Side of the peer's input patch, pixels (GazeNeRF ``evaluate_metrics.py:117``, ``gaze_estimation_utils.py:86``)."""
PEER_FOCAL = 960.0
"""Focal length of the peer's virtual camera, pixels (``gaze_estimation_utils.py:84``)."""
PEER_DISTANCE_M = 0.6
"""Distance of the peer's virtual camera to the face centre (600 mm, ``gaze_estimation_utils.py:85``)."""
PEER_SPAN_M = PEER_SIZE * PEER_DISTANCE_M / PEER_FOCAL
"""0.14 m: the width, in the face's plane, that the peer's 224 patch spans."""
PROJECT_SPAN_M = 0.26
"""The width the project's normalized images span at their 0.6 m face distance (``train/data/generate.py``
``NORM_CROP``; docs/data.md "Cameras")."""
IMAGENET_MEAN = (0.485, 0.456, 0.406)
IMAGENET_STD = (0.229, 0.224, 0.225)
"""``Normalize`` of GazeNeRF ``utils/metrics_utils.py:34`` and ETH-XGaze ``data_loader.py:14-15``, RGB order."""
EYE_CORNERS = (36, 39, 42, 45)
NOSE_CORNERS = (31, 35)
"""iBUG-68 landmarks whose 3D fit sets the peer's face centre (``gaze_estimation_utils.py:65, 92-97``)."""
CONTAINER_KEY = "model_state"
"""Where ETH-XGaze's trainer puts the weights (``trainer.py:99``) and GazeNeRF reads them (``evaluate_metrics.py:135``)."""


def _fail(path: str | os.PathLike, what: str) -> ToolkitError:
    return ToolkitError(" ".join(f"{path}: {what}".split()))  # one line, whatever the parts hold


def _state_dict(obj: object, path: str | os.PathLike) -> dict[str, torch.Tensor]:
    """The weights inside what ``torch.load`` returned: ``obj["model_state"]`` or a bare state dict, with a
    ``module.`` prefix (a DataParallel save) dropped when every key has it."""
    if not isinstance(obj, dict):
        raise _fail(path, f"expected a checkpoint dict, got {type(obj).__name__}")
    if CONTAINER_KEY in obj:
        obj = obj[CONTAINER_KEY]
        if not isinstance(obj, dict):
            raise _fail(path, f"'{CONTAINER_KEY}' holds a {type(obj).__name__}, expected a state dict")
    elif not obj or not all(isinstance(v, torch.Tensor) for v in obj.values()):
        keys = sorted(str(k) for k in obj)[:5]
        raise _fail(path, f"not a gaze estimator checkpoint: no '{CONTAINER_KEY}' entry and not a state dict "
                          f"(top-level keys {keys}); expected ETH-XGaze's trainer format")
    bad = [str(k) for k, v in obj.items() if not isinstance(k, str) or not isinstance(v, torch.Tensor)]
    if bad:
        raise _fail(path, f"state dict entry {bad[0]!r} is not a named tensor")
    if obj and all(k.startswith("module.") for k in obj):
        obj = {k[len("module."):]: v for k, v in obj.items()}
    return obj


def _outputs(state: dict[str, torch.Tensor]) -> int:
    """4 (GazeNeRF's gaze + head) or 2 (ETH-XGaze's gaze-only release), read off ``gaze_fc.0.weight``;
    4 when that tensor is absent or odd, so the key check names it."""
    w = state.get("gaze_fc.0.weight")
    if w is not None and w.dim() == 2 and w.shape[1] == RESNET50_FEATURES and w.shape[0] in (2, 4):
        return int(w.shape[0])
    return 4


def _check_state(net: nn.Module, state: dict[str, torch.Tensor], path: str | os.PathLike) -> None:
    """Names, shapes and values as ``load_state_dict(strict=True)`` needs them, as one-line errors."""
    own = net.state_dict()
    # BatchNorm fills a missing num_batches_tracked itself (files saved before torch 0.4.1): not missing.
    missing = [k for k in own if k not in state and not k.endswith("num_batches_tracked")]
    unexpected = [k for k in state if k not in own]
    if missing or unexpected:
        raise _fail(path, f"not GazeNeRF's ETH-XGaze ResNet-50 gaze estimator: {len(missing)} missing tensor(s) "
                          f"{missing[:4]}, {len(unexpected)} unexpected {unexpected[:4]}")
    for k, v in state.items():
        if tuple(v.shape) != tuple(own[k].shape):
            raise _fail(path, f"tensor {k!r} has shape {list(v.shape)}, expected {list(own[k].shape)} "
                              "(GazeNeRF's ETH-XGaze ResNet-50 gaze estimator)")
    if broken := nonfinite_tensors(state):
        raise _fail(path, f"tensor {broken[0]!r} holds NaN or inf")


def load_gazenerf_estimator(path: str | os.PathLike, device: str | torch.device = "cpu") -> XGazeGazeNetwork:
    """GazeNeRF's (or ETH-XGaze's) gaze estimator from its ``.pth.tar`` file, frozen (eval mode, no grad).

    The file is read with ``weights_only=True``; a missing or unreadable file, another container, wrong or
    missing tensor names (the first few listed), a wrong shape, or NaN weights is one ``ToolkitError`` line
    naming the file. ``model(x [B, 3, 224, 224])`` -> [B, 4] (or [B, 2]); feed it :func:`gazenerf_preprocess`
    output, or wrap it in :class:`PeerGazeEstimator`.
    """
    obj = load_foreign_torch_checkpoint(path)  # its refusal is one line already (toolkit.errors.one_line)
    state = _state_dict(obj, path)
    net = XGazeGazeNetwork(_outputs(state))
    _check_state(net, state, path)
    try:
        net.load_state_dict(state, strict=True)
    except RuntimeError as e:  # not expected after the checks; kept to one line all the same
        raise _fail(path, f"does not load into GazeNeRF's gaze estimator ({e})") from None
    net.eval()  # BatchNorm on its running statistics, as GazeNeRF evaluates (evaluate_metrics.py:136)
    for p in net.parameters():
        p.requires_grad_(False)
    return net.to(device)


def peer_face_centre(landmarks: torch.Tensor) -> torch.Tensor:
    """[B, 68, 2] landmarks (pixels) -> [B, 2]: the image point the peer's normalization looks at, the mean of
    the eye-corner mean and the nose-corner mean. GazeNeRF averages the 3D points of its face-model fit
    (``gaze_estimation_utils.py:91-97``); on a normalized face the 2D mean lands within a fraction of a pixel."""
    eyes = landmarks[:, list(EYE_CORNERS)].mean(1)
    nose = landmarks[:, list(NOSE_CORNERS)].mean(1)
    return (eyes + nose) / 2


def _check_inputs(images: torch.Tensor, landmarks: torch.Tensor | None) -> None:
    if images.dim() != 4 or images.shape[1] != 3 or not images.is_floating_point():
        raise ToolkitError(f"gazenerf_preprocess: images must be float [B, 3, H, W] RGB in [0, 1], got "
                           f"{images.dtype} {list(images.shape)}")
    if landmarks is not None and tuple(landmarks.shape) != (images.shape[0], 68, 2):
        raise ToolkitError(f"gazenerf_preprocess: landmarks must be [B={images.shape[0]}, 68, 2] pixels, "
                           f"got {list(landmarks.shape)}")


def gazenerf_preprocess(images: torch.Tensor, landmarks: torch.Tensor | None = None, *,
                        face_span_m: float = PROJECT_SPAN_M, quantize: bool = True) -> torch.Tensor:
    """Project images -> the tensor GazeNeRF's estimator receives: [B, 3, H, W] float RGB in [0, 1] ->
    [B, 3, 224, 224] ImageNet-normalized RGB.

    The images are normalized face crops ``face_span_m`` wide at the face (the project's 0.26 m; ETH-XGaze's
    448 patches and 224 patches span 0.14 m; GazeNeRF's own 512 images 0.2176 m). The peer's re-normalization
    then samples a square ``W * 0.14 / face_span_m`` pixels wide, bilinearly, centred on
    :func:`peer_face_centre` of ``landmarks`` (edge-origin pixels, as the project stores them), or on the
    image centre without them. Its output pixel index j sits (j - 112) / 960 off the axis: the virtual
    camera's principal point is pixel 112, ``roiSize / 2`` (``gaze_estimation_utils.py:105-111``). Outside the
    image is black, as ``cv2.warpPerspective`` leaves it.

    ``quantize`` (default) reproduces the two uint8 steps: the image truncated to uint8 before the warp, the
    warp's result rounded to uint8 (cv2 interpolates to 1/32 pixel and rounds; this differs by at most one
    grey level on rare pixels). Without it the function is differentiable.
    """
    _check_inputs(images, landmarks)
    B, _, H, W = images.shape
    x = images.float()
    x = torch.floor(x.clamp(0, 1) * 255) if quantize else x * 255
    if landmarks is None:
        centre = x.new_tensor([W / 2, H / 2]).expand(B, 2)
    else:
        centre = peer_face_centre(landmarks.to(x.device, x.dtype))
    step = W * PEER_SPAN_M / face_span_m / PEER_SIZE  # source pixels per output pixel
    offsets = (torch.arange(PEER_SIZE, device=x.device, dtype=x.dtype) - PEER_SIZE / 2) * step
    u = centre[:, :1] + offsets  # [B, 224] edge-origin source coordinates of the output columns
    v = centre[:, 1:] + offsets  # [B, 224] ... and rows
    grid = torch.stack([(2 * u / W - 1)[:, None, :].expand(B, PEER_SIZE, PEER_SIZE),
                        (2 * v / H - 1)[:, :, None].expand(B, PEER_SIZE, PEER_SIZE)], -1)
    out = F.grid_sample(x, grid, mode="bilinear", padding_mode="zeros", align_corners=False)
    if quantize:
        out = torch.floor(out + 0.5)  # cv2's uint8 rounding: halves go up
    mean = x.new_tensor(IMAGENET_MEAN).view(1, 3, 1, 1)
    std = x.new_tensor(IMAGENET_STD).view(1, 3, 1, 1)
    return (out / 255 - mean) / std


class PeerGazeEstimator(nn.Module):
    """GazeNeRF's estimator on project images: ``forward(images [B, 3, H, W] RGB in [0, 1], landmarks
    [B, 68, 2] | None)`` -> [B, 2] gaze (pitch, yaw), radians, this project's convention (the network's own,
    see the module notes). ``gaze_and_head`` -> [B, 4] (gaze, head pose), the layout of
    :class:`train.estimator.network.GazeEstimator`'s output, for 4-output checkpoints; ``head=True`` makes
    that the forward's output (what the evaluation protocol reads).

    Pass the landmarks when the images have them: the peer centres its crop on the face (GazeNeRF uses the
    target's landmarks for both the target and the render, ``utils/metrics_utils.py:248, 266-313``).
    """

    def __init__(self, model: XGazeGazeNetwork, *, face_span_m: float = PROJECT_SPAN_M, quantize: bool = True,
                 head: bool = False):
        super().__init__()
        if not face_span_m > 0:
            raise ToolkitError(f"PeerGazeEstimator.face_span_m: expected a width > 0 metres, got {face_span_m}")
        if head and model.outputs != 4:
            raise ToolkitError(f"PeerGazeEstimator: this checkpoint reads gaze only ({model.outputs} outputs); "
                               "scoring head pose too needs GazeNeRF's 4-output estimator")
        self.model, self.head = model, bool(head)
        self.face_span_m = float(face_span_m)
        self.quantize = bool(quantize)

    def readings(self, images: torch.Tensor, landmarks: torch.Tensor | None = None) -> torch.Tensor:
        """[B, 3, H, W] -> [B, outputs]: the network's raw outputs on the peer's preprocessing."""
        device = next(self.model.parameters()).device
        x = gazenerf_preprocess(images.to(device), landmarks, face_span_m=self.face_span_m, quantize=self.quantize)
        return self.model(x)

    def forward(self, images: torch.Tensor, landmarks: torch.Tensor | None = None) -> torch.Tensor:
        """[B, 2] gaze, or with ``head`` [B, 4] (gaze, head pose) as the project's estimators read."""
        return self.gaze_and_head(images, landmarks) if self.head else self.readings(images, landmarks)[:, :2]

    def gaze_and_head(self, images: torch.Tensor, landmarks: torch.Tensor | None = None) -> torch.Tensor:
        """[B, 3, H, W] -> [B, 4] (gaze pitch, gaze yaw, head pitch, head yaw), radians."""
        if self.model.outputs != 4:
            raise ToolkitError(f"PeerGazeEstimator: this checkpoint reads gaze only ({self.model.outputs} outputs); "
                               "head pose needs GazeNeRF's 4-output estimator")
        return self.readings(images, landmarks)
