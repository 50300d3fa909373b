"""Minimal-sample generators for the RANSAC engine, batched over problems and hypotheses.

A sampler is built once per RANSAC call from the points' image coordinates and validity mask and
then asked for ``(B, K, s)`` index tensors: K samples of s distinct valid points per problem.
"""

from __future__ import annotations

import torch
from torch import Tensor


def resolve_generator(generator: torch.Generator | None, device: torch.device | str = "cpu") -> torch.Generator:
    """The one randomness policy: the caller's generator, or one seeded with 0 (reproducible)."""
    return generator if generator is not None else torch.Generator(device=device).manual_seed(0)


def side_generator(generator: torch.Generator | None) -> torch.Generator | None:
    """A new generator seeded as ``generator`` was (None stays None): draws made from it leave
    the caller's stream as it would be without them (an optional search must not change what
    follows it)."""
    return None if generator is None else torch.Generator(generator.device).manual_seed(generator.initial_seed())


def _weighted_top_k(weights: Tensor, k: int, generator: torch.Generator | None) -> Tensor:
    """Indices of k draws without replacement, each ∝ its weight among the remaining.

    Efraimidis & Spirakis (2006): keep the k largest keys log(u) / w, u ~ U(0, 1); a zero
    weight gets key -inf and is never drawn while others remain. weights (*, M) -> (*, k).
    """
    u = torch.rand(weights.shape, generator=generator, dtype=torch.float32, device=weights.device)
    return torch.topk(torch.log(u.clamp_min(1e-30)) / weights, k, dim=-1).indices


def draws_without_replacement(weights: Tensor, count: int, generator: torch.Generator | None) -> Tensor:
    """Indices of ``count`` draws without replacement from each row of (R, M) positive weights,
    each ∝ its weight among the remaining (``torch.multinomial`` without replacement): (R, count).

    Draws with replacement where each repeat is discarded have the same law — a draw conditioned
    on being new is ∝ the remaining weights — and cost a tenth as much (one binary search per
    draw, not a pass over the row). Each row draws 2 ``count`` so; a row that sees fewer than
    ``count`` distinct indices among them (weight on a few entries) goes on from the ones it has,
    without replacement over the rest. (:func:`_weighted_top_k` draws the same law by sorted keys,
    a pass over every row; the RANSAC samplers keep it, for their seeded draws to stay as they are.)
    """
    R = weights.shape[0]
    draws = torch.multinomial(weights, 2 * count, replacement=True, generator=generator)  # (R, 2 count)
    new = ~torch.tril(draws[:, :, None] == draws[:, None, :], diagonal=-1).any(2)  # not a repeat of an earlier draw
    rank = new.cumsum(1)
    position = torch.arange(2 * count, device=weights.device).expand(R, -1)
    first = torch.where(new & (rank <= count), position, 2 * count).sort(1).values[:, :count]  # the first new draws, in order
    chosen = draws.gather(1, first.clamp_max(2 * count - 1))
    short = torch.nonzero(rank[:, -1] < count).flatten()
    if short.numel():  # go on without replacement from the distinct draws each short row holds
        have = rank[short, -1]  # (S,)
        held = first[short] < 2 * count  # (S, count): entries of ``chosen`` that are draws
        rows = torch.arange(short.numel(), device=weights.device)[:, None].expand(-1, count)
        remaining = weights[short].index_put((rows[held], chosen[short][held]), weights.new_zeros(()))
        more = torch.multinomial(remaining, count - int(have.min()), generator=generator)  # (S, count - fewest held)
        slot = torch.arange(count, device=weights.device)[None] - have[:, None]  # (S, count): index into ``more`` where >= 0
        chosen[short] = torch.where(slot >= 0, more.gather(1, slot.clamp(0, more.shape[1] - 1)), chosen[short])
    return chosen


class UniformSampler:
    """Every valid point equally likely; s distinct points per sample.

    Args:
        coordinates: (B, N, 2) point positions (unused, kept for a common signature).
        valid: (B, N) bool, False for padding.
    """

    def __init__(self, coordinates: Tensor, valid: Tensor, grid_size: int = 8) -> None:
        self.weights = valid.float()  # (B, N)

    def sample(self, num_samples: int, sample_size: int, generator: torch.Generator | None,
               problems: Tensor | None = None) -> Tensor:
        """(P, num_samples, sample_size) indices of distinct valid points of the problems
        ``problems`` (P,) (default: all B)."""
        weights = self.weights[slice(None) if problems is None else problems]
        P, N = weights.shape
        return _weighted_top_k(weights[:, None, :].expand(P, num_samples, N), sample_size, generator)


class BucketedSampler:
    """Bucketed sampling of thesis §3.3.3 (after Zhang et al. 1995).

    The bounding box of each problem's points is cut into ``grid_size`` × ``grid_size`` buckets.
    A sample draws ``s`` distinct buckets, each with probability proportional to its point count
    among the buckets not yet drawn (the thesis' interval mapping, repeated until the buckets are
    distinct), then one point uniformly from each chosen bucket. Problems with fewer than ``s``
    occupied buckets fall back to uniform sampling.

    Args:
        coordinates: (B, N, 2) image positions used for bucketing (pixels).
        valid: (B, N) bool, False for padding.
        grid_size: buckets per image side (thesis: 8).
    """

    def __init__(self, coordinates: Tensor, valid: Tensor, grid_size: int = 8) -> None:
        B, N, _ = coordinates.shape
        coordinates = coordinates.float()
        large = torch.finfo(coordinates.dtype).max
        low = torch.where(valid[..., None], coordinates, large).amin(dim=1, keepdim=True)  # (B, 1, 2)
        high = torch.where(valid[..., None], coordinates, -large).amax(dim=1, keepdim=True)
        extent = (high - low).clamp_min(1e-12)
        cell = ((coordinates - low) / extent * grid_size).floor().long().clamp(0, grid_size - 1)  # (B, N, 2)
        num_buckets = grid_size * grid_size
        bucket = torch.where(valid, cell[..., 1] * grid_size + cell[..., 0], num_buckets)  # (B, N)
        counts = torch.zeros(B, num_buckets + 1, dtype=torch.long, device=coordinates.device)
        counts.scatter_add_(1, bucket, torch.ones_like(bucket))
        self.counts = counts[:, :num_buckets]  # (B, G²)
        self.starts = torch.cumsum(self.counts, dim=1) - self.counts
        self.order = torch.argsort(bucket, dim=1, stable=True)  # point indices grouped by bucket
        self.occupied = (self.counts > 0).sum(dim=1)  # (B,)
        self.uniform = UniformSampler(coordinates, valid)

    def sample(self, num_samples: int, sample_size: int, generator: torch.Generator | None,
               problems: Tensor | None = None) -> Tensor:
        """(P, num_samples, sample_size) indices of distinct points from distinct buckets of the
        problems ``problems`` (P,) (default: all B)."""
        rows = slice(None) if problems is None else problems
        bucket_counts, bucket_starts, order, occupied = self.counts[rows], self.starts[rows], self.order[rows], self.occupied[rows]
        P, G = bucket_counts.shape
        buckets = _weighted_top_k(bucket_counts[:, None, :].float().expand(P, num_samples, G), sample_size, generator)
        flat = buckets.reshape(P, -1)
        counts = torch.gather(bucket_counts, 1, flat)
        starts = torch.gather(bucket_starts, 1, flat)
        u = torch.rand(flat.shape, generator=generator, device=flat.device)
        offset = (u * counts).long().clamp_max(counts - 1).clamp_min(0)
        # an empty bucket (drawn only when fewer than s are occupied: replaced below) must not index past the end
        position = (starts + offset).clamp_max(order.shape[1] - 1)
        indices = torch.gather(order, 1, position).reshape(P, num_samples, sample_size)
        too_few_buckets = occupied < sample_size
        if bool(too_few_buckets.any()):
            fallback = self.uniform.sample(num_samples, sample_size, generator, problems)
            indices = torch.where(too_few_buckets[:, None, None], fallback, indices)
        return indices


SAMPLERS = {"uniform": UniformSampler, "bucketed": BucketedSampler}
