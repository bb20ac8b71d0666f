"""The CLI (python -m train.run): stage selection and skipping, config errors before any work, torchrun, reruns."""

import json
import shutil

import pytest
import torch

from toolkit import ToolkitError
from train import run
from train.presets import PRESETS, preset
from train.stages.checks import check_config

TINY = ["--preset", "tiny"]


def test_unchanged_stages_are_skipped_and_changes_rerun_downstream(tiny_run, tmp_path, capsys):
    d = tmp_path / "run"
    shutil.copytree(tiny_run, d)  # the shared run stays as it is
    assert run.main([*TINY, "--run-dir", str(d), "--stages", "all"]) == 0
    status = json.loads(capsys.readouterr().out.strip().splitlines()[-1])["stages"]
    assert set(status.values()) == {"skipped"}
    assert run.main([*TINY, "--run-dir", str(d), "--stages", "eval", "eval.pairs_per_subject=1"]) == 0
    status = json.loads(capsys.readouterr().out.strip().splitlines()[-1])["stages"]
    assert status == {"eval": "ran"}


@pytest.mark.parametrize(
    "override,msg",
    [
        ("gaussian.stepz=3", "unknown config key 'gaussian.stepz'; did you mean 'steps'"),
        ("gaussian.steps=many", "'gaussian.steps': expected an integer"),
        ("gaussian.renderer=gan", "'gaussian.renderer': expected one of"),
        ("colour=red", "unknown config key 'colour'"),
        ("codec.eye_weight=-1", "'codec.eye_weight': expected a weight >= 0"),
        ("eval.tta_renderer_lr=0", "'eval.tta_renderer_lr': expected a learning rate in \\(0, 1\\]"),
        ("eval.tta_gaze_weight=-1", "'eval.tta_gaze_weight': expected a weight >= 0"),
        ("eval.tta_gaze_terms=[eyes]", "'eval.tta_gaze_terms"),
        ("eval.tta_gaze_every=0", "'eval.tta_gaze_every': expected a step count >= 1"),
        ("eval.tta_gaze_reach=[eyes]", "eval.tta_gaze_reach.0.': expected one of"),  # the list's item [0]
        ("eval.tta_gaze_reach=[eye_field]", "'eval.tta_gaze_reach': the gaze term may reach only the code and"),
        ("gaussian.feature_upscale=3", "'gaussian.feature_upscale': expected a power of two"),
        ("geometry.eye_gaussians=2", "'geometry.eye_gaussians': expected 0"),
        ("geometry.lid_gaussians=-1", "'geometry.lid_gaussians': expected 0"),
        ("estimator.blur_prob=1.5", "'estimator.blur_prob': expected a probability"),
        ("estimator.blur_sigma=-1", "'estimator.blur_sigma': expected a width >= 0"),
        ("estimator.blur_prob=-0.1", "'estimator.blur_prob': expected a probability"),
        ("data.test_frames=-1", "'data.test_frames': expected 0"),
        ("data.test_frames=3", "'data.test_frames': expected 0"),
        ("data.test_frames=0", "'data.frames': with data.test_frames=0 the held-out subjects get data.frames frames, "
                               "which must be even"),
        ("data.test_fraction=1.5", "'data.test_fraction': expected a share"),
        ("gaussian.onestep_fraction=1.5", "'gaussian.onestep_fraction': expected a share in"),
        ("gaussian.lr_final=-0.1", "'gaussian.lr_final': expected a factor in"),
        ("gaussian.ema_decay=1", "'gaussian.ema_decay': expected a decay in"),
        ("gaussian.dit_feature_hidden=0", "'gaussian.dit_feature_hidden': expected a channel count"),
        ("gaussian.lr_schedule=linear", "'gaussian.lr_schedule': expected one of"),
        ("eval.tta_weights=[features,eye_colours]", "'eval.tta_weights': 'eye_colours' needs gaussian.eyeball_colours"),
        ("gaussian.lr=-1", "'gaussian.lr': expected a learning rate in \\(0, 1\\]"),
        ("gaussian.renderer_lr=0", "'gaussian.renderer_lr': expected a learning rate in \\(0, 1\\]"),
        ("gaussian.means_lr=-1e-4", "'gaussian.means_lr': expected a learning rate in \\(0, 1\\]"),
        ("gaussian.lr=.nan", "'gaussian.lr': expected a finite number"),
        ("gaussian.weak_weight=.inf", "'gaussian.weak_weight': expected a finite number"),
        ("gaussian.steps=0", "'gaussian.steps': expected a count >= 1"),
        ("gaussian.batch=0", "'gaussian.batch': expected a count >= 1"),
        ("estimator.steps=-5", "'estimator.steps': expected a count >= 1"),
        ("eval.pairs_per_subject=0", "'eval.pairs_per_subject': expected a count >= 1"),
        ("gaussian.ckpt_every=0", "'gaussian.ckpt_every': expected a count >= 1"),
        ("gaussian.log_every=0", "'gaussian.log_every': expected a count >= 1"),
        ("gaussian.grad_clip=-1", "'gaussian.grad_clip': expected a gradient-norm bound >= 0"),
        ("eval.sweep_frames=0", "'eval.sweep_frames': expected a count >= 1"),
        ("geometry.subject=-1", "'geometry.subject': expected a training-subject index >= 0"),
        ("eval.pairing_file=/nonexistent/pairs.json", "'eval.pairing_file': "),
        ("eval.tta_steps=-1", "'eval.tta_steps': expected a step count >= 0"),
        ("device=tpu", "'device': expected auto, cpu, cuda or cuda:N"),
        ("data.subjects=1", "'data.subjects': expected >= 2 synthetic subjects"),
        ("data.frames=0", "'data.frames': expected a count >= 1"),
        ("data.res=8", "'data.res': expected an image size in"),
        ("geometry.gaussians=0", "'geometry.gaussians': expected a count >= 1"),
        ("geometry.pool=0", "'geometry.pool': expected a count >= 1"),
        ("codec.base_channels=0", "'codec.base_channels': expected a count >= 1"),
        ("estimator.synthetic_frames=0", "'estimator.synthetic_frames': expected a count >= 1"),
        ("gaussian.sampling_steps=0", "'gaussian.sampling_steps': expected a count >= 1"),
        ("gaussian.gaussians_hidden=0", "'gaussian.gaussians_hidden': expected a count >= 1"),
        ("geometry.pretrain_steps=-1", "'geometry.pretrain_steps': expected a finite value >= 0"),
        ("estimator.synthetic_subjects=-2", "'estimator.synthetic_subjects': expected a finite value >= 0"),
        ("gaussian.lambda_gaze=-0.1", "'gaussian.lambda_gaze': expected a finite value >= 0"),
        ("gaussian.ortho_weight=-1", "'gaussian.ortho_weight': expected a finite value >= 0"),
        ("geometry.extract_res=2", "'geometry.extract_res': expected a tet-grid resolution in"),
        ("geometry.extract_res=1024", "'geometry.extract_res': expected a tet-grid resolution in"),
        ("gaussian.sampler_range_deg=0", "'gaussian.sampler_range_deg': expected"),
        ("gaussian.sampler_range_deg=95", "'gaussian.sampler_range_deg': expected"),
        ("data.light_jitter=-0.5", "'data.light_jitter': expected a value in"),
        ("codec.downsample=3", "'codec.downsample': expected a power of two dividing"),
        ("seed=-1", "'seed': expected a seed >= 0"),
        ("data.seed=-3", "'data.seed': expected a seed >= 0"),
        ("seed=18446744073709551616", "'seed': expected a seed below 2\\^32"),
        ("threads=100000000000", "'threads': expected a thread count in \\[0, 1024\\]"),
        ("geometry.gaussians=8", "'geometry.gaussians': expected >= 16"),
        ("geometry.pool=2", "'geometry.pool': expected >= 1000"),
        ("estimator.cameras_per_frame=40", "'estimator.cameras_per_frame': expected at most the rig's"),
        ("gaussian.sampling_steps=2000", "'gaussian.sampling_steps': expected at most the diffusion's 1000"),
        ("gaussian.lr=1e39", r"'gaussian.lr': expected a learning rate in \(0, 1\], got 1e\+39"),
        ("eval.tta_renderer_lr=2", r"'eval.tta_renderer_lr': expected a learning rate in \(0, 1\]"),
        ("gaussian.dit_model=foo", "'gaussian.dit_model': expected one of .*got 'foo'"),
        ("estimator.loss_path=/nonexistent/loss.safetensors", "'estimator.loss_path': /nonexistent/loss.safetensors: "
                                                              "no such file"),
        ("estimator.eval_path=nope.safetensors", "'estimator.eval_path': nope.safetensors: no such file"),
        ("codec.kind=sd-vae", "'codec.sd_vae_path': '': no such directory"),
        ("gaussian.steps=010", "override 'gaussian.steps=010': '010' would read as a base-8"),
        ("eval.sampling_steps=-1", r"'eval.sampling_steps': expected 0 \(gaussian.sampling_steps\) or a DDIM step"),
        ("eval.sampling_steps=1001", "'eval.sampling_steps': expected at most the diffusion's 1000 timesteps"),
    ],
)
def test_bad_config_fails_before_any_work(tmp_path, capsys, override, msg):
    from toolkit.errors import run_cli

    d = tmp_path / "never"
    assert run_cli(run.main, [*TINY, "--run-dir", str(d), override]) == 2
    err = capsys.readouterr().err
    assert err.startswith("error: ") and msg.split("'")[1] in err and err.count("\n") == 1
    assert not d.exists()
    with pytest.raises(ToolkitError, match=msg):
        run.main([*TINY, "--run-dir", str(d), override])


@pytest.mark.parametrize(
    "overrides, msg",
    [
        (["codec.kind=sd-vae", "codec.sd_vae_path=x", "data.res=36"], "'data.res': the SD-VAE codec downsamples 8x"),
        (["estimator.crop=face", "estimator.input_size=8"], "'estimator.input_size': GazeEstimatorConfig: input"),
        (["estimator.crop=eye_band", "estimator.input_size=20"], "'estimator.input_size': GazeEstimatorConfig: input"),
        (["eval.lpips_vgg_path=/nonexistent/vgg16.pth"], r"LPIPS needs both files"),
        (["eval.lpips_lin_path=/nonexistent/vgg.pth"], r"LPIPS needs both files"),
        (["eval.lpips_vgg_path=/nonexistent/a.pth", "eval.lpips_lin_path=/nonexistent/b.pth"],
         "'eval.lpips_vgg_path': /nonexistent/a.pth: no such file"),
        (["eval.identity_model_path=/nonexistent/backbone.pth"], "'eval.identity_model_path': /nonexistent/backbone"),
        (["eval.identity_arch=iresnet7"], "'eval.identity_arch': expected one of"),
    ],
)
def test_settings_that_fail_together_fail_before_any_work(tmp_path, overrides, msg):
    d = tmp_path / "never"
    with pytest.raises(ToolkitError, match=msg):
        run.main([*TINY, "--run-dir", str(d), *overrides])
    assert not d.exists()


def test_an_eye_patch_estimator_ignores_input_size():
    cfg = preset("tiny")
    cfg.estimator.crop, cfg.estimator.input_size = "eyes", 8
    check_config(cfg)


@pytest.mark.parametrize("name", sorted(PRESETS))
def test_every_preset_passes_the_value_checks(name, monkeypatch):
    monkeypatch.setenv("DITGAZE_MEMORY_GB", "64")  # the paper preset's arrays need a larger machine than CI's
    check_config(preset(name))


def test_the_paper_preset_states_what_memory_it_needs(monkeypatch):
    monkeypatch.setenv("DITGAZE_MEMORY_GB", "16")
    with pytest.raises(ToolkitError, match=r"estimator.synthetic_subjects.*would allocate 35.2 GiB"):
        check_config(preset("paper"))


def test_lids_without_dense_eyes_fail_before_any_work(tmp_path):
    d = tmp_path / "never"
    with pytest.raises(ToolkitError, match="'geometry.lid_gaussians': expected 0, or > 0 with geometry.eye_gaussians > 0, "
                                           "got 100 with geometry.eye_gaussians=0"):
        run.main([*TINY, "--run-dir", str(d), "geometry.lid_gaussians=100", "geometry.eye_gaussians=0"])
    assert not d.exists()


def test_two_sources_of_eye_colour_fail_before_any_work(tmp_path):
    d = tmp_path / "never"
    with pytest.raises(ToolkitError, match="'gaussian.eyeball_colours' and 'gaussian.eye_appearance' both"):
        run.main([*TINY, "--run-dir", str(d), "gaussian.eyeball_colours=true", "gaussian.eye_appearance=true"])
    assert not d.exists()


@pytest.mark.parametrize("no_decoder", ["codec.kind=pixel", "gaussian.renderer=unet"])
def test_fitting_a_decoder_that_is_not_there_fails_before_any_work(tmp_path, capsys, no_decoder):
    from toolkit.errors import run_cli

    d = tmp_path / "never"
    assert run_cli(run.main, [*TINY, "--run-dir", str(d), no_decoder, "eval.tta_weights=[features,decoder]"]) == 2
    err = capsys.readouterr().err
    assert err.startswith("error: config key 'eval.tta_weights'") and err.count("\n") == 1
    with pytest.raises(ToolkitError, match="'eval.tta_weights': 'decoder' needs a codec decoder"):
        run.main([*TINY, "--run-dir", str(d), no_decoder, "eval.tta_weights=[features,decoder]"])
    assert not d.exists()


def test_unknown_stage_and_missing_dataset(tmp_path):
    with pytest.raises(ToolkitError, match="unknown stage"):
        run.main([*TINY, "--run-dir", str(tmp_path), "--stages", "train"])
    with pytest.raises(ToolkitError, match=r"--force: unknown stage\(s\) \['evl'\]"):
        run.main([*TINY, "--run-dir", str(tmp_path / "never"), "--stages", "eval", "--force", "evl"])
    with pytest.raises(ToolkitError, match=r"--force: stage\(s\) \['gaussian'\] are not among --stages eval"):
        run.main([*TINY, "--run-dir", str(tmp_path / "never"), "--stages", "eval", "--force", "gaussian"])
    assert not (tmp_path / "never").exists()
    with pytest.raises(ToolkitError, match="data.root"):
        run.main([*TINY, "--run-dir", str(tmp_path), "--stages", "data", f"data.root={tmp_path / 'nope'}"])


def test_torchrun_runs_the_gaussian_stage_alone(tmp_path, monkeypatch):
    monkeypatch.setenv("WORLD_SIZE", "2")
    for stages in ("all", "gaussian,eval", "data"):
        with pytest.raises(ToolkitError, match="only stage gaussian is distributed"):
            run.main([*TINY, "--run-dir", str(tmp_path / "r"), "--stages", stages])
    assert not (tmp_path / "r" / "config.yaml").exists()  # refused before any work


def test_a_stage_rerun_continues_the_runs_config_and_a_refused_run_leaves_it_alone(tiny_run, tmp_path):
    d = tmp_path / "run"
    shutil.copytree(tiny_run, d)
    before = (d / "config.yaml").read_bytes()
    # Another preset's config: its gaussian fingerprint differs, so eval is refused, naming why, before any write.
    with pytest.raises(ToolkitError, match="made under another config"):
        run.main(["--preset", "demo", "--run-dir", str(d), "--stages", "eval"])
    assert (d / "config.yaml").read_bytes() == before
    # A selection refused because a stage it re-runs would leave another one it reads stale: also before the write.
    with pytest.raises(ToolkitError, match="select 'geometry' too"):
        run.main(["--run-dir", str(d), "--stages", "data,gaussian", "--force", "data", "gaussian.steps=8"])
    assert (d / "config.yaml").read_bytes() == before
    # Never run at all: the other message.
    with pytest.raises(ToolkitError, match="which has not run"):
        run.main(["--preset", "tiny", "--run-dir", str(tmp_path / "empty"), "--stages", "eval"])
    assert not (tmp_path / "empty").exists()
    # No --preset and no --config: the run's own config.yaml, with the overrides on top.
    old = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        assert run.main(["--run-dir", str(d), "--stages", "eval", "eval.tta_steps=1"]) == 0
    finally:
        torch.set_num_threads(old)
    assert "tta_steps: 1" in (d / "config.yaml").read_text()
    # The evaluation's DDIM steps are the eval stage's own: other steps re-run the eval alone, no retraining.
    torch.set_num_threads(1)
    try:
        out = run.main(["--run-dir", str(d), "--stages", "eval", "eval.sampling_steps=2"])
    finally:
        torch.set_num_threads(old)
    assert out == 0 and "DDIM steps 2," in (d / "report.md").read_text()
