"""Fixtures of the render tests: the shared headless GL context."""

from __future__ import annotations

import pytest

from tests.gl import skip_without_gl
from toolkit.errors import ToolkitError


@pytest.fixture(scope="module")
def ctx():
    from render.gl_context import shared_context

    try:
        return shared_context()
    except ToolkitError as e:  # no EGL on this machine: the message itself is tested below
        skip_without_gl(f"no headless OpenGL: {e}")
