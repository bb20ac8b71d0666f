"""train.losses: what training and evaluation score — the image, gaze and orthogonality losses, the image metrics,
LPIPS, the VGG16 features and ArcFace identity.

The three losses of DiT-Gaze are re-exported here: :class:`ImageLoss` (``image``), :class:`GazeLoss`
(``gaze``), :class:`OrthogonalityLoss` (``orthogonality``).
"""

from train.losses.gaze import GazeLoss, gaze_to_camera, head_to_camera_rotation
from train.losses.image import REGIONS, ImageLoss, ImageLossConfig
from train.losses.metrics import composite_on_white
from train.losses.orthogonality import OrthogonalityLoss

__all__ = ["GazeLoss", "ImageLoss", "ImageLossConfig", "OrthogonalityLoss", "REGIONS", "composite_on_white",
           "gaze_to_camera", "head_to_camera_rotation"]
