"""SIFT features (ours around Kornia's): Kornia's scale-space detector and RootSIFT descriptor
with the parts that dominated their time on a CPU rewritten to give Kornia's numbers — the
detector's non-maximum suppression (:class:`SlidingNonMaxima`, bit for bit), the patches at the
local affine frames (:func:`pyramid_patches`) and the descriptor's spatial pooling
(:class:`PooledSIFTDescriptor`, both up to rounding) — and mutual nearest neighbours passing
Lowe's ratio test (:func:`mutual_ratio_matches`, Kornia's ``match_smnn`` pairs). Used by the
N-view pipeline's SIFT stages and bridge (:mod:`torchsfm.sfm.sift`)."""

from __future__ import annotations

import math

import torch
import torch.nn.functional as F
from torch import Tensor, nn
from kornia.feature import LAFOrienter, SIFTDescriptor, SIFTFeature, get_laf_center, get_laf_orientation, laf_is_filled, \
    set_laf_orientation
from kornia.geometry.subpix import NonMaximaSuppression2d
from kornia.geometry.transform import pyrdown

from torchsfm.features.filters import central_differences, running_maximum
from torchsfm.images import inside_mask, to_unit_float
from torchsfm.threads import map_in_threads


def mutual_ratio_matches(descriptors1: Tensor, descriptors2: Tensor, ratio: float) -> Tensor:
    """(M, 2) index pairs of (N1, D) and (N2, D) descriptors that are each other's nearest
    (Euclidean) neighbours and pass Lowe's ratio test both ways, nearest over second-nearest
    distance at most ``ratio``: Kornia's ``match_smnn``, rows in ascending order of the first
    index, none where either side has fewer than two descriptors. One matrix of squared
    distances (one product, as ``cdist`` makes it) read both ways: each row's nearest by ``argmin``
    and its second by ``amin`` with the nearest masked; a row's nearest j is mutual where the
    distance equals column j's ``amin``, whose second is read with that entry masked — where
    Kornia's ``topk`` on rows and columns took most of its time."""
    if descriptors1.shape[0] < 2 or descriptors2.shape[0] < 2:
        return torch.empty(0, 2, dtype=torch.long, device=descriptors1.device)
    squared = torch.addmm(descriptors2.square().sum(1)[None], descriptors1, descriptors2.T, alpha=-2.0)
    squared += descriptors1.square().sum(1)[:, None]  # (N1, N2)
    rows = torch.arange(squared.shape[0], device=squared.device)
    nearest = squared.argmin(1)
    nearest_value = squared[rows, nearest]
    squared[rows, nearest] = torch.inf
    forward = passes_ratio(nearest_value, squared.amin(1), ratio)
    squared[rows, nearest] = nearest_value
    column_nearest = squared.amin(0)  # (N2,)
    candidate = torch.nonzero(forward & (nearest_value == column_nearest[nearest])).flatten()
    columns = nearest[candidate]
    squared[candidate, columns] = torch.inf
    backward = passes_ratio(column_nearest[columns], squared.amin(0)[columns], ratio)
    alone = torch.bincount(columns, minlength=squared.shape[1])[columns] == 1  # two rows at a column's least distance: ratio 1
    keep = backward & alone
    return torch.stack([candidate[keep], columns[keep]], 1)


def passes_ratio(nearest: Tensor, second: Tensor, ratio: float) -> Tensor:
    """Lowe's ratio test on squared distances (rounding below zero clamped, as ``cdist`` does):
    sqrt(nearest) / sqrt(second) <= ``ratio`` (0 / 0, two copies of one descriptor, fails)."""
    return nearest.clamp_min(0.0).sqrt() / second.clamp_min(0.0).sqrt() <= ratio


DESCRIBED_PER_CALL = 256  # patches per call of the patch descriptor


class InBatches(nn.Module):
    """A patch module (P, C, h, w) -> (P, D) applied to ``size`` patches at a time: the SIFT
    patch descriptor runs a dozen or more element-wise passes over its input, and over a whole
    image's 41 × 41 patches (4000: 27 MB a pass) they stream from memory, where blocks of 256
    stay in the caches (a sixth of the time on this machine; the same numbers — no pass mixes
    patches)."""

    def __init__(self, module: nn.Module, size: int) -> None:
        super().__init__()
        self.module, self.size = module, size

    def forward(self, patches: Tensor) -> Tensor:
        return torch.cat([self.module(block) for block in patches.split(self.size)]) if patches.shape[0] else self.module(patches)


class PooledSIFTDescriptor(SIFTDescriptor):
    """Kornia's SIFT patch descriptor with the gradient's orientation bins pooled by one matrix
    product, where Kornia runs one strided convolution per bin over a mask of the bin: the
    magnitude is split between the two nearest bins (one scatter into an (P, bins, h, w) stack)
    and every bin's cells are pooled at once by the convolution written out as a (h·w, cells)
    matrix of its kernel (:meth:`pooling_matrix`) — Kornia's numbers up to the order of the sums
    (``tests/features/test_sift.py``), in a fraction of the time. (P, 1, h, w) float patches -> (P, 128)
    descriptors."""

    @classmethod
    def like(cls, descriptor: SIFTDescriptor) -> PooledSIFTDescriptor:
        """One with ``descriptor``'s patch size, bins, clipping and RootSIFT setting."""
        return cls(descriptor.patch_size, descriptor.num_ang_bins, descriptor.num_spatial_bins, descriptor.rootsift, descriptor.clipval)

    def __init__(self, *args, **kwargs) -> None:
        super().__init__(*args, **kwargs)
        self.register_buffer("pooling", self.pooling_matrix(), persistent=False)

    def pooling_matrix(self) -> Tensor:
        """(h·w, cells²) float32: column (i, j) holds the pooling kernel placed where the
        convolution (stride, zero padding) centres cell (i, j) on the patch."""
        kernel = self.pk.weight.detach()[0, 0]  # (k, k)
        size, (stride, _), (pad, _) = self.patch_size, self.pk.stride, self.pk.padding
        cells = self.num_spatial_bins
        origin = torch.arange(cells) * stride - pad  # each cell's first patch row (or column)
        offset = torch.arange(size)[None] - origin[:, None]  # (cells, size): the kernel's row at each patch row
        inside = (offset >= 0) & (offset < kernel.shape[0])
        rows = offset.clamp(0, kernel.shape[0] - 1)
        placed = kernel[rows[:, :, None, None], rows[None, None]]  # (cells, size, cells, size): [i, y, j, x]
        placed = placed * (inside[:, :, None, None] & inside[None, None])
        return placed.permute(1, 3, 0, 2).reshape(size * size, cells * cells)

    def forward(self, patches: Tensor) -> Tensor:
        gx, gy = central_differences(patches)
        squared = gx * gx + gy * gy
        moving = squared > 0  # a flat pixel has no orientation and adds nothing
        magnitude = torch.where(moving, torch.sqrt(squared + self.eps), 0.0) * self.gk.to(patches.dtype)
        angle = torch.where(moving, torch.atan2(gy, gx + self.eps) + 2 * math.pi, 2 * math.pi)
        position = self.num_ang_bins * angle / (2 * math.pi)  # in bins
        lower = torch.floor(position)
        upper_share = position - lower
        lower_bin = (lower % self.num_ang_bins).long()
        P, _, h, w = patches.shape
        bins = patches.new_zeros(P, self.num_ang_bins, h, w)
        bins.scatter_(1, lower_bin, (1.0 - upper_share) * magnitude)
        bins.scatter_add_(1, (lower_bin + 1) % self.num_ang_bins, upper_share * magnitude)
        pooled = (bins.view(P * self.num_ang_bins, h * w) @ self.pooling.to(patches.dtype)).view(P, -1)
        pooled = F.normalize(F.normalize(pooled, dim=1).clamp(0.0, self.clipval), dim=1)
        return torch.sqrt(F.normalize(pooled, p=1, dim=1) + self.eps) if self.rootsift else pooled


def pyramid_patches(image: Tensor, frames: Tensor, size: int) -> Tensor:
    """(N, 1, size, size) patches of a (1, 1, H, W) float image at (N, 2, 3) local affine frames
    (pixels, pixel centres at integers), sampled as Kornia's ``extract_patches_from_pyramid``
    samples them: cell (i, j) at c + A (u_j, u_i), u_k = (2k + 1) / size - 1, read bilinearly from
    the pyramid level (``pyrdown``, halving while the shorter side keeps ``size`` pixels) numbered
    floor(log2(2 sqrt|det A| / size)), clamped to the levels there are, and outside a level from
    its nearest border pixel. Kornia builds each cell's coordinate by a chain of element-wise passes
    over all N · size² cells (and an expanded copy of the base grid per frame); here a cell's
    normalized coordinate, the same at every level, is one broadcast sum of a row's and a
    column's offsets — the same patches up to the rounding of the coordinates, in a sixth of the
    time (4000 41-pixel patches of a 768 × 512 image)."""
    h, w = image.shape[-2:]
    levels = [image]
    for _ in range(1, max(1, min(h, w) // size)):
        level_h, level_w = levels[-1].shape[-2:]
        if min(level_h, level_w) <= 2 or min(level_h // 2, level_w // 2) < size:
            break
        levels.append(pyrdown(levels[-1]))
    A, centre = frames[:, :, :2], frames[:, :, 2]
    level = (2 * A.det().abs().sqrt() / size).log2().clamp(0, len(levels) - 1).long()
    sides = image.new_tensor([w, h])  # normalized coordinate (2x + 1) / side - 1 at pixel x of every level
    u = (2 * torch.arange(size, dtype=image.dtype, device=image.device) + 1) / size - 1
    along_row = (2 * A[:, :, 0] / sides)[:, None] * u[None, :, None]  # (N, size, 2): column j's offset
    down_column = (2 * A[:, :, 1] / sides)[:, None] * u[None, :, None] + ((2 * centre + 1) / sides - 1)[:, None]
    patches = image.new_zeros(frames.shape[0], 1, size, size)
    for number, level_image in enumerate(levels):
        which = torch.nonzero(level == number).flatten()
        if which.numel():
            grid = down_column[which, :, None] + along_row[which, None]  # (n, size, size, 2)
            patches[which] = F.grid_sample(level_image, grid.view(1, -1, size, 2), padding_mode="border",
                                           align_corners=False).view(-1, 1, size, size)
    return patches


class SlidingNonMaxima(NonMaximaSuppression2d):
    """Kornia's :class:`~kornia.geometry.subpix.NonMaximaSuppression2d` (a strict maximum of its
    window, the window's centre excluded; positions whose window leaves the image are none) with
    the maxima of the same four rectangles around the centre by
    :func:`~torchsfm.features.filters.running_maximum` (log2 k whole-tensor passes), where Kornia
    pools them with ``max_pool2d`` (one scalar comparison per window cell on a CPU: a third of the
    SIFT detector's time at 15 × 15). The same result, bit for bit: maxima are
    exact. (B, C, H, W) response -> the response where it is a maximum, else 0."""

    def forward(self, x: Tensor, mask_only: bool = False) -> Tensor:
        (ky, kx), (H, W) = self.kernel_size, x.shape[-2:]
        above, below, left, right = (ky - 1) // 2, ky // 2, (kx - 1) // 2, kx // 2
        if min(above, left) == 0 or H < ky or W < kx:  # windows one pixel thin or larger than the image: Kornia's own
            return super().forward(x, mask_only)
        rows = running_maximum(x, kx, 3)  # (B, C, H, W - kx + 1): each row's window
        centre_row = x[..., above:H - below, :]
        neighbours = torch.maximum(torch.maximum(running_maximum(rows[..., :H - below - 1, :], above, 2),
                                                 running_maximum(rows[..., above + 1:, :], below, 2)),
                                   torch.maximum(running_maximum(centre_row[..., :W - right - 1], left, 3),
                                                 running_maximum(centre_row[..., left + 1:], right, 3)))
        mask = torch.zeros_like(x, dtype=torch.bool)
        mask[..., above:H - below, left:W - right] = x[..., above:H - below, left:W - right] > neighbours
        return mask if mask_only else torch.where(mask, x, 0)


class PyramidOrienter(LAFOrienter):
    """Kornia's :class:`~kornia.feature.LAFOrienter` on patches from :func:`pyramid_patches`:
    (1, N, 2, 3) frames and the (1, 1, H, W) image -> the frames turned to their patches' dominant
    gradient."""

    def forward(self, laf: Tensor, img: Tensor) -> Tensor:
        angles = self.angle_detector(pyramid_patches(img, laf[0], self.patch_size)).view(laf.shape[:2])
        return set_laf_orientation(laf, torch.rad2deg(angles) + get_laf_orientation(laf).view_as(angles))


def sift_features(greys: list[Tensor], num_features: int, masks: list[Tensor | None] | None = None
                  ) -> tuple[list[Tensor], list[Tensor]]:
    """SIFT keypoint centres (K_v, 2) float64 pixels and descriptors (K_v, 128) of every view of
    (V, 1, H, W) grey images (:func:`_describe`); only where each view's (H, W) bool mask
    keeps, given ``masks`` (None entries: everywhere). The views are described side by side
    (:func:`~torchsfm.threads.map_in_threads`: one image's pyramid and patches are too small for
    the intra-op threads to share; the same numbers as one view at a time)."""
    masks = masks or [None] * len(greys)
    described = map_in_threads(lambda view: _describe(*view, num_features), list(zip(greys, masks)))
    return [points for points, _ in described], [descriptors for _, descriptors in described]


def _describe(grey: Tensor, mask: Tensor | None, num_features: int) -> tuple[Tensor, Tensor]:
    """:func:`sift_features` of one (1, H, W) grey image: (K, 2) centres, (K, 128) descriptors —
    Kornia's SIFTFeature (its detector, 41-pixel patches, RootSIFT) with the suppression of
    :class:`SlidingNonMaxima`, the patches of :func:`pyramid_patches` and the descriptor of
    :class:`PooledSIFTDescriptor`, applied :data:`DESCRIBED_PER_CALL` patches at a time; the
    detector's unfilled slots (an image with fewer blobs than ``num_features``) dropped. A SIFT module of its own (its construction takes
    milliseconds), for a thread of its own."""
    sift = SIFTFeature(num_features=num_features)
    orienter = sift.detector.ori
    sift.detector.ori = PyramidOrienter(orienter.patch_size, orienter.num_ang_bins)
    sift.detector.nms = SlidingNonMaxima(sift.detector.nms.kernel_size)
    describe = InBatches(PooledSIFTDescriptor.like(sift.descriptor.descriptor), DESCRIBED_PER_CALL)
    image = to_unit_float(grey[None])
    with torch.no_grad():
        frames, _ = sift.detector(image)
        frames = frames[0][laf_is_filled(frames)[0]]
        described = describe(pyramid_patches(image, frames, sift.descriptor.patch_size))
    centres = get_laf_center(frames[None])[0].double()
    kept = inside_mask(centres, mask)
    return centres[kept], described[kept]
