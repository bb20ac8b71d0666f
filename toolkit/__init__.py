"""toolkit: the shared Gaussian scene format, cameras, rotations and gaze angles, eyeballs, atomic I/O, the
error type, the one YAML reader (``safe_yaml``), the procedural demo head and ``python -m toolkit``.

Owns every convention the other packages speak (see README "Conventions"): OpenCV camera axes,
wxyz quaternions, ETH-XGaze gaze pitch/yaw, safetensors + JSON storage, the graphdeco 3DGS PLY layout.

May import: nothing of ours (torch, numpy, safetensors, PyYAML and the standard library; scipy lazily, in the
procedural head's nearest-neighbour query).
"""

from toolkit.errors import ToolkitError

__all__ = ["ToolkitError"]
