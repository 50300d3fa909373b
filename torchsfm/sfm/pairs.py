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
plus the pairs of the sequential window that score at least ``min_score`` (so a shuffled set
wastes no time on its file neighbours); ``auto`` — exhaustive up to ``exhaustive_up_to`` views,
else similarity.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor
from torch.nn import functional

from torchsfm.config import HarrisConfig, PairsConfig, RansacConfig
from torchsfm.features.harris import detect_corners
from torchsfm.images import to_unit_float
from torchsfm.matching.ncc import extract_patches
from torchsfm.robust.models import HomographyModel
from torchsfm.robust.ransac import ransac


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


def coarse_features(greys: Tensor, config: PairsConfig) -> CoarseFeatures:
    """Harris corners and NCC patches of (V, 1, H, W) grey images (uint8 or float in [0, 1])
    reduced to ``coarse_size`` (a few views at a time: no full-resolution float copy of them all)."""
    H, W = greys.shape[-2:]
    factor = max(1, round(max(H, W) / config.coarse_size))
    small = torch.cat([functional.avg_pool2d(to_unit_float(greys[first:first + 8]), factor)
                       for first in range(0, greys.shape[0], 8)])
    corners = detect_corners(small, HarrisConfig(max_corners=config.coarse_corners, spread_grid=4, border=config.patch_half_size + 1))
    patches = []
    for v in range(greys.shape[0]):
        patches.append(extract_patches(small[v], corners.positions[v].double(), config.patch_half_size))
    patches = torch.stack(patches) * corners.valid[..., None]
    points = (corners.positions.double() + 0.5) * factor - 0.5  # pixel centres of the reduced image
    return CoarseFeatures(points=points, patches=patches, valid=corners.valid)


def _mutual_best(ncc: Tensor, threshold: float) -> tuple[Tensor, Tensor]:
    """Mutually best pairs above ``threshold`` of one (K1, K2) NCC table."""
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
        ncc = features.patches[i + 1:] @ features.patches[i].T  # (V - i - 1, L, K): corner l of view v, corner k of i
        best2 = ncc.argmax(1)  # (.., K): best partner in view v of each corner of i
        best1 = ncc.argmax(2)  # (.., L): best corner of i for each corner of v
        mutual = best1.gather(1, best2) == torch.arange(ncc.shape[2])[None]
        strong = ncc.gather(1, best2[:, None])[:, 0] > threshold
        scores[i, i + 1:] = (mutual & strong & features.valid[i][None]).sum(1)
    return scores + scores.T


def select_pairs(scores: Tensor | None, config: PairsConfig, num_views: int) -> list[tuple[int, int]]:
    """View pairs (i < j) of ``num_views`` to verify, from the coarse scores (V, V) and
    ``config.mode`` (``sequential`` and ``exhaustive`` need no scores: None)."""
    V = num_views
    mode = config.mode
    if mode == "auto":
        mode = "exhaustive" if V <= config.exhaustive_up_to else "similarity"
    if mode == "exhaustive":
        return [(i, j) for i in range(V) for j in range(i + 1, V)]
    window = {(i, i + d) for d in range(1, config.window + 1) for i in range(V - d)}
    if mode == "sequential":
        return sorted(window)
    chosen = {(i, j) for i, j in window if int(scores[i, j]) >= config.min_score}
    ranked = torch.argsort(scores, dim=1, descending=True)[:, : config.neighbours]
    for i in range(V):
        for j in ranked[i].tolist():
            if j != i and int(scores[i, j]) >= config.min_score:
                chosen.add((min(i, j), max(i, j)))
    return sorted(chosen)


def pairs_to_match(greys: Tensor, config: PairsConfig, features: CoarseFeatures | None = None) -> list[tuple[int, int]]:
    """The view pairs (i < j) of (V, 1, H, W) grey images to match: :func:`select_pairs` on the
    coarse scores, which only the ``auto`` and ``similarity`` modes compute (from ``features`` if
    given, else from the images)."""
    scores = None
    if config.mode not in ("sequential", "exhaustive"):
        scores = pair_scores(features if features is not None else coarse_features(greys, config), config.ncc_threshold)
    return select_pairs(scores, config, greys.shape[0])


def predicted_homography(features: CoarseFeatures, i: int, j: int, config: PairsConfig,
                         generator: torch.Generator | None = None) -> Tensor | None:
    """The homography (3, 3) mapping view i's pixels to view j's, fitted by RANSAC to the coarse
    mutual-best matches; None if fewer than ``min_score`` matches support it."""
    ki, kj = features.valid[i], features.valid[j]
    ncc = features.patches[i][ki] @ features.patches[j][kj].T
    a, b = _mutual_best(ncc, config.ncc_threshold)
    if a.numel() < config.min_score:
        return None
    data = torch.cat([features.points[i][ki][a], features.points[j][kj][b]], dim=-1)[None]
    found = ransac(HomographyModel(data), data, RansacConfig(inlier_threshold=config.homography_threshold, max_trials=2000),
                   generator=generator)
    if int(found.inlier_mask.sum()) < config.min_score:
        return None
    return found.model[0]
