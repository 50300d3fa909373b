"""The demo job: robust two-view geometry on the bundled Merton College I ground truth.

For each adjacent view pair, a fraction of the true corner matches is replaced by random pixels;
``estimate_fundamental`` and ``estimate_relative_pose`` (K from the ground-truth cameras) then
recover the geometry, and the result is compared with the ground truth.
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from pathlib import Path

import torch

from torchsfm.camera import project, projection_matrix
from torchsfm.errors import InputError
from torchsfm.io.datasets import read_oxford_multiview
from torchsfm.sfm.two_view_geometry import estimate_relative_pose
from torchsfm.testing import mask_recall_precision, replace_with_random_points, rotation_error_deg, translation_direction_error_deg

SAMPLE = Path(__file__).resolve().parent / "data" / "oxford_merton1"
IMAGE_SIZE = (1024, 768)


@dataclass
class DemoPair:
    """What the demo measured on one view pair."""

    views: tuple[int, int]
    matches: int
    inliers: int
    recall: float
    precision: float
    rotation_error_deg: float
    translation_error_deg: float
    reprojection_rms_px: float
    seconds: float


def run_demo(outliers: float = 0.4, seed: int = 0) -> list[DemoPair]:
    """Run the two-view pipeline on every adjacent pair of the bundled sample."""
    if not 0 <= outliers < 1:
        raise InputError(f"outliers must lie in [0, 1), got {outliers}")
    dataset = read_oxford_multiview(SAMPLE)
    K, _, _ = dataset.cameras()
    pairs = []
    for i in range(dataset.num_views - 1):
        generator = torch.Generator().manual_seed(seed + i)
        x1, x2 = dataset.correspondences(i, i + 1)
        x2, truth = replace_with_random_points(x2, outliers, IMAGE_SIZE, generator)
        start = time.perf_counter()
        pose = estimate_relative_pose(x1, x2, K[i], K[i + 1], generator=generator)
        seconds = time.perf_counter() - start
        R_true, t_true = dataset.relative_pose(i, i + 1)
        recall, precision = mask_recall_precision(pose.inlier_mask, truth)
        P1 = projection_matrix(K[i], torch.eye(3, dtype=torch.float64), torch.zeros(3, dtype=torch.float64))
        P2 = projection_matrix(K[i + 1], pose.R, pose.t)
        kept = pose.inlier_mask
        squared = ((project(P1, pose.points3d) - x1[kept]) ** 2).sum(-1) + ((project(P2, pose.points3d) - x2[kept]) ** 2).sum(-1)
        pairs.append(DemoPair(
            views=(i, i + 1), matches=len(truth), inliers=int(kept.sum()), recall=recall, precision=precision,
            rotation_error_deg=rotation_error_deg(pose.R, R_true), translation_error_deg=translation_direction_error_deg(pose.t, t_true),
            reprojection_rms_px=float((squared.mean() / 2).sqrt()), seconds=seconds,
        ))
    return pairs


def print_demo(pairs: list[DemoPair], outliers: float) -> None:
    print(f"torchsfm demo: Oxford VGG Merton College I (bundled), {outliers:.0%} of the matches replaced by random pixels")
    print(f"{'pair':>5s} {'matches':>8s} {'inliers':>8s} {'recall':>7s} {'precis.':>8s} {'R err °':>8s} {'t err °':>8s} {'reproj px':>10s} {'ms':>7s}")
    for pair in pairs:
        print(f"{pair.views[0]}-{pair.views[1]:<3d} {pair.matches:8d} {pair.inliers:8d} {pair.recall:7.3f} {pair.precision:8.3f} "
              f"{pair.rotation_error_deg:8.3f} {pair.translation_error_deg:8.3f} {pair.reprojection_rms_px:10.3f} {1000 * pair.seconds:7.1f}")
