"""The one guard of every division by a non-negative quantity that may be zero."""

from __future__ import annotations

import torch
from torch import Tensor


def floor_tiny(x: Tensor) -> Tensor:
    """``x`` clamped below at the smallest positive normal number of its dtype (a fixed constant
    such as 1e-300 is 0 in float32, where it would guard nothing)."""
    return x.clamp_min(torch.finfo(x.dtype).tiny)
