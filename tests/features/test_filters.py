"""The slice-arithmetic filters give Kornia's and torch's results."""

import kornia
import pytest
import torch
import torch.nn.functional as F

from torchsfm.features.filters import central_differences, sobel_gradients, sobel_second_derivatives, window_maximum

SHAPES = [(2, 1, 37, 53), (1, 1, 2, 3), (3, 5, 9)]  # batched, smaller than a kernel, other leading dimensions


def as_batch(image: torch.Tensor) -> torch.Tensor:
    """Any (..., H, W) as Kornia's (B, 1, H, W)."""
    return image.reshape(-1, 1, *image.shape[-2:])


@pytest.mark.parametrize("shape", SHAPES)
def test_sobel_gradients_are_kornias(shape):
    image = torch.rand(shape, generator=torch.Generator().manual_seed(0), dtype=torch.float64)
    expected = kornia.filters.spatial_gradient(as_batch(image), normalized=True)[:, 0]  # (B, 2, H, W)
    dx, dy = sobel_gradients(image)
    torch.testing.assert_close(torch.stack([as_batch(dx)[:, 0], as_batch(dy)[:, 0]], 1), expected, rtol=0, atol=1e-12)


@pytest.mark.parametrize("shape", SHAPES)
def test_central_differences_are_kornias(shape):
    """Float32 (as the SIFT descriptor uses them): bit for bit Kornia's, the halving being exact."""
    image = torch.rand(shape, generator=torch.Generator().manual_seed(2))
    expected = kornia.filters.spatial_gradient(as_batch(image), mode="diff")[:, 0]  # (B, 2, H, W)
    dx, dy = central_differences(image)
    assert torch.equal(torch.stack([as_batch(dx)[:, 0], as_batch(dy)[:, 0]], 1), expected)


@pytest.mark.parametrize("shape", SHAPES)
def test_second_derivatives_are_kornias(shape):
    image = torch.rand(shape, generator=torch.Generator().manual_seed(1), dtype=torch.float64)
    expected = kornia.filters.spatial_gradient(as_batch(image), order=2, normalized=False)[:, 0]  # xx, xy, yy
    ours = torch.stack([as_batch(d)[:, 0] for d in sobel_second_derivatives(image)], 1)
    torch.testing.assert_close(ours, expected, rtol=0, atol=1e-12)


def test_a_ramp_has_its_slope():
    y, x = torch.meshgrid(torch.arange(6.0), torch.arange(7.0), indexing="ij")
    dx, dy = sobel_gradients(0.5 * x - 2 * y)
    torch.testing.assert_close(dx[1:-1, 1:-1], torch.full((4, 5), 0.5), rtol=0, atol=1e-6)
    torch.testing.assert_close(dy[1:-1, 1:-1], torch.full((4, 5), -2.0), rtol=0, atol=1e-6)


@pytest.mark.parametrize("radius", [0, 1, 2, 3, 5])
@pytest.mark.parametrize("shape", SHAPES)
def test_window_maximum_is_max_pool(shape, radius):
    image = torch.rand(shape, generator=torch.Generator().manual_seed(radius))
    batch = as_batch(image)
    expected = F.max_pool2d(batch, 2 * radius + 1, stride=1, padding=radius) if radius else batch
    assert torch.equal(as_batch(window_maximum(image, radius)), expected)
