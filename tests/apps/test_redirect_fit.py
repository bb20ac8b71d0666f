"""apps.redirect --fit-weights: each input row is fitted as the evaluation fits a pair (code, face features,
renderer, with the loss estimator's gaze term at the row's target gazes in turn), from the trained weights."""

import h5py
import numpy as np
import pytest
import torch

from apps import redirect, redirect_parts
from tests.apps.helpers import interrupt_redirect_before_assembly
from toolkit.errors import ToolkitError, run_cli
from train.trained_run import TrainedRun


def _test_subject(run_dir):
    return sorted((run_dir / "data").glob("*.h5"))[-1]


def test_fit_weights_fits_every_row_from_the_trained_weights(tiny_trained_run, tmp_path, monkeypatch):
    import train.evaluation.fitting as evaluate

    ctx = TrainedRun.open(tiny_trained_run)
    model, renderer = ctx.load_model(torch.device("cpu"))
    state = lambda m, r: {**{f"m.{k}": v.clone() for k, v in m.state_dict().items()},  # noqa: E731
                          **{f"r.{k}": v.clone() for k, v in r.state_dict().items()}}
    trained = state(model, renderer)
    seen = []
    real_fit = evaluate.test_time_fit

    def spy(model, renderer, batch, image, mask, res, steps, **kw):
        start = state(model, renderer)
        seen.append((batch, image, mask, steps, kw, start))
        return real_fit(model, renderer, batch, image, mask, res, steps, **kw)

    monkeypatch.setattr(evaluate, "test_time_fit", spy)
    src = _test_subject(tiny_trained_run)
    plain, fitted = tmp_path / "plain.h5", tmp_path / "fitted.h5"
    args = [str(tiny_trained_run), str(src), "--gazes", "grid:1x3:20", "--rows", "2", "--batch", "1"]
    assert redirect.main(args[:2] + [str(plain)] + args[2:]) == 0
    assert not seen  # HDF5 rows carry their codes: no fitting unless asked
    assert redirect.main(args[:2] + [str(fitted)] + args[2:] + ["--fit-weights", "--fit-steps", "3"]) == 0
    assert len(seen) == 2  # one fit per input row
    gz = torch.from_numpy(redirect.parse_gazes("grid:1x3:20")).float()
    with h5py.File(src) as f:
        for r, (batch, image, mask, steps, kw, start) in enumerate(seen):
            assert steps == 3 and kw["weights"] == tuple(ctx.config.eval.tta_weights)
            assert kw["renderer_lr"] == ctx.config.eval.tta_renderer_lr
            assert kw["gaze"] is not None and kw["gaze"].weight == ctx.config.eval.tta_gaze_weight
            # The gaze term reads the loss estimator, never the evaluation one.
            loss_w = ctx.estimator("loss", "cpu").state_dict()
            assert all(torch.equal(kw["gaze"].loss.estimator.state_dict()[k], v) for k, v in loss_w.items())
            assert torch.equal(batch["target_gazes"][0], gz)
            assert np.allclose(batch["code"][0].numpy(), f["latent_codes"][r])
            assert np.allclose(batch["in_gaze_head"][0].numpy(), f["pitchyaw_head"][r])
            assert image.shape == (1, 3, 64, 64) and mask.shape == (1, 1, 64, 64)
            # Every row starts from the trained weights (the model's features and the renderer's): the previous
            # row's fit was undone.
            assert set(start) == set(trained) and all(torch.equal(start[k], trained[k]) for k in trained)
    with h5py.File(plain) as a, h5py.File(fitted) as b:
        assert a["face_patch"].shape == b["face_patch"].shape == (6, 64, 64, 3)
        assert np.array_equal(a["pitchyaw_cam"][:], b["pitchyaw_cam"][:])
        assert not np.array_equal(a["face_patch"][:], b["face_patch"][:])
        assert not np.allclose(a["latent_codes"][:], b["latent_codes"][:])  # the fitted code is what was rendered
        assert np.isfinite(b["latent_codes"][:]).all()


def test_natural_eyes_fits_the_natural_weights_with_a_term_that_only_turns_the_eyes(tiny_trained_run, tmp_path,
                                                                                   monkeypatch):
    """``--natural-eyes``: each row's fit takes ``NATURAL_EYES_FIT`` (weights, gaze weight, reach) instead of the
    run's eval section."""
    import train.evaluation.fitting as evaluate
    from train.presets import NATURAL_EYES_FIT

    seen = []
    real_fit = evaluate.test_time_fit

    def spy(model, renderer, batch, image, mask, res, steps, **kw):
        seen.append(kw)
        return real_fit(model, renderer, batch, image, mask, res, steps, **kw)

    monkeypatch.setattr(evaluate, "test_time_fit", spy)
    src = _test_subject(tiny_trained_run)
    out = tmp_path / "natural.h5"
    args = [str(tiny_trained_run), str(src), str(out), "--gazes", "grid:1x2:20", "--rows", "1", "--fit-weights",
            "--fit-steps", "2", "--natural-eyes"]
    assert redirect.main(args) == 0 and out.is_file()
    nat = NATURAL_EYES_FIT
    assert len(seen) == 1 and seen[0]["weights"] == nat["weights"]
    assert seen[0]["weights"] != tuple(TrainedRun.open(tiny_trained_run).config.eval.tta_weights)
    assert seen[0]["gaze"].weight == nat["gaze_weight"] and seen[0]["gaze"].reach == nat["reach"]
    with h5py.File(out) as f:
        assert f["face_patch"].shape == (2, 64, 64, 3) and np.isfinite(f["latent_codes"][:]).all()
    # The chunks' settings record the natural fit itself: a resume after NATURAL_EYES_FIT changed is refused.
    import argparse

    ns = argparse.Namespace(dataset=str(src), batch=1, steps=0, fit_weights=True, natural_eyes=True, seed=0)
    settings = redirect_parts.redirect_settings(TrainedRun.open(tiny_trained_run), ns, ns, np.zeros((2, 2)), 1, 2)
    assert settings["natural_eyes"] and settings["natural_eyes_fit"]["reach"] == list(nat["reach"])
    assert "natural_eyes_fit" not in redirect_parts.redirect_settings(TrainedRun.open(tiny_trained_run), ns,
                                                                argparse.Namespace(**{**vars(ns), "natural_eyes": False}),
                                                                np.zeros((2, 2)), 1, 2)


def test_natural_eyes_without_fit_weights_is_one_line_error(tiny_trained_run, tmp_path, capsys):
    src = _test_subject(tiny_trained_run)
    code = run_cli(redirect.main, [str(tiny_trained_run), str(src), str(tmp_path / "o.h5"), "--natural-eyes"])
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2 and len(err) == 1 and "--natural-eyes sets how --fit-weights fits" in err[0]
    assert not (tmp_path / "o.h5").exists()


def test_term_gaze_order_cycles_or_spreads():
    from toolkit.errors import ToolkitError
    from train.evaluation.fitting import term_gaze_order

    assert term_gaze_order(3, 7) == [0, 1, 2, 0, 1, 2, 0]
    many = term_gaze_order(25, 20)  # grid:5x5 under 40 steps, every 2nd: first to last, no repeats
    assert len(many) == 20 and many[0] == 0 and many[-1] == 24 and many == sorted(set(many))
    assert term_gaze_order(4, 0) == []
    with pytest.raises(ToolkitError, match="expected >= 1 gazes"):
        term_gaze_order(0, 5)


def test_resumed_run_with_other_settings_is_refused(tiny_trained_run, tmp_path, capsys, monkeypatch):
    monkeypatch.chdir(tmp_path)  # the test changes directory below
    """OUT.parts records the settings its chunks were made with: resuming with --fit-weights on chunks rendered
    without it would mix fitted and unfitted rows, so it is a one-line error; the same settings resume."""
    src = _test_subject(tiny_trained_run)
    out = tmp_path / "o.h5"
    args = [str(tiny_trained_run), str(src), str(out), "--gazes", "grid:1x2:10", "--rows", "2", "--batch", "1"]

    interrupt_redirect_before_assembly(args, monkeypatch)
    capsys.readouterr()  # the interrupted run's progress bar
    parts = tmp_path / "o.h5.parts"
    assert (parts / "settings.json").is_file() and len(list(parts.glob("part_*.npz"))) == 2 and not out.exists()
    assert run_cli(redirect.main, args + ["--fit-weights"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "holds chunks of a run with other settings (" in err[0]
    assert "fit_weights" in err[0].split("(")[1].split(")")[0]
    assert not out.exists()
    # The same settings spelt otherwise resume: the dataset by another path, the run's DDIM steps given
    # explicitly, a --seed that grid gazes do not use.
    import os

    os.chdir(src.parent)
    same = [str(tiny_trained_run), src.name, str(out), "--gazes", "grid:1x2:10", "--rows", "2", "--batch", "1",
            "--steps", str(TrainedRun.open(tiny_trained_run).config.gaussian.sampling_steps), "--seed", "7"]
    assert redirect.main(same) == 0 and out.is_file() and not parts.exists()
    # Settings with no chunk yet (stopped before the first) are replaced, not held against the next run.
    parts.mkdir()
    redirect_parts.check_parts_settings(parts, {"anything": 1})
    out.unlink()
    assert redirect.main(args + ["--fit-weights", "--fit-steps", "1"]) == 0 and out.is_file()


def test_gaze_term_takes_the_target_gazes_in_turn(tiny_trained_run):
    """With ``batch["target_gazes"]`` [B, G, 2] the k-th gaze term of the fit reads gaze k mod G (every entry
    counted, the last fitting step included)."""
    from train.data.dataset import GazeDataset
    from train.evaluation.fitting import FitGaze, test_time_fit

    ctx = TrainedRun.open(tiny_trained_run)
    model, renderer = ctx.load_model(torch.device("cpu"))
    it = GazeDataset([_test_subject(tiny_trained_run)], res=64)[0]
    t = lambda k: torch.as_tensor(it[k]).float()[None]  # noqa: E731
    gazes = torch.tensor([[[0.1, 0.2], [-0.3, 0.0], [0.0, 0.4]]])
    read = []

    class Recording(FitGaze):
        def term(self, model, renderer, batch, *a, **k):
            read.append(batch["gaze_head"].clone())
            return super().term(model, renderer, batch, *a, **k)

    from train.losses import GazeLoss

    gaze = Recording(GazeLoss(ctx.estimator("loss", "cpu")), 0.01, ("target",), every=2)
    batch = {"code": t("latent_code"), "in_pose": t("pose"), "in_gaze_head": t("pitchyaw_head"),
             "in_viewmat": t("viewmat"), "K": t("K"), "landmarks": t("landmarks"), "in_head_mask": t("head_mask"),
             "gaze_head": gazes[:, 0], "target_gazes": gazes}
    with torch.enable_grad():
        code = test_time_fit(model, renderer, batch, t("image"), t("head_mask"), 64, 7, gaze=gaze)
    assert torch.isfinite(code).all()
    # 7 steps, every 2nd counted from the last: steps 0, 2, 4, 6 -> gazes 0, 1, 2, 0.
    assert len(read) == 4
    for k, g in enumerate(read):
        assert torch.equal(g, gazes[:, k % 3])


@pytest.mark.parametrize("case", ["no_gaze", "no_steps"])
def test_fit_weights_bad_input_is_one_line_error(tiny_trained_run, tmp_path, capsys, case):
    src = _test_subject(tiny_trained_run)
    if case == "no_gaze":  # a CSV row without its own gaze cannot be fitted at it
        import cv2

        with h5py.File(src) as f:
            cv2.imwrite(str(tmp_path / "a.png"), f["face_patch"][0])
            np.save(tmp_path / "c.npy", f["latent_codes"][0])
        (tmp_path / "labels.csv").write_text("image,head_pitch,head_yaw,gaze_pitch,gaze_yaw,code\n"
                                             "a.png,0,0,,,c.npy\n")
        dataset, extra, expect = str(tmp_path / "labels.csv"), [], "line 2: --fit-weights fits the image at its own gaze"
    else:
        dataset, extra, expect = str(src), ["--fit-steps", "0"], "--fit-weights needs --fit-steps >= 1"
    code = run_cli(redirect.main, [str(tiny_trained_run), dataset, str(tmp_path / "o.h5"), "--fit-weights", *extra])
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2 and len(err) == 1 and expect in err[0]
    assert not (tmp_path / "o.h5").exists()


@pytest.mark.skipif(not torch.distributed.is_available() or not torch.distributed.is_gloo_available(),
                    reason="torch.distributed/gloo unavailable")
def test_redirect_sharded_over_two_torchrun_processes_writes_what_one_process_writes(tiny_trained_run, tmp_path):
    """torchrun with 2 CPU processes: each renders its chunks, rank 0 assembles one file equal to one process's.
    The rows are fitted: the fit draws the diffusion renderer's noise, from each chunk's own stream."""
    import os
    import subprocess
    import sys
    from pathlib import Path

    root = Path(__file__).resolve().parents[2]
    src = _test_subject(tiny_trained_run)
    outs = {}
    for name, launcher in (("one", [sys.executable]),
                           ("two", [sys.executable, "-m", "torch.distributed.run", "--standalone", "--nproc_per_node=2"])):
        outs[name] = tmp_path / f"{name}.h5"
        cmd = [*launcher, "-m", "apps.redirect", str(tiny_trained_run), str(src), str(outs[name]),
               "--gazes", "grid:1x2:20", "--rows", "5", "--batch", "2",  # 3 chunks: rank 0 renders two, rank 1 one
               "--fit-weights", "--fit-steps", "2"]
        env = {**os.environ, "OMP_NUM_THREADS": "1"}
        r = subprocess.run(cmd, cwd=root, capture_output=True, text=True, timeout=300, env=env)
        if r.returncode != 0 and "terminate called without an active exception" in r.stderr:
            r = subprocess.run(cmd, cwd=root, capture_output=True, text=True, timeout=300, env=env)  # gloo teardown race
        assert r.returncode == 0, r.stderr[-3000:]
    assert not (tmp_path / "two.h5.parts").exists()  # the chunks were assembled and removed
    with h5py.File(outs["one"]) as a, h5py.File(outs["two"]) as b:
        assert a["face_patch"].shape == b["face_patch"].shape == (10, 64, 64, 3)
        for key in a:
            if isinstance(a[key], h5py.Dataset):
                assert np.array_equal(a[key][:], b[key][:]), key


def test_output_that_is_a_folder_fails_before_any_rendering(tiny_trained_run, tmp_path, capsys):
    src = _test_subject(tiny_trained_run)
    (tmp_path / "o.h5").mkdir()
    code = run_cli(redirect.main, [str(tiny_trained_run), str(src), str(tmp_path / "o.h5")])
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2 and len(err) == 1 and "o.h5: is a directory, expected the path of the HDF5 file" in err[0]
    assert not (tmp_path / "o.h5.parts").exists()  # nothing was rendered


@pytest.mark.parametrize("extra, expect", [
    (["--gazes", "grid:0x5:30"], "a grid needs at least 1 row and 1 column, got 0x5"),
    (["--rows", "-1"], "--rows: expected a row count (0 = all rows) in [0, 1000000000], got -1"),
    (["--steps", "-5"], "--steps: expected DDIM steps (0 = the run's setting) in [0, 100000], got -5"),
    (["--steps", "5000"], "--steps must be 0 (the run's setting) or 1..1000 DDIM steps, got 5000"),
    (["--out-name", "x.png"], "x.png: expected an HDF5 file name ending in .h5 or .hdf5"),
    (["--gazes", "random:5:nan"], "expected a range in [0, 90) degrees, got nan"),
    (["--gazes", "grid:3x3:inf"], "expected a range in [0, 90) degrees, got inf"),
    (["--gazes", "random:5:-10"], "expected a range in [0, 90) degrees, got -10"),
    (["--gazes", "random:0:10"], "expected 1..100000 random gazes per input row, got 0"),
    (["--gazes", "grid:1000x1000:10"], "1000000 gazes; at most 100000 per input row"),
    (["--seed", "-1"], "--seed must be in [0, 2^32), got -1"),
    (["--seed", "20000000000000"], "--seed must be in [0, 2^32), got 20000000000000"),
    (["--fit-lr", "inf"], "--fit-lr must be in (0, 1], got inf"),
    (["--fit-lr", "0"], "--fit-lr must be in (0, 1], got 0.0"),
])
def test_bad_flags_fail_before_any_rendering(tiny_trained_run, tmp_path, capsys, extra, expect):
    src = _test_subject(tiny_trained_run)
    out = tmp_path / "o.h5"
    if extra[0] == "--out-name":
        out, extra = tmp_path / extra[1], []
    code = run_cli(redirect.main, [str(tiny_trained_run), str(src), str(out), *extra])
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2 and len(err) == 1 and expect in err[0], err
    assert not out.exists() and not out.with_suffix(out.suffix + ".parts").exists()


def test_output_that_is_the_input_dataset_is_refused(tiny_trained_run, tmp_path, capsys):
    src = tmp_path / "in.h5"
    src.write_bytes(_test_subject(tiny_trained_run).read_bytes())
    before = src.read_bytes()
    code = run_cli(redirect.main, [str(tiny_trained_run), str(src), str(tmp_path / "." / "in.h5")])
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2 and len(err) == 1 and "is the input dataset" in err[0], err
    assert src.read_bytes() == before and not (tmp_path / "in.h5.parts").exists()


def test_output_that_is_a_subject_of_the_input_folder_is_refused(tiny_trained_run, tmp_path, capsys):
    folder = tmp_path / "subjects"
    folder.mkdir()
    subject = folder / "subject0009.h5"
    subject.write_bytes(_test_subject(tiny_trained_run).read_bytes())
    before = subject.read_bytes()
    code = run_cli(redirect.main, [str(tiny_trained_run), str(folder), str(subject)])
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2 and len(err) == 1 and "is the input dataset" in err[0], err
    assert subject.read_bytes() == before and not (folder / "subject0009.h5.parts").exists()


def test_a_replaced_input_file_is_not_resumed(tiny_trained_run, tmp_path, capsys, monkeypatch):
    """The chunks are tied to the input's contents, not only its path: a file replaced under the same name
    between two runs would otherwise mix two subjects' rows in one output."""
    subjects = sorted((tiny_trained_run / "data").glob("*.h5"))
    src = tmp_path / "in.h5"
    src.write_bytes(subjects[-1].read_bytes())
    out = tmp_path / "o.h5"
    args = [str(tiny_trained_run), str(src), str(out), "--gazes", "grid:1x1:0", "--rows", "2", "--batch", "1"]
    interrupt_redirect_before_assembly(args, monkeypatch)
    capsys.readouterr()
    (tmp_path / "o.h5.parts" / "part_00001.npz").unlink()
    src.write_bytes(subjects[0].read_bytes())
    assert run_cli(redirect.main, args) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "other settings (input_stamp differ)" in err[0], err
    assert not out.exists()


def test_a_long_gaze_list_renders_in_slices_with_the_images_of_one_pass(tiny_trained_run, monkeypatch):
    """More gazes than RENDER_BATCH are rendered a slice at a time, each image as the whole list in one
    forward pass renders it (a diffusion renderer's noise is drawn for all of them first)."""
    model, renderer = TrainedRun.open(tiny_trained_run).load_model(torch.device("cpu"))
    ds_item = __import__("train.data.dataset", fromlist=["GazeDataset"]).GazeDataset(
        [_test_subject(tiny_trained_run)], res=TrainedRun.open(tiny_trained_run).config.data.res, with_mesh=True)[0]
    res = TrainedRun.open(tiny_trained_run).config.data.res
    gazes = redirect.parse_gazes("random:7:30", seed=3)
    whole = redirect.render_chunk(model, renderer, [ds_item], [0], gazes, res, 2, torch.device("cpu"))
    from apps import redirect_render

    monkeypatch.setattr(redirect_render, "RENDER_BATCH", 3)
    sliced = redirect.render_chunk(model, renderer, [ds_item], [0], gazes, res, 2, torch.device("cpu"))
    assert whole["face_patch"].shape[0] == 7
    assert np.abs(whole["face_patch"].astype(int) - sliced["face_patch"].astype(int)).max() <= 1


def test_gazes_file_with_a_header_names_the_file(tmp_path):
    f = tmp_path / "g.csv"
    f.write_text("pitch,yaw\n10,20\n")
    with pytest.raises(ToolkitError, match=r"--gazes file .*g\.csv: expected lines of 'pitch,yaw' in degrees"):
        redirect.parse_gazes(f"file:{f}")
    f.write_text("# only a comment\n")
    with pytest.raises(ToolkitError, match=r"--gazes file .*g\.csv: no gazes in the file"):
        redirect.parse_gazes(f"file:{f}")
    f.write_text("# pitch,yaw\n10,20\n-5,0\n")
    assert np.allclose(np.degrees(redirect.parse_gazes(f"file:{f}")), [[10, 20], [-5, 0]], atol=1e-4)


def test_chunks_without_their_settings_are_refused(tmp_path):
    """A clean-up cut short after settings.json went would leave chunks no run could vouch for: refused, never
    adopted by whatever settings come next."""
    parts = tmp_path / "o.h5.parts"
    parts.mkdir()
    np.savez(parts / "part_00000.npz", face_patch=np.zeros((1, 4, 4, 3), np.uint8))
    with pytest.raises(ToolkitError, match="holds chunks but no settings.json"):
        redirect_parts.check_parts_settings(parts, {"anything": 1})
    assert not (parts / "settings.json").exists()
    # Settings an older version wrote lack a key no flag can now match: say so, not "rerun with the same".
    (parts / "settings.json").write_text('{"anything": 1}')
    with pytest.raises(ToolkitError, match=r"from another version of apps.redirect \(settings version 1, this one "
                                           rf"writes {redirect_parts.SETTINGS_VERSION}\); delete"):
        redirect_parts.check_parts_settings(parts, {"anything": 1, "version": redirect_parts.SETTINGS_VERSION})


_FAILING_RANK = """
import os, sys
sys.path.insert(0, {root!r})
from apps import redirect
from toolkit.errors import ToolkitError, run_cli
real = redirect.render_chunk
def render_chunk(*a, **k):
    if os.environ["RANK"] == "1":
        raise ToolkitError("rank 1 failed on purpose")
    return real(*a, **k)
redirect.render_chunk = render_chunk
sys.exit(run_cli(redirect.main, sys.argv[1:]))
"""


def test_a_failing_process_stops_its_torchrun_peers_instead_of_leaving_them_waiting(tiny_trained_run, tmp_path):
    import os
    import subprocess
    import sys
    from pathlib import Path

    root = Path(__file__).resolve().parents[2]
    script = tmp_path / "failing_rank.py"
    script.write_text(_FAILING_RANK.format(root=str(root)))
    out = tmp_path / "o.h5"
    cmd = [sys.executable, "-m", "torch.distributed.run", "--standalone", "--nproc_per_node=2", str(script),
           str(tiny_trained_run), str(_test_subject(tiny_trained_run)), str(out), "--gazes", "grid:1x2:20",
           "--rows", "4", "--batch", "2"]
    # Without the agreement torchrun's agent kills rank 0 when rank 1 exits (under other launchers it would wait at
    # the barrier): with it, rank 0 stops on its own, says why and keeps its finished chunk.
    r = subprocess.run(cmd, cwd=root, capture_output=True, text=True, timeout=240,
                       env={**os.environ, "OMP_NUM_THREADS": "1"})
    assert r.returncode != 0 and not out.exists()
    assert "error: rank 1 failed on purpose" in r.stderr
    assert "error: redirect: another process failed" in r.stderr and "rerun the same command to resume" in r.stderr
    assert (tmp_path / "o.h5.parts" / "part_00000.npz").is_file()  # rank 0's chunk is kept for the rerun


def test_assembly_streams_the_chunks_into_one_file_with_sensible_hdf5_chunks(tmp_path):
    parts = tmp_path / "o.h5.parts"
    parts.mkdir()
    rng = np.random.default_rng(0)
    chunks = [{"face_patch": rng.integers(0, 255, (n, 8, 8, 3), dtype=np.uint8),
               "pitchyaw_head": rng.normal(size=(n, 2)).astype(np.float32), "scale": np.ones((n, 1), np.float32)}
              for n in (1, 3, 2)]
    for k, c in enumerate(chunks):
        np.savez(parts / f"part_{k:05d}.npz", **c)
    assert redirect_parts.assemble(parts, 3, tmp_path / "o.h5", {"generator": "test"}) == 6
    with h5py.File(tmp_path / "o.h5") as h:
        for key in chunks[0]:
            np.testing.assert_array_equal(h[key][:], np.concatenate([c[key] for c in chunks]))
            assert h[key].dtype == chunks[0][key].dtype
        assert h["face_patch"].chunks == (1, 8, 8, 3) and h["face_patch"].compression == "lzf"
        assert h["scale"].chunks[0] == 4096 and h["scale"].compression is None  # not 1 row per chunk
        assert h.attrs["generator"] == "test"
