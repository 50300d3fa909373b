"""SIFT (:mod:`torchsfm.features.sift`) as the N-view pipeline's features (``pairs.matcher = "sift"``): scale-space
keypoints with RootSIFT descriptors, matched by mutual nearest neighbours that pass Lowe's
ratio test — an option for rotations and scale changes that even warped NCC cannot follow.
The stages replace :class:`~torchsfm.sfm.stages.DetectCorners` and
:class:`~torchsfm.sfm.stages.MatchPairs`; pair selection, verification and the mapper are the
same. With the NCC matcher, :func:`sift_homographies` guides the matching of the pairs that may
link views the mapper left out (:class:`~torchsfm.sfm.stages.BridgeWithSift`)."""

from __future__ import annotations

from typing import TYPE_CHECKING

import torch
from torch import Tensor

from torchsfm.camera import undistort_points
from torchsfm.config import PairsConfig
from torchsfm.features.sift import mutual_ratio_matches, sift_features
from torchsfm.images import to_grey_bytes
from torchsfm.sfm.pairs import fit_homographies, pairs_to_match
from torchsfm.pipeline import ConfiguredStage

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
            index = mutual_ratio_matches(state.descriptors[i], state.descriptors[j], config.pairs.sift_ratio)
            if index.shape[0] >= config.reconstruction.min_pair_inliers:
                state.putative[(i, j)] = (index[:, 0], index[:, 1])
        return state


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
        index = mutual_ratio_matches(descriptors_i, descriptors_j, config.sift_ratio)
        matches.append(torch.cat([points_i[index[:, 0]], points_j[index[:, 1]]], -1))
    homographies, _ = fit_homographies(pairs, matches, config, generator)
    return {pair: H for pair, H in homographies.items() if H is not None}
