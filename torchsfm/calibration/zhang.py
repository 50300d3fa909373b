"""Zhang's planar calibration (thesis Appendix A; Zhang 2000), with the ERRATA's u0.

Per view, the homography H from the board plane (Z = 0) to the image: the normalized DLT, then LM
on the reprojection error (eq. A.3–A.4). Each H = λ K [r1 r2 t] gives two linear constraints on
B = K⁻ᵀK⁻¹ (eq. A.5–A.6); their null vector gives K in closed form (eq. A.7) and each view's pose
(eq. A.8). Finally one LM over fx, fy, cx, cy, k1, k2 and every pose minimizes the reprojection
error of all corners (the eq. A.8 cost with the radial model of :mod:`torchsfm.camera`). Both LMs
use analytic Jacobians (each pose's rotation updated on the manifold, R ← exp([ω]x) R).
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
from torchsfm.geometry.rotation import axis_angle_to_rotation, nearest_rotation, skew
from torchsfm.inference import without_autograd
from torchsfm.optim.lm import levenberg_marquardt
from torchsfm.validation import check_finite, check_floating, check_shapes, lie_on_one_line


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


def view_homographies(board: Tensor, image_points: Tensor, lm: LMConfig) -> Tensor:
    """Board plane → image homographies (V, 3, 3), h33 = 1: normalized DLT, then LM on the
    reprojection error (eq. A.3–A.4), all views at once."""
    V = image_points.shape[0]
    H = homography_dlt(board.expand(V, -1, -1), image_points)
    H = H / H[:, 2:, 2:]

    points = to_homogeneous(board)  # (N, 3)

    def residuals(h: Tensor) -> Tensor:
        return (_map_board(h, points)[1] - image_points).flatten(1)

    refined = levenberg_marquardt(residuals, H.flatten(1)[:, :8], lm, jacobian=lambda h: _homography_jacobian(h, points)).params
    return torch.cat([refined, torch.ones_like(refined[:, :1])], dim=-1).reshape(V, 3, 3)


def _map_board(h: Tensor, points: Tensor) -> tuple[Tensor, Tensor]:
    """Homographies (V, 8) (h33 = 1) applied to homogeneous board points (N, 3) -> (V, N, 3)
    q = H p and (V, N, 2) pixels q1 / q3, q2 / q3."""
    q = points @ torch.cat([h, torch.ones_like(h[:, :1])], dim=-1).reshape(-1, 3, 3).transpose(-1, -2)
    return q, q[..., :2] / q[..., 2:]


def _homography_jacobian(h: Tensor, points: Tensor) -> Tensor:
    """d pixels / d(h11 .. h32) of :func:`_map_board`: (V, 2N, 8), rows in the order of the
    (V, N, 2) pixels (u = q1 / q3: p / q3 on h11..h13, -u p / q3 on h31, h32; v likewise)."""
    q, pixels = _map_board(h, points)
    scaled = points / q[..., 2:]  # (V, N, 3): p / q3
    zeros = torch.zeros_like(scaled)
    du = torch.cat([scaled, zeros, -pixels[..., :1] * scaled[..., :2]], dim=-1)  # (V, N, 8)
    dv = torch.cat([zeros, scaled, -pixels[..., 1:] * scaled[..., :2]], dim=-1)
    return torch.stack([du, dv], dim=2).flatten(1, 2)


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
    """The state (6 + 12 V,) = fx, fy, cx, cy, k1, k2, then every view's R (9) and t (3) ->
    K (3, 3), (k1, k2), R (V, 3, 3), t (V, 3)."""
    fx, fy, cx, cy, k1, k2 = params[:6].unbind()
    zero, one = torch.zeros_like(fx), torch.ones_like(fx)
    K = torch.stack([torch.stack([fx, zero, cx]), torch.stack([zero, fy, cy]), torch.stack([zero, zero, one])])
    poses = params[6:].reshape(V, 12)
    return K, torch.stack([k1, k2]), poses[:, :9].reshape(V, 3, 3), poses[:, 9:]


def _retract(params: Tensor, delta: Tensor) -> Tensor:
    """(1, 6 + 12 V) state after a (1, 6 + 6 V) step: intrinsics and t added, each R ← exp([ω]x) R."""
    V = (params.shape[1] - 6) // 12
    poses, steps = params[0, 6:].reshape(V, 12), delta[0, 6:].reshape(V, 6)
    R = axis_angle_to_rotation(steps[:, :3]) @ poses[:, :9].reshape(V, 3, 3)
    return torch.cat([params[0, :6] + delta[0, :6], torch.cat([R.flatten(1), poses[:, 9:] + steps[:, 3:]], -1).flatten()])[None]


def _projection_jacobian(K: Tensor, distortion: Tensor, R: Tensor, t: Tensor, board: Tensor) -> Tensor:
    """d pixels / d step of :func:`project_board` for :func:`_retract`'s steps: (V N 2, 6 + 6 V),
    rows in the order of the (V, N, 2) pixels. With Y = R X + t, (a, b) = (Y1, Y2) / Y3,
    d = 1 + k1 r² + k2 r⁴ (r² = a² + b²) and u = fx a d + cx, v = fy b d + cy: the intrinsics'
    columns directly, then d(u, v)/d(a, b) · d(a, b)/dY · dY/d(ω, t), where dY/dω = -[R X]x
    (the step turns the board about the camera's origin) and dY/dt = I."""
    V, N = R.shape[0], board.shape[0]
    X = torch.cat([board, torch.zeros_like(board[:, :1])], dim=-1)
    turned = X @ R.transpose(-1, -2)  # (V, N, 3): R X
    Y = turned + t[:, None]
    a, b = Y[..., 0] / Y[..., 2], Y[..., 1] / Y[..., 2]
    r2 = a * a + b * b
    k1, k2 = distortion[0], distortion[1]
    d = 1 + k1 * r2 + k2 * r2 * r2
    slope = 2 * (k1 + 2 * k2 * r2)  # d(d)/d(r²) times 2: d(d)/da = slope a
    fx, fy = K[0, 0], K[1, 1]
    zero, one = torch.zeros_like(a), torch.ones_like(a)
    du = torch.stack([a * d, zero, one, zero, fx * a * r2, fx * a * r2 * r2], -1)  # (V, N, 6): fx, fy, cx, cy, k1, k2
    dv = torch.stack([zero, b * d, zero, one, fy * b * r2, fy * b * r2 * r2], -1)
    intrinsics = torch.stack([du, dv], dim=2)  # (V, N, 2, 6)
    d_ab = torch.stack([torch.stack([fx * (d + slope * a * a), fx * slope * a * b], -1),
                        torch.stack([fy * slope * a * b, fy * (d + slope * b * b)], -1)], dim=-2)  # (V, N, 2, 2)
    inverse_depth = 1 / Y[..., 2]
    d_Y = torch.stack([torch.stack([inverse_depth, zero, -a * inverse_depth], -1),
                       torch.stack([zero, inverse_depth, -b * inverse_depth], -1)], dim=-2)  # (V, N, 2, 3)
    chain = d_ab @ d_Y  # (V, N, 2, 3): d pixels / dY
    pose = torch.cat([chain @ -skew(turned), chain], dim=-1)  # (V, N, 2, 6): ω, t
    poses = pose.new_zeros(V, N, 2, V, 6)  # a view's rows depend on its own pose only
    view = torch.arange(V, device=R.device)
    poses[view, :, :, view] = pose
    return torch.cat([intrinsics, poses.flatten(-2)], dim=-1).reshape(V * N * 2, 6 + 6 * V)


@without_autograd
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
    if bool(lie_on_one_line(board, 1e-9)):
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
                         torch.cat([R.flatten(1), t], dim=-1).flatten()])

    def residuals(params: Tensor) -> Tensor:  # (1, S) -> (1, 2 V N)
        K_, distortion, R_, t_ = _unpack(params[0], V)
        return (project_board(K_, distortion, R_, t_, board) - image_points).reshape(1, -1)

    def jacobian(params: Tensor) -> Tensor:  # (1, S) -> (1, 2 V N, 6 + 6 V)
        return _projection_jacobian(*_unpack(params[0], V), board)[None]

    params = levenberg_marquardt(residuals, initial[None], config.lm, retract=_retract, tangent_dim=6 + 6 * V,
                                 jacobian=jacobian).params[0]
    K, distortion, R, t = _unpack(params, V)
    errors = (project_board(K, distortion, R, t, board) - image_points).square().sum(-1)  # (V, N)
    return Calibration(K=K, distortion=distortion, R=R, t=t, view_rms=errors.mean(-1).sqrt(), rms=float(errors.mean().sqrt()))
