"""Bad input to ``python -m train.run``: config files, overrides, the environment torchrun sets, a run directory's
own ``config.yaml`` on resume, a pairing file. Each is refused in one line before any work, the run folder untouched."""

from __future__ import annotations

import pytest

from tests.fuzz.cli import assert_refused

BILLION_LAUGHS = "a: &a [x, x, x, x, x, x, x, x, x]\n" + "".join(
    f"{chr(98 + i)}: &{chr(98 + i)} [{', '.join(['*' + chr(97 + i)] * 9)}]\n" for i in range(8)) + "seed: *i\n"

# (id, overrides, error regex): each refused by the config check, before the run directory is made.
OVERRIDES = [
    ("seed-2^64", ["seed=18446744073709551616"], r"'seed': expected a seed below 2\^32"),
    ("seed-negative", ["seed=-1"], r"'seed': expected a seed >= 0"),
    ("data-seed-2^32", ["data.seed=4294967296"], r"'data.seed': expected a seed below 2\^32"),
    ("threads-1e20", ["threads=1e20"], r"'threads': expected an integer"),
    ("threads-huge", ["threads=100000"], r"'threads': expected a thread count in \[0, 1024\]"),
    ("gaussians-1e9", ["geometry.gaussians=1000000000"], r"geometry.gaussians.*would allocate .* GiB"),
    ("pool-1e11", ["geometry.pool=100000000000"], r"geometry.pool.*would allocate"),
    ("gaussian-batch-1e6", ["gaussian.batch=1000000"], r"gaussian.batch.*would allocate"),
    ("codec-batch-1e7", ["codec.batch=10000000"], r"codec.batch.*would allocate"),
    ("estimator-batch", ["estimator.batch=1000000000"], r"estimator.batch.*would allocate"),
    ("frames-1e9", ["data.frames=1000000000"], r"data.frames.*would allocate"),
    ("steps-1e11", ["gaussian.steps=100000000000"], r"'gaussian.steps': expected at most 10000000 steps"),
    ("geometry-steps", ["geometry.steps=99999999999"], r"'geometry.steps': expected at most"),
    ("tta-steps", ["eval.tta_steps=1000000000"], r"'eval.tta_steps': expected at most"),
    ("nan-lr", ["gaussian.lr=.nan"], r"'gaussian.lr': expected a finite number"),
    ("inf-weight", ["gaussian.ortho_weight=.inf"], r"'gaussian.ortho_weight': expected a finite number"),
    ("lr-above-1", ["gaussian.lr=5"], r"'gaussian.lr': expected a learning rate in \(0, 1\]"),
    ("unknown-key", ["gaussian.stpes=3"], r"unknown config key 'gaussian.stpes'; did you mean 'steps'"),
    ("not-a-section", ["seed.x=1"], r"'seed' is not a section"),
    ("no-equals", ["gaussian.steps"], r"expected KEY=VALUE"),
    ("yaml-alias", ["gaussian.steps=*a"], r"override .*aliases .* are not accepted"),
    ("octal-seed", ["seed=010"], r"base-8"),
    ("bool-count", ["gaussian.steps=true"], r"'gaussian.steps': expected an integer"),
    ("string-count", ["data.frames=four"], r"'data.frames': expected an integer"),
    ("res-range", ["data.res=100000"], r"'data.res': expected an image size"),
    ("missing-pairing", ["eval.pairing_file=/nonexistent/pairs.txt"], r"eval.pairing_file"),
    ("missing-estimator", ["estimator.eval_path=/nonexistent/e.safetensors"], r"estimator.eval_path.*no such file"),
    ("device", ["device=tpu"], r"'device': expected auto, cpu, cuda or cuda:N"),
]


@pytest.mark.parametrize("argv, match", [pytest.param(a, m, id=i) for i, a, m in OVERRIDES])
def test_bad_overrides_are_refused_before_any_work(tmp_path, argv, match):
    assert_refused("train.run", ["--preset", "tiny", "--run-dir", tmp_path / "run", *argv], match, out_dir=tmp_path)


CONFIG_FILES = [
    ("non-string-key", "1: x\n", r"bad.yaml.*key must be a string"),
    ("yes-key", "yes: x\n", r"key must be a string"),
    ("alias-bomb", BILLION_LAUGHS, r"aliases"),
    ("deep", "[" * 100_000 + "]" * 100_000, r"deeper than"),
    ("5000-digits", "seed: " + "9" * 5000 + "\n", r"more than 30 digits"),
    ("base-60", "seed: 1:30\n", r"base-8 or base-60"),
    ("list-top", "- 1\n- 2\n", r"expected a mapping at the top level"),
    ("unknown-section", "gausian:\n  steps: 3\n", r"unknown config key 'gausian'"),
    ("section-not-mapping", "gaussian: 3\n", r"'gaussian': expected a mapping"),
]


@pytest.mark.parametrize("text, match", [pytest.param(t, m, id=i) for i, t, m in CONFIG_FILES])
def test_bad_config_files_are_refused(tmp_path, text, match):
    cfg = tmp_path / "bad.yaml"
    cfg.write_text(text)
    assert_refused("train.run", ["--config", cfg, "--run-dir", tmp_path / "run"], match, inputs=[cfg],
                   out_dir=tmp_path)


def test_binary_and_latin1_config_files_are_refused(tmp_path):
    for name, data, match in (("bin.yaml", bytes(range(256)), r"bin.yaml"),
                              ("latin.yaml", "name: caf\xe9\n".encode("latin-1"), r"not UTF-8")):
        cfg = tmp_path / name
        cfg.write_bytes(data)
        assert_refused("train.run", ["--config", cfg, "--run-dir", tmp_path / "run"], match, inputs=[cfg],
                       out_dir=tmp_path)


def test_a_run_directory_with_a_bad_config_yaml_is_refused_untouched(tmp_path):
    run = tmp_path / "run"
    run.mkdir()
    (run / "config.yaml").write_text("1: x\n")
    assert_refused("train.run", ["--run-dir", run, "--resume"], r"config.yaml.*key must be a string",
                   inputs=[run], out_dir=tmp_path)


def test_a_run_directory_that_is_a_file_is_named_as_the_flag(tmp_path):
    (tmp_path / "run").write_text("notes\n")
    for run in (tmp_path / "run", tmp_path / "run" / "sub"):
        assert_refused("train.run", ["--preset", "tiny", "--run-dir", run],
                       rf"^error: --run-dir {run}: {tmp_path / 'run'} is a file, not a folder", inputs=[tmp_path / "run"],
                       out_dir=tmp_path)


@pytest.mark.parametrize("value", ["abc", "0", "-2", "1e3", "99999999999"])
def test_a_bad_torchrun_environment_is_one_line(tmp_path, monkeypatch, value):
    monkeypatch.setenv("WORLD_SIZE", value)
    assert_refused("train.run", ["--preset", "tiny", "--run-dir", tmp_path / "run"],
                   r"environment variable WORLD_SIZE: expected an integer in \[1, 65536\]", out_dir=tmp_path)


def test_a_rank_beyond_the_world_is_one_line(tmp_path, monkeypatch):
    monkeypatch.setenv("WORLD_SIZE", "2")
    monkeypatch.setenv("RANK", "5")
    from toolkit.errors import ToolkitError
    from train.training.distributed import init_distributed

    with pytest.raises(ToolkitError, match=r"environment variable RANK: expected an integer in \[0, 1\], got '5'"):
        init_distributed("cpu")


def test_the_memory_budget_follows_the_environment(tmp_path, monkeypatch):
    monkeypatch.setenv("DITGAZE_MEMORY_GB", "0.0001")  # 100 KiB: the tiny preset's own arrays no longer fit
    assert_refused("train.run", ["--preset", "tiny", "--run-dir", tmp_path / "run"], r"would allocate",
                   out_dir=tmp_path)
    monkeypatch.setenv("DITGAZE_MEMORY_GB", "lots")
    assert_refused("train.run", ["--preset", "tiny", "--run-dir", tmp_path / "run"], r"^error: DITGAZE_MEMORY_GB",
                   out_dir=tmp_path)


def _finished_looking_run(run):
    """A run directory whose config.yaml and stage records say every stage of the tiny preset finished (each
    record with no output files): what the checks before any work read, without training anything."""
    from toolkit.io import atomic_write_json
    from train.config import save_yaml_config
    from train.presets import preset
    from train.stages import STAGES
    from train.stages.pipeline import fingerprint

    cfg = preset("tiny")
    run.mkdir()
    save_yaml_config(cfg, run / "config.yaml")
    prints = {}
    for stage in STAGES:
        prints[stage.name] = fingerprint(stage, cfg, prints)
        atomic_write_json(run / "stages" / f"{stage.name}.json", {"fingerprint": prints[stage.name], "outputs": {}})


# (id, what is done to the finished run, error regex): each read only through the stages the eval stage reads.
DAMAGED_RUNS = [
    ("garbage-data-record", lambda r: (r / "stages/data.json").write_text("garbage\n"), r"data\.json: unreadable"),
    ("truncated-codec-record", lambda r: (r / "stages/codec.json").write_text("{\n"), r"codec\.json: unreadable"),
    ("no-data-record", lambda r: (r / "stages/data.json").unlink(),
     r"stage 'eval' needs stage 'data' \(through stage '\w+'\), which has not run"),
    ("no-geometry-record", lambda r: (r / "stages/geometry.json").unlink(),
     r"stage 'eval' needs stage 'geometry' \(through stage 'gaussian'\), which has not run"),
    ("qualitative-is-a-dir", lambda r: (r / "qualitative.png").mkdir(),
     r"qualitative\.png: is a directory, expected a file path to write"),
    ("report-is-a-dir", lambda r: (r / "report.md").mkdir(), r"report\.md: is a directory, expected a file path"),
]


@pytest.mark.parametrize("damage, match", [pytest.param(f, m, id=i) for i, f, m in DAMAGED_RUNS])
def test_a_refused_eval_rerun_leaves_the_run_and_its_config_as_they_were(tmp_path, damage, match):
    """The overrides must not reach config.yaml when the run is refused for what its stage records say (an
    upstream stage read only through another one too) or for an eval output it cannot write."""
    run = tmp_path / "run"
    _finished_looking_run(run)
    damage(run)
    assert_refused("train.run", ["--run-dir", run, "--stages", "eval", "eval.pairs_per_subject=1",
                                 "eval.tta_steps=0"], match, inputs=[run], out_dir=tmp_path)


def test_a_bad_record_of_a_stage_downstream_is_refused_before_the_config_is_written(tmp_path):
    """--stages data on a finished run skips data, then reads the eval stage's record: a bad one is refused
    before the overrides are written."""
    run = tmp_path / "run"
    _finished_looking_run(run)
    (run / "stages/eval.json").write_text("[]\n")
    assert_refused("train.run", ["--run-dir", run, "--stages", "data", "eval.tta_steps=0"],
                   r"eval\.json: expected a JSON object", inputs=[run], out_dir=tmp_path)
