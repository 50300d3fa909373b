"""torchsfm: structure from motion as PyTorch/Kornia tensor pipelines.

Stable entry points (outside code calls these):

* :func:`estimate_fundamental` — robust F from pixel correspondences.
* :func:`estimate_relative_pose` — R, t and 3-D points of two calibrated views.
* :func:`triangulate` — 3-D points from two views by any method of thesis §3.5.
"""

from torchsfm.camera import Camera
from torchsfm.config import Config, load_config, with_overrides
from torchsfm.errors import (
    ConfigError,
    DegenerateConfigurationError,
    InputError,
    NotEnoughDataError,
    ShapeError,
    TorchSfmError,
)
from torchsfm.geometry.triangulation import TRIANGULATION_METHODS, triangulate
from torchsfm.sfm.two_view_geometry import (
    FundamentalEstimate,
    RelativePose,
    RelativePoseEstimator,
    RobustFundamental,
    estimate_fundamental,
    estimate_relative_pose,
)

__version__ = "0.1.0"

__all__ = [
    "Camera",
    "Config",
    "ConfigError",
    "DegenerateConfigurationError",
    "FundamentalEstimate",
    "InputError",
    "NotEnoughDataError",
    "RelativePose",
    "RelativePoseEstimator",
    "RobustFundamental",
    "ShapeError",
    "TRIANGULATION_METHODS",
    "TorchSfmError",
    "estimate_fundamental",
    "estimate_relative_pose",
    "load_config",
    "triangulate",
    "with_overrides",
]
