import pytest
import torch

from torchsfm.robust.samplers import SAMPLERS, BucketedSampler


def _grid_points(n=400, seed=0):
    g = torch.Generator().manual_seed(seed)
    return torch.rand(2, n, 2, generator=g, dtype=torch.float64) * torch.tensor([640.0, 480.0], dtype=torch.float64)


@pytest.mark.parametrize("name", sorted(SAMPLERS))
def test_samples_are_distinct_valid_points(name):
    points = _grid_points()
    valid = torch.ones(2, 400, dtype=torch.bool)
    valid[1, 300:] = False  # padding of a shorter second problem
    sampler = SAMPLERS[name](points, valid, 8)
    indices = sampler.sample(256, 8, torch.Generator().manual_seed(1))
    assert indices.shape == (2, 256, 8)
    sorted_indices = indices.sort(-1).values
    assert (sorted_indices[..., 1:] != sorted_indices[..., :-1]).all()
    assert (indices[1] < 300).all()


def test_bucketed_samples_come_from_distinct_buckets():
    points = _grid_points()
    sampler = BucketedSampler(points, torch.ones(2, 400, dtype=torch.bool), 8)
    indices = sampler.sample(128, 8, torch.Generator().manual_seed(2))
    low, high = points.amin(1, keepdim=True), points.amax(1, keepdim=True)  # buckets span the bounding box
    cells = ((points - low) / (high - low) * 8).floor().clamp(0, 7)
    bucket = cells[..., 1] * 8 + cells[..., 0]
    chosen = torch.gather(bucket, 1, indices.reshape(2, -1)).reshape(2, 128, 8).sort(-1).values
    assert (chosen[..., 1:] != chosen[..., :-1]).all()


def test_bucket_probability_is_proportional_to_its_count():
    """A bucket holding half the points is drawn first about half the time."""
    crowded = torch.full((1, 300, 2), 5.0, dtype=torch.float64) + torch.rand(1, 300, 2, dtype=torch.float64, generator=torch.Generator().manual_seed(104))
    spread = torch.rand(1, 300, 2, dtype=torch.float64, generator=torch.Generator().manual_seed(105)) * 800
    points = torch.cat([crowded, spread], dim=1)
    points[0, 0] = torch.tensor([0.0, 0.0], dtype=torch.float64)
    points[0, 1] = torch.tensor([800.0, 800.0], dtype=torch.float64)
    sampler = BucketedSampler(points, torch.ones(1, 600, dtype=torch.bool), 8)
    first = sampler.sample(20000, 1, torch.Generator().manual_seed(3))[0, :, 0]
    fraction_crowded = (first < 300).double().mean().item()
    expected = (sampler.counts[0].max() / 600).item()
    assert abs(fraction_crowded - expected) < 0.02


def test_few_buckets_fall_back_to_uniform():
    points = torch.zeros(1, 20, 2, dtype=torch.float64)
    points[0, 10:] = 100.0  # two occupied buckets only
    sampler = BucketedSampler(points, torch.ones(1, 20, dtype=torch.bool), 8)
    indices = sampler.sample(50, 8, torch.Generator().manual_seed(4)).sort(-1).values
    assert (indices[..., 1:] != indices[..., :-1]).all()


def test_sampling_is_deterministic_given_a_seed():
    points = _grid_points()
    sampler = BucketedSampler(points, torch.ones(2, 400, dtype=torch.bool), 8)
    a = sampler.sample(64, 8, torch.Generator().manual_seed(5))
    b = sampler.sample(64, 8, torch.Generator().manual_seed(5))
    assert torch.equal(a, b)
