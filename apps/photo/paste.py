"""A (redirected) normalized crop pasted back into its photo at the photo's own resolution, feathered at the head
mask's edge: the inverse of ``apps.photo.normalize.warp_image`` for the pixels of the head.

Pixel convention: u = 0 the left edge (docs/data.md) for ``warp``; OpenCV's integer-centre pixels only inside.
"""

from __future__ import annotations

import numpy as np

from apps.photo.normalize import to_opencv, warp_points
from toolkit.errors import ToolkitError

FEATHER = 0.02
"""Default feather width, a fraction of the crop's side (10 px of a 512² crop): the mask is eroded by it and
blurred over it, so the pasted head fades into the photo inside its outline."""


def feathered_alpha(head_mask: np.ndarray, feather_px: float) -> np.ndarray:
    """[S, S] uint8 0/255 (or bool) mask -> [S, S] float32 alpha in [0, 1]: 0 outside the mask and on the crop's
    border pixels, ramping to 1 over ~``feather_px`` crop pixels inside its edge (eroded by ``feather_px``, then a
    Gaussian of σ = feather_px / 2)."""
    import cv2

    m = (np.asarray(head_mask) > 0).astype(np.float32)
    m[[0, -1]] = 0  # the crop's border rows and columns: nothing is pasted beyond the crop's pixel centres
    m[:, [0, -1]] = 0
    r = max(0.0, float(feather_px))
    if r < 0.5:
        return m
    k = int(round(r))
    # outside the crop counts as not head, so the head fades out at the crop's edges as at its outline
    eroded = cv2.erode(m, cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * k + 1, 2 * k + 1)),
                       borderType=cv2.BORDER_CONSTANT, borderValue=0)
    alpha = np.clip(cv2.GaussianBlur(eroded, (0, 0), r / 2), 0.0, 1.0) * m  # never beyond the mask itself
    alpha[alpha < 1 / 512] = 0  # a blend that would round to the photo's own value anyway
    return alpha


def paste_back(photo_bgr: np.ndarray, crop_bgr: np.ndarray, head_mask: np.ndarray, warp: np.ndarray, *,
               warp_size: int | None = None, feather_px: float | None = None) -> np.ndarray:
    """The photo with the crop's head pasted in.

    Args:
        photo_bgr: [H, W, 3] uint8, the photo the crop was made from (as ``apps.photo.images.load_photo`` gives it).
        crop_bgr: [S, S, 3] uint8, the crop (redirected or not), at any size S.
        head_mask: [S, S] uint8 0/255 or bool, the crop's head mask (the row's ``head_mask``, or the redirected
            row's).
        warp: [3, 3] the row's ``warp``: photo pixels -> pixels of a ``warp_size`` crop.
        warp_size: the crop side ``warp`` maps into (the prepared file's ``--size``; default S). A crop of another
            size is the same square: the map is scaled by S / warp_size.
        feather_px: feather width in pixels of the crop (default :data:`FEATHER` × S).

    Returns a new [H, W, 3] uint8 array: bilinear samples of the crop blended by the feathered mask's alpha;
    every pixel where the alpha is 0 (outside the mask, outside the crop) is the photo's, bit for bit.
    """
    import cv2

    S = crop_bgr.shape[0]
    if crop_bgr.shape[:2] != (S, S) or np.asarray(head_mask).shape != (S, S):
        raise ToolkitError(f"paste_back: expected a square crop and a mask of its size, got {list(crop_bgr.shape)} "
                           f"and {list(np.asarray(head_mask).shape)}")
    W = np.diag([S / (warp_size or S), S / (warp_size or S), 1.0]) @ np.asarray(warp, np.float64)
    H, Wd = photo_bgr.shape[:2]
    corners = warp_points(np.array([[0, 0], [S, 0], [S, S], [0, S]], np.float64), np.linalg.inv(W))
    x0, y0 = np.clip(np.floor(corners.min(0)) - 1, 0, [Wd, H]).astype(int)
    x1, y1 = np.clip(np.ceil(corners.max(0)) + 1, 0, [Wd, H]).astype(int)
    out = photo_bgr.copy()
    if x1 <= x0 or y1 <= y0:
        return out
    shift = np.array([[1.0, 0, x0], [0, 1.0, y0], [0, 0, 1.0]])  # region pixels -> photo pixels
    M = to_opencv(W @ shift)  # region -> crop, OpenCV pixels: sampled with WARP_INVERSE_MAP
    size = (int(x1 - x0), int(y1 - y0))
    flags = cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP
    pasted = cv2.warpPerspective(crop_bgr, M, size, flags=flags, borderMode=cv2.BORDER_CONSTANT)
    alpha = feathered_alpha(head_mask, FEATHER * S if feather_px is None else feather_px)
    a = cv2.warpPerspective(alpha, M, size, flags=flags, borderMode=cv2.BORDER_CONSTANT, borderValue=0)[..., None]
    region = out[y0:y1, x0:x1]
    blended = np.clip(np.rint(a * pasted + (1.0 - a) * region), 0, 255).astype(np.uint8)
    out[y0:y1, x0:x1] = np.where(a > 0, blended, region)
    return out
