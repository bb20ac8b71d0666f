"""The eval stage's fidelity measures at the tiny preset: identity drift (dlib embedding; n/a without the extra),
eye realism, and the natural fit's row beside a fit with a gaze term."""

import json
import shutil
import sys

import pytest

from train import run
from train.evaluation.report import fidelity_section, protocol_note
from train.evaluation.summary import natural_fit_summary
from train.presets import tiny_preset
from train.run_config import EvalConfig
from train.stages.eval import natural_fit_applies

TINY = ["--preset", "tiny"]


def test_the_tiny_run_reports_identity_drift_eye_realism_and_the_natural_fit(tiny_run):
    """The tiny preset's fit has a gaze term (weight 0.0002, 2 steps): the natural row is there, pair for pair."""
    pytest.importorskip("dlib", reason="the optional extra 'identity' (make setup installs it)")
    out = json.loads((tiny_run / "metrics.json").read_text())
    m = out["metrics"]
    for key in ("identity_drift", "identity_drift_real"):
        lo, hi = m[f"{key}_ci95"]
        assert 0 <= lo <= m[key] <= hi < 2, key
    drift = [(r["identity_drift"], r["identity_drift_real"]) for r in out["per_pair"]]
    assert len(drift) == m["pairs"] and all(d >= 0 and f >= 0 for d, f in drift)
    assert m["identity_similarity_input"] is None  # no ArcFace weights given
    nat = m["natural_fit"]
    assert nat["pairs"] == m["pairs"] and 0 <= nat["gaze_error_deg"] <= 180 and nat["psnr"] > 0
    assert [(r["subject"], r["pair"]) for r in out["natural_fit_per_pair"]] == \
        [(r["subject"], r["pair"]) for r in out["per_pair"]]
    assert nat["gaze_error_delta_deg"] == pytest.approx(nat["gaze_error_deg"] - m["gaze_error_deg"], abs=1e-5)
    assert 0 <= nat["render_vs_label_gaze_deg"] <= 180
    report = (tiny_run / "report.md").read_text()
    assert "## Redirection fidelity" in report and "| identity drift: dlib embedding distance to the input ↓ | " \
        f"{m['identity_drift']:.3f}" in report
    assert f"| eye realism: the evaluation estimator's error against the label gaze ↓ | " \
        f"{out['labels']['render']['gaze_error_deg']:.2f}° | {out['labels']['target']['gaze_error_deg']:.2f}° |" in report
    assert "| *natural fit: no gaze term (how the toolkit produces data)* | " f"{nat['gaze_error_deg']:.2f} |" in report
    assert "that is the field's protocol" in report and "as readable as a real one" in report


def test_without_the_extra_and_without_a_gaze_term(tiny_run, tmp_path, monkeypatch, capsys):
    """dlib missing: the eval runs, identity drift is n/a and the report says how to get it. A fit without a gaze
    term (here none at all) has no natural row: the main row is the natural fit."""
    d = tmp_path / "run"
    shutil.copytree(tiny_run, d)
    monkeypatch.setitem(sys.modules, "dlib", None)  # import dlib -> ImportError
    assert run.main([*TINY, "--run-dir", str(d), "--stages", "eval", "eval.tta_steps=0"]) == 0
    assert "n/a: identity drift needs the optional extra 'identity'" in capsys.readouterr().out
    out = json.loads((d / "metrics.json").read_text())
    m = out["metrics"]
    assert m["identity_drift"] is None and m["identity_drift_real"] is None and m["identity_drift_ci95"] is None
    assert "natural_fit" not in m and "natural_fit_per_pair" not in out
    assert all("identity_drift" not in r for r in out["per_pair"])
    report = (d / "report.md").read_text()
    assert "| identity drift: dlib embedding distance to the input ↓ | n/a | n/a |" in report
    assert "pip install 'ditgaze[identity]'" in report and "has no gaze term: the main row is the natural fit" in report
    assert "*natural fit" not in report


def test_the_natural_row_applies_exactly_with_a_gaze_term_and_the_switch():
    assert natural_fit_applies(EvalConfig(tta_steps=2, tta_gaze_weight=1e-3))
    assert not natural_fit_applies(EvalConfig(tta_steps=2, tta_gaze_weight=1e-3, natural_fit_row=False))
    assert not natural_fit_applies(EvalConfig(tta_steps=2, tta_gaze_weight=0.0))
    assert not natural_fit_applies(EvalConfig(tta_steps=0, tta_gaze_weight=1e-3))
    off = protocol_note(EvalConfig(tta_steps=2, tta_gaze_weight=1e-3, natural_fit_row=False), None)
    assert "field's protocol" in off and "`eval.natural_fit_row=true` adds" in off
    on = EvalConfig(tta_steps=2, tta_gaze_weight=1e-3)
    assert "(7.25°; paired change +1.50°)" in protocol_note(on, {"gaze_error_deg": 7.25, "gaze_error_delta_deg": 1.5})
    # no pair scored in both rows: the change is left out, not a TypeError
    assert "(n/a)" in protocol_note(on, {"gaze_error_deg": None, "gaze_error_delta_deg": None})


def test_natural_fit_summary_pairs_the_rows_by_subject_and_pair():
    per_pair = [{"subject": "a", "pair": 0, "gaze_error_deg": 4.0}, {"subject": "a", "pair": 5, "gaze_error_deg": 6.0},
                {"subject": "b", "pair": 0, "gaze_error_deg": 8.0}]
    recs = [{"subject": "b", "pair": 0, "gaze_error_deg": 9.0}, {"subject": "a", "pair": 0, "gaze_error_deg": 5.0},
            {"subject": "a", "pair": 5, "gaze_error_deg": 9.0}]
    natural = {"gaze_err": [9.0, 5.0, 9.0], "head_err": [1.0, 2.0, 3.0], "psnrs": [20.0, 22.0, 24.0],
               "ssims": [0.5, 0.6, 0.7], "per_pair": recs, "label_scores": {"target": {}, "render": {}}}
    s = natural_fit_summary(natural, per_pair)
    assert s["gaze_error_delta_deg"] == pytest.approx((1 + 1 + 3) / 3)  # b/0: +1, a/0: +1, a/5: +3
    lo, hi = s["gaze_error_delta_ci95_deg"]
    assert 1 <= lo <= hi <= 3 and s["gaze_error_deg"] == pytest.approx(23 / 3) and s["gaze_error_median_deg"] == 9
    assert s["render_vs_label_gaze_deg"] is None and s["pairs"] == 3 and s["psnr"] == pytest.approx(22.0)


def test_fidelity_section_without_labels_or_drift():
    res = {"metrics": {"identity_drift": None}, "labels": {}}
    text = fidelity_section(res, tiny_preset())
    assert "eye realism" not in text and "Identity drift is n/a" in text and text.endswith("\n")
