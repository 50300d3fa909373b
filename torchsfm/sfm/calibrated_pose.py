"""Calibrated relative pose from a candidate inlier set: multi-start local optimization.

A fundamental matrix has 7 degrees of freedom, an essential matrix 5. On short baselines seen
through a narrow field of view the two extra degrees let a robust F absorb a few wrong
matches, and E = K2ᵀ F K1 then starts the calibrated refinement in the wrong basin (the
rotation/translation ambiguity: a ~10° rotation error with a translation ~90° off explains half
the points). We therefore refine several starts at once, as one batched LM problem: the pose
decomposed from F plus ``num_starts`` essential matrices fitted (8-point algorithm, projected to
singular values 1, 1, 0) to random bucketed subsets of ``start_sample_size`` of F's inliers —
larger than minimal, since the candidates hold few outliers and larger samples start closer. Each start re-classifies its inliers under its own calibrated model with a shrinking
threshold (factor, factor/2, ..., 1) × threshold and is refined on them; the start with the
lowest truncated quadratic cost (MSAC) over all points wins (LO-RANSAC's idea applied to every
start rather than to the best one).
"""

from __future__ import annotations

import torch
from torch import Tensor

from torchsfm.camera import pixels_to_normalized
from torchsfm.config import Config
from torchsfm.geometry.essential import POSE_CANDIDATES, essential_from_pose, project_to_essential, select_pose
from torchsfm.geometry.fundamental import eight_point, fundamental_from_pose, sampson_error
from torchsfm.geometry.pose_refinement import refine_relative_pose
from torchsfm.robust.samplers import BucketedSampler


def threshold_schedule(threshold: float, start_factor: float) -> list[float]:
    """threshold × (start_factor, start_factor / 2, ..., 1)."""
    factors = [start_factor]
    while factors[-1] > 1:
        factors.append(max(1.0, factors[-1] / 2))
    return [threshold * factor for factor in factors]


def calibrated_pose(
    E: Tensor,
    x1: Tensor,
    x2: Tensor,
    K1: Tensor,
    K2: Tensor,
    candidates: Tensor,
    config: Config,
    generator: torch.Generator | None,
) -> tuple[Tensor, Tensor, Tensor]:
    """Best calibrated pose over a batch of starts.

    Args:
        E: (B, 3, 3) essential matrix of the robust F, E = K2ᵀ F K1.
        x1, x2: (B, N, 2) pixel correspondences; K1, K2: (B, 3, 3).
        candidates: (B, N) bool, F's inliers (starts are drawn from them).
        config: ``relative_pose``, ``fundamental.ransac`` (threshold, grid) and ``lm``.
        generator: random source of the extra starts.

    Returns:
        R (B, 3, 3), unit t (B, 3) and the inlier mask (B, N) under the calibrated model.
    """
    B, N, _ = x1.shape
    settings = config.relative_pose
    n1, n2 = pixels_to_normalized(x1, K1), pixels_to_normalized(x2, K2)
    starts = E[:, None]
    sample_size = min(settings.start_sample_size, int(candidates.sum(-1).min()))
    if settings.num_starts > 0 and sample_size >= 8:
        sampler = BucketedSampler(x1, candidates, config.fundamental.ransac.grid_size)
        index = sampler.sample(settings.num_starts, sample_size, generator)  # (B, S', size)
        subsets = torch.zeros(B, settings.num_starts, N, dtype=x1.dtype, device=x1.device).scatter_(2, index, 1.0)
        sampled = project_to_essential(eight_point(n1[:, None], n2[:, None], subsets))
        starts = torch.cat([starts, sampled], dim=1)
    S = starts.shape[1]

    def flat(x: Tensor) -> Tensor:  # (B, ...) -> (B * S, ...)
        return x[:, None].expand(B, S, *x.shape[1:]).reshape(B * S, *x.shape[1:])

    x1s, x2s, K1s, K2s, n1s, n2s, valid = (flat(x) for x in (x1, x2, K1, K2, n1, n2, candidates))
    R, t, _ = select_pose(*POSE_CANDIDATES[settings.method](starts.reshape(B * S, 3, 3)), n1s, n2s, valid.to(x1.dtype))
    threshold = config.fundamental.ransac.inlier_threshold
    inliers = valid
    for stage_threshold in threshold_schedule(threshold, settings.start_threshold_factor) if settings.refine else []:
        inliers = sampson_error(fundamental_from_pose(K1s, K2s, R, t), x1s, x2s) < stage_threshold**2
        R, t, _ = refine_relative_pose(R, t, x1s, x2s, K1s, K2s, inliers.to(x1.dtype), config.lm)
    errors = sampson_error(fundamental_from_pose(K1s, K2s, R, t), x1s, x2s)
    inliers = errors < threshold**2
    truncated_cost = errors.clamp_max(threshold**2).sum(-1)  # MSAC: inliers by residual, others by the threshold
    best = truncated_cost.reshape(B, S).argmin(-1) + torch.arange(B, device=x1.device) * S
    R, t, inliers = R[best], t[best], inliers[best]
    # Epipolar errors cannot tell (R, t) from (R, -t) or the twisted pair: settle it by cheirality.
    R, t, _ = select_pose(*POSE_CANDIDATES["svd"](essential_from_pose(R, t)), n1, n2, inliers.to(x1.dtype))
    return R, t, inliers
