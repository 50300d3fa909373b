"""A distortion-bearing camera: reconstructions with ``calibrate``'s output match those with the
true calibration (synthetic images of a textured building corner, k1 = -0.25, k2 = 0.08)."""

import pytest
import torch

import torchsfm
from torchsfm.actions import SAMPLE
from torchsfm.calibration.chessboard import detect_chessboard
from torchsfm.calibration.zhang import board_points, calibrate_camera
from torchsfm.evaluation import camera_errors
from torchsfm.geometry.rotation import axis_angle_to_rotation
from torchsfm.images import read_image
from torchsfm.sfm.two_view import TwoViewReconstruction
from torchsfm.testing import (render_chessboard, render_corner_scene, rotation_error_deg, translation_direction_error_deg,
                              visible_board_poses, wide_angle_camera)

K_TRUE, DISTORTION_TRUE = wide_angle_camera()


@pytest.fixture(scope="module")
def calibrated():
    R, t = visible_board_poses(10, 0, K_TRUE, DISTORTION_TRUE)
    corners = torch.stack([detect_chessboard(render_chessboard(K_TRUE, DISTORTION_TRUE, R[v], t[v], (9, 7)), (9, 7)).corners
                           for v in range(10)])
    result = calibrate_camera(board_points((9, 7), 1.0), corners)
    return result.K, result.distortion


@pytest.fixture(scope="module")
def scene():
    """Three views of the corner scene: (images, R (3, 3, 3), t (3, 3))."""
    texture = read_image(SAMPLE / "0004.jpg")
    yaw = torch.tensor([0.0, -0.06, -0.11], dtype=torch.float64)
    centres = torch.tensor([[0.0, 0.0, 0.0], [0.8, 0.1, 0.2], [1.6, 0.0, 0.3]], dtype=torch.float64)
    R = axis_angle_to_rotation(torch.stack([torch.zeros(3, dtype=torch.float64), yaw, torch.zeros(3, dtype=torch.float64)], -1))
    t = -(R @ centres[..., None])[..., 0]
    return [render_corner_scene(texture, K_TRUE, DISTORTION_TRUE, R[v], t[v]) for v in range(3)], R, t


def test_two_view_with_the_calibration_is_as_accurate_as_with_the_truth(calibrated, scene):
    images, R, t = scene
    R_rel, t_rel = R[1] @ R[0].T, t[1] - R[1] @ R[0].T @ t[0]

    def errors(K, distortion):
        model = TwoViewReconstruction()(images[0], images[1], K, distortion=distortion, generator=torch.Generator().manual_seed(0))
        return rotation_error_deg(model.cameras.R[1], R_rel), translation_direction_error_deg(model.cameras.t[1], t_rel)

    truth, ours, ignored = errors(K_TRUE, DISTORTION_TRUE), errors(*calibrated), errors(K_TRUE, torch.zeros(2, dtype=torch.float64))
    assert ours[0] <= 1.5 * truth[0] + 0.02 and ours[1] <= 1.5 * truth[1] + 0.1, (truth, ours)
    assert ignored[0] > 5 * max(ours[0], 0.05)  # the distortion matters here


def test_reconstruct_with_the_calibration_is_as_accurate_as_with_the_truth(calibrated, scene):
    images, R, t = scene

    def errors(K, distortion):
        model = torchsfm.reconstruct(images, K, distortion=distortion, generator=torch.Generator().manual_seed(0))
        assert model.num_views == 3
        result = camera_errors(model.cameras.R, model.cameras.t, R[model.view_indices], t[model.view_indices])
        return float(result.rotation.max()), float(result.centre.max()) / result.extent

    truth, ours = errors(K_TRUE, DISTORTION_TRUE), errors(*calibrated)
    assert ours[0] <= 1.5 * truth[0] + 0.02 and ours[1] <= 1.5 * truth[1] + 0.002, (truth, ours)
