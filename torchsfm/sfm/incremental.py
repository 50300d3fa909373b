"""Incremental reconstruction of a calibrated sequence (thesis chapter 4, Fig. 4.1–4.2).

Corners of every view (one batched Harris call) → the view pairs worth matching (coarse matching
of every pair, :mod:`torchsfm.sfm.pairs`) → putative matches guided by the coarse homography,
verified by a robust F → tracks → an initial pair (enough inliers, not explained by a
homography, enough parallax) reconstructed by the two-view geometry → repeatedly: the view that
sees most reconstructed tracks is resected (RANSAC + LM) and its new tracks triangulated (a view
that fails is retried after the next registration) →
sparse bundle adjustment (optionally every k views, always at the end) → outlier observations
removed and the model adjusted once more.
"""

from __future__ import annotations

import dataclasses
import math
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import torch
from torch import Tensor

from torchsfm.camera import (Camera, check_intrinsics, from_homogeneous, project, projection_matrix, to_homogeneous,
                             undistort_points)
from torchsfm.config import Config, RansacConfig
from torchsfm.errors import DegenerateConfigurationError, InputError, NotEnoughDataError, ShapeError, TorchSfmError
from torchsfm.features.harris import detect_corners
from torchsfm.geometry.self_calibration import focal_from_fundamentals, intrinsics
from torchsfm.geometry.triangulation import triangulate_points
from torchsfm.images import read_image, to_grey
from torchsfm.matching.matcher import PutativeMatches, match_corners
from torchsfm.moving.imor import MovingObjectRejection
from torchsfm.moving.whole_track import reject_moving_objects_in_tracks
from torchsfm.optim.bundle import BundleProblem, bundle_adjust
from torchsfm.robust.models import HomographyModel
from torchsfm.robust.ransac import ransac
from torchsfm.estimators.absolute_pose import estimate_absolute_pose
from torchsfm.sfm.pairs import coarse_features, pair_scores, predicted_homography, select_pairs
from torchsfm.reconstruction import Reconstruction
from torchsfm.sfm.tracks import Tracks, build_tracks
from torchsfm.estimators.two_view_geometry import estimate_fundamental, estimate_relative_pose
from torchsfm.validation import check_finite

Progress = Callable[[str], None]
DETECTION_CHUNK = 8  # views per batched Harris call
FOCAL_PRIOR = 1.2  # × the larger image side: the search's centre without K (a common camera's field of view)
FOCAL_REFINEMENT_RANGE = 1.1  # the bundle-adjusted profile searches f / 1.1 .. f × 1.1
PRINCIPAL_POINT_RANGE = 0.02  # ... and the principal point ± 2% of the image's larger side
INTRINSICS_REFINEMENT_STEPS = 10


@dataclass
class _PairMatches:
    index1: Tensor
    index2: Tensor
    homography_ratio: float
    F: Tensor


def _triangulation_angle(X: Tensor, centre1: Tensor, centre2: Tensor) -> Tensor:
    """Angle (degrees) between the rays from two centres (3,) to points X (N, 3): (N,)."""
    a, b = centre1 - X, centre2 - X
    cosine = (a * b).sum(-1) / (a.norm(dim=-1) * b.norm(dim=-1)).clamp_min(1e-300)
    return torch.rad2deg(torch.acos(cosine.clamp(-1, 1)))


class _Model:
    """The growing reconstruction: poses of registered views and a 3-D point per track."""

    def __init__(self, tracks: Tracks, corners: list[Tensor], raw: list[Tensor], K: Tensor, config: Config) -> None:
        self.tracks, self.corners, self.K, self.config = tracks, corners, K, config
        V = len(corners)
        self.R = torch.eye(3, dtype=torch.float64).repeat(V, 1, 1)
        self.t = torch.zeros(V, 3, dtype=torch.float64)
        self.registered = torch.zeros(V, dtype=torch.bool)
        self.points = torch.zeros(tracks.num_tracks, 3, dtype=torch.float64)
        self.has_point = torch.zeros(tracks.num_tracks, dtype=torch.bool)
        self.pixels = tracks.gather(corners)  # (T, 2) undistorted
        self.raw_pixels = tracks.gather(raw)  # as detected (for colours)

    def centre(self, view: int) -> Tensor:
        return -self.R[view].T @ self.t[view]

    def projection(self, view: int) -> Tensor:
        return projection_matrix(self.K[view], self.R[view], self.t[view])

    def observation_errors(self) -> Tensor:
        """Reprojection error of every track observation in a registered view with a point
        (+inf elsewhere): (T,)."""
        view, track = self.tracks.view, self.tracks.track
        usable = self.registered[view] & self.has_point[track]
        errors = torch.full((view.numel(),), float("inf"), dtype=torch.float64)
        if bool(usable.any()):
            camera = Camera(self.K[view[usable]], self.R[view[usable]], self.t[view[usable]])
            camera_points = camera.world_to_camera(self.points[track[usable]][:, None])[:, 0]
            projected = camera.project(self.points[track[usable]][:, None])[:, 0]
            error = (projected - self.pixels[usable]).norm(dim=-1)
            errors[usable] = torch.where(camera_points[:, 2] > 0, error, float("inf"))
        return errors

    def triangulate_new(self, view: int) -> int:
        """Triangulate the tracks seen by ``view`` and another registered view that have no point
        yet, each with the partner view of widest baseline; keep the well-conditioned ones."""
        view_of, track_of = self.tracks.view, self.tracks.track
        in_view = view_of == view
        candidates = torch.zeros(self.tracks.num_tracks, dtype=torch.bool)
        candidates[track_of[in_view]] = True
        candidates &= ~self.has_point
        partner_observation = candidates[track_of] & self.registered[view_of] & (view_of != view)
        if not bool(partner_observation.any()):
            return 0
        distances = torch.stack([(self.centre(v) - self.centre(view)).norm() for v in range(len(self.corners))])
        # for every candidate track: its registered partner observation farthest from the view
        score = torch.where(partner_observation, distances[view_of], -1.0)
        best = torch.full((self.tracks.num_tracks,), -1.0, dtype=torch.float64).scatter_reduce(0, track_of, score, "amax")
        chosen = partner_observation & (score == best[track_of])
        chosen_tracks, first = torch.unique(track_of[chosen], return_inverse=True)
        partner_index = torch.full((chosen_tracks.numel(),), -1, dtype=torch.long).scatter_(0, first, torch.nonzero(chosen).flatten())
        own_index = torch.full((self.tracks.num_tracks,), -1, dtype=torch.long)
        own_index[track_of[in_view]] = torch.nonzero(in_view).flatten()
        own_index = own_index[chosen_tracks]
        added = 0
        partners = view_of[partner_index]
        for partner in torch.unique(partners).tolist():
            mine = partners == partner
            x_view, x_partner = self.pixels[own_index[mine]], self.pixels[partner_index[mine]]
            P_view, P_partner = self.projection(view), self.projection(partner)
            X = triangulate_points(x_partner, x_view, P_partner, P_view, self.config.triangulation)
            good = self._acceptable(X, [(partner, x_partner), (view, x_view)])
            tracks = chosen_tracks[mine][good]
            self.points[tracks], self.has_point[tracks] = X[good], True
            added += int(good.sum())
        return added

    def _acceptable(self, X: Tensor, views: list[tuple[int, Tensor]]) -> Tensor:
        settings = self.config.reconstruction
        good = torch.isfinite(X).all(-1)
        for view, pixels in views:
            camera_points = X @ self.R[view].T + self.t[view]
            error = (project(self.projection(view), X) - pixels).norm(dim=-1)
            good &= (camera_points[:, 2] > 0) & (error < settings.max_reprojection_error)
        angle = _triangulation_angle(X, self.centre(views[0][0]), self.centre(views[1][0]))
        return good & (angle >= settings.min_point_angle)


def _putative_matches(greys: Tensor, raw: list[Tensor], config: Config, generator: torch.Generator,
                      report: Progress) -> dict[tuple[int, int], PutativeMatches]:
    """NCC + strength-measure matches of the view pairs chosen by ``config.pairs``
    (:mod:`torchsfm.sfm.pairs`), at the detected (``raw``) corners, with the search disc centred
    on the coarse homography's prediction where it moves corners by more than a quarter of the
    disc; pairs with fewer than ``min_pair_inliers`` matches are dropped."""
    features = coarse_features(greys, config.pairs)
    pairs = select_pairs(pair_scores(features, config.pairs.ncc_threshold), config.pairs)
    putative = {}
    for i, j in pairs:
        report(f"matching views {i} and {j}")
        predicted = None
        H = predicted_homography(features, i, j, config.pairs, generator) if config.pairs.guided else None
        if H is not None:
            moved = from_homogeneous(to_homogeneous(raw[i].double()) @ H.T)
            if float((moved - raw[i]).norm(dim=-1).median()) > config.matching.search_radius / 4:
                predicted = moved
        matches = match_corners(greys[i], greys[j], raw[i], raw[j], config.matching, predicted)
        if matches.index1.numel() >= config.reconstruction.min_pair_inliers:
            putative[(i, j)] = matches
    return putative


def _verify_pairs(putative: dict[tuple[int, int], PutativeMatches], corners: list[Tensor], config: Config,
                  generator: torch.Generator, report: Progress) -> dict[tuple[int, int], _PairMatches]:
    """Robust F of every pair (the undistorted ``corners``), then the homography test on F's
    inliers; pairs keeping ``min_pair_inliers`` survive. One call per pair: measured faster than
    one ragged batched call today (the engine's rounds run until the slowest problem stops)."""
    report(f"verifying {len(putative)} pairs")
    homography_config = RansacConfig(inlier_threshold=config.reconstruction.homography_threshold)
    result = {}
    for (i, j), matches in putative.items():
        x1, x2 = corners[i][matches.index1], corners[j][matches.index2]
        try:
            fundamental = estimate_fundamental(x1, x2, config=config, generator=generator)
        except TorchSfmError:
            continue
        inliers = fundamental.inlier_mask
        if int(inliers.sum()) < config.reconstruction.min_pair_inliers:
            continue
        data = torch.cat([x1[inliers], x2[inliers]], -1)[None]
        homography = ransac(HomographyModel(data), data, homography_config, generator=generator)
        ratio = float(homography.inlier_mask.sum()) / float(inliers.sum())
        result[(i, j)] = _PairMatches(matches.index1[inliers], matches.index2[inliers], ratio, fundamental.F)
    return result


def _initial_pair(pairs: dict[tuple[int, int], _PairMatches], corners: list[Tensor], K: Tensor, config: Config,
                  generator: torch.Generator) -> tuple[tuple[int, int], Tensor, Tensor, str]:
    """The first pair (by inlier count) that passes the homography and parallax tests."""
    settings = config.reconstruction
    rejected = []
    for (i, j), match in sorted(pairs.items(), key=lambda item: -item[1].index1.numel()):
        if match.homography_ratio > settings.max_homography_ratio:
            rejected.append(f"{i}-{j}: a homography explains {match.homography_ratio:.0%} of its inliers")
            continue
        x1, x2 = corners[i][match.index1], corners[j][match.index2]
        try:
            pose = estimate_relative_pose(x1, x2, K[i], K[j], config=config, generator=generator)
        except TorchSfmError as error:
            rejected.append(f"{i}-{j}: {error}")
            continue
        centre2 = -pose.R.T @ pose.t
        angle = float(_triangulation_angle(pose.points3d, torch.zeros(3, dtype=torch.float64), centre2).median())
        if angle < settings.min_initial_angle:
            rejected.append(f"{i}-{j}: median triangulation angle {angle:.2f} deg")
            continue
        return (i, j), pose.R, pose.t, "; ".join(rejected)
    raise DegenerateConfigurationError("no view pair can start the reconstruction (" + ("; ".join(rejected) or "no pair has enough verified matches") + ")")


def _bundle(model: _Model, config: Config, fixed_view: int, usable: Tensor | None = None) -> float:
    """Adjust the registered cameras and the points with their inlier observations (or the
    ``usable`` (T,) ones), in place, with ``reconstruction.bundle_loss``; returns the final cost
    per observation (px²)."""
    if usable is None:
        usable = model.observation_errors() < config.reconstruction.max_reprojection_error
    views = torch.nonzero(model.registered).flatten()
    tracks = torch.nonzero(model.has_point).flatten()
    camera_of = torch.full((len(model.corners),), -1, dtype=torch.long)
    camera_of[views] = torch.arange(views.numel())
    point_of = torch.full((model.tracks.num_tracks,), -1, dtype=torch.long)
    point_of[tracks] = torch.arange(tracks.numel())
    problem = BundleProblem(
        camera_model="pinhole", rotations=model.R[views], translations=model.t[views], intrinsics=model.K[views],
        points=model.points[tracks], camera_index=camera_of[model.tracks.view[usable]],
        point_index=point_of[model.tracks.track[usable]], observations=model.pixels[usable],
        fixed_cameras=views == fixed_view,
    )
    settings = dataclasses.replace(config.bundle_adjustment, loss=config.reconstruction.bundle_loss)
    result = bundle_adjust(problem, config=settings)
    adjusted = result.problem
    model.R[views], model.t[views], model.points[tracks] = adjusted.rotations, adjusted.translations, adjusted.points
    return result.final_cost / max(int(usable.sum()), 1)


def _detect(greys: Tensor, config: Config) -> list[Tensor]:
    """Corners of every view, detected ``DETECTION_CHUNK`` views per batched call (the Harris
    response's intermediate maps of a whole video would not fit in memory at once)."""
    corners = []
    for first in range(0, greys.shape[0], DETECTION_CHUNK):
        detected = detect_corners(greys[first:first + DETECTION_CHUNK], config.harris)
        corners += [detected.of_image(b) for b in range(detected.valid.shape[0])]
    return corners


def _self_calibrate(pairs: dict[tuple[int, int], _PairMatches], size: tuple[int, int], config: Config) -> Tensor:
    """K (3, 3) with the principal point at the image centre and the focal length that makes the
    verified pairs' essential matrices best (pairs a homography explains are left out when
    others exist: their F does not fix the focal length)."""
    if not pairs:
        raise DegenerateConfigurationError("no view pair could be verified, so the focal length cannot be estimated: give K")
    H, W = size
    centre = torch.tensor([(W - 1) / 2, (H - 1) / 2], dtype=torch.float64)
    general = [m.F for m in pairs.values() if m.homography_ratio <= config.reconstruction.max_homography_ratio]
    F = torch.stack(general or [m.F for m in pairs.values()]).double()
    return intrinsics(focal_from_fundamentals(F, centre, FOCAL_PRIOR * max(H, W)), centre)


def _refine_intrinsics(model: _Model, config: Config, fixed_view: int) -> None:
    """The shared focal length and principal point minimizing the bundle-adjusted reprojection
    cost: golden-section profiles over log f (± ``FOCAL_REFINEMENT_RANGE``), then cx and cy
    (± ``PRINCIPAL_POINT_RANGE`` of the image size), then f again, every evaluation a bundle
    adjustment from the current model over one fixed set of observations; the model ends
    adjusted at the best values."""
    start = (model.R.clone(), model.t.clone(), model.points.clone())
    usable = model.observation_errors() < config.reconstruction.max_reprojection_error  # one set for every K
    size = 2 * float(model.K[0, :2, 2].max()) + 1

    def cost(K: Tensor) -> float:
        model.R, model.t, model.points = (tensor.clone() for tensor in start)
        model.K = K.expand_as(model.K).clone()
        return _bundle(model, config, fixed_view, usable)

    def with_value(K: Tensor, which: str, value: float) -> Tensor:
        K = K.clone()
        if which == "f":
            K[0, 0] = K[1, 1] = math.exp(value)
        else:
            K[0 if which == "cx" else 1, 2] = value
        return K

    K = model.K[0].clone()
    for which in ("f", "cx", "cy", "f"):
        if which == "f":
            centre, half = math.log(float(K[0, 0])), math.log(FOCAL_REFINEMENT_RANGE)
        else:
            centre, half = float(K[0 if which == "cx" else 1, 2]), PRINCIPAL_POINT_RANGE * size
        low, high = centre - half, centre + half
        ratio = (math.sqrt(5) - 1) / 2
        a, b = high - ratio * (high - low), low + ratio * (high - low)
        cost_a, cost_b = cost(with_value(K, which, a)), cost(with_value(K, which, b))
        for _ in range(INTRINSICS_REFINEMENT_STEPS):
            if cost_a < cost_b:
                high, b, cost_b = b, a, cost_a
                a = high - ratio * (high - low)
                cost_a = cost(with_value(K, which, a))
            else:
                low, a, cost_a = a, b, cost_b
                b = low + ratio * (high - low)
                cost_b = cost(with_value(K, which, b))
        K = with_value(K, which, (low + high) / 2)
    cost(K)


def reconstruct(images: list[Tensor | str | Path], K: Tensor | None = None, *, distortion: Tensor | None = None,
                names: list[str] | None = None, config: Config | None = None,
                generator: torch.Generator | None = None, progress: Progress | None = None) -> Reconstruction:
    """Reconstruct a calibrated image sequence.

    Images given as paths are read here; one that cannot be read is listed in ``unregistered``
    with the reason and the others are reconstructed without it.

    Args:
        images: V >= 2 image paths or tensors (3, H, W) / (1, H, W), uint8 or float in [0, 1],
            all the same size.
        K: intrinsics (3, 3) shared by all views, or (V, 3, 3); None: unknown — the principal
            point is taken at the image centre, the focal length (shared by all views) is
            estimated from the verified pairs' fundamental matrices (Mendonça & Cipolla, searched
            around 1.2 × the larger image side) and refined by bundle adjustment; the estimate is
            the model's ``cameras.K``. All images must then have one size.
        distortion: radial (k1, k2) of the camera, (2,) or (V, 2); corners are undistorted
            before any geometry (the model's keypoints are then ideal pixels).
        names: view names (default: the file names, or ``view0``, ``view1``, ...).
        config: every stage's settings; generator: the random source of all RANSACs.
        progress: called with a message at each step.

    Returns:
        A :class:`~torchsfm.reconstruction.Reconstruction` of the registered views
        (``view_indices`` maps them to the input list; ``unregistered`` gives the others with the
        reason). Scale: the initial pair's baseline is 1.
    """
    if len(images) < 2:
        raise NotEnoughDataError(f"a reconstruction needs at least 2 images, got {len(images)}")
    names = names or [Path(image).name if isinstance(image, (str, Path)) else f"view{v}" for v, image in enumerate(images)]
    estimate_focal = K is None
    if estimate_focal:
        if distortion is not None:
            raise InputError("distortion needs K: give both, or neither")
        K = torch.eye(3, dtype=torch.float64)  # replaced once the image size is known
    K = K.double()
    K = K.expand(len(images), 3, 3) if K.dim() == 2 else K
    if K.shape != (len(images), 3, 3):
        raise InputError(f"K must be (3, 3) or ({len(images)}, 3, 3), got {tuple(K.shape)}")
    check_intrinsics(K=K)
    if distortion is not None:
        distortion = distortion.double()
        if distortion.shape not in ((2,), (len(images), 2)):
            raise ShapeError(f"distortion must be (2,) or ({len(images)}, 2), got {tuple(distortion.shape)}")
    distortion = K.new_zeros(len(images), 2) if distortion is None else distortion.double().expand(len(images), 2)
    check_finite(distortion=distortion)
    loaded, kept, unreadable = [], [], {}
    for v, image in enumerate(images):
        if isinstance(image, (str, Path)):
            try:
                image = read_image(image)
            except InputError as error:
                unreadable[v] = str(error)
                continue
        loaded.append(image)
        kept.append(v)
    if len(loaded) < 2:
        raise NotEnoughDataError(f"only {len(loaded)} of {len(images)} images could be read: " + "; ".join(unreadable.values()))
    model = _reconstruct_views(loaded, K[kept], distortion[kept], names=[names[v] for v in kept], config=config,
                               generator=generator, progress=progress, estimate_focal=estimate_focal)
    model.view_indices = [kept[v] for v in model.view_indices]
    model.unregistered = {**{kept[v]: reason for v, reason in model.unregistered.items()}, **unreadable}
    model.moving_objects = {tuple(kept[v] for v in triplet): result for triplet, result in model.moving_objects.items()}
    model.moving_rejections_per_view = {kept[v]: count for v, count in model.moving_rejections_per_view.items()}
    return model


def _reconstruct_views(images: list[Tensor], K: Tensor, distortion: Tensor, *, names: list[str], config: Config | None = None,
                       generator: torch.Generator | None = None, progress: Progress | None = None,
                       estimate_focal: bool = False) -> Reconstruction:
    """:func:`reconstruct` on decoded images, with K (V, 3, 3), distortion (V, 2) and names given
    (with ``estimate_focal``, K is replaced by the self-calibrated one)."""
    config = config or Config()
    generator = generator or torch.Generator().manual_seed(0)
    report = progress or (lambda message: None)
    V = len(images)
    sizes = {tuple(image.shape[-2:]) for image in images}
    if len(sizes) != 1 or any(image.dim() != 3 or image.shape[0] not in (1, 3) for image in images):
        raise InputError(f"all images must be (3 or 1, H, W) of one size, got {sorted({tuple(i.shape) for i in images})}")
    timings: dict[str, float] = {}

    def timed(name: str, function):
        start = time.perf_counter()
        result = function()
        timings[name] = timings.get(name, 0.0) + time.perf_counter() - start
        return result

    greys = torch.stack([to_grey(image) for image in images])
    report(f"corners of {V} views")
    raw = timed("corners", lambda: _detect(greys, config))
    corners = [undistort_points(raw[v].double(), K[v], distortion[v]) for v in range(V)]
    putative = timed("matching", lambda: _putative_matches(greys, raw, config, generator, report))
    pairs = timed("verification", lambda: _verify_pairs(putative, corners, config, generator, report))
    if estimate_focal:
        K = timed("self-calibration", lambda: _self_calibrate(pairs, images[0].shape[-2:], config)).expand(V, 3, 3)
        report(f"focal length estimated from {len(pairs)} verified pairs: {float(K[0, 0, 0]):.1f} px")
    tracks = build_tracks([c.shape[0] for c in corners], {key: (m.index1, m.index2) for key, m in pairs.items()})
    report(f"{tracks.num_tracks} tracks from {len(pairs)} verified pairs")
    rejections, rejected_per_view = {}, []
    if config.moving_objects.enabled:
        tracks, rejections, rejected_per_view = timed("moving objects", lambda: _reject_moving_tracks(tracks, corners, config, generator))
        report(f"{tracks.num_tracks} tracks kept as static by IMOR + RANSAC")
    (first, second), R, t, _ = timed("initial pair", lambda: _initial_pair(pairs, corners, K, config, generator))
    model = _Model(tracks, corners, raw, K, config)
    model.R[second], model.t[second] = R.double(), t.double()
    model.registered[[first, second]] = True
    model.triangulate_new(second)
    report(f"initial pair {first}-{second}: {int(model.has_point.sum())} points")
    unregistered: dict[int, str] = {}  # views that failed since the last registration: retried after the next one
    since_bundle = 0
    while True:
        waiting = [v for v in range(V) if not model.registered[v] and v not in unregistered]
        if not waiting:
            break
        seen = torch.zeros(V, dtype=torch.long).index_add_(0, tracks.view, model.has_point[tracks.track].long())
        view = max(waiting, key=lambda v: int(seen[v]))
        if int(seen[view]) < config.reconstruction.min_resection_inliers:
            for v in waiting:
                unregistered[v] = f"sees only {int(seen[v])} reconstructed points (needs {config.reconstruction.min_resection_inliers})"
            break
        report(f"registering view {view} ({names[view]}) from {int(seen[view])} points")
        mine = (tracks.view == view) & model.has_point[tracks.track]
        try:
            pose = timed("resection", lambda: estimate_absolute_pose(model.points[tracks.track[mine]], model.pixels[mine], K[view],
                                                                     config=config, generator=generator))
        except TorchSfmError as error:
            unregistered[view] = f"resection failed: {error}"
            continue
        if int(pose.inlier_mask.sum()) < config.reconstruction.min_resection_inliers:
            unregistered[view] = f"resection kept {int(pose.inlier_mask.sum())} inliers (needs {config.reconstruction.min_resection_inliers})"
            continue
        model.R[view], model.t[view] = pose.R, pose.t
        model.registered[view] = True
        unregistered.clear()  # more points now: every view that failed gets another try
        timed("triangulation", lambda: model.triangulate_new(view))
        since_bundle += 1
        if config.reconstruction.bundle_every and since_bundle >= config.reconstruction.bundle_every:
            timed("bundle adjustment", lambda: _bundle(model, config, first))
            since_bundle = 0
    report(f"bundle adjustment of {int(model.registered.sum())} views and {int(model.has_point.sum())} points")
    timed("bundle adjustment", lambda: _bundle(model, config, first))
    for _ in range(config.reconstruction.retriangulations):  # the adjusted cameras triangulate tracks the early ones could not
        for view in torch.nonzero(model.registered).flatten().tolist():
            timed("triangulation", lambda: model.triangulate_new(view))
        timed("bundle adjustment", lambda: _bundle(model, config, first))
    # drop outlier observations and weak points, then adjust once more
    errors = model.observation_errors()
    inlier_count = torch.zeros(tracks.num_tracks, dtype=torch.long).index_add_(0, tracks.track, (errors < config.reconstruction.max_reprojection_error).long())
    model.has_point &= inlier_count >= config.reconstruction.min_track_views
    timed("bundle adjustment", lambda: _bundle(model, config, first))
    if estimate_focal:
        timed("intrinsics refinement", lambda: _refine_intrinsics(model, config, first))
        report(f"focal length refined by bundle adjustment: {float(model.K[0, 0, 0]):.1f} px")
    result = _result(model, images, names, unregistered, timings)
    result.moving_objects = rejections
    result.moving_rejections_per_view = dict(enumerate(rejected_per_view))
    return result


def _reject_moving_tracks(tracks: Tracks, corners: list[Tensor], config: Config, generator: torch.Generator
                          ) -> tuple[Tracks, dict[tuple[int, int, int], MovingObjectRejection], list[int]]:
    """Keep the tracks :func:`~torchsfm.moving.whole_track.reject_moving_objects_in_tracks` keeps
    (``moving_objects.track_method``; the triplet votes use every consecutive view triplet; tracks
    it cannot test are dropped too). Returns the kept tracks (renumbered), each tested triplet's
    result, and per view the number of its observations rejected."""
    V, T = len(corners), tracks.num_tracks
    pixels = torch.zeros(V, T, 2, dtype=torch.float64)
    visible = torch.zeros(V, T, dtype=torch.bool)
    pixels[tracks.view, tracks.track] = tracks.gather(corners)
    visible[tracks.view, tracks.track] = True
    triplets = [(first, first + 1, first + 2) for first in range(V - 2)]
    decision = reject_moving_objects_in_tracks(pixels, visible, triplets=triplets, config=config, generator=generator)
    results = dict(zip(decision.triplets, decision.results))
    rejected_per_view = (visible & ~decision.background_mask[None]).sum(1).tolist()
    return tracks.subset(decision.background_mask), results, rejected_per_view


def _result(model: _Model, images: list[Tensor], names: list[str], unregistered: dict[int, str],
            timings: dict[str, float]) -> Reconstruction:
    errors = model.observation_errors()
    tracks = model.tracks
    keep = errors < model.config.reconstruction.max_reprojection_error
    views = torch.nonzero(model.registered).flatten()
    camera_of = torch.full((len(images),), -1, dtype=torch.long)
    camera_of[views] = torch.arange(views.numel())
    count = torch.zeros(tracks.num_tracks, dtype=torch.long).index_add_(0, tracks.track, keep.long())
    point_tracks = torch.nonzero(model.has_point & (count >= model.config.reconstruction.min_track_views)).flatten()
    point_of = torch.full((tracks.num_tracks,), -1, dtype=torch.long)
    point_of[point_tracks] = torch.arange(point_tracks.numel())
    keep &= point_of[tracks.track] >= 0
    first_observation = torch.full((tracks.num_tracks,), tracks.view.numel(), dtype=torch.long).scatter_reduce(
        0, tracks.track[keep], torch.nonzero(keep).flatten(), "amin")[point_tracks]
    stacked = torch.stack([image.expand(3, -1, -1) for image in images])  # (V, 3, H, W)
    pixel = model.raw_pixels[first_observation].round().long()
    colours = stacked[tracks.view[first_observation], :, pixel[:, 1], pixel[:, 0]]  # (P, 3), one gather
    if colours.dtype != torch.uint8:
        colours = (colours.float() * 255).round().clamp(0, 255).to(torch.uint8)
    H, W = images[0].shape[-2:]
    return Reconstruction(
        cameras=Camera(model.K[views], model.R[views], model.t[views]),
        image_names=[names[v] for v in views.tolist()],
        image_sizes=torch.tensor([[W, H]] * views.numel()),
        points3d=model.points[point_tracks],
        colors=colours,
        observation_points=point_of[tracks.track[keep]],
        observation_views=camera_of[tracks.view[keep]],
        keypoints=model.pixels[keep],
        view_indices=views.tolist(),
        unregistered=unregistered,
        timings=timings,
    )

