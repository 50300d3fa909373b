"""Disambiguating candidate matches: the strength measure and relaxation (thesis §3.2.2.2–3.2.2.3).

The strength measure (eq. 3.2.6–3.2.9 with the ERRATA, after Zhang, Deriche, Faugeras & Luong
1995) rewards a candidate match (m1i, m2j) for every neighbouring candidate (n1k, n2l) whose
offsets from m1i and m2j are alike:

    SM(i, j) = c_ij Σ_{k ∈ N(m1i)} max_{l ∈ N(m2j)} c_kl δ(i, j; k, l) / (1 + dist),
    dist = (d(m1i, n1k) + d(m2j, n2l)) / 2,  r = |d(m1i, n1k) - d(m2j, n2l)| / dist,
    δ = exp(-r / ε_r) if (n1k, n2l) is a candidate and r < ε_r, else 0,

with the symmetry fix of §3.2.2.2.1, made exact: a neighbour pair (k, l) counts only when l is
k's best and k is l's best. (The thesis keeps, among the k whose best is the same l, the largest;
that removes the double counting but is not symmetric when a dropped k has another partner — the
mutual-best rule gives the same SM whichever image comes first, which is what the fix is for, and
agrees with the thesis' rule whenever the best partners are unique.) Candidate pairs are evaluated a
block of spatially nearby rows at a time (tiles half a neighbourhood radius wide, taken in Z order)
against the candidates in the surrounding tiles, and only the pairs within the radius whose
distances are alike (δ > 0) are kept (a sparse list), so the cost grows with the candidates' local
density, not with their number squared.
Relaxation then accepts matches iteratively: winner-take-all accepts every candidate that is the
best of both its points; some-winners-take-all (default) accepts only those in the top α of both
the SM table and the ambiguity table (U = 1 - SM⁽²⁾/SM⁽¹⁾, eq. 3.2.10).
"""

from __future__ import annotations

import math

import torch
from torch import Tensor

from torchsfm.config import MatchingConfig
from torchsfm.matching.ncc import CandidateMatches

_ROW_BLOCK = 128
_TILES_PER_RADIUS = 2  # Herz-Jesu-P8's 23 guided pairs: 112 M row x column entries with 1 (row-major, blocks of 256), 79 M with 2 in Z order


def _z_order(tile: Tensor) -> Tensor:
    """(M,) Morton keys of (M, 2) non-negative integer (x, y) tiles: the bits of x and y
    interleaved, so that tiles close in the order are close in the plane."""
    key = torch.zeros_like(tile[:, 0])
    for bit in range(max(1, int(tile.max()).bit_length())):
        key |= ((tile[:, 0] >> bit) & 1) << (2 * bit) | ((tile[:, 1] >> bit) & 1) << (2 * bit + 1)
    return key


def strength_measure(points1: Tensor, points2: Tensor, candidates: CandidateMatches,
                     config: MatchingConfig | None = None) -> Tensor:
    """SM of every candidate match (eq. 3.2.6 with the symmetry fix): (M,).

    Args:
        points1, points2: (N1, 2), (N2, 2) corner positions.
        candidates: the candidate match set (indices and NCC scores c).
        config: neighbourhood radius and ε_r.
    """
    config = config or MatchingConfig()
    i, j, c = candidates.index1, candidates.index2, candidates.score
    M = i.numel()
    strength = torch.zeros(M, dtype=points1.dtype, device=points1.device)
    if M == 0:
        return strength
    # rows in blocks of nearby candidates; a block's columns are the candidates in its tiles and
    # the tiles around them (tiles 1 / _TILES_PER_RADIUS radius wide: every neighbour lies within
    # _TILES_PER_RADIUS tiles), not all M. The blocks follow the tiles in Z order, so that each
    # covers a compact patch of tiles rather than a strip. A row's columns come in candidate order
    # whatever the block, so its sum below is the same.
    reach = _TILES_PER_RADIUS
    tile = torch.div(points1[i] - points1[i].amin(0), config.neighbourhood_radius / reach, rounding_mode="floor").long()  # (M, 2)
    order = torch.argsort(_z_order(tile), stable=True)
    grid_shape = (int(tile[:, 1].max()) + 1 + 2 * reach, int(tile[:, 0].max()) + 1 + 2 * reach)  # reach tiles of margin on each side
    around = torch.arange(2 * reach + 1, device=points1.device)
    for start in range(0, M, _ROW_BLOCK):
        rows = order[start:start + _ROW_BLOCK]
        near = torch.zeros(grid_shape, dtype=torch.bool, device=points1.device)
        near[tile[rows, 1, None, None] + around[:, None], tile[rows, 0, None, None] + around] = True  # each row's tile and those within reach (margin-shifted)
        cols = torch.nonzero(near[tile[:, 1] + reach, tile[:, 0] + reach]).flatten()
        ci, cj = i[cols], j[cols]
        d1 = _distances(points1[i[rows]], points1[ci])  # (R, C): d(m1i, n1k) for every nearby candidate (k, l)
        d2 = _distances(points2[j[rows]], points2[cj])  # and d(m2j, n2l)
        dist = 0.5 * (d1 + d2)
        # r is 2 where the neighbour shares one corner with the row (one distance 0: ε_r <= 2 drops it)
        # and NaN where it shares both (the row itself: 0 / 0, never below ε_r)
        r = (d1 - d2).abs_().div_(dist)
        alike = (torch.maximum(d1, d2) < config.neighbourhood_radius) & (r < config.relative_distance_threshold)  # δ > 0: the E that count
        r_index, c_index = torch.nonzero(alike, as_tuple=True)
        r, dist = r[r_index, c_index], dist[r_index, c_index]
        value = c[cols[c_index]] * torch.exp(-r / config.relative_distance_threshold) / (1 + dist)  # (E,)
        R = rows.numel()
        points_k, local_k = torch.unique(ci, return_inverse=True)  # the columns name few corners of each image:
        points_l, local_l = torch.unique(cj, return_inverse=True)  # tables over those, not over all N1, N2
        k_slot = r_index * points_k.numel() + local_k[c_index]  # (E,): entry (row, k) of a flattened (R, K) table
        l_slot = r_index * points_l.numel() + local_l[c_index]  # (E,): entry (row, l) of a flattened (R, L) table
        best_of_k = value.new_zeros(R * points_k.numel()).scatter_reduce(0, k_slot, value, "amax")
        best_of_l = value.new_zeros(R * points_l.numel()).scatter_reduce(0, l_slot, value, "amax")
        counted = (value > 0) & (value == best_of_k[k_slot]) & (value == best_of_l[l_slot])  # mutual best: the symmetry fix
        total = value.new_zeros(R).index_add_(0, r_index, torch.where(counted, value, 0.0))
        strength[rows] = c[rows] * total
    return strength


def _distances(a: Tensor, b: Tensor) -> Tensor:
    """(R, C) Euclidean distances between the points a (R, 2) and b (C, 2), from the coordinates'
    differences: through |a|² + |b|² - 2a·b (``cdist``'s default) float32 loses the digits of near
    neighbours, and ``cdist`` from the differences takes 3x as long. (The coordinates are made
    contiguous first: a broadcast difference of strided columns takes 3x as long.)"""
    (ax, ay), (bx, by) = a.T.contiguous(), b.T.contiguous()
    dx = ax[:, None] - bx
    dy = ay[:, None] - by
    return dx.mul_(dx).addcmul_(dy, dy).sqrt_()


def relaxation(candidates: CandidateMatches, strength: Tensor, num_points: tuple[int, int],
               config: MatchingConfig | None = None) -> tuple[Tensor, Tensor]:
    """Accept matches iteratively from the candidate set (Algorithm 3.2.2, step 3).

    Args:
        candidates: the candidate set; strength: (M,) score of each candidate (SM, or NCC for
            the NCC-only baseline).
        num_points: (N1, N2), the number of corners in each image.
        config: ``relaxation`` ("some_winners" or "winner_take_all"), ``alpha``,
            ``strength_threshold``, ``max_relaxation_iterations``.

    Returns:
        The accepted matches as (index1, index2) int64 tensors (one-to-one).
    """
    config = config or MatchingConfig()
    i, j = candidates.index1, candidates.index2
    N1, N2 = num_points
    active = torch.nonzero(strength > config.strength_threshold)[:, 0]  # the candidates still in play
    accepted = torch.zeros_like(strength, dtype=torch.bool)
    for _ in range(config.max_relaxation_iterations):
        ai, aj, score = i[active], j[active], strength[active]
        best1 = score.new_full((N1,), float("-inf")).scatter_reduce(0, ai, score, "amax")
        best2 = score.new_full((N2,), float("-inf")).scatter_reduce(0, aj, score, "amax")
        potential = (score == best1[ai]) & (score == best2[aj])
        if not bool(potential.any()):
            break
        if config.relaxation == "some_winners":
            second1 = score.new_full((N1,), float("-inf")).scatter_reduce(0, ai, torch.where(score == best1[ai], float("-inf"), score), "amax")
            second2 = score.new_full((N2,), float("-inf")).scatter_reduce(0, aj, torch.where(score == best2[aj], float("-inf"), score), "amax")
            runner_up = torch.maximum(second1[ai], second2[aj]).clamp_min(0.0)
            ambiguity = 1 - runner_up / score.clamp_min(1e-30)  # eq. 3.2.10
            selected = potential & _in_top_fraction(score, potential, config.alpha) & _in_top_fraction(ambiguity, potential, config.alpha)
            if not bool(selected.any()):  # the two tables share no top entry: take the strongest
                selected = potential & (score == score[potential].max())
        else:
            selected = potential
        accepted[active[selected]] = True
        used1 = torch.zeros(N1, dtype=torch.bool, device=i.device).index_fill_(0, ai[selected], True)
        used2 = torch.zeros(N2, dtype=torch.bool, device=j.device).index_fill_(0, aj[selected], True)
        active = active[~used1[ai] & ~used2[aj]]
    return i[accepted], j[accepted]


def _in_top_fraction(values: Tensor, mask: Tensor, fraction: float) -> Tensor:
    """Entries of ``mask`` whose value is within the top ceil(fraction × count) of the masked values."""
    count = int(mask.sum())
    keep = max(1, math.ceil(fraction * count))
    threshold = torch.topk(values[mask], keep).values[-1]
    return mask & (values >= threshold)
