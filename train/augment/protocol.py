"""The augmentation benchmark's two protocols (see :mod:`train.augment`). Each returns
``{arm: {level: [error per unit]}}``: gaze errors in degrees, one per unit (protocol A: a repetition and a
held-out person; protocol B: a repetition), in the same unit order for every arm, so arms compare paired."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path
from typing import Callable

import numpy as np
import torch

from train.augment.config import AugmentConfig
from train.augment.rows import Rows, concat, gaze_grid, read_rows, redirected_rows, source_rows, truth_rows

ARMS_A = ("i", "ii", "iii", "iv")
"""(i) the base estimator; (ii) fine-tuned on k real frames; (iii) plus their redirected copies; (iv) plus the
generator's ground truth at the same gazes."""
ARMS_B = ("real", "redirected")


class Estimators:
    """Trains and scores the estimator under test: the run's design (``estimator.crop``), seeds of its own."""

    def __init__(self, run, cfg: AugmentConfig, device):
        from train.config import component
        from train.estimator.config import GazeEstimatorTrainConfig
        from train.stages.estimator import estimator_design

        self.design = component(estimator_design(run.config), run.config.estimator)
        self.train_config = component(GazeEstimatorTrainConfig, run.config.estimator)
        self.base_steps = cfg.base_steps or self.train_config.steps
        self.cfg, self.device = cfg, device

    def seed(self, repetition: int) -> int:
        return 1000 + 10 * self.cfg.seed + repetition

    def train(self, rows: Rows, repetition: int, *, init=None):
        """From scratch (``init`` None: the base schedule after ``warmup_steps``) or fine-tuned from ``init``
        (``tune_steps`` at ``tune_lr``, no warm-up), with the stage's standard augmentation (flip, blur, colour
        jitter)."""
        from train.estimator.training import train_gaze_estimator

        if init is None:
            schedule = {"steps": self.base_steps, "warmup_steps": self.cfg.warmup_steps}
        else:
            schedule = {"steps": self.cfg.tune_steps, "lr": self.cfg.tune_lr, "warmup_steps": 0}
        tc = replace(self.train_config, seed=self.seed(repetition), log_every=10**9, **schedule)
        model, _ = train_gaze_estimator(rows.images, rows.labels, self.design, tc, landmarks=rows.landmarks,
                                        device=self.device, init=init)
        return model

    def error(self, model, rows: Rows) -> float:
        from train.estimator.training import evaluate_gaze_estimator

        return evaluate_gaze_estimator(model, rows.images, rows.labels, rows.landmarks, device=self.device)["val_gaze_deg"]


def protocol_a(run, cfg: AugmentConfig, device, log: Callable[[str], None] = print) -> dict:
    """Personal calibration: per repetition a base estimator, then per held-out person and k the four arms."""
    est = Estimators(run, cfg, device)
    res, layout = run.config.data.res, run.config.data.layout
    train = _all_rows(run.split("train"), res, layout)
    model, renderer = run.load_model(device)
    fit_steps = cfg.fit_steps or run.config.eval.tta_steps
    gazes = gaze_grid(cfg.grid, cfg.grid_deg)
    out: dict = {arm: {} for arm in ARMS_A}
    for rep in range(cfg.seeds):
        log(f"[augment] A rep {rep}: the base estimator on {len(train)} training rows ({est.base_steps} steps)")
        base = est.train(train, rep)
        for path in run.split("test"):
            person = read_rows(path, res, layout)
            frames = np.random.default_rng(est.seed(rep) * 7919 + len(out["i"])).permutation(
                sorted(set(person.frames.tolist())))
            ks = [k for k in cfg.ks if k < len(frames)]
            if not ks:
                log(f"[augment] {path.name}: {len(frames)} frames, no k of {list(cfg.ks)} leaves a test frame")
                continue
            test = person.take(~person.in_frames(frames[:max(ks)]))
            made = _augmented(run, model, renderer, path, person, frames[:max(ks)], gazes, fit_steps, cfg, device)
            log(f"[augment] A rep {rep} {path.name}: {len(made['iii'])} redirected and true images of "
                f"{max(ks)} calibration frames; {len(test)} test rows")
            for k in ks:
                real = person.take(person.in_frames(frames[:k]))
                arms = {"i": base, "ii": est.train(real, rep, init=base),
                        "iii": est.train(real.cat(made["iii"].take(made["iii"].in_frames(frames[:k]))), rep, init=base),
                        "iv": est.train(real.cat(made["iv"].take(made["iv"].in_frames(frames[:k]))), rep, init=base)}
                errors = {arm: est.error(m, test) for arm, m in arms.items()}
                for arm, e in errors.items():
                    out[arm].setdefault(str(k), []).append(e)
                log(f"[augment] A rep {rep} {path.name} k={k}: " + ", ".join(f"{a} {e:.2f}" for a, e in errors.items()))
    return out


def _augmented(run, model, renderer, path: Path, person: Rows, frames, gazes: torch.Tensor, fit_steps: int,
               cfg: AugmentConfig, device) -> dict[str, Rows]:
    """{"iii": the run's redirected copies, "iv": the generator's ground truth} of ``cfg.redirect_cameras``
    cameras of each of ``frames``."""
    rows = source_rows(person, frames, cfg.redirect_cameras)
    return {"iii": redirected_rows(run, model, renderer, path, rows, gazes, fit_steps, device),
            "iv": truth_rows(path, rows, gazes, run.config.data.res)}


def protocol_b(run, cfg: AugmentConfig, device, log: Callable[[str], None] = print) -> dict:
    """Few subjects: estimators from scratch on n training subjects, without and with redirected copies of their
    frames (the run's trained codes: no fit), scored on every held-out subject."""
    est = Estimators(run, cfg, device)
    res, layout = run.config.data.res, run.config.data.layout
    files = run.split("train")
    test = _all_rows(run.split("test"), res, layout)
    model, renderer = run.load_model(device)
    gazes = gaze_grid(cfg.grid, cfg.grid_deg)
    subjects = {path: read_rows(path, res, layout) for path in files}
    copies: dict[Path, Rows] = {}
    out: dict = {arm: {} for arm in ARMS_B}
    for rep in range(cfg.seeds):
        order = np.random.default_rng(est.seed(rep)).permutation(len(files))
        for n in [n for n in cfg.subjects if n <= len(files)]:
            chosen = [files[i] for i in order[:n]]
            for path in chosen:
                if path not in copies:
                    person = subjects[path]
                    rows = source_rows(person, sorted(set(person.frames.tolist())), cfg.redirect_cameras)
                    copies[path] = redirected_rows(run, model, renderer, path, rows, gazes, 0, device)
            real = concat([subjects[p] for p in chosen])
            errors = {"real": est.error(est.train(real, rep), test),
                      "redirected": est.error(est.train(real.cat(concat([copies[p] for p in chosen])), rep), test)}
            for arm, e in errors.items():
                out[arm].setdefault(str(n), []).append(e)
            log(f"[augment] B rep {rep} n={n}: " + ", ".join(f"{a} {e:.2f}" for a, e in errors.items()))
    return out


def _all_rows(files: list[Path], res: int, layout: str) -> Rows:
    return concat([read_rows(p, res, layout) for p in files])
