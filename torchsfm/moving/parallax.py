"""Plane + parallax decomposition (thesis §5.2, Irani & Anandan 1998).

Every other frame is registered to the reference frame by the dominant plane; what the plane
does not explain is the residual parallax μ = p_w − p, where p_w is the point of the other frame
warped back into the reference frame by the plane. For a static point μ = γ c (e − p_w): γ is the
point's projective structure (frame-independent) and c, e depend on the frame only.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor

from torchsfm.camera import from_homogeneous, to_homogeneous
from torchsfm.config import MovingObjectsConfig
from torchsfm.geometry.planar_flow import planar_flow
from torchsfm.robust.models import HomographyModel, JointModel, PlanarFlowModel
from torchsfm.robust.ransac import ransac


@dataclass
class PlaneParallax:
    """Decomposition of J frames' points against the reference frame.

    Fields:
        warped: (J, N, 2) p_w, every frame's points warped into the reference frame by its plane.
        parallax: (J, N, 2) residual parallax μ = p_w − p (pixels of the reference frame).
        plane_inliers: (N,) bool, the dominant plane's RANSAC inliers (in every frame).
        num_trials: RANSAC samples drawn.
    """

    warped: Tensor
    parallax: Tensor
    plane_inliers: Tensor
    num_trials: int


def plane_parallax(reference: Tensor, others: Tensor, config: MovingObjectsConfig,
                   generator: torch.Generator | None = None) -> PlaneParallax:
    """Register each frame to the reference by its dominant plane and split off the parallax.

    Args:
        reference: (N, 2) points of the reference frame, pixels, float64.
        others: (J, N, 2) the same points in J other frames.
        config: plane model, its RANSAC settings.
        generator: random source of the RANSACs.
    """
    data = torch.cat([reference, others.transpose(0, 1).flatten(1)], dim=-1)[None]  # (1, N, 2 + 2J)
    if config.plane_model == "quadratic":
        model = PlanarFlowModel(data)
        found = ransac(model, data, config.plane_ransac, generator=generator)
        flow = model.fit_weighted(data, found.inlier_mask.to(data.dtype))[0]  # (J, 8) least squares on the inliers
        x, _ = model.normalize(data)
        warped = others - planar_flow(flow[None], x)[0] / model.T[0, 0, 0]
    else:
        model = JointModel(HomographyModel, data)
        found = ransac(model, data, config.plane_ransac, generator=generator)
        H = model.fit_weighted(data, found.inlier_mask.to(data.dtype))[0]  # (J, 3, 3)
        inverse, info = torch.linalg.inv_ex(H)  # a singular plane (degenerate points) warps to infinity: IMOR falls back
        inverse = torch.where((info == 0)[:, None, None], inverse, torch.full_like(inverse, float("inf")))
        warped = from_homogeneous(to_homogeneous(others) @ inverse.transpose(-1, -2))
    return PlaneParallax(warped=warped, parallax=warped - reference, plane_inliers=found.inlier_mask[0],
                         num_trials=int(found.num_trials[0]))
