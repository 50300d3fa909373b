"""Which view pairs to match, and where to look: coarse matching of every view pair.

Each image is reduced so that its long side is about ``coarse_size`` pixels; Harris corners and
NCC patches there give every pair a cheap score — the number of mutually best NCC matches over
the whole image, no search disc — batched over all pairs (one GEMM per view). The score picks
the pairs worth verifying when the file order cannot be trusted, and a homography fitted
(RANSAC) to a pair's coarse matches predicts where each corner of one image lies in the other,
so the full-resolution NCC search disc is centred on the prediction instead of on the corner's
own position: disparities of hundreds of pixels then need no larger disc.

Pair selection (``pairs.mode``): ``sequential`` — (i, i + d) for d = 1 .. ``window`` (video);
``exhaustive`` — every pair; ``similarity`` — each view's ``neighbours`` best-scoring partners
and the pairs of the sequential window, where the pair's coarse homography holds (so a shuffled
set wastes no time on its file neighbours, nor a set on views that share nothing); ``auto`` —
similarity, over every pair up to ``exhaustive_up_to`` views. In the last two, a chosen pair
that alone joins two parts of the chosen pairs' graph (a bridge) gets a second pair across the
same cut, the considered one with the most coarse homography inliers (:func:`second_links`),
even if its homography holds on too few.
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass

import torch
from torch import Tensor
from torch.nn import functional

from torchsfm.config import HarrisConfig, PairsConfig, RansacConfig
from torchsfm.features.harris import detect_corners
from torchsfm.images import reduce_mask, same_size_batches, stacked_masks, to_unit_float
from torchsfm.matching.ncc import extract_patches, zero_mean_unit_norm
from torchsfm.robust.models import HomographyModel
from torchsfm.robust.ragged import pad_rows
from torchsfm.robust.ransac import ransac
from torchsfm.robust.samplers import side_generator

HOMOGRAPHY_BATCH = 32  # view pairs per batched RANSAC call of the coarse homographies
SCORED_VIEWS = 8  # views scored against one view per product (measured: 1.7x faster than all at once at 150 views)


@dataclass
class CoarseFeatures:
    """Corners of V reduced images, in full-resolution pixels.

    Fields:
        points: (V, K, 2) corner positions (full-resolution pixels), padded.
        patches: (V, K, D) zero-mean unit-norm patches (zeros for padding).
        valid: (V, K) bool.
    """

    points: Tensor
    patches: Tensor
    valid: Tensor


def coarse_features(greys: list[Tensor], config: PairsConfig, focal: Tensor | None = None,
                    masks: list[Tensor | None] | None = None) -> CoarseFeatures:
    """Harris corners and NCC patches of (1, H_v, W_v) grey images (uint8 or float in [0, 1])
    reduced so that every view is seen at one scale (:func:`reduction_factors`), a few views of
    one size and factor at a time (no full-resolution float copy of them all). ``focal``: (V,)
    each view's focal length in pixels, where known; ``masks``: per view (H_v, W_v) bool, where
    corners may be (None entries: everywhere), reduced with the image."""
    factors = reduction_factors(greys, config.coarse_size, focal, smallest=2 * (config.patch_half_size + 1) + 1)
    harris = HarrisConfig(max_corners=config.coarse_corners, spread_grid=4, border=config.patch_half_size + 1)
    positions: dict[int, Tensor] = {}
    patches: dict[int, Tensor] = {}
    for factor in sorted(set(factors)):
        alike = [v for v in range(len(greys)) if factors[v] == factor]
        for batch in same_size_batches([greys[v] for v in alike], 8):
            views = [alike[b] for b in batch]
            small = functional.avg_pool2d(to_unit_float(torch.stack([greys[v] for v in views])), factor)
            mask = stacked_masks(masks, views, greys[views[0]].shape[-2:])
            corners = detect_corners(small, harris, None if mask is None else torch.stack([reduce_mask(m, factor) for m in mask]))
            for b, v in enumerate(views):
                positions[v] = (corners.of_image(b).double() + 0.5) * factor - 0.5  # pixel centres of the reduced image
                patches[v] = extract_patches(small[b], corners.of_image(b).double(), config.patch_half_size)
    views = range(len(greys))
    patches_padded, valid = pad_rows([patches[v] for v in views])
    return CoarseFeatures(points=pad_rows([positions[v] for v in views])[0], patches=patches_padded, valid=valid)


def reduction_factors(greys: list[Tensor], coarse_size: int, focal: Tensor | None = None, smallest: int = 1) -> list[int]:
    """Per (1, H_v, W_v) image the integer factor it is reduced by for coarse matching: the
    largest image by the factor that brings its long side to about ``coarse_size`` px, and —
    given each view's focal length (V,) in pixels — every other view by the factor that brings
    its focal length to that image's reduced one (the largest image of the shortest focal
    length where several are largest), so that views from several cameras or zoom settings are
    seen at one angular resolution, as patch matching needs. Without focal lengths (one camera,
    one image size) and for views of one camera and one size: one factor for all. No view is
    reduced below ``smallest`` px on its short side (a patch and its border)."""
    sides = [max(grey.shape[-2:]) for grey in greys]
    if focal is None:
        return [max(1, round(max(sides) / coarse_size))] * len(greys)
    focal = focal.double().cpu().tolist()
    reference = max(range(len(greys)), key=lambda v: (sides[v], -focal[v]))
    coarse_focal = focal[reference] / max(1, round(sides[reference] / coarse_size))
    return [max(1, min(round(f / coarse_focal), min(grey.shape[-2:]) // smallest)) for f, grey in zip(focal, greys)]


def _mutual_best(ncc: Tensor, threshold: float) -> tuple[Tensor, Tensor]:
    """Mutually best pairs above ``threshold`` of one (K1, K2) NCC table."""
    if ncc.numel() == 0:
        return torch.zeros(0, dtype=torch.long, device=ncc.device), torch.zeros(0, dtype=torch.long, device=ncc.device)
    best2 = ncc.argmax(1)
    best1 = ncc.argmax(0)
    index1 = torch.arange(ncc.shape[0])
    mutual = (best1[best2] == index1) & (ncc[index1, best2] > threshold)
    return index1[mutual], best2[mutual]


def pair_scores(features: CoarseFeatures, threshold: float) -> Tensor:
    """(V, V) number of mutually best coarse NCC matches above ``threshold`` (0 on the diagonal)."""
    V = features.patches.shape[0]
    scores = torch.zeros(V, V, dtype=torch.long)
    for i in range(V - 1):  # the views after i only: a mutual best match is mutual both ways
        scores[i, i + 1:] = mutual_best_counts(features, i, torch.arange(i + 1, V), threshold)
    return scores + scores.T


def mutual_best_counts(features: CoarseFeatures, view: int, others: Tensor, threshold: float) -> Tensor:
    """(O,) number of mutually best coarse NCC matches above ``threshold`` between ``view`` and
    each of the (O,) ``others``: one GEMM per ``SCORED_VIEWS`` of them, whose (SCORED_VIEWS, L, K)
    table stays in the cache while its best matches are read (one GEMM against all others made a
    (O, L, K) table — 360 MB at 500 views — and took 1.7× as long)."""
    if features.patches.shape[1] == 0 or others.numel() == 0:  # no view has a coarse corner
        return torch.zeros(others.numel(), dtype=torch.long)
    counts = []
    for part in others.split(SCORED_VIEWS):
        ncc = features.patches[part] @ features.patches[view].T  # (o, L, K): corner l of view o, corner k of the view
        best2 = ncc.argmax(1)  # (o, K): best partner in view o of each corner of the view
        best1 = ncc.argmax(2)  # (o, L): best corner of the view for each corner of o
        mutual = best1.gather(1, best2) == torch.arange(ncc.shape[2])[None]
        strong = ncc.gather(1, best2[:, None])[:, 0] > threshold
        counts.append((mutual & strong & features.valid[view][None]).sum(1))
    return torch.cat(counts)


def considered_pairs(scores: Tensor | None, config: PairsConfig, num_views: int) -> list[tuple[int, int]]:
    """The view pairs (i < j) that ``config.mode`` considers: ``sequential`` the window (i, i + d),
    d = 1 .. ``window``, ``exhaustive`` every pair (both final, no scores needed: None);
    ``similarity`` (and ``auto`` beyond ``exhaustive_up_to`` views) the window and each view's
    ``neighbours`` best-scoring partners by the coarse scores (V, V); ``auto`` up to
    ``exhaustive_up_to`` views every pair."""
    V = num_views
    pairs = [(i, j) for i in range(V) for j in range(i + 1, V)]
    window = {(i, i + d) for d in range(1, config.window + 1) for i in range(V - d)}
    if config.mode == "exhaustive" or (config.mode == "auto" and V <= config.exhaustive_up_to):
        return pairs
    if config.mode == "sequential":
        return sorted(window)
    return sorted(window | _best_partners(scores, config))


def select_pairs(scores: Tensor | None, config: PairsConfig, num_views: int,
                 coarse_inliers: dict[tuple[int, int], int] | None = None) -> list[tuple[int, int]]:
    """View pairs (i < j) of ``num_views`` to verify: the :func:`considered_pairs` that have
    ``min_score`` coarse mutual-best matches (``scores`` (V, V)) and, where ``coarse_inliers`` is
    given, that many inliers of their coarse homography (``sequential`` and ``exhaustive``: all
    considered pairs). Views that show nothing in common still share chance mutual-best matches
    (dozens on a textured facade), but no homography joins more than a handful of them, so the
    geometric count is the one that tells related pairs apart. A view left without any pair falls
    back to its best-scoring partners (the score alone), so no view loses the pairs it had."""
    considered = considered_pairs(scores, config, num_views)
    if config.mode in ("sequential", "exhaustive"):
        return considered
    scored = [pair for pair in considered if int(scores[pair]) >= config.min_score]
    chosen = {pair for pair in scored if coarse_inliers is None or coarse_inliers[pair] >= config.min_score}
    partners = _best_partners(scores, config)
    for v in set(range(num_views)) - {v for pair in chosen for v in pair}:
        chosen |= {pair for pair in partners if v in pair and int(scores[pair]) >= config.min_score}
    return sorted(chosen)


def _best_partners(scores: Tensor, config: PairsConfig) -> set[tuple[int, int]]:
    """Each view's ``neighbours`` best-scoring partners, as pairs (i < j)."""
    ranked = torch.argsort(scores, dim=1, descending=True)[:, : config.neighbours]
    return {(min(i, j), max(i, j)) for i in range(scores.shape[0]) for j in ranked[i].tolist() if j != i}


def bridge_pairs(features: CoarseFeatures, stranded: list[int], registered: list[int], config: PairsConfig) -> list[tuple[int, int]]:
    """View pairs (i < j) that may link each ``stranded`` view to the ``registered`` ones: its
    ``neighbours`` best-scoring registered partners by the coarse score
    (:func:`mutual_best_counts`; wide baselines score low but still rank) of the views' coarse
    ``features``."""
    if not stranded or not registered:
        return []
    others = torch.tensor(registered)
    pairs = set()
    for view in stranded:
        scores = mutual_best_counts(features, view, others, config.ncc_threshold)
        best = others[scores.argsort(descending=True, stable=True)[:config.neighbours]]
        pairs |= {(min(view, other), max(view, other)) for other in best.tolist()}
    return sorted(pairs)


def pairs_to_match(greys: list[Tensor], config: PairsConfig, generator: torch.Generator | None = None,
                   guided: bool = False, focal: Tensor | None = None,
                   masks: list[Tensor | None] | None = None) -> dict[tuple[int, int], Tensor | None]:
    """The view pairs (i < j) of (V, 1, H, W) grey images to match (:func:`select_pairs` on the
    coarse features; ``focal`` (V,) pixels where known and ``masks``, see :func:`coarse_features`), each with
    its coarse homography (:func:`coarse_homographies`) where ``guided`` asks for it (None
    otherwise, and where none holds). The considered pairs' homographies are fitted once, for
    the selection and the guidance alike. Where the pairs with a homography leave the views in
    several groups (``similarity`` and ``auto`` modes), the considered pairs between groups are
    tried with one view's patches turned (:func:`turned_homographies`: portrait and tilted
    shots), with random draws of their own (the others' as without them), and the pairs a turn
    joins are matched too."""
    features = coarse_features(greys, config, focal, masks)
    scores = None if config.mode in ("sequential", "exhaustive") else pair_scores(features, config.ncc_threshold)
    considered = considered_pairs(scores, config, len(greys))
    homographies, inliers = {}, None
    if guided or scores is not None:
        homographies, inliers = coarse_homographies(features, considered, config, generator)
    chosen = {pair: homographies.get(pair) if guided else None for pair in select_pairs(scores, config, len(greys), inliers)}
    if scores is not None:
        group = view_groups([pair for pair in considered if homographies[pair] is not None], len(greys))
        between = [(i, j) for i, j in considered if group[i] != group[j]]
        if between:
            turned = turned_homographies(features, between, config, side_generator(generator))
            chosen.update({pair: H if guided else None for pair, H in turned.items()})
        if config.second_links:
            second = second_links(list(chosen), considered, scores, inliers, config, len(greys))
            chosen.update({pair: homographies.get(pair) if guided else None for pair in second})
    return dict(sorted(chosen.items()))


def single_links(pairs: list[tuple[int, int]], num_views: int) -> list[tuple[tuple[int, int], Tensor]]:
    """The ``pairs`` that alone join two parts of the view graph they make over ``num_views``
    views (its bridges: without one, its part of the graph falls in two), each with the (V,)
    bool mask of the views on one side of it. Tarjan's bridge search, one depth-first pass
    (iterative: a video's chain of views is deeper than Python's recursion)."""
    neighbours: list[list[tuple[int, int]]] = [[] for _ in range(num_views)]
    for k, (i, j) in enumerate(pairs):
        neighbours[i].append((j, k))
        neighbours[j].append((i, k))
    entry, low, last = [-1] * num_views, [0] * num_views, [0] * num_views  # last: the subtree's latest entry
    found, clock = [], 0
    for root in range(num_views):
        if entry[root] >= 0:
            continue
        entry[root] = low[root] = clock
        clock += 1
        stack = [(root, -1, iter(neighbours[root]))]
        while stack:
            view, via, rest = stack[-1]
            for other, k in rest:
                if k == via:
                    continue
                if entry[other] < 0:
                    entry[other] = low[other] = clock
                    clock += 1
                    stack.append((other, k, iter(neighbours[other])))
                    break
                low[view] = min(low[view], entry[other])
            else:
                stack.pop()
                last[view] = clock - 1
                if stack:
                    parent = stack[-1][0]
                    low[parent] = min(low[parent], low[view])
                    if low[view] > entry[parent]:
                        found.append((via, view))
    entries = torch.tensor(entry)
    return [(pairs[k], (entries >= entry[view]) & (entries <= last[view])) for k, view in found]


def second_links(chosen: list[tuple[int, int]], considered: list[tuple[int, int]], scores: Tensor,
                 inliers: dict[tuple[int, int], int], config: PairsConfig, num_views: int) -> list[tuple[int, int]]:
    """For each pair that alone joins two parts of the ``chosen`` pairs' view graph
    (:func:`single_links`), the ``considered`` pair across the same cut with the most coarse
    homography ``inliers`` (then the higher coarse score; ``min_score`` coarse matches at least),
    where there is one. Every track that ties one part to the other runs through that one pair's
    matches, so the parts' relative pose and scale rest on it alone: a weak one (few right
    matches, little parallax under forward motion) leaves them misplaced against each other with
    nothing to tell, where a second pair lets the mapping and the adjustment check one against
    the other. The second pair's coarse homography may hold on too few matches (under forward
    motion no one plane holds most of a pair's matches)."""
    taken = set(chosen)
    candidates = [pair for pair in considered if pair not in taken and int(scores[pair]) >= config.min_score]
    if not candidates:
        return []
    group = torch.tensor(view_groups(chosen, num_views))
    first, second = torch.tensor(candidates).T  # (C,) each
    score = scores[first, second].long()
    rank = torch.tensor([inliers[pair] for pair in candidates]) * (int(score.max()) + 1) + score  # by inliers, then score
    free = group[first] == group[second]  # (C,): a candidate within one part of the graph, not yet added
    added = []
    for (i, _), side in single_links(chosen, num_views):
        across = free & (group[first] == group[i]) & (side[first] != side[second])
        if bool(across.any()):
            best = int(torch.where(across, rank, -1).argmax())  # the first of equals, as the considered order has them
            free[best] = False
            added.append(candidates[best])
    return added


def view_groups(pairs: list[tuple[int, int]], num_views: int) -> list[int]:
    """Per view of ``num_views`` the group it belongs to (the smallest view of the group): the
    views the ``pairs`` join, directly or through others."""
    group = list(range(num_views))
    for i, j in pairs:
        a, b = group_root(group, i), group_root(group, j)
        group[max(a, b)] = min(a, b)
    return [group_root(group, v) for v in range(num_views)]


def group_root(group: list[int], v: int) -> int:
    """The view that names view v's group in the union-find forest ``group`` (each view's
    parent, itself at a root), the path halved on the way."""
    while group[v] != v:
        group[v] = group[group[v]]
        v = group[v]
    return v


def coarse_homographies(features: CoarseFeatures, pairs: list[tuple[int, int]], config: PairsConfig,
                        generator: torch.Generator | None = None, turn: int = 0
                        ) -> tuple[dict[tuple[int, int], Tensor | None], dict[tuple[int, int], int]]:
    """:func:`fit_homographies` of the view pairs' :func:`coarse_matches` with the second view
    turned by ``turn`` twelfths of a turn."""
    return fit_homographies(pairs, coarse_matches(features, pairs, config, turn), config, generator)


def coarse_matches(features: CoarseFeatures, pairs: list[tuple[int, int]], config: PairsConfig, turn: int = 0) -> list[Tensor]:
    """Each view pair's (M, 4) coarse mutual-best matches x_i, x_j (pixels), the second view's
    patches turned by ``turn`` twelfths of a turn (:func:`turned_patches`: a view turned against
    the other turns its patches alike — a portrait shot among landscape ones, a tilted one)."""
    matches = []
    for i, j in pairs:
        ki, kj = features.valid[i], features.valid[j]
        first, second = turned_patches(features.patches[i][ki], features.patches[j][kj], config.patch_half_size, turn)
        a, b = _mutual_best(first @ second.T, config.ncc_threshold)
        matches.append(torch.cat([features.points[i][ki][a], features.points[j][kj][b]], dim=-1))
    return matches


TURNS = 12  # the turns of one view against another tried where no upright homography joins them: every 30 degrees
FITTED_TURNS = 3  # of them, those with the most coarse mutual-best matches get a homography fitted (see turned_homographies)


def turned_patches(first: Tensor, second: Tensor, half_size: int, turn: int) -> tuple[Tensor, Tensor]:
    """Two views' zero-mean unit-norm (K, (2n + 1)²) patches made comparable with the second
    view turned by ``turn`` twelfths of a turn (counter-clockwise in the image): quarter turns
    permute the second view's pixels (exact); the other turns resample them bilinearly at the
    turned positions, and both views' patches are then compared over the inscribed disc only
    (zero mean and unit norm there), the part of a patch that a turn keeps inside it."""
    side = 2 * half_size + 1
    if turn % (TURNS // 4) == 0:
        return first, second[:, torch.rot90(torch.arange(side * side).reshape(side, side), turn // (TURNS // 4)).flatten()]
    weights, disc = _turn_weights(half_size, 2 * math.pi * turn / TURNS, first.dtype)
    return zero_mean_unit_norm(first[:, disc]), zero_mean_unit_norm((second @ weights.T)[:, disc])


@functools.lru_cache(maxsize=None)  # a few (size, turn) pairs, asked for once per view pair
def _turn_weights(half_size: int, angle: float, dtype: torch.dtype) -> tuple[Tensor, Tensor]:
    """(P, P) bilinear weights that sample a (2n + 1)² patch (P pixels, row-major) turned by
    ``angle`` radians about its centre — pixel (x, y) takes the patch's value at its position
    turned back, as :func:`torch.rot90` turns a quarter — and the (P,) bool inscribed disc, where
    every such position lies inside the patch."""
    side = 2 * half_size + 1
    offsets = torch.arange(-half_size, half_size + 1, dtype=torch.float64)
    dy, dx = torch.meshgrid(offsets, offsets, indexing="ij")
    dx, dy = dx.flatten(), dy.flatten()
    cos, sin = math.cos(angle), math.sin(angle)
    x, y = cos * dx - sin * dy + half_size, sin * dx + cos * dy + half_size  # (P,) source positions in the patch
    disc = dx.square() + dy.square() <= half_size**2
    x0, y0 = x.floor().clamp(0, side - 2), y.floor().clamp(0, side - 2)
    fx, fy = x - x0, y - y0
    weights = torch.zeros(side * side, side * side, dtype=torch.float64)
    rows = torch.arange(side * side)
    for ox, oy, w in ((0, 0, (1 - fx) * (1 - fy)), (1, 0, fx * (1 - fy)), (0, 1, (1 - fx) * fy), (1, 1, fx * fy)):
        weights.index_put_((rows, ((y0 + oy) * side + x0 + ox).long()), w, accumulate=True)
    return weights.to(dtype), disc


def turned_homographies(features: CoarseFeatures, pairs: list[tuple[int, int]], config: PairsConfig,
                        generator: torch.Generator | None = None) -> dict[tuple[int, int], Tensor]:
    """The coarse homographies (3, 3) of the view pairs whose second view is turned against the
    first (portrait and landscape shots of one set, a tilted shot): per pair, of the ``TURNS``
    (every 30 degrees) the turn whose homography fitted to the :func:`coarse_matches` keeps the
    most inliers, where it keeps more than the unturned one (and ``min_score`` at least). Only the
    ``FITTED_TURNS`` turns with the most matches get a fit (one RANSAC call per rank over all
    pairs): chance matches are as many at every turn, the right turn adds its true ones. Measured
    on 21 turned pairs (Herz-Jesu-P8 with two portrait views, Fountain-P11 with two views tilted
    30 degrees; ``examples/real_world.py``): the right turn had the most matches in each (77-139
    against at most 65-86 at another), and the other turns' fits kept 5-11 inliers (fewer than
    ``min_score``) — eleven fits where three decide, on pairs that mostly hold no turn at all."""
    matches = [coarse_matches(features, pairs, config, turn) for turn in range(TURNS)]
    _, best = fit_homographies(pairs, matches[0], config, generator)  # the upright fit's inliers: the count to beat
    counts = torch.tensor([[rows.shape[0] for rows in turn] for turn in matches[1:]]).reshape(TURNS - 1, len(pairs))
    ranked = 1 + counts.argsort(dim=0, descending=True, stable=True)[:FITTED_TURNS]  # (FITTED_TURNS, pairs): turns
    found = {}
    for rank in ranked.tolist():
        homographies, inliers = fit_homographies(pairs, [matches[turn][k] for k, turn in enumerate(rank)], config, generator)
        for pair in pairs:
            if homographies[pair] is not None and inliers[pair] > best[pair]:
                found[pair], best[pair] = homographies[pair], inliers[pair]
    return found


def fit_homographies(pairs: list[tuple[int, int]], matches: list[Tensor], config: PairsConfig,
                     generator: torch.Generator | None = None
                     ) -> tuple[dict[tuple[int, int], Tensor | None], dict[tuple[int, int], int]]:
    """Per view pair (i, j), the homography (3, 3) mapping view i's pixels to view j's, fitted by
    RANSAC (``homography_threshold`` px) to its (M, 4) matches x_i, x_j (None with fewer than
    ``min_score`` inliers), and its number of inliers (the number of matches where too few to
    fit). The fits run as ragged batches of ``HOMOGRAPHY_BATCH`` pairs (one RANSAC call each)."""
    homographies = dict.fromkeys(pairs)
    inliers = {pair: rows.shape[0] for pair, rows in zip(pairs, matches)}
    fitted = [k for k, rows in enumerate(matches) if rows.shape[0] >= config.min_score]
    ransac_config = RansacConfig(inlier_threshold=config.homography_threshold, max_trials=2000)
    for first in range(0, len(fitted), HOMOGRAPHY_BATCH):
        chunk = fitted[first:first + HOMOGRAPHY_BATCH]
        data, valid = pad_rows([matches[k] for k in chunk])
        found = ransac(HomographyModel(data, valid), data, ransac_config, valid=valid, generator=generator)
        for row, k in enumerate(chunk):
            count = int(found.inlier_mask[row].sum())
            inliers[pairs[k]] = count
            if count >= config.min_score and bool(found.success[row]):
                homographies[pairs[k]] = found.model[row]
    return homographies, inliers
