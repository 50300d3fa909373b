"""Plane-induced homographies: normalized DLT and transfer errors (x2 ~ H x1)."""

from __future__ import annotations

import torch
from torch import Tensor

from torchsfm.camera import map_by_each, to_homogeneous
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
    mapped = map_by_each(H, x1)  # (*, N, h, 3)
    w = mapped[..., 2]
    error = (mapped[..., 0] / w - x2[..., :1]).square_() + (mapped[..., 1] / w - x2[..., 1:]).square_()
    return torch.where(w.abs() > 1e-12, error, torch.full_like(error, float("inf"))).transpose(-1, -2)


def homography_jacobian(H: Tensor, x: Tensor) -> Tensor:
    """(N, 2, 2) derivative of the mapping x -> H x (pixels to pixels) at points x (N, 2): the
    local affine approximation of the homography (3, 3) there."""
    h = torch.cat([x, torch.ones_like(x[:, :1])], dim=-1) @ H.T  # (N, 3)
    mapped = h[:, :2] / h[:, 2:]
    return (H[None, :2, :2] - mapped[:, :, None] * H[None, 2:, :2]) / h[:, 2, None, None]


def decompose_homography(H: Tensor) -> tuple[Tensor, Tensor, Tensor]:
    """The four motions and planes of a calibrated homography (3, 3), H ~ R + t nᵀ (x2 ~ H x1 in
    normalized coordinates, X2 = R X1 + t, the plane nᵀ X1 = 1 in camera 1's frame: t is the
    translation over the plane's distance). The analytic decomposition of Ma, Soatto, Košecká
    and Sastry (An Invitation to 3-D Vision, §5.3.3): H is scaled to unit middle singular value
    with the sign that makes x2ᵀ H x1 positive, which the caller ensures (``H`` as given here is
    that one). Returns R (4, 3, 3), t (4, 3), n (4, 3) (unit); in pairs (R, t, n), (R, -t, -n),
    of which the points in front of camera 1 (nᵀ x1 > 0) choose at most two. A pure rotation
    (no translation) leaves n free: t is then 0 in every solution. Float64."""
    H = H.double()
    H = H / torch.linalg.svdvals(H)[1]
    squared, V = torch.linalg.eigh(H.T @ H)  # ascending: σ3², σ2² (= 1), σ1²
    V = V.flip(-1) * torch.linalg.det(V)  # columns v1, v2, v3 in SO(3)
    s1, s3 = float(squared[2]), float(squared[0])
    v1, v2, v3 = V.unbind(-1)
    spread = max(s1 - s3, 1e-24)
    a, b = max(1.0 - s3, 0.0) ** 0.5 / spread ** 0.5, max(s1 - 1.0, 0.0) ** 0.5 / spread ** 0.5
    solutions = []
    for u in (a * v1 + b * v3, a * v1 - b * v3):
        U = torch.stack([v2, u, torch.linalg.cross(v2, u)], dim=-1)
        W = torch.stack([H @ v2, H @ u, torch.linalg.cross(H @ v2, H @ u)], dim=-1)
        R = W @ U.T
        n = torch.linalg.cross(v2, u)
        t = (H - R) @ n
        solutions += [(R, t, n), (R, -t, -n)]
    R, t, n = (torch.stack(parts) for parts in zip(*solutions))
    return R, t, n
