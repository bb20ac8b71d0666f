"""apps/demo.py helpers that run without training."""

import numpy as np
import pytest

from apps.demo import most_frontal
from toolkit.errors import ToolkitError


def test_most_frontal_picks_the_smallest_head_rotation():
    poses = [np.array([0.9, -0.1]), np.array([-0.05, 0.1]), np.array([0.0, -0.6]), np.array([0.2, 0.2])]
    assert most_frontal(poses) == 1
    with pytest.raises(ToolkitError, match="no rows"):
        most_frontal([])


def test_pipeline_outputs_fit_the_held_out_face_first(tiny_trained_run, tmp_path, monkeypatch):
    """After training (here: the tiny run, every stage up to date) the demo sweeps and redirects a held-out
    subject, each after fitting: one fit for the sweep (the evaluation's), one per redirected row (natural eyes)."""
    import shutil

    import h5py

    import train.evaluation.fitting as evaluate
    from apps.demo import run_pipeline
    from train.presets import NATURAL_EYES_FIT

    shutil.copytree(tiny_trained_run, tmp_path / "run")
    fits = []
    real_fit = evaluate.test_time_fit

    def spy(model, renderer, batch, *a, **kw):
        fits.append((batch["target_gazes"].shape, kw["weights"]))
        return real_fit(model, renderer, batch, *a, **kw)

    monkeypatch.setattr(evaluate, "test_time_fit", spy)
    run_pipeline(tmp_path, "tiny", [])
    for name in ("heldout_gaze_sweep.mp4", "heldout_gaze_sweep.png", "redirected_mini.h5", "report.md"):
        assert (tmp_path / name).stat().st_size > 0, name
    # The report sits at OUT/report.md, its figures linked into the run directory.
    import re

    links = re.findall(r"\]\(([^)]+\.png)\)", (tmp_path / "report.md").read_text())
    assert links and all(link.startswith("run/") and (tmp_path / link).is_file() for link in links), links
    with h5py.File(tmp_path / "redirected_mini.h5") as f:
        assert f["face_patch"].shape[0] == 4 * 9 and np.isfinite(f["latent_codes"][:]).all()
    sweep = 3  # the tiny preset's eval.sweep_frames
    run_weights = tuple(run_config_of(tmp_path / "run").eval.tta_weights)
    natural = NATURAL_EYES_FIT["weights"]
    assert run_weights != natural
    assert fits == [((1, sweep, 2), run_weights)] + [((1, 9, 2), natural)] * 4


def run_config_of(run_dir):
    from train.trained_run import TrainedRun

    return TrainedRun.open(run_dir).config


# (id, argv after --out, regex the error line matches): each refused before the head is built or a file written.
BAD_DEMO_ARGS = [
    ("unknown preset", ["--preset", "bogus"], r"--preset: expected one of \['demo', 'paper', 'tiny'\], got 'bogus'"),
    ("override not a section", ["x.y=1"], r"unknown config key 'x'"),
    ("override without =", ["notanoverride"], r"override 'notanoverride': expected KEY=VALUE"),
    ("negative steps", ["gaussian.steps=-5"], r"'gaussian.steps': expected a count >= 1, got -5"),
    ("bad override on another preset", ["--preset", "tiny", "seed=4294967296"], r"'seed': expected a seed below 2\^32"),
    ("1e10 Gaussians", ["--skip-training", "--gaussians", "10000000000"],
     r"--gaussians: expected a number of demo Gaussians in \[64, 2000000\], got 10000000000"),
    ("too few Gaussians", ["--skip-training", "--gaussians", "3"], r"--gaussians: expected .* got 3"),
    ("seed 2^64", ["--skip-training", "--seed", "18446744073709551616"],
     r"--seed: expected a seed in \[-9223372036854775808, 18446744073709551615\], got 18446744073709551616"),
    ("seed below -2^63", ["--skip-training", "--seed", "-9223372036854775809"], r"--seed: expected a seed in .* got -9"),
    ("overrides without training", ["--skip-training", "gaussian.steps=3"],
     r"--skip-training runs no training, so gaussian.steps=3 would be ignored"),
    ("preset without training", ["--skip-training", "--preset", "tiny"],
     r"--skip-training runs no training, so --preset tiny would be ignored"),
    ("out under a file", ["--skip-training", "--out", "{tmp}/file.txt/demo"], r"--out: .*file\.txt is a file"),
]


@pytest.fixture
def demo_does_no_work(monkeypatch):
    """Building the demo head fails the test: a refusal that came after it would show as that failure, at once."""
    import apps.demo

    def built(*a, **k):
        raise AssertionError("the demo head was built before the arguments were refused")

    monkeypatch.setattr(apps.demo, "demo_head_scene", built)


@pytest.mark.parametrize("argv, match", [pytest.param(a, m, id=i) for i, a, m in BAD_DEMO_ARGS])
def test_demo_refuses_bad_arguments_before_writing(tmp_path, demo_does_no_work, argv, match):
    from tests.fuzz.cli import assert_refused

    (tmp_path / "file.txt").write_text("a file, not a folder\n")
    args = ["--out", tmp_path / "demo", *(a.format(tmp=tmp_path) for a in argv)]
    assert_refused("apps.demo", args, match, inputs=[tmp_path / "file.txt"], out_dir=tmp_path, seconds=20)


def test_demo_refuses_an_empty_out(tmp_path, monkeypatch, demo_does_no_work):
    """An empty --out is the current folder: refused, nothing written there."""
    from tests.fuzz.cli import assert_refused

    monkeypatch.chdir(tmp_path)
    assert_refused("apps.demo", ["--out", "", "--skip-training", "--gaussians", "64"],
                   r"--out: expected an output folder, got an empty path", out_dir=tmp_path, seconds=20)
