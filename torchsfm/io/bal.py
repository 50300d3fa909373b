"""Bundle Adjustment in the Large (BAL) problem files (Agarwal, Snavely, Seitz & Szeliski 2010)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch

from torchsfm.errors import InputError
from torchsfm.geometry.rotation import axis_angle_to_rotation, rotation_to_axis_angle
from torchsfm.io.atomic import atomic_write_text
from torchsfm.optim.bundle import BundleProblem


def read_bal(path: str | Path) -> BundleProblem:
    """Read a BAL text file: header, observations (camera, point, x, y), 9 parameters per camera
    (Rodrigues ω, t, f, k1, k2) and 3 per point. Returns a ``bal`` :class:`BundleProblem`."""
    path = Path(path)
    try:
        values = np.loadtxt(path, dtype=np.float64, max_rows=1)
        num_cameras, num_points, num_observations = (int(v) for v in values)
        observations = np.loadtxt(path, dtype=np.float64, skiprows=1, max_rows=num_observations)
        parameters = np.loadtxt(path, dtype=np.float64, skiprows=1 + num_observations).reshape(-1)
    except (OSError, ValueError) as error:
        raise InputError(f"cannot read BAL file {path}: {error}") from None
    expected = 9 * num_cameras + 3 * num_points
    if observations.shape != (num_observations, 4) or parameters.size != expected:
        raise InputError(f"BAL file {path} is inconsistent: header says {num_cameras} cameras, {num_points} points, "
                         f"{num_observations} observations")
    cameras = torch.from_numpy(parameters[: 9 * num_cameras].reshape(num_cameras, 9).copy())
    observations = torch.from_numpy(observations)
    return BundleProblem(
        camera_model="bal",
        rotations=axis_angle_to_rotation(cameras[:, :3]),
        translations=cameras[:, 3:6].clone(),
        intrinsics=cameras[:, 6:9].clone(),
        points=torch.from_numpy(parameters[9 * num_cameras:].reshape(num_points, 3).copy()),
        camera_index=observations[:, 0].long(),
        point_index=observations[:, 1].long(),
        observations=observations[:, 2:].clone(),
    )


def write_bal(path: str | Path, problem: BundleProblem) -> None:
    """Write a ``bal`` problem in the BAL text format (atomically)."""
    if problem.camera_model != "bal":
        raise InputError("write_bal needs a problem with the bal camera model")
    lines = [f"{problem.num_cameras} {problem.num_points} {problem.observations.shape[0]}"]
    for c, p, (x, y) in zip(problem.camera_index.tolist(), problem.point_index.tolist(), problem.observations.tolist()):
        lines.append(f"{c} {p} {x:.17g} {y:.17g}")
    cameras = torch.cat([rotation_to_axis_angle(problem.rotations), problem.translations, problem.intrinsics], dim=1)
    lines += [f"{v:.17g}" for v in cameras.flatten().tolist()]
    lines += [f"{v:.17g}" for v in problem.points.flatten().tolist()]
    atomic_write_text(path, "\n".join(lines) + "\n")
