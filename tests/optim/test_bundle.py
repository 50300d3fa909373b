import copy
import math

import pytest
import torch
from torch.testing import assert_close

from torchsfm.config import BundleAdjustmentConfig
from torchsfm.errors import InputError, ShapeError
from torchsfm.geometry.rotation import axis_angle_to_rotation
from torchsfm.io.bal import read_bal, write_bal
from torchsfm.optim.bundle import BundleProblem, _project, bundle_adjust

DOUBLE = dict(dtype=torch.float64)


def _ring(model: str, cameras=8, points=300, noise=0.0, seed=0, perturb=True, tilt=0.0):
    """Cameras on a ring around a ball of points; every point seen by the 4 nearest cameras;
    ``tilt`` (radians): each camera turned about a random axis by about that much (rotations
    about one axis only are a critical motion for self-calibration)."""
    g = torch.Generator().manual_seed(seed)
    X = torch.randn(points, 3, generator=g, **DOUBLE)
    angles = torch.arange(cameras, **DOUBLE) * 2 * math.pi / cameras
    flip = torch.diag(torch.tensor([1.0, -1.0, -1.0], **DOUBLE)) if model == "bal" else torch.eye(3, **DOUBLE)
    R, t = [], []
    for a in angles:
        centre = torch.stack([6 * torch.cos(a), 6 * torch.sin(a), torch.tensor(0.3, **DOUBLE)])
        z = -centre / centre.norm()
        x = torch.linalg.cross(torch.tensor([0.0, 0.0, 1.0], **DOUBLE), z)
        x = x / x.norm()
        rotation = flip @ torch.stack([x, torch.linalg.cross(z, x), z])
        if tilt:
            rotation = axis_angle_to_rotation(tilt * torch.randn(3, generator=g, **DOUBLE)) @ rotation
        R.append(rotation)
        t.append(-rotation @ centre)
    R, t = torch.stack(R), torch.stack(t)
    if model == "bal":
        intrinsics = torch.tensor([500.0, -0.05, 0.01], **DOUBLE).repeat(cameras, 1)
    else:
        intrinsics = torch.tensor([[500.0, 0, 320], [0, 500, 240], [0, 0, 1]], **DOUBLE).repeat(cameras, 1, 1)
    seen_by = min(4, cameras)
    angular_distance = (torch.atan2(X[:, 1:2], X[:, 0:1]) - angles[None] + math.pi).remainder(2 * math.pi).sub(math.pi).abs()
    nearest = torch.topk(angular_distance, seen_by, dim=1, largest=False).indices
    point_index = torch.arange(points).repeat_interleave(seen_by)
    camera_index = nearest.flatten()
    truth = BundleProblem(model, R, t, intrinsics, X, camera_index, point_index, torch.zeros(seen_by * points, 2, **DOUBLE))
    observations = truth.residuals() + noise * torch.randn(seen_by * points, 2, generator=g, **DOUBLE)
    truth.observations = observations
    if not perturb:
        return truth, truth
    start = BundleProblem(model, axis_angle_to_rotation(0.01 * torch.randn(cameras, 3, generator=g, **DOUBLE)) @ R,
                          t + 0.02 * torch.randn(cameras, 3, generator=g, **DOUBLE),
                          intrinsics * (1 + 0.005 * torch.randn(intrinsics.shape, generator=g, **DOUBLE)) if model == "bal" else intrinsics,
                          X + 0.02 * torch.randn(points, 3, generator=g, **DOUBLE), camera_index, point_index, observations)
    return truth, start


@pytest.mark.parametrize("model", ["pinhole", "bal"])
def test_analytic_jacobians_match_autodiff(model):
    truth, problem = _ring(model, cameras=3, points=5)
    _, d_camera, d_point = _project(problem, problem.rotations, problem.translations, problem.intrinsics, problem.points, True)
    c, p = problem.camera_index, problem.point_index
    for o in range(c.numel()):
        def prediction(camera_step, point):
            R = axis_angle_to_rotation(camera_step[:3]) @ problem.rotations
            t = problem.translations + camera_step[3:6]
            intrinsics = problem.intrinsics + camera_step[6:9] if model == "bal" else problem.intrinsics
            points = problem.points.clone()
            points[p[o]] = point
            single = BundleProblem(model, R, t, intrinsics, points, c[o:o + 1], p[o:o + 1], problem.observations[o:o + 1])
            return single.residuals()[0]
        zero = torch.zeros(9 if model == "bal" else 6, **DOUBLE)
        J_camera, J_point = torch.autograd.functional.jacobian(prediction, (zero, problem.points[p[o]]))
        assert_close(d_camera[:, :, o], J_camera, rtol=1e-7, atol=1e-7)
        assert_close(d_point[:, :, o], J_point, rtol=1e-7, atol=1e-7)


@pytest.mark.parametrize("model", ["pinhole", "bal"])
@pytest.mark.parametrize("solver", ["dense", "cg"])
def test_noise_free_problems_converge_to_zero_cost(model, solver):
    truth, start = _ring(model)
    if model == "pinhole":
        start.fixed_cameras = torch.arange(8) == 0
    result = bundle_adjust(start, config=BundleAdjustmentConfig(linear_solver=solver))
    assert result.initial_cost > 1e2
    assert result.final_cost < 1e-10
    if model == "pinhole":  # the fixed camera does not move
        assert_close(result.problem.rotations[0], start.rotations[0], rtol=0, atol=0)
        assert_close(result.problem.translations[0], start.translations[0], rtol=0, atol=0)


@pytest.mark.parametrize("chunk_numbers, block_number_flops", [(2**22, 1), (7 * 36, 1), (2**22, 30), (2**22, 10**9)])
def test_the_dense_solver_s_two_paths_agree(monkeypatch, chunk_numbers, block_number_flops):
    """The reduced camera system built track by track equals the one of the GEMM path, which a
    memory budget of zero rules out. The ring's tracks here are of 3 and 4 views; a
    ``BLOCK_NUMBER_FLOPS`` of 1 makes every one short (per-point blocks, formed all at once or a
    few points at a time: ``BLOCK_CHUNK_NUMBERS`` of 7 blocks, under one point's n² = 9), 10⁹
    every one long (dense products, C dc / 6 = 12 points at a time), and 30 puts the
    crossover (n² dc² F > 3 (C dc)²) between them, so both kinds add into one system. (By
    default this ring takes the GEMM path: its tracks of n = 3, 4 views among C = 12 give
    100 n² > 3 C², the crossover of ``_dense``.)"""
    _, start = _ring("pinhole", cameras=12, noise=0.5)
    every_other = (start.point_index % 2 == 0) & (torch.arange(start.point_index.numel()) % 4 == 0)  # one view less
    start.camera_index, start.point_index, start.observations = (x[~every_other] for x in (start.camera_index, start.point_index,
                                                                                            start.observations))
    assert set(torch.bincount(start.point_index).tolist()) == {3, 4}
    config = BundleAdjustmentConfig(linear_solver="dense")
    gemm = bundle_adjust(start, config=config)
    monkeypatch.setattr("torchsfm.optim.bundle.DENSE_BUFFER_BYTES", 0)
    monkeypatch.setattr("torchsfm.optim.bundle.BLOCK_CHUNK_NUMBERS", chunk_numbers)
    monkeypatch.setattr("torchsfm.optim.bundle.BLOCK_NUMBER_FLOPS", block_number_flops)
    by_tracks = bundle_adjust(start, config=config)
    assert_close(by_tracks.problem.points, gemm.problem.points, rtol=0, atol=1e-9)
    assert_close(by_tracks.final_cost, gemm.final_cost, rtol=1e-9, atol=0)


def test_dense_and_cg_reach_the_same_cost_under_noise():
    _, start = _ring("bal", noise=0.5)
    dense = bundle_adjust(start, config=BundleAdjustmentConfig(linear_solver="dense"))
    cg = bundle_adjust(start, config=BundleAdjustmentConfig(linear_solver="cg"))
    assert abs(dense.final_cost - cg.final_cost) <= 1e-6 * dense.final_cost
    # ½ Σ r² ≈ σ² (observations - parameters): a statistical check of the optimum
    expected = 0.5 * 0.25 * (2 * start.observations.shape[0] - 9 * 8 - 3 * 300)
    assert 0.7 * expected < dense.final_cost < 1.3 * expected


@pytest.mark.parametrize("loss", ["huber", "cauchy"])
def test_robust_losses_resist_outlier_observations(loss):
    truth, start = _ring("pinhole", noise=0.3, seed=1)
    start.fixed_cameras = torch.arange(8) == 0
    g = torch.Generator().manual_seed(2)
    bad = torch.randperm(start.observations.shape[0], generator=g)[:60]
    start.observations = start.observations.clone()
    start.observations[bad] += 30 * torch.randn(60, 2, generator=g, **DOUBLE)
    plain = bundle_adjust(start).problem
    robust = bundle_adjust(start, config=BundleAdjustmentConfig(loss=loss, loss_scale=1.0)).problem
    good = torch.ones(start.observations.shape[0], dtype=torch.bool)
    good[bad] = False
    rms = lambda problem: problem.residuals()[good].square().sum(-1).mean().sqrt()  # noqa: E731
    assert rms(robust) < 0.8 * rms(plain)
    if loss == "cauchy":  # redescending: the outliers lose all influence (noise: 0.3 px per coordinate)
        assert rms(robust) < 0.35 < rms(plain)


def test_a_cauchy_adjustment_doubles_the_steps_its_model_undersells(monkeypatch):
    """A fifth of the observations 5 px off (noise 0.3 px), Cauchy loss at 1 px: the weights'
    model is too curved along the steps that release those observations (gain ratios near 2), and
    LM without the step doubling crawls to the optimum; with it, under half the iterations reach a
    cost no higher (to the cost tolerance, 1e-6 relative)."""
    _, start = _ring("pinhole", noise=0.3, seed=1)
    start.fixed_cameras = torch.arange(8) == 0
    g = torch.Generator().manual_seed(2)
    bad = torch.randperm(start.observations.shape[0], generator=g)[: start.observations.shape[0] // 5]
    start.observations = start.observations.clone()
    start.observations[bad] += 5 * torch.randn(bad.numel(), 2, generator=g, **DOUBLE)
    config = BundleAdjustmentConfig(loss="cauchy", loss_scale=1.0)
    doubled = bundle_adjust(start, config=config)
    monkeypatch.setattr("torchsfm.optim.lm.EXPANSION_GAIN", float("inf"))
    crawling = bundle_adjust(start, config=config)
    assert doubled.status == crawling.status == "converged"
    assert 2 * doubled.num_iterations < crawling.num_iterations
    assert doubled.problem.robust_cost("cauchy", 1.0) <= (1 + 1e-6) * crawling.problem.robust_cost("cauchy", 1.0)


def test_robust_cost_is_the_sum_of_the_loss_over_the_observations():
    """Σ ρ(‖r‖²): twice the plain cost without a loss; Cauchy's c² log(1 + s / c²) by hand."""
    _, problem = _ring("pinhole", noise=0.5, seed=3)
    squared = problem.residuals().square().sum(-1)
    assert_close(problem.robust_cost("none", 1.0), 2 * problem.cost(), rtol=1e-12, atol=0)
    assert_close(problem.robust_cost("cauchy", 2.0), float((4 * torch.log1p(squared / 4)).sum()), rtol=1e-12, atol=0)
    assert problem.robust_cost("huber", 1.0) <= problem.robust_cost("none", 1.0)


def test_bal_round_trip(tmp_path):
    _, problem = _ring("bal", cameras=3, points=10)
    write_bal(tmp_path / "p.txt", problem)
    back = read_bal(tmp_path / "p.txt")
    assert_close(back.rotations, problem.rotations, rtol=0, atol=1e-12)
    assert_close(back.points, problem.points)
    assert back.cost() == pytest.approx(problem.cost(), rel=1e-12)


def test_ladybug_initial_cost_and_optimum(shared_data):
    problem = read_bal(shared_data / "bal_ladybug_49" / "problem-49-7776-pre.txt")
    assert problem.cost() == pytest.approx(8.509125e05, rel=1e-6)  # PROVENANCE: what a correct reader reproduces
    in_front = torch.ones(problem.num_points, dtype=torch.bool)
    in_front[problem.point_index[problem.depths() <= 0]] = False
    result = bundle_adjust(problem.select_points(in_front))
    # Ceres (pycolmap) reaches 1.330849e4 on the same problem (benchmarks/bundle_adjustment.py)
    assert result.final_cost < 1.330849e4 * 1.001


def test_bad_input():
    _, problem = _ring("pinhole", cameras=3, points=5, perturb=False)
    with pytest.raises(InputError, match="camera_model"):
        BundleProblem("fisheye", problem.rotations, problem.translations, problem.intrinsics, problem.points,
                      problem.camera_index, problem.point_index, problem.observations)
    with pytest.raises(ShapeError):
        BundleProblem("pinhole", problem.rotations, problem.translations, problem.intrinsics[:, :2], problem.points,
                      problem.camera_index, problem.point_index, problem.observations)
    with pytest.raises(InputError, match="point_index must lie"):
        BundleProblem("pinhole", problem.rotations, problem.translations, problem.intrinsics, problem.points,
                      problem.camera_index, problem.point_index + 100, problem.observations)
    with pytest.raises(InputError, match="NaN"):
        BundleProblem("pinhole", problem.rotations, problem.translations, problem.intrinsics, problem.points * float("nan"),
                      problem.camera_index, problem.point_index, problem.observations)
    with pytest.raises(InputError, match="must share one dtype, got rotations torch.float64, .* points torch.float32"):
        BundleProblem("pinhole", problem.rotations, problem.translations, problem.intrinsics, problem.points.float(),
                      problem.camera_index, problem.point_index, problem.observations)
    with pytest.raises(InputError, match="camera_index must be an integer tensor, got torch.float32"):
        BundleProblem("pinhole", problem.rotations, problem.translations, problem.intrinsics, problem.points,
                      problem.camera_index.float(), problem.point_index, problem.observations)
    sheared = problem.rotations.clone()
    sheared[1, 0, 1] += 1e-3
    with pytest.raises(InputError, match=r"rotations\[1\] is not a rotation matrix"):
        BundleProblem("pinhole", sheared, problem.translations, problem.intrinsics, problem.points,
                      problem.camera_index, problem.point_index, problem.observations)
    with pytest.raises(InputError, match=r"rotations\[2\] is not a rotation matrix"):  # a reflection
        BundleProblem("pinhole", problem.rotations * torch.tensor([1.0, 1.0, -1.0, -1.0])[:3, None, None].double(), problem.translations,
                      problem.intrinsics, problem.points, problem.camera_index, problem.point_index, problem.observations)
    with pytest.raises(ShapeError, match="fixed_cameras has C=2 but rotations has C=3"):
        BundleProblem("pinhole", problem.rotations, problem.translations, problem.intrinsics, problem.points,
                      problem.camera_index, problem.point_index, problem.observations, fixed_cameras=torch.ones(2, dtype=torch.bool))
    with pytest.raises(InputError, match="fixed_cameras must be a bool tensor"):
        BundleProblem("pinhole", problem.rotations, problem.translations, problem.intrinsics, problem.points,
                      problem.camera_index, problem.point_index, problem.observations, fixed_cameras=torch.tensor([1, 0, 0]))


@pytest.mark.parametrize("solver", ["dense", "cg"])
def test_shared_intrinsics_are_recovered_exactly_from_a_wrong_start(solver):
    """Noise-free ring, K started 3 % off in focal length (fx ≠ fy after) and 6 px off in the
    principal point: the joint adjustment returns the true K and zero cost."""
    truth, start = _ring("pinhole", cameras=8, points=300, tilt=0.15)
    wrong = start.intrinsics.clone()
    wrong[:, 0, 0] *= 1.03
    wrong[:, 1, 1] *= 0.98
    wrong[:, 0, 2] += 6
    wrong[:, 1, 2] -= 5
    start.intrinsics, start.shared_intrinsics = wrong, ("fx", "fy", "cx", "cy")
    start.fixed_cameras = torch.arange(8) == 0
    config = BundleAdjustmentConfig(linear_solver=solver)
    result = bundle_adjust(start, config=config)
    assert result.final_cost < 1e-12 * start.observations.shape[0]
    assert_close(result.problem.intrinsics, truth.intrinsics, rtol=0, atol=1e-6)  # pixels


@pytest.mark.parametrize("solver", ["dense", "cg"])
def test_a_shared_radial_coefficient_is_recovered_exactly_with_the_intrinsics(solver):
    """Noise-free ring seen through radial distortion k1 = -0.05 (observations made with it),
    adjusted from k1 = 0 and a K 2 % and 4 px off: the true k1 and K, zero cost; and the
    distorted problem's residuals are those of its own projection (checked against the model)."""
    truth, start = _ring("pinhole", cameras=8, points=300, tilt=0.15)
    distorted = copy.copy(truth)
    distorted.radial = -0.05
    observed = distorted.residuals() + truth.observations  # the predictions of the distorted cameras
    c, p = truth.camera_index, truth.point_index
    camera_point = (truth.rotations[c] @ truth.points[p][..., None])[..., 0] + truth.translations[c]
    normalized = camera_point[:, :2] / camera_point[:, 2:]
    K = truth.intrinsics[c]
    expected = (K[:, :2, :2] @ (normalized * (1 - 0.05 * normalized.square().sum(-1, keepdim=True)))[..., None])[..., 0] + K[:, :2, 2]
    assert_close(observed, expected, rtol=0, atol=1e-9)
    start.observations = observed
    start.intrinsics = start.intrinsics * torch.tensor([[1.02, 1, 1], [1, 1.02, 1], [1, 1, 1]], **DOUBLE)
    start.intrinsics[:, 0, 2] += 4
    start.shared_intrinsics, start.fixed_cameras = ("f", "cx", "cy", "k1"), torch.arange(8) == 0
    result = bundle_adjust(start, config=BundleAdjustmentConfig(linear_solver=solver))
    assert result.final_cost < 1e-12 * start.observations.shape[0]
    assert abs(result.problem.radial + 0.05) < 1e-9
    assert_close(result.problem.intrinsics, truth.intrinsics, rtol=0, atol=1e-6)


def test_a_shared_square_pixel_focal_length_moves_fx_and_fy_together():
    truth, start = _ring("pinhole", cameras=8, points=300, tilt=0.15)
    start.intrinsics = start.intrinsics * torch.tensor([[1.04, 1, 1], [1, 1.04, 1], [1, 1, 1]], **DOUBLE)
    start.shared_intrinsics, start.fixed_cameras = ("f",), torch.arange(8) == 0
    result = bundle_adjust(start)
    assert_close(result.problem.intrinsics, truth.intrinsics, rtol=0, atol=1e-6)


def test_shared_intrinsics_need_one_K_for_every_camera():
    _, problem = _ring("pinhole", cameras=3, points=10)
    K = problem.intrinsics.clone()
    K[1, 0, 0] += 1
    with pytest.raises(InputError, match="shared_intrinsics"):
        BundleProblem("pinhole", problem.rotations, problem.translations, K, problem.points, problem.camera_index,
                      problem.point_index, problem.observations, shared_intrinsics=("f",))
    with pytest.raises(InputError, match="shared_intrinsics must name"):
        BundleProblem("pinhole", problem.rotations, problem.translations, problem.intrinsics, problem.points, problem.camera_index,
                      problem.point_index, problem.observations, shared_intrinsics=("f", "fx"))


def test_the_intrinsics_covariance_matches_their_spread_over_noise_draws():
    """Ring of 8 cameras turned about random axes, 0.5 px noise, 40 draws: each adjusted
    intrinsic's standard deviation over the draws agrees with the one
    ``intrinsics_covariance`` predicts (mean over draws) within 25 % (40 draws: the sample
    deviation itself is within ±11 % for 1 σ); the prediction holds the truth within 3 σ."""
    from torchsfm.optim.bundle import intrinsics_covariance

    names = ("f", "cx", "cy")
    estimates, predicted = [], []
    for seed in range(40):
        truth, start = _ring("pinhole", cameras=8, points=300, tilt=0.15, noise=0.5, seed=seed)
        start.shared_intrinsics, start.fixed_cameras = names, torch.arange(8) == 0
        adjusted = bundle_adjust(start, config=BundleAdjustmentConfig(loss="none")).problem
        K = adjusted.intrinsics[0]
        estimates.append(torch.stack([K[0, 0], K[0, 2], K[1, 2]]))
        predicted.append(intrinsics_covariance(adjusted, config=BundleAdjustmentConfig(loss="none")).diagonal().sqrt())
    estimates, predicted = torch.stack(estimates), torch.stack(predicted).mean(0)
    spread = estimates.std(0)
    assert_close(spread, predicted, rtol=0.25, atol=0.0)
    truth_K = torch.tensor([500.0, 320.0, 240.0], **DOUBLE)
    assert bool(((estimates - truth_K).abs() <= 3 * predicted).float().mean() >= 0.95)
    with pytest.raises(InputError, match="needs shared_intrinsics"):
        intrinsics_covariance(truth)



@pytest.mark.parametrize("case", ["pinhole", "pinhole_intrinsics", "bal", "bal_blocks", "pinhole_cg", "bal_cg"])
def test_the_schur_step_is_the_damped_gauss_newton_step_of_the_dense_jacobian(monkeypatch, case):
    """One linearization of a noisy problem (Cauchy loss, a fixed camera) against the dense
    normal equations built from the Jacobian of the weighted residuals by autodiff along the
    step's own parametrization: the gradient, the diagonal and the damped step (JᵀJ + D) δ = -Jᵀr
    agree to 1e-9 relative — dense solver on its GEMM and its camera-pair-block paths, CG, and
    with shared intrinsics (f, cx, cy, k1: the border of the reduced camera system)."""
    from torchsfm.optim.bundle import _BundleLM

    model = case.split("_")[0]
    _, problem = _ring(model, cameras=5, points=12, noise=2.0, seed=4, tilt=0.1)
    problem.fixed_cameras = torch.arange(5) == 1
    if case == "pinhole_intrinsics":
        problem.shared_intrinsics, problem.radial = ("f", "cx", "cy", "k1"), -0.02
    if case == "bal_blocks":
        monkeypatch.setattr("torchsfm.optim.bundle.DENSE_BUFFER_BYTES", 0)
    solver = "cg" if case.endswith("cg") else "dense"
    config = BundleAdjustmentConfig(loss="cauchy", loss_scale=1.5, linear_solver=solver, cg_tolerance=1e-14, cg_max_iterations=500)
    lm = _BundleLM(problem, config)
    params = lm.pack(problem)
    residuals, _, weights = lm._weighted(params, False)[:3]
    root = weights.sqrt()[:, None]

    def weighted_residuals(delta):
        return ((lm._weighted(lm.retract(params, delta[None]), False)[0]) * root).flatten()

    size = lm.linearize(params).gradient.shape[1]
    J = torch.autograd.functional.jacobian(weighted_residuals, torch.zeros(size, **DOUBLE))  # (2 O, S)
    gradient = -J.T @ (residuals * root).flatten()
    damping = 0.3 * (J.square().sum(0) + 1.0)
    expected = torch.linalg.solve(J.T @ J + torch.diag(damping), gradient)
    linearization = lm.linearize(params)
    assert_close(linearization.gradient[0], gradient, rtol=1e-9, atol=1e-9)
    assert_close(linearization.diagonal[0], J.square().sum(0), rtol=1e-9, atol=1e-9)
    step, ok = linearization.solve(damping[None])
    assert bool(ok[0])
    assert_close(step[0], expected, rtol=1e-9, atol=1e-9 * float(expected.abs().max()))
