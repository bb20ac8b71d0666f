"""Acceptance of the mesh stage on the synthetic dataset, at the default (demo) FitConfig.

A subject is rendered by train.data (18 ETH-XGaze-like cameras x 3 frames, 128 px), the neutral head is
fitted by ``geometry.fit_dataset.fit_dataset`` from its head masks and 3D landmarks with rig cameras
2, 7, 10 and 15 held out, and the result must reach silhouette IoU >= 0.97 on the held-out views and a
Chamfer distance <= 1 % of the head's bounding-box diagonal to the generator's ground-truth neutral
mesh. (Timing is reported in fit.json, never asserted; the < 5 min CPU budget is checked by hand.)
"""

from __future__ import annotations

import json

import pytest
import torch


@pytest.mark.slow
def test_fit_synthetic_subject_meets_acceptance(tmp_path):
    from geometry.fit import FitConfig
    from geometry.fit_dataset import fit_dataset, read_subject
    from tests.gl import require_gl
    from toolkit.scene import GaussianScene
    from train.data.format import write_subject_h5
    from train.data.generate import generate_subject
    from train.data.synthetic import SubjectParams

    require_gl()  # the generator renders through headless GL; only a missing GL skips
    rows, subj, attrs = generate_subject(SubjectParams.sample(0), n_frames=3, res=128, seed=0)
    path = write_subject_h5(tmp_path / "subject.h5", rows, subject=subj, attrs=attrs)
    data = read_subject(path)
    assert data["landmarks"].shape == (68, 3) and data["viewmats"].shape[0] == 54
    out = tmp_path / "fit"
    summary = fit_dataset(path, out, FitConfig())
    assert summary["heldout_views"] == 12 and summary["train_views"] == 42
    assert summary["heldout_iou_mean"] >= 0.97, summary
    assert summary["heldout_iou_min"] >= 0.95, summary
    assert summary["chamfer_rel_diag"] <= 0.01, summary
    assert summary["skipped_steps"] == 0
    for name in ("neutral_mesh.ply", "sdf.safetensors", "gaussians.safetensors", "fit.json"):
        assert (out / name).exists()
    assert json.loads((out / "fit.json").read_text())["chamfer_rel_diag"] == summary["chamfer_rel_diag"]
    scene = GaussianScene.load(out / "gaussians.safetensors")
    eyes = scene.metadata["eyes"]
    gt = torch.as_tensor(subj["eyeball_centers"])
    for i, name in enumerate(("left", "right")):
        assert float((torch.tensor(eyes[name]["center"]) - gt[i]).norm()) < 0.005
