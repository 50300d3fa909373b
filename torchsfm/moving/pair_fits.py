"""Two-view fits of track sets, one per frame pair: the residuals the segmentation judges tracks by (ours).

Least-trimmed-squares fundamental matrices or homographies of C track sets over (P, 2) frame
pairs and every track's RMS distance to them (:func:`track_residuals`; from RANSAC's inliers
where strays could pull the first fit), the frame pairs a sequence is judged over
(:func:`frame_pairs`), and the per-set summaries built on them.
"""

from __future__ import annotations

import torch
from torch import Tensor

from torchsfm.config import FundamentalConfig
from torchsfm.geometry.fundamental import eight_point, sampson_error
from torchsfm.geometry.homography import homography_dlt, transfer_error
from torchsfm.robust.models import FundamentalModel
from torchsfm.robust.ransac import ransac

SAMPLE_SIZE = 8  # tracks an 8-point fit stands on (a sample, and the fewest a set is fitted from)
REFITS = 3  # trimmed refits of a motion's F (diagnostics)
BLOCK_ELEMENTS = 2**15  # tracks × set-and-pair problems fitted at a time (see ``track_residuals``)


def frame_pairs(visible: Tensor, count: int | None = None) -> Tensor:
    """(P, 2) frame pairs (f, f + gap) for (F, N) visibility: gap = a third of the sequence, at
    most the median span (last frame − first frame) of the tracks seen twice, at least 1 — wide
    enough for parallax, short enough that the tracks of a video are seen at both ends; the
    first frames spread evenly, ``count`` of them (default: every possible one)."""
    F = visible.shape[0]
    gap = max(1, min((F - 1) // 3, median_span(visible)))
    starts = torch.linspace(0, F - 1 - gap, min(count or F, F - gap), device=visible.device).round().long().unique()
    return torch.stack([starts, starts + gap], 1)


def median_span(visible: Tensor) -> int:
    """The median over the tracks seen at least twice of their span, last frame − first frame
    ((F, N) visibility; 0 if none)."""
    frame = torch.arange(visible.shape[0], device=visible.device)[:, None]
    first = torch.where(visible, frame, visible.shape[0]).amin(0)
    last = torch.where(visible, frame, -1).amax(0)
    spans = (last - first)[visible.sum(0) >= 2]
    return int(spans.median()) if spans.numel() else 0


def pairs_seen(visible: Tensor, pairs: Tensor) -> Tensor:
    """(N,) how many of the (P, 2) frame pairs each track is seen in (at least 1): (F, N) visibility."""
    return (visible[pairs[:, 0]] & visible[pairs[:, 1]]).sum(0).clamp_min(1)


def track_residuals(tracks: Tensor, visible: Tensor, members: Tensor, pairs: Tensor,
                    model: str = "fundamental", generator: torch.Generator | None = None) -> tuple[Tensor, Tensor]:
    """Every track's RMS distance (pixels) to one two-view model per frame pair fitted to each of
    C track sets: (F, N, 2) tracks, (F, N) visibility, (C, N) bool members, (P, 2) frame pairs ->
    (C, N) RMS and (C, N) bool where defined (the track seen in a pair the set could fit). The
    ``model`` is ``fundamental`` (8-point, Sampson distance) or ``homography`` (DLT, transfer
    distance: a plane, or a scene without parallax). A least-trimmed-squares fit (``REFITS``
    refits on the half of the set with the smallest residuals, so up to half of it may be
    strays), from all the set's tracks — or, given a ``generator`` (``fundamental`` only), from
    each pair's RANSAC inliers (``FundamentalConfig().ransac``): gross strays then cannot pull
    the first fit away."""
    a, b = pairs[:, 0], pairs[:, 1]
    both = (visible[a] & visible[b])[None]  # (1, P, N)
    seen = members[:, None] & both  # (C, P, N)
    C, P, N = seen.shape
    x1, x2 = tracks[a].expand(C, -1, -1, -1), tracks[b].expand(C, -1, -1, -1)  # (C, P, N, 2)
    weights = seen.to(tracks.dtype)
    if generator is not None and model == "fundamental":
        weights = ransac_inliers(x1, x2, seen, generator).to(tracks.dtype)
    # a few pairs at a time: each (set, pair) fit is its own problem, and the DLT's (C, P, 2N, 9)
    # design matrices of a long video's pairs at once stream from memory (ten times slower)
    step = max(1, BLOCK_ELEMENTS // (C * N))
    blocks = [trimmed_pair_fits(x1[:, k:k + step], x2[:, k:k + step], seen[:, k:k + step], weights[:, k:k + step], model)[1:]
              for k in range(0, P, step)]
    residual, usable = (torch.cat(parts, 1) for parts in zip(*blocks))
    valid = both & usable[..., None]
    squares = torch.where(valid, residual.square(), 0.0).sum(1)
    return (squares / valid.sum(1).clamp_min(1)).sqrt(), valid.any(1)


def trimmed_pair_fits(x1: Tensor, x2: Tensor, seen: Tensor, weights: Tensor, model: str) -> tuple[Tensor, Tensor, Tensor]:
    """The least-trimmed-squares fits of :func:`track_residuals` for (*, p) set-and-pair problems:
    (*, p, N, 2) positions, (*, p, N) bool seen and starting weights -> the last fits (*, p, 3, 3),
    every track's (*, p, N) distance to its problem's last fit, and (*, p) bool where a fit stood
    on ``SAMPLE_SIZE`` tracks throughout. The refits see only the M tracks some problem holds, the
    last fit measures all N: the other tracks weigh nothing in a fit (a video's left out of the
    clustering, the other motions' — KITTI 06's scene: about 3 000 of 12 638 tracks)."""
    fit, distance = PAIR_MODELS[model]
    held = torch.nonzero(seen.flatten(0, -2).any(0))[:, 0]  # (M,)
    if held.numel() < SAMPLE_SIZE:  # no problem can be fitted: every track stands in, as for an unusable problem
        held = torch.arange(seen.shape[-1], device=seen.device)
    y1, y2, held_seen, weights = x1[..., held, :], x2[..., held, :], seen[..., held], weights[..., held]
    usable = held_seen.sum(-1) >= SAMPLE_SIZE  # (*, p)
    for _ in range(REFITS + 1):
        models = fit(y1, y2, torch.where(usable[..., None], weights, 1.0))
        residual = distance(models, y1, y2)  # (*, p, M)
        half = torch.where(held_seen, residual, torch.nan).nanmedian(-1).values  # (*, p)
        weights = (held_seen & (residual <= half[..., None])).to(x1.dtype)
        usable &= weights.sum(-1) >= SAMPLE_SIZE
    return models, distance(models, x1, x2), usable


def ransac_inliers(x1: Tensor, x2: Tensor, seen: Tensor, generator: torch.Generator) -> Tensor:
    """(C, P, N) bool: the inliers of one RANSAC fundamental matrix (the project's defaults) per
    track set and frame pair, among the ``seen`` (C, P, N) tracks of (C, P, N, 2) positions x1,
    x2; all ``seen`` where RANSAC finds none."""
    C, P, N = seen.shape
    data = torch.cat([x1, x2], -1).reshape(C * P, N, 4)
    valid = seen.reshape(C * P, N)
    found = ransac(FundamentalModel(data, valid), data, FundamentalConfig().ransac, valid=valid, generator=generator)
    return torch.where(found.success[:, None], found.inlier_mask, valid).reshape(C, P, N)


def motion_residuals(tracks: Tensor, visible: Tensor, members: Tensor, pairs: Tensor,
                     generator: torch.Generator | None = None) -> Tensor:
    """How well one rigid motion explains each of C track sets: (C,) median over each set's
    tracks of their RMS Sampson distance (:func:`track_residuals`, from RANSAC's inliers given a
    ``generator``); NaN where a set has fewer than 8 tracks in every pair."""
    rms, judged = track_residuals(tracks, visible, members, pairs, generator=generator)
    return torch.where(judged & members, rms, torch.nan).nanmedian(-1).values


def plane_residuals(tracks: Tensor, visible: Tensor, members: Tensor, pairs: Tensor) -> Tensor:
    """(N,) every track's RMS transfer distance (pixels) to the (N,) bool ``members`` tracks'
    homographies, one per frame pair (:func:`track_residuals`); NaN where not judged."""
    return _one_set_residuals(tracks, visible, members, pairs, "homography")


def epipolar_residuals(tracks: Tensor, visible: Tensor, members: Tensor, pairs: Tensor) -> Tensor:
    """(N,) every track's RMS Sampson distance (pixels) to the (N,) bool ``members`` tracks'
    fundamental matrices, one per frame pair (:func:`track_residuals`); NaN where not judged."""
    return _one_set_residuals(tracks, visible, members, pairs, "fundamental")


def _one_set_residuals(tracks: Tensor, visible: Tensor, members: Tensor, pairs: Tensor, model: str) -> Tensor:
    """:func:`track_residuals` of one (N,) bool set -> (N,), NaN where not judged."""
    rms, judged = track_residuals(tracks, visible, members[None], pairs, model)
    return torch.where(judged[0], rms[0], torch.nan)


PAIR_MODELS = {
    "fundamental": (eight_point, lambda F, x1, x2: sampson_error(F, x1, x2).sqrt()),
    "homography": (homography_dlt, lambda G, x1, x2: transfer_error(G, x1, x2).sqrt()),
}
