"""GazeNeRF's protocol on real subject files: pairs from GazeNeRF's target list, each input fitted and rendered
at its stored target row's camera, head pose and gaze, and scored against that row's stored image; synthetic
files keep their generator targets. A "real" file here is a synthetic one without its ``subject_params``."""

from __future__ import annotations

import dataclasses

import pytest
import torch

from tests.train.helpers import one_frame_subject_file, untrained_eval_parts
from toolkit.errors import ToolkitError

# GazeNeRF's xgaze_evaluation_target_single_subject.txt scaled down to an 18-row file (its exact 100-integer
# form: tests/train/data/test_pairing.py): input row i -> target row TARGETS[i], a permutation of the second
# half, one integer a line as GazeNeRF's file holds them (datasets/eth_xgaze.py:280, :358-359).
TARGETS = [13, 9, 16, 11, 17, 10, 14, 12, 15]


@pytest.fixture(scope="module")
def files(tmp_path_factory):
    """(synthetic file subject0000.h5, its real-like copy subject0001.h5, the target list file): one frame seen
    by the rig's 18 cameras at 64²."""
    import shutil

    import h5py

    d = tmp_path_factory.mktemp("real")
    synthetic = one_frame_subject_file(d, subject_seed=5, frame_seed=2)
    real = d / "subject0001.h5"
    shutil.copy(synthetic, real)
    with h5py.File(real, "r+") as f:
        del f.attrs["subject_params"]
    targets = d / "xgaze_evaluation_target_single_subject.txt"
    targets.write_text("".join(f"{t}\n" for t in TARGETS))
    return synthetic, real, targets


def _first_rows(src, dst, n: int):
    """``src``'s first ``n`` rows as a real-like file ``dst``."""
    import h5py

    from train.data.format import OPTIONAL, REQUIRED, write_subject_h5

    with h5py.File(src, "r") as f:
        rows = {k: f[k][:n] for k in f if k in REQUIRED or k in OPTIONAL}
        subject = {k: f[k][()] for k in f if k not in rows}
        attrs = {k: v for k, v in f.attrs.items() if k not in ("subject_params", "format_version")}
    return write_subject_h5(dst, rows, subject=subject, attrs=attrs)


def _render_the_stored_row(files, seen: list):
    """A stand-in for ``render_pairs``: each pair's render is the stored image (as the dataset gives it) of the
    row whose camera the batch names -- a perfect render where the batch asks for the target's camera, the
    input's image where it asks for the input's. ``seen`` gets each batch."""
    from train.data.dataset import GazeDataset

    rows = [GazeDataset([files[1]], res=64)[i] for i in range(18)]

    def render(model, renderer, batch, res, steps):
        seen.append({k: v.detach().cpu().clone() for k, v in batch.items()})
        out = []
        for V in batch["viewmat"].cpu():
            (k,) = [i for i, r in enumerate(rows) if torch.equal(r["viewmat"], V)]  # 18 cameras, 18 views
            out.append(rows[k]["image"])
        return torch.stack(out).to(batch["code"].device)

    return rows, render


def test_a_real_file_is_scored_against_its_stored_targets_a_synthetic_one_against_the_generator(files, monkeypatch):
    import train.evaluation.protocol as protocol
    from train.data.pairing import load_pairing
    from train.evaluation.report import describe_protocol

    synthetic, real, targets = files
    seen: list = []
    rows, render = _render_the_stored_row(files, seen)
    monkeypatch.setattr(protocol, "render_pairs", render)
    model, renderer, est = untrained_eval_parts()
    out = protocol.evaluate(model, renderer, est, [synthetic, real], res=64, pairs_per_subject=3, tta_steps=1,
                            own_gaze_row=True, log=lambda s: None, pairing=load_pairing(targets))
    assert [r["protocol"] for r in out["per_subject"]] == ["synthetic", "stored"]
    # The pairs: spread over the list (0, 4, 8), input row i -> target row TARGETS[i].
    assert [(r["subject"], r["pair"]) for r in out["per_pair"]] == [(f.name, i) for f in (synthetic, real)
                                                                    for i in (0, 4, 8)]
    inputs, tgts = [0, 4, 8], [TARGETS[i] for i in (0, 4, 8)]
    at = lambda key, idx: torch.stack([rows[i][key] for i in idx])  # noqa: E731
    synth_batch, _, real_batch, real_own = seen  # the render and the own-gaze render of each subject
    # Synthetic: the target is the input's view re-rendered at the target gaze.
    torch.testing.assert_close(synth_batch["viewmat"], at("viewmat", inputs))
    # Real: the target row's camera, intrinsics, head pose and gaze; the fit and the own-gaze row the input's.
    for key, batch_key in (("viewmat", "viewmat"), ("K", "K"), ("pose", "pose"), ("pitchyaw_head", "gaze_head")):
        torch.testing.assert_close(real_batch[batch_key], at(key, tgts), rtol=0, atol=0)
    assert not torch.equal(at("viewmat", tgts), at("viewmat", inputs))  # the check can fail: other cameras
    for key in ("viewmat", "K", "pose"):
        torch.testing.assert_close(real_batch["in_" + key], at(key, inputs), rtol=0, atol=0)
    torch.testing.assert_close(real_own["viewmat"], at("viewmat", inputs))
    # Rendered at the target's camera, the stored target row is reproduced: scored against it, perfect.
    for r in out["per_pair"][3:]:
        assert r["psnr"] > 99 and r["ssim"] > 0.9999 and r["gaze_error_deg"] < 1e-2, r
    assert out["own_gaze"]["psnr"] > 99  # the own-gaze row: the input's camera gives the input's image
    # The synthetic pairs of this one-frame file share the input's gaze: their target is the input, redrawn.
    assert all(r["psnr"] > 30 for r in out["per_pair"][:3])
    assert describe_protocol(out["per_subject"], str(targets)) == (
        f"synthetic: generator targets, pairing file {targets} (1 subject); "
        f"GazeNeRF: stored targets, pairing file {targets} (1 subject)")


def test_the_real_protocol_fits_and_scores_with_the_real_renderer(files):
    """No stand-ins: the fit and the render on a real file, per pair with fitted weights; the report names the
    protocol."""
    from train.data.pairing import load_pairing
    from train.evaluation.protocol import evaluate
    from train.evaluation.report import report_markdown
    from train.presets import preset

    _, real, targets = files
    model, renderer, est = untrained_eval_parts()
    out = evaluate(model, renderer, est, [real], res=64, pairs_per_subject=2, tta_steps=1, tta_weights=("features",),
                   own_gaze_row=True, log=lambda s: None, pairing=load_pairing(targets))
    m = out["metrics"]
    assert m["pairs"] == 2 and 5 < m["psnr"] < 60 and 0 < m["ssim"] < 1 and 0 <= m["gaze_error_deg"] <= 180
    assert [r["pair"] for r in out["per_pair"]] == [0, 8] and out["per_subject"][0]["protocol"] == "stored"
    cfg = preset("tiny")
    cfg = dataclasses.replace(cfg, eval=dataclasses.replace(cfg.eval, pairing_file=str(targets)))
    report = report_markdown(out, cfg, targets.parent, {})
    assert f"Protocol: GazeNeRF: stored targets, pairing file {targets}. " in report
    default = report_markdown(out, preset("tiny"), targets.parent, {})
    assert "Protocol: GazeNeRF: stored targets, generated pairing (first half -> permuted second half). " in default


def test_pairs_outside_a_subjects_rows_stop_the_evaluation_before_any_work(files, tmp_path, monkeypatch):
    import train.evaluation.protocol as protocol
    from train.data.pairing import load_pairing
    from train.presets import preset
    from train.stages.checks import check_config, check_eval_pairing

    _, real, targets = files
    short = _first_rows(real, tmp_path / "subject0002.h5", 10)

    def no_work(*args, **kwargs):
        raise AssertionError("the evaluation started")

    monkeypatch.setattr(protocol, "test_time_fit", no_work)
    monkeypatch.setattr(protocol, "render_pairs", no_work)
    model, renderer, est = untrained_eval_parts()
    with pytest.raises(ToolkitError) as err:
        protocol.evaluate(model, renderer, est, [real, short], res=64, pairs_per_subject=3, tta_steps=1,
                          log=lambda s: None, pairing=load_pairing(targets))
    assert str(err.value) == (f"evaluate: {short}: pair 0 of the pairing (input row 0, target row 13) is out of "
                              f"range: the file has 10 rows (0-9); 8 of its 9 pairs are")
    # The run's checks: with data.root the held-out files are known before training (the config check), else
    # the eval stage checks them first; each names the pairing file.
    cfg = preset("tiny")
    cfg = dataclasses.replace(cfg, eval=dataclasses.replace(cfg.eval, pairing_file=str(targets)))
    with pytest.raises(ToolkitError, match=rf"^config key 'eval.pairing_file': {short}: pair 0 of the pairing file "
                                           rf"{targets} \(input row 0, target row 13\) is out of range: the file "
                                           r"has 10 rows \(0-9\); 8 of its 9 pairs are$"):
        check_eval_pairing(cfg, [real, short])
    _first_rows(real, tmp_path / "subject0001.h5", 18)  # subject0002.h5 is held out (the last quarter)
    with pytest.raises(ToolkitError, match=rf"^config key 'eval.pairing_file': {short}: pair 0 "):
        check_config(dataclasses.replace(cfg, data=dataclasses.replace(cfg.data, root=str(tmp_path))))
    # A real file too short for the generated pairing, and no pairing file: what to give.
    (tmp_path / "one").mkdir()
    one = _first_rows(real, tmp_path / "one" / "subject0003.h5", 1)
    with pytest.raises(ToolkitError, match=rf"^{one}: 1 row; the generated pairing \(the first half of the rows with "
                                           r"a permutation of the second half\) needs at least 2 rows: give "
                                           r"eval.pairing_file \(GazeNeRF's target list, or JSON pairs of this "
                                           r"file's rows\), or a file with more rows$"):
        check_eval_pairing(preset("tiny"), [one])
