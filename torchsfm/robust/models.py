"""Estimator plug-ins for the RANSAC engine (see :class:`torchsfm.robust.ransac.RobustModel`)."""

from __future__ import annotations

import torch
from torch import Tensor

from torchsfm.geometry.fundamental import eight_point, eight_point_minimal, sampson_error_of_hypotheses
from torchsfm.geometry.normalization import hartley_normalize


class FundamentalModel:
    """F from correspondences; data rows are ``(x1, y1, x2, y2)`` in pixels (D = 4).

    Minimal solver: the normalized 8-point algorithm (Alg. 3.3.2) with Hartley's normalization
    computed once on all valid correspondences of each problem; non-minimal refits normalize
    their own point set. Residual: the Sampson error (eq. 3.3.6) in pixels², so the RANSAC
    threshold is a Sampson distance in pixels. Residuals are computed in float32 (scoring only
    compares them with the threshold; the error is ~1e-3 px).

    Args:
        data: (B, N, 4) the correspondences the model will be fitted to.
        valid: optional (B, N) bool mask of real rows.
    """

    sample_size = 8

    def __init__(self, data: Tensor, valid: Tensor | None = None) -> None:
        weights = None if valid is None else valid.to(data.dtype)
        self.T1 = hartley_normalize(data[..., :2], weights)[1]
        self.T2 = hartley_normalize(data[..., 2:], weights)[1]

    def fit_minimal(self, samples: Tensor) -> tuple[Tensor, Tensor]:
        F = eight_point_minimal(samples[..., :2], samples[..., 2:], self.T1, self.T2)  # (B, K, 3, 3)
        return F, torch.isfinite(F).flatten(-2).all(-1)

    def fit_weighted(self, data: Tensor, weights: Tensor) -> Tensor:
        return eight_point(data[..., :2], data[..., 2:], weights)

    def residuals(self, models: Tensor, data: Tensor) -> Tensor:
        x1, x2 = data[..., :2].float(), data[..., 2:].float()
        return sampson_error_of_hypotheses(models.float(), x1, x2)

    def sampling_coordinates(self, data: Tensor) -> Tensor:
        return data[..., :2]
