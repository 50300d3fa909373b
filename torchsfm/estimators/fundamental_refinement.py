"""LM refinement of F on the total Sampson error of its inliers (thesis §3.3.4, eq. 3.3.8).

F is parametrized by its orthonormal representation (Bartoli & Sturm 2004),
``F = U diag(1, sigma, 0) Vᵀ`` with U, V rotations, so every iterate has rank exactly 2 and the
step has the 7 degrees of freedom of a fundamental matrix: 3 + 3 rotation increments and one for
sigma. The parametrization is applied to F in Hartley-normalized coordinates (well scaled),
while the residuals are Sampson distances in pixels.
"""

from __future__ import annotations

import torch
from torch import Tensor

from torchsfm.config import LMConfig
from torchsfm.geometry.fundamental import normalize_scale, sampson_jacobian, sampson_residual
from torchsfm.geometry.normalization import hartley_normalize
from torchsfm.geometry.rotation import axis_angle_to_rotation, skew
from torchsfm.optim.lm import LMResult, levenberg_marquardt
from torchsfm.robust.ragged import weighted_rows_first
from torchsfm.numerics import floor_tiny


def _to_orthonormal(F: Tensor) -> Tensor:
    """(B, 3, 3) rank-2 F -> (B, 19) state [U (9), V (9), sigma] with det U = det V = +1."""
    U, S, Vh = torch.linalg.svd(F)
    V = Vh.transpose(-1, -2)
    U = U * torch.sign(torch.linalg.det(U))[:, None, None]
    V = V * torch.sign(torch.linalg.det(V))[:, None, None]
    sigma = S[:, 1:2] / floor_tiny(S[:, 0:1])
    return torch.cat([U.flatten(1), V.flatten(1), sigma], dim=-1)


def _from_orthonormal(state: Tensor) -> Tensor:
    """(B, 19) -> F (B, 3, 3) = U diag(1, sigma, 0) Vᵀ."""
    U = state[:, :9].reshape(-1, 3, 3)
    V = state[:, 9:18].reshape(-1, 3, 3)
    diag = torch.stack([torch.ones_like(state[:, 18]), state[:, 18], torch.zeros_like(state[:, 18])], dim=-1)
    return (U * diag[:, None, :]) @ V.transpose(-1, -2)


def _retract(state: Tensor, delta: Tensor) -> Tensor:
    U = state[:, :9].reshape(-1, 3, 3) @ axis_angle_to_rotation(delta[:, 0:3])
    V = state[:, 9:18].reshape(-1, 3, 3) @ axis_angle_to_rotation(delta[:, 3:6])
    return torch.cat([U.flatten(1), V.flatten(1), state[:, 18:] + delta[:, 6:7]], dim=-1)


_ROTATION_GENERATORS = skew(torch.eye(3, dtype=torch.float64))  # [e_k]x, (3, 3, 3)
_SIGMA_DIRECTION = torch.diag(torch.tensor([0.0, 1.0, 0.0], dtype=torch.float64))[None]  # d diag(1, σ, 0) / dσ


def _tangent_derivatives(state: Tensor) -> Tensor:
    """dF/d delta at delta = 0 for the 7 tangent directions: (B, 19) -> (B, 7, 3, 3).

    U ← U exp([ω]x) gives U [e_k]x S Vᵀ; V ← V exp([ω]x) gives -U S [e_k]x Vᵀ; sigma gives
    U diag(0, 1, 0) Vᵀ.
    """
    U = state[:, :9].reshape(-1, 1, 3, 3)
    Vt = state[:, 9:18].reshape(-1, 1, 3, 3).transpose(-1, -2)
    S = torch.diag_embed(torch.stack([torch.ones_like(state[:, 18]), state[:, 18], torch.zeros_like(state[:, 18])], dim=-1))[:, None]
    generators = torch.cat([_ROTATION_GENERATORS.to(state), _SIGMA_DIRECTION.to(state)])  # (4, 3, 3)
    return torch.cat([U @ generators[:3] @ S @ Vt, -(U @ S @ generators[:3] @ Vt), U @ generators[3:] @ Vt], dim=1)


def refine_fundamental(
    F: Tensor, x1: Tensor, x2: Tensor, weights: Tensor, config: LMConfig
) -> tuple[Tensor, LMResult]:
    """Minimize Σ wᵢ·Sampson(F, x1ᵢ, x2ᵢ) over rank-2 F.

    Args:
        F: (B, 3, 3) initial fundamental matrices (pixels).
        x1, x2: (B, N, 2) pixel correspondences.
        weights: (B, N) 0/1 inlier mask as floats (0 drops a point).
        config: LM settings.

    Returns:
        The refined F (B, 3, 3), unit Frobenius norm and the sign of the input, and the
        :class:`~torchsfm.optim.lm.LMResult` (its costs are ½ Σ w·Sampson, in pixels²).
    """
    weights, x1, x2 = weighted_rows_first(weights, x1, x2)  # LM on the supported rows only
    _, T1 = hartley_normalize(x1, weights)
    _, T2 = hartley_normalize(x2, weights)
    F_normalized = torch.linalg.inv(T2).transpose(-1, -2) @ F @ torch.linalg.inv(T1)
    root_weights = weights.sqrt()

    def residuals(state: Tensor) -> Tensor:
        F_pixels = T2.transpose(-1, -2) @ _from_orthonormal(state) @ T1
        return sampson_residual(F_pixels, x1, x2) * root_weights

    def jacobian(state: Tensor) -> Tensor:
        F_pixels = T2.transpose(-1, -2) @ _from_orthonormal(state) @ T1
        d_pixels = T2.transpose(-1, -2)[:, None] @ _tangent_derivatives(state) @ T1[:, None]  # (B, 7, 3, 3)
        return sampson_jacobian(F_pixels, x1, x2, d_pixels) * root_weights[..., None]

    result = levenberg_marquardt(residuals, _to_orthonormal(F_normalized), config, retract=_retract, tangent_dim=7,
                                 jacobian=jacobian)
    refined = normalize_scale(T2.transpose(-1, -2) @ _from_orthonormal(result.params) @ T1)
    sign = torch.sign((refined * F).sum(dim=(-2, -1)))
    return refined * torch.where(sign == 0, 1.0, sign).to(F.dtype)[:, None, None], result
