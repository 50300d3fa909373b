"""The incremental mapper (thesis chapter 4): the growing model, the initial pair, resection and
triangulation of each next view, bundle adjustment, intrinsics refinement and the result."""

from __future__ import annotations

import dataclasses
import math
import time

import torch
from torch import Tensor

from torchsfm.camera import Camera, pixels_to_normalized, projection_matrix, rescale_pixels, to_homogeneous, undistort_points
from torchsfm.config import BundleAdjustmentConfig, Config
from torchsfm.errors import DegenerateConfigurationError, TorchSfmError
from torchsfm.geometry.essential import POSE_CANDIDATES, essential_from_fundamental, select_pose
from torchsfm.geometry.fundamental import fundamental_from_pose, sampson_error
from torchsfm.geometry.rotation import angle_between
from torchsfm.geometry.triangulation import triangulate_points
from torchsfm.optim.bundle import BundleProblem, bundle_adjust, intrinsics_covariance
from torchsfm.reconstruction import Reconstruction
from torchsfm.robust.ragged import pad_rows
from torchsfm.robust.samplers import side_generator
from torchsfm.estimators.two_view_geometry import estimate_relative_pose
from torchsfm.estimators.absolute_pose import AbsolutePose, estimate_absolute_pose
from torchsfm.estimators.planar_pose import PlanarPose, choose_by_normal, planar_poses
from torchsfm.sfm.projection_search import join_observations, model_pixels, observations_by_projection, points_seen_by_projection
from torchsfm.sfm.tracks import Tracks
from torchsfm.sfm.view_pairs import PairMatches, verify_pairs
from torchsfm.numerics import floor_tiny

FOCAL_PRECISION = 0.25  # a refined focal length is trusted where the data pin it within this share of it (one sd)
PRINCIPAL_POINT_PRECISION = 0.01  # the principal point leaves the image centre where the data pin it within this share of the larger side
INTRINSICS_ROUNDS = 6  # adjustments of K (each followed by triangulation) while the focal length still moves
FOCAL_SETTLED = 1e-3  # ... by more than this share
INTRINSIC_ENTRIES = {"f": (0, 0), "fx": (0, 0), "fy": (1, 1), "cx": (0, 2), "cy": (1, 2)}  # where each sits in K
PAIR_POSE_MIN_POINTS = 3  # a length along one ray needs one point; three that agree, and a majority, make it robust
PAIR_POSE_SCALE_TOLERANCE = 0.1  # a point fixes a translation's length if 10 % more or less moves it by the resection threshold
PARALLAX_BATCH = 64  # pairs per batched parallax screen of the initial-pair candidates
WIDER_PAIR_CANDIDATES = 12  # pairs linked only through tracks that may start a model when no matched pair can
RESECTION_SHARE = 0.75  # the views that see this share of the best view's points are resected together (OpenMVG's rule)
STILL = 0.5  # px: matched corners that move less than this (median) show a camera that did not move (sub-pixel corner noise)


def triangulation_angle(X: Tensor, centre1: Tensor, centre2: Tensor) -> Tensor:
    """Angle (degrees) between the rays from two centres (3,) to points X (N, 3): (N,)."""
    a, b = centre1 - X, centre2 - X
    cosine = (a * b).sum(-1) / floor_tiny((a.norm(dim=-1) * b.norm(dim=-1)))
    return torch.rad2deg(torch.acos(cosine.clamp(-1, 1)))


class MapperState:
    """The growing reconstruction: poses of registered views and a 3-D point per track."""

    def __init__(self, tracks: Tracks, corners: list[Tensor], raw: list[Tensor], K: Tensor, config: Config) -> None:
        self.tracks, self.corners, self.K, self.config = tracks, corners, K, config
        V = len(corners)
        self.R = torch.eye(3, dtype=torch.float64).repeat(V, 1, 1)
        self.t = torch.zeros(V, 3, dtype=torch.float64)
        self.registered = torch.zeros(V, dtype=torch.bool)
        self.loose_resections: dict[int, float] = {}  # view -> the widened threshold its resection needed (px)
        self.tracked_resections: dict[int, int] = {}  # view -> inliers of its resection from the points tracking against the map found
        self.still_frames: dict[int, int] = {}  # view -> the keyframe it did not move from (posed, not adjusted)
        self.points = torch.zeros(tracks.num_tracks, 3, dtype=torch.float64)
        self.has_point = torch.zeros(tracks.num_tracks, dtype=torch.bool)
        self.pixels = tracks.gather(corners)  # (T, 2) undistorted
        self.raw_pixels = tracks.gather(raw)  # as detected (for colours)
        self.observed = self.pixels  # the pixels before an estimated radial distortion is undone (K unknown)
        self.radial = 0.0  # that distortion's k1: undone in ``pixels``

    @property
    def one_principal_point(self) -> bool:
        """Whether every view has the same principal point (not so where some are turned to portrait)."""
        return bool((self.K[:, :2, 2] == self.K[0, :2, 2]).all())

    def observing(self, view: int) -> Tensor:
        """The view's observations (ascending indices into ``tracks``) of tracks with a point."""
        own = self.tracks.of_view(view)
        return own[self.has_point[self.tracks.track[own]]]

    def centres(self) -> Tensor:
        """(V, 3) camera centres (meaningful for registered views)."""
        return -(self.R.transpose(1, 2) @ self.t[..., None])[..., 0]

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
        yet, each with the partner view of widest baseline; keep the well-conditioned ones. Only
        the view's observations and those of its tracks are read (a long video calls this once
        per view)."""
        tracks = self.tracks
        own = tracks.of_view(view)
        own = own[~self.has_point[tracks.track[own]]]  # (M,) the view's observations of tracks without a point
        members, owner = tracks.observations_of(tracks.track[own])  # those tracks' observations, (K,)
        view_of = tracks.view[members]
        partner_observation = self.registered[view_of] & (view_of != view)
        if not bool(partner_observation.any()):
            return 0
        centres = self.centres()
        distances = (centres - centres[view]).norm(dim=-1)
        # for every candidate track: its registered partner observation farthest from the view
        score = torch.where(partner_observation, distances[view_of], -1.0)
        best = torch.full((own.numel(),), -1.0, dtype=torch.float64).scatter_reduce(0, owner, score, "amax")
        chosen = partner_observation & (score == best[owner])
        chosen_owners, first = torch.unique(owner[chosen], return_inverse=True)
        partner_index = torch.full((chosen_owners.numel(),), -1, dtype=torch.long).scatter_(0, first, members[chosen])
        own_index = own[chosen_owners]
        chosen_tracks = tracks.track[own_index]
        partners = tracks.view[partner_index]  # (M',): each track's partner view, all triangulated as one batch
        x_view, x_partner = self.pixels[own_index], self.pixels[partner_index]
        P = projection_matrix(self.K, self.R, self.t)  # (V, 3, 4)
        X = triangulate_points(x_partner[:, None], x_view[:, None], P[partners], P[view].expand_as(P[partners]),
                               self.config.triangulation)[:, 0]
        good = self._acceptable(X, partners, x_partner, view, x_view)
        self.points[chosen_tracks[good]], self.has_point[chosen_tracks[good]] = X[good], True
        return int(good.sum())

    def _acceptable(self, X: Tensor, partners: Tensor, x_partner: Tensor, view: int, x_view: Tensor) -> Tensor:
        """(M,) bool: points X (M, 3) in front of their partner views (M,) and of ``view``, within
        ``max_reprojection_error`` of their pixels (M, 2) in both, at ``min_point_angle`` degrees."""
        settings = self.config.reconstruction
        good = torch.isfinite(X).all(-1)
        for views, pixels in ((partners, x_partner), (torch.full_like(partners, view), x_view)):
            camera = Camera(self.K[views], self.R[views], self.t[views])  # one camera per point
            depth = camera.world_to_camera(X[:, None])[:, 0, 2]
            error = (camera.project(X[:, None])[:, 0] - pixels).norm(dim=-1)
            good &= (depth > 0) & (error < settings.max_reprojection_error)
        centres = self.centres()
        return good & (triangulation_angle(X, centres[partners], centres[view]) >= settings.min_point_angle)


def initial_pair(pairs: dict[tuple[int, int], PairMatches], corners: list[Tensor], K: Tensor, config: Config,
                  generator: torch.Generator) -> tuple[tuple[int, int], Tensor, Tensor, str]:
    """The first pair (by inlier count) that passes the homography and parallax tests. The
    parallax of every pair is first screened from its verified F (:func:`parallax_angles`, batched),
    so that the full relative pose is estimated only for pairs that can pass (a video's
    neighbouring frames mostly cannot)."""
    settings = config.reconstruction
    rejected = []
    ordered = sorted(pairs.items(), key=lambda item: -item[1].index1.numel())
    candidates = {key: match for key, match in ordered if match.homography_ratio <= settings.max_homography_ratio}
    screened = dict(zip(candidates, parallax_angles(list(candidates.values()), list(candidates), corners, K).tolist()))
    for (i, j), match in ordered:
        if match.homography_ratio > settings.max_homography_ratio:
            motion = float((corners[j][match.index2] - corners[i][match.index1]).norm(dim=-1).median())
            rejected.append(f"{i}-{j}: a homography explains {match.homography_ratio:.0%} of its inliers "
                            f"(median image motion {motion:.1f} px{': the camera did not move' if motion < STILL else ''})")
            continue
        if screened[(i, j)] < settings.min_initial_angle:
            rejected.append(f"{i}-{j}: median triangulation angle {screened[(i, j)]:.2f} deg (from its verified F)")
            continue
        x1, x2 = corners[i][match.index1], corners[j][match.index2]
        try:
            pose = estimate_relative_pose(x1, x2, K[i], K[j], config=config, generator=generator)
        except TorchSfmError as error:
            rejected.append(f"{i}-{j}: {error}")
            continue
        centre2 = -pose.R.T @ pose.t
        angle = float(triangulation_angle(pose.points3d, torch.zeros(3, dtype=torch.float64), centre2).median())
        if angle < settings.min_initial_angle:
            rejected.append(f"{i}-{j}: median triangulation angle {angle:.2f} deg")
            continue
        return (i, j), pose.R, pose.t, "; ".join(rejected)
    raise DegenerateConfigurationError("no view pair can start the reconstruction (" + ("; ".join(rejected) or "no pair has enough verified matches") + ")")


def planar_initial_pair(pairs: dict[tuple[int, int], PairMatches], corners: list[Tensor], K: Tensor, config: Config,
                        generator: torch.Generator) -> tuple[tuple[int, int], Tensor, Tensor, str]:
    """The first pair of a planar scene, where :func:`initial_pair` refused every pair because a
    homography explains it: by inlier count, the first homography-explained pair whose motion
    from the homography (:func:`~torchsfm.estimators.planar_pose.planar_poses`; of twin motions
    the one whose plane agrees with the first view's other planar pairs,
    :func:`~torchsfm.estimators.planar_pose.choose_by_normal`) triangulates its inliers with a
    median angle of ``min_initial_angle``. Same return as :func:`initial_pair`."""
    settings = config.reconstruction
    planar = {key: match for key, match in pairs.items() if match.homography_ratio > settings.max_homography_ratio}
    rejected = []

    decomposed: dict[tuple[int, int], list[PlanarPose] | TorchSfmError] = {}  # each ordered pair decomposed once

    def motions(view: int, other: int, match: PairMatches) -> list[PlanarPose]:
        if (view, other) not in decomposed:
            index_view, index_other = (match.index1, match.index2) if view < other else (match.index2, match.index1)
            try:
                decomposed[(view, other)] = planar_poses(corners[view][index_view], corners[other][index_other], K[view], K[other],
                                                         config=config, generator=generator)
            except TorchSfmError as error:
                decomposed[(view, other)] = error
        found = decomposed[(view, other)]
        if isinstance(found, TorchSfmError):
            raise found
        return found

    def median_angle(pose: PlanarPose) -> float:
        return float(triangulation_angle(pose.points3d, torch.zeros(3, dtype=torch.float64), -pose.R.T @ pose.t).median())

    def normals_seen_from(view: int, pair: tuple[int, int]) -> list[Tensor]:
        """The plane normals (in ``view``'s frame) of ``view``'s planar pairs other than ``pair``."""
        normals = []
        for (a, b), match in planar.items():
            if view in (a, b) and (a, b) != pair:
                try:
                    normals.append(torch.stack([pose.normal for pose in motions(view, a + b - view, match)]))
                except TorchSfmError:
                    continue
        return normals

    for (i, j), match in sorted(planar.items(), key=lambda item: -item[1].index1.numel()):
        try:
            poses = motions(i, j, match)
        except TorchSfmError as error:
            rejected.append(f"{i}-{j}: {error}")
            continue
        can_pass = max(median_angle(pose) for pose in poses) >= settings.min_initial_angle  # else no twin test: a camera only turning
        pose = choose_by_normal(poses, normals_seen_from(i, (i, j))) if len(poses) > 1 and can_pass else poses[0]
        angle = median_angle(pose)
        if angle < settings.min_initial_angle:
            rejected.append(f"{i}-{j}: median triangulation angle {angle:.2f} deg (from its homography)")
            continue
        return (i, j), pose.R, pose.t, "; ".join(rejected)
    raise DegenerateConfigurationError("no planar pair can start the reconstruction from its homography ("
                                       + ("; ".join(rejected) or "no pair is explained by a homography") + ")")


def parallax_angles(matches: list[PairMatches], keys: list[tuple[int, int]], corners: list[Tensor], K: Tensor) -> Tensor:
    """(M,) median angle (degrees) between the two rays of each pair's verified matches, from its
    verified F: E = K_jᵀ F K_i, the rotation of the decomposition with most points in front, and
    the angle between x̃_i and Rᵀ x̃_j (the triangulation angle, whatever the translation's scale).
    Batched, ``PARALLAX_BATCH`` pairs per call."""
    angles = []
    for first in range(0, len(matches), PARALLAX_BATCH):
        chunk = list(zip(keys[first:first + PARALLAX_BATCH], matches[first:first + PARALLAX_BATCH]))
        x1, valid = pad_rows([pixels_to_normalized(corners[i][m.index1].double(), K[i]) for (i, _), m in chunk])
        x2, _ = pad_rows([pixels_to_normalized(corners[j][m.index2].double(), K[j]) for (_, j), m in chunk])
        K1, K2 = K[[i for (i, _), _ in chunk]].double(), K[[j for (_, j), _ in chunk]].double()
        E = essential_from_fundamental(torch.stack([m.F.double() for _, m in chunk]), K1, K2)
        R, _, _ = select_pose(*POSE_CANDIDATES["svd"](E), x1, x2, valid.double())
        angle = angle_between(to_homogeneous(x1), to_homogeneous(x2) @ R)  # x̃_i and Rᵀ x̃_j (as rows)
        angles.append(torch.where(valid, angle, torch.nan).nanmedian(-1).values)
    return torch.cat(angles) if angles else torch.zeros(0, dtype=torch.float64)


def pairs_through_tracks(state, config: Config, allowed: Tensor, exclude: dict) -> dict[tuple[int, int], PairMatches]:
    """Verified matches of view pairs that were not matched directly but share at least
    ``min_pair_inliers`` tracks (chained through the views between them): the
    ``WIDER_PAIR_CANDIDATES`` of widest RMS disparity, verified like matched pairs. Under
    forward motion or a slow camera, neighbouring frames have too little parallax to start a model;
    frames further apart along the same tracks have more."""
    tracks, V = state.tracks, len(state.corners)
    counts = tracks.covisibility(V)
    disparity = rms_disparity(tracks, tracks.gather(state.raw), V, counts)
    usable = (counts >= config.reconstruction.min_pair_inliers) & allowed[:, None] & allowed[None, :]
    usable = usable.triu(1)
    for i, j in exclude:
        usable[i, j] = False
    candidates = torch.nonzero(usable)
    widest = candidates[torch.argsort(disparity[usable], descending=True)[:WIDER_PAIR_CANDIDATES]].tolist()
    return verify_pairs({(i, j): tracks.shared(i, j) for i, j in widest}, state.corners, config, state.generator, state.report)


def rms_disparity(tracks: Tracks, pixels: Tensor, num_views: int, counts: Tensor) -> Tensor:
    """(V, V) RMS displacement (px) between two views of the tracks seen in both (``pixels`` (T,
    2) their observations, ``counts`` (V, V) how many), for every pair at once from sums over
    shared tracks: Σ |x_i - x_j|² = Σ |x_i|² + Σ |x_j|² - 2 Σ x_i · x_j."""
    ones, square = torch.ones(pixels.shape[0], dtype=torch.float64), (pixels.double() ** 2).sum(-1)
    square_sum = tracks.pair_sums(num_views, square, ones)
    cross = sum(tracks.pair_sums(num_views, pixels[:, k], pixels[:, k]) for k in range(2))
    return ((square_sum + square_sum.T - 2 * cross).clamp_min(0) / counts.clamp_min(1)).sqrt()


def bundle_problem(model: MapperState, views: Tensor, tracks: Tensor, usable: Tensor, fixed: Tensor,
                   intrinsics: tuple[str, ...] = ()) -> BundleProblem:
    """The bundle problem of the model's ``views`` (C,) and ``tracks`` (P,) with their ``usable``
    (T,) observations; ``fixed`` (V,) views hold still, the named shared ``intrinsics`` move
    (with ``k1``: the observations as detected, the distortion in the cameras; where the views'
    principal points differ — some turned to portrait — the observations are taken about them,
    so that one K is shared)."""
    radial = "k1" in intrinsics
    K, observations = model.K[views], (model.observed if radial else model.pixels)[usable]
    if intrinsics and not model.one_principal_point:
        observations = observations - model.K[model.tracks.view[usable], :2, 2]
        K = K.clone()
        K[:, :2, 2] = 0
    camera_of = torch.full((len(model.corners),), -1, dtype=torch.long)
    camera_of[views] = torch.arange(views.numel())
    point_of = torch.full((model.tracks.num_tracks,), -1, dtype=torch.long)
    point_of[tracks] = torch.arange(tracks.numel())
    return BundleProblem(
        camera_model="pinhole", rotations=model.R[views], translations=model.t[views], intrinsics=K,
        points=model.points[tracks], camera_index=camera_of[model.tracks.view[usable]],
        point_index=point_of[model.tracks.track[usable]], observations=observations,
        fixed_cameras=fixed[views], shared_intrinsics=intrinsics, radial=model.radial if radial else 0.0,
    )


def bundle_settings(config: Config) -> BundleAdjustmentConfig:
    """The mapper's bundle adjustment: ``bundle_adjustment`` with ``reconstruction.bundle_loss``."""
    return dataclasses.replace(config.bundle_adjustment, loss=config.reconstruction.bundle_loss)


def bundle(model: MapperState, config: Config, fixed_view: int, usable: Tensor | None = None,
           free_views: Tensor | None = None, intrinsics: tuple[str, ...] = ()) -> float:
    """Adjust the registered cameras and the points with their inlier observations (or the
    ``usable`` (T,) ones), in place, with ``reconstruction.bundle_loss``; returns the final cost
    per observation (px²). ``free_views`` (V,) bool: a local adjustment — only the points those
    views see, and only those cameras move (the others that see the points hold them fixed).
    ``intrinsics``: these parameters of the K shared by every view are adjusted too (names of
    :data:`~torchsfm.optim.bundle.INTRINSIC_PARAMETERS`)."""
    if usable is None:
        usable = model.observation_errors() < config.reconstruction.max_reprojection_error
    selected, fixed = model.has_point, torch.arange(len(model.corners)) == fixed_view
    if free_views is not None:
        selected = torch.zeros_like(model.has_point)
        selected[model.tracks.track[usable & free_views[model.tracks.view]]] = True
        usable = usable & selected[model.tracks.track]
        fixed = fixed | ~free_views
    seen = torch.zeros_like(model.registered)
    seen[model.tracks.view[usable]] = True
    views = torch.nonzero(seen if free_views is not None else model.registered).flatten()
    tracks = torch.nonzero(selected).flatten()
    problem = bundle_problem(model, views, tracks, usable, fixed, intrinsics)
    result = bundle_adjust(problem, config=bundle_settings(config))
    adjusted = result.problem
    model.R[views], model.t[views], model.points[tracks] = adjusted.rotations, adjusted.translations, adjusted.points
    if intrinsics and model.one_principal_point:
        model.K = adjusted.intrinsics[:1].expand_as(model.K).clone()
    elif intrinsics:  # the shared focal length, each view's principal point as it was
        model.K = model.K.clone()
        model.K[:, :2, :2] = adjusted.intrinsics[0, :2, :2]
    if "k1" in intrinsics:  # undone in the pixels every other step uses
        model.radial = adjusted.radial
        lens = model.K.new_tensor([model.radial, 0.0])
        model.pixels = (undistort_points(model.observed, model.K[0], lens) if model.one_principal_point else
                        undistort_points(model.observed[:, None], model.K[model.tracks.view], lens)[:, 0])
    return result.final_cost / max(int(usable.sum()), 1)


def resect(X: Tensor, x: Tensor, K: Tensor, config: Config, generator: torch.Generator,
           first: AbsolutePose | None = None) -> tuple[AbsolutePose, float] | str:
    """The pose of a new view from its tracks' points X (N, 3) and pixels x (N, 2) and the
    threshold (px) it needed, or why there is none.

    The points were triangulated from other views, and their depth error grows into the new
    view's image with how far it moves along its line of sight: in forward motion, under the true
    pose, many of them reproject several pixels off. A resection that keeps fewer than
    ``min_resection_inliers`` is therefore tried again at double the threshold, up to
    ``max_resection_threshold`` px (chance agreement stays negligible: 20 wrong pairs within 8 px
    of one pose do not happen), and the bundle adjustments restore the precision. ``first``: the
    resection at the RANSAC threshold when it is already done (:func:`resect_views`)."""
    settings, needed = config.resection, config.reconstruction.min_resection_inliers
    threshold = settings.ransac.inlier_threshold
    while True:
        if first is not None:
            pose, first = first, None
        else:
            try:
                pose = estimate_absolute_pose(X, x, K, config=at_resection_threshold(config, threshold, needed), generator=generator)
            except TorchSfmError as error:
                return f"resection failed: {error}"
        kept = int(pose.inlier_mask.sum())
        if kept >= needed:
            return pose, threshold
        if 2 * threshold > config.reconstruction.max_resection_threshold:
            return f"resection kept {kept} inliers within {threshold:g} px (needs {needed})"
        threshold *= 2


def at_resection_threshold(config: Config, threshold: float, needed: int = 0) -> Config:
    """``config`` with the resection's RANSAC threshold set to ``threshold`` px and its
    ``min_inliers`` to ``needed`` (a pose with fewer inliers is refused: no more samples are drawn
    than finding one with that many takes)."""
    ransac = dataclasses.replace(config.resection.ransac, inlier_threshold=threshold, min_inliers=needed)
    return dataclasses.replace(config, resection=dataclasses.replace(config.resection, ransac=ransac))


def resect_views(model: MapperState, views: list[int], config: Config, generator: torch.Generator
                 ) -> list[tuple[AbsolutePose, float] | str]:
    """:func:`resect` of several views from the model's points as it stands: the first rung of
    every view in one ragged call; a view that keeps too few inliers there climbs the rest of
    its threshold ladder on its own."""
    tracks = model.tracks
    rows = [model.observing(view) for view in views]
    if len(views) == 1:
        return [resect(model.points[tracks.track[rows[0]]], model.pixels[rows[0]], model.K[views[0]], config, generator)]
    data, valid = pad_rows([torch.cat([model.points[tracks.track[mine]], model.pixels[mine]], -1) for mine in rows])
    first_rung = at_resection_threshold(config, config.resection.ransac.inlier_threshold, config.reconstruction.min_resection_inliers)
    poses = estimate_absolute_pose(data[..., :3], data[..., 3:], model.K[views], valid=valid, config=first_rung, generator=generator)
    return [resect(model.points[tracks.track[mine]], model.pixels[mine], model.K[view], config, generator,
                   first=AbsolutePose(R=poses.R[b], t=poses.t[b], inlier_mask=poses.inlier_mask[b, : mine.numel()],
                                      num_trials=poses.num_trials[b], success=poses.success[b]))
            for b, (view, mine) in enumerate(zip(views, rows))]


def pose_by_tracking(model: MapperState, view: int, greys: list[Tensor], distortion: Tensor, linked: Tensor, config: Config,
                     generator: torch.Generator | None, mask: Tensor | None = None, prediction: AbsolutePose | None = None) -> AbsolutePose | str:
    """The pose of ``view`` tracked against the map, or why not: each of the model's points is
    searched within ``max_resection_threshold`` of where a predicted pose puts it, by the patch of
    its nearest observation (:func:`~torchsfm.sfm.projection_search.points_seen_by_projection`),
    and the view is resected again, at the RANSAC threshold, from what is found. The pose stands
    with ``min_resection_inliers`` inliers, whose observations then join the model (each
    replacing the view's own tie to that point); otherwise the view's pose is left as it was.

    The prediction: the ``prediction`` given (a resection that needed a widened threshold: its
    points, up to that far off, are a weaker support than the points found within the RANSAC
    threshold), else the view's resection from its own ties at the widest threshold. Its matches
    may tie many of its corners to the wrong points (a repeated texture: a scaffolded façade seen
    12 m further on), so that too few agree on a pose for it to register, but the pose those few
    fix predicts where the points lie. ``greys``, ``distortion``, ``linked`` and the view's
    ``mask`` as for :func:`~torchsfm.sfm.projection_search.observations_by_projection`; the draws
    come from a generator seeded as ``generator`` (a search that fails leaves the caller's stream
    as it was)."""
    settings, needed = config.resection, config.reconstruction.min_resection_inliers
    widest = config.reconstruction.max_resection_threshold
    generator = side_generator(generator)
    predicted = prediction
    if predicted is None:
        rows = model.observing(view)
        try:
            predicted = estimate_absolute_pose(model.points[model.tracks.track[rows]], model.pixels[rows], model.K[view],
                                               config=at_resection_threshold(config, widest), generator=generator)
        except TorchSfmError as error:
            return f"no pose to track it from: {error}"
    before = model.R[view].clone(), model.t[view].clone()
    model.R[view], model.t[view] = predicted.R, predicted.t
    tracks, raw = points_seen_by_projection(model, greys, distortion, linked, config, view, math.ceil(widest), mask)
    views = torch.full_like(tracks, view)
    kept = 0
    if tracks.numel() >= needed:  # enough to be worth a resection (its errors, e.g. collinear points, leave kept at 0)
        try:
            pose = estimate_absolute_pose(model.points[tracks], model_pixels(model, distortion, views, raw)[1], model.K[view],
                                          config=at_resection_threshold(config, settings.ransac.inlier_threshold, needed),
                                          generator=generator)
            kept = int(pose.inlier_mask.sum())
        except TorchSfmError:
            pass
    if kept < needed:
        model.R[view], model.t[view] = before
        return (f"tracked against the map from the pose of {int(predicted.inlier_mask.sum())} inliers: "
                f"{tracks.numel()} of the model's points found, {kept} within {settings.ransac.inlier_threshold:g} px of one pose (needs {needed})")
    join_observations(model, distortion, views[pose.inlier_mask], tracks[pose.inlier_mask], raw[pose.inlier_mask])
    return pose


def strongest_registered_pair(model: MapperState, pairs: dict[tuple[int, int], PairMatches], view: int
                              ) -> tuple[tuple[int, int], PairMatches] | None:
    """``view``'s verified pair with most matches among those whose other view is registered,
    or None."""
    partners = [(key, match) for key, match in pairs.items() if view in key and bool(model.registered[sum(key) - view])]
    return max(partners, key=lambda item: item[1].index1.numel()) if partners else None


def pose_from_pair(model: MapperState, pairs: dict[tuple[int, int], PairMatches], view: int, config: Config,
                   generator: torch.Generator) -> tuple[Tensor, Tensor, str] | str:
    """The pose of ``view`` — one that sees too few reconstructed points to be resected — from
    its verified pair with most matches among the registered views: the pair's relative pose
    (:func:`estimate_relative_pose` on its matches: the rotation and the direction of travel from
    hundreds of matches, where a wide baseline left few tracks that reach the model), its
    translation's length from the reconstructed points ``view`` sees (each fixes one along its
    ray; their median). Only points that the length moves count as evidence: those a change of
    ``PAIR_POSE_SCALE_TOLERANCE`` of it would shift by the resection threshold or more (in
    forward motion the points near the epipole hardly move, whatever the length). The pose
    stands if most of those points, and at least ``PAIR_POSE_MIN_POINTS``, reproject within the
    resection threshold. Returns (R (3, 3),
    t (3,), what was done) or why not."""
    strongest = strongest_registered_pair(model, pairs, view)
    if strongest is None:
        return "no verified pair with a registered view"
    (i, j), match = strongest
    other = i + j - view
    try:
        pose = estimate_relative_pose(model.corners[i][match.index1], model.corners[j][match.index2], model.K[i], model.K[j],
                                      config=config, generator=generator)  # camera j = R camera i + t
    except TorchSfmError as error:
        return f"its pair with view {other}: {error}"
    R, t = (pose.R, pose.t) if i == other else (pose.R.T, -pose.R.T @ pose.t)  # camera view = R camera other + t
    tracks = model.tracks
    rows = model.observing(view)
    X = model.points[tracks.track[rows]]
    ray = to_homogeneous(pixels_to_normalized(model.pixels[rows], model.K[view]))  # (n, 3)
    fixed = (X @ model.R[other].T + model.t[other]) @ R.T  # camera view = fixed + s t
    across_fixed, across_t = torch.linalg.cross(ray, fixed), torch.linalg.cross(ray, t.expand_as(ray))
    scales = -(across_fixed * across_t).sum(-1) / floor_tiny(across_t.square().sum(-1))
    if scales.numel() == 0:
        return f"it sees no reconstructed point to scale its pair with view {other}"
    scale = scales.median()
    R_view, t_view = R @ model.R[other], R @ model.t[other] + scale * t
    camera = Camera(model.K[view], R_view, t_view)
    depth = camera.world_to_camera(X[None])[0, :, 2]
    error = (camera.project(X[None])[0] - model.pixels[rows]).norm(dim=-1)
    threshold = config.resection.ransac.inlier_threshold
    seen = fixed + scale * t  # (n, 3) the points in the view's camera frame
    focal = model.K[view].diagonal()[:2].mean()
    shift = focal * (t[:2] * seen[:, 2:] - seen[:, :2] * t[2]).norm(dim=-1) / seen[:, 2].square()  # px per unit of length
    informative = (depth > 0) & (PAIR_POSE_SCALE_TOLERANCE * scale.abs() * shift >= threshold)
    agree = int((informative & (error < threshold)).sum())
    if agree < PAIR_POSE_MIN_POINTS or 2 * agree <= int(informative.sum()):
        return (f"its pair with view {other} agrees with only {agree} of the {int(informative.sum())} reconstructed points "
                f"that fix the length of its translation (of {scales.numel()} it sees)")
    return R_view, t_view, (f"view {view} posed from its verified pair with view {other} ({match.index1.numel()} matches), "
                            f"scaled by the {agree} of its {scales.numel()} reconstructed points that agree and fix it")


def pair_disagreement(model: MapperState, pairs: dict[tuple[int, int], PairMatches], view: int, R: Tensor, t: Tensor,
                      threshold: float) -> str | None:
    """Why the pose R (3, 3), t (3,) of ``view`` from a resection at a widened ``threshold`` (px)
    is refused, or None: the epipolar geometry of that pose and of its registered partner with
    most verified matches must fit most of those matches within the same threshold. A widened
    threshold also admits a wrong pose that collects the points whose depth errors put them
    pixels off; the pair's matches, hundreds, verified on their own, do not move with the points."""
    strongest = strongest_registered_pair(model, pairs, view)
    if strongest is None:
        return None
    (i, j), match = strongest
    other = i + j - view
    (R_i, t_i), (R_j, t_j) = [(R, t) if v == view else (model.R[v], model.t[v]) for v in (i, j)]
    relative = R_j @ R_i.T
    F = fundamental_from_pose(model.K[i], model.K[j], relative, t_j - relative @ t_i)
    fit = int((sampson_error(F, model.corners[i][match.index1], model.corners[j][match.index2]) < threshold**2).sum())
    if 2 * fit > match.index1.numel():
        return None
    return (f"its resection at {threshold:g} px disagrees with its verified pair with view {other}: "
            f"{fit} of the pair's {match.index1.numel()} matches fit the two poses")


def refine_intrinsics(model: MapperState, config: Config, fixed_view: int) -> str:
    """The K shared by every view adjusted with the cameras and points, in place: each
    alternative set of ``reconstruction.refined_intrinsics`` (``|`` between them) refined from
    the same start (:func:`refine_alternative`), and the one the observations choose kept — the
    smallest geometric AIC (Kanatani 1998), J + 2 p σ²: J the robust cost of the observations of
    the points the model had and every alternative kept, p the intrinsics the alternative
    refined, σ² the smallest J over the residual degrees of freedom (2 per observation less 3 per
    point and 6 per view, plus the 7 of the gauge). The default weighs a free principal point
    (f, cx, cy) against one radial coefficient with the principal point at the image centre
    (f, k1: COLMAP's SIMPLE_RADIAL): a lens's distortion otherwise pulls the principal point to
    absorb it, an undistorted camera's off-centre principal point otherwise bends k1. Two views get
    the first alternative only: their one epipolar geometry lets a distortion coefficient bend
    with the focal length (Fountain-P11 views 0 and 5: k1 0.21 ± 0.05 kept, 7.4° rotation error
    against 0.15° without it). Returns what was done, for the progress report."""
    alternatives = [tuple(name for name in names.split(",") if name) for names in config.reconstruction.refined_intrinsics.split("|")]
    if len(alternatives) == 1 or int(model.registered.sum()) < 3:
        return refine_alternative(model, config, fixed_view, alternatives[0])[0]
    start, points = snapshot(model), model.has_point.clone()
    outcomes = []
    for names in alternatives:
        load(model, start)
        message, refined = refine_alternative(model, config, fixed_view, names)
        outcomes.append((message, refined, snapshot(model)))
        points &= model.has_point
    usable = points[model.tracks.track] & model.registered[model.tracks.view]
    costs = []
    for _, _, state in outcomes:
        load(model, state)
        costs.append(robust_cost(model, points, usable, config))
    freedom = max(2 * int(usable.sum()) - 3 * int(points.sum()) - 6 * int(model.registered.sum()) + 7, 1)
    variance = min(costs) / freedom
    scores = [cost + 2 * len(refined) * variance for cost, (_, refined, _) in zip(costs, outcomes)]
    best = min(range(len(outcomes)), key=scores.__getitem__)
    message, refined, state = outcomes[best]
    load(model, state)
    others = "; ".join(f"{', '.join(outcomes[k][1]) or 'none kept'} {costs[k]:.1f}" for k in range(len(outcomes)) if k != best)
    return (f"{message} — chosen by the geometric AIC: robust cost {costs[best]:.1f} px² with {len(refined)} "
            f"intrinsic{'s' if len(refined) != 1 else ''} (σ = {math.sqrt(variance):.2f} px) against {others}")


def snapshot(model: MapperState) -> tuple:
    """Copies of what refining the intrinsics changes: K, R, t, points, has_point, and the pixels
    and radial k1 (never changed in place)."""
    return (model.K.clone(), model.R.clone(), model.t.clone(), model.points.clone(), model.has_point.clone(), model.pixels, model.radial)


def load(model: MapperState, state: tuple) -> None:
    """Put a :func:`snapshot` back (copied: the snapshot can be loaded again)."""
    model.K, model.R, model.t, model.points, model.has_point = (value.clone() for value in state[:5])
    model.pixels, model.radial = state[5:]


def robust_cost(model: MapperState, points: Tensor, usable: Tensor, config: Config) -> float:
    """Σ ρ(‖r‖²) of the ``usable`` (T,) observations of ``points`` (tracks,) in the registered
    views, with the mapper's robust loss (px²), as detected (through the model's k1, if any)."""
    fixed = torch.zeros(len(model.corners), dtype=torch.bool)
    problem = bundle_problem(model, torch.nonzero(model.registered).flatten(), torch.nonzero(points).flatten(), usable, fixed,
                             ("k1",) if model.radial else ())
    settings = bundle_settings(config)
    return problem.robust_cost(settings.loss, settings.loss_scale)


def refine_alternative(model: MapperState, config: Config, fixed_view: int, names: tuple[str, ...]) -> tuple[str, tuple[str, ...]]:
    """The K shared by every view — ``names`` of fx, fy, cx, cy and the radial k1 — adjusted
    jointly with the cameras and points
    (:class:`~torchsfm.optim.bundle.BundleProblem` ``shared_intrinsics``; an estimated k1 is
    undone in the model's pixels after each adjustment, :func:`bundle`), in place, and kept only
    where the data determine it.

    The adjustment repeats, each round followed by triangulation of the tracks the new K reaches,
    while the focal length moves (``INTRINSICS_ROUNDS`` at most; one adjustment from a prior twice
    the true focal length gets only part of the way). Then each intrinsic's standard deviation,
    cameras and points marginalized (:func:`~torchsfm.optim.bundle.intrinsics_covariance`),
    decides: a principal point pinned no closer than ``PRINCIPAL_POINT_PRECISION`` of the larger
    image side (forward motion, few views) goes back to the image centre and the focal length
    alone is adjusted; a focal length pinned no closer than ``FOCAL_PRECISION`` of itself (a
    critical motion leaves it free, e.g. two views whose optical axes meet) is not trusted: the
    model is restored and adjusted with K as it was. Returns what was done, for the progress
    report, and the names refined (none where not trusted)."""
    start = snapshot(model)
    size = 2 * float(model.K[0, :2, 2].max()) + 1
    turned_note = ""
    if not model.one_principal_point and {"cx", "cy"} & set(names):  # a turned view's principal point turns with it
        names = tuple(name for name in names if name not in ("cx", "cy"))
        turned_note = ", principal points at each image's centre (views turned to portrait)"
    rounds, deviation = adjust_intrinsics(model, config, fixed_view, names)
    free_centre, centre_note = tuple(name for name in names if name not in ("cx", "cy")), ""
    if deviation is not None and len(free_centre) < len(names):
        centre_deviation = max(float(deviation[names.index(name)]) for name in ("cx", "cy") if name in names)
        if centre_deviation > PRINCIPAL_POINT_PRECISION * size:  # from the start again: the points fit the centre there
            load(model, start)
            rounds, deviation = adjust_intrinsics(model, config, fixed_view, free_centre)
            names = free_centre
            centre_note = f", principal point at the image centre (the data pin it to ±{centre_deviation:.0f} px only)"
    K = model.K[0]
    value = {name: model.radial if name == "k1" else float(K[INTRINSIC_ENTRIES[name]]) for name in names}
    spread = {name: float("inf") if deviation is None else float(deviation[k]) for k, name in enumerate(names)}
    focal_spread = max((spread[name] / value[name] for name in names if name in ("f", "fx", "fy")), default=0.0)
    if deviation is None or focal_spread > FOCAL_PRECISION:
        load(model, start)
        bundle(model, config, fixed_view)
        return (f"intrinsics refinement not trusted (the data pin the focal length to ±{100 * focal_spread:.0f} % only): "
                f"focal length kept at {float(start[0][0, 0, 0]):.1f} px"), ()
    described = ", ".join(f"{name} {value[name]:.4f} ± {spread[name]:.4f}" if name == "k1" else
                          f"{name} {value[name]:.1f} ± {spread[name]:.1f} px" for name in names)
    return f"intrinsics refined by bundle adjustment ({rounds} round{'s' if rounds > 1 else ''}): {described}{centre_note}{turned_note}", names


def adjust_intrinsics(model: MapperState, config: Config, fixed_view: int, names: tuple[str, ...]) -> tuple[int, Tensor | None]:
    """Bundle adjustments of the cameras, points and the shared intrinsics ``names``, each followed
    by triangulation, until the focal length settles (``FOCAL_SETTLED``, ``INTRINSICS_ROUNDS``
    at most), in place; the rounds run and the intrinsics' standard deviations (in ``names``'
    order; None where the data leave one free)."""
    rounds = 0
    for rounds in range(1, INTRINSICS_ROUNDS + 1):
        before = float(model.K[0, 0, 0])
        bundle(model, config, fixed_view, intrinsics=names)
        for view in torch.nonzero(model.registered).flatten().tolist():
            model.triangulate_new(view)
        if abs(float(model.K[0, 0, 0]) / before - 1) < FOCAL_SETTLED:
            break
    usable = model.observation_errors() < config.reconstruction.max_reprojection_error
    seen_twice = torch.zeros(model.tracks.num_tracks, dtype=torch.long).index_add_(0, model.tracks.track, usable.long()) >= 2
    points = model.has_point & seen_twice  # a point seen once carries no information (and no block to invert)
    usable &= points[model.tracks.track]
    fixed = torch.arange(len(model.corners)) == fixed_view
    problem = bundle_problem(model, torch.nonzero(model.registered).flatten(), torch.nonzero(points).flatten(), usable, fixed, names)
    covariance = intrinsics_covariance(problem, config=bundle_settings(config))
    return rounds, None if covariance is None else covariance.diagonal().clamp_min(0).sqrt()


def map_incrementally(state, config: Config) -> Reconstruction:
    """The incremental mapper on a :class:`~torchsfm.sfm.stages.ViewSet` with verified ``pairs``,
    ``corners``, ``raw`` corners and ``tracks``: one model grown by :func:`grow_model`; when views
    are left that the model cannot reach (the set splits), another model is started from the
    verified pairs among them, and so on. The model with most views is returned; the others are
    its ``other_models``, largest first, and its ``unregistered`` names, for every view it lacks,
    the separate model it belongs to or why it belongs to none. With ``reconstruction.keyframes``,
    the frames whose camera did not move (:func:`still_frames`) take no part in growing a model:
    each is resected from the finished model of its keyframe (:func:`pose_still_frames`)."""
    V = len(state.corners)
    still = still_frames(state.tracks, state.corners, config) if config.reconstruction.keyframes else {}
    if still:
        state.report(f"{len(still)} frames did not move from the keyframe before them: posed against the model, not adjusted")
    keyframes = torch.ones(V, dtype=torch.bool)
    keyframes[list(still)] = False
    grown: list[tuple[MapperState, dict[int, str]]] = []
    remaining = torch.ones(V, dtype=torch.bool)
    while int((remaining & keyframes).sum()) >= 2:
        try:
            model, unregistered = grow_model(state, config, remaining & keyframes)
        except DegenerateConfigurationError:
            if not grown:
                raise
            break  # the views left cannot start a model of their own: they keep their reasons
        start = time.perf_counter()
        unregistered.update(pose_still_frames(model, still, config, state.generator))
        state.timings["resection"] = state.timings.get("resection", 0.0) + time.perf_counter() - start
        grown.append((model, unregistered))
        remaining &= ~model.registered
    grown.sort(key=lambda item: -int(item[0].registered.sum()))
    reasons = {frame: f"the camera did not move from view {key}, which no model holds" for frame, key in still.items()}
    for _, unregistered in reversed(grown):  # the largest model's reasons last: they stand
        reasons.update(unregistered)
    colours = [colour if colour is not None else image for colour, image in zip(state.colours or [None] * V, state.images)]
    sizes = [tuple(image.shape[-2:]) for image in state.images] if state.images else None
    built = [build_reconstruction(model, colours or None, sizes, state.names, {}, {}) for model, _ in grown]
    primary = built[0]
    for k, other in enumerate(built[1:], start=1):
        for view in other.view_indices:
            reasons[view] = f"in separate model {k} ({other.num_views} views): no verified link to this model strong enough to register it"
    primary.unregistered = {view: reasons[view] for view in range(V) if view not in primary.view_indices}
    primary.other_models = built[1:]
    return primary


def still_frames(tracks: Tracks, corners: list[Tensor], config: Config) -> dict[int, int]:
    """The frames, in file order, whose camera did not move from the last keyframe before them
    (a car waiting at a light), as {frame: keyframe}: they share ``min_resection_inliers`` tracks
    or more with it, whose corners (K_v, 2) moved less than ``STILL`` px (median) — sub-pixel
    corner noise, no baseline to triangulate from. Each frame is measured against the keyframe,
    not its predecessor, so that a slow drift starts a new keyframe once it adds up. Empty when
    fewer than two keyframes would be left (the initial-pair test then names the still camera).
    One pass over each view's observations: the keyframe's pixel of every track in a table."""
    def pixels(view: int) -> tuple[Tensor, Tensor]:
        mine = tracks.of_view(view)
        return tracks.track[mine], corners[view][tracks.corner[mine]].double()

    still, key = {}, 0
    at_key = torch.full((tracks.num_tracks, 2), torch.nan, dtype=torch.float64)  # the keyframe's pixel per track
    seen, where = pixels(0)
    at_key[seen] = where
    for view in range(1, len(corners)):
        seen, where = pixels(view)
        motion = (where - at_key[seen]).norm(dim=-1)
        motion = motion[~motion.isnan()]  # the tracks shared with the keyframe
        if motion.numel() >= config.reconstruction.min_resection_inliers and float(motion.median()) < STILL:
            still[view] = key
            continue
        at_key[pixels(key)[0]] = torch.nan
        key = view
        at_key[seen] = where
    return still if len(corners) - len(still) >= 2 else {}


def pose_still_frames(model: MapperState, still: dict[int, int], config: Config, generator: torch.Generator) -> dict[int, str]:
    """Register the ``still`` frames ({frame: keyframe}) whose keyframe the model holds, each
    resected from the model's final points (:func:`resect_views`) and left out of the
    adjustments (its observations would only repeat its keyframe's); returns, for each of them
    that could not be posed, why."""
    frames = [frame for frame, key in sorted(still.items()) if model.registered[key]]
    reasons = {}
    for frame, outcome in zip(frames, resect_views(model, frames, config, generator) if frames else []):
        if isinstance(outcome, str):
            reasons[frame] = f"the camera did not move from view {still[frame]}; {outcome}"
            continue
        pose, threshold = outcome
        model.R[frame], model.t[frame] = pose.R, pose.t
        model.registered[frame] = True
        model.still_frames[frame] = still[frame]
        if threshold > config.resection.ransac.inlier_threshold:
            model.loose_resections[frame] = threshold
    return reasons


def starting_pair(state, pairs: dict[tuple[int, int], PairMatches], config: Config, allowed: Tensor, timed
                  ) -> tuple[tuple[int, int], Tensor, Tensor]:
    """The initial pair (and camera j's pose R, t relative to camera i) of a model over the
    ``allowed`` views, from the first of these that gives one: :func:`initial_pair` on the
    matched ``pairs``; on the wider pairs linked through tracks (forward motion: the matched
    pairs are too close together); on both at half ``min_initial_angle`` (COLMAP's fallback: the
    angles scale with 1 / f, and a focal length the pairs cannot determine, e.g. driving
    straight, may be the prior's twice over); :func:`planar_initial_pair` on both (a plane — a
    wall, a flat moving object: every pair refused for its homography). ``timed(name, function)``
    runs a step and adds its time to the mapper's timings.

    Raises:
        DegenerateConfigurationError: none of them gives a pair; the message has each one's reason.
    """

    def attempt(choose) -> tuple[tuple | None, DegenerateConfigurationError | None]:
        try:
            return timed("initial pair", choose)[:3], None
        except DegenerateConfigurationError as error:
            return None, error

    start, error = attempt(lambda: initial_pair(pairs, state.corners, state.K, config, state.generator))
    if start:
        return start
    wider = timed("initial pair", lambda: pairs_through_tracks(state, config, allowed, exclude=pairs))
    state.report(f"no matched pair can start the model; trying {len(wider)} wider pairs linked through tracks")
    start, wider_error = attempt(lambda: initial_pair(wider, state.corners, state.K, config, state.generator))
    if start:
        return start
    halved = config.reconstruction.min_initial_angle / 2
    relaxed = dataclasses.replace(config, reconstruction=dataclasses.replace(config.reconstruction, min_initial_angle=halved))
    start, _ = attempt(lambda: initial_pair({**pairs, **wider}, state.corners, state.K, relaxed, state.generator))
    if start:
        state.report(f"no pair reaches {config.reconstruction.min_initial_angle:g} deg of triangulation angle: "
                     f"started from {start[0][0]}-{start[0][1]} at half of it")
        return start
    start, planar_error = attempt(lambda: planar_initial_pair({**pairs, **wider}, state.corners, state.K, config, state.generator))
    if start:
        state.report(f"every pair is explained by a homography: started from {start[0][0]}-{start[0][1]}, posed from its homography")
        return start
    raise DegenerateConfigurationError(f"{error}; nor can the wider pairs linked through tracks ({wider_error}); "
                                       f"nor any at half the angle, {halved:g} deg; {planar_error}")


def grow_model(state, config: Config, allowed: Tensor) -> tuple[MapperState, dict[int, str]]:
    """One model over the ``allowed`` (V,) views: the initial pair among them, then repeatedly the
    views that see most reconstructed tracks — every view that sees ``RESECTION_SHARE`` of the
    best one's count, resected together (:func:`resect_views`) and registered most first (a view
    whose resection keeps too few inliers at the RANSAC threshold is tracked against the map,
    :func:`pose_by_tracking`; a view that fails is retried after the next registration; when no view sees enough points, one with
    a verified pair into the model is posed from it, :func:`pose_from_pair`) — then bundle adjustment,
    retriangulation, outlier removal and, when K was estimated, its refinement; last the
    observations its views miss, found by projection among verified partners
    (:func:`~torchsfm.sfm.projection_search.observations_by_projection`), and one more
    adjustment. Returns the model and, for every allowed view left out, the reason."""
    tracks, V = state.tracks, len(state.corners)
    timings = state.timings

    def timed(name: str, function):
        start = time.perf_counter()
        value = function()
        timings[name] = timings.get(name, 0.0) + time.perf_counter() - start
        return value

    pairs = {(i, j): match for (i, j), match in state.pairs.items() if allowed[i] and allowed[j]}
    linked = torch.zeros(V, V, dtype=torch.bool)  # the verified pairs: a view is searched for its partners' points
    ends = torch.tensor(list(pairs), dtype=torch.long).reshape(-1, 2).T
    linked[ends[0], ends[1]] = linked[ends[1], ends[0]] = True
    def track(view: int, prediction: AbsolutePose | None = None) -> AbsolutePose | str | None:
        """:func:`pose_by_tracking`, noted and reported; None where ``reconstruction.track_against_map``
        is off or there are no images (tracks given without them)."""
        if not (config.reconstruction.track_against_map and state.greys):
            return None
        mask = state.masks[view] if state.masks is not None else None
        tracked = timed("tracking against the map", lambda: pose_by_tracking(model, view, state.greys, state.distortion, linked, config,
                                                                             state.generator, mask, prediction))
        if not isinstance(tracked, str):
            model.tracked_resections[view] = int(tracked.inlier_mask.sum())
            state.report(f"view {view} tracked against the map: {model.tracked_resections[view]} inliers among the points found")
        return tracked

    (first, second), R, t = starting_pair(state, pairs, config, allowed, timed)
    model = MapperState(tracks, state.corners, state.raw, state.K, config)
    model.R[second], model.t[second] = R.double(), t.double()
    model.registered[[first, second]] = True
    model.triangulate_new(second)
    state.report(f"initial pair {first}-{second}: {int(model.has_point.sum())} points")
    unregistered: dict[int, str] = {}  # views that failed since the last registration: retried after the next one
    since_bundle, order, window = 0, [first, second], config.reconstruction.local_bundle_window
    while True:
        waiting = allowed & ~model.registered
        waiting[list(unregistered)] = False
        if not bool(waiting.any()):
            break
        seen = torch.zeros(V, dtype=torch.long).index_add_(0, model.tracks.view, model.has_point[model.tracks.track].long())
        most = int(torch.where(waiting, seen, -1).max())
        if most < config.reconstruction.min_resection_inliers:  # too few points to resect: a verified pair may pose one
            stuck = torch.nonzero(waiting).flatten()
            posed = None
            for v in stuck[torch.argsort(seen[stuck], descending=True, stable=True)].tolist():
                outcome = timed("pose from a pair", lambda: pose_from_pair(model, pairs, v, config, state.generator))
                if not isinstance(outcome, str):
                    posed = v
                    break
                unregistered[v] = f"sees only {int(seen[v])} reconstructed points (needs {config.reconstruction.min_resection_inliers}); {outcome}"
            if posed is None:
                break
            model.R[posed], model.t[posed], done = outcome
            model.registered[posed] = True
            order.append(posed)
            state.report(done)
            timed("triangulation", lambda: model.triangulate_new(posed))
            timed("bundle adjustment", lambda: bundle(model, config, first))
            unregistered.clear()
            continue
        # the views that see nearly as many points as the best one, most first: resected together
        share = max(config.reconstruction.min_resection_inliers, math.ceil(RESECTION_SHARE * most))
        candidates = torch.nonzero(waiting & (seen >= share)).flatten()
        candidates = candidates[torch.argsort(seen[candidates], descending=True, stable=True)].tolist()
        state.report(f"registering view{'s' if len(candidates) > 1 else ''} "
                     + ", ".join(f"{view} ({state.names[view]})" for view in candidates) + f" from {most} points or more")
        found = timed("resection", lambda: resect_views(model, candidates, config, state.generator))
        registered = 0
        for view, outcome in zip(candidates, found):
            tracked = track(view) if isinstance(outcome, str) else None  # too few inliers at any threshold
            if isinstance(tracked, AbsolutePose):
                outcome = tracked, config.resection.ransac.inlier_threshold
            elif tracked is not None:
                outcome = f"{outcome}; {tracked}"
            if isinstance(outcome, str):
                unregistered[view] = outcome
                continue
            pose, threshold = outcome
            if threshold > config.resection.ransac.inlier_threshold:
                refused = pair_disagreement(model, pairs, view, pose.R, pose.t, threshold)
                if refused is not None:
                    unregistered[view] = refused
                    continue
                tracked = track(view, pose)  # resected from points found within the RANSAC threshold where it can be
                if isinstance(tracked, AbsolutePose):
                    pose, threshold = tracked, config.resection.ransac.inlier_threshold
                else:
                    model.loose_resections[view] = threshold
            model.R[view], model.t[view] = pose.R, pose.t
            model.registered[view] = True
            order.append(view)
            registered += 1
            timed("triangulation", lambda: model.triangulate_new(view))
            since_bundle += 1
            if config.reconstruction.bundle_every and since_bundle >= config.reconstruction.bundle_every:
                timed("bundle adjustment", lambda: bundle(model, config, first))
                since_bundle = 0
            elif window and len(order) > window:  # the model outgrew the window: adjust the newest views only
                free = torch.zeros_like(model.registered)
                free[order[-window:]] = True
                timed("local bundle adjustment", lambda: bundle(model, config, first, free_views=free))
        if registered:
            unregistered.clear()  # more points now: every view that failed gets another try
    state.report(f"bundle adjustment of {int(model.registered.sum())} views and {int(model.has_point.sum())} points")
    timed("bundle adjustment", lambda: bundle(model, config, first))
    for _ in range(config.reconstruction.retriangulations):  # the adjusted cameras triangulate tracks the early ones could not
        for view in torch.nonzero(model.registered).flatten().tolist():
            timed("triangulation", lambda: model.triangulate_new(view))
        timed("bundle adjustment", lambda: bundle(model, config, first))
    # an observation gated out against earlier, rougher cameras stays out of every later adjustment,
    # which fits its point without it: one adjustment with those within twice the gate (a point fitted
    # to them moves toward them; the robust loss bounds the pull of the ones that do not fit) lets
    # those that fit back in before the gate is applied again
    readmitted = model.observation_errors() < 2 * config.reconstruction.max_reprojection_error
    timed("bundle adjustment", lambda: bundle(model, config, first, usable=readmitted))
    # drop outlier observations and weak points, then adjust once more
    errors = model.observation_errors()
    inlier_count = torch.zeros(tracks.num_tracks, dtype=torch.long).index_add_(0, model.tracks.track, (errors < config.reconstruction.max_reprojection_error).long())
    model.has_point &= inlier_count >= config.reconstruction.min_track_views
    timed("bundle adjustment", lambda: bundle(model, config, first))
    if state.estimate_focal:
        state.report(timed("intrinsics refinement", lambda: refine_intrinsics(model, config, first)))
    if config.reconstruction.observations_by_projection and state.greys:  # with the final cameras and intrinsics
        added = timed("observations by projection",
                      lambda: observations_by_projection(model, state.greys, state.distortion, linked, config, state.masks))
        state.report(f"{added} observations of the model's points found by projection")
        if added:
            timed("bundle adjustment", lambda: bundle(model, config, first))
    return model, unregistered


def build_reconstruction(model: MapperState, colours: list[Tensor] | None, sizes: list[tuple[int, int]] | None, names: list[str],
                         unregistered: dict[int, str], timings: dict[str, float]) -> Reconstruction:
    """The model's registered views and its points seen in ``min_track_views`` inlier views of
    images of ``sizes`` (H, W) per view, coloured from each view's image in ``colours`` (any
    resolution: sampled at the rescaled pixel; None: tracks without images, every point grey,
    every size that of the pixels' extent)."""
    errors = model.observation_errors()
    tracks = model.tracks
    keep = errors < model.config.reconstruction.max_reprojection_error
    views = torch.nonzero(model.registered).flatten()
    camera_of = torch.full((len(names),), -1, dtype=torch.long)
    camera_of[views] = torch.arange(views.numel())
    count = torch.zeros(tracks.num_tracks, dtype=torch.long).index_add_(0, tracks.track, keep.long())
    point_tracks = torch.nonzero(model.has_point & (count >= model.config.reconstruction.min_track_views)).flatten()
    point_of = torch.full((tracks.num_tracks,), -1, dtype=torch.long)
    point_of[point_tracks] = torch.arange(point_tracks.numel())
    keep &= point_of[tracks.track] >= 0
    first_observation = torch.full((tracks.num_tracks,), tracks.view.numel(), dtype=torch.long).scatter_reduce(
        0, tracks.track[keep], torch.nonzero(keep).flatten(), "amin")[point_tracks]
    sizes = sizes or [(int(model.pixels[:, 1].max()) + 1, int(model.pixels[:, 0].max()) + 1)] * len(names)
    colour_view = tracks.view[first_observation]
    point_colours = torch.full((point_tracks.numel(), 3), 128, dtype=torch.uint8)
    for view in torch.unique(colour_view).tolist() if colours else []:  # one gather per view: no stack of every image
        mine = colour_view == view
        source = colours[view]
        pixel = rescale_pixels(model.raw_pixels[first_observation[mine]], source.shape[-1] / sizes[view][1]).round().long()
        pixel = torch.minimum(pixel.clamp_min(0), torch.tensor([source.shape[-1] - 1, source.shape[-2] - 1]))
        colour = source.expand(3, -1, -1)[:, pixel[:, 1], pixel[:, 0]].T
        point_colours[mine] = colour if colour.dtype == torch.uint8 else (colour.float() * 255).round().clamp(0, 255).to(torch.uint8)
    return Reconstruction(
        cameras=Camera(model.K[views], model.R[views], model.t[views],  # an estimated k1 with the pixels as detected
                       model.K.new_tensor([model.radial, 0.0]).expand(views.numel(), 2) if model.radial else None),
        image_names=[names[v] for v in views.tolist()],
        image_sizes=torch.tensor([[sizes[v][1], sizes[v][0]] for v in views.tolist()]),
        points3d=model.points[point_tracks],
        colors=point_colours,
        observation_points=point_of[tracks.track[keep]],
        observation_views=camera_of[tracks.view[keep]],
        keypoints=(model.observed if model.radial else model.pixels)[keep],
        view_indices=views.tolist(),
        point_tracks=point_tracks,
        unregistered=unregistered,
        loose_resections={view: threshold for view, threshold in sorted(model.loose_resections.items()) if model.registered[view]},
        tracked_resections={view: kept for view, kept in sorted(model.tracked_resections.items()) if model.registered[view]},
        still_frames=dict(sorted(model.still_frames.items())),
        timings=timings,
    )

