import collections
import itertools

import pytest
import torch

from torchsfm.robust.samplers import SAMPLERS, BucketedSampler, draws_without_replacement


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


def _sequential_law(weights: torch.Tensor, count: int) -> dict[tuple[int, ...], float]:
    """Probability of every ordered draw of ``count`` distinct indices, each ∝ its weight among
    the remaining."""
    law = {}
    for order in itertools.permutations(range(weights.numel()), count):
        probability, left = 1.0, float(weights.sum())
        for index in order:
            probability *= float(weights[index]) / left
            left -= float(weights[index])
        law[order] = probability
    return law


@pytest.mark.parametrize("weights, count", [([5.0, 3.0, 1.0, 1.0], 2),  # most rows complete in their first draws
                                            ([100.0, 100.0, 1e-3, 1e-3, 1e-3], 3),  # most rows go on without replacement
                                            ([1.0, 2.0, 3.0, 4.0, 5.0, 6.0], 4)])
def test_draws_without_replacement_follow_the_sequential_law(weights, count):
    """200 000 rows: every ordered draw's frequency within 5 standard errors of its probability
    (sequential draws, each ∝ its weight among the remaining: torch.multinomial's law)."""
    rows = 200_000
    weights = torch.tensor(weights, dtype=torch.float64)
    drawn = draws_without_replacement(weights.expand(rows, -1).contiguous(), count, torch.Generator().manual_seed(0))
    assert drawn.shape == (rows, count)
    assert bool((drawn.sort(1).values.diff(dim=1) > 0).all())  # distinct in every row
    frequency = collections.Counter(map(tuple, drawn.tolist()))
    for order, probability in _sequential_law(weights, count).items():
        error = (probability * (1 - probability) / rows) ** 0.5
        assert abs(frequency[order] / rows - probability) <= 5 * error + 1e-9, order
