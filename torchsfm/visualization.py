"""Pictures a person can look at: matches and epipolar lines drawn with tensor ops, saved as PNG."""

from __future__ import annotations

from pathlib import Path

import kornia.io
import torch
from torch import Tensor

from torchsfm.io.atomic import atomic_write_bytes

GREEN = (40, 220, 60)
RED = (230, 40, 40)
YELLOW = (250, 220, 30)


def _as_rgb_uint8(image: Tensor) -> Tensor:
    image = image if image.dtype == torch.uint8 else (image.float().clamp(0, 1) * 255).round().to(torch.uint8)
    return image.expand(3, -1, -1).clone() if image.shape[0] == 1 else image.clone()


def draw_segments(canvas: Tensor, starts: Tensor, ends: Tensor, color: tuple[int, int, int]) -> None:
    """Draw (S, 2) → (S, 2) pixel segments into a (3, H, W) uint8 canvas, in place."""
    if starts.numel() == 0:
        return
    length = int((ends - starts).norm(dim=-1).max().ceil().item()) + 1
    steps = torch.linspace(0, 1, length, dtype=starts.dtype)
    samples = (starts[:, None] + steps[None, :, None] * (ends - starts)[:, None]).reshape(-1, 2).round().long()
    H, W = canvas.shape[-2:]
    inside = (samples[:, 0] >= 0) & (samples[:, 0] < W) & (samples[:, 1] >= 0) & (samples[:, 1] < H)
    samples = samples[inside]
    canvas[:, samples[:, 1], samples[:, 0]] = torch.tensor(color, dtype=torch.uint8)[:, None]


def draw_points(canvas: Tensor, points: Tensor, color: tuple[int, int, int], radius: int = 1) -> None:
    """Draw (P, 2) pixels as small squares, in place."""
    offsets = torch.arange(-radius, radius + 1)
    dy, dx = torch.meshgrid(offsets, offsets, indexing="ij")
    pixels = points.round().long()[:, None] + torch.stack([dx.flatten(), dy.flatten()], -1)[None]
    draw_segments(canvas, pixels.reshape(-1, 2).to(points.dtype), pixels.reshape(-1, 2).to(points.dtype), color)


def epipolar_segments(F: Tensor, x1: Tensor, width: int, height: int) -> tuple[Tensor, Tensor]:
    """Where the epipolar lines F x1 of (S, 2) points cross image 2: start and end (S, 2) each."""
    lines = torch.cat([x1, torch.ones_like(x1[:, :1])], -1) @ F.T  # a x + b y + c = 0
    a, b, c = lines.unbind(-1)
    steep = b.abs() < a.abs()
    x_at = lambda y: -(b * y + c) / torch.where(a.abs() > 1e-12, a, 1e-12)  # noqa: E731
    y_at = lambda x: -(a * x + c) / torch.where(b.abs() > 1e-12, b, 1e-12)  # noqa: E731
    zero, last_x, last_y = torch.zeros_like(a), torch.full_like(a, width - 1.0), torch.full_like(a, height - 1.0)
    start = torch.where(steep[:, None], torch.stack([x_at(zero), zero], -1), torch.stack([zero, y_at(zero)], -1))
    end = torch.where(steep[:, None], torch.stack([x_at(last_y), last_y], -1), torch.stack([last_x, y_at(last_x)], -1))
    return start, end


def _spread(mask: Tensor, count: int) -> Tensor:
    """Up to ``count`` indices of True entries, evenly spaced through the mask."""
    chosen = torch.nonzero(mask).flatten()
    if chosen.numel() <= count:
        return chosen
    return chosen[torch.linspace(0, chosen.numel() - 1, count).round().long()]


def matches_figure(image1: Tensor, image2: Tensor, x1: Tensor, x2: Tensor, inliers: Tensor, F: Tensor,
                   max_matches: int = 150, num_epipolar_lines: int = 20) -> Tensor:
    """Side-by-side picture: a spread of up to ``max_matches`` inlier matches (green) and a quarter
    as many rejected ones (red), with the epipolar lines (yellow) of ``num_epipolar_lines``
    inliers drawn in image 2. Images (C, H, W); returns (3, H, 2W) uint8."""
    left, right = _as_rgb_uint8(image1), _as_rgb_uint8(image2)
    H, W = left.shape[-2:]
    canvas = torch.cat([left, right], dim=-1)
    shift = torch.tensor([float(W), 0.0], dtype=x1.dtype)
    rejected, kept = _spread(~inliers, max_matches // 4), _spread(inliers, max_matches)
    draw_segments(canvas, x1[rejected], x2[rejected] + shift, RED)
    draw_segments(canvas, x1[kept], x2[kept] + shift, GREEN)
    chosen = _spread(inliers, num_epipolar_lines)
    start, end = epipolar_segments(F.to(x1.dtype), x1[chosen], W, H)
    draw_segments(canvas, start + shift, end + shift, YELLOW)
    draw_points(canvas, x1[chosen], YELLOW, radius=2)
    return canvas


def write_png(path: str | Path, image: Tensor) -> None:
    """Write a (3, H, W) uint8 image as PNG, atomically (encoded by Kornia, then renamed)."""
    path = Path(path)
    temporary = path.with_name(f".{path.stem}.encoding.png")
    path.parent.mkdir(parents=True, exist_ok=True)
    try:
        kornia.io.write_image(temporary, image.contiguous())
        atomic_write_bytes(path, temporary.read_bytes())
    finally:
        temporary.unlink(missing_ok=True)


def corners_figure(image: Tensor, corners: Tensor, pattern: tuple[int, int]) -> Tensor:
    """A (3, H, W) uint8 copy of the image with detected chessboard corners: rows joined in
    yellow, corners green, the first corner (the board's origin) red."""
    canvas = _as_rgb_uint8(image)
    cols, rows = pattern
    grid = corners.reshape(rows, cols, 2)
    draw_segments(canvas, grid[:, :-1].reshape(-1, 2), grid[:, 1:].reshape(-1, 2), YELLOW)
    radius = max(2, round(max(canvas.shape[-2:]) / 400))
    draw_points(canvas, corners, GREEN, radius)
    draw_points(canvas, corners[:1], RED, 2 * radius)
    return canvas


MOTION_COLOURS = ((150, 150, 150), (230, 40, 40), (40, 120, 230), (40, 200, 60), (240, 170, 20), (190, 60, 210),
                  (20, 200, 200), (140, 90, 40))


def segmentation_figure(tracks: Tensor, visible: Tensor, labels: Tensor, size: tuple[int, int],
                        image: Tensor | None = None) -> Tensor:
    """A (3, H, W) uint8 picture of segmented tracks: every track's path over the frames it is
    seen in, coloured by its (N,) label (0 the static scene grey, 1.. the moving bodies in
    colours, -1 unassigned black), its last position as a dot; over ``image`` (a frame) if given,
    else on white. tracks (F, N, 2) pixels, visible (F, N), size (width, height)."""
    W, H = size
    canvas = _as_rgb_uint8(image) if image is not None else torch.full((3, H, W), 255, dtype=torch.uint8)
    steps = visible[:-1] & visible[1:]  # (F - 1, N) consecutive frames both seen
    for label in labels.unique().tolist():
        colour = (0, 0, 0) if label < 0 else MOTION_COLOURS[label % len(MOTION_COLOURS)]
        mine = (labels == label)[None] & steps
        draw_segments(canvas, tracks[:-1][mine], tracks[1:][mine], colour)
        seen = visible & (labels == label)[None]
        last = (torch.arange(tracks.shape[0], device=tracks.device)[:, None] * seen).argmax(0)  # (N,)
        ends = tracks[last, torch.arange(tracks.shape[1], device=tracks.device)][labels == label]
        draw_points(canvas, ends, colour, radius=max(1, round(max(W, H) / 400)))
    return canvas
