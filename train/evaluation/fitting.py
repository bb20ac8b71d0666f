"""Test-time fitting: tune a new face's shape code (and optionally some weights) on its input image.

The evaluation (:mod:`train.evaluation.protocol`) and the apps fit each held-out input before rendering it
at a target gaze: Adam on the shape code -- and optionally the Gaussians' features, the eye rotation field,
the renderer and a latent renderer's codec decoder (:data:`TTA_WEIGHT_GROUPS`) -- against the input image,
with an optional gaze term read by the frozen loss estimator (:class:`FitGaze`). Fitted weights change in
place: :func:`restored_weights` puts them back.
"""

from __future__ import annotations

from contextlib import contextmanager
from dataclasses import dataclass
from typing import Any, Iterator

import torch
import torch.nn.functional as F

from toolkit.errors import ToolkitError
from train.evaluation.pairs import spread_indices
from train.losses.metrics import composite_on_white, dilate_mask

TTA_WEIGHT_GROUPS = ("features", "eye_features", "eye_colours", "eye_field", "renderer", "decoder")
"""Weights test-time fitting may tune besides the code: the face Gaussians' canonical features (all channels;
0..2 are the RGB), the eye Gaussians' features, the eye rotation field (``eye_field``: the MLP that turns each
eyeball for a gaze), the neural renderer (the DiT; the baseline's whole network) and a latent renderer's codec
decoder (``decoder``: frozen in training, unfrozen for the fit alone; on a latent DiT's demo run it gave
+0.04 dB and +0.18° gaze error, docs/results.md, 2026-11-23). The encoder, the face deformation field, the eye appearance field
(``gaussian.eye_appearance``; the code it reads is fitted) and the Gaussians' geometry are never fitted. The
features are also field inputs under two switches, so fitting them moves more than colours: with
``gaussian.field_input=feature`` the face features condition the face field's scale, rotation and opacity
deltas, and with ``gaussian.eye_field_terms`` the eye features the eye Gaussians' gaze-driven scale and opacity.

``eye_colours`` (a model with ``eyeball_colours``, :class:`train.model.fields.EyeballColours`): the parametric
eyeball's pupil, iris and sclera colours and its two edge angles, at the code's rate. Eleven numbers,
symmetric about the optical axis: a fit can give the new face its iris but cannot paint one off the axis.

``eye_field`` and ``eye_features`` let a fit with a gaze term (:class:`FitGaze`) turn and redraw a new face's
eyes where the term reads them, instead of only bending the renderer (demo run: gaze 5.95° -> 5.50°,
PSNR 33.60 -> 34.07 dB; docs/results.md, 2026-11-23).

With ``tta_region="face"`` the fitting loss cuts the input's eyes out (:func:`face_only_mask`) and never
checks what the eye Gaussians' features draw: fitting them then only lets the eyes drift (demo run:
held-out gaze 24.4° with them, 20.5° without; docs/results.md, 2026-11-22). They are a group of their own, off by
default."""

NETWORK_GROUPS = ("eye_field", "renderer", "decoder")
"""The ``TTA_WEIGHT_GROUPS`` fitted at the renderer's learning rate."""
COLOUR_GROUPS = ("features", "eye_features", "eye_colours")
"""The ``TTA_WEIGHT_GROUPS`` fitted at the code's learning rate."""

TTA_REGIONS = ("head", "face")
"""What test-time fitting compares: the input's whole head, or its face with the eyes cut out
(:func:`face_only_mask`). The head fits better (demo run, 40 fitting steps: held-out gaze 10.34° against
11.38° with the DiT renderer, 8.04° against 8.16° with the U-Net; docs/results.md, 2026-11-22): the eyes at
the input's own gaze tell the fit more about a new face's eyes than they teach it the wrong gaze."""


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
    estimator (it needs ``batch["gaze_head"]`` and ``batch["landmarks"]``). The input's view is ``batch``'s
    ``in_pose``, ``in_gaze_head``, ``in_viewmat`` and ``in_K`` (else ``K``). Returns the fitted code.
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
    in_K = batch.get("in_K", batch["K"])  # the input's intrinsics, where they differ from the target's
    for step in range(steps):
        # A fresh face stream every step: an unchanged code (a zero gradient) would otherwise hit the cache and
        # reuse the previous step's freed graph.
        model.clear_cache()
        maps = model(code, batch["in_pose"], batch["in_gaze_head"], batch["in_viewmat"], in_K, res, res,
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
    eyes stay natural, at ~1° of the metric (docs/results.md, 2026-11-23)."""

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
            in_K = batch.get("in_K", batch["K"])  # the input's view, with its own intrinsics where given
            maps = model(code, batch["in_pose"], batch["gaze_head"], batch["in_viewmat"], in_K, res, res,
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


