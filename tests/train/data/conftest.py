"""One small synthetic subject file shared by the data tests (2 frames × 18 cameras at 96²)."""

from __future__ import annotations

import pytest

from tests.gl import gl_available, skip_without_gl

EGL = gl_available()
needs_gl = pytest.mark.skipif(not EGL, reason="no headless EGL OpenGL 3.3 context on this machine")


@pytest.fixture(scope="package")
def subject_params():
    from train.data.subject_params import SubjectParams

    return SubjectParams.sample(11)


@pytest.fixture(scope="package")
def subject(subject_params):
    from train.data.synthetic import build_subject

    return build_subject(subject_params)


@pytest.fixture(scope="package")
def subject_file(tmp_path_factory, subject_params, subject):
    if not EGL:
        skip_without_gl("no headless EGL OpenGL 3.3 context on this machine")
    from train.data.format import write_subject_h5
    from train.data.generate import generate_subject

    rows, subj, attrs = generate_subject(subject_params, n_frames=2, res=96, seed=5, subject=subject)
    return write_subject_h5(tmp_path_factory.mktemp("synth") / "subject0000.h5", rows, subject=subj, attrs=attrs)
