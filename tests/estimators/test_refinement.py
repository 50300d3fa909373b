import torch
from torch.testing import assert_close

from torchsfm.config import LMConfig
from torchsfm.estimators import fundamental_refinement, pose_refinement
from torchsfm.geometry.fundamental import eight_point, fundamental_from_pose, normalize_scale, sampson_error
from torchsfm.geometry.rotation import axis_angle_to_rotation
from torchsfm.optim.lm import forward_jacobian
from torchsfm.testing import rotation_error_deg, synthetic_two_view, translation_direction_error_deg

DOUBLE = dict(dtype=torch.float64)


def test_orthonormal_representation_round_trip_and_tangent_derivatives():
    F = eight_point(*(lambda s: (s.x1, s.x2))(synthetic_two_view(30, noise=1.0, seed=0)))[None]
    state = fundamental_refinement._to_orthonormal(F)
    assert_close(normalize_scale(fundamental_refinement._from_orthonormal(state)), F * torch.sign((fundamental_refinement._from_orthonormal(state) * F).sum()), rtol=0, atol=1e-12)
    automatic = forward_jacobian(lambda s: fundamental_refinement._from_orthonormal(s).flatten(1), state, fundamental_refinement._retract, 7)
    analytic = fundamental_refinement._tangent_derivatives(state).flatten(-2).transpose(-1, -2)
    assert_close(analytic, automatic, rtol=1e-10, atol=1e-12)


def test_F_refinement_lowers_the_sampson_error_and_keeps_rank_2():
    scene = synthetic_two_view(200, noise=1.0, seed=1)
    x1, x2 = scene.x1[None], scene.x2[None]
    F0 = eight_point(x1, x2)
    F, result = fundamental_refinement.refine_fundamental(F0, x1, x2, torch.ones(1, 200, **DOUBLE), LMConfig())
    assert result.cost < result.initial_cost
    assert_close(0.5 * sampson_error(F, x1, x2).sum(), result.cost[0], rtol=1e-9, atol=0)
    assert torch.linalg.svdvals(F[0])[2] < 1e-12 * torch.linalg.svdvals(F[0])[0]
    assert result.converged.all()


def test_F_refinement_keeps_an_exact_solution():
    scene = synthetic_two_view(50, seed=2)
    F, _ = fundamental_refinement.refine_fundamental(scene.F[None], scene.x1[None], scene.x2[None], torch.ones(1, 50, **DOUBLE), LMConfig())
    assert_close(F[0], scene.F * torch.sign((F[0] * scene.F).sum()), rtol=0, atol=1e-10)


def test_pose_jacobian_matches_autodiff():
    scene = synthetic_two_view(30, noise=1.0, seed=3)
    K = scene.K1[None]
    weights = torch.rand(1, 30, **DOUBLE, generator=torch.Generator().manual_seed(110))
    residuals, jacobian = pose_refinement.relative_pose_problem(scene.x1[None], scene.x2[None], K, K, weights)
    state = torch.cat([scene.R.flatten(), scene.t])[None]
    automatic = forward_jacobian(residuals, state, pose_refinement.retract_pose, 5)
    assert_close(jacobian(state), automatic, rtol=1e-9, atol=1e-10)


def test_pose_refinement_recovers_a_perturbed_pose():
    scene = synthetic_two_view(100, seed=4)
    R0 = axis_angle_to_rotation(torch.tensor([0.01, -0.02, 0.015], **DOUBLE)) @ scene.R
    t0 = scene.t + torch.tensor([0.05, -0.03, 0.02], **DOUBLE)
    R, t, result = pose_refinement.refine_relative_pose(R0[None], t0[None], scene.x1[None], scene.x2[None], scene.K1[None], scene.K2[None], torch.ones(1, 100, **DOUBLE), LMConfig())
    assert rotation_error_deg(R[0], scene.R) < 1e-8
    assert translation_direction_error_deg(t[0], scene.t) < 1e-8
    assert_close(fundamental_from_pose(scene.K1, scene.K2, R[0], t[0]), scene.F, rtol=0, atol=1e-10)


def test_F_refinement_ignores_the_rows_without_weight():
    """Rows of weight 0 (outliers, padding) are gathered out before LM: holding wild values
    there changes nothing (float64, 1e-12), in a batch whose problems support different counts."""
    scenes = [synthetic_two_view(60, noise=0.5, seed=seed) for seed in (4, 5)]
    x1, x2 = torch.stack([s.x1 for s in scenes]), torch.stack([s.x2 for s in scenes])
    F0 = eight_point(x1, x2)
    weights = torch.ones(2, 60, **DOUBLE)
    weights[0, ::3] = 0
    weights[1, 50:] = 0
    wild1 = x1.clone()
    wild1[weights == 0] = 1e4
    F, _ = fundamental_refinement.refine_fundamental(F0, wild1, x2, weights, LMConfig())
    for b in range(2):
        kept = weights[b] > 0
        alone, _ = fundamental_refinement.refine_fundamental(F0[b:b + 1], x1[b:b + 1, kept], x2[b:b + 1, kept],
                                                             weights[b:b + 1, kept], LMConfig())
        assert_close(F[b], alone[0], rtol=0, atol=1e-12)
