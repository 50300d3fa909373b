"""Zhang's planar calibration (thesis Appendix A; Zhang 2000), with the ERRATA's u0.

Per view, the homography H from the board plane (Z = 0) to the image: the normalized DLT, then LM
on the reprojection error (eq. A.3–A.4). Each H = λ K [r1 r2 t] gives two linear constraints on
B = K⁻ᵀK⁻¹ (eq. A.5–A.6); their null vector gives K in closed form (eq. A.7) and each view's pose
(eq. A.8). Finally one LM over fx, fy, cx, cy, k1, k2 and every pose minimizes the reprojection
error of all corners (the eq. A.8 cost with the radial model of :mod:`torchsfm.camera`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
from torch import Tensor

from torchsfm.camera import distort_normalized, from_homogeneous, to_homogeneous
from torchsfm.config import CalibrationConfig, LMConfig
from torchsfm.errors import DegenerateConfigurationError, InputError, NotEnoughDataError
from torchsfm.geometry.homography import homography_dlt
from torchsfm.geometry.normalization import hartley_normalize
from torchsfm.geometry.rotation import axis_angle_to_rotation, nearest_rotation, rotation_to_axis_angle
from torchsfm.optim.lm import levenberg_marquardt
from torchsfm.validation import check_finite, check_floating, check_shapes


@dataclass
class Calibration:
    """Result of :func:`calibrate_camera` for V views.

    Fields:
        K: (3, 3) intrinsics. distortion: (2,) radial (k1, k2) on normalized coordinates.
        R, t: (V, 3, 3), (V, 3) board-to-camera poses (board units, e.g. millimetres).
        view_rms: (V,) RMS reprojection error per view, pixels. rms: over all corners, pixels.
    """

    K: Tensor
    distortion: Tensor
    R: Tensor
    t: Tensor
    view_rms: Tensor
    rms: float


def board_points(pattern: tuple[int, int], square: float) -> Tensor:
    """Inner corners of a (cols, rows) board on its plane, row by row: (cols * rows, 2) float64."""
    cols, rows = pattern
    if cols < 1 or rows < 1:
        raise InputError(f"a board pattern needs at least one corner per row and column, got {cols}x{rows}")
    if not math.isfinite(square) or square <= 0:
        raise InputError(f"the board's square size must be a finite positive length, got {square}")
    j, i = torch.meshgrid(torch.arange(rows, dtype=torch.float64), torch.arange(cols, dtype=torch.float64), indexing="ij")
    return square * torch.stack([i, j], dim=-1).reshape(-1, 2)


def _apply(H: Tensor, x: Tensor) -> Tensor:
    return from_homogeneous(to_homogeneous(x) @ H.transpose(-1, -2))


def view_homographies(board: Tensor, image_points: Tensor, lm: LMConfig) -> Tensor:
    """Board plane → image homographies (V, 3, 3), h33 = 1: normalized DLT, then LM on the
    reprojection error (eq. A.3–A.4), all views at once."""
    V = image_points.shape[0]
    H = homography_dlt(board.expand(V, -1, -1), image_points)
    H = H / H[:, 2:, 2:]

    def residuals(h: Tensor) -> Tensor:
        matrices = torch.cat([h, torch.ones_like(h[:, :1])], dim=-1).reshape(V, 3, 3)
        return (_apply(matrices, board.expand(V, -1, -1)) - image_points).flatten(1)

    refined = levenberg_marquardt(residuals, H.flatten(1)[:, :8], lm).params
    return torch.cat([refined, torch.ones_like(refined[:, :1])], dim=-1).reshape(V, 3, 3)


def _constraint(H: Tensor, i: int, j: int) -> Tensor:
    """v_ij of eq. A.6 for homographies (V, 3, 3): (V, 6)."""
    a, b = H[..., :, i], H[..., :, j]
    return torch.stack([a[..., 0] * b[..., 0], a[..., 0] * b[..., 1] + a[..., 1] * b[..., 0], a[..., 1] * b[..., 1],
                        a[..., 2] * b[..., 0] + a[..., 0] * b[..., 2], a[..., 2] * b[..., 1] + a[..., 1] * b[..., 2],
                        a[..., 2] * b[..., 2]], dim=-1)


def intrinsics_from_homographies(H: Tensor, T: Tensor | None = None) -> Tensor:
    """K (3, 3) in closed form (eq. A.5–A.7) from V >= 3 homographies (V, 3, 3).

    With T (3, 3), a similarity normalizing the image points (Hartley), the system is solved for
    T K and K mapped back (conditioning). Raises DegenerateConfigurationError when the views do
    not constrain K: boards all parallel to each other (or to the image) leave B's null space
    more than one-dimensional.
    """
    T = torch.eye(3, dtype=H.dtype) if T is None else T
    Hn = T @ H
    Hn = Hn / Hn.flatten(-2).norm(dim=-1)[:, None, None]
    A = torch.cat([_constraint(Hn, 0, 1), _constraint(Hn, 0, 0) - _constraint(Hn, 1, 1)])  # (2V, 6)
    _, sigma, Vh = torch.linalg.svd(A)
    if float(sigma[-2]) < 10 * float(sigma[-1]) or float(sigma[-2]) < 1e-9 * float(sigma[0]):
        raise DegenerateConfigurationError(
            "the board views do not determine K: they are (nearly) parallel to each other; tilt the board "
            f"differently in each photo (singular values of Zhang's system: {sigma[-2]:.2e}, {sigma[-1]:.2e})")
    B11, B12, B22, B13, B23, B33 = Vh[-1].tolist()
    if B11 < 0:  # b is defined up to sign: B must be positive definite
        B11, B12, B22, B13, B23, B33 = -B11, -B12, -B22, -B13, -B23, -B33
    denominator = B11 * B22 - B12**2
    no_real_K = DegenerateConfigurationError("Zhang's closed form gives no real K: the views are degenerate or too noisy")
    if B11 <= 0 or denominator <= 0:
        raise no_real_K
    v0 = (B12 * B13 - B11 * B23) / denominator
    lam = B33 - (B13**2 + v0 * (B12 * B13 - B11 * B23)) / B11
    if lam / B11 <= 0:
        raise no_real_K
    alpha = math.sqrt(lam / B11)
    beta = math.sqrt(lam * B11 / denominator)
    gamma = -B12 * alpha**2 * beta / lam
    u0 = gamma * v0 / beta - B13 * alpha**2 / lam  # ERRATA: not w0 / beta
    K = torch.tensor([[alpha, gamma, u0], [0.0, beta, v0], [0.0, 0.0, 1.0]], dtype=torch.float64)
    K = torch.linalg.inv(T) @ K
    return K / K[2, 2]


def extrinsics_from_homographies(K: Tensor, H: Tensor) -> tuple[Tensor, Tensor]:
    """Poses (eq. A.8) from K and homographies (V, 3, 3): R (V, 3, 3) (nearest rotation), t (V, 3)."""
    M = torch.linalg.inv(K) @ H
    scale = 1 / M[:, :, 0].norm(dim=-1)
    scale = torch.where(M[:, 2, 2] * scale < 0, -scale, scale)  # the board in front: t_z > 0
    r1, r2, t = (M * scale[:, None, None]).unbind(-1)
    R = nearest_rotation(torch.stack([r1, r2, torch.linalg.cross(r1, r2)], dim=-1))
    return R, t


def project_board(K: Tensor, distortion: Tensor, R: Tensor, t: Tensor, board: Tensor) -> Tensor:
    """Pixels (V, N, 2) of board points (N, 2) under poses (V, ...), K (3, 3) and (k1, k2)."""
    X = torch.cat([board, torch.zeros_like(board[:, :1])], dim=-1)
    camera = X @ R.transpose(-1, -2) + t[:, None]
    x = distort_normalized(from_homogeneous(camera), distortion)
    return x @ K[:2, :2].T + K[:2, 2]


def _unpack(params: Tensor, V: int) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    fx, fy, cx, cy, k1, k2 = params[:6].unbind()
    zero, one = torch.zeros_like(fx), torch.ones_like(fx)
    K = torch.stack([torch.stack([fx, zero, cx]), torch.stack([zero, fy, cy]), torch.stack([zero, zero, one])])
    poses = params[6:].reshape(V, 6)
    return K, torch.stack([k1, k2]), axis_angle_to_rotation(poses[:, :3]), poses[:, 3:]


def calibrate_camera(board: Tensor, image_points: Tensor, config: CalibrationConfig | None = None) -> Calibration:
    """Zhang's calibration from V views of a planar target.

    Args:
        board: (N, 2) target points on its plane (e.g. :func:`board_points`), float64.
        image_points: (V, N, 2) their detected pixels in each view, V >= ``config.min_views``.
        config: LM settings, minimum views, zero skew.

    Returns:
        A :class:`Calibration`.

    Raises:
        ShapeError, InputError: malformed input. NotEnoughDataError: too few views or points.
        DegenerateConfigurationError: views that do not determine K (boards all parallel).
    """
    config = config or CalibrationConfig()
    sizes = check_shapes(board=(board, "N 2"), image_points=(image_points, "V N 2"))
    check_floating(board=board, image_points=image_points)
    check_finite(board=board, image_points=image_points)
    if sizes["V"] < config.min_views:
        raise NotEnoughDataError(f"calibration needs at least {config.min_views} views of the board, got {sizes['V']}")
    if sizes["N"] < 4:
        raise NotEnoughDataError(f"a view needs at least 4 board points, got {sizes['N']}")
    board, image_points = board.double(), image_points.double()
    spread = torch.linalg.svdvals(board - board.mean(0))  # (2,): the board's extent along its two axes
    if float(spread[1]) <= 1e-9 * float(spread[0]):
        raise DegenerateConfigurationError("the board points are collinear (one row or column): a plane's homography needs a 2-D target")
    V = sizes["V"]
    H = view_homographies(board, image_points, config.lm)
    if not bool(torch.isfinite(H).all()):
        raise DegenerateConfigurationError("a view's board points do not determine its homography (collinear or coincident in the image)")
    K = intrinsics_from_homographies(H, hartley_normalize(image_points.reshape(-1, 2))[1])
    if config.zero_skew:
        K[0, 1] = 0.0
    R, t = extrinsics_from_homographies(K, H)
    initial = torch.cat([torch.stack([K[0, 0], K[1, 1], K[0, 2], K[1, 2]]), torch.zeros(2, dtype=torch.float64),
                         torch.cat([rotation_to_axis_angle(R), t], dim=-1).flatten()])

    def residuals(params: Tensor) -> Tensor:  # (1, S) -> (1, 2 V N)
        K_, distortion, R_, t_ = _unpack(params[0], V)
        return (project_board(K_, distortion, R_, t_, board) - image_points).reshape(1, -1)

    params = levenberg_marquardt(residuals, initial[None], config.lm).params[0]
    K, distortion, R, t = _unpack(params, V)
    errors = (project_board(K, distortion, R, t, board) - image_points).square().sum(-1)  # (V, N)
    return Calibration(K=K, distortion=distortion, R=R, t=t, view_rms=errors.mean(-1).sqrt(), rms=float(errors.mean().sqrt()))
