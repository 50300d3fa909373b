"""Two-view triangulation by every method of thesis §3.5, batched over points and problems.

Every method maps pixel correspondences x1, x2 (*, N, 2) and cameras P1, P2 (*, 3, 4) to
homogeneous points (*, N, 4); :func:`triangulate_points` dehomogenizes. Methods:

* ``midpoint`` — midpoint of the common perpendicular of the two rays (§3.5.2); Euclidean only.
* ``linear_eigen`` — unit X minimizing ‖A X‖ (§3.5.3.1), by SVD of the 4x4 system.
* ``linear_ls`` — X = (x, y, z, 1) by least squares on A (§3.5.3.2); affine invariant.
* ``iterative_eigen``, ``iterative_ls`` — Hartley & Sturm's reweighting of A's rows by the
  projective depths of the previous estimate (§3.5.4).
* ``polynomial`` — Hartley & Sturm's optimal method (§3.5.5 with the ERRATA): correct the
  points onto a pair of matching epipolar lines minimizing the reprojection error by the roots
  of a degree-6 polynomial, then intersect the (now exactly consistent) rays.
"""

from __future__ import annotations

from collections.abc import Callable

import torch
from torch import Tensor

from torchsfm.camera import camera_center, from_homogeneous, to_homogeneous
from torchsfm.config import TriangulationConfig
from torchsfm.errors import DegenerateConfigurationError, InputError, ShapeError
from torchsfm.geometry.fundamental import fundamental_from_projections
from torchsfm.validation import check_finite, check_floating, check_min_count, check_shapes
from torchsfm.numerics import floor_tiny

TriangulationFn = Callable[..., Tensor]


def _linear_system(x1: Tensor, x2: Tensor, P1: Tensor, P2: Tensor) -> Tensor:
    """Rows of eq. 3.5.8, (*, N, 4, 4): u p3ᵀ - p1ᵀ and v p3ᵀ - p2ᵀ for both views."""
    def rows(x: Tensor, P: Tensor) -> Tensor:
        P = P[..., None, :, :]  # (*, 1, 3, 4)
        return x[..., :, None] * P[..., 2:3, :] - P[..., :2, :]  # (*, N, 2, 4)

    return torch.cat([rows(x1, P1), rows(x2, P2)], dim=-2)


def _null_vector(A: Tensor) -> Tensor:
    """Right singular vector of the smallest singular value: (*, 4, 4) -> (*, 4); NaN where A
    holds a non-finite number (e.g. a zero-baseline pair's correction), not an error for the batch."""
    finite = torch.isfinite(A).flatten(-2).all(-1)
    vector = torch.linalg.svd(torch.where(finite[..., None, None], A, 0.0)).Vh[..., -1, :]
    return torch.where(finite[..., None], vector, float("nan"))


def _least_squares_point(A: Tensor) -> Tensor:
    """(x, y, z, 1) minimizing ‖A [x y z 1]ᵀ‖: (*, 4, 4) -> (*, 4)."""
    solution = torch.linalg.lstsq(A[..., :3], -A[..., 3:]).solution.squeeze(-1)
    return to_homogeneous(solution)


def triangulate_linear_eigen(x1: Tensor, x2: Tensor, P1: Tensor, P2: Tensor) -> Tensor:
    """Linear-eigen method: (*, N, 2) x2, (*, 3, 4) x2 -> (*, N, 4)."""
    return _null_vector(_linear_system(x1, x2, P1, P2))


def triangulate_linear_ls(x1: Tensor, x2: Tensor, P1: Tensor, P2: Tensor) -> Tensor:
    """Linear least-squares method (fourth coordinate fixed to 1): -> (*, N, 4)."""
    return _least_squares_point(_linear_system(x1, x2, P1, P2))


def _iterative(solve: Callable[[Tensor], Tensor], x1: Tensor, x2: Tensor, P1: Tensor, P2: Tensor,
               max_iterations: int, tolerance: float) -> Tensor:
    """Hartley & Sturm's reweighting: divide each view's rows by p3ᵀX of the last estimate."""
    A = _linear_system(x1, x2, P1, P2)  # (*, N, 4, 4)
    X = solve(A)
    depth_rows = torch.stack([P1[..., 2, :], P2[..., 2, :]], dim=-2)  # (*, 2, 4)
    weights = torch.ones_like(A[..., :2, 0])  # (*, N, 2)
    for _ in range(max_iterations):
        new_weights = X @ depth_rows.transpose(-1, -2)  # (*, N, 2): p3ᵀX for each view
        new_weights = torch.where(new_weights.abs() > 1e-300, new_weights, torch.ones_like(new_weights))
        change = ((new_weights - weights).abs() / new_weights.abs()).amax()
        weights = new_weights
        scale = weights.repeat_interleave(2, dim=-1)  # (*, N, 4): two rows per view
        X = solve(A / scale[..., None])
        if float(change) < tolerance:
            break
    return X


def triangulate_iterative_eigen(x1: Tensor, x2: Tensor, P1: Tensor, P2: Tensor,
                                max_iterations: int = 10, tolerance: float = 1e-10) -> Tensor:
    """Iterative-eigen method (Hartley & Sturm 1997): -> (*, N, 4)."""
    return _iterative(_null_vector, x1, x2, P1, P2, max_iterations, tolerance)


def triangulate_iterative_ls(x1: Tensor, x2: Tensor, P1: Tensor, P2: Tensor,
                             max_iterations: int = 10, tolerance: float = 1e-10) -> Tensor:
    """Iterative-LS method (Hartley & Sturm 1997): -> (*, N, 4)."""
    return _iterative(_least_squares_point, x1, x2, P1, P2, max_iterations, tolerance)


def triangulate_midpoint(x1: Tensor, x2: Tensor, P1: Tensor, P2: Tensor) -> Tensor:
    """Midpoint of the shortest segment between the back-projected rays: -> (*, N, 4)."""
    C1, C2 = camera_center(P1)[..., None, :], camera_center(P2)[..., None, :]  # (*, 1, 3)
    d1 = torch.linalg.solve(P1[..., None, :, :3], to_homogeneous(x1)[..., None]).squeeze(-1)  # (*, N, 3)
    d2 = torch.linalg.solve(P2[..., None, :, :3], to_homogeneous(x2)[..., None]).squeeze(-1)
    w0 = C1 - C2
    a, b, c = (d1 * d1).sum(-1), (d1 * d2).sum(-1), (d2 * d2).sum(-1)
    d, e = (d1 * w0).sum(-1), (d2 * w0).sum(-1)
    denominator = floor_tiny((a * c - b * b))  # 0 only for parallel rays
    lambda1 = (b * e - c * d) / denominator
    lambda2 = (a * e - b * d) / denominator
    midpoint = 0.5 * (C1 + lambda1[..., None] * d1 + C2 + lambda2[..., None] * d2)
    return to_homogeneous(midpoint)


def _polymul(p: Tensor, q: Tensor) -> Tensor:
    """Product of polynomials with ascending coefficients: (*, m), (*, n) -> (*, m + n - 1)."""
    out = p.new_zeros(*(p[..., 0] * q[..., 0]).shape, p.shape[-1] + q.shape[-1] - 1)  # the broadcast leading shape
    for i in range(p.shape[-1]):
        out[..., i:i + q.shape[-1]] += p[..., i:i + 1] * q
    return out


def _real_roots_degree6(coefficients: Tensor) -> Tensor:
    """Real parts of the roots of polynomials of degree <= 6: (*, 7) ascending -> (*, 6).

    Negligible leading coefficients are dropped by multiplying by a power of t (adding roots at
    0, which are harmless extra candidates), so a lower degree never yields a singular
    companion matrix. Roots come from the eigenvalues of the companion matrix.
    """
    scale = coefficients.abs().amax(-1, keepdim=True)
    c = coefficients / torch.where(scale > 0, scale, torch.ones_like(scale))
    significant = c.abs() > 1e-12
    powers = torch.arange(7, device=c.device)
    degree = torch.where(significant, powers, -1).amax(-1)  # (*,)
    degree_zero = degree <= 0
    shift = (6 - degree.clamp_min(0))[..., None]
    source = powers - shift  # (*, 7): coefficient j of t^shift p(t) is c[j - shift]
    c = torch.where(source >= 0, c.gather(-1, source.clamp_min(0)), torch.zeros_like(c))
    c = torch.where(degree_zero[..., None], (powers == 6).to(c.dtype), c)  # constant: roots at 0
    monic = c[..., :6] / c[..., 6:7]
    companion = torch.diag_embed(torch.ones_like(monic[..., :5]), offset=-1)  # (*, 6, 6)
    companion[..., 0, :] = -monic.flip(-1)
    return torch.linalg.eigvals(companion).real


def correct_correspondences(x1: Tensor, x2: Tensor, F: Tensor) -> tuple[Tensor, Tensor]:
    """Hartley–Sturm optimal correction (H&Z Alg. 12.1): the closest pair to (x1, x2) with
    ``x̂2ᵀ F x̂1 = 0`` in summed squared image distance. (*, N, 2) x2, F (*, 3, 3) -> two (*, N, 2).
    """
    dtype = x1.dtype
    F = F[..., None, :, :]  # (*, 1, 3, 3)
    _, _, Vh = torch.linalg.svd(F)
    e1 = Vh[..., -1, :]  # F e1 = 0
    _, _, Vh_t = torch.linalg.svd(F.transpose(-1, -2))
    e2 = Vh_t[..., -1, :]  # Fᵀ e2 = 0

    def to_origin(x: Tensor, e: Tensor) -> tuple[Tensor, Tensor, Tensor]:
        """Epipole after moving x to the origin, scaled so e_x² + e_y² = 1, and the rotation R."""
        moved = torch.stack([e[..., 0] - e[..., 2] * x[..., 0], e[..., 1] - e[..., 2] * x[..., 1], e[..., 2].expand_as(x[..., 0])], dim=-1)
        moved = moved / floor_tiny(moved[..., :2].norm(dim=-1, keepdim=True))
        ex, ey = moved[..., 0], moved[..., 1]
        zero, one = torch.zeros_like(ex), torch.ones_like(ex)
        R = torch.stack([ex, ey, zero, -ey, ex, zero, zero, zero, one], dim=-1).reshape(*ex.shape, 3, 3)
        T_inverse = torch.stack([one, zero, x[..., 0], zero, one, x[..., 1], zero, zero, one], dim=-1).reshape(*ex.shape, 3, 3)
        return moved, R, T_inverse

    e1n, R1, T1_inv = to_origin(x1, e1)
    e2n, R2, T2_inv = to_origin(x2, e2)
    F_t = R2 @ T2_inv.transpose(-1, -2) @ F @ T1_inv @ R1.transpose(-1, -2)  # (*, N, 3, 3)
    f1, f2 = e1n[..., 2], e2n[..., 2]
    a, b, c, d = F_t[..., 1, 1], F_t[..., 1, 2], F_t[..., 2, 1], F_t[..., 2, 2]

    at_b = torch.stack([b, a], dim=-1)  # a t + b
    ct_d = torch.stack([d, c], dim=-1)  # c t + d
    quadratic = _polymul(at_b, at_b) + (f2 * f2)[..., None] * _polymul(ct_d, ct_d)
    zero = torch.zeros_like(a)
    one_plus = torch.stack([torch.ones_like(a), zero, f1 * f1], dim=-1)  # 1 + f² t²
    first = _polymul(torch.stack([zero, torch.ones_like(a)], dim=-1), _polymul(quadratic, quadratic))  # degree 5
    second = (a * d - b * c)[..., None] * _polymul(_polymul(one_plus, one_plus), _polymul(at_b, ct_d))  # degree 6
    g = torch.cat([first, torch.zeros_like(first[..., :1])], dim=-1) - second  # (*, N, 7)
    t = _real_roots_degree6(g)  # (*, N, 6)

    def cost(t: Tensor) -> Tensor:
        a_, b_, c_, d_ = a[..., None], b[..., None], c[..., None], d[..., None]
        f1_, f2_ = f1[..., None], f2[..., None]
        return t * t / (1 + f1_ * f1_ * t * t) + (c_ * t + d_) ** 2 / floor_tiny(((a_ * t + b_) ** 2 + f2_ * f2_ * (c_ * t + d_) ** 2))

    costs = cost(t)
    best_cost, best = costs.min(dim=-1)
    t_best = t.gather(-1, best[..., None]).squeeze(-1)
    infinity_cost = torch.where(f1 != 0, 1 / floor_tiny((f1 * f1)) + c * c / floor_tiny((a * a + f2 * f2 * c * c)), torch.full_like(f1, float("inf")))
    at_infinity = infinity_cost < best_cost

    one = torch.ones_like(t_best)
    line1 = torch.where(at_infinity[..., None], torch.stack([f1, zero, -one], -1), torch.stack([t_best * f1, one, -t_best], -1))
    line2 = torch.where(at_infinity[..., None], torch.stack([-f2 * c, a, c], -1),
                        torch.stack([-f2 * (c * t_best + d), a * t_best + b, c * t_best + d], -1))

    def foot_of_origin(line: Tensor) -> Tensor:
        return torch.stack([-line[..., 0] * line[..., 2], -line[..., 1] * line[..., 2], (line[..., :2] ** 2).sum(-1)], dim=-1)

    x1_hat = from_homogeneous((foot_of_origin(line1)[..., None, :] @ (T1_inv @ R1.transpose(-1, -2)).transpose(-1, -2)).squeeze(-2))
    x2_hat = from_homogeneous((foot_of_origin(line2)[..., None, :] @ (T2_inv @ R2.transpose(-1, -2)).transpose(-1, -2)).squeeze(-2))
    return x1_hat.to(dtype), x2_hat.to(dtype)


def triangulate_polynomial(x1: Tensor, x2: Tensor, P1: Tensor, P2: Tensor) -> Tensor:
    """Optimal (polynomial) triangulation: correct, then intersect the rays: -> (*, N, 4)."""
    x1_hat, x2_hat = correct_correspondences(x1, x2, fundamental_from_projections(P1, P2))
    return triangulate_linear_eigen(x1_hat, x2_hat, P1, P2)


TRIANGULATION_METHODS: dict[str, TriangulationFn] = {
    "midpoint": triangulate_midpoint,
    "linear_eigen": triangulate_linear_eigen,
    "linear_ls": triangulate_linear_ls,
    "iterative_eigen": triangulate_iterative_eigen,
    "iterative_ls": triangulate_iterative_ls,
    "polynomial": triangulate_polynomial,
}


def triangulate_points(x1: Tensor, x2: Tensor, P1: Tensor, P2: Tensor, config: TriangulationConfig) -> Tensor:
    """Dehomogenized triangulation with the configured method: -> (*, N, 3). No input checks."""
    method = TRIANGULATION_METHODS[config.method]
    if config.method.startswith("iterative"):
        X = method(x1, x2, P1, P2, max_iterations=config.max_iterations, tolerance=config.tolerance)
    else:
        X = method(x1, x2, P1, P2)
    return from_homogeneous(X)


def parallel_rays(x1: Tensor, x2: Tensor, P1: Tensor, P2: Tensor) -> Tensor:
    """(*, N) bool: the rays of pixels x1, x2 (*, N, 2) through finite cameras P1, P2 (*, 3, 4)
    are parallel to float64 rounding (the sine of their angle at most 1e-12)."""
    d1 = torch.linalg.solve(P1[..., :3], to_homogeneous(x1).transpose(-1, -2)).transpose(-1, -2)  # (*, N, 3) directions
    d2 = torch.linalg.solve(P2[..., :3], to_homogeneous(x2).transpose(-1, -2)).transpose(-1, -2)
    return torch.linalg.cross(d1, d2).norm(dim=-1) <= 1e-12 * d1.norm(dim=-1) * d2.norm(dim=-1)


def triangulate(x1: Tensor, x2: Tensor, P1: Tensor, P2: Tensor, method: str = "polynomial") -> Tensor:
    """Triangulate pixel correspondences seen by two cameras.

    Args:
        x1, x2: pixels (N, 2) or (B, N, 2).
        P1, P2: projection matrices (3, 4) or (B, 3, 4), finite cameras with distinct centres.
        method: one of :data:`TRIANGULATION_METHODS` (default: the optimal polynomial method).

    Returns:
        3-D points (N, 3) or (B, N, 3) in the frame of the cameras, in the input dtype
        (computed in float64).

    Raises:
        ShapeError, InputError: malformed input or unknown method. DegenerateConfigurationError:
        a camera with a singular left 3x3 block, both cameras at the same centre, or a
        correspondence whose two rays are parallel (a point at infinity: no finite position).
    """
    if method not in TRIANGULATION_METHODS:
        raise InputError(f"unknown triangulation method {method!r}; choose one of {', '.join(TRIANGULATION_METHODS)}")
    check_shapes(x1=(x1, "* N 2"), x2=(x2, "* N 2"), P1=(P1, "* 3 4"), P2=(P2, "* 3 4"))
    if x1.dim() not in (2, 3) or x1.shape != x2.shape:
        raise ShapeError(f"x1 and x2 must both be (N, 2) or (B, N, 2), got {tuple(x1.shape)} and {tuple(x2.shape)}")
    check_floating(x1=x1, x2=x2, P1=P1, P2=P2)
    check_finite(x1=x1, x2=x2, P1=P1, P2=P2)
    check_min_count("x1", x1.shape[-2], 1, "triangulation (points)")
    P1d, P2d = P1.double(), P2.double()
    for name, P in (("P1", P1d), ("P2", P2d)):
        M = P[..., :3]
        if bool((torch.linalg.det(M).abs() <= 1e-12 * M.abs().amax(dim=(-2, -1)) ** 3).any()):
            raise DegenerateConfigurationError(f"{name} is not a finite camera (its left 3x3 block is singular)")
    C1, C2 = camera_center(P1d), camera_center(P2d)
    scale = torch.maximum(C1.norm(dim=-1), C2.norm(dim=-1)).clamp_min(1.0)
    if bool(((C1 - C2).norm(dim=-1) <= 1e-12 * scale).any()):
        raise DegenerateConfigurationError("P1 and P2 have the same centre: no baseline to triangulate from")
    parallel = parallel_rays(x1.double(), x2.double(), P1d, P2d)
    if bool(parallel.any()):
        raise DegenerateConfigurationError(
            f"{int(parallel.sum())} correspondence(s) have parallel rays (the first: point {int(parallel.flatten().nonzero()[0, 0]) % x1.shape[-2]}): "
            "a point at infinity has no finite position")
    X = triangulate_points(x1.double(), x2.double(), P1d, P2d, TriangulationConfig(method=method))
    return X.to(x1.dtype)
