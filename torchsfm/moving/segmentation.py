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
   the tracks into ``pieces``; pieces are merged two at a time, the pair most strongly linked
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
   too: a track that the scene's pose puts behind both cameras is not explained
   (:func:`beyond_infinity`: a car overtaking the camera is seen exactly like static points
   behind it, which every epipolar and projective test accepts).
   Where that leaves another motion both larger than the scene and covering more of the image,
   that motion is made the scene and settled in turn (:func:`rechosen_scene`: a scene first
   taken together with a large object loses the background it did not explain, and that part
   becomes the scene; where the motion is exactly as the clustering gave it, a moving body was
   first taken for the scene, and every other track goes back to the motion the clustering gave it,
   outliers left out — the pieces cut from that body were bodies only against it; a scene that
   only lost coverage stays).
   Given the number of motions, the settled partition is kept when it has that many. With
   fewer, the motion whose cut in two gains most is cut until it has that many
   (:func:`split_least_rigid`: two bodies taken for one); that partition or the pieces cut into
   that many anew (step 4 with the count given, unsettled), whichever explains the tracks better
   (:func:`partition_residual`). With more, the cut anew. The number says how many motions there
   are, the scene's geometry which tracks belong to it.

7. **An ensemble** (``config.runs`` > 1; 1 by default): steps 1-6 run that many times on
   successive draws of the generator, and the result is the run whose partition agrees most with
   the others' (the sum of adjusted Rand indices, :func:`adjusted_rand_index`:
   the ensemble's medoid; ties to the earliest run). Each run's random hypotheses and k-means
   starts can take a wrong turn — the scene cut in two, a body merged into it — and a turn most
   runs do not take is outvoted (measured in :class:`~torchsfm.config.SegmentationConfig`).

Tracks seen in fewer than ``min_frames`` frames are labelled -1 (too short to judge). Two-frame
input (matches with several motions) is accepted: the F hypotheses then use the one pair.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import torch
from torch import Tensor

from torchsfm.camera import FOCAL_PRIOR, pixels_to_normalized, to_homogeneous
from torchsfm.config import FundamentalConfig, MovingObjectsConfig, SegmentationConfig
from torchsfm.errors import NotEnoughDataError
from torchsfm.geometry.essential import POSE_CANDIDATES, essential_from_fundamental, parallax_from_infinity, select_pose
from torchsfm.geometry.fundamental import eight_point, eight_point_minimal, sampson_error
from torchsfm.geometry.homography import homography_dlt, transfer_error
from torchsfm.geometry.normalization import hartley_normalize
from torchsfm.geometry.self_calibration import intrinsics
from torchsfm.moving.imor import MIN_VECTORS
from torchsfm.moving.static_tracks import rms_bound, rigid_group
from torchsfm.moving.track_input import check_tracks
from torchsfm.robust.models import FundamentalModel
from torchsfm.robust.ransac import ransac
from torchsfm.robust.samplers import draws_without_replacement, resolve_generator

SAMPLE_SIZE = 8
COVERAGE_GRID = 8
CHUNK_ELEMENTS = 2**21  # numbers per hypothesis chunk: memory bounded for thousands of tracks; 16 MB of float64,
# under glibc's 32 MB ceiling for serving freed blocks again instead of fresh (page-faulting) maps
REFITS = 3  # trimmed refits of a motion's F (diagnostics)
BLOCK_ELEMENTS = 2**15  # tracks × set-and-pair problems fitted at a time (see ``track_residuals``)
SPARSE_EIGEN_TRACKS = 1500  # from here the sparse LOBPCG beats the dense eigh (0.16 s against 0.37 s; at 1000, 0.12 against 0.14)
WEAK_PARALLAX_RATIO = 3.0  # noise alone puts a plane's tracks 2x as far from its homographies (transfer distance,
# noise in both images: 2σ RMS) as from its F fits (Sampson distance: σ); measured 2.09-2.15 on synthetic planes at
# σ = 0.1-1 px; 3 leaves parallax of √5 σ RMS beyond the noise: the plane explains the tracks measurably worse than F
EIGEN_RESIDUAL = 1e-6  # largest LOBPCG residual accepted: it stops near 1e-8 (sqrt of float64 eps); a stalled run is far off


@dataclass
class MotionSegmentation:
    """Result of :func:`segment_motions` for N tracks.

    Fields:
        labels: (N,) int64: 0 the static scene, 1..k the independently moving bodies (largest
            first), -1 unassigned (seen in fewer than ``min_frames`` frames, or an outlier).
        num_motions: rigid motions found, the static scene included (k + 1).
        sizes: (num_motions,) tracks per label 0..k.
        coverage: (num_motions,) grid cells (of 64) each label's tracks cover over all frames.
        residuals: (num_motions,) how rigid each label's tracks are: the median over its tracks
            of their RMS Sampson distance (pixels) to one F per frame pair fitted from RANSAC's
            inliers (:func:`motion_residuals`: tracks the clustering let in by mistake neither
            pull the fit nor set the median); NaN for a label too small to fit.
        eigenvalues: (pieces,) leading eigenvalues of the normalized affinity.
        affinity: (n, n) the sparsified symmetric affinity the clustering used, over the
            ``clustered`` (n,) tracks (input indices).
        pieces: (N,) int64 the piece of the over-segmentation (spectral k-means, before the
            merges) each clustered track fell in, -1 for the others; every motion is a union of
            pieces.
    """

    labels: Tensor
    num_motions: int
    sizes: Tensor
    coverage: Tensor
    residuals: Tensor
    eigenvalues: Tensor
    affinity: Tensor
    clustered: Tensor
    pieces: Tensor


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
        ShapeError, InputError: malformed tracks or visibility, non-finite visible positions.
        NotEnoughDataError: fewer than 2 frames, fewer than 12 tracks seen in ``min_frames``
            frames (or fitting any motion), or ``num_motions`` outside 1..N.
    """
    config = config or SegmentationConfig()
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
    if num_motions is not None and not 1 <= num_motions <= index.numel():
        raise NotEnoughDataError(f"cannot split {index.numel()} tracks into {num_motions} motions")
    pieces = min(vectors.shape[1], max(num_motions or 1, min(config.pieces, index.numel() // (2 * config.support))))
    cut = spectral_partition(vectors, pieces, config, generator)
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
        if split is not None and int(split.max()) + 1 == num_motions:
            candidates.append(split)
        labels = min(candidates, key=lambda partition: partition_residual(tracks, visible, partition))
    num_motions = int(labels.max()) + 1
    if left_out.numel():
        labels[left_out] = label_by_residual(tracks, visible, labels, left_out, num_motions)
    assigned = labels[index]
    sizes = torch.bincount(assigned[assigned >= 0], minlength=num_motions)
    members = labels[None] == torch.arange(num_motions, device=tracks.device)[:, None]
    residuals = motion_residuals(tracks, visible, members, frame_pairs(visible), generator)
    return MotionSegmentation(labels=labels, num_motions=num_motions, sizes=sizes,
                              coverage=grid_coverage(tracks, visible, labels, num_motions), residuals=residuals,
                              eigenvalues=eigenvalues, affinity=affinity, clustered=index, pieces=piece_of)


def scene_first(tracks: Tensor, visible: Tensor, clusters: Tensor) -> Tensor:
    """(N,) cluster labels 0..C-1 (largest first; -1 none) relabelled so that the static scene
    — the cluster covering most grid cells over all frames, ties to the most tracks — is 0."""
    count = int(clusters.max()) + 1
    coverage = grid_coverage(tracks, visible, clusters, count)
    sizes = torch.bincount(clusters[clusters >= 0], minlength=count)
    static = int((coverage * (clusters.numel() + 1) + sizes).argmax())
    order = torch.tensor([static, *(c for c in range(count) if c != static)], device=clusters.device)
    relabel = torch.empty_like(order)
    relabel[order] = torch.arange(count, device=clusters.device)
    return torch.where(clusters >= 0, relabel[clusters.clamp_min(0)], -1)


def rechosen_scene(clusters: Tensor, settled: Tensor, scene: int) -> Tensor:
    """(N,) labels with motion ``scene`` of the (N,) ``settled`` labels as the static scene (0),
    renumbered in their order, from the (N,) ``clusters`` labels before settling (0 the scene
    first chosen).

    A motion exactly as the clustering gave it (settling leaves the other motions whole or joins
    them to the scene) was out-covered by a moving body taken for the scene: every other track
    goes back to its motion in ``clusters``, the tracks settling left unassigned (-1: no rigid
    motion explains them) staying so. Settling had cut that body where its ill-fitting
    reconstruction did not explain it, each refit on fewer tracks explaining less (measured on
    Hopkins155 cars10's two cars without the background — the two-motion sequence Hopkins155
    itself forms from them: the larger car, 138 tracks, cut into three bodies of 62, 54 and 22
    before the other car, 76 tracks, was made the scene; 35.5 % misclassified), and those pieces
    were bodies only against it. A body settling cut out of the scene first chosen (a scene taken together with a large
    object loses the background it did not explain) shows those cuts were right: the two labels
    only swap."""
    new_scene = settled == scene
    origin = clusters[new_scene][0]
    if origin == 0 or not torch.equal(new_scene, clusters == origin):  # cut out of the scene first chosen
        return torch.where(new_scene, 0, torch.where(settled == 0, scene, settled))
    labels = torch.where(new_scene, 0, torch.where((clusters >= 0) & (settled >= 0), clusters + 1, -1))
    _, labels[labels >= 0] = labels[labels >= 0].unique(return_inverse=True)
    return labels


def scene_excess(tracks: Tensor, visible: Tensor, scene: Tensor, pairs: Tensor, config: SegmentationConfig,
                 generator: torch.Generator) -> Tensor:
    """(N,) every track's residual under the scene's rigid motion over its inconsistency bound
    (> 1: inconsistent; NaN where not judged), for the (N,) bool ``scene`` tracks.

    The bound is the larger of ``config.scene_tolerance`` (the tracker's noise floor, px) and
    σ·sqrt(χ²_(1−α)(d) / n) (σ the scene's median residual, n the residual's terms, d its
    degrees of freedom, α = ``config.scene_significance``). The residual is the scene's
    projective reconstruction over all frames (:func:`~torchsfm.moving.static_tracks.rigid_group`,
    at most ``config.scene_refinements`` camera / point alternations; reprojection RMS, d = 2m − 3 for m
    frames) when the scene has parallax — its median distance to one homography per frame pair
    beyond the noise floor — and its tracks tie the frames together (median span at least a
    third of the sequence, :func:`median_span`), for then the multi-view constraint also fixes
    where along its epipolar line a point must be. Otherwise (a plane or a distant scene: the
    reconstruction is degenerate; a video of short tracks: one projective reconstruction
    chained over all its frames drifts) the residual is the RMS Sampson distance to one F per
    frame pair (:func:`track_residuals`; d = n = the pairs a track is seen in). A scene without
    parallax moves by one homography per frame pair, and the F fitted to it is degenerate (any F
    compatible with the homography fits, and extrapolates anywhere): there a track's excess is the
    lesser of that and its RMS transfer distance to those homographies over its bound (d = 2n).
    A scene whose parallax is within the noise floor but beyond its own noise
    (:func:`weak_parallax`: a few planes of a room seen from a distance, split apart by the
    clustering) takes the least of those and of its projective reconstruction's excess, where its
    tracks tie the frames together: a track any of the three explains is consistent (the
    reconstruction of a scene with weak parallax extrapolates to the rest of the scene's planes,
    where its homographies and F fits do not; alone it would also cut pieces of a scene it fits
    badly).
    """
    tied = 3 * median_span(visible[:, scene]) >= tracks.shape[0] - 1
    plane = plane_residuals(tracks, visible, scene, pairs)
    parallax = has_parallax(plane, scene, config)
    if tied and parallax:
        reconstructed = reconstruction_excess(tracks, visible, scene, config, generator)
        if reconstructed is not None:
            return reconstructed
    rms = epipolar_residuals(tracks, visible, scene, pairs)
    seen = pairs_seen(visible, pairs)
    excess = rms / _bound(rms[scene].nanmedian(), seen, seen, config)
    if parallax:
        return excess
    # no parallax: the scene's homographies are its motion, and its F fits are degenerate
    excess = torch.fmin(excess, plane / _bound(plane[scene].nanmedian(), 2 * seen, 2 * seen, config))
    if not (tied and weak_parallax(plane, rms, scene)):
        return excess
    # parallax beyond the scene's own noise: its reconstruction is one more way a static track is explained
    reconstructed = reconstruction_excess(tracks, visible, scene, config, generator)
    return excess if reconstructed is None else torch.fmin(excess, reconstructed)


def reconstruction_excess(tracks: Tensor, visible: Tensor, scene: Tensor, config: SegmentationConfig,
                          generator: torch.Generator) -> Tensor | None:
    """(N,) every track's reprojection RMS under the (N,) bool ``scene`` tracks' projective
    reconstruction over all frames (:func:`~torchsfm.moving.static_tracks.rigid_group`) over its
    bound (d = 2m - 3 for m frames; NaN where not judged), or None where the reconstruction
    fails (:func:`scene_excess`)."""
    group = rigid_group(tracks, visible, scene, fundamental_ransac=FundamentalConfig().ransac,
                        resection_ransac=MovingObjectsConfig().resection_ransac,  # the project's defaults
                        refinements=config.scene_refinements, threshold=config.scene_tolerance,
                        significance=config.scene_significance, generator=generator)
    if isinstance(group, str):
        return None
    rms = torch.where(group.rms.isfinite(), group.rms, torch.nan)
    terms = 2 * group.frames_seen.clamp_min(3)
    return rms / _bound(rms[scene].nanmedian(), terms - 3, terms, config)


def with_depth_order(excess: Tensor, tracks: Tensor, visible: Tensor, scene: Tensor, pairs: Tensor,
                     config: SegmentationConfig) -> Tensor:
    """(N,) :func:`scene_excess` ``excess`` raised, where a track lies beyond infinity under the
    (N,) bool ``scene`` tracks' pose (:func:`beyond_infinity`), to that distance over the bound
    noise at the tracker's floor (``config.scene_tolerance``) stays within for as many frame
    pairs; NaN kept. Only for a scene with parallax: without it the pose's translation is noise."""
    if not has_parallax(plane_residuals(tracks, visible, scene, pairs), scene, config):
        return excess
    behind = beyond_infinity(tracks, visible, scene, pairs) / _noise_bound(pairs_seen(visible, pairs), config)
    return torch.where(excess.isnan(), excess, torch.maximum(excess, behind))


def beyond_infinity(tracks: Tensor, visible: Tensor, scene: Tensor, pairs: Tensor) -> Tensor:
    """(N,) every track's RMS over the frame pairs it is seen in of how far (pixels) it lies
    beyond infinity under the (N,) bool ``scene`` tracks' relative pose — behind both cameras,
    which no static point can be (:func:`~torchsfm.geometry.essential.parallax_from_infinity`;
    0 where in front). The scene's F per pair (least-trimmed squares, as :func:`track_residuals`)
    becomes a pose through the prior K of a camera without calibration (focal length
    ``FOCAL_PRIOR`` × the larger side of the tracks' extent, principal point at its centre). The
    sign of a track's parallax hardly depends on it where the camera mostly translates, and more
    where it turns (measured with the true background as the scene, focal length 0.6, 1.2 and 2.0 ×
    the side: on KT3DMoSeg nearly the same tracks beyond 4 px at all three; on Hopkins155 at most
    3 background tracks of a sequence beyond 4 px at 1.2 ×, up to 13 at 0.6 × and 15 at 2.0 ×).
    The parallax counts as a distance of the track in both images together (÷ √2), the measure of
    the Sampson distance, so the same noise bound applies."""
    a, b = pairs[:, 0], pairs[:, 1]
    seen = visible[a] & visible[b]  # (P, N)
    x1, x2 = tracks[a], tracks[b]
    members = seen & scene
    F, residual, usable = _trimmed_pair_fits(x1, x2, members, members.to(tracks.dtype), "fundamental")
    inliers = members & (residual <= torch.where(members, residual, torch.nan).nanmedian(-1).values[:, None])
    extent = tracks[visible]
    low, high = extent.amin(0), extent.amax(0)
    K = intrinsics(FOCAL_PRIOR * float((high - low).max()), (low + high) / 2).to(tracks.dtype)
    n1, n2 = pixels_to_normalized(x1, K), pixels_to_normalized(x2, K)
    own = torch.nonzero(scene)[:, 0]  # the pose's vote over the scene's tracks only (depths for 4 poses × all pairs × all N: 215 MB on KITTI 06)
    R, t, _ = select_pose(*POSE_CANDIDATES["svd"](essential_from_fundamental(F, K, K)), n1[:, own], n2[:, own],
                          inliers[:, own].to(tracks.dtype))
    behind = (-K[0, 0] * parallax_from_infinity(R, t, n1, n2) / math.sqrt(2)).clamp_min(0)
    counted = seen & usable[:, None]
    return (torch.where(counted, behind.square(), 0.0).sum(0) / counted.sum(0).clamp_min(1)).sqrt()


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


def weak_parallax(plane: Tensor, epipolar: Tensor, members: Tensor) -> bool:
    """Whether the (N,) bool ``members`` tracks have parallax beyond their own noise: the median
    over them of their (N,) :func:`plane_residuals` beyond ``WEAK_PARALLAX_RATIO`` times that of
    their (N,) :func:`epipolar_residuals` (within the noise floor, :func:`has_parallax` says no)."""
    return float(plane[members].nanmedian()) > WEAK_PARALLAX_RATIO * float(epipolar[members].nanmedian())


def has_parallax(plane: Tensor, members: Tensor, config: SegmentationConfig) -> bool:
    """Whether the (N,) bool ``members`` tracks have parallax: the median over them of their
    (N,) :func:`plane_residuals` beyond the noise floor ``config.scene_tolerance``. Without it (a
    camera that only turns, a plane, a distant scene) their rigid motion is one homography per
    pair, and fixes no depth."""
    return float(plane[members].nanmedian()) > config.scene_tolerance


def pairs_seen(visible: Tensor, pairs: Tensor) -> Tensor:
    """(N,) how many of the (P, 2) frame pairs each track is seen in (at least 1): (F, N) visibility."""
    return (visible[pairs[:, 0]] & visible[pairs[:, 1]]).sum(0).clamp_min(1)


def _bound(sigma: Tensor, dof: Tensor, terms: Tensor, config: SegmentationConfig) -> Tensor:
    """:func:`rms_bound` of σ with the scene's significance and tolerance, per track."""
    return rms_bound(sigma.square(), dof, terms, config.scene_significance, config.scene_tolerance)


def _noise_bound(seen: Tensor, config: SegmentationConfig) -> Tensor:
    """(N,) the RMS that noise at the tracker's floor (``config.scene_tolerance``) stays within,
    per track, over the (N,) frame pairs it is seen in (:func:`_bound` with σ the floor)."""
    floor = torch.tensor(config.scene_tolerance, dtype=torch.float64, device=seen.device)
    return _bound(floor, seen, seen, config)


def settle_scene(tracks: Tensor, visible: Tensor, labels: Tensor, pieces: Tensor, affinity: Tensor,
                 clustered: Tensor, config: SegmentationConfig, generator: torch.Generator) -> Tensor:
    """Make the static scene (label 0) what its rigid motion explains: motions it explains join
    it, pieces of it that it does not explain are cut out.

    The preference clustering may merge a body into the scene when their epipolar geometry
    nearly agrees over the sampled frames (a car driving along the camera's direction), and may
    split a scene of several planes. Every track's residual under the scene's rigid motion is
    weighed against its noise bound (:func:`scene_excess`): a motion with at most half its
    tracks beyond it joins the scene, and so does, before anything is cut, a motion whose own
    rigid motion explains the scene (:func:`join_explaining`); a piece of the scene (:attr:`MotionSegmentation.pieces`)
    with more than half its tracks beyond it is cut. The scene without the cut pieces judges the
    motions and its pieces again, until it cuts nothing more: a fit over a scene that still holds
    a body's pieces is pulled towards them and explains some. Then the last fit's excess is raised
    by the depth order (:func:`with_depth_order`) and the cutting goes on until it cuts nothing
    more: only then, for a pose fitted together with a body it explains misplaces infinity
    (measured on a synthetic scene of two bodies: with 20 of a body's tracks among the scene's
    202, the check put 33 background tracks behind the cameras and cut a piece of 18). The cut
    pieces are merged into bodies by :func:`merge_clusters` over their own links and labelled
    after the other motions — those a rigid motion of their own explains, over the frames their
    tracks span, to within the tracker's noise (:func:`noise_explained`; measured on KT3DMoSeg, a 1 px bound on the median
    labelled whole groups of cars driving together outliers); the others are outliers (-1).
    Nothing is cut when fewer than 12 scene tracks would remain. When pieces were cut, the scene
    as it now stands judges every motion once more (:func:`join_explained`).

    Args:
        tracks: (F, N, 2) pixels; visible: (F, N) bool.
        labels: (N,) int64, 0 the scene, 1..k the other motions, -1 none.
        pieces: (N,) int64 piece of each clustered track; affinity: (n, n) over the
            ``clustered`` (n,) tracks.

    Returns:
        (N,) int64 labels, the motions renumbered 0..k' in their order.
    """
    pairs = frame_pairs(visible)
    cut = torch.zeros_like(labels, dtype=torch.bool)  # labelled 0 until made bodies, but out of the scene's fit
    depth_order = False  # judged once the residuals cut nothing more: a pose fitted with a body's pieces misplaces infinity
    excess = None  # fitted anew whenever the scene changes
    while True:  # each pass cuts a piece or ends
        scene = (labels == 0) & ~cut
        if excess is None:
            excess = scene_excess(tracks, visible, scene, pairs, config, generator)
            if depth_order:
                excess = with_depth_order(excess, tracks, visible, scene, pairs, config)
        labels = torch.where(cut, 0, join_explained(torch.where(cut, -1, labels), excess))
        if not bool(cut.any()) and not depth_order:  # before any cut: a motion whose own fit explains the scene joins it, and the scene is fitted anew
            joined = join_explaining(tracks, visible, labels, pairs, config, generator)
            if int(joined.max()) < int(labels.max()):
                labels, excess = joined, None
                continue
        scene = (labels == 0) & ~cut
        scene_pieces = pieces[scene].unique()
        inconsistent = torch.stack([excess[scene & (pieces == p)].nanmedian() > 1 for p in scene_pieces])
        more = scene & torch.isin(pieces, scene_pieces[inconsistent])
        if not bool(more.any()) or int((scene & ~more).sum()) < MIN_VECTORS:
            if depth_order:
                break
            depth_order = True  # the same fit, now also judging which side of infinity the tracks lie
            excess = with_depth_order(excess, tracks, visible, scene, pairs, config)
            continue
        cut |= more
        excess = None
    if not bool(cut.any()):
        return labels
    position = torch.nonzero(cut[clustered])[:, 0]
    _, piece_index = pieces[clustered[position]].unique(return_inverse=True)
    bodies = merge_clusters(affinity[position][:, position], piece_index, None, config)
    members = torch.zeros(int(bodies.max()) + 1, labels.numel(), dtype=torch.bool, device=labels.device)
    members[bodies, clustered[position]] = True
    rigid = noise_explained(tracks, visible, members, config)
    labels[clustered[position]] = torch.where(rigid[bodies], int(labels.max()) + rigid.cumsum(0)[bodies], -1)
    # the scene that judged the cut pieces held them: its last fit, without them, may explain one after all
    return join_explained(labels, excess)


def split_least_rigid(tracks: Tensor, visible: Tensor, labels: Tensor, pieces: Tensor, affinity: Tensor,
                      clustered: Tensor, config: SegmentationConfig, generator: torch.Generator) -> Tensor | None:
    """(N,) labels with one more motion: of the motions cut in two, the one whose cut explains
    its tracks best relative to the motion whole.

    Each motion with 2 × ``config.support`` clustered tracks is cut in two: its pieces merged
    down to two (:func:`merge_clusters`) or a direct spectral cut of its own links, whichever has
    the smaller normalized cut. The gain of a cut: the sum over the motion's tracks of their RMS
    Sampson distance to one F per frame pair fitted to the whole motion (:func:`track_residuals`)
    over the same with each part fitted on its own — two motions taken for one leave the
    smaller one's tracks far from the whole's fit; a rigid motion's parts fit hardly better.
    Known limit: the trimmed fit of a motion half of whose tracks lie on one plane is degenerate,
    and cutting it gains too (a synthetic background half on one wall: cut instead of two boxes
    merged). None when no motion can be cut.
    """
    count = int(labels.max()) + 1
    within = labels[clustered]
    wholes, seconds = [], []  # per cut: (N,) the motion, (N,) its part that becomes a new motion
    for motion in range(count):
        position = torch.nonzero(within == motion)[:, 0]
        if position.numel() < 2 * config.support:
            continue
        links = affinity[position][:, position]
        _, vectors = leading_eigenvectors(links, 2)
        candidates = [largest_first(spectral_partition(vectors, 2, config, generator))]
        _, piece_index = pieces[clustered[position]].unique(return_inverse=True)
        if int(piece_index.max()) > 0:
            candidates.append(merge_clusters(links, piece_index, 2, config))
        part = min(candidates, key=lambda partition: normalized_cut(links, partition))
        second = torch.zeros_like(labels, dtype=torch.bool)
        second[clustered[position[part == 1]]] = True
        wholes.append(labels == motion)
        seconds.append(second)
    if not wholes:
        return None
    whole, second = torch.stack(wholes), torch.stack(seconds)  # (M, N)
    first = whole & ~second
    M = whole.shape[0]
    rms, judged = track_residuals(tracks, visible, torch.cat([whole, first, second]), frame_pairs(visible))
    split = torch.where(second, rms[2 * M:], rms[M:2 * M])
    held = whole & judged[:M] & torch.where(second, judged[2 * M:], judged[M:2 * M])
    gain = torch.where(held, rms[:M], 0.0).sum(-1) / torch.where(held, split, 0.0).sum(-1).clamp_min(torch.finfo(rms.dtype).tiny)
    clusters = labels.clone()
    clusters[second[int(gain.argmax())]] = count
    return scene_first(tracks, visible, clusters)


def partition_residual(tracks: Tensor, visible: Tensor, labels: Tensor) -> float:
    """How well a partition's motions explain the tracks: the mean over the tracks of their RMS
    Sampson distance to one F per frame pair fitted to their motion (:func:`track_residuals`),
    the best of the motions for an unassigned track: (F, N, 2) tracks, (F, N) visibility, (N,)
    labels 0..k (-1 unassigned)."""
    members = labels[None] == torch.arange(int(labels.max()) + 1, device=labels.device)[:, None]
    rms, judged = track_residuals(tracks, visible, members, frame_pairs(visible))
    rms = torch.where(judged, rms, torch.inf)
    own = torch.where(labels >= 0, rms.gather(0, labels.clamp_min(0)[None])[0], rms.amin(0))
    return float(own[own.isfinite()].mean())


def noise_explained(tracks: Tensor, visible: Tensor, members: Tensor, config: SegmentationConfig) -> Tensor:
    """(C,) bool: which of C (C, N) track sets one rigid motion of their own explains — the
    median over a set's tracks of their RMS Sampson distance to one F per frame pair
    (:func:`track_residuals`; the pairs :func:`frame_pairs` of the set's own tracks: a body seen
    in a few frames of a video has no tracks at both ends of the sequence's pairs) over the bound that noise at the tracker's floor
    (``config.scene_tolerance`` px) stays within at ``config.scene_significance`` for as many
    pairs as the track is seen in (sqrt(χ²(d) / d) times the floor: 3.3× for one pair, 1.6× for
    14). False where the set is too small to fit."""
    verdicts = []
    for member in members:  # each set on the frame pairs its own tracks span (a short-lived body's tracks never span the sequence's)
        pairs = frame_pairs(visible[:, member])
        rms, judged = track_residuals(tracks, visible, member[None], pairs)
        seen = pairs_seen(visible, pairs)
        verdicts.append(torch.where(judged & member, rms / _noise_bound(seen, config), torch.nan).nanmedian(-1).values <= 1)
    return torch.cat(verdicts)


def join_explained(labels: Tensor, excess: Tensor) -> Tensor:
    """(N,) labels with every motion that the scene's rigid motion explains (median (N,)
    :func:`scene_excess` at most 1) joined to the scene (label 0), renumbered."""
    return joined_to_scene(labels, [motion for motion in range(1, int(labels.max()) + 1)
                                    if bool(excess[labels == motion].nanmedian() <= 1)])


def join_explaining(tracks: Tensor, visible: Tensor, labels: Tensor, pairs: Tensor, config: SegmentationConfig,
                    generator: torch.Generator) -> Tensor:
    """(N,) labels with every motion whose own rigid motion explains the scene (the median over
    the scene's tracks of their :func:`scene_excess` under the motion's fit at most 1) joined to
    the scene, renumbered: the converse of :func:`join_explained`. A scene fit pulled by the body
    tracks it still holds can fail to explain the rest of the background, which the clustering
    split off as a motion of its own, while that clean half's fit explains the scene.
    Only for a scene with parallax (:func:`has_parallax`, or :func:`weak_parallax`: beyond its
    own noise): a camera that only turns, a plane or a
    distant scene is explained by any motion that shares the camera's rotation (as points at
    infinity), so the test would say nothing. Motions of fewer than 12 tracks are not fitted."""
    scene = labels == 0
    plane = plane_residuals(tracks, visible, scene, pairs)
    if not has_parallax(plane, scene, config) and not weak_parallax(plane, epipolar_residuals(tracks, visible, scene, pairs), scene):
        return labels
    explaining = []
    for motion in range(1, int(labels.max()) + 1):
        own = labels == motion
        if int(own.sum()) >= MIN_VECTORS and bool(scene_excess(tracks, visible, own, pairs, config, generator)[scene].nanmedian() <= 1):
            explaining.append(motion)
    return joined_to_scene(labels, explaining)


def joined_to_scene(labels: Tensor, motions: list[int]) -> Tensor:
    """(N,) labels with the listed motions relabelled 0 (the scene) and the rest renumbered
    0..k' in their order (-1 kept); a new tensor."""
    joined = torch.tensor(motions, dtype=labels.dtype, device=labels.device)
    labels = torch.where(torch.isin(labels, joined), 0, labels)
    _, labels[labels >= 0] = labels[labels >= 0].unique(return_inverse=True)
    return labels


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


def sample_hypotheses(tracks: Tensor, visible: Tensor, count: int, frames_per: int, size: int,
                      config: SegmentationConfig, generator: torch.Generator,
                      guide: Tensor | None) -> tuple[Tensor, Tensor, Tensor]:
    """``count`` samples of ``size`` tracks, each seen in the same ``frames_per`` frames.

    tracks (F, N, 2), visible (F, N), guide None or (N, N) similarity -> frames (H, m) sorted,
    sample (H, size) track indices and usable (H,) bool (every sampled track seen in every chosen
    frame). The seed comes first; without a guide the others are among its ``config.neighbours``
    nearest tracks in the first frame for a share ``config.local_share`` of the samples and
    anywhere for the rest; with a guide they are drawn with probability proportional to their
    similarity to the seed (same-motion tracks spread over the whole body, so the model is fitted
    over its extent rather than a patch).
    """
    F, N, _ = tracks.shape
    H, m = count, min(frames_per, F)
    device = tracks.device
    rows = torch.arange(H, device=device)
    seeds = torch.randint(0, N, (H,), generator=generator, device=device)
    frames = torch.multinomial(visible[:, seeds].T.double(), m, generator=generator).sort(1).values  # (H, m)
    seen_in_all = visible[frames].all(1)  # (H, N)
    local = torch.rand(H, generator=generator, device=device) < config.local_share
    if guide is not None:
        weight = torch.where(seen_in_all, guide[seeds], 0.0) + 1e-9 * seen_in_all  # too few similar: uniform
        weight[rows, seeds] = 0.0
        drawn = draws_without_replacement(weight + 1e-30, size - 1, generator)
        sample = torch.cat([seeds[:, None], drawn], 1)
        return frames, sample, seen_in_all.gather(1, sample).all(1)
    key = torch.rand(H, N, generator=generator, dtype=tracks.dtype, device=device)
    start = tracks[frames[local, 0]]  # (h, N, 2) the first frames of the local samples
    key[local] = (start - start[torch.arange(start.shape[0], device=device), seeds[local]][:, None]).norm(dim=-1)
    key = torch.where(seen_in_all, key, torch.inf)
    key[rows, seeds] = -1.0  # the seed comes first
    pool = min(config.neighbours, N)
    nearest = key.topk(pool, dim=1, largest=False).indices  # (H, pool), seed first
    pick = torch.rand(H, pool - 1, generator=generator, device=device).argsort(1)[:, :size - 1]
    sample = torch.cat([seeds[:, None], nearest[:, 1:].gather(1, pick)], 1)
    usable = torch.isfinite(key.gather(1, sample)).all(1)
    return frames, sample, usable


def fundamental_residuals(tracks: Tensor, visible: Tensor, count: int, config: SegmentationConfig, generator: torch.Generator,
                          guide: Tensor | None = None) -> tuple[Tensor, Tensor]:
    """Residuals of every track to ``count`` sampled multi-frame F models.

    tracks (F, N, 2) float64, visible (F, N) -> residuals (H, N) px² (the largest squared Sampson
    distance over the hypothesis' frame pairs: squared, for only their order counts — the
    preferences are ranks) and defined (H, N) bool.
    """
    frames, sample, usable = sample_hypotheses(tracks, visible, count, config.sample_frames, SAMPLE_SIZE, config, generator, guide)

    def fit(x1: Tensor, x2: Tensor) -> Tensor:
        return eight_point_minimal(x1[:, None], x2[:, None], hartley_normalize(x1)[1], hartley_normalize(x2)[1])[:, 0]

    return worst_over_pairs(tracks, visible, frames, sample, usable, fit, sampson_to_each)


def worst_over_pairs(tracks: Tensor, visible: Tensor, frames: Tensor, sample: Tensor, usable: Tensor,
                     fit: Callable[[Tensor, Tensor], Tensor], distance: Callable[[Tensor, Tensor, Tensor], Tensor]
                     ) -> tuple[Tensor, Tensor]:
    """Two-view models of H samples over every pair of their m frames: ``fit`` (H, s, 2) x2 ->
    (H, 3, 3) models, ``distance`` (h models (h, 3, 3), the points (N, 2) of their first frame,
    each model's second frame's points (2, h, N), the coordinates apart) -> (h, N) (pixels, or
    any increasing function of them).
    Returns each track's largest distance over the pairs in which it is seen (H, N), and where
    that is defined (H, N): seen in a pair, a usable sample, a finite model, and not one of the
    sample's tracks. In blocks of hypotheses whose (h · P, N) table of distances fits
    ``CHUNK_ELEMENTS`` (P = m(m - 1)/2 pairs), the models of a block's hypotheses sharing a
    pair's first frame are scored together on its points (one product for all; a video has up
    to F²/2 frame pairs but F first frames), each into its own row of the table; the largest over
    a hypothesis' P rows is taken per block."""
    H, m = frames.shape
    N = tracks.shape[1]
    first, second = torch.triu_indices(m, m, 1, device=frames.device)
    a, b = frames[:, first], frames[:, second]  # (H, P) frame pairs of every hypothesis
    P = a.shape[1]
    models = torch.stack([fit(tracks[a[:, p, None], sample], tracks[b[:, p, None], sample]) for p in range(P)], 1).reshape(-1, 3, 3)
    coordinates = tracks.permute(2, 0, 1).contiguous()  # (2, F, N)
    worst = tracks.new_empty(H, N)
    block = max(1, CHUNK_ELEMENTS // (P * N))
    for start in range(0, H, block):
        part = slice(start * P, min(H, start + block) * P)  # row h * P + p: hypothesis h on its pair p
        starts, ends, block_models = a.reshape(-1)[part], b.reshape(-1)[part], models[part]
        per_pair = tracks.new_empty(starts.numel(), N)  # 0 where the track is not seen in the pair
        order = starts.argsort()
        firsts, counts = starts[order].unique_consecutive(return_counts=True)
        for i, rows in zip(firsts.tolist(), order.split(counts.tolist())):
            second = ends[rows]
            unseen = ~(visible[i] & visible[second])  # (h, N)
            per_pair[rows] = distance(block_models[rows], tracks[i], coordinates[:, second]).masked_fill_(unseen, 0.0)
        worst[start:start + block] = per_pair.view(-1, P, N).amax(1)  # residuals are >= 0 (or NaN)
    seen_in_a_pair = (visible[a] & visible[b]).any(1)  # (H, N)
    defined = seen_in_a_pair & usable[:, None] & torch.isfinite(worst)
    return worst, defined.scatter(1, sample, False)


def affine_residuals(tracks: Tensor, visible: Tensor, count: int, config: SegmentationConfig, generator: torch.Generator,
                     guide: Tensor | None = None) -> tuple[Tensor, Tensor]:
    """Residuals of every track to ``count`` sampled affine-camera motions over ``config.affine_frames``
    frames: 4 tracks span the 3-dimensional affine subspace of trajectories of their rigid
    motion (Tomasi & Kanade); a track's residual is its squared distance to it per frame (px²:
    only the order counts). Defined where the track is seen in all the frames. -> (H, N), (H, N)
    bool."""
    frames, sample, usable = sample_hypotheses(tracks, visible, count, config.affine_frames, 4, config, generator, guide)
    H, m = frames.shape
    F, N, _ = tracks.shape
    centred = torch.where(visible[..., None], tracks - tracks[visible].mean(0), 0.0)  # smaller terms to cancel
    flat = centred.permute(1, 0, 2).reshape(N, 2 * F)  # every track's trajectory: x, y of frame 0, of frame 1, ...
    columns = (2 * frames[..., None] + torch.arange(2, device=tracks.device)).reshape(H, 2 * m)
    chosen = flat[sample[..., None], columns[:, None]]  # (H, 4, 2m) the sample's trajectories
    origin = chosen[:, 0]
    basis, triangle = torch.linalg.qr((chosen[:, 1:] - origin[:, None]).transpose(1, 2))  # (H, 2m, 3)
    extent = triangle.diagonal(dim1=1, dim2=2).abs().amin(1)
    rows = torch.arange(H, device=tracks.device)[:, None]
    select = flat.new_zeros(H, 2 * F).index_put_((rows, columns), flat.new_ones(()))
    origin_full = flat.new_zeros(H, 2 * F).index_put_((rows, columns), origin)
    basis_full = flat.new_zeros(H, 2 * F, 3).index_put_((rows, columns), basis)
    origin_norm = origin.square().sum(1, keepdim=True)
    origin_in_basis = (basis * origin[..., None]).sum(1)  # (H, 3)
    residual = tracks.new_empty(H, N)
    trajectories, squares = flat.T, flat.square().T  # (2F, N)
    chunk = max(1, CHUNK_ELEMENTS // (3 * N))  # hypotheses at a time: (chunk, 3, N) projections
    for first in range(0, H, chunk):  # distance² to the span: |t - o|² - |Bᵀ(t - o)|², B orthonormal
        part = slice(first, first + chunk)
        offset_norm = select[part] @ squares - 2 * origin_full[part] @ trajectories + origin_norm[part]
        axes = basis_full[part].transpose(1, 2)  # (h, 3, 2F): one product for all hypotheses
        projection = (axes.reshape(-1, 2 * F) @ trajectories).view(-1, 3, N).sub_(origin_in_basis[part, :, None])
        residual[part] = (offset_norm - projection.square_().sum(1)).clamp_min(0) / m
    seen = visible[frames].all(1)
    defined = seen & (usable & (extent > 1.0))[:, None]
    return residual, defined.scatter(1, sample, False)


def preference_similarity(tracks: Tensor, visible: Tensor, config: SegmentationConfig, generator: torch.Generator,
                          guide: Tensor | None) -> Tensor:
    """(N, N) Tanimoto similarity of the (F, N, 2) tracks' preferences over one round of
    hypotheses, shared equally by the configured kinds of model (sampled near the ``guide``
    similarity's strongest links from the round before, if given). A function of its own so
    that the round's residual tables are freed before the next round's are made."""
    kinds = config.kinds_for(tracks.shape[0])
    fits = [MODELS[name](tracks, visible, config.hypotheses // len(kinds), config, generator, guide) for name in kinds]
    preferences = [ordered_preferences(residuals, defined, config) for residuals, defined in fits]
    del fits
    return tanimoto_similarity(torch.cat([p for p, _ in preferences], 1), torch.cat([d for _, d in preferences], 1), tracks.dtype)


def ordered_preferences(residuals: Tensor, defined: Tensor, config: SegmentationConfig) -> tuple[Tensor, Tensor]:
    """(H, N) residuals -> (N, H) bool preferences, each track preferring the ``preference_share``
    of its defined hypotheses with the smallest residuals (ordered-residual kernel), and the
    (N, H) bool mask of defined entries."""
    masked = torch.where(defined, residuals, torch.inf).T.contiguous()  # (N, H)
    defined = defined.T
    keep = (defined.sum(1) * config.preference_share).ceil().long().clamp_min(1)  # (N,)
    smallest = masked.topk(int(keep.max()), dim=1, largest=False).values  # (N, k) ascending
    largest_kept = smallest.gather(1, keep[:, None] - 1)  # the keep-th smallest of each track
    return (masked <= largest_kept) & defined, defined


def explained_tracks(similarity: Tensor, config: SegmentationConfig) -> Tensor:
    """(N, N) preference similarity -> (N,) bool: tracks whose ``config.support`` most similar
    tracks are, on average, more than ``config.outlier_factor`` times as similar as two tracks
    with unrelated preferences would be by chance — q / (2 - q) for preference share q, the
    expected Tanimoto similarity of two random subsets of that share. A gross outlier (a
    tracking error) fits no motion, so its preferences are unrelated to every other track's."""
    share = config.preference_share
    chance = share / (2.0 - share)
    support = similarity.topk(min(config.support, similarity.shape[0] - 1), dim=1).values.mean(1)
    return support > config.outlier_factor * chance


def tanimoto_similarity(preference: Tensor, mask: Tensor, dtype: torch.dtype) -> Tensor:
    """(N, H) bool preferences and defined mask -> (N, N) Tanimoto similarity (``dtype``) over
    the hypotheses defined for both tracks (zero diagonal)."""
    preference, mask = binary_operand(preference), binary_operand(mask)  # each converted once
    inner = binary_products(preference, preference)
    own = binary_products(preference, mask)  # |p_i| restricted to the hypotheses defined for j
    denominator = (own + own.T).sub_(inner)  # >= inner (p_j lies within j's defined mask): 0 only where inner is
    del own  # (N, N) tables: at 3000 tracks each is 36 MB, so they are made in place where they can be
    return inner.div_(denominator.clamp_min_(1.0)).to(dtype).fill_diagonal_(0.0)


def binary_operand(x: Tensor) -> Tensor:
    """A 0/1 matrix in the dtype :func:`binary_products` multiplies: int8 on the CPU (int32 sums,
    ``torch._int_mm``: 5x faster than float32 on a CPU with VNNI), float32 elsewhere."""
    return x.to(torch.int8 if x.device.type == "cpu" else torch.float32)


def binary_products(a: Tensor, b: Tensor) -> Tensor:
    """(n, h) and (m, h) 0/1 matrices from :func:`binary_operand` -> (n, m) float32 counts
    a @ b.T, exact (up to 2^24)."""
    if a.dtype == torch.int8:
        return torch._int_mm(a, b.T).float()
    return a @ b.T


def strongest_links(similarity: Tensor, links: int) -> Tensor:
    """(N, N) similarity -> symmetric affinity keeping each row's ``links`` strongest entries."""
    k = min(links, similarity.shape[0] - 1)
    strongest = similarity.topk(k, dim=1).indices
    sparse = torch.zeros_like(similarity).scatter_(1, strongest, similarity.gather(1, strongest))
    return torch.maximum(sparse, sparse.T)


def leading_eigenvectors(affinity: Tensor, count: int) -> tuple[Tensor, Tensor]:
    """The ``count`` largest eigenvalues (descending) and eigenvectors (N, count) of the
    normalized affinity D^-1/2 A D^-1/2.

    From ``SPARSE_EIGEN_TRACKS`` tracks on, by LOBPCG on the sparse matrix (each row keeps about
    2 × ``links`` entries; a fixed-seed start, so the result is reproducible), kept where every
    pair's residual ‖M v − λ v‖ is at most ``EIGEN_RESIDUAL`` (M's norm is at most 1), else by the
    dense ``eigh``. On a 3000-track video's affinity both give the eigenvalues to 1e-14 and the
    subspace to 1e-13 (residuals near 1e-8), in 0.7 s instead of 3.4 s."""
    degree = affinity.sum(1).clamp_min(torch.finfo(affinity.dtype).tiny)
    scale = degree.rsqrt()
    normalized = affinity * scale[:, None] * scale[None]
    N = normalized.shape[0]
    count = min(count, N)
    if N >= SPARSE_EIGEN_TRACKS and 3 * count <= N:
        start = torch.randn(N, count, generator=torch.Generator(normalized.device).manual_seed(0), dtype=normalized.dtype,
                            device=normalized.device)
        values, vectors = torch.lobpcg(normalized.to_sparse(), k=count, X=start, largest=True)
        values, order = values.sort(descending=True)
        vectors = vectors[:, order]
        if float((normalized @ vectors - vectors * values).norm(dim=0).max()) <= EIGEN_RESIDUAL:
            return values, vectors
    values, vectors = torch.linalg.eigh(normalized)
    return values.flip(0)[:count], vectors.flip(1)[:, :count]


def kmeans(points: Tensor, k: int, restarts: int, iterations: int, generator: torch.Generator) -> Tensor:
    """Lloyd's k-means on (N, D) points with ``restarts`` random initializations run as one
    batch, for ``iterations`` steps or until every restart's labels repeat (a fixed point: the
    centres, and so every later step, would repeat too); the labels (N,) of the restart with the
    smallest within-cluster sum of squares."""
    N = points.shape[0]
    start = torch.rand(restarts, N, generator=generator, device=points.device).argsort(1)[:, :k]
    centres = points[start]  # (R, k, D)
    previous = None
    for _ in range(iterations):
        labels = torch.cdist(points[None].expand(restarts, -1, -1), centres).argmin(2)  # (R, N)
        if previous is not None and torch.equal(labels, previous):
            break
        previous = labels
        one_hot = torch.nn.functional.one_hot(labels, k).to(points.dtype)  # (R, N, k)
        counts = one_hot.sum(1)  # (R, k)
        sums = one_hot.transpose(1, 2) @ points  # (R, k, D)
        centres = torch.where(counts[..., None] > 0, sums / counts[..., None].clamp_min(1), centres)
    labels = torch.cdist(points[None].expand(restarts, -1, -1), centres).argmin(2)
    cost = (points[None] - centres.gather(1, labels[..., None].expand(-1, -1, points.shape[1]))).square().sum((1, 2))
    return labels[int(cost.argmin())]


def homography_residuals(tracks: Tensor, visible: Tensor, count: int, config: SegmentationConfig, generator: torch.Generator,
                         guide: Tensor | None = None) -> tuple[Tensor, Tensor]:
    """Residuals of every track to ``count`` sampled plane motions: 4 tracks over ``config.sample_frames``
    frames, one homography per frame pair (4-point solve in Hartley-normalized coordinates); a
    track's residual is its largest squared transfer distance (px²: only the order counts) over the
    pairs in which it is seen.
    A plane is a local model: it separates a body from the scene around it even where their
    epipolar geometry agrees (a car driving along the camera's direction). -> (H, N), (H, N) bool."""
    frames, sample, usable = sample_hypotheses(tracks, visible, count, config.sample_frames, 4, config, generator, guide)
    return worst_over_pairs(tracks, visible, frames, sample, usable, four_point_homography, transfer_to_each)


def sampson_to_each(F: Tensor, x1: Tensor, x2: Tensor) -> Tensor:
    """Squared Sampson distances (h, N) of h fundamental matrices F (h, 3, 3), each between the
    points x1 (N, 2) and its own second points x2 (2, h, N) (the coordinates apart): the
    epipolar lines F x1 as one (3h, 3) x (3, N) product, the rest element by element."""
    lines = images_by_each(F, x1)  # (3, h, N)
    u, v = x2
    algebraic = lines[0] * u
    algebraic += lines[1] * v
    algebraic += lines[2]
    entry = F[..., None]  # (h, 3, 3, 1): one entry of each model against its row of points
    back_u = entry[:, 0, 0] * u  # (Fᵀ x2) rows 0 and 1
    back_u += entry[:, 1, 0] * v
    back_u += entry[:, 2, 0]
    back_v = entry[:, 0, 1] * u
    back_v += entry[:, 1, 1] * v
    back_v += entry[:, 2, 1]
    gradient = lines[0].square()
    gradient += lines[1].square()
    gradient += back_u.square_()
    gradient += back_v.square_()
    return algebraic.square_().div_(gradient.clamp_min_(1e-30))


def transfer_to_each(G: Tensor, x1: Tensor, x2: Tensor) -> Tensor:
    """Squared transfer distances (h, N) of h homographies G (h, 3, 3), each mapping the points
    x1 (N, 2) onto its own second points x2 (2, h, N) (the coordinates apart); +inf where a
    point maps to infinity."""
    mapped = images_by_each(G, x1)  # (3, h, N)
    w = mapped[2]
    error = (mapped[0] / w - x2[0]).square_()
    error += (mapped[1] / w - x2[1]).square_()
    return torch.where(w.abs() > 1e-12, error, torch.inf)


def images_by_each(M: Tensor, x: Tensor) -> Tensor:
    """Homogeneous images (3, h, N) of the points x (N, 2) under each of h matrices M (h, 3, 3),
    as one (3h, 3) x (3, N) product: entry (k, r, n) is row k of M_r applied to x_n."""
    h = M.shape[0]
    return (M.transpose(0, 1).reshape(3 * h, 3) @ to_homogeneous(x).T).view(3, h, -1)


def four_point_homography(x1: Tensor, x2: Tensor) -> Tensor:
    """(H, 4, 2) correspondences -> (H, 3, 3) homographies x2 ~ H x1 (h33 = 1 in normalized
    coordinates; NaN for a degenerate sample)."""
    n1, T1 = hartley_normalize(x1)
    n2, T2 = hartley_normalize(x2)
    x, y, u, v = n1[..., 0], n1[..., 1], n2[..., 0], n2[..., 1]
    one, zero = torch.ones_like(x), torch.zeros_like(x)
    rows_u = torch.stack([x, y, one, zero, zero, zero, -u * x, -u * y], -1)
    rows_v = torch.stack([zero, zero, zero, x, y, one, -v * x, -v * y], -1)
    h, info = torch.linalg.solve_ex(torch.cat([rows_u, rows_v], -2), torch.cat([u, v], -1)[..., None])
    G = torch.cat([h[..., 0], torch.ones_like(h[..., :1, 0])], -1).reshape(-1, 3, 3)
    G = torch.where((info == 0)[:, None, None], G, torch.nan)
    return torch.linalg.inv(T2) @ G @ T1


MODELS = {"fundamental": fundamental_residuals, "affine": affine_residuals, "homography": homography_residuals}


def merge_clusters(affinity: Tensor, labels: Tensor, count: int | None, config: SegmentationConfig) -> Tensor:
    """Merge the clusters of an over-segmentation (N,) labels 0..K-1 down to ``count`` clusters.

    Each step joins the two clusters most strongly linked relative to the smaller one's volume,
    cut(A, B) / min(vol(A), vol(B)): the pieces of one motion are linked along their borders,
    distinct motions hardly at all. Without ``count`` the merges run down to one cluster and the
    number kept is the one before the largest relative drop of that link,
    (s_c + floor) / (s_(c-1) + floor) over c = 2..``config.max_motions`` (s_c: the link of the
    merge that leaves c clusters, ``config.link_floor`` the link counted as none); one cluster
    if no drop reaches ``config.min_link_drop``. Returns labels 0..C-1, most tracks first.
    """
    K = int(labels.max()) + 1
    one_hot = torch.nn.functional.one_hot(labels, K).to(affinity.dtype)  # (N, K)
    links = one_hot.T @ affinity @ one_hot  # (K, K)
    alive = torch.bincount(labels, minlength=K) > 0
    tiny = torch.finfo(links.dtype).tiny
    merges: list[tuple[int, int, float]] = []
    while int(alive.sum()) > 1:
        volume = links.sum(1)
        score = links / torch.minimum(volume[:, None], volume[None]).clamp_min(tiny)
        score = torch.where(alive[:, None] & alive[None], score, -1.0).fill_diagonal_(-1.0)
        best = int(score.argmax())
        a, b = divmod(best, K)
        merges.append((a, b, float(score.view(-1)[best])))
        links[a] += links[b]
        links[:, a] += links[:, b]
        links[b] = 0
        links[:, b] = 0
        alive[b] = False
    start = len(merges) + 1  # clusters before any merge
    if count is None:
        link = {start - 1 - i: merge[2] for i, merge in enumerate(merges)}  # clusters left -> link
        drops = {c: (link[c] + config.link_floor) / (link[c - 1] + config.link_floor)
                 for c in range(2, min(config.max_motions, start - 1) + 1)}
        count = max(drops, key=drops.get) if drops and max(drops.values()) >= config.min_link_drop else 1
    groups = torch.arange(K, device=labels.device)
    for a, b, _ in merges[:max(start - count, 0)]:
        groups[groups == b] = a
    merged = groups[labels]
    return largest_first(merged)


def largest_first(labels: Tensor) -> Tensor:
    """(N,) labels >= 0 renumbered 0..C-1 by decreasing number of tracks."""
    survivors, sizes = labels.unique(return_counts=True)
    survivors = survivors[sizes.argsort(descending=True)]
    renumber = torch.full((int(labels.max()) + 1,), -1, dtype=torch.long, device=labels.device)
    renumber[survivors] = torch.arange(survivors.numel(), device=labels.device)
    return renumber[labels]


def spectral_partition(vectors: Tensor, count: int, config: SegmentationConfig, generator: torch.Generator) -> Tensor:
    """(N,) labels 0..count-1: k-means (``config.restarts`` restarts) of the rows of the
    ``count`` leading (N, >= count) eigenvectors of the normalized affinity, each row scaled to
    unit length (Ng, Jordan & Weiss 2001)."""
    embedding = vectors[:, :count]
    embedding = embedding / embedding.norm(dim=1, keepdim=True).clamp_min(torch.finfo(embedding.dtype).tiny)
    return kmeans(embedding, count, config.restarts, config.kmeans_iterations, generator)


def normalized_cut(affinity: Tensor, labels: Tensor) -> float:
    """Shi & Malik's normalized cut of a partition, sum over its clusters of cut(c, rest) /
    vol(c): (n, n) affinity, (n,) labels 0..C-1 (every label used)."""
    one_hot = torch.nn.functional.one_hot(labels).to(affinity.dtype)  # (n, C)
    links = one_hot.T @ affinity @ one_hot  # (C, C)
    volume = links.sum(1)
    return float(((volume - links.diagonal()) / volume.clamp_min(torch.finfo(volume.dtype).tiny)).sum())


def grid_coverage(tracks: Tensor, visible: Tensor, labels: Tensor, count: int) -> Tensor:
    """(count,) cells of a COVERAGE_GRID² grid over the tracks' bounding box that each label's
    visible positions touch over all frames."""
    points = tracks[visible]
    low, high = points.amin(0), points.amax(0)
    cell = ((tracks - low) / (high - low).clamp_min(1e-9) * COVERAGE_GRID).long().clamp(0, COVERAGE_GRID - 1)
    cell_index = cell[..., 0] * COVERAGE_GRID + cell[..., 1]  # (F, N)
    seen = visible & (labels >= 0)
    occupied = torch.zeros(count, COVERAGE_GRID ** 2, dtype=torch.bool, device=tracks.device)
    occupied[labels[None].expand_as(cell_index)[seen], cell_index[seen]] = True
    return occupied.sum(1)


def median_span(visible: Tensor) -> int:
    """The median over the tracks seen at least twice of their span, last frame − first frame
    ((F, N) visibility; 0 if none)."""
    frame = torch.arange(visible.shape[0], device=visible.device)[:, None]
    first = torch.where(visible, frame, visible.shape[0]).amin(0)
    last = torch.where(visible, frame, -1).amax(0)
    spans = (last - first)[visible.sum(0) >= 2]
    return int(spans.median()) if spans.numel() else 0


def frame_pairs(visible: Tensor, count: int | None = None) -> Tensor:
    """(P, 2) frame pairs (f, f + gap) for (F, N) visibility: gap = a third of the sequence, at
    most the median span (last frame − first frame) of the tracks seen twice, at least 1 — wide
    enough for parallax, short enough that the tracks of a video are seen at both ends; the
    first frames spread evenly, ``count`` of them (default: every possible one)."""
    F = visible.shape[0]
    gap = max(1, min((F - 1) // 3, median_span(visible)))
    starts = torch.linspace(0, F - 1 - gap, min(count or F, F - gap), device=visible.device).round().long().unique()
    return torch.stack([starts, starts + gap], 1)


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
    blocks = [_trimmed_pair_fits(x1[:, k:k + step], x2[:, k:k + step], seen[:, k:k + step], weights[:, k:k + step], model)[1:]
              for k in range(0, P, step)]
    residual, usable = (torch.cat(parts, 1) for parts in zip(*blocks))
    valid = both & usable[..., None]
    squares = torch.where(valid, residual.square(), 0.0).sum(1)
    return (squares / valid.sum(1).clamp_min(1)).sqrt(), valid.any(1)


def _trimmed_pair_fits(x1: Tensor, x2: Tensor, seen: Tensor, weights: Tensor, model: str) -> tuple[Tensor, Tensor, Tensor]:
    """The least-trimmed-squares fits of :func:`track_residuals` for (*, p) set-and-pair problems:
    (*, p, N, 2) positions, (*, p, N) bool seen and starting weights -> the last fits (*, p, 3, 3),
    every track's (*, p, N) distance to its problem's last fit, and (*, p) bool where a fit stood
    on ``SAMPLE_SIZE`` tracks throughout."""
    fit, distance = PAIR_MODELS[model]
    usable = seen.sum(-1) >= SAMPLE_SIZE  # (*, p)
    for _ in range(REFITS + 1):
        models = fit(x1, x2, torch.where(usable[..., None], weights, 1.0))
        residual = distance(models, x1, x2)  # (*, p, N)
        half = torch.where(seen, residual, torch.nan).nanmedian(-1).values  # (*, p)
        weights = (seen & (residual <= half[..., None])).to(x1.dtype)
        usable &= weights.sum(-1) >= SAMPLE_SIZE
    return models, residual, usable


def ransac_inliers(x1: Tensor, x2: Tensor, seen: Tensor, generator: torch.Generator) -> Tensor:
    """(C, P, N) bool: the inliers of one RANSAC fundamental matrix (the project's defaults) per
    track set and frame pair, among the ``seen`` (C, P, N) tracks of (C, P, N, 2) positions x1,
    x2; all ``seen`` where RANSAC finds none."""
    C, P, N = seen.shape
    data = torch.cat([x1, x2], -1).reshape(C * P, N, 4)
    valid = seen.reshape(C * P, N)
    found = ransac(FundamentalModel(data, valid), data, FundamentalConfig().ransac, valid=valid, generator=generator)
    return torch.where(found.success[:, None], found.inlier_mask, valid).reshape(C, P, N)


PAIR_MODELS = {
    "fundamental": (eight_point, lambda F, x1, x2: sampson_error(F, x1, x2).sqrt()),
    "homography": (homography_dlt, lambda G, x1, x2: transfer_error(G, x1, x2).sqrt()),
}


def motion_residuals(tracks: Tensor, visible: Tensor, members: Tensor, pairs: Tensor,
                     generator: torch.Generator | None = None) -> Tensor:
    """How well one rigid motion explains each of C track sets: (C,) median over each set's
    tracks of their RMS Sampson distance (:func:`track_residuals`, from RANSAC's inliers given a
    ``generator``); NaN where a set has fewer than 8 tracks in every pair."""
    rms, judged = track_residuals(tracks, visible, members, pairs, generator=generator)
    return torch.where(judged & members, rms, torch.nan).nanmedian(-1).values