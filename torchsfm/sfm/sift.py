"""Kornia's SIFT as the N-view pipeline's features (``pairs.matcher = "sift"``): scale-space
keypoints with RootSIFT descriptors, matched by mutual nearest neighbours that pass Lowe's
ratio test — an option for rotations and scale changes that even warped NCC cannot follow.
The stages replace :class:`~torchsfm.sfm.stages.DetectCorners` and
:class:`~torchsfm.sfm.stages.MatchPairs`; pair selection, verification and the mapper are the
same. With the NCC matcher, :func:`sift_homographies` guides the matching of the pairs that may
link views the mapper left out (:class:`~torchsfm.sfm.stages.BridgeWithSift`)."""

from __future__ import annotations

from typing import TYPE_CHECKING

import torch
from torch import Tensor, nn
from kornia.feature import LAFDescriptor, SIFTFeature, get_laf_center, match_smnn

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
    """A patch module (P, C, h, w) -> (P, D) applied to ``size`` patches at a time: Kornia's
    SIFT descriptor runs some twenty element-wise passes over its input, and over a whole
    image's 41 × 41 patches (4000: 27 MB a pass) they stream from memory, where blocks of 256
    stay in the caches (a sixth of the time on this machine; the same numbers — no pass mixes
    patches)."""

    def __init__(self, module: nn.Module, size: int) -> None:
        super().__init__()
        self.module, self.size = module, size

    def forward(self, patches: Tensor) -> Tensor:
        return torch.cat([self.module(block) for block in patches.split(self.size)]) if patches.shape[0] else self.module(patches)


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
        sift.descriptor.descriptor = InBatches(sift.descriptor.descriptor, DESCRIBED_PER_CALL)
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
