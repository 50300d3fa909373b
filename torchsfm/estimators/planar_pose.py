"""Relative pose of two calibrated views of a plane, from their homography.

Where every point lies on one plane (a wall, a poster, a flat object moving through the scene),
the epipolar geometry is degenerate: F is not determined, and E with it. The homography is, and
its decomposition gives the motion and the plane up to a two-fold ambiguity that the points in
front of both cameras do not always resolve (:func:`planar_poses`); a third view does: the plane's
normal in the first view's frame is one, the false twin's differs from pair to pair
(:func:`choose_by_normal`). COLMAP's two-view geometry falls back to the same decomposition for
its planar pairs.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor

from torchsfm.camera import projection_matrix, to_homogeneous
from torchsfm.config import Config, RansacConfig
from torchsfm.errors import DegenerateConfigurationError
from torchsfm.geometry.homography import decompose_homography
from torchsfm.geometry.triangulation import triangulate_points
from torchsfm.robust.models import HomographyModel
from torchsfm.robust.ransac import ransac


@dataclass
class PlanarPose:
    """One physically valid motion of two views of a plane (:func:`planar_poses`).

    Fields:
        R: (3, 3) rotation of camera 2 relative to camera 1 (X2 = R X1 + t); t: (3,) unit translation.
        normal: (3,) the plane's unit normal in camera 1's frame (pointing away from camera 1).
        inlier_mask: (N,) bool, the homography's inliers that triangulate in front of both cameras.
        points3d: (M, 3) those inliers triangulated in camera 1's frame (scale: ‖t‖ = 1).
    """

    R: Tensor
    t: Tensor
    normal: Tensor
    inlier_mask: Tensor
    points3d: Tensor


def planar_poses(x1: Tensor, x2: Tensor, K1: Tensor, K2: Tensor, *, config: Config, generator: torch.Generator) -> list[PlanarPose]:
    """The motions of two views of a plane from pixel correspondences x1, x2 (N, 2) and
    intrinsics K1, K2 (3, 3): a robust homography (``reconstruction.homography_threshold`` px,
    ``fundamental.ransac``'s confidence and limits), its four decompositions, and of those the
    ones that put most of its inliers in front of both cameras — one or two (the twin), most
    points in front first. Float64.

    Raises:
        DegenerateConfigurationError: no decomposition puts most inliers in front (no
            translation, or no plane).
    """
    x1, x2, K1, K2 = x1.double(), x2.double(), K1.double(), K2.double()
    data = torch.cat([x1, x2], dim=-1)[None]
    settings = RansacConfig(inlier_threshold=config.reconstruction.homography_threshold, confidence=config.fundamental.ransac.confidence,
                            max_trials=config.fundamental.ransac.max_trials)
    fit = ransac(HomographyModel(data), data, settings, generator=generator)
    inliers = fit.inlier_mask[0]
    H = torch.linalg.inv(K2) @ fit.model[0] @ K1  # in normalized coordinates
    n1, n2 = to_homogeneous(torch.linalg.solve(K1, to_homogeneous(x1).T).T[:, :2]), torch.linalg.solve(K2, to_homogeneous(x2).T).T
    H = H * torch.sign(((n2[inliers] * (n1[inliers] @ H.T)).sum(-1)).median())  # x2ᵀ H x1 > 0: positive depths
    P1 = projection_matrix(K1, torch.eye(3, dtype=torch.float64), torch.zeros(3, dtype=torch.float64))
    poses = []
    for R, t, normal in zip(*decompose_homography(H)):
        if float(t.norm()) == 0.0:
            continue
        t = t / t.norm()
        X = triangulate_points(x1, x2, P1, projection_matrix(K2, R, t), config.triangulation)
        in_front = inliers & (X[:, 2] > 0) & ((X @ R.T + t)[:, 2] > 0) & torch.isfinite(X).all(-1)
        if 2 * int(in_front.sum()) > int(inliers.sum()):
            poses.append(PlanarPose(R=R, t=t, normal=normal, inlier_mask=in_front, points3d=X[in_front]))
    if not poses:
        raise DegenerateConfigurationError(f"no motion of the homography of {int(inliers.sum())} inliers puts most of them in front of "
                                           "both cameras (no translation, or no plane)")
    return sorted(poses, key=lambda pose: -int(pose.inlier_mask.sum()))


def choose_by_normal(poses: list[PlanarPose], other_normals: list[Tensor]) -> PlanarPose:
    """Of a pair's twin motions, the one whose plane normal (camera 1's frame) agrees best with
    the normals that camera 1's other planar pairs give, ``other_normals`` (each (m, 3): that
    pair's valid decompositions' normals in the same frame): the smallest sum over those pairs of
    the angle to their nearest normal. The true plane is the same in every pair; the twin's normal
    depends on each pair's motion. Without other pairs, the first pose (most points in front)."""
    if len(poses) == 1 or not other_normals:
        return poses[0]
    normals = torch.stack([pose.normal for pose in poses])  # (p, 3)
    disagreement = sum(torch.arccos((normals @ other.T).clamp(-1, 1)).amin(-1) for other in other_normals)
    return poses[int(torch.argmin(disagreement))]
