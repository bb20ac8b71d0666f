"""Stage gaussian: resuming, the weight average, the splat size, pixel-space DiT, parametric eyeballs, torchrun."""

import json
import shutil
from pathlib import Path

import pytest
import torch

from toolkit import ToolkitError
from train import run
from train.trained_run import TrainedRun

TINY = ["--preset", "tiny"]
ROOT = Path(__file__).resolve().parents[3]


def test_a_resume_under_another_config_is_refused(tiny_run, tmp_path):
    """The Gaussian stage's checkpoints carry the training's fingerprint (the seed, the stage's config but its
    step counts, the upstream stages'): --resume under another one is refused instead of loading another
    training's weights; more steps resume."""
    d = tmp_path / "run"
    shutil.copytree(tiny_run, d)
    args = [*TINY, "--run-dir", str(d), "--stages", "gaussian"]
    assert run.main([*args, "--force", "gaussian", "gaussian.steps=2"]) == 0
    with pytest.raises(ToolkitError, match=r"ckpt_00000002.safetensors: written by a run under another config"):
        run.main([*args, "--resume", "gaussian.steps=4", "gaussian.lr=0.01"])
    assert run.main([*args, "--resume", "gaussian.steps=4", "gaussian.ckpt_every=1"]) == 0


@pytest.mark.parametrize("average", [[], ["gaussian.ema_decay=0.75"]], ids=["last", "ema"])
def test_resumed_gaussian_stage_reproduces_uninterrupted(tiny_run, tmp_path, average):
    from train.training.checkpoint import CheckpointManager

    full = tmp_path / "full"
    shutil.copytree(tiny_run, full)
    part = tmp_path / "part"
    shutil.copytree(tiny_run, part)
    args = ["--stages", "gaussian", "--force", "gaussian", "gaussian.steps=4", "gaussian.ckpt_every=2", *average]
    assert run.main([*TINY, "--run-dir", str(full), *args, "gaussian.ckpt_every=1"]) == 0  # keeps steps 3 and 4
    shutil.rmtree(part / "gaussian")
    # A "crash" after step 2: run the 4-step schedule, keep only its step-2 checkpoint, and resume from it.
    mgr = CheckpointManager(part / "gaussian" / "checkpoints")
    assert run.main([*TINY, "--run-dir", str(part), *args, "gaussian.log_every=2"]) == 0
    for p in mgr.all():
        if not p.name.endswith("0002.safetensors"):
            p.unlink()
    log = part / "metrics.jsonl"
    logged = lambda: [json.loads(line)["time"] for line in log.read_text().splitlines()  # noqa: E731
                      if json.loads(line)["stage"] == "gaussian"]
    before = logged()
    assert run.main([*TINY, "--run-dir", str(part), "--resume", *args, "gaussian.log_every=2"]) == 0
    # It went on from step 2: step 2's record stays, step 4's is logged anew in place of the crashed run's (a
    # retrain from step 0 would match the weights too), and no step is logged twice.
    after = logged()
    assert len(before) == len(after) == 2 and after[0] == before[0] and after[1] > before[1]
    from toolkit.io import load_tensors

    a, _ = load_tensors(full / "gaussian" / "final.safetensors")
    b, _ = load_tensors(part / "gaussian" / "final.safetensors")
    weights = [k for k in a if k.startswith("module/")]
    assert weights and all(torch.equal(a[k], b[k]) for k in weights)
    before_last, last = (load_tensors(p)[0] for p in CheckpointManager(full / "gaussian" / "checkpoints").all()[-2:])
    moved = [k for k in weights if not torch.equal(last[k], a[k])]
    if not average:  # the final model is the last step's
        assert not moved and not any(k.startswith("module/ema_") for k in last)
        return
    # With the average, the final model is the checkpoint's average, which lags the last step's weights ...
    assert all(torch.equal(a[k], last[k.replace("module/", "module/ema_", 1)]) for k in weights)
    assert any(k.startswith("module/model/") for k in moved) and any(k.startswith("module/renderer/") for k in moved)
    model, renderer = TrainedRun.open(full).load_model("cpu")
    assert torch.equal(model.state_dict()["face_means"], a["module/model/face_means"])
    assert load_tensors(full / "gaussian" / "final.safetensors")[1]["extra"]["ema_decay"] == 0.75
    # A checkpoint written without the average cannot resume with one: the error names the key.
    none = tmp_path / "none"
    shutil.copytree(tiny_run, none)
    assert run.main([*TINY, "--run-dir", str(none), "--stages", "gaussian", "--force", "gaussian", "gaussian.steps=2"]) == 0
    with pytest.raises(ToolkitError, match="written without a weight average.*gaussian.ema_decay=0.75"):
        run.main([*TINY, "--run-dir", str(none), "--resume", "--stages", "gaussian", "gaussian.steps=4", *average])
    # ... by exactly one update of decay 0.75 per step (not 0.25, not two, not none), after that step's optimizer
    # step; frozen weights (the codec) are copied as they are.
    trained = {f"module/{m}/{n}" for m, mod in (("model", model), ("renderer", renderer))
               for n, p in mod.named_parameters() if p.requires_grad}
    assert trained and len(trained) < len(weights)
    for k in weights:
        ema = k.replace("module/", "module/ema_", 1)
        if k in trained:
            expect = before_last[ema].clone().mul_(0.75).add_(last[k], alpha=0.25)
        else:
            expect = last[k] if k in last else a[k]
        assert torch.equal(last[ema], expect), k


@pytest.mark.parametrize("renderer,upscale", [("dit", 1), ("unet", 1), ("dit", 2), ("unet", 2), ("dit", 4)])
def test_feature_upscale_sets_the_splat_size(tiny_run, tmp_path, renderer, upscale):
    d = tmp_path / renderer
    shutil.copytree(tiny_run, d)
    over = [f"gaussian.renderer={renderer}", f"gaussian.feature_upscale={upscale}", "gaussian.steps=2",
            "eval.pairs_per_subject=1"]
    assert run.main([*TINY, "--run-dir", str(d), "--stages", "gaussian,eval", *over]) == 0
    ctx = TrainedRun.open(d)
    model, renderer_ = ctx.load_model("cpu")
    res = ctx.config.data.res
    assert renderer_.upscale == upscale and model.config.render_scale == 1 / upscale
    vm = torch.eye(4)[None].clone()
    vm[0, 2, 3] = 1.0  # the head 1 m in front of the camera
    K = torch.tensor([[[2.0 * res, 0, res / 2], [0, 2.0 * res, res / 2], [0, 0, 1]]])
    with torch.no_grad():
        maps = model(torch.zeros(1, 144), torch.zeros(1, 6), torch.zeros(1, 2), vm, K, res, res, renders=("head",))
        image = renderer_.render(maps["head"], torch.zeros(1, 144))
    assert maps["head"].shape[-2:] == (res // upscale, res // upscale) and image.shape[-2:] == (res, res)
    m = json.loads((d / "metrics.json").read_text())["metrics"]
    assert m["psnr"] == m["psnr"] and m["gaze_error_deg"] == m["gaze_error_deg"]


def test_pixel_space_dit_runs_without_a_codec(tiny_run, tmp_path):
    from train.model.codec import PixelCodec

    d = tmp_path / "pixel"
    shutil.copytree(tiny_run, d)
    over = ["codec.kind=pixel", "gaussian.dit_model=DiT-Gaze-pixel", "gaussian.steps=2", "eval.pairs_per_subject=1",
            "gaussian.dit_feature_hidden=8"]
    assert run.main([*TINY, "--run-dir", str(d), "--stages", "codec,gaussian,eval", *over]) == 0
    _, renderer = TrainedRun.open(d).load_model("cpu")
    assert isinstance(renderer.codec, PixelCodec) and renderer.dit.config.patch_size == 8
    assert renderer.dit.feature_encoder.conv_in.out_channels == 8  # gaussian.dit_feature_hidden
    m = json.loads((d / "metrics.json").read_text())
    assert m["metrics"]["psnr"] == m["metrics"]["psnr"] and len(m["per_pair"]) == m["metrics"]["pairs"]
    # No codec: the report scores no "through the codec" reference (it would be the target itself).
    assert list(m["references"]) == ["target at half resolution"]


def test_demo_preset_renders_in_pixel_space_at_its_resolution():
    from train.model.codec import PixelCodec
    from train.model.renderer import make_renderer
    from train.presets import preset
    from train.run_config import RunConfig

    cfg = preset("demo")
    g, res = cfg.gaussian, cfg.data.res
    assert (cfg.codec.kind, g.dit_model, cfg.estimator.steps) == ("pixel", "DiT-Gaze-pixel", 1200)
    assert (g.steps, cfg.eval.tta_steps) == (240, 30)  # sized for the slowest 2-core machine measured
    # The natural fit (the gaze term only turns the eyes), and the Gaussian stage at twice the rates.
    from train.presets import NATURAL_EYES_FIT

    assert (cfg.eval.tta_weights, cfg.eval.tta_gaze_weight, cfg.eval.tta_gaze_reach, cfg.eval.tta_gaze_terms,
            cfg.eval.tta_gaze_every) == tuple(NATURAL_EYES_FIT[k] for k in ("weights", "gaze_weight", "reach",
                                                                           "terms", "every"))
    assert (g.lr, g.renderer_lr) == (4e-3, 1e-3)
    assert g.eyeball_colours and not g.eye_appearance  # the eyes' RGB is a parametric eyeball
    assert cfg.geometry.gaussians == 12_000  # a sharper splat
    # The preset alone changed: the dataclass defaults and the paper preset keep the latent DiT.
    plain = RunConfig()
    assert (plain.codec.kind, plain.gaussian.dit_model, plain.estimator.steps) == ("ae", "DiT-Gaze-tiny", 1000)
    assert preset("paper").codec.kind == "ae" and not plain.gaussian.eyeball_colours
    renderer = make_renderer("dit", PixelCodec(), model=g.dit_model, output_size=res, upscale=g.feature_upscale,
                             residual=g.residual)
    assert renderer.dit.config.patch_size == 8
    feats = torch.rand(1, renderer.dit.config.feature_channels, res // g.feature_upscale, res // g.feature_upscale)
    with torch.no_grad():
        image = renderer.render(feats, torch.zeros(1, renderer.dit.config.shape_dim))
    assert image.shape == (1, 3, res, res) and torch.isfinite(image).all()
    # The untrained residual renderer returns the splat's own RGB: the DiT starts from the splat's image.
    assert torch.allclose(image, feats[:, :3].clamp(0, 1), atol=1e-5)


def _gaussian_weights(run_dir):
    from safetensors.torch import load_file

    return load_file(str(run_dir / "gaussian" / "final.safetensors"))


@pytest.mark.skipif(not torch.distributed.is_available() or not torch.distributed.is_gloo_available(),
                    reason="torch.distributed/gloo unavailable")
def test_gaussian_stage_in_two_torchrun_processes_equals_one_process(tiny_run, tmp_path):
    """torchrun with 2 CPU processes (gloo): each takes half of the global batch (and the same rows of every random
    draw) and the gradients are averaged, so the trained weights equal one process's on the whole batch up to
    float sums. A rank that trained alone on its shard, or on the whole batch, ends far from them."""
    import os
    import subprocess
    import sys

    runs = {}
    for name, launcher in (("one", [sys.executable]),
                           ("two", [sys.executable, "-m", "torch.distributed.run", "--standalone", "--nproc_per_node=2"])):
        d = tmp_path / name
        shutil.copytree(tiny_run, d)
        cmd = [*launcher, "-m", "train.run", "--config", str(d / "config.yaml"), "--run-dir", str(d),
               "--stages", "gaussian", "--force", "gaussian"]
        env = {**os.environ, "OMP_NUM_THREADS": "1"}  # one thread per process, as torchrun gives each rank
        r = subprocess.run(cmd, cwd=ROOT, capture_output=True, text=True, timeout=300, env=env)
        if r.returncode != 0 and "terminate called without an active exception" in r.stderr:
            r = subprocess.run(cmd, cwd=ROOT, capture_output=True, text=True, timeout=300, env=env)  # gloo teardown race
        assert r.returncode == 0, r.stderr[-3000:]
        # rank 0 alone logs: one "running" line and one closing JSON line, whatever the process count
        assert r.stdout.count("[gaussian] running") == 1 and r.stdout.count('"run_dir"') == 1, r.stdout[-2000:]
        runs[name] = _gaussian_weights(d)
    from safetensors.torch import load_file

    first = load_file(str(sorted((tmp_path / "one" / "gaussian" / "checkpoints").glob("*.safetensors"))[0]))
    moved = max(float((runs["one"][k].float() - first[k].float()).abs().max()) for k in runs["one"] if k in first)
    assert moved > 1e-3  # the last steps moved the weights far more than the tolerance below
    worst = max(float((runs["one"][k].float() - runs["two"][k].float()).abs().max()) for k in runs["one"])
    assert worst < 1e-4, worst
    # ... and the work was split: rank 0 logged the loss of its half of the batch, not the whole batch's.
    last = {name: [json.loads(x) for x in (tmp_path / name / "metrics.jsonl").read_text().splitlines()
                   if json.loads(x).get("stage") == "gaussian"][-1] for name in runs}
    assert last["one"]["step"] == last["two"]["step"] and abs(last["one"]["image"] - last["two"]["image"]) > 1e-4


def test_parametric_eyeballs_train_save_and_fit_through_the_stages(tiny_run, tmp_path):
    d = tmp_path / "eyeballs"
    shutil.copytree(tiny_run, d)
    over = ["gaussian.eyeball_colours=true", "gaussian.steps=2", "eval.pairs_per_subject=1",
            "eval.tta_weights=[features,eye_colours]"]
    assert run.main([*TINY, "--run-dir", str(d), "--stages", "gaussian,eval", *over]) == 0
    model, _ = TrainedRun.open(d).load_model("cpu")
    assert model.eyeball_colours is not None
    start = torch.logit(torch.tensor(0.92))  # EyeballColours' sclera prior, before training
    assert not torch.allclose(model.eyeball_colours.sclera.detach(), start.expand(3))  # trained
    m = json.loads((d / "metrics.json").read_text())["metrics"]
    assert m["psnr"] == m["psnr"] and m["gaze_error_deg"] == m["gaze_error_deg"]
    assert "the eyeball's colours" in (d / "report.md").read_text()
