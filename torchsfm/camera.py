"""The pinhole camera with two-coefficient radial distortion (thesis §2.1, errata to §2.1.2).

Conventions, written once for the whole package:

* **Pixels.** ``(x, y)`` with x to the right and y down; the *centre* of the top-left pixel is
  ``(0, 0)`` (the Oxford VGG and Strecha convention). Image tensors are ``(B, C, H, W)``.
* **Poses.** ``R, t`` map world to camera: ``X_cam = R X_world + t`` (COLMAP's
  ``cam_from_world``). The camera centre is ``C = -Rᵀ t`` and ``P = K [R | t]``.
* **Normalized coordinates.** ``x_n = K⁻¹ x`` (dehomogenized), the image of a camera with K = I.
* **Radial distortion.** Applied in normalized coordinates to the ideal (undistorted) point:
  ``x_d = x_n (1 + k1 r² + k2 r⁴)`` with ``r = ‖x_n‖`` the Euclidean distance to the principal
  point (Hartley & Zisserman §7.4; the thesis' eq. 2.1.13 uses r² where it says r, see ERRATA).
  ``distortion`` tensors are ``(*, 2)`` holding ``(k1, k2)``; OpenCV's model with
  ``p1 = p2 = k3 = 0`` is the same model.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from kornia.geometry.transform import remap
from torch import Tensor

from torchsfm.errors import DegenerateConfigurationError, InputError, ShapeError
from torchsfm.validation import check_finite, check_floating, check_shapes
from torchsfm.numerics import floor_tiny

FOCAL_PRIOR = 1.2  # × the larger image side: the focal length of a camera without calibration (a common field of view, as COLMAP's)


def to_homogeneous(x: Tensor) -> Tensor:
    """Append a coordinate 1: (*, D) -> (*, D + 1)."""
    return torch.cat([x, torch.ones_like(x[..., :1])], dim=-1)


def from_homogeneous(x: Tensor) -> Tensor:
    """Divide by the last coordinate: (*, D + 1) -> (*, D). No guard: callers keep it non-zero."""
    return x[..., :-1] / x[..., -1:]


def map_by_each(M: Tensor, x: Tensor) -> Tensor:
    """Homogeneous images (*, N, H, 3) of the points x (*, N, D) under each of H matrices M
    (*, H, 3, D + 1) (homographies, cameras): :func:`map_homogeneous_by_each` of x with a 1 appended."""
    return map_homogeneous_by_each(M, to_homogeneous(x))


def map_homogeneous_by_each(M: Tensor, X: Tensor) -> Tensor:
    """Images (*, N, H, 3) of the homogeneous points X (*, N, K) under each of H matrices M
    (*, H, 3, K), as one (N, K) x (K, 3H) product per problem: no per-matrix copy of the points."""
    H = M.shape[-3]
    stacked = M.transpose(-1, -2).transpose(-3, -2).reshape(*M.shape[:-3], M.shape[-1], 3 * H)  # column 3k + j: row j of M_k
    return (X @ stacked).unflatten(-1, (H, 3))


def check_intrinsics(**matrices: Tensor) -> None:
    """Raise if any K (*, 3, 3) is non-finite, singular (|det K| tiny against its scale) or has a
    focal length (fx or fy, over K[2, 2]) that is not positive (a mirrored or flipped camera)."""
    check_shapes(**{name: (K, "* 3 3") for name, K in matrices.items()})
    check_finite(**matrices)
    for name, K in matrices.items():
        scale = floor_tiny(K.abs().amax(dim=(-2, -1)))
        if bool((torch.linalg.det(K).abs() <= 1e-12 * scale**3).any()):
            raise DegenerateConfigurationError(f"{name} is singular: an intrinsic matrix must be invertible")
        focal = K[..., [0, 1], [0, 1]] * K[..., 2:, 2]  # the signs of fx / K22, fy / K22
        if bool((focal <= 0).any()):
            bad = K[..., [0, 1], [0, 1]][(focal <= 0).any(-1)][0].tolist()
            raise InputError(f"{name} has a focal length that is not positive (fx, fy = {bad[0]:g}, {bad[1]:g}): "
                             "an intrinsic matrix has fx, fy > 0 (with K[2, 2] > 0)")


def intrinsics_per_view(K: Tensor, count: int, name: str = "K") -> Tensor:
    """One checked (:func:`check_intrinsics`) K for all ``count`` views, (3, 3), or one per view,
    (count, 3, 3) -> (count, 3, 3) float64; any other shape is a ShapeError that names both."""
    check_floating(**{name: K})
    check_intrinsics(**{name: K})
    if K.dim() not in (2, 3) or (K.dim() == 3 and K.shape[0] != count):
        raise ShapeError(f"{name} must be (3, 3) or ({count}, 3, 3), got {tuple(K.shape)}")
    return K.double().expand(count, 3, 3)


def projection_matrix(K: Tensor, R: Tensor, t: Tensor) -> Tensor:
    """P = K [R | t]: (*, 3, 3), (*, 3, 3), (*, 3) -> (*, 3, 4)."""
    return K @ torch.cat([R, t[..., None]], dim=-1)


def project(P: Tensor, X: Tensor) -> Tensor:
    """Pixels of 3-D points: P (*, 3, 4), X (*, N, 3) -> (*, N, 2)."""
    return from_homogeneous(to_homogeneous(X) @ P.transpose(-1, -2))


def camera_center(P: Tensor) -> Tensor:
    """Centre C with P [C; 1] = 0 of a finite camera: (*, 3, 4) -> (*, 3)."""
    return -torch.linalg.solve(P[..., :3], P[..., 3:]).squeeze(-1)


def decompose_projection(P: Tensor) -> tuple[Tensor, Tensor, Tensor]:
    """Split a finite P (*, 3, 4) into K (positive diagonal, K[2,2] = 1), R and t: P ∝ K [R | t].

    RQ decomposition of the left 3x3 block M with the signs chosen so that K's diagonal is
    positive. The overall sign of P is kept, so depths ``(R X + t)_z`` have the sign of
    ``P[2] · [X; 1]`` and ``det R = sign(det M)``: a P written in a left-handed (mirrored) world
    frame yields det R = -1 (relative poses ``R_j R_iᵀ`` are still proper rotations).
    """
    M = P[..., :3]
    flip = torch.flip(torch.eye(3, dtype=P.dtype, device=P.device), dims=[0])
    Q, U = torch.linalg.qr((flip @ M).transpose(-1, -2))  # RQ via QR of the flipped transpose
    K = flip @ U.transpose(-1, -2) @ flip
    R = flip @ Q.transpose(-1, -2)
    D = torch.diag_embed(torch.sign(torch.diagonal(K, dim1=-2, dim2=-1)))
    K, R = K @ D, D @ R
    t = torch.linalg.solve(K, P[..., 3:]).squeeze(-1)
    return K / K[..., 2:3, 2:3], R, t


def rescale_pixels(x: Tensor, scale: float) -> Tensor:
    """Pixel coordinates (*, 2) of an image resampled by ``scale`` (pixel centres at integers:
    x' = (x + 0.5) · scale − 0.5)."""
    return (x + 0.5) * scale - 0.5


def rescale_intrinsics(K: Tensor, scale: float) -> Tensor:
    """K (*, 3, 3) of the same camera in an image resampled by ``scale`` (:func:`rescale_pixels`)."""
    A = torch.tensor([[scale, 0.0, (scale - 1) / 2], [0.0, scale, (scale - 1) / 2], [0.0, 0.0, 1.0]], dtype=K.dtype, device=K.device)
    return A @ K


def pixels_to_normalized(x: Tensor, K: Tensor) -> Tensor:
    """x_n = K⁻¹ x: pixels (*, N, 2), K (*, 3, 3) -> normalized coordinates (*, N, 2)."""
    return from_homogeneous(to_homogeneous(x) @ torch.linalg.inv(K).transpose(-1, -2))


def normalized_to_pixels(x: Tensor, K: Tensor) -> Tensor:
    """x = K x_n: normalized (*, N, 2), K (*, 3, 3) -> pixels (*, N, 2)."""
    return from_homogeneous(to_homogeneous(x) @ K.transpose(-1, -2))


def distort_normalized(x: Tensor, distortion: Tensor) -> Tensor:
    """Apply the radial model to ideal normalized points: (*, N, 2), (*, 2) -> (*, N, 2)."""
    k1, k2 = distortion[..., None, 0:1], distortion[..., None, 1:2]
    r2 = (x * x).sum(-1, keepdim=True)
    return x * (1 + k1 * r2 + k2 * r2 * r2)


def undistort_normalized(x: Tensor, distortion: Tensor, iterations: int = 20) -> Tensor:
    """Invert :func:`distort_normalized` by Newton's method on the radius: (*, N, 2) -> (*, N, 2).

    The radial model only scales a point along its ray, so the inverse solves the scalar equation
    ``r (1 + k1 r² + k2 r⁴) = r_d`` per point. Converges to machine precision in a few steps for
    any distortion that keeps the model monotonic over the image.
    """
    k1, k2 = distortion[..., None, 0], distortion[..., None, 1]
    r_d = x.norm(dim=-1)
    r = r_d.clone()
    for _ in range(iterations):
        r2 = r * r
        value = r * (1 + k1 * r2 + k2 * r2 * r2) - r_d
        slope = 1 + 3 * k1 * r2 + 5 * k2 * r2 * r2
        r = r - value / slope
    scale = torch.where(r_d > 0, r / floor_tiny(r_d), torch.ones_like(r_d))
    return x * scale[..., None]


def distort_points(x: Tensor, K: Tensor, distortion: Tensor) -> Tensor:
    """Ideal pixels -> distorted (observed) pixels: (*, N, 2), K (*, 3, 3), (*, 2) -> (*, N, 2)."""
    return normalized_to_pixels(distort_normalized(pixels_to_normalized(x, K), distortion), K)


def undistort_points(x: Tensor, K: Tensor, distortion: Tensor) -> Tensor:
    """Observed pixels -> ideal pixels: (*, N, 2), K (*, 3, 3), (*, 2) -> (*, N, 2)."""
    return normalized_to_pixels(undistort_normalized(pixels_to_normalized(x, K), distortion), K)


def undistort_image(image: Tensor, K: Tensor, distortion: Tensor) -> Tensor:
    """Resample an image as the same camera without distortion: (B, C, H, W) -> (B, C, H, W).

    Each output (ideal) pixel is distorted forward and the input is sampled there bilinearly, so
    no inverse of the model is needed. K is (B, 3, 3) or (3, 3); distortion (B, 2) or (2,).
    """
    return _sampled_through(image, K, distortion, distort_points)


def distort_image(image: Tensor, K: Tensor, distortion: Tensor) -> Tensor:
    """Resample an ideal image as the same camera with distortion would record it (the inverse
    of :func:`undistort_image`; e.g. a synthetic lens): (B, C, H, W) float -> (B, C, H, W).

    Each output (observed) pixel is undistorted (:func:`undistort_points`) and the input is
    sampled there bilinearly. K is (B, 3, 3) or (3, 3); distortion (B, 2) or (2,).
    """
    return _sampled_through(image, K, distortion, undistort_points)


def _sampled_through(image: Tensor, K: Tensor, distortion: Tensor, where) -> Tensor:
    """(B, C, H, W) image sampled bilinearly, at each output pixel, where ``where`` (pixels, K,
    distortion) -> pixels puts it."""
    B, _, H, W = image.shape
    ys, xs = torch.meshgrid(
        torch.arange(H, dtype=K.dtype, device=image.device),
        torch.arange(W, dtype=K.dtype, device=image.device),
        indexing="ij",
    )
    grid = torch.stack([xs, ys], dim=-1).reshape(1, H * W, 2).expand(B, -1, -1)
    source = where(grid, K.expand(B, 3, 3), distortion.expand(B, 2)).to(image.dtype)
    source = source.reshape(B, H, W, 2)
    return remap(image, source[..., 0], source[..., 1], align_corners=True)


@dataclass
class Camera:
    """A calibrated camera: intrinsics, pose (camera from world) and radial distortion.

    Fields: ``K`` (*, 3, 3), ``R`` (*, 3, 3), ``t`` (*, 3), ``distortion`` (*, 2) = (k1, k2).
    """

    K: Tensor
    R: Tensor
    t: Tensor
    distortion: Tensor | None = None

    def __post_init__(self) -> None:
        check_shapes(K=(self.K, "* 3 3"), R=(self.R, "* 3 3"), t=(self.t, "* 3"))
        if self.distortion is None:
            self.distortion = self.K.new_zeros(*self.K.shape[:-2], 2)
        check_shapes(distortion=(self.distortion, "* 2"))

    @property
    def P(self) -> Tensor:
        """Projection matrix K [R | t]: (*, 3, 4)."""
        return projection_matrix(self.K, self.R, self.t)

    @property
    def center(self) -> Tensor:
        """Camera centre in world coordinates, -Rᵀ t: (*, 3)."""
        return -(self.R.transpose(-1, -2) @ self.t[..., None]).squeeze(-1)

    def world_to_camera(self, X: Tensor) -> Tensor:
        """World points (*, N, 3) -> camera-frame points (*, N, 3)."""
        return X @ self.R.transpose(-1, -2) + self.t[..., None, :]

    def project(self, X: Tensor) -> Tensor:
        """World points (*, N, 3) -> observed (distorted) pixels (*, N, 2)."""
        x_n = from_homogeneous(self.world_to_camera(X))
        return normalized_to_pixels(distort_normalized(x_n, self.distortion), self.K)
