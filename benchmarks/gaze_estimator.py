"""Gaze estimator: held-out gaze error against training time (and inference speed).

Trains the compact CNN of ``train.gaze_estimator`` on the synthetic dataset (``--data DIR`` written by
``python -m train.data synth``; its split.json holds out whole subjects) or, without data, on drawn face
crops (``train.drawn_faces``, held-out subjects too). Prints a table of training time against held-out
gaze / head error, the inference throughput, and writes ``out/benchmarks/gaze_estimator.png``.
``--instances 2`` trains the two independent estimators the method needs (seeds differ): one for the gaze
loss, one for evaluation only; ``--save DIR`` writes them as ``loss.safetensors`` / ``eval.safetensors``.

    .venv/bin/python -m train.data synth --subjects 16 --frames 16 --res 128 --out data/synth
    .venv/bin/python benchmarks/gaze_estimator.py --data data/synth --steps 3000
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from benchmarks.common import OUT_DIR, format_table, machine_info, save_plot, timeit  # noqa: E402
from toolkit.errors import ToolkitError, run_cli  # noqa: E402
from train.gaze_estimator import (  # noqa: E402
    GazeEstimatorConfig,
    GazeEstimatorTrainConfig,
    evaluate_gaze_estimator,
    train_gaze_estimator,
)


def load_split(data: str, split: str, res: int) -> tuple[torch.Tensor, torch.Tensor]:
    """All images of a GazeDataset split as uint8 [N, 3, res, res] and labels [N, 4] (camera-frame gaze, head)."""
    from train.data.dataset import GazeDataset

    ds = GazeDataset(data, split=split, res=res)
    imgs, labels = [], []
    for i in range(len(ds)):
        s = ds[i]
        if "pitchyaw_cam" not in s:
            raise ToolkitError(f"{data}: sample {i} has no 'pitchyaw_cam' (camera-frame gaze label) to train on")
        imgs.append((s["image"] * 255).round().to(torch.uint8))
        labels.append(torch.cat([s["pitchyaw_cam"], s["face_head_pose"]]))
    ds.close()
    return torch.stack(imgs), torch.stack(labels)


def error_by_view(model, images: torch.Tensor, labels: torch.Tensor, edges=(20, 40, 60, 90, 180)) -> list[dict]:
    """Held-out gaze error binned by the gaze's angle from the camera axis (eyes turn invisible far off-axis)."""
    from toolkit.rotations import angular_error_deg

    with torch.no_grad():
        pred = torch.cat([model(images[i:i + 256].float() / (255 if images.dtype == torch.uint8 else 1))
                          for i in range(0, len(images), 256)])
    err = angular_error_deg(pred[:, :2], labels[:, :2].float())
    off = angular_error_deg(labels[:, :2].float(), torch.zeros_like(labels[:, :2]).float())
    rows, lo = [], 0.0
    for hi in edges:
        m = (off >= lo) & (off < hi)
        if bool(m.any()):
            rows.append({"gaze_off_axis_deg": f"[{lo:g}, {hi:g})", "images": int(m.sum()),
                         "mean_err_deg": float(err[m].mean()), "median_err_deg": float(err[m].median())})
        lo = hi
    rows.append({"gaze_off_axis_deg": "all", "images": len(err), "mean_err_deg": float(err.mean()),
                 "median_err_deg": float(err.median())})
    return rows


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--data", help="synthetic dataset folder (python -m train.data synth); default: drawn faces")
    ap.add_argument("--steps", type=int, default=2000)
    ap.add_argument("--batch", type=int, default=64)
    ap.add_argument("--lr", type=float, default=2e-3)
    ap.add_argument("--input-size", type=int, default=64)
    ap.add_argument("--channels", default="32,64,96,128")
    ap.add_argument("--instances", type=int, default=1)
    ap.add_argument("--loss-space", default="vectors", choices=["vectors", "angles"])
    ap.add_argument("--log-every", type=int, default=250)
    ap.add_argument("--threads", type=int, default=0, help="torch threads (0: torch default)")
    ap.add_argument("--save", help="folder for loss.safetensors / eval.safetensors")
    ap.add_argument("--drawn-train", type=int, default=6000)
    ap.add_argument("--eval-only", nargs="+", metavar="CKPT", help="only evaluate saved estimator checkpoint(s)")
    a = ap.parse_args(argv)
    if a.threads:
        torch.set_num_threads(a.threads)
    print(machine_info())
    t0 = time.perf_counter()
    if a.data:
        train = (torch.zeros(0, 3, 1, 1), torch.zeros(0, 4)) if a.eval_only else load_split(a.data, "train", a.input_size)
        test = load_split(a.data, "test", a.input_size)
        source = f"synthetic dataset {a.data}"
    else:
        from train.drawn_faces import drawn_face_dataset

        train = drawn_face_dataset(a.drawn_train, a.input_size, n_subjects=24, subjects=list(range(18)), seed=0)[:2]
        test = drawn_face_dataset(1000, a.input_size, n_subjects=24, subjects=list(range(18, 24)), seed=1)[:2]
        source = "drawn faces (18 train / 6 held-out subjects)"
    print(f"data: {source}: {len(train[0])} train / {len(test[0])} held-out images at {a.input_size}px "
          f"(loaded in {time.perf_counter() - t0:.1f} s)")
    if a.eval_only:
        from train.gaze_estimator import GazeEstimator

        for path in a.eval_only:
            print(f"{path}:")
            print(format_table(error_by_view(GazeEstimator.load(path), *test)))
        return 0
    cfg = GazeEstimatorConfig(input_size=a.input_size, channels=tuple(int(c) for c in a.channels.split(",")))
    names = ["loss", "eval"][: a.instances] if a.instances <= 2 else [f"est{i}" for i in range(a.instances)]
    rows, series = [], {}
    for k, name in enumerate(names):
        tc = GazeEstimatorTrainConfig(steps=a.steps, batch_size=a.batch, lr=a.lr, log_every=a.log_every, seed=k,
                                      loss_space=a.loss_space)
        start = time.perf_counter()
        stamps = []
        def progress(step, rec, st=stamps, t0=start, name=name):
            st.append(time.perf_counter() - t0)
            print(f"  {name} step {step}: {st[-1]:.0f} s, loss {rec['loss']:.4f}, held-out gaze "
                  f"{rec['val_gaze_deg']:.2f} deg, head {rec['val_head_deg']:.2f} deg", flush=True)

        model, hist = train_gaze_estimator(*train, cfg, tc, val=test, callback=progress)
        for rec, t in zip(hist, stamps):
            rows.append({"instance": name, "step": rec["step"], "train_s": t, "loss": rec["loss"],
                         "heldout_gaze_deg": rec["val_gaze_deg"], "heldout_head_deg": rec["val_head_deg"]})
        series[f"{name} (seed {k})"] = (stamps, [r["val_gaze_deg"] for r in hist])
        if a.save:
            model.save(Path(a.save) / f"{name}.safetensors",
                       {"seed": k, "steps": a.steps, "data": source, "heldout_gaze_deg": hist[-1]["val_gaze_deg"]})
        final = evaluate_gaze_estimator(model, *test)
        print(format_table(error_by_view(model, *test)))
        x = test[0][: a.batch].float() / 255
        with torch.no_grad():
            sec = timeit(lambda m=model, x=x: m(x), repeats=5)
        print(f"{name}: final held-out gaze {final['val_gaze_deg']:.2f} deg, head {final['val_head_deg']:.2f} deg; "
              f"inference {a.batch / sec:.0f} images/s (batch {a.batch})")
    print(format_table(rows, ["instance", "step", "train_s", "loss", "heldout_gaze_deg", "heldout_head_deg"]))
    png = save_plot(OUT_DIR / "gaze_estimator.png", series, xlabel="training time (s)",
                    ylabel="held-out gaze error (deg)", title=f"gaze estimator on {source}", logy=True)
    print(f"plot: {png}")
    return 0


if __name__ == "__main__":
    sys.exit(run_cli(main))
