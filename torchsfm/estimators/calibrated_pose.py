"""Calibrated relative pose from a candidate inlier set: multi-start local optimization.

A fundamental matrix has 7 degrees of freedom, an essential matrix 5. On short baselines seen
through a narrow field of view the two extra degrees let a robust F absorb a few wrong
matches, and E = K2ᵀ F K1 then starts the calibrated refinement in the wrong basin (the
rotation/translation ambiguity: a ~10° rotation error with a translation ~90° off explains half
the points). We therefore refine several starts at once, as one batched LM problem: the pose
decomposed from F plus ``num_starts`` essential matrices fitted (8-point algorithm, projected to
singular values 1, 1, 0) to random bucketed subsets of ``start_sample_size`` of F's inliers —
larger than minimal, since the candidates hold few outliers and larger samples start closer. After the first stage only the ``kept_starts`` starts of lowest truncated cost go on. Each
start re-classifies its support under its own calibrated model with a shrinking
threshold (start factor, start factor / 2, ..., support factor) × threshold and is refined on it
(the last support is wider than the inlier threshold, so that the refinement does not see a noise
distribution truncated at the threshold); the start with the
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
from torchsfm.estimators.pose_refinement import refine_relative_pose
from torchsfm.robust.samplers import BucketedSampler, resolve_generator


def threshold_schedule(threshold: float, start_factor: float, end_factor: float) -> list[float]:
    """threshold × (start_factor, start_factor / 2, ..., end_factor)."""
    factors = [start_factor]
    while factors[-1] > end_factor:
        factors.append(max(end_factor, factors[-1] / 2))
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
    valid: Tensor | None = None,
) -> tuple[Tensor, Tensor, Tensor]:
    """Best calibrated pose over a batch of starts.

    Args:
        E: (B, 3, 3) essential matrix of the robust F, E = K2ᵀ F K1.
        x1, x2: (B, N, 2) pixel correspondences; K1, K2: (B, 3, 3).
        candidates: (B, N) bool, F's inliers (starts are drawn from them).
        config: ``relative_pose``, ``fundamental.ransac`` (threshold, grid) and ``lm``.
        generator: random source of the extra starts.
        valid: optional (B, N) bool, the real rows of a padded batch (default: all).

    Returns:
        R (B, 3, 3), unit t (B, 3) and the inlier mask (B, N) under the calibrated model.
    """
    B, N, _ = x1.shape
    settings = config.relative_pose
    valid = torch.ones(B, N, dtype=torch.bool, device=x1.device) if valid is None else valid
    n1, n2 = pixels_to_normalized(x1, K1), pixels_to_normalized(x2, K2)
    starts = E[:, None]
    sample_size = min(settings.start_sample_size, int(candidates.sum(-1).min()))
    if settings.num_starts > 0 and sample_size >= 8:
        sampler = BucketedSampler(x1, candidates, config.fundamental.ransac.grid_size)
        index = sampler.sample(settings.num_starts, sample_size, resolve_generator(generator, x1.device))  # (B, S', size)
        subsets = torch.zeros(B, settings.num_starts, N, dtype=x1.dtype, device=x1.device).scatter_(2, index, 1.0)
        sampled = project_to_essential(eight_point(n1[:, None], n2[:, None], subsets))
        starts = torch.cat([starts, sampled], dim=1)
    threshold = config.fundamental.ransac.inlier_threshold
    schedule = threshold_schedule(threshold, settings.start_threshold_factor, settings.refine_support_factor)
    R, t = _decompose_starts(starts, n1, n2, candidates, settings.method)  # (B, S, 3, 3), (B, S, 3)
    for stage, stage_threshold in enumerate(schedule if settings.refine else []):
        R, t = _refine_starts(R, t, x1, x2, K1, K2, valid, stage_threshold, config)
        if stage == 0 and R.shape[1] > settings.kept_starts:  # prune to the most promising starts
            keep = _truncated_cost(R, t, x1, x2, K1, K2, valid, threshold).topk(settings.kept_starts, dim=1, largest=False).indices
            R = torch.gather(R, 1, keep[..., None, None].expand(B, -1, 3, 3))
            t = torch.gather(t, 1, keep[..., None].expand(B, -1, 3))
    best = _truncated_cost(R, t, x1, x2, K1, K2, valid, threshold).argmin(dim=1)
    batch = torch.arange(B, device=best.device)
    R, t = R[batch, best], t[batch, best]
    inliers = (sampson_error(fundamental_from_pose(K1, K2, R, t), x1, x2) < threshold**2) & valid
    # Epipolar errors cannot tell (R, t) from (R, -t) or the twisted pair: settle it by cheirality.
    R, t, _ = select_pose(*POSE_CANDIDATES["svd"](essential_from_pose(R, t)), n1, n2, inliers.to(x1.dtype))
    return R, t, inliers


def _expand(x: Tensor, S: int) -> Tensor:
    """(B, ...) -> (B * S, ...): one copy of a problem's data per start."""
    return x[:, None].expand(x.shape[0], S, *x.shape[1:]).reshape(x.shape[0] * S, *x.shape[1:])


def _decompose_starts(E: Tensor, n1: Tensor, n2: Tensor, candidates: Tensor, method: str) -> tuple[Tensor, Tensor]:
    """(B, S, 3, 3) essential starts -> cheirality-selected R (B, S, 3, 3), t (B, S, 3)."""
    B, S = E.shape[:2]
    R, t, _ = select_pose(*POSE_CANDIDATES[method](E.reshape(B * S, 3, 3)), _expand(n1, S), _expand(n2, S),
                          _expand(candidates, S).to(n1.dtype))
    return R.reshape(B, S, 3, 3), t.reshape(B, S, 3)


def _refine_starts(R: Tensor, t: Tensor, x1: Tensor, x2: Tensor, K1: Tensor, K2: Tensor, valid: Tensor, threshold: float,
                   config: Config) -> tuple[Tensor, Tensor]:
    """One stage: each start's support (valid rows with Sampson < threshold under its own
    pose), then LM on it."""
    B, S = R.shape[:2]
    x1s, x2s, K1s, K2s, valid_s = (_expand(x, S) for x in (x1, x2, K1, K2, valid))
    R, t = R.reshape(B * S, 3, 3), t.reshape(B * S, 3)
    support = (sampson_error(fundamental_from_pose(K1s, K2s, R, t), x1s, x2s) < threshold**2) & valid_s
    R, t, _ = refine_relative_pose(R, t, x1s, x2s, K1s, K2s, support.to(x1.dtype), config.lm)
    return R.reshape(B, S, 3, 3), t.reshape(B, S, 3)


def _truncated_cost(R: Tensor, t: Tensor, x1: Tensor, x2: Tensor, K1: Tensor, K2: Tensor, valid: Tensor, threshold: float) -> Tensor:
    """MSAC cost Σ min(Sampson, threshold²) of every start over the valid points: (B, S)."""
    F = fundamental_from_pose(K1[:, None], K2[:, None], R, t)  # (B, S, 3, 3)
    return (sampson_error(F, x1[:, None], x2[:, None]).clamp_max(threshold**2) * valid[:, None]).sum(-1)
