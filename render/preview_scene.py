"""Scene-level helpers of the preview: a fixed per-scene feature-to-RGB map and the eye Gaussians that move
with gaze (the preview's dynamic set, bounded by each eyeball's sphere)."""

from __future__ import annotations

import numpy as np

from render.preview_footprints import as_float32
from toolkit.errors import ToolkitError


class FeatureColors:
    """A fixed per-scene map from features [N, D] to RGB [N, 3]: identity for D = 3, else a PCA to RGB.

    The PCA (and its 1st–99th percentile normalization to [0, 1]) is fitted once, on the scene it is built
    from, so colours stay put while the Gaussians move. D = 1 is shown as grey, D = 2 as (red, green).
    """

    def __init__(self, features):
        f = as_float32(features, "features", (None, None)).astype(np.float64)
        self.dim = f.shape[1]
        self.mean = f.mean(0) if f.shape[0] else np.zeros(self.dim)
        if self.dim == 3:
            self.basis = None
            return
        if self.dim < 3:
            self.basis = np.eye(self.dim, 3) if self.dim == 2 else np.ones((1, 3))
        else:
            sub = f[np.random.default_rng(0).permutation(f.shape[0])[:20000]] - self.mean
            basis = np.zeros((self.dim, 3))
            if sub.shape[0]:
                _, _, vt = np.linalg.svd(sub, full_matrices=False)
                basis[:, :min(3, vt.shape[0])] = vt[:3].T  # fewer than 3 Gaussians span fewer than 3 axes
            basis *= np.sign(basis[np.abs(basis).argmax(0), range(3)])  # a deterministic sign per axis
            self.basis = basis
        proj = (f - self.mean) @ self.basis if f.shape[0] else np.zeros((1, 3))
        self.lo, self.hi = np.percentile(proj, 1, axis=0), np.percentile(proj, 99, axis=0)

    def __call__(self, features) -> np.ndarray:
        f = as_float32(features, "features", (None, self.dim))
        if self.basis is None:
            return f
        proj = (f.astype(np.float64) - self.mean) @ self.basis
        return np.clip((proj - self.lo) / np.maximum(self.hi - self.lo, 1e-12), 0, 1).astype(np.float32)


def scene_colors(scene, feature_map=None) -> np.ndarray:
    """[N, 3] display colours of a scene's features (see :class:`FeatureColors`)."""
    fmap = feature_map if feature_map is not None else FeatureColors(scene.features)
    return fmap(scene.features)


def eye_dynamics(scene):
    """(dynamic [N] bool of the eye Gaussians or None, [(centre [3], radius)] of each eye's sphere of means)."""
    from toolkit.eyes import EYE_PARTS, eyeball_info

    part = scene.part.detach().cpu().numpy()
    dynamic = (part == 1) | (part == 2)
    if not dynamic.any():
        return None, None
    try:
        info = eyeball_info(scene)
    except ToolkitError:
        return dynamic, None  # too few eye Gaussians for a sphere: layers fall back to the depth range
    means = scene.means.detach().cpu().numpy()
    spheres = []
    for name, eye in info.items():
        c = eye["center"].detach().cpu().numpy().astype(np.float64)
        m = means[part == EYE_PARTS[name]]
        spheres.append((c, float(np.linalg.norm(m - c, axis=1).max()) * (1 + 1e-5) + 1e-9))
    return dynamic, spheres
