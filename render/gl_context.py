"""The headless OpenGL context of the process: one EGL context shared by every GL user of ``render``.

The mesh rasterizer (``render.mesh_gl``) and the preview splatter (``render.preview``) both draw through
:func:`shared_context`. One context per process, because EGL contexts are slow to make and because with two
standalone contexts in one process a GL call can land in the other context's objects. A window (glfw)
brings its own context and passes it to the renderers instead.

moderngl is imported inside the functions: importing ``render`` stays light.
"""

from __future__ import annotations

import ctypes.util
import os
from typing import Any

from toolkit.errors import ToolkitError

GL_VERSION = 330  # GL 3.3 core: no SSBOs, float render targets, instancing

_SHARED_CONTEXT: Any = None  # (pid that made it, context)


def _missing_library_hint() -> str:
    """What to install, naming the EGL / GL system libraries the loader cannot find (if any)."""
    missing = [lib for lib in ("EGL", "GL") if ctypes.util.find_library(lib) is None]
    if not missing:
        return "EGL is present but gave no OpenGL 3.3 core context (Debian: apt-get install libgl1-mesa-dri)"
    return (f"missing system librar{'y' if len(missing) == 1 else 'ies'} "
            + ", ".join(f"lib{m}.so" for m in missing)
            + " (Debian: apt-get install libegl1 libgl1 libgl1-mesa-dri)")


def create_context():
    """A new standalone OpenGL 3.3 core context through EGL, made current on creation.

    Raises a ToolkitError naming what is missing: the moderngl package, or the EGL / GL system libraries
    (with what moderngl said).
    """
    try:
        import moderngl
    except ImportError as e:
        raise ToolkitError(f"headless OpenGL needs the Python package 'moderngl' ({e}); pip install moderngl") from None
    try:
        return moderngl.create_context(standalone=True, backend="egl", require=GL_VERSION)
    except Exception as e:  # moderngl/glcontext raise plain Exceptions for missing libraries or drivers
        raise ToolkitError(f"cannot create a headless OpenGL 3.3 context through EGL: {_missing_library_hint()}; "
                           f"moderngl said: {type(e).__name__}: {str(e).strip()[:160]}") from None


def shared_context():
    """The process's one headless context, created on first use (what the renderers use by default).

    EGL does not survive ``fork``: a child forked after the parent initialised GL can neither use the
    parent's context nor reliably create its own (Mesa hangs), so it gets a ToolkitError instead.
    """
    global _SHARED_CONTEXT
    if _SHARED_CONTEXT is not None and _SHARED_CONTEXT[0] != os.getpid():
        raise ToolkitError(
            "render.gl_context: this process was forked after OpenGL was initialised in its parent; EGL cannot "
            "be used here. Start workers with the 'spawn' method (e.g. DataLoader(multiprocessing_context="
            "'spawn')) or render before/without forking"
        )
    if _SHARED_CONTEXT is None:
        _SHARED_CONTEXT = (os.getpid(), create_context())
    return _SHARED_CONTEXT[1]


def make_current(ctx) -> None:
    """Make a standalone moderngl context current on this thread.

    A process can hold several GL contexts (the shared one, a glfw window's, one a caller made) and every GL
    call goes to whichever is current, so each entry point that touches GL claims its context first.
    """
    ctx.__enter__()  # glcontext: make current (remembering the previous one for a matching __exit__)
