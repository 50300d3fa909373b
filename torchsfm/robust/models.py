"""Estimator plug-ins for the RANSAC engine (see :class:`torchsfm.robust.ransac.RobustModel`)."""

from __future__ import annotations

import copy

import torch
from torch import Tensor

from torchsfm.camera import map_homogeneous_by_each, to_homogeneous
from torchsfm.geometry.essential import project_to_essential
from torchsfm.geometry.five_point import five_point_essential
from torchsfm.geometry.fundamental import eight_point, eight_point_minimal, sampson_error_of_hypotheses, seven_point_minimal
from torchsfm.geometry.homography import homography_dlt, transfer_error_of_hypotheses
from torchsfm.geometry.planar_flow import fit_planar_flow, planar_flow, planar_flow_design
from torchsfm.geometry.normalization import apply_affine, hartley_normalize
from torchsfm.geometry.projective import projection_distance_squared, projective_resection
from torchsfm.geometry.resection import dlt_projection, p3p, pose_from_projection, reprojection_errors_of_hypotheses


class FundamentalModel:
    """F from correspondences; data rows are ``(x1, y1, x2, y2)`` in pixels (D = 4).

    Minimal solver: ``eight_point``, the normalized 8-point algorithm (Alg. 3.3.2), or
    ``seven_point`` (up to three F per sample; fewer samples at the same confidence), with
    Hartley's normalization computed once on all valid correspondences of each problem;
    non-minimal refits normalize their own point set. Residual: the Sampson error (eq. 3.3.6)
    in pixels², so the RANSAC threshold is a Sampson distance in pixels. Residuals are computed in float32 (scoring only
    compares them with the threshold; the error is ~1e-3 px).

    Args:
        data: (B, N, 4) the correspondences the model will be fitted to.
        valid: optional (B, N) bool mask of real rows.
        solver: ``eight_point`` or ``seven_point``.
    """

    sample_size = 8

    def __init__(self, data: Tensor, valid: Tensor | None = None, solver: str = "eight_point") -> None:
        weights = None if valid is None else valid.to(data.dtype)
        self.T1 = hartley_normalize(data[..., :2], weights)[1]
        self.T2 = hartley_normalize(data[..., 2:], weights)[1]
        self.solver = solver
        self.sample_size = 7 if solver == "seven_point" else 8

    def restricted(self, problems: Tensor) -> FundamentalModel:
        return _restricted(self, problems, "T1", "T2")

    def fit_minimal(self, samples: Tensor) -> tuple[Tensor, Tensor]:
        if self.solver == "eight_point":
            F = eight_point_minimal(samples[..., :2], samples[..., 2:], self.T1, self.T2)  # (B, K, 3, 3)
            return F, torch.isfinite(F).flatten(-2).all(-1)
        F = seven_point_minimal(samples[..., :2], samples[..., 2:], self.T1, self.T2).flatten(1, 2)  # (B, 3K, 3, 3)
        return _solutions_first(F, torch.isfinite(F).flatten(-2).all(-1))

    def fit_weighted(self, data: Tensor, weights: Tensor) -> Tensor:
        return eight_point(data[..., :2], data[..., 2:], weights)

    def residuals(self, models: Tensor, data: Tensor) -> Tensor:
        x1, x2 = data[..., :2].float(), data[..., 2:].float()
        return sampson_error_of_hypotheses(models.float(), x1, x2)

    def sampling_coordinates(self, data: Tensor) -> Tensor:
        return data[..., :2]


class EssentialModel:
    """E of two calibrated views, as the F it induces; data rows ``(x1, y1, x2, y2)`` in pixels.

    Minimal solver: the five-point algorithm (:func:`~torchsfm.geometry.five_point.five_point_essential`,
    up to ten E per sample of 5) on K⁻¹-normalized points; non-minimal: the 8-point algorithm
    on the normalized points, projected to the nearest essential matrix. Models are
    F = K2⁻ᵀ E K1⁻¹ (unit norm), scored like :class:`FundamentalModel` (Sampson, pixels²).

    Args:
        K1, K2: (B, 3, 3) intrinsics of the two views.
    """

    sample_size = 5

    def __init__(self, K1: Tensor, K2: Tensor) -> None:  # no Hartley normalization: K⁻¹ normalizes
        self.K1_inv, self.K2_inv = torch.linalg.inv(K1), torch.linalg.inv(K2)

    def restricted(self, problems: Tensor) -> EssentialModel:
        return _restricted(self, problems, "K1_inv", "K2_inv")

    def _normalized(self, data: Tensor) -> tuple[Tensor, Tensor]:
        extra = data.dim() - 3  # sample axes between the problem and the rows
        K1_inv = self.K1_inv.reshape(-1, *[1] * extra, 3, 3)
        K2_inv = self.K2_inv.reshape(-1, *[1] * extra, 3, 3)
        return apply_affine(K1_inv, data[..., :2]), apply_affine(K2_inv, data[..., 2:])

    def _fundamental(self, E: Tensor) -> Tensor:
        extra = E.dim() - 3
        F = self.K2_inv.reshape(-1, *[1] * extra, 3, 3).transpose(-1, -2) @ E @ self.K1_inv.reshape(-1, *[1] * extra, 3, 3)
        return F / F.flatten(-2).norm(dim=-1)[..., None, None]

    def fit_minimal(self, samples: Tensor) -> tuple[Tensor, Tensor]:
        E, ok = five_point_essential(*self._normalized(samples))  # (B, K, 10, 3, 3), (B, K, 10)
        return _solutions_first(self._fundamental(E).flatten(1, 2), ok.flatten(1))

    def fit_weighted(self, data: Tensor, weights: Tensor) -> Tensor:
        return self._fundamental(project_to_essential(eight_point(*self._normalized(data), weights)))

    residuals = FundamentalModel.residuals
    sampling_coordinates = FundamentalModel.sampling_coordinates


class ResectionModel:
    """A calibrated camera pose from 3-D↔2-D pairs; data rows ``(X, Y, Z, x, y)`` (D = 5).

    Minimal solver: ``p3p`` (Grunert, 3 pairs, up to 4 poses per sample) or ``dlt`` (the
    normalized DLT on 6 pairs, then the pose nearest to K⁻¹P). Non-minimal fit: the DLT on the
    weighted pairs, then the nearest pose. Models are P = K [R | t] (3, 4); the residual is the
    squared reprojection error in pixels² (+inf behind the camera), in float32 with the points
    taken about one of them (scoring only compares it with the threshold).

    Args:
        K: (B, 3, 3) intrinsics; solver: ``p3p`` or ``dlt``.
    """

    def __init__(self, K: Tensor, solver: str = "p3p") -> None:
        self.K, self.K_inv, self.solver = K, torch.linalg.inv(K), solver
        self.sample_size = 3 if solver == "p3p" else 6

    def restricted(self, problems: Tensor) -> ResectionModel:
        return _restricted(self, problems, "K", "K_inv")

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
        X = data[..., :3]
        centre = X[..., :1, :]  # any point of the problem: about it, the scene's extent, not its offset, sets the float32 error
        P = torch.cat([models[..., :3], models[..., 3:] + models[..., :3] @ centre[..., None, :, :].transpose(-1, -2)], dim=-1)
        return reprojection_errors_of_hypotheses(P.float(), (X - centre).float(), data[..., 3:].float())

    def sampling_coordinates(self, data: Tensor) -> Tensor:
        return data[..., 3:]


class HomographyModel:
    """A homography x2 ~ H x1; data rows ``(x1, y1, x2, y2)`` (D = 4). Minimal solver: the 8×8
    linear system of 4 pairs with h33 = 1, in Hartley-normalized coordinates computed once per
    problem (one batched solve instead of an SVD per sample); non-minimal: the normalized DLT.
    Residual: squared one-way transfer error (pixels²).

    Args:
        data: (B, N, 4) the correspondences; valid: optional (B, N) mask of real rows.
    """

    sample_size = 4

    def __init__(self, data: Tensor, valid: Tensor | None = None) -> None:
        weights = None if valid is None else valid.to(data.dtype)
        self.T1 = hartley_normalize(data[..., :2], weights)[1]
        self.T2 = hartley_normalize(data[..., 2:], weights)[1]

    def restricted(self, problems: Tensor) -> HomographyModel:
        return _restricted(self, problems, "T1", "T2")

    def fit_minimal(self, samples: Tensor) -> tuple[Tensor, Tensor]:
        T1, T2 = self.T1[:, None], self.T2[:, None]  # (B, 1, 3, 3)
        x, u = apply_affine(T1, samples[..., :2]), apply_affine(T2, samples[..., 2:])
        one, zero = torch.ones_like(x[..., :1]), torch.zeros_like(x[..., :1])
        rows_u = torch.cat([x, one, zero, zero, zero, -u[..., :1] * x], dim=-1)  # (B, K, 4, 8)
        rows_v = torch.cat([zero, zero, zero, x, one, -u[..., 1:] * x], dim=-1)
        A = torch.stack([rows_u, rows_v], dim=-2).flatten(-3, -2)  # (B, K, 8, 8)
        solvable = torch.linalg.det(A).abs() > 1e-10
        A = torch.where(solvable[..., None, None], A, torch.eye(8, dtype=A.dtype, device=A.device))
        h = torch.linalg.solve(A, u.flatten(-2)[..., None])[..., 0]
        H = torch.cat([h, torch.ones_like(h[..., :1])], dim=-1).unflatten(-1, (3, 3))
        H = torch.linalg.inv(T2) @ H @ T1
        return H / H.flatten(-2).norm(dim=-1)[..., None, None], solvable

    def fit_weighted(self, data: Tensor, weights: Tensor) -> Tensor:
        return homography_dlt(data[..., :2], data[..., 2:], weights)

    def residuals(self, models: Tensor, data: Tensor) -> Tensor:
        return transfer_error_of_hypotheses(models, data[..., :2], data[..., 2:])

    def sampling_coordinates(self, data: Tensor) -> Tensor:
        return data[..., :2]


class PlanarFlowModel:
    """The quadratic planar flow (eq. 5.2.1) of one dominant plane between a reference frame and
    J other frames; data rows ``(x, y, x'_1, y'_1, ..., x'_J, y'_J)``: a point of the reference
    frame and its positions in the other frames (pixels, D = 2 + 2J). A model is (J, 8), one
    flow per frame, all fitted to the same points so that every frame is registered by the same
    plane (with two independent fits an inserted planar object can win one frame pair).

    Fitted in the Hartley-normalized frame of all valid reference points (one similarity per
    problem, so minimal and weighted fits share it). Minimal solver: the affine part (p7 = p8
    = 0) from 3 correspondences (ours: 3-point samples need far fewer trials than the 4 points
    the 8 parameters take, and the LO refits and the final fit restore the quadratic terms);
    non-minimal: weighted least squares of all 8. Residual: the largest over the frames of the
    squared distance (pixels²) between x'_j and x + u_j(x).

    Args:
        data: (B, N, 2 + 2J) the correspondences; valid: optional (B, N) mask of real rows.
    """

    sample_size = 3

    def __init__(self, data: Tensor, valid: Tensor | None = None) -> None:
        weights = None if valid is None else valid.to(data.dtype)
        self.T = hartley_normalize(data[..., :2], weights)[1]  # (B, 3, 3)

    def restricted(self, problems: Tensor) -> PlanarFlowModel:
        return _restricted(self, problems, "T")

    def normalize(self, data: Tensor) -> tuple[Tensor, Tensor]:
        """Reference points (B, ..., 2) and displacements (B, ..., J, 2) of (B, ..., D) rows in
        the normalized frame."""
        T = self.T.reshape(self.T.shape[0], *[1] * (data.dim() - 3), 3, 3)
        x = data[..., :2]
        others = data[..., 2:].unflatten(-1, (-1, 2))  # (B, ..., N, J, 2)
        return apply_affine(T, x), (others - x[..., None, :]) * T[..., None, None, 0, 0, None]

    def fit_minimal(self, samples: Tensor) -> tuple[Tensor, Tensor]:
        x, displacement = self.normalize(samples)  # (B, K, 3, 2), (B, K, 3, J, 2)
        A = planar_flow_design(x)[..., :6].flatten(-3, -2)  # (B, K, 6, 6): the affine part
        solvable = torch.linalg.det(A).abs() > 1e-9
        A = torch.where(solvable[..., None, None], A, torch.eye(6, dtype=A.dtype, device=A.device))
        affine = torch.linalg.solve(A[..., None, :, :], displacement.transpose(-2, -3).flatten(-2)[..., None])[..., 0]  # (B, K, J, 6)
        return torch.cat([affine, torch.zeros_like(affine[..., :2])], dim=-1), solvable

    def fit_weighted(self, data: Tensor, weights: Tensor) -> Tensor:
        x, displacement = self.normalize(data)  # (B, N, 2), (B, N, J, 2)
        J = displacement.shape[-2]
        return fit_planar_flow(x[:, None].expand(-1, J, -1, -1), displacement.transpose(1, 2), weights[:, None].expand(-1, J, -1))

    def residuals(self, models: Tensor, data: Tensor) -> Tensor:
        x, displacement = self.normalize(data)  # (B, N, 2), (B, N, J, 2)
        B, H, J = models.shape[:3]
        predicted = planar_flow(models.flatten(1, 2), x).unflatten(1, (H, J))  # (B, H, J, N, 2)
        scale = self.T[:, 0, 0].reshape(-1, 1, 1)
        squared = (displacement.transpose(1, 2)[:, None] - predicted).square().sum(-1)  # (B, H, J, N)
        return squared.amax(2) / scale.square()

    def sampling_coordinates(self, data: Tensor) -> Tensor:
        return data[..., :2]


class JointModel:
    """One model per frame, all fitted to the same samples: data rows ``(x, y, x'_1, y'_1, ...,
    x'_J, y'_J)`` (D = 2 + 2J); the model of frame j is fitted to ``(x, y, x'_j, y'_j)``. Models
    are (J, *M); a row's residual is its largest over the frames, so an inlier fits every frame.
    The J frames run as J·B problems of one ``model_class`` plug-in (one call per step, not one
    per frame).

    Args:
        model_class: a single-solution plug-in for (x, y, x', y') rows built as
            ``model_class(data, valid)`` (e.g. :class:`HomographyModel`).
        data: (B, N, 2 + 2J) rows; valid: optional (B, N) mask of real rows.
    """

    def __init__(self, model_class, data: Tensor, valid: Tensor | None = None) -> None:
        self.frames = (data.shape[-1] - 2) // 2
        self.model = model_class(self._pairs(data), None if valid is None else valid.repeat_interleave(self.frames, 0))
        self.sample_size = self.model.sample_size

    def restricted(self, problems: Tensor) -> JointModel:
        joint = copy.copy(self)
        rows = problems[:, None] * self.frames + torch.arange(self.frames, device=problems.device)
        joint.model = self.model.restricted(rows.flatten())
        return joint

    def _pairs(self, rows: Tensor) -> Tensor:
        """(B, ..., 2 + 2J) rows -> (B·J, ..., 4) rows of frame pairs, frame-major within a problem."""
        reference = rows[..., :2].unsqueeze(1).expand(-1, self.frames, *rows.shape[1:-1], 2)
        others = rows[..., 2:].unflatten(-1, (self.frames, 2)).movedim(-2, 1)  # (B, J, ..., 2)
        return torch.cat([reference, others], -1).flatten(0, 1)

    def fit_minimal(self, samples: Tensor) -> tuple[Tensor, Tensor]:
        models, solvable = self.model.fit_minimal(self._pairs(samples))  # (B·J, K, *M), (B·J, K)
        models = models.unflatten(0, (-1, self.frames)).movedim(1, 2)  # (B, K, J, *M)
        return models, solvable.unflatten(0, (-1, self.frames)).all(1)

    def fit_weighted(self, data: Tensor, weights: Tensor) -> Tensor:
        return self.model.fit_weighted(self._pairs(data), weights.repeat_interleave(self.frames, 0)).unflatten(0, (-1, self.frames))

    def residuals(self, models: Tensor, data: Tensor) -> Tensor:
        per_frame = models.movedim(2, 1).flatten(0, 1)  # (B·J, H, *M)
        return self.model.residuals(per_frame, self._pairs(data)).unflatten(0, (-1, self.frames)).amax(1)

    def sampling_coordinates(self, data: Tensor) -> Tensor:
        return data[..., :2]


class ProjectiveResectionModel:
    """A projective camera from homogeneous-point↔image pairs; data rows ``(X1..X4, x, y)``
    (D = 6), all in normalized coordinates.

    Minimal solver: the 6-point DLT (:func:`torchsfm.geometry.projective.projective_resection`);
    non-minimal: the same on weighted pairs. Residual: the squared reprojection error divided by
    ``scale²`` (pixels² when ``scale`` is the normalization's pixels-to-normalized factor).
    """

    sample_size = 6

    def __init__(self, scale: float = 1.0) -> None:
        self.scale = scale

    def restricted(self, problems: Tensor) -> ProjectiveResectionModel:
        return self  # nothing per problem

    def fit_minimal(self, samples: Tensor) -> tuple[Tensor, Tensor]:
        P = projective_resection(samples[..., :4], samples[..., 4:])
        return P, torch.isfinite(P).flatten(-2).all(-1)

    def fit_weighted(self, data: Tensor, weights: Tensor) -> Tensor:
        return projective_resection(data[..., :4], data[..., 4:], weights)

    def residuals(self, models: Tensor, data: Tensor) -> Tensor:
        projected = map_homogeneous_by_each(models, data[..., :4])  # (B, N, H, 3): the points are not copied per model
        return projection_distance_squared(projected, data[..., None, 4:]).transpose(-1, -2) / self.scale**2

    def sampling_coordinates(self, data: Tensor) -> Tensor:
        return data[..., 4:]


def _solutions_first(models: Tensor, ok: Tensor) -> tuple[Tensor, Tensor]:
    """(B, M, ...) models of a solver with several solutions per sample and (B, M) ``ok`` (a real
    solution): per problem the real ones first, every problem cut to the most any problem has."""
    keep = max(1, int(ok.sum(1).max()))
    order = ok.to(torch.int8).argsort(dim=1, descending=True, stable=True)[:, :keep]
    rows = torch.arange(models.shape[0], device=models.device)[:, None]
    return models[rows, order], ok[rows, order]


def _restricted(model, problems: Tensor, *per_problem: str):
    """A shallow copy of ``model`` whose (B, ...) attributes ``per_problem`` keep the rows
    ``problems`` (P,) only."""
    subset = copy.copy(model)
    for name in per_problem:
        setattr(subset, name, getattr(model, name)[problems])
    return subset
