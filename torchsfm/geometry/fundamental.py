"""The fundamental matrix: normalized 8-point algorithm, rank-2 enforcement and error measures.

Convention: ``x2ᵀ F x1 = 0`` for a correspondence x1 (image 1) ↔ x2 (image 2), both in pixels.
Every function broadcasts over leading dimensions, so F (B, K, 3, 3) against points
(B, 1, N, 2) scores K hypotheses of B problems at once.
"""

from __future__ import annotations

import torch
from torch import Tensor

from torchsfm.camera import to_homogeneous
from torchsfm.geometry.normalization import apply_affine, hartley_normalize
from torchsfm.geometry.rotation import skew
from torchsfm.geometry.small_linalg import smallest_eigenvector_sym3
from torchsfm.numerics import floor_tiny


def enforce_rank2(F: Tensor) -> Tensor:
    """Nearest rank-2 matrix in Frobenius norm (eq. 3.3.5): (*, 3, 3) -> (*, 3, 3)."""
    U, S, Vh = torch.linalg.svd(F)
    S = torch.cat([S[..., :2], torch.zeros_like(S[..., 2:])], dim=-1)
    return U @ torch.diag_embed(S) @ Vh


def normalize_scale(F: Tensor) -> Tensor:
    """Scale a homogeneous 3x3 matrix to unit Frobenius norm: (*, 3, 3)."""
    return F / floor_tiny(F.flatten(-2).norm(dim=-1))[..., None, None]


def epipolar_design_matrix(x1: Tensor, x2: Tensor) -> Tensor:
    """Rows ``u`` of eq. 3.3.3 with ``uᵀ f = x2ᵀ F x1`` for row-major f: (*, N, 2) x2 -> (*, N, 9)."""
    u1, v1 = x1.unbind(-1)
    u2, v2 = x2.unbind(-1)
    one = torch.ones_like(u1)
    return torch.stack([u2 * u1, u2 * v1, u2, v2 * u1, v2 * v1, v2, u1, v1, one], dim=-1)


def smallest_right_singular_vector(A: Tensor, weights: Tensor | None = None) -> Tensor:
    """Unit f minimizing ‖diag(w)^½ A f‖: A (*, N, M), weights (*, N) -> (*, M).

    Solved as the eigenvector of the smallest eigenvalue of AᵀWA, which batches cheaply; callers
    normalize their data first (Hartley), which keeps AᵀWA well conditioned in float64.
    """
    if weights is not None:
        A_weighted = A * weights[..., None]
    else:
        A_weighted = A
    _, vectors = torch.linalg.eigh(A_weighted.transpose(-1, -2) @ A)
    return vectors[..., 0]


def eight_point(x1: Tensor, x2: Tensor, weights: Tensor | None = None, *, enforce_rank2_constraint: bool = True) -> Tensor:
    """Normalized 8-point algorithm with rank-2 enforcement (Alg. 3.3.2).

    Args:
        x1, x2: pixel correspondences (*, N, 2), N >= 8 points of non-zero weight.
        weights: optional (*, N) weights; 0 drops a point (outliers, padding), so one call fits
            minimal samples and inlier sets alike.
        enforce_rank2_constraint: False returns the linear solution of Alg. 3.3.1 step 3 (rank 3
            under noise), for studies of what the constraint buys.

    Returns:
        F (*, 3, 3) of unit Frobenius norm with ``x2ᵀ F x1 ≈ 0``.
    """
    n1, T1 = hartley_normalize(x1, weights)
    n2, T2 = hartley_normalize(x2, weights)
    f = smallest_right_singular_vector(epipolar_design_matrix(n1, n2), weights)
    F = f.reshape(*f.shape[:-1], 3, 3)
    if enforce_rank2_constraint:
        F = enforce_rank2(F)
    return normalize_scale(T2.transpose(-1, -2) @ F @ T1)


# A fixed generic row appended to an 8x9 design matrix makes the null vector the solution of a
# square system; it only fails if the null vector is orthogonal to it (measure zero).
_GAUGE_ROW = (0.31, 0.53, 0.71, 0.17, 0.43, 0.89, 0.61, 0.23, 0.97)


def minimal_null_vectors(x1: Tensor, x2: Tensor, A1: Tensor, A2: Tensor) -> Tensor:
    """Epipolar matrices G of 8-point minimal samples in conditioned coordinates, unconstrained.

    The points are mapped by affine conditioning maps A1, A2 (Hartley's, computed once on all
    correspondences of the problem, so each sample costs an affine map rather than its own
    statistics); G satisfies (A2 x2)ᵀ G (A1 x1) = 0 on the sample. The null vector comes from one
    9x9 LU solve (the design matrix plus a fixed generic gauge row), which batches far better
    than an SVD per sample.

    Args:
        x1, x2: (B, K, 8, 2) pixel samples.
        A1, A2: (B, 3, 3) affine conditioning maps of image 1 and 2 (last row 0, 0, 1).

    Returns:
        (B, K, 3, 3) G, NaN for a degenerate sample.
    """
    design = epipolar_design_matrix(apply_affine(A1[:, None], x1), apply_affine(A2[:, None], x2))  # (B, K, 8, 9)
    gauge = design.new_tensor(_GAUGE_ROW).expand(*design.shape[:-2], 1, 9)
    rhs = design.new_zeros(*design.shape[:-2], 9, 1)
    rhs[..., 8, 0] = 1.0
    f, info = torch.linalg.solve_ex(torch.cat([design, gauge], dim=-2), rhs)
    return torch.where((info == 0)[..., None, None], f, torch.nan).reshape(*f.shape[:-2], 3, 3)


def det3(M: Tensor) -> Tensor:
    """Determinants of (*, 3, 3) matrices by cofactors (cheaper than an LU for many tiny ones)."""
    return (M[..., 0, 0] * (M[..., 1, 1] * M[..., 2, 2] - M[..., 1, 2] * M[..., 2, 1])
            - M[..., 0, 1] * (M[..., 1, 0] * M[..., 2, 2] - M[..., 1, 2] * M[..., 2, 0])
            + M[..., 0, 2] * (M[..., 1, 0] * M[..., 2, 1] - M[..., 1, 1] * M[..., 2, 0]))


def real_cubic_roots(a: Tensor, b: Tensor, c: Tensor) -> tuple[Tensor, Tensor]:
    """Real roots of x³ + a x² + b x + c (tensors of one shape *): (*, 3) roots and (*, 3) bool
    real. Depressed cubic t³ + p t + q (x = t − a/3): one real root by Cardano where the
    discriminant (q/2)² + (p/3)³ is positive, else three by the trigonometric method."""
    p = b - a.square() / 3
    q = 2 * a.pow(3) / 27 - a * b / 3 + c
    discriminant = (q / 2).square() + (p / 3).pow(3)
    one = discriminant > 0
    root = torch.sqrt(discriminant.clamp_min(0))
    cardano = torch.sign(-q / 2 + root) * (-q / 2 + root).abs().pow(1 / 3) + torch.sign(-q / 2 - root) * (-q / 2 - root).abs().pow(1 / 3)
    negative_p = (-p).clamp_min(torch.finfo(p.dtype).tiny)
    cosine = ((3 * q / (2 * -negative_p)) * torch.sqrt(3 / negative_p)).clamp(-1, 1)
    angle = torch.acos(cosine)[..., None] / 3 - 2 * torch.pi * torch.arange(3, dtype=p.dtype, device=p.device) / 3
    trigonometric = 2 * torch.sqrt(negative_p / 3)[..., None] * torch.cos(angle)
    t = torch.where(one[..., None], torch.stack([cardano, cardano, cardano], -1), trigonometric)
    real = torch.ones_like(t, dtype=torch.bool)
    real[..., 1:] = ~one[..., None]
    return t - (a / 3)[..., None], real & torch.isfinite(t)


def seven_point_minimal(x1: Tensor, x2: Tensor, T1: Tensor, T2: Tensor) -> Tensor:
    """The 7-point algorithm on (B, K, 7, 2) samples, built for RANSAC batches: up to three F.

    In the conditioned frame (T1, T2 (B, 3, 3), Hartley's maps of the whole problem) the 7×9
    design matrix has a 2-dimensional null space G1, G2 (one 9×9 LU solve with two generic gauge
    rows and two right-hand sides, as :func:`minimal_null_vectors`); det(α G1 + (1 − α) G2) = 0 is
    a cubic in α, its coefficients interpolated from four determinants and its real roots the
    closed-form roots (:func:`real_cubic_roots`). Each real root gives a rank-2 F, exact on the sample.
    Fewer samples than the 8-point algorithm's at the same confidence (0.4^7 vs 0.4^8 good
    samples at 60 % outliers: 2.5× fewer), at up to three hypotheses per sample.

    Returns:
        (B, K, 3, 3, 3) F in pixels (unit norm), the roots along dim 2 (NaN where a root is
        complex or the sample degenerate).
    """
    design = epipolar_design_matrix(apply_affine(T1[:, None], x1), apply_affine(T2[:, None], x2))  # (B, K, 7, 9)
    gauge = design.new_tensor([_GAUGE_ROW, _GAUGE_ROW[::-1]]).expand(*design.shape[:-2], 2, 9)
    rhs = design.new_zeros(*design.shape[:-2], 9, 2)
    rhs[..., 7, 0] = rhs[..., 8, 1] = 1.0
    null, info = torch.linalg.solve_ex(torch.cat([design, gauge], dim=-2), rhs)
    G1, G2 = null[..., 0].reshape(*null.shape[:-2], 3, 3), null[..., 1].reshape(*null.shape[:-2], 3, 3)
    d = det3(torch.stack([a * G1 + (1 - a) * G2 for a in (-1.0, 0.0, 1.0, 2.0)], dim=-3))  # (B, K, 4)
    c0, c2 = d[..., 1], (d[..., 2] + d[..., 0]) / 2 - d[..., 1]
    odd = (d[..., 2] - d[..., 0]) / 2  # c3 + c1
    c3 = (d[..., 3] - 4 * c2 - c0 - 2 * odd) / 6
    c1 = odd - c3
    usable = (info == 0) & (c3.abs() > 1e-12 * d.abs().amax(-1)) & torch.isfinite(d).all(-1)
    lead = torch.where(usable, c3, 1.0)
    alpha, real = real_cubic_roots(c2 / lead, c1 / lead, c0 / lead)  # (B, K, 3)
    real &= usable[..., None]
    alpha = alpha[..., None, None]
    G = alpha * G1[..., None, :, :] + (1 - alpha) * G2[..., None, :, :]  # (B, K, 3, 3, 3)
    F = normalize_scale(T2[:, None, None].transpose(-1, -2) @ G @ T1[:, None, None])
    return torch.where(real[..., None, None], F, torch.nan)


def eight_point_minimal(x1: Tensor, x2: Tensor, T1: Tensor, T2: Tensor) -> Tensor:
    """The normalized 8-point algorithm on (B, K, 8, 2) samples, built for RANSAC batches.

    Rank 2 is enforced in the normalized frame as ``G - (G v) vᵀ`` with v the closed-form
    smallest right singular vector (same result as the SVD truncation of eq. 3.3.5).
    T1, T2 (B, 3, 3) are Hartley normalizations; returns F (B, K, 3, 3) in pixels, unit norm.
    """
    G = minimal_null_vectors(x1, x2, T1, T2)
    v = smallest_eigenvector_sym3(G.transpose(-1, -2) @ G)
    G = G - (G @ v[..., None]) @ v[..., None, :]
    return normalize_scale(T2[:, None].transpose(-1, -2) @ G @ T1[:, None])


def _epipolar_terms(F: Tensor, x1: Tensor, x2: Tensor) -> tuple[Tensor, Tensor, Tensor]:
    """(x2ᵀ F x1 (*, N), F x1 (*, 3, N), Fᵀ x2 (*, 3, N)) for broadcast F (*, 3, 3), points (*, N, 2).

    Lines are kept coordinate-major so that scoring K hypotheses is one batched GEMM each.
    """
    h1, h2 = to_homogeneous(x1).transpose(-1, -2), to_homogeneous(x2).transpose(-1, -2)  # (*, 3, N)
    line2 = F @ h1  # epipolar lines in image 2
    line1 = F.transpose(-1, -2) @ h2  # epipolar lines in image 1
    algebraic = (h2 * line2).sum(-2)
    return algebraic, line2, line1


def sampson_residual(F: Tensor, x1: Tensor, x2: Tensor) -> Tensor:
    """Signed Sampson residual (pixels); its square is the Sampson error of eq. 3.3.6: (*, N)."""
    algebraic, line2, line1 = _epipolar_terms(F, x1, x2)
    denominator = line2[..., :2, :].square().sum(-2) + line1[..., :2, :].square().sum(-2)
    return algebraic / floor_tiny(denominator).sqrt()


def sampson_jacobian(F: Tensor, x1: Tensor, x2: Tensor, directions: Tensor) -> Tensor:
    """Derivatives of :func:`sampson_residual` along directions in the space of F.

    F (B, 3, 3), x1, x2 (B, N, 2), directions D (B, P, 3, 3) -> (B, N, P) with entry p the
    derivative of the residual along F + εD_p. With a = x2ᵀFx1, l2 = F x1, l1 = Fᵀ x2,
    d = l2₁² + l2₂² + l1₁² + l1₂² and c = a / d:
    dr/dF = (u x1ᵀ - x2 vᵀ) / √d with u = x2 - c (l2₁, l2₂, 0), v = c (l1₁, l1₂, 0), and
    dr·D_p = ⟨dr/dF, D_p⟩: one (N, 9) x (9, P) product. The outer products are formed
    coordinate-major, each element-wise step running along the N points (point-major, over
    trailing axes of 3, they ran at half the speed).
    """
    B, P = directions.shape[:2]
    N = x1.shape[-2]
    h1, h2 = to_homogeneous(x1), to_homogeneous(x2)  # (B, N, 3)
    line2 = h1 @ F.transpose(-1, -2)  # (B, N, 3)
    line1 = h2 @ F
    products = h2 * line2
    algebraic = products[..., 0] + products[..., 1] + products[..., 2]  # not .sum(-1): 7x slower over 3, same sum
    squares2, squares1 = line2[..., :2].square(), line1[..., :2].square()
    denominator = floor_tiny((squares2[..., 0] + squares2[..., 1]) + (squares1[..., 0] + squares1[..., 1]))
    c = (algebraic / denominator)[..., None]
    first_two = torch.tensor([1.0, 1.0, 0.0], dtype=F.dtype, device=F.device)
    line2, line1 = line2 * first_two, line1 * first_two
    u, v, h1, h2 = ((h2 - c * line2).mT.contiguous(), (c * line1).mT.contiguous(), h1.mT.contiguous(), h2.mT.contiguous())
    gradient = u[:, :, None] * h1[:, None] - h2[:, :, None] * v[:, None]  # (B, 3, 3, N): coordinate-major, each step along N
    gradient = gradient.reshape(B, 9, N).mT.contiguous()  # (B, N, 9) for the product
    return (gradient @ directions.reshape(B, P, 9).mT) / denominator.sqrt()[..., None]


def sampson_error(F: Tensor, x1: Tensor, x2: Tensor) -> Tensor:
    """Sampson error of eq. 3.3.6 (pixels²), F (*, 3, 3), x1, x2 (*, N, 2) -> (*, N)."""
    return sampson_residual(F, x1, x2).square()


def sampson_error_of_hypotheses(F: Tensor, x1: Tensor, x2: Tensor) -> Tensor:
    """Sampson error (pixels²) of H hypotheses on the same points, as three GEMMs per problem.

    F (B, H, 3, 3), x1, x2 (B, N, 2) -> (B, H, N); computed in the dtype of the inputs. The
    algebraic error is (x2 ⊗ x1)·vec(F) and the line components are an (N, 3) x (3, 2H) product
    per image, so the cost is dominated by matrix products instead of per-hypothesis
    broadcasting.
    """
    B, H = F.shape[:2]
    N = x1.shape[-2]
    h1, h2 = to_homogeneous(x1), to_homogeneous(x2)  # (B, N, 3)
    algebraic = epipolar_design_matrix(x1, x2) @ F.reshape(B, H, 9).transpose(-1, -2)  # (B, N, H): rows x2 ⊗ x1
    line2 = h1 @ F[:, :, :2, :].reshape(B, 2 * H, 3).transpose(-1, -2)  # (B, N, 2H): rows 0, 1 of F on h1
    line1 = h2 @ F[:, :, :, :2].transpose(-1, -2).reshape(B, 2 * H, 3).transpose(-1, -2)  # columns 0, 1 on h2
    line2, line1 = line2.square_().reshape(B, N, H, 2), line1.square_().reshape(B, N, H, 2)
    denominator = line2[..., 0] + line2[..., 1]  # not .sum(-1): slow over 2; in place: no more (B, N, H) tables
    denominator += line1[..., 0]
    denominator += line1[..., 1]
    return algebraic.square_().div_(denominator.clamp_min_(1e-30)).transpose(-1, -2)


def epipolar_line_distances(F: Tensor, x1: Tensor, x2: Tensor) -> tuple[Tensor, Tensor]:
    """Distances (pixels) of x1 to its epipolar line Fᵀx2 and of x2 to F x1: two (*, N)."""
    algebraic, line2, line1 = _epipolar_terms(F, x1, x2)
    d1 = algebraic.abs() / floor_tiny(line1[..., :2, :].norm(dim=-2))
    d2 = algebraic.abs() / floor_tiny(line2[..., :2, :].norm(dim=-2))
    return d1, d2


def symmetric_epipolar_distance(F: Tensor, x1: Tensor, x2: Tensor) -> Tensor:
    """Root mean square of the two point-to-epipolar-line distances, in pixels: (*, N).

    ``sqrt((d(x1, Fᵀx2)² + d(x2, F x1)²) / 2)``, so a value of 1 px means each point lies about
    1 px from its epipolar line.
    """
    d1, d2 = epipolar_line_distances(F, x1, x2)
    return ((d1.square() + d2.square()) / 2).sqrt()


def fundamental_from_projections(P1: Tensor, P2: Tensor) -> Tensor:
    """F = [e2]x P2 P1⁺ with e2 = P2 C1 (H&Z eq. 9.1): (*, 3, 4) x2 -> (*, 3, 3), unit norm."""
    _, _, Vh = torch.linalg.svd(P1)
    C1 = Vh[..., -1, :]  # (*, 4): right null vector of P1
    e2 = (P2 @ C1[..., None]).squeeze(-1)
    return normalize_scale(skew(e2) @ P2 @ torch.linalg.pinv(P1))


def fundamental_from_pose(K1: Tensor, K2: Tensor, R: Tensor, t: Tensor) -> Tensor:
    """F = K2⁻ᵀ [t]x R K1⁻¹ for camera 2 = [R | t] relative to camera 1: (*, 3, 3), unit norm."""
    E = skew(t) @ R
    return normalize_scale(torch.linalg.inv(K2).transpose(-1, -2) @ E @ torch.linalg.inv(K1))
