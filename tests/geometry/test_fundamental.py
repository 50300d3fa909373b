import pytest
import torch
from torch.testing import assert_close

from torchsfm.geometry.fundamental import (
    eight_point,
    eight_point_minimal,
    enforce_rank2,
    epipolar_line_distances,
    fundamental_from_projections,
    minimal_null_vectors,
    normalize_scale,
    real_cubic_roots,
    sampson_error,
    sampson_error_of_hypotheses,
    sampson_jacobian,
    sampson_residual,
    seven_point_minimal,
    symmetric_epipolar_distance,
)
from torchsfm.geometry.normalization import hartley_normalize
from torchsfm.optim.lm import forward_jacobian
from torchsfm.testing import synthetic_two_view

DOUBLE = dict(dtype=torch.float64)


def _same_up_to_sign(F, G, atol):
    F, G = normalize_scale(F), normalize_scale(G)
    sign = torch.sign((F * G).sum(dim=(-2, -1)))[..., None, None]
    assert_close(F * sign, G, rtol=0, atol=atol)


def test_hartley_normalization():
    x = torch.rand(2, 30, 2, **DOUBLE, generator=torch.Generator().manual_seed(108)) * 500
    normalized, T = hartley_normalize(x)
    assert_close(normalized.mean(-2), torch.zeros(2, 2, **DOUBLE), rtol=0, atol=1e-12)
    assert_close(normalized.norm(dim=-1).mean(-1), torch.full((2,), 2**0.5, **DOUBLE))
    homogeneous = torch.cat([x, torch.ones_like(x[..., :1])], -1) @ T.transpose(-1, -2)
    assert_close(homogeneous[..., :2], normalized)


@pytest.mark.parametrize("num_points", [8, 9, 50])
def test_eight_point_recovers_noise_free_F_exactly(num_points):
    scene = synthetic_two_view(num_points, seed=num_points)
    F = eight_point(scene.x1, scene.x2)
    _same_up_to_sign(F, scene.F, atol=1e-8)
    assert torch.linalg.matrix_rank(F) == 2


def test_minimal_solver_agrees_with_the_general_one():
    scene = synthetic_two_view(400, noise=0.5, seed=3)
    index = torch.stack([torch.randperm(400, generator=torch.Generator().manual_seed(i))[:8] for i in range(64)])
    x1, x2 = scene.x1[index][None], scene.x2[index][None]  # (1, 64, 8, 2)
    T1 = hartley_normalize(scene.x1[None])[1]
    T2 = hartley_normalize(scene.x2[None])[1]
    minimal = eight_point_minimal(x1, x2, T1, T2)
    assert torch.linalg.matrix_rank(minimal).eq(2).all()
    # before the rank-2 projection the null vector interpolates the 8 points exactly
    G = minimal_null_vectors(x1, x2, T1, T2)
    h1 = torch.cat([x1, torch.ones_like(x1[..., :1])], -1) @ T1[:, None, None].transpose(-1, -2)
    h2 = torch.cat([x2, torch.ones_like(x2[..., :1])], -1) @ T2[:, None, None].transpose(-1, -2)
    algebraic = (h2 * (h1 @ G.transpose(-1, -2))).sum(-1) / G.flatten(-2).norm(dim=-1)[..., None]
    assert algebraic.abs().amax() < 1e-12
    # after it, the same F as the SVD-based 8-point algorithm would give in that frame
    reference = enforce_rank2(G)
    _same_up_to_sign(T2[:, None].transpose(-1, -2) @ reference @ T1[:, None], minimal, atol=1e-9)
    exact = synthetic_two_view(8, seed=5)
    F = eight_point_minimal(exact.x1[None, None], exact.x2[None, None], hartley_normalize(exact.x1[None])[1], hartley_normalize(exact.x2[None])[1])
    _same_up_to_sign(F[0, 0], exact.F, atol=1e-8)


def test_weights_drop_points():
    scene = synthetic_two_view(40, outlier_ratio=0.3, seed=2)
    F = eight_point(scene.x1, scene.x2, scene.is_inlier.double())
    _same_up_to_sign(F, scene.F, atol=1e-8)


def test_rank2_enforcement_is_the_nearest_rank2_matrix():
    F = torch.randn(3, 3, **DOUBLE, generator=torch.Generator().manual_seed(109))
    F2 = enforce_rank2(F)
    S = torch.linalg.svdvals(F)
    assert torch.linalg.matrix_rank(F2) == 2
    assert_close(torch.linalg.matrix_norm(F - F2), S[2])


def test_fundamental_from_projections_matches_pose():
    scene = synthetic_two_view(10, seed=1)
    _same_up_to_sign(fundamental_from_projections(scene.P1, scene.P2), scene.F, atol=1e-12)


def test_error_measures():
    scene = synthetic_two_view(50, seed=4)
    assert sampson_error(scene.F, scene.x1, scene.x2).amax() < 1e-20
    # moving x2 by d pixels perpendicular to its epipolar line gives distance d in image 2
    line = torch.cat([scene.x1, torch.ones(50, 1, **DOUBLE)], -1) @ scene.F.T
    normal = line[:, :2] / line[:, :2].norm(dim=-1, keepdim=True)
    d1, d2 = epipolar_line_distances(scene.F, scene.x1, scene.x2 + 2.0 * normal)
    assert_close(d2, torch.full((50,), 2.0, **DOUBLE))
    assert_close(symmetric_epipolar_distance(scene.F, scene.x1, scene.x2 + 2.0 * normal), ((d1**2 + 4) / 2).sqrt())
    # Sampson distance is the first-order geometric error: below d2, above d2/2 for a shift in one image
    sampson = sampson_error(scene.F, scene.x1, scene.x2 + 2.0 * normal).sqrt()
    assert (sampson <= 2.0 + 1e-9).all() and (sampson > 1.0).all()


def test_hypothesis_scoring_matches_the_plain_formula():
    g = torch.Generator().manual_seed(0)
    F = torch.randn(2, 7, 3, 3, generator=g, **DOUBLE)
    x1, x2 = torch.randn(2, 30, 2, generator=g, **DOUBLE) * 300, torch.randn(2, 30, 2, generator=g, **DOUBLE) * 300
    assert_close(sampson_error_of_hypotheses(F, x1, x2), sampson_error(F, x1[:, None], x2[:, None]), rtol=1e-9, atol=1e-9)


def test_sampson_jacobian_matches_autodiff():
    g = torch.Generator().manual_seed(1)
    F = torch.randn(2, 3, 3, generator=g, **DOUBLE)
    x1, x2 = torch.randn(2, 20, 2, generator=g, **DOUBLE), torch.randn(2, 20, 2, generator=g, **DOUBLE)
    automatic = forward_jacobian(lambda f: sampson_residual(f.reshape(-1, 3, 3), x1, x2), F.reshape(2, 9), lambda p, d: p + d, 9)
    unit_directions = torch.eye(9, **DOUBLE).reshape(9, 3, 3).expand(2, 9, 3, 3)
    assert_close(sampson_jacobian(F, x1, x2, unit_directions), automatic, rtol=1e-10, atol=1e-12)


def test_real_cubic_roots_one_and_three():
    """(x - 1)(x - 2)(x + 3) = x³ - 7x + 6: three real roots; x³ + x + 1: one (−0.6823278...)."""
    roots, real = real_cubic_roots(torch.tensor([0.0, 0.0], **DOUBLE), torch.tensor([-7.0, 1.0], **DOUBLE),
                                   torch.tensor([6.0, 1.0], **DOUBLE))
    assert real[0].all() and real[1].tolist() == [True, False, False]
    assert_close(roots[0].sort().values, torch.tensor([-3.0, 1.0, 2.0], **DOUBLE), rtol=0, atol=1e-12)
    assert_close(roots[1, 0], torch.tensor(-0.6823278038280193, **DOUBLE), rtol=0, atol=1e-12)


def test_seven_point_recovers_the_true_F_among_its_roots():
    """Noise-free: one of the (up to three) rank-2 F of every 7-point sample is the true F to
    1e-8; every real root is exact on its sample; a degenerate sample (seven identical points)
    raises nothing and returns no infinity (NaN, or a finite F that RANSAC's scoring discards)."""
    scene = synthetic_two_view(60, seed=7)
    index = torch.stack([torch.randperm(60, generator=torch.Generator().manual_seed(i))[:7] for i in range(16)])
    x1, x2 = scene.x1[index][None], scene.x2[index][None]  # (1, 16, 7, 2)
    F = seven_point_minimal(x1, x2, hartley_normalize(scene.x1[None])[1], hartley_normalize(scene.x2[None])[1])[0]
    assert F.shape == (16, 3, 3, 3)
    real = torch.isfinite(F).flatten(-2).all(-1)
    assert real[:, 0].all()
    error = sampson_error(F.nan_to_num(), scene.x1[None, None], scene.x2[None, None]).amax(-1)  # (16, 3) over all points
    assert bool((error.where(real, torch.inf).amin(1) < 1e-12).all())
    on_sample = sampson_error(F.nan_to_num(), x1[0][:, None], x2[0][:, None]).amax(-1)
    assert bool((on_sample[real] < 1e-12).all())
    assert torch.linalg.matrix_rank(F[real]).eq(2).all()
    same = x1[:, :1].clone()
    same[..., 1:, :] = same[..., :1, :]  # seven identical points
    degenerate = seven_point_minimal(same, x2[:, :1], hartley_normalize(scene.x1[None])[1], hartley_normalize(scene.x2[None])[1])
    assert degenerate.shape == (1, 1, 3, 3, 3) and not torch.isinf(degenerate).any()
