"""Comparing a reconstruction with ground-truth cameras (similarity alignment, pose errors)."""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor

from torchsfm.geometry.rotation import nearest_rotation, rotation_angle


@dataclass
class CameraErrors:
    """Errors of estimated cameras against the ground truth after a similarity alignment.

    Fields: ``centre`` (V,) camera-centre errors in ground-truth units; ``extent`` the diagonal of
    the ground-truth centres' bounding box; ``rotation`` (V,) degrees; ``relative_rotation``
    (V (V-1) / 2,) degrees between every pair of views (independent of the alignment).
    """

    centre: Tensor
    extent: float
    rotation: Tensor
    relative_rotation: Tensor


def camera_errors(R: Tensor, t: Tensor, R_true: Tensor, t_true: Tensor) -> CameraErrors:
    """Align estimated cameras (V, 3, 3), (V, 3) (camera from world) to the ground truth.

    The similarity's rotation is the chordal mean of R_trueᵢᵀ Rᵢ (from the orientations, which
    pin it down even for cameras on a line or an arc), its scale and translation the least-squares
    fit of the rotated centres to the true centres.
    """
    centres = (-R.transpose(-1, -2) @ t[..., None])[..., 0]
    true_centres = (-R_true.transpose(-1, -2) @ t_true[..., None])[..., 0]
    A = nearest_rotation((R_true.transpose(-1, -2) @ R).sum(0))  # world_true ≈ s A world + b
    rotated = centres @ A.T
    mean, true_mean = rotated.mean(0), true_centres.mean(0)
    scale = ((rotated - mean) * (true_centres - true_mean)).sum() / (rotated - mean).square().sum().clamp_min(1e-300)
    centre = (scale * (rotated - mean) + true_mean - true_centres).norm(dim=-1)
    rotation = rotation_angle(R @ A.T, R_true)
    pairs = torch.triu_indices(R.shape[0], R.shape[0], 1)
    relative = rotation_angle(R[pairs[0]] @ R[pairs[1]].transpose(-1, -2), R_true[pairs[0]] @ R_true[pairs[1]].transpose(-1, -2))
    extent = float((true_centres.amax(0) - true_centres.amin(0)).norm())
    return CameraErrors(centre=centre, extent=extent, rotation=rotation, relative_rotation=relative)
