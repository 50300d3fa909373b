"""The division guard holds in float32 too (a constant 1e-300 is 0 there); graph components."""

import pytest
import torch

from torchsfm.geometry.essential import project_to_essential
from torchsfm.geometry.fundamental import normalize_scale
from torchsfm.numerics import component_labels, floor_tiny


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_floor_tiny_is_positive_in_every_dtype(dtype):
    assert float(floor_tiny(torch.zeros((), dtype=dtype))) == torch.finfo(dtype).tiny > 0


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_a_zero_matrix_normalizes_to_zero_not_nan(dtype):
    zero = torch.zeros(2, 3, 3, dtype=dtype)
    assert torch.equal(normalize_scale(zero), zero)
    assert torch.isfinite(project_to_essential(zero)).all()


def test_component_labels_name_each_component_by_its_smallest_node():
    """A path 9-8-7-6-5 given from its far end (labels travel four steps), a pair, a triangle
    given twice, and a node without edges."""
    first = torch.tensor([9, 8, 7, 6, 0, 3, 4, 10, 4])
    second = torch.tensor([8, 7, 6, 5, 2, 4, 10, 3, 3])
    expected = torch.tensor([0, 1, 0, 3, 3, 5, 5, 5, 5, 5, 3])
    torch.testing.assert_close(component_labels(first, second, 11), expected, rtol=0, atol=0)
    torch.testing.assert_close(component_labels(first[:0], second[:0], 3), torch.arange(3), rtol=0, atol=0)
