"""The run presets (``--preset demo|paper|tiny``) and the natural-eyes test-time fit the demo preset and
``apps.redirect --natural-eyes`` use: what each preset chooses, and why, in its docstring."""

from __future__ import annotations

from toolkit.errors import ToolkitError
from train.run_config import (
    CodecStageConfig,
    DataConfig,
    EstimatorStageConfig,
    EvalConfig,
    GaussianStageConfig,
    GeometryStageConfig,
    RunConfig,
)

NATURAL_EYES_FIT = {"weights": ("features", "eye_field", "renderer"), "gaze_weight": 0.002,
                    "reach": ("code", "eye_field"), "terms": ("target", "own"), "every": 2}
"""A test-time fit whose gaze term turns a new face's eyes but cannot repaint them
(``train.evaluation.fitting.FitGaze.reach``): no coloured specks, the iris keeps the trained model's colour.
Its term reads the input's view turned to the target gaze (``target``) and the fitting render against the
loss estimator's reading of the input (``own``), which lowered the gaze error on five seeds (docs/results.md,
2026-11-24). ``apps.redirect --natural-eyes`` and the demo preset fit this way. With ``gaussian.eye_appearance``
the code sets the eye colours too, so a term reaching the code can recolour them."""


def natural_eyes_eval(**others) -> "EvalConfig":
    """An eval section whose test-time fit is :data:`NATURAL_EYES_FIT`; ``others`` set its other fields."""
    n = NATURAL_EYES_FIT
    return EvalConfig(tta_weights=n["weights"], tta_gaze_weight=n["gaze_weight"], tta_gaze_reach=n["reach"],
                      tta_gaze_terms=n["terms"], tta_gaze_every=n["every"], **others)


def demo_preset() -> RunConfig:
    """The CPU demo: ``make demo`` in minutes on 2 cores, 128² renders. Its choices:

    - pixel codec with ``DiT-Gaze-pixel``: the autoencoder the demo can afford capped a latent DiT's renders
      (docs/results.md, 2026-11-23);
    - 12000 Gaussians: a sharper splat and a lower gaze error (docs/results.md, 2026-11-24);
    - parametric eyeball colours: a lower gaze error than free eye colours (docs/results.md, 2026-11-24);
    - the Gaussian stage at twice the default rates (4e-3, renderer 1e-3) (docs/results.md, 2026-11-23);
    - the natural-eyes fit (:data:`NATURAL_EYES_FIT`), 30 steps (docs/results.md, 2026-11-23 and 2026-11-24);
    - step counts (estimators 1200, Gaussian stage 240, fit 30) sized for the slowest 2-core machines seen
      (docs/results.md, 2026-11-23);
    - the estimators' learning rate warmed up over 100 steps: each of 3 seeds' two estimators came out better,
      by 0.2-1.5° (docs/results.md, 2026-11-27)."""
    return RunConfig(preset="demo", geometry=GeometryStageConfig(gaussians=12_000),
                     codec=CodecStageConfig(kind="pixel"),
                     estimator=EstimatorStageConfig(steps=1200, warmup_steps=100),
                     gaussian=GaussianStageConfig(dit_model="DiT-Gaze-pixel", steps=240, lr=4e-3, renderer_lr=1e-3,
                                                  eyeball_colours=True),
                     eval=natural_eyes_eval(tta_steps=30))


def paper_preset() -> RunConfig:
    """The paper's setting, on a GPU: 512² renders, DiT depth 6 / 8 heads (``DiT-Gaze-paper``), 4x feature
    upscaling and GazeGaussian's schedule lengths; ``lambda_ssim`` 0.2, since 0.8 was measured at the demo's
    scale only. Its optimizer: Adam at 1e-4 with GazeGaussian's step decay 0.1^(epoch / 1000) over its 100
    epochs, here 100,000 steps (``lr_decay_steps`` 1,000,000: the rates end at 0.79 of their start). The face
    field reads each Gaussian's feature z₀ and the eyes have gaze-driven appearance terms (``field_input``
    ``feature``, ``eye_field_terms``), as GazeGaussian's fields do. The face and eye terms come from the
    face-only and eye-only Gaussians' own renders (``region_renders`` ``separate``), and the geometry stage
    pre-trains the fields for 3000 steps (``pretrain_fields``; the paper gives no count: the SDF fit's). The
    perceptual term needs the user's VGG16 weights (``gaussian.vgg_path``). Its estimators warm their learning
    rate up over 100 steps, as the demo's."""
    return RunConfig(
        preset="paper",
        data=DataConfig(subjects=80, frames=20, test_frames=0, res=512),
        geometry=GeometryStageConfig(steps=3000, extract_res=128, gaussians=100_000, pretrain_fields=3000),
        codec=CodecStageConfig(steps=20_000, base_channels=64, downsample=8, batch=16),
        estimator=EstimatorStageConfig(steps=20_000, input_size=224, batch=64, synthetic_subjects=200,
                                       synthetic_frames=120, warmup_steps=100),
        gaussian=GaussianStageConfig(dit_model="DiT-Gaze-paper", steps=100_000, batch=4, gaussians_hidden=256,
                                     lambda_ssim=0.2, feature_upscale=4, ckpt_every=2000, log_every=50,
                                     lr=1e-4, renderer_lr=1e-4, lr_schedule="step", lr_decay_steps=1_000_000,
                                     field_input="feature", eye_field_terms=True, region_renders="separate"),
        eval=EvalConfig(pairs_per_subject=100),
    )


def tiny_preset() -> RunConfig:
    """Seconds, for tests: 2 subjects at 64², a few steps of every stage."""
    return RunConfig(
        preset="tiny",
        data=DataConfig(subjects=2, frames=1, test_frames=2, res=64, test_fraction=0.5),
        geometry=GeometryStageConfig(steps=20, extract_res=24, pretrain_steps=50, pool=20000, gaussians=800),
        codec=CodecStageConfig(steps=4, base_channels=8, batch=4),
        estimator=EstimatorStageConfig(steps=4, input_size=32, batch=8, synthetic_subjects=1, synthetic_frames=2),
        gaussian=GaussianStageConfig(steps=4, batch=2, gaussians_hidden=16, ckpt_every=2, log_every=2),
        eval=EvalConfig(pairs_per_subject=2, sweep_frames=3, tta_steps=2),
    )


PRESETS = {"demo": demo_preset, "paper": paper_preset, "tiny": tiny_preset}


def preset(name: str) -> RunConfig:
    if name not in PRESETS:
        raise ToolkitError(f"unknown preset {name!r}; presets are {sorted(PRESETS)}")
    return PRESETS[name]()


__all__ = ["PRESETS", "NATURAL_EYES_FIT", "natural_eyes_eval", "preset", "demo_preset", "paper_preset", "tiny_preset"]
