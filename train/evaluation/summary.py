"""Joining and summarizing the protocol's raw results: :func:`train.evaluation.protocol.evaluate_raw`'s
per-pair scores of disjoint subject groups merged, put back in subject order, and made into the metrics
table (means, medians, bootstrap intervals, FID), with the identity measures and the natural fit's row."""

from __future__ import annotations

from typing import Any

import numpy as np
import torch

from toolkit.errors import ToolkitError
from train.evaluation.fid import fid_or_none
from train.evaluation.figures import WORST_EYE_PAIRS
from train.losses.metrics import bootstrap_mean_interval, summarize


def merge_raw_evaluations(parts: list[dict[str, Any]]) -> dict[str, Any]:
    """:func:`evaluate_raw` results of disjoint subject groups, in order, joined into one (lists concatenated,
    counts and times summed, the first group's examples)."""
    if not parts:
        raise ToolkitError("merge_raw_evaluations: expected at least one evaluation")
    lists = ("gaze_err", "head_err", "psnrs", "ssims", "reals", "fakes", "per_subject", "per_pair", "worst_eyes")
    out: dict[str, Any] = {k: [] for k in lists}
    out.update(ref_scores={}, own_scores={}, label_scores={}, examples=None, n_images=0, render_seconds=0.0)
    for part in parts:
        for k in lists:
            out[k] += part[k]
        for field in ("ref_scores", "label_scores"):
            for name, scores in part[field].items():
                for key, vals in scores.items():
                    out[field].setdefault(name, {}).setdefault(key, []).extend(vals)
        for key, vals in part["own_scores"].items():
            out["own_scores"].setdefault(key, []).extend(vals)
        if out["examples"] is None:
            out["examples"] = part["examples"]
        out["n_images"] += part["n_images"]
        out["render_seconds"] += part["render_seconds"]
    return out


PAIR_LISTS = {"gaze_err": "gaze_error_deg", "head_err": "head_pose_error_deg", "psnrs": "psnr", "ssims": "ssim"}
"""The flat per-pair lists of an :func:`evaluate_raw` result and the ``per_pair`` record key each copies."""


def in_subject_order(raw: dict[str, Any], subjects: list[str]) -> dict[str, Any]:
    """A merged evaluation (:func:`merge_raw_evaluations` of groups that interleave the subjects) back in the
    order of ``subjects`` (file names): the per-subject and per-pair records, and the flat lists the means and
    bootstrap intervals are drawn from, so the summary is what one process evaluating them in turn gives."""
    order = {name: i for i, name in enumerate(subjects)}
    out = dict(raw)
    out["per_subject"] = sorted(raw["per_subject"], key=lambda r: order[r["subject"]])
    out["per_pair"] = sorted(raw["per_pair"], key=lambda r: order[r["subject"]])  # stable: pairs keep their order
    for key, field in PAIR_LISTS.items():
        out[key] = [r[field] for r in out["per_pair"]]
    return out


IDENTITY_KEYS = ("identity_similarity", "identity_similarity_input", "identity_drift", "identity_drift_real")
"""The per-pair identity scores (``train.evaluation.protocol``), each in a record only when its model was given:
ArcFace similarity render <-> target and input <-> render, dlib embedding distance input -> render and, its
floor, input -> real target."""


def summarize_evaluation(raw: dict[str, Any], *, own_gaze_row: bool = False, log=print,
                         natural_fit: dict[str, Any] | None = None) -> dict[str, Any]:
    """:func:`evaluate`'s result from :func:`evaluate_raw`'s (or :func:`merge_raw_evaluations`'s). ``natural_fit``:
    the same pairs' raw result under the fit without a gaze term (the eval stage's second pass), summarized
    into ``metrics["natural_fit"]`` (:func:`natural_fit_summary`), its pairs' records in
    ``"natural_fit_per_pair"``."""
    psnrs = raw["psnrs"]
    reals, fakes, n_images, total_render_time = raw["reals"], raw["fakes"], raw["n_images"], raw["render_seconds"]
    metrics = {
        **render_scores(raw),
        **{k: summarize([r[k] for r in raw["per_pair"] if k in r]) for k in ("lpips", *IDENTITY_KEYS)},
        **identity_drift_intervals(raw["per_pair"]),
        "fid": fid_or_none(torch.cat(reals), torch.cat(fakes), log) if reals else None,
        "images_per_s": n_images / max(total_render_time, 1e-9) if n_images else None, "pairs": len(psnrs),
    }
    references_out = {name: {k: summarize(v) for k, v in sc.items()} for name, sc in raw["ref_scores"].items()}
    labels = {who: {k: summarize(v) for k, v in sc.items()} for who, sc in raw["label_scores"].items() if sc}
    worst = sorted(raw["worst_eyes"], key=lambda r: -r["gaze_error_deg"])[:WORST_EYE_PAIRS]
    out = {"metrics": metrics, "per_subject": raw["per_subject"], "per_pair": raw["per_pair"],
           "examples": raw["examples"], "references": references_out, "labels": labels, "worst_eyes": worst}
    if own_gaze_row:
        out["own_gaze"] = {k: summarize(v) for k, v in raw["own_scores"].items()}
    if natural_fit is not None:
        metrics["natural_fit"] = natural_fit_summary(natural_fit, raw["per_pair"])
        out["natural_fit_per_pair"] = natural_fit["per_pair"]
    return out


def render_scores(raw: dict[str, Any]) -> dict[str, Any]:
    """The renders' scores of a raw evaluation (the main row's and the natural fit's alike): gaze error (mean,
    median, 95% interval), head-pose error, PSNR (mean, interval), SSIM."""
    gaze_err, psnrs = raw["gaze_err"], raw["psnrs"]
    return {
        "gaze_error_deg": summarize(gaze_err), "head_pose_error_deg": summarize(raw["head_err"]),
        # The mean is the protocol's; the median shows how much of it a few pairs make (side views where the
        # target looks far away from the camera and the estimator barely sees an iris).
        "gaze_error_median_deg": float(np.median(gaze_err)) if gaze_err else None,
        # How far the mean could move with other pairs of the same subjects: a few pairs make much of it.
        "gaze_error_ci95_deg": bootstrap_mean_interval(gaze_err), "psnr_ci95": bootstrap_mean_interval(psnrs),
        "psnr": summarize(psnrs), "ssim": summarize(raw["ssims"])}


def identity_drift_intervals(per_pair: list[dict[str, Any]]) -> dict[str, tuple[float, float] | None]:
    """95% bootstrap intervals over the pairs of the mean identity drift (input -> render), of its floor (input
    -> real target) and of their paired difference (``identity_drift_excess_ci95``: what the redirection loses
    beyond a change of gaze); None without the face embedding."""
    drift = [r for r in per_pair if "identity_drift" in r]
    return {"identity_drift_ci95": bootstrap_mean_interval([r["identity_drift"] for r in drift]),
            "identity_drift_real_ci95": bootstrap_mean_interval([r["identity_drift_real"] for r in drift]),
            "identity_drift_excess_ci95": bootstrap_mean_interval(
                [r["identity_drift"] - r["identity_drift_real"] for r in drift])}


def natural_fit_summary(natural: dict[str, Any], per_pair: list[dict[str, Any]]) -> dict[str, Any]:
    """The natural fit's row from its raw result (the same pairs fitted without a gaze term): gaze and
    head-pose errors, PSNR, SSIM with the main row's spread measures, the renders' reading against the
    targets' labels (``render_vs_label_gaze_deg``, eye realism; None without labels), and the paired change of
    the gaze error against the main row's fit, ``per_pair`` (``gaze_error_delta_deg``: natural minus main, mean
    and 95% interval over the pairs both scored)."""
    main = {(r["subject"], r["pair"]): r["gaze_error_deg"] for r in per_pair}
    delta = [r["gaze_error_deg"] - main[k] for r in natural["per_pair"] if (k := (r["subject"], r["pair"])) in main]
    return {**render_scores(natural),
            "render_vs_label_gaze_deg": summarize(natural["label_scores"].get("render", {}).get("gaze_error_deg", [])),
            "gaze_error_delta_deg": summarize(delta), "gaze_error_delta_ci95_deg": bootstrap_mean_interval(delta),
            "pairs": len(natural["psnrs"])}

