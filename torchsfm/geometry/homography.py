"""Plane-induced homographies: normalized DLT and transfer errors (x2 ~ H x1)."""

from __future__ import annotations

import torch
from torch import Tensor

from torchsfm.camera import to_homogeneous
from torchsfm.geometry.fundamental import smallest_right_singular_vector
from torchsfm.geometry.normalization import hartley_normalize
from torchsfm.numerics import floor_tiny


def homography_dlt(x1: Tensor, x2: Tensor, weights: Tensor | None = None) -> Tensor:
    """Normalized DLT: (*, N, 2) x2, N >= 4, optional (*, N) weights -> H (*, 3, 3), unit norm."""
    n1, T1 = hartley_normalize(x1, weights)
    n2, T2 = hartley_normalize(x2, weights)
    h1 = to_homogeneous(n1)
    zero = torch.zeros_like(h1)
    u, v = n2[..., 0:1], n2[..., 1:2]
    rows_u = torch.cat([-h1, zero, u * h1], dim=-1)  # u h3ᵀx - h1ᵀx = 0
    rows_v = torch.cat([zero, -h1, v * h1], dim=-1)
    A = torch.cat([rows_u, rows_v], dim=-2)
    w = None if weights is None else torch.cat([weights, weights], dim=-1)
    H = smallest_right_singular_vector(A, w).reshape(*A.shape[:-2], 3, 3)
    H = torch.linalg.inv(T2) @ H @ T1
    return H / floor_tiny(H.flatten(-2).norm(dim=-1)[..., None, None])


def transfer_error(H: Tensor, x1: Tensor, x2: Tensor) -> Tensor:
    """Squared one-way transfer error ‖x2 - π(H x1)‖² (pixels²) of one homography (*, 3, 3) per
    point set (*, N, 2): (*, N); +inf where H x1 is at infinity."""
    return transfer_error_of_hypotheses(H[..., None, :, :], x1, x2)[..., 0, :]


def transfer_error_of_hypotheses(H: Tensor, x1: Tensor, x2: Tensor) -> Tensor:
    """:func:`transfer_error` of h homographies (*, h, 3, 3) on the same (*, N, 2) points ->
    (*, h, N), as one (N, 3) x (3, 3h) product per problem: no per-hypothesis copy of the points,
    and no reduction over the coordinate pair (slow in torch)."""
    h = H.shape[-3]
    stacked = H.transpose(-1, -2).transpose(-3, -2).reshape(*H.shape[:-3], 3, 3 * h)  # column 3k + j: row j of H_k
    mapped = (to_homogeneous(x1) @ stacked).unflatten(-1, (h, 3))  # (*, N, h, 3)
    w = mapped[..., 2]
    error = (mapped[..., 0] / w - x2[..., :1]).square_() + (mapped[..., 1] / w - x2[..., 1:]).square_()
    return torch.where(w.abs() > 1e-12, error, torch.full_like(error, float("inf"))).transpose(-1, -2)


def homography_jacobian(H: Tensor, x: Tensor) -> Tensor:
    """(N, 2, 2) derivative of the mapping x -> H x (pixels to pixels) at points x (N, 2): the
    local affine approximation of the homography (3, 3) there."""
    h = torch.cat([x, torch.ones_like(x[:, :1])], dim=-1) @ H.T  # (N, 3)
    mapped = h[:, :2] / h[:, 2:]
    return (H[None, :2, :2] - mapped[:, :, None] * H[None, 2:, :2]) / h[:, 2, None, None]
