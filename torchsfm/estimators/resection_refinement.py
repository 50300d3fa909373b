"""LM refinement of a calibrated camera pose on the reprojection error (thesis §4.2.1.3,
Appendix E): R ← exp([ω]x) R and t, analytic Jacobian."""

from __future__ import annotations

import torch
from torch import Tensor

from torchsfm.camera import from_homogeneous
from torchsfm.config import LMConfig
from torchsfm.geometry.rotation import axis_angle_to_rotation, skew
from torchsfm.optim.lm import LMResult, levenberg_marquardt


def refine_pose(R: Tensor, t: Tensor, X: Tensor, x: Tensor, K: Tensor, weights: Tensor, config: LMConfig
                ) -> tuple[Tensor, Tensor, LMResult]:
    """LM on Σ wᵢ ‖π(K (R Xᵢ + t)) - xᵢ‖² over R ← exp([ω]x) R and t.

    R (B, 3, 3), t (B, 3), X (B, N, 3), x (B, N, 2), K (B, 3, 3), weights (B, N).
    """
    root = weights.sqrt()

    def unpack(state: Tensor) -> tuple[Tensor, Tensor]:
        return state[:, :9].reshape(-1, 3, 3), state[:, 9:]

    def residuals(state: Tensor) -> Tensor:
        R, t = unpack(state)
        camera = X @ R.transpose(-1, -2) + t[:, None]
        pixels = from_homogeneous(camera @ K.transpose(-1, -2))
        return ((pixels - x) * root[..., None]).flatten(1)

    def jacobian(state: Tensor) -> Tensor:
        R, t = unpack(state)
        rotated = X @ R.transpose(-1, -2)
        camera = rotated + t[:, None]
        cx, cy, z = camera.unbind(-1)
        d_normalized = torch.zeros(*camera.shape[:-1], 2, 3, dtype=X.dtype, device=X.device)
        d_normalized[..., 0, 0], d_normalized[..., 1, 1] = 1 / z, 1 / z
        d_normalized[..., 0, 2], d_normalized[..., 1, 2] = -cx / z**2, -cy / z**2
        d_camera = K[:, None, :2, :2] @ d_normalized  # (B, N, 2, 3)
        J = torch.cat([d_camera @ -skew(rotated), d_camera], dim=-1) * root[..., None, None]  # (B, N, 2, 6)
        return J.flatten(1, 2)

    def retract(state: Tensor, delta: Tensor) -> Tensor:
        R, t = unpack(state)
        return torch.cat([(axis_angle_to_rotation(delta[:, :3]) @ R).flatten(1), t + delta[:, 3:]], dim=-1)

    result = levenberg_marquardt(residuals, torch.cat([R.flatten(1), t], dim=-1), config, retract=retract,
                                 tangent_dim=6, jacobian=jacobian)
    R, t = unpack(result.params)
    return R, t, result
