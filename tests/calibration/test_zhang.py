"""Zhang's method (Appendix A with the ERRATA's u0) on exact and noisy synthetic corners."""

import math

import pytest
import torch
from torch.testing import assert_close

from torchsfm.calibration.zhang import board_points, calibrate_camera, intrinsics_from_homographies, project_board, view_homographies
from torchsfm.config import LMConfig
from torchsfm.errors import DegenerateConfigurationError, NotEnoughDataError, ShapeError
from torchsfm.geometry.rotation import axis_angle_to_rotation

from torchsfm.testing import visible_board_poses, wide_angle_camera

PATTERN = (9, 7)
K_TRUE, DISTORTION_TRUE = wide_angle_camera()

BOARD = board_points(PATTERN, 1.0)


def test_exact_without_noise_and_distortion():
    """float64, exact corners, no distortion: K to 1e-6 (relative), distortion 0 to 1e-8."""
    R, t = visible_board_poses(10, 1, K_TRUE, torch.zeros(2, dtype=torch.float64))
    corners = project_board(K_TRUE, torch.zeros(2, dtype=torch.float64), R, t, BOARD)
    result = calibrate_camera(BOARD, corners)
    assert_close(result.K, K_TRUE, rtol=1e-6, atol=1e-6)
    assert_close(result.distortion, torch.zeros(2, dtype=torch.float64), rtol=0, atol=1e-8)
    assert result.rms < 1e-6
    assert_close(result.R, R, rtol=0, atol=1e-8)


def test_closed_form_is_exact_with_skew():
    """The closed form alone (eq. A.7 with u0 = γ v0 / β − B13 α² / λ) recovers a skewed K."""
    K = K_TRUE.clone()
    K[0, 1] = 3.0
    R, t = visible_board_poses(5, 2, K, torch.zeros(2, dtype=torch.float64))
    corners = project_board(K, torch.zeros(2, dtype=torch.float64), R, t, BOARD)
    H = view_homographies(BOARD, corners, LMConfig())
    assert_close(intrinsics_from_homographies(H), K, rtol=1e-7, atol=1e-7)


def _radial_factor(distortion: torch.Tensor, r2: float) -> float:
    return float(distortion[0] * r2 + distortion[1] * r2 * r2)


def test_noisy_corners_with_distortion():
    """0.2 px noise, 10 views, k1 = -0.25, k2 = 0.08, over 3 seeds: K within 0.5%; the radial
    distortion k1 r² + k2 r⁴ at the image corner within 5%, k1 within 5%, k2 within 10% (k1 and
    k2 trade off: k2 alone is the least determined; measured up to 5.1% off)."""
    R, t = visible_board_poses(10, 0, K_TRUE, DISTORTION_TRUE)
    exact = project_board(K_TRUE, DISTORTION_TRUE, R, t, BOARD)
    for seed in range(3):
        noisy = exact + 0.2 * torch.randn(exact.shape, generator=torch.Generator().manual_seed(seed), dtype=torch.float64)
        result = calibrate_camera(BOARD, noisy)
        entries = [(0, 0), (1, 1), (0, 2), (1, 2)]
        for i, j in entries:
            assert abs(float(result.K[i, j] / K_TRUE[i, j]) - 1) < 0.005, (seed, i, j, result.K)
        corner_r2 = float(((torch.tensor([640.0, 480.0], dtype=torch.float64) - K_TRUE[:2, 2]) / K_TRUE.diagonal()[:2]).square().sum())
        truth = _radial_factor(DISTORTION_TRUE, corner_r2)
        assert abs(_radial_factor(result.distortion, corner_r2) / truth - 1) < 0.05, (seed, result.distortion)
        assert abs(float(result.distortion[0] / DISTORTION_TRUE[0]) - 1) < 0.05
        assert abs(float(result.distortion[1] / DISTORTION_TRUE[1]) - 1) < 0.10
        assert 0.2 < result.rms < 0.35  # 2-D RMS: about 0.2 sqrt(2)


def test_parallel_views_are_degenerate():
    """Boards that only turn about the view axis and translate: every view parallel to the image."""
    R = axis_angle_to_rotation(torch.tensor([[0, 0, a] for a in (0.0, 0.3, -0.4, 0.8)], dtype=torch.float64))
    t = torch.tensor([[-4.0, -3.0, 12.0], [-3.0, -2.0, 13.0], [-5.0, -3.5, 11.0], [-2.5, -4.0, 14.0]], dtype=torch.float64)
    corners = project_board(K_TRUE, torch.zeros(2, dtype=torch.float64), R, t, BOARD)
    with pytest.raises(DegenerateConfigurationError, match="parallel"):
        calibrate_camera(BOARD, corners)


def test_bad_input():
    R, t = visible_board_poses(3, 3, K_TRUE, DISTORTION_TRUE)
    corners = project_board(K_TRUE, DISTORTION_TRUE, R, t, BOARD)
    with pytest.raises(NotEnoughDataError, match="at least 3 views"):
        calibrate_camera(BOARD, corners[:2])
    with pytest.raises(ShapeError, match="image_points"):
        calibrate_camera(BOARD, corners[:, :10])
    assert math.isfinite(calibrate_camera(BOARD, corners).rms)


def test_analytic_jacobians_equal_forward_mode_autodiff():
    """The two LMs' analytic Jacobians (the board homographies; K, distortion and the poses
    with R ← exp([ω]x) R) against forward-mode autodiff of the same residuals, at a distorted
    state off the optimum: 1e-9 relative."""
    from torchsfm.calibration import zhang
    from torchsfm.optim.lm import forward_jacobian

    R, t = visible_board_poses(4, 3, K_TRUE, DISTORTION_TRUE)
    distortion = torch.tensor([-0.2, 0.05], dtype=torch.float64)
    state = torch.cat([torch.tensor([610.0, 590.0, 322.0, 236.0], dtype=torch.float64), distortion,
                       torch.cat([R.flatten(1), t], -1).flatten()])[None]
    image = project_board(K_TRUE, DISTORTION_TRUE, R, t, BOARD)

    def residuals(params):
        return (project_board(*zhang._unpack(params[0], 4), BOARD) - image).reshape(1, -1)

    expected = forward_jacobian(residuals, state, zhang._retract, 6 + 6 * 4)[0]
    analytic = zhang._projection_jacobian(*zhang._unpack(state[0], 4), BOARD)
    assert_close(analytic, expected, rtol=1e-9, atol=1e-9 * float(expected.abs().max()))

    H = view_homographies(BOARD, image, LMConfig()).flatten(1)[:, :8] * 1.01  # off the optimum
    points = torch.cat([BOARD, torch.ones_like(BOARD[:, :1])], -1)
    expected = forward_jacobian(lambda h: (zhang._map_board(h, points)[1] - image).flatten(1), H, lambda p, d: p + d, 8)
    assert_close(zhang._homography_jacobian(H, points), expected, rtol=1e-9, atol=1e-9 * float(expected.abs().max()))
