"""Self-calibration of views with different principal points (one camera, some views turned)."""

from __future__ import annotations

import torch

from torchsfm.geometry.fundamental import fundamental_from_pose
from torchsfm.geometry.rotation import axis_angle_to_rotation
from torchsfm.geometry.self_calibration import focal_from_fundamentals, intrinsics
from torchsfm.sfm.view_pairs import about_centres


def test_pairs_of_landscape_and_portrait_views_give_the_focal_length_about_their_centres():
    """Exact F between views whose principal points differ (640 × 480 and 480 × 640 images of a
    camera with f = 700 px): taken about each view's centre, every pair's F has one K with the
    principal point at the origin, and the focal length comes out to 1e-6 from a prior 40 % off."""
    g = torch.Generator().manual_seed(0)
    centres = [torch.tensor([319.5, 239.5], dtype=torch.float64), torch.tensor([239.5, 319.5], dtype=torch.float64)]
    F = []
    for k in range(6):
        ci, cj = centres[k % 2], centres[(k // 2) % 2]
        R = axis_angle_to_rotation((torch.rand(3, generator=g, dtype=torch.float64) - 0.5) * 0.4)
        t = torch.randn(3, generator=g, dtype=torch.float64)
        F.append(about_centres(fundamental_from_pose(intrinsics(700.0, ci), intrinsics(700.0, cj), R, t), ci, cj))
    focal = focal_from_fundamentals(torch.stack(F), torch.zeros(2, dtype=torch.float64), prior=1.4 * 700.0)
    assert abs(focal / 700.0 - 1) < 1e-6
