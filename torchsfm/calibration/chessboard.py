"""Chessboard inner-corner detection in torch/Kornia: saddle points → lattice → sub-pixel corners.

1. Candidates: the inner corners of a chessboard are saddle points of the intensity. On a
   Gaussian-smoothed copy of the image (long side scaled to at most ``detection_size`` px) the
   saddle response ``Ixy² − Ixx·Iyy`` (minus the Hessian determinant) is large there; its local
   maxima are kept if the intensity on a circle around them alternates dark/bright exactly four
   times (an X-junction, not a blob or an edge end).
2. Lattice: from a seed candidate and its two nearest neighbours along independent directions, the
   grid grows breadth-first: each next node is predicted by linear extrapolation along its row or
   column and takes the nearest unused candidate within ``search_radius`` × the local spacing.
   The board is found when the grown grid spans exactly the pattern (in either orientation) with
   at most ``max_missing`` holes, which are filled by prediction.
3. Order: the pattern's first dimension runs along the grid axis closest to image +x, the second
   along image +y (never mirrored); corners come row by row.
4. Sub-pixel: gradient orthogonality (Förstner; OpenCV's cornerSubPix): within a window every
   gradient is orthogonal to the vector from the corner, so q = (Σ g gᵀ)⁻¹ Σ g gᵀ p, iterated,
   batched over all corners.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import kornia
import torch
import torch.nn.functional as F
from torch import Tensor

from torchsfm.config import ChessboardConfig
from torchsfm.errors import InputError
from torchsfm.features.filters import sobel_gradients, sobel_second_derivatives, window_maximum
from torchsfm.images import check_image, to_grey
from torchsfm.inference import without_autograd

NEIGHBOURS = ((1, 0), (-1, 0), (0, 1), (0, -1))


@dataclass
class ChessboardDetection:
    """Outcome of :func:`detect_chessboard`.

    Fields:
        corners: (cols * rows, 2) float64 pixels, row by row, or None when not found.
        reason: why the board was not found (None when found).
        candidates: number of saddle-point candidates considered.
    """

    corners: Tensor | None
    reason: str | None
    candidates: int

    @property
    def found(self) -> bool:
        return self.corners is not None


def saddle_candidates(grey: Tensor, config: ChessboardConfig) -> tuple[Tensor, Tensor]:
    """X-junction candidates of a (1, H, W) float image: positions (K, 2) and responses (K,)."""
    sigma = config.sigma
    size = 2 * math.ceil(3 * sigma) + 1
    smooth = kornia.filters.gaussian_blur2d(grey[None], (size, size), (sigma, sigma))
    xx, xy, yy = sobel_second_derivatives(smooth[0, 0])
    response = (xy.square() - xx * yy).clamp_min(0)
    peak = window_maximum(response, config.nms_radius)
    keep = (response == peak) & (response > config.relative_threshold * response.max())
    y, x = torch.nonzero(keep, as_tuple=True)
    strength = response[y, x]
    order = torch.argsort(strength, descending=True)[: config.max_candidates]
    points = torch.stack([x[order], y[order]], dim=-1).to(grey.dtype)
    junction = _is_x_junction(smooth[0], points, config)
    return points[junction], strength[order][junction]


def _sample(image: Tensor, points: Tensor) -> Tensor:
    """Bilinear samples of a (C, H, W) image at (..., 2) pixel positions: (C, ...)."""
    H, W = image.shape[-2:]
    flat = points.reshape(1, -1, 1, 2)
    grid = torch.stack([2 * flat[..., 0] / (W - 1) - 1, 2 * flat[..., 1] / (H - 1) - 1], dim=-1).to(image.dtype)
    values = F.grid_sample(image[None], grid, align_corners=True, padding_mode="border")[0, :, :, 0]
    return values.reshape(image.shape[0], *points.shape[:-1])


def _is_x_junction(smooth: Tensor, points: Tensor, config: ChessboardConfig) -> Tensor:
    """(K,) True where the intensity on a circle around the point changes sign exactly 4 times."""
    if points.numel() == 0:
        return torch.zeros(0, dtype=torch.bool)
    angles = torch.arange(24, dtype=points.dtype) * (2 * math.pi / 24)
    circle = config.junction_radius * torch.stack([angles.cos(), angles.sin()], dim=-1)
    ring = _sample(smooth, points[:, None, :] + circle)[0]  # (K, 24)
    centred = ring - ring.mean(-1, keepdim=True)
    signs = centred > 0
    changes = (signs != signs.roll(1, dims=-1)).sum(-1)
    contrast = ring.amax(-1) - ring.amin(-1)
    return (changes == 4) & (contrast > config.min_contrast)


def _grow(points: Tensor, seed: int, config: ChessboardConfig) -> dict[tuple[int, int], int] | None:
    """Grid coordinates → candidate index, grown from ``seed``; None if the seed has no lattice."""
    distances = torch.cdist(points[seed:seed + 1], points)[0]
    distances[seed] = float("inf")
    near = torch.argsort(distances)[:6]
    first = int(near[0])
    u = points[first] - points[seed]
    second = None
    for candidate in near[1:].tolist():
        v = points[candidate] - points[seed]
        cosine = float((u * v).sum() / (u.norm() * v.norm()))
        ratio = float(v.norm() / u.norm())
        if abs(cosine) < 0.5 and 0.5 < ratio < 2.0:
            second = candidate
            break
    if second is None:
        return None
    grid = {(0, 0): seed, (1, 0): first, (0, 1): second}
    used = {seed, first, second}

    def axis_step(node: tuple[int, int], axis: tuple[int, int]) -> Tensor | None:
        """p(n + axis) - p(n) at the grid node nearest to ``node`` that has such a pair."""
        pairs = [n for n in grid if (n[0] + axis[0], n[1] + axis[1]) in grid]
        if not pairs:
            return None
        n = min(pairs, key=lambda m: abs(m[0] - node[0]) + abs(m[1] - node[1]))
        return points[grid[(n[0] + axis[0], n[1] + axis[1])]] - points[grid[n]]

    queue = list(grid)
    while queue:
        node = queue.pop(0)
        for di, dj in NEIGHBOURS:
            target = (node[0] + di, node[1] + dj)
            if target in grid:
                continue
            behind = (node[0] - di, node[1] - dj)
            if behind in grid:  # linear extrapolation along the row or column
                step = points[grid[node]] - points[grid[behind]]
            else:
                step = axis_step(node, (abs(di), abs(dj)))
                if step is None:
                    continue
                step = step * (di + dj)
            predicted = points[grid[node]] + step
            gaps = (points - predicted).norm(dim=-1)
            best = int(torch.argmin(gaps))
            if best not in used and float(gaps[best]) < config.search_radius * float(step.norm()):
                grid[target] = best
                used.add(best)
                queue.append(target)
    return grid


def _fit_pattern(grid: dict[tuple[int, int], int], points: Tensor, strength: Tensor, pattern: tuple[int, int],
                 config: ChessboardConfig) -> Tensor | str:
    """(cols * rows, 2) ordered corners from a grown grid, or why it does not match the pattern.

    A grid larger than the pattern is cut to the pattern-sized window, in either orientation, with
    the fewest holes and the strongest saddles, if the corners left out are weak (stray junctions
    along the board's edge: below ``stray_strength`` × the window's mean saddle response);
    otherwise the board is larger than the pattern.
    """
    coordinates = torch.tensor(list(grid), dtype=torch.long)
    low = coordinates.amin(0)
    span = (coordinates.amax(0) - low + 1).tolist()
    cols, rows = pattern
    index = torch.full(span, -1, dtype=torch.long)
    index[coordinates[:, 0] - low[0], coordinates[:, 1] - low[1]] = torch.tensor(list(grid.values()))
    windows = []
    for a, b in {(cols, rows), (rows, cols)}:
        for i in range(span[0] - a + 1):
            for j in range(span[1] - b + 1):
                window = index[i:i + a, j:j + b]
                present = window >= 0
                holes = int((~present).sum())
                if holes <= config.max_missing:
                    windows.append((holes, -float(strength[window[present]].sum()), window))
    if not windows:
        return f"the largest corner lattice is {span[0]}x{span[1]}, with no complete {cols}x{rows} window"
    _, _, window = min(windows, key=lambda w: (w[0], w[1]))
    outside = torch.ones(span, dtype=torch.bool)
    outside[torch.isin(index, window)] = False
    extra = index[outside & (index >= 0)]
    inner = window[window >= 0]
    if extra.numel() and float(strength[extra].mean()) > config.stray_strength * float(strength[inner].mean()):
        return f"the corner lattice is {span[0]}x{span[1]}, larger than the {cols}x{rows} pattern"
    table = torch.where((window >= 0)[..., None], points[window.clamp_min(0)], torch.full_like(points[:1], float("nan")))
    for _ in range(config.max_missing):  # fill holes by linear prediction from complete neighbours
        for i, j in torch.nonzero(torch.isnan(table[..., 0])).tolist():
            guesses = [2 * table[i + a, j + b] - table[i + 2 * a, j + 2 * b]
                       for a, b in NEIGHBOURS if 0 <= i + 2 * a < table.shape[0] and 0 <= j + 2 * b < table.shape[1]]
            guesses = [g for g in guesses if torch.isfinite(g).all()]
            if guesses:
                table[i, j] = torch.stack(guesses).mean(0)
    if torch.isnan(table).any():
        return f"the {cols}x{rows} lattice has holes that cannot be filled"
    if table.shape[0] != cols:  # the first axis must hold the pattern's first dimension
        table = table.transpose(0, 1)
    # never mirrored: with the first axis along +x, the second must point along +y
    first_axis = (table[-1] - table[0]).mean(0)
    second_axis = (table[:, -1] - table[:, 0]).mean(0)
    if first_axis[0] * second_axis[1] - first_axis[1] * second_axis[0] < 0:
        table = table.flip(1)
    if (table[-1] - table[0]).mean(0)[0] < 0:  # first axis towards -x: rotate by 180 degrees
        table = table.flip(0).flip(1)
    return table.transpose(0, 1).reshape(-1, 2)


def refine_corners(grey: Tensor, corners: Tensor, half_window: int, iterations: int = 20) -> Tensor:
    """Gradient-orthogonality sub-pixel refinement of (K, 2) corners in a (1, H, W) float image.
    The gradients are computed over the corners' bounding box only, with a margin of three
    windows (a corner moves less than a window per iteration and settles within one or two)."""
    margin = 3 * half_window + 3
    low = (corners.amin(0).floor().long() - margin).clamp_min(0)
    high = corners.amax(0).ceil().long() + margin + 1
    crop = grey[:, int(low[1]):int(high[1]), int(low[0]):int(high[0])]
    gradients = torch.stack(sobel_gradients(crop[0].double()))  # (2, h, w)
    corners = corners - low.to(corners.dtype)
    offsets = torch.arange(-half_window, half_window + 1, dtype=torch.float64)
    dy, dx = torch.meshgrid(offsets, offsets, indexing="ij")
    window = torch.stack([dx, dy], dim=-1).reshape(-1, 2)  # (S, 2)
    weight = torch.exp(-window.square().sum(-1) / (2 * (half_window / 2) ** 2))
    q = corners.double().clone()
    for _ in range(iterations):
        p = q[:, None, :] + window  # (K, S, 2)
        g = _sample(gradients, p).permute(1, 2, 0)  # (K, S, 2)
        gg = weight[None, :, None, None] * g[..., :, None] * g[..., None, :]  # (K, S, 2, 2)
        A = gg.sum(1)
        b = (gg @ p[..., None]).sum(1)[..., 0]
        solvable = torch.linalg.det(A).abs() > 1e-12
        A = torch.where(solvable[:, None, None], A, torch.eye(2, dtype=A.dtype))
        new = torch.where(solvable[:, None], torch.linalg.solve(A, b), q)
        moved = (new - q).norm(dim=-1)
        q = torch.where((moved < half_window)[:, None], new, q)  # never leave the window
        if float(moved.max()) < 1e-3:
            break
    return q + low.to(q.dtype)


@without_autograd
def detect_chessboard(image: Tensor, pattern: tuple[int, int], config: ChessboardConfig | None = None) -> ChessboardDetection:
    """Find the (cols, rows) inner corners of a chessboard in a (3 or 1, H, W) image.

    Args:
        image: uint8 or float in [0, 1], colour or grey.
        pattern: inner corners per row and per column, e.g. (9, 7).
        config: detection settings.

    Returns:
        A :class:`ChessboardDetection`: ``corners`` (cols * rows, 2) float64 pixels row by row
        (first corner at the top left of the board as seen, rows along +x), or ``reason``.
    """
    config = config or ChessboardConfig()
    check_image(image)
    cols, rows = pattern
    if cols < 2 or rows < 2:
        raise InputError(f"a chessboard pattern needs at least 2x2 inner corners, got {cols}x{rows}")
    grey = to_grey(image)
    H, W = grey.shape[-2:]
    smallest = 2 * math.ceil(3 * config.sigma) + 2  # the saddle filter's support, plus one pixel
    if min(H, W) < smallest:
        return ChessboardDetection(None, f"the image ({H}x{W} px) is too small to hold a chessboard (needs {smallest} px a side)", 0)
    scale = min(1.0, config.detection_size / max(H, W))
    small = F.interpolate(grey[None], scale_factor=scale, mode="area")[0] if scale < 1 else grey
    points, strength = saddle_candidates(small, config)
    count = points.shape[0]
    if count < max(4, cols * rows - config.max_missing):
        return ChessboardDetection(None, f"only {count} chessboard-like corners (X-junctions) found, {cols * rows} needed", count)
    reason = "no corner lattice found"
    centre = points.mean(0)
    # seeds: the strongest candidates near the middle of the candidates first
    order = torch.argsort((points - centre).norm(dim=-1) / (points - centre).norm(dim=-1).max() - strength / strength.max())
    for seed in order[: config.seeds].tolist():
        grid = _grow(points.double(), seed, config)
        if grid is None or len(grid) < cols * rows - config.max_missing:
            continue
        fitted = _fit_pattern(grid, points.double(), strength.double(), pattern, config)
        if isinstance(fitted, str):
            reason = fitted
            continue
        corners = fitted / scale
        spacing = float((corners.reshape(rows, cols, 2)[:, 1:] - corners.reshape(rows, cols, 2)[:, :-1]).norm(dim=-1).median())
        half_window = int(min(max(round(0.3 * spacing), 2), config.max_half_window))
        low, high = torch.tensor([half_window, half_window]), torch.tensor([W - 1 - half_window, H - 1 - half_window])
        if bool(((corners < low) | (corners > high)).any()):
            reason = "the board is not entirely inside the image"
            continue
        return ChessboardDetection(refine_corners(grey, corners, half_window), None, count)
    return ChessboardDetection(None, reason, count)
