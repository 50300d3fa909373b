"""Pipelines run on ground-truth data sets and scored: an Oxford view pair with planted
outliers, a real triplet with an inserted moving object."""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor

from torchsfm.geometry.fundamental import epipolar_line_distances, fundamental_from_pose
from torchsfm.estimators.two_view_geometry import estimate_fundamental, estimate_relative_pose
from torchsfm.testing.rendering import insert_moving_patch, inside_boxes
from torchsfm.testing.scenes import replace_with_random_points
from torchsfm.evaluation import mask_recall_precision, rotation_error_deg, translation_direction_error_deg


def evaluate_two_view_pair(dataset, i: int, j: int, image_size: tuple[int, int], outliers: float, seed: int,
                           config=None) -> dict[str, float]:
    """Corrupt the ground-truth matches of views (i, j) of an Oxford set and score both estimators.

    A fraction ``outliers`` of view j's matched corners is replaced by uniform random pixels;
    :func:`torchsfm.estimate_fundamental` and :func:`torchsfm.estimate_relative_pose` (K from
    the ground-truth P) then run. Returns recall/precision of both inlier masks (and the counts
    behind them, for pooling) and the rotation / translation-direction errors in degrees.
    """
    generator = torch.Generator().manual_seed(seed)
    K, _, _ = dataset.cameras()
    x1, x2 = dataset.correspondences(i, j)
    x2, truth = replace_with_random_points(x2, outliers, image_size, generator)
    fundamental = estimate_fundamental(x1, x2, config=config, generator=generator)
    pose = estimate_relative_pose(x1, x2, K[i], K[j], config=config, generator=generator)
    R_true, t_true = dataset.relative_pose(i, j)
    f_recall, f_precision = mask_recall_precision(fundamental.inlier_mask, truth)
    p_recall, p_precision = mask_recall_precision(pose.inlier_mask, truth)
    return {
        "matches": float(len(truth)),
        "true_inliers": float(truth.sum()),
        "F_hits": float((fundamental.inlier_mask & truth).sum()),
        "F_kept": float(fundamental.inlier_mask.sum()),
        "pose_hits": float((pose.inlier_mask & truth).sum()),
        "pose_kept": float(pose.inlier_mask.sum()),
        "F_recall": f_recall,
        "F_precision": f_precision,
        "pose_recall": p_recall,
        "pose_precision": p_precision,
        "R_error_deg": rotation_error_deg(pose.R, R_true),
        "t_error_deg": translation_direction_error_deg(pose.t, t_true),
    }


@dataclass
class InsertedObjectTriplet:
    """Three consecutive real frames with a pasted moving patch, and their matched triplets.

    Fields:
        images: three (3, H, W) uint8 frames with the patch. boxes: (3, 4) its boxes.
        tracks: (3, N, 2) float64 corners of frame 1 matched into frames 0 and 2.
        labels: (N,) 0 static (within ``static_threshold`` px of the ground-truth epipolar
            geometry of pairs (1, 0) and (1, 2)), 1 on the patch, -1 other outliers.
    """

    images: list[Tensor]
    boxes: Tensor
    tracks: Tensor
    labels: Tensor


def match_triplet(images: list[Tensor], config=None) -> Tensor:
    """Matches of image 0 to image 1 whose image-1 corner is also matched into image 2, as the
    two-view pipeline chains them: (3, N, 2) float64 for three (C, H, W) images."""
    from torchsfm.config import Config
    from torchsfm.features.harris import HarrisCorners
    from torchsfm.images import to_grey
    from torchsfm.matching.matcher import PutativeMatcher, chain_matches

    config = config or Config()
    grey = torch.stack([to_grey(image) for image in images])
    corners = HarrisCorners(config.harris)(grey)
    points = [corners.of_image(v).double() for v in range(3)]
    matcher = PutativeMatcher(config.matching)
    first, onward = matcher(grey[0], grey[1], points[0], points[1]), matcher(grey[1], grey[2], points[1], points[2])
    seen, third = chain_matches(first, onward, points[1].shape[0])
    return torch.stack([points[0][first.index1[seen]], points[1][first.index2[seen]], points[2][third]])


def inserted_object_triplet(sequence, first: int, patch: Tensor, *, static_threshold: float = 2.0,
                            config=None) -> InsertedObjectTriplet:
    """Frames first..first+2 of a :class:`~torchsfm.io.datasets.StrechaSequence` with ``patch``
    pasted at :data:`PATCH_POSITIONS`, matched, and labelled against the ground truth."""
    from torchsfm.images import read_image

    frames, boxes = insert_moving_patch([read_image(sequence.images[first + j]) for j in range(3)], patch)
    tracks = match_triplet(frames, config)
    static = torch.ones(tracks.shape[1], dtype=torch.bool)
    for other in (0, 2):
        R, t = sequence.relative_pose(first + 1, first + other)
        F = fundamental_from_pose(sequence.K[first + 1], sequence.K[first + other], R, t)
        static &= torch.maximum(*epipolar_line_distances(F, tracks[1], tracks[other])) < static_threshold
    labels = torch.where(inside_boxes(tracks, boxes), 1, torch.where(static, 0, -1))
    return InsertedObjectTriplet(images=frames, boxes=boxes, tracks=tracks, labels=labels)
