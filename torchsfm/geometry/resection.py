"""Camera resection from 3-D↔2-D correspondences (thesis §4.1–4.2, Alg. 4.1.1, with the ERRATA).

* :func:`dlt_projection` — the normalized DLT for P (11 DOF, at least 6 pairs; 3-D points scaled
  to mean distance √3, image points to √2), weighted so one function fits minimal samples and
  inlier sets.
* :func:`p3p` — Grunert's solution of the calibrated minimal problem (3 pairs, up to 4 poses;
  Haralick et al. 1994), batched: the quartic's roots come from companion-matrix eigenvalues and
  each pose from the frames of the world and camera triangles.
* :func:`pose_from_projection` — (R, t) of a DLT P once K is known.
"""

from __future__ import annotations

import torch
from torch import Tensor

from torchsfm.camera import to_homogeneous
from torchsfm.geometry.fundamental import smallest_right_singular_vector
from torchsfm.geometry.normalization import hartley_normalize
from torchsfm.geometry.rotation import nearest_rotation
from torchsfm.numerics import floor_tiny


def dlt_projection(X: Tensor, x: Tensor, weights: Tensor | None = None) -> Tensor:
    """Normalized DLT (Alg. 4.1.1): X (*, N, 3), x (*, N, 2), N >= 6 -> P (*, 3, 4), unit norm,
    signed so that most (weighted) points have positive depth."""
    Xn, T3 = hartley_normalize(X, weights)
    xn, T2 = hartley_normalize(x, weights)
    Xh = to_homogeneous(Xn)  # (*, N, 4)
    zero = torch.zeros_like(Xh)
    u, v = xn[..., 0:1], xn[..., 1:2]
    rows_u = torch.cat([-Xh, zero, u * Xh], dim=-1)  # u p3ᵀX - p1ᵀX = 0
    rows_v = torch.cat([zero, -Xh, v * Xh], dim=-1)
    A = torch.cat([rows_u, rows_v], dim=-2)  # (*, 2N, 12)
    w = None if weights is None else torch.cat([weights, weights], dim=-1)
    P = smallest_right_singular_vector(A, w).reshape(*A.shape[:-2], 3, 4)
    P = torch.linalg.inv(T2) @ P @ T3
    in_front = torch.sign(to_homogeneous(X) @ P[..., 2, :, None])[..., 0]  # (*, N): sign of the depths
    sign = torch.sign((in_front if weights is None else in_front * weights).sum(-1))
    P = P * torch.where(sign == 0, 1.0, sign)[..., None, None]
    return P / floor_tiny(P.flatten(-2).norm(dim=-1)[..., None, None])


def pose_from_projection(P: Tensor, K: Tensor, X: Tensor | None = None) -> tuple[Tensor, Tensor]:
    """(R, t) with P ∝ K [R | t]: K⁻¹P = λ [M | m], R = nearest rotation of ±M, t = m / λ.

    The sign is chosen so that the (optional) points X (*, N, 3) lie in front of the camera
    (else so that det M > 0). P (*, 3, 4), K (*, 3, 3) -> R (*, 3, 3), t (*, 3).
    """
    A = torch.linalg.solve(K, P)
    M, m = A[..., :3], A[..., 3]
    sign = torch.sign(torch.linalg.det(M))
    if X is not None:
        depth = (X @ M.transpose(-1, -2) + m[..., None, :])[..., 2]
        sign = torch.sign(depth.sum(-1))
    sign = torch.where(sign == 0, 1.0, sign).to(P.dtype)
    M, m = M * sign[..., None, None], m * sign[..., None]
    scale = torch.linalg.svdvals(M).mean(-1)
    return nearest_rotation(M), m / scale[..., None]


def _triangle_frame(points: Tensor) -> tuple[Tensor, Tensor]:
    """Orthonormal frame of each triangle (*, 3, 3) (rows: its corners): columns the first edge's
    direction, the in-plane normal to it, the plane's normal; and the sine of the angle at the
    first corner (*,) (0: collinear, no frame)."""
    edge, other = points[..., 1, :] - points[..., 0, :], points[..., 2, :] - points[..., 0, :]
    normal = torch.linalg.cross(edge, other)
    edge_length, normal_length = edge.norm(dim=-1, keepdim=True), normal.norm(dim=-1, keepdim=True)
    first, third = edge / floor_tiny(edge_length), normal / floor_tiny(normal_length)
    frame = torch.stack([first, torch.linalg.cross(third, first), third], dim=-1)
    sine = normal_length / floor_tiny(edge_length * other.norm(dim=-1, keepdim=True))
    return frame, sine[..., 0]


def p3p(X: Tensor, bearings: Tensor) -> tuple[Tensor, Tensor, Tensor]:
    """Grunert's P3P: world points X (*, 3, 3) and unit bearing vectors (*, 3, 3) (rows).

    Returns R (*, 4, 3, 3), t (*, 4, 3) and a (*, 4) validity mask (real, positive-depth roots).
    """
    X1, X2, X3 = X.unbind(-2)
    j1, j2, j3 = bearings.unbind(-2)
    a2 = (X2 - X3).square().sum(-1)
    b2 = (X1 - X3).square().sum(-1)
    c2 = (X1 - X2).square().sum(-1)
    cos_alpha, cos_beta, cos_gamma = (j2 * j3).sum(-1), (j1 * j3).sum(-1), (j1 * j2).sum(-1)
    p = (a2 - c2) / b2
    q = (a2 + c2) / b2
    A4 = (p - 1) ** 2 - 4 * c2 / b2 * cos_alpha**2
    A3 = 4 * (p * (1 - p) * cos_beta - (1 - q) * cos_alpha * cos_gamma + 2 * c2 / b2 * cos_alpha**2 * cos_beta)
    A2 = 2 * (p**2 - 1 + 2 * p**2 * cos_beta**2 + 2 * (b2 - c2) / b2 * cos_alpha**2
              - 4 * q * cos_alpha * cos_beta * cos_gamma + 2 * (b2 - a2) / b2 * cos_gamma**2)
    A1 = 4 * (-p * (1 + p) * cos_beta + 2 * a2 / b2 * cos_gamma**2 * cos_beta - (1 - q) * cos_alpha * cos_gamma)
    A0 = (1 + p) ** 2 - 4 * a2 / b2 * cos_gamma**2
    coefficients = torch.stack([A3, A2, A1, A0], dim=-1) / A4[..., None]
    # a degenerate sample (coincident or collinear points: b2 or A4 = 0) gives a non-finite
    # quartic; LAPACK's eigvals must never see one (it can crash the process): solve a harmless
    # stand-in and mark the sample invalid
    finite = torch.isfinite(coefficients).all(-1)
    coefficients = torch.where(finite[..., None], coefficients, torch.zeros_like(coefficients))
    companion = torch.zeros(*A4.shape, 4, 4, dtype=X.dtype, device=X.device)
    companion[..., 0, :] = -coefficients
    companion[..., 1, 0] = companion[..., 2, 1] = companion[..., 3, 2] = 1.0
    roots = torch.linalg.eigvals(companion)  # (*, 4)
    v = roots.real
    real = roots.imag.abs() <= 1e-6 * (1 + roots.abs())
    u = ((p[..., None] - 1) * v**2 - 2 * p[..., None] * cos_beta[..., None] * v + 1 + p[..., None]) / (2 * (cos_gamma[..., None] - v * cos_alpha[..., None]))
    s1_squared = c2[..., None] / (1 + u**2 - 2 * u * cos_gamma[..., None])
    s1 = s1_squared.clamp_min(0).sqrt()
    depths = torch.stack([s1, u * s1, v * s1], dim=-1)  # (*, 4, 3)
    in_camera = depths[..., :, None] * bearings[..., None, :, :]  # (*, 4, 3, 3)
    usable = torch.isfinite(in_camera).flatten(-2).all(-1) & torch.isfinite(X).flatten(-2).all(-1)[..., None]
    in_camera = torch.where(usable[..., None, None], in_camera, torch.zeros_like(in_camera))  # invalid poses stay finite
    # the camera's triangle is the world's moved rigidly (its sides are the world's by
    # construction): R maps the world triangle's frame onto the camera triangle's, no SVD
    world = torch.nan_to_num(X)
    world_frame, world_sine = _triangle_frame(world)
    camera_frame, _ = _triangle_frame(in_camera)
    R = camera_frame @ world_frame[..., None, :, :].transpose(-1, -2)
    t = in_camera.mean(-2) - (R @ world.mean(-2)[..., None, :, None])[..., 0]
    valid = (finite[..., None] & usable & real & (s1_squared > 0) & (depths > 0).all(-1) & (world_sine > 1e-9)[..., None]
             & torch.isfinite(R).flatten(-2).all(-1) & torch.isfinite(t).all(-1))
    return R, t, valid


def reprojection_errors(P: Tensor, X: Tensor, x: Tensor) -> Tensor:
    """Squared reprojection errors (pixels²) of one camera P (*, 3, 4) per point set X (*, N, 3),
    x (*, N, 2) -> (*, N); points behind the camera get +inf."""
    return reprojection_errors_of_hypotheses(P[..., None, :, :], X, x)[..., 0, :]


def reprojection_errors_of_hypotheses(P: Tensor, X: Tensor, x: Tensor) -> Tensor:
    """:func:`reprojection_errors` of H cameras P (*, H, 3, 4) on the same points X (*, N, 3),
    x (*, N, 2) -> (*, H, N), as one (3H, 4) x (4, N) product per problem: no per-hypothesis copy
    of the points, and each image coordinate of every hypothesis a contiguous (H, N) block."""
    H = P.shape[-3]
    rows = P.transpose(-3, -2).reshape(*P.shape[:-3], 3 * H, 4)  # row j H + k: row j of P_k
    projected = (rows @ to_homogeneous(X).transpose(-1, -2)).unflatten(-2, (3, H))  # (*, 3, H, N)
    depth = projected[..., 2, :, :]
    inverse_depth = depth.reciprocal()
    error = (projected[..., 0, :, :] * inverse_depth - x[..., None, :, 0]).square_()
    error += (projected[..., 1, :, :] * inverse_depth - x[..., None, :, 1]).square_()
    return error.masked_fill_(depth <= 0, float("inf"))
