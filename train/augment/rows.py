"""Labelled estimator rows of the augmentation benchmark: real rows read from subject files, and the copies the
run redirects (or the generator renders) at a grid of gazes."""

from __future__ import annotations

import math
from dataclasses import dataclass, fields
from pathlib import Path

import numpy as np
import torch


@dataclass
class Rows:
    """Estimator rows: ``images`` [N, 3, R, R] uint8 RGB, ``labels`` [N, 4] radians (camera-frame gaze, head
    pose: what :func:`train.estimator.training.train_gaze_estimator` reads), ``landmarks`` [N, 68, 2] pixels,
    ``frames`` and ``cams`` [N] int64 (the frame and rig camera of each row's source)."""

    images: torch.Tensor
    labels: torch.Tensor
    landmarks: torch.Tensor
    frames: torch.Tensor
    cams: torch.Tensor

    def __len__(self) -> int:
        return self.images.shape[0]

    def take(self, mask_or_index: torch.Tensor) -> "Rows":
        return Rows(*(getattr(self, f.name)[mask_or_index] for f in fields(self)))

    def cat(self, other: "Rows") -> "Rows":
        return concat([self, other])

    def in_frames(self, frames) -> torch.Tensor:
        """[N] bool: the rows of ``frames``."""
        return torch.isin(self.frames, torch.as_tensor(list(frames), dtype=torch.int64))


def _to_u8(image: torch.Tensor) -> torch.Tensor:
    return (image * 255).round().clamp(0, 255).to(torch.uint8)


def read_rows(path: Path, res: int, layout: str = "auto") -> Rows:
    """Every row of one subject file as estimator rows (the estimator stage's conversions)."""
    from train.data.dataset import GazeDataset

    ds = GazeDataset([path], res=res, layout=layout)
    items = [ds[i] for i in range(len(ds))]
    ds.close()
    st = lambda k: torch.stack([torch.as_tensor(it[k]) for it in items])  # noqa: E731
    return Rows(_to_u8(st("image")), torch.cat([st("pitchyaw_cam"), st("face_head_pose")], 1).float(),
                st("landmarks").float(), st("frame_index").long(), st("cam_index").long())


def gaze_grid(n: int, half_width_deg: float) -> torch.Tensor:
    """[n * n, 2] head-frame gazes (pitch, yaw) in radians on a square grid of half-width ``half_width_deg``."""
    axis = torch.linspace(-1, 1, n) * math.radians(half_width_deg) if n > 1 else torch.zeros(1)
    pitch, yaw = torch.meshgrid(axis, axis, indexing="ij")
    return torch.stack([pitch.reshape(-1), yaw.reshape(-1)], 1)


def spread_cameras(cams: torch.Tensor, n: int) -> list[int]:
    """``n`` of the distinct camera indices ``cams``, spread evenly over them (all when there are fewer)."""
    distinct = sorted(set(cams.tolist()))
    if n >= len(distinct):
        return distinct
    return [distinct[int(i)] for i in np.linspace(0, len(distinct) - 1, n).round()]


def source_rows(rows: Rows, frames, cameras: int) -> list[int]:
    """The indices of the rows of ``frames`` at ``cameras`` cameras per frame (:func:`spread_cameras`)."""
    out = []
    for f in frames:
        idx = torch.nonzero(rows.frames == int(f)).flatten()
        keep = set(spread_cameras(rows.cams[idx], cameras))
        out += [int(i) for i in idx if int(rows.cams[i]) in keep]
    return out


def _camera_labels(item: dict, gazes: torch.Tensor) -> torch.Tensor:
    """[G, 4]: ``gazes`` [G, 2] (head frame) seen from the item's camera, with the item's head pose."""
    from train.losses import gaze_to_camera, head_to_camera_rotation

    R = head_to_camera_rotation(torch.as_tensor(item["viewmat"])[None].float(), torch.as_tensor(item["pose"])[None].float())
    cam = gaze_to_camera(gazes.float(), R.expand(gazes.shape[0], 3, 3))
    return torch.cat([cam, torch.as_tensor(item["face_head_pose"]).float()[None].expand(gazes.shape[0], 2)], 1)


def _grid_rows(images: torch.Tensor, item: dict, gazes: torch.Tensor) -> Rows:
    G = gazes.shape[0]
    return Rows(_to_u8(images.cpu()), _camera_labels(item, gazes), torch.as_tensor(item["landmarks"]).float()[None].expand(G, 68, 2),
                torch.full((G,), int(item["frame_index"])), torch.full((G,), int(item["cam_index"])))


def redirected_rows(run, model, renderer, path: Path, rows: list[int], gazes: torch.Tensor, fit_steps: int,
                    device) -> Rows:
    """The run's redirected copies of ``rows`` of ``path`` at head-frame ``gazes`` [G, 2]: each row fitted first
    (``fit_steps`` > 0: the natural fit without a gaze term, ``TrainedRun.row_fitter``; the fitted weights
    restored after it), then rendered at every gaze. Labels: the target gazes in the row's camera, its head
    pose; landmarks: the row's (the synthetic subjects' gaze moves no landmark)."""
    from train.data.dataset import GazeDataset
    from train.evaluation.figures import model_gaze_sweep
    from train.evaluation.fitting import restored_weights
    from train.run_config import eval_sampling_steps

    cfg = run.config
    ds = GazeDataset([path], res=cfg.data.res, layout=cfg.data.layout)
    fit = run.row_fitter(model, renderer, device, fit_steps, gaze_term=False, natural_eyes=True) if fit_steps else None
    out = []
    for r in rows:
        item = ds[r]
        with restored_weights(model, renderer):
            if fit is not None:
                item = {**item, "latent_code": fit(item, gazes.to(device))[0].detach().cpu()}
            with torch.no_grad():
                images = model_gaze_sweep(model, renderer, item, gazes, cfg.data.res, eval_sampling_steps(cfg), device)
        out.append(_grid_rows(images, item, gazes))
    ds.close()
    return concat(out)


def truth_rows(path: Path, rows: list[int], gazes: torch.Tensor, res: int) -> Rows:
    """The generator's ground truth for :func:`redirected_rows`: each row's view, pose, expression and light at
    every gaze (a synthetic subject file only)."""
    from train.data.pairing import SyntheticRedirectionPairs

    pairs = SyntheticRedirectionPairs(path, res=res)
    out = []
    for r in rows:
        item = pairs.data[r]
        targets = [pairs.render_target(r, g.double().numpy()) for g in gazes]
        out.append(_grid_rows(torch.stack([t["image"] for t in targets]), item, gazes))
    pairs.data.close()
    return concat(out)


def concat(parts: list[Rows]) -> Rows:
    """The rows of ``parts`` (at least one) in order."""
    return Rows(*(torch.cat([getattr(p, f.name) for p in parts]) for f in fields(Rows)))
