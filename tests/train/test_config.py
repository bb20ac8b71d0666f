from dataclasses import dataclass, field
from typing import Literal, Optional

import pytest

from toolkit import ToolkitError
from train.config import (
    NEUTRAL,
    apply_overrides,
    at_least,
    config_hash,
    from_dict,
    load_yaml_config,
    rule,
    save_yaml_config,
    to_dict,
    within,
)


@dataclass
class Inner:
    lr: float = 1e-3
    steps: int = 10
    mode: Literal["dit", "unet"] = "dit"


@dataclass
class Outer:
    name: str = "x"
    inner: Inner = field(default_factory=Inner)
    sizes: tuple[int, int] = (1, 2)
    path: Optional[str] = None
    flag: bool = False


def test_yaml_round_trip(tmp_path):
    cfg = apply_overrides(Outer(), ["inner.lr=0.5", "sizes=[3, 4]", "path=/x", "flag=true", "inner.mode=unet"])
    assert cfg.inner.lr == 0.5 and cfg.sizes == (3, 4) and cfg.flag is True and cfg.inner.mode == "unet"
    save_yaml_config(cfg, tmp_path / "c.yaml")
    assert load_yaml_config(Outer, tmp_path / "c.yaml") == cfg
    assert config_hash(cfg) == config_hash(load_yaml_config(Outer, tmp_path / "c.yaml"))
    assert config_hash(cfg) != config_hash(Outer())
    assert to_dict(cfg)["inner"]["steps"] == 10


def test_exponent_without_a_dot_is_a_float(tmp_path):
    """PyYAML follows YAML 1.1, where 4e-3 (no dot) is a string; float fields accept it anyway."""
    assert apply_overrides(Outer(), ["inner.lr=4e-3"]).inner.lr == 0.004
    assert apply_overrides(Outer(), ["inner.lr=-1E+2"]).inner.lr == -100.0
    (tmp_path / "c.yaml").write_text("inner:\n  lr: 1e-3\n")
    assert load_yaml_config(Outer, tmp_path / "c.yaml").inner.lr == 0.001
    for bad in ("4e-3x", "e-3", "4e"):
        with pytest.raises(ToolkitError, match="'inner.lr': expected a number"):
            apply_overrides(Outer(), [f"inner.lr={bad}"])
    with pytest.raises(ToolkitError, match="expected an integer"):  # ints stay strict
        apply_overrides(Outer(), ["inner.steps=1e3"])


@pytest.mark.parametrize(
    "override,msg",
    [
        ("inner.lrr=1", "unknown config key 'inner.lrr'; did you mean 'lr'"),
        ("nope=1", "unknown config key 'nope'"),
        ("inner.steps=1.5", "'inner.steps': expected an integer"),
        ("inner.steps=abc", "'inner.steps': expected an integer"),
        ("inner.mode=gan", r"'inner.mode': expected one of \['dit', 'unet'\]"),
        ("flag=3", "'flag': expected true/false"),
        ("sizes=[1]", "'sizes': expected 2 values"),
        ("name.x=1", "'name' is not a section"),
        ("justakey", "expected KEY=VALUE"),
        ("inner.steps=010", r"'010' would read as a base-8 or base-60 number \(8\)"),
        ("inner.steps=1:30", r"'1:30' would read as a base-8 or base-60 number \(90\)"),
        ("inner.lr=1:30.5", r"'1:30.5' would read as a base-8 or base-60 number"),
    ],
)
def test_bad_overrides_name_the_key(override, msg):
    with pytest.raises(ToolkitError, match=msg):
        apply_overrides(Outer(), [override])


def test_bad_yaml_files(tmp_path):
    p = tmp_path / "c.yaml"
    p.write_text("inner:\n  lr: [unclosed\n")
    with pytest.raises(ToolkitError, match="not valid YAML"):
        load_yaml_config(Outer, p)
    p.write_text("inner:\n  stepz: 3\n")
    with pytest.raises(ToolkitError, match="c.yaml: unknown config key 'inner.stepz'"):
        load_yaml_config(Outer, p)
    p.write_text("- a\n- b\n")
    with pytest.raises(ToolkitError, match="mapping"):
        load_yaml_config(Outer, p)
    with pytest.raises(ToolkitError, match="expected a mapping"):
        from_dict(Outer, {"inner": 3})


def test_neutral_fields_at_their_defaults_leave_the_hash_unchanged():
    """An option added later with a behaviour-preserving default (metadata NEUTRAL) does not make the stages of
    older runs stale; set to anything else it counts like any field."""
    from train.config import NEUTRAL

    @dataclass
    class Before:
        steps: int = 3
        names: tuple[str, ...] = ("a",)

    @dataclass
    class After:
        steps: int = 3
        names: tuple[str, ...] = ("a",)
        schedule: str = field(default="constant", metadata=NEUTRAL)

    @dataclass
    class Outer:
        inner: After = field(default_factory=After)

    assert config_hash(After()) == config_hash(Before())
    assert config_hash(After(schedule="cosine")) != config_hash(Before())
    assert config_hash(After(steps=4)) == config_hash(Before(steps=4)) != config_hash(Before())
    assert config_hash(Outer()) == config_hash({"inner": to_dict(Before())})  # nested sections too
    assert "schedule" in to_dict(After())  # the YAML still shows it


def test_neutral_fields_with_a_default_factory():
    from train.config import NEUTRAL

    @dataclass
    class Before:
        steps: int = 3

    @dataclass
    class After:
        steps: int = 3
        extra: list = field(default_factory=list, metadata=NEUTRAL)

    assert config_hash(After()) == config_hash(Before())
    assert config_hash(After(extra=[1])) != config_hash(Before())


def test_the_options_added_to_the_gaussian_stage_are_neutral_at_their_defaults():
    from train.run_config import GaussianStageConfig

    base = to_dict(GaussianStageConfig())
    older = {k: v for k, v in base.items() if k not in ("lr_schedule", "lr_final", "dit_feature_hidden",
                                                         "eyeball_colours", "ema_decay", "lr_decay_steps",
                                                         "vgg_path", "lambda_perceptual", "field_input",
                                                         "eye_field_terms", "region_renders")}
    assert config_hash(GaussianStageConfig()) == config_hash(older)
    assert config_hash(GaussianStageConfig(vgg_path="v.pth")) != config_hash(older)
    assert config_hash(GaussianStageConfig(lr_schedule="step", lr_decay_steps=10)) != config_hash(older)
    assert config_hash(GaussianStageConfig(lr_schedule="cosine")) != config_hash(older)
    assert config_hash(GaussianStageConfig(dit_feature_hidden=16)) != config_hash(older)
    assert config_hash(GaussianStageConfig(eyeball_colours=True)) != config_hash(older)
    assert config_hash(GaussianStageConfig(ema_decay=0.5)) != config_hash(older)
    assert config_hash(GaussianStageConfig(field_input="feature")) != config_hash(older)
    assert config_hash(GaussianStageConfig(eye_field_terms=True)) != config_hash(older)
    assert config_hash(GaussianStageConfig(region_renders="separate")) != config_hash(older)


def test_the_field_pretraining_is_neutral_off_and_ties_the_geometry_stage_to_the_model_when_on():
    """geometry.pretrain_fields=0 leaves the geometry stage's fingerprint as before; on, the stage also hashes the
    two-stream model's config (the pre-trained fields' architecture), and only then."""
    from train.presets import preset
    from train.run_config import GeometryStageConfig

    older = {k: v for k, v in to_dict(GeometryStageConfig()).items() if k not in ("pretrain_fields", "lid_gaussians")}
    assert config_hash(GeometryStageConfig()) == config_hash(older)
    prints = lambda *o: _stage_fingerprints(apply_overrides(preset("tiny"), list(o)))["geometry"]  # noqa: E731
    off, on = prints(), prints("geometry.pretrain_fields=5")
    assert on != off
    assert prints("gaussian.gaussians_hidden=8") == off  # off: the Gaussian stage's fields are not the geometry's
    assert prints("geometry.pretrain_fields=5", "gaussian.gaussians_hidden=8") != on
    assert prints("geometry.pretrain_fields=5", "gaussian.lr=0.01") == on  # the training's settings are not


def test_the_options_added_to_the_eval_stage_are_neutral_at_their_defaults():
    from train.run_config import EvalConfig

    added = ("sampling_steps", "lpips_vgg_path", "lpips_lin_path", "identity_model_path", "identity_arch",
             "estimator_path", "data_root", "data_layout", "data_split_file", "natural_fit_row")
    older = {k: v for k, v in to_dict(EvalConfig()).items() if k not in added}
    assert config_hash(EvalConfig()) == config_hash(older)
    assert config_hash(EvalConfig(sampling_steps=4)) != config_hash(older)
    assert config_hash(EvalConfig(lpips_vgg_path="a", lpips_lin_path="b")) != config_hash(older)
    assert config_hash(EvalConfig(identity_model_path="c")) != config_hash(older)
    assert config_hash(EvalConfig(estimator_path="d")) != config_hash(older)
    assert config_hash(EvalConfig(data_root="e")) != config_hash(older)
    assert config_hash(EvalConfig(natural_fit_row=False)) != config_hash(older)


def test_the_data_layout_and_split_file_are_neutral_at_their_defaults():
    from train.run_config import DataConfig

    older = {k: v for k, v in to_dict(DataConfig()).items() if k not in ("layout", "split_file", "kappa_deg")}
    assert config_hash(DataConfig()) == config_hash(older)
    assert config_hash(DataConfig(layout="gazegaussian")) != config_hash(older)
    assert config_hash(DataConfig(split_file="s.json")) != config_hash(older)
    assert config_hash(DataConfig(kappa_deg=5.0)) != config_hash(older)


def test_a_section_given_as_a_mapping_keeps_its_other_values():
    """``inner={steps: 5}`` changes steps alone: the section's other values stay those of the config it
    overrides (a preset's, say), not the dataclass defaults. Leading zeros that YAML 1.1 reads as decimal pass."""
    base = apply_overrides(Outer(), ["inner.lr=0.5", "inner.mode=unet"])
    cfg = apply_overrides(base, ["inner={steps: 5}"])
    assert (cfg.inner.lr, cfg.inner.steps, cfg.inner.mode) == (0.5, 5, "unet")
    assert apply_overrides(Outer(), ["inner.steps=07"]).inner.steps == 7


# ----------------------------------------------------------------------------- declared field rules
@dataclass
class Ruled:
    steps: int = field(default=3, metadata=at_least(1, "a count"))
    lr: float = field(default=0.1, metadata=within(0, 1, "a learning rate", low_open=True))
    share: float = field(default=0.5, metadata=within(0, 1, "a share {} of the batch", high_open=True))
    pool: int = field(default=2000, metadata=at_least(1, "a count") | rule(lambda n: n >= 1000, ">= 1000 points"))
    frames: int = field(default=2, metadata=NEUTRAL | rule(lambda n: n % 2 == 0, "an even count"))


@dataclass
class RuledOuter:
    inner: Ruled = field(default_factory=Ruled)


@pytest.mark.parametrize(
    "override,msg",
    [
        ("inner.steps=0", r"config key 'inner.steps': expected a count >= 1, got 0$"),
        ("inner.lr=0", r"config key 'inner.lr': expected a learning rate in \(0, 1\], got 0.0$"),
        ("inner.lr=1.5", r"config key 'inner.lr': expected a learning rate in \(0, 1\], got 1.5$"),
        ("inner.share=1", r"config key 'inner.share': expected a share in \[0, 1\) of the batch, got 1.0$"),
        ("inner.pool=0", r"config key 'inner.pool': expected a count >= 1, got 0$"),  # the rules in order
        ("inner.pool=999", r"config key 'inner.pool': expected >= 1000 points, got 999$"),
        ("inner.frames=3", r"config key 'inner.frames': expected an even count, got 3$"),
        ("inner.lr=.nan", r"config key 'inner.lr': expected a finite number, got nan"),
        ("inner.steps=true", r"config key 'inner.steps': expected an integer, got True"),
        ("inner.lr=false", r"config key 'inner.lr': expected a number, got False"),
    ],
)
def test_declared_rules_fail_at_override_and_load_time(tmp_path, override, msg):
    with pytest.raises(ToolkitError, match=msg):
        apply_overrides(RuledOuter(), [override])
    key, value = override.split("=")
    (tmp_path / "c.yaml").write_text(f"inner:\n  {key.split('.')[1]}: {value}\n")
    with pytest.raises(ToolkitError, match="c.yaml: " + msg):
        load_yaml_config(RuledOuter, tmp_path / "c.yaml")


def test_check_fields_refuses_what_python_code_set():
    """A config built or changed in Python (a preset, a test) is checked the same way: types included."""
    from train.config import check_fields

    cfg = RuledOuter()
    assert check_fields(cfg) is cfg
    for name, bad, msg in [("lr", float("nan"), "expected a finite number"), ("steps", True, "expected an integer"),
                           ("steps", 2.0, "expected an integer"), ("lr", "0.1", "expected a number"),
                           ("frames", 5, "expected an even count")]:
        cfg = RuledOuter()
        setattr(cfg.inner, name, bad)
        with pytest.raises(ToolkitError, match=f"config key 'inner.{name}': {msg}"):
            check_fields(cfg)


def test_rules_keep_neutral_and_the_hash():
    """Rules are metadata beside NEUTRAL: a neutral field with a rule still leaves the hash at its default."""
    @dataclass
    class Before:
        steps: int = 3

    @dataclass
    class After:
        steps: int = field(default=3, metadata=at_least(1, "a count"))
        frames: int = field(default=2, metadata=NEUTRAL | rule(lambda n: n % 2 == 0, "an even count"))

    assert config_hash(After()) == config_hash(Before())
    assert config_hash(After(frames=4)) != config_hash(Before())


def test_every_run_config_field_rule_reads_its_own_default():
    """Every preset passes its field rules (a rule that refused a default would make every run fail)."""
    from train.config import check_fields
    from train.presets import PRESETS
    from train.run_config import RunConfig

    check_fields(RunConfig())
    for make in PRESETS.values():
        check_fields(make())


# ----------------------------------------------------------------------------- component configs
def _component_classes():
    from geometry.fit import FitConfig
    from geometry.init_gaussians import InitConfig
    from train.estimator.config import GazeEstimatorConfig, GazeEstimatorTrainConfig
    from train.losses import ImageLossConfig
    from train.model.codec import AutoencoderConfig
    from train.model.gaussian_config import GaussianModelConfig
    from train.training.gaze_sampler import GazeSamplerConfig

    return {c.__name__: c for c in (FitConfig, InitConfig, GazeEstimatorConfig, GazeEstimatorTrainConfig,
                                    ImageLossConfig, AutoencoderConfig, GaussianModelConfig, GazeSamplerConfig)}


def test_every_mapped_stage_field_names_a_field_of_its_component():
    import dataclasses

    from train.run_config import RunConfig

    classes, mapped = _component_classes(), set()
    sections = [getattr(RunConfig(), f.name) for f in dataclasses.fields(RunConfig)]
    for section in filter(dataclasses.is_dataclass, sections):
        for f in dataclasses.fields(section):
            if "maps_to" in f.metadata:
                cls, name = f.metadata["maps_to"]
                assert name in {c.name for c in dataclasses.fields(classes[cls])}, (type(section).__name__, f.name)
                mapped.add((cls, name))
    assert len(mapped) == 24 and set(classes) == {cls for cls, _ in mapped}


def test_component_configs_take_the_stage_values():
    from train.config import component
    from train.run_config import EstimatorStageConfig, GaussianStageConfig, GeometryStageConfig
    from train.training.trainer import model_config

    classes = _component_classes()
    g = GeometryStageConfig(steps=7, pool=5000, gaussians=900, eye_gaussians=8, lid_gaussians=10)
    fit = component(classes["FitConfig"], g, seed=3)
    assert (fit.steps, fit.pool, fit.extract_res, fit.pretrain_steps, fit.seed) == (7, 5000, 64, 100, 3)
    assert fit.batch == classes["FitConfig"]().batch  # what no stage field sets keeps the component's default
    init = component(classes["InitConfig"], g, seed=3)
    assert (init.n_points, init.eye_points, init.lid_points, init.seed) == (900, 8, 10, 3)
    e = EstimatorStageConfig(steps=5, batch=4, blur_prob=0.25, blur_sigma=0.5, mirror_average=False, warmup_steps=2)
    tc = component(classes["GazeEstimatorTrainConfig"], e, seed=1, log_every=5)
    assert (tc.steps, tc.batch_size, tc.blur_prob, tc.blur_sigma, tc.warmup_steps, tc.seed) == (5, 4, 0.25, 0.5, 2, 1)
    design = classes["GazeEstimatorConfig"](input_size=48)
    assert component(design, e) == classes["GazeEstimatorConfig"](input_size=48, mirror_average=False)
    m = model_config(GaussianStageConfig(gaussians_hidden=8, eyes_follow_face=False, eyeball_colours=True,
                                         feature_upscale=2))
    assert (m.hidden, m.eyes_follow_face, m.eye_appearance, m.eyeball_colours, m.render_scale) == (8, False, False,
                                                                                                    True, 0.5)
    with pytest.raises(TypeError):  # the stage sets a mapped field twice: refused, not silently overwritten
        component(classes["FitConfig"], g, steps=1)


def test_a_component_rule_is_named_by_the_config_key():
    from train.config import check_component
    from train.run_config import GaussianStageConfig

    GazeSamplerConfig = _component_classes()["GazeSamplerConfig"]
    check_component(GazeSamplerConfig, GaussianStageConfig(), "gaussian.")
    with pytest.raises(ToolkitError, match=r"^config key 'gaussian.sampler_range_deg': expected \(0, 89\] degrees, "
                                           r"got 95.0$"):
        check_component(GazeSamplerConfig, GaussianStageConfig(sampler_range_deg=95.0), "gaussian.")


# ----------------------------------------------------------------------------- run directories made before
OLD_TINY_CONFIG = """\
preset: tiny
seed: 0
device: auto
threads: 0
data:
  root: ''
  subjects: 2
  frames: 1
  test_frames: 2
  res: 64
  test_fraction: 0.5
  seed: 0
  light_jitter: 0.0
geometry:
  steps: 20
  extract_res: 24
  pretrain_steps: 50
  pool: 20000
  gaussians: 800
  eye_gaussians: 400
  lid_gaussians: 0
  subject: 0
codec:
  kind: ae
  sd_vae_path: ''
  steps: 4
  base_channels: 8
  downsample: 4
  batch: 4
  eye_weight: 100.0
estimator:
  loss_path: ''
  eval_path: ''
  steps: 4
  input_size: 32
  batch: 8
  crop: eyes
  synthetic_subjects: 1
  synthetic_frames: 2
  cameras_per_frame: 2
  mirror_average: true
  blur_prob: 0.5
  blur_sigma: 1.2
gaussian:
  renderer: dit
  dit_model: DiT-Gaze-tiny
  dit_feature_hidden: 64
  residual: true
  sampling_steps: 1
  onestep_fraction: 0.5
  rgb_init: true
  orthogonality: true
  ortho_weight: 0.01
  weak_supervision: true
  weak_weight: 0.5
  sampler_mode: mixed
  sampler_range_deg: 35.0
  steps: 4
  batch: 2
  lr: 0.002
  means_lr: 0.00016
  renderer_lr: 0.0005
  lr_schedule: constant
  lr_final: 0.1
  ema_decay: 0.0
  lambda_rgb: 1.0
  lambda_gaze: 0.002
  lambda_ssim: 0.8
  diffusion_weight: 1.0
  gaussians_hidden: 16
  feature_upscale: 1
  eyes_follow_face: true
  eye_appearance: false
  eyeball_colours: false
  ckpt_every: 2
  log_every: 2
  grad_clip: 1.0
eval:
  pairs_per_subject: 2
  tta_steps: 2
  tta_weights:
  - features
  - renderer
  tta_region: head
  tta_renderer_lr: 0.001
  tta_gaze_weight: 0.0002
  tta_gaze_every: 2
  tta_gaze_terms:
  - target
  tta_gaze_reach: []
  pairing_file: ''
  sweep_frames: 3
  sampling_steps: 0
  lpips_vgg_path: ''
  lpips_lin_path: ''
  identity_model_path: ''
  identity_arch: iresnet50
"""
"""The ``config.yaml`` the tiny preset's run wrote before the fields declared their rules and mappings."""


def test_a_config_yaml_written_before_loads_and_round_trips(tmp_path):
    from train.presets import preset
    from train.run_config import RunConfig

    (tmp_path / "old.yaml").write_text(OLD_TINY_CONFIG)
    cfg = load_yaml_config(RunConfig, tmp_path / "old.yaml")
    assert cfg == preset("tiny")
    save_yaml_config(cfg, tmp_path / "new.yaml")
    # The same file, key for key, plus the keys added since (at their neutral defaults).
    added = "  estimator_path: ''\n"
    data_added = "  kappa_deg: 0.0\n  layout: auto\n  split_file: ''\n"
    expected = OLD_TINY_CONFIG.replace("  pairing_file: ''\n", added + "  pairing_file: ''\n")
    expected = expected.replace("  light_jitter: 0.0\n", "  light_jitter: 0.0\n" + data_added)
    expected = expected.replace("  lr_final: 0.1\n", "  lr_decay_steps: 1000\n  lr_final: 0.1\n")
    expected = expected.replace("  ema_decay: 0.0\n", "  vgg_path: ''\n  lambda_perceptual: 0.1\n  ema_decay: 0.0\n")
    expected = expected.replace("  sweep_frames: 3\n",
                                "  data_root: ''\n  data_layout: auto\n  data_split_file: ''\n  sweep_frames: 3\n")
    expected = expected.replace("  eyeball_colours: false\n",
                                "  eyeball_colours: false\n  region_renders: masks\n  field_input: position\n"
                                "  eye_field_terms: false\n")
    expected = expected.replace("  subject: 0\n", "  subject: 0\n  pretrain_fields: 0\n")
    expected = expected.replace("  blur_sigma: 1.2\n", "  blur_sigma: 1.2\n  warmup_steps: 0\n")
    expected = expected.replace("  identity_arch: iresnet50\n", "  identity_arch: iresnet50\n  natural_fit_row: true\n")
    assert (tmp_path / "new.yaml").read_text() == expected
    assert load_yaml_config(RunConfig, tmp_path / "new.yaml") == cfg


MAPPED_OVERRIDES = [
    "geometry.steps=7", "geometry.extract_res=16", "geometry.pretrain_steps=3", "geometry.pool=5000",
    "geometry.gaussians=900", "geometry.eye_gaussians=8", "geometry.lid_gaussians=10", "codec.downsample=2",
    "codec.base_channels=4", "estimator.steps=5", "estimator.batch=4", "estimator.input_size=48",
    "estimator.mirror_average=false", "estimator.blur_prob=0.25", "estimator.blur_sigma=0.5",
    "gaussian.gaussians_hidden=8", "gaussian.eyes_follow_face=false", "gaussian.eyeball_colours=true",
    "gaussian.lambda_ssim=0.3", "gaussian.sampler_mode=uniform", "gaussian.sampler_range_deg=20",
    "gaussian.dit_feature_hidden=16", "gaussian.residual=false", "gaussian.feature_upscale=2",
    "eval.tta_gaze_weight=0.001", "eval.tta_gaze_terms=[target,own]", "eval.tta_gaze_every=3",
    "eval.tta_gaze_reach=[code]"]
"""``section.field=value`` overrides of the stage fields that set component configs, as users wrote them."""


def _stage_fingerprints(cfg) -> dict[str, str]:
    from train.run import STAGES
    from train.stages.pipeline import fingerprint

    prints: dict[str, str] = {}
    for stage in STAGES:
        prints[stage.name] = fingerprint(stage, cfg, prints)
    return prints


def test_stage_fingerprints_are_those_of_runs_made_before():
    """A run directory made before stays up to date: the fingerprints below were computed by the code before the
    fields declared their rules and component mappings, for the presets and for every mapped field changed."""
    from train.presets import preset

    assert _stage_fingerprints(preset("tiny")) == {
        "data": "db21dac3ae9cd246", "geometry": "4991e636ad3a1e1c", "codec": "de494783a5e00c84",
        "estimator": "1efdf414b7e892c8", "gaussian": "9e5483ce107fb81b", "eval": "df17b24c0793fc01"}
    # the demo and paper presets warm their estimators up since 2026-11-27 (estimator.warmup_steps=100): their
    # estimator stages are other trainings, so the estimator fingerprints (and the Gaussian's and eval's after
    # them) differ from the runs made before, while data, geometry and codec stay; a run directory keeps its own
    # config.yaml, where the key is absent (0), so an old run stays up to date
    assert _stage_fingerprints(preset("demo")) == {
        "data": "1a5f68e91e56f7db", "geometry": "5cda16a313497540", "codec": "60547948bf352234",
        "estimator": "40d8c02c7ff13afa", "gaussian": "d7d7bd9d6cb2a769", "eval": "a9d2c29b6a37924c"}
    old_demo = preset("demo")
    old_demo.estimator.warmup_steps = 0
    assert _stage_fingerprints(old_demo) == {
        "data": "1a5f68e91e56f7db", "geometry": "5cda16a313497540", "codec": "60547948bf352234",
        "estimator": "10736ce72ae20e23", "gaussian": "08a7a333e21d3520", "eval": "aeb8274f425f85e3"}
    # the paper preset's optimizer is the paper's since 2026-11-27 (Adam 1e-4, step decay), and so are its fields'
    # inputs and eye terms (gaussian.field_input, gaussian.eye_field_terms), its region renders and its fields'
    # pre-training in the geometry stage (gaussian.region_renders, geometry.pretrain_fields): its geometry and
    # Gaussian stages are other trainings, so their fingerprints (and the eval's) differ from the runs made
    # before; a run directory keeps its own config.yaml, so an old paper run stays up to date
    assert _stage_fingerprints(preset("paper")) == {
        "data": "af896099bae7e529", "geometry": "015b52b8cb71a1e4", "codec": "4dcd3c5e93298486",
        "estimator": "7be0b24e7a57c564", "gaussian": "b9412b22fc36a710", "eval": "12ea30944fb376f8"}
    assert _stage_fingerprints(apply_overrides(preset("tiny"), MAPPED_OVERRIDES)) == {
        "data": "db21dac3ae9cd246", "geometry": "dc13af8ddc940534", "codec": "1acc1d10a8090196",
        "estimator": "4dd48a805590f945", "gaussian": "034c8f6fda0a7a88", "eval": "8add558ad7e302fb"}
