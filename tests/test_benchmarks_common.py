"""benchmarks/common.py's plot writer: atomic like every other output."""

import os

import pytest

from benchmarks.common import save_plot
from toolkit.errors import ToolkitError


def test_plot_is_written_whole_with_the_umask_mode(tmp_path):
    mask = os.umask(0)
    os.umask(mask)
    out = save_plot(tmp_path / "p.png", {"a": ([1, 2, 3], [3, 1, 2])}, xlabel="x", ylabel="y", title="t")
    assert out.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n" and out.stat().st_mode & 0o777 == 0o666 & ~mask
    assert sorted(tmp_path.iterdir()) == [out]  # no temporary file left beside it


def test_plot_into_an_unwritable_place_is_a_clear_error(tmp_path):
    (tmp_path / "afile").write_text("")
    with pytest.raises(ToolkitError, match="cannot write here"):
        save_plot(tmp_path / "afile" / "p.png", {"a": ([1, 2], [1, 2])}, xlabel="x", ylabel="y", title="t")
    assert sorted(tmp_path.iterdir()) == [tmp_path / "afile"]


# Bad flags of the benchmarks: each refused in one line (exit 2) before any head, data set or model is made and
# before anything is written. (id, benchmark, argv with a {tmp} placeholder, regex the error line matches, env)
BAD_BENCH_ARGS = [
    ("scales 1e12 Gaussians", "field_switches", ["--scales", "1000000000000:16:64:2"],
     r"--scales N: expected a number of demo Gaussians in \[64, 2000000\], got 1000000000000", {}),
    ("scales huge side", "field_switches", ["--scales", "800:16:100000:2"], r"--scales size: expected pixels", {}),
    ("scales over the memory budget", "field_switches", ["--scales", "2000000:4096:64:64"],
     r"--scales 2000000:4096:64:64 would allocate .* memory budget", {}),
    ("default scales under a tiny budget", "field_switches", [], r"--scales 12000:64:128:4 would allocate",
     {"DITGAZE_MEMORY_GB": "0.5"}),
    ("1e12 Gaussians", "gaussian_model", ["--gaussians", "1000000000000"],
     r"--gaussians: expected a comma list of integers in \[64, 2000000\], got '1000000000000'", {}),
    ("1e9 pixel side", "gaussian_model", ["--sizes", "1000000000"],
     r"--sizes: expected a comma list of integers in \[16, 8192\], got '1000000000'", {}),
    ("huge batch", "gaussian_model", ["--batch", "100000"], r"--batch 100000 .* would allocate .* memory budget", {}),
    ("missing data", "gaze_estimator", ["--data", "{tmp}/nodata"], r"--data: .*nodata: no such file", {}),
    ("data not a dataset", "gaze_estimator", ["--data", "{tmp}/file.txt"], r"--data: split 'test' is empty", {}),
    ("cache under a file", "gaze_estimator", ["--cache", "{tmp}/file.txt/cache"],
     r"--cache: .*file\.txt is a file, not a folder", {}),
    ("empty cache", "gaze_estimator", ["--cache="], r"--cache: expected a folder, got an empty path", {}),
    ("save under a file", "gaze_estimator", ["--save", "{tmp}/file.txt/models"],
     r"--save: .*file\.txt is a file, not a folder", {}),
    ("mirror above 1", "gaze_estimator", ["--mirror", "2"], r"--mirror: expected a probability in \[0, 1\], got 2", {}),
    ("mirror nan", "gaze_estimator", ["--mirror", "nan"], r"--mirror: expected a probability .* got nan", {}),
    ("landmark noise nan", "gaze_estimator", ["--landmark-noise", "nan"],
     r"--landmark-noise: expected a jitter in \[0, 128\] pixels \(--res\), got nan", {}),
    ("landmark noise negative", "gaze_estimator", ["--landmark-noise", "-1"], r"--landmark-noise: .* got -1", {}),
    ("train size 7", "renderer", ["--train-size", "7"],
     r"--train-size: expected a multiple of 16 \(DiT-Gaze-tiny: .*\), got 7", {}),
    ("train size of another patch", "renderer", ["--model", "DiT-Gaze-paper/4", "--train-size", "16"],
     r"--train-size: expected a multiple of 32 .* got 16", {}),
    ("training set over the memory budget", "renderer", ["--train-size", "4096"],
     r"--train-images 2048 --test-images 32 at --train-size 4096 would allocate", {}),
    ("unknown variant", "train", ["--variants", "ditt"],
     r"--variants: unknown variant 'ditt'; .* one of \['dit', 'unet'\]", {}),
    ("name without overrides", "train", ["--variants", "dit,base:"], r"--variants: unknown variant 'base'", {}),
    ("variant override typo", "train", ["--variants", "dit:,nogaze:gaussian.lambda_gazee=0"],
     r"--variants nogaze: unknown config key 'gaussian.lambda_gazee'", {}),
    ("override typo", "train", ["gaussian.stpes=3"], r"unknown config key 'gaussian.stpes'", {}),
]

# What each benchmark does first once its flags pass: made to fail the test, so that a refusal that came too
# late shows at once (instead of running the benchmark).
FIRST_WORK = {"field_switches": ["demo_head_scene", "_time_scale"], "gaussian_model": ["demo_head_scene"],
              "gaze_estimator": ["procedural_set", "load_split", "_train_mode"],
              "renderer": ["speed_table", "fit_renderers"], "train": ["open_prereqs"]}


@pytest.mark.parametrize("case, bench, argv, match, env", BAD_BENCH_ARGS, ids=[c[0] for c in BAD_BENCH_ARGS])
def test_benchmarks_refuse_bad_flags_before_any_work(tmp_path, monkeypatch, case, bench, argv, match, env):
    import importlib

    from tests.fuzz.cli import assert_refused

    module = importlib.import_module(f"benchmarks.{bench}")
    for name in FIRST_WORK[bench]:
        if name == "load_split" and "--data" in argv:
            continue  # reading --data is its check

        def work(*a, name=name, **k):
            raise AssertionError(f"benchmarks.{bench}: {name} ran before the flags were refused")

        monkeypatch.setattr(module, name, work)
    monkeypatch.setattr(module, "OUT_DIR", tmp_path / "bench")
    monkeypatch.chdir(tmp_path)
    for key, value in env.items():
        monkeypatch.setenv(key, value)
    (tmp_path / "file.txt").write_text("a file, not a folder\n")
    args = [a.format(tmp=tmp_path) for a in argv]
    if bench == "train":
        args = ["--run-dir", str(tmp_path / "run"), *args]
    assert_refused(f"benchmarks.{bench}", args, match, inputs=[tmp_path / "file.txt"], out_dir=tmp_path, seconds=20)
