"""The quadratic (pseudo-projective) planar flow of thesis eq. 5.2.1, as corrected in ERRATA:

    u = p1 x + p2 y + p5 + p7 x² + p8 xy,     v = p3 x + p4 y + p6 + p7 xy + p8 y²,

the image motion (u, v) at (x, y) of a plane under a small camera motion (Irani & Anandan 1998).
The family is closed under translations and isotropic scalings of the image, so the parameters
are estimated in Hartley-normalized coordinates of the reference points (for conditioning) and
the model is applied there too: a model is the (8,) vector p together with its (3, 3) similarity.
"""

from __future__ import annotations

import torch
from torch import Tensor


def planar_flow_design(x: Tensor) -> Tensor:
    """Rows of the linear system for p: (*, N, 2) points -> (*, N, 2, 8), u then v."""
    X, Y = x[..., 0], x[..., 1]
    one, zero = torch.ones_like(X), torch.zeros_like(X)
    u = torch.stack([X, Y, zero, zero, one, zero, X * X, X * Y], dim=-1)
    v = torch.stack([zero, zero, X, Y, zero, one, X * Y, Y * Y], dim=-1)
    return torch.stack([u, v], dim=-2)


def planar_flow(p: Tensor, x: Tensor) -> Tensor:
    """Displacements (u, v) of H flows p (B, H, 8) at points x (B, N, 2) -> (B, H, N, 2), one GEMM."""
    B, N = x.shape[:2]
    flows = planar_flow_design(x).reshape(B, 2 * N, 8) @ p.transpose(-1, -2)  # (B, 2N, H)
    return flows.transpose(-1, -2).reshape(B, p.shape[1], N, 2)


def fit_planar_flow(x: Tensor, displacement: Tensor, weights: Tensor | None = None) -> Tensor:
    """Weighted least-squares p (*, 8) from points x (*, N, 2) and their displacements (*, N, 2).

    N >= 4 points in general position are needed (two equations each); a tiny ridge (1e-12 of
    the normal matrix' trace) keeps degenerate sets finite instead of raising.
    """
    A = planar_flow_design(x).flatten(-3, -2)  # (*, 2N, 8)
    b = displacement.flatten(-2)  # (*, 2N)
    if weights is not None:
        w = weights.repeat_interleave(2, dim=-1)
        A, b = A * w[..., None], b * w
    normal = A.transpose(-1, -2) @ A
    ridge = 1e-12 * normal.diagonal(dim1=-2, dim2=-1).sum(-1)[..., None, None] * torch.eye(8, dtype=A.dtype, device=A.device)
    return torch.linalg.solve(normal + ridge, (A.transpose(-1, -2) @ b[..., None]))[..., 0]
