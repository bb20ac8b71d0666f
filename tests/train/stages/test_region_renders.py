"""gaussian.region_renders: the face and eye terms from the head render's masks (the default) or from the face-only
and eye-only Gaussians' own renders (GazeGaussian's form), on the tiny preset's trained run."""

import copy

import pytest
import torch

from train.run_config import GaussianStageConfig
from train.trained_run import TrainedRun


class SpyRenderer(torch.nn.Module):
    """The run's renderer, recording the feature maps and targets each training pass is given."""

    def __init__(self, inner):
        super().__init__()
        self.inner, self.calls = inner, []
        self.upscale = inner.upscale

    def __getattr__(self, name):
        try:
            return super().__getattr__(name)
        except AttributeError:
            return getattr(self.inner, name)

    def training_forward(self, feats, code, target, **kw):
        self.calls.append((feats.detach().clone(), target.detach().clone()))
        return self.inner.training_forward(feats, code, target, **kw)


def _trainer(run_dir, region_renders: str, weak: bool = False):
    from train.training.trainer import GaussianTrainer, open_split

    tr = TrainedRun.open(run_dir)
    torch.manual_seed(0)
    model, renderer = tr.build_model("cpu")
    data = open_split(tr.split("train"), "all", tr.config.data.res)
    cfg = GaussianStageConfig(batch=2, region_renders=region_renders, weak_supervision=weak)
    spy = SpyRenderer(renderer)
    return GaussianTrainer(cfg, model, spy, tr.estimator("loss", "cpu"), data, torch.device("cpu"), 4), spy


def _batch(trainer, seed: int):
    """The rows ``trainer.step`` draws first with a generator seeded ``seed``."""
    idx = torch.randint(0, len(trainer.data), (trainer.cfg.batch,), generator=torch.Generator().manual_seed(seed))
    return trainer.data.take(idx, "cpu")


def _only(model, keep: str):
    """A copy of ``model`` whose other stream's Gaussians are transparent (opacity logits -1e4)."""
    m = copy.deepcopy(model)
    with torch.no_grad():
        (m.eye_opacity_logits if keep == "face" else m.face_opacity_logits).fill_(-1e4)
    m.clear_cache()
    return m


def test_separate_renders_the_face_without_the_eyes_and_the_eyes_without_the_face(tiny_run):
    trainer, spy = _trainer(tiny_run, "separate")
    try:
        terms = trainer.step(0, torch.Generator().manual_seed(3))
        b = _batch(trainer, 3)
    finally:
        trainer.data.close()
    assert [k for k in ("rgb_face", "rgb_eyes", "diffusion_face", "diffusion_eyes") if k in terms] == \
        ["rgb_face", "rgb_eyes", "diffusion_face", "diffusion_eyes"]
    assert all(torch.isfinite(v).all() for v in terms.values())
    terms["total"].backward()
    grads = [p.grad for p in trainer.model.parameters() if p.grad is not None]
    assert grads and all(torch.isfinite(g).all() for g in grads)
    assert trainer.model.face_field.expr_mlp.last.weight.grad.abs().sum() > 0
    # head, face-only, eye-only: three renders, the last two against the target on white outside their region
    assert len(spy.calls) == 3
    R = trainer.data.res
    args = (b["code"], b["pose"], b["gaze_head"], b["viewmat"], b["K"], R, R)
    model = trainer.model
    with torch.no_grad():
        ref = model(*args)
        face_alone = _only(model, "face")(*args, renders=("head",))
        eyes_alone = _only(model, "eyes")(*args, renders=("head",))
    assert torch.allclose(spy.calls[0][0], ref["head"], atol=1e-5)
    assert torch.allclose(spy.calls[1][0], ref["face"], atol=1e-5)
    assert torch.allclose(spy.calls[2][0], ref["eyes"], atol=1e-5)
    # the face-only render is the head with its eye Gaussians removed, the eye-only one the head without its face
    assert torch.allclose(ref["face"], face_alone["head"], atol=1e-4)
    assert torch.allclose(ref["eyes"], eyes_alone["head"], atol=1e-4)
    covered = lambda a: (a > 0.5).float().sum()  # noqa: E731
    assert covered(ref["head_alpha"]) > covered(ref["eyes_alpha"]) > 0  # the eyes: a few pixels of the head
    assert float((ref["head_alpha"] - ref["face_alpha"]).max()) > 0.1  # where the eyes were, the face lets light through
    masks = {"face": (b["head"] - b["eyes"] * b["head"]).clamp(0, 1), "eyes": b["eyes"] * b["head"]}
    for (_, target), r in zip(spy.calls[1:], ("face", "eyes")):
        assert torch.equal(target, b["image"] * masks[r] + (1 - masks[r]))


def test_masks_renders_the_head_alone(tiny_run):
    trainer, spy = _trainer(tiny_run, "masks")
    try:
        terms = trainer.step(0, torch.Generator().manual_seed(3))
    finally:
        trainer.data.close()
    assert len(spy.calls) == 1 and not any(k.endswith(("_face", "_eyes")) for k in terms)
    assert torch.isfinite(terms["total"])


@pytest.mark.parametrize("region_renders", ["separate"])
def test_the_region_terms_stay_finite_on_empty_regions_and_extreme_inputs(tiny_run, region_renders):
    """Stress: no eye (or face) pixel in the masks, and codes far outside the data's range: finite losses and
    gradients."""
    trainer, _ = _trainer(tiny_run, region_renders)
    take = trainer.data.take

    def extreme(idx, device):
        b = take(idx, device)
        b["eyes"] = torch.zeros_like(b["eyes"])
        b["code"] = b["code"] * 1e3
        return b

    trainer.data.take = extreme
    try:
        terms = trainer.step(0, torch.Generator().manual_seed(1))
        terms["total"].backward()
    finally:
        trainer.data.close()
    assert all(torch.isfinite(v).all() for v in terms.values())
    assert all(torch.isfinite(p.grad).all() for p in trainer.model.parameters() if p.grad is not None)
