"""``python -m train.run augment``: both protocols on the tiny run, the paired statistics, the outputs, and
bad input as one line."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
import torch

from tests.fuzz.cli import assert_refused
from train import run
from train.augment.report import paired, summarize, t95

FAST = ["--seeds", "2", "--ks", "1", "--subjects", "1", "--base-steps", "4", "--tune-steps", "3", "--grid", "2",
        "--redirect-cameras", "1", "--fit-steps", "1"]


@pytest.fixture(scope="module")
def augmented(tiny_run, tmp_path_factory):
    out = tmp_path_factory.mktemp("augment")
    old = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        assert run.main(["augment", "--run-dir", str(tiny_run), "--out", str(out), *FAST]) == 0
    finally:
        torch.set_num_threads(old)
    return out


def test_the_outputs_hold_every_arm_paired_with_the_control(augmented):
    res = json.loads((augmented / "augment.json").read_text())
    assert set(res["A"]) == {"i", "ii", "iii", "iv"} and set(res["B"]) == {"real", "redirected"}
    for protocol, control in (("A", "ii"), ("B", "real")):
        for arm, cells in res[protocol].items():
            for level, c in cells.items():
                errs, ref = res["raw"][protocol][arm][level], res["raw"][protocol][control][level]
                assert len(errs) == len(ref) == c["n"] == 2  # 2 repetitions x 1 held-out person (A), 2 (B)
                assert c["mean"] == pytest.approx(np.mean(errs)) and c["diff"] == pytest.approx(np.mean(errs) - np.mean(ref))
                assert c["lo"] <= c["diff"] <= c["hi"] or (arm == control and c["lo"] == c["hi"] == 0)
                assert all(math.isfinite(e) and 0 <= e <= 180 for e in errs)
    md = (augmented / "augment.md").read_text()
    assert "Protocol A: personal calibration" in md and "| iii |" in md and "closes" in md
    ii, iii = res["A"]["ii"]["1"]["mean"], res["A"]["iii"]["1"]["mean"]  # a gain reads negative, as diff does
    assert f"k = 1: (iii) against (ii), {100 * (iii - ii) / ii:+.1f} % error (negative is better)" in md
    assert (augmented / "augment.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_paired_intervals_are_students():
    # d = [1, 2, 3]: mean 2, sd 1, t(2) = 4.303 -> 2 +- 4.303 / sqrt(3)
    c = paired([11, 12, 13], [10, 10, 10])
    assert (c["mean"], c["diff"], c["n"]) == (12, 2, 3)
    assert c["hi"] - c["diff"] == pytest.approx(4.303 / math.sqrt(3))
    assert t95(1) == 12.706 and t95(11) == 2.228 and t95(100) == 1.96 and t95(0) == math.inf
    s = summarize({"A": {"ii": {"1": [1.0, 2.0]}, "iii": {"1": [0.5, 1.0]}}})
    assert s["A"]["iii"]["1"]["diff"] == pytest.approx(-0.75) and s["A"]["ii"]["1"]["diff"] == 0


def test_the_arms_differ_only_in_their_data(tiny_run):
    """The estimator under test is trained the same way for every arm: same data and seed, same weights; its
    seeds are not the estimator stage's."""
    from train.augment.config import AugmentConfig
    from train.augment.protocol import Estimators
    from train.augment.rows import read_rows
    from train.trained_run import TrainedRun

    t = TrainedRun.open(tiny_run)
    est = Estimators(t, AugmentConfig(base_steps=3), "cpu")
    rows = read_rows(t.split("train")[0], t.config.data.res)
    a, b = est.train(rows, 0), est.train(rows, 0)
    assert all(torch.equal(x, y) for x, y in zip(a.state_dict().values(), b.state_dict().values()))
    c = est.train(rows.take(torch.arange(len(rows)) % 2 == 0), 0)
    assert not all(torch.equal(x, y) for x, y in zip(a.state_dict().values(), c.state_dict().values()))
    assert est.seed(0) not in (t.config.seed * 10 + 1, t.config.seed * 10 + 2)


def test_warmup_reaches_training_from_scratch_and_not_fine_tuning(tiny_run):
    from train.augment.config import AugmentConfig
    from train.augment.protocol import Estimators
    from train.augment.rows import read_rows
    from train.trained_run import TrainedRun

    t = TrainedRun.open(tiny_run)
    rows = read_rows(t.split("train")[0], t.config.data.res)
    cold, warm = (Estimators(t, AugmentConfig(base_steps=3, tune_steps=2, warmup_steps=w), "cpu") for w in (0, 5))
    base_cold, base_warm = cold.train(rows, 0), warm.train(rows, 0)
    same = [torch.equal(x, y) for x, y in zip(base_cold.state_dict().values(), base_warm.state_dict().values())]
    assert not all(same)
    tuned_cold, tuned_warm = cold.train(rows, 0, init=base_cold), warm.train(rows, 0, init=base_cold)
    assert all(torch.equal(x, y) for x, y in zip(tuned_cold.state_dict().values(), tuned_warm.state_dict().values()))


def test_bad_settings_are_one_line(tiny_run, tmp_path):
    out = tmp_path / "out"
    assert_refused("train.run", ["augment", "--run-dir", tiny_run, "--out", out, "--ks", "0"],
                   r"augment --ks: expected integers >= 1", inputs=[tiny_run], out_dir=tmp_path)
    assert_refused("train.run", ["augment", "--run-dir", tiny_run, "--out", out, "--protocols", "C"],
                   r"augment --protocols: expected A, B or both", inputs=[tiny_run], out_dir=tmp_path)
    assert_refused("train.run", ["augment", "--run-dir", tmp_path, "--out", out],
                   r"not a run directory", out_dir=tmp_path)
    assert_refused("train.run", ["augment", "--run-dir", tiny_run, "--out", out, "--seeds", "0"],
                   r"'augment --seeds': expected a count", inputs=[tiny_run], out_dir=tmp_path)
    assert_refused("train.run", ["augment", "--run-dir", tiny_run, "--out", out, "--warmup-steps", "-1"],
                   r"'augment --warmup-steps': expected a step count", inputs=[tiny_run], out_dir=tmp_path)
    for flag, value, expected in (("--seed", str(2**32), "a seed below 2\\^32"), ("--device", "tpu", "auto, cpu, cuda"),
                                  ("--grid", "16", r"gazes per axis in \[1, 15\]"),
                                  ("--base-steps", "100000000", "at most 10000000 steps")):
        assert_refused("train.run", ["augment", "--run-dir", tiny_run, "--out", out, flag, value],
                       rf"'augment {flag}': expected {expected}", inputs=[tiny_run], out_dir=tmp_path)
    assert_refused("train.run", ["augment", "--run-dir", tiny_run, "--out", out, "--ks", "50", "60"],
                   r"augment --ks \[50, 60\]: the run's held-out persons have at most \d+ frames, and a k must "
                   r"leave a frame to test on", inputs=[tiny_run], out_dir=tmp_path)
    assert not out.exists()


def test_output_places_and_memory_are_checked_before_any_work(tiny_run, tmp_path, monkeypatch):
    """Each refusal comes before the base estimator trains (the time cap): a path under a file, an output file
    that is a folder, and copies that would not fit the memory budget."""
    blocker = tmp_path / "blocker"
    blocker.write_text("a file")
    assert_refused("train.run", ["augment", "--run-dir", tiny_run, "--out", blocker / "sub", *FAST],
                   r"--out .*blocker/sub: .*blocker is a file, not a folder", inputs=[tiny_run, blocker], seconds=20)
    taken = tmp_path / "taken"
    (taken / "augment.png").mkdir(parents=True)
    assert_refused("train.run", ["augment", "--run-dir", tiny_run, "--out", taken, *FAST],
                   r"augment.png is a folder; expected a file", inputs=[tiny_run], out_dir=taken, seconds=20)
    monkeypatch.setenv("DITGAZE_MEMORY_GB", "0.001")
    assert_refused("train.run", ["augment", "--run-dir", tiny_run, "--out", tmp_path / "o", *FAST, "--grid", "15"],
                   r"augment's \d+ redirected images would allocate .*; lower --grid or --redirect-cameras",
                   inputs=[tiny_run], out_dir=tmp_path, seconds=20)
