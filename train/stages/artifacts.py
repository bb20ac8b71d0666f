"""What a run's stages wrote, read back: the split files, the estimators, the codec, the renderer and the
two-stream model, and the evaluation's test-time fitting as the run's config sets it.

The stages read their inputs through :class:`RunArtifacts`; ``train.trained_run.TrainedRun`` (what apps and
benchmarks open a finished run with) is the same class with a way to open a run directory.
"""

from __future__ import annotations

from pathlib import Path
from typing import Callable

import torch

from toolkit.errors import ToolkitError
from train.run_config import RunConfig
from train.stages.pipeline import RunContext


def resolve_device(cfg: RunConfig) -> torch.device:
    """The device ``cfg.device`` names ("auto": CUDA when available); a ToolkitError for CUDA without one."""
    if cfg.device == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    if cfg.device.startswith("cuda") and not torch.cuda.is_available():
        raise ToolkitError("device=cuda but CUDA is not available; use device=cpu or device=auto")
    return torch.device(cfg.device)


class RunArtifacts:
    """A run's stage outputs so far (``context.outputs``: stage -> {name: path in the run directory}) and what
    is built from them. Each method reads the outputs of the stage that made it (a clear ToolkitError when
    that stage has not run)."""

    def __init__(self, context: RunContext):
        self.context = context

    @property
    def config(self) -> RunConfig:
        return self.context.config

    @property
    def run_dir(self) -> Path:
        return self.context.run_dir

    @property
    def device(self) -> torch.device:
        """The device the run's config names (:func:`resolve_device`)."""
        return resolve_device(self.config)

    # ------------------------------------------------------------------------------------------ data
    def subject_files(self) -> list[Path]:
        """Every subject file of the run's dataset: ``data.root`` when set, else the data stage's folder."""
        from train.data.dataset import find_subject_files

        root = Path(self.config.data.root) if self.config.data.root else self.context.path("data", "dir")
        return find_subject_files([root])

    def split(self, which: str) -> list[Path]:
        """The subject files of the ``"train"`` or ``"test"`` split (``data.split_file``, a split file beside the
        files, else ``data.test_fraction`` held out)."""
        from train.data.dataset import split_files

        d = self.config.data
        return split_files(self.subject_files(), which, d.split_file or None, d.test_fraction, d.layout)

    # ------------------------------------------------------------------------------------ estimators
    def configured_estimator(self, role: str) -> str:
        """The user's estimator path for ``role`` ("loss" or "eval"), or "" when the estimator stage trains it."""
        e = self.config.estimator
        return e.loss_path if role == "loss" else e.eval_path

    def estimator_file(self, role: str) -> Path:
        """The estimator file of ``role`` ("loss" or "eval"): the configured path, else the estimator stage's."""
        given = self.configured_estimator(role)
        return Path(given) if given else self.context.path("estimator", role)

    def estimator(self, role: str, device):
        """The gaze estimator of ``role``, loaded onto ``device``: for "eval" with ``eval.estimator_path`` set,
        GazeNeRF's checkpoint in the project's ResNet-50, reading [B, 4] (gaze, head pose) as the run's do."""
        from train.estimator.network import GazeEstimator

        peer = self.config.eval.estimator_path
        if role == "eval" and peer:
            from train.estimator.peer import PeerGazeEstimator, load_gazenerf_estimator

            return PeerGazeEstimator(load_gazenerf_estimator(peer, device), head=True).to(device)
        return GazeEstimator.load(self.estimator_file(role), device)

    # -------------------------------------------------------------------------------- model, renderer
    def codec(self, device):
        """The codec ``codec.kind`` names: the pixel codec, the SD-VAE, or the codec stage's autoencoder."""
        from train.model.codec import PixelCodec, SDVAECodec, load_autoencoder

        c = self.config.codec
        if c.kind == "pixel":
            return PixelCodec().to(device)
        if c.kind == "sd-vae":
            return SDVAECodec(c.sd_vae_path).to(device)
        return load_autoencoder(self.context.path("codec", "codec"), device)

    def renderer(self, device):
        """A fresh renderer as ``gaussian.renderer`` sets it (the DiT around the run's codec, or the U-Net)."""
        from train.model.renderer import make_renderer

        g = self.config.gaussian
        codec = self.codec(device) if g.renderer == "dit" else None
        dit_kw = {"feature_hidden": g.dit_feature_hidden} if g.renderer == "dit" else {}
        return make_renderer("dit" if g.renderer == "dit" else "baseline", codec, model=g.dit_model,
                             output_size=self.config.data.res, upscale=g.feature_upscale, residual=g.residual,
                             **dit_kw).to(device)

    def build_model(self, device):
        """(model, renderer) before training: the two-stream model on the geometry stage's Gaussians."""
        from train.training.trainer import build_model

        return build_model(self.context.path("geometry", "scene"), self.config.gaussian, device), self.renderer(device)

    def load_model(self, device):
        """(model, renderer) restored from the Gaussian stage's final checkpoint, in eval mode (a clear
        ToolkitError when the checkpoint does not fit the config)."""
        from train.training.checkpoint import load_training_checkpoint

        model, renderer = self.build_model(device)
        load_training_checkpoint(self.context.path("gaussian", "checkpoint"),
                                 modules={"model": model, "renderer": renderer}, restore_rng=False)
        return model.eval(), renderer.eval()

    # ----------------------------------------------------------------------------- test-time fitting
    def fit_gaze_term(self, device, **given):
        """The test-time fitting's gaze term as the run's eval section sets it (``FitGaze`` around the frozen
        loss estimator), or None when its weight is 0. ``given`` (``gaze_weight``, ``terms``, ``every``,
        ``reach``) replace the section's settings (``NATURAL_EYES_FIT``'s, say)."""
        from train.evaluation.fitting import FitGaze
        from train.losses import GazeLoss

        e = self.config.eval
        s = {"gaze_weight": e.tta_gaze_weight, "terms": tuple(e.tta_gaze_terms), "every": e.tta_gaze_every,
             "reach": tuple(e.tta_gaze_reach), **given}
        if not s["gaze_weight"] > 0:
            return None
        return FitGaze(GazeLoss(self.estimator("loss", device)), s["gaze_weight"], tuple(s["terms"]),
                       every=s["every"], reach=tuple(s["reach"]))

    def row_fitter(self, model, renderer, device, steps: int, *, gaze_term: bool = True,
                   natural_eyes: bool = False) -> Callable[[dict, torch.Tensor], torch.Tensor]:
        """The evaluation's test-time fitting for one input row, as a function (item, gazes [G, 2]) -> fitted
        code [1, C]: ``steps`` Adam steps of the code and the run's ``eval.tta_weights`` on the input image,
        compared on ``eval.tta_region``, with the loss estimator's gaze term (``eval.tta_gaze_weight``) at the
        row's target gazes in turn (``train.evaluation.fitting.term_gaze_order``). The weights are tuned in
        place: the caller restores them (``train.evaluation.fitting.restored_weights``) after rendering the
        row. ``gaze_term=False`` leaves the gaze term out whatever the run's weight. ``natural_eyes`` fits
        ``train.run_config.NATURAL_EYES_FIT`` instead of the run's weights and gaze term: the term
        may turn the eyes but not repaint them."""
        from train.evaluation.fitting import face_only_mask, test_time_fit
        from train.run_config import NATURAL_EYES_FIT

        e = self.config.eval
        weights = NATURAL_EYES_FIT["weights"] if natural_eyes else tuple(e.tta_weights)
        natural = {k: v for k, v in NATURAL_EYES_FIT.items() if k != "weights"} if natural_eyes else {}
        gaze = self.fit_gaze_term(device, **natural) if gaze_term else None
        res = self.config.data.res

        def fit(it: dict, gazes: torch.Tensor) -> torch.Tensor:
            t = lambda k: torch.as_tensor(it[k]).float()[None].to(device)  # noqa: E731
            head = t("head_mask")
            mask = head if e.tta_region == "head" else face_only_mask(head, (t("left_eye_mask") + t("right_eye_mask")).clamp(0, 1))
            batch = {"code": t("latent_code"), "in_pose": t("pose"), "in_gaze_head": t("pitchyaw_head"),
                     "in_viewmat": t("viewmat"), "K": t("K"), "landmarks": t("landmarks"), "in_head_mask": head,
                     "gaze_head": gazes[:1], "target_gazes": gazes[None]}
            with torch.enable_grad():
                return test_time_fit(model, renderer, batch, t("image"), mask, res, steps, weights=weights,
                                     renderer_lr=e.tta_renderer_lr, gaze=gaze)

        return fit
