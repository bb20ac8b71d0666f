"""CUDA against CPU (skipped without CUDA): the same weights and inputs give the same outputs on both devices,
training starts from the same weights and takes the same first steps, and the whole tiny pipeline runs with
``device=cuda``.

Tolerances are loose on purpose: cuDNN convolutions and CUDA matmuls may run in TF32, so the devices agree
to ~1e-3, not bitwise.
"""

import json

import pytest
import torch

from tests.train.helpers import model_inputs, small_model

pytestmark = [pytest.mark.gpu, pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")]


@pytest.fixture(autouse=True)
def _torch_splatter(monkeypatch):
    """The same code on both devices: the torch splatter on CUDA too (gsplat's agreement is tested on its own)."""
    monkeypatch.setenv("DITGAZE_SPLAT", "torch")


def _close(a: torch.Tensor, b: torch.Tensor, tol: float) -> float:
    """Max abs difference of two tensors (any devices), asserted below ``tol`` and finite."""
    a, b = a.detach().float().cpu(), b.detach().float().cpu()
    assert torch.isfinite(a).all() and torch.isfinite(b).all()
    err = float((a - b).abs().max())
    assert err < tol, err
    return err


def test_gaussian_model_renders_the_same_on_cuda():
    from toolkit.procedural import demo_head_scene

    model = small_model(demo_head_scene(400))
    code, pose, gaze, V, K = model_inputs(2)
    out_cpu = model(code, pose, gaze, V, K, 32, 32)
    model_gpu = small_model(demo_head_scene(400)).cuda()
    out_gpu = model_gpu(*(t.cuda() for t in (code, pose, gaze, V, K)), 32, 32)
    for name in ("head", "head_alpha", "eyes", "face"):
        _close(out_cpu[name], out_gpu[name], 2e-3)
    # Gradients reach the parameters on the GPU too.
    out_gpu["head"].square().mean().backward()
    grads = [p.grad for p in model_gpu.parameters() if p.grad is not None]
    assert grads and all(torch.isfinite(g).all() for g in grads)


@pytest.mark.parametrize("kind", ["dit", "baseline"])
def test_renderers_match_cpu(kind):
    from train.model.codec import AutoencoderConfig, KLAutoencoder
    from train.model.renderer import make_renderer

    torch.manual_seed(0)
    codec = KLAutoencoder(AutoencoderConfig(downsample=8, base_channels=8)).freeze() if kind == "dit" else None
    r = make_renderer(kind, codec, output_size=64).eval()
    with torch.no_grad():  # adaLN-Zero starts each DiT block as the identity: perturb so the blocks matter
        for p in r.parameters():
            if p.requires_grad:
                p.add_(0.02 * torch.randn_like(p))
    g = torch.Generator().manual_seed(1)
    feats, code = torch.randn(2, 32, 16, 16, generator=g), torch.randn(2, 144, generator=g)
    with torch.no_grad():
        a = r.render(feats, code)
        b = r.cuda().render(feats.cuda(), code.cuda())
    assert b.is_cuda and a.shape == b.shape == (2, 3, 64, 64)
    _close(a, b, 5e-3)


def test_estimator_and_codec_training_take_the_same_first_steps_on_cuda():
    from train.estimator.config import GazeEstimatorConfig, GazeEstimatorTrainConfig
    from train.estimator.training import train_gaze_estimator
    from train.model.codec import AutoencoderConfig, train_autoencoder

    g = torch.Generator().manual_seed(0)
    images = (torch.rand(16, 3, 32, 32, generator=g) * 255).to(torch.uint8)
    labels = (torch.rand(16, 4, generator=g) - 0.5) * 0.8
    cfg, tc = GazeEstimatorConfig(input_size=32), GazeEstimatorTrainConfig(steps=3, batch_size=8, log_every=1)
    # Full float32 on the GPU: TF32 convolutions would move the first loss by ~1e-3 already.
    tf32 = torch.backends.cudnn.allow_tf32, torch.backends.cuda.matmul.allow_tf32
    torch.backends.cudnn.allow_tf32 = torch.backends.cuda.matmul.allow_tf32 = False
    try:
        _, h_cpu = train_gaze_estimator(images, labels, cfg, tc)
        model, h_gpu = train_gaze_estimator(images, labels, cfg, tc, device="cuda")
        x = images.float() / 255
        ae_cfg = AutoencoderConfig(downsample=4, base_channels=8)
        _, l_cpu = train_autoencoder(x, ae_cfg, steps=3, batch_size=4)
        ae, l_gpu = train_autoencoder(x, ae_cfg, steps=3, batch_size=4, device="cuda")
    finally:
        torch.backends.cudnn.allow_tf32, torch.backends.cuda.matmul.allow_tf32 = tf32
    assert next(model.parameters()).is_cuda and next(ae.parameters()).is_cuda
    # The same initial weights and batches: the first losses agree closely. Adam turns float noise in tiny
    # gradients into whole steps, so later steps only stay near.
    assert abs(h_cpu[0]["loss"] - h_gpu[0]["loss"]) < 1e-4 * max(1.0, abs(h_cpu[0]["loss"])), (h_cpu, h_gpu)
    assert abs(l_cpu[0] - l_gpu[0]) < 1e-4, (l_cpu, l_gpu)
    for a, b in zip(h_cpu[1:], h_gpu[1:]):
        assert abs(a["loss"] - b["loss"]) < 0.03 * max(1.0, abs(a["loss"])), (h_cpu, h_gpu)
    assert max(abs(a - b) for a, b in zip(l_cpu, l_gpu)) < 0.03, (l_cpu, l_gpu)


def test_tiny_pipeline_runs_on_cuda(tmp_path):
    """Every stage with device=cuda; the trained model then renders the same on CPU and GPU."""
    pytest.importorskip("open3d")  # the geometry stage's mesh distances
    from train import run
    from train.data.dataset import GazeDataset
    from train.evaluation.figures import model_gaze_sweep
    from train.trained_run import TrainedRun

    assert run.main(["--preset", "tiny", "--run-dir", str(tmp_path), "device=cuda"]) == 0
    m = json.loads((tmp_path / "metrics.json").read_text())["metrics"]
    for k in ("gaze_error_deg", "head_pose_error_deg", "psnr", "ssim"):
        assert m[k] is not None and m[k] == m[k], k
    trained = TrainedRun.open(tmp_path)
    item = GazeDataset([trained.split("test")[0]], res=trained.config.data.res)[0]
    gazes = torch.tensor([[0.0, 0.0], [0.2, -0.3]])
    frames = []
    for device in ("cpu", "cuda"):
        model, renderer = trained.load_model(device)
        frames.append(model_gaze_sweep(model, renderer, item, gazes, trained.config.data.res, device=device))
    _close(frames[0], frames[1], 2e-2)
