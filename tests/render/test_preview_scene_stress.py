"""Stress tests of render.preview_scene's feature-to-RGB map (a PCA with a percentile normalization, numpy, no
GL): features of zero variance (the normalization's range is 0), a single Gaussian, rank-one features, and
spreads of 1e-30 and 1e30, for feature widths 1, 2, 3 and 8. Colours stay finite and inside [0, 1]."""

from __future__ import annotations

import numpy as np
import pytest

from render.preview_scene import FeatureColors


def _cases(d: int):
    rng = np.random.default_rng(d)
    noise = rng.normal(size=(60, d))
    return {
        "constant": np.full((60, d), 0.3),
        "single": np.ones((1, d)),
        "rank-one": np.outer(np.arange(60), np.linspace(1, 2, d)),
        "tiny-spread": 0.5 + noise * 1e-30,
        "huge-spread": noise * 1e30,
        "float32-max": np.full((4, d), 3e38),
    }


@pytest.mark.parametrize("d", [1, 2, 3, 8])
def test_feature_colours_of_degenerate_and_extreme_features(d):
    for name, f in _cases(d).items():
        f = f.astype(np.float32)
        fmap = FeatureColors(f)
        cols = fmap(f)
        assert cols.shape == (f.shape[0], 3) and np.isfinite(cols).all(), name
        if d != 3:  # D = 3 is the identity map (the features are the colours)
            assert cols.min() >= 0 and cols.max() <= 1, name
        # Gaussians outside the fitted range (moving ones, later frames) are clipped, not blown up.
        far = fmap(np.clip(f.astype(np.float64) * 10 + 1e3, -3e38, 3e38).astype(np.float32))
        assert np.isfinite(far).all(), name
