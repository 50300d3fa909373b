"""Two images and K in, a sparse 3-D model out (thesis §3.1, Fig. 3.1), as a sequence of stages.

Harris corners → NCC candidates → strength measure + relaxation → robust F (bucketed RANSAC,
LM) → E → R, t → polynomial triangulation → :class:`~torchsfm.reconstruction.Reconstruction`.
"""

from __future__ import annotations

import time
from collections.abc import Callable

import torch
from torch import Tensor, nn

from torchsfm.camera import Camera, check_intrinsics, undistort_points
from torchsfm.config import Config
from torchsfm.errors import DegenerateConfigurationError, InputError, NotEnoughDataError, ShapeError
from torchsfm.features.harris import HarrisCorners
from torchsfm.images import to_grey
from torchsfm.matching.matcher import PutativeMatcher, chain_matches
from torchsfm.moving.imor import reject_moving_objects
from torchsfm.reconstruction import Reconstruction
from torchsfm.estimators.two_view_geometry import RelativePoseEstimator
from torchsfm.validation import check_finite, check_shapes

Progress = Callable[[str], None]


def _check_images(image1: Tensor, image2: Tensor, names: tuple[str, str] = ("image1", "image2")) -> None:
    for name, image in zip(names, (image1, image2)):
        if not isinstance(image, Tensor) or image.dim() != 3 or image.shape[0] not in (1, 3):
            shape = tuple(image.shape) if isinstance(image, Tensor) else type(image).__name__
            raise ShapeError(f"{name} must be a (3, H, W) colour or (1, H, W) grey tensor, got {shape}")
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


class TwoViewReconstruction(nn.Module):
    """The two-view pipeline as stages: corners, putative matches, relative pose and points.

    ``forward(image1, image2, K1, K2=None)`` takes (3, H, W) colour or (1, H, W) grey images of
    the same size (uint8 or float in [0, 1]) and (3, 3) intrinsics (K2 defaults to K1). With
    ``distortion`` (k1, k2), the radial distortion of the camera that took them, corners are
    undistorted before any geometry (the model's keypoints and matches are then ideal pixels).

    With ``config.moving_objects.enabled`` it also needs ``third_image``, the frame after
    image2: image2's corners are matched into both other images, and only matches seen in all
    three frames that IMOR + RANSAC keeps as static background (image2 the reference) go on to
    the relative pose. Matches not seen in the third frame cannot be tested and are dropped.
    """

    def __init__(self, config: Config | None = None) -> None:
        super().__init__()
        self.config = config or Config()
        self.corners = HarrisCorners(self.config.harris)
        self.matcher = PutativeMatcher(self.config.matching)
        self.pose = RelativePoseEstimator(self.config)

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
        K1, K2 = K1.double(), K2.double()
        if distortion is not None:
            check_shapes(distortion=(distortion, "2"))
            check_finite(distortion=distortion)
        timings: dict[str, float] = {}
        report = progress or (lambda message: None)

        def stage(name: str, function: Callable[[], object]):
            report(f"{name} ...")
            start = time.perf_counter()
            result = function()
            timings[name] = time.perf_counter() - start
            return result

        grey = torch.stack([to_grey(image) for image in (image1, image2, third_image) if image is not None])
        corners = stage("corners", lambda: self.corners(grey))
        raw = [corners.of_image(v) for v in range(grey.shape[0])]
        for view, name in enumerate([*names, "third_image"][: grey.shape[0]]):
            if raw[view].shape[0] < 8:
                raise NotEnoughDataError(f"{name} has {raw[view].shape[0]} corners, at least 8 are needed (a textureless image?)")
        # images are matched as taken; the geometry sees ideal (undistorted) positions
        points = [p.double() if distortion is None else undistort_points(p.double(), K, distortion.double())
                  for p, K in zip(raw, (K1, K2, K2))]
        matches = stage("matching", lambda: self.matcher(grey[0], grey[1], raw[0], raw[1]))
        x1, x2 = points[0][matches.index1].double(), points[1][matches.index2].double()
        if x1.shape[0] < 8:
            raise NotEnoughDataError(f"only {x1.shape[0]} putative matches between {names[0]} and {names[1]}, at least 8 are needed")
        parallax = float((x2 - x1).norm(dim=-1).median())
        if parallax < self.config.two_view.min_median_parallax:
            raise DegenerateConfigurationError(
                f"{names[0]} and {names[1]} show no baseline: matched corners moved by a median of {parallax:.2f} px "
                f"(< two_view.min_median_parallax = {self.config.two_view.min_median_parallax})")
        static = torch.ones(x1.shape[0], dtype=torch.bool)
        rejections = {}
        if moving:
            static, rejections[(0, 1, 2)] = stage("moving objects", lambda: self._static_matches(grey, raw, points, matches, generator))
        pose = stage("geometry", lambda: self.pose(x1[static], x2[static], K1, K2, generator=generator))
        inliers = torch.zeros_like(static)
        inliers[static] = pose.inlier_mask
        P = int(inliers.sum())
        colours = (_colours(image1, raw[0][matches.index1][inliers]) + _colours(image2, raw[1][matches.index2][inliers])) / 2
        if image1.dtype != torch.uint8:
            colours = colours * 255
        identity = torch.eye(3, dtype=torch.float64)
        cameras = Camera(K=torch.stack([K1, K2]), R=torch.stack([identity, pose.R.double()]),
                         t=torch.stack([torch.zeros(3, dtype=torch.float64), pose.t.double()]))
        point_index = torch.arange(P)
        return Reconstruction(
            cameras=cameras,
            image_names=list(names),
            image_sizes=torch.tensor([[image1.shape[-1], image1.shape[-2]]] * 2),
            points3d=pose.points3d.double(),
            colors=colours.round().clamp(0, 255).to(torch.uint8),
            observation_points=torch.cat([point_index, point_index]),
            observation_views=torch.cat([torch.zeros(P, dtype=torch.long), torch.ones(P, dtype=torch.long)]),
            keypoints=torch.cat([x1[inliers], x2[inliers]]),
            matches=torch.cat([x1, x2], dim=-1),
            inlier_mask=inliers,
            timings=timings,
            moving_objects=rejections,
        )

    def _static_matches(self, grey: Tensor, raw: list[Tensor], points: list[Tensor], matches, generator: torch.Generator | None):
        """(M,) mask of the image1–image2 matches that IMOR + RANSAC keeps as static, and its result."""
        onward = self.matcher(grey[1], grey[2], raw[1], raw[2])
        seen, third = chain_matches(matches, onward, points[1].shape[0])
        rejection = reject_moving_objects(points[0][matches.index1[seen]], points[1][matches.index2[seen]],
                                          points[2][third], config=self.config, generator=generator)
        static = torch.zeros(matches.index1.numel(), dtype=torch.bool)
        static[seen[rejection.background_mask]] = True
        return static, rejection

    def extra_repr(self) -> str:
        return f"two_view={self.config.two_view}"
