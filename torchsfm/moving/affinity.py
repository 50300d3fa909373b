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
from torchsfm.numerics import sparse_rows_of_transpose

SPARSE_PREFERENCES = 0.02  # share of set preference entries below which the Tanimoto counts multiply sparsely (see
# tanimoto_similarity): 0.5-0.8 % (KITTI 06's tracks, 500-3000 of them) 0.31-0.59x the dense time, 4-8 % (KT3DMoSeg's clips) 0.94-1.65x;
# undefined entries below the same share take the sparse complement (1000 tracks seen throughout, 0.6 % undefined: 59 -> 18 ms)
GRAM_BLOCKS = 4  # column blocks of the symmetric preference product (binary_gram)


def preference_similarity(tracks: Tensor, visible: Tensor, config: SegmentationConfig, generator: torch.Generator,
                          guide: Tensor | None) -> Tensor:
    """(N, N) Tanimoto similarity of the (F, N, 2) tracks' preferences over one round of
    hypotheses, shared equally by the configured kinds of model (sampled near the ``guide``
    similarity's strongest links from the round before, if given). A function of its own so
    that the round's residual tables are freed before the next round's are made."""
    kinds = config.kinds_for(tracks.shape[0])
    fits = [MODELS[name](tracks, visible, config.hypotheses // len(kinds), config, generator, guide) for name in kinds]
    preferences = torch.cat([ordered_preferences(residuals, defined, config) for residuals, defined in fits])
    mask = torch.cat([defined for _, defined in fits])
    del fits
    return tanimoto_similarity(preferences, mask, tracks.dtype)


def ordered_preferences(residuals: Tensor, defined: Tensor, config: SegmentationConfig) -> Tensor:
    """(H, N) residuals and defined mask -> (H, N) bool preferences, each track preferring the
    ``preference_share`` of its defined hypotheses with the smallest residuals (ordered-residual
    kernel)."""
    masked = residuals.masked_fill(~defined, torch.inf)  # (H, N)
    keep = (defined.sum(0) * config.preference_share).ceil().long().clamp_min(1)  # (N,)
    smallest = masked.topk(int(keep.max()), dim=0, largest=False).values  # (k, N) ascending
    largest_kept = smallest.gather(0, keep[None] - 1)  # the keep-th smallest of each track
    return (masked <= largest_kept) & defined


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
    """(H, N) bool preferences and defined mask (a row per hypothesis) -> (N, N) Tanimoto
    similarity (``dtype``) over the hypotheses defined for both tracks (zero diagonal), from the
    counts |p_i ∧ p_j| and |p_i ∧ D_j| (i's preferences among the hypotheses defined for j) as
    products over the hypotheses. Preferences sparser than ``SPARSE_PREFERENCES`` (tracks with
    visibility gaps are defined for few hypotheses) multiply as a sparse matrix, others densely
    (:func:`binary_products`); where the undefined entries are that sparse instead (tracks seen
    throughout are undefined only for the hypotheses sampled from them), |p_i ∧ D_j| is
    |p_i| − |p_i ∧ ¬D_j|, the second term a sparse product. The same counts on every path."""
    if int(preference.sum()) < SPARSE_PREFERENCES * preference.numel():
        rows = sparse_rows_of_transpose(preference)  # (N, H)
        inner, own = (torch.sparse.mm(rows, x.float()) for x in (preference, mask))
    else:
        operand = binary_operand(preference)
        inner = binary_gram(operand)
        undefined = ~mask
        if int(undefined.sum()) < SPARSE_PREFERENCES * undefined.numel():
            outside = torch.sparse.mm(sparse_rows_of_transpose(undefined), operand.float())  # (N, N): |p_j ∧ ¬D_i| at (i, j)
            own = outside.T.neg_().add_(preference.sum(0, dtype=torch.float32)[:, None])
        else:
            own = binary_products(operand, binary_operand(mask))
    denominator = (own + own.T).sub_(inner)  # >= inner (p_j lies within j's defined mask): 0 only where inner is
    del own  # (N, N) tables: at 3000 tracks each is 36 MB, so they are made in place where they can be
    return inner.div_(denominator.clamp_min_(1.0)).to(dtype).fill_diagonal_(0.0)


def binary_operand(x: Tensor) -> Tensor:
    """A 0/1 matrix in the dtype :func:`binary_products` multiplies: int8 (int32 sums,
    ``torch._int_mm``) on a CPU where those products are faster than float32 ones
    (:func:`int8_products_are_faster`), float32 elsewhere."""
    faster = x.device.type == "cpu" and int8_products_are_faster()
    return x.to(torch.int8 if faster else torch.float32)


def binary_products(a: Tensor, b: Tensor) -> Tensor:
    """(h, n) and (h, m) 0/1 matrices from :func:`binary_operand` -> (n, m) float32 counts
    a.T @ b, exact (up to 2^24)."""
    if a.dtype == torch.int8:
        return torch._int_mm(a.T, b).float()
    return a.T @ b


def binary_gram(a: Tensor) -> Tensor:
    """(h, n) 0/1 matrix from :func:`binary_operand` -> the (n, n) float32 counts a.T @ a, exact:
    each of ``GRAM_BLOCKS`` column blocks times the blocks from its own on (the upper block
    triangle: 5/8 of the whole product's work for 4 blocks; 1000 tracks over 4000 hypotheses
    47 -> 36 ms), the lower triangle mirrored."""
    n = a.shape[1]
    gram = torch.empty(n, n, dtype=torch.float32, device=a.device)
    edges = [n * i // GRAM_BLOCKS for i in range(GRAM_BLOCKS + 1)]
    for start, end in zip(edges[:-1], edges[1:]):
        block = binary_products(a[:, start:end], a[:, start:])  # (end - start, n - start)
        gram[start:end, start:] = block
        gram[end:, start:end] = block[:, end - start:].T
    return gram


@functools.cache
def int8_products_are_faster() -> bool:
    """Whether int8 products with int32 sums beat float32 ones on this CPU, timed once per
    process on 1024 x 128 operands (best of three each). int8 was measured 5x faster on a CPU
    with VNNI instructions (when it was introduced) and 27x slower on one with AVX2 only. Both
    are exact on 0/1 counts, so the choice sets the time, never the result. False where this
    build has no CPU int8 products."""
    operand = torch.rand(1024, 128, generator=torch.Generator().manual_seed(0)) < 0.5

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
