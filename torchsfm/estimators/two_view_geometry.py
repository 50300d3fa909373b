"""Two-view geometry from putative correspondences: robust F, then the calibrated relative pose.

The public entry points :func:`estimate_fundamental` and :func:`estimate_relative_pose` accept
one problem (N, 2) or a batch (B, N, 2), check their input, work in float64 and return results in
the input's dtype. :class:`RobustFundamental` and :class:`RelativePoseEstimator` are the same
operations as pipeline stages.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor, nn

from torchsfm.camera import intrinsics_per_view, projection_matrix
from torchsfm.config import Config
from torchsfm.errors import DegenerateConfigurationError, NotEnoughDataError, ShapeError
from torchsfm.geometry.essential import essential_from_fundamental, parallax_is_noise
from torchsfm.geometry.fundamental import fundamental_from_pose, sampson_error
from torchsfm.estimators.fundamental_refinement import refine_fundamental
from torchsfm.geometry.triangulation import triangulate_points
from torchsfm.inference import without_autograd
from torchsfm.robust.models import EssentialModel, FundamentalModel
from torchsfm.estimators.calibrated_pose import calibrated_pose
from torchsfm.robust.ransac import ransac
from torchsfm.validation import check_finite, check_floating, check_min_count, check_shapes, count_distinct_rows, has_distinct_rows


@dataclass
class FundamentalEstimate:
    """Result of :func:`estimate_fundamental` (leading B only for batched input).

    Fields:
        F: (B, 3, 3), unit Frobenius norm, ``x2ᵀ F x1 ≈ 0`` in pixels.
        inlier_mask: (B, N) bool, Sampson distance below the threshold under the final F.
        num_trials: (B,) int64, RANSAC minimal samples drawn.
        sampson_rms: (B,) root mean Sampson error of the inliers, pixels.
        success: (B,) bool, a model with at least 8 inliers was found (always True unless
            ``valid`` was given: a ragged batch reports failures per problem instead of raising).
    """

    F: Tensor
    inlier_mask: Tensor
    num_trials: Tensor
    sampson_rms: Tensor
    success: Tensor


@dataclass
class RelativePose:
    """Result of :func:`estimate_relative_pose` (leading B only for batched input).

    Fields:
        R: (B, 3, 3) rotation of camera 2 relative to camera 1 (X2 = R X1 + t).
        t: (B, 3) unit translation.
        inlier_mask: (B, N) bool, epipolar inliers that triangulate in front of both cameras.
        points3d: inlier points in the camera-1 frame (scale: ‖t‖ = 1), (M, 3) for one problem
            and a tuple of B such tensors for a batch.
        F: (B, 3, 3) the fundamental matrix of the final pose, K2⁻ᵀ [t]x R K1⁻¹ (unit norm).
        num_trials: (B,) RANSAC minimal samples drawn.
        success: (B,) bool, a pose was found (always True without ``valid``: a failure raises);
            a problem without one has R = I, t = 0, F = 0 and no inliers.
    """

    R: Tensor
    t: Tensor
    inlier_mask: Tensor
    points3d: Tensor | tuple[Tensor, ...]
    F: Tensor
    num_trials: Tensor
    success: Tensor


def _check_correspondences(x1: Tensor, x2: Tensor, valid: Tensor | None = None) -> tuple[Tensor, Tensor, bool, Tensor]:
    """Validate (N, 2) / (B, N, 2) pairs and an optional (B, N) validity mask; return float64
    (B, N, 2) copies (zeros where not valid), 'was unbatched' and the (B, N) mask."""
    sizes = check_shapes(x1=(x1, "* N 2"), x2=(x2, "* N 2"))
    if x1.dim() not in (2, 3) or x1.shape[:-2] != x2.shape[:-2]:
        raise ShapeError(f"x1 and x2 must both be (N, 2) or (B, N, 2), got {tuple(x1.shape)} and {tuple(x2.shape)}")
    check_floating(x1=x1, x2=x2)
    unbatched = x1.dim() == 2
    x1, x2 = (x.double() if not unbatched else x.double()[None] for x in (x1, x2))
    if valid is None:
        check_finite(x1=x1, x2=x2)
        check_min_count("x1", sizes["N"], 8, "the 8-point algorithm (correspondences)")
        mask = torch.ones(x1.shape[:2], dtype=torch.bool, device=x1.device)
    else:
        if not isinstance(valid, Tensor) or valid.dtype != torch.bool or valid.shape != x1.shape[:2]:
            raise ShapeError(f"valid must be a bool tensor of shape {tuple(x1.shape[:2])}, got "
                             f"{f'{valid.dtype} {tuple(valid.shape)}' if isinstance(valid, Tensor) else type(valid).__name__}")
        mask = valid
        check_finite(x1=x1[mask], x2=x2[mask])
        x1, x2 = (torch.where(mask[..., None], x, 0.0) for x in (x1, x2))
    if valid is None:
        for name, x in (("x1", x1), ("x2", x2)):
            enough = has_distinct_rows(x, 8)  # (B,)
            if not bool(enough.all()):
                b = int(torch.nonzero(~enough)[0, 0])
                raise DegenerateConfigurationError(
                    f"{name}{'' if unbatched else f'[{b}]'} has only {int(count_distinct_rows(x[b]))} distinct point(s); "
                    "a fundamental matrix needs at least 8 distinct correspondences"
                )
    return x1, x2, unbatched, mask


def _raise_on_failure(success: Tensor, unbatched: bool) -> None:
    if not bool(success.all()):
        failed = torch.nonzero(~success).flatten().tolist()
        where = "" if unbatched else f" for problem(s) {failed}"
        raise NotEnoughDataError(f"RANSAC found no fundamental matrix with at least 8 inliers{where}")


def _robust_fundamental(x1: Tensor, x2: Tensor, config: Config, generator: torch.Generator | None, valid: Tensor):
    """RANSAC + optional LM on float64 (B, N, 2) inputs with a (B, N) validity mask
    -> (F, inlier mask, trials, success)."""
    data = torch.cat([x1, x2], dim=-1)
    model = FundamentalModel(data, valid, config.fundamental.minimal_solver)
    found = ransac(model, data, config.fundamental.ransac, valid=valid, generator=generator)
    found_one = found.success & torch.isfinite(found.model).flatten(1).all(-1)
    stand_in = torch.tensor([[0.0, 0.0, 0.0], [0.0, 0.0, -1.0], [0.0, 1.0, 0.0]], dtype=x1.dtype, device=x1.device)  # [e1]x
    F = torch.where(found_one[:, None, None], found.model, stand_in / stand_in.norm())  # failed problems: finite, unused
    threshold_sq = config.fundamental.ransac.inlier_threshold**2
    for _ in range(config.fundamental.refine_rounds if config.fundamental.refine else 0):
        support = valid & found_one[:, None] & (sampson_error(F, x1, x2) < threshold_sq * config.fundamental.refine_support_factor**2)
        F, _ = refine_fundamental(F, x1, x2, support.double(), config.lm)
    inliers = valid & (sampson_error(F, x1, x2) < threshold_sq)
    success = found_one & (inliers.sum(-1) >= 8) & torch.isfinite(F).flatten(1).all(-1)
    return F, inliers & success[:, None], found.num_trials, success


def _robust_essential(x1: Tensor, x2: Tensor, K1: Tensor, K2: Tensor, config: Config, generator: torch.Generator | None,
                      valid: Tensor):
    """RANSAC on the five-point E (``config.fundamental.ransac``) on float64 (B, N, 2) inputs,
    (B, 3, 3) intrinsics and a (B, N) validity mask -> (F = K2⁻ᵀ E K1⁻¹, inlier mask, trials,
    success); no LM here (the pose's LM refines E's five degrees of freedom)."""
    data = torch.cat([x1, x2], dim=-1)
    found = ransac(EssentialModel(K1, K2), data, config.fundamental.ransac, valid=valid, generator=generator)
    success = found.success & torch.isfinite(found.model).flatten(1).all(-1) & (found.inlier_mask.sum(-1) >= 8)
    F = torch.where(success[:, None, None], found.model, 0.0)
    return F, found.inlier_mask & success[:, None], found.num_trials, success


@without_autograd
def estimate_fundamental(
    x1: Tensor, x2: Tensor, *, valid: Tensor | None = None, config: Config | None = None,
    generator: torch.Generator | None = None
) -> FundamentalEstimate:
    """Robust fundamental matrix: bucketed RANSAC on the normalized 8-point algorithm, then LM.

    Args:
        x1, x2: pixel correspondences (N, 2) or (B, N, 2), N >= 8.
        valid: optional (B, N) bool: a ragged batch padded to one N (False rows are ignored,
            whatever they hold). With it, a problem without a model is reported in ``success``
            instead of raising, so one bad problem does not stop the others.
        config: a :class:`~torchsfm.config.Config`; ``config.fundamental`` and ``config.lm``
            are used. Defaults to the thesis' settings.
        generator: source of RANSAC's random draws (seed it for reproducible results).

    Returns:
        A :class:`FundamentalEstimate` without the batch dimension for (N, 2) input.

    Raises:
        ShapeError, InputError: malformed input. NotEnoughDataError: fewer than 8
        correspondences, or no model with 8 inliers. DegenerateConfigurationError: fewer than 8
        distinct points.
    """
    config = config or Config()
    x1b, x2b, unbatched, mask = _check_correspondences(x1, x2, valid)
    dtype = x1.dtype
    F, inliers, trials, success = _robust_fundamental(x1b, x2b, config, generator, mask)
    if valid is None:
        _raise_on_failure(success, unbatched)
    sampson = sampson_error(F, x1b, x2b)
    rms = ((sampson * inliers).sum(-1) / inliers.sum(-1).clamp_min(1)).sqrt()
    F = torch.where(success[:, None, None], F, 0.0)
    result = FundamentalEstimate(F=F.to(dtype), inlier_mask=inliers, num_trials=trials, sampson_rms=rms.to(dtype), success=success)
    return _unbatch(result) if unbatched else result


@without_autograd
def estimate_relative_pose(
    x1: Tensor,
    x2: Tensor,
    K1: Tensor,
    K2: Tensor,
    *,
    valid: Tensor | None = None,
    config: Config | None = None,
    generator: torch.Generator | None = None,
) -> RelativePose:
    """Relative pose of two calibrated views from putative correspondences (thesis §3.3–3.5).

    Robust F (:func:`estimate_fundamental`) → E = K2ᵀ F K1 → four (R, t) → cheirality →
    optional LM on (R, t̂) over the Sampson error → triangulation of the inliers. With
    ``config.relative_pose.solver = "five_point"`` RANSAC fits E itself (five correspondences
    per sample) and the LM starts from it (and the ``num_starts`` extra starts).

    Args:
        x1, x2: pixel correspondences (N, 2) or (B, N, 2).
        K1, K2: intrinsics (3, 3) or (B, 3, 3).
        valid: optional (B, N) bool: a ragged batch padded to one N (False rows are ignored,
            whatever they hold). With it, a problem without a pose is reported in ``success``
            instead of raising, so one bad problem does not stop the others.
        config: uses ``fundamental``, ``relative_pose``, ``triangulation`` and ``lm``.
        generator: RANSAC's random source.

    Returns:
        A :class:`RelativePose` (camera 2 from camera 1, unit t).
    """
    config = config or Config()
    x1b, x2b, unbatched, mask = _check_correspondences(x1, x2, valid)
    dtype = x1.dtype
    B = x1b.shape[0]
    K1b, K2b = intrinsics_per_view(K1, B, "K1"), intrinsics_per_view(K2, B, "K2")

    if config.relative_pose.solver == "five_point":
        F, candidates, trials, success = _robust_essential(x1b, x2b, K1b, K2b, config, generator, mask)
    else:
        F, candidates, trials, success = _robust_fundamental(x1b, x2b, config, generator, mask)
    if valid is None:
        _raise_on_failure(success, unbatched)
    R = torch.eye(3, dtype=torch.float64, device=x1b.device).repeat(B, 1, 1)
    t = torch.zeros(B, 3, dtype=torch.float64, device=x1b.device)
    inliers = torch.zeros_like(mask)
    X = torch.zeros(B, x1b.shape[1], 3, dtype=torch.float64, device=x1b.device)
    found = torch.nonzero(success).flatten()  # the problems with an F: a pose for each
    if found.numel():
        x1f, x2f, K1f, K2f = x1b[found], x2b[found], K1b[found], K2b[found]
        Rf, tf, inf = calibrated_pose(essential_from_fundamental(F[found], K1f, K2f), x1f, x2f, K1f, K2f, candidates[found],
                                      config, generator, mask[found])
        no_parallax, parallax = parallax_is_noise(Rf, tf, x1f, x2f, K1f, K2f, inf, config.fundamental.ransac.inlier_threshold,
                                                  config.relative_pose.parallax_significance)
        if valid is None and bool(no_parallax.any()):
            b = int(torch.nonzero(no_parallax)[0, 0])
            raise DegenerateConfigurationError(
                f"the correspondences{'' if unbatched else f' of problem {int(found[b])}'} show no parallax beyond noise "
                f"(median {float(parallax[b]):.2f} px along the epipolar lines of {int(inf[b].sum())} inliers): a rotation "
                "alone explains them — the camera turned in place or did not move — so the translation is undetermined")
        inf = inf & ~no_parallax[:, None]
        P1 = projection_matrix(K1f, torch.eye(3, dtype=torch.float64, device=K1b.device).expand(found.numel(), 3, 3),
                               torch.zeros(found.numel(), 3, dtype=torch.float64, device=K1b.device))
        Xf = triangulate_points(x1f, x2f, P1, projection_matrix(K2f, Rf, tf), config.triangulation)  # (B', N, 3)
        depth2 = (Xf @ Rf.transpose(-1, -2) + tf[:, None, :])[..., 2]
        inf = inf & (Xf[..., 2] > 0) & (depth2 > 0) & torch.isfinite(Xf).all(-1)
        R[found], t[found], inliers[found], X[found] = Rf, tf, inf, torch.where(inf[..., None], Xf, 0.0)
    success = success & (inliers.sum(-1) >= 5)
    if valid is None:
        _raise_on_failure(success, unbatched)
    R, t = torch.where(success[:, None, None], R, torch.eye(3, dtype=torch.float64, device=R.device)), t * success[:, None]
    inliers = inliers & success[:, None]
    F = torch.where(success[:, None, None], fundamental_from_pose(K1b, K2b, R, t), 0.0)
    points = tuple(X[b][inliers[b]].to(dtype) for b in range(B))
    result = RelativePose(R=R.to(dtype), t=t.to(dtype), inlier_mask=inliers, points3d=points, F=F.to(dtype), num_trials=trials,
                          success=success)
    if unbatched:
        result = _unbatch(result)
    return result


def _unbatch(result):
    """Drop the leading batch dimension of every tensor field (tuples of one: their element)."""
    for name, value in vars(result).items():
        setattr(result, name, value[0])
    return result


class RobustFundamental(nn.Module):
    """Pipeline stage: (x1, x2) pixels -> :class:`FundamentalEstimate` (see :func:`estimate_fundamental`)."""

    def __init__(self, config: Config | None = None) -> None:
        super().__init__()
        self.config = config or Config()

    def forward(self, x1: Tensor, x2: Tensor, generator: torch.Generator | None = None) -> FundamentalEstimate:
        return estimate_fundamental(x1, x2, config=self.config, generator=generator)

    def extra_repr(self) -> str:
        return repr(self.config.fundamental)


class RelativePoseEstimator(nn.Module):
    """Pipeline stage: (x1, x2, K1, K2) -> :class:`RelativePose` (see :func:`estimate_relative_pose`)."""

    def __init__(self, config: Config | None = None) -> None:
        super().__init__()
        self.config = config or Config()

    def forward(self, x1: Tensor, x2: Tensor, K1: Tensor, K2: Tensor,
                generator: torch.Generator | None = None) -> RelativePose:
        return estimate_relative_pose(x1, x2, K1, K2, config=self.config, generator=generator)

    def extra_repr(self) -> str:
        return f"{self.config.relative_pose}, {self.config.triangulation}"
