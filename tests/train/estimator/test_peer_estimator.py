"""GazeNeRF's evaluation gaze estimator: the ResNet-50's torchvision layout, loading the peer's checkpoint
layout strictly, its one-line errors, and the peer's preprocessing checked against values worked out by hand.

Peer facts (AlessandroRuzzi/GazeNeRF eb0a5f1; xucong-zhang/ETH-XGaze ef9bff0) used below:
- checkpoint ``{"epoch", "model_state", "optim_state", "scheule_state"}``: ETH-XGaze ``trainer.py:97-103``;
  read as ``state_dict["model_state"]``, strictly, no prefix: GazeNeRF ``evaluate_metrics.py:131-136``;
- network: ``gaze_network`` ResNet-50 trunk (its unused 1000-way ``fc`` included) + ``gaze_fc.0`` Linear(2048, 4):
  GazeNeRF ``gaze_estimation/xgaze_baseline_resnet.py:6-22``, ``gaze_estimation/resnet.py:198, 258-273``;
  ETH-XGaze's release has Linear(2048, 2): ETH-XGaze ``model.py:10-12``;
- input: uint8 by truncation (``utils/metrics_utils.py:266-269``), warped to 224 x 224 at focal 960 px and
  600 mm with principal point 112 (``utils/gaze_estimation_utils.py:84-86, 100-132``), /255, ImageNet mean/std,
  RGB (``utils/metrics_utils.py:30-37``, ``datasets/eth_xgaze.py:330-332``).
"""

from __future__ import annotations

import math
from collections import OrderedDict

import numpy as np
import pytest
import torch

from toolkit.errors import ToolkitError
from train.estimator.peer import (
    IMAGENET_MEAN,
    IMAGENET_STD,
    PeerGazeEstimator,
    gazenerf_preprocess,
    load_gazenerf_estimator,
)
from train.estimator.resnet50 import ResNet50, XGazeGazeNetwork

TORCHVISION_RESNET50_PARAMS = 25_557_032  # torchvision.models.resnet50(): 1000-way fc
GAZENERF_ESTIMATOR_PARAMS = 25_557_032 + 2048 * 4 + 4  # 25,565,228: + gaze_fc Linear(2048, 4)
XGAZE_BASELINE_PARAMS = 25_557_032 + 2048 * 2 + 2  # 25,561,130: + gaze_fc Linear(2048, 2)


def torchvision_resnet50_shapes(num_classes: int = 1000) -> "OrderedDict[str, tuple[int, ...]]":
    """torchvision's resnet50 state-dict names and shapes, written out from its architecture (not from the
    module under test): stem, bottlenecks of widths 64..512 (downsample on each stage's first block), fc."""
    shapes: OrderedDict[str, tuple[int, ...]] = OrderedDict()

    def bn(name: str, c: int) -> None:
        for k in ("weight", "bias", "running_mean", "running_var"):
            shapes[f"{name}.{k}"] = (c,)
        shapes[f"{name}.num_batches_tracked"] = ()

    shapes["conv1.weight"] = (64, 3, 7, 7)
    bn("bn1", 64)
    c_in = 64
    for stage, (blocks, w) in enumerate(zip((3, 4, 6, 3), (64, 128, 256, 512)), 1):
        for b in range(blocks):
            p = f"layer{stage}.{b}"
            shapes[f"{p}.conv1.weight"] = (w, c_in, 1, 1)
            bn(f"{p}.bn1", w)
            shapes[f"{p}.conv2.weight"] = (w, w, 3, 3)
            bn(f"{p}.bn2", w)
            shapes[f"{p}.conv3.weight"] = (4 * w, w, 1, 1)
            bn(f"{p}.bn3", 4 * w)
            if b == 0:
                shapes[f"{p}.downsample.0.weight"] = (4 * w, c_in, 1, 1)
                bn(f"{p}.downsample.1", 4 * w)
            c_in = 4 * w
    shapes["fc.weight"] = (num_classes, 2048)
    shapes["fc.bias"] = (num_classes,)
    return shapes


def peer_shapes(outputs: int = 4) -> "OrderedDict[str, tuple[int, ...]]":
    """The peer's ``model.state_dict()`` layout: the trunk under ``gaze_network.``, then ``gaze_fc.0``."""
    shapes = OrderedDict((f"gaze_network.{k}", v) for k, v in torchvision_resnet50_shapes().items())
    shapes["gaze_fc.0.weight"] = (outputs, 2048)
    shapes["gaze_fc.0.bias"] = (outputs,)
    return shapes


def random_peer_state(seed: int = 0, outputs: int = 4) -> "OrderedDict[str, torch.Tensor]":
    """Random weights in the peer's layout, scaled so a forward stays finite (He-like convs, BN near identity)."""
    g = torch.Generator().manual_seed(seed)
    state = OrderedDict()
    for k, shape in peer_shapes(outputs).items():
        if k.endswith("num_batches_tracked"):
            state[k] = torch.tensor(1000, dtype=torch.long)
        elif k.endswith("running_var"):
            state[k] = 1 + 0.1 * torch.rand(shape, generator=g)
        elif k.endswith(("running_mean", "bias")):
            state[k] = 0.1 * torch.randn(shape, generator=g)
        elif len(shape) == 1:  # BatchNorm weight
            state[k] = 1 + 0.1 * torch.randn(shape, generator=g)
        else:  # conv / linear weight
            state[k] = torch.randn(shape, generator=g) / math.sqrt(math.prod(shape[1:]))
    return state


def constant_peer_state(outputs: int = 4) -> "OrderedDict[str, torch.Tensor]":
    """The layout with stride-0 tensors: the saved file stays a few kB (for the error cases)."""
    return OrderedDict((k, torch.zeros((), dtype=torch.long) if k.endswith("num_batches_tracked")
                        else torch.full((), 0.5).expand(shape)) for k, shape in peer_shapes(outputs).items())


def as_eth_xgaze_checkpoint(state) -> dict:
    """The container ETH-XGaze's trainer writes (trainer.py:97-103; the 'scheule_state' spelling is theirs)."""
    return {"epoch": 8, "model_state": state,
            "optim_state": {"state": {}, "param_groups": [{"lr": 1e-4, "betas": (0.9, 0.999), "params": [0, 1]}]},
            "scheule_state": {"step_size": 10, "gamma": 0.1, "last_epoch": 8}}


@pytest.fixture(scope="module")
def peer_file(tmp_path_factory):
    state = random_peer_state()
    path = tmp_path_factory.mktemp("peer") / "epoch_7_resnet_correct_ckpt.pth.tar"
    torch.save(as_eth_xgaze_checkpoint(state), path)
    return path, state


@pytest.fixture(scope="module")
def peer_model(peer_file):
    return load_gazenerf_estimator(peer_file[0])


def test_resnet50_has_torchvisions_names_shapes_and_parameter_count():
    net = ResNet50()
    assert [(k, tuple(v.shape)) for k, v in net.state_dict().items()] == list(torchvision_resnet50_shapes().items())
    assert len(net.state_dict()) == 320 and len(list(net.parameters())) == 161
    assert sum(p.numel() for p in net.parameters()) == TORCHVISION_RESNET50_PARAMS
    head = XGazeGazeNetwork(4)
    assert [(k, tuple(v.shape)) for k, v in head.state_dict().items()] == list(peer_shapes(4).items())
    assert sum(p.numel() for p in head.parameters()) == GAZENERF_ESTIMATOR_PARAMS == 25_565_228
    assert sum(p.numel() for p in XGazeGazeNetwork(2).parameters()) == XGAZE_BASELINE_PARAMS == 25_561_130


def test_loads_the_peer_checkpoint_strictly_and_frozen(peer_file, peer_model):
    _, state = peer_file
    loaded = peer_model.state_dict()
    assert list(loaded) == list(state)
    assert all(torch.equal(loaded[k], v) for k, v in state.items())
    assert peer_model.outputs == 4 and not peer_model.training
    assert not any(p.requires_grad for p in peer_model.parameters())


def test_forward_shape_determinism_and_no_sign_change(peer_model):
    g = torch.Generator().manual_seed(1)
    images = torch.rand(2, 3, 96, 96, generator=g)
    landmarks = 40 + 16 * torch.rand(2, 68, 2, generator=g)
    est = PeerGazeEstimator(peer_model)
    with torch.no_grad():
        raw = peer_model(gazenerf_preprocess(images, landmarks))
        out = est(images, landmarks)
        again = est(images, landmarks)
        both = est.gaze_and_head(images[:1], landmarks[:1])
    assert out.shape == (2, 2) and raw.shape == (2, 4) and torch.isfinite(raw).all()
    assert torch.equal(out, again)
    # ETH-XGaze's face_gaze convention is the project's: the readings pass through unchanged.
    torch.testing.assert_close(out, raw[:, :2], rtol=0, atol=1e-5)
    # eval-mode BatchNorm: a row does not depend on its batch.
    torch.testing.assert_close(both, raw[:1], rtol=0, atol=1e-4)


def test_eth_xgaze_release_layout_bare_and_data_parallel_prefixed(tmp_path):
    state = constant_peer_state(outputs=2)
    path = tmp_path / "epoch_24_ckpt.pth.tar"
    torch.save({f"module.{k}": v for k, v in state.items()}, path)
    net = load_gazenerf_estimator(path)
    assert net.outputs == 2 and float(net.gaze_fc[0].weight[1, 7]) == 0.5
    with pytest.raises(ToolkitError, match="gaze only"):
        PeerGazeEstimator(net).gaze_and_head(torch.rand(1, 3, 32, 32))


def _one_line_error(path, match: str) -> str:
    with pytest.raises(ToolkitError, match=match) as info:
        load_gazenerf_estimator(path)
    msg = str(info.value)
    assert "\n" not in msg and str(path) in msg, msg
    return msg


def test_one_line_errors_name_the_file(tmp_path):
    _one_line_error(tmp_path / "absent.pth.tar", "no such")

    text = tmp_path / "notes.pth.tar"
    text.write_bytes(b"this is not a torch checkpoint\n")
    _one_line_error(text, "could not be read as a weights-only torch checkpoint")

    other = tmp_path / "other.pth.tar"
    torch.save({"epoch": 3, "lr": 0.1}, other)
    _one_line_error(other, "no 'model_state'")

    state = constant_peer_state()
    del state["gaze_network.layer3.2.conv2.weight"]
    state["gaze_network.extra.weight"] = torch.zeros(2)
    missing = tmp_path / "missing.pth.tar"
    torch.save(as_eth_xgaze_checkpoint(state), missing)
    msg = _one_line_error(missing, "1 missing tensor")
    assert "layer3.2.conv2.weight" in msg and "gaze_network.extra.weight" in msg

    state = constant_peer_state()
    state["gaze_network.layer2.0.conv1.weight"] = torch.zeros(()).expand(128, 256, 3, 3)
    shape = tmp_path / "shape.pth.tar"
    torch.save(as_eth_xgaze_checkpoint(state), shape)
    _one_line_error(shape, r"'gaze_network.layer2.0.conv1.weight' has shape \[128, 256, 3, 3\], expected \[128, 256, 1, 1\]")

    state = constant_peer_state()
    state["gaze_fc.0.bias"] = torch.tensor([0.0, math.nan, 0.0, 0.0])
    nan = tmp_path / "nan.pth.tar"
    torch.save(as_eth_xgaze_checkpoint(state), nan)
    _one_line_error(nan, "NaN")


def _normalized(value: float, channel: int) -> float:
    return (value - IMAGENET_MEAN[channel]) / IMAGENET_STD[channel]


def test_preprocess_one_pixel_by_hand_and_rgb_order():
    # 0.5 -> (0.5 * 255 = 127.5).astype(uint8) = 127 -> 127 / 255 = 0.498039 -> (x - mean) / std per channel.
    x = gazenerf_preprocess(torch.full((1, 3, 64, 64), 0.5))
    assert x.shape == (1, 3, 224, 224)
    expected = [0.056940, 0.187675, 0.409063]  # (0.498039 - 0.485) / 0.229, (- 0.456) / 0.224, (- 0.406) / 0.225
    for c in range(3):
        assert abs(float(x[0, c, 100, 37]) - expected[c]) < 1e-5
        assert abs(expected[c] - _normalized(127 / 255, c)) < 1e-5
    red = torch.zeros(1, 3, 64, 64)
    red[:, 0] = 1.0  # RGB red stays in channel 0: (1 - 0.485) / 0.229 = 2.248908; 0 -> -0.456 / 0.224 = -2.035714
    y = gazenerf_preprocess(red)
    torch.testing.assert_close(y[0, :, 5, 200], torch.tensor([2.248908, -2.035714, -1.804444]), rtol=0, atol=1e-5)


def test_preprocess_crop_geometry_by_hand():
    # A 260-pixel project image spans 0.26 m, so the peer's 0.14 m patch is 140 source pixels for 224 output
    # pixels: output index j samples u = 130 + (j - 112) * 0.625 (edge-origin pixels). A ramp whose pixel k
    # holds (k + 0.5) / 260 reads u / 260 there, exactly, under bilinear sampling.
    k = (torch.arange(260) + 0.5) / 260
    ramp = torch.zeros(1, 3, 260, 260)
    ramp[:, 0] = k.view(1, 260)  # red: columns
    ramp[:, 1] = k.view(260, 1)  # green: rows
    x = gazenerf_preprocess(ramp, quantize=False)
    for j, u in ((0, 60.0), (112, 130.0), (223, 199.375)):
        assert abs(float(x[0, 0, 50, j]) - _normalized(u / 260, 0)) < 1e-5
        assert abs(float(x[0, 1, j, 50]) - _normalized(u / 260, 1)) < 1e-5
    # With landmarks the patch centres on the mean of the eye-corner mean and the nose-corner mean.
    lm = torch.zeros(1, 68, 2)
    lm[0, [36, 39, 42, 45]] = torch.tensor([[120.0, 100.0], [140.0, 102.0], [160.0, 102.0], [180.0, 100.0]])
    lm[0, [31, 35]] = torch.tensor([[140.0, 138.0], [160.0, 138.0]])  # eyes (150, 101), nose (150, 138)
    x = gazenerf_preprocess(ramp, lm, quantize=False)
    assert abs(float(x[0, 0, 0, 112]) - _normalized(150 / 260, 0)) < 1e-5
    assert abs(float(x[0, 1, 112, 0]) - _normalized(119.5 / 260, 1)) < 1e-5


def _peer_warp_reference(image: np.ndarray, focal: float, distance_m: float) -> np.ndarray:
    """The peer's warp re-derived for a face centred on the axis with no rotation (R = I):
    W = cam_norm · S · K⁻¹ with cam_norm = [[960, 0, 112], [0, 960, 112], [0, 0, 1]], S = diag(1, 1, 0.6 / d)
    (utils/gaze_estimation_utils.py:100-130); cv2.warpPerspective samples W⁻¹ (j, i, 1) for each output pixel
    (j, i), bilinearly, in integer-centred pixels, where K's principal point is (W / 2 - 0.5, H / 2 - 0.5)."""
    H, Wd = image.shape[:2]
    K = np.array([[focal, 0, Wd / 2 - 0.5], [0, focal, H / 2 - 0.5], [0, 0, 1]])
    cam_norm = np.array([[960.0, 0, 112], [0, 960.0, 112], [0, 0, 1]])
    warp = cam_norm @ np.diag([1, 1, 0.6 / distance_m]) @ np.linalg.inv(K)
    j, i = np.meshgrid(np.arange(224.0), np.arange(224.0))
    src = np.linalg.inv(warp) @ np.stack([j.ravel(), i.ravel(), np.ones(j.size)])
    sx, sy = src[0] / src[2], src[1] / src[2]
    x0, y0 = np.floor(sx).astype(int), np.floor(sy).astype(int)
    fx, fy = sx - x0, sy - y0
    out = np.zeros((j.size, 3))
    for dx, dy, w in ((0, 0, (1 - fx) * (1 - fy)), (1, 0, fx * (1 - fy)), (0, 1, (1 - fx) * fy), (1, 1, fx * fy)):
        xs, ys = x0 + dx, y0 + dy
        inside = (xs >= 0) & (xs < Wd) & (ys >= 0) & (ys < H)
        out[inside] += w[inside, None] * image[ys[inside], xs[inside]]
    return out.reshape(224, 224, 3)


@pytest.mark.parametrize("size, focal, distance_m", [
    (130, 130 * 0.6 / 0.26, 0.6),  # this project's normalization: 0.26 m wide at 0.6 m
    (256, 1600 * 256 / 512, 0.68),  # GazeNeRF's own images (pre_processing/data_process.py:62, 348), at half size
])
def test_preprocess_matches_the_peer_warp(size, focal, distance_m):
    g = torch.Generator().manual_seed(2)
    image = torch.rand(1, 3, size, size, generator=g)
    span = size * distance_m / focal
    x = gazenerf_preprocess(image, face_span_m=span, quantize=False)
    pixels = (x * torch.tensor(IMAGENET_STD).view(1, 3, 1, 1) + torch.tensor(IMAGENET_MEAN).view(1, 3, 1, 1)) * 255
    reference = _peer_warp_reference(image[0].permute(1, 2, 0).double().numpy() * 255, focal, distance_m)
    # float32 grid arithmetic: ~0.004 grey levels; a half-pixel shift of this noise image would miss by tens.
    np.testing.assert_allclose(pixels[0].permute(1, 2, 0).numpy(), reference, atol=1e-2)


def test_the_eval_stage_reads_with_the_peer_estimator_when_configured(peer_file, tmp_path):
    from train.config import apply_overrides
    from train.evaluation.report import ruler_note
    from train.presets import preset
    from train.stages.artifacts import RunArtifacts
    from train.stages.checks import check_config
    from train.stages.pipeline import RunContext

    path = peer_file[0]
    cfg = apply_overrides(preset("tiny"), [f"eval.estimator_path={path}"])
    check_config(cfg)
    est = RunArtifacts(RunContext(tmp_path, cfg)).estimator("eval", "cpu")
    with torch.no_grad():
        out = est(torch.rand(2, 3, 64, 64), None)
    assert out.shape == (2, 4) and torch.isfinite(out).all()  # gaze and head pose, as the protocol reads
    assert "GazeNeRF's ETH-XGaze ResNet-50" in ruler_note(cfg, tmp_path)
    with pytest.raises(ToolkitError, match=r"config key 'eval.estimator_path': .*missing.pth.tar: no such file"):
        check_config(apply_overrides(preset("tiny"), [f"eval.estimator_path={tmp_path / 'missing.pth.tar'}"]))
