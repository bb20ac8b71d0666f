"""Stage eval at the tiny preset: the report and its figures, pairing files, processes at once, the fit's gaze term."""

import json
import shutil
from pathlib import Path

import pytest
import torch

from toolkit import ToolkitError
from train import run
from train.stages.artifacts import RunArtifacts
from train.stages.eval import _eval_subjects, eval_groups, stage_eval
from train.trained_run import TrainedRun

TINY = ["--preset", "tiny"]


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
    cfg = TrainedRun.open(tiny_run).config
    assert fig.shape[0] == 4 * cfg.data.res and fig.shape[1] >= cfg.eval.sweep_frames * cfg.data.res
    # Ablation-ready: the resolved config, and a command per Table 3 switch flipped on a copy of the run.
    from train.config import load_yaml_config
    from train.run_config import RunConfig

    block = report.split("```yaml\n", 1)[1].split("```", 1)[0]
    (tiny_run.parent / "from_report.yaml").write_text(block)
    assert load_yaml_config(RunConfig, tiny_run.parent / "from_report.yaml") == TrainedRun.open(tiny_run).config
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


def test_a_pairing_that_misses_a_held_out_subject_leaves_the_config_as_it_was(tiny_run, tmp_path):
    """A pairing file naming none of a held-out subject's rows is refused against the run's own held-out files
    before config.yaml is written (it was refused only at the eval stage's start, the override already saved)."""
    d = tmp_path / "run"
    shutil.copytree(tiny_run, d)
    split = json.loads((d / "data" / "split.json").read_text())
    pairs = tmp_path / "pairs.txt"
    pairs.write_text(f"{Path(split['train'][0]).stem} 0 20\n")  # a training subject's rows only
    before = (d / "config.yaml").read_bytes()
    with pytest.raises(ToolkitError, match=r"'eval.pairing_file': .*no pairs for .*" + Path(split["test"][0]).stem):
        run.main(["--run-dir", str(d), "--stages", "eval", f"eval.pairing_file={pairs}"])
    assert (d / "config.yaml").read_bytes() == before


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


def test_eval_groups_split_only_per_pair_fits_on_a_multithreaded_cpu():
    files = [f"s{i}.h5" for i in range(5)]
    assert eval_groups(files, 2, True, True) == [["s0.h5", "s2.h5", "s4.h5"], ["s1.h5", "s3.h5"]]
    for threads, per_pair, cpu, n in ((1, True, True, 5), (2, False, True, 5), (2, True, False, 5), (4, True, True, 1)):
        assert eval_groups(files[:n], threads, per_pair, cpu) == [files[:n]]


def test_eval_in_two_processes_equals_one_process(tiny_run, tmp_path, monkeypatch):
    """With 2 threads and 2 test subjects the eval stage evaluates them in two 1-thread processes: its metrics,
    per-subject and per-pair scores must be exactly those of one 1-thread process evaluating both in turn."""
    d = tmp_path / "run"
    shutil.copytree(tiny_run, d)
    ctx = TrainedRun.open(d).context
    (src,) = RunArtifacts(ctx).split("test")
    twin = src.with_name("subject_twin.h5")
    shutil.copy(src, twin)  # a second test subject: the same file under another name
    real_split = RunArtifacts.split
    monkeypatch.setattr(RunArtifacts, "split", lambda a, which: [src, twin] if which == "test" else real_split(a, which))
    lines = []
    ctx.log = lines.append
    torch.set_num_threads(2)
    try:
        stage_eval(ctx)
    finally:
        torch.set_num_threads(1)
    assert any("2 test subjects in 2 processes at once, 1 thread(s) each" in s for s in lines)
    got = json.loads((d / "metrics.json").read_text())
    from train.evaluation.summary import summarize_evaluation

    raw = _eval_subjects(config=ctx.config, run_dir=d, outputs=dict(ctx.outputs), files=[src, twin], threads=1)
    want = summarize_evaluation(raw, own_gaze_row=True, log=lambda m: None)
    assert [r["subject"] for r in got["per_pair"]] == [src.name] * 2 + [twin.name] * 2
    assert got["per_pair"] == want["per_pair"]
    assert got["per_subject"] == [{**r, "ms_per_image": g["ms_per_image"]}
                                  for r, g in zip(want["per_subject"], got["per_subject"])]
    for k in ("gaze_error_deg", "head_pose_error_deg", "psnr", "ssim", "pairs"):
        assert got["metrics"][k] == want["metrics"][k], k
    assert got["own_gaze"] == want["own_gaze"] and got["references"] == want["references"]
    assert got["labels"] == want["labels"] and (d / "eyes.png").stat().st_size > 0


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
    ctx = TrainedRun.open(d).context
    ctx.config.estimator.loss_path = ctx.config.estimator.eval_path = str(d / "estimator_eval.safetensors")
    with pytest.raises(ToolkitError, match="'eval.tta_gaze_weight'.*also the evaluation estimator"):
        stage_eval(ctx)
    copy = tmp_path / "copy_of_eval.safetensors"  # the same weights under another name
    shutil.copyfile(d / "estimator_eval.safetensors", copy)
    ctx.config.estimator.loss_path = str(copy)
    with pytest.raises(ToolkitError, match="also the evaluation estimator"):
        stage_eval(ctx)
    ctx.config.eval.tta_gaze_weight = 0.0
    assert stage_eval(ctx)


def test_corrupt_checkpoint_is_clear_error(tiny_run, tmp_path):
    d = tmp_path / "c"
    shutil.copytree(tiny_run, d)
    ck = d / "gaussian" / "final.safetensors"
    ck.write_bytes(ck.read_bytes()[:1000])
    with pytest.raises(ToolkitError, match="final.safetensors: not a valid safetensors"):
        run.main([*TINY, "--run-dir", str(d), "--stages", "eval", "--force", "eval"])


def test_config_and_report_know_every_fitting_group():
    """The config's allowed ``eval.tta_weights``, the report's wording and ``train.evaluation.fitting``'s groups are three
    listings of one set: a group added to one must be added to all."""
    import typing

    from train.evaluation.fitting import TTA_WEIGHT_GROUPS
    from train.evaluation.report import describe_fitting
    from train.run_config import EvalConfig

    (allowed, _) = typing.get_args(typing.get_type_hints(EvalConfig)["tta_weights"])
    assert typing.get_args(allowed) == TTA_WEIGHT_GROUPS
    text = describe_fitting(EvalConfig(tta_steps=1, tta_weights=TTA_WEIGHT_GROUPS))
    assert "the eye rotation field" in text and "the codec's decoder" in text


def test_labels_note_says_whether_the_fit_may_repaint_the_eyes():
    from dataclasses import replace

    from train.evaluation.report import labels_note
    from train.presets import NATURAL_EYES_FIT
    from train.run_config import EvalConfig, RunConfig

    def note(eye_appearance=False, eyeball_colours=False, **ev):
        cfg = RunConfig(eval=EvalConfig(**ev))
        return labels_note(labels, replace(cfg, gaussian=replace(cfg.gaussian, eye_appearance=eye_appearance,
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
    assert labels_note({}, RunConfig()) == ""
