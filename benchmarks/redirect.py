"""apps.redirect on a run's synthetic subjects (held out, or its training ones): seconds per redirected image
against its error, by fitting.

For a trained run, every held-out subject's rows (``--rows``, spread over the file; ``--split train``: every
training subject's instead, the faces the model was trained on, so its redirection of a face it knows: the
bound a fit of a new face approaches) are redirected to
``--gazes`` with ``apps.redirect.render_chunk`` -- the app's own rendering path -- once per ``--fit-steps``
value: 0 renders with the file's codes and the trained weights as they are (the app's default for HDF5
input); N > 0 first fits each row as the evaluation fits a pair (``TrainedRun.row_fitter``, the app's
``--fit-weights``: code, ``eval.tta_weights``, the loss estimator's gaze term at the row's target gazes), N
steps (``--no-gaze-steps``: also N steps without the gaze term; ``--natural-steps``: N steps as the app's
``--natural-eyes`` fits). Each redirected image is compared with the generator's ground truth of the same row
turned to the same gaze (``SyntheticRedirectionPairs.render_target``), both on white outside the ground
truth's head mask:

- ``label °``: the run's *evaluation* estimator reading the redirected image, against the label the app
  wrote (``pitchyaw_cam``): how wrong the new dataset's labels are, as that estimator sees it;
- ``vs truth °``: the same estimator on the redirected image against it on the ground truth (the eval
  stage's protocol); ``PSNR``/``SSIM`` against the ground truth;
- ``s/image``: wall-clock seconds of ``render_chunk`` (fitting included) over the images it wrote.

The ``ground truth`` row reads the ground truth itself against its label: the ruler's own error, the floor
of the ``label °`` column. A fit with the gaze term can read *below* it: the term tunes the render to the loss
estimator, a sibling of the evaluation one, so ``vs truth °`` is the column to rank settings by. Prints the
table and writes ``out/benchmarks/redirect.png`` (``redirect_train.png`` with ``--split train``; both gaze
columns against seconds per image).

    .venv/bin/python benchmarks/redirect.py [--run-dir out/demo/run] [--rows 4] [--gazes grid:3x3:25]
                                            [--fit-steps 0 10 20 40] [--split test|train] [--threads 2]
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import numpy as np  # noqa: E402
import torch  # noqa: E402

from benchmarks.common import OUT_DIR, count, demo_or_tiny_run, format_table, machine_info, save_plot  # noqa: E402
from toolkit.errors import CliParser, run_cli  # noqa: E402


def ground_truth(files, rows: dict, gazes: np.ndarray, res: int) -> dict[str, torch.Tensor]:
    """The generator's images of every (row, gaze), in render_chunk's order (row-major): image [N, 3, R, R]
    on white, head_mask [N, 1, R, R], pitchyaw_cam [N, 2]."""
    from train.data.pairing import SyntheticRedirectionPairs

    out: dict[str, list] = {"image": [], "head_mask": [], "pitchyaw_cam": []}
    for f in files:
        pairs = SyntheticRedirectionPairs(f, res=res)
        for r in rows[f]:
            for g in gazes:
                t = pairs.render_target(r, g)
                for k in out:
                    out[k].append(t[k])
    return {k: torch.stack(v) for k, v in out.items()}


def spread_rows(files, n: int, res: int) -> tuple[dict, list]:
    """``n`` rows spread over each file: ({file: row numbers}, [(file, row, GazeDataset item)])."""
    from train.data.dataset import GazeDataset
    from train.evaluation.pairs import spread_indices

    rows, items = {}, []
    for f in files:
        ds = GazeDataset([f], res=res, with_mesh=True)
        rows[f] = spread_indices(len(ds), min(n, len(ds)))
        items += [(f, r, ds[r]) for r in rows[f]]
    return rows, items


def score(images: torch.Tensor, landmarks: torch.Tensor, labels: torch.Tensor, truth: dict, estimator) -> dict:
    from toolkit.rotations import angular_error_deg
    from train.losses.metrics import composite_on_white, psnr, ssim

    mask = truth["head_mask"]
    img_w, tgt_w = composite_on_white(images, mask), composite_on_white(truth["image"], mask)
    with torch.no_grad():
        e_img, e_tgt = estimator(img_w, landmarks), estimator(tgt_w, landmarks)
    label = angular_error_deg(e_img[:, :2], labels)
    return {"label °": float(label.mean()), "label median °": float(label.median()),
            "vs truth °": float(angular_error_deg(e_img[:, :2], e_tgt[:, :2]).mean()),
            "PSNR dB": float(psnr(img_w, tgt_w).mean()), "SSIM": float(ssim(img_w, tgt_w).mean())}


def main(argv=None) -> int:
    ap = CliParser(description=__doc__.split("\n")[0], epilog=__doc__,
                   formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--run-dir", default=None,
                    help="a trained run (train/run.py) on synthetic data (default: out/demo/run when `make demo` "
                         "made one, else the tiny preset is trained into out/benchmarks/redirect_tiny_run, ~30 s)")
    ap.add_argument("--rows", type=count("--rows", 1), default=4, help="input rows per held-out subject (spread over the file)")
    ap.add_argument("--gazes", default="grid:3x3:25", help="target gazes (apps.redirect --gazes)")
    ap.add_argument("--fit-steps", type=count("--fit-steps", 0), nargs="+", default=[0, 10, 20, 40])
    ap.add_argument("--no-gaze-steps", type=count("--no-gaze-steps", 0), nargs="*", default=[40],
                    help="also fit these step counts without the gaze term (what the term adds)")
    ap.add_argument("--natural-steps", type=count("--natural-steps", 0), nargs="*", default=[],
                    help="also fit these step counts as apps.redirect --natural-eyes does (a gaze term that may "
                         "only turn the eyes)")
    ap.add_argument("--split", choices=("test", "train"), default="test",
                    help="redirect the run's held-out subjects (default) or its training subjects")
    ap.add_argument("--threads", type=count("--threads", 1), default=2)
    args = ap.parse_args(argv)
    torch.set_num_threads(args.threads)
    torch.manual_seed(0)

    from apps.redirect import parse_gazes, render_chunk
    from train.trained_run import TrainedRun

    run_dir = args.run_dir or demo_or_tiny_run("redirect_tiny_run")
    trained = TrainedRun.open(run_dir)
    cfg = trained.config
    res, device = cfg.data.res, torch.device("cpu")
    model, renderer = trained.load_model(device)
    estimator = trained.estimator("eval", device)
    gazes = parse_gazes(args.gazes)
    files = trained.split(args.split)
    rows, items = spread_rows(files, args.rows, res)
    G = len(gazes)
    landmarks = torch.stack([torch.as_tensor(it["landmarks"]).float() for _, _, it in items]).repeat_interleave(G, 0)
    t0 = time.perf_counter()
    truth = ground_truth(files, rows, gazes, res)
    print(f"{machine_info()}\nrun {run_dir}, {args.split} subjects: {len(items)} rows x {G} gazes, ground truth rendered in "
          f"{time.perf_counter() - t0:.1f} s")

    table = [{"fit steps": "ground truth", "s/image": None,
              **score(truth["image"], landmarks, truth["pitchyaw_cam"], truth, estimator),
              "vs truth °": None, "PSNR dB": None, "SSIM": None}]  # itself against itself: n/a, not a measurement
    variants = ([(n, True, False) for n in args.fit_steps] + [(n, False, False) for n in args.no_gaze_steps if n > 0]
                + [(n, True, True) for n in args.natural_steps if n > 0])
    # One discarded call, the first row fitted for one step: the first render and the first fit pay one-time
    # costs that would land on whichever variant ran first.
    render_chunk(model, renderer, [items[0][2]], [items[0][1]], gazes[:1], res, cfg.gaussian.sampling_steps, device,
                 trained.row_fitter(model, renderer, device, 1))
    for steps, gaze_term, natural in variants:
        fit = (trained.row_fitter(model, renderer, device, steps, gaze_term=gaze_term, natural_eyes=natural)
               if steps > 0 else None)
        t0 = time.perf_counter()
        arrays = render_chunk(model, renderer, [it for _, _, it in items], [r for _, r, _ in items], gazes, res,
                              cfg.gaussian.sampling_steps, device, fit)
        seconds = time.perf_counter() - t0
        images = torch.from_numpy(arrays["face_patch"][..., ::-1].copy()).permute(0, 3, 1, 2).float() / 255
        labels = torch.from_numpy(arrays["pitchyaw_cam"]).float()
        if not torch.allclose(labels, truth["pitchyaw_cam"], atol=1e-4):
            raise RuntimeError("the app's labels disagree with the generator's camera-frame gazes")
        name = f"{steps}, natural eyes" if natural else steps if gaze_term or steps == 0 else f"{steps}, no gaze term"
        table.append({"fit steps": name, "s/image": seconds / images.shape[0],
                      **score(images, landmarks, labels, truth, estimator)})
        print(format_table(table[-1:]), flush=True)
    print()
    print(format_table(table))
    fitted = [r for r in table if isinstance(r["fit steps"], int)]
    x = [r["s/image"] for r in fitted]
    path = save_plot(OUT_DIR / ("redirect.png" if args.split == "test" else f"redirect_{args.split}.png"),
                     {"read against the ground truth's reading": (x, [r["vs truth °"] for r in fitted]),
                      "read against its label": (x, [r["label °"] for r in fitted]),
                      "ground truth against its label (the ruler)": ([min(x), max(x)], [table[0]["label °"]] * 2)},
                     xlabel="seconds per redirected image (fitting included)",
                     ylabel="gaze error, evaluation estimator (deg)", title="apps.redirect: time against gaze error")
    print(f"plot: {path}")
    return 0


if __name__ == "__main__":
    sys.exit(run_cli(main))
