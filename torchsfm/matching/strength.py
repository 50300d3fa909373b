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
agrees with the thesis' rule whenever the best partners are unique.) The candidates are sorted
into horizontal strips a quarter radius high; each candidate is paired only with the later ones
that lie over the disc's chord in its own strip and the strips below (every unordered pair once,
δ and dist being symmetric), a flat list of pairs, and only the pairs within the radius in both
images whose distances are alike (δ > 0) are kept; the two maxima of the symmetry fix are runs of
that list sorted by (row, k) and by (row, l). The cost grows with the candidates' local density,
not with their number squared.
Relaxation then accepts matches iteratively: winner-take-all accepts every candidate that is the
best of both its points; some-winners-take-all (default) accepts only those in the top α of both
the SM table and the ambiguity table (U = 1 - SM⁽²⁾/SM⁽¹⁾, eq. 3.2.10).
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import torch
from torch import Tensor

from torchsfm.config import MatchingConfig
from torchsfm.matching.ncc import CandidateMatches

_STRIPS_PER_RADIUS = 4  # neighbours are looked for in horizontal strips a quarter radius high
_CHUNK_PAIRS = 1 << 21  # candidate pairs examined at once: memory bounded whatever the number of candidates


def strength_measure(points1: Tensor, points2: Tensor, candidates: CandidateMatches,
                     config: MatchingConfig | None = None) -> Tensor:
    """SM of every candidate match (eq. 3.2.6 with the symmetry fix): (M,).

    Args:
        points1, points2: (N1, 2), (N2, 2) corner positions.
        candidates: the candidate match set (indices and NCC scores c).
        config: neighbourhood radius and ε_r.
    """
    config = config or MatchingConfig()
    M, N1, N2 = candidates.index1.numel(), points1.shape[0], points2.shape[0]
    if M == 0:
        return torch.zeros(M, dtype=points1.dtype, device=points1.device)
    canonical = torch.argsort(candidates.index1 * N2 + candidates.index2, stable=True)  # row-major (k, l) order (the identity as ncc_candidates gives them)
    i, j, c = (t.index_select(0, canonical) for t in (candidates.index1, candidates.index2, candidates.score))
    row, col, delta, closeness = _alike_pairs(points1[i], points2[j], config.neighbourhood_radius, config.relative_distance_threshold)
    # each pair counts both ways: row m with neighbour n scores c_n δ / (1 + dist), row n with neighbour m c_m δ / (1 + dist)
    row, col = torch.cat([row, col]), torch.cat([col, row])
    dtype = torch.int32 if M * max(M, N1, N2) <= torch.iinfo(torch.int32).max else torch.int64  # int32 keys sort twice as fast
    row, col = row.to(dtype), col.to(dtype)
    in_order = torch.argsort(row * M + col)  # by row, then in (k, l) order: a row's neighbours sharing k side by side
    row, col, delta, closeness = (t.index_select(0, in_order) for t in (row, col, torch.cat([delta, delta]), torch.cat([closeness, closeness])))
    value = c.index_select(0, col) * delta / closeness  # (E,)
    best_of_k = _best_in_runs(value, row * N1 + i.index_select(0, col).to(dtype))
    l_key = row * N2 + j.index_select(0, col).to(dtype)
    by_l = torch.argsort(l_key)  # a row's neighbours sharing l side by side
    best_of_l = torch.empty_like(value).index_copy_(0, by_l, _best_in_runs(value.index_select(0, by_l), l_key.index_select(0, by_l)))
    counted = (value > 0) & (value == best_of_k) & (value == best_of_l)  # mutual best: the symmetry fix
    strength = c * value.new_zeros(M).index_add_(0, row, torch.where(counted, value, 0.0))  # a row's neighbours summed in (k, l) order
    return torch.empty_like(strength).index_copy_(0, canonical, strength)


def _alike_pairs(first: Tensor, second: Tensor, radius: float, epsilon: float) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """The pairs (m, n), m ≠ n, of candidates whose corners lie within ``radius`` of each other
    in both images (``first``, ``second``: (M, 2) positions) at alike distances (r < ε_r), each
    pair once: (E,) m, (E,) n, (E,) δ = exp(-r / ε_r) and (E,) 1 + dist."""
    order, start, stop = _strip_ranges(first, radius)
    # the candidates in strip order, each coordinate a column of its own (gathers from 1-D tensors are the fast ones)
    x1, y1 = first.index_select(0, order).T.contiguous()
    x2, y2 = second.index_select(0, order).T.contiguous()
    found = []
    for begin, end in _row_chunks((stop - start).sum(1)):
        row, col = _enumerate(begin, start[begin:end], stop[begin:end])  # (P,), (P,): positions in strip order
        d1 = _distances(x1, y1, row, col)  # d(m1i, n1k)
        d2 = _distances(x2, y2, row, col)  # d(m2j, n2l)
        dist = 0.5 * (d1 + d2)
        # r is 2 where the neighbour shares one corner with the row (one distance 0: ε_r <= 2 drops it)
        # and NaN where it shares both (the same corners twice: 0 / 0, never below ε_r)
        r = (d1 - d2).abs_().div_(dist)
        alike = torch.nonzero((torch.maximum(d1, d2) < radius) & (r < epsilon)).flatten()  # δ > 0: the pairs that count
        row, col, r, dist = (t.index_select(0, alike) for t in (row, col, r, dist))
        found.append((order.index_select(0, row), order.index_select(0, col), torch.exp(-r / epsilon), 1 + dist))
    return tuple(torch.cat(part) for part in zip(*found))


def _best_in_runs(value: Tensor, key: Tensor) -> Tensor:
    """(E,) for each entry the largest of 0 and the ``value`` (E,) of the run of consecutive
    entries with equal ``key`` (E,) that it belongs to."""
    change = torch.ones_like(key, dtype=torch.bool)
    torch.ne(key[1:], key[:-1], out=change[1:])
    run = torch.cumsum(change, 0) - 1
    return value.new_zeros(value.numel()).scatter_reduce_(0, run, value, "amax").index_select(0, run)


def _strip_ranges(points: Tensor, radius: float) -> tuple[Tensor, Tensor, Tensor]:
    """Where to look for the neighbours of (M, 2) points, each pair once: the points sorted by
    horizontal strip (1 / ``_STRIPS_PER_RADIUS`` radius high), then by x: ``order`` (M,); and for
    every point of that order and each of the S = ``_STRIPS_PER_RADIUS`` + 1 strips from its own
    down to a radius below, the positions [``start``, ``stop``) (M, S) in that order of the points
    after it whose x lies within the disc's chord over the strip. Every later point closer than
    ``radius`` is among them (with a few farther ones)."""
    reach = _STRIPS_PER_RADIUS
    height = radius / reach
    x, y = (points.double() - points.double().amin(0)).unbind(-1)
    strip = torch.div(y, height, rounding_mode="floor")
    span = float(x.max()) + 2 * radius + 1  # a strip's keys, x within a radius of any point's, stay below the next strip's
    key = strip * span + x
    order = torch.argsort(key)
    key, x, y, strip = key[order], x[order], y[order], strip[order]
    steps = torch.arange(reach + 1, dtype=x.dtype, device=x.device)  # (S,)
    gap = ((strip[:, None] + steps) * height - y[:, None]).clamp_min(0) * (steps > 0)  # (M, S): from the point to the strip's nearest y
    chord = (radius ** 2 - gap ** 2).clamp_min(0).sqrt() * (1 + 1e-6) + 1e-6  # half its width, generous by a rounding error
    centre = (strip[:, None] + steps) * span + x[:, None]
    start = torch.searchsorted(key, centre - chord)
    start[:, 0] = torch.maximum(start[:, 0], torch.arange(1, key.numel() + 1, device=key.device))  # in its own strip: the points after it
    stop = torch.maximum(torch.searchsorted(key, centre + chord, right=True), start)
    return order, start, stop


def _row_chunks(counts: Tensor) -> list[tuple[int, int]]:
    """Consecutive rows [first, last) whose ``counts`` (M,) sum to at most ``_CHUNK_PAIRS``
    (one row at least)."""
    ends = torch.cumsum(counts, 0)
    chunks, first = [], 0
    while first < counts.numel():
        before = int(ends[first - 1]) if first else 0
        last = max(int(torch.searchsorted(ends, before + _CHUNK_PAIRS, right=True)), first + 1)
        chunks.append((first, last))
        first = last
    return chunks


def _enumerate(first: int, start: Tensor, stop: Tensor) -> tuple[Tensor, Tensor]:
    """The (row, column) pairs (P,), (P,) of rows ``first``, ``first`` + 1, ... whose columns
    are the positions [``start``, ``stop``) (R, S) of each row's S slices, row by row."""
    lengths = (stop - start).flatten()
    slot = torch.repeat_interleave(lengths)  # (P,): each pair's slice
    shift = start.flatten() - (torch.cumsum(lengths, 0) - lengths)  # a slice's first position less the pairs before it
    row = torch.repeat_interleave(lengths.view(start.shape).sum(1)).add_(first)
    return row, torch.arange(slot.numel(), device=start.device).add_(shift.index_select(0, slot))


def _distances(x: Tensor, y: Tensor, row: Tensor, col: Tensor) -> Tensor:
    """(P,) Euclidean distances between the points (``x``, ``y``) (M,), (M,) numbered ``row``
    and ``col`` (P,), from the coordinates' differences: through |a|² + |b|² - 2a·b float32 loses
    the digits of near neighbours."""
    dx = x.index_select(0, row) - x.index_select(0, col)
    dy = y.index_select(0, row) - y.index_select(0, col)
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
    return relaxation_batch([candidates], [strength], [num_points], config)[0]


def relaxation_batch(candidates: Sequence[CandidateMatches], strengths: Sequence[Tensor], num_points: Sequence[tuple[int, int]],
                     config: MatchingConfig | None = None) -> list[tuple[Tensor, Tensor]]:
    """:func:`relaxation` of P independent problems in one loop: the p-th of ``candidates``,
    ``strengths`` (M_p,) and ``num_points`` (N1_p, N2_p). Their candidates lie side by side, the
    corners of each problem numbered after those of the problems before it (no two problems share
    a corner), and the top fractions are taken per problem: the same matches as P calls, for the
    operations of one (many view pairs' relaxations cost about one's)."""
    config = config or MatchingConfig()
    P, device = len(strengths), strengths[0].device
    sizes = [s.numel() for s in strengths]
    problem = torch.repeat_interleave(torch.arange(P, device=device), torch.tensor(sizes, device=device))  # (M,)
    corners = torch.tensor(num_points, dtype=torch.long, device=device).reshape(P, 2)
    first_corner = torch.cumsum(corners, 0) - corners  # (P, 2): each problem's corners numbered from there
    i = torch.cat([c.index1 for c in candidates]) + first_corner[problem, 0]
    j = torch.cat([c.index2 for c in candidates]) + first_corner[problem, 1]
    strength = torch.cat(strengths)
    N1, N2 = (int(n) for n in corners.sum(0))
    active = torch.nonzero(strength > config.strength_threshold)[:, 0]  # the candidates still in play
    accepted = torch.zeros_like(strength, dtype=torch.bool)
    for _ in range(config.max_relaxation_iterations):
        ai, aj, score, group = i[active], j[active], strength[active], problem[active]
        best1 = score.new_full((N1,), float("-inf")).scatter_reduce(0, ai, score, "amax")
        best2 = score.new_full((N2,), float("-inf")).scatter_reduce(0, aj, score, "amax")
        first1, first2 = score == best1[ai], score == best2[aj]
        potential = first1 & first2
        if not bool(potential.any()):
            break
        if config.relaxation == "some_winners":
            second1 = score.new_full((N1,), float("-inf")).scatter_reduce(0, ai, torch.where(first1, float("-inf"), score), "amax")
            second2 = score.new_full((N2,), float("-inf")).scatter_reduce(0, aj, torch.where(first2, float("-inf"), score), "amax")
            runner_up = torch.maximum(second1[ai], second2[aj]).clamp_min(0.0)
            ambiguity = 1 - runner_up / score.clamp_min(1e-30)  # eq. 3.2.10
            selected = potential & _in_top_fraction(score, potential, config.alpha, group, P) \
                & _in_top_fraction(ambiguity, potential, config.alpha, group, P)
            selected |= _strongest_where_none(score, potential, selected, group, P)
        else:
            selected = potential
        accepted[active[selected]] = True
        used1 = torch.zeros(N1, dtype=torch.bool, device=device).index_fill_(0, ai[selected], True)
        used2 = torch.zeros(N2, dtype=torch.bool, device=device).index_fill_(0, aj[selected], True)
        active = active[~used1[ai] & ~used2[aj]]
    return [(c.index1[taken], c.index2[taken]) for c, taken in zip(candidates, torch.split(accepted, sizes))]


def _in_top_fraction(values: Tensor, mask: Tensor, fraction: float, group: Tensor, groups: int) -> Tensor:
    """Entries of ``mask`` whose value is within the top ceil(fraction × count) of the masked
    values of their ``group`` (one of ``groups``)."""
    if groups == 1:
        keep = max(1, math.ceil(fraction * int(mask.sum())))
        return mask & (values >= torch.topk(values[mask], keep).values[-1])
    masked, owner = values[mask], group[mask]
    count = torch.bincount(owner, minlength=groups)
    keep = torch.ceil(fraction * count.double()).long().clamp_min(1)
    by_value = torch.argsort(masked, descending=True, stable=True)
    ranked = masked[by_value[torch.argsort(owner[by_value], stable=True)]]  # by group, then largest first
    threshold = ranked[(torch.cumsum(count, 0) - count + keep - 1).clamp(0, max(ranked.numel() - 1, 0))]  # (groups,); unused where count is 0
    return mask & (values >= threshold[group])


def _strongest_where_none(score: Tensor, potential: Tensor, selected: Tensor, group: Tensor, groups: int) -> Tensor:
    """Where a group's two top tables share no entry (nothing ``selected``), its strongest
    ``potential`` entries: they are taken instead."""
    if groups == 1:
        if bool(selected.any()):
            return torch.zeros_like(selected)
        return potential & (score == score[potential].max())
    chosen = torch.zeros(groups, dtype=torch.bool, device=score.device).index_fill_(0, group[selected], True)
    strongest = score.new_full((groups,), float("-inf")).scatter_reduce(0, group, torch.where(potential, score, float("-inf")), "amax")
    return potential & ~chosen[group] & (score == strongest[group])
