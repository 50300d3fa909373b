"""Kornia's SIFT as the N-view pipeline's features (``pairs.matcher = "sift"``): scale-space
keypoints with RootSIFT descriptors, matched by mutual nearest neighbours that pass Lowe's
ratio test — an option for rotations and scale changes that even warped NCC cannot follow.
The stages replace :class:`~torchsfm.sfm.stages.DetectCorners` and
:class:`~torchsfm.sfm.stages.MatchPairs`; pair selection, verification and the mapper are the
same."""

from __future__ import annotations

from typing import TYPE_CHECKING

import torch
from kornia.feature import SIFTFeature, get_laf_center, match_smnn

from torchsfm.camera import undistort_points
from torchsfm.images import to_grey_bytes, to_unit_float
from torchsfm.sfm.pairs import pairs_to_match
from torchsfm.pipeline import ConfiguredStage

if TYPE_CHECKING:  # the state type only: stages.py builds its default pipeline from these stages
    from torchsfm.sfm.stages import ViewSet


class DetectSiftFeatures(ConfiguredStage):
    """SIFT keypoints and descriptors of every view, one view at a time: fills ``greys``, ``raw``
    (keypoint centres, pixels), ``corners`` (undistorted) and ``descriptors`` ((K_v, 128) each)."""

    SECTIONS = ("pairs",)

    def forward(self, state: ViewSet) -> ViewSet:
        state.greys = torch.stack([to_grey_bytes(image) for image in state.images])
        state.report(f"SIFT features of {len(state.images)} views")
        sift = SIFTFeature(num_features=self.config.pairs.sift_features)
        state.raw, state.descriptors = [], []
        with torch.no_grad():
            for grey in state.greys:
                frames, _, descriptors = sift(to_unit_float(grey[None]))
                state.raw.append(get_laf_center(frames)[0].double())
                state.descriptors.append(descriptors[0])
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
        for i, j in pairs_to_match(state.greys, config.pairs, generator=state.generator):
            state.report(f"matching views {i} and {j}")
            _, index = match_smnn(state.descriptors[i], state.descriptors[j], config.pairs.sift_ratio)
            if index.shape[0] >= config.reconstruction.min_pair_inliers:
                state.putative[(i, j)] = (index[:, 0], index[:, 1])
        return state
