"""View-pair work of the N-view pipeline: corners, guided putative matches of the chosen pairs,
their robust verification, self-calibration of the focal length, and the moving-object decision
on the tracks built from them."""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import torch
from torch import Tensor

from torchsfm.camera import FOCAL_PRIOR, from_homogeneous, to_homogeneous
from torchsfm.config import Config, HarrisConfig, RansacConfig
from torchsfm.estimators.two_view_geometry import estimate_fundamental
from torchsfm.errors import DegenerateConfigurationError
from torchsfm.features.harris import detect_corners
from torchsfm.images import same_size_batches, stacked_masks, to_unit_float
from torchsfm.geometry.fundamental import sampson_error
from torchsfm.geometry.homography import homography_jacobian
from torchsfm.geometry.self_calibration import focal_from_fundamentals, intrinsics
from torchsfm.matching.matcher import match_candidates, ranking_score
from torchsfm.matching.ncc import CandidateMatches, chance_equivalent_threshold, ncc_candidates, ncc_table, select_candidates
from torchsfm.matching.strength import relaxation_batch
from torchsfm.moving.imor import MovingObjectRejection
from torchsfm.moving.whole_track import reject_moving_objects_in_tracks
from torchsfm.robust.models import HomographyModel
from torchsfm.robust.ragged import pad_rows
from torchsfm.robust.ransac import ransac
from torchsfm.sfm.pairs import pairs_to_match
from torchsfm.sfm.tracks import Tracks
from torchsfm.pipeline import Progress
from torchsfm.threads import map_in_threads, one_at_a_time

DETECTION_CHUNK = 8  # views per batched Harris call
MAX_PATCH_SCALE = 3.0  # a patch warp scales by at most this (or its inverse)
VERIFY_BATCH = 32  # view pairs per batched verification call
MATCH_BATCH = 32  # view pairs whose relaxations run as one (their candidates held at once)
FIXED_SIGNIFICANCE = 1e-3  # chance that noise leaves a still point's two detections as close as a match fixed in the image


@dataclass
class PairMatches:
    """The verified matches of a view pair (i, j), i < j: corner indices ``index1`` (M,) in view
    i and ``index2`` (M,) in view j, F's inliers; ``homography_ratio``: the share of them a
    homography explains; ``F`` (3, 3), x_jᵀ F x_i = 0. ``other_motion``: the (M', ) index pairs
    of a second rigid motion among F's outliers (a moving object), where it was looked for and
    found; they join the tracks, not the pair's own geometry."""

    index1: Tensor
    index2: Tensor
    homography_ratio: float
    F: Tensor
    other_motion: tuple[Tensor, Tensor] | None = None


def detect(greys: list[Tensor], config: HarrisConfig, masks: list[Tensor | None] | None = None) -> list[Tensor]:
    """Corners of every view of (1, H_v, W_v) grey images (uint8 or float in [0, 1]), detected
    ``DETECTION_CHUNK`` views of one size per batched call (the Harris response's intermediate
    maps of a whole video would not fit in memory at once); only where each view's (H_v, W_v)
    bool mask keeps, given ``masks`` (None entries: everywhere)."""
    corners: dict[int, Tensor] = {}
    for views in same_size_batches(greys, DETECTION_CHUNK):
        batch_masks = stacked_masks(masks, views, greys[views[0]].shape[-2:])
        detected = detect_corners(to_unit_float(torch.stack([greys[v] for v in views])), config, batch_masks)
        for b, v in enumerate(views):
            corners[v] = detected.of_image(b)
    return [corners[v] for v in range(len(greys))]


def putative_matches(greys: list[Tensor], raw: list[Tensor], config: Config, generator: torch.Generator, report: Progress,
                     other_motions: bool = False, focal: Tensor | None = None, masks: list[Tensor | None] | None = None
                     ) -> tuple[dict[tuple[int, int], tuple[Tensor, Tensor]], dict[tuple[int, int], Tensor | None]]:
    """NCC + strength-measure matches of the view pairs chosen by ``config.pairs``
    (:mod:`torchsfm.sfm.pairs`), at the detected (``raw``) corners, with the search disc centred
    on the coarse homography's prediction where it moves corners by more than a quarter of the
    disc; pairs with fewer than ``min_pair_inliers`` matches are dropped. Only the matched corner
    indices (index1, index2) are kept per pair (the NCC tables are dropped: memory bounded by one
    pair, not by the number of pairs). Also returns each matched pair's coarse homography (None
    where none holds or ``pairs.guided`` is off). ``other_motions``: see :func:`guided_matches`;
    ``focal``: (V,) the views' focal lengths in pixels where known (coarse matching at one
    angular resolution, :func:`~torchsfm.sfm.pairs.coarse_features`); ``masks``: per view where
    coarse corners may be."""
    homographies = pairs_to_match(greys, config.pairs, generator=generator, guided=config.pairs.guided, focal=focal, masks=masks)
    return guided_matches(greys, raw, homographies, config, report, other_motions), homographies


def guided_matches(greys: list[Tensor], raw: list[Tensor], homographies: dict[tuple[int, int], Tensor | None], config: Config,
                   report: Progress, other_motions: bool = False) -> dict[tuple[int, int], tuple[Tensor, Tensor]]:
    """NCC + strength-measure matches (index1, index2) of every view pair (i, j) of
    ``homographies``, the search disc centred on the pair's homography's prediction where it
    moves corners by more than a quarter of the disc, and the patches warped by its local affine
    map (``pairs.warp_patches``); a None homography: the plain disc. The patches of the view that
    sees the scene larger are the ones warped (:func:`second_sees_larger`). With
    ``other_motions`` (moving bodies to be reconstructed), a pair matched at the prediction is
    matched in the plain disc too, and the corners that left unmatched there join: an object
    moving on its own is not where the scene's homography puts it.
    Pairs with fewer than ``min_pair_inliers`` matches are left out. The pairs' candidates are
    found side by side (:func:`~torchsfm.threads.map_in_threads`) and relaxed together,
    ``MATCH_BATCH`` pairs in one loop (:func:`~torchsfm.matching.strength.relaxation_batch`): the
    same matches as one pair after another."""

    report = one_at_a_time(report)  # called from the matching threads
    config = replace(config, matching=config.matching.for_images(*(grey.shape for grey in greys)))

    def scored(pair: tuple[int, int]) -> _PairCandidates:
        (i, j), H = pair, homographies[pair]
        report(f"matching views {i} and {j}")
        if H is not None and config.pairs.warp_patches and second_sees_larger(H, raw[i]):
            return _candidates_along(greys, raw, j, i, torch.linalg.inv(H), config, other_motions)
        return _candidates_along(greys, raw, i, j, H, config, other_motions)

    matches = {}
    pairs = list(homographies)
    for start in range(0, len(pairs), MATCH_BATCH):
        batch = pairs[start:start + MATCH_BATCH]
        found = map_in_threads(scored, batch)
        relaxed = iter(relaxation_batch(*zip(*(problem for pair in found for problem in pair.problems)), config.matching))
        for (i, j), pair in zip(batch, found):
            index1, index2 = next(relaxed)
            if len(pair.problems) == 2:  # the plain disc's matches whose corners the guided ones left free join
                plain1, plain2 = next(relaxed)
                free = ~torch.isin(plain1, index1) & ~torch.isin(plain2, index2)
                index1, index2 = torch.cat([index1, plain1[free]]), torch.cat([index2, plain2[free]])
            if pair.views != (i, j):
                index1, index2 = index2, index1
            if index1.numel() >= config.reconstruction.min_pair_inliers:
                matches[(i, j)] = (index1, index2)
    return matches


def second_sees_larger(H: Tensor, points: Tensor) -> bool:
    """Whether view j sees the scene larger than view i: the homography H (3, 3) from i to j
    enlarges the surroundings of view i's (N, 2) ``points`` (median local area scale above 1).
    Then view j's patches are the ones to warp: shrunk, they keep their detail, where view i's,
    magnified, would blur."""
    return float(torch.linalg.det(homography_jacobian(H, points.double())).median()) > 1


@dataclass
class _PairCandidates:
    """The candidates of a view pair as matched: ``views`` (i, j), view i's patches the warped
    ones; ``problems``: (candidates, ranking score, (N_i, N_j) corners) at the homography's
    prediction, and in the plain disc where that is matched too: what relaxation takes."""

    views: tuple[int, int]
    problems: list[tuple[CandidateMatches, Tensor, tuple[int, int]]]


def _candidates_along(greys: list[Tensor], raw: list[Tensor], i: int, j: int, H: Tensor | None, config: Config,
                      other_motions: bool) -> _PairCandidates:
    """The scored candidates of views i and j, guided by the homography H (3, 3) from i to j (or
    None) as :func:`guided_matches` says."""
    predicted = warp = None
    if H is not None:
        moved = from_homogeneous(to_homogeneous(raw[i].double()) @ H.T)
        if float((moved - raw[i]).norm(dim=-1).median()) > config.matching.search_radius / 4:
            predicted = moved
        if config.pairs.warp_patches:
            warp = patch_warps(H, raw[i].double())
    image1, image2 = to_unit_float(greys[i]), to_unit_float(greys[j])
    discs = [(predicted, warp)] + ([(None, None)] if other_motions and predicted is not None else [])
    problems = []
    for centres, patch_warp in discs:
        candidates = ncc_candidates(image1, image2, raw[i], raw[j], config.matching, centres, patch_warp)
        problems.append((candidates, ranking_score(raw[i], raw[j], candidates, config.matching), (raw[i].shape[0], raw[j].shape[0])))
    return _PairCandidates((i, j), problems)


def epipolar_matches(greys: list[Tensor], raw: list[Tensor], corners: list[Tensor], pairs: dict[tuple[int, int], PairMatches],
                     homographies: dict[tuple[int, int], Tensor | None], config: Config) -> dict[tuple[int, int], PairMatches]:
    """Verified pairs matched again, guided by their F: each corner's candidates are the other
    view's corners in its epipolar band — Sampson distance under F (on the undistorted
    ``corners``) within the RANSAC inlier threshold, on the side of the epipole that puts the
    point in front of both cameras (:func:`oriented_side`) — instead of the search disc, with the coarse
    homography's patch warps (``pairs.warp_patches``). The band holds about a tenth of the disc's
    corners, so its NCC threshold is the one at which a corner gets no more chance candidates
    than the disc gets at ``matching.ncc_threshold`` (:func:`chance_equivalent_threshold`: about
    0.5-0.65 instead of 0.8 on the Strecha pairs); then the strength measure and relaxation as
    before. Every match is consistent with F by construction. A pair keeps the guided matches
    where they are more than its verified ones. The pairs are matched side by side, as in
    :func:`guided_matches`."""
    matching = config.matching.for_images(*(grey.shape for grey in greys))

    def rematch(pair: tuple[int, int]) -> PairMatches:
        (i, j), verified = pair, pairs[pair]
        H = homographies.get((i, j))
        warp = patch_warps(H, raw[i].double()) if H is not None and config.pairs.warp_patches else None
        ncc = ncc_table(to_unit_float(greys[i]), to_unit_float(greys[j]), raw[i], raw[j], matching.patch_half_size, warp)
        band = epipolar_band(verified.F.double(), corners[i].double(), corners[j].double(), config.fundamental.ransac.inlier_threshold)
        band &= oriented_side(verified.F.double(), corners[i].double(), corners[j].double(),
                              corners[i][verified.index1].double(), corners[j][verified.index2].double())
        disc = torch.cdist(raw[i].double(), raw[j].double()) < matching.search_radius
        threshold = chance_equivalent_threshold(ncc, disc, band, matching.ncc_threshold)
        matches = match_candidates(raw[i], raw[j], select_candidates(ncc, band, threshold), matching)
        more = matches.index1.numel() > verified.index1.numel()
        return replace(verified, index1=matches.index1, index2=matches.index2) if more else verified

    return dict(zip(pairs, map_in_threads(rematch, pairs)))


def epipolar_band(F: Tensor, x1: Tensor, x2: Tensor, threshold: float) -> Tensor:
    """(N1, N2) bool: the pairs of points x1 (N1, 2), x2 (N2, 2) whose Sampson distance under F
    (3, 3) is below ``threshold`` (pixels)."""
    h1, h2 = to_homogeneous(x1), to_homogeneous(x2)
    line2, line1 = h1 @ F.T, h2 @ F  # (N1, 3) lines F x1 in image 2, (N2, 3) lines Fᵀ x2 in image 1
    algebraic = line2 @ h2.T  # (N1, N2): x2ᵀ F x1
    denominator = line2[:, :2].square().sum(-1)[:, None] + line1[:, :2].square().sum(-1)[None]
    return algebraic.square() < threshold**2 * denominator


def oriented_side(F: Tensor, x1: Tensor, x2: Tensor, inliers1: Tensor, inliers2: Tensor) -> Tensor:
    """(N1, N2) bool: the pairs of points x1 (N1, 2), x2 (N2, 2) on the side of the epipole in
    image 2 that F's verified matches ``inliers1`` ↔ ``inliers2`` (M, 2) take — the oriented
    epipolar constraint (Werner & Pajdla 2001): for a scene point in front of both cameras,
    e2 × x2 and F x1 are the same line with one sign. A match on the other side would put its
    point behind a camera; in forward motion (the epipole inside the image) it halves the band.
    The sign is the verified matches' majority."""
    e2 = torch.linalg.svd(F.T).Vh[-1]  # Fᵀ e2 = 0, up to sign: the majority sign absorbs it

    def lines_and_rays(a: Tensor, b: Tensor) -> tuple[Tensor, Tensor]:  # F a (A, 3) and e2 × b (B, 3)
        return to_homogeneous(a) @ F.T, torch.linalg.cross(e2.expand(b.shape[0], 3), to_homogeneous(b))

    lines, rays = lines_and_rays(inliers1, inliers2)
    majority = torch.sign(torch.sign((lines * rays).sum(-1)).sum())  # one sign per verified match, then the vote
    lines, rays = lines_and_rays(x1, x2)
    return (lines @ rays.T) * majority > 0


def patch_warps(H: Tensor, points: Tensor) -> Tensor | None:
    """(N, 2, 2) per point (N, 2) of view i, the affine map from view j's patch offsets to view
    i's: the inverse of the homography's local Jacobian, so that view i's patch is sampled as
    view j sees it. Points where the local map is a reflection or scales by more than
    ``MAX_PATCH_SCALE`` (the homography is a poor local model there) keep the identity; None
    when no point needs a warp (every map within 5 % of the identity)."""
    jacobian = homography_jacobian(H, points)
    determinant = torch.linalg.det(jacobian)
    usable = (determinant > MAX_PATCH_SCALE ** -2) & (determinant < MAX_PATCH_SCALE ** 2)
    identity = torch.eye(2, dtype=jacobian.dtype).expand_as(jacobian)
    warp = torch.where(usable[:, None, None], torch.linalg.inv(torch.where(usable[:, None, None], jacobian, identity)), identity)
    if float((warp - identity).abs().amax()) < 0.05:
        return None
    return warp


def verify_pairs(putative: dict[tuple[int, int], tuple[Tensor, Tensor]], corners: list[Tensor], config: Config,
                 generator: torch.Generator, report: Progress, other_motions: bool = False) -> dict[tuple[int, int], PairMatches]:
    """Robust F of every pair (the undistorted ``corners``), then the homography test on F's
    inliers; pairs keeping ``min_pair_inliers`` survive. Both run as ragged batches of
    ``VERIFY_BATCH`` pairs (one call each: the engine's rounds run on the pairs still drawing).
    With ``other_motions`` (moving bodies to be reconstructed), a second F is fitted to each
    pair's outliers, and where it keeps ``moving_objects.min_object_tracks`` of them they are
    the pair's ``other_motion``: a moving object's matches, which one F per pair throws away.
    Matches that stay where they are while the pair's scene moves (:func:`fixed_in_image`: a
    video's burnt-in overlay) are not inliers."""
    report(f"verifying {len(putative)} pairs")
    homography_config = RansacConfig(inlier_threshold=config.reconstruction.homography_threshold)
    keys = list(putative)
    result = {}
    for first in range(0, len(keys), VERIFY_BATCH):
        chunk = keys[first:first + VERIFY_BATCH]
        data, valid = pad_rows([torch.cat([corners[i][putative[(i, j)][0]], corners[j][putative[(i, j)][1]]], -1) for i, j in chunk])
        fundamental = estimate_fundamental(data[..., :2], data[..., 2:], valid=valid, config=config, generator=generator)
        inliers = fundamental.inlier_mask & ~fixed_in_image(data, fundamental.inlier_mask, fundamental.F)  # (B, N)
        kept = torch.nonzero(fundamental.success & (inliers.sum(-1) >= config.reconstruction.min_pair_inliers)).flatten()
        if kept.numel() == 0:
            continue
        homography = ransac(HomographyModel(data[kept], inliers[kept]), data[kept], homography_config, valid=inliers[kept],
                            generator=generator)
        ratios = homography.inlier_mask.sum(-1) / inliers[kept].sum(-1)
        others = second_motions(data[kept], valid[kept] & ~inliers[kept], config, generator) if other_motions else [None] * kept.numel()
        for b, ratio, other in zip(kept.tolist(), ratios.tolist(), others):
            index1, index2 = putative[chunk[b]]
            mask = inliers[b, : index1.numel()]
            other = None if other is None else (index1[other[: index1.numel()]], index2[other[: index1.numel()]])
            result[chunk[b]] = PairMatches(index1[mask], index2[mask], ratio, fundamental.F[b], other)
    return result


def fixed_in_image(data: Tensor, inliers: Tensor, F: Tensor) -> Tensor:
    """(B, N) bool: which of B pairs' (B, N, 4) matches (x1, x2) are fixed in the image — their two
    positions closer than noise would leave even a point that does not move, in a pair whose
    ``inliers`` (B, N) do move: an overlay burnt into a video (a time stamp, a logo), which looks
    like a point at infinity to a camera that drives straight and bends the cameras towards its
    zero motion where it turns. With σ the pair's noise (1.4826 × the median Sampson distance of
    its inliers to F (B, 3, 3)), a still point's displacement d has |d|² ~ 2σ²χ²(2), so |d| < 2σ√α
    has probability α (``FIXED_SIGNIFICANCE``) and |d| > 2σ√ln(1/α) too: the pair moves where the
    median inlier exceeds that. Identical image content gives identical sub-pixel corners (|d| = 0);
    a point's independent detections in two images never come as close but by that chance."""
    x1, x2 = data[..., :2], data[..., 2:]
    moved = (x2 - x1).norm(dim=-1)
    sigma = 1.4826 * torch.where(inliers, sampson_error(F, x1, x2).sqrt(), torch.nan).nanmedian(-1).values
    moving = torch.where(inliers, moved, torch.nan).nanmedian(-1).values > 2 * sigma * math.sqrt(math.log(1 / FIXED_SIGNIFICANCE))
    return inliers & moving[:, None] & (moved < 2 * sigma[:, None] * math.sqrt(FIXED_SIGNIFICANCE))


def second_motions(data: Tensor, outliers: Tensor, config: Config, generator: torch.Generator) -> list[Tensor | None]:
    """Per pair of (B, N, 4) correspondences, the (N,) mask of a second F's inliers among the
    (B, N) ``outliers`` of the first, or None where fewer than ``moving_objects.min_object_tracks``
    fit one (one ragged call for the B pairs)."""
    fundamental = estimate_fundamental(data[..., :2], data[..., 2:], valid=outliers, config=config, generator=generator)
    inliers = fundamental.inlier_mask & outliers
    enough = fundamental.success & (inliers.sum(-1) >= config.moving_objects.min_object_tracks)
    return [mask if bool(found) else None for mask, found in zip(inliers, enough)]


def image_centre(size: tuple[int, int]) -> Tensor:
    """The centre (2,) float64 of an image of ``size`` (H, W), in pixel coordinates."""
    H, W = size
    return torch.tensor([(W - 1) / 2, (H - 1) / 2], dtype=torch.float64)


def centred_intrinsics(focals: list[float], sizes: list[tuple[int, int]]) -> Tensor:
    """K (V, 3, 3) of square pixels: each view's focal length (px) with the principal point at
    the centre of its image of size (H, W)."""
    return torch.stack([intrinsics(focal, image_centre(size)) for focal, size in zip(focals, sizes)])


def self_calibrate(pairs: dict[tuple[int, int], PairMatches], sizes: list[tuple[int, int]], config: Config) -> tuple[Tensor, bool]:
    """K (V, 3, 3) of the views of ``sizes`` (H, W) each — one camera, some views possibly turned
    to portrait — with the principal point at each image's centre and the focal length that
    makes the verified pairs' essential matrices best (pairs a homography explains are left out
    when others exist: their F does not fix the focal length), and whether the pairs determined
    it: where they do not (a camera translating without turning, e.g. driving straight), the
    focal length is the prior ``FOCAL_PRIOR`` × the larger image side, as in COLMAP. Where the
    centres differ (a turned view), each pair's F is taken to coordinates about them."""
    if not pairs:
        raise DegenerateConfigurationError("no view pair could be verified, so the focal length cannot be estimated: give K")
    centres = torch.stack([image_centre(size) for size in sizes])  # (V, 2)
    one_centre = bool((centres == centres[0]).all())
    general = {key: m for key, m in pairs.items() if m.homography_ratio <= config.reconstruction.max_homography_ratio} or pairs
    F = torch.stack([m.F.double() if one_centre else about_centres(m.F.double(), centres[i], centres[j]) for (i, j), m in general.items()])
    prior = FOCAL_PRIOR * max(max(size) for size in sizes)
    focal = focal_from_fundamentals(F, centres[0] if one_centre else centres.new_zeros(2), prior)
    return centred_intrinsics([prior if focal is None else focal] * len(sizes), sizes), focal is not None


def about_centres(F: Tensor, centre_i: Tensor, centre_j: Tensor) -> Tensor:
    """F (3, 3) with x_jᵀ F x_i = 0 in pixels, for coordinates about the centres (2,) of views i and
    j: T_jᵀ F T_i, T the translation from centred coordinates to pixels."""
    T_i, T_j = torch.eye(3, dtype=F.dtype), torch.eye(3, dtype=F.dtype)
    T_i[:2, 2], T_j[:2, 2] = centre_i, centre_j
    return T_j.T @ F @ T_i


def reject_moving_tracks(tracks: Tracks, corners: list[Tensor], config: Config, generator: torch.Generator
                          ) -> tuple[Tracks, dict[tuple[int, int, int], MovingObjectRejection], list[int], Tensor]:
    """Keep the tracks :func:`~torchsfm.moving.whole_track.reject_moving_objects_in_tracks` keeps
    (``moving_objects.track_method``, ``segmentation`` with ``reconstruct_objects``; the triplet
    votes use every consecutive view triplet; tracks it cannot test are dropped too). Returns the
    kept tracks (renumbered), each tested triplet's result, per view the number of its
    observations rejected, and every track's rigid-motion label (T,) (0 the static scene, -1
    none; all -1 for ``triplets``)."""
    V = len(corners)
    pixels, visible = tracks.dense(corners, V)
    triplets = [(first, first + 1, first + 2) for first in range(V - 2)]
    if config.moving_objects.reconstruct_objects:
        config = replace(config, moving_objects=replace(config.moving_objects, track_method="segmentation"))
    decision = reject_moving_objects_in_tracks(pixels, visible, triplets=triplets, config=config, generator=generator)
    results = dict(zip(decision.triplets, decision.results))
    rejected_per_view = (visible & ~decision.background_mask[None]).sum(1).tolist()
    return tracks.subset(decision.background_mask), results, rejected_per_view, decision.group_labels


