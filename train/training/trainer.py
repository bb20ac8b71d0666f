"""Stage ``gaussian``: end-to-end training of the two-stream Gaussian model with the neural renderer.

One step on a batch of training images (all in the input's camera, head pose and codes):

1. splat the head feature map at 1/4 resolution (:class:`train.model.gaussian_model.GaussianModel`);
2. render it with the DiT (``training_forward``: the decoded x0 estimate at a sampled diffusion time; a
   share ``onestep_fraction`` of the batch uses t = T−1, the deterministic one-step path used at inference)
   or with the U-Net baseline;
3. losses: per-region image loss (L1 + SSIM, white background) on the decoded image, L1 of the splatted
   RGB channels against the downsampled target, the diffusion loss, the gaze loss (frozen estimator on
   render vs target), the orthogonality loss on the first layers of the gaze / pose / expression MLPs. With
   ``gaussian.region_renders=separate`` the face and eye terms come from the face-only and eye-only Gaussians'
   own renders instead of the head render's regions (:meth:`GaussianTrainer._separate_regions`);
4. weak supervision: the same inputs with an intermediate gaze φ from the gaze sampler (progressive range),
   rendered on the one-step path; supervised by the gaze loss against φ (converted to the camera frame of
   the estimator's labels) and by the image loss on the **face region only** — the eyes are not compared
   with the source image, which would penalize the redirection itself.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import torch
import torch.nn.functional as F

from train.config import component
from train.losses import (
    GazeLoss,
    ImageLoss,
    ImageLossConfig,
    OrthogonalityLoss,
    composite_on_white,
    gaze_to_camera,
    head_to_camera_rotation,
)
from train.model.gaussian_model import RENDERS, GaussianModel, GaussianModelConfig
from train.run_config import GaussianStageConfig
from train.training.gaze_sampler import GazeSampler, GazeSamplerConfig


@dataclass
class TrainBatchData:
    """Training rows held in memory: the paper configuration's benchmark builds a few upsampled ones, the codec
    stage still loads its split this way (:func:`load_split`). The Gaussian and estimator stages read their
    split with :func:`open_split`. Images in [0, 1], white background."""

    image: torch.Tensor  # [N, 3, R, R]
    head: torch.Tensor  # [N, 1, R, R] masks in {0, 1}
    eyes: torch.Tensor
    code: torch.Tensor  # [N, 144]
    pose: torch.Tensor  # [N, 6]
    gaze_head: torch.Tensor  # [N, 2]
    gaze_cam: torch.Tensor  # [N, 2]
    head_pose_cam: torch.Tensor  # [N, 2]
    viewmat: torch.Tensor  # [N, 4, 4]
    K: torch.Tensor  # [N, 3, 3]
    landmarks: torch.Tensor  # [N, 68, 2] pixels (eye-patch gaze estimators read them)

    @property
    def res(self) -> int:
        return int(self.image.shape[-1])

    def __len__(self) -> int:
        return int(self.image.shape[0])

    def take(self, idx: torch.Tensor, device: torch.device | str) -> dict[str, torch.Tensor]:
        return {k: getattr(self, k)[idx].to(device) for k in self.__dataclass_fields__}

    def head_to_camera(self, b: dict[str, torch.Tensor]) -> torch.Tensor:
        """[B, 3, 3] rotation from the head frame to the camera frame (w2c ∘ pose)."""
        return head_to_camera_rotation(b["viewmat"], b["pose"])


def load_split(files: list[Path], split: str, res: int, layout: str = "auto") -> TrainBatchData:
    """The whole split in memory (~5 MB a row at 512²): for small splits only; the training stages stream
    theirs with :func:`open_split`, which gives the same tensors."""
    from train.data.dataset import GazeDataset

    ds = GazeDataset(files, split=split, res=res, layout=layout)
    items = [ds[i] for i in range(len(ds))]
    st = lambda k: torch.stack([torch.as_tensor(it[k]) for it in items]).float()  # noqa: E731
    eyes = (st("left_eye_mask") + st("right_eye_mask")).clamp(0, 1)
    return TrainBatchData(image=st("image"), head=st("head_mask"), eyes=eyes, code=st("latent_code"),
                          pose=st("pose"), gaze_head=st("pitchyaw_head"), gaze_cam=st("pitchyaw_cam"),
                          head_pose_cam=st("face_head_pose"), viewmat=st("viewmat"), K=st("K"),
                          landmarks=st("landmarks"))


ROW_KEYS = {"image": "image", "head": "head_mask", "eyes": None, "code": "latent_code", "pose": "pose",
            "gaze_head": "pitchyaw_head", "gaze_cam": "pitchyaw_cam", "head_pose_cam": "face_head_pose",
            "viewmat": "viewmat", "K": "K", "landmarks": "landmarks"}
"""A training row's tensors (:class:`TrainBatchData`'s fields) and the dataset keys they come from; ``eyes`` is
the union of the two eye masks."""


def train_row(item: dict[str, torch.Tensor]) -> dict[str, torch.Tensor]:
    """One ``GazeDataset`` item as a training row: :func:`load_split`'s conversions, on one row."""
    f = lambda k: torch.as_tensor(item[k]).float()  # noqa: E731
    return {name: (f(key) if key else (f("left_eye_mask") + f("right_eye_mask")).clamp(0, 1))
            for name, key in ROW_KEYS.items()}


class TrainRows:
    """The training split read from its subject files a batch at a time (:class:`train.data.rows.RowSource`):
    :class:`TrainBatchData`'s interface and tensors, with only a bounded cache of rows in memory."""

    def __init__(self, source, res: int):
        self.source, self.res = source, int(res)

    def __len__(self) -> int:
        return len(self.source)

    def take(self, idx: torch.Tensor, device: torch.device | str) -> dict[str, torch.Tensor]:
        """{field: [B, ...]} the rows ``idx`` [B] on ``device``."""
        return {k: v.to(device) for k, v in self.source.stack(idx.tolist()).items()}

    def prefetch(self, idx: torch.Tensor) -> None:
        """Start reading the rows ``idx`` (a later batch's) in the background."""
        self.source.prefetch(idx.tolist())

    head_to_camera = TrainBatchData.head_to_camera

    def close(self) -> None:
        self.source.close()


def open_split(files: list[Path], split: str, res: int, *, cache_bytes: int | None = None,
               workers: int | None = None, layout: str = "auto") -> TrainRows:
    """The split ``split`` of ``files`` at ``res`` as :class:`TrainRows` (the same rows as :func:`load_split`);
    ``cache_bytes`` / ``workers``: :class:`train.data.rows.RowSource`'s (default: its defaults for this machine);
    ``layout``: the files' layout (``train.data.layouts``; ``auto``: detected per file)."""
    from train.data.dataset import GazeDataset
    from train.data.rows import DEFAULT_CACHE_BYTES, RowSource, default_workers

    ds = GazeDataset(files, split=split, res=res, layout=layout)
    source = RowSource(ds, train_row, cache_bytes=DEFAULT_CACHE_BYTES if cache_bytes is None else cache_bytes,
                       workers=default_workers() if workers is None else workers)
    return TrainRows(source, res)


INIT_RGB_IMAGES = 64
"""Training images :func:`init_rgb` reads (``init_rgb_from_images``'s default)."""


def init_rgb(model: GaussianModel, data: TrainBatchData | TrainRows) -> float:
    """Start the model's RGB channels from (up to 64, evenly spaced) training images (:mod:`train.model.rgb_init`;
    only they are read and moved to the model's device); returns the fraction of Gaussians some image saw."""
    from train.model.rgb_init import init_rgb_from_images

    # rgb_init's own choice of rows, made here so that only they are read; it then takes all of them.
    n = len(data)
    idx = torch.linspace(0, n - 1, min(n, INIT_RGB_IMAGES)).round().long().unique()
    b = data.take(idx, model.face_features.device)
    return init_rgb_from_images(model, b["image"], b["head"], b["code"], b["pose"], b["gaze_head"], b["viewmat"],
                                b["K"], max_images=INIT_RGB_IMAGES)


def drawn_rows(n: int, batch: int, seed: int, step: int) -> torch.Tensor:
    """[batch] the rows of ``n`` that :meth:`GaussianTrainer.step` draws at ``step`` of a loop seeded with
    ``seed``: the first draw of the step's generator (:func:`train.training.loop.step_generator`)."""
    from train.training.loop import step_generator

    return torch.randint(0, n, (batch,), generator=step_generator(seed, step))


def region_masks(b: dict[str, torch.Tensor]) -> dict[str, torch.Tensor]:
    eyes = b["eyes"] * b["head"]
    return {"head": b["head"], "eyes": eyes, "face": (b["head"] - eyes).clamp(0, 1)}


class GaussianTrainer:
    """Holds the model, renderer and losses of the stage; ``step(step, generator)`` is the loop's step_fn."""

    def __init__(self, cfg: GaussianStageConfig, model: GaussianModel, renderer: torch.nn.Module,
                 estimator: torch.nn.Module, data: TrainBatchData | TrainRows, device: torch.device, total_steps: int,
                 shard: slice | None = None, seed: int = 0):
        """``seed`` seeds the intermediate-gaze sampler (the run's seed: each seed draws its own gazes); the loop
        is expected to train with it too (the rows read ahead are guessed from it: :meth:`_prefetch`).
        ``shard`` (torchrun, :func:`train.training.distributed.shard`): this rank's slice of the global batch of
        ``cfg.batch``. Every random draw is made for the whole global batch and sliced (the samples, the
        timesteps, the diffusion noise, the sampled gazes), so with the gradients averaged over the ranks a
        step equals one process's step on the global batch up to float sums (tested)."""
        self.cfg, self.model, self.renderer, self.data, self.device = cfg, model, renderer, data, device
        self.seed = seed
        self.total_steps = total_steps
        self.shard = shard
        # the perceptual term only with the user's VGG16 weights (gaussian.vgg_path)
        self.image_loss = ImageLoss(component(ImageLossConfig, cfg, vgg_path=cfg.vgg_path or None,
                                              lambda_perceptual=cfg.lambda_perceptual if cfg.vgg_path else 0.0)).to(device)
        self.gaze_loss = GazeLoss(estimator).to(device)
        self.ortho = OrthogonalityLoss(*model.orthogonality_layers()) if cfg.orthogonality else None
        self.sampler = GazeSampler(component(GazeSamplerConfig, cfg, progressive=True, seed=seed))

    def fast_forward(self, steps: int) -> None:
        """Replay the sampler's draws of ``steps`` earlier steps so a resumed run sees the same gazes."""
        for s in range(steps):
            self.sampler.sample(self.cfg.batch, progress=s / max(1, self.total_steps))

    def _timesteps(self, B: int, g: torch.Generator) -> torch.Tensor | None:
        diff = getattr(self.renderer, "diffusion", None)
        if diff is None:
            return None
        T = diff.num_timesteps
        t = torch.randint(0, T, (B,), generator=g)
        onestep = torch.rand(B, generator=g) < self.cfg.onestep_fraction
        return torch.where(onestep, torch.full_like(t, T - 1), t).to(self.device)

    def _render(self, b, gaze, target, g, t=None, renders=("head",)):
        R = self.data.res
        maps = self.model(b["code"], b["pose"], gaze, b["viewmat"], b["K"], R, R, renders=renders)
        return maps, self._decode(maps["head"], b, gaze, target, g, t)

    def _decode(self, feats, b, gaze, target, g, t=None):
        """The renderer's training pass on the splatted ``feats`` [B, F, h, w] against ``target`` [B, 3, H, W]."""
        extra = {}
        if self.shard is not None and getattr(self.renderer, "diffusion", None) is not None:
            # The global batch's noise, drawn where the renderer would draw it, then this rank's rows.
            shape = self.renderer.latent_shape(feats)
            extra["noise"] = torch.randn((self.cfg.batch, *shape[1:]), generator=g)[self.shard].to(self.device)
        return self.renderer.training_forward(feats, b["code"], target, gaze=gaze, pose=b["pose"], generator=g,
                                              t=t, **extra)

    def _separate_regions(self, b, maps, masks, target, g, t) -> tuple[dict[str, torch.Tensor], dict[str, torch.Tensor]]:
        """``gaussian.region_renders=separate``: the face-only and eye-only splats (``maps["face"]``, ``maps["eyes"]``)
        rendered on their own against the target on white outside their region, as GazeGaussian does
        (models/gaze_gaussian.py L142-163; losses/gazenerf_loss.py L363-442: the face and eye terms on those renders
        against ``gt * mask + (1 - mask)``). Returns ({"face", "eyes"}: [B, 3, H, W] decoded images, for the image
        loss's regions) and the extra terms {"rgb_face", "rgb_eyes": the splats' RGB L1 in their region, at the
        splat's size; "diffusion_face", "diffusion_eyes": the renderer's own losses on those renders}."""
        images, terms = {}, {}
        for r in ("face", "eyes"):
            on_white = composite_on_white(target, masks[r])
            out = self._decode(maps[r], b, b["gaze_head"], on_white, g, t)
            images[r] = out.image
            terms[f"diffusion_{r}"] = out.aux_loss
            small = F.interpolate(on_white, size=maps[r].shape[-2:], mode="area")
            m = F.interpolate(masks[r], size=maps[r].shape[-2:], mode="area")
            terms[f"rgb_{r}"] = ((maps[r][:, :3] - small).abs() * m).sum() / (3 * m.sum() + 1e-6)
        return images, terms

    def _prefetch(self, step: int) -> None:
        """Start reading the rows step ``step`` will draw, while this step computes. They are guessed: the loop
        seeds each step's generator from (seed, step) (:func:`train.training.loop.step_generator`) and the rows
        are its first draw. A wrong guess (a loop seeded otherwise) costs one batch of reads, never other data:
        :meth:`step` takes the rows it draws."""
        prefetch = getattr(self.data, "prefetch", None)
        if prefetch is not None:
            prefetch(self._rows(drawn_rows(len(self.data), self.cfg.batch, self.seed, step)))

    def _rows(self, x):
        """This rank's rows of a global-batch tensor (all of them in one process)."""
        return x if self.shard is None or x is None else x[self.shard]

    def step(self, step: int, g: torch.Generator) -> dict[str, torch.Tensor]:
        cfg = self.cfg
        idx = torch.randint(0, len(self.data), (cfg.batch,), generator=g)
        b = self.data.take(self._rows(idx), self.device)
        self._prefetch(step + 1)
        B = b["image"].shape[0]
        masks = region_masks(b)
        target = b["image"]
        separate = cfg.region_renders == "separate"
        t = self._rows(self._timesteps(cfg.batch, g))
        maps, out = self._render(b, b["gaze_head"], target, g, t, renders=RENDERS if separate else ("head",))
        img = out.image
        pred, regions = (self._separate_regions(b, maps, masks, target, g, t) if separate else ({}, {}))
        l_img, _ = self.image_loss({"head": img, **pred} if separate else img, target, masks)
        small = F.interpolate(target, size=maps["rgb"].shape[-2:], mode="area")
        l_rgb = (maps["rgb"] - small).abs().mean()
        l_gaze = self.gaze_loss(img, target_image=target, landmarks=b["landmarks"])
        terms = {"image": l_img, "rgb": l_rgb, "diffusion": out.aux_loss, "gaze": l_gaze}
        total = l_img + cfg.lambda_rgb * l_rgb + cfg.diffusion_weight * out.aux_loss + cfg.lambda_gaze * l_gaze
        if separate:
            terms.update(regions)
            total = total + cfg.lambda_rgb * (regions["rgb_face"] + regions["rgb_eyes"]) \
                + cfg.diffusion_weight * (regions["diffusion_face"] + regions["diffusion_eyes"])
        if self.ortho is not None:
            l_ortho = self.ortho()
            terms["ortho"] = l_ortho
            total = total + cfg.ortho_weight * l_ortho
        if cfg.weak_supervision:
            phi = self._rows(self.sampler.sample(cfg.batch, progress=step / max(1, self.total_steps))).to(self.device)
            t_last = None
            if getattr(self.renderer, "diffusion", None) is not None:
                t_last = torch.full((B,), self.renderer.diffusion.num_timesteps - 1, device=self.device)
            _, out_w = self._render(b, phi, target, g, t_last)
            l_face, _ = self.image_loss(out_w.image, target, {"face": masks["face"]},
                                        weights={"head": 0.0, "eyes": 0.0, "face": 1.0})
            phi_cam = gaze_to_camera(phi, self.data.head_to_camera(b))
            l_weak_gaze = self.gaze_loss(out_w.image, target_gaze=phi_cam, landmarks=b["landmarks"])
            terms.update(weak_face=l_face, weak_gaze=l_weak_gaze)
            total = total + cfg.weak_weight * (l_face + cfg.lambda_gaze * l_weak_gaze)
        terms["total"] = total
        return terms


def build_model(scene_path: Path, cfg: GaussianStageConfig, device, code_widths: tuple[int, int] = (80, 64)
                ) -> GaussianModel:
    """The two-stream model from the geometry stage's scene; its ``metadata["landmarks"]`` drive λτ. ``code_widths``:
    (identity, expression) of its code, the data's (``train.data.layouts.code_widths``)."""
    from toolkit.scene import GaussianScene

    scene = GaussianScene.load(scene_path)
    landmarks = scene.metadata.get("landmarks")
    landmarks = None if landmarks is None else torch.tensor(landmarks, dtype=torch.float32)
    return GaussianModel.from_scene(scene, model_config(cfg, code_widths), landmarks=landmarks).to(device)


def model_config(cfg: GaussianStageConfig, code_widths: tuple[int, int] = (80, 64)) -> GaussianModelConfig:
    """The two-stream model's configuration that the stage's options set (the fields that map to it, and the
    splat's scale from ``feature_upscale``), for codes of ``code_widths`` (identity, expression)."""
    return component(GaussianModelConfig, cfg, render_scale=1.0 / cfg.feature_upscale,
                     identity_dim=int(code_widths[0]), expression_dim=int(code_widths[1]))


CANONICAL_MEANS = ("face_means", "eye_means")


def optimizer_groups(model: GaussianModel, renderer: torch.nn.Module, cfg: GaussianStageConfig) -> list[dict]:
    """Adam parameter groups: the canonical Gaussian centres at ``cfg.means_lr`` × the head radius
    (``model.norm_scale``), every other model weight at ``cfg.lr``, the renderer at ``cfg.renderer_lr``.

    Why the centres get their own rate: Adam moves every weight by about its learning rate per step whatever
    the gradient's size, and the centres are in scene units (metres). At ``cfg.lr`` = 2e-3 a centre can walk
    2 mm per step -- 64 cm over the demo's 320 steps -- and noisy gradients through the renderer scatter the
    head into floaters. 3D Gaussian Splatting likewise trains positions at 1.6e-4 × the scene extent."""
    centres = [p for n, p in model.named_parameters() if n in CANONICAL_MEANS and p.requires_grad]
    others = [p for n, p in model.named_parameters() if n not in CANONICAL_MEANS and p.requires_grad]
    groups = [{"params": others, "lr": cfg.lr},
              {"params": [p for p in renderer.parameters() if p.requires_grad], "lr": cfg.renderer_lr},
              {"params": centres, "lr": cfg.means_lr * float(model.norm_scale)}]
    return [g for g in groups if g["params"]]


def lr_factor(cfg: GaussianStageConfig):
    """``step -> factor`` of the configured rates (``cfg.lr_schedule``), for :func:`train.training.loop.train_loop`."""
    if cfg.lr_schedule == "constant":
        return lambda step: 1.0
    if cfg.lr_schedule == "step":
        return lambda step: 0.1 ** (step / cfg.lr_decay_steps)
    total = max(1, cfg.steps - 1)
    return lambda step: cfg.lr_final + (1.0 - cfg.lr_final) * 0.5 * (1.0 + math.cos(math.pi * min(step, total) / total))


def describe(terms: dict[str, Any]) -> str:
    return ", ".join(f"{k}={float(v):.4g}" for k, v in terms.items())
