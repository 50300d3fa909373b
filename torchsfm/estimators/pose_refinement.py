"""LM refinement of a calibrated relative pose on the Sampson error in pixels.

Once K1, K2 are known, F = K2⁻ᵀ [t]x R K1⁻¹ has only the 5 degrees of freedom of (R, t̂). We
refine them directly (3 for a rotation increment, 2 on the sphere of unit translations), which
enforces the essential-matrix constraints the thesis' 7-DOF F refinement leaves free.
"""

from __future__ import annotations

from collections.abc import Callable

import torch
from torch import Tensor

from torchsfm.config import LMConfig
from torchsfm.geometry.fundamental import sampson_jacobian, sampson_residual
from torchsfm.geometry.rotation import axis_angle_to_rotation, skew
from torchsfm.optim.lm import LMResult, levenberg_marquardt
from torchsfm.robust.ragged import weighted_rows_first


_ROTATION_GENERATORS = skew(torch.eye(3, dtype=torch.float64))  # [e_k]x, (3, 3, 3)


def sphere_tangent_basis(t: Tensor) -> Tensor:
    """Two unit vectors orthogonal to unit t and to each other: (*, 3) -> (*, 2, 3)."""
    axes = torch.eye(3, dtype=t.dtype, device=t.device)
    least_aligned = axes[t.abs().argmin(-1)]  # (*, 3)
    b1 = torch.linalg.cross(t, least_aligned)
    b1 = b1 / b1.norm(dim=-1, keepdim=True)
    return torch.stack([b1, torch.linalg.cross(t, b1)], dim=-2)


def retract_pose(state: Tensor, delta: Tensor) -> Tensor:
    """(R, t̂) ← (exp([ω]x) R, normalize(t̂ + b1 β1 + b2 β2)) for delta = (ω, β): (B, 12), (B, 5)."""
    R = axis_angle_to_rotation(delta[:, :3]) @ state[:, :9].reshape(-1, 3, 3)
    t = state[:, 9:]
    t = t + (delta[:, 3:, None] * sphere_tangent_basis(t)).sum(-2)
    return torch.cat([R.flatten(1), t / t.norm(dim=-1, keepdim=True)], dim=-1)


def relative_pose_problem(
    x1: Tensor, x2: Tensor, K1: Tensor, K2: Tensor, weights: Tensor
) -> tuple[Callable[[Tensor], Tensor], Callable[[Tensor], Tensor]]:
    """Residual and analytic Jacobian functions of the weighted Sampson error over (R, t̂).

    States are (B, 12) = [R (9, row-major), t (3)]; the Jacobian (B, N, 5) is taken along the
    tangent step of :func:`_retract` (rotation increment ω, two sphere coordinates of t).
    """
    K1_inv, K2_inv_t = torch.linalg.inv(K1), torch.linalg.inv(K2).transpose(-1, -2)
    root_weights = weights.sqrt()

    def fundamental(state: Tensor) -> Tensor:
        return K2_inv_t @ skew(state[:, 9:]) @ state[:, :9].reshape(-1, 3, 3) @ K1_inv

    def residuals(state: Tensor) -> Tensor:
        return sampson_residual(fundamental(state), x1, x2) * root_weights

    def jacobian(state: Tensor) -> Tensor:
        R, t = state[:, None, :9].reshape(-1, 1, 3, 3), state[:, None, 9:]
        d_rotation = skew(t) @ _ROTATION_GENERATORS.to(state) @ R  # R ← exp([ω]x) R: (B, 3, 3, 3)
        d_translation = skew(sphere_tangent_basis(state[:, 9:])) @ R  # (B, 2, 3, 3)
        d_F = K2_inv_t[:, None] @ torch.cat([d_rotation, d_translation], dim=1) @ K1_inv[:, None]
        return sampson_jacobian(fundamental(state), x1, x2, d_F) * root_weights[..., None]

    return residuals, jacobian


def refine_relative_pose(
    R: Tensor, t: Tensor, x1: Tensor, x2: Tensor, K1: Tensor, K2: Tensor, weights: Tensor, config: LMConfig
) -> tuple[Tensor, Tensor, LMResult]:
    """Minimize Σ wᵢ·Sampson(K2⁻ᵀ[t]xR K1⁻¹, x1ᵢ, x2ᵢ) over rotations R and unit t.

    Args:
        R, t: (B, 3, 3), (B, 3) initial pose of camera 2 relative to camera 1.
        x1, x2: (B, N, 2) pixels; K1, K2: (B, 3, 3); weights: (B, N) 0/1 inlier mask.

    Returns:
        Refined R (B, 3, 3), unit t (B, 3) and the LM report (costs in pixels²).
    """
    weights, x1, x2 = weighted_rows_first(weights, x1, x2)  # LM on the inliers only
    residuals, jacobian = relative_pose_problem(x1, x2, K1, K2, weights)
    state = torch.cat([R.flatten(1), t / t.norm(dim=-1, keepdim=True)], dim=-1)
    result = levenberg_marquardt(residuals, state, config, retract=retract_pose, tangent_dim=5, jacobian=jacobian)
    return result.params[:, :9].reshape(-1, 3, 3), result.params[:, 9:], result
