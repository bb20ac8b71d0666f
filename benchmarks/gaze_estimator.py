"""Gaze estimator: held-out gaze error against training time, per estimator design (and inference speed).

Training images come from ``train.data.generate.estimator_images`` (procedural subjects, many random gazes,
two random rig cameras per gaze, 128² normalized face crops); the held-out subjects are disjoint seeds.
``--data DIR`` evaluates on the held-out split of a dataset written by ``python -m train.data synth`` instead.
Designs (``--modes``): ``eyes`` (eye patches cut at the landmarks + landmark layout; the default of the
estimator stage) and ``face`` (the whole face crop). Prints the run-time-against-error table, the held-out
error binned by how far the head is turned from the camera and (procedural test subjects) by how much iris
the better-seen eye shows, the inference throughput, and writes
``out/benchmarks/gaze_estimator.png``. ``--save DIR`` writes each trained estimator as ``<mode>.safetensors``.
``--cache DIR`` keeps the rendered procedural sets as safetensors, so several runs (in parallel on one GPU,
say) render them once.
``--budget-s`` sets the step count from a short timed probe instead of ``--steps``: the cosine schedule needs
its length up front, and a run sharing a device cannot know its step time in advance.

    .venv/bin/python benchmarks/gaze_estimator.py --subjects 32 --frames 120 --steps 3000
"""

from __future__ import annotations

import argparse
import dataclasses
import os
import sys
import time
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from benchmarks.common import (  # noqa: E402
    OUT_DIR,
    check_device,
    count,
    format_table,
    machine_info,
    positive,
    save_plot,
    timeit,
)
from toolkit.errors import CliParser, ToolkitError, run_cli  # noqa: E402
from toolkit.io import check_output_folder, load_tensors, save_tensors  # noqa: E402
from toolkit.rotations import angular_error_deg  # noqa: E402
from train.estimator.config import GazeEstimatorConfig, GazeEstimatorTrainConfig, eye_config  # noqa: E402
from train.estimator.network import GazeEstimator  # noqa: E402
from train.estimator.training import evaluate_gaze_estimator, train_gaze_estimator  # noqa: E402

TRAIN_SEEDS, TEST_SEEDS = 200_000, 300_000  # disjoint subject-seed ranges
SET_KEYS = ("images", "labels", "landmarks", "iris")  # estimator_images' outputs, in order (iris optional)


def load_split(data: str, split: str) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """A dataset split as uint8 images [N, 3, R, R], labels [N, 4] (camera-frame gaze, head) and landmarks."""
    from train.data.dataset import GazeDataset

    ds = GazeDataset(data, split=split)
    imgs, labels, lms = [], [], []
    for i in range(len(ds)):
        s = ds[i]
        imgs.append((s["image"] * 255).round().to(torch.uint8))
        labels.append(torch.cat([s["pitchyaw_cam"], s["face_head_pose"]]))
        lms.append(s["landmarks"])
    ds.close()
    if not imgs:
        raise ToolkitError(f"{data}: split {split!r} is empty")
    return torch.stack(imgs), torch.stack(labels), torch.stack(lms)


@torch.no_grad()
def predict(model, images: torch.Tensor, landmarks: torch.Tensor) -> torch.Tensor:
    """[N, 4] predictions on the CPU; batches move to the model's device."""
    dev = next(model.parameters()).device
    return torch.cat([model(images[i:i + 256].to(dev).float() / 255, landmarks[i:i + 256].to(dev)).cpu()
                      for i in range(0, len(images), 256)])


def procedural_set(seeds: range, *, n_frames: int, seed: int, res: int, workers: int, iris: bool,
                   cache: str | None) -> list[torch.Tensor]:
    """``estimator_images`` for these subjects, read from / written to ``cache`` when given (one
    safetensors file per argument set; the images do not depend on ``workers``)."""
    from train.data.generate import estimator_images

    path = None
    if cache:
        path = Path(cache) / f"estimator_{seeds.start}_{len(seeds)}x{n_frames}_seed{seed}_{res}px.safetensors"
        if path.exists():
            tensors, _ = load_tensors(path)
            return [tensors[k] for k in SET_KEYS[:3 + iris]]
    out = list(estimator_images(seeds, n_frames=n_frames, seed=seed, res=res, iris_pixels=iris, workers=workers))
    if path is not None:
        path.parent.mkdir(parents=True, exist_ok=True)
        save_tensors(path, dict(zip(SET_KEYS, out)))
    return out


def probe_step_s(train: list[torch.Tensor], cfg: GazeEstimatorConfig, tc: GazeEstimatorTrainConfig, device: str,
                 steps: int = 40, skip: int = 10, init=None) -> float:
    """Seconds per training step of this design, timed over steps ``skip``..``steps`` of a throwaway run (the
    first steps pay for allocation and cuDNN's algorithm search)."""
    stamps = []

    def stamp(step, rec):
        if step in (skip, steps):
            if device.startswith("cuda"):
                torch.cuda.synchronize()
            stamps.append(time.perf_counter())

    probe = dataclasses.replace(tc, steps=steps, log_every=1)
    train_gaze_estimator(train[0], train[1], cfg, probe, landmarks=train[2], device=device, init=init,
                         callback=stamp)
    return (stamps[1] - stamps[0]) / (steps - skip)


def _error_rows(err: torch.Tensor, values: torch.Tensor, edges, name: str, label, share: bool = False) -> list[dict]:
    """One row per non-empty bin [lo, hi) of ``values`` (lo starting at 0): image count, mean and median of
    ``err`` (and with ``share`` the bin's share of the summed error); ``label(lo, hi)`` names the bin in
    column ``name``."""
    rows, lo = [], 0
    for hi in edges:
        m = (values >= lo) & (values < hi)
        if bool(m.any()):
            row = {name: label(lo, hi), "images": int(m.sum()), "mean_gaze_err_deg": float(err[m].mean()),
                   "median_gaze_err_deg": float(err[m].median())}
            if share:
                row["share_of_mean"] = float(err[m].sum() / err.sum())
            rows.append(row)
        lo = hi
    return rows


def error_by_view(pred: torch.Tensor, labels: torch.Tensor, edges=(20, 40, 60, 90)) -> list[dict]:
    """Held-out gaze error binned by the head's angle from the camera axis (one eye hides far off-axis)."""
    err = angular_error_deg(pred[:, :2], labels[:, :2].float())
    off = angular_error_deg(labels[:, 2:].float(), torch.zeros_like(labels[:, 2:]).float())
    rows = _error_rows(err, off, edges, "head_off_axis_deg", lambda lo, hi: f"[{lo:g}, {hi:g})")
    rows.append({"head_off_axis_deg": "all", "images": len(err), "mean_gaze_err_deg": float(err.mean()),
                 "median_gaze_err_deg": float(err.median())})
    return rows


def error_by_iris(pred: torch.Tensor, labels: torch.Tensor, iris: torch.Tensor, edges=(1, 10, 10**9)) -> list[dict]:
    """Held-out gaze error binned by the visible iris pixels of the better-seen eye ([N, 2] counts): with no
    iris in view the gaze cannot be read from the eyes at all."""
    err = angular_error_deg(pred[:, :2], labels[:, :2].float())
    return _error_rows(err, iris.max(1).values, edges, "iris_px_best_eye",
                       lambda lo, hi: f"[{lo}, {hi})" if hi < 10**9 else f">= {lo}", share=True)


def _parser() -> argparse.ArgumentParser:
    ap = CliParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--subjects", type=count("--subjects", 1), default=32, help="procedural training subjects")
    ap.add_argument("--frames", type=count("--frames", 1), default=120, help="random gazes per training subject (2 cameras each)")
    ap.add_argument("--test-subjects", type=count("--test-subjects", 1), default=8)
    ap.add_argument("--data", help="evaluate on this dataset's held-out split instead of procedural test subjects")
    ap.add_argument("--modes", default="eyes,face")
    ap.add_argument("--steps", type=count("--steps", 1), default=3000)
    ap.add_argument("--budget-s", type=positive("--budget-s"), help="training seconds per mode: the steps follow from a timed "
                    "probe (overrides --steps)")
    ap.add_argument("--batch", type=count("--batch", 1), default=64)
    ap.add_argument("--channels", help="comma list of stride-2 stage widths (default: the design's own)")
    ap.add_argument("--lr", type=positive("--lr"), default=2e-3)
    ap.add_argument("--warmup-steps", type=count("--warmup-steps", 0), default=0,
                    help="linear learning-rate warm-up steps before the cosine decay (0: none)")
    ap.add_argument("--input-size", type=count("--input-size", 1), default=64, help="face mode: input width")
    ap.add_argument("--res", type=count("--res", 1), default=128, help="face-crop size of the rendered images (eyes mode: "
                    "train.estimator.config.eye_config(res), the estimator stage's design at that size)")
    ap.add_argument("--landmark-noise", type=float, default=GazeEstimatorTrainConfig.landmark_noise,
                    help="training jitter of the landmarks, pixels")
    ap.add_argument("--mirror", type=float, default=GazeEstimatorTrainConfig.mirror,
                    help="probability of mirroring a training sample left-right")
    ap.add_argument("--camera-frame", action="store_true",
                    help="regress the camera-frame gaze directly (default: head-frame gaze + head pose, composed)")
    ap.add_argument("--no-mirror-average", action="store_true",
                    help="predict from the image alone (default: average with its mirror)")
    ap.add_argument("--log-every", type=count("--log-every", 1), default=250)
    ap.add_argument("--threads", type=count("--threads", 0), default=1, help="torch threads (0: torch default)")
    ap.add_argument("--save", help="folder for <mode>.safetensors")
    ap.add_argument("--cache", help="folder keeping the rendered procedural sets between runs")
    ap.add_argument("--init", help="fine-tune this saved estimator (its design replaces --modes, --camera-frame, "
                    "--channels and --no-mirror-average; the rate schedule starts afresh)")
    ap.add_argument("--device", default="cuda" if torch.cuda.is_available() else "cpu",
                    help="where the estimators train and run (default: cuda when available)")
    ap.add_argument("--workers", type=count("--workers", 1), default=os.cpu_count() or 1,
                    help="processes rendering the procedural subjects (the images do not depend on it)")
    return ap


def _modes_and_channels(a: argparse.Namespace) -> tuple[list[str], tuple[int, ...] | None]:
    """The designs to train (``--modes``) and the ``--channels`` override (None: each design's own)."""
    modes = [m for m in a.modes.split(",") if m]
    if not modes or set(modes) - {"eyes", "face"}:
        raise ToolkitError(f"--modes: expected a comma list of eyes, face; got {a.modes!r}")
    try:
        channels = tuple(int(c) for c in a.channels.split(",")) if a.channels else None
    except ValueError:
        raise ToolkitError(f"--channels: expected a comma list of integers, got {a.channels!r}") from None
    if channels is not None and (not channels or min(channels) < 1):
        raise ToolkitError(f"--channels: expected positive widths, got {a.channels!r}")
    if a.budget_s is not None and a.budget_s <= 0:
        raise ToolkitError(f"--budget-s: expected a positive number of seconds, got {a.budget_s}")
    return modes, channels


def _check_flags(a: argparse.Namespace) -> None:
    """The flags the training reads only after the sets are rendered, and the folders written only after it:
    checked first, so a typo costs neither the rendering nor a trained model."""
    # The trainer's own checks (GazeEstimatorTrainConfig.validate) run after the sets are made, and a NaN jitter
    # passes them and poisons the first step's loss instead.
    if not 0.0 <= a.mirror <= 1.0:  # NaN fails too
        raise ToolkitError(f"--mirror: expected a probability in [0, 1], got {a.mirror}")
    if not 0.0 <= a.landmark_noise <= a.res:  # a jitter beyond the crop moves the eye patches off the image
        raise ToolkitError(f"--landmark-noise: expected a jitter in [0, {a.res}] pixels (--res), got {a.landmark_noise}")
    for flag, folder in (("--save", a.save), ("--cache", a.cache)):
        if folder is not None:
            if not folder.strip():  # an empty path is the current folder
                raise ToolkitError(f"{flag}: expected a folder, got an empty path")
            check_output_folder(folder, flag)


def _datasets(a: argparse.Namespace, data_test):
    """(training set, test set, a description of the test set's source, the test images' visible iris pixels
    or None), the training set on ``--device``; ``data_test``: ``--data``'s held-out split, read already."""
    t0 = time.perf_counter()
    train = procedural_set(range(TRAIN_SEEDS, TRAIN_SEEDS + a.subjects), n_frames=a.frames, seed=0, res=a.res,
                           workers=a.workers, iris=False, cache=a.cache)
    if data_test is not None:
        test, source, iris = data_test, f"held-out split of {a.data}", None
    else:
        *test, iris = procedural_set(range(TEST_SEEDS, TEST_SEEDS + a.test_subjects), n_frames=30, seed=1,
                                     res=a.res, workers=a.workers, iris=True, cache=a.cache)
        source = f"{a.test_subjects} held-out procedural subjects"
    print(f"data: {len(train[0])} training images ({a.subjects} subjects x {a.frames} gazes x 2 cameras), "
          f"{len(test[0])} test images ({source}), {train[0].shape[-1]}px, made in {time.perf_counter() - t0:.0f} s")
    # The training set lives where the models train (uint8: 7680 images at 256² are 1.5 GB), copied there once for
    # every mode, so a GPU step gathers its batch on the GPU instead of copying it from host memory.
    return [t.to(a.device) for t in train], test, source, iris


def _design(a: argparse.Namespace, mode: str, init, channels: tuple[int, ...] | None) -> GazeEstimatorConfig:
    """The estimator design of ``mode`` with the command line's overrides (``--init``'s own design when given)."""
    if init is not None:
        return init.config
    cfg = eye_config(a.res) if mode == "eyes" else GazeEstimatorConfig(input_size=a.input_size)
    cfg = dataclasses.replace(cfg, mirror_average=not a.no_mirror_average, head_frame=not a.camera_frame)
    if channels is not None:
        cfg = dataclasses.replace(cfg, channels=channels)
    return cfg


def _train_mode(a: argparse.Namespace, mode: str, cfg: GazeEstimatorConfig, train, test, init):
    """Train one design, printing each held-out evaluation: (model, its training config, history, and the
    training seconds at each history record, the held-out evaluations left out)."""
    tc = GazeEstimatorTrainConfig(steps=a.steps, batch_size=a.batch, lr=a.lr, log_every=a.log_every,
                                  landmark_noise=a.landmark_noise, mirror=a.mirror, warmup_steps=a.warmup_steps)
    if a.budget_s is not None:
        step_s = probe_step_s(train, cfg, tc, a.device, init=init)
        tc = dataclasses.replace(tc, steps=max(1, int(a.budget_s / step_s)))
        print(f"{mode}: {1e3 * step_s:.1f} ms per step (probe) -> {tc.steps} steps in {a.budget_s:g} s", flush=True)
    start, stamps, eval_s = time.perf_counter(), [], [0.0]

    def progress(step, rec):
        eval_s[0] += rec["val_s"]  # training time: the trainer's held-out evaluations left out
        stamps.append(time.perf_counter() - start - eval_s[0])
        print(f"  {mode} step {step}: {stamps[-1]:.0f} s, loss {rec['loss']:.4f}, held-out gaze "
              f"{rec['val_gaze_deg']:.2f} deg, head {rec['val_head_deg']:.2f} deg", flush=True)

    if init is not None:
        print(f"{mode}: starting from {a.init}: held-out gaze "
              f"{evaluate_gaze_estimator(init.to(a.device), *test, device=a.device)['val_gaze_deg']:.2f} deg",
              flush=True)
    model, hist = train_gaze_estimator(train[0], train[1], cfg, tc, landmarks=train[2], val=test,
                                       callback=progress, device=a.device, init=init)
    return model, tc, hist, stamps


def _report_mode(a: argparse.Namespace, mode: str, model, hist: list[dict], test, iris) -> None:
    """Print a trained design's held-out error by view (and by visible iris) and its inference throughput."""
    pred = predict(model, test[0], test[2])
    print(format_table(error_by_view(pred, test[1])))
    if iris is not None:
        print(format_table(error_by_iris(pred, test[1], iris)))
    x, lm = test[0][: a.batch].to(a.device).float() / 255, test[2][: a.batch].to(a.device)
    with torch.no_grad():
        sec = timeit(lambda: model(x, lm), repeats=5, sync_cuda=x.is_cuda)
    print(f"{mode}: held-out gaze {hist[-1]['val_gaze_deg']:.2f} deg, head {hist[-1]['val_head_deg']:.2f} deg; "
          f"inference {len(x) / sec:.0f} images/s (batch {len(x)}, {a.device}, {torch.get_num_threads()} threads)")


def main(argv=None) -> int:
    a = _parser().parse_args(argv)
    if a.threads:
        torch.set_num_threads(a.threads)
    check_device(a.device)
    torch.backends.cudnn.benchmark = True  # fixed input shapes: let cuDNN pick its fastest convolutions once
    init = None
    if a.init:
        init = GazeEstimator.load(a.init, frozen=False)
        a.modes = "eyes" if init.config.eyes else "face"
    modes, channels = _modes_and_channels(a)
    _check_flags(a)
    # --data's held-out split is read before the training set is rendered: a wrong --data costs no rendering.
    data_test = None
    if a.data:
        try:
            data_test = load_split(a.data, "test")
        except ToolkitError as e:  # the dataset's message names its file, not the flag that chose it
            raise ToolkitError(f"--data: {e}") from None
    print(machine_info())
    train, test, source, iris = _datasets(a, data_test)
    rows, series = [], {}
    for mode in modes:
        model, tc, hist, stamps = _train_mode(a, mode, _design(a, mode, init, channels), train, test, init)
        for rec, t in zip(hist, stamps):
            rows.append({"mode": mode, "step": rec["step"], "train_s": t, "loss": rec["loss"],
                         "heldout_gaze_deg": rec["val_gaze_deg"], "heldout_head_deg": rec["val_head_deg"]})
        series[mode] = (stamps, [r["val_gaze_deg"] for r in hist])
        if a.save:
            model.save(Path(a.save) / f"{mode}.safetensors",
                       {"steps": tc.steps, "data": source, "heldout_gaze_deg": hist[-1]["val_gaze_deg"]})
        _report_mode(a, mode, model, hist, test, iris)
    print(format_table(rows, ["mode", "step", "train_s", "loss", "heldout_gaze_deg", "heldout_head_deg"]))
    png = save_plot(OUT_DIR / "gaze_estimator.png", series, xlabel="training time (s)",
                    ylabel="held-out gaze error (deg)", title=f"gaze estimator, {source}", logy=True)
    print(f"plot: {png}")
    return 0


if __name__ == "__main__":
    np.set_printoptions(precision=3)
    sys.exit(run_cli(main))
