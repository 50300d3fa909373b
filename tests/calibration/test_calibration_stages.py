"""Calibration as stages: a prefix on real photos, a user-written detector in place of
DetectBoards, and the failures the last stage reports."""

import pytest
import torch
from torch import nn
from torch.testing import assert_close

from torchsfm.calibration.stages import BoardViews, CalibrateFromBoards, DetectBoards, calibration_stages
from torchsfm.calibration.zhang import board_points, project_board
from torchsfm.errors import NotEnoughDataError
from torchsfm.testing import visible_board_poses, wide_angle_camera

PATTERN = (9, 7)
K_TRUE, DISTORTION_TRUE = wide_angle_camera()


class KnownCorners(nn.Module):
    """A user's stage in place of DetectBoards: the exact corners of synthetic board views."""

    def forward(self, state: BoardViews) -> BoardViews:
        R, t = visible_board_poses(len(state.names), 0, K_TRUE, DISTORTION_TRUE)
        corners = project_board(K_TRUE, DISTORTION_TRUE, R, t, board_points(state.pattern, state.square))
        state.corners = dict(zip(state.names, corners))
        state.sizes = {(640, 480)}
        return state


def test_a_user_detector_in_place_of_detect_boards():
    pipeline = calibration_stages()
    assert [type(stage) for stage in pipeline] == [DetectBoards, CalibrateFromBoards]
    pipeline[0] = KnownCorners()
    state = pipeline(BoardViews(images=[], names=[f"view{v}" for v in range(8)], pattern=PATTERN, square=1.0))
    assert_close(state.calibration.K, K_TRUE, rtol=1e-6, atol=1e-6)
    assert_close(state.calibration.distortion, DISTORTION_TRUE, rtol=1e-5, atol=1e-7)
    assert set(state.timings) == {"KnownCorners", "CalibrateFromBoards"}


def test_too_few_boards_name_the_photos_without_one():
    state = BoardViews(images=[], names=["a.jpg", "b.jpg"], pattern=PATTERN, square=25.0, sizes={(640, 480)},
                       corners={"a.jpg": torch.zeros(63, 2, dtype=torch.float64)}, not_found={"b.jpg": "no corner lattice found"})
    with pytest.raises(NotEnoughDataError, match="b.jpg: no corner lattice found"):
        CalibrateFromBoards()(state)


def test_the_detection_prefix_on_real_photos(shared_data):
    paths = sorted((shared_data / "chessboard_c920_9x7").glob("*.jpg"))
    state = calibration_stages()[:1](BoardViews(images=paths, names=[p.name for p in paths], pattern=PATTERN, square=25.0))
    assert len(state.corners) == len(paths) and not state.not_found and state.calibration is None
    assert all(corners.shape == (63, 2) for corners in state.corners.values()) and len(state.sizes) == 1
