"""Projective multi-view geometry: canonical cameras of F, homogeneous DLT resection, and
linear triangulation of points seen in any subset of F views.

Points are homogeneous 4-vectors (a point may lie on the plane at infinity of a projective
frame); cameras are 3×4 matrices P with x ~ P X. Inputs should be normalized (e.g. Hartley) so
the linear systems are well conditioned.
"""

from __future__ import annotations

import torch
from torch import Tensor

from torchsfm.geometry.fundamental import smallest_right_singular_vector
from torchsfm.geometry.rotation import skew
from torchsfm.numerics import floor_tiny


def canonical_cameras(F: Tensor) -> tuple[Tensor, Tensor]:
    """P1 = [I | 0], P2 = [[e']x F | e'] with F (*, 3, 3) mapping view 1 to view 2 (x2ᵀ F x1 = 0),
    e' the epipole of view 2 (Fᵀ e' = 0). Returns two (*, 3, 4)."""
    e2 = torch.linalg.svd(F.transpose(-1, -2)).Vh[..., -1, :]  # (*, 3): Fᵀ e' = 0
    P1 = torch.cat([torch.eye(3, dtype=F.dtype, device=F.device).expand(*F.shape[:-2], 3, 3),
                    F.new_zeros(*F.shape[:-2], 3, 1)], dim=-1)
    P2 = torch.cat([skew(e2) @ F, e2[..., None]], dim=-1)
    return P1, P2


def projective_resection(X: Tensor, x: Tensor, weights: Tensor | None = None) -> Tensor:
    """DLT for a projective camera from homogeneous points: X (*, N, 4), x (*, N, 2), N >= 6
    (non-zero weights) -> P (*, 3, 4) of unit Frobenius norm, x ~ P X."""
    X = X / floor_tiny(X.norm(dim=-1, keepdim=True))
    zero = torch.zeros_like(X)
    u, v = x[..., 0:1], x[..., 1:2]
    rows_u = torch.cat([-X, zero, u * X], dim=-1)  # u p3ᵀX − p1ᵀX = 0
    rows_v = torch.cat([zero, -X, v * X], dim=-1)
    A = torch.cat([rows_u, rows_v], dim=-2)  # (*, 2N, 12)
    w = None if weights is None else torch.cat([weights, weights], dim=-1)
    return smallest_right_singular_vector(A, w).reshape(*A.shape[:-2], 3, 4)


def project(P: Tensor, X: Tensor) -> Tensor:
    """Homogeneous projections P X: P (*, 3, 4), X (*, N, 4) -> (*, N, 3)."""
    return X @ P.transpose(-1, -2)


def projection_distance_squared(h: Tensor, x: Tensor) -> Tensor:
    """Squared distances between x (*, N, 2) and homogeneous projections h (*, N, 3) (from
    :func:`project`): (*, N); +inf for a projection at infinity."""
    w = h[..., 2]
    safe = torch.where(w.abs() > 1e-12, w, torch.ones_like(w))
    d = (h[..., :2] / safe[..., None] - x).square().sum(-1)
    return torch.where(w.abs() > 1e-12, d, torch.full_like(d, float("inf")))


def triangulate_multiview(P: Tensor, x: Tensor, weights: Tensor, iterations: int = 3) -> Tensor:
    """Points seen in any subset of V views, by reweighted linear triangulation.

    Each view contributes the rows x p3ᵀ − p1ᵀ, y p3ᵀ − p2ᵀ scaled by 1 / |p3ᵀX| of the previous
    estimate (Hartley & Sturm's iterative linear method), so the algebraic error approaches the
    reprojection error. The first solution is the smallest eigenvector of each point's 4×4
    normal matrix; the reweighted ones refine the previous estimate by inverse iteration
    (:func:`inverse_iteration`: the reweighting moves it little, and a 4×4 solve costs a
    twentieth of an eigendecomposition).

    Args:
        P: (V, 3, 4) cameras.
        x: (V, N, 2) image points.
        weights: (V, N) 1 where the point is seen (0 elsewhere; coordinates there are ignored).
        iterations: reweighting passes after the first linear solution.

    Returns:
        (N, 4) homogeneous points of unit norm.
    """
    x = torch.where(weights[..., None] > 0, x, torch.zeros_like(x))
    a = x[..., 0:1] * P[:, None, 2] - P[:, None, 0]  # (V, N, 4)
    b = x[..., 1:2] * P[:, None, 2] - P[:, None, 1]

    def normal_matrices(scale: Tensor) -> Tensor:  # (N, 4, 4): each point's rows, scaled, squared
        w = scale.square()
        return torch.einsum("vn,vni,vnj->nij", w, a, a) + torch.einsum("vn,vni,vnj->nij", w, b, b)

    X = torch.linalg.eigh(normal_matrices(weights)).eigenvectors[..., 0]  # (N, 4)
    for _ in range(iterations):
        depth = (P[:, None, 2] * X).sum(-1).abs()  # (V, N)
        scale = weights / depth.clamp_min(1e-12 * float(floor_tiny(depth.max())))
        X = inverse_iteration(normal_matrices(scale / floor_tiny(scale.amax(0, keepdim=True))), X)
    return X


def inverse_iteration(M: Tensor, X: Tensor, steps: int = 2) -> Tensor:
    """The eigenvectors of the smallest eigenvalues of symmetric M (N, 4, 4) nearest the unit
    estimates X (N, 4), by ``steps`` inverse iterations (each multiplies the error by the ratio of
    the two smallest eigenvalues); a point whose M is singular keeps its estimate (which then lies
    in its null space already). Returns (N, 4) unit vectors."""
    for _ in range(steps):
        solved, info = torch.linalg.solve_ex(M, X)
        norm = solved.norm(dim=-1, keepdim=True)
        usable = (info == 0)[:, None] & torch.isfinite(solved).all(-1, keepdim=True) & (norm > 0)
        X = torch.where(usable, solved / torch.where(usable, norm, 1.0), X)
    return X
