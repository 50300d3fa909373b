"""The N-view pipeline as composable stages.

Every stage is an ``nn.Module`` whose ``forward`` takes the :class:`ViewSet` state and returns it
with its own fields filled; :class:`Pipeline` runs a sequence of them (``nn.Sequential``-like:
index it, slice it for a prefix, replace or insert a stage) and times each. A configurable
stage holds the config sections it reads and no others (:class:`ConfiguredStage`).

    pipeline = default_pipeline(config)       # DetectCorners, MatchPairs, VerifyPairs,
                                              # SelfCalibrate, BuildTracks, RejectMovingObjects,
                                              # MapIncrementally, RematchUnregistered,
                                              # BridgeWithSift
    state = pipeline[:3](ViewSet.of(images, K))   # verified pairs only
    pipeline[1] = MyMatcher()                 # any module: ViewSet -> ViewSet
    pipeline[2] = VerifyPairs(fundamental=FundamentalConfig(minimal_solver="seven_point"))
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from functools import partial

import torch
from torch import Tensor

from torchsfm.camera import FOCAL_PRIOR, undistort_points
from torchsfm.config import Config
from torchsfm.errors import InputError
from torchsfm.images import check_image, check_mask, is_grey_bytes, one_camera, sizes_named, to_grey_bytes
from torchsfm.moving.imor import MovingObjectRejection
from torchsfm.reconstruction import Reconstruction
from torchsfm.robust.samplers import side_generator
from torchsfm.sfm.mapping import map_incrementally
from torchsfm.pipeline import ConfiguredStage, Pipeline, Progress
from torchsfm.sfm.pairs import bridge_pairs, coarse_features, group_root, turned_homographies
from torchsfm.sfm.sift import DetectSiftFeatures, MatchSiftFeatures, sift_homographies
from torchsfm.sfm.tracks import Tracks, build_tracks, chained_matches
from torchsfm.sfm.view_pairs import (PairMatches, centred_intrinsics, detect, epipolar_matches, guided_matches, putative_matches,
                                     reject_moving_tracks, self_calibrate, verify_pairs)



@dataclass
class ViewSet:
    """The state the N-view stages pass along (each fills its own fields).

    Fields:
        images: V decoded images (3 or 1, H_v, W_v) (one size where K is estimated).
        colours: per view, where its image holds only the grey of a colour file (to bound
            memory), a reduced colour copy the points take their colours from; else None.
        K: (V, 3, 3) intrinsics (replaced by :class:`SelfCalibrate` when ``estimate_focal``).
        distortion: (V, 2) radial coefficients.
        names: view names.
        estimate_focal: K is a placeholder to be estimated; exif_focal: the focal length (px)
            every image's EXIF records, if they agree (the estimate's start, refined later).
        generator: the random source of every RANSAC; report: progress messages.
        masks: per view (H_v, W_v) bool, where features may be detected (None: everywhere), or
            None for no masks at all.
        greys: V (1, H_v, W_v) uint8 grey images; raw: per view (K_v, 2) detected corners; corners:
            the same undistorted; descriptors: per view (K_v, D) (``pairs.matcher`` ``sift``);
            putative: matched corner indices (index1, index2) per view pair; homographies: each
            matched pair's coarse homography (or None); pairs: verified matches;
            tracks; rejections, rejected_per_view: the moving-object decision; all_tracks,
            track_labels: with ``moving_objects.reconstruct_objects``, the tracks before the
            decision and each one's rigid-motion label (T,) (0 the static scene, 1..k the moving
            bodies, -1 none); reconstruction: the result; timings: seconds per stage.
    """

    images: list[Tensor]
    K: Tensor
    distortion: Tensor
    names: list[str]
    estimate_focal: bool = False
    exif_focal: float | None = None
    generator: torch.Generator = field(default_factory=lambda: torch.Generator().manual_seed(0))
    report: Progress = field(default=lambda message: None)
    colours: list[Tensor | None] | None = None
    masks: list[Tensor | None] | None = None
    greys: list[Tensor] | None = None
    raw: list[Tensor] | None = None
    corners: list[Tensor] | None = None
    putative: dict[tuple[int, int], tuple[Tensor, Tensor]] | None = None
    homographies: dict[tuple[int, int], Tensor | None] = field(default_factory=dict)
    pairs: dict[tuple[int, int], PairMatches] | None = None
    tracks: Tracks | None = None
    rejections: dict[tuple[int, int, int], MovingObjectRejection] = field(default_factory=dict)
    rejected_per_view: list[int] = field(default_factory=list)
    descriptors: list[Tensor] | None = None
    all_tracks: Tracks | None = None
    track_labels: Tensor | None = None
    reconstruction: Reconstruction | None = None
    timings: dict[str, float] = field(default_factory=dict)

    @classmethod
    def of(cls, images: list[Tensor], K: Tensor, *, distortion: Tensor | None = None, names: list[str] | None = None,
           generator: torch.Generator | None = None, progress: Progress | None = None,
           estimate_focal: bool = False, exif_focal: float | None = None, colours: list[Tensor | None] | None = None,
           masks: list[Tensor | None] | None = None) -> ViewSet:
        """A state for decoded images with K (3, 3) or (V, 3, 3). Images of different sizes (a
        photo set with portrait and landscape shots, several cameras) need their K: a focal
        length is estimated (``estimate_focal``) for one camera, with one image size.
        ``masks``: per view an (H_v, W_v) mask of where features may be detected (nonzero) or
        None (everywhere)."""
        V = len(images)
        for v, image in enumerate(images):
            check_image(image, f"image {v}")
        if masks is not None:
            if len(masks) != V:
                raise InputError(f"{len(masks)} masks for {V} images: give one per image (None for none)")
            masks = [None if mask is None else check_mask(mask, image, f"mask {v}") for v, (mask, image) in enumerate(zip(masks, images))]
        if estimate_focal and not one_camera(images):
            raise InputError(f"images of different sizes ({sizes_named(images)}) need their intrinsics K (or a focal "
                             f"length in every file's EXIF): without K one camera is assumed, with one image size (some views may be "
                             f"turned to portrait)")
        K = K.double().expand(V, 3, 3)
        distortion = K.new_zeros(V, 2) if distortion is None else distortion.double().expand(V, 2)
        return cls(images=list(images), K=K, distortion=distortion, names=names or [f"view{v}" for v in range(V)],
                   estimate_focal=estimate_focal, exif_focal=exif_focal, colours=colours, masks=masks,
                   generator=generator or torch.Generator().manual_seed(0),
                   report=progress or (lambda message: None))

    def focal_lengths(self) -> Tensor | None:
        """(V,) each view's focal length in pixels (the mean of fx and fy), None while K is a
        placeholder to be estimated."""
        return None if self.estimate_focal else self.K[:, [0, 1], [0, 1]].mean(-1)


class DetectCorners(ConfiguredStage):
    """Harris corners of every view (batched), undistorted: fills ``greys``, ``raw``, ``corners``."""

    SECTIONS = ("harris",)

    def forward(self, state: ViewSet) -> ViewSet:
        state.greys = [to_grey_bytes(image) for image in state.images]
        for v, image in enumerate(state.images):  # a grey image becomes a view of its grey: one copy in memory, not two
            if is_grey_bytes(image):
                state.images[v] = state.greys[v].expand_as(image)
        state.report(f"corners of {len(state.images)} views")
        state.raw = detect(state.greys, self.config.harris, state.masks)
        state.corners = [undistort_points(raw.double(), state.K[v], state.distortion[v]) for v, raw in enumerate(state.raw)]
        return state


class MatchPairs(ConfiguredStage):
    """Coarse matching of every view pair, pair selection and guided NCC + strength-measure
    matches of the chosen pairs (with moving bodies to reconstruct, in the plain disc too): fills
    ``putative`` and ``homographies``."""

    SECTIONS = ("pairs", "matching", "reconstruction", "moving_objects")

    def forward(self, state: ViewSet) -> ViewSet:
        objects = self.config.moving_objects
        state.putative, state.homographies = putative_matches(state.greys, state.raw, self.config, state.generator, state.report,
                                                              other_motions=objects.enabled and objects.reconstruct_objects,
                                                              focal=state.focal_lengths(), masks=state.masks)
        return state


class VerifyPairs(ConfiguredStage):
    """Robust F and the homography test of every matched pair (with moving bodies to reconstruct,
    a second motion's matches too): fills ``pairs``."""

    SECTIONS = ("fundamental", "lm", "reconstruction", "moving_objects")

    def forward(self, state: ViewSet) -> ViewSet:
        objects = self.config.moving_objects
        state.pairs = verify_pairs(state.putative, state.corners, self.config, state.generator, state.report,
                                   other_motions=objects.enabled and objects.reconstruct_objects)
        return state


class SelfCalibrate(ConfiguredStage):
    """Without K: the focal length recorded in the images' EXIF (``exif_focal``) where they have
    one, else estimated from the verified pairs' F; the principal point at the image centre."""

    SECTIONS = ("reconstruction",)

    def forward(self, state: ViewSet) -> ViewSet:
        if not state.estimate_focal:
            return state
        sizes = [tuple(image.shape[-2:]) for image in state.images]
        if state.exif_focal is not None:
            K = centred_intrinsics([state.exif_focal] * len(sizes), sizes)
            state.report(f"focal length from EXIF: {state.exif_focal:.1f} px")
        else:
            K, determined = self_calibrate(state.pairs, sizes, self.config)
            state.report(f"focal length estimated from {len(state.pairs)} verified pairs: {float(K[0, 0, 0]):.1f} px" if determined else
                         f"the {len(state.pairs)} verified pairs do not determine the focal length (a camera moving without "
                         f"turning): the prior {float(K[0, 0, 0]):.1f} px ({FOCAL_PRIOR} x the larger image side)")
        state.K = K
        return state


class BuildTracks(ConfiguredStage):
    """Chain the verified matches into tracks: fills ``tracks``. Where verification kept a second
    motion's matches (:func:`~torchsfm.sfm.view_pairs.verify_pairs`), those that chain among
    themselves over ``moving_objects.min_object_frames`` views join (the fewest a body is
    reconstructed from; a pair's chance agreements among its outliers rarely chain)."""

    SECTIONS = ("moving_objects",)

    def forward(self, state: ViewSet) -> ViewSet:
        sizes = [c.shape[0] for c in state.corners]
        matches = {key: (m.index1, m.index2) for key, m in state.pairs.items()}
        others = chained_matches(sizes, {key: m.other_motion for key, m in state.pairs.items() if m.other_motion is not None},
                                 self.config.moving_objects.min_object_frames)
        for key, (a, b) in others.items():
            matches[key] = (torch.cat([matches[key][0], a]), torch.cat([matches[key][1], b]))
        state.tracks = build_tracks(sizes, matches)
        state.report(f"{state.tracks.num_tracks} tracks from {len(state.pairs)} verified pairs"
                     + (f" ({sum(a.numel() for a, _ in others.values())} matches of other motions)" if others else ""))
        return state


class RejectMovingObjects(ConfiguredStage):
    """With ``moving_objects.enabled``: keep the tracks the whole-track decision keeps."""

    SECTIONS = ("moving_objects", "segmentation", "fundamental", "lm")

    def forward(self, state: ViewSet) -> ViewSet:
        if self.config.moving_objects.enabled:
            everything = state.tracks
            state.tracks, state.rejections, state.rejected_per_view, labels = reject_moving_tracks(
                everything, state.corners, self.config, state.generator)
            state.report(f"{state.tracks.num_tracks} tracks kept as static")
            if self.config.moving_objects.reconstruct_objects:
                state.all_tracks, state.track_labels = everything, labels
        return state


class RetryStage(ConfiguredStage):
    """A stage that runs ``retry`` (default: :class:`BuildTracks`, :class:`RejectMovingObjects`,
    :class:`MapIncrementally` at their default settings) on changed pairs and keeps the better
    model (:func:`_better_of`)."""

    def __init__(self, retry: Pipeline | None = None, **sections) -> None:
        super().__init__(**sections)
        self.retry = retry if retry is not None else Pipeline(BuildTracks(), RejectMovingObjects(), MapIncrementally())


class RematchUnregistered(RetryStage):
    """When views stay unregistered although a verified pair links them to the model, or
    registered only at a widened resection threshold (``Reconstruction.loose_resections``)
    (``pairs.epipolar_matching``): the verified pairs of those views and of their partners (the
    tracks through a partner link a view to the model) are matched again in their epipolar
    bands (:func:`epipolar_matches`), and the tracks, the moving-object decision and the mapping
    run again; the model that stands higher (:func:`_standing`) is kept. Costs nothing where
    every view registers at the threshold, or where the others form separate groups. ``retry``
    is the pipeline run again on the rematched pairs (:class:`RetryStage`)."""

    SECTIONS = ("matching", "pairs", "fundamental")

    def forward(self, state: ViewSet) -> ViewSet:
        first = state.reconstruction
        registered = set(first.view_indices)
        stranded = {v for key in state.pairs for v in key if v not in registered and set(key) & registered}
        stranded |= set(first.loose_resections)
        linked = {v for key in state.pairs if stranded & set(key) for v in key}  # the stranded views and their partners
        weak = {key: m for key, m in state.pairs.items() if linked & set(key)}
        if not weak:
            return state
        state.report(f"{len(stranded)} views unregistered or loosely registered: matching {len(weak)} verified pairs of them "
                     "and their partners along epipolar lines")
        rematched = epipolar_matches(state.greys, state.raw, state.corners, weak, state.homographies, self.config)
        return _better_of(state, self.retry(replace(state, pairs={**state.pairs, **rematched})))


class BridgeWithSift(RetryStage):
    """When views stay out of the model (``pairs.sift_bridge``): the pairs that may link each of
    them to the registered views (:func:`~torchsfm.sfm.pairs.bridge_pairs`) get a homography
    in place of the coarse NCC one — from the coarse NCC matches of the partner's patches turned
    every 30 degrees where that fits one (:func:`~torchsfm.sfm.pairs.turned_homographies`: a
    portrait shot among landscape ones, a tilted one; such a view needs no SIFT), else from SIFT matches
    (:func:`~torchsfm.sfm.sift.sift_homographies`): a wide baseline (rotations of 40-60 degrees)
    leaves too few coarse NCC matches to fit it, or fits a false one. Then the thesis' matching
    as before: NCC + strength measure at the corners, the disc centred on the homography's
    prediction and the patches warped by it, and
    robust verification, of which only the strongest pair joining two groups of views is kept
    (:func:`joining_pairs`; the groups: the model, the other models, and the left-out views that
    verified pairs link); then the epipolar-band rematch (:func:`epipolar_matches`) of the
    joining pairs and of the other verified pairs of their views and of the left-out views
    (their tracks carry the link into the model). These pairs replace those of the same views,
    and the tracks, the moving-object decision and the mapping run again; the model that
    stands higher (:func:`_standing`) is kept, and the stage repeats while it gains (each view
    described once). SIFT only finds where to look: every match is still a Harris corner pair.
    Costs nothing where every view registers. ``retry``: see :class:`RetryStage`."""

    SECTIONS = ("matching", "pairs", "fundamental", "lm", "reconstruction")

    def forward(self, state: ViewSet) -> ViewSet:
        if len(state.reconstruction.view_indices) == len(state.images):
            return state
        features = coarse_features(state.greys, self.config.pairs, state.focal_lengths(), state.masks)  # once: every round ranks partners by them
        described: dict[int, tuple[Tensor, Tensor]] = {}  # SIFT of the views described so far
        tried: set[tuple[int, int]] = set()
        while True:  # again while the model grows: the views it gained bring new partners
            registered = sorted(state.reconstruction.view_indices)
            stranded = sorted(set(range(len(state.images))) - set(registered))
            candidates = [pair for pair in bridge_pairs(features, stranded, registered, self.config.pairs) if pair not in tried]
            if not candidates:
                return state
            tried |= set(candidates)
            own = side_generator(state.generator)  # the draws below as without it
            homographies = turned_homographies(features, candidates, self.config.pairs, own)
            turned = {v for pair in homographies for v in pair if v in stranded}  # linked already: no SIFT for them
            unturned = [pair for pair in candidates if not set(pair) & turned]
            state.report(f"{len(stranded)} views left out: {len(candidates)} pairs may link them, {len(homographies)} of them "
                         f"with a view turned against the other; SIFT homographies for {len(unturned)}")
            homographies.update(sift_homographies(state.greys, unturned, self.config.pairs, state.generator, described, state.masks))
            putative = guided_matches(state.greys, state.raw, homographies, self.config, state.report)
            groups = [registered, *(other.view_indices for other in state.reconstruction.other_models),
                      *(list(key) for key in state.pairs if not set(key) & set(registered))]  # links among left-out views stand
            verified = joining_pairs(verify_pairs(putative, state.corners, self.config, state.generator, state.report),
                                     groups, len(state.images))
            if not verified:
                return state
            joined = set(stranded) | {v for key in verified for v in key}
            partners = {key: match for key, match in state.pairs.items() if joined & set(key)}
            homographies = {**state.homographies, **homographies}
            rematched = epipolar_matches(state.greys, state.raw, state.corners, {**partners, **verified}, homographies, self.config)
            chosen = _better_of(state, self.retry(replace(state, pairs={**state.pairs, **rematched}, homographies=homographies)))
            if chosen is state:
                return state
            state = chosen


def joining_pairs(bridges: dict[tuple[int, int], PairMatches], groups: list[list[int]], num_views: int
                  ) -> dict[tuple[int, int], PairMatches]:
    """The ``bridges`` that each join two groups of views not yet joined — views that share one
    of the (overlapping) ``groups``, or a view in none — strongest (most matches) first: a
    maximum spanning forest over the groups (Kruskal). One link per join: a wide-baseline pair
    can verify falsely (a dominant plane and a few chance matches), and the strongest link is the
    likeliest true one."""
    group = list(range(num_views))
    root = partial(group_root, group)
    for views in groups:
        for v in views[1:]:
            group[root(v)] = root(views[0])
    joining = {}
    for (i, j), match in sorted(bridges.items(), key=lambda item: -item[1].index1.numel()):
        if root(i) != root(j):
            group[root(i)] = root(j)
            joining[(i, j)] = match
    return joining


def _better_of(first: ViewSet, second: ViewSet) -> ViewSet:
    """The state whose model stands higher (:func:`_standing`; ``first`` on a tie)."""
    def described(standing: tuple[int, int, int]) -> str:
        return f"{standing[0]} views ({-standing[1]} loosely, {standing[2]} points)"

    mine, theirs = _standing(first.reconstruction), _standing(second.reconstruction)
    better = theirs > mine
    first.report(f"the second attempt registers {described(theirs)} against {described(mine)}: "
                 + ("kept" if better else "the first model kept"))
    return second if better else first


def _standing(model: Reconstruction) -> tuple[int, int, int]:
    """How a model ranks against another of the same views: more views registered, then fewer
    of them loosely, then more points (of two models of as many views, the one a wrong pair
    started has few: its matches are mostly chance ones that a second view seldom confirms)."""
    return len(model.view_indices), -len(model.loose_resections), model.num_points


class MapIncrementally(ConfiguredStage):
    """Initial pair, resection and triangulation of every next view, bundle adjustment (and, when
    K was estimated, its refinement), then the observations found by projection and one more
    adjustment: fills ``reconstruction``."""

    SECTIONS = ("reconstruction", "matching", "resection", "lm", "triangulation", "bundle_adjustment", "relative_pose", "fundamental")

    def forward(self, state: ViewSet) -> ViewSet:
        state.reconstruction = map_incrementally(state, self.config)
        state.reconstruction.moving_objects = state.rejections
        state.reconstruction.moving_rejections_per_view = dict(enumerate(state.rejected_per_view))
        return state


def default_pipeline(config: Config | None = None) -> Pipeline:
    """The stages of :func:`torchsfm.reconstruct` (SIFT's two first with ``pairs.matcher``
    ``sift``), each given its sections of ``config``."""
    config = config or Config()
    sift = config.pairs.matcher == "sift"
    features = (DetectSiftFeatures, MatchSiftFeatures) if sift else (DetectCorners, MatchPairs)
    reject, mapper = RejectMovingObjects.from_config(config), MapIncrementally.from_config(config)
    tracks = BuildTracks.from_config(config)
    retry = Pipeline(tracks, reject, mapper)
    rematch = (RematchUnregistered.from_config(config, retry=retry),) if config.pairs.epipolar_matching and not sift else ()
    bridge = (BridgeWithSift.from_config(config, retry=retry),) if config.pairs.sift_bridge and not sift else ()
    return Pipeline(*(stage.from_config(config) for stage in features), VerifyPairs.from_config(config),
                    SelfCalibrate.from_config(config), tracks, reject, mapper, *rematch, *bridge)
