"""Two images and K in, a sparse 3-D model out (thesis §3.1, Fig. 3.1), as a sequence of stages.

Harris corners → NCC candidates → strength measure + relaxation → (IMOR + RANSAC on a third
frame) → robust F (bucketed RANSAC, LM) → E → R, t → polynomial triangulation →
:class:`~torchsfm.reconstruction.Reconstruction`. Each step is a stage on a :class:`PairState`
(:func:`two_view_stages`), as the N-view pipeline's are on a ``ViewSet``:

    pipeline = TwoViewReconstruction(config)
    pipeline.stages[1] = MyMatcher()          # any module: PairState -> PairState
    model = pipeline(image1, image2, K)
"""

from __future__ import annotations

from dataclasses import dataclass, field

import torch
from torch import Tensor, nn

from torchsfm.camera import Camera, check_intrinsics, undistort_points
from torchsfm.config import Config
from torchsfm.errors import DegenerateConfigurationError, InputError, NotEnoughDataError
from torchsfm.estimators.two_view_geometry import RelativePose, RelativePoseEstimator
from torchsfm.features.harris import detect_corners
from torchsfm.images import check_image, to_grey
from torchsfm.matching.matcher import PutativeMatches, chain_matches, match_corners
from torchsfm.moving.imor import MovingObjectRejection, reject_moving_objects
from torchsfm.reconstruction import Reconstruction
from torchsfm.pipeline import ConfiguredStage, Pipeline, Progress
from torchsfm.validation import check_finite, check_shapes



def _check_images(image1: Tensor, image2: Tensor, names: tuple[str, str] = ("image1", "image2")) -> None:
    for name, image in zip(names, (image1, image2)):
        check_image(image, name)
    if image1.shape[-2:] != image2.shape[-2:]:
        (h1, w1), (h2, w2) = image1.shape[-2:], image2.shape[-2:]
        raise InputError(f"the images differ in size: {names[0]} is {w1}x{h1}, {names[1]} {w2}x{h2}")


def _colours(image: Tensor, points: Tensor) -> Tensor:
    """RGB (P, 3) float of a (3 or 1, H, W) image at the nearest pixels of (P, 2) points."""
    H, W = image.shape[-2:]
    x = points[:, 0].round().long().clamp(0, W - 1)
    y = points[:, 1].round().long().clamp(0, H - 1)
    colours = image[:, y, x].T.float()
    return colours.expand(-1, 3) if colours.shape[1] == 1 else colours


@dataclass
class PairState:
    """The state the two-view stages pass along (each fills its own fields).

    Fields:
        images: image1, image2 (and the third frame with moving-object rejection), each
            (3 or 1, H, W), one size; K: (2, 3, 3) float64 intrinsics of image1 and image2 (the
            third frame shares image2's); distortion: (2,) radial (k1, k2) or None; names: the
            two images' names; moving: moving-object rejection on; generator: the random source
            of every RANSAC; report: progress messages.
        greys: (2 or 3, 1, H, W) float grey images; raw: per image (N_v, 2) detected corners;
        points: the same undistorted, float64; matches: image1–image2 putative matches; x1, x2:
        (M, 2) their ideal positions; static: (M,) bool, the matches kept as background
        (all without rejection); rejections: IMOR + RANSAC's result for the triplet (0, 1, 2);
        pose: the relative pose; reconstruction: the result; timings: seconds per stage.
    """

    images: list[Tensor]
    K: Tensor
    distortion: Tensor | None
    names: tuple[str, str]
    moving: bool
    generator: torch.Generator | None = None
    report: Progress = field(default=lambda message: None)
    greys: Tensor | None = None
    raw: list[Tensor] | None = None
    points: list[Tensor] | None = None
    matches: PutativeMatches | None = None
    x1: Tensor | None = None
    x2: Tensor | None = None
    static: Tensor | None = None
    rejections: dict[tuple[int, int, int], MovingObjectRejection] = field(default_factory=dict)
    pose: RelativePose | None = None
    reconstruction: Reconstruction | None = None
    timings: dict[str, float] = field(default_factory=dict)


class DetectPairCorners(ConfiguredStage):
    """Harris corners of each image (batched; ``harris``), at least 8 each, undistorted:
    fills ``greys``, ``raw``, ``points``."""

    SECTIONS = ("harris",)

    def forward(self, state: PairState) -> PairState:
        state.report("corners ...")
        state.greys = torch.stack([to_grey(image) for image in state.images])
        corners = detect_corners(state.greys, self.config.harris)
        state.raw = [corners.of_image(v) for v in range(state.greys.shape[0])]
        for view, name in enumerate([*state.names, "third_image"][: state.greys.shape[0]]):
            if state.raw[view].shape[0] < 8:
                raise NotEnoughDataError(f"{name} has {state.raw[view].shape[0]} corners, at least 8 are needed (a textureless image?)")
        # images are matched as taken; the geometry sees ideal (undistorted) positions
        K = [state.K[0], state.K[1], state.K[1]]
        state.points = [p.double() if state.distortion is None else undistort_points(p.double(), K[v], state.distortion.double())
                        for v, p in enumerate(state.raw)]
        return state


class MatchPair(ConfiguredStage):
    """NCC + strength-measure matches of image1's corners in image2 (``matching``,
    ``two_view.min_median_parallax``); at least 8, and a baseline: fills ``matches``, ``x1``,
    ``x2``, ``static`` (all True)."""

    SECTIONS = ("matching", "two_view")

    def forward(self, state: PairState) -> PairState:
        state.report("matching ...")
        state.matches = match_corners(state.greys[0], state.greys[1], state.raw[0], state.raw[1],
                                      self.config.matching.for_images(state.greys.shape))
        state.x1, state.x2 = state.points[0][state.matches.index1], state.points[1][state.matches.index2]
        (name1, name2), count = state.names, state.x1.shape[0]
        if count < 8:
            raise NotEnoughDataError(f"only {count} putative matches between {name1} and {name2}, at least 8 are needed")
        parallax = float((state.x2 - state.x1).norm(dim=-1).median())
        minimum = self.config.two_view.min_median_parallax
        if parallax < minimum:
            raise DegenerateConfigurationError(f"{name1} and {name2} show no baseline: matched corners moved by a median of "
                                               f"{parallax:.2f} px (< two_view.min_median_parallax = {minimum})")
        state.static = torch.ones(count, dtype=torch.bool)
        return state


class RejectMovingMatches(ConfiguredStage):
    """With ``state.moving``: image2's corners matched into the third frame too; the matches seen
    in all three frames that IMOR + RANSAC keeps as static (image2 the reference) stay in
    ``static``, the others (untestable ones included) leave it; fills ``rejections``."""

    SECTIONS = ("matching", "moving_objects", "fundamental", "lm")

    def forward(self, state: PairState) -> PairState:
        if not state.moving:
            return state
        state.report("moving objects ...")
        onward = match_corners(state.greys[1], state.greys[2], state.raw[1], state.raw[2],
                               self.config.matching.for_images(state.greys.shape))
        seen, third = chain_matches(state.matches, onward, state.points[1].shape[0])
        rejection = reject_moving_objects(state.x1[seen], state.x2[seen], state.points[2][third], config=self.config,
                                          generator=state.generator)
        state.static = torch.zeros_like(state.static)
        state.static[seen[rejection.background_mask]] = True
        state.rejections[(0, 1, 2)] = rejection
        return state


class EstimatePose(ConfiguredStage):
    """Robust F, E and (R, t), triangulated points of the static matches: fills ``pose``."""

    SECTIONS = ("relative_pose", "fundamental", "lm", "triangulation")

    def __init__(self, **sections) -> None:
        super().__init__(**sections)
        self.estimator = RelativePoseEstimator(self.config)

    def forward(self, state: PairState) -> PairState:
        state.report("geometry ...")
        state.pose = self.estimator(state.x1[state.static], state.x2[state.static], state.K[0], state.K[1], generator=state.generator)
        return state


class BuildPairModel(nn.Module):
    """The :class:`~torchsfm.reconstruction.Reconstruction` of the pose's inliers, coloured by
    both images: fills ``reconstruction``."""

    def forward(self, state: PairState) -> PairState:
        inliers = torch.zeros_like(state.static)
        inliers[state.static] = state.pose.inlier_mask
        P = int(inliers.sum())
        image1, image2 = state.images[:2]
        colours = (_colours(image1, state.raw[0][state.matches.index1][inliers])
                   + _colours(image2, state.raw[1][state.matches.index2][inliers])) / 2
        if image1.dtype != torch.uint8:
            colours = colours * 255
        identity = torch.eye(3, dtype=torch.float64)
        cameras = Camera(K=state.K, R=torch.stack([identity, state.pose.R.double()]),
                         t=torch.stack([torch.zeros(3, dtype=torch.float64), state.pose.t.double()]))
        point_index = torch.arange(P)
        state.reconstruction = Reconstruction(
            cameras=cameras,
            image_names=list(state.names),
            image_sizes=torch.tensor([[image1.shape[-1], image1.shape[-2]]] * 2),
            points3d=state.pose.points3d.double(),
            colors=colours.round().clamp(0, 255).to(torch.uint8),
            observation_points=torch.cat([point_index, point_index]),
            observation_views=torch.cat([torch.zeros(P, dtype=torch.long), torch.ones(P, dtype=torch.long)]),
            keypoints=torch.cat([state.x1[inliers], state.x2[inliers]]),
            matches=torch.cat([state.x1, state.x2], dim=-1),
            inlier_mask=inliers,
            moving_objects=state.rejections,
        )
        return state


def two_view_stages(config: Config | None = None) -> Pipeline:
    """The stages of :class:`TwoViewReconstruction`."""
    config = config or Config()
    return Pipeline(*(stage.from_config(config) for stage in (DetectPairCorners, MatchPair, RejectMovingMatches, EstimatePose)),
                    BuildPairModel())


class TwoViewReconstruction(nn.Module):
    """The two-view pipeline: corners, putative matches, (moving objects,) relative pose and
    points — :func:`two_view_stages` on a :class:`PairState`, or the ``pipeline`` given (swap,
    drop or insert a stage: any module ``PairState -> PairState``).

    ``forward(image1, image2, K1, K2=None)`` takes (3, H, W) colour or (1, H, W) grey images of
    the same size (uint8 or float in [0, 1]) and (3, 3) intrinsics (K2 defaults to K1). With
    ``distortion`` (k1, k2), the radial distortion of the camera that took them, corners are
    undistorted before any geometry (the model's keypoints and matches are then ideal pixels).

    With ``config.moving_objects.enabled`` it also needs ``third_image``, the frame after
    image2: image2's corners are matched into both other images, and only matches seen in all
    three frames that IMOR + RANSAC keeps as static background (image2 the reference) go on to
    the relative pose. Matches not seen in the third frame cannot be tested and are dropped.
    """

    def __init__(self, config: Config | None = None, pipeline: Pipeline | None = None) -> None:
        super().__init__()
        self.config = config or Config()
        self.stages = pipeline if pipeline is not None else two_view_stages(self.config)

    def forward(self, image1: Tensor, image2: Tensor, K1: Tensor, K2: Tensor | None = None, *,
                distortion: Tensor | None = None, third_image: Tensor | None = None, names: tuple[str, str] = ("image1", "image2"),
                generator: torch.Generator | None = None, progress: Progress | None = None) -> Reconstruction:
        K2 = K1 if K2 is None else K2
        moving = self.config.moving_objects.enabled
        if moving and third_image is None:
            raise InputError("moving-object rejection (moving_objects.enabled) needs a third image: the frame after image2")
        _check_images(image1, image2)
        if moving:
            _check_images(image2, third_image, ("image2", "third_image"))
        check_intrinsics(K1=K1, K2=K2)
        if distortion is not None:
            check_shapes(distortion=(distortion, "2"))
            check_finite(distortion=distortion)
        images = [image1, image2] + ([third_image] if moving else [])
        state = PairState(images=images, K=torch.stack([K1.double(), K2.double()]), distortion=distortion, names=names,
                          moving=moving, generator=generator, report=progress or (lambda message: None))
        state = self.stages(state)
        state.reconstruction.timings = state.timings
        return state.reconstruction
