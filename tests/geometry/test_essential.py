import pytest
import torch
from torch.testing import assert_close

from torchsfm.camera import pixels_to_normalized
from torchsfm.geometry.essential import (
    POSE_CANDIDATES,
    cheirality_counts,
    essential_from_fundamental,
    essential_from_pose,
    parallax_from_infinity,
    parallax_is_noise,
    select_pose,
    two_view_depths,
)
from torchsfm.geometry.fundamental import eight_point
from torchsfm.testing import synthetic_two_view

DOUBLE = dict(dtype=torch.float64)


def _normalized(scene):
    return pixels_to_normalized(scene.x1, scene.K1), pixels_to_normalized(scene.x2, scene.K2)


def test_essential_from_fundamental_is_the_true_essential():
    scene = synthetic_two_view(20, seed=0)
    E = essential_from_fundamental(scene.F, scene.K1, scene.K2)
    reference = essential_from_pose(scene.R, scene.t)
    reference = reference * (2**0.5 / reference.norm())
    sign = torch.sign((E * reference).sum())
    assert_close(E * sign, reference, rtol=0, atol=1e-10)
    assert_close(torch.linalg.svdvals(E), torch.tensor([1.0, 1.0, 0.0], **DOUBLE), rtol=0, atol=1e-10)


@pytest.mark.parametrize("method", sorted(POSE_CANDIDATES))
@pytest.mark.parametrize("seed", [0, 1, 2])
def test_every_decomposition_recovers_the_pose_exactly(method, seed):
    scene = synthetic_two_view(50, seed=seed)
    E = essential_from_fundamental(scene.F, scene.K1, scene.K2)
    R, t = POSE_CANDIDATES[method](E)
    assert R.shape == (4, 3, 3) and t.shape == (4, 3)
    R_best, t_best, in_front = select_pose(R, t, *_normalized(scene))
    assert_close(R_best, scene.R, rtol=0, atol=1e-8)
    assert_close(t_best, scene.t, rtol=0, atol=1e-8)
    assert in_front == 1.0


def test_cheirality_separates_the_four_candidates():
    scene = synthetic_two_view(30, seed=5)
    R, t = POSE_CANDIDATES["svd"](essential_from_fundamental(scene.F, scene.K1, scene.K2))
    counts = cheirality_counts(R, t, *_normalized(scene))
    assert sorted(counts.tolist())[-1] == 30 and sorted(counts.tolist())[-2] < 30


def test_depths_in_closed_form():
    scene = synthetic_two_view(30, seed=6)
    depth1, depth2 = two_view_depths(scene.R, scene.t, *_normalized(scene))
    assert_close(depth1, scene.points3d[:, 2], rtol=1e-10, atol=0)
    assert_close(depth2, (scene.points3d @ scene.R.T + scene.t)[:, 2], rtol=1e-10, atol=0)


def test_parallax_from_infinity_is_positive_in_front_zero_at_infinity_and_negative_behind():
    """Exact on a noise-free pair: each point X in front of both cameras, its mirror image −X
    behind both (the same image in camera 1, and on the same epipolar line in camera 2), and a
    point at infinity (camera 2 sees it at R x̃1). The parallax's size is the distance from that
    image along the line: |parallax| = ‖x2 − p∞‖ for points on the line."""
    scene = synthetic_two_view(30, seed=7)
    n1, n2 = _normalized(scene)
    ray = torch.cat([n1, torch.ones_like(n1[:, :1])], -1) @ scene.R.T
    at_infinity = ray[:, :2] / ray[:, 2:]
    in_front = parallax_from_infinity(scene.R, scene.t, n1, n2)
    assert bool((in_front > 0).all())
    assert_close(in_front, (n2 - at_infinity).norm(dim=-1), rtol=1e-10, atol=0)
    mirrored = -scene.points3d @ scene.R.T + scene.t  # -X in camera 2: behind camera 1 (depth -Z) and camera 2
    assert bool((mirrored[:, 2] < 0).all())
    behind = parallax_from_infinity(scene.R, scene.t, n1, mirrored[:, :2] / mirrored[:, 2:])
    assert bool((behind < 0).all())
    assert_close(parallax_from_infinity(scene.R, scene.t, n1, at_infinity), torch.zeros(30, **DOUBLE), rtol=0, atol=1e-12)
    assert_close(parallax_from_infinity(scene.R, torch.zeros(3, **DOUBLE), n1, n2), torch.zeros(30, **DOUBLE), rtol=0, atol=0)


@pytest.mark.parametrize("case, undetermined", [
    ("noise", True),  # every parallax within the bound (2.33 px for a 1 px threshold, α = 0.001)
    ("noise and mismatches on both sides", True),  # 10 %, beyond the bound: 5 ahead, 5 behind
    ("a near minority in front", False),  # 30 % beyond the bound, all ahead: the sign test finds them
    ("large parallax on both sides", False),  # the median beyond the bound: not "no parallax" (a false pair)
])
def test_parallax_is_noise_tells_a_rotation_from_a_translation(case, undetermined):
    """R = I, t along x, K = I: each point's parallax is its x displacement, set per case."""
    g = torch.Generator().manual_seed(0)
    n = 100
    parallax = 0.3 * torch.randn(n, generator=g, dtype=torch.float64)
    if case == "noise and mismatches on both sides":
        parallax[:10] = torch.tensor([6.0, -7.0] * 5, dtype=torch.float64)
    elif case == "a near minority in front":
        parallax[:30] = 5 + 10 * torch.rand(30, generator=g, dtype=torch.float64)
    elif case == "large parallax on both sides":
        parallax = torch.where(torch.arange(n) % 2 == 0, -8.0, 8.0).double()
    x1 = 100 * torch.rand(1, n, 2, generator=g, dtype=torch.float64)
    x2 = x1 + torch.stack([parallax, torch.zeros(n, dtype=torch.float64)], -1)[None]
    eye = torch.eye(3, dtype=torch.float64)[None]
    result, median = parallax_is_noise(eye, torch.tensor([[1.0, 0.0, 0.0]], dtype=torch.float64), x1, x2, eye, eye,
                                       torch.ones(1, n, dtype=torch.bool), 1.0, 1e-3)
    assert result.tolist() == [undetermined]
    assert_close(median, parallax.abs().sort().values[(n - 1) // 2][None], rtol=0, atol=1e-12)  # the lower middle; x2 - x1 rounds


def test_methods_agree_on_a_noisy_rank2_E():
    """On a rank-2 E all three decompositions are the same orthogonal Procrustes answer (they
    differ only on a rank-3 E, see examples/essential_methods.py)."""
    for seed in range(5):
        scene = synthetic_two_view(100, noise=1.0, seed=seed)
        E = essential_from_fundamental(eight_point(scene.x1, scene.x2), scene.K1, scene.K2)
        poses = {method: select_pose(*candidates(E), *_normalized(scene))[:2] for method, candidates in POSE_CANDIDATES.items()}
        for method in ("linear", "quaternion"):
            assert_close(poses[method][0], poses["svd"][0], rtol=0, atol=1e-9)
            assert_close(poses[method][1], poses["svd"][1], rtol=0, atol=1e-9)
