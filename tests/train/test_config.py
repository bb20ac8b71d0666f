from dataclasses import dataclass, field
from typing import Literal, Optional

import pytest

from toolkit import ToolkitError
from train.config import apply_overrides, config_hash, from_dict, load_yaml_config, save_yaml_config, to_dict


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
                                                         "eyeball_colours", "ema_decay")}
    assert config_hash(GaussianStageConfig()) == config_hash(older)
    assert config_hash(GaussianStageConfig(lr_schedule="cosine")) != config_hash(older)
    assert config_hash(GaussianStageConfig(dit_feature_hidden=16)) != config_hash(older)
    assert config_hash(GaussianStageConfig(eyeball_colours=True)) != config_hash(older)
    assert config_hash(GaussianStageConfig(ema_decay=0.5)) != config_hash(older)


def test_the_options_added_to_the_eval_stage_are_neutral_at_their_defaults():
    from train.run_config import EvalConfig

    added = ("sampling_steps", "lpips_vgg_path", "lpips_lin_path", "identity_model_path", "identity_arch")
    older = {k: v for k, v in to_dict(EvalConfig()).items() if k not in added}
    assert config_hash(EvalConfig()) == config_hash(older)
    assert config_hash(EvalConfig(sampling_steps=4)) != config_hash(older)
    assert config_hash(EvalConfig(lpips_vgg_path="a", lpips_lin_path="b")) != config_hash(older)
    assert config_hash(EvalConfig(identity_model_path="c")) != config_hash(older)


def test_a_section_given_as_a_mapping_keeps_its_other_values():
    """``inner={steps: 5}`` changes steps alone: the section's other values stay those of the config it
    overrides (a preset's, say), not the dataclass defaults. Leading zeros that YAML 1.1 reads as decimal pass."""
    base = apply_overrides(Outer(), ["inner.lr=0.5", "inner.mode=unet"])
    cfg = apply_overrides(base, ["inner={steps: 5}"])
    assert (cfg.inner.lr, cfg.inner.steps, cfg.inner.mode) == (0.5, 5, "unet")
    assert apply_overrides(Outer(), ["inner.steps=07"]).inner.steps == 7
