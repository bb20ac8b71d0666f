"""The paper preset runs end to end on a CPU at its own resolution (512²) and model sizes, with every stage cut to
a few steps and the data to a few images: what a GPU user starts from trains here too (slow: minutes)."""

import json
import math

import pytest

from train import run

FEW_STEPS = ["data.subjects=2", "data.frames=1", "data.test_frames=2", "data.test_fraction=0.5",
             "geometry.steps=20", "geometry.pretrain_steps=50", "geometry.extract_res=24", "geometry.pool=20000",
             "geometry.gaussians=4000", "geometry.pretrain_fields=2",
             "codec.steps=2", "codec.batch=2",
             "estimator.steps=2", "estimator.batch=4", "estimator.synthetic_subjects=1", "estimator.synthetic_frames=2",
             "gaussian.steps=2", "gaussian.batch=1", "gaussian.ckpt_every=2", "gaussian.log_every=1",
             "eval.pairs_per_subject=1", "eval.tta_steps=1", "eval.sweep_frames=2"]
"""Step counts and data sizes only: the resolution, the DiT-Gaze-paper renderer, the field and eye-term switches,
the separate region renders, the optimizer and the codec's shape stay the paper preset's."""


@pytest.mark.slow
def test_the_paper_preset_trains_a_few_steps_at_512(tmp_path):
    d = tmp_path / "paper"
    assert run.main(["--preset", "paper", "--run-dir", str(d), *FEW_STEPS]) == 0
    metrics = [json.loads(line) for line in (d / "metrics.jsonl").read_text().splitlines()]
    losses = [m["total"] for m in metrics if m.get("stage") == "gaussian" and "total" in m]
    assert len(losses) == 2 and all(math.isfinite(v) for v in losses)
    config = (d / "config.yaml").read_text()
    assert "res: 512" in config and "DiT-Gaze-paper" in config and "field_input: feature" in config
    assert (d / "gaussian" / "final.safetensors").is_file() and (d / "metrics.json").is_file()
