"""Focal length from fundamental matrices (Mendonça & Cipolla)."""

from __future__ import annotations

import torch

from torchsfm.geometry.fundamental import fundamental_from_pose
from torchsfm.geometry.rotation import axis_angle_to_rotation
from torchsfm.geometry.self_calibration import focal_from_fundamentals, intrinsics, singular_value_gap


def _pairs(K: torch.Tensor, count: int = 6) -> torch.Tensor:
    g = torch.Generator().manual_seed(0)
    F = []
    for _ in range(count):
        R = axis_angle_to_rotation((torch.rand(3, generator=g, dtype=torch.float64) - 0.5) * 0.4)
        t = torch.randn(3, generator=g, dtype=torch.float64)
        F.append(fundamental_from_pose(K, K, R, t))
    return torch.stack(F)


def test_exact_focal_from_noise_free_pairs():
    """Exact F of six random pairs: the focal length to 1e-6 relative, from a prior 40% off."""
    K = intrinsics(812.5, torch.tensor([319.5, 239.5], dtype=torch.float64))
    focal = focal_from_fundamentals(_pairs(K), K[:2, 2], prior=1.4 * 812.5)
    assert abs(focal / 812.5 - 1) < 1e-6


def test_gap_vanishes_only_at_the_true_focal_length():
    K = intrinsics(600.0, torch.tensor([300.0, 200.0], dtype=torch.float64))
    gaps = singular_value_gap(_pairs(K), torch.tensor([500.0, 600.0, 700.0], dtype=torch.float64), K[:2, 2])
    torch.testing.assert_close(gaps[1], torch.zeros(6, dtype=torch.float64), atol=1e-9, rtol=0)
    assert bool((gaps[[0, 2]] > 1e-3).all())


def test_a_camera_translating_without_turning_leaves_the_focal_length_undetermined():
    """Pure translations (forward driving and sideways): every focal length makes E essential,
    so the search says so (None) instead of returning the end of its range; a little turning
    between some pairs (0.4 rad) determines it again."""
    K = intrinsics(707.0, torch.tensor([612.5, 184.5], dtype=torch.float64))
    g = torch.Generator().manual_seed(1)
    translations = torch.randn(8, 3, generator=g, dtype=torch.float64) * torch.tensor([0.1, 0.05, 1.0], dtype=torch.float64)
    F = torch.stack([fundamental_from_pose(K, K, torch.eye(3, dtype=torch.float64), t) for t in translations])
    assert focal_from_fundamentals(F, K[:2, 2], prior=1.2 * 1226) is None
    focal = focal_from_fundamentals(torch.cat([F[:2], _pairs(K)]), K[:2, 2], prior=1.2 * 1226)
    assert focal is not None and abs(focal / 707.0 - 1) < 1e-6
