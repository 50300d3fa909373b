"""Reconstruction from tracks instead of images: the incremental mapper on (F, N, 2) tracks with
gaps, and one model per rigid motion of a scene with moving objects.

:func:`reconstruct_tracks` verifies the frame pairs that share enough tracks (each frame with the
frames 1, 2, 4, 8, ... after it: a video's short and long baselines without every pair) and runs
the mapper of :mod:`torchsfm.sfm.mapping` on them. :func:`reconstruct_motions` segments the
tracks into rigid motions (:func:`~torchsfm.moving.segmentation.segment_motions`) and
reconstructs each: the static scene with the camera's poses, and every moving body in its own
frame — the camera's poses relative to the body, and the body's shape (up to its own scale) —
from several starts (:func:`reconstruct_body`).
:class:`ReconstructObjects` is the image pipeline's stage that does the same for the moving
bodies the segmentation found in a :class:`~torchsfm.sfm.stages.ViewSet`.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace

import torch
from torch import Tensor

from torchsfm.camera import intrinsics_per_view, to_homogeneous
from torchsfm.config import Config
from torchsfm.errors import NotEnoughDataError, TorchSfmError
from torchsfm.geometry.projective import triangulate_multiview
from torchsfm.inference import without_autograd
from torchsfm.moving.segmentation import MotionSegmentation, segment_motions
from torchsfm.moving.track_input import check_tracks
from torchsfm.reconstruction import MovingObject, Reconstruction
from torchsfm.sfm.mapping import map_incrementally
from torchsfm.pipeline import ConfiguredStage, Progress
from torchsfm.sfm.stages import ViewSet
from torchsfm.sfm.tracks import Tracks
from torchsfm.sfm.view_pairs import verify_pairs
from torchsfm.visualization import MOTION_COLOURS


MAX_REMAPS = 3  # the static scene is mapped again at most this many times with the tracks it explains


def frame_pairs(num_frames: int) -> list[tuple[int, int]]:
    """(i, i + d) for d = 1, 2, 4, 8, ...: every frame with near and far partners, F log F pairs."""
    pairs, step = [], 1
    while step < num_frames:
        pairs += [(i, i + step) for i in range(num_frames - step)]
        step *= 2
    return pairs


@without_autograd
def reconstruct_tracks(tracks: Tensor, K: Tensor, visible: Tensor | None = None, *, config: Config | None = None,
                       generator: torch.Generator | None = None, progress: Progress | None = None) -> Reconstruction:
    """Camera poses and a 3-D point per track from tracked pixels.

    Args:
        tracks: (F, N, 2) pixels (ideal: undistorted), F >= 2 frames, N tracks.
        K: (3, 3) intrinsics of every frame, or (F, 3, 3).
        visible: (F, N) bool, where each track is seen (default: everywhere).
        config: ``reconstruction`` (pair and resection minimums, gates) and the RANSAC settings;
        generator: the random source of every RANSAC; progress: called with each step.

    Returns:
        A :class:`~torchsfm.reconstruction.Reconstruction` (``view_indices``: the frames;
        ``unregistered``: the others with the reason; ``other_models`` when the frames split;
        ``point_tracks``: the input track of each point); points grey. Scale: the initial pair's baseline is 1.

    Raises:
        NotEnoughDataError / DegenerateConfigurationError: no frame pair can start a model.
    """
    config = config or Config()
    tracks, visible = check_tracks(tracks, visible, min_frames=2)
    F, N, _ = tracks.shape
    K = intrinsics_per_view(K, F)
    seen_twice = visible.sum(0) >= 2
    visible = visible & seen_twice
    corner_of = torch.cumsum(visible.long(), dim=1) - 1  # (F, N): each visible track's corner index in its frame
    frame, track = torch.nonzero(visible.T, as_tuple=True)[::-1]  # observations sorted by track
    renumbered = torch.cumsum(seen_twice.long(), 0) - 1
    observations = Tracks(view=frame, corner=corner_of[frame, track], track=renumbered[track], num_tracks=int(seen_twice.sum()))
    corners = [tracks[f][visible[f]] for f in range(F)]
    putative = {}
    for i, j in frame_pairs(F):
        both = visible[i] & visible[j]
        if int(both.sum()) >= config.reconstruction.min_pair_inliers:
            putative[(i, j)] = (corner_of[i][both], corner_of[j][both])
    if not putative:
        raise NotEnoughDataError(f"no frame pair shares {config.reconstruction.min_pair_inliers} tracks "
                                 "(reconstruction.min_pair_inliers): nothing to start a model from")
    report = progress or (lambda message: None)
    state = ViewSet(images=[], K=K, distortion=K.new_zeros(F, 2), names=[f"frame{f}" for f in range(F)],
                    generator=generator or torch.Generator().manual_seed(0), report=report)
    state.raw = state.corners = corners
    state.pairs = verify_pairs(putative, corners, config, state.generator, report)
    state.tracks = observations
    model = map_incrementally(state, config)
    model.timings = state.timings
    input_index = torch.nonzero(seen_twice).flatten()
    for part in (model, *model.other_models):
        part.point_tracks = input_index[part.point_tracks]
    return model


@dataclass
class MotionModels:
    """One model per rigid motion of tracks (:func:`reconstruct_motions`).

    Fields:
        segmentation: the :class:`~torchsfm.moving.segmentation.MotionSegmentation` of the tracks
            (label 0 the static scene, 1..k the moving bodies, -1 unassigned).
        models: per label, the model of its tracks: label 0 in the scene's frame (the camera's
            poses), a moving body's in the body's own frame (the camera's poses relative to it);
            ``point_tracks`` index the input tracks.
        track_indices: per label, the input tracks the segmentation gave it (the model's
            ``point_tracks`` are those it kept: seen in enough frames, consistent with the motion).
        failed: per label that could not be reconstructed, why (too few tracks, no baseline).
    """

    segmentation: MotionSegmentation
    models: dict[int, Reconstruction] = field(default_factory=dict)
    track_indices: dict[int, Tensor] = field(default_factory=dict)
    failed: dict[int, str] = field(default_factory=dict)


@without_autograd
def reconstruct_motions(tracks: Tensor, K: Tensor, visible: Tensor | None = None, *, config: Config | None = None,
                        num_motions: int | None = None, generator: torch.Generator | None = None) -> MotionModels:
    """Segment (F, N, 2) tracks into rigid motions and reconstruct each with K (3, 3) or (F, 3,
    3): the static scene and every moving body as its own model (see :class:`MotionModels`).
    ``num_motions``: the number of motions, the static scene included, if known."""
    config = config or Config()
    generator = generator or torch.Generator().manual_seed(0)
    tracks, visible = check_tracks(tracks, visible)
    segmentation = segment_motions(tracks, visible, config=config.segmentation, num_motions=num_motions, generator=generator)
    result = MotionModels(segmentation=segmentation)
    config = with_track_views(config, min(config.segmentation.min_frames, tracks.shape[0]))
    for label in range(segmentation.num_motions):
        members = torch.nonzero(segmentation.labels == label).flatten()
        reconstruct = reconstruct_tracks if label == 0 else reconstruct_body
        try:
            model = reconstruct(tracks[:, members], K, visible[:, members], config=config, generator=generator)
        except TorchSfmError as error:
            result.failed[label] = f"{members.numel()} tracks: {error}"
            continue
        for part in (model, *model.other_models):
            part.point_tracks = members[part.point_tracks]  # indices into the input tracks
        result.models[label], result.track_indices[label] = model, members
    return result


def with_track_views(config: Config, views: int) -> Config:
    """``config`` with points kept only where seen within the gate in ``views`` views (at least
    ``reconstruction.min_track_views``): for tracks selected for being seen that often, a track
    of another motion that the segmentation let in fits two views by chance, not three."""
    settings = config.reconstruction
    return replace(config, reconstruction=replace(settings, min_track_views=max(settings.min_track_views, views)))


def reconstruct_body(tracks: Tensor, K: Tensor, visible: Tensor | None = None, *, config: Config,
                     generator: torch.Generator) -> Reconstruction:
    """A moving body's model from its (F, N, 2) tracks (K (3, 3) or (F, 3, 3), (F, N) visibility):
    :func:`reconstruct_tracks` from ``moving_objects.object_starts`` independent draws of the
    ``generator``; of the models, the one that registers most frames, then has the smallest
    truncated squared reprojection error over the observations (MSAC's cost: an observation
    outside the gate T = ``reconstruction.max_reprojection_error`` costs T², one inside its
    squared error; the observations are the same for every start). Raises the last start's
    error when no start gives a model."""
    best, failure, gate = None, None, config.reconstruction.max_reprojection_error
    for _ in range(config.moving_objects.object_starts):
        try:
            model = reconstruct_tracks(tracks, K, visible, config=config, generator=generator)
        except TorchSfmError as error:
            failure = error
            continue
        errors = model.observation_errors()
        rank = (model.num_views, float((gate ** 2 - errors.square()).sum()))
        if best is None or rank > best[0]:
            best = (rank, model)
    if best is None:
        raise failure
    return best[1]


def consistent_with_scene(pixels: Tensor, visible: Tensor, K: Tensor, scene: Reconstruction, threshold: float) -> tuple[Tensor, Tensor]:
    """Which tracks a static point explains in the scene's cameras: (V, N, 2) undistorted pixels,
    (V, N) visibility and (V, 3, 3) K over the state's V views, the scene's ``view_indices`` in
    the same numbering -> (N,) bool testable: seen in two registered views or more, and (N,) bool
    consistent: testable, and one point (linear triangulation over those views) in front of each
    and within ``threshold`` px of every observation. A track with too little parallax passes
    (no evidence against it)."""
    V, N = visible.shape
    R = torch.zeros(V, 3, 3, dtype=torch.float64)
    t = torch.zeros(V, 3, dtype=torch.float64)
    registered = torch.zeros(V, dtype=torch.bool)
    views = torch.tensor(scene.view_indices, dtype=torch.long)
    R[views], t[views], registered[views] = scene.cameras.R, scene.cameras.t, True
    seen = visible & registered[:, None]
    normalized = (torch.linalg.inv(K)[:, None] @ to_homogeneous(pixels)[..., None])[..., :2, 0]  # (V, N, 2)
    X = triangulate_multiview(torch.cat([R, t[..., None]], dim=-1), normalized, seen.double(), iterations=0)  # (N, 4) linear
    camera_points = (R[:, None] @ X[None, :, :3, None])[..., 0] + t[:, None] * X[None, :, 3:]  # (V, N, 3) up to X's scale
    depth_sign = torch.sign(camera_points[..., 2] * X[None, :, 3].sign())
    projected = (K[:, None] @ camera_points[..., None])[..., 0]
    errors = (projected[..., :2] / projected[..., 2:] - pixels).norm(dim=-1)
    fits = (errors <= threshold) & (depth_sign > 0)
    testable = seen.sum(0) >= 2
    return testable, testable & (fits | ~seen).all(0)


class ReconstructObjects(ConfiguredStage):
    """After :class:`~torchsfm.sfm.stages.MapIncrementally`, with the segmentation's
    ``track_labels`` (``moving_objects.reconstruct_objects``): a segment most of whose testable
    tracks a static point explains in the scene's cameras (:func:`consistent_with_scene`, within
    ``reconstruction.max_reprojection_error``) is part of the static scene (the segmentation cut
    the scene apart), and so is every track the segmentation left unassigned (too short to judge)
    that a static point explains: they go back to the scene and it is mapped again, up to
    ``MAX_REMAPS`` times while that adds tracks (each mapping registers views that test more). Every other
    moving body with at least ``min_object_tracks`` tracks seen in ``min_object_frames`` frames
    is reconstructed from its tracks (:func:`reconstruct_tracks`, the views' K; points in the
    body's colour of :data:`~torchsfm.visualization.MOTION_COLOURS`). Fills
    ``reconstruction.objects`` (views by the state's indices) and ``segmented_tracks``."""

    SECTIONS = ("moving_objects", "reconstruction", "matching", "resection", "lm", "triangulation", "bundle_adjustment", "relative_pose",
                "fundamental")

    def forward(self, state: ViewSet) -> ViewSet:
        labels = state.track_labels.clone()
        pixels, visible = state.all_tracks.dense(state.corners, len(state.corners))
        for _ in range(MAX_REMAPS):
            testable, static = consistent_with_scene(pixels, visible, state.K, state.reconstruction,
                                                     self.config.reconstruction.max_reprojection_error)
            size = int(labels.max()) + 2  # counts per label + 1 (label -1 first)
            tested, explained = (torch.bincount(labels[mask] + 1, minlength=size) for mask in (testable, static))
            merged = [label for label in range(1, size - 1) if 2 * int(explained[label + 1]) > int(tested[label + 1]) > 0]
            joining = ((labels == -1) & static) | torch.isin(labels, torch.tensor(merged, dtype=torch.long))
            if not bool(joining.any()):
                break
            state.report(f"{int(joining.sum())} tracks back to the static scene (a static point explains them in its cameras"
                         + (f"; segments {merged}" if merged else "") + "): mapping it again")
            labels[joining] = 0
            state.tracks = state.all_tracks.subset(labels == 0)
            scene = map_incrementally(state, self.config)
            scene.moving_objects = state.reconstruction.moving_objects
            scene.moving_rejections_per_view = dict(enumerate((visible & (labels != 0)[None]).sum(1).tolist()))
            state.reconstruction = scene
        state.reconstruction.segmented_tracks = (pixels, visible, labels)
        state.reconstruction.objects = [self._body(state, label, pixels[:, labels == label], visible[:, labels == label])
                                        for label in range(1, int(labels.max()) + 1) if bool((labels == label).any())]
        return state

    def _body(self, state: ViewSet, label: int, pixels: Tensor, visible: Tensor) -> MovingObject:
        settings = self.config.moving_objects
        long_enough = visible.sum(0) >= settings.min_object_frames
        count = int(long_enough.sum())
        body = MovingObject(label=label, num_tracks=visible.shape[1])
        if count < settings.min_object_tracks:
            body.reason = (f"{count} of its {visible.shape[1]} tracks are seen in {settings.min_object_frames} frames or more "
                           f"(needs {settings.min_object_tracks}: moving_objects.min_object_tracks)")
        else:
            try:
                body.model = reconstruct_body(pixels[:, long_enough], state.K, visible[:, long_enough],
                                              config=with_track_views(self.config, settings.min_object_frames), generator=state.generator)
                body.model.image_names = [state.names[v] for v in body.model.view_indices]
                scene = state.reconstruction  # each view's size as the scene has it (a view it lacks: its first view's)
                size_of = dict(zip(scene.view_indices, scene.image_sizes.tolist()))
                body.model.image_sizes = torch.tensor([size_of.get(v, scene.image_sizes[0].tolist()) for v in body.model.view_indices])
                body.model.colors[:] = torch.tensor(MOTION_COLOURS[label % len(MOTION_COLOURS)], dtype=torch.uint8)
            except TorchSfmError as error:
                body.reason = f"no model from its {count} tracks: {error}"
        state.report(f"moving body {label}: " + (body.reason or f"{body.model.num_views} views, {body.model.num_points} points"))
        return body
