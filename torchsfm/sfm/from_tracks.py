"""Reconstruction from tracks instead of images: the incremental mapper on (F, N, 2) tracks with
gaps, and one model per rigid motion of a scene with moving objects.

:func:`reconstruct_tracks` verifies the frame pairs that share enough tracks (each frame with the
frames 1, 2, 4, 8, ... after it: a video's short and long baselines without every pair) and runs
the mapper of :mod:`torchsfm.sfm.mapping` on them. :func:`reconstruct_motions` segments the
tracks into rigid motions (:func:`~torchsfm.moving.segmentation.segment_motions`) and
reconstructs each: the static scene with the camera's poses, and every moving body in its own
frame — the camera's poses relative to the body, and the body's shape (up to its own scale).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import torch
from torch import Tensor

from torchsfm.camera import check_intrinsics
from torchsfm.config import Config
from torchsfm.errors import InputError, NotEnoughDataError, TorchSfmError
from torchsfm.moving.segmentation import MotionSegmentation, segment_motions
from torchsfm.moving.track_input import check_tracks
from torchsfm.reconstruction import Reconstruction
from torchsfm.sfm.mapping import map_incrementally
from torchsfm.sfm.stages import Progress, ViewSet
from torchsfm.sfm.tracks import Tracks
from torchsfm.sfm.view_pairs import verify_pairs


def frame_pairs(num_frames: int) -> list[tuple[int, int]]:
    """(i, i + d) for d = 1, 2, 4, 8, ...: every frame with near and far partners, F log F pairs."""
    pairs, step = [], 1
    while step < num_frames:
        pairs += [(i, i + step) for i in range(num_frames - step)]
        step *= 2
    return pairs


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
    K = K.double().expand(F, 3, 3) if K.dim() == 2 else K.double()
    if K.shape != (F, 3, 3):
        raise InputError(f"K must be (3, 3) or ({F}, 3, 3), got {tuple(K.shape)}")
    check_intrinsics(K=K)
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
    for label in range(segmentation.num_motions):
        members = torch.nonzero(segmentation.labels == label).flatten()
        try:
            model = reconstruct_tracks(tracks[:, members], K, visible[:, members], config=config, generator=generator)
        except TorchSfmError as error:
            result.failed[label] = f"{members.numel()} tracks: {error}"
            continue
        for part in (model, *model.other_models):
            part.point_tracks = members[part.point_tracks]  # indices into the input tracks
        result.models[label], result.track_indices[label] = model, members
    return result
