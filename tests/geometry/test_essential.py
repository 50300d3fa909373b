import pytest
import torch
from torch.testing import assert_close

from torchsfm.camera import pixels_to_normalized
from torchsfm.geometry.essential import (
    POSE_CANDIDATES,
    cheirality_counts,
    essential_from_fundamental,
    essential_from_pose,
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
