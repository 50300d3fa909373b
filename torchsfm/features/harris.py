"""Harris corners with the biquadric sub-pixel fit of thesis §3.2.1 and Appendix B.

Algorithm 3.2.1, batched over images (B, 1, H, W): Sobel gradients, an N×N Gaussian on their
products, R = det M - k trace² M, non-maximum suppression in N×N windows, a threshold relative to
the image's strongest response, the best ``max_corners`` (optionally spread over a grid of
cells), and the peak of a least-squares biquadric fitted to R on the same N×N support (the
thesis recommends one N throughout). Gradients and blur come from Kornia.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
import torch.nn.functional as functional
from kornia.filters import gaussian_blur2d
from torch import Tensor, nn

from torchsfm.config import HarrisConfig
from torchsfm.errors import InputError, ShapeError
from torchsfm.features.filters import sobel_gradients, window_maximum


@dataclass
class Corners:
    """Corners of B images, padded to the largest count.

    Fields:
        positions: (B, K, 2) pixels (x, y), top-left pixel centre at (0, 0).
        scores: (B, K) Harris response at the corner pixel.
        valid: (B, K) bool, False for padding.
    """

    positions: Tensor
    scores: Tensor
    valid: Tensor

    def of_image(self, b: int) -> Tensor:
        """The (K_b, 2) valid positions of image b."""
        return self.positions[b][self.valid[b]]


def gaussian_sigma(window: int) -> float:
    """The σ OpenCV pairs with an N×N Gaussian kernel: 0.3 ((N - 1) / 2 - 1) + 0.8."""
    return 0.3 * ((window - 1) * 0.5 - 1) + 0.8


RESPONSE_CHUNK_PIXELS = 2**20  # pixels per filtering call: Kornia's intermediates take ~150 bytes a pixel


def harris_response(image: Tensor, k: float = 0.04, window: int = 3) -> Tensor:
    """R = det M - k trace² M with M the N×N-Gaussian-smoothed gradient products (eq. 3.2.2-3.2.3).

    image (B, 1, H, W) float -> (B, 1, H, W); filtered a few images at a time (at most
    ``RESPONSE_CHUNK_PIXELS`` pixels, at least one image), so a long video's batch needs memory for
    its response only, not for the filters' intermediate maps of every image at once.
    """
    chunk = max(1, RESPONSE_CHUNK_PIXELS // (image.shape[-2] * image.shape[-1]))
    if image.shape[0] > chunk:
        return torch.cat([harris_response(image[first:first + chunk], k, window) for first in range(0, image.shape[0], chunk)])
    dx, dy = sobel_gradients(image)  # (B, 1, H, W) each
    sigma = gaussian_sigma(window)
    products = gaussian_blur2d(torch.cat([dx * dx, dy * dy, dx * dy], dim=1), window, (sigma, sigma))
    xx, yy, xy = products[:, 0:1], products[:, 1:2], products[:, 2:3]
    return xx * yy - xy * xy - k * (xx + yy) ** 2


def _biquadric_solver(window: int, dtype: torch.dtype, device: torch.device) -> Tensor:
    """Pseudo-inverse (6, N²) of the design matrix of eq. B.2 on the N×N offsets (row-major)."""
    half = window // 2
    ys, xs = torch.meshgrid(torch.arange(-half, half + 1, dtype=dtype, device=device), torch.arange(-half, half + 1, dtype=dtype, device=device), indexing="ij")
    x, y = xs.flatten(), ys.flatten()
    design = torch.stack([x * x, y * y, x * y, x, y, torch.ones_like(x)], dim=-1)
    return torch.linalg.pinv(design)


def biquadric_peaks(response: Tensor, pixels: Tensor, window: int) -> tuple[Tensor, Tensor]:
    """Sub-pixel peaks of R around integer pixels by the biquadric fit of Appendix B.

    Args:
        response: (1, H, W) Harris response of one image.
        pixels: (K, 2) integer (x, y) corner pixels at least window // 2 from the border.
        window: N, the fit's support.

    Returns:
        Offsets (K, 2) to add to the pixels (eq. B.6) and a (K,) bool mask of fits that have a
        proper maximum inside the support; other offsets are 0.
    """
    half = window // 2
    steps = torch.arange(-half, half + 1, device=pixels.device)
    padded = functional.pad(response, (half, half, half, half))[0]  # zeros outside, as the fit has always seen them
    values = padded[pixels[:, 1, None, None] + half + steps[:, None], pixels[:, 0, None, None] + half + steps]  # (K, N, N)
    offsets, proper = biquadric_offsets(values.flatten(1).double(), window)
    return offsets.to(response.dtype), proper


def biquadric_offsets(values: Tensor, window: int) -> tuple[Tensor, Tensor]:
    """The maxima of (K, N²) samples on the N×N offsets around their centres (row-major) by the
    biquadric fit of Appendix B: offsets (K, 2) (x, y) from the centre (eq. B.6) and a (K,)
    bool mask of fits that have a proper maximum inside the support; other offsets are 0."""
    K1, K2, K3, K4, K5, _ = (values @ _biquadric_solver(window, values.dtype, values.device).T).unbind(-1)
    determinant = 4 * K1 * K2 - K3 * K3
    x0 = (K3 * K5 - 2 * K2 * K4) / determinant
    y0 = (K3 * K4 - 2 * K1 * K5) / determinant
    offsets = torch.stack([x0, y0], dim=-1)
    proper = (determinant > 0) & (K1 < 0) & (offsets.abs() <= 0.5 * window).all(-1) & torch.isfinite(offsets).all(-1)
    return torch.where(proper[:, None], offsets, 0.0), proper


def _select(scores: Tensor, width: int, height: int, config: HarrisConfig) -> Tensor:
    """Indices (into a flattened H×W map) of the corners kept from a map of candidate scores.

    With ``spread_grid`` G > 0, each of the G×G cells first contributes its best
    ceil(max_corners / G²) corners; the remaining budget goes to the best of the rest.
    """
    candidates = torch.nonzero(torch.isfinite(scores)).flatten()
    order = candidates[torch.argsort(scores[candidates], descending=True)]
    if config.spread_grid == 0 or order.numel() <= config.max_corners:
        return order[: config.max_corners]
    grid = config.spread_grid
    x, y = order % width, order // width
    cell = (y * grid // height) * grid + (x * grid // width)
    by_cell = torch.argsort(cell, stable=True)  # grouped by cell, best first inside each cell
    counts = torch.bincount(cell, minlength=grid * grid)
    starts = torch.cumsum(counts, 0) - counts
    rank = torch.empty_like(by_cell)
    rank[by_cell] = torch.arange(by_cell.numel(), device=by_cell.device) - starts[cell[by_cell]]
    quota = math.ceil(config.max_corners / (grid * grid))
    first = order[rank < quota]
    rest = order[rank >= quota]
    chosen = torch.cat([first, rest])[: config.max_corners]
    return chosen


def detect_corners(image: Tensor, config: HarrisConfig | None = None, mask: Tensor | None = None) -> Corners:
    """Harris corners of a batch of grey images (Algorithm 3.2.1).

    Args:
        image: (B, 1, H, W) float intensities (any range; the threshold is relative).
        config: response, suppression, selection and sub-pixel settings.
        mask: (B, H, W) bool, where corners may be (e.g. not on a video's fixed overlay); the
            relative threshold is then taken over those pixels only. Default: everywhere.

    Returns:
        :class:`Corners` padded to the largest count in the batch.

    Raises:
        InputError: images too small to hold a corner inside the border.
    """
    config = config or HarrisConfig()
    B, _, H, W = image.shape
    smallest = 2 * max(config.border, config.window // 2) + 1
    if min(H, W) < smallest:
        raise InputError(f"images of {W}x{H} px are too small for Harris corners: a corner lies {config.border} px "
                         f"(harris.border) inside the image, so each side needs {smallest} px")
    response = harris_response(image, config.k, config.window)
    half = config.window // 2
    is_peak = response == window_maximum(response, half)
    border = max(config.border, half)
    inside = torch.zeros_like(is_peak)
    inside[..., border:H - border, border:W - border] = True
    if mask is not None:
        if mask.shape != (B, H, W):
            raise ShapeError(f"mask must be ({B}, {H}, {W}) like the images, got {tuple(mask.shape)}")
        inside &= mask[:, None]
    usable = response if mask is None else torch.where(mask[:, None], response, 0.0)
    strongest = usable.flatten(1).amax(-1).clamp_min(1e-30)[:, None, None, None]
    keep = is_peak & inside & (response > config.relative_threshold * strongest)
    positions, scores = [], []
    for b in range(B):
        candidate_scores = torch.where(keep[b, 0], response[b, 0], float("-inf")).flatten()
        chosen = _select(candidate_scores, W, H, config)
        pixels = torch.stack([chosen % W, chosen // W], dim=-1)
        position = pixels.to(image.dtype)
        if config.subpixel and chosen.numel():
            offsets, _ = biquadric_peaks(response[b], pixels, config.window)
            position = position + offsets
        positions.append(position)
        scores.append(response[b, 0].flatten()[chosen])
    count = max((p.shape[0] for p in positions), default=0)
    valid = torch.zeros(B, count, dtype=torch.bool, device=image.device)
    padded = image.new_zeros(B, count, 2)
    padded_scores = image.new_zeros(B, count)
    for b, (position, score) in enumerate(zip(positions, scores)):
        valid[b, : position.shape[0]] = True
        padded[b, : position.shape[0]] = position
        padded_scores[b, : score.shape[0]] = score
    return Corners(positions=padded, scores=padded_scores, valid=valid)


class HarrisCorners(nn.Module):
    """Pipeline stage: (B, 1, H, W) grey images -> :class:`Corners` (see :func:`detect_corners`)."""

    def __init__(self, config: HarrisConfig | None = None) -> None:
        super().__init__()
        self.config = config or HarrisConfig()

    def forward(self, image: Tensor) -> Corners:
        return detect_corners(image, self.config)

    def extra_repr(self) -> str:
        return repr(self.config)
