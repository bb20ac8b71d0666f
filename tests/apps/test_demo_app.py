"""apps/demo.py helpers that run without training."""

import numpy as np
import pytest

from apps.demo import most_frontal
from toolkit.errors import ToolkitError


def test_most_frontal_picks_the_smallest_head_rotation():
    poses = [np.array([0.9, -0.1]), np.array([-0.05, 0.1]), np.array([0.0, -0.6]), np.array([0.2, 0.2])]
    assert most_frontal(poses) == 1
    with pytest.raises(ToolkitError, match="no rows"):
        most_frontal([])
