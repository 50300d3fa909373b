"""Every public estimator runs where its inputs live and answers there (CPU always; CUDA where
available — never required)."""

from __future__ import annotations

import pytest
import torch

import torchsfm
from torchsfm.testing import synthetic_moving_scene

DEVICES = ["cpu", pytest.param("cuda", marks=pytest.mark.skipif(not torch.cuda.is_available(), reason="no CUDA device here"))]
K = torch.tensor([[500.0, 0.0, 320.0], [0.0, 500.0, 240.0], [0.0, 0.0, 1.0]], dtype=torch.float64)


def _two_views(device: str, n: int = 80):
    g = torch.Generator().manual_seed(0)
    X = torch.randn(n, 3, generator=g, dtype=torch.float64) + torch.tensor([0.0, 0.0, 6.0], dtype=torch.float64)
    x1 = X @ K.T
    x2 = (X - torch.tensor([1.0, 0.1, 0.0], dtype=torch.float64)) @ K.T
    return X.to(device), (x1[:, :2] / x1[:, 2:]).to(device), (x2[:, :2] / x2[:, 2:]).to(device)


@pytest.fixture(params=DEVICES)
def device(request) -> str:
    return request.param


def _on(device: str, *tensors: torch.Tensor) -> bool:
    return all(t.device.type == device for t in tensors)


def test_estimators_stay_on_the_device(device):
    X, x1, x2 = _two_views(device)
    Kd = K.to(device)
    generator = torch.Generator(device=device).manual_seed(0)
    fundamental = torchsfm.estimate_fundamental(x1, x2, generator=generator)
    assert _on(device, fundamental.F, fundamental.inlier_mask) and bool(fundamental.inlier_mask.all())
    pose = torchsfm.estimate_relative_pose(x1, x2, Kd, Kd, generator=generator)
    assert _on(device, pose.R, pose.t, pose.inlier_mask)
    torch.testing.assert_close(pose.R.cpu(), torch.eye(3, dtype=torch.float64), atol=1e-8, rtol=0)
    P1 = torch.cat([Kd, torch.zeros(3, 1, dtype=torch.float64, device=device)], dim=1)
    P2 = Kd @ torch.cat([torch.eye(3, dtype=torch.float64, device=device), -torch.tensor([[1.0], [0.1], [0.0]], dtype=torch.float64, device=device)], dim=1)
    points = torchsfm.triangulate(x1, x2, P1, P2)
    assert _on(device, points)
    torch.testing.assert_close(points, X, atol=1e-8, rtol=0)
    absolute = torchsfm.estimate_absolute_pose(X, x1, Kd, generator=generator)
    assert _on(device, absolute.R, absolute.t)
    torch.testing.assert_close(absolute.R.cpu(), torch.eye(3, dtype=torch.float64), atol=1e-8, rtol=0)


def test_ragged_batches_stay_on_the_device(device):
    X, x1, x2 = _two_views(device)
    valid = torch.ones(2, X.shape[0], dtype=torch.bool, device=device)
    valid[1, 50:] = False
    Kd = K.to(device)
    batch = [t.expand(2, *t.shape).clone() for t in (X, x1, x2)]
    for result in (torchsfm.estimate_fundamental(batch[1], batch[2], valid=valid, generator=torch.Generator(device=device).manual_seed(0)),
                   torchsfm.estimate_relative_pose(batch[1], batch[2], Kd, Kd, valid=valid,
                                                   generator=torch.Generator(device=device).manual_seed(0)),
                   torchsfm.estimate_absolute_pose(batch[0], batch[1], Kd, valid=valid,
                                                   generator=torch.Generator(device=device).manual_seed(0))):
        assert _on(device, result.inlier_mask, result.success) and result.success.tolist() == [True, True]
        assert torch.equal(result.inlier_mask, valid)


def test_moving_object_rejection_stays_on_the_device(device):
    scene = synthetic_moving_scene(0, num_frames=3)
    tracks = scene.tracks.to(device)
    result = torchsfm.reject_moving_objects(*tracks, generator=torch.Generator(device=device).manual_seed(0))
    assert _on(device, result.background_mask)
    whole = torchsfm.reject_moving_objects_in_tracks(tracks, generator=torch.Generator(device=device).manual_seed(0))
    assert _on(device, whole.background_mask, whole.tested)
    config = torchsfm.with_overrides(torchsfm.Config(), ["moving_objects.track_method=both"])
    votes = torchsfm.reject_moving_objects_in_tracks(tracks, config=config, generator=torch.Generator(device=device).manual_seed(0))
    assert _on(device, votes.background_mask, votes.rejection_share)


def test_bundle_adjustment_stays_on_the_device(device):
    X, x1, x2 = _two_views(device, n=40)
    R = torch.eye(3, dtype=torch.float64, device=device).repeat(2, 1, 1)
    t = torch.tensor([[0.0, 0.0, 0.0], [-1.0, -0.1, 0.0]], dtype=torch.float64, device=device)
    problem = torchsfm.BundleProblem(
        camera_model="pinhole", rotations=R, translations=t, intrinsics=K.to(device).expand(2, 3, 3),
        points=X + 0.01, camera_index=torch.arange(2, device=device).repeat_interleave(40),
        point_index=torch.arange(40, device=device).repeat(2), observations=torch.cat([x1, x2]),
        fixed_cameras=torch.tensor([True, False], device=device))
    result = torchsfm.bundle_adjust(problem)
    assert _on(device, result.problem.points, result.problem.translations)
    assert result.final_cost < 1e-12
