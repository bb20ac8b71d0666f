"""Head and eye masks of a normalized crop from its landmarks, without face-parsing weights.

**Head**: a region built from the landmarks (the jaw line below; above the ear-level jaw ends a half ellipse as
high as :data:`HEAD_TOP` × the eye-line-to-chin distance, :data:`HEAD_WIDTH` × the jaw's width wide, for the
forehead and hair), cut to the person by mediapipe's SelfieSegmentation run on the crop itself (probability >
:data:`PERSON_THRESHOLD`), then joined with the face outline and the eyes, which are always head. The selfie
model separates a person from the background but not the head from the neck and shoulders, which the region
leaves out; the region alone (no segmenter) over-covers hair-less backgrounds. ``cv2.grabCut`` seeded from the
landmarks (the region probable foreground, the face sure foreground) was the alternative: on skimage's astronaut
its mask agreed with this one to IoU 0.96 but took ~1 s a 512² crop (5 iterations) against ~6 ms.

**Eyes**: the eyelid margins (mediapipe's 16-point eyelid loops, else iBUG 36-41 / 42-47) filled: the visible
eyeball, as the generator's eye masks are.

All polygons are in crop pixels, u = 0 the left edge; filled with OpenCV's sub-pixel ``shift`` so a pixel is in
when its centre is.
"""

from __future__ import annotations

import numpy as np

HEAD_TOP = 1.3
"""Height of the head region above the line through the ear-level jaw ends (iBUG 0, 16), in eye-line-to-chin
distances: the eyes lie about halfway down an adult's head, hair adds to it; the person mask trims the rest."""
HEAD_WIDTH = 1.45
"""Width of the head region's upper half over the distance between iBUG 0 and 16 (hair and ears beyond the jaw;
the person mask trims the background)."""
PERSON_THRESHOLD = 0.5
SHIFT = 4  # bits of sub-pixel precision in cv2.fillPoly


def fill_polygons(size: int, polygons: list[np.ndarray]) -> np.ndarray:
    """[size, size] uint8 0/255: each polygon [K, 2] (u = 0 left-edge pixels) filled, pixel centres inside."""
    import cv2

    mask = np.zeros((size, size), np.uint8)
    pts = [np.round((np.asarray(p, np.float64) - 0.5) * (1 << SHIFT)).astype(np.int32) for p in polygons]
    cv2.fillPoly(mask, pts, 255, lineType=cv2.LINE_8, shift=SHIFT)
    return mask


def head_region(landmarks68: np.ndarray, n_cap: int = 24) -> np.ndarray:
    """[68, 2] crop landmarks -> [17 + n_cap, 2] polygon: the jaw (0 -> 16) then a half ellipse back over the
    top of the head (:data:`HEAD_TOP`, :data:`HEAD_WIDTH`)."""
    lm = np.asarray(landmarks68, np.float64)
    a, b = lm[0], lm[16]
    mid = 0.5 * (a + b)
    across = (b - a) / max(np.linalg.norm(b - a), 1e-9)
    up = np.array([across[1], -across[0]])  # the image's up when the jaw runs left to right
    eye_line = 0.5 * (lm[36:42].mean(0) + lm[42:48].mean(0))
    chin_to_eyes = abs(float((lm[8] - eye_line) @ up))
    half_w = 0.5 * HEAD_WIDTH * np.linalg.norm(b - a)
    theta = np.linspace(0.0, np.pi, n_cap)  # from b's side over the top to a's side
    cap = mid + np.outer(np.cos(theta) * half_w, across) + np.outer(np.sin(theta) * HEAD_TOP * chin_to_eyes, up)
    return np.concatenate([lm[0:17], cap])


def head_mask(size: int, landmarks68: np.ndarray, outline: np.ndarray, eyelids: np.ndarray,
              person: np.ndarray | None = None) -> np.ndarray:
    """[size, size] uint8 0/255 head mask of a crop: the convex hull of :func:`head_region` cut by ``person`` ([size, size]
    probabilities, optional), joined with ``outline`` [K, 2] (the face, always head) and ``eyelids`` [2, L, 2]."""
    import cv2

    hull = cv2.convexHull(head_region(landmarks68).astype(np.float32))[:, 0]
    region = fill_polygons(size, [hull])
    if person is not None:
        region &= np.where(person > PERSON_THRESHOLD, 255, 0).astype(np.uint8)
    return region | fill_polygons(size, [outline]) | fill_polygons(size, list(eyelids))


def eye_masks(size: int, eyelids: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(left, right) [size, size] uint8 0/255: each eyelid loop [L, 2] filled; image-left eye first."""
    return fill_polygons(size, [eyelids[0]]), fill_polygons(size, [eyelids[1]])
