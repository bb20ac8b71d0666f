"""Training and scoring a :class:`train.estimator.network.GazeEstimator` on in-memory labelled images."""

from __future__ import annotations

import functools
import logging
import math
import time
from typing import Callable

import torch

from toolkit.errors import ToolkitError
from toolkit.rotations import angular_error_deg, camera_to_head_gaze, pitchyaw_to_vector
from train.estimator.augment import BLUR_BOX_MARGIN, augment_batch, augment_eye_inputs, random_blur
from train.estimator.config import GazeEstimatorConfig, GazeEstimatorTrainConfig
from train.estimator.crops import eye_patch_box, mirror_faces
from train.estimator.network import GazeEstimator

log = logging.getLogger(__name__)


def train_gaze_estimator(images: torch.Tensor, labels: torch.Tensor, config: GazeEstimatorConfig | None = None,
                         train_config: GazeEstimatorTrainConfig | None = None, *,
                         landmarks: torch.Tensor | None = None, val: tuple | None = None,
                         device: str | torch.device = "cpu", init: GazeEstimator | None = None,
                         callback: Callable[[int, dict], None] | None = None,
                         on_step: Callable[[int, float], None] | None = None) -> tuple[GazeEstimator, list[dict]]:
    """Train a :class:`GazeEstimator` on in-memory data.

    Args:
        images: [N, 3, H, W] uint8 or float in [0, 1]; labels: [N, 4] radians (camera-frame gaze pitch, yaw,
            head pitch, yaw in the normalized camera).
        landmarks: [N, 68, 2] pixels, required by eye-patch estimators (``config.eyes``).
        val: optional held-out (images, labels[, landmarks]) evaluated every ``log_every`` steps.
        init: start from this estimator's weights (fine-tuning; the learning-rate schedule starts afresh); its
            configuration must equal ``config``.
        callback: called as ``callback(step, record)`` after each history record, the record with one more key,
            ``val_s``: the wall seconds its held-out evaluation took (0 without ``val``), so a caller can time
            training alone. Timings stay out of the history, which is deterministic for a seed.
        on_step: called as ``on_step(step, loss)`` after every step (a progress bar's hook).
    Returns:
        (model in eval mode, history: list of {"step", "loss", ["val_gaze_deg", "val_head_deg"]}).
    """
    tc = train_config or GazeEstimatorTrainConfig()
    _check_training_inputs(images, labels, config, tc, landmarks=landmarks, val=val)
    torch.manual_seed(tc.seed)
    g = torch.Generator().manual_seed(tc.seed)
    model = _initial_estimator(config, init, device)
    opt = torch.optim.AdamW(model.parameters(), lr=tc.lr, weight_decay=tc.weight_decay)
    sched = torch.optim.lr_scheduler.LambdaLR(opt, functools.partial(_rate_factor, tc.steps, tc.warmup_steps))
    n = images.shape[0]
    history: list[dict] = []
    perm, pos = torch.randperm(n, generator=g), 0
    model.train()
    for step in range(1, tc.steps + 1):
        if pos + tc.batch_size > n:
            perm, pos = torch.randperm(n, generator=g), 0
        idx = perm[pos:pos + tc.batch_size]
        pos += tc.batch_size
        if pos + tc.batch_size <= n and hasattr(images, "prefetch"):  # streamed rows: read the next batch meanwhile
            images.prefetch(perm[pos:pos + tc.batch_size])
        x, y, lm = _training_batch(model, images, labels, landmarks, idx, tc, g, device)
        loss = _estimator_loss(model, x, y, lm, tc, g)
        if not torch.isfinite(loss):  # never a silent NaN estimator: every later reading would be NaN
            raise ToolkitError(f"train_gaze_estimator: non-finite loss at step {step} ({float(loss.detach())}); the estimator "
                               "keeps no checkpoint, nothing was saved: check the training images and labels for "
                               "NaN, or lower the learning rate")
        opt.zero_grad(set_to_none=True)
        loss.backward()
        opt.step()
        sched.step()
        if on_step is not None:
            on_step(step, float(loss.detach()))
        if step % tc.log_every == 0 or step == tc.steps:
            history.append(_history_record(model, step, loss, val, device, callback))
    model.eval()
    return model, history


def _rate_factor(steps: int, warmup: int, step: int) -> float:
    """The learning rate's factor before optimizer step ``step + 1``: a half cosine from 1 to 0 over ``steps``,
    times a linear ramp ``(step + 1) / warmup`` over the first ``warmup`` steps."""
    factor = 0.5 * (1 + math.cos(math.pi * min(step, steps) / steps))
    return factor * (step + 1) / warmup if step < warmup else factor


@torch.no_grad()
def evaluate_gaze_estimator(model: GazeEstimator, images: torch.Tensor, labels: torch.Tensor,
                            landmarks: torch.Tensor | None = None, *, batch_size: int = 256,
                            device: str | torch.device = "cpu") -> dict[str, float]:
    """Mean angular errors in degrees on (images [N, 3, H, W], labels [N, 4], landmarks [N, 68, 2] for
    eye-patch estimators): {"val_gaze_deg", "val_head_deg"}."""
    _check_data(images, labels, "eval")
    _check_landmarks(landmarks, images.shape[0], model.config.eyes, "eval")
    was = model.training
    model.eval()
    g_err, h_err = [], []
    for i in range(0, images.shape[0], batch_size):
        x = _to_float(images[i:i + batch_size].to(device))
        y = labels[i:i + batch_size].float().to(device)
        lm = landmarks[i:i + batch_size].float().to(device) if landmarks is not None else None
        p = model(x, lm)
        g_err.append(angular_error_deg(p[:, :2], y[:, :2]).cpu())
        h_err.append(angular_error_deg(p[:, 2:], y[:, 2:]).cpu())
    model.train(was)
    return {"val_gaze_deg": float(torch.cat(g_err).mean()), "val_head_deg": float(torch.cat(h_err).mean())}


def _check_training_inputs(images: torch.Tensor, labels: torch.Tensor, config: GazeEstimatorConfig | None,
                           tc: GazeEstimatorTrainConfig, *, landmarks: torch.Tensor | None, val: tuple | None) -> None:
    needs = bool(config is not None and config.eyes)
    _check_data(images, labels, "train")
    _check_landmarks(landmarks, images.shape[0], needs, "train")
    if val is not None:
        _check_data(val[0], val[1], "val")
        _check_landmarks(val[2] if len(val) > 2 else None, val[0].shape[0], needs, "val")
    tc.validate()


def _check_data(images: torch.Tensor, labels: torch.Tensor, name: str) -> None:
    if images.dim() != 4 or images.shape[1] != 3:
        raise ToolkitError(f"{name} images: expected [N, 3, H, W], got {list(images.shape)}")
    if labels.shape != (images.shape[0], 4):
        raise ToolkitError(f"{name} labels: expected [N={images.shape[0]}, 4] (gaze pitch, yaw, head pitch, yaw), got {list(labels.shape)}")
    if not bool(torch.isfinite(labels).all()):
        raise ToolkitError(f"{name} labels: contain NaN or inf")


def _check_landmarks(landmarks: torch.Tensor | None, n: int, model_needs: bool, name: str) -> None:
    if model_needs and landmarks is None:
        raise ToolkitError(f"{name}: this estimator reads eye patches; landmarks [N, 68, 2] are required")
    if landmarks is not None:
        if tuple(landmarks.shape) != (n, 68, 2):
            raise ToolkitError(f"{name} landmarks: expected [N={n}, 68, 2] pixels, got {list(landmarks.shape)}")
        if not bool(torch.isfinite(landmarks).all()):
            raise ToolkitError(f"{name} landmarks: contain NaN or inf")


def _initial_estimator(config: GazeEstimatorConfig | None, init: GazeEstimator | None, device) -> GazeEstimator:
    """A fresh estimator of ``config`` on ``device`` (drawn from the global random state), with ``init``'s weights
    when given."""
    model = GazeEstimator(config).to(device)
    if init is not None:
        if init.config != model.config:
            raise ToolkitError(f"train_gaze_estimator: init has configuration {init.config}, expected {model.config}")
        model.load_state_dict(init.state_dict())
    return model


def _training_batch(model: GazeEstimator, images: torch.Tensor, labels: torch.Tensor, landmarks: torch.Tensor | None,
                    idx: torch.Tensor, tc: GazeEstimatorTrainConfig, g: torch.Generator, device
                    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor | None]:
    """The samples ``idx`` on ``device`` as (images [B, 3, H, W] float, labels [B, 4], landmarks [B, 68, 2] or
    None), mirrored and blurred by the augmentation (the rest of it acts on what the network reads)."""
    x = _to_float(images[idx].to(device, non_blocking=True))  # uint8 travels: 4x fewer bytes than float
    y = labels[idx].float().to(device)
    lm = landmarks[idx].float().to(device) if landmarks is not None else None
    if tc.augment and tc.mirror > 0:
        x, y, lm = mirror_faces(x, y, lm, torch.rand(len(idx), generator=g) < tc.mirror)
    if tc.augment and tc.blur_prob > 0:
        # Eye-patch designs read the eyes alone: blur their box, widened for the landmark jitter drawn next.
        box = (eye_patch_box(lm, x.shape[2], x.shape[3], margin=BLUR_BOX_MARGIN) if model.config.eyes
               else None)
        x = random_blur(x, tc.blur_prob, tc.blur_sigma, g, box)
    return x, y, lm


def _to_float(images: torch.Tensor) -> torch.Tensor:
    return images.float() / 255.0 if images.dtype == torch.uint8 else images.float()


def _estimator_loss(model: GazeEstimator, x: torch.Tensor, y: torch.Tensor, lm: torch.Tensor | None,
                    tc: GazeEstimatorTrainConfig, g: torch.Generator) -> torch.Tensor:
    """[] the training loss of one batch (:attr:`GazeEstimatorTrainConfig.loss_space`), the rest of the
    augmentation applied to what the network reads."""
    if model.config.eyes:
        eye_in = augment_eye_inputs(x, lm, model, tc, g) if tc.augment else model.eye_inputs(x, lm)
        parts = model.from_eye_inputs(*eye_in)
    else:
        parts = model.forward_parts(augment_batch(x, tc, g) if tc.augment else x)
    pred = model.compose(parts)
    if tc.loss_space != "vectors":
        w = torch.tensor([1.0, 1.0, tc.head_weight, tc.head_weight], device=pred.device)
        return ((pred - y).abs() * w).mean()
    pv = torch.cat([pitchyaw_to_vector(pred[:, :2]), pitchyaw_to_vector(pred[:, 2:])], -1)
    yv = torch.cat([pitchyaw_to_vector(y[:, :2]), pitchyaw_to_vector(y[:, 2:])], -1)
    d = (pv - yv).abs()
    loss = d[:, :3].mean() + tc.head_weight * d[:, 3:].mean()
    if model.config.head_frame:
        # Supervise the head-frame gaze too: it is what the eyes show, whatever the view.
        d_h = pitchyaw_to_vector(parts[:, :2]) - pitchyaw_to_vector(camera_to_head_gaze(y[:, :2], y[:, 2:]))
        loss = loss + d_h.abs().mean()
    return loss


def _history_record(model: GazeEstimator, step: int, loss: torch.Tensor, val: tuple | None, device,
                    callback: Callable[[int, dict], None] | None) -> dict:
    """The history record of ``step``: its loss and, with ``val``, the held-out errors; logged and passed to
    ``callback`` with the seconds the held-out evaluation took."""
    rec, val_s = {"step": step, "loss": float(loss.detach())}, 0.0
    if val is not None:
        t0 = time.perf_counter()
        rec.update(evaluate_gaze_estimator(model, *val, device=device))
        val_s = time.perf_counter() - t0
        model.train()
    log.info("gaze estimator step %d: %s", step, rec)
    if callback is not None:
        callback(step, dict(rec, val_s=val_s))
    return rec
