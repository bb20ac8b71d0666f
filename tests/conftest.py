"""Shared pytest fixtures: deterministic seeds and small synthetic scenes made by the project itself."""

from __future__ import annotations

import os
import random

import numpy as np
import pytest
import torch
from hypothesis import HealthCheck, settings

# Property tests: `make test` runs a small, derandomized sample (the same examples on every run, no example
# database written); `make fuzz` (HYPOTHESIS_PROFILE=fuzz) runs many more, freshly drawn each time.
settings.register_profile("default", max_examples=25, derandomize=True, database=None, deadline=None,
                          suppress_health_check=[HealthCheck.too_slow])
settings.register_profile("fuzz", max_examples=1000, deadline=None, suppress_health_check=[HealthCheck.too_slow])
settings.load_profile(os.environ.get("HYPOTHESIS_PROFILE", "default"))

# Test tensors are small: extra threads only add overhead, and on a busy 2-core machine they thrash
# (10-50x slowdowns were measured). Benchmarks, not tests, measure multi-threaded speed.
torch.set_num_threads(1)


@pytest.fixture(autouse=True)
def _seed_everything():
    random.seed(0)
    np.random.seed(0)
    torch.manual_seed(0)
    yield


def random_scene(n: int = 50, d: int = 3, sh_degree: int | None = None, seed: int = 0):
    """A small random GaussianScene (all fields filled, mixed part labels)."""
    from toolkit.scene import GaussianScene

    g = torch.Generator().manual_seed(seed)
    sh = None
    if sh_degree is not None:
        sh = torch.randn(n, (sh_degree + 1) ** 2, 3, generator=g)
    return GaussianScene(
        means=torch.randn(n, 3, generator=g),
        quats=torch.randn(n, 4, generator=g),
        log_scales=torch.randn(n, 3, generator=g) - 3,
        opacity_logits=torch.randn(n, generator=g),
        features=torch.rand(n, d, generator=g),
        part=torch.randint(0, 3, (n,), generator=g).to(torch.int8),
        sh=sh,
        metadata={"units": "m", "feature_kind": "rgb" if d == 3 else "neural", "note": "test"},
    )


@pytest.fixture
def scene_factory():
    return random_scene
