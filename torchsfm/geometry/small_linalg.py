"""Closed-form linear algebra on batches of 3x3 matrices.

LAPACK calls cost microseconds per tiny matrix; RANSAC needs thousands per round. These routines
use elementwise tensor ops only and are exact up to rounding for well-separated eigenvalues,
which is all hypothesis generation needs (final models use ``torch.linalg``).
"""

from __future__ import annotations

import torch
from torch import Tensor

from torchsfm.numerics import floor_tiny


def symmetric_eigenvalues3(M: Tensor) -> Tensor:
    """Eigenvalues of symmetric 3x3 matrices in ascending order (Smith 1961): (*, 3, 3) -> (*, 3)."""
    q = torch.diagonal(M, dim1=-2, dim2=-1).sum(-1) / 3
    off = M[..., 0, 1] ** 2 + M[..., 0, 2] ** 2 + M[..., 1, 2] ** 2
    diagonal = torch.diagonal(M, dim1=-2, dim2=-1) - q[..., None]
    p = torch.sqrt((diagonal.square().sum(-1) + 2 * off) / 6)
    eye = torch.eye(3, dtype=M.dtype, device=M.device)
    shifted = (M - q[..., None, None] * eye) / floor_tiny(p)[..., None, None]
    phi = torch.acos((torch.linalg.det(shifted) / 2).clamp(-1, 1)) / 3
    angles = phi[..., None] + torch.tensor([2 * torch.pi / 3, 4 * torch.pi / 3, 0.0], dtype=M.dtype, device=M.device)
    return q[..., None] + 2 * p[..., None] * torch.cos(angles)  # cos(phi + 2pi/3) <= cos(phi + 4pi/3) <= cos(phi)


def eigenvector_sym3(M: Tensor, eigenvalue: Tensor) -> Tensor:
    """Unit eigenvector of symmetric M (*, 3, 3) for a simple eigenvalue (*,): -> (*, 3).

    The largest cross product of two rows of M - λI (all rows are orthogonal to the eigenvector).
    """
    rows = M - eigenvalue[..., None, None] * torch.eye(3, dtype=M.dtype, device=M.device)
    crosses = torch.stack([torch.linalg.cross(rows[..., 0, :], rows[..., 1, :]),
                           torch.linalg.cross(rows[..., 0, :], rows[..., 2, :]),
                           torch.linalg.cross(rows[..., 1, :], rows[..., 2, :])], dim=-2)
    norms = crosses.norm(dim=-1)
    best = torch.gather(crosses, -2, norms.argmax(-1)[..., None, None].expand(*norms.shape[:-1], 1, 3)).squeeze(-2)
    return best / floor_tiny(norms.amax(-1, keepdim=True))


def smallest_eigenvector_sym3(M: Tensor) -> Tensor:
    """Unit eigenvector of the smallest eigenvalue of symmetric 3x3 matrices: (*, 3, 3) -> (*, 3)."""
    return eigenvector_sym3(M, symmetric_eigenvalues3(M)[..., 0])
