"""Binary PLY point clouds with colours (MeshLab, Open3D, CloudCompare, plyfile read them)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch
from torch import Tensor

from torchsfm.errors import InputError
from torchsfm.io.atomic import atomic_write_bytes
from torchsfm.validation import check_finite, check_shapes


def ply_bytes(points: Tensor, colors: Tensor) -> bytes:
    """Binary little-endian PLY of (P, 3) finite points (written as float32) and (P, 3) uint8
    colours; anything else is an error, not a file a viewer chokes on."""
    check_shapes(points=(points, "P 3"), colors=(colors, "P 3"))
    check_finite(points=points)
    if colors.dtype != torch.uint8:
        raise InputError(f"colors must be uint8 (0-255), got {colors.dtype}")
    vertices = np.empty(points.shape[0], dtype=[("x", "<f4"), ("y", "<f4"), ("z", "<f4"),
                                                 ("red", "u1"), ("green", "u1"), ("blue", "u1")])
    xyz = points.detach().cpu().numpy()
    rgb = colors.detach().cpu().numpy()
    for k, axis in enumerate("xyz"):
        vertices[axis] = xyz[:, k]
    for k, channel in enumerate(("red", "green", "blue")):
        vertices[channel] = rgb[:, k]
    header = (
        "ply\nformat binary_little_endian 1.0\ncomment written by torchsfm\n"
        f"element vertex {points.shape[0]}\n"
        "property float x\nproperty float y\nproperty float z\n"
        "property uchar red\nproperty uchar green\nproperty uchar blue\nend_header\n"
    )
    return header.encode("ascii") + vertices.tobytes()


def write_ply(path: str | Path, points: Tensor, colors: Tensor) -> None:
    """Write a coloured point cloud atomically."""
    atomic_write_bytes(path, ply_bytes(points, colors))
