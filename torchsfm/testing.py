"""Seeded synthetic scenes with ground truth, for tests, examples and benchmarks."""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
from torch import Tensor

from torchsfm.camera import pixels_to_normalized, project, projection_matrix, to_homogeneous, undistort_normalized
from torchsfm.geometry.fundamental import epipolar_line_distances, fundamental_from_pose
from torchsfm.geometry.rotation import angle_between, axis_angle_to_rotation, rotation_angle
from torchsfm.estimators.two_view_geometry import estimate_fundamental, estimate_relative_pose


@dataclass
class TwoViewScene:
    """Two calibrated views of random points, with planted outliers.

    Fields (float64 unless noted):
        K1, K2: (3, 3) intrinsics. R, t: (3, 3), (3,) camera 2 from camera 1 (‖t‖ = 1).
        points3d: (N, 3) true points in the camera-1 frame.
        x1_true, x2_true: (N, 2) exact projections (pixels).
        x1, x2: (N, 2) observations: noisy projections, and random pixels at outlier rows.
        is_inlier: (N,) bool, False where x2 was replaced by a random point.
        image_size: (width, height) in pixels.
    """

    K1: Tensor
    K2: Tensor
    R: Tensor
    t: Tensor
    points3d: Tensor
    x1_true: Tensor
    x2_true: Tensor
    x1: Tensor
    x2: Tensor
    is_inlier: Tensor
    image_size: tuple[int, int]

    @property
    def F(self) -> Tensor:
        """Ground-truth fundamental matrix (unit norm)."""
        return fundamental_from_pose(self.K1, self.K2, self.R, self.t)

    @property
    def P1(self) -> Tensor:
        return projection_matrix(self.K1, torch.eye(3, dtype=self.K1.dtype), torch.zeros(3, dtype=self.K1.dtype))

    @property
    def P2(self) -> Tensor:
        return projection_matrix(self.K2, self.R, self.t)


def _uniform(shape: tuple[int, ...], low: float, high: float, generator: torch.Generator) -> Tensor:
    return low + (high - low) * torch.rand(shape, generator=generator, dtype=torch.float64)


def look_at_rotation(center: Tensor, target: Tensor, roll: float = 0.0) -> Tensor:
    """Rotation (camera from world) of a camera at ``center`` looking at ``target``, y down."""
    z = target - center
    z = z / z.norm()
    up = torch.tensor([0.0, -1.0, 0.0], dtype=center.dtype)
    x = torch.linalg.cross(up, z)
    x = x / x.norm()
    y = torch.linalg.cross(z, x)
    R = torch.stack([x, y, z])
    return axis_angle_to_rotation(torch.tensor([0.0, 0.0, roll], dtype=center.dtype)) @ R


def synthetic_two_view(
    num_points: int = 200,
    *,
    noise: float = 0.0,
    outlier_ratio: float = 0.0,
    image_size: tuple[int, int] = (640, 480),
    focal: float = 600.0,
    baseline: float = 1.0,
    depth: tuple[float, float] = (4.0, 8.0),
    min_outlier_distance: float = 5.0,
    seed: int = 0,
) -> TwoViewScene:
    """Random points seen by two cameras converging on them, with noise and planted outliers.

    Points fill a box in front of camera 1 at ``depth``; camera 2 sits ``baseline`` away and looks
    at the box centre, so both views see every point. Gaussian noise of std ``noise`` pixels is
    added to both images; a fraction ``outlier_ratio`` of rows gets a uniformly random x2 at least
    ``min_outlier_distance`` pixels (symmetric) from the true epipolar geometry.
    """
    generator = torch.Generator().manual_seed(seed)
    width, height = image_size
    K = torch.tensor([[focal, 0.0, (width - 1) / 2], [0.0, focal * 1.02, (height - 1) / 2], [0.0, 0.0, 1.0]], dtype=torch.float64)
    centre = torch.tensor([0.0, 0.0, sum(depth) / 2], dtype=torch.float64)
    direction = torch.cat([_uniform((2,), -1.0, 1.0, generator), _uniform((1,), -0.3, 0.3, generator)])
    C2 = baseline * direction / direction.norm()
    R = look_at_rotation(C2, centre, roll=float(_uniform((1,), -0.2, 0.2, generator)))
    t = -R @ C2
    P1 = projection_matrix(K, torch.eye(3, dtype=torch.float64), torch.zeros(3, dtype=torch.float64))
    P2 = projection_matrix(K, R, t)

    points = []
    count = 0
    while count < num_points:
        z = _uniform((4 * num_points,), depth[0], depth[1], generator)
        xy = _uniform((4 * num_points, 2), -0.5, 0.5, generator) * torch.tensor([width, height], dtype=torch.float64) / focal * z[:, None]
        X = torch.cat([xy, z[:, None]], dim=-1)
        x2 = project(P2, X)
        margin = 2.0
        visible = ((x2[:, 0] > margin) & (x2[:, 0] < width - 1 - margin) & (x2[:, 1] > margin) & (x2[:, 1] < height - 1 - margin)
                   & ((X @ R.T + t)[:, 2] > 0))
        points.append(X[visible])
        count += int(visible.sum())
    X = torch.cat(points)[:num_points]
    x1_true, x2_true = project(P1, X), project(P2, X)
    x1 = x1_true + noise * torch.randn(x1_true.shape, generator=generator, dtype=torch.float64)
    x2 = x2_true + noise * torch.randn(x2_true.shape, generator=generator, dtype=torch.float64)

    num_outliers = int(round(outlier_ratio * num_points))
    is_inlier = torch.ones(num_points, dtype=torch.bool)
    F = fundamental_from_pose(K, K, R, t)
    # every epipolar line of image 1 passes through its epipole, so a point that close to it has
    # no x2 far from its line: it cannot be made an outlier
    epipole = torch.linalg.svd(F).Vh[-1]
    placeable = torch.ones(num_points, dtype=torch.bool)
    if float(epipole[2].abs()) > 1e-12:
        placeable = (x1 - epipole[:2] / epipole[2]).norm(dim=-1) >= min_outlier_distance
    order = torch.randperm(num_points, generator=generator)
    outliers = order[placeable[order]][:num_outliers]
    is_inlier[outliers] = False
    pending = outliers
    while pending.numel():
        x2[pending] = _uniform((pending.numel(), 2), 0.0, 1.0, generator) * torch.tensor([width - 1, height - 1], dtype=torch.float64)
        d1, d2 = epipolar_line_distances(F, x1[pending], x2[pending])
        pending = pending[torch.minimum(d1, d2) < min_outlier_distance]
    return TwoViewScene(K1=K, K2=K.clone(), R=R, t=t / t.norm(), points3d=X / t.norm(), x1_true=x1_true, x2_true=x2_true,
                        x1=x1, x2=x2, is_inlier=is_inlier, image_size=image_size)


def rotation_error_deg(R_estimated: Tensor, R_true: Tensor) -> float:
    """Angle of R_estimatedᵀ R_true in degrees."""
    return float(rotation_angle(R_estimated.double(), R_true.double()))


def translation_direction_error_deg(t_estimated: Tensor, t_true: Tensor) -> float:
    """Angle between two translation directions in degrees (sign matters)."""
    return float(angle_between(t_estimated.double(), t_true.double()))


def replace_with_random_points(
    x: Tensor, fraction: float, image_size: tuple[int, int], generator: torch.Generator
) -> tuple[Tensor, Tensor]:
    """Replace a random ``fraction`` of the rows of x (N, 2) by uniform pixels of the image.

    Returns the corrupted copy and the (N,) bool mask of rows left untouched.
    """
    n = x.shape[0]
    replaced = torch.randperm(n, generator=generator)[: int(round(fraction * n))]
    corrupted = x.clone()
    size = torch.tensor(image_size, dtype=x.dtype) - 1
    corrupted[replaced] = torch.rand(len(replaced), 2, generator=generator, dtype=x.dtype) * size
    kept = torch.ones(n, dtype=torch.bool)
    kept[replaced] = False
    return corrupted, kept


def mask_recall_precision(estimated: Tensor, truth: Tensor) -> tuple[float, float]:
    """(recall, precision) of an estimated inlier mask against the true one."""
    hits = int((estimated & truth).sum())
    return hits / max(int(truth.sum()), 1), hits / max(int(estimated.sum()), 1)


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


def render_squares(squares: list[tuple[float, float, float, float, float]], size: tuple[int, int] = (200, 160),
                   blur: float = 1.0, background: float = 0.2) -> Tensor:
    """A grey image (1, H, W) float64 of axis-aligned bright squares with blurred edges.

    Each square is (x0, y0, x1, y1, intensity) in pixels (any sub-pixel position); edges follow
    a Gaussian-integrated step of std ``blur`` pixels, as a lens would render them, so its
    corners sit exactly at the given coordinates.
    """
    width, height = size
    ys, xs = torch.meshgrid(torch.arange(height, dtype=torch.float64), torch.arange(width, dtype=torch.float64), indexing="ij")

    def step(distance: Tensor) -> Tensor:
        return 0.5 * (1 + torch.erf(distance / (blur * 2**0.5)))

    image = torch.full((height, width), background, dtype=torch.float64)
    for x0, y0, x1, y1, intensity in squares:
        image = image + intensity * step(xs - x0) * step(x1 - xs) * step(ys - y0) * step(y1 - ys)
    return image[None]


def random_squares(seed: int, shift: tuple[float, float] = (0.0, 0.0)) -> list[tuple[float, float, float, float, float]]:
    """Six squares at seeded sub-pixel positions in a 200×160 frame (for :func:`render_squares`),
    all moved by ``shift``: the same seed with two shifts gives two renderings of one scene."""
    generator = torch.Generator().manual_seed(seed)
    squares = []
    for i in range(3):
        for j in range(2):
            x0 = 20 + 60 * i + 5 * torch.rand(1, generator=generator).item()
            y0 = 20 + 70 * j + 5 * torch.rand(1, generator=generator).item()
            width = 25 + 5 * torch.rand(1, generator=generator).item()
            squares.append((x0 + shift[0], y0 + shift[1], x0 + width + shift[0], y0 + 30 + shift[1], 0.6))
    return squares


def square_corners(squares: list[tuple[float, float, float, float, float]]) -> Tensor:
    """The (4 S, 2) float64 corners of :func:`random_squares` squares."""
    return torch.tensor([[x, y] for x0, y0, x1, y1, _ in squares for x, y in ((x0, y0), (x1, y0), (x0, y1), (x1, y1))],
                        dtype=torch.float64)


@dataclass
class MovingObjectScene:
    """A static scene with rigid objects moving independently, seen by a moving camera.

    Fields (float64 unless noted):
        K: (3, 3) intrinsics. R, t: (F, 3, 3), (F, 3) cameras (camera from world).
        tracks: (F, N, 2) observed pixels (noisy; random pixels at outlier rows).
        labels: (N,) int64: 0 static background, k >= 1 the k-th moving object, -1 outlier.
        image_size: (width, height).
        object_rotations: (num_objects, F, 3, 3) each object's rotation since frame 0 (world
            frame): its points at frame f are object_rotations[k - 1, f] (X - c) + c' for its
            frame-0 points X, centre c, and centre c' at f.
        object_centres: (num_objects, F, 3) each object's centre c' per frame (world).
    """

    K: Tensor
    R: Tensor
    t: Tensor
    tracks: Tensor
    labels: Tensor
    image_size: tuple[int, int]
    object_rotations: Tensor
    object_centres: Tensor


def synthetic_moving_scene(seed: int, *, num_frames: int = 3, num_objects: int = 2, background_points: int = 400,
                           object_points: int = 60, outlier_fraction: float = 0.1, noise: float = 0.3,
                           plane_share: float = 0.5, static_camera: bool = False,
                           constant_velocity: bool = False) -> MovingObjectScene:
    """A seeded scene for moving-object rejection (640×480, f = 800 px).

    The background is a wall (a share ``plane_share`` of its points, the dominant plane) and
    points scattered 6–20 m deep in front of it; each object is a 2 m box of points 6–10 m away
    translating 0.3–0.6 m and turning up to 3° per frame in its own direction, independently of
    the camera (which moves ~0.5 m and turns ~1.5° per frame, at constant velocity). An object
    takes a new random step every frame: at constant velocity, a point moving straight is, to
    first order, indistinguishable from a static one over three frames (its virtual camera moves
    at a constant velocity too), for the rigidity constraint and for any three-view test. With
    ``constant_velocity`` each object repeats its first step and turn instead (a car driving
    steadily). Outliers are random pixels in every frame. Only points that stay in the image in
    every frame are kept.
    """
    g = torch.Generator().manual_seed(seed)
    W, H = 640, 480
    K = torch.tensor([[800.0, 0, W / 2], [0, 800.0, H / 2], [0, 0, 1]], dtype=torch.float64)
    R, t = [torch.eye(3, dtype=torch.float64)], [torch.zeros(3, dtype=torch.float64)]
    step = torch.tensor([0.5, 0.05, 0.15], dtype=torch.float64) + _uniform((3,), -0.1, 0.1, g)
    spin = _uniform((3,), -1.5, 1.5, g) * math.pi / 180
    if static_camera:
        step, spin = torch.zeros_like(step), torch.zeros_like(spin)
    for _ in range(num_frames - 1):
        R.append(axis_angle_to_rotation(spin) @ R[-1])
        t.append(axis_angle_to_rotation(spin) @ t[-1] - step)
    R, t = torch.stack(R), torch.stack(t)

    def inside(points: Tensor) -> tuple[Tensor, Tensor]:  # (F, n, 3) per-frame world points
        camera = points @ R.transpose(-1, -2) + t[:, None]
        pixels = camera @ K.T
        pixels = pixels[..., :2] / pixels[..., 2:]
        ok = (camera[..., 2] > 0.5) & (pixels[..., 0] > 0) & (pixels[..., 0] < W) & (pixels[..., 1] > 0) & (pixels[..., 1] < H)
        return pixels, ok.all(0)

    wall_count = int(3 * background_points * plane_share)
    wall = torch.stack([_uniform((wall_count,), -12, 14, g), _uniform((wall_count,), -9, 9, g), torch.full((wall_count,), 20.0, dtype=torch.float64)], -1)
    free_count = 3 * background_points - wall_count
    free = torch.stack([_uniform((free_count,), -8, 10, g), _uniform((free_count,), -6, 6, g), _uniform((free_count,), 6, 20, g)], -1)
    static = torch.cat([wall, free])
    pixels, ok = inside(static.expand(num_frames, -1, -1))
    keep = torch.nonzero(ok).flatten()
    keep = keep[torch.randperm(keep.numel(), generator=g)[:background_points]]
    tracks, labels = [pixels[:, keep]], [torch.zeros(keep.numel(), dtype=torch.long)]
    object_rotations = torch.eye(3, dtype=torch.float64).repeat(num_objects, num_frames, 1, 1)
    object_centres = torch.zeros(num_objects, num_frames, 3, dtype=torch.float64)
    for k in range(1, num_objects + 1):
        centre = torch.stack([_uniform((), -3, 3, g), _uniform((), -2, 2, g), _uniform((), 6, 10, g)])
        body = centre + _uniform((3 * object_points, 3), -1, 1, g)
        frames, position = [body], centre
        object_centres[k - 1, 0] = centre
        for f in range(1, num_frames):  # a new random step and turn every frame (or the first one again)
            if f == 1 or not constant_velocity:
                direction = _uniform((3,), -1, 1, g)
                move = direction / direction.norm() * _uniform((), 0.3, 0.6, g)
                turn = axis_angle_to_rotation(_uniform((3,), -3, 3, g) * math.pi / 180)
            object_rotations[k - 1, f] = turn @ object_rotations[k - 1, f - 1]
            object_centres[k - 1, f] = position + move
            frames.append((frames[-1] - position) @ turn.T + position + move)
            position = position + move
        pixels, ok = inside(torch.stack(frames))
        chosen = torch.nonzero(ok).flatten()[:object_points]
        tracks.append(pixels[:, chosen])
        labels.append(torch.full((chosen.numel(),), k, dtype=torch.long))
    tracks = torch.cat(tracks, 1)
    tracks = tracks + noise * torch.randn(tracks.shape, generator=g, dtype=torch.float64)
    labels = torch.cat(labels)
    num_outliers = round(outlier_fraction * labels.numel() / (1 - outlier_fraction))
    outliers = torch.stack([_uniform((num_frames, num_outliers), 0, W, g), _uniform((num_frames, num_outliers), 0, H, g)], -1)
    tracks = torch.cat([tracks, outliers], 1)
    labels = torch.cat([labels, torch.full((num_outliers,), -1, dtype=torch.long)])
    order = torch.randperm(labels.numel(), generator=g)
    return MovingObjectScene(K=K, R=R, t=t, tracks=tracks[:, order], labels=labels[order], image_size=(W, H),
                             object_rotations=object_rotations, object_centres=object_centres)


def rejection_figures(background: Tensor, labels: Tensor) -> dict[str, float]:
    """Table 5.1's counts for a background decision (N,) bool against labels (N,) (0 = static).

    Returns wrong rejections (static vectors rejected), undetected (moving or outlier vectors
    kept), inliers (vectors kept), total, and the rates: wrongly rejected share of the static
    vectors and undetected share of the others.
    """
    static = labels == 0
    wrong = int((static & ~background).sum())
    undetected = int((~static & background).sum())
    return {"wrong_rejections": wrong, "undetected": undetected, "inliers": int(background.sum()), "total": labels.numel(),
            "wrong_rate": wrong / max(int(static.sum()), 1), "undetected_rate": undetected / max(int((~static).sum()), 1)}


# Where the inserted object sits in the three frames of :func:`insert_moving_patch` (top-left
# corners, pixels of a 768×512 image): a step right and up, then right and down — an
# independent, non-constant motion.
PATCH_POSITIONS = ((150, 260), (215, 235), (250, 300))


def insert_moving_patch(images: list[Tensor], patch: Tensor, positions: tuple[tuple[int, int], ...] = PATCH_POSITIONS
                        ) -> tuple[list[Tensor], Tensor]:
    """Paste a textured patch (C, h, w) into each image (C, H, W) at its top-left position (x, y),
    as the thesis did (§5.5). Returns the new images and the (F, 4) boxes (x0, y0, x1, y1)."""
    h, w = patch.shape[-2:]
    pasted, boxes = [], []
    for image, (x, y) in zip(images, positions):
        image = image.clone()
        image[:, y:y + h, x:x + w] = patch
        pasted.append(image)
        boxes.append([x, y, x + w, y + h])
    return pasted, torch.tensor(boxes, dtype=torch.float64)


def inside_boxes(tracks: Tensor, boxes: Tensor, margin: float = 4.0) -> Tensor:
    """(F, N, 2) points against (F, 4) boxes grown by ``margin`` px: (N,) True where any frame's
    point lies in its frame's box."""
    low, high = boxes[:, None, :2] - margin, boxes[:, None, 2:] + margin
    return ((tracks >= low) & (tracks <= high)).all(-1).any(0)


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


def board_poses(num_views: int, seed: int, distance: float = 10.0, spread: float = 2.5) -> tuple[Tensor, Tensor]:
    """Seeded board-to-camera poses for calibration tests: a 9 x 7 board of unit squares (its
    middle at (4, 3)) ``distance`` units away, shifted up to ``spread`` units sideways, tilted
    15-40 degrees about a random in-plane axis and turned up to 20 degrees about the view axis.
    Returns R (V, 3, 3), t (V, 3)."""
    g = torch.Generator().manual_seed(seed)
    R, t = [], []
    for _ in range(num_views):
        axis_angle = _uniform((), 0, 2 * math.pi, g)
        tilt = _uniform((), 15, 40, g) * math.pi / 180
        axis = torch.stack([axis_angle.cos(), axis_angle.sin(), torch.zeros((), dtype=torch.float64)])
        turn = torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64) * _uniform((), -20, 20, g) * math.pi / 180
        rotation = axis_angle_to_rotation(axis * tilt) @ axis_angle_to_rotation(turn)
        centre = torch.tensor([4.0, 3.0, 0.0], dtype=torch.float64)  # the middle of a 9 x 7 pattern, unit squares
        offset = torch.stack([_uniform((), -spread, spread, g), _uniform((), -0.75 * spread, 0.75 * spread, g),
                              _uniform((), distance - 1, distance + 1, g)])
        R.append(rotation)
        t.append(offset - rotation @ centre)
    return torch.stack(R), torch.stack(t)


def render_chessboard(K: Tensor, distortion: Tensor, R: Tensor, t: Tensor, pattern: tuple[int, int],
                      size: tuple[int, int] = (640, 480), supersample: int = 3) -> Tensor:
    """A (1, H, W) uint8 photo of a chessboard with (cols, rows) inner corners at (i, j) board
    units (unit squares), a one-square white margin, on a grey background, seen by a camera with
    radial distortion (k1, k2) at pose (R, t); anti-aliased by ``supersample``² samples a pixel."""
    W, H = size
    cols, rows = pattern
    ys, xs = torch.meshgrid((torch.arange(H * supersample, dtype=torch.float64) + 0.5) / supersample - 0.5,
                            (torch.arange(W * supersample, dtype=torch.float64) + 0.5) / supersample - 0.5, indexing="ij")
    ideal = undistort_normalized(pixels_to_normalized(torch.stack([xs, ys], dim=-1).reshape(-1, 2), K), distortion)
    plane = torch.linalg.inv(torch.stack([R[:, 0], R[:, 1], t], dim=-1))  # normalized image -> board plane
    board = to_homogeneous(ideal) @ plane.T
    in_front = board[:, 2] > 0
    u, v = board[:, 0] / board[:, 2], board[:, 1] / board[:, 2]
    squares = (u > -1) & (u < cols) & (v > -1) & (v < rows) & in_front
    margin = (u > -2) & (u < cols + 1) & (v > -2) & (v < rows + 1) & in_front
    dark = ((torch.floor(u) + torch.floor(v)) % 2 == 0) & squares
    value = torch.where(dark, 0.08, torch.where(margin, 0.92, 0.5))
    value = value.reshape(H, supersample, W, supersample).mean((1, 3))
    return (value * 255).round().clamp(0, 255).to(torch.uint8)[None]


def render_corner_scene(texture: Tensor, K: Tensor, distortion: Tensor, R: Tensor, t: Tensor,
                        size: tuple[int, int] = (640, 480), supersample: int = 2) -> Tensor:
    """A (3, H, W) uint8 photo of a textured building corner seen by a camera with radial
    distortion (k1, k2) at pose (R, t) (camera from world).

    The scene: two walls meeting at the line x = 0, z = 10 (apex towards the camera), the left
    one on x + z = 10 (x <= 0), the right one on -x + z = 10 (x >= 0), from y = -6 to 6, each
    covered by the texture (C, h, w) stretched over 12 × 12 units; grey elsewhere.
    """
    W, H = size
    ys, xs = torch.meshgrid((torch.arange(H * supersample, dtype=torch.float64) + 0.5) / supersample - 0.5,
                            (torch.arange(W * supersample, dtype=torch.float64) + 0.5) / supersample - 0.5, indexing="ij")
    rays = to_homogeneous(undistort_normalized(pixels_to_normalized(torch.stack([xs, ys], -1).reshape(-1, 2), K), distortion))
    origin = -R.T @ t
    direction = rays @ R  # world directions (rows: Rᵀ d)
    colour = torch.full((rays.shape[0], texture.shape[0]), 0.5, dtype=torch.float64)
    for side in (-1.0, 1.0):  # the wall side * x + z = 10 restricted to side * x >= 0... left wall: x <= 0
        normal = torch.tensor([-side, 0.0, 1.0], dtype=torch.float64)  # left wall (side -1): x + z = 10
        depth = (10 - normal @ origin) / (direction @ normal)
        hit = origin + depth[:, None] * direction
        along = (hit[:, 0] ** 2 + (hit[:, 2] - 10) ** 2).sqrt()  # distance from the corner line
        on_wall = (depth > 0) & (side * hit[:, 0] >= 0) & (along <= 12) & (hit[:, 1].abs() <= 6)
        u = along / 12 * 2 - 1 if side > 0 else 1 - along / 12 * 2  # texture x in [-1, 1], mirrored on the left
        v = hit[:, 1] / 6
        grid = torch.stack([u, v], -1).float()[None, None]
        sampled = torch.nn.functional.grid_sample(texture.float()[None] / 255, grid, align_corners=True)[0, :, 0].T.double()
        colour = torch.where(on_wall[:, None], sampled, colour)
    image = colour.reshape(H, supersample, W, supersample, -1).mean((1, 3)).permute(2, 0, 1)
    return (image * 255).round().clamp(0, 255).to(torch.uint8)


def wide_angle_camera() -> tuple[Tensor, Tensor]:
    """K and (k1, k2) of a 640×480 wide-angle camera with barrel distortion, for calibration tests."""
    K = torch.tensor([[500.0, 0.0, 330.0], [0.0, 495.0, 235.0], [0.0, 0.0, 1.0]], dtype=torch.float64)
    return K, torch.tensor([-0.25, 0.08], dtype=torch.float64)


def visible_board_poses(count: int, seed: int, K: Tensor, distortion: Tensor, pattern: tuple[int, int] = (9, 7),
                        size: tuple[int, int] = (640, 480), margin: float = 15.0) -> tuple[Tensor, Tensor]:
    """``count`` poses of :func:`board_poses` whose corners all lie ``margin`` px inside the image."""
    from torchsfm.calibration.zhang import board_points, project_board

    R, t = board_poses(4 * count, seed)
    pixels = project_board(K, distortion, R, t, board_points(pattern, 1.0))
    inside = ((pixels[..., 0] > margin) & (pixels[..., 0] < size[0] - 1 - margin) & (pixels[..., 1] > margin)
              & (pixels[..., 1] < size[1] - 1 - margin)).all(-1)
    keep = torch.nonzero(inside).flatten()[:count]
    if keep.numel() < count:
        raise ValueError(f"only {keep.numel()} of {4 * count} poses show the whole board")
    return R[keep], t[keep]
