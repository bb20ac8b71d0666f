"""Stage ``eval``: the GazeNeRF redirection protocol (``train.evaluation.protocol``) on the held-out subjects
-> ``metrics.json``, ``report.md`` and the figures (``train.evaluation.report``). Synthetic subject files are
scored against generator targets, real ones against their stored target rows (``train.data.pairing``). When the
test-time fit has a gaze term, the same pairs are evaluated a second time after the natural fit, without it
(``eval.natural_fit_row``)."""

from __future__ import annotations

import time
from dataclasses import replace
from pathlib import Path

import torch

from toolkit.errors import ToolkitError
from train.run_config import EvalConfig, RunConfig, eval_sampling_steps
from train.stages.artifacts import RunArtifacts, resolve_device
from train.stages.pipeline import RunContext
from train.stages.processes import run_at_once, tensors_from_numpy, tensors_to_numpy


def stage_eval(ctx: RunContext) -> dict[str, str]:
    """The evaluation protocol on the test split, the report and the figures. Test subjects may be evaluated in
    two processes at once (:func:`eval_groups`); each subject's scores depend only on the threads its process
    has, and the merged result is what one process with that many threads gives (tested)."""
    from train.evaluation.report import (
        check_eval_outputs,
        describe_protocol,
        figure_pngs,
        report_markdown,
        write_eval_outputs,
    )
    from train.evaluation.summary import summarize_evaluation
    from train.stages.checks import check_eval_pairing

    check_eval_outputs(ctx.run_dir)  # minutes of work must not end in a refusal that leaves half the outputs new
    run = RunArtifacts(ctx)
    device = run.device
    _check_the_fit_reads_another_estimator(run)
    check_eval_pairing(ctx.config, run.eval_files())  # one line before the models load
    t0 = time.perf_counter()
    raw = _evaluate_test_split(ctx, run, device)
    natural = None
    if natural_fit_applies(ctx.config.eval):
        t1 = time.perf_counter()
        ctx.log(f"[eval] {t1 - t0:.0f} s; now the same pairs after the natural fit (no gaze term)")
        natural = _evaluate_test_split(ctx, run, device, natural=True)
        ctx.log(f"[eval] the natural fit's pass: {time.perf_counter() - t1:.0f} s")
    res = summarize_evaluation(raw, own_gaze_row=True, log=ctx.log, natural_fit=natural)
    if res["metrics"]["identity_drift"] is None:
        from train.losses.face_embedding import IDENTITY_EXTRA

        ctx.log(f"[eval] n/a: {IDENTITY_EXTRA}")
    protocol = describe_protocol(res["per_subject"], ctx.config.eval.pairing_file)
    datasets = run.dataset_names()
    ctx.log(f"[eval] protocol: {protocol}; trained on {datasets['train']}, evaluated on {datasets['eval']}")
    res["datasets"] = datasets
    metrics = {"protocol": protocol, "datasets": datasets, "metrics": res["metrics"],
               "per_subject": res["per_subject"], "per_pair": res["per_pair"], "own_gaze": res["own_gaze"],
               "references": res["references"], "labels": res["labels"],
               **({"natural_fit_per_pair": res["natural_fit_per_pair"]} if natural is not None else {})}
    # Every output is made before the first is written, so that a failure while making one (the sweep's fit,
    # a figure) leaves the previous evaluation's set whole; the pipeline writes the stage's record after them.
    pngs = figure_pngs(res, _eval_sweep(run, device))
    figures = {k: name for k, (name, _) in pngs.items()}
    write_eval_outputs(ctx.run_dir, metrics, pngs, report_markdown(res, ctx.config, ctx.run_dir, figures))
    ctx.log(f"[eval] report: {ctx.run_dir / 'report.md'}")
    return {"report": "report.md", "metrics": "metrics.json", **figures}


def natural_fit_applies(e: EvalConfig) -> bool:
    """Whether the eval stage scores the natural-fit row too: ``eval.natural_fit_row`` and a fit with a gaze term.

    The peers' evaluation fits each input with a gaze term read by an estimator of the metric's family: GazeNeRF
    (AlessandroRuzzi/GazeNeRF, ``utils/metrics_utils.py`` L245 fits before every pair's render, through
    ``trainer/gazenerf_trainer.py`` L946-1022; its loss, ``losses/gazenerf_loss.py`` L384-391, adds the angle
    between the render's and the input's readings by ``GazePerceptualLoss``, L105-117: ETH-XGaze's ResNet-50 as
    the evaluation estimator, ``evaluate_metrics.py`` L131-135, with other weights). GazeGaussian's
    ``train_single_image`` (ucwxb/GazeGaussian, ``trainer/gazegaussian_trainer.py`` L316-345) fits with the same
    term (``losses/gazenerf_loss.py`` L444-449) but its release has no evaluation script. The main row is that
    protocol; the natural row is how the toolkit produces data (``train.augment.rows``), so both are reported."""
    return e.natural_fit_row and e.tta_gaze_weight > 0 and e.tta_steps > 0


def _check_the_fit_reads_another_estimator(run: RunArtifacts) -> None:
    """Refuse a fitting gaze term whose loss estimator is the evaluation estimator (the same file, or the same
    bytes): the metric's ruler must not be what the fit optimizes."""
    e = run.config.eval
    if not (e.tta_gaze_weight > 0 and e.tta_steps > 0):
        return
    loss_file, eval_file = (run.estimator_file(r).resolve() for r in ("loss", "eval"))
    if loss_file == eval_file or (loss_file.is_file() and eval_file.is_file()
                                  and loss_file.read_bytes() == eval_file.read_bytes()):
        raise ToolkitError(f"config key 'eval.tta_gaze_weight': the gaze term of the fit reads the loss estimator, "
                           f"and {loss_file} is also the evaluation estimator ({eval_file}); give another estimator.loss_path "
                           f"or set eval.tta_gaze_weight=0")


def _evaluate_test_split(ctx: RunContext, run: RunArtifacts, device: torch.device, natural: bool = False) -> dict:
    """``train.evaluation.protocol.evaluate_raw``'s result on the test split, in this process or in groups of
    subjects in processes at once (merged back into the split's order). ``natural``: the fit without its gaze
    term, scoring the renders alone (no references, own-gaze row or optional metrics)."""
    from train.evaluation.summary import in_subject_order, merge_raw_evaluations

    cfg = ctx.config
    if natural:
        cfg = replace(cfg, eval=replace(cfg.eval, tta_gaze_weight=0.0))
    files = run.eval_files()
    threads = torch.get_num_threads()
    groups = eval_groups(files, threads, cfg.eval.tta_steps > 0 and bool(cfg.eval.tta_weights), device.type == "cpu")
    job = dict(config=cfg, run_dir=ctx.run_dir, outputs=dict(ctx.outputs), lean=natural)
    if len(groups) == 1:
        log = (lambda m: ctx.log(m.replace("[eval]", "[eval] natural fit,", 1))) if natural else ctx.log
        return _eval_subjects(**job, files=groups[0], threads=threads, log=log)
    split = [threads // len(groups)] * len(groups)
    ctx.log(f"[eval] {len(files)} test subjects in {len(groups)} processes at once, {split[0]} thread(s) each")
    parts = [tensors_from_numpy(part) for part in
             run_at_once([(_eval_subjects, dict(job, files=g, threads=n, portable=True))
                          for g, n in zip(groups, split)])]
    # Back into the split's order (the groups alternate), so the summary reads as in one process.
    raw = in_subject_order(merge_raw_evaluations(parts), [Path(f).name for f in files])
    for r in raw["per_subject"]:
        ctx.log(f"[eval]{' natural fit,' * natural} {r['subject']}: gaze {r['gaze_error_deg']:.2f} deg, PSNR {r['psnr']:.2f} dB, "
                f"SSIM {r['ssim']:.3f} ({r['pairs']} pairs)")
    return raw


def eval_groups(files: list[Path], threads: int, per_pair_fit: bool, cpu: bool) -> list[list[Path]]:
    """How the eval stage splits the test subjects between processes: on the CPU, with >= 2 threads, >= 2
    subjects and per-pair fitting (batch-1 fits, which use a second thread poorly: the demo's eval on 2 cores
    took 69 s on 1 thread and 47 s on 2 for the same 6 pairs), two processes take alternate subjects, one
    thread each. Otherwise one group: everything in this process."""
    if cpu and threads >= 2 and len(files) >= 2 and per_pair_fit:
        return [files[0::2], files[1::2]]
    return [list(files)]


def _eval_subjects(*, config: RunConfig, run_dir: Path, outputs: dict, files: list[Path], threads: int, log=None,
                   portable: bool = False, lean: bool = False) -> dict:
    """The eval stage's protocol on ``files`` (test subjects) with ``threads`` torch threads, in this process or a
    spawned one: ``train.evaluation.protocol.evaluate_raw``'s unsummarized result (``portable``: its tensors as
    numpy arrays, ``train.stages.processes.tensors_to_numpy``). ``lean``: the renders' scores alone (no
    references, own-gaze renders, LPIPS or identity measures)."""
    from train.evaluation.protocol import evaluate_raw, reference_transforms

    torch.set_num_threads(threads)
    run = RunArtifacts(RunContext(run_dir, config, outputs=outputs, log=log or (lambda m: None)))
    cfg, device = config, resolve_device(config)
    model, renderer = run.load_model(device)
    est = run.estimator("eval", device)
    fit_gaze = run.fit_gaze_term(device) if cfg.eval.tta_steps > 0 else None
    lpips, identity, pairing, embedding = _optional_scorers(cfg, device, lean)
    raw = evaluate_raw(model, renderer, est, files, res=cfg.data.res, pairs_per_subject=cfg.eval.pairs_per_subject,
                       sampling_steps=eval_sampling_steps(cfg), tta_steps=cfg.eval.tta_steps,
                       tta_weights=tuple(cfg.eval.tta_weights), tta_renderer_lr=cfg.eval.tta_renderer_lr, seed=cfg.seed,
                       device=device, log=run.context.log, references=None if lean else reference_transforms(renderer),
                       own_gaze_row=not lean, tta_region=cfg.eval.tta_region, tta_gaze=fit_gaze, lpips=lpips,
                       identity=identity, pairing=pairing, layout=run.eval_layout, face_embedding=embedding)
    return tensors_to_numpy(raw) if portable else raw


def _optional_scorers(cfg: RunConfig, device, lean: bool = False) -> tuple:
    """(LPIPS, the ArcFace identity model, the pairing, the face embedding): the first two when the eval section
    names their weights, the pairing when it names a file, the embedding when the extra ``identity`` is
    installed (``train.losses.face_embedding``); each None otherwise, and all but the pairing when ``lean``."""
    from train.losses.face_embedding import load_face_embedding

    lpips = identity = pairing = None
    if cfg.eval.pairing_file:
        from train.data.pairing import load_pairing

        pairing = load_pairing(cfg.eval.pairing_file)
    if lean:
        return lpips, identity, pairing, None
    if cfg.eval.lpips_vgg_path:
        from train.losses.lpips import load_lpips

        lpips = load_lpips(cfg.eval.lpips_vgg_path, cfg.eval.lpips_lin_path).to(device)
    if cfg.eval.identity_model_path:
        from train.losses.identity import load_identity_model

        identity = load_identity_model(cfg.eval.identity_model_path, cfg.eval.identity_arch).to(device)
    return lpips, identity, pairing, load_face_embedding(log=lambda m: None)  # the stage says n/a once


def _eval_sweep(run: RunArtifacts, device) -> torch.Tensor:
    """The qualitative figure's last row [G, 3, H, W]: the first held-out pair's input, fitted as the evaluation
    fits it, rendered at ``eval.sweep_frames`` gazes (``train.evaluation.figures.sweep_gazes``)."""
    from train.data.pairing import load_pairing, redirection_pairs, subject_pairing
    from train.evaluation.figures import model_gaze_sweep, sweep_gazes
    from train.evaluation.fitting import restored_weights

    cfg = run.config
    first = run.eval_files()[0]
    pairing = load_pairing(cfg.eval.pairing_file) if cfg.eval.pairing_file else None
    pairs = redirection_pairs(first, subject_pairing(pairing, first.stem), res=cfg.data.res, seed=cfg.seed,
                              layout=run.eval_layout)
    item = pairs.data[int(pairs.pairs[0][0])]  # the first pair's input (its target is not needed here)
    model, renderer = run.load_model(device)
    gazes = sweep_gazes(cfg.eval.sweep_frames)
    with restored_weights(model, renderer):
        if cfg.eval.tta_steps > 0:
            torch.manual_seed(cfg.seed)  # a diffusion renderer's noise while fitting
            code = run.row_fitter(model, renderer, device, cfg.eval.tta_steps)(item, gazes.to(device))
            item = {**item, "latent_code": code[0].cpu()}
        return model_gaze_sweep(model, renderer, item, gazes, cfg.data.res, eval_sampling_steps(cfg), device)
