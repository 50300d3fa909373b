"""Preferences and affinity (steps 2-3 of :mod:`torchsfm.moving.segmentation`).

Each track prefers the share of hypotheses it fits best (ordered residuals: ranks, no noise
threshold); two tracks are as similar as their preferences overlap (Tanimoto); a track no other
track resembles more than chance allows fits no motion; the affinity keeps each track's
strongest links.
"""

from __future__ import annotations

import functools
import time

import torch
from torch import Tensor

from torchsfm.config import SegmentationConfig
from torchsfm.moving.hypotheses import MODELS
from torchsfm.numerics import sparse_rows

SPARSE_PREFERENCES = 0.02  # share of set preference entries below which the Tanimoto counts multiply sparsely (see
# tanimoto_similarity): 0.5-0.8 % (KITTI 06's tracks, 500-3000 of them) 0.31-0.59x the dense time, 4-8 % (KT3DMoSeg's clips) 0.94-1.65x


def preference_similarity(tracks: Tensor, visible: Tensor, config: SegmentationConfig, generator: torch.Generator,
                          guide: Tensor | None) -> Tensor:
    """(N, N) Tanimoto similarity of the (F, N, 2) tracks' preferences over one round of
    hypotheses, shared equally by the configured kinds of model (sampled near the ``guide``
    similarity's strongest links from the round before, if given). A function of its own so
    that the round's residual tables are freed before the next round's are made."""
    kinds = config.kinds_for(tracks.shape[0])
    fits = [MODELS[name](tracks, visible, config.hypotheses // len(kinds), config, generator, guide) for name in kinds]
    preferences = [ordered_preferences(residuals, defined, config) for residuals, defined in fits]
    del fits
    return tanimoto_similarity(torch.cat([p for p, _ in preferences], 1), torch.cat([d for _, d in preferences], 1), tracks.dtype)


def ordered_preferences(residuals: Tensor, defined: Tensor, config: SegmentationConfig) -> tuple[Tensor, Tensor]:
    """(H, N) residuals -> (N, H) bool preferences, each track preferring the ``preference_share``
    of its defined hypotheses with the smallest residuals (ordered-residual kernel), and the
    (N, H) bool mask of defined entries."""
    masked = residuals.masked_fill(~defined, torch.inf)  # (H, N)
    keep = (defined.sum(0) * config.preference_share).ceil().long().clamp_min(1)  # (N,)
    smallest = masked.topk(int(keep.max()), dim=0, largest=False).values  # (k, N) ascending
    largest_kept = smallest.gather(0, keep[None] - 1)  # the keep-th smallest of each track
    return ((masked <= largest_kept) & defined).T, defined.T  # transposed as bools: an eighth of the doubles' bytes


def explained_tracks(similarity: Tensor, config: SegmentationConfig) -> Tensor:
    """(N, N) preference similarity -> (N,) bool: tracks whose ``config.support`` most similar
    tracks are, on average, more than ``config.outlier_factor`` times as similar as two tracks
    with unrelated preferences would be by chance — q / (2 - q) for preference share q, the
    expected Tanimoto similarity of two random subsets of that share. A gross outlier (a
    tracking error) fits no motion, so its preferences are unrelated to every other track's."""
    share = config.preference_share
    chance = share / (2.0 - share)
    support = similarity.topk(min(config.support, similarity.shape[0] - 1), dim=1).values.mean(1)
    return support > config.outlier_factor * chance


def tanimoto_similarity(preference: Tensor, mask: Tensor, dtype: torch.dtype) -> Tensor:
    """(N, H) bool preferences and defined mask -> (N, N) Tanimoto similarity (``dtype``) over
    the hypotheses defined for both tracks (zero diagonal). Preferences sparser than
    ``SPARSE_PREFERENCES`` (tracks with visibility gaps are defined for few hypotheses) multiply
    as a sparse matrix (:func:`sparse_binary_products`), others densely (:func:`binary_products`):
    the same counts either way."""
    if int(preference.sum()) < SPARSE_PREFERENCES * preference.numel():
        inner, own = sparse_binary_products(preference, [preference, mask])
    else:
        preference, mask = binary_operand(preference), binary_operand(mask)  # each converted once
        inner = binary_products(preference, preference)
        own = binary_products(preference, mask)  # |p_i| restricted to the hypotheses defined for j
    denominator = (own + own.T).sub_(inner)  # >= inner (p_j lies within j's defined mask): 0 only where inner is
    del own  # (N, N) tables: at 3000 tracks each is 36 MB, so they are made in place where they can be
    return inner.div_(denominator.clamp_min_(1.0)).to(dtype).fill_diagonal_(0.0)


def sparse_binary_products(a: Tensor, others: list[Tensor]) -> list[Tensor]:
    """(n, h) bool ``a`` and each (m, h) bool of ``others`` -> the (n, m) float32 counts a @ b.T,
    exact (up to 2^24), with ``a`` as one compressed-sparse-row matrix: the work is a's nonzeros
    times m, not n · h · m."""
    rows = sparse_rows(a.float())
    return [torch.sparse.mm(rows, b.float().T) for b in others]


def binary_operand(x: Tensor) -> Tensor:
    """A 0/1 matrix in the dtype :func:`binary_products` multiplies: int8 (int32 sums,
    ``torch._int_mm``) on a CPU where those products are faster than float32 ones
    (:func:`int8_products_are_faster`), float32 elsewhere."""
    faster = x.device.type == "cpu" and int8_products_are_faster()
    return x.to(torch.int8 if faster else torch.float32)


def binary_products(a: Tensor, b: Tensor) -> Tensor:
    """(n, h) and (m, h) 0/1 matrices from :func:`binary_operand` -> (n, m) float32 counts
    a @ b.T, exact (up to 2^24)."""
    if a.dtype == torch.int8:
        return torch._int_mm(a, b.T).float()
    return a @ b.T


@functools.cache
def int8_products_are_faster() -> bool:
    """Whether int8 products with int32 sums beat float32 ones on this CPU, timed once per
    process on 128 x 1024 operands (best of three each). int8 was measured 5x faster on a CPU
    with VNNI instructions (when it was introduced) and 27x slower on one with AVX2 only. Both
    are exact on 0/1 counts, so the choice sets the time, never the result. False where this
    build has no CPU int8 products."""
    operand = torch.rand(128, 1024, generator=torch.Generator().manual_seed(0)) < 0.5

    def seconds(a: Tensor) -> float:
        start = time.perf_counter()
        binary_products(a, a)
        return time.perf_counter() - start

    def best_time(a: Tensor) -> float:
        return min(seconds(a) for _ in range(3))

    try:
        int8_time = best_time(operand.to(torch.int8))
    except RuntimeError:  # no int8 kernel in this build
        return False
    return int8_time < best_time(operand.float())


def strongest_links(similarity: Tensor, links: int) -> Tensor:
    """(N, N) similarity -> symmetric affinity keeping each row's ``links`` strongest entries."""
    k = min(links, similarity.shape[0] - 1)
    strongest = similarity.topk(k, dim=1).indices
    sparse = torch.zeros_like(similarity).scatter_(1, strongest, similarity.gather(1, strongest))
    return torch.maximum(sparse, sparse.T)
