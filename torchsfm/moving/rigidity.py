"""The parallax-based rigidity constraint over three frames (thesis §5.3, eq. 5.3.1–5.3.2).

For a support point s and a point i, with Δ = p_w,i − p_w,s and Δ⊥ = (−Δy, Δx), a static pair
has a_j = μ_iᵀΔ⊥ ∝ γ_i and b_j = μ_sᵀΔ⊥ ∝ γ_s with the same factor in frame j (the thesis' eq.
5.3.1 has the ratio upside down: γ_i/γ_s = a/b; the constraint is unaffected). Eq. 5.3.2 as a
ratio difference is unstable where b → 0; we use its cross-multiplied form

    c = a_0 b_1 − b_0 a_1 = 0

divided by its first-order standard deviation under isotropic unit noise on the four parallax
vectors, sqrt(|Δ_0|² (a_1² + b_1²) + |Δ_1|² (a_0² + b_0²)). The residual is then in pixels of
parallax noise: one threshold serves every support, scene and image size (the thesis' t1 = 1e-5
was tied to its image size and coordinates, ERRATA).
"""

from __future__ import annotations

import torch
from torch import Tensor

from torchsfm.numerics import floor_tiny


def rigidity_residuals(support: Tensor, warped: Tensor, parallax: Tensor) -> tuple[Tensor, Tensor]:
    """Normalized rigidity residuals of every point against each support.

    Args:
        support: (S,) indices of the support points.
        warped: (2, N, 2) p_w of the two non-reference frames.
        parallax: (2, N, 2) their residual parallax μ.

    Returns:
        (S, N) residuals in pixels, 0 where both points lie on the plane (the constraint holds
        trivially there) and for the support itself; and (S, N) the strength of each test,
        sqrt(b_0² + b_1²) / |Δ|: the support's parallax across the line joining the two points
        (pixels). A test weaker than the noise passes every point.
    """
    dx = warped[:, None, :, 0] - warped[:, support, None, 0]  # (2, S, N): Δ = p_w,i − p_w,s
    dy = warped[:, None, :, 1] - warped[:, support, None, 1]
    a = parallax[:, None, :, 1] * dx - parallax[:, None, :, 0] * dy  # μ_i · Δ⊥ with Δ⊥ = (−Δy, Δx)
    b = parallax[:, support, None, 1] * dx - parallax[:, support, None, 0] * dy  # μ_s · Δ⊥
    cross = a[0] * b[1] - b[0] * a[1]
    length_sq = dx.square_() + dy.square_()  # in place from here on: (2, S, N) tables are the cost
    a.square_()
    b.square_()
    variance = length_sq[0] * (a[1] + b[1]) + length_sq[1] * (a[0] + b[0])
    residual = torch.where(variance > 0, cross / floor_tiny(variance).sqrt_(), torch.zeros_like(cross))
    strength = (b[0] + b[1]).div_(floor_tiny(length_sq[0].add_(length_sq[1]).mul_(0.5))).sqrt_()
    return residual, strength
