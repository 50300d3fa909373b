"""The five-point essential matrix: exact on noise-free data, every real solution an essential
matrix that fits the five correspondences."""

import torch
from torch.testing import assert_close

from torchsfm.geometry.essential import essential_from_pose
from torchsfm.geometry.five_point import MAX_SOLUTIONS, five_point_essential
from torchsfm.geometry.rotation import axis_angle_to_rotation


def _views(batch: int, seed: int):
    """(batch, 5) points 4–8 m in front of a camera and of a second one moved by a random pose:
    normalized coordinates x1, x2 and the true unit-norm E."""
    g = torch.Generator().manual_seed(seed)
    R = axis_angle_to_rotation(0.3 * torch.randn(batch, 3, generator=g, dtype=torch.float64))
    t = torch.nn.functional.normalize(torch.randn(batch, 3, generator=g, dtype=torch.float64), dim=-1)
    X = torch.rand(batch, 5, 3, generator=g, dtype=torch.float64) * torch.tensor([4.0, 4.0, 4.0], dtype=torch.float64) \
        + torch.tensor([-2.0, -2.0, 4.0], dtype=torch.float64)
    Y = X @ R.transpose(-1, -2) + t[:, None]
    E = essential_from_pose(R, t)
    return X[..., :2] / X[..., 2:], Y[..., :2] / Y[..., 2:], E / E.flatten(1).norm(dim=1)[:, None, None]


def test_the_true_essential_matrix_is_among_the_solutions():
    """200 random configurations: one real solution equals the true E (up to sign) to 1e-8."""
    x1, x2, truth = _views(200, 0)
    E, real = five_point_essential(x1, x2)
    assert E.shape == (200, MAX_SOLUTIONS, 3, 3) and real.shape == (200, MAX_SOLUTIONS)
    distance = torch.minimum((E - truth[:, None]).flatten(2).norm(dim=-1), (E + truth[:, None]).flatten(2).norm(dim=-1))
    best = torch.where(real, distance, torch.inf).min(1).values
    assert_close(best, torch.zeros(200, dtype=torch.float64), rtol=0, atol=1e-8)
    assert bool((real.sum(1) % 2 == 0).all())  # complex solutions come in conjugate pairs


def test_every_real_solution_is_essential_and_fits_the_points():
    """Each real solution: x2ᵀ E x1 = 0 on the five pairs, singular values (s, s, 0), unit norm;
    the others are NaN."""
    x1, x2, _ = _views(100, 1)
    E, real = five_point_essential(x1, x2)
    h1 = torch.cat([x1, torch.ones_like(x1[..., :1])], -1)
    h2 = torch.cat([x2, torch.ones_like(x2[..., :1])], -1)
    solutions = E[real]  # (S, 3, 3)
    owner = torch.nonzero(real)[:, 0]
    residual = torch.einsum("sni,sij,snj->sn", h2[owner], solutions, h1[owner])
    assert_close(residual, torch.zeros_like(residual), rtol=0, atol=1e-10)
    singular = torch.linalg.svdvals(solutions)
    assert_close(singular[:, 0], singular[:, 1], rtol=0, atol=1e-8)
    assert_close(singular[:, 2], torch.zeros_like(singular[:, 2]), rtol=0, atol=1e-8)
    assert_close(solutions.flatten(1).norm(dim=1), torch.ones(len(solutions), dtype=torch.float64), rtol=0, atol=1e-12)
    assert bool(torch.isnan(E[~real]).all())
