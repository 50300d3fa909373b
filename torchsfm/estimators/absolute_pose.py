"""Calibrated camera pose from 3-D↔2-D correspondences (thesis Alg. 4.2.1, Fig. 4.1)."""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor

from torchsfm.camera import check_intrinsics
from torchsfm.config import Config
from torchsfm.errors import NotEnoughDataError, ShapeError
from torchsfm.estimators.resection_refinement import refine_pose
from torchsfm.geometry.resection import reprojection_errors
from torchsfm.robust.models import ResectionModel
from torchsfm.robust.ransac import ransac
from torchsfm.validation import check_finite, check_floating, check_min_count, check_shapes


@dataclass
class AbsolutePose:
    """Result of :func:`estimate_absolute_pose` (leading B only for batched input).

    Fields: ``R`` (B, 3, 3), ``t`` (B, 3) camera from world; ``inlier_mask`` (B, N) bool
    (reprojection error below the threshold); ``num_trials`` (B,) RANSAC samples drawn.
    """

    R: Tensor
    t: Tensor
    inlier_mask: Tensor
    num_trials: Tensor


def estimate_absolute_pose(X: Tensor, x: Tensor, K: Tensor, *, config: Config | None = None,
                           generator: torch.Generator | None = None) -> AbsolutePose:
    """Robust resection of a calibrated camera: RANSAC (P3P or DLT minimal samples, bucketed,
    adaptive) on the reprojection error, then LM on the pose over the inliers.

    Args:
        X: world points (N, 3) or (B, N, 3); x: their pixels (N, 2) or (B, N, 2), N >= 6.
        K: intrinsics (3, 3) or (B, 3, 3).
        config: uses ``config.resection`` and ``config.lm``.
        generator: RANSAC's random source.
    """
    config = config or Config()
    settings = config.resection
    sizes = check_shapes(X=(X, "* N 3"), x=(x, "* N 2"), K=(K, "* 3 3"))
    if X.dim() not in (2, 3) or X.shape[:-2] != x.shape[:-2]:
        raise ShapeError(f"X and x must be (N, 3) and (N, 2), or batched alike, got {tuple(X.shape)} and {tuple(x.shape)}")
    check_floating(X=X, x=x, K=K)
    check_finite(X=X, x=x)
    check_intrinsics(K=K)
    check_min_count("X", sizes["N"], 6, "resection (3-D↔2-D pairs)")
    unbatched = X.dim() == 2
    X64, x64 = X.double().reshape(-1, sizes["N"], 3), x.double().reshape(-1, sizes["N"], 2)
    B = X64.shape[0]
    K64 = K.double().expand(B, 3, 3) if K.dim() == 2 else K.double()
    data = torch.cat([X64, x64], dim=-1)
    found = ransac(ResectionModel(K64, settings.solver), data, settings.ransac, generator=generator)
    if not bool(found.success.all()):
        raise NotEnoughDataError("RANSAC found no camera pose with at least 6 inliers")
    pose = torch.linalg.solve(K64, found.model)  # [R | t]
    R, t = pose[..., :3], pose[..., 3]
    threshold_sq = settings.ransac.inlier_threshold**2
    if settings.refine:
        support = reprojection_errors(found.model[:, None], X64[:, None], x64[:, None])[:, 0] < threshold_sq * settings.refine_support_factor**2
        R, t, _ = refine_pose(R, t, X64, x64, K64, support.double(), config.lm)
    P = K64 @ torch.cat([R, t[..., None]], dim=-1)
    inliers = reprojection_errors(P, X64, x64) < threshold_sq
    result = AbsolutePose(R=R.to(X.dtype), t=t.to(X.dtype), inlier_mask=inliers, num_trials=found.num_trials)
    if unbatched:
        result = AbsolutePose(R=result.R[0], t=result.t[0], inlier_mask=inliers[0], num_trials=found.num_trials[0])
    return result
