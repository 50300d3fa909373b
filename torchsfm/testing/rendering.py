"""Synthetic images with known geometry: blurred squares with exact corners, chessboards and
textured corners through a distorting camera, an object pasted into real frames."""

from __future__ import annotations


import torch
from torch import Tensor

from torchsfm.camera import pixels_to_normalized, to_homogeneous, undistort_normalized


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


def patch_coordinates(model, boxes: Tensor) -> tuple[Tensor, Tensor]:
    """Where a model's points lie on a pasted patch: ``model`` a
    :class:`~torchsfm.reconstruction.Reconstruction` whose ``view_indices`` index the (V, 4)
    ``boxes`` (:func:`insert_moving_patch`). Returns (P,) bool, the point seen inside its view's
    box in every view it is seen in, and (P, 2) float64 its mean position relative to the box's
    top-left corner — its pixel in the patch — NaN where it is not on the patch."""
    box = boxes[torch.tensor(model.view_indices)[model.observation_views]]  # (O, 4)
    inside = ((model.keypoints >= box[:, :2]) & (model.keypoints <= box[:, 2:])).all(-1)
    seen = torch.bincount(model.observation_points, minlength=model.num_points).double()
    on_patch = torch.zeros(model.num_points, dtype=torch.float64).index_add_(0, model.observation_points, inside.double()) == seen
    uv = torch.zeros(model.num_points, 2, dtype=torch.float64).index_add_(0, model.observation_points, model.keypoints.double() - box[:, :2])
    return on_patch, torch.where(on_patch[:, None], uv / seen[:, None], torch.nan)
