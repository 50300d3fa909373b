"""Rotations: cross-product matrices, axis-angle (so(3) exponential/logarithm), unit quaternions.

Conventions: rotation matrices act on column vectors (x' = R x); quaternions are ``(w, x, y, z)``
with ``w`` the scalar part (thesis eq. 3.4.15, Appendix E with the errata's sign fix). All
functions broadcast over leading dimensions and are differentiable (forward and reverse mode),
including at the zero rotation.
"""

from __future__ import annotations

import torch
from torch import Tensor

from torchsfm.numerics import floor_tiny


_SKEW_BASIS = torch.tensor(
    [[0, 0, 0, 0, 0, -1, 0, 1, 0], [0, 0, 1, 0, 0, 0, -1, 0, 0], [0, -1, 0, 1, 0, 0, 0, 0, 0]], dtype=torch.float64
)  # row k: [e_k]x flattened


def skew(v: Tensor) -> Tensor:
    """Cross-product matrix ``[v]x`` with ``[v]x w = v × w``: (*, 3) -> (*, 3, 3)."""
    return (v @ _SKEW_BASIS.to(v)).reshape(*v.shape[:-1], 3, 3)


def _safe_angle(squared: Tensor, small: float) -> tuple[Tensor, Tensor]:
    """(angle, is_small) with the square root kept away from 0 so derivatives stay finite."""
    is_small = squared < small
    return torch.sqrt(torch.where(is_small, torch.ones_like(squared), squared)), is_small


def axis_angle_to_rotation(omega: Tensor) -> Tensor:
    """Rodrigues' formula, exp([omega]x): (*, 3) -> (*, 3, 3); Taylor series near zero."""
    theta_sq = (omega * omega).sum(-1)
    theta, is_small = _safe_angle(theta_sq, 1e-10)
    a = torch.where(is_small, 1 - theta_sq / 6, torch.sin(theta) / theta)
    b = torch.where(is_small, 0.5 - theta_sq / 24, (1 - torch.cos(theta)) / (theta * theta))
    omega_x = skew(omega)
    eye = torch.eye(3, dtype=omega.dtype, device=omega.device)
    return eye + a[..., None, None] * omega_x + b[..., None, None] * (omega_x @ omega_x)


def rotation_to_axis_angle(R: Tensor) -> Tensor:
    """log(R) as an axis-angle vector, (*, 3, 3) -> (*, 3), angle in [0, pi]; via quaternions."""
    q = rotation_to_quaternion(R)  # w >= 0
    w, v = q[..., 0], q[..., 1:]
    v_norm = v.norm(dim=-1)
    angle = 2 * torch.atan2(v_norm, w)
    scale = torch.where(v_norm > 1e-12, angle / floor_tiny(v_norm), 2.0 / floor_tiny(w))
    return scale[..., None] * v


def quaternion_to_rotation(q: Tensor) -> Tensor:
    """Unit quaternion ``(w, x, y, z)`` -> rotation matrix (eq. 3.4.15): (*, 4) -> (*, 3, 3).

    The quaternion is normalized first, so any non-zero 4-vector is accepted.
    """
    q = q / q.norm(dim=-1, keepdim=True)
    w, x, y, z = q.unbind(-1)
    rows = (
        w * w + x * x - y * y - z * z, 2 * (x * y - w * z), 2 * (x * z + w * y),
        2 * (x * y + w * z), w * w - x * x + y * y - z * z, 2 * (y * z - w * x),
        2 * (x * z - w * y), 2 * (y * z + w * x), w * w - x * x - y * y + z * z,
    )
    return torch.stack(rows, dim=-1).reshape(*q.shape[:-1], 3, 3)


def rotation_to_quaternion(R: Tensor) -> Tensor:
    """Rotation matrix -> unit quaternion ``(w, x, y, z)`` with w >= 0: (*, 3, 3) -> (*, 4).

    Uses the eigenvector of the symmetric 4x4 matrix of Bar-Itzhack (2000), which is exact for a
    rotation and gives the nearest quaternion for a slightly non-orthogonal matrix.
    """
    r = R
    k = torch.stack(
        [
            r[..., 0, 0] - r[..., 1, 1] - r[..., 2, 2], r[..., 1, 0] + r[..., 0, 1], r[..., 2, 0] + r[..., 0, 2], r[..., 2, 1] - r[..., 1, 2],
            r[..., 1, 0] + r[..., 0, 1], r[..., 1, 1] - r[..., 0, 0] - r[..., 2, 2], r[..., 2, 1] + r[..., 1, 2], r[..., 0, 2] - r[..., 2, 0],
            r[..., 2, 0] + r[..., 0, 2], r[..., 2, 1] + r[..., 1, 2], r[..., 2, 2] - r[..., 0, 0] - r[..., 1, 1], r[..., 1, 0] - r[..., 0, 1],
            r[..., 2, 1] - r[..., 1, 2], r[..., 0, 2] - r[..., 2, 0], r[..., 1, 0] - r[..., 0, 1], r[..., 0, 0] + r[..., 1, 1] + r[..., 2, 2],
        ],
        dim=-1,
    ).reshape(*R.shape[:-2], 4, 4) / 3.0
    _, vectors = torch.linalg.eigh(k)
    x, y, z, w = vectors[..., -1].unbind(-1)
    q = torch.stack([w, x, y, z], dim=-1)
    return q * torch.where(w < 0, -1.0, 1.0).to(q.dtype)[..., None]


def nearest_rotation(M: Tensor) -> Tensor:
    """The rotation closest to ``M`` in Frobenius norm (SVD projection, det = +1): (*, 3, 3)."""
    U, _, Vh = torch.linalg.svd(M)
    d = torch.det(U @ Vh)
    D = torch.diag_embed(torch.stack([torch.ones_like(d), torch.ones_like(d), d], dim=-1))
    return U @ D @ Vh


def rotation_angle(R1: Tensor, R2: Tensor) -> Tensor:
    """Angle of ``R1ᵀ R2`` in degrees, (*, 3, 3) x (*, 3, 3) -> (*); accurate for tiny angles."""
    delta = rotation_to_axis_angle(R1.transpose(-1, -2) @ R2)
    return torch.rad2deg(delta.norm(dim=-1))


def angle_between(a: Tensor, b: Tensor, *, unsigned_direction: bool = False) -> Tensor:
    """Angle between vectors in degrees, (*, 3) x (*, 3) -> (*).

    With ``unsigned_direction`` the sign of the vectors is ignored (result in [0, 90]).
    """
    cross = torch.linalg.cross(a, b).norm(dim=-1)
    dot = (a * b).sum(-1)
    if unsigned_direction:
        dot = dot.abs()
    return torch.rad2deg(torch.atan2(cross, dot))


__all__ = [
    "skew",
    "axis_angle_to_rotation",
    "rotation_to_axis_angle",
    "quaternion_to_rotation",
    "rotation_to_quaternion",
    "nearest_rotation",
    "rotation_angle",
    "angle_between",
]
