"""``python -m train.run ablate``: Table 3's rows trained on shared earlier stages, tabled against the full model,
resumable."""

from __future__ import annotations

import json
import shutil

import pytest

from toolkit.errors import ToolkitError
from train import run
from train.ablate import ROWS, _cell, summarize_rows, table_rows

QUICK = ["gaussian.steps=2", "eval.pairs_per_subject=1", "eval.tta_steps=0", "estimator.steps=2", "codec.steps=2"]


@pytest.fixture(scope="module")
def ablation(tmp_path_factory):
    root = tmp_path_factory.mktemp("ablate")
    assert run.main(["ablate", "--preset", "tiny", "--seeds", "1", "--run-dir", str(root), *QUICK]) == 0
    return root


def test_every_row_is_trained_on_the_full_runs_earlier_stages(ablation):
    seed = ablation / "seed0"
    assert sorted(p.name for p in seed.iterdir()) == ["full", "no_dit_renderer", "no_orthogonality_loss",
                                                     "no_weak_supervision"]
    full = {s: json.loads((seed / "full" / "stages" / f"{s}.json").read_text())["fingerprint"]
            for s in ("data", "geometry", "codec", "estimator", "gaussian")}
    for row in ("no_dit_renderer", "no_orthogonality_loss", "no_weak_supervision"):
        prints = {s: json.loads((seed / row / "stages" / f"{s}.json").read_text())["fingerprint"] for s in full}
        assert {s: prints[s] for s in ("data", "geometry", "codec", "estimator")} == \
            {s: full[s] for s in ("data", "geometry", "codec", "estimator")}
        assert prints["gaussian"] != full["gaussian"]  # the row's switch, and nothing before it
    cfg = (seed / "no_dit_renderer" / "config.yaml").read_text()
    assert "renderer: unet" in cfg and "feature_upscale: 4" in cfg


def test_the_table_names_every_row_and_a_rerun_trains_nothing(ablation):
    table = json.loads((ablation / "ablation.json").read_text())
    assert list(table["rows"]) == [name for name, _ in ROWS]
    assert table["rows"]["full"]["gaze"]["diff"] == 0
    md = (ablation / "ablation.md").read_text()
    assert "| w/o DiT renderer |" in md and "wall time" in md and "LPIPS" not in md  # no LPIPS weights given
    assert (ablation / "ablation.png").read_bytes()[:4] == b"\x89PNG"
    ckpt = ablation / "seed0" / "no_orthogonality_loss" / "gaussian" / "final.safetensors"
    before = ckpt.stat().st_mtime_ns
    assert run.main(["ablate", "--preset", "tiny", "--seeds", "1", "--run-dir", str(ablation), *QUICK]) == 0
    assert ckpt.stat().st_mtime_ns == before


def test_rows_compare_paired_over_seeds():
    runs = {"full": [{"gaze_error_deg": 5.0, "psnr": 30.0, "seconds": 10.0},
                     {"gaze_error_deg": 6.0, "psnr": 31.0, "seconds": 12.0}],
            "w/o orthogonality loss": [{"gaze_error_deg": 6.0, "psnr": 29.0, "seconds": 9.0},
                                       {"gaze_error_deg": 8.0, "psnr": 30.0, "seconds": 11.0}]}
    table = summarize_rows(runs)
    cell = table["w/o orthogonality loss"]["gaze"]
    assert (cell["mean"], cell["diff"], cell["n"]) == (7.0, 1.5, 2)
    assert table["w/o orthogonality loss"]["PSNR"]["diff"] == -1.0 and table["full"]["LPIPS"] is None


def test_table_cells_keep_large_values_out_of_exponent_form():
    row = {"mean": 384.4, "diff": -994.6, "lo": -5121.0, "hi": 3080.2}
    assert _cell(row, full=False) == "384 (-995 [-5121, +3080])"
    assert _cell({"mean": 1379.0}, full=True) == "1379"
    assert _cell({"mean": 0.98531}, full=True) == "0.985"
    assert _cell({"mean": 5.07, "diff": 0.1, "lo": -1.46, "hi": 1.66}, full=False) == "5.07 (+0.1 [-1.5, +1.7])"


def test_rows_of_ones_own_share_the_full_model(ablation, tmp_path):
    """``--row NAME OVERRIDE...`` trains those rows instead of Table 3's, against the same (here: copied,
    already trained) full model, which is not retrained."""
    shutil.copytree(ablation / "seed0" / "full", tmp_path / "seed0" / "full")
    ckpt = tmp_path / "seed0" / "full" / "gaussian" / "final.safetensors"
    before = ckpt.stat().st_mtime_ns
    assert run.main(["ablate", "--preset", "tiny", "--seeds", "1", "--run-dir", str(tmp_path), *QUICK,
                     "--row", "ssim 0.2", "gaussian.lambda_ssim=0.2"]) == 0
    assert ckpt.stat().st_mtime_ns == before
    assert sorted(p.name for p in (tmp_path / "seed0").iterdir()) == ["full", "ssim_0.2"]
    assert "lambda_ssim: 0.2" in (tmp_path / "seed0" / "ssim_0.2" / "config.yaml").read_text()
    table = json.loads((tmp_path / "ablation.json").read_text())
    assert list(table["rows"]) == ["full", "ssim 0.2"]
    assert table["row_overrides"]["ssim 0.2"] == ["gaussian.lambda_ssim=0.2"]
    assert (tmp_path / "ablation.md").read_text().startswith("# Switches against the full model")


@pytest.mark.parametrize("row, expected", [(["x"], "one or more section.key=value"),
                                           (["x", "lambda_ssim=0.2"], "one or more section.key=value"),
                                           (["full", "gaussian.steps=2"], "a name of its own"),
                                           (["//", "gaussian.steps=2"], "a name of its own")])
def test_a_bad_row_is_one_line_before_any_training(row, expected):
    with pytest.raises(ToolkitError, match=expected):
        table_rows([row])
    assert table_rows(None) == ROWS
    assert [n for n, _ in table_rows([["a b", "gaussian.steps=2"], ["c", "eval.tta_steps=0"]])] == ["full", "a b", "c"]


def test_lpips_and_fid_become_columns_when_every_run_scores_them():
    from types import SimpleNamespace

    from train.ablate import ablation_markdown

    def run(gaze, lpips, fid):
        return {"gaze_error_deg": gaze, "psnr": 30.0, "lpips": lpips, "fid": fid, "seconds": 5.0}

    given = summarize_rows({"full": [run(5.0, 0.20, 60.0), run(6.0, 0.22, 62.0)],
                            "w/o DiT renderer": [run(9.0, 0.30, 150.0), run(11.0, 0.34, 160.0)]})
    assert given["w/o DiT renderer"]["LPIPS"]["diff"] == pytest.approx(0.11)
    args = SimpleNamespace(row=None, preset="demo", seeds=2)
    header = ablation_markdown(given, args).splitlines()[4]
    assert "| LPIPS |" in header and "| FID |" in header
    # a seed of a row without LPIPS: that row's cell is n/a, never a mean over the seeds that had it
    row_gap = summarize_rows({"full": [run(5.0, 0.20, 60.0), run(6.0, 0.22, 62.0)],
                              "w/o DiT renderer": [run(9.0, 0.30, 150.0), run(11.0, None, 160.0)]})
    assert row_gap["w/o DiT renderer"]["LPIPS"] is None and row_gap["full"]["LPIPS"]["mean"] == pytest.approx(0.21)
    # a seed of the full model without it: every row's cell is n/a (each is paired against the full model)
    full_gap = summarize_rows({"full": [run(5.0, 0.20, 60.0), run(6.0, None, 62.0)],
                               "w/o DiT renderer": [run(9.0, 0.30, 150.0), run(11.0, 0.34, 160.0)]})
    assert full_gap["full"]["LPIPS"] is None and full_gap["w/o DiT renderer"]["LPIPS"] is None
    assert full_gap["w/o DiT renderer"]["FID"]["diff"] == pytest.approx(94.0)


def test_the_augment_column_compares_each_row_with_the_full_models_gain():
    from types import SimpleNamespace

    from train.ablate import AUGMENT_COLUMN, ablation_markdown

    def run(gain_k1):
        return {"gaze_error_deg": 5.0, "psnr": 30.0, "seconds": 5.0, "augment_A": {"1": gain_k1}}

    table = summarize_rows({"full": [run(-2.0), run(-3.0), run(-1.0)],
                            "w/o DiT renderer": [run(-1.0), run(-2.5), run(-0.5)]})
    full, row = table["full"][f"{AUGMENT_COLUMN} k=1"], table["w/o DiT renderer"][f"{AUGMENT_COLUMN} k=1"]
    # full: (iii) − (ii) against 0 over the seeds, t(2) = 4.303, sd 1: -2 ± 4.303 / sqrt(3)
    assert (full["mean"], full["diff"]) == (-2.0, -2.0)
    assert full["hi"] == pytest.approx(-2.0 + 4.303 / 3 ** 0.5, abs=1e-3)
    # the row: its gain against the full model's, seed by seed: +1.0, +0.5, +0.5 (sd 0.289, half-width 0.717)
    assert row["mean"] == pytest.approx(-4 / 3) and row["diff"] == pytest.approx(2 / 3)
    md = ablation_markdown(table, SimpleNamespace(row=None, preset="demo", seeds=3))
    line = {ln.split("|")[1].strip(): ln for ln in md.splitlines() if ln.startswith("| ")}
    assert line["full"].endswith("| -2 [-4.5, +0.48] |")
    assert line["w/o DiT renderer"].endswith("| -1.33 (+0.67 [-0.05, +1.4]) |")
    assert "(iii) − (ii) in degrees" in md


def test_a_rows_augment_result_is_reused_not_recomputed(tmp_path, monkeypatch):
    import train.augment.cli
    from train.ablate import _augment_row

    (tmp_path / "augment").mkdir()
    (tmp_path / "augment" / "augment.json").write_text(json.dumps(
        {"A": {"iii": {"1": {"mean": 7.0, "diff": -1.5, "lo": -2.0, "hi": -1.0, "n": 2}}}}))
    monkeypatch.setattr(train.augment.cli, "main", lambda argv: pytest.fail("protocol A ran again"))
    assert _augment_row(tmp_path) == {"1": -1.5}


@pytest.mark.parametrize("argv, expected", [
    (["--row", "myrow", "gaussian.stpes=3"], r"ablate row 'myrow': unknown config key 'gaussian.stpes'"),
    (["--preset", "bogus"], r"ablate --preset 'bogus': expected one of \["),
    (["gaussian.lr=nan"], r"ablate overrides \(every row's\): config key 'gaussian.lr': expected a number, got 'nan'"),
    (["--row", "r", "gaussian.renderer=gan"], r"ablate row 'r': config key 'gaussian.renderer': expected one of")])
def test_every_rows_config_is_checked_before_any_training(tmp_path, argv, expected):
    from tests.fuzz.cli import assert_refused

    preset = [] if "--preset" in argv else ["--preset", "tiny"]
    assert_refused("train.run", ["ablate", *preset, "--seeds", "1", "--run-dir", tmp_path / "t", *argv], expected,
                   out_dir=tmp_path, seconds=30)
    assert not (tmp_path / "t").exists()


def test_a_failed_row_is_one_error_line_naming_it(tmp_path, monkeypatch):
    """The row's process hands its error line over through the error file: it becomes the command's one line
    (its other output reaches the terminal as it runs)."""
    import argparse
    import os
    import subprocess

    from toolkit.errors import ERROR_FILE_ENV
    from train.ablate import _run_row

    def child(argv, env):
        with open(env[ERROR_FILE_ENV], "w") as f:
            f.write("data.root: no such folder")
        return subprocess.CompletedProcess(argv, 2)

    monkeypatch.setattr(subprocess, "run", child)
    args = argparse.Namespace(preset="tiny", overrides=[], augment=False)
    with pytest.raises(ToolkitError, match=r"full: the row's run failed: data.root: no such folder$"):
        _run_row(args, tmp_path / "full", tmp_path / "full", 0, ())
    monkeypatch.setattr(subprocess, "run", lambda argv, env: subprocess.CompletedProcess(argv, 1))  # a traceback
    with pytest.raises(ToolkitError, match=r"the row's run failed: exit 1 \(its output is above\)$"):
        _run_row(args, tmp_path / "full", tmp_path / "full", 0, ())
    assert ERROR_FILE_ENV not in os.environ


def test_a_rows_copy_leaves_out_the_full_models_own_results(tmp_path):
    from train.ablate import _copy_run

    full = tmp_path / "full"
    for name in ("config.yaml", "geometry/mesh.ply", "gaussian/final.safetensors", "augment/augment.json",
                 "metrics.json"):
        (full / name).parent.mkdir(parents=True, exist_ok=True)
        (full / name).write_text(name)
    (tmp_path / ".row.copying").mkdir()  # an interrupted copy's leftovers
    _copy_run(full, tmp_path / "row")
    copied = sorted(str(p.relative_to(tmp_path / "row")) for p in (tmp_path / "row").rglob("*"))
    assert copied == ["config.yaml", "geometry", "geometry/mesh.ply"]
    assert sorted(p.name for p in tmp_path.iterdir()) == ["full", "row"]
    (tmp_path / "row" / "config.yaml").unlink()  # a folder of that name that is no run: named, not copied into
    with pytest.raises(ToolkitError, match=r"row: exists but is not a run directory \(no config.yaml\)"):
        _copy_run(full, tmp_path / "row")
