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
    return plane_parallax_batch(reference[None], others[None], None, config, generator)[0]


def plane_parallax_batch(reference: Tensor, others: Tensor, valid: Tensor | None, config: MovingObjectsConfig,
                         generator: torch.Generator | None = None) -> list[PlaneParallax]:
    """:func:`plane_parallax` of B problems as one ragged RANSAC call.

    Args:
        reference: (B, N, 2) points of each problem's reference frame, pixels, float64.
        others: (B, J, N, 2) the same points in J other frames.
        valid: (B, N) bool, the real rows of each problem (padding last); None: all.
        config, generator: as for :func:`plane_parallax`.

    Returns:
        Per problem its decomposition, on its real rows only.
    """
    B, J, N, _ = others.shape
    data = torch.cat([reference, others.transpose(1, 2).flatten(2)], dim=-1)  # (B, N, 2 + 2J)
    if config.plane_model == "quadratic":
        model = PlanarFlowModel(data, valid)
        found = ransac(model, data, config.plane_ransac, valid=valid, generator=generator)
        flow = model.fit_weighted(data, found.inlier_mask.to(data.dtype))  # (B, J, 8) least squares on the inliers
        x, _ = model.normalize(data)
        warped = others - planar_flow(flow, x) / model.T[:, 0, 0, None, None, None]
    else:
        model = JointModel(HomographyModel, data, valid)
        found = ransac(model, data, config.plane_ransac, valid=valid, generator=generator)
        H = model.fit_weighted(data, found.inlier_mask.to(data.dtype))  # (B, J, 3, 3)
        inverse, info = torch.linalg.inv_ex(H)  # a singular plane (degenerate points) warps to infinity: IMOR falls back
        inverse = torch.where((info == 0)[..., None, None], inverse, torch.full_like(inverse, float("inf")))
        warped = from_homogeneous(to_homogeneous(others) @ inverse.transpose(-1, -2))
    parallax = warped - reference[:, None]
    counts = [N] * B if valid is None else valid.sum(-1).tolist()
    return [PlaneParallax(warped=warped[b, :, :n], parallax=parallax[b, :, :n], plane_inliers=found.inlier_mask[b, :n],
                          num_trials=int(found.num_trials[b])) for b, n in enumerate(counts)]
