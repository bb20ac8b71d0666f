"""The evaluation tests' subject files: one frame (each pair's input and target share their gaze) and two."""

import pytest

from tests.train.helpers import one_frame_subject_file


@pytest.fixture(scope="module")
def subject_file(tmp_path_factory):
    return one_frame_subject_file(tmp_path_factory.mktemp("eval"), subject_seed=5, frame_seed=2)


@pytest.fixture(scope="module")
def two_frame_file(tmp_path_factory):
    """Two frames: every pair's target has another gaze than its input."""
    return one_frame_subject_file(tmp_path_factory.mktemp("eval2"), subject_seed=6, frame_seed=3, n_frames=2)
