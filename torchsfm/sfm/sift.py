"""Kornia's SIFT as the N-view pipeline's features (``pairs.matcher = "sift"``): scale-space
keypoints with RootSIFT descriptors, matched by mutual nearest neighbours that pass Lowe's
ratio test — an option for rotations and scale changes that even warped NCC cannot follow.
The stages replace :class:`~torchsfm.sfm.stages.DetectCorners` and
:class:`~torchsfm.sfm.stages.MatchPairs`; pair selection, verification and the mapper are the
same. With the NCC matcher, :func:`sift_homographies` guides the matching of the pairs that may
link views the mapper left out (:class:`~torchsfm.sfm.stages.BridgeWithSift`)."""

from __future__ import annotations

import math
from typing import TYPE_CHECKING

import torch
import torch.nn.functional as F
from torch import Tensor, nn
from kornia.feature import LAFDescriptor, SIFTDescriptor, SIFTFeature, get_laf_center, match_smnn
from kornia.filters import spatial_gradient

from torchsfm.camera import undistort_points
from torchsfm.config import PairsConfig
from torchsfm.images import inside_mask, to_grey_bytes, to_unit_float
from torchsfm.sfm.pairs import fit_homographies, pairs_to_match
from torchsfm.pipeline import ConfiguredStage
from torchsfm.threads import map_in_threads

if TYPE_CHECKING:  # the state type only: stages.py builds its default pipeline from these stages
    from torchsfm.sfm.stages import ViewSet


class DetectSiftFeatures(ConfiguredStage):
    """SIFT keypoints and descriptors of every view, one view at a time: fills ``greys``, ``raw``
    (keypoint centres, pixels), ``corners`` (undistorted) and ``descriptors`` ((K_v, 128) each)."""

    SECTIONS = ("pairs",)

    def forward(self, state: ViewSet) -> ViewSet:
        state.greys = [to_grey_bytes(image) for image in state.images]
        state.report(f"SIFT features of {len(state.images)} views")
        state.raw, state.descriptors = sift_features(state.greys, self.config.pairs.sift_features, state.masks)
        state.corners = [undistort_points(raw, state.K[v], state.distortion[v]) for v, raw in enumerate(state.raw)]
        return state


class MatchSiftFeatures(ConfiguredStage):
    """The pairs ``config.pairs`` selects (coarse scores as for NCC), each matched by mutual
    nearest descriptors passing the ratio test; pairs with fewer than ``min_pair_inliers``
    matches are dropped: fills ``putative``."""

    SECTIONS = ("pairs", "reconstruction")

    def forward(self, state: ViewSet) -> ViewSet:
        config = self.config
        state.putative = {}
        for i, j in pairs_to_match(state.greys, config.pairs, generator=state.generator, focal=state.focal_lengths(), masks=state.masks):
            state.report(f"matching views {i} and {j}")
            _, index = match_smnn(state.descriptors[i], state.descriptors[j], config.pairs.sift_ratio)
            if index.shape[0] >= config.reconstruction.min_pair_inliers:
                state.putative[(i, j)] = (index[:, 0], index[:, 1])
        return state


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
    """Kornia's SIFT patch descriptor with the gradient's orientation bins pooled by one
    convolution over all of them, where Kornia runs one per bin over a mask of the bin: the
    magnitude is split between the two nearest bins (one scatter into an (P, bins, h, w) stack)
    and every bin is pooled by the same kernel — the same numbers (``tests/sfm/test_sift.py``),
    in two thirds of the time. (P, 1, h, w) float patches -> (P, 128) descriptors."""

    @classmethod
    def like(cls, descriptor: SIFTDescriptor) -> PooledSIFTDescriptor:
        """One with ``descriptor``'s patch size, bins, clipping and RootSIFT setting."""
        return cls(descriptor.patch_size, descriptor.num_ang_bins, descriptor.num_spatial_bins, descriptor.rootsift, descriptor.clipval)

    def forward(self, patches: Tensor) -> Tensor:
        gradient = spatial_gradient(patches, "diff")
        gx, gy = gradient[:, :, 0], gradient[:, :, 1]
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
        pooled = F.conv2d(bins.view(P * self.num_ang_bins, 1, h, w), self.pk.weight.to(patches.dtype), None, self.pk.stride,
                          self.pk.padding).view(P, -1)
        pooled = F.normalize(F.normalize(pooled, dim=1).clamp(0.0, self.clipval), dim=1)
        return torch.sqrt(F.normalize(pooled, p=1, dim=1) + self.eps) if self.rootsift else pooled


def sift_features(greys: list[Tensor], num_features: int, masks: list[Tensor | None] | None = None
                  ) -> tuple[list[Tensor], list[Tensor]]:
    """SIFT keypoint centres (K_v, 2) float64 pixels and descriptors (K_v, 128) of every view of
    (V, 1, H, W) grey images (Kornia's :class:`~kornia.feature.SIFTFeature`, its patch descriptor
    applied :data:`DESCRIBED_PER_CALL` patches at a time); only where each view's (H, W) bool mask
    keeps, given ``masks`` (None entries: everywhere). The views are described side by side
    (:func:`~torchsfm.threads.map_in_threads`: one image's pyramid and patches are too small for
    the intra-op threads to share; the same numbers as one view at a time)."""
    masks = masks or [None] * len(greys)
    described = map_in_threads(lambda view: _describe(*view, num_features), list(zip(greys, masks)))
    return [points for points, _ in described], [descriptors for _, descriptors in described]


def _describe(grey: Tensor, mask: Tensor | None, num_features: int) -> tuple[Tensor, Tensor]:
    """:func:`sift_features` of one (1, H, W) grey image: (K, 2) centres, (K, 128) descriptors;
    a SIFT module of its own (its construction takes milliseconds), for a thread of its own."""
    sift = SIFTFeature(num_features=num_features)
    if isinstance(sift.descriptor, LAFDescriptor):
        sift.descriptor.descriptor = InBatches(PooledSIFTDescriptor.like(sift.descriptor.descriptor), DESCRIBED_PER_CALL)
    with torch.no_grad():
        frames, _, described = sift(to_unit_float(grey[None]))
    centres = get_laf_center(frames)[0].double()
    kept = inside_mask(centres, mask)
    return centres[kept], described[0][kept]


def sift_homographies(greys: list[Tensor], pairs: list[tuple[int, int]], config: PairsConfig,
                      generator: torch.Generator | None = None, described: dict[int, tuple[Tensor, Tensor]] | None = None,
                      masks: list[Tensor | None] | None = None) -> dict[tuple[int, int], Tensor]:
    """A homography (3, 3) mapping view i's pixels to view j's for each view pair (i, j) of
    (V, 1, H, W) grey images where one holds: RANSAC (:func:`~torchsfm.sfm.pairs.fit_homographies`)
    on the SIFT matches (mutual nearest descriptors passing the ratio test), ``min_score``
    inliers at least. Only the views of ``pairs`` are described; ``described`` (view -> keypoints,
    descriptors) holds views described before and receives the new ones; ``masks`` as in
    :func:`sift_features`."""
    described = {} if described is None else described
    new = sorted({v for pair in pairs for v in pair} - set(described))
    if new:
        described.update(zip(new, zip(*sift_features([greys[v] for v in new], config.sift_features,
                                                      None if masks is None else [masks[v] for v in new]))))
    matches = []
    for i, j in pairs:
        (points_i, descriptors_i), (points_j, descriptors_j) = described[i], described[j]
        _, index = match_smnn(descriptors_i, descriptors_j, config.sift_ratio)
        matches.append(torch.cat([points_i[index[:, 0]], points_j[index[:, 1]]], -1))
    homographies, _ = fit_homographies(pairs, matches, config, generator)
    return {pair: H for pair, H in homographies.items() if H is not None}
