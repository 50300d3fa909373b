"""Hartley normalization of point sets (thesis Alg. 3.3.2 and 4.1.1, as corrected in ERRATA)."""

from __future__ import annotations

import math

import torch
from torch import Tensor

from torchsfm.numerics import floor_tiny


def hartley_normalize(x: Tensor, weights: Tensor | None = None) -> tuple[Tensor, Tensor]:
    """Translate the (weighted) centroid to the origin and scale the mean distance to sqrt(D).

    Args:
        x: points, shape (*, N, D) with D = 2 (image) or 3 (space).
        weights: optional non-negative weights (*, N); zero-weight points (outliers, padding)
            do not influence the transform.

    Returns:
        The normalized points (*, N, D) and the similarity T (*, D + 1, D + 1) with
        ``x_normalized = T x`` in homogeneous coordinates. A set with zero spread gets scale 1.
    """
    D = x.shape[-1]
    if weights is None:
        weights = torch.ones_like(x[..., 0])
    total = floor_tiny(weights.sum(-1, keepdim=True))  # (*, 1)
    centroid = (weights[..., None] * x).sum(-2) / total  # (*, D)
    centered = x - centroid[..., None, :]
    mean_distance = (weights * centered.norm(dim=-1)).sum(-1, keepdim=True) / total  # (*, 1)
    scale = torch.where(mean_distance > 0, math.sqrt(D) / floor_tiny(mean_distance), torch.ones_like(mean_distance))
    T = torch.diag_embed(torch.cat([scale.expand(*scale.shape[:-1], D), torch.ones_like(scale)], dim=-1))
    T[..., :D, D] = -scale * centroid
    return centered * scale[..., None], T


def apply_affine(T: Tensor, x: Tensor) -> Tensor:
    """T x for points (*, N, 2) and affine maps T (*, 3, 3) (last row 0 0 1, e.g. from
    :func:`hartley_normalize`) whose batch dimensions broadcast against x's: (*, N, 2)."""
    return x @ T[..., :2, :2].transpose(-1, -2) + T[..., None, :2, 2]
