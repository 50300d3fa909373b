import pytest
import torch
from torch.testing import assert_close

import torchsfm
from torchsfm.config import LMConfig
from torchsfm.errors import DegenerateConfigurationError, NotEnoughDataError, ShapeError
from torchsfm.estimators.resection_refinement import refine_pose
from torchsfm.camera import from_homogeneous, to_homogeneous
from torchsfm.geometry.resection import (dlt_projection, p3p, pose_from_projection, reprojection_errors,
                                         reprojection_errors_of_hypotheses)
from torchsfm.geometry.rotation import axis_angle_to_rotation, rotation_angle

DOUBLE = dict(dtype=torch.float64)
K = torch.tensor([[600.0, 0, 319.5], [0, 610.0, 239.5], [0, 0, 1]], **DOUBLE)


def _scene(n=100, noise=0.0, outliers=0.0, seed=0):
    g = torch.Generator().manual_seed(seed)
    R = axis_angle_to_rotation(0.4 * torch.randn(3, generator=g, **DOUBLE))
    t = torch.randn(3, generator=g, **DOUBLE)
    pixels = torch.rand(n, 2, generator=g, **DOUBLE) * torch.tensor([639.0, 479.0], **DOUBLE)
    depth = 3 + 5 * torch.rand(n, 1, generator=g, **DOUBLE)
    X = (torch.cat([pixels, torch.ones(n, 1, **DOUBLE)], -1) @ torch.linalg.inv(K).T * depth - t) @ R
    x = pixels + noise * torch.randn(n, 2, generator=g, **DOUBLE)
    truth = torch.ones(n, dtype=torch.bool)
    m = int(outliers * n)
    x[:m] = (x[:m] + 50 + 200 * torch.rand(m, 2, generator=g, **DOUBLE)) % torch.tensor([639.0, 479.0], **DOUBLE)
    truth[:m] = False
    return X, x, R, t, truth


def test_reprojection_errors_of_many_cameras_equal_one_at_a_time():
    """The (N, 4) x (4, 3H) product gives each camera's ‖x - π(P X)‖² (float64, to 1e-12
    relative against the projection written out), +inf for points behind a camera (here every
    point, for a camera turned around); :func:`reprojection_errors` is its one-camera case."""
    generator = torch.Generator().manual_seed(2)
    X, x, *_ = _scene(40)
    R = axis_angle_to_rotation(0.2 * torch.randn(6, 3, generator=generator, **DOUBLE))
    t = torch.randn(6, 3, generator=generator, **DOUBLE)
    P = K @ torch.cat([R, t[..., None]], -1)  # (6, 3, 4)
    P[0] = -P[0]  # the same camera turned around: every point behind it
    batched = reprojection_errors_of_hypotheses(P[None], X[None], x[None])[0]
    assert batched.shape == (6, 40)
    in_front = (to_homogeneous(X) @ P[1:].transpose(-1, -2))[..., 2] > 0
    assert bool(batched[0].isinf().all()) and bool(in_front.all())
    written_out = torch.stack([(from_homogeneous(to_homogeneous(X) @ camera.T) - x).square().sum(-1) for camera in P[1:]])
    assert_close(batched[1:], written_out, rtol=1e-12, atol=0)
    assert_close(reprojection_errors(P, X.expand(6, -1, -1), x.expand(6, -1, -1)), batched, rtol=1e-12, atol=0)


def test_dlt_is_exact_with_six_points_and_more():
    for n in (6, 50):
        X, x, R, t, _ = _scene(n)
        P = dlt_projection(X, x)
        R_est, t_est = pose_from_projection(P, K, X)
        assert_close(R_est, R, rtol=0, atol=1e-8)
        assert_close(t_est, t, rtol=0, atol=1e-8)
        assert reprojection_errors(P, X, x).max() < 1e-12


def test_p3p_finds_the_true_pose_among_its_solutions():
    for seed in range(50):
        X, x, R, t, _ = _scene(3, seed=seed)
        rays = torch.cat([x, torch.ones(3, 1, **DOUBLE)], -1) @ torch.linalg.inv(K).T
        Rs, ts, valid = p3p(X, rays / rays.norm(dim=-1, keepdim=True))
        errors = rotation_angle(Rs, R[None]) + (ts - t).norm(dim=-1)
        assert errors[valid].min() < 1e-6, seed


def test_refine_pose_recovers_a_perturbed_pose():
    X, x, R, t, _ = _scene(60)
    R0 = axis_angle_to_rotation(torch.tensor([0.02, -0.01, 0.015], **DOUBLE)) @ R
    R1, t1, result = refine_pose(R0[None], (t + 0.05)[None], X[None], x[None], K[None], torch.ones(1, 60, **DOUBLE), LMConfig())
    assert_close(R1[0], R, rtol=0, atol=1e-9)
    assert_close(t1[0], t, rtol=0, atol=1e-9)


@pytest.mark.parametrize("solver", ["p3p", "dlt"])
def test_estimate_absolute_pose_with_planted_outliers(solver):
    X, x, R, t, truth = _scene(200, outliers=0.5, seed=3)
    config = torchsfm.with_overrides(torchsfm.Config(), [f"resection.solver={solver}"])
    pose = torchsfm.estimate_absolute_pose(X, x, K, config=config, generator=torch.Generator().manual_seed(0))
    assert torch.equal(pose.inlier_mask, truth)
    assert_close(pose.R, R, rtol=0, atol=1e-8)
    assert_close(pose.t, t, rtol=0, atol=1e-8)


def test_a_scene_far_from_the_origin_is_scored_as_well():
    """RANSAC scores in float32 with the points taken about one of them: a scene 10⁶ m from the
    world origin (where float32 world coordinates alone would be off by ~0.06 m, ~7 px here)
    gives the exact inliers of the same scene at the origin, its rotation to 1e-6 and its camera
    centre to 1 mm (float64 itself keeps only ~1e-10 m per operation at 2·10⁶ m)."""
    X, x, R, t, truth = _scene(200, outliers=0.5, seed=3)
    offset = torch.tensor([1e6, -2e6, 5e5], **DOUBLE)
    pose = torchsfm.estimate_absolute_pose(X + offset, x, K, generator=torch.Generator().manual_seed(0))
    assert torch.equal(pose.inlier_mask, truth)
    assert_close(pose.R, R, rtol=0, atol=1e-6)
    assert_close(-pose.R.T @ pose.t, -R.T @ t + offset, rtol=0, atol=1e-3)


def test_noisy_pose_accuracy():
    errors = []
    for seed in range(10):
        X, x, R, t, _ = _scene(300, noise=0.5, outliers=0.3, seed=seed)
        pose = torchsfm.estimate_absolute_pose(X, x, K, generator=torch.Generator().manual_seed(seed))
        errors.append(float(rotation_angle(pose.R, R)))
    assert torch.tensor(errors).median() < 0.05


def test_bad_input():
    X, x, _, _, _ = _scene(20)
    with pytest.raises(NotEnoughDataError, match="at least 6, got 5"):
        torchsfm.estimate_absolute_pose(X[:5], x[:5], K)
    with pytest.raises(NotEnoughDataError, match="at least 6, got 0"):
        torchsfm.estimate_absolute_pose(X[:0], x[:0], K)
    with pytest.raises(ShapeError):
        torchsfm.estimate_absolute_pose(X, x[:10], K)
    with pytest.raises(DegenerateConfigurationError, match="K is singular"):
        torchsfm.estimate_absolute_pose(X, x, torch.zeros(3, 3, **DOUBLE))


def test_points_on_one_line_are_refused_by_name_not_answered_with_a_pose():
    """30 points along one line, seen exactly: every pose turned about the line fits them. The
    error says so (in float32 input too, where rounding takes them off the line and RANSAC would
    return one of those poses); in a ragged batch (float32 again) that problem alone fails."""
    along = torch.linspace(-1.0, 1.0, 30, **DOUBLE)[:, None]
    X = torch.tensor([0.2, -0.1, 5.0], **DOUBLE) + along * torch.tensor([1.0, 0.5, 1.0], **DOUBLE)
    x = (X @ K.T)[:, :2] / (X @ K.T)[:, 2:]
    for dtype in (torch.float64, torch.float32):
        with pytest.raises(DegenerateConfigurationError, match="30 3-D points lie on one line"):
            torchsfm.estimate_absolute_pose(X.to(dtype), x.to(dtype), K.to(dtype), generator=torch.Generator().manual_seed(0))
    good_X, good_x, _, _, _ = _scene(30)
    poses = torchsfm.estimate_absolute_pose(torch.stack([good_X, X]).float(), torch.stack([good_x, x]).float(), K.float(),
                                            valid=torch.ones(2, 30, dtype=torch.bool), generator=torch.Generator().manual_seed(0))
    assert poses.success.tolist() == [True, False]


def test_p3p_degenerate_samples_are_invalid_not_fatal():
    """Regression: coincident 3-D points once fed a non-finite companion matrix to LAPACK (a
    segmentation fault). They come back invalid, and so do collinear ones (a family of poses
    about their line: no frame of the triangle to map), without error."""
    X = torch.tensor([[[0.0, 0.0, 5.0]] * 3, [[0.0, 0.0, 5.0], [1.0, 0.0, 5.0], [2.0, 0.0, 5.0]]], dtype=torch.float64)
    bearings = X / X.norm(dim=-1, keepdim=True)
    R, t, valid = p3p(X, bearings)
    assert not valid.any()
    assert torch.isfinite(R).all() and torch.isfinite(t).all()


def test_p3p_poses_are_rotations_that_map_the_sample_exactly():
    """Each valid solution is a proper rotation (float64, 1e-12) and maps the three world points
    onto their bearing rays, over many random noise-free samples at once: the sine of the angle to
    the ray is below 1e-12 for the median solution and below 1e-5 for all (a root near a double
    root of the quartic comes out of the eigenvalue solver less accurate: 2 of 423 here above 1e-9)."""
    g = torch.Generator().manual_seed(1)
    X = torch.randn(200, 3, 3, generator=g, **DOUBLE) + torch.tensor([0.0, 0.0, 6.0], **DOUBLE)
    bearings = X / X.norm(dim=-1, keepdim=True)
    R, t, valid = p3p(X, bearings)
    assert valid.any(-1).all()
    R, t, sample = R[valid], t[valid], valid.nonzero()[:, 0]  # each solution and the sample it solves
    eye = torch.eye(3, **DOUBLE).expand_as(R)
    assert_close(R @ R.transpose(-1, -2), eye, rtol=0, atol=1e-12)
    assert_close(torch.linalg.det(R), torch.ones(R.shape[0], **DOUBLE), rtol=0, atol=1e-12)
    mapped = X[sample] @ R.transpose(-1, -2) + t[:, None]
    directions = mapped / mapped.norm(dim=-1, keepdim=True)
    sines = torch.linalg.cross(directions, bearings[sample]).norm(dim=-1).amax(-1)
    assert sines.median() < 1e-12 and sines.max() < 1e-5


def test_estimate_absolute_pose_with_half_the_points_identical():
    """The reported crash: half the 3-D points identical. The pose comes back from the others."""
    g = torch.Generator().manual_seed(0)
    X = torch.randn(40, 3, generator=g, dtype=torch.float64) + torch.tensor([0.0, 0.0, 6.0], dtype=torch.float64)
    X[20:] = X[0]
    K = torch.tensor([[500.0, 0, 320], [0, 500, 240], [0, 0, 1]], dtype=torch.float64)
    x = X @ K.T
    pose = torchsfm.estimate_absolute_pose(X, x[:, :2] / x[:, 2:], K, generator=g)
    torch.testing.assert_close(pose.R, torch.eye(3, dtype=torch.float64), atol=1e-8, rtol=0)


def test_ragged_batch_is_exact_per_problem_and_survives_a_bad_one():
    """Problems of 200 and 80 pairs (50 % / 30 % outliers) and one of 4 pairs, padded with NaN to
    200 in one call: the first two recover the pose exactly with the planted outliers found, the
    third reports failure instead of raising."""
    scenes = [_scene(200, outliers=0.5, seed=3), _scene(80, outliers=0.3, seed=5)]
    X = torch.full((3, 200, 3), float("nan"), **DOUBLE)
    x = torch.full((3, 200, 2), float("nan"), **DOUBLE)
    valid = torch.zeros(3, 200, dtype=torch.bool)
    for b, (Xb, xb, _, _, _) in enumerate(scenes):
        n = Xb.shape[0]
        X[b, :n], x[b, :n], valid[b, :n] = Xb, xb, True
    X[2, :4], x[2, :4], valid[2, :4] = scenes[1][0][-4:], scenes[1][1][-4:], True
    pose = torchsfm.estimate_absolute_pose(X, x, K, valid=valid, generator=torch.Generator().manual_seed(0))
    assert pose.success.tolist() == [True, True, False]
    for b, (Xb, _, R, t, truth) in enumerate(scenes):
        n = Xb.shape[0]
        assert torch.equal(pose.inlier_mask[b, :n], truth) and not pose.inlier_mask[b, n:].any()
        assert_close(pose.R[b], R, rtol=0, atol=1e-8)
        assert_close(pose.t[b], t, rtol=0, atol=1e-8)
    assert not pose.inlier_mask[2].any() and torch.isfinite(pose.R).all() and torch.isfinite(pose.t).all()
    with pytest.raises(ShapeError, match="valid"):
        torchsfm.estimate_absolute_pose(X, x, K, valid=valid[:, :10])
