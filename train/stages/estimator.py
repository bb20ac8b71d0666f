"""Stage ``estimator``: train the loss and the evaluation gaze estimators, independently seeded, on the
training split plus extra procedural subjects of their own, validated on the held-out split.

A ``data.root`` of ETH-XGaze release files (``data.layout=xgaze``, or detected) is read by
``train.data.patches`` instead: the estimators train on the release's normalized face patches with their
``face_gaze`` and ``face_head_pose`` labels and are scored on the held-out subjects that have labels
(:func:`release_split`; docs/model.md, "ETH-XGaze release files")."""

from __future__ import annotations

from pathlib import Path

import torch

from toolkit.errors import ToolkitError
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
    release = bool(ctx.config.data.root) and is_release(run)
    if not release:
        train_files, test_files = run.split("train"), run.split("test")
    elif todo:
        check_release_design(ctx.config)
        train_files, test_files = release_split(run, ctx.log)
        ctx.log(f"[estimator] ETH-XGaze release files: {len(train_files)} training and {len(test_files)} scored "
                f"held-out subject(s); face patches read at {release_res(ctx.config)}², labels face_gaze and "
                f"face_head_pose (normalized camera)")
    else:  # both estimators given by path: nothing reads the files
        train_files, test_files = [], []
    job = dict(config=ctx.config, train_files=train_files, test_files=test_files, run_dir=ctx.run_dir, device=device)
    if release:
        job["release"] = True
    if len(todo) == 2 and device.type == "cpu" and threads >= 2:
        split = (threads // 2, threads - threads // 2)
        ctx.log(f"[estimator] training the loss and evaluation estimators at once: 2 processes, "
                f"{split[0]} + {split[1]} threads")
        results = run_at_once([(_train_estimator, dict(job, index=k, role=name, seed=seed, threads=n))
                               for (k, name, seed), n in zip(todo, split)])
    else:
        data = _estimator_data(ctx.config, train_files, test_files, release=release) if todo else None
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
        if "val_gaze_deg" in record:
            ctx.log(f"[estimator] {name}: {record['train_images']} training images, held-out gaze error "
                    f"{record['val_gaze_deg']:.2f} deg")
        else:  # release files whose held-out subjects have no labels (release_split said so)
            ctx.log(f"[estimator] {name}: {record['train_images']} training images, not scored (no held-out "
                    f"images with gaze labels)")
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
                    workers: int | None = None, release: bool = False) -> tuple:
    """The estimator stage's data of the run's splits: (train images, labels [N, 4], landmarks [N, 68, 2], val:
    the same three of the held-out split). The images are :class:`train.data.rows.RowImages` of uint8 [N, 3, R, R],
    read from the subject files when a batch indexes them (the paper's split is ~11 GB as uint8); the labels
    and landmarks, a few hundred bytes a row, are read up front. ``release``: ETH-XGaze release files
    (:func:`_release_data`)."""
    if release:
        return _release_data(config, train_files, test_files, workers)
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
                     data: tuple | None = None, release: bool = False) -> tuple[str, dict]:
    """Train and save one estimator of the estimator stage (in this process, or a spawned one, with
    ``threads`` torch threads): its training split plus its own extra procedural subjects, validated on the
    held-out split (``data``: :func:`_estimator_data`, loaded here when None). Returns (file name in
    ``run_dir``, its last history record with ``train_images``)."""
    torch.set_num_threads(threads)
    job = dict(config=config, run_dir=run_dir, device=device, index=index, role=role, seed=seed, threads=threads,
               log=log)
    if release:
        job["release"] = True
    if data is not None:
        return _fit_estimator(**job, data=data)
    from train.data.rows import default_workers

    # Reading threads within this process's share of the cores (two estimators may train at once).
    data = _estimator_data(config, train_files, test_files, workers=min(threads, default_workers()), release=release)
    try:
        return _fit_estimator(**job, data=data)
    finally:
        _close_data(data)


def _close_data(data: tuple | None) -> None:
    """Stop the reading threads of :func:`_estimator_data`'s images (and close the release files' handles)."""
    if data is None:
        return
    from train.data.patches import ReleasePatches

    for images in (data[0], data[3][0] if data[3] is not None else None):
        if images is not None:
            images.source.close()
            if isinstance(images.source.dataset, ReleasePatches):
                images.source.dataset.close()


def _fit_estimator(*, config: RunConfig, run_dir: Path, device: torch.device, index: int, role: str, seed: int,
                   threads: int, log, data: tuple, release: bool = False) -> tuple[str, dict]:
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
    info = {"role": role, "train_images": len(images)}
    if release:  # what it was trained on: the release's face patches, not this project's renders
        info["data_layout"] = "xgaze"
    model.save(Path(run_dir) / file, info)
    return file, dict(hist[-1] if hist else {}, train_images=len(images))


def estimator_design(config: RunConfig):
    """The estimator stage's network design for ``config.estimator.crop``: eye patches sized for the image, or a
    face / eye-band crop resized to ``estimator.input_size``."""
    from train.estimator.config import EYE_BAND, GazeEstimatorConfig, eye_config

    e = config.estimator
    if e.crop == "eyes":
        return eye_config(config.data.res)
    return GazeEstimatorConfig(input_size=e.input_size, crop=EYE_BAND if e.crop == "eye_band" else (0.0, 1.0, 0.0, 1.0))


# ------------------------------------------------------------------------------------ ETH-XGaze release files

def is_release(run: RunArtifacts) -> bool:
    """Whether the run's ``data.root`` holds ETH-XGaze release files (``train.data.patches.release_layout``)."""
    from train.data.patches import release_layout

    return release_layout(run.subject_files(), run.config.data.layout)


def check_release_design(config: RunConfig) -> None:
    """One line when ``estimator.crop`` cannot read release patches: ``eye_band`` cuts rows measured on this
    project's crops, 0.26 m across at the face (docs/data.md), while the release's show 0.14 m (448 px at a focal
    length of 960 px and 300 mm, ETH-XGaze normalization_example.py L28-30), so its band would miss the eyes.
    (``eyes`` needs the files' landmarks: :func:`release_split` checks them.)"""
    if config.estimator.crop == "eye_band":
        raise ToolkitError("estimator.crop=eye_band: the eye band's rows are those of this project's synthetic crops "
                           "(0.26 m across at the face); the ETH-XGaze release's face patches show 0.14 m, so the "
                           "band would miss the eyes: set estimator.crop=face (the whole patch, as ETH-XGaze's own "
                           "baseline reads it)")


def release_res(config: RunConfig) -> int:
    """The square size release patches are read at: the image size the estimator's design reads without
    resampling. ``face``: ``estimator.input_size`` (224: the xgaze_224 patches as they are); ``eyes``: ``data.res``,
    the image size :func:`train.estimator.config.eye_config` sizes its eye patches for."""
    return config.data.res if config.estimator.crop == "eyes" else config.estimator.input_size


def release_split(run: RunArtifacts, log=print) -> tuple[list[Path], list[Path]]:
    """The estimator stage's (training, scored held-out) files of a ``data.root`` of ETH-XGaze release files.

    The subjects are split as the other stages split theirs (``data.split_file``, else a split file beside the
    files, read in the release's form {"train", "test"}; else the last ``data.test_fraction`` of the sorted files
    held out), with two differences the release needs: held-out subjects the split file names but ``data.root``
    lacks (the release keeps its test subjects in a ``test/`` folder beside ``train/``) are not an error, and
    held-out subjects without ``face_gaze`` (the release's test subjects: README.md L45-46) are not scored. Each
    is said in one log line; when no held-out subject is left the estimators are trained and not scored (one line
    says how to score them). Training subjects without ``face_gaze`` are left out (one line); none left is one
    ToolkitError. For ``estimator.crop=eyes`` every file used must hold ``facial_landmarks`` (one ToolkitError
    naming the first that does not, and ``estimator.crop=face``)."""
    from train.data.dataset import SPLIT_FILE_NAMES, held_out_count, subject_key
    from train.data.layout_files import read_split_file
    from train.data.patches import has_labels, has_landmarks

    d = run.config.data
    files = run.subject_files()
    beside = [files[0].parent / name for name in SPLIT_FILE_NAMES if (files[0].parent / name).exists()]
    sf = Path(d.split_file) if d.split_file else (beside[0] if beside else None)
    if sf is not None:
        train_names, held_names = read_split_file(sf, "xgaze")
        by_key = {subject_key(f.stem): f for f in files}  # as split_files: "subject0003" names xgaze_subject0003.h5
        missing = [n for n in train_names if subject_key(n) not in by_key]
        if missing:
            raise ToolkitError(f"{sf}: 'train' names subject {missing[0]}, which is not among the {len(files)} subject "
                               f"files of data.root {d.root} (file {missing[0]}.h5 expected)")
        train = [by_key[subject_key(n)] for n in train_names]
        held = [by_key[subject_key(n)] for n in held_names if subject_key(n) in by_key]
        absent = len(held_names) - len(held)
        where = f"{sf.name}'s 'test' list"
    else:
        files = sorted(files)
        n_test = held_out_count(len(files), d.test_fraction)
        train, held, absent = files[:len(files) - n_test], files[len(files) - n_test:], 0
        where = f"the last data.test_fraction={d.test_fraction} of the files"
    unlabelled = [f for f in train if not has_labels(f)]
    if unlabelled:
        log(f"[estimator] {len(unlabelled)} training subject(s) without face_gaze left out (the release's test "
            f"subjects, whose labels are withheld): {', '.join(f.stem for f in unlabelled[:3])}"
            f"{' ...' if len(unlabelled) > 3 else ''}")
        train = [f for f in train if f not in unlabelled]
    if not train:
        raise ToolkitError(f"data.root {d.root}: no training subject has gaze labels ('face_gaze'): the ETH-XGaze "
                           f"release's labelled subjects are those of its train/ folder")
    scored = [f for f in held if has_labels(f)]
    if absent or len(scored) < len(held):
        log(f"[estimator] held-out subjects not scored: {absent} of {where} not in data.root, "
            f"{len(held) - len(scored)} without face_gaze (the release's test subjects: their labels are withheld)")
    if not scored:
        log(f"[estimator] no held-out subject with face_gaze: the estimators train on {len(train)} subjects and are "
            f"not scored (leave data.split_file empty, with no split file beside the files, to hold out "
            f"data.test_fraction of the labelled subjects)")
    if run.config.estimator.crop == "eyes":
        bare = next((f for f in train + scored if not has_landmarks(f)), None)
        if bare is not None:
            raise ToolkitError(f"{bare}: estimator.crop=eyes reads the eyes at each image's facial_landmarks, which "
                               f"this release file lacks (the published xgaze_224 / xgaze_448 files hold none): set "
                               f"estimator.crop=face to read the whole normalized face patch, as ETH-XGaze's "
                               f"baseline does")
    return train, scored


def _release_data(config: RunConfig, train_files: list[Path], test_files: list[Path], workers: int | None) -> tuple:
    """:func:`_estimator_data` of ETH-XGaze release files (``train.data.patches.release_rows``): patches at
    :func:`release_res`, labels (``face_gaze``, ``face_head_pose``) in the normalized camera, landmarks for the
    eye design; val None when no held-out subject is scored."""
    from train.data.patches import release_rows
    from train.data.rows import default_workers

    workers = default_workers() if workers is None else workers
    kw = dict(res=release_res(config), landmarks=config.estimator.crop == "eyes", workers=workers)
    tr = release_rows(train_files, **kw)
    if not test_files:
        return (*tr, None)
    try:
        te = release_rows(test_files, **kw, cache_bytes=0)  # read once, at the end of the training
    except BaseException:
        tr[0].source.close()
        tr[0].source.dataset.close()
        raise
    return (*tr, te if te[2] is not None else te[:2])
