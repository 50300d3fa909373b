import math

import torch
from torch.testing import assert_close

from torchsfm.geometry.rotation import (
    angle_between,
    axis_angle_to_rotation,
    nearest_rotation,
    quaternion_to_rotation,
    rotation_angle,
    rotation_to_axis_angle,
    rotation_to_quaternion,
    skew,
)

DOUBLE = dict(dtype=torch.float64)


def _axis_angles(n=50, seed=0):
    g = torch.Generator().manual_seed(seed)
    omega = torch.randn(n, 3, generator=g, **DOUBLE)
    return omega / omega.norm(dim=-1, keepdim=True) * torch.rand(n, 1, generator=g, **DOUBLE) * 3.0


def test_skew_is_the_cross_product():
    a, b = torch.randn(5, 3, **DOUBLE, generator=torch.Generator().manual_seed(106)), torch.randn(5, 3, **DOUBLE, generator=torch.Generator().manual_seed(107))
    assert_close((skew(a) @ b[..., None]).squeeze(-1), torch.linalg.cross(a, b), rtol=0, atol=1e-14)
    # the errata's sign convention for Appendix E
    assert_close(skew(torch.tensor([1.0, 2.0, 3.0], **DOUBLE)), torch.tensor([[0, -3, 2], [3, 0, -1], [-2, 1, 0.0]], **DOUBLE))


def test_axis_angle_round_trip_and_orthogonality():
    omega = _axis_angles()
    R = axis_angle_to_rotation(omega)
    assert_close(R @ R.transpose(-1, -2), torch.eye(3, **DOUBLE).expand(50, 3, 3), rtol=0, atol=1e-14)
    assert_close(torch.linalg.det(R), torch.ones(50, **DOUBLE), rtol=0, atol=1e-14)
    assert_close(rotation_to_axis_angle(R), omega, rtol=0, atol=1e-10)


def test_small_angles_are_exact_and_differentiable_at_zero():
    omega = torch.tensor([[1e-9, -2e-9, 3e-9], [0.0, 0.0, 0.0]], **DOUBLE)
    assert_close(rotation_to_axis_angle(axis_angle_to_rotation(omega)), omega, rtol=0, atol=1e-15)
    _, tangent = torch.func.jvp(axis_angle_to_rotation, (torch.zeros(3, **DOUBLE),), (torch.tensor([1.0, 0, 0], **DOUBLE),))
    assert_close(tangent, skew(torch.tensor([1.0, 0, 0], **DOUBLE)))


def test_quaternion_round_trip():
    R = axis_angle_to_rotation(_axis_angles())
    q = rotation_to_quaternion(R)
    assert (q[:, 0] >= 0).all()
    assert_close(quaternion_to_rotation(q), R, rtol=0, atol=1e-13)


def test_nearest_rotation_and_angles():
    R = axis_angle_to_rotation(torch.tensor([0.0, 0.0, 0.1], **DOUBLE))
    assert_close(nearest_rotation(R + 1e-9), R, rtol=0, atol=1e-8)
    assert_close(rotation_angle(torch.eye(3, **DOUBLE), R), torch.tensor(math.degrees(0.1), **DOUBLE))
    a = torch.tensor([1.0, 0, 0], **DOUBLE)
    assert_close(angle_between(a, -a), torch.tensor(180.0, **DOUBLE))
    assert_close(angle_between(a, -a, unsigned_direction=True), torch.tensor(0.0, **DOUBLE))
