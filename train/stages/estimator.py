"""Stage ``estimator``: train the loss and the evaluation gaze estimators, independently seeded, on the
training split plus extra procedural subjects of their own, validated on the held-out split."""

from __future__ import annotations

from pathlib import Path

import torch

from toolkit.io import atomic_write_json
from train.config import component
from train.run_config import RunConfig
from train.stages.artifacts import RunArtifacts
from train.stages.pipeline import RunContext
from train.stages.processes import run_at_once

ESTIMATOR_ROLES = (("loss", 1), ("eval", 2))
"""The two independently trained gaze estimators: (role, seed offset). The loss estimator is frozen inside the
gaze loss (and the evaluation's fitting term); the evaluation estimator is only ever the metric's ruler."""


ESTIMATOR_SUSPECT_DEG = 30.0
"""A held-out gaze error (degrees) above which the stage warns that an estimator's training failed: trained
estimators read 2-7 deg on synthetic subjects, and one read 87 deg after too short a training."""


def stage_estimator(ctx: RunContext) -> dict[str, str]:
    """Train each estimator whose path is not given. On the CPU with >= 2 torch threads and both to train,
    they train at once, in two processes that split the threads: this small CNN uses a second thread poorly
    (the demo's stage on 2 cores: 349 s in turn on 2 threads, 242 s at once on 1 thread each).
    Each estimator's numbers depend only on the threads it trains with: the two processes with 1 thread each
    give exactly what one process with 1 thread gives in turn. Each shows a progress bar of its own (with its
    loss); the stage logs both results when they are done, and their final records go to ``metrics.jsonl``."""
    run = RunArtifacts(ctx)
    todo = [(k, name, seed) for k, (name, seed) in enumerate(ESTIMATOR_ROLES) if not run.configured_estimator(name)]
    if ctx.config.estimator.synthetic_subjects > 0 and ctx.config.data.root:
        ctx.log("[estimator] synthetic_subjects ignored: data.root is an external dataset")
    threads = torch.get_num_threads()
    device = run.device
    job = dict(config=ctx.config, train_files=run.split("train"), test_files=run.split("test"),
               run_dir=ctx.run_dir, device=device)
    if len(todo) == 2 and device.type == "cpu" and threads >= 2:
        split = (threads // 2, threads - threads // 2)
        ctx.log(f"[estimator] training the loss and evaluation estimators at once: 2 processes, "
                f"{split[0]} + {split[1]} threads")
        results = run_at_once([(_train_estimator, dict(job, index=k, role=name, seed=seed, threads=n))
                               for (k, name, seed), n in zip(todo, split)])
    else:
        data = _estimator_data(ctx.config, job["train_files"], job["test_files"]) if todo else None
        try:
            results = [_train_estimator(**job, index=k, role=name, seed=seed, threads=threads, log=ctx.log,
                                        data=data) for k, name, seed in todo]
        finally:
            _close_data(data)
    summary = _log_results(ctx, [name for _, name, _ in todo], results)
    atomic_write_json(ctx.run_dir / "estimators.json", summary)
    return {**{name: file for (_, name, _), (file, _) in zip(todo, results)}, "summary": "estimators.json"}


def _log_results(ctx: RunContext, roles: list[str], results: list[tuple[str, dict]]) -> dict[str, dict]:
    """Log each trained estimator's final record (to ``metrics.jsonl`` and the run's log, with a warning for
    one that reads held-out gazes far off); returns {role: record}."""
    from train.training.loop import MetricsLogger

    summary = {}
    metrics = MetricsLogger(ctx.run_dir, tensorboard=True)
    for name, (_, record) in zip(roles, results):
        summary[name] = record
        # Trained in one go (in child processes, silent, when two train at once): the final record is logged.
        metrics.start(f"estimator_{name}", 0)
        metrics.log(f"estimator_{name}", ctx.config.estimator.steps,
                    {k: float(v) for k, v in record.items() if k != "step"})
        ctx.log(f"[estimator] {name}: {record['train_images']} training images, held-out gaze error "
                f"{record.get('val_gaze_deg', float('nan')):.2f} deg")
        err = record.get("val_gaze_deg", float("nan"))
        if "val_gaze_deg" in record and not err <= ESTIMATOR_SUSPECT_DEG:  # NaN too
            # Not an error: tiny test runs train for a few steps. But a real run must not go on silently with it.
            ctx.log(f"[estimator] WARNING: the {name} estimator reads held-out gazes {err:.1f} deg off (trained "
                    f"estimators read 2-7 deg on synthetic subjects): its training failed or was too short, and "
                    f"{'the gaze loss and the fit' if name == 'loss' else 'the gaze metric'} will be wrong; rerun "
                    f"this stage with more estimator.steps")
    metrics.close()
    return summary


def _estimator_data(config: RunConfig, train_files: list[Path], test_files: list[Path], *,
                    workers: int | None = None) -> tuple:
    """The estimator stage's data of the run's splits: (train images, labels [N, 4], landmarks [N, 68, 2], val:
    the same three of the held-out split). The images are :class:`train.data.rows.RowImages` of uint8 [N, 3, R, R],
    read from the subject files when a batch indexes them (the paper's split is ~11 GB as uint8); the labels
    and landmarks, a few hundred bytes a row, are read up front."""
    res = config.data.res
    tr = _estimator_rows(train_files, res, workers)
    te = _estimator_rows(test_files, res, workers, cache_bytes=0)  # read once, at the end of the training
    return (*tr, tuple(te))


def _estimator_row(item: dict[str, torch.Tensor]) -> dict[str, torch.Tensor]:
    """A dataset item as the estimator reads it: the image as uint8 (4x fewer bytes than float), its labels
    (camera-frame gaze, head pose) and landmarks -- the whole-split loader's conversions, on one row."""
    from train.training.trainer import train_row

    row = train_row(item)
    return {"image": (row["image"] * 255).round().clamp(0, 255).to(torch.uint8),
            "label": torch.cat([row["gaze_cam"], row["head_pose_cam"]]), "landmarks": row["landmarks"]}


def _estimator_rows(files: list[Path], res: int, workers: int | None, cache_bytes: int | None = None) -> tuple:
    """(RowImages uint8 [N, 3, res, res], labels [N, 4], landmarks [N, 68, 2]) of ``files``; the labels are read
    in one pass over the rows, which also fills the cache with the first images."""
    from train.data.dataset import GazeDataset
    from train.data.rows import DEFAULT_CACHE_BYTES, RowImages, RowSource, default_workers

    ds = GazeDataset(files, split="all", res=res)
    source = RowSource(ds, _estimator_row, cache_bytes=DEFAULT_CACHE_BYTES if cache_bytes is None else cache_bytes,
                       workers=default_workers() if workers is None else workers)
    labels, landmarks = [], []
    for start in range(0, len(source), 64):
        for row in source.rows(range(start, min(len(source), start + 64))):
            labels.append(row["label"])
            landmarks.append(row["landmarks"])
    images = RowImages(source, "image", (3, res, res), torch.uint8)
    return images, torch.stack(labels), torch.stack(landmarks)


def _train_estimator(*, config: RunConfig, train_files: list[Path], test_files: list[Path], run_dir: Path,
                     device: torch.device, index: int, role: str, seed: int, threads: int, log=None,
                     data: tuple | None = None) -> tuple[str, dict]:
    """Train and save one estimator of the estimator stage (in this process, or a spawned one, with
    ``threads`` torch threads): its training split plus its own extra procedural subjects, validated on the
    held-out split (``data``: :func:`_estimator_data`, loaded here when None). Returns (file name in
    ``run_dir``, its last history record with ``train_images``)."""
    torch.set_num_threads(threads)
    job = dict(config=config, run_dir=run_dir, device=device, index=index, role=role, seed=seed, threads=threads,
               log=log)
    if data is not None:
        return _fit_estimator(**job, data=data)
    from train.data.rows import default_workers

    # Reading threads within this process's share of the cores (two estimators may train at once).
    data = _estimator_data(config, train_files, test_files, workers=min(threads, default_workers()))
    try:
        return _fit_estimator(**job, data=data)
    finally:
        _close_data(data)


def _close_data(data: tuple | None) -> None:
    """Stop the reading threads of :func:`_estimator_data`'s images."""
    if data is not None:
        data[0].source.close()
        data[3][0].source.close()


def _fit_estimator(*, config: RunConfig, run_dir: Path, device: torch.device, index: int, role: str, seed: int,
                   threads: int, log, data: tuple) -> tuple[str, dict]:
    """:func:`_train_estimator` on its data (:func:`_estimator_data`)."""
    from train.estimator.config import GazeEstimatorTrainConfig
    from train.estimator.training import train_gaze_estimator

    e, res = config.estimator, config.data.res
    images, targets, lms, val = data
    if e.synthetic_subjects > 0 and not config.data.root:
        from train.data.generate import estimator_images

        # Disjoint seed ranges: far above the data stage's subject seeds (seed * 100003 + index) and
        # different for the two estimators, which must stay independent.
        base = config.data.seed * 100003 + 50_000 + 10_000 * index
        extra, extra_labels, extra_lms = estimator_images(
            range(base, base + e.synthetic_subjects), n_frames=e.synthetic_frames,
            cameras_per_frame=e.cameras_per_frame, res=res, seed=seed, log=log, workers=threads)
        images, targets = images.cat(extra), torch.cat([targets, extra_labels])
        lms = torch.cat([lms, extra_lms])
    from tqdm import tqdm

    # One bar a role, each on its own line: the two estimators may train at once, in two processes.
    with tqdm(total=e.steps, desc=f"estimator {role}", position=index, dynamic_ncols=True) as bar:
        def on_step(step: int, loss: float) -> None:
            bar.update(1)
            if step % 20 == 0 or step == e.steps:
                bar.set_postfix(loss=f"{loss:.4g}")

        model, hist = train_gaze_estimator(
            images, targets, component(estimator_design(config), e),
            component(GazeEstimatorTrainConfig, e, seed=config.seed * 10 + seed, log_every=max(1, e.steps)),
            landmarks=lms, val=val, device=device, on_step=on_step)
    file = f"estimator_{role}.safetensors"
    model.save(Path(run_dir) / file, {"role": role, "train_images": len(images)})
    return file, dict(hist[-1] if hist else {}, train_images=len(images))


def estimator_design(config: RunConfig):
    """The estimator stage's network design for ``config.estimator.crop``: eye patches sized for the image, or a
    face / eye-band crop resized to ``estimator.input_size``."""
    from train.estimator.config import EYE_BAND, GazeEstimatorConfig, eye_config

    e = config.estimator
    if e.crop == "eyes":
        return eye_config(config.data.res)
    return GazeEstimatorConfig(input_size=e.input_size, crop=EYE_BAND if e.crop == "eye_band" else (0.0, 1.0, 0.0, 1.0))
