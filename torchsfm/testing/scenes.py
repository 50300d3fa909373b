"""Seeded synthetic scenes with ground truth: two calibrated views, a moving camera among
independently moving objects, calibration-board poses."""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
from torch import Tensor

from torchsfm.camera import project, projection_matrix
from torchsfm.geometry.fundamental import epipolar_line_distances, fundamental_from_pose
from torchsfm.geometry.rotation import axis_angle_to_rotation


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
        points: (N, 3) each track's point in the world at frame 0 (an object's point moves with
            it as above); NaN for outliers.
    """

    K: Tensor
    R: Tensor
    t: Tensor
    tracks: Tensor
    labels: Tensor
    image_size: tuple[int, int]
    object_rotations: Tensor
    object_centres: Tensor
    points: Tensor

    def motion_labels(self, min_tracks: int) -> Tensor:
        """(N,) ``labels`` with every motion of fewer than ``min_tracks`` tracks (an object mostly
        out of view) counted as outliers (-1) and the others renumbered in their order: the
        motions a segmentation can find."""
        counted = self.labels >= 0
        label = self.labels.clamp_min(0)
        kept = torch.bincount(label[counted], minlength=int(self.labels.max()) + 1) >= min_tracks
        return torch.where(counted & kept[label], (torch.cumsum(kept, 0) - 1)[label], -1)

    def body_cameras(self, body: int) -> tuple[Tensor, Tensor]:
        """The camera's true poses relative to object ``body`` (1..k) in every frame, (F, 3, 3) and
        (F, 3): the object's frame is the world at frame 0, so they are R_f O_f and
        R_f (c_f - O_f c_0) + t_f (O the object's rotations, c its centres)."""
        O, c = self.object_rotations[body - 1], self.object_centres[body - 1]
        return self.R @ O, (self.R @ (c - (O @ c[0][:, None])[..., 0])[..., None])[..., 0] + self.t


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
    tracks, labels, points = [pixels[:, keep]], [torch.zeros(keep.numel(), dtype=torch.long)], [static[keep]]
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
        points.append(body[chosen])
        labels.append(torch.full((chosen.numel(),), k, dtype=torch.long))
    tracks = torch.cat(tracks, 1)
    tracks = tracks + noise * torch.randn(tracks.shape, generator=g, dtype=torch.float64)
    labels = torch.cat(labels)
    num_outliers = round(outlier_fraction * labels.numel() / (1 - outlier_fraction))
    outliers = torch.stack([_uniform((num_frames, num_outliers), 0, W, g), _uniform((num_frames, num_outliers), 0, H, g)], -1)
    tracks = torch.cat([tracks, outliers], 1)
    labels = torch.cat([labels, torch.full((num_outliers,), -1, dtype=torch.long)])
    points = torch.cat([*points, torch.full((num_outliers, 3), torch.nan, dtype=torch.float64)])
    order = torch.randperm(labels.numel(), generator=g)
    return MovingObjectScene(K=K, R=R, t=t, tracks=tracks[:, order], labels=labels[order], image_size=(W, H),
                             object_rotations=object_rotations, object_centres=object_centres, points=points[order])


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


def sliding_plane_scene(noise: float, seed: int = 0) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """80 points on a 1.5 m square of the plane Z = 5 m, off the optical axis, seen by 5 cameras
    that slide along the plane without turning (K: f = 700 px, 640×480): the homography of
    frames 0-1 has a twin motion that puts every point in front of both cameras. Returns tracks
    (5, 80, 2) with ``noise`` px of Gaussian noise, K (3, 3), R (5, 3, 3), t (5, 3); float64."""
    generator = torch.Generator().manual_seed(seed)
    X = torch.cat([1.5 * torch.rand(80, 2, generator=generator, dtype=torch.float64) - 2.2,
                   torch.full((80, 1), 5.0, dtype=torch.float64)], dim=-1)
    K = torch.tensor([[700.0, 0, 320], [0, 700, 240], [0, 0, 1]], dtype=torch.float64)
    C = torch.tensor([[0.4 * f * (1 if f % 2 else 0.7), -0.15 * f * (f % 3), 0.0] for f in range(5)], dtype=torch.float64)
    R, t = torch.eye(3, dtype=torch.float64).expand(5, 3, 3), -C
    projected = (X[None] + t[:, None]) @ K.T
    tracks = projected[..., :2] / projected[..., 2:] + noise * torch.randn(5, 80, 2, generator=generator, dtype=torch.float64)
    return tracks, K, R, t
