"""The division guard holds in float32 too (a constant 1e-300 is 0 there)."""

import pytest
import torch

from torchsfm.geometry.essential import project_to_essential
from torchsfm.geometry.fundamental import normalize_scale
from torchsfm.numerics import floor_tiny


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_floor_tiny_is_positive_in_every_dtype(dtype):
    assert float(floor_tiny(torch.zeros((), dtype=dtype))) == torch.finfo(dtype).tiny > 0


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_a_zero_matrix_normalizes_to_zero_not_nan(dtype):
    zero = torch.zeros(2, 3, 3, dtype=dtype)
    assert torch.equal(normalize_scale(zero), zero)
    assert torch.isfinite(project_to_essential(zero)).all()
