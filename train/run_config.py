"""The configuration of a DiT-Gaze run: one dataclass per stage, and the paper's ablation switches (the presets
are in ``train.presets``).

Stored as ``config.yaml`` in the run directory; any field can be overridden from the command line as
``section.field=value`` (see ``train.config``). Each field declares its range in its metadata (checked at load
and override time); the rules across fields are in ``train.stages.checks``. A stage field that sets a field of
a component's own config declares it with ``maps_to`` (``train.config.component`` builds that config).

Ablations of the paper's Table 3: ``gaussian.renderer=dit|unet``, ``gaussian.orthogonality=true|false``,
``gaussian.weak_supervision=true|false``.
"""

from __future__ import annotations

import re
from dataclasses import dataclass, field, replace
from typing import Literal

from train.config import NEUTRAL, at_least, maps_to, rule, within

COUNT = at_least(1, "a count")
"""Something counted (steps, images, channels): >= 1."""
WEIGHT = at_least(0, "a finite value")
"""A loss weight or an optional count: 0 turns it off."""
RATE = within(0, 1, "a learning rate", low_open=True)
"""An Adam learning rate: Adam's step is about the rate, so > 1 overflows."""
SEED = at_least(0, "a seed") | rule(lambda s: s < 2**32, "a seed below 2^32")
MAX_STEPS = 10_000_000
STEP_CAP = rule(lambda n: n <= MAX_STEPS, f"at most {MAX_STEPS} steps (a loop that long is a typo)")
"""Every step count's upper bound: the paper's longest schedule is 100,000 steps."""
DEVICE = rule(lambda d: re.fullmatch(r"auto|cpu|cuda(:\d+)?", d) is not None, "auto, cpu, cuda or cuda:N")


@dataclass
class DataConfig:
    root: str = ""
    """folder of HDF5 subject files (docs/data.md); empty: generate the synthetic dataset into the run dir."""
    subjects: int = 10
    """synthetic subjects to generate, >= 2; the last ``test_fraction`` of them are held out. More training
    identities lower the held-out gaze error (docs/results.md, 2026-11-22)."""
    frames: int = field(default=4, metadata=COUNT)
    """synthetic frames per subject, each seen by the 18 rig cameras."""
    test_frames: int = field(default=8, metadata=rule(lambda n: n >= 0 and n % 2 == 0,
                                                      "0 (as data.frames) or an even frame count"))
    """synthetic frames per held-out subject: 0 (as ``frames``) or an even count. A pair's input comes from the
    first half of a subject's rows and its target from the second, so this sets how many distinct
    redirections the gaze error averages over (docs/results.md, 2026-11-22)."""
    res: int = 128
    """image size in pixels for training and evaluation, in ``train.data.generate.RES_RANGE``."""
    test_fraction: float = field(default=0.2, metadata=within(0, 1, "a share", high_open=True))
    """share of the subjects held out for evaluation, in [0, 1)."""
    seed: int = field(default=0, metadata=SEED)
    """seed of the synthetic subjects, in [0, 2^32)."""
    light_jitter: float = field(default=0.0, metadata=within(0, 2))
    """spread of the synthetic per-frame light direction, in [0, 2]; 0: one frontal light, like ETH-XGaze's
    full-lighting frames. The model has no light input: only test-time fitting recovers a held-out light."""
    kappa_deg: float = field(default=0.0, metadata=NEUTRAL | within(0, 15, "degrees"))
    """synthetic subjects' angle κ between each eye's optical axis and the gaze label, degrees in [0, 15]: each
    subject draws its own around this (``SubjectParams.sample``), as real people differ (~5°); 0: none. Without
    it no person differs from the others in how the eyes look at a gaze, so personal calibration cannot pay
    (docs/results.md, 2026-11-27)."""
    layout: Literal["auto", "ditgaze", "gazegaussian", "gazenerf", "xgaze"] = field(default="auto", metadata=NEUTRAL)
    """how ``root``'s files are laid out (``train.data.layouts``, docs/data.md): ``auto`` decides from each file's
    keys and asks for this key where they fit several layouts; a named layout is checked against the keys."""
    split_file: str = field(default="", metadata=NEUTRAL)
    """the split of ``root``'s subjects: a JSON file in the layout's form (``split.json`` {"train", "test"};
    the peers' ``train_test_split.json`` {"train", "val"}); empty: the one beside the files, else the last
    ``test_fraction`` of them held out."""


@dataclass
class GeometryStageConfig:
    steps: int = field(default=300, metadata=COUNT | maps_to("FitConfig", "steps") | STEP_CAP)
    """SDF fitting steps after the sphere pre-training, >= 1."""
    extract_res: int = field(default=64, metadata=within(4, 512, "a tet-grid resolution")
                             | maps_to("FitConfig", "extract_res"))
    """DMTet grid resolution of the neutral mesh, in [4, 512]."""
    pretrain_steps: int = field(default=100, metadata=WEIGHT | maps_to("FitConfig", "pretrain_steps") | STEP_CAP)
    """sphere pre-training steps of the SDF network, >= 0."""
    pool: int = field(default=100_000, metadata=COUNT | maps_to("FitConfig", "pool") | rule(
        lambda n: n >= 1000, ">= 1000 pool points (the SDF fit draws its batches and surface seeds from them)"))
    """labelled sample points (visual-hull signed distances) the SDF fit draws from, >= 1000."""
    gaussians: int = field(default=6000, metadata=COUNT | maps_to("InitConfig", "n_points") | rule(
        lambda n: n >= 16, ">= 16 Gaussians (the initialization needs 16 surface points)"))
    """Gaussians sampled on the neutral mesh (face and eyes), >= 16."""
    eye_gaussians: int = field(default=400, metadata=maps_to("InitConfig", "eye_points") | rule(
        lambda n: n == 0 or n >= 4, "0 (the mesh's eye points) or >= 4"))
    """Gaussians per eye, spread evenly over its eyeball's front cap: 0 (the mesh's own points, ~40 per eye of
    6000) or >= 4. 400 lowered the demo's held-out gaze error (docs/results.md, 2026-11-22)."""
    lid_gaussians: int = field(default=0, metadata=NEUTRAL | maps_to("InitConfig", "lid_points"))
    """face Gaussians per eye on a lid shell in front of the eyeball, outside the lid landmarks' polygon, >= 0;
    > 0 needs ``eye_gaussians`` > 0. Off: they helped the unfitted renders but not the fitted redirections
    (docs/results.md, 2026-11-24)."""
    subject: int = field(default=0, metadata=at_least(0, "a training-subject index"))
    """index of the training subject whose views define the neutral mesh (the last one if beyond)."""
    pretrain_fields: int = field(default=0, metadata=NEUTRAL | at_least(0, "a step count") | STEP_CAP)
    """steps pre-training the two-stream model's face deformation and eye rotation fields on the training split
    after the mesh is fitted (GazeGaussian's MeshHead stage; ``train.stages.field_pretrain``, docs/model.md), >= 0;
    the Gaussian stage starts from them. 0: off, the fields start untrained (zero last layers). With it on, the
    stage also depends on the ``gaussian`` section's model fields (the fields' architecture)."""


@dataclass
class CodecStageConfig:
    kind: Literal["ae", "sd-vae", "pixel"] = "ae"
    """latent codec: the small KL autoencoder trained here (``ae``), Stable Diffusion's VAE from a local folder
    (``sd-vae``, needs ``data.res`` a multiple of 8), or pixels (``pixel``, with ``gaussian.dit_model=
    DiT-Gaze-pixel``; the stage then does nothing)."""
    sd_vae_path: str = ""
    """local diffusers AutoencoderKL folder, for ``kind=sd-vae``."""
    steps: int = field(default=640, metadata=COUNT | STEP_CAP)
    """Adam steps of the autoencoder. A better reconstruction raised the DiT's renders with it
    (docs/results.md, 2026-11-22)."""
    base_channels: int = field(default=16, metadata=COUNT | maps_to("AutoencoderConfig", "base_channels"))
    """channels of the autoencoder at full resolution, >= 1."""
    downsample: int = field(default=4, metadata=maps_to("AutoencoderConfig", "downsample"))
    """spatial reduction of the autoencoder's latent: a power of two dividing ``data.res`` (SD's VAE: 8)."""
    batch: int = field(default=8, metadata=COUNT)
    """images per autoencoder step."""
    eye_weight: float = field(default=100.0, metadata=at_least(0, "a weight"))
    """extra weight of the eye pixels (eye masks dilated by 2 px) in the reconstruction loss, >= 0: the eyes
    are ~1% of a face crop, and a plain L1 blurs the gaze away (docs/results.md, 2026-11-22)."""


@dataclass
class EstimatorStageConfig:
    loss_path: str = ""
    """a trained gaze estimator (.safetensors) for the gaze loss; empty: train one."""
    eval_path: str = ""
    """an independently trained estimator for the evaluation; empty: train one (another seed)."""
    steps: int = field(default=1000, metadata=COUNT | maps_to("GazeEstimatorTrainConfig", "steps") | STEP_CAP)
    """training steps of each estimator."""
    input_size: int = field(default=64, metadata=COUNT)
    """width in pixels the estimator's input region is resized to (``face`` and ``eye_band`` crops only)."""
    batch: int = field(default=64, metadata=COUNT | maps_to("GazeEstimatorTrainConfig", "batch_size"))
    """images per estimator step."""
    crop: Literal["eyes", "face", "eye_band"] = "eyes"
    """what the estimators read: two eye patches cut at the eye landmarks plus the landmark layout
    (``GazeEstimatorConfig.eyes``), the whole normalized face crop, or the band holding both eyes
    (``train.estimator.config.EYE_BAND``)."""
    synthetic_subjects: int = field(default=20, metadata=WEIGHT)
    """extra procedural subjects rendered for each estimator's training only, >= 0 (synthetic runs; ignored
    with ``data.root``); their seeds are disjoint from the data stage's and between the two estimators."""
    synthetic_frames: int = field(default=20, metadata=COUNT)
    """random (gaze, pose, expression) frames per extra subject. More faces help more than more frames per face
    (docs/results.md, 2026-11-21)."""
    cameras_per_frame: int = field(default=2, metadata=COUNT)
    """rig cameras drawn at random per extra frame, at most the rig's 18."""
    mirror_average: bool = field(default=True, metadata=maps_to("GazeEstimatorConfig", "mirror_average"))
    """the estimators trained here also read the mirrored image and average the two (estimators given by path
    keep their own setting)."""
    blur_prob: float = field(default=0.5, metadata=maps_to("GazeEstimatorTrainConfig", "blur_prob"))
    """probability of a random Gaussian blur on a training image, in [0, 1], so a softer render of the same eyes
    reads as the same gaze (docs/results.md, 2026-11-22)."""
    blur_sigma: float = field(default=1.2, metadata=maps_to("GazeEstimatorTrainConfig", "blur_sigma"))
    """largest standard deviation of that blur, pixels, >= 0."""
    warmup_steps: int = field(default=0, metadata=NEUTRAL | at_least(0, "a step count") | STEP_CAP
                              | maps_to("GazeEstimatorTrainConfig", "warmup_steps"))
    """steps of a linear learning-rate warm-up before each estimator's cosine decay, >= 0; 0: none (the demo and
    paper presets: 100, which made every seed's estimator better; docs/results.md, 2026-11-27)."""


@dataclass
class GaussianStageConfig:
    renderer: Literal["dit", "unet"] = "dit"
    """the neural renderer: the latent DiT (ours) or GazeGaussian's U-Net-style baseline."""
    dit_model: str = "DiT-Gaze-tiny"
    """DiT only: the model size, a name of ``train.model.dit.DIT_MODELS``."""
    dit_feature_hidden: int = field(default=64, metadata=NEUTRAL | at_least(1, "a channel count"))
    """DiT only: hidden channels of the renderer's feature encoder (``DiTConfig.feature_hidden``)."""
    residual: bool = True
    """DiT only: predict the clean latent as the encoded, upsampled splat RGB plus a learned residual (the
    untrained renderer outputs the splat's own image); false: the plain latent DiT (train/model/renderer.py)."""
    sampling_steps: int = field(default=1, metadata=COUNT)
    """DDIM steps at evaluation, at most the diffusion's timesteps (1: the deterministic one-step path). Part of
    this stage's fingerprint, so changing it retrains; ``eval.sampling_steps`` does not."""
    onestep_fraction: float = field(default=0.5, metadata=within(0, 1, "a share"))
    """DiT only: share of each training batch rendered at t = T - 1, the one-step path evaluation uses, in
    [0, 1]; the rest at uniformly drawn diffusion times."""
    rgb_init: bool = True
    """start the Gaussians' RGB channels from the training images (train/model/rgb_init.py) instead of the
    geometry stage's SDF features (docs/results.md, 2026-11-22)."""
    orthogonality: bool = True
    """the orthogonality loss between the gaze / pose / expression features."""
    ortho_weight: float = field(default=0.01, metadata=WEIGHT)
    """weight of the orthogonality loss, >= 0."""
    weak_supervision: bool = True
    """intermediate-gaze weak supervision (gaze loss to the sampled gaze + face-region image loss)."""
    weak_weight: float = field(default=0.5, metadata=WEIGHT)
    """weight of the weak supervision's losses, >= 0."""
    sampler_mode: Literal["uniform", "biased_center", "mixed"] = field(
        default="mixed", metadata=maps_to("GazeSamplerConfig", "mode"))
    """how the intermediate gazes are drawn (``train.training.gaze_sampler``)."""
    sampler_range_deg: float = field(default=35.0, metadata=maps_to("GazeSamplerConfig", "range_deg"))
    """half-width of the intermediate gazes' pitch and yaw range, degrees, in (0, 89]."""
    steps: int = field(default=320, metadata=COUNT | STEP_CAP)
    """training steps of the stage."""
    batch: int = field(default=4, metadata=COUNT)
    """images per step (split over the processes under torchrun)."""
    lr: float = field(default=2e-3, metadata=RATE)
    """Adam learning rate of the Gaussian model's weights (fields, features, scales, opacities, rotations)."""
    means_lr: float = field(default=1.6e-4, metadata=RATE)
    """learning rate of the canonical Gaussian centres, as a fraction of the head's radius per step (3DGS's
    position rate relative to the scene extent; ``train.training.trainer.optimizer_groups``)."""
    renderer_lr: float = field(default=5e-4, metadata=RATE)
    """Adam learning rate of the neural renderer."""
    lr_schedule: Literal["constant", "cosine", "step"] = field(default="constant", metadata=NEUTRAL)
    """the rates over the stage: constant; a half cosine from the configured rates down to ``lr_final`` times
    them at the last step; or ``step``, the paper's step decay, tenfold every ``lr_decay_steps`` steps
    (0.1^(step / lr_decay_steps), every group alike). A resumed run with more steps follows the longer curve."""
    lr_decay_steps: int = field(default=1000, metadata=NEUTRAL | COUNT)
    """step schedule: steps per tenfold fall of the rates, >= 1 (GazeGaussian's ``step_decay`` 1000; docs/model.md)."""
    lr_final: float = field(default=0.1, metadata=NEUTRAL | within(
        0, 1, "a factor {} of the rates at the last step"))
    """cosine schedule: the rates' factor at the last step, in [0, 1]."""
    vgg_path: str = field(default="", metadata=NEUTRAL)
    """a local VGG16 state dict (torchvision layout, ``train.losses.vgg``): turns on the perceptual term of the
    image loss at ``lambda_perceptual``, as the paper trains; empty: off (docs/model.md)."""
    lambda_perceptual: float = field(default=0.1, metadata=NEUTRAL | WEIGHT)
    """weight of the perceptual term when ``vgg_path`` is given, >= 0 (GazeGaussian's ``vgg_importance`` 0.1)."""
    ema_decay: float = field(default=0.0, metadata=NEUTRAL | within(
        0, 1, "a decay {} (0: no average)", high_open=True))
    """decay of an exponential moving average of the model's and renderer's weights, in [0, 1), updated after
    every step; the final checkpoint then holds the average (``train.training.ema``). 0: none, as in the demo,
    where the average lags a model still improving (docs/results.md, 2026-11-24)."""
    lambda_rgb: float = field(default=1.0, metadata=WEIGHT)
    """weight of the low-resolution RGB supervision of the splatted feature maps' first three channels."""
    lambda_gaze: float = field(default=0.002, metadata=WEIGHT)
    """weight of the gaze losses (degrees), >= 0. At 0.05 their gradient swamped the image loss's and the
    renders lost their faces (docs/results.md, 2026-11-22)."""
    lambda_ssim: float = field(default=0.8, metadata=WEIGHT | maps_to("ImageLossConfig", "lambda_ssim"))
    """weight of (1 - SSIM) beside the L1 in the image loss, >= 0; 0.8 rendered better than 0.2 at the demo's
    scale (docs/results.md, 2026-11-22)."""
    diffusion_weight: float = field(default=1.0, metadata=WEIGHT)
    """weight of the renderer's diffusion loss, >= 0."""
    gaussians_hidden: int = field(default=64, metadata=COUNT | maps_to("GaussianModelConfig", "hidden"))
    """hidden width of the Gaussian model's MLPs."""
    feature_upscale: int = 1
    """output size / splatted feature-map size, a power of two dividing ``data.res``. GazeGaussian uses 4 at
    512² (the paper preset); at 128² a 1:1 map keeps the eyes ~12 px wide (docs/results.md, 2026-11-22)."""
    eyes_follow_face: bool = field(default=True, metadata=maps_to("GaussianModelConfig", "eyes_follow_face"))
    """move each eyeball with its socket as the face field deforms the face, so the eyes follow the identity
    the code describes and a fit of a new face's code moves them too."""
    eye_appearance: bool = field(default=False, metadata=maps_to("GaussianModelConfig", "eye_appearance"))
    """code-conditioned colours of the eye Gaussians (each identity its own iris); excludes
    ``eyeball_colours``. Off: no gaze gain on the demo (docs/results.md, 2026-11-23)."""
    eyeball_colours: bool = field(default=False, metadata=NEUTRAL | maps_to("GaussianModelConfig", "eyeball_colours"))
    """the eye Gaussians' RGB from a parametric pupil / iris / sclera (:class:`train.model.fields.EyeballColours`)
    instead of a free colour each; excludes ``eye_appearance``."""
    region_renders: Literal["masks", "separate"] = field(default="masks", metadata=NEUTRAL)
    """where the image loss's face and eye terms come from: ``masks``, the head render under the face and eye
    masks; ``separate``, GazeGaussian's form: the face-only and the eye-only Gaussians also splatted and rendered
    on their own, their terms taken from those renders against the masked targets (and their splatted RGB
    against the target in their region): three splats and three renderer passes instead of one, 1.6x the tiny
    preset's step time (docs/model.md)."""
    field_input: Literal["position", "feature"] = field(
        default="position", metadata=NEUTRAL | maps_to("GaussianModelConfig", "field_input"))
    """what the face field's MLPs read per Gaussian: ``position``, PE(x) for every delta; ``feature``, the
    paper's form (GazeGaussian's eq. 2): PE(x) for Δposition, the Gaussian's canonical feature z₀ for Δfeature,
    Δscale, Δrotation and Δopacity (docs/model.md)."""
    eye_field_terms: bool = field(default=False, metadata=NEUTRAL | maps_to("GaussianModelConfig", "eye_field_terms"))
    """gaze-driven deltas of the eye Gaussians' features, scales and opacities from their canonical features (the
    paper's eye-branch appearance terms; zero at initialization). With ``eyeball_colours`` the RGB stays
    parametric and the terms move the other channels, the scales and the opacities (docs/model.md)."""
    ckpt_every: int = field(default=100, metadata=COUNT)
    """steps between checkpoints."""
    log_every: int = field(default=10, metadata=COUNT)
    """steps between metric records."""
    grad_clip: float = field(default=1.0, metadata=at_least(0, "a gradient-norm bound {} (0 = no clipping)"))
    """bound of the gradients' global norm, >= 0 (0: no clipping)."""


FittedWeight = Literal["features", "eye_features", "eye_colours", "eye_field", "renderer", "decoder"]


@dataclass
class EvalConfig:
    pairs_per_subject: int = field(default=12, metadata=COUNT)
    """redirection pairs per held-out subject (GazeNeRF protocol: inputs paired with a fixed permutation)."""
    tta_steps: int = field(default=40, metadata=at_least(0, "a step count") | STEP_CAP)
    """test-time fitting steps on each input image, >= 0 (0: none), restarted per pair from the trained
    weights; more steps fit better and cost time (docs/results.md, 2026-11-22)."""
    tta_weights: tuple[FittedWeight, ...] = ("features", "renderer")
    """weights fitted with the shape code: the face Gaussians' features, the eye Gaussians' features
    (``eye_features``), the parametric eyeball's colours (``eye_colours``, needs ``gaussian.eyeball_colours``),
    the eye rotation field (``eye_field``, at ``tta_renderer_lr``), the renderer (pairs are then fitted one at
    a time), a latent DiT's codec decoder (``decoder``); () fits the code alone, a subject's pairs in one batch."""
    tta_region: Literal["head", "face"] = "head"
    """what test-time fitting compares: the input's whole head, or its face with the eyes cut out
    (docs/results.md, 2026-11-22)."""
    tta_renderer_lr: float = field(default=1e-3, metadata=RATE)
    """Adam learning rate of the renderer's weights in test-time fitting (code and features: 1e-2)."""
    tta_gaze_weight: float = field(default=0.0002, metadata=at_least(0, "a weight"))
    """weight of the fit's gaze term, >= 0 (0: none), in degrees like ``gaussian.lambda_gaze``: the frozen *loss*
    estimator, never the evaluation one, reads renders of the fitted input (``train.evaluation.fitting.FitGaze``;
    docs/results.md, 2026-11-23)."""
    tta_gaze_every: int = field(default=2, metadata=at_least(1, "a step count"))
    """the gaze term enters every this-many fitting steps, the last one included (its ``target`` render doubles
    a step's cost); every 2nd step at twice the weight matched every step (docs/results.md, 2026-11-23)."""
    tta_gaze_terms: tuple[Literal["target", "own"], ...] = ("target",)
    """what the gaze term reads, at least one when ``tta_gaze_weight`` > 0: ``target``, one more render per step
    at the input's view turned to the pair's target gaze, against that gaze; ``own``, the fitting render,
    against the estimator's reading of the input image."""
    tta_gaze_reach: tuple[Literal["code", FittedWeight], ...] = ()
    """what the gaze term's gradient may change: ``code`` and some of ``tta_weights``; (): all that is fitted.
    With colours or the renderer in reach it paints specks that read as the target gaze; ``[code, eye_field]``
    only turns the eyes (:data:`NATURAL_EYES_FIT`; docs/results.md, 2026-11-23)."""
    estimator_path: str = field(default="", metadata=NEUTRAL)
    """GazeNeRF's published ETH-XGaze ResNet-50 gaze estimator checkpoint (``epoch_7_resnet_correct_ckpt.pth.tar``,
    read with ``weights_only=True``), scoring the gaze and head-pose errors instead of the run's evaluation
    estimator so that they compare with the peers' (``train.estimator.peer``, docs/model.md); empty: the run's."""
    pairing_file: str = ""
    """a pairing file (``train.data.pairing.load_pairing``): GazeNeRF's target list read verbatim (one integer a
    line: input row i -> target row list[i] for every subject), JSON ``{"subject0008": [[input_row, target_row],
    ...]}`` (``"*"``: every subject not named) or lines ``subject0008 input_row target_row``; empty: generated
    pairs (the first half of a subject's rows with a fixed permutation of the second half). Files without
    ``subject_params`` (real data) are scored against their stored target rows (docs/evaluation.md)."""
    data_root: str = field(default="", metadata=NEUTRAL)
    """a folder of another dataset's subject files to evaluate on (cross-dataset evaluation, the paper's
    Table 2): its held-out subjects (``data_split_file``, or a split file beside them), else all of them;
    empty: the run's own held-out subjects."""
    data_layout: Literal["auto", "ditgaze", "gazegaussian", "gazenerf", "xgaze"] = field(default="auto",
                                                                                        metadata=NEUTRAL)
    """the layout of ``data_root``'s files, as ``data.layout``."""
    data_split_file: str = field(default="", metadata=NEUTRAL)
    """the split of ``data_root``'s subjects, as ``data.split_file``; empty: the one beside them, else all."""
    sweep_frames: int = field(default=9, metadata=COUNT)
    """gazes in the qualitative figure's sweep row."""
    sampling_steps: int = field(default=0, metadata=NEUTRAL | rule(
        lambda n: n >= 0, "0 (gaussian.sampling_steps) or a DDIM step count >= 1"))
    """DDIM steps of the evaluation's renders, at most the diffusion's timesteps; 0: ``gaussian.sampling_steps``.
    Changing it re-runs the eval stage alone."""
    lpips_vgg_path: str = field(default="", metadata=NEUTRAL)
    """LPIPS (VGG): a local torchvision-layout VGG16 state dict (.pth read with weights_only, or .safetensors);
    with ``lpips_lin_path`` the eval stage scores LPIPS, else reports it as n/a (``train.losses.lpips``)."""
    lpips_lin_path: str = field(default="", metadata=NEUTRAL)
    """LPIPS (VGG): the ``lpips`` package's linear-layer weights (``weights/v0.1/vgg.pth``)."""
    identity_model_path: str = field(default="", metadata=NEUTRAL)
    """identity similarity: a local insightface ArcFace backbone (``backbone.pth``, read with weights_only, or
    .safetensors); the eval stage then scores the cosine similarity of render and target embeddings, else n/a
    (``train.losses.identity``)."""
    identity_arch: Literal["iresnet18", "iresnet34", "iresnet50", "iresnet100"] = field(default="iresnet50",
                                                                                        metadata=NEUTRAL)
    """the ArcFace backbone's architecture (its file's block counts must match)."""
    natural_fit_row: bool = field(default=True, metadata=NEUTRAL)
    """when the test-time fit has a gaze term (``tta_gaze_weight`` > 0 and ``tta_steps`` > 0), also evaluate the
    same pairs after the natural fit, without any gaze term (same steps and weights), and report its gaze error,
    PSNR and SSIM beside the main row (``metrics.natural_fit``): the fit the toolkit produces data with. A second
    fitting pass (the demo's eval stage: 1.2x its CPU time, docs/results.md 2026-11-27); false skips it. No
    effect without a gaze term."""


def eval_sampling_steps(cfg: "RunConfig") -> int:
    """The DDIM steps the evaluation (and the demo's sweep) renders with."""
    return cfg.eval.sampling_steps or cfg.gaussian.sampling_steps


@dataclass
class RunConfig:
    preset: str = "demo"
    """the preset the config started from (named in the report)."""
    seed: int = field(default=0, metadata=SEED)
    """seed of every stage's training, in [0, 2^32)."""
    device: str = field(default="auto", metadata=DEVICE)
    """"auto" (CUDA when available), "cpu", "cuda" or "cuda:N"."""
    threads: int = field(default=0, metadata=within(0, 1024, "a thread count {}"))
    """torch CPU threads, 0 to 1024 (0: torch's default)."""
    data: DataConfig = field(default_factory=DataConfig)
    geometry: GeometryStageConfig = field(default_factory=GeometryStageConfig)
    codec: CodecStageConfig = field(default_factory=CodecStageConfig)
    estimator: EstimatorStageConfig = field(default_factory=EstimatorStageConfig)
    gaussian: GaussianStageConfig = field(default_factory=GaussianStageConfig)
    eval: EvalConfig = field(default_factory=EvalConfig)


__all__ = ["RunConfig", "eval_sampling_steps", "replace"]
