"""torchsfm: structure from motion as PyTorch/Kornia tensor pipelines.

Stable entry points (outside code calls these):

* :func:`estimate_fundamental` — robust F from pixel correspondences.
* :func:`estimate_relative_pose` — R, t and 3-D points of two calibrated views.
* :func:`triangulate` — 3-D points from two views by any method of thesis §3.5.
* :func:`estimate_absolute_pose` — a calibrated camera from 3-D↔2-D pairs.
* :func:`reconstruct` — a calibrated image sequence to cameras and points.
* :func:`reconstruct_tracks` — the same from (F, N, 2) tracks with gaps.
* :func:`reconstruct_motions` — one model per rigid motion of tracks: the static scene and
  each moving body in its own frame.
* :func:`bundle_adjust`, :func:`torchsfm.io.read_bal` — sparse bundle adjustment.
* :func:`reject_moving_objects` — IMOR + RANSAC on points tracked over three frames.
* :func:`reject_moving_objects_in_tracks` — the same over whole tracks with gaps.
* :func:`segment_motions` — every independent rigid motion among tracks (number found).
* :func:`detect_chessboard`, :func:`calibrate_camera` — chessboard corners and Zhang's calibration.
"""

from torchsfm.calibration.chessboard import detect_chessboard
from torchsfm.calibration.zhang import Calibration, board_points, calibrate_camera
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
from torchsfm.moving.imor import MovingObjectRejection, reject_moving_objects
from torchsfm.moving.segmentation import MotionSegmentation, segment_motions
from torchsfm.moving.whole_track import TrackRejection, reject_moving_objects_in_tracks
from torchsfm.optim.bundle import BundleProblem, BundleResult, bundle_adjust
from torchsfm.estimators.absolute_pose import AbsolutePose, estimate_absolute_pose
from torchsfm.sfm.from_tracks import MotionModels, reconstruct_motions, reconstruct_tracks
from torchsfm.sfm.incremental import reconstruct
from torchsfm.reconstruction import Reconstruction
from torchsfm.estimators.two_view_geometry import (
    FundamentalEstimate,
    RelativePose,
    RelativePoseEstimator,
    RobustFundamental,
    estimate_fundamental,
    estimate_relative_pose,
)

__version__ = "0.1.0"

__all__ = [
    "AbsolutePose",
    "BundleProblem",
    "BundleResult",
    "Calibration",
    "Camera",
    "Config",
    "ConfigError",
    "DegenerateConfigurationError",
    "FundamentalEstimate",
    "InputError",
    "MotionModels",
    "MotionSegmentation",
    "MovingObjectRejection",
    "NotEnoughDataError",
    "Reconstruction",
    "RelativePose",
    "RelativePoseEstimator",
    "RobustFundamental",
    "ShapeError",
    "TRIANGULATION_METHODS",
    "TorchSfmError",
    "TrackRejection",
    "board_points",
    "bundle_adjust",
    "calibrate_camera",
    "detect_chessboard",
    "estimate_absolute_pose",
    "estimate_fundamental",
    "estimate_relative_pose",
    "load_config",
    "reconstruct",
    "reconstruct_motions",
    "reconstruct_tracks",
    "reject_moving_objects",
    "reject_moving_objects_in_tracks",
    "segment_motions",
    "triangulate",
    "with_overrides",
]
