"""toolkit: the shared Gaussian scene format, cameras, rotations, atomic I/O and the error type.

Owns every convention the other packages speak (see README "Conventions"): OpenCV camera axes,
wxyz quaternions, ETH-XGaze gaze pitch/yaw, safetensors + JSON storage, the graphdeco 3DGS PLY layout.

May import: nothing of ours (only torch, numpy, safetensors and the standard library).
"""

from toolkit.errors import ToolkitError

__all__ = ["ToolkitError"]
