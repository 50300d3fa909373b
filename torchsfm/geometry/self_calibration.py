"""Focal length from fundamental matrices (self-calibration with a known principal point).

For a camera with intrinsics K = [[f, 0, cx], [0, f, cy], [0, 0, 1]] shared by two views, the
essential matrix E = Kᵀ F K has two equal non-zero singular values. Mendonça & Cipolla (1999):
the focal length is the f that makes the normalized gap (σ1 − σ2) / (σ1 + σ2) smallest, summed
over many view pairs (robustly: the median over pairs). A 1-D search over log f (a coarse grid,
then golden-section refinement) needs no derivative and no starting point beyond a range.

Motions that leave f free are detected, not guessed at: for a camera translating without turning
(e.g. driving straight) F = [e]x with the epipole e, and Mᵀ [e]x M = det(M) [M⁻¹ e]x is an
essential matrix for every candidate K (M = K), so the gap is flat over the whole range. f is
taken as determined only where a focal length wrong by the range's factor opens the gap, at one
end at least, to ``IDENTIFIABLE_RATIO`` times its minimum plus ``GAP_RESOLUTION`` (for a general
motion it grows from noise level to order one).
"""

from __future__ import annotations

import math
from collections.abc import Callable

import torch
from torch import Tensor

from torchsfm.numerics import floor_tiny

IDENTIFIABLE_RATIO = 2.0  # the gap at the range's worse end over its minimum, at least, where f is determined
GAP_RESOLUTION = 1e-6  # gaps closer than this are equal: rounding of an exact essential matrix, far below a measured F's


def intrinsics(focal: float | Tensor, principal_point: Tensor) -> Tensor:
    """K (3, 3) of square pixels, zero skew: focal (px), principal point (2,)."""
    K = torch.eye(3, dtype=torch.float64, device=principal_point.device)
    K[0, 0] = K[1, 1] = float(focal)
    K[:2, 2] = principal_point.double()
    return K


def singular_value_gap(F: Tensor, focal: Tensor, principal_point: Tensor) -> Tensor:
    """(σ1 − σ2) / (σ1 + σ2) of E = Kᵀ F K for P pairs F (P, 3, 3) and G candidate focal lengths
    (G,): (G, P)."""
    K = torch.zeros(focal.shape[0], 3, 3, dtype=torch.float64, device=F.device)
    K[:, 0, 0] = K[:, 1, 1] = focal.double()
    K[:, :2, 2] = principal_point.double()
    K[:, 2, 2] = 1
    E = K[:, None].transpose(-1, -2) @ F.double()[None] @ K[:, None]  # (G, P, 3, 3)
    sigma = torch.linalg.svdvals(E)
    return (sigma[..., 0] - sigma[..., 1]) / floor_tiny((sigma[..., 0] + sigma[..., 1]))


def focal_from_fundamentals(F: Tensor, principal_point: Tensor, prior: float, *, spread: float = 4.0,
                            steps: int = 64, refinements: int = 30) -> float | None:
    """The focal length (px) minimizing the median singular-value gap over the pairs F (P, 3, 3),
    searched in [prior / spread, prior × spread] (log grid of ``steps``, then golden section);
    None where the pairs do not determine it (a flat gap: see the module docstring)."""
    def cost(focal: Tensor) -> Tensor:
        return singular_value_gap(F, focal, principal_point).median(dim=1).values

    grid = prior * torch.logspace(-math.log10(spread), math.log10(spread), steps, dtype=torch.float64, device=F.device)
    costs = cost(grid)
    if float(torch.maximum(costs[0], costs[-1])) < IDENTIFIABLE_RATIO * float(costs.min()) + GAP_RESOLUTION:
        return None
    best = int(costs.argmin())
    low, high = math.log(float(grid[max(best - 1, 0)])), math.log(float(grid[min(best + 1, steps - 1)]))
    scalar = lambda log_focal: float(cost(torch.tensor([math.exp(log_focal)], dtype=torch.float64, device=F.device))[0])  # noqa: E731
    return math.exp(golden_section(scalar, low, high, refinements))


def golden_section(cost: Callable[[float], float], low: float, high: float, steps: int) -> float:
    """The minimizer of a unimodal ``cost`` on [low, high] by golden-section search: ``steps``
    shrinkings (each one new evaluation), the middle of the last interval."""
    ratio = (math.sqrt(5) - 1) / 2
    a, b = high - ratio * (high - low), low + ratio * (high - low)
    cost_a, cost_b = cost(a), cost(b)
    for _ in range(steps):
        if cost_a < cost_b:
            high, b, cost_b = b, a, cost_a
            a = high - ratio * (high - low)
            cost_a = cost(a)
        else:
            low, a, cost_a = a, b, cost_b
            b = low + ratio * (high - low)
            cost_b = cost(b)
    return (low + high) / 2
