"""The essential matrix and the relative pose it encodes (thesis §3.4, with the ERRATA).

Convention: camera 1 is ``[I | 0]``, camera 2 is ``[R | t]`` (``X2 = R X1 + t``) and
``E = [t]x R`` so that ``x2ᵀ E x1 = 0`` for normalized coordinates. Three ways from E to the
four (R, t) candidates are offered, all resolved by the same cheirality test:

* ``svd`` — E = U diag(1, 1, 0) Vᵀ; R ∈ {U W Vᵀ, U Wᵀ Vᵀ}, t = ±u3 (H&Z §9.6.2).
* ``linear`` — thesis eq. 3.4.10–3.4.11: t̂ from a cross product of E's columns, R column by
  column; R is projected onto SO(3) at the end (the thesis leaves it raw).
* ``quaternion`` — thesis eq. 3.4.12–3.4.15: t̂ as the least-squares null vector of Eᵀ (the
  thesis writes EᵀE; the left null vector of E is what satisfies Eᵀt̂ = 0), then R from the
  quaternion minimizing ‖Rᵀ[-t̂]x - Eᵀ‖.
"""

from __future__ import annotations

import math

import torch
from torch import Tensor

from torchsfm.geometry.rotation import nearest_rotation, quaternion_to_rotation, skew
from torchsfm.numerics import floor_tiny


def essential_from_fundamental(F: Tensor, K1: Tensor, K2: Tensor) -> Tensor:
    """E = K2ᵀ F K1 (the ERRATA's general form of eq. 3.4.1), scaled to ‖E‖_F = sqrt(2)."""
    E = K2.transpose(-1, -2) @ F @ K1
    return E * (math.sqrt(2) / floor_tiny(E.flatten(-2).norm(dim=-1)))[..., None, None]


def project_to_essential(E: Tensor) -> Tensor:
    """Nearest essential matrix in Frobenius norm, U diag(1, 1, 0) Vᵀ: (*, 3, 3) -> (*, 3, 3)."""
    U, _, Vh = torch.linalg.svd(E)
    return U @ torch.diag(E.new_tensor([1.0, 1.0, 0.0])) @ Vh


def essential_from_pose(R: Tensor, t: Tensor) -> Tensor:
    """E = [t]x R: (*, 3, 3), (*, 3) -> (*, 3, 3)."""
    return skew(t) @ R


def _proper(U: Tensor) -> Tensor:
    """Flip the sign of an orthogonal matrix with det -1 so it becomes a rotation."""
    return U * torch.sign(torch.linalg.det(U))[..., None, None]


def pose_candidates_svd(E: Tensor) -> tuple[Tensor, Tensor]:
    """The four (R, t) of E by SVD: (*, 3, 3) -> R (*, 4, 3, 3), unit t (*, 4, 3)."""
    U, _, Vh = torch.linalg.svd(E)
    U, Vh = _proper(U), _proper(Vh)
    W = E.new_tensor([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])
    Ra, Rb = U @ W @ Vh, U @ W.transpose(-1, -2) @ Vh
    t = U[..., :, 2]
    return torch.stack([Ra, Ra, Rb, Rb], dim=-3), torch.stack([t, -t, t, -t], dim=-2)


def pose_candidates_linear(E: Tensor) -> tuple[Tensor, Tensor]:
    """The four (R, t) of eq. 3.4.10–3.4.11 (signs of E and t̂): -> (*, 4, 3, 3), (*, 4, 3).

    t̂ is taken from the pair of columns with the largest cross product (the best conditioned
    choice among i ≠ j); each R is projected to the nearest rotation.
    """
    def one(E: Tensor, t_sign: float) -> tuple[Tensor, Tensor]:
        e = E.transpose(-1, -2)  # rows are the columns e1, e2, e3
        crosses = torch.stack([torch.linalg.cross(e[..., 0, :], e[..., 1, :]),
                               torch.linalg.cross(e[..., 1, :], e[..., 2, :]),
                               torch.linalg.cross(e[..., 2, :], e[..., 0, :])], dim=-2)
        best = crosses.norm(dim=-1).argmax(-1)
        cross = torch.gather(crosses, -2, best[..., None, None].expand(*best.shape, 1, 3)).squeeze(-2)
        t = t_sign * cross / floor_tiny(cross.norm(dim=-1, keepdim=True))
        k = torch.sqrt(0.5 * E.square().sum(dim=(-2, -1)))[..., None]
        columns = []
        for i in range(3):
            ej, ek = e[..., (i + 1) % 3, :], e[..., (i + 2) % 3, :]
            along_t = (t * torch.linalg.cross(ej, ek)).sum(-1, keepdim=True) / (k * k)
            columns.append(along_t * t + torch.linalg.cross(e[..., i, :], t) / k)
        return nearest_rotation(torch.stack(columns, dim=-1)), t

    candidates = [one(sign_E * E, sign_t) for sign_E in (1.0, -1.0) for sign_t in (1.0, -1.0)]
    return torch.stack([c[0] for c in candidates], dim=-3), torch.stack([c[1] for c in candidates], dim=-2)


def _quaternion_rotation(C: Tensor, D: Tensor) -> Tensor:
    """Rotation Q minimizing Σ‖Q cᵢ - dᵢ‖² over the columns of C, D (eq. 3.4.14): (*, 3, 3)."""
    B_total = torch.zeros(*C.shape[:-2], 4, 4, dtype=C.dtype, device=C.device)
    for i in range(3):
        c, d = C[..., :, i], D[..., :, i]
        top = torch.cat([torch.zeros_like(c[..., :1]), (c - d)], dim=-1)[..., None, :]  # (*, 1, 4)
        bottom = torch.cat([(d - c)[..., :, None], skew(d + c)], dim=-1)  # (*, 3, 4)
        B_i = torch.cat([top, bottom], dim=-2)
        B_total = B_total + B_i.transpose(-1, -2) @ B_i
    _, vectors = torch.linalg.eigh(B_total)
    return quaternion_to_rotation(vectors[..., 0])


def pose_candidates_quaternion(E: Tensor) -> tuple[Tensor, Tensor]:
    """The four (R, t) of eq. 3.4.12–3.4.15 (signs of E and t̂): -> (*, 4, 3, 3), (*, 4, 3)."""
    _, vectors = torch.linalg.eigh(E @ E.transpose(-1, -2))
    t0 = vectors[..., 0]  # unit, minimizes ‖Eᵀ t‖
    Rs, ts = [], []
    for sign_E in (1.0, -1.0):
        for sign_t in (1.0, -1.0):
            t = sign_t * t0
            Q = _quaternion_rotation(skew(-t), sign_E * E.transpose(-1, -2))  # Q [-t]x ≈ Eᵀ, Q = Rᵀ
            Rs.append(Q.transpose(-1, -2))
            ts.append(t)
    return torch.stack(Rs, dim=-3), torch.stack(ts, dim=-2)


POSE_CANDIDATES = {
    "svd": pose_candidates_svd,
    "linear": pose_candidates_linear,
    "quaternion": pose_candidates_quaternion,
}


def two_view_depths(R: Tensor, t: Tensor, x1: Tensor, x2: Tensor) -> tuple[Tensor, Tensor]:
    """Depths (λ1, λ2) with λ2 x̃2 ≈ λ1 R x̃1 + t, in closed form (cross products with x̃2, R x̃1).

    R (*, 3, 3), t (*, 3), normalized points x1, x2 (*, N, 2) -> two (*, N). A point is in front
    of both cameras when both depths are positive. R x̃1 and the cross products are written out
    per coordinate: each step then runs along the N points (``torch.linalg.cross`` over a last
    axis of 3 ran at a fifth of the speed, and the product with R copied the points per candidate).
    """
    v0, v1 = x1.unbind(-1)  # x̃1 = (v0, v1, 1)
    r0, r1, r2 = (R[..., k, 0, None] * v0 + R[..., k, 1, None] * v1 + R[..., k, 2, None] for k in range(3))  # R x̃1, (*, N) each
    u0, u1 = x2.unbind(-1)  # x̃2 = (u0, u1, 1)
    t0, t1, t2 = (component[..., None] for component in t.unbind(-1))
    c0, c1, c2 = u1 * r2 - r1, r0 - u0 * r2, u0 * r1 - u1 * r0  # x̃2 × R x̃1
    squared_norm = floor_tiny(c0 * c0 + c1 * c1 + c2 * c2)
    depth1 = -(c0 * (u1 * t2 - t1) + c1 * (t0 - u0 * t2) + c2 * (u0 * t1 - u1 * t0)) / squared_norm  # c · (x̃2 × t)
    depth2 = (c0 * (t1 * r2 - t2 * r1) + c1 * (t2 * r0 - t0 * r2) + c2 * (t0 * r1 - t1 * r0)) / squared_norm  # c · (t × R x̃1)
    return depth1, depth2


def cheirality_counts(R: Tensor, t: Tensor, x1: Tensor, x2: Tensor, weights: Tensor | None = None) -> Tensor:
    """Number of points in front of both cameras for each candidate pose.

    Args:
        R, t: candidates (*, C, 3, 3), (*, C, 3).
        x1, x2: normalized correspondences (*, N, 2).
        weights: optional (*, N) 0/1 mask.

    Returns:
        (*, C) counts (as floats).
    """
    depth1, depth2 = two_view_depths(R, t, x1[..., None, :, :], x2[..., None, :, :])  # (*, C, N)
    in_front = ((depth1 > 0) & (depth2 > 0)).to(R.dtype)
    if weights is not None:
        in_front = in_front * weights[..., None, :]
    return in_front.sum(-1)


def select_pose(R: Tensor, t: Tensor, x1: Tensor, x2: Tensor, weights: Tensor | None = None) -> tuple[Tensor, Tensor, Tensor]:
    """Keep the candidate with the most points in front of both cameras.

    Returns R (*, 3, 3), t (*, 3) and the fraction (*,) of (weighted) points in front.
    """
    counts = cheirality_counts(R, t, x1, x2, weights)
    best = counts.argmax(-1)
    R_best = torch.gather(R, -3, best[..., None, None, None].expand(*best.shape, 1, 3, 3)).squeeze(-3)
    t_best = torch.gather(t, -2, best[..., None, None].expand(*best.shape, 1, 3)).squeeze(-2)
    total = weights.sum(-1) if weights is not None else torch.full_like(counts[..., 0], x1.shape[-2])
    return R_best, t_best, counts.amax(-1) / total.clamp_min(1)


def parallax_from_infinity(R: Tensor, t: Tensor, x1: Tensor, x2: Tensor) -> Tensor:
    """Signed parallax of x2 along its epipolar line, from where x1's point at infinity would be
    seen (the image of R x̃1) towards where a nearer point in front of both cameras would be.

    A point at inverse depth ρ ≥ 0 in camera 1 is seen in camera 2 at (R x̃1 + ρ t) / (R x̃1 + ρ t)_3,
    which leaves the image p∞ of R x̃1 at ρ = 0 in the direction u = sign((R x̃1)_3) (t_xy − p∞ t_3).
    The parallax is (x2 − p∞) · u / ‖u‖: positive for a point in front of both cameras, about
    zero for a distant one, negative for one "beyond infinity" — behind both cameras, which no
    static point can be (a body moving faster than the camera along its direction of travel).
    Unlike the Sampson distance it measures along the epipolar line, where F says nothing.

    Args:
        R, t: the relative pose (*, 3, 3), (*, 3) (``X2 = R X1 + t``).
        x1, x2: normalized correspondences (*, N, 2).

    Returns:
        (*, N) parallax in normalized units (0 where the direction is undefined: no translation).
    """
    ray = torch.cat([x1, torch.ones_like(x1[..., :1])], -1) @ R.transpose(-1, -2)  # (*, N, 3): R x̃1
    at_infinity = ray[..., :2] / ray[..., 2:]  # p∞ (*, N, 2)
    direction = (t[..., None, :2] - at_infinity * t[..., None, 2:]) * torch.sign(ray[..., 2:])
    direction = direction / floor_tiny(direction.norm(dim=-1, keepdim=True))
    return ((x2 - at_infinity) * direction).sum(-1)


def parallax_is_noise(R: Tensor, t: Tensor, x1: Tensor, x2: Tensor, K1: Tensor, K2: Tensor, inliers: Tensor,
                      threshold: float, significance: float) -> tuple[Tensor, Tensor]:
    """Whether a relative pose's translation is undetermined: its inliers' parallax along their
    epipolar lines (:func:`parallax_from_infinity`, in pixels of image 2) is what a rotation
    alone (the camera turned in place, or did not move) leaves, noise and mismatches.

    Noise model: the inlier ``threshold`` bounds the Sampson distance at 2σ, σ the noise of each
    image coordinate; a point at infinity's parallax is then N(0, 2σ²) (x2's noise, and x1's
    carried over by the rotation), beyond c = √2 σ z(1 − α/2) (α = ``significance``) on either
    side as often. A point in front of both cameras lies beyond c on the positive side (the
    cheirality test chose t's sign so), a mismatch that F let through along its epipolar line on
    either side. So the translation is undetermined where the median inlier lies within c and
    no more inliers lie beyond c on the positive side than a fair coin would put there among all
    those beyond c (a one-sided sign test at α, exact binomial tail). A pose with many inliers
    beyond c on both sides (a false pair, or a wrong pose) is not this function's to judge.

    Args:
        R, t: (B, 3, 3), (B, 3) poses (``X2 = R X1 + t``); x1, x2: (B, N, 2) pixels; K1, K2:
            (B, 3, 3); inliers: (B, N) bool.

    Returns:
        (B,) bool, undetermined; and (B,) the median absolute parallax of the inliers (px; 0
        without inliers).
    """
    at_infinity = K2 @ R @ torch.linalg.inv(K1)  # pixels of image 1 -> image 2's pixels of the same rays
    parallax = parallax_from_infinity(at_infinity, (K2 @ t[..., None])[..., 0], x1, x2)  # (B, N) px
    spread = math.sqrt(2) * threshold / 2  # √2 σ
    bound = spread * math.sqrt(2) * torch.erfinv(torch.tensor(1 - significance, dtype=torch.float64)).item()  # × z(1 − α/2)
    ahead = (inliers & (parallax > bound)).sum(-1)  # (B,)
    beyond = ahead + (inliers & (parallax < -bound)).sum(-1)
    count = torch.arange(x1.shape[-2] + 1, device=x1.device)  # (N + 1,) the binomial's outcomes
    k, j = beyond[:, None].double(), count[None].double()
    log_pmf = torch.lgamma(k + 1) - torch.lgamma(j + 1) - torch.lgamma((k - j).clamp_min(0) + 1) - k * math.log(2)
    tail = torch.where((count[None] >= ahead[:, None]) & (count[None] <= beyond[:, None]), log_pmf, -torch.inf).logsumexp(-1)
    median = torch.where(inliers, parallax.abs(), torch.nan).nanmedian(-1).values.nan_to_num(0.0)
    return (median <= bound) & (tail > math.log(significance)), median
