"""Numeric helpers the batched engines share: the one guard of every division by a non-negative
quantity that may be zero, and the per-problem choice between two batched tensors."""

from __future__ import annotations

import torch
from torch import Tensor


def floor_tiny(x: Tensor) -> Tensor:
    """``x`` clamped below at the smallest positive normal number of its dtype (a fixed constant
    such as 1e-300 is 0 in float32, where it would guard nothing)."""
    return x.clamp_min(torch.finfo(x.dtype).tiny)


def where_per_problem(condition: Tensor, a: Tensor, b: Tensor) -> Tensor:
    """Per problem, ``a`` where the (B,) ``condition`` holds, else ``b``: two (B, *M) tensors."""
    return torch.where(condition.reshape(-1, *([1] * (a.dim() - 1))), a, b)
