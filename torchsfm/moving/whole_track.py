"""Moving-object rejection over whole tracks with visibility gaps (ours, beyond one triplet).

Two kinds of evidence, combined by ``moving_objects.track_method``:

* ``triplets`` — the thesis' IMOR + RANSAC on frame triplets (0, k, 2k) (each on the tracks
  seen in all three frames); a track rejected by at least ``min_rejection_share`` of the
  triplets that tested it is moving.
* ``rigid_groups`` — the tracks are split into rigid motions one after another
  (:func:`torchsfm.moving.static_tracks.rigid_group`: a projective reconstruction of the largest
  remaining group over all frames, then the next), each track going to the group that explains
  it best; the static scene is the group the triplet votes reject least (ties and groups no
  triplet saw: the group covering most cells of an 8×8 grid over the image, i.e. the scene
  surrounds the objects). Every track of the static group is background.
* ``both`` — background for both.
* ``segmentation`` (the default) — every rigid motion is segmented first
  (:func:`torchsfm.moving.segmentation.segment_motions`, the number of motions found by the
  method) and the static scene is its label 0: the motion covering most of the image (measured
  on Hopkins155 and KT3DMoSeg: a better choice than the motion the triplet votes reject least),
  then made what its own rigid motion explains (``settle_scene``); no triplet votes are cast. Tracks it leaves unassigned (too short, outliers) are untested.

A track seen in fewer than three frames cannot be judged: it is reported as untested and not
kept as background.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor

from torchsfm.config import Config
from torchsfm.errors import ShapeError, TorchSfmError
from torchsfm.inference import without_autograd
from torchsfm.moving.imor import MIN_VECTORS, MovingObjectRejection, reject_moving_objects_in_triplets
from torchsfm.moving.scene import grid_coverage
from torchsfm.moving.segmentation import MotionSegmentation, segment_motions
from torchsfm.moving.static_tracks import RigidGroup, rigid_group
from torchsfm.moving.track_input import check_tracks


@dataclass
class TrackRejection:
    """Result of :func:`reject_moving_objects_in_tracks` for N tracks over F frames.

    Fields:
        background_mask: (N,) bool, the decision of ``method`` (False for untested tracks).
        tested: (N,) bool, tracks the method could judge (seen in >= 3 frames; for
            ``triplets``, seen in a tested triplet).
        rejection_share: (N,) share of the triplets that rejected each track (NaN where no
            triplet tested it; all NaN for ``segmentation``).
        group_labels: (N,) int64 rigid group of each track (-1: none explains it, or not
            computed with ``triplets``; the segmentation's labels for ``segmentation``).
        static_group: index of the group taken for the static scene (-1 if none).
        rms: (N,) RMS reprojection error under the static group's cameras, pixels (NaN where
            not computed or untested): the whole-track evidence.
        groups: the rigid groups found, largest first.
        triplets: the frame triplets that were tested (seen by at least 12 tracks, a model found);
        results: their :class:`MovingObjectRejection`, in the same order.
        method: ``triplets``, ``rigid_groups``, ``both`` or ``segmentation``.
        segmentation: the :class:`MotionSegmentation` (``segmentation`` only, else None).
        fallback: why the rigid groups could not be found (the triplet votes then decide), else None.
    """

    background_mask: Tensor
    tested: Tensor
    rejection_share: Tensor
    group_labels: Tensor
    static_group: int
    rms: Tensor
    groups: list[RigidGroup]
    triplets: list[tuple[int, int, int]]
    results: list[MovingObjectRejection]
    method: str
    fallback: str | None
    segmentation: MotionSegmentation | None = None


@without_autograd
def reject_moving_objects_in_tracks(tracks: Tensor, visible: Tensor | None = None, *,
                                    triplets: list[tuple[int, int, int]] | None = None, config: Config | None = None,
                                    generator: torch.Generator | None = None) -> TrackRejection:
    """Keep the static scene among N tracks over F frames (see the module docstring).

    Args:
        tracks: (F, N, 2) pixels, F >= 3 (values where not visible are ignored).
        visible: (F, N) bool, where each track is seen (default: everywhere).
        triplets: frame triplets for the votes (default: (0, k, 2k) for every k up to (F - 1) / 2).
        config: ``config.moving_objects`` (method, thresholds) and ``config.fundamental``.
        generator: random source of all RANSACs.

    Returns:
        A :class:`TrackRejection`.

    Raises:
        ShapeError, InputError: malformed tracks or visibility, non-finite visible positions.
        NotEnoughDataError: fewer than 3 frames, fewer than 12 tracks seen in >= 3 frames.
    """
    config = config or Config()
    settings = config.moving_objects
    tracks, visible = check_tracks(tracks, visible)
    F, N, _ = tracks.shape
    triplets = triplets or [(0, k, 2 * k) for k in range(1, (F - 1) // 2 + 1)]
    for triplet in triplets:
        if len(triplet) != 3 or len(set(triplet)) != 3 or not all(0 <= f < F for f in triplet):
            raise ShapeError(f"triplet {triplet} must name three distinct frames of 0..{F - 1}")
    nan = torch.full((N,), float("nan"), dtype=torch.float64, device=tracks.device)
    if settings.track_method == "segmentation":
        segmentation = segment_motions(tracks, visible, config=config.segmentation, generator=generator)
        return TrackRejection(background_mask=segmentation.labels == 0, tested=segmentation.labels >= 0,
                              rejection_share=nan, group_labels=segmentation.labels, static_group=0, rms=nan, groups=[],
                              triplets=[], results=[], method="segmentation", fallback=None, segmentation=segmentation)
    share, tested_triplets, results = _triplet_votes(tracks, visible, triplets, config, generator)
    voted = ~share.isnan()
    by_votes = voted & (share < settings.min_rejection_share)
    labels, groups, fallback = torch.full((N,), -1, dtype=torch.long, device=tracks.device), [], None
    static_group, rms = -1, nan
    if settings.track_method != "triplets":
        found = _rigid_groups(tracks, visible, config, generator)
        if isinstance(found, str):
            fallback = found
        else:
            labels, groups = found
            static_group = _static_group(tracks, visible, labels, len(groups), share)
            rms = torch.where(groups[static_group].rms.isfinite(), groups[static_group].rms, nan)
    if settings.track_method == "triplets" or fallback is not None:
        background, tested = by_votes, voted
    else:
        tested = visible.sum(0) >= 3
        background = labels == static_group
        if settings.track_method == "both":
            background &= ~voted | by_votes
    return TrackRejection(background_mask=background, tested=tested, rejection_share=share, group_labels=labels,
                          static_group=static_group, rms=rms, groups=groups, triplets=tested_triplets, results=results,
                          method=settings.track_method, fallback=fallback)


def _triplet_votes(tracks: Tensor, visible: Tensor, triplets: list[tuple[int, int, int]], config: Config,
                   generator: torch.Generator | None
                   ) -> tuple[Tensor, list[tuple[int, int, int]], list[MovingObjectRejection]]:
    """IMOR + RANSAC on every triplet's fully seen tracks, all triplets in one batched call
    (:func:`~torchsfm.moving.imor.reject_moving_objects_in_triplets`): (N,) rejection share
    (NaN: untested), the triplets tested and their results."""
    N = tracks.shape[1]
    seen = torch.stack([visible[list(triplet)].all(0) for triplet in triplets]) if triplets else visible[:0]  # (T, N)
    usable = [t for t in range(len(triplets)) if int(seen[t].sum()) >= MIN_VECTORS]
    found = reject_moving_objects_in_triplets([tracks[list(triplets[t])][:, seen[t]] for t in usable], config=config,
                                              generator=generator) if usable else []
    rejected = torch.zeros(N, dtype=torch.float64, device=tracks.device)
    tested = torch.zeros(N, dtype=torch.float64, device=tracks.device)
    tested_triplets, results = [], []
    for t, result in zip(usable, found):
        if isinstance(result, str):  # RANSAC found no F on this triplet: it casts no vote
            continue
        tested_triplets.append(tuple(triplets[t]))
        results.append(result)
        tested[seen[t]] += 1
        rejected[seen[t]] += (~result.background_mask).double()
    return torch.where(tested > 0, rejected / tested.clamp_min(1), float("nan")), tested_triplets, results


def _rigid_groups(tracks: Tensor, visible: Tensor, config: Config, generator: torch.Generator | None
                  ) -> tuple[Tensor, list[RigidGroup]] | str:
    """Rigid groups one after another; each track labelled with the group explaining it best."""
    settings = config.moving_objects
    remaining = visible.sum(0) >= 3
    groups: list[RigidGroup] = []
    while len(groups) < settings.max_motions and int(remaining.sum()) >= 2 * settings.min_group_tracks:
        try:
            group = rigid_group(tracks, visible, remaining, fundamental_ransac=config.fundamental.ransac,
                                resection_ransac=settings.resection_ransac, refinements=settings.track_refinements,
                                threshold=settings.track_tolerance, significance=settings.track_significance,
                                generator=generator)
        except TorchSfmError as error:
            group = str(error)
        if isinstance(group, str):
            if not groups:
                return f"no rigid group could be reconstructed: {group}"
            break
        if int(group.members.sum()) < settings.min_group_tracks:
            break
        groups.append(group)
        remaining &= ~group.members
    if not groups:
        return f"fewer than {2 * settings.min_group_tracks} tracks are seen in three frames"
    members = torch.stack([group.members for group in groups])  # (G, N)
    rms = torch.where(members, torch.stack([group.rms for group in groups]), float("inf"))
    return torch.where(members.any(0), rms.argmin(0), -1), groups


def _static_group(tracks: Tensor, visible: Tensor, labels: Tensor, num_groups: int, share: Tensor) -> int:
    """The group the triplet votes reject least; ties and unvoted groups go to the group
    covering most cells of a grid over the image."""
    coverage = grid_coverage(tracks, visible, labels, num_groups)
    scores = []
    for g in range(num_groups):
        voted = (labels == g) & ~share.isnan()
        rejection = float(share[voted].mean()) if bool(voted.any()) else 1.0
        scores.append((rejection, -int(coverage[g])))
    return min(range(num_groups), key=lambda g: scores[g])
