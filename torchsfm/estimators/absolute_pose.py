"""Calibrated camera pose from 3-D↔2-D correspondences (thesis Alg. 4.2.1, Fig. 4.1)."""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor

from torchsfm.camera import intrinsics_per_view
from torchsfm.config import Config
from torchsfm.errors import DegenerateConfigurationError, NotEnoughDataError, ShapeError
from torchsfm.estimators.resection_refinement import refine_pose
from torchsfm.geometry.resection import reprojection_errors
from torchsfm.inference import without_autograd
from torchsfm.robust.models import ResectionModel
from torchsfm.robust.ragged import fill_padding
from torchsfm.robust.ransac import ransac
from torchsfm.validation import check_finite, check_floating, check_min_count, check_shapes, lie_on_one_line


@dataclass
class AbsolutePose:
    """Result of :func:`estimate_absolute_pose` (leading B only for batched input).

    Fields: ``R`` (B, 3, 3), ``t`` (B, 3) camera from world; ``inlier_mask`` (B, N) bool
    (reprojection error below the threshold); ``num_trials`` (B,) RANSAC samples drawn;
    ``success`` (B,) bool, a pose was found (always True without ``valid``: a failure raises).
    """

    R: Tensor
    t: Tensor
    inlier_mask: Tensor
    num_trials: Tensor
    success: Tensor


@without_autograd
def estimate_absolute_pose(X: Tensor, x: Tensor, K: Tensor, *, valid: Tensor | None = None, config: Config | None = None,
                           generator: torch.Generator | None = None) -> AbsolutePose:
    """Robust resection of a calibrated camera: RANSAC (P3P or DLT minimal samples, bucketed,
    adaptive) on the reprojection error, then LM on the pose over the inliers.

    Args:
        X: world points (N, 3) or (B, N, 3); x: their pixels (N, 2) or (B, N, 2), N >= 6.
        K: intrinsics (3, 3) or (B, 3, 3).
        valid: optional (B, N) bool: a ragged batch padded to one N (False rows are ignored,
            whatever they hold). With it, a problem without a pose (fewer than 6 valid rows, or
            no consensus) is reported in ``success`` (identity pose, no inliers) instead of
            raising, so one bad problem does not stop the others.
        config: uses ``config.resection`` and ``config.lm``.
        generator: RANSAC's random source.

    Raises:
        ShapeError, InputError: malformed input. NotEnoughDataError: fewer than 6 pairs, or (without
        ``valid``) no pose with 6 inliers. DegenerateConfigurationError: (without ``valid``) the
        3-D points lie on one line (the rotation about it is undetermined; with ``valid``, such a
        problem gets ``success`` False).
    """
    config = config or Config()
    settings = config.resection
    sizes = check_shapes(X=(X, "* N 3"), x=(x, "* N 2"))
    if X.dim() not in (2, 3) or X.shape[:-2] != x.shape[:-2]:
        raise ShapeError(f"X and x must be (N, 3) and (N, 2), or batched alike, got {tuple(X.shape)} and {tuple(x.shape)}")
    check_floating(X=X, x=x)
    unbatched = X.dim() == 2
    X64, x64 = (X.double(), x.double()) if X.dim() == 3 else (X.double()[None], x.double()[None])
    B = X64.shape[0]
    if valid is None:
        check_finite(X=X, x=x)
        check_min_count("X", sizes["N"], 6, "resection (3-D↔2-D pairs)")
    else:
        if not isinstance(valid, Tensor) or valid.dtype != torch.bool or unbatched or valid.shape != X64.shape[:2]:
            raise ShapeError(f"valid must be a bool tensor of shape (B, N) = {tuple(X.shape[:-1])} with batched X, got "
                             f"{f'{valid.dtype} {tuple(valid.shape)}' if isinstance(valid, Tensor) else type(valid).__name__}")
        check_finite(X=X64[valid], x=x64[valid])
        X64, x64 = fill_padding(X64, valid), fill_padding(x64, valid)
    collinear = lie_on_one_line(X64, 1e3 * torch.finfo(X.dtype).eps)  # (B,) across a line: within the input's rounding
    if valid is None and bool(collinear.any()):
        which = "" if unbatched else f" (problems {torch.nonzero(collinear).flatten().tolist()})"
        raise DegenerateConfigurationError(f"the {X64.shape[1]} 3-D points lie on one line{which}: the camera's rotation "
                                           "about it is undetermined")
    K64 = intrinsics_per_view(K, B)
    data = torch.cat([X64, x64], dim=-1)
    found = ransac(ResectionModel(K64, settings.solver), data, settings.ransac, valid=valid, generator=generator)
    success = found.success
    if valid is None and not bool(success.all()):
        raise NotEnoughDataError("RANSAC found no camera pose with at least 6 inliers")
    if valid is not None:
        success = success & (valid.sum(-1) >= 6) & ~collinear  # as many pairs as an unbatched call needs
    mask = success[:, None] if valid is None else valid & success[:, None]
    identity = torch.eye(3, 4, dtype=torch.float64, device=X64.device)
    pose = torch.where(success[:, None, None], torch.linalg.solve(K64, found.model), identity)  # [R | t]
    R, t = pose[..., :3], pose[..., 3]
    threshold_sq = settings.ransac.inlier_threshold**2
    if settings.refine:
        support = reprojection_errors(found.model, X64, x64) < threshold_sq * settings.refine_support_factor**2
        R, t, _ = refine_pose(R, t, X64, x64, K64, (support & mask).double(), config.lm)
    P = K64 @ torch.cat([R, t[..., None]], dim=-1)
    inliers = (reprojection_errors(P, X64, x64) < threshold_sq) & mask
    result = AbsolutePose(R=R.to(X.dtype), t=t.to(X.dtype), inlier_mask=inliers, num_trials=found.num_trials, success=success)
    if unbatched:
        result = AbsolutePose(R=result.R[0], t=result.t[0], inlier_mask=inliers[0], num_trials=found.num_trials[0],
                              success=success[0])
    return result
