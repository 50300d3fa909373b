"""Chessboard detection on rendered boards and on real photos (../shared/data/chessboard_c920_9x7)."""

import pytest
import torch

from torchsfm.calibration.chessboard import detect_chessboard
from torchsfm.calibration.zhang import board_points, calibrate_camera, project_board
from torchsfm.images import read_image
from torchsfm.testing import render_chessboard, visible_board_poses, wide_angle_camera

PATTERN = (9, 7)
K_TRUE, DISTORTION_TRUE = wide_angle_camera()

BOARD = board_points(PATTERN, 1.0)


@pytest.fixture(scope="module")
def boards():
    """(R, t) of 10 board views fully inside the image of the distorted camera."""
    return visible_board_poses(10, 0, K_TRUE, DISTORTION_TRUE)
# OpenCV's result on the same 7 photos (PROVENANCE.md of the data set): 5 coefficients
OPENCV_FX, OPENCV_FY, OPENCV_RMS = 1485.9, 1376.3, 1.83


def test_rendered_boards_are_found_in_order_and_to_a_tenth_of_a_pixel(boards):
    R, t = boards
    truth = project_board(K_TRUE, DISTORTION_TRUE, R, t, BOARD)
    errors = []
    for view in range(R.shape[0]):
        detection = detect_chessboard(render_chessboard(K_TRUE, DISTORTION_TRUE, R[view], t[view], PATTERN), PATTERN)
        assert detection.found, (view, detection.reason)
        direct = (detection.corners - truth[view]).norm(dim=-1)
        rotated = (detection.corners - truth[view].flip(0)).norm(dim=-1)  # the board turned by 180 degrees
        errors.append(direct if direct.max() < rotated.max() else rotated)
        assert errors[-1].max() < 0.5  # the truth's order or turned by 180 degrees, never mirrored
    errors = torch.cat(errors)
    assert float(errors.median()) < 0.1 and float(errors.max()) < 0.5


def test_rendered_calibration_recovers_the_camera(boards):
    """10 rendered views through the detector: K within 0.5%, distortion within 5%."""
    R, t = boards
    corners = torch.stack([detect_chessboard(render_chessboard(K_TRUE, DISTORTION_TRUE, R[v], t[v], PATTERN), PATTERN).corners
                           for v in range(R.shape[0])])
    result = calibrate_camera(BOARD, corners)
    for i, j in ((0, 0), (1, 1), (0, 2), (1, 2)):
        assert abs(float(result.K[i, j] / K_TRUE[i, j]) - 1) < 0.005
    assert ((result.distortion - DISTORTION_TRUE).abs() < 0.05 * DISTORTION_TRUE.abs()).all(), result.distortion


def test_no_board_and_wrong_pattern_are_reported(boards):
    R, t = boards
    noise = (torch.rand(1, 480, 640, generator=torch.Generator().manual_seed(0)) * 255).to(torch.uint8)
    missing = detect_chessboard(noise, PATTERN)
    assert not missing.found and missing.reason
    wrong = detect_chessboard(render_chessboard(K_TRUE, DISTORTION_TRUE, R[0], t[0], PATTERN), (8, 6))
    assert not wrong.found and "9x7" in wrong.reason.replace("7x9", "9x7")


def test_real_photos_agree_with_opencv(shared_data):
    paths = sorted((shared_data / "chessboard_c920_9x7").glob("*.jpg"))
    detections = [detect_chessboard(read_image(path), PATTERN) for path in paths]
    assert all(d.found for d in detections), [d.reason for d in detections]
    result = calibrate_camera(BOARD, torch.stack([d.corners for d in detections]))
    assert abs(float(result.K[0, 0]) / OPENCV_FX - 1) < 0.02
    assert abs(float(result.K[1, 1]) / OPENCV_FY - 1) < 0.02
    assert result.rms <= 1.1 * OPENCV_RMS
