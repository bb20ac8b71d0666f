"""render: rasterizers that turn a GaussianScene (or a mesh) and cameras into images.

Owns: the differentiable pure-PyTorch Gaussian splatter used for training (``render.splat``), the
moderngl headless preview splatter (``render.preview``) and the GL mesh rasterizer (``render.mesh_gl``).
All share the camera and scene conventions of ``toolkit``; the two GL renderers share one headless EGL
context per process (``render.gl_context``).

May import: toolkit. Heavy optional dependencies (moderngl, open3d, pymeshlab) are imported lazily
inside the functions that need them, so ``import render`` stays light.
"""
