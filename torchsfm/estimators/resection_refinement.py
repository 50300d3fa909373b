"""LM refinement of a calibrated camera pose on the reprojection error (thesis §4.2.1.3,
Appendix E): R ← exp([ω]x) R and t, analytic Jacobian."""

from __future__ import annotations

import torch
from torch import Tensor

from torchsfm.config import LMConfig
from torchsfm.geometry.rotation import axis_angle_to_rotation
from torchsfm.optim.lm import LMResult, levenberg_marquardt


def refine_pose(R: Tensor, t: Tensor, X: Tensor, x: Tensor, K: Tensor, weights: Tensor, config: LMConfig
                ) -> tuple[Tensor, Tensor, LMResult]:
    """LM on Σ wᵢ ‖π(K (R Xᵢ + t)) - xᵢ‖² over R ← exp([ω]x) R and t.

    R (B, 3, 3), t (B, 3), X (B, N, 3), x (B, N, 2), K (B, 3, 3) (last row 0 0 1), weights (B, N).
    Points are held coordinate-major, (B, 3, N): every step is a (3, 3) x (3, N) product or an
    operation on contiguous (B, N) rows; the residuals are ordered all x, then all y.
    """
    root = weights.sqrt()[:, None]  # (B, 1, N)
    points, pixels = X.transpose(-1, -2).contiguous(), x.transpose(-1, -2).contiguous()  # (B, 3, N), (B, 2, N)

    def unpack(state: Tensor) -> tuple[Tensor, Tensor]:
        return state[:, :9].reshape(-1, 3, 3), state[:, 9:]

    def residuals(state: Tensor) -> Tensor:
        R, t = unpack(state)
        projected = K @ (R @ points + t[..., None])  # (B, 3, N)
        return ((projected[:, :2] / projected[:, 2:] - pixels) * root).flatten(1)

    def jacobian(state: Tensor) -> Tensor:
        R, t = unpack(state)
        rotated = R @ points  # (B, 3, N)
        camera = rotated + t[..., None]
        inverse_depth = camera[:, 2].reciprocal()
        u, v = camera[:, 0] * inverse_depth, camera[:, 1] * inverse_depth  # normalized coordinates
        q0, q1, q2 = rotated.unbind(1)
        rows = []
        for pixel_row in K[:, :2, :2].unbind(1):  # d pixel / d camera point = K₂ₓ₂ [[1, 0, -u], [0, 1, -v]] / z
            k0, k1 = pixel_row[:, 0, None] * inverse_depth, pixel_row[:, 1, None] * inverse_depth
            d0, d1, d2 = k0, k1, -(k0 * u + k1 * v)
            # a rotation step ω moves the point by ω × rotated: the derivative along ω is rotated × d
            rows.append(torch.stack([q1 * d2 - q2 * d1, q2 * d0 - q0 * d2, q0 * d1 - q1 * d0, d0, d1, d2], dim=1))
        return (torch.stack(rows, dim=2) * root[:, None]).flatten(2).transpose(-1, -2)  # (B, 2N, 6)

    def retract(state: Tensor, delta: Tensor) -> Tensor:
        R, t = unpack(state)
        return torch.cat([(axis_angle_to_rotation(delta[:, :3]) @ R).flatten(1), t + delta[:, 3:]], dim=-1)

    result = levenberg_marquardt(residuals, torch.cat([R.flatten(1), t], dim=-1), config, retract=retract,
                                 tangent_dim=6, jacobian=jacobian)
    R, t = unpack(result.params)
    return R, t, result
