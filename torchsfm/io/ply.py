"""Binary PLY point clouds with colours (MeshLab, Open3D, CloudCompare, plyfile read them)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
from torch import Tensor

from torchsfm.io.atomic import atomic_write_bytes


def ply_bytes(points: Tensor, colors: Tensor) -> bytes:
    """Binary little-endian PLY of (P, 3) points (written as float32) and (P, 3) uint8 colours."""
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
