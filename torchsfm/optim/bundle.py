"""Sparse bundle adjustment (thesis Appendix D, after Lourakis & Argyros) on the one LM.

The normal equations of a bundle problem have the arrow shape [[U, W], [Wᵀ, V]] with U block
diagonal over cameras and V block diagonal (3x3) over points. Each damped step eliminates the
points by the Schur complement — the per-point blocks V* are inverted as one batch — solves the
reduced camera system S δc = g_c - W V*⁻¹ g_p (dense Cholesky when small, conjugate gradients
with a block-Jacobi preconditioner when large) and back-substitutes δp. The iteration itself
(Nielsen damping, acceptance, stopping) is :func:`torchsfm.optim.lm.minimize`.

Camera models:

* ``pinhole`` — torchsfm's calibrated camera: pixels = K (R X + t) dehomogenized, K fixed;
  6 parameters per camera (a rotation increment R ← exp([ω]x) R, and t). With
  ``shared_intrinsics`` one K common to every camera is adjusted too — the named ones of
  ``f`` (fx and fy together: square pixels), ``fx``, ``fy``, ``cx``, ``cy`` and the radial
  coefficient ``k1`` (pixels = K x_n (1 + k1 |x_n|²), x_n = (X/Z, Y/Z); ``radial``, 0 unless
  given or adjusted): m ≤ 5 global parameters, a border on the reduced camera system (the camera
  solve gets m more right-hand sides and an m×m Schur complement gives the intrinsics' step).
* ``bal`` — Bundle Adjustment in the Large: P = R X + t, p = -P_xy / P_z,
  x = f (1 + k1 |p|² + k2 |p|⁴) p; 9 parameters per camera (ω, t, f, k1, k2).

Optional robust losses (Huber, Cauchy) reweight observations (iteratively reweighted least
squares). Gauge: cameras can be held fixed (``fixed_cameras``); the pipeline fixes the first
camera and lets the damping absorb the remaining scale freedom.
"""

from __future__ import annotations

import copy
import time
from dataclasses import dataclass, field

import torch
from torch import Tensor

from torchsfm.config import BundleAdjustmentConfig
from torchsfm.errors import InputError
from torchsfm.geometry.rotation import axis_angle_to_rotation
from torchsfm.inference import without_autograd
from torchsfm.optim.lm import minimize
from torchsfm.validation import check_finite, check_floating, check_shapes
from torchsfm.numerics import floor_tiny

CAMERA_DOF = {"pinhole": 6, "bal": 9}
DENSE_BUFFER_BYTES = 2**29  # the dense solver's GEMM path holds two (3 P, C dc) buffers only up to this size
BLOCK_CHUNK_NUMBERS = 2**22  # its block path forms the camera-pair blocks of this many numbers at a time (32 MiB)
BLOCK_NUMBER_FLOPS = 100  # measured: forming and adding one number of a camera-pair block costs about this many GEMM flops
ROTATION_TOLERANCE = 1e-5  # largest |RᵀR − I| entry: a rotation written with 6 significant digits passes, a scaled one does not
INTRINSIC_PARAMETERS = {"f": (1.0, 1.0, 0.0, 0.0, 0.0), "fx": (1.0, 0.0, 0.0, 0.0, 0.0), "fy": (0.0, 1.0, 0.0, 0.0, 0.0),
                        "cx": (0.0, 0.0, 1.0, 0.0, 0.0), "cy": (0.0, 0.0, 0.0, 1.0, 0.0),
                        "k1": (0.0, 0.0, 0.0, 0.0, 1.0)}  # each one's direction in (fx, fy, cx, cy, k1)


@dataclass
class BundleProblem:
    """Cameras, points and observations (float64).

    Fields:
        camera_model: ``pinhole`` or ``bal``.
        rotations: (C, 3, 3) camera from world; translations: (C, 3).
        intrinsics: ``pinhole``: K (C, 3, 3), held fixed unless ``shared_intrinsics``; ``bal``:
            (C, 3) = (f, k1, k2), adjusted.
        points: (P, 3) world points.
        camera_index, point_index: (O,) int64 of each observation.
        observations: (O, 2) measured image coordinates.
        fixed_cameras: (C,) bool, cameras held fixed (gauge); none by default.
        shared_intrinsics: ``pinhole`` only: every camera has the same K (zero skew), and these
            of its parameters are adjusted with the cameras and points (names of
            ``INTRINSIC_PARAMETERS``; ``f`` keeps fx / fy as they are).
        radial: ``pinhole`` only: the radial coefficient k1 every camera shares (normalized
            coordinates; 0: none); adjusted where ``shared_intrinsics`` names ``k1``.
    """

    camera_model: str
    rotations: Tensor
    translations: Tensor
    intrinsics: Tensor
    points: Tensor
    camera_index: Tensor
    point_index: Tensor
    observations: Tensor
    fixed_cameras: Tensor | None = None
    shared_intrinsics: tuple[str, ...] = ()
    radial: float = 0.0

    def __post_init__(self) -> None:
        if self.camera_model not in CAMERA_DOF:
            raise InputError(f"camera_model must be one of {', '.join(CAMERA_DOF)}, got {self.camera_model!r}")
        intrinsics_spec = "C 3 3" if self.camera_model == "pinhole" else "C 3"
        check_shapes(rotations=(self.rotations, "C 3 3"), translations=(self.translations, "C 3"),
                     intrinsics=(self.intrinsics, intrinsics_spec), points=(self.points, "P 3"),
                     camera_index=(self.camera_index, "O"), point_index=(self.point_index, "O"),
                     observations=(self.observations, "O 2"))
        floating = dict(rotations=self.rotations, translations=self.translations, intrinsics=self.intrinsics,
                        points=self.points, observations=self.observations)
        check_floating(**floating)
        if len({x.dtype for x in floating.values()}) > 1:
            raise InputError("rotations, translations, intrinsics, points and observations must share one dtype, got "
                             + ", ".join(f"{name} {x.dtype}" for name, x in floating.items()))
        check_finite(**floating)
        for name, index in (("camera_index", self.camera_index), ("point_index", self.point_index)):
            if index.dtype.is_floating_point or index.dtype.is_complex or index.dtype == torch.bool:
                raise InputError(f"{name} must be an integer tensor, got {index.dtype}")
        C, P = self.rotations.shape[0], self.points.shape[0]
        gram = self.rotations.transpose(-1, -2) @ self.rotations - torch.eye(3, dtype=self.rotations.dtype, device=self.rotations.device)
        improper = (gram.abs().amax((-2, -1)) > ROTATION_TOLERANCE) | (torch.linalg.det(self.rotations) <= 0)  # (C,)
        if bool(improper.any()):
            raise InputError(f"rotations[{int(improper.nonzero()[0, 0])}] is not a rotation matrix "
                             f"(RᵀR = I within {ROTATION_TOLERANCE:g}, det R = +1)")
        if self.camera_index.numel() and (int(self.camera_index.min()) < 0 or int(self.camera_index.max()) >= C):
            raise InputError(f"camera_index must lie in [0, {C})")
        if self.point_index.numel() and (int(self.point_index.min()) < 0 or int(self.point_index.max()) >= P):
            raise InputError(f"point_index must lie in [0, {P})")
        if self.fixed_cameras is None:
            self.fixed_cameras = torch.zeros(C, dtype=torch.bool, device=self.points.device)
        check_shapes(rotations=(self.rotations, "C 3 3"), fixed_cameras=(self.fixed_cameras, "C"))
        if self.fixed_cameras.dtype != torch.bool:
            raise InputError(f"fixed_cameras must be a bool tensor (True: held fixed), got {self.fixed_cameras.dtype}")
        names = self.shared_intrinsics
        if any(name not in INTRINSIC_PARAMETERS for name in names) or len(set(names)) < len(names) or ("f" in names and ({"fx", "fy"} & set(names))):
            raise InputError(f"shared_intrinsics must name distinct ones of {', '.join(INTRINSIC_PARAMETERS)} (f or fx / fy), got {names}")
        if names and (self.camera_model != "pinhole" or not bool((self.intrinsics == self.intrinsics[:1]).all())
                      or float(self.intrinsics[0, 0, 1]) != 0):
            raise InputError("shared_intrinsics needs the pinhole model and one K without skew for every camera")
        if self.radial and self.camera_model != "pinhole":
            raise InputError("radial is the pinhole model's (BAL cameras carry their own k1, k2)")

    @property
    def num_cameras(self) -> int:
        return self.rotations.shape[0]

    @property
    def num_points(self) -> int:
        return self.points.shape[0]

    def depths(self) -> Tensor:
        """Depth of every observation's point in its camera (positive = in front): (O,)."""
        z = _camera_points(self, self.rotations, self.translations, self.points)[2][2]
        return z if self.camera_model == "pinhole" else -z  # BAL cameras look down -z

    def select_points(self, keep: Tensor) -> BundleProblem:
        """A copy with only the points where ``keep`` (P,) holds, their observations, re-indexed."""
        new_index = torch.full((self.num_points,), -1, dtype=torch.long, device=keep.device)
        new_index[keep] = torch.arange(int(keep.sum()), device=keep.device)
        observed = keep[self.point_index]
        return BundleProblem(self.camera_model, self.rotations, self.translations, self.intrinsics, self.points[keep],
                             self.camera_index[observed], new_index[self.point_index[observed]],
                             self.observations[observed], self.fixed_cameras, self.shared_intrinsics, self.radial)

    def residuals(self) -> Tensor:
        """Predicted minus observed coordinates: (O, 2)."""
        return _project(self, self.rotations, self.translations, self.intrinsics, self.points, radial=self.radial)[0] - self.observations

    def cost(self) -> float:
        """½ Σ ‖r‖² (pixels²)."""
        return float(0.5 * self.residuals().square().sum())

    def robust_cost(self, loss: str, scale: float) -> float:
        """Σ ρ(‖r‖²) with a robust ``loss`` (``none``, ``huber``, ``cauchy``) at ``scale`` pixels (pixels²)."""
        return float(_loss(self.residuals().square().sum(-1), loss, scale)[0].sum())


@dataclass
class BundleResult:
    """Outcome of :func:`bundle_adjust`: the adjusted problem and ½ Σ ‖r‖² before and after;
    ``status`` is ``converged``, ``stalled`` (no step decreased the cost any more), ``failed``
    (the initial cost was not finite) or ``max_iterations``."""

    problem: BundleProblem
    initial_cost: float
    final_cost: float
    num_iterations: int
    converged: bool
    status: str = "converged"
    timings: dict[str, float] = field(default_factory=dict)


def _products(A: Tensor, B: Tensor) -> Tensor:
    """One small matrix product per observation, coordinate-major: A (a, k, O), B (k, b, O) ->
    (a, b, O) with [:, :, o] = A[:, :, o] B[:, :, o]; k multiply-adds, each along the O
    observations (a batched GEMM of O blocks of 2 or 3 rows ran 4-8x slower)."""
    out = A[:, 0, None] * B[0, None]
    for k in range(1, A.shape[1]):
        out.addcmul_(A[:, k, None], B[k, None])
    return out


def _camera_points(problem: BundleProblem, R: Tensor, t: Tensor, points: Tensor) -> tuple[Tensor, Tensor, Tensor]:
    """Every observation's camera rotation (3, 3, O), its point rotated into the camera, R X
    (3, O), and the point in the camera frame, R X + t (3, O): coordinate-major."""
    c, p = problem.camera_index, problem.point_index
    rotation = R.reshape(-1, 9).T[:, c].reshape(3, 3, -1)
    X = points.T[:, p]
    rotated = _products(rotation, X[:, None])[:, 0]
    return rotation, rotated, rotated + t.T[:, c]


def _project(problem: BundleProblem, R: Tensor, t: Tensor, intrinsics: Tensor, points: Tensor, jacobians: bool = False,
             radial: Tensor | float = 0.0):
    """Predictions (O, 2) and, on request, d prediction / d(camera tangent) (2, dc, O) and
    d prediction / d point (2, 3, O): the derivatives coordinate-major, row i of an
    observation's 2 × n block in [i, :, o] (see :func:`_products`); ``radial``: the pinhole
    cameras' shared k1 (a 0-d tensor while it is adjusted)."""
    c = problem.camera_index
    rotation, rotated, camera_point = _camera_points(problem, R, t, points)
    inverse_z = 1 / camera_point[2]
    zero = torch.zeros_like(inverse_z)
    if problem.camera_model == "pinhole":
        fx, shear, cx, fy, cy = intrinsics.reshape(-1, 9)[:, [0, 1, 2, 4, 5]].T[:, c]
        normalized = camera_point[:2] * inverse_z  # (2, O)
        distorted = isinstance(radial, Tensor) or radial != 0
        if distorted:
            r2 = normalized[0].square() + normalized[1].square()
            seen = normalized * (1 + radial * r2)
        else:
            seen = normalized
        prediction = torch.stack([fx * seen[0] + shear * seen[1] + cx, fy * seen[1] + cy], dim=-1)
        if not jacobians:
            return prediction, None, None
        d_normalized = torch.stack([torch.stack([inverse_z, zero, -normalized[0] * inverse_z]),
                                    torch.stack([zero, inverse_z, -normalized[1] * inverse_z])])  # (2, 3, O)
        if distorted:  # d seen / d normalized = (1 + k1 r²) I + 2 k1 n nᵀ
            outer = 2 * radial * normalized[:, None] * normalized[None]  # (2, 2, O)
            d_seen = outer + (1 + radial * r2) * torch.eye(2, dtype=r2.dtype, device=r2.device)[..., None]
            d_normalized = _products(d_seen, d_normalized)
        d_camera_point = torch.stack([fx * d_normalized[0] + shear * d_normalized[1], fy * d_normalized[1]])  # K₂ₓ₂ · (2, 3, O)
        d_intrinsics = d_camera_point[:, :0]
    else:
        f, k1, k2 = intrinsics.T[:, c]
        projected = -camera_point[:2] * inverse_z  # (2, O)
        r2 = projected[0].square() + projected[1].square()
        distortion = 1 + k1 * r2 + k2 * r2 * r2
        prediction = ((f * distortion) * projected).T
        if not jacobians:
            return prediction, None, None
        d_projected = torch.stack([torch.stack([-inverse_z, zero, -projected[0] * inverse_z]),
                                   torch.stack([zero, -inverse_z, -projected[1] * inverse_z])])  # (2, 3, O)
        outer = (2 * k1 + 4 * k2 * r2) * projected[:, None] * projected[None]  # (2, 2, O)
        d_prediction = f * (outer + distortion * torch.eye(2, dtype=r2.dtype, device=r2.device)[..., None])
        d_camera_point = _products(d_prediction, d_projected)
        d_intrinsics = torch.stack([distortion, f * r2, f * r2 * r2])[None] * projected[:, None]  # d / d(f, k1, k2): (2, 3, O)
    # δω (left): d camera point = δω × R X, so row m of d_camera_point gives (R X × m)ᵀ; δt: the identity
    d_rotation = torch.linalg.cross(rotated.expand_as(d_camera_point), d_camera_point, dim=1)
    d_camera = torch.cat([d_rotation, d_camera_point, d_intrinsics], dim=1)
    return prediction, d_camera, _products(d_camera_point, rotation)


def _loss(squared: Tensor, kind: str, scale: float) -> tuple[Tensor, Tensor]:
    """ρ(s) and ρ'(s) of the robust loss on squared residual norms s (O,)."""
    if kind == "huber":
        inside = squared <= scale**2
        root = floor_tiny(squared).sqrt()
        return torch.where(inside, squared, 2 * scale * root - scale**2), torch.where(inside, 1.0, scale / root)
    if kind == "cauchy":
        return scale**2 * torch.log1p(squared / scale**2), 1 / (1 + squared / scale**2)
    return squared, torch.ones_like(squared)


class _SchurLinearization:
    """The arrow-shaped normal equations at one point of a bundle problem (batch of one)."""

    def __init__(self, problem: "_BundleLM", d_camera: Tensor, d_point: Tensor, residuals: Tensor, weights: Tensor,
                 d_intrinsics: Tensor | None = None) -> None:
        """The blocks from the coordinate-major derivatives of :func:`_project` — d_camera
        (2, dc, O), d_point (2, 3, O), the shared intrinsics' d_intrinsics (2, m, O) — the (O, 2)
        residuals and the (O,) loss weights. W and Y (:meth:`_camera_system`) stay
        coordinate-major, (dc, 3, O)."""
        self.problem = problem
        bundle = problem.bundle
        root = weights.sqrt()
        Jc = d_camera * (problem.free_observations * root)  # fixed cameras: no columns
        Jp, r = d_point * root, residuals.T * root  # (2, 3, O), (2, O)
        C, P, dc = bundle.num_cameras, bundle.num_points, problem.dc
        c, p = bundle.camera_index, bundle.point_index
        Jc_t, Jp_t = Jc.transpose(0, 1), Jp.transpose(0, 1)  # (dc, 2, O), (3, 2, O): left factors of _products
        # U: one GEMM per camera over its observations' 2 rows each (columns in camera order)
        by_camera = Jc[:, :, problem.camera_order].permute(1, 2, 0).reshape(dc, -1)
        self.U = torch.stack([columns @ columns.T for columns in torch.split(by_camera, problem.camera_rows, dim=1)])
        self.V = torch.zeros(P, 9, dtype=r.dtype, device=r.device).index_add_(0, p, _products(Jp_t, Jp).reshape(9, -1).T).reshape(P, 3, 3)
        self.W = _products(Jc_t, Jp)  # (dc, 3, O)
        g_camera = torch.zeros(C, dc, dtype=r.dtype, device=r.device).index_add_(0, c, -_products(Jc_t, r[:, None])[:, 0].T)
        g_point = torch.zeros(P, 3, dtype=r.dtype, device=r.device).index_add_(0, p, -_products(Jp_t, r[:, None])[:, 0].T)
        self.gradient = torch.cat([g_camera.flatten(), g_point.flatten()])[None]
        self.diagonal = torch.cat([torch.diagonal(self.U, dim1=1, dim2=2).flatten(), torch.diagonal(self.V, dim1=1, dim2=2).flatten()])[None]
        self.border = None
        if d_intrinsics is not None:  # the shared intrinsics' blocks: with the cameras, the points, themselves
            Jk = d_intrinsics * root  # (2, m, O)
            m = Jk.shape[1]
            E = torch.zeros(C, dc, m, dtype=r.dtype, device=r.device).index_add_(0, c, _products(Jc_t, Jk).permute(2, 0, 1))
            Wk = torch.zeros(P, m, 3, dtype=r.dtype, device=r.device).index_add_(0, p, _products(Jk.transpose(0, 1), Jp).permute(2, 0, 1))
            G = Jk[0] @ Jk[0].T + Jk[1] @ Jk[1].T
            g_k = -_products(Jk.transpose(0, 1), r[:, None])[:, 0].sum(-1)
            self.border = (E, Wk, G)
            self.gradient = torch.cat([self.gradient, g_k[None]], dim=1)
            self.diagonal = torch.cat([self.diagonal, torch.diagonal(G)[None]], dim=1)

    def _camera_system(self, damping: Tensor) -> tuple[Tensor, Tensor, Tensor, Tensor, Tensor] | None:
        """The points eliminated and the reduced camera system solved, at (S,) ``damping``: the
        cameras' right-hand side (C, dc) — with the intrinsics' border, (C, dc, 1 + m) holding
        S_ck too — its solution S_cc⁻¹ of the same shape, whether that worked, (P, 3, 3) V*⁻¹ and
        the (P, 3) points' gradient; None where a point block is singular."""
        problem, bundle = self.problem, self.problem.bundle
        C, P, dc = bundle.num_cameras, bundle.num_points, problem.dc
        U = self.U + torch.diag_embed(damping[: C * dc].reshape(C, dc))
        V = self.V + torch.diag_embed(damping[C * dc:C * dc + 3 * P].reshape(P, 3))
        L, info = torch.linalg.cholesky_ex(V)
        if bool((info != 0).any()):
            return None
        V_inverse = torch.cholesky_inverse(L)  # (P, 3, 3): every point block at once
        g_camera = self.gradient[0, : C * dc].reshape(C, dc)
        g_point = self.gradient[0, C * dc:C * dc + 3 * P].reshape(P, 3)
        c, p = bundle.camera_index, bundle.point_index
        Y = _products(self.W, V_inverse.reshape(P, 9).T[:, p].reshape(3, 3, -1))  # (dc, 3, O) = W V*⁻¹
        rhs = g_camera - torch.zeros(C, dc, dtype=U.dtype, device=U.device).index_add_(0, c, _products(Y, g_point.T[:, None, p])[:, 0].T)
        if self.border is not None:  # one more right-hand side per intrinsic: S_ck = E - Σ W V*⁻¹ Wkᵀ
            E, Wk, _ = self.border
            rhs = torch.cat([rhs[..., None], E - torch.zeros_like(E).index_add_(0, c, _products(Y, Wk.permute(2, 1, 0)[:, :, p]).permute(2, 0, 1))], dim=-1)
        if problem.config.linear_solver == "dense" or (problem.config.linear_solver == "auto" and C * dc <= problem.config.dense_limit):
            solution, ok = self._dense(U, V_inverse, Y, rhs)
        else:
            solution, ok = self._conjugate_gradients(U, V_inverse, Y, rhs)
        return rhs, solution, ok, V_inverse, g_point

    def solve(self, damping: Tensor) -> tuple[Tensor, Tensor]:
        problem, bundle = self.problem, self.problem.bundle
        C, P, dc = bundle.num_cameras, bundle.num_points, problem.dc
        damping = damping[0]
        system = self._camera_system(damping)
        if system is None:
            return torch.zeros_like(self.gradient), torch.zeros(1, dtype=torch.bool)
        rhs, solution, ok, V_inverse, g_point = system
        c, p = bundle.camera_index, bundle.point_index
        if self.border is None:
            delta_camera, delta_intrinsics, back = solution, None, g_point
        else:
            delta_intrinsics, ok = self._intrinsics_step(rhs, solution, V_inverse, g_point, damping[C * dc + 3 * P:], ok)
            delta_camera = solution[..., 0] - solution[..., 1:] @ delta_intrinsics
            back = g_point - (self.border[1].transpose(1, 2) @ delta_intrinsics)
        back = back - torch.zeros_like(g_point).index_add_(0, p, _products(self.W.transpose(0, 1), delta_camera.T[:, None, c])[:, 0].T)
        delta_point = (V_inverse @ back[..., None])[..., 0]
        parts = [delta_camera.flatten(), delta_point.flatten()] + ([] if delta_intrinsics is None else [delta_intrinsics])
        return torch.cat(parts)[None], ok[None]

    def _intrinsics_information(self, rhs: Tensor, solution: Tensor, V_inverse: Tensor, damping: Tensor) -> Tensor:
        """The m×m Schur complement of the camera and point blocks — the intrinsics' information
        with cameras and points marginalized: rhs (C, dc, 1 + m) holds the cameras' right-hand
        side and S_ck, solution (C, dc, 1 + m) S_cc⁻¹ of them, (m,) damping."""
        _, Wk, G = self.border
        m = G.shape[0]
        S_kk = G + torch.diag(damping) - (Wk @ V_inverse @ Wk.transpose(1, 2)).sum(0)
        S_ck = rhs[..., 1:].reshape(-1, m)
        return S_kk - S_ck.T @ solution[..., 1:].reshape(-1, m)

    def intrinsics_information(self) -> Tensor | None:
        """(m, m) :meth:`_intrinsics_information` without damping (a trace of it on the cameras and
        points, 1e-12 of each diagonal entry and of their mean: the gauge the fixed camera leaves,
        the scale, has no information, and a fixed camera's block is empty); None where the
        system is singular."""
        diagonal = self.diagonal[0]
        system = self._camera_system(1e-12 * (diagonal + diagonal.mean()))
        if system is None or not bool(system[2]):
            return None
        rhs, solution, _, V_inverse, _ = system
        return self._intrinsics_information(rhs, solution, V_inverse, torch.zeros_like(self.border[2][0]))

    def _intrinsics_step(self, rhs: Tensor, solution: Tensor, V_inverse: Tensor, g_point: Tensor, damping: Tensor,
                         ok: Tensor) -> tuple[Tensor, Tensor]:
        """The intrinsics' step from the m×m Schur complement of the camera block: rhs (C, dc, 1 + m)
        holds the cameras' right-hand side and S_ck, solution (C, dc, 1 + m) S_cc⁻¹ of them."""
        _, Wk, G = self.border
        m = G.shape[0]
        g_k = self.gradient[0, -m:] - (Wk @ V_inverse @ g_point[..., None])[..., 0].sum(0)
        reduced = self._intrinsics_information(rhs, solution, V_inverse, damping)
        L, info = torch.linalg.cholesky_ex(reduced)
        if int(info) != 0:
            return torch.zeros_like(g_k), torch.tensor(False, device=g_k.device)
        S_ck = rhs[..., 1:].reshape(-1, m)
        step = torch.cholesky_solve((g_k - S_ck.T @ solution[..., 0].flatten())[:, None], L)[:, 0]
        return step, ok

    def _dense(self, U: Tensor, V_inverse: Tensor, Y: Tensor, rhs: Tensor) -> tuple[Tensor, Tensor]:
        """S = U* - Σ_p W_p V*_p⁻¹ W_pᵀ, then Cholesky; rhs (C, dc) or (C, dc, m) columns.

        The sum from the camera-pair blocks of every point (:meth:`_camera_pair_blocks`: Σ_p
        n_p² blocks of dc² numbers), or, where those outweigh it, from one GEMM with
        W laid out densely as (C dc, 3 P) (measured crossover: a block number costs about
        ``BLOCK_NUMBER_FLOPS`` GEMM flops) unless its two (3 P, C dc) buffers would exceed
        ``DENSE_BUFFER_BYTES`` (many views and many points). Fixed cameras have zero rows in U and W, so only their
        damping remains on S's diagonal and their step is exactly 0.
        """
        problem, bundle = self.problem, self.problem.bundle
        C, P, dc = bundle.num_cameras, bundle.num_points, problem.dc
        block_count = sum(observations.shape[0] * observations.shape[1] ** 2 for observations in problem.track_groups)
        buffer_bytes = 2 * 3 * P * C * dc * torch.finfo(U.dtype).bits // 8
        if block_count * dc * dc * BLOCK_NUMBER_FLOPS <= (C * dc) ** 2 * 3 * P or buffer_bytes > DENSE_BUFFER_BYTES:
            reduction = self._camera_pair_blocks(Y)
        else:
            Wt, VWt, rows = problem.dense_buffers()  # (P, 3, C, dc) each, reused across iterations
            Wt.view(-1, dc).index_copy_(0, rows, self.W.permute(2, 1, 0).reshape(-1, dc))  # each (point, camera) block is observed once
            VWt.view(-1, dc).index_copy_(0, rows, Y.permute(2, 1, 0).reshape(-1, dc))  # V*⁻¹ Wᵀ, only the observed blocks
            reduction = Wt.reshape(3 * P, C * dc).T @ VWt.reshape(3 * P, C * dc)
        S = reduction.neg_()  # S = U* - reduction, in place: the (C dc)² matrix is the solver's largest buffer
        diagonal = S.view(C, dc, C, dc).diagonal(dim1=0, dim2=2)  # (dc, dc, C): the camera blocks
        diagonal += U.permute(1, 2, 0)
        L, info = torch.linalg.cholesky_ex(S)
        if int(info) != 0:
            return torch.zeros_like(rhs), torch.tensor(False)
        columns = rhs.reshape(C * dc, -1)  # (C dc) x 1, or 1 + m with the intrinsics' border
        return torch.cholesky_solve(columns, L).reshape(rhs.shape), torch.tensor(True, device=U.device)

    def _camera_pair_blocks(self, Y: Tensor) -> Tensor:
        """Σ_p W_p V*_p⁻¹ W_pᵀ (C dc, C dc) from Y = W V*⁻¹ (dc, 3, O), block by block: block
        (c_a, c_b) = Σ Y_a W_bᵀ over the pairs of observations a, b of one point in cameras c_a,
        c_b. Points in groups of equal track length n, ``BLOCK_CHUNK_NUMBERS`` numbers at a time:
        one batched product (n dc × 3)(3 × n dc) per chunk gives every camera-pair block of its
        points, added into S. The blocks' positions in S are made per chunk, not kept: Σ n² of
        them is hundreds of megabytes for a long video's tracks. Tracks so long that their n²
        blocks cost more than their three columns of the dense product (:meth:`_dense`'s
        crossover, per track: n² dc² ``BLOCK_NUMBER_FLOPS`` > 3 (C dc)² — a long video's distant
        points, seen from most of its frames) are summed by dense products instead
        (:meth:`_add_long_track_products`)."""
        problem, bundle = self.problem, self.problem.bundle
        C, dc = bundle.num_cameras, problem.dc
        blocks = torch.zeros(C * C, dc, dc, dtype=Y.dtype, device=Y.device)
        Y_blocks, W_blocks = Y.permute(2, 0, 1), self.W.permute(2, 0, 1)  # (O, dc, 3) views
        long = []
        for observations in problem.track_groups:  # (P_n, n) observation ids
            n = observations.shape[1]
            if n * n * dc * dc * BLOCK_NUMBER_FLOPS > 3 * (C * dc) ** 2:
                long.append(observations)
                continue
            points_at_a_time = max(1, BLOCK_CHUNK_NUMBERS // (n * n * dc * dc))
            for start in range(0, observations.shape[0], points_at_a_time):
                part = observations[start:start + points_at_a_time]
                cameras = bundle.camera_index[part]  # (p, n)
                products = Y_blocks[part].reshape(-1, n * dc, 3) @ W_blocks[part].reshape(-1, n * dc, 3).transpose(1, 2)
                blocks.index_add_(0, (cameras[:, :, None] * C + cameras[:, None, :]).flatten(),
                                  products.view(-1, n, dc, n, dc).transpose(2, 3).reshape(-1, dc, dc))
        reduction = blocks.view(C, C, dc, dc).transpose(1, 2).reshape(C * dc, C * dc)
        del blocks  # (C², dc, dc): as large as the reduction, and no longer needed beside the dense products' buffers
        if long:
            self._add_long_track_products(reduction, long, Y_blocks, W_blocks)
        return reduction

    def _add_long_track_products(self, reduction: Tensor, groups: list[Tensor], Y_blocks: Tensor, W_blocks: Tensor) -> None:
        """Add Σ_p W_p V*_p⁻¹ W_pᵀ over the points of ``groups`` ((P_n, n) observation ids each)
        to ``reduction`` (C dc, C dc) as dense products: their Y and W blocks (O, dc, 3) laid out
        as (C dc, 3 p) for p = C dc / 6 points at a time, so that the two buffers together hold no
        more than the reduction itself."""
        bundle, dc = self.problem.bundle, self.problem.dc
        C = bundle.num_cameras
        lengths = torch.cat([torch.full((group.shape[0],), group.shape[1], dtype=torch.long, device=Y_blocks.device) for group in groups])
        observations = torch.cat([group.flatten() for group in groups])  # point by point
        slot = torch.repeat_interleave(torch.arange(lengths.numel(), device=Y_blocks.device), lengths)  # each one's point
        camera = bundle.camera_index[observations]
        ends = torch.cumsum(lengths, 0).tolist()
        at_a_time = max(1, C * dc // 6)
        for first in range(0, lengths.numel(), at_a_time):
            last = min(first + at_a_time, lengths.numel())
            rows = slice(ends[first - 1] if first else 0, ends[last - 1])
            where = (camera[rows], slice(None), slot[rows] - first)
            Y_dense = torch.zeros(C, dc, last - first, 3, dtype=Y_blocks.dtype, device=Y_blocks.device)
            W_dense = torch.zeros_like(Y_dense)
            Y_dense[where], W_dense[where] = Y_blocks[observations[rows]], W_blocks[observations[rows]]
            reduction.addmm_(Y_dense.view(C * dc, -1), W_dense.view(C * dc, -1).T)

    def _conjugate_gradients(self, U: Tensor, V_inverse: Tensor, Y: Tensor, rhs: Tensor) -> tuple[Tensor, Tensor]:
        """Matrix-free PCG on S with a block-Jacobi preconditioner (S's camera diagonal blocks);
        rhs (C, dc), or (C, dc, m): one solve per column."""
        if rhs.dim() == 3:
            columns = [self._conjugate_gradients(U, V_inverse, Y, rhs[..., k]) for k in range(rhs.shape[-1])]
            return torch.stack([x for x, _ in columns], dim=-1), torch.stack([ok for _, ok in columns]).all()
        problem, bundle = self.problem, self.problem.bundle
        C, P, dc = bundle.num_cameras, bundle.num_points, problem.dc
        c, p = bundle.camera_index, bundle.point_index

        def apply(x: Tensor) -> Tensor:  # S x for x (C, dc)
            through_points = torch.zeros(P, 3, dtype=U.dtype, device=U.device).index_add_(0, p, _products(self.W.transpose(0, 1), x.T[:, None, c])[:, 0].T)
            back = torch.zeros(C, dc, dtype=U.dtype, device=U.device).index_add_(0, c, _products(Y, through_points.T[:, None, p])[:, 0].T)
            return (U @ x[..., None])[..., 0] - back

        diagonal_blocks = U - torch.zeros(C, dc, dc, dtype=U.dtype, device=U.device).index_add_(0, c, _products(Y, self.W.transpose(0, 1)).permute(2, 0, 1))
        preconditioner = torch.linalg.inv(diagonal_blocks)
        x = torch.zeros_like(rhs)
        residual = rhs.clone()
        z = (preconditioner @ residual[..., None])[..., 0]
        direction = z.clone()
        rz = (residual * z).sum()
        target = problem.config.cg_tolerance * residual.norm()
        for _ in range(problem.config.cg_max_iterations):
            if residual.norm() <= target:
                break
            Sd = apply(direction)
            step = rz / floor_tiny((direction * Sd).sum())
            x = x + step * direction
            residual = residual - step * Sd
            z = (preconditioner @ residual[..., None])[..., 0]
            rz_new = (residual * z).sum()
            direction = z + (rz_new / floor_tiny(rz)) * direction
            rz = rz_new
        return x, torch.isfinite(x).all()


def track_groups(point_index: Tensor, num_points: int) -> list[Tensor]:
    """Points grouped by track length n: per group, the (P_n, n) observation ids of its points."""
    order = torch.argsort(point_index, stable=True)
    counts = torch.bincount(point_index, minlength=num_points)
    starts = torch.cumsum(counts, 0) - counts
    groups = []
    for n in torch.unique(counts[counts > 0]).tolist():
        points = torch.nonzero(counts == n).flatten()
        groups.append(order[starts[points][:, None] + torch.arange(n, device=order.device)[None]])  # (P_n, n)
    return groups


class _BundleLM:
    """A :class:`~torchsfm.optim.lm.LMProblem` view of a bundle problem (batch of one).

    Parameters are flattened to (1, S): per camera R (9), t (3) and for BAL (f, k1, k2), then
    the points, then with ``shared_intrinsics`` (fx, fy, cx, cy, k1). Steps are (1, C dc + 3 P [+ m]),
    the intrinsics' m along ``intrinsics_basis`` (5, m).
    """

    def __init__(self, bundle: BundleProblem, config: BundleAdjustmentConfig) -> None:
        self.bundle, self.config = bundle, config
        self.dc = CAMERA_DOF[bundle.camera_model]
        self.state_size = 12 if bundle.camera_model == "pinhole" else 15
        self.free = (~bundle.fixed_cameras)[:, None].expand(-1, self.dc).to(bundle.points.dtype)
        self.free_observations = self.free.T[:, bundle.camera_index]  # (dc, O): 0 in a fixed camera's rows
        self.track_groups = track_groups(bundle.point_index, bundle.num_points)
        self._buffers: tuple[Tensor, Tensor, Tensor] | None = None
        self.camera_order = torch.argsort(bundle.camera_index, stable=True)
        self.camera_rows = (2 * torch.bincount(bundle.camera_index, minlength=bundle.num_cameras)).tolist()
        self.intrinsics_basis = torch.tensor([INTRINSIC_PARAMETERS[name] for name in bundle.shared_intrinsics],
                                             dtype=bundle.points.dtype, device=bundle.points.device).reshape(-1, 5).T

    def dense_buffers(self) -> tuple[Tensor, Tensor, Tensor]:
        """Two zeroed (P, 3, C, dc) buffers for the dense reduced-camera-system product, allocated once
        (fresh allocations of this size cost more in page faults than the product itself), and the
        (3 O,) rows of their (P 3 C, dc) views that each observation's (3, dc) block fills: (p 3 + k) C + c."""
        if self._buffers is None:
            bundle = self.bundle
            shape = (bundle.num_points, 3, bundle.num_cameras, self.dc)
            rows = (bundle.point_index[:, None] * 3 + torch.arange(3, device=bundle.point_index.device)) * bundle.num_cameras
            self._buffers = (*(torch.zeros(shape, dtype=bundle.points.dtype, device=bundle.points.device) for _ in range(2)),
                             (rows + bundle.camera_index[:, None]).flatten())
        return self._buffers


    def pack(self, bundle: BundleProblem) -> Tensor:
        parts = [bundle.rotations.flatten(1), bundle.translations]
        if bundle.camera_model == "bal":
            parts.append(bundle.intrinsics)
        shared = [bundle.intrinsics[0, [0, 1, 0, 1], [0, 1, 2, 2]], bundle.points.new_tensor([bundle.radial])] if bundle.shared_intrinsics else []
        return torch.cat([torch.cat(parts, dim=1).flatten(), bundle.points.flatten()] + shared)[None]

    def unpack(self, params: Tensor) -> tuple[Tensor, Tensor, Tensor, Tensor, Tensor | float]:
        """Rotations, translations, intrinsics, points and the pinhole cameras' radial k1 (a 0-d
        tensor with ``shared_intrinsics``)."""
        C, P = self.bundle.num_cameras, self.bundle.num_points
        cameras = params[0, : C * self.state_size].reshape(C, self.state_size)
        points = params[0, C * self.state_size:C * self.state_size + 3 * P].reshape(-1, 3)
        intrinsics = cameras[:, 12:15] if self.bundle.camera_model == "bal" else self.bundle.intrinsics
        radial: Tensor | float = self.bundle.radial
        if self.bundle.shared_intrinsics:  # (fx, fy, cx, cy, k1) after the points
            fx, fy, cx, cy, k1 = params[0, -5:].unbind()
            zero, one = torch.zeros_like(fx), torch.ones_like(fx)
            K = torch.stack([fx, zero, cx, zero, fy, cy, zero, zero, one]).reshape(3, 3)
            intrinsics = K.expand(C, 3, 3)
            radial = k1 if "k1" in self.bundle.shared_intrinsics else self.bundle.radial
        return cameras[:, :9].reshape(C, 3, 3), cameras[:, 9:12], intrinsics, points, radial

    def _weighted(self, params: Tensor, jacobians: bool):
        R, t, intrinsics, points, radial = self.unpack(params)
        prediction, d_camera, d_point = _project(self.bundle, R, t, intrinsics, points, jacobians, radial)
        residuals = prediction - self.bundle.observations
        rho, weights = _loss(residuals.square().sum(-1), self.config.loss, self.config.loss_scale)
        d_intrinsics = None
        if jacobians and self.bundle.shared_intrinsics:
            # d(u, v) / d(fx, fy, cx, cy, k1) = [[sx, 0, 1, 0, fx nx r²], [0, sy, 0, 1, fy ny r²]], s = n (1 + k1 r²)
            K = intrinsics[0]
            focal = torch.stack([K[0, 0], K[1, 1]])[:, None]
            seen = (prediction.T - K[:2, 2, None]) / focal  # (2, O)
            d_intrinsics = torch.zeros(2, 5, prediction.shape[0], dtype=prediction.dtype, device=prediction.device)
            d_intrinsics[0, 0], d_intrinsics[1, 1] = seen[0], seen[1]
            d_intrinsics[0, 2] = d_intrinsics[1, 3] = 1
            if "k1" in self.bundle.shared_intrinsics:
                camera_point = _camera_points(self.bundle, R, t, points)[2]
                normalized = camera_point[:2] / camera_point[2]
                d_intrinsics[:, 4] = focal * normalized * normalized.square().sum(0)
            d_intrinsics = _products(d_intrinsics, self.intrinsics_basis[..., None])  # (2, m, O)
        return residuals, rho, weights, d_camera, d_point, d_intrinsics

    def cost(self, params: Tensor) -> Tensor:
        rho = self._weighted(params, False)[1]
        return 0.5 * rho.sum()[None]

    def linearize(self, params: Tensor) -> _SchurLinearization:
        residuals, _, weights, d_camera, d_point, d_intrinsics = self._weighted(params, True)
        return _SchurLinearization(self, d_camera, d_point, residuals, weights, d_intrinsics)

    def retract(self, params: Tensor, delta: Tensor) -> Tensor:
        C, P, dc = self.bundle.num_cameras, self.bundle.num_points, self.dc
        R, t, intrinsics, points, _ = self.unpack(params)
        step_camera = delta[0, : C * dc].reshape(C, dc) * self.free
        R = axis_angle_to_rotation(step_camera[:, :3]) @ R
        t = t + step_camera[:, 3:6]
        parts = [R.flatten(1), t] + ([intrinsics + step_camera[:, 6:9]] if self.bundle.camera_model == "bal" else [])
        points = points + delta[0, C * dc:C * dc + 3 * P].reshape(-1, 3)
        m = self.intrinsics_basis.shape[1]
        shared = [params[0, -5:] + self.intrinsics_basis @ delta[0, -m:]] if self.bundle.shared_intrinsics else []
        return torch.cat([torch.cat(parts, dim=1).flatten(), points.flatten()] + shared)[None]


def intrinsics_covariance(problem: BundleProblem, *, config: BundleAdjustmentConfig | None = None) -> Tensor | None:
    """(m, m) covariance of the ``shared_intrinsics`` (in their order) at the problem's state,
    the cameras and points marginalized: σ² times the inverse of their information (the Schur
    complement of the Gauss–Newton normal equations), σ² the loss-weighted residual sum of
    squares over its degrees of freedom. Meaningful at an optimum (after :func:`bundle_adjust`);
    None where the information is singular (an intrinsic the data leave free)."""
    if not problem.shared_intrinsics:
        raise InputError("intrinsics_covariance needs shared_intrinsics")
    lm_problem = _BundleLM(problem, config or BundleAdjustmentConfig())
    params = lm_problem.pack(problem)
    information = lm_problem.linearize(params).intrinsics_information()
    if information is None:
        return None
    residuals, _, weights = lm_problem._weighted(params, False)[:3]
    unknowns = int(lm_problem.free.sum()) + 3 * problem.num_points + information.shape[0]
    sigma_sq = (weights * residuals.square().sum(-1)).sum() / max(residuals.numel() - unknowns, 1)
    covariance, info = torch.linalg.inv_ex(information)
    return sigma_sq * covariance if int(info) == 0 else None


@without_autograd
def bundle_adjust(problem: BundleProblem, *, config: BundleAdjustmentConfig | None = None) -> BundleResult:
    """Minimize the (robustified) reprojection error over cameras and points.

    Returns a :class:`BundleResult` whose costs are ½ Σ ‖r‖² in pixels² (not robustified) and
    whose ``problem`` is an adjusted copy (the input is not modified).
    """
    config = config or BundleAdjustmentConfig()
    start = time.perf_counter()
    lm_problem = _BundleLM(problem, config)
    result = minimize(lm_problem, lm_problem.pack(problem), config.lm)
    R, t, intrinsics, points, radial = lm_problem.unpack(result.params)
    adjusted = copy.copy(problem)
    adjusted.rotations, adjusted.translations, adjusted.points = R.clone(), t.clone(), points.clone()
    adjusted.intrinsics = intrinsics.clone()  # a shared K: one copy per camera
    adjusted.radial = float(radial)
    return BundleResult(problem=adjusted, initial_cost=problem.cost(), final_cost=adjusted.cost(),
                        num_iterations=int(result.num_iterations[0]), converged=bool(result.converged[0]),
                        status=("converged" if bool(result.converged[0]) else "stalled" if bool(result.stalled[0])
                                else "failed" if bool(result.failed[0]) else "max_iterations"),
                        timings={"bundle_adjustment": time.perf_counter() - start})
