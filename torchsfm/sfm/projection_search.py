"""Observations found by projection: every registered view searched for the model's points it
does not observe yet, and a view the mapper could not resect searched for all of them where a
predicted pose puts them (:func:`points_seen_by_projection`: tracking against the map).

The matcher pairs Harris corners, each found at one scale in its own image; a view that sees
the scene at another scale (a smaller image, a zoom) or blurred shares few corners with its
partners, and its pose rests on few observations. Once the cameras are adjusted, each point's
projection tells where to look: around it, the patch of the view that observes the point from
the nearest direction — warped to this view through the plane at the point that faces both
cameras (normal along the bisector of the two rays), low-passed where it shrinks — is compared
by NCC with this view's image at every integer offset within the reprojection gate; an interior
peak at the matcher's NCC threshold is taken, sub-pixel by the biquadric fit of the Harris
detector. The new observations join their tracks; the adjustments that follow gate and weigh
them like the others.
"""

from __future__ import annotations

import math
from collections import OrderedDict
from typing import TYPE_CHECKING

import torch
import torch.nn.functional as functional
from kornia.filters import gaussian_blur2d
from torch import Tensor

from torchsfm.camera import Camera, distort_points, to_homogeneous, undistort_points
from torchsfm.config import Config
from torchsfm.features.harris import biquadric_offsets
from torchsfm.images import inside_mask, to_unit_float
from torchsfm.matching.ncc import extract_patches, sample_patches
from torchsfm.sfm.tracks import Tracks

if TYPE_CHECKING:  # the mapper's state type only: mapping.py calls this module
    from torchsfm.sfm.mapping import MapperState

SEARCH_CHUNK = 1024  # candidate points per batched search: (chunk, offsets, patch) samples, 25 MB of float64


def observations_by_projection(model: MapperState, greys: list[Tensor], distortion: Tensor, linked: Tensor, config: Config,
                               masks: list[Tensor | None] | None = None) -> int:
    """Add to the ``model`` the observations of its points that its registered views miss, found
    by projection (module docstring); returns how many.

    Args:
        greys: per view the (1, H_v, W_v) grey image the corners were detected on.
        distortion: (V, 2) the views' known radial coefficients (the corners undistorted by them).
        linked: (V, V) bool, the view pairs whose matches were verified: a view is searched for
            the points its linked views observe (their images overlap at a scale and angle the
            matcher could bridge; a video's distant frames are not searched for each other's points).
        masks: per view the (H_v, W_v) bool mask of where features may be found (None:
            everywhere), kept to as the detector keeps to it.

    Where the model has estimated a radial distortion (``model.radial``), the search looks
    through it too."""
    inlier = model.observation_errors() < config.reconstruction.max_reprojection_error
    sources = LowPassedImages(greys)
    lenses = _lenses(model, distortion)
    radius = math.ceil(config.reconstruction.max_reprojection_error)
    found_views, found_tracks, found_raw = [], [], []
    for view in torch.nonzero(model.registered).flatten().tolist():
        mask = masks[view] if masks is not None else None
        tracks, raw = _search_view(model, sources, lenses, mask, config, view, inlier & linked[view][model.tracks.view], radius)
        found_views.append(torch.full_like(tracks, view))
        found_tracks.append(tracks)
        found_raw.append(raw)
    track = torch.cat(found_tracks)
    join_observations(model, distortion, torch.cat(found_views), track, torch.cat(found_raw))
    return int(track.numel())


def points_seen_by_projection(model: MapperState, greys: list[Tensor], distortion: Tensor, linked: Tensor, config: Config,
                              view: int, radius: int, mask: Tensor | None = None) -> tuple[Tensor, Tensor]:
    """Where ``view``, at the pose the model holds for it (a prediction: the view need not be
    registered), is found to see the model's points: each point searched within ``radius`` px of
    its projection as :func:`observations_by_projection` searches, also the points the view's own
    matches already tie to a corner of it (in a repeated texture those ties may be wrong).
    Returns the tracks (M,) and where the view sees them (M, 2), as detected; arguments as for
    :func:`observations_by_projection`, ``mask`` the view's."""
    inlier = model.observation_errors() < config.reconstruction.max_reprojection_error
    return _search_view(model, LowPassedImages(greys), _lenses(model, distortion), mask, config, view,
                        inlier & linked[view][model.tracks.view], radius, observed_too=True)


def model_pixels(model: MapperState, distortion: Tensor, views: Tensor, raw: Tensor) -> tuple[Tensor, Tensor]:
    """The (M, 2) pixels ``raw`` of the (M,) ``views`` as detected, as the model holds its
    observations: with the known distortion undone (``observed``) and then the model's estimated
    k1 too (``pixels``)."""
    lenses = _lenses(model, distortion)
    observed = _through(lenses[0], raw, model.K[views], views, undistort_points)
    return observed, _through(lenses[1], observed, model.K[views], views, undistort_points)


def join_observations(model: MapperState, distortion: Tensor, views: Tensor, tracks: Tensor, raw: Tensor) -> None:
    """Add to the ``model`` the observations of the (M,) ``tracks`` in the (M,) ``views`` at the
    (M, 2) pixels ``raw`` as detected, each replacing the view's observation of its track where
    it has one."""
    if not tracks.numel():
        return
    observed, pixels = model_pixels(model, distortion, views, raw)
    old = model.tracks
    key = old.view * old.num_tracks + old.track
    kept = ~torch.isin(key, views * old.num_tracks + tracks)
    order = torch.argsort(torch.cat([old.track[kept], tracks]), stable=True)  # Tracks are sorted by track
    corner = torch.full_like(tracks, -1)  # no detected corner
    model.tracks = Tracks(view=torch.cat([old.view[kept], views])[order], corner=torch.cat([old.corner[kept], corner])[order],
                          track=torch.cat([old.track[kept], tracks])[order], num_tracks=old.num_tracks)
    model.raw_pixels = torch.cat([model.raw_pixels[kept].to(raw.dtype), raw])[order]
    model.observed = torch.cat([model.observed[kept], observed])[order]
    model.pixels = torch.cat([model.pixels[kept], pixels])[order]


def _lenses(model: MapperState, distortion: Tensor) -> tuple[Tensor | None, Tensor | None]:
    """The two distortions between a view's detected pixels and the model's: the (V, 2) known
    radial coefficients (undone on the corners), then the model's estimated k1 (undone in its
    pixels), each None where it is zero."""
    estimated = torch.zeros_like(distortion)
    estimated[:, 0] = model.radial
    return (distortion if bool(distortion.any()) else None), (estimated if model.radial else None)


def _through(lens: Tensor | None, points: Tensor, K: Tensor, view: Tensor | int, mapping) -> Tensor:
    """The (M, 2) points mapped by ``mapping`` (:func:`distort_points` or :func:`undistort_points`)
    through each one's view's (V, 2) ``lens`` with its (M, 3, 3) or (3, 3) K; unchanged where
    there is no lens."""
    if lens is None:
        return points
    if K.dim() == 2:
        return mapping(points, K, lens[view])
    return mapping(points[:, None], K, lens[view])[:, 0]


def _search_view(model: MapperState, sources: LowPassedImages, lenses: tuple[Tensor | None, Tensor | None], mask: Tensor | None,
                 config: Config, view: int, usable: Tensor, radius: int, observed_too: bool = False) -> tuple[Tensor, Tensor]:
    """The tracks (M,) whose points ``view`` is found to see and where (M, 2), as detected, each
    searched within ``radius`` px of its projection with the patch of one of its ``usable`` (T,)
    observations, where the view's ``mask`` (or None) keeps; the points the view observes
    already only if ``observed_too``."""
    half = config.matching.patch_half_size
    image = sources.at(view, 1.0)
    height, width = image.shape
    tracks_of, views_of = model.tracks.track, model.tracks.view
    seen_here = torch.zeros(model.tracks.num_tracks, dtype=torch.bool)
    if not observed_too:
        seen_here[tracks_of[views_of == view]] = True
    candidates = torch.nonzero(model.has_point & ~seen_here).flatten()
    camera = Camera(model.K[view], model.R[view], model.t[view])
    X = model.points[candidates]
    depth = camera.world_to_camera(X[None])[0, :, 2]
    undistorted = camera.project(X[None])[0]
    projected = _through(lenses[0], _through(lenses[1], undistorted, model.K[view], view, distort_points), model.K[view], view,
                         distort_points)  # as detected
    margin = half + radius + 1
    inside = (depth > 0) & (projected >= margin).all(-1) & (projected[:, 0] <= width - 1 - margin) & (projected[:, 1] <= height - 1 - margin)
    reference = _nearest_observations(model, candidates[inside], view, usable)
    kept = torch.zeros_like(inside)
    kept[inside] = reference >= 0
    candidates, X, undistorted, projected, reference = (candidates[kept], X[kept], undistorted[kept], projected[kept],
                                                        reference[reference >= 0])
    if not candidates.numel():
        return candidates, projected
    warp = _plane_warps(model, X, undistorted, view, views_of[reference])
    scale = warp.det().abs().sqrt()  # reference pixels per pixel of this view
    # a patch whose footprint in its partner's image exceeds that image (a plane nearly edge-on,
    # a point near the partner camera) has nothing to be compared with: not searched
    fits = scale * (2 * half + 1) <= sources.shorter_sides[views_of[reference]]
    candidates, projected, reference, warp, scale = candidates[fits], projected[fits], reference[fits], warp[fits], scale[fits]
    if not candidates.numel():
        return candidates, projected
    patches = torch.empty(candidates.numel(), (2 * half + 1) ** 2, dtype=image.dtype)
    partners = views_of[reference]
    for partner in partners.unique().tolist():
        mine = torch.nonzero(partners == partner).flatten()
        source = sources.at(partner, float(scale[mine].median()))
        patches[mine] = extract_patches(source[None], model.raw_pixels[reference[mine]].double(), half, warp[mine])
    peaks = [_ncc_peaks(image, projected[chunk], patches[chunk], half, radius, config.matching.ncc_threshold)
             for chunk in torch.arange(candidates.numel()).split(SEARCH_CHUNK)]
    positions, found = torch.cat([position for position, _ in peaks]), torch.cat([found for _, found in peaks])
    found &= inside_mask(positions, mask)
    return candidates[found], positions[found]


def _nearest_observations(model: MapperState, candidates: Tensor, view: int, usable: Tensor) -> Tensor:
    """For each candidate track (M,), its ``usable`` (T,) observation (index into the model's
    tracks) in the view whose ray to the point is nearest in direction to ``view``'s; -1 if none."""
    tracks_of, views_of = model.tracks.track, model.tracks.view
    slot = torch.full((model.tracks.num_tracks,), -1, dtype=torch.long)
    slot[candidates] = torch.arange(candidates.numel())
    usable = usable & (slot[tracks_of] >= 0)
    rows = torch.nonzero(usable).flatten()
    centres = model.centres()
    point = model.points[tracks_of[rows]]
    towards_view = functional.normalize(centres[view] - point, dim=-1)
    towards_partner = functional.normalize(centres[views_of[rows]] - point, dim=-1)
    closeness = (towards_view * towards_partner).sum(-1)  # cosine of the angle between the rays
    best = torch.full((candidates.numel(),), -2.0, dtype=closeness.dtype).scatter_reduce(0, slot[tracks_of[rows]], closeness, "amax")
    chosen = closeness == best[slot[tracks_of[rows]]]
    reference = torch.full((candidates.numel(),), -1, dtype=torch.long)
    reference[slot[tracks_of[rows[chosen]]]] = rows[chosen]
    return reference


def _plane_warps(model: MapperState, X: Tensor, pixels: Tensor, view: int, partners: Tensor) -> Tensor:
    """(M, 2, 2) linear maps from offsets around the undistorted ``pixels`` (M, 2) in ``view`` to
    offsets in each point's partner view (M,), through the plane at the point X (M, 3) whose
    normal bisects the rays to the two cameras (central differences of one pixel; a known lens
    distortion's local change of scale, a few percent, is left out)."""
    centres = model.centres()
    normal = functional.normalize(functional.normalize(centres[view] - X, dim=-1) + functional.normalize(centres[partners] - X, dim=-1), dim=-1)
    camera = Camera(model.K[partners], model.R[partners], model.t[partners])
    inverse_K = torch.linalg.inv(model.K[view])

    def to_partner(x: Tensor) -> Tensor:
        ray = (to_homogeneous(x) @ inverse_K.T) @ model.R[view]  # world directions
        along = ((X - centres[view]) * normal).sum(-1) / (ray * normal).sum(-1)
        on_plane = centres[view] + along[:, None] * ray
        return camera.project(on_plane[:, None])[:, 0]

    step = torch.eye(2, dtype=X.dtype) * 0.5
    columns = [to_partner(pixels + step[k]) - to_partner(pixels - step[k]) for k in range(2)]
    return torch.stack(columns, -1)


class LowPassedImages:
    """The views' grey images as float64 (H, W) in [0, 1], each blurred for sampling at ``scale``
    of its pixels per sample (> 1: shrinking it; sigma √(s² − 1) / 2, the blur that brings its
    half-pixel resolution to that of the samples), the scale rounded up to a quarter octave so
    that a few blurs per view serve every pair. The images made are kept for the next views
    while they fit in ``CACHE_BYTES``, the least recently used dropped first: memory bounded
    however long a video (500 KITTI frames kept every view, 4.6 GiB peak), and a view's
    partners — its neighbours in a video — are the recently used ones."""

    STEPS_PER_OCTAVE = 4
    CACHE_BYTES = 256 * 2**20

    def __init__(self, greys: list[Tensor]) -> None:
        self.greys = greys
        self.shorter_sides = torch.tensor([min(grey.shape[-2:]) for grey in greys], dtype=torch.float64)  # (V,) pixels
        self.made: OrderedDict[tuple[int, int], Tensor] = OrderedDict()
        self.kept_bytes = 0

    def at(self, view: int, scale: float) -> Tensor:
        level = max(0, math.ceil(self.STEPS_PER_OCTAVE * math.log2(max(scale, 1.0)) - 1e-9))
        key = (view, level)
        if key in self.made:
            self.made.move_to_end(key)
            return self.made[key]
        image = to_unit_float(self.greys[view])[0].double()
        if level:
            sigma = 0.5 * math.sqrt(2 ** (2 * level / self.STEPS_PER_OCTAVE) - 1)
            size = 2 * math.ceil(3 * sigma) + 1
            image = gaussian_blur2d(image[None, None], (size, size), (sigma, sigma))[0, 0]
        self.made[key] = image
        self.kept_bytes += image.nbytes
        while len(self.made) > 1 and self.kept_bytes > self.CACHE_BYTES:
            self.kept_bytes -= self.made.popitem(last=False)[1].nbytes
        return image


def _ncc_peaks(image: Tensor, centres: Tensor, patches: Tensor, half: int, radius: int, threshold: float
               ) -> tuple[Tensor, Tensor]:
    """Where each of the (M, (2 half + 1)²) normalized ``patches`` correlates best with the
    (H, W) ``image`` within ``radius`` integer px of its (M, 2) ``centres``: the sub-pixel peak
    (M, 2) and (M,) bool where it is interior, at least ``threshold`` and a proper maximum."""
    side, size = 2 * (half + radius) + 1, 2 * half + 1
    window = sample_patches(image[None], centres, half + radius).view(-1, 1, side, side)
    shifted = window[:, 0].unfold(1, size, 1).unfold(2, size, 1)  # (M, offset y, offset x, size, size): views
    shifted = shifted.permute(0, 3, 4, 1, 2).reshape(window.shape[0], size * size, -1)  # (M, patch pixels, offsets row-major)
    products = torch.bmm(patches[:, None], shifted)[:, 0]  # (M, offsets); patches sum to 0
    sums, squares = (functional.avg_pool2d(values, size, stride=1).flatten(1) * size**2 for values in (window, window.square()))
    spread = (squares - sums.square() / size**2).clamp_min(0).sqrt()  # each offset's patch less its mean: its norm
    scores = torch.where(spread > 1e-8, products / spread.clamp_min(1e-12), 0.0).view(-1, 2 * radius + 1, 2 * radius + 1)
    best = scores.flatten(1).argmax(1)
    row, column = best // (2 * radius + 1), best % (2 * radius + 1)
    interior = (row > 0) & (row < 2 * radius) & (column > 0) & (column < 2 * radius)
    rows = torch.arange(scores.shape[0])
    neighbourhood = torch.stack([scores[rows, (row + dy).clamp(0, 2 * radius), (column + dx).clamp(0, 2 * radius)]
                                 for dy in (-1, 0, 1) for dx in (-1, 0, 1)], -1)  # (M, 9) row-major
    sub_pixel, proper = biquadric_offsets(neighbourhood, 3)
    peak = scores.flatten(1).amax(1)
    position = centres + torch.stack([column, row], -1).to(centres.dtype) - radius + sub_pixel.to(centres.dtype)
    return position, interior & proper & (peak >= threshold) & (sub_pixel.abs() <= 1).all(-1)
