"""Small shared pieces of the train/ tests: a tiny model on the procedural head, inputs, the rasterizer."""

from __future__ import annotations

import torch

from toolkit.procedural import demo_camera
from train.model.gaussian_model import GaussianModel, GaussianModelConfig


def rasterizer_for_tests():
    """``render.splat.rasterize`` (the project's torch splatter)."""
    from render.splat import rasterize

    return rasterize


def small_model(scene, seed: int = 0, **overrides) -> GaussianModel:
    cfg = GaussianModelConfig(hidden=32, depth=3, **overrides)
    torch.manual_seed(seed)
    return GaussianModel.from_scene(scene, cfg, rasterizer=rasterizer_for_tests())


def model_inputs(batch: int, seed: int = 0, width: int = 64, height: int = 64):
    """(code [B, 144], pose [B, 6] zeros, gaze [B, 2], viewmats [B, 4, 4], Ks [B, 3, 3]) for a frontal camera."""
    g = torch.Generator().manual_seed(seed)
    code = torch.randn(batch, 144, generator=g) * 0.5
    pose = torch.zeros(batch, 6)
    gaze = (torch.rand(batch, 2, generator=g) - 0.5) * 0.6
    cam = demo_camera(width, height)
    return code, pose, gaze, cam.viewmat.expand(batch, 4, 4).clone(), cam.K.expand(batch, 3, 3).clone()


def fit_renderer(renderer, feats: torch.Tensor, code: torch.Tensor, target: torch.Tensor, g: torch.Generator,
                 steps: int, lr: float = 3e-3) -> float:
    """Train ``renderer.dit`` on one batch (its own loss + L1 on the image) -> the L1 error of a render after."""
    opt = torch.optim.Adam(renderer.dit.parameters(), lr=lr)
    for _ in range(steps):
        out = renderer.training_forward(feats, code, target, generator=g)
        loss = out.aux_loss + (out.image - target).abs().mean()
        opt.zero_grad()
        loss.backward()
        opt.step()
    with torch.no_grad():
        return float((renderer.render(feats, code) - target).abs().mean())


def one_frame_subject_file(directory, subject_seed: int, frame_seed: int, res: int = 64, n_frames: int = 1):
    """A synthetic subject file (``n_frames`` frames x 18 rig cameras) in ``directory``; skips the calling test
    where no headless EGL OpenGL context exists."""
    from tests.gl import require_gl
    from train.data.format import write_subject_h5
    from train.data.generate import generate_subject
    from train.data.synthetic import SubjectParams

    require_gl()
    rows, subj, attrs = generate_subject(SubjectParams.sample(subject_seed), n_frames=n_frames, res=res, seed=frame_seed)
    return write_subject_h5(directory / "subject0000.h5", rows, subject=subj, attrs=attrs)


def untrained_eval_parts():
    """(model on the procedural head, U-Net baseline renderer, whole-face gaze estimator), untrained, seeded:
    what ``train.evaluation.protocol`` needs, in eval mode."""
    from toolkit.procedural import demo_head_scene
    from train.estimator.config import GazeEstimatorConfig
    from train.estimator.network import GazeEstimator
    from train.model.renderer import make_renderer

    torch.manual_seed(0)
    model = GaussianModel.from_scene(demo_head_scene(300), GaussianModelConfig(hidden=16)).eval()
    return model, make_renderer("baseline").eval(), GazeEstimator(GazeEstimatorConfig(input_size=32)).eval()


def save_state_file(path, state: dict):
    """Write a state dict as a user's weight file: ``.safetensors``, else a torch ``.pth`` (returns the path)."""
    from toolkit.io import save_tensors

    if path.suffix == ".safetensors":
        save_tensors(path, state)
    else:
        torch.save(state, path)
    return path
