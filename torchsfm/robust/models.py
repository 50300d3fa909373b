"""Estimator plug-ins for the RANSAC engine (see :class:`torchsfm.robust.ransac.RobustModel`)."""

from __future__ import annotations

import torch
from torch import Tensor

from torchsfm.camera import to_homogeneous
from torchsfm.geometry.fundamental import eight_point, eight_point_minimal, sampson_error_of_hypotheses
from torchsfm.geometry.homography import homography_dlt, transfer_error
from torchsfm.geometry.normalization import hartley_normalize
from torchsfm.geometry.resection import dlt_projection, p3p, pose_from_projection, reprojection_errors


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


class ResectionModel:
    """A calibrated camera pose from 3-D↔2-D pairs; data rows ``(X, Y, Z, x, y)`` (D = 5).

    Minimal solver: ``p3p`` (Grunert, 3 pairs, up to 4 poses per sample) or ``dlt`` (the
    normalized DLT on 6 pairs, then the pose nearest to K⁻¹P). Non-minimal fit: the DLT on the
    weighted pairs, then the nearest pose. Models are P = K [R | t] (3, 4); the residual is the
    squared reprojection error in pixels² (+inf behind the camera).

    Args:
        K: (B, 3, 3) intrinsics; solver: ``p3p`` or ``dlt``.
    """

    def __init__(self, K: Tensor, solver: str = "p3p") -> None:
        self.K, self.K_inv, self.solver = K, torch.linalg.inv(K), solver
        self.sample_size = 3 if solver == "p3p" else 6

    def _projection(self, R: Tensor, t: Tensor) -> Tensor:
        K = self.K.reshape(self.K.shape[0], *[1] * (R.dim() - 3), 3, 3)
        return K @ torch.cat([R, t[..., None]], dim=-1)

    def fit_minimal(self, samples: Tensor) -> tuple[Tensor, Tensor]:
        X, x = samples[..., :3], samples[..., 3:]  # (B, K, s, 3), (B, K, s, 2)
        B, K = samples.shape[:2]
        if self.solver == "p3p":
            rays = to_homogeneous(x) @ self.K_inv[:, None].transpose(-1, -2)
            R, t, valid = p3p(X, rays / rays.norm(dim=-1, keepdim=True))  # (B, K, 4, ...)
            return self._projection(R, t).reshape(B, 4 * K, 3, 4), valid.reshape(B, 4 * K)
        R, t = pose_from_projection(dlt_projection(X, x), self.K[:, None], X)
        P = self._projection(R, t)
        return P, torch.isfinite(P).flatten(-2).all(-1)

    def fit_weighted(self, data: Tensor, weights: Tensor) -> Tensor:
        X, x = data[..., :3], data[..., 3:]
        R, t = pose_from_projection(dlt_projection(X, x, weights), self.K, X)
        return self._projection(R, t)

    def residuals(self, models: Tensor, data: Tensor) -> Tensor:
        return reprojection_errors(models, data[:, None, :, :3], data[:, None, :, 3:])

    def sampling_coordinates(self, data: Tensor) -> Tensor:
        return data[..., 3:]


class HomographyModel:
    """A homography x2 ~ H x1; data rows ``(x1, y1, x2, y2)`` (D = 4). Minimal and non-minimal
    solver: the normalized DLT (4 pairs); residual: squared one-way transfer error (pixels²)."""

    sample_size = 4

    def fit_minimal(self, samples: Tensor) -> tuple[Tensor, Tensor]:
        H = homography_dlt(samples[..., :2], samples[..., 2:])
        return H, torch.isfinite(H).flatten(-2).all(-1)

    def fit_weighted(self, data: Tensor, weights: Tensor) -> Tensor:
        return homography_dlt(data[..., :2], data[..., 2:], weights)

    def residuals(self, models: Tensor, data: Tensor) -> Tensor:
        return transfer_error(models, data[:, None, :, :2], data[:, None, :, 2:])

    def sampling_coordinates(self, data: Tensor) -> Tensor:
        return data[..., :2]
