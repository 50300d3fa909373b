"""Calibration on synthetic boards with known K and distortion, and what it buys a reconstruction.

A 640×480 wide-angle camera (fx 500, fy 495, k1 = -0.25, k2 = 0.08), 10 board views:

1. exact corners, no distortion: errors of K and distortion (should be ~0);
2. exact corners + 0.2 px noise (3 seeds): relative errors of fx, fy, cx, cy, k1, k2 and of the
   radial factor k1 r² + k2 r⁴ at the image corner;
3. rendered photos through the chessboard detector: corner error against the truth, and the
   calibration from the detected corners;
4. a textured building corner photographed by the same camera (3 views): relative pose errors of
   the two-view pipeline and camera errors of ``reconstruct`` with the true calibration, with the
   calibration from step 3, and ignoring the distortion.

    python examples/calibration_study.py
"""

from __future__ import annotations

import torch

import torchsfm
from torchsfm.actions import SAMPLE
from torchsfm.calibration.chessboard import detect_chessboard
from torchsfm.calibration.zhang import board_points, calibrate_camera, project_board
from torchsfm.evaluation import camera_errors
from torchsfm.geometry.rotation import axis_angle_to_rotation
from torchsfm.images import read_image
from torchsfm.sfm.two_view import TwoViewReconstruction
from torchsfm.testing import (render_chessboard, render_corner_scene, rotation_error_deg, translation_direction_error_deg,
                              visible_board_poses, wide_angle_camera)

PATTERN = (9, 7)
BOARD = board_points(PATTERN, 1.0)


def describe(K: torch.Tensor, distortion: torch.Tensor, K_true: torch.Tensor, distortion_true: torch.Tensor) -> str:
    corner_r2 = float(((torch.tensor([640.0, 480.0], dtype=torch.float64) - K_true[:2, 2]) / K_true.diagonal()[:2]).square().sum())
    factor = lambda d: float(d[0] * corner_r2 + d[1] * corner_r2**2)  # noqa: E731
    parts = [f"{name} {100 * (float(K[i, j]) / float(K_true[i, j]) - 1):+.3f}%" for name, i, j in
             (("fx", 0, 0), ("fy", 1, 1), ("cx", 0, 2), ("cy", 1, 2))]
    parts += [f"k{k + 1} {100 * (float(distortion[k]) / float(distortion_true[k]) - 1):+.2f}%" for k in range(2)]
    parts.append(f"radial factor at the corner {100 * (factor(distortion) / factor(distortion_true) - 1):+.2f}%")
    return ", ".join(parts)


def main() -> None:
    torch.set_num_threads(2)
    K_true, distortion_true = wide_angle_camera()
    zero = torch.zeros(2, dtype=torch.float64)

    R, t = visible_board_poses(10, 1, K_true, zero)
    exact = calibrate_camera(BOARD, project_board(K_true, zero, R, t, BOARD))
    print(f"1. exact corners, no distortion: max |K error| {float((exact.K - K_true).abs().max()):.2e} px, "
          f"max |distortion| {float(exact.distortion.abs().max()):.2e}, RMS {exact.rms:.2e} px")

    R, t = visible_board_poses(10, 0, K_true, distortion_true)
    truth = project_board(K_true, distortion_true, R, t, BOARD)
    print("2. 0.2 px noise, 10 views:")
    for seed in range(3):
        noisy = truth + 0.2 * torch.randn(truth.shape, generator=torch.Generator().manual_seed(seed), dtype=torch.float64)
        result = calibrate_camera(BOARD, noisy)
        print(f"   seed {seed}: {describe(result.K, result.distortion, K_true, distortion_true)}, RMS {result.rms:.3f} px")

    detected, gaps = [], []
    for view in range(10):
        corners = detect_chessboard(render_chessboard(K_true, distortion_true, R[view], t[view], PATTERN), PATTERN).corners
        gaps.append(torch.minimum((corners - truth[view]).norm(dim=-1), (corners - truth[view].flip(0)).norm(dim=-1)))
        detected.append(corners)
    gaps = torch.cat(gaps)
    calibrated = calibrate_camera(BOARD, torch.stack(detected))
    print(f"3. rendered photos: corners found 10/10, error median {float(gaps.median()):.3f} px, max {float(gaps.max()):.3f} px; "
          f"calibration: {describe(calibrated.K, calibrated.distortion, K_true, distortion_true)}, RMS {calibrated.rms:.3f} px")

    texture = read_image(SAMPLE / "0004.jpg")
    yaw = torch.tensor([0.0, -0.06, -0.11], dtype=torch.float64)
    centres = torch.tensor([[0.0, 0.0, 0.0], [0.8, 0.1, 0.2], [1.6, 0.0, 0.3]], dtype=torch.float64)
    R_scene = axis_angle_to_rotation(torch.stack([torch.zeros(3, dtype=torch.float64), yaw, torch.zeros(3, dtype=torch.float64)], -1))
    t_scene = -(R_scene @ centres[..., None])[..., 0]
    images = [render_corner_scene(texture, K_true, distortion_true, R_scene[v], t_scene[v]) for v in range(3)]
    R_rel, t_rel = R_scene[1], t_scene[1]
    print("4. building corner, 3 views:")
    for name, K, distortion in (("true calibration", K_true, distortion_true), ("calibrate's output", calibrated.K, calibrated.distortion),
                                ("distortion ignored", K_true, zero)):
        pair = TwoViewReconstruction()(images[0], images[1], K, distortion=distortion, generator=torch.Generator().manual_seed(0))
        model = torchsfm.reconstruct(images, K, distortion=distortion, generator=torch.Generator().manual_seed(0))
        errors = camera_errors(model.cameras.R, model.cameras.t, R_scene[model.view_indices], t_scene[model.view_indices])
        print(f"   {name:20s} two-view: R {rotation_error_deg(pair.cameras.R[1], R_rel):.4f} deg, t "
              f"{translation_direction_error_deg(pair.cameras.t[1], t_rel):.4f} deg, {pair.num_points} points; reconstruct: "
              f"{model.num_views} views, rotation max {float(errors.rotation.max()):.4f} deg, centre max "
              f"{100 * float(errors.centre.max()) / errors.extent:.3f}% of the path, RMS {model.reprojection_rms():.3f} px")


if __name__ == "__main__":
    main()
