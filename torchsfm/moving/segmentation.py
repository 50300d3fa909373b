"""Motion segmentation: every independent rigid motion among N tracks over F frames (ours).

Preference clustering (in the family of J-/T-linkage and the ordered-residual kernel) on batched
minimal-sample models:

1. **Hypotheses** of the kinds in ``config.models`` (default all three; ``homography`` on three
   frames or more only), ``config.hypotheses`` per round shared equally by the kinds used:
   ``fundamental`` — an 8-point F fitted to 8 tracks over every pair of ``sample_frames``
   frames (a track's residual: its largest Sampson distance over those pairs in which it is
   seen); ``affine`` — the 3-dimensional affine subspace of trajectories that 4 tracks span over
   ``affine_frames`` frames (Tomasi–Kanade; a track's residual: its distance to it, RMS per
   frame); ``homography`` — a plane's 4-point homographies over the same frame
   pairs as F (a local model: it separates a car driving along the camera's direction, whose
   epipolar geometry nearly agrees with the scene's). A hypothesis is not evaluated on the
   tracks it was sampled from. In the first round
   half the samples are local (a seed track and its nearest neighbours in the image: a rigid body
   is usually a compact region); in each of the ``guided_rounds`` that follow, the other tracks
   of a sample are drawn in proportion to their similarity to the seed in the previous round —
   same-motion tracks spread over the whole body, so models are fitted over its extent rather than
   over a patch (a patch's F extrapolates badly, which made large backgrounds fall apart).
2. **Preferences**: each track prefers the ``preference_share`` of its defined hypotheses with
   the smallest residuals (ordered-residual kernel, Chin, Wang & Suter 2009) — a rank, so no
   noise threshold is fitted to a data set.
3. **Similarity**: the Tanimoto similarity of two tracks' preferences over the hypotheses defined
   for both (tracks seen in different frames compare on what they share). A track whose
   ``support`` most similar tracks are on average at most ``outlier_factor`` times as similar as
   two unrelated preference sets are by chance (q / (2 - q) for share q) fits no motion: it is
   an outlier, labelled -1. The affinity keeps each track's ``links`` strongest links.
4. **Clustering**: spectral k-means (normalized affinity, ``restarts`` batched restarts) cuts
   the tracks into ``pieces``, each split along the affinity graph's unlinked groups
   (:func:`split_by_components`); pieces are merged two at a time, the pair most strongly linked
   relative to the smaller one's volume first. The number of motions (when not given) is the
   count just before the largest relative drop of that link over the merges (model selection on
   the dendrogram; see :func:`merge_clusters`). The tracks are then also cut directly into that
   many clusters (spectral k-means on as many eigenvectors), and the partition with the smaller
   normalized cut (Shi & Malik 2000) is kept: merging pieces can leave a small piece on its own
   while joining two motions, a direct cut can split a motion along a weak seam; the normalized
   cut is the objective both approximate.
5. **The static scene** is the motion whose tracks cover most cells of an 8×8 grid over the
   image over all frames (the scene surrounds the objects; ties: the most tracks); it becomes
   label 0, the others 1..k in decreasing size. This is a prior, not geometry: with a moving
   camera every rigid body is an equally valid "world" (measured on the translating-camera
   sequences of Hopkins155: a better choice than the largest motion or the motion the thesis'
   rigidity votes reject least); callers holding better evidence choose another label as the
   scene (``sizes`` and ``coverage`` are per label).
6. **The scene settled**: motions the scene's rigid motion explains join it, pieces of it that
   it does not explain are cut out as bodies, the scene refitted without them until it cuts
   nothing more (:func:`settle_scene`, :func:`scene_excess`; a scene whose parallax is beyond
   its own noise but within the tracker's floor explains a track by its projective
   reconstruction too: :func:`weak_parallax`, a room's planes split apart); then again with the depth order
   too: a track that the scene's pose (judged once, by the scene the residuals left) puts
   behind both cameras is not explained (:func:`beyond_infinity`: a car overtaking the camera
   is seen exactly like static points behind it, which every epipolar and projective test accepts).
   Where that leaves another motion both larger than the scene and covering more of the image,
   that motion is made the scene and settled in turn (:func:`rechosen_scene`: a scene first
   taken together with a large object loses the background it did not explain, and that part
   becomes the scene; where the motion is exactly as the clustering gave it, a moving body was
   first taken for the scene, and every other track goes back to the motion the clustering gave it,
   outliers left out — the pieces cut from that body were bodies only against it; a scene that
   only lost coverage stays).
   Given the number of motions, the settled partition is kept when it has that many. With
   fewer, the motion whose cut in two gains most is cut until it has that many
   (:func:`split_least_rigid`: two bodies taken for one); with more, the two motions that
   one rigid motion explains best are joined until it has that many (:func:`merge_most_rigid`:
   one motion taken for two, such as a room's walls). That partition or the pieces cut into
   that many anew (step 4 with the count given, unsettled), whichever explains the tracks better
   (:func:`partition_residual`). The number says how many motions there are, the scene's
   geometry which tracks belong to it.

7. **An ensemble** (``config.runs`` > 1; 1 by default): steps 1-6 run that many times on
   successive draws of the generator, and the result is the run whose partition agrees most with
   the others' (the sum of adjusted Rand indices, :func:`adjusted_rand_index`:
   the ensemble's medoid; ties to the earliest run). Each run's random hypotheses and k-means
   starts can take a wrong turn — the scene cut in two, a body merged into it — and a turn most
   runs do not take is outvoted (measured in :class:`~torchsfm.config.SegmentationConfig`).

Tracks seen in fewer than ``min_frames`` frames are labelled -1 (too short to judge). Two-frame
input (matches with several motions) is accepted: the F hypotheses then use the one pair.

The steps' code: :mod:`~torchsfm.moving.hypotheses` (step 1), :mod:`~torchsfm.moving.affinity`
(2-3), :mod:`~torchsfm.moving.clustering` (4) and :mod:`~torchsfm.moving.scene` (5-6), on the
two-view fits per frame pair of :mod:`~torchsfm.moving.pair_fits`; this module runs them, and
step 7.
"""

from __future__ import annotations

import operator
from collections.abc import Callable
from dataclasses import dataclass, field
from functools import cached_property, partial

import torch
from torch import Tensor

from torchsfm.config import SegmentationConfig
from torchsfm.errors import InputError, NotEnoughDataError
from torchsfm.inference import without_autograd
from torchsfm.moving.affinity import explained_tracks, preference_similarity, strongest_links
from torchsfm.moving.clustering import (largest_first, leading_eigenvectors, merge_clusters, normalized_cut, spectral_partition,
                                       split_by_components)
from torchsfm.moving.imor import MIN_VECTORS
from torchsfm.moving.pair_fits import frame_pairs, motion_residuals, track_residuals
from torchsfm.moving.scene import (grid_coverage, merge_most_rigid, partition_residual, rechosen_scene, scene_first, settle_scene,
                                   split_least_rigid)
from torchsfm.moving.track_input import check_tracks
from torchsfm.robust.samplers import resolve_generator, side_generator


@dataclass
class MotionSegmentation:
    """Result of :func:`segment_motions` for N tracks.

    Fields:
        labels: (N,) int64: 0 the static scene, 1..k the independently moving bodies (largest
            first), -1 unassigned (seen in fewer than ``min_frames`` frames, or an outlier).
        num_motions: rigid motions found, the static scene included (k + 1).
        sizes: (num_motions,) tracks per label 0..k.
        coverage: (num_motions,) grid cells (of 64) each label's tracks cover over all frames.
        eigenvalues: (pieces,) leading eigenvalues of the normalized affinity.
        affinity: (n, n) the sparsified symmetric affinity the clustering used, over the
            ``clustered`` (n,) tracks (input indices).
        pieces: (N,) int64 the piece of the over-segmentation (spectral k-means, before the
            merges) each clustered track fell in, -1 for the others; every motion is a union of
            pieces.
        rigidity: what computes :attr:`residuals`, each motion's rigidity, when it is first read.
    """

    labels: Tensor
    num_motions: int
    sizes: Tensor
    coverage: Tensor
    eigenvalues: Tensor
    affinity: Tensor
    clustered: Tensor
    pieces: Tensor
    rigidity: Callable[[], Tensor] = field(repr=False, compare=False)

    @cached_property
    def residuals(self) -> Tensor:
        """(num_motions,) how rigid each label's tracks are: the median over its tracks of their
        RMS Sampson distance (pixels) to one F per frame pair fitted from RANSAC's inliers
        (:func:`motion_residuals`: tracks the clustering let in by mistake neither pull the fit
        nor set the median); NaN for a label too small to fit. A RANSAC per motion and frame
        pair that no decision needs (about a twentieth of a 1000-track segmentation's time): made when
        first read, with draws of its own (the caller's stream goes on as without it)."""
        return without_autograd(self.rigidity)()


@without_autograd
def segment_motions(tracks: Tensor, visible: Tensor | None = None, *, config: SegmentationConfig | None = None,
                    num_motions: int | None = None, generator: torch.Generator | None = None) -> MotionSegmentation:
    """Segment N tracks over F frames into rigid motions (see the module docstring).

    Args:
        tracks: (F, N, 2) pixels, F >= 2 (values where not visible are ignored).
        visible: (F, N) bool, where each track is seen (default: everywhere).
        config: the ``segmentation`` section (default settings if None).
        num_motions: the number of rigid motions, static scene included, when known (benchmarks
            that are given it; step 6 of the module docstring); None finds it (model selection
            on the merges).
        generator: random source of the hypotheses and of k-means.

    Returns:
        A :class:`MotionSegmentation`.

    Raises:
        ShapeError, InputError: malformed tracks or visibility, non-finite visible positions,
            ``num_motions`` not a positive int.
        NotEnoughDataError: fewer than 2 frames, fewer than 12 tracks seen in ``min_frames``
            frames (or fitting any motion), or ``num_motions`` above the tracks clustered.
    """
    config = config or SegmentationConfig()
    if num_motions is not None:
        num_motions = positive_count(num_motions)
    tracks, visible = check_tracks(tracks, visible, min_frames=2)
    generator = resolve_generator(generator, tracks.device)
    if config.runs == 1:
        return _segment_once(tracks, visible, config, num_motions, generator)
    runs = []
    for _ in range(config.runs):
        run = _segment_once(tracks, visible, config, num_motions, generator)
        run.affinity = run.affinity.to_sparse()  # (n, n) with 2 ``links`` entries a row at most: held compactly meanwhile
        runs.append(run)
    agreement = [sum(adjusted_rand_index(run.labels, other.labels) for other in runs if other is not run) for run in runs]
    medoid = runs[max(range(len(runs)), key=lambda r: (agreement[r], -r))]  # the earliest on ties
    medoid.affinity = medoid.affinity.to_dense()
    return medoid


def adjusted_rand_index(first: Tensor, second: Tensor) -> float:
    """Agreement of two partitions of the same N points, (N,) integer labels each (-1 a class of
    its own): the Rand index corrected for chance (Hubert & Arabie 1985), 1 for the same
    partition whatever the label values, about 0 for unrelated ones; 1 when both put every point
    in one class."""
    _, a = torch.unique(first, return_inverse=True)
    _, b = torch.unique(second, return_inverse=True)
    table = torch.zeros(int(a.max()) + 1, int(b.max()) + 1, dtype=torch.float64, device=a.device)
    table.index_put_((a, b), torch.ones_like(a, dtype=torch.float64), accumulate=True)

    def pairs(counts: Tensor) -> Tensor:
        return (counts * (counts - 1) / 2).sum()

    together, rows, columns = pairs(table), pairs(table.sum(1)), pairs(table.sum(0))
    n = first.numel()
    expected = rows * columns / max(n * (n - 1) / 2, 1)
    largest = (rows + columns) / 2
    return 1.0 if float(largest - expected) == 0 else float((together - expected) / (largest - expected))


def positive_count(num_motions: object) -> int:
    """``num_motions`` as an int (a Python, NumPy or 0-d tensor integer), or an :class:`InputError`
    naming it where it is not a positive integer."""
    try:
        count = operator.index(num_motions)
    except TypeError:
        count = None
    if isinstance(num_motions, bool) or count is None or count < 1:
        raise InputError(f"num_motions must be a positive int (the static scene counts as one) or None, got {num_motions!r}")
    return count


def _segment_once(tracks: Tensor, visible: Tensor, config: SegmentationConfig, num_motions: int | None,
                  generator: torch.Generator) -> MotionSegmentation:
    """One run of :func:`segment_motions` (steps 1-6 of the module docstring) on checked input."""
    judged = visible.sum(0) >= min(config.min_frames, tracks.shape[0])
    if int(judged.sum()) < MIN_VECTORS:
        raise NotEnoughDataError(f"only {int(judged.sum())} tracks are seen in {config.min_frames} frames (needs {MIN_VECTORS})")
    index = torch.nonzero(judged)[:, 0]
    left_out = index[:0]
    if index.numel() > config.max_tracks:  # cluster a seeded subset; the others go to the motion that fits them
        chosen = torch.zeros(index.numel(), dtype=torch.bool, device=index.device)
        chosen[torch.randperm(index.numel(), generator=generator, device=generator.device)[:config.max_tracks].to(index.device)] = True
        index, left_out = index[chosen], index[~chosen]
    similarity = None
    for _ in range(1 + config.guided_rounds):
        similarity = preference_similarity(tracks[:, index], visible[:, index], config, generator, similarity)
    explained = explained_tracks(similarity, config)
    if int(explained.sum()) < MIN_VECTORS:
        raise NotEnoughDataError(f"only {int(explained.sum())} tracks fit any rigid motion (needs {MIN_VECTORS})")
    index, similarity = index[explained], similarity[explained][:, explained]
    affinity = strongest_links(similarity, config.links)
    eigenvalues, vectors = leading_eigenvectors(affinity, max(config.pieces, num_motions or 0))
    if num_motions is not None and num_motions > index.numel():  # a positive int (checked by segment_motions)
        raise NotEnoughDataError(f"cannot split {index.numel()} tracks into {num_motions} motions")
    pieces = min(vectors.shape[1], max(num_motions or 1, min(config.pieces, index.numel() // (2 * config.support))))
    cut = split_by_components(affinity, spectral_partition(vectors, pieces, config, generator), MIN_VECTORS)
    N = tracks.shape[1]
    piece_of = torch.full((N,), -1, dtype=torch.long, device=tracks.device)
    piece_of[index] = cut

    def motions(count: int | None) -> Tensor:
        """(N,) labels of ``count`` motions cut from the pieces (None: as many as found, the scene settled)."""
        found = merge_clusters(affinity, cut, count, config)
        if int(found.max()) > 0:  # the same number of motions cut directly: the partition with the smaller normalized cut
            direct = largest_first(spectral_partition(vectors, int(found.max()) + 1, config, generator))
            found = min(found, direct, key=lambda partition: normalized_cut(affinity, partition))
        clusters = torch.full((N,), -1, dtype=torch.long, device=tracks.device)
        clusters[index] = found
        labels = scene_first(tracks, visible, clusters)
        if count is not None:
            return labels
        settled = settle_scene(tracks, visible, labels, piece_of, affinity, index, config, generator)
        found_count = int(settled.max()) + 1
        coverage = grid_coverage(tracks, visible, settled, found_count)
        sizes = torch.bincount(settled[settled >= 0], minlength=found_count)
        dominant = (coverage > coverage[0]) & (sizes > sizes[0])
        if not bool(dominant.any()):
            return settled
        # settling left a motion both larger than the scene and covering more of the image: it is the scene
        scene = int(torch.where(dominant, coverage, -1).argmax())
        return settle_scene(tracks, visible, rechosen_scene(labels, settled, scene), piece_of, affinity, index, config,
                            generator)

    labels = motions(None)  # given their number, a settled partition of that many motions is kept
    if num_motions is not None and int(labels.max()) + 1 != num_motions:
        candidates = [motions(num_motions)]  # the pieces cut into that many anew
        split = labels
        while split is not None and int(split.max()) + 1 < num_motions:
            split = split_least_rigid(tracks, visible, split, piece_of, affinity, index, config, generator)
        while split is not None and int(split.max()) + 1 > num_motions:
            split = merge_most_rigid(tracks, visible, split, config, generator)
        if split is not None and int(split.max()) + 1 == num_motions:
            candidates.append(split)
        labels = min(candidates, key=lambda partition: partition_residual(tracks, visible, partition))
    num_motions = int(labels.max()) + 1
    if left_out.numel():
        labels[left_out] = label_by_residual(tracks, visible, labels, left_out, num_motions)
    assigned = labels[index]
    sizes = torch.bincount(assigned[assigned >= 0], minlength=num_motions)
    members = labels[None] == torch.arange(num_motions, device=tracks.device)[:, None]
    rigidity = partial(motion_residuals, tracks, visible, members, frame_pairs(visible), side_generator(generator))
    return MotionSegmentation(labels=labels, num_motions=num_motions, sizes=sizes,
                              coverage=grid_coverage(tracks, visible, labels, num_motions), eigenvalues=eigenvalues,
                              affinity=affinity, clustered=index, pieces=piece_of, rigidity=rigidity)


def label_by_residual(tracks: Tensor, visible: Tensor, labels: Tensor, queries: Tensor, num_motions: int) -> Tensor:
    """Labels for the ``queries`` (M,) tracks left out of the clustering: the motion whose
    fundamental matrices (fitted to its labelled tracks, :func:`track_residuals`) explain each
    best, if within 3× that motion's median residual over its own tracks, else -1 (an outlier):
    (F, N, 2) tracks, (F, N) visibility, (N,) labels -> (M,) labels."""
    members = labels[None] == torch.arange(num_motions, device=labels.device)[:, None]
    rms, judged = track_residuals(tracks, visible, members, frame_pairs(visible))  # (C, N)
    own = torch.where(judged & members, rms, torch.nan).nanmedian(-1).values  # (C,)
    candidate = torch.where(judged[:, queries] & (rms[:, queries] <= 3 * own[:, None]), rms[:, queries], torch.inf)
    best = candidate.min(0)
    return torch.where(torch.isfinite(best.values), best.indices, -1)
