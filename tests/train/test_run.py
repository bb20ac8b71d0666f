"""The staged pipeline end to end at the tiny preset: stages, skipping, config errors, resume, eval, redirect."""

import json
import shutil
from pathlib import Path

import h5py
import pytest
import torch

from toolkit import ToolkitError
from train import run
from train.stages.checks import check_config

TINY = ["--preset", "tiny"]
ROOT = Path(__file__).resolve().parents[2]


@pytest.fixture(scope="module")
def tiny_run(tmp_path_factory):
    d = tmp_path_factory.mktemp("run")
    torch.set_num_threads(1)  # tiny tensors: threads only add overhead (and thrash on a loaded machine)
    assert run.main([*TINY, "--run-dir", str(d)]) == 0
    return d


def test_all_stages_write_their_outputs(tiny_run):
    for rel in ("config.yaml", "data/split.json", "geometry/gaussians.safetensors", "geometry/neutral_mesh.ply",
                "codec.safetensors", "estimator_loss.safetensors", "estimator_eval.safetensors",
                "gaussian/final.safetensors", "report.md", "metrics.json", "qualitative.png", "eyes.png",
                "metrics.jsonl"):
        assert (tiny_run / rel).exists(), rel
    m = json.loads((tiny_run / "metrics.json").read_text())["metrics"]
    for k in ("gaze_error_deg", "head_pose_error_deg", "psnr", "ssim"):
        assert m[k] is not None and m[k] == m[k], k
    assert m["lpips"] is None
    report = (tiny_run / "report.md").read_text()
    assert "| Method | Gaze" in report and "n/a" in report
    assert "estimator's own held-out error" in report
    assert "Median gaze error over the pairs: " in report and m["gaze_error_median_deg"] >= 0
    lo, hi = m["gaze_error_ci95_deg"]
    assert lo <= m["gaze_error_deg"] <= hi and f"gaze {lo:.2f}-{hi:.2f}°" in report
    assert m["psnr_ci95"][0] <= m["psnr"] <= m["psnr_ci95"][1]
    # The references the renders are read against: scored, in the table and in metrics.json.
    assert "*reference: target at half resolution*" in report and "*reference: target through the codec*" in report
    assert "*diagnostic: the input re-rendered at its own gaze*" in report
    own = json.loads((tiny_run / "metrics.json").read_text())["own_gaze"]
    assert 0 <= own["gaze_error_deg"] <= 180 and own["psnr"] > 0
    # The ruler against the synthetic targets' exact labels: a table row, the renders' reading, the eye figure.
    labels = json.loads((tiny_run / "metrics.json").read_text())["labels"]
    assert set(labels) == {"target", "render"} and all(0 <= v <= 180 for d in labels.values() for v in d.values())
    assert "*reference: the target read against its labels*" in report and "![eyes](eyes.png)" in report
    # Every training stage logs to metrics.jsonl: the codec as it trains, the estimators' final records.
    stages = {json.loads(line)["stage"] for line in (tiny_run / "metrics.jsonl").read_text().splitlines()}
    assert {"codec", "estimator_loss", "estimator_eval", "gaussian"} <= stages, stages
    # The qualitative figure: input, target, render rows, then the first pair's input swept over the gazes.
    import cv2

    fig = cv2.imread(str(tiny_run / "qualitative.png"))
    cfg = run.open_run(tiny_run).config
    assert fig.shape[0] == 4 * cfg.data.res and fig.shape[1] >= cfg.eval.sweep_frames * cfg.data.res
    # Ablation-ready: the resolved config, and a command per Table 3 switch flipped on a copy of the run.
    from train.config import load_yaml_config
    from train.run_config import RunConfig

    block = report.split("```yaml\n", 1)[1].split("```", 1)[0]
    (tiny_run.parent / "from_report.yaml").write_text(block)
    assert load_yaml_config(RunConfig, tiny_run.parent / "from_report.yaml") == run.open_run(tiny_run).config
    for switch in ("gaussian.renderer=unet", "gaussian.orthogonality=false", "gaussian.weak_supervision=false"):
        assert f"--stages gaussian,eval {switch}`" in report, switch


def test_the_eval_stage_reads_a_pairing_file(tiny_run, tmp_path):
    """eval.pairing_file (text lines 'subject input_row target_row') gives each test subject its pairs; a file
    that does not read is refused before any work."""
    d = tmp_path / "run"
    shutil.copytree(tiny_run, d)
    test = json.loads((d / "data" / "split.json").read_text())["test"]
    pairs = tmp_path / "pairs.txt"
    pairs.write_text("# GazeNeRF-style\n" + "".join(f"{Path(t).stem} 0 {r}\n" for t in test for r in (20, 30, 35)))
    old = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        assert run.main(["--run-dir", str(d), "--stages", "eval", f"eval.pairing_file={pairs}",
                         "eval.pairs_per_subject=3"]) == 0
    finally:
        torch.set_num_threads(old)
    per_pair = json.loads((d / "metrics.json").read_text())["per_pair"]
    assert len(per_pair) == 3 * len(test) and sorted({r["pair"] for r in per_pair}) == [0, 1, 2]
    pairs.write_text("subject 0\n")
    with pytest.raises(ToolkitError, match=r"'eval.pairing_file': .*pairs.txt: not a pairing file"):
        run.main(["--run-dir", str(d), "--stages", "eval", f"eval.pairing_file={pairs}"])


def test_the_reports_ablation_command_runs(tiny_run, tmp_path):
    """The report's command for a Table 3 switch works as printed: on a copy of the run, only the Gaussian and
    eval stages run again, and the new report names the flipped switch."""
    import re
    import shlex

    d = tmp_path / "run"
    shutil.copytree(tiny_run, d)
    line = next(m for m in re.findall(r"`(cp -r [^`]+)`", (d / "report.md").read_text()) if "orthogonality" in m)
    line = line.replace(str(tiny_run), str(d))  # the report names the run it was written in
    copy_cmd, train_cmd = (shlex.split(part) for part in line.split(" && "))
    assert copy_cmd[:2] == ["cp", "-r"] and train_cmd[:3] == ["python", "-m", "train.run"]
    shutil.copytree(copy_cmd[2], copy_cmd[3])
    old = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        assert run.main(train_cmd[3:]) == 0
    finally:
        torch.set_num_threads(old)
    out = Path(copy_cmd[3])
    ran = json.loads((out / "stages" / "gaussian.json").read_text())["fingerprint"]
    assert ran != json.loads((d / "stages" / "gaussian.json").read_text())["fingerprint"]
    assert "orthogonality=False" in (out / "report.md").read_text()
    assert (out / "stages" / "data.json").read_text() == (d / "stages" / "data.json").read_text()
    pair = json.loads((tiny_run / "metrics.json").read_text())["per_pair"][0]
    assert 0 <= pair["target_vs_label_gaze_deg"] <= 180 and 0 <= pair["render_vs_label_gaze_deg"] <= 180
    refs = json.loads((tiny_run / "metrics.json").read_text())["references"]
    assert refs["target through the codec"]["gaze_error_deg"] >= 0 and refs["target at half resolution"]["psnr"] > 0
    # Each estimator trained on the run's training split plus its own extra synthetic subject.
    est = json.loads((tiny_run / "estimators.json").read_text())
    n_split = 18  # tiny preset: one training subject x one frame x 18 rig cameras
    extra = 1 * 2 * 2  # synthetic_subjects x synthetic_frames x cameras_per_frame
    assert est["loss"]["train_images"] == est["eval"]["train_images"] == n_split + extra
    from train.estimator.network import GazeEstimator

    assert GazeEstimator.load(tiny_run / "estimator_eval.safetensors").config.eyes


def _estimator_stage(run_dir, threads: int, **estimator) -> tuple[dict, list[str]]:
    """Run stage estimator on ``run_dir`` with ``threads`` torch threads (and estimator-section overrides);
    returns its outputs and log lines."""
    ctx = run.open_run(run_dir)
    for k, v in estimator.items():
        setattr(ctx.config.estimator, k, v)
    lines = []
    ctx.log = lines.append
    torch.set_num_threads(threads)
    try:
        return run.stage_estimator(ctx), lines
    finally:
        torch.set_num_threads(1)


def test_estimators_trained_at_once_equal_those_trained_in_turn(tiny_run, tmp_path):
    """With 2 CPU threads the stage trains both estimators at once, one process and thread each: the weights
    must be exactly those of the 1-thread run that trained them in turn (the fixture), and the summary too."""
    from safetensors.torch import load_file

    d = tmp_path / "run"
    shutil.copytree(tiny_run, d)
    for role in ("loss", "eval"):
        (d / f"estimator_{role}.safetensors").unlink()
    (d / "estimators.json").unlink()
    outs, lines = _estimator_stage(d, threads=2)
    assert any("2 processes, 1 + 1 threads" in s for s in lines)
    # The tiny preset's 4-step estimators read far off: the stage says so, for each of them.
    assert sum("WARNING" in s and "training failed or was too short" in s for s in lines) == 2
    assert outs == {"loss": "estimator_loss.safetensors", "eval": "estimator_eval.safetensors",
                    "summary": "estimators.json"}
    for role in ("loss", "eval"):
        a, b = load_file(tiny_run / outs[role]), load_file(d / outs[role])
        assert set(a) == set(b) and all(torch.equal(a[k], b[k]) for k in a), role
    assert json.loads((d / "estimators.json").read_text()) == json.loads((tiny_run / "estimators.json").read_text())


def test_eval_groups_split_only_per_pair_fits_on_a_multithreaded_cpu():
    files = [f"s{i}.h5" for i in range(5)]
    assert run.eval_groups(files, 2, True, True) == [["s0.h5", "s2.h5", "s4.h5"], ["s1.h5", "s3.h5"]]
    for threads, per_pair, cpu, n in ((1, True, True, 5), (2, False, True, 5), (2, True, False, 5), (4, True, True, 1)):
        assert run.eval_groups(files[:n], threads, per_pair, cpu) == [files[:n]]


def test_eval_in_two_processes_equals_one_process(tiny_run, tmp_path, monkeypatch):
    """With 2 threads and 2 test subjects the eval stage evaluates them in two 1-thread processes: its metrics,
    per-subject and per-pair scores must be exactly those of one 1-thread process evaluating both in turn."""
    d = tmp_path / "run"
    shutil.copytree(tiny_run, d)
    ctx = run.open_run(d)
    (src,) = run._split(ctx, "test")
    twin = src.with_name("subject_twin.h5")
    shutil.copy(src, twin)  # a second test subject: the same file under another name
    real_split = run._split
    monkeypatch.setattr(run, "_split", lambda c, which: [src, twin] if which == "test" else real_split(c, which))
    lines = []
    ctx.log = lines.append
    torch.set_num_threads(2)
    try:
        run.stage_eval(ctx)
    finally:
        torch.set_num_threads(1)
    assert any("2 test subjects in 2 processes at once, 1 thread(s) each" in s for s in lines)
    got = json.loads((d / "metrics.json").read_text())
    from train.evaluation.summary import summarize_evaluation

    raw = run._eval_subjects(config=ctx.config, run_dir=d, outputs=dict(ctx.outputs), files=[src, twin], threads=1)
    want = summarize_evaluation(raw, own_gaze_row=True, log=lambda m: None)
    assert [r["subject"] for r in got["per_pair"]] == [src.name] * 2 + [twin.name] * 2
    assert got["per_pair"] == want["per_pair"]
    assert got["per_subject"] == [{**r, "ms_per_image": g["ms_per_image"]}
                                  for r, g in zip(want["per_subject"], got["per_subject"])]
    for k in ("gaze_error_deg", "head_pose_error_deg", "psnr", "ssim", "pairs"):
        assert got["metrics"][k] == want["metrics"][k], k
    assert got["own_gaze"] == want["own_gaze"] and got["references"] == want["references"]
    assert got["labels"] == want["labels"] and (d / "eyes.png").stat().st_size > 0


def test_estimator_stage_warns_only_about_a_failed_estimator(tiny_run, tmp_path, monkeypatch):
    d = tmp_path / "run"
    shutil.copytree(tiny_run, d)
    readings = {"loss": 4.2, "eval": 87.0}

    def fake_train(*, role, run_dir, **kw):
        return f"estimator_{role}.safetensors", {"train_images": 18, "val_gaze_deg": readings[role]}

    monkeypatch.setattr(run, "_train_estimator", fake_train)
    outs, lines = _estimator_stage(d, threads=1)
    warnings = [s for s in lines if "WARNING" in s]
    assert len(warnings) == 1 and "eval estimator reads held-out gazes 87.0 deg off" in warnings[0]


def test_run_at_once_returns_in_order_and_a_failure_stops_the_others(tmp_path):
    """Results come back in job order; the first failure is raised at once, the other job is stopped rather than
    waited for (its marker file never appears), and a process that dies is a one-line ToolkitError."""
    from tests.train import procs

    assert run.run_at_once([(procs.echo, {"value": 1}), (procs.echo, {"value": "b"})]) == [1, "b"]
    marker = tmp_path / "finished"
    slow = (procs.sleep_then_touch, {"seconds": 30, "path": str(marker)})
    with pytest.raises(ValueError, match="job failed"):
        run.run_at_once([slow, (procs.fail, {})])
    with pytest.raises(ToolkitError, match="a worker process died"):
        run.run_at_once([slow, (procs.die, {})])
    assert not marker.exists()
    # What cannot make the trip back comes back as an error, never as a hang or a misleading TypeError.
    with pytest.raises(TypeError, match="cannot pickle"):
        run.run_at_once([(procs.unpicklable, {})])
    with pytest.raises(RuntimeError, match="TwoArgError: needs two"):
        run.run_at_once([(procs.raise_two_arg, {})])


def test_estimators_at_once_with_render_workers_of_their_own(tiny_run, tmp_path):
    """With 4 threads each estimator's process gets 2, and renders its extra subjects with 2 processes of its
    own: the stage's processes must be allowed children."""
    d = tmp_path / "run"
    shutil.copytree(tiny_run, d)
    outs, lines = _estimator_stage(d, threads=4, synthetic_subjects=2)
    assert any("2 processes, 2 + 2 threads" in s for s in lines)
    est = json.loads((d / outs["summary"]).read_text())
    assert est["loss"]["train_images"] == est["eval"]["train_images"] == 18 + 2 * 2 * 2


def test_unchanged_stages_are_skipped_and_changes_rerun_downstream(tiny_run, capsys):
    assert run.main([*TINY, "--run-dir", str(tiny_run), "--stages", "all"]) == 0
    status = json.loads(capsys.readouterr().out.strip().splitlines()[-1])["stages"]
    assert set(status.values()) == {"skipped"}
    assert run.main([*TINY, "--run-dir", str(tiny_run), "--stages", "eval", "eval.pairs_per_subject=1"]) == 0
    status = json.loads(capsys.readouterr().out.strip().splitlines()[-1])["stages"]
    assert status == {"eval": "ran"}


def test_eval_gaze_term_fits_with_the_loss_estimator(tiny_run, tmp_path, capsys, monkeypatch):
    """``eval.tta_gaze_weight`` > 0: test-time fitting reads the *loss* estimator (its weights, not the evaluation
    one's), the metric still reads the evaluation estimator, and the report names the term."""
    from safetensors.torch import load_file

    import train.evaluation.fitting as ev

    d = tmp_path / "run"
    shutil.copytree(tiny_run, d)
    seen = []
    term = ev.FitGaze.term

    def spy(self, *a, **k):
        seen.append(self)
        return term(self, *a, **k)

    monkeypatch.setattr(ev.FitGaze, "term", spy)
    assert run.main([*TINY, "--run-dir", str(d), "--stages", "eval", "eval.tta_gaze_weight=0.01",
                     "eval.tta_gaze_terms=[target,own]", "eval.tta_gaze_every=1", "eval.tta_gaze_reach=[code]"]) == 0
    assert json.loads(capsys.readouterr().out.strip().splitlines()[-1])["stages"] == {"eval": "ran"}
    assert seen and all(g.weight == 0.01 and g.terms == ("target", "own") and g.every == 1 and g.reach == ("code",)
                        for g in seen)
    loss_w, eval_w = load_file(d / "estimator_loss.safetensors"), load_file(d / "estimator_eval.safetensors")
    fitted = seen[0].loss.estimator.state_dict()
    assert set(fitted) == set(loss_w) and all(torch.equal(fitted[k], loss_w[k]) for k in fitted)
    assert any(not torch.equal(fitted[k], eval_w[k]) for k in fitted)
    assert ("with the loss estimator's gaze term (weight 0.01, every step; target, own; reaching code only)"
            in (d / "report.md").read_text())


def test_eval_gaze_term_refuses_the_evaluation_estimator(tiny_run, tmp_path):
    """A loss estimator that is the evaluation estimator's file would let the fit optimize the metric's ruler."""
    d = tmp_path / "run"
    shutil.copytree(tiny_run, d)
    ctx = run.open_run(d)
    ctx.config.estimator.loss_path = ctx.config.estimator.eval_path = str(d / "estimator_eval.safetensors")
    with pytest.raises(ToolkitError, match="'eval.tta_gaze_weight'.*also the evaluation estimator"):
        run.stage_eval(ctx)
    copy = tmp_path / "copy_of_eval.safetensors"  # the same weights under another name
    shutil.copyfile(d / "estimator_eval.safetensors", copy)
    ctx.config.estimator.loss_path = str(copy)
    with pytest.raises(ToolkitError, match="also the evaluation estimator"):
        run.stage_eval(ctx)
    ctx.config.eval.tta_gaze_weight = 0.0
    assert run.stage_eval(ctx)


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
    cfg = run.preset("tiny")
    cfg.estimator.crop, cfg.estimator.input_size = "eyes", 8
    check_config(cfg)


@pytest.mark.parametrize("name", sorted(run.PRESETS))
def test_every_preset_passes_the_value_checks(name):
    check_config(run.preset(name))


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
    model, renderer = run.load_trained(run.open_run(full), "cpu")
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
    ctx = run.open_run(d)
    model, renderer_ = run.load_trained(ctx, "cpu")
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
    _, renderer = run.load_trained(run.open_run(d), "cpu")
    assert isinstance(renderer.codec, PixelCodec) and renderer.dit.config.patch_size == 8
    assert renderer.dit.feature_encoder.conv_in.out_channels == 8  # gaussian.dit_feature_hidden
    m = json.loads((d / "metrics.json").read_text())
    assert m["metrics"]["psnr"] == m["metrics"]["psnr"] and len(m["per_pair"]) == m["metrics"]["pairs"]
    # No codec: the report scores no "through the codec" reference (it would be the target itself).
    assert list(m["references"]) == ["target at half resolution"]


def test_demo_preset_renders_in_pixel_space_at_its_resolution():
    from train.model.codec import PixelCodec
    from train.model.renderer import make_renderer
    from train.run_config import RunConfig, preset

    cfg = preset("demo")
    g, res = cfg.gaussian, cfg.data.res
    assert (cfg.codec.kind, g.dit_model, cfg.estimator.steps) == ("pixel", "DiT-Gaze-pixel", 1200)
    assert (g.steps, cfg.eval.tta_steps) == (240, 30)  # session 19: sized for the slowest 2-core machine seen
    # Session 22: the natural fit (the gaze term only turns the eyes), and the Gaussian stage at twice the rates.
    from train.evaluation.fitting import NATURAL_EYES_FIT

    assert (cfg.eval.tta_weights, cfg.eval.tta_gaze_weight, cfg.eval.tta_gaze_reach, cfg.eval.tta_gaze_terms,
            cfg.eval.tta_gaze_every) == tuple(NATURAL_EYES_FIT[k] for k in ("weights", "gaze_weight", "reach",
                                                                           "terms", "every"))
    assert (g.lr, g.renderer_lr) == (4e-3, 1e-3)
    assert g.eyeball_colours and not g.eye_appearance  # session 24: the eyes' RGB is a parametric eyeball
    assert cfg.geometry.gaussians == 12_000  # session 24: a sharper splat
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


def test_corrupt_checkpoint_is_clear_error(tiny_run, tmp_path):
    d = tmp_path / "c"
    shutil.copytree(tiny_run, d)
    ck = d / "gaussian" / "final.safetensors"
    ck.write_bytes(ck.read_bytes()[:1000])
    with pytest.raises(ToolkitError, match="final.safetensors: not a valid safetensors"):
        run.main([*TINY, "--run-dir", str(d), "--stages", "eval", "--force", "eval"])


def test_redirect_app_writes_a_loadable_dataset(tiny_run, tmp_path):
    from apps import redirect
    from train.data.dataset import GazeDataset

    src = sorted((tiny_run / "data").glob("*.h5"))[-1]
    out = tmp_path / "redirected.h5"
    assert redirect.main([str(tiny_run), str(src), str(out), "--gazes", "grid:2x2:20", "--rows", "2", "--batch", "1"]) == 0
    with h5py.File(out) as f:
        assert f["face_patch"].shape[0] == 8 and f["pitchyaw_head"].shape == (8, 2)
        assert not (out.parent / "redirected.h5.parts").exists()
    ds = GazeDataset([out])
    assert len(ds) == 8
    with pytest.raises(ToolkitError, match="--gazes"):
        redirect.main([str(tiny_run), str(src), str(out), "--gazes", "spiral:3"])
    with pytest.raises(ToolkitError, match="not a run directory"):
        redirect.main([str(tmp_path), str(src), str(out)])
    from toolkit.errors import run_cli

    assert run_cli(redirect.main, [str(tiny_run), str(src), str(out), "--batch", "0"]) == 2


def test_preview_opens_a_trained_run(tiny_run, tmp_path):
    from apps.preview import load_scene, render_gaze_sweep

    scene = load_scene(str(tiny_run))
    assert scene.features.shape[1] == 3 and {1, 2} <= set(scene.part.unique().tolist())
    info = render_gaze_sweep(scene, tmp_path / "sweep.png", [0], [-20, 20], 64, 64)
    assert (tmp_path / "sweep.png").exists() and len(info["gazes"]) == 2
    with pytest.raises(ToolkitError, match=r"a trained run directory \(with config.yaml\)"):
        load_scene(str(tmp_path))


def test_open_run_uses_a_run_finished_under_an_older_config(tiny_run, tmp_path, caplog):
    """A finished model must still open when its stages' fingerprints no longer match config.yaml (edited
    since, or hashed by an older toolkit whose config lacked a field), with a warning naming them."""
    import re

    d = tmp_path / "old"
    shutil.copytree(tiny_run, d)
    text = (d / "config.yaml").read_text()
    edited = re.sub(r"(?m)^  ckpt_every: (\d+)$", lambda m: f"  ckpt_every: {int(m.group(1)) + 1}", text, count=1)
    assert edited != text
    (d / "config.yaml").write_text(edited)
    ctx = run.open_run(d)
    assert ctx.path("gaussian", "checkpoint").exists()
    assert "gaussian" in caplog.text and "different config" in caplog.text


def test_data_stage_gives_the_held_out_subjects_their_frames(tmp_path):
    d = tmp_path / "run"
    assert run.main([*TINY, "--run-dir", str(d), "--stages", "data", "data.test_frames=4"]) == 0
    from train.data.dataset import find_subject_files, split_files

    rows = {}
    for split in ("train", "test"):
        for p in split_files(find_subject_files([d / "data"]), split):
            with h5py.File(p) as f:
                rows[split] = len(f["pitchyaw_head"])
    assert rows == {"train": 18, "test": 72}  # 1 frame per training subject (tiny), 4 held out, 18 cameras


def test_config_and_report_know_every_fitting_group():
    """The config's allowed ``eval.tta_weights``, the report's wording and ``train.evaluation.protocol``'s groups are three
    listings of one set: a group added to one must be added to all."""
    import typing

    from train.evaluation.fitting import TTA_WEIGHT_GROUPS
    from train.run_config import EvalConfig

    (allowed, _) = typing.get_args(typing.get_type_hints(EvalConfig)["tta_weights"])
    assert typing.get_args(allowed) == TTA_WEIGHT_GROUPS
    text = run._fitting(EvalConfig(tta_steps=1, tta_weights=TTA_WEIGHT_GROUPS))
    assert "the eye rotation field" in text and "the codec's decoder" in text


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


def test_labels_note_says_whether_the_fit_may_repaint_the_eyes():
    from dataclasses import replace

    from train.evaluation.fitting import NATURAL_EYES_FIT
    from train.run import _labels_note
    from train.run_config import EvalConfig, RunConfig

    def note(eye_appearance=False, eyeball_colours=False, **ev):
        cfg = RunConfig(eval=EvalConfig(**ev))
        return _labels_note(labels, replace(cfg, gaussian=replace(cfg.gaussian, eye_appearance=eye_appearance,
                                                                  eyeball_colours=eyeball_colours)))

    labels = {"target": {"gaze_error_deg": 5.5}, "render": {"gaze_error_deg": 5.0}}
    natural = dict(tta_weights=NATURAL_EYES_FIT["weights"], tta_gaze_weight=NATURAL_EYES_FIT["gaze_weight"],
                   tta_gaze_reach=NATURAL_EYES_FIT["reach"])
    painting = note(tta_gaze_weight=0.001)  # reach (): all it fits, the renderer included
    assert "pushes the renders toward those labels as read" in painting and "no measure of how real" in painting
    assert "cannot repaint" not in painting
    turning = note(**natural, tta_gaze_terms=NATURAL_EYES_FIT["terms"])
    assert "pushes the renders toward those labels and the input's own gaze as read" in turning
    assert "no measure" not in turning
    # A term that reads only the input does not push the renders toward the targets' labels.
    own = note(**natural, tta_gaze_terms=("own",))
    assert "toward the input's own gaze as read" in own and "those labels" not in own
    assert "It reaches code, eye_field, and cannot repaint the eyes" in turning
    # With code-conditioned eye colours a term reaching the code can recolour the eyes.
    assert "no measure of how real" in note(eye_appearance=True, **natural)
    # The parametric eyeball's numbers set the iris's size and colour: a term reaching them may repaint.
    eyeball = dict(natural, tta_weights=("features", "eye_colours", "eye_field"), tta_gaze_reach=("code", "eye_colours"))
    assert "no measure of how real" in note(eyeball_colours=True, **eyeball)
    no_term = note(tta_gaze_weight=0.0)
    assert "5.00°" in no_term and "gaze term" not in no_term
    assert _labels_note({}, RunConfig()) == ""


def test_parametric_eyeballs_train_save_and_fit_through_the_stages(tiny_run, tmp_path):
    d = tmp_path / "eyeballs"
    shutil.copytree(tiny_run, d)
    over = ["gaussian.eyeball_colours=true", "gaussian.steps=2", "eval.pairs_per_subject=1",
            "eval.tta_weights=[features,eye_colours]"]
    assert run.main([*TINY, "--run-dir", str(d), "--stages", "gaussian,eval", *over]) == 0
    model, _ = run.load_trained(run.open_run(d), "cpu")
    assert model.eyeball_colours is not None
    start = torch.logit(torch.tensor(0.92))  # EyeballColours' sclera prior, before training
    assert not torch.allclose(model.eyeball_colours.sclera.detach(), start.expand(3))  # trained
    m = json.loads((d / "metrics.json").read_text())["metrics"]
    assert m["psnr"] == m["psnr"] and m["gaze_error_deg"] == m["gaze_error_deg"]
    assert "the eyeball's colours" in (d / "report.md").read_text()
