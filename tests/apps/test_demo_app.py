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
