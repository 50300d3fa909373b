"""The putative-matching stage: NCC candidates → strength measure → relaxation (Alg. 3.2.2)."""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor, nn

from torchsfm.config import MatchingConfig
from torchsfm.matching.ncc import CandidateMatches, ncc_candidates
from torchsfm.matching.strength import relaxation, strength_measure


@dataclass
class PutativeMatches:
    """One-to-one matches between the corners of two images.

    Fields:
        index1, index2: (M,) int64 corner indices.
        candidates: the candidate set they were chosen from.
        strength: (C,) the score each candidate was ranked by (SM, or NCC for the baseline).
    """

    index1: Tensor
    index2: Tensor
    candidates: CandidateMatches
    strength: Tensor


def match_corners(image1: Tensor, image2: Tensor, points1: Tensor, points2: Tensor,
                  config: MatchingConfig | None = None, predicted1: Tensor | None = None,
                  warp1: Tensor | None = None) -> PutativeMatches:
    """Putative matches between the corners of two grey images (1, H, W) (Algorithm 3.2.2);
    ``predicted1`` (N1, 2) centres the search discs and ``warp1`` (N1, 2, 2) warps image 1's
    patches (see :func:`ncc_candidates`)."""
    config = config or MatchingConfig()
    return match_candidates(points1, points2, ncc_candidates(image1, image2, points1, points2, config, predicted1, warp1), config)


def match_candidates(points1: Tensor, points2: Tensor, candidates: CandidateMatches,
                     config: MatchingConfig | None = None) -> PutativeMatches:
    """One-to-one matches of corners (N1, 2), (N2, 2) from a candidate set: the strength measure
    (or NCC alone) and relaxation (Algorithm 3.2.2, steps 2-3)."""
    config = config or MatchingConfig()
    strength = ranking_score(points1, points2, candidates, config)
    index1, index2 = relaxation(candidates, strength, (points1.shape[0], points2.shape[0]), config)
    return PutativeMatches(index1=index1, index2=index2, candidates=candidates, strength=strength)


def ranking_score(points1: Tensor, points2: Tensor, candidates: CandidateMatches, config: MatchingConfig) -> Tensor:
    """(M,) what relaxation ranks the candidates of corners (N1, 2), (N2, 2) by: the strength
    measure, or NCC alone (``config.strength``)."""
    return strength_measure(points1, points2, candidates, config) if config.strength == "sm" else candidates.score


class PutativeMatcher(nn.Module):
    """Pipeline stage: (image1, image2, points1, points2) -> :class:`PutativeMatches`."""

    def __init__(self, config: MatchingConfig | None = None) -> None:
        super().__init__()
        self.config = config or MatchingConfig()

    def forward(self, image1: Tensor, image2: Tensor, points1: Tensor, points2: Tensor) -> PutativeMatches:
        return match_corners(image1, image2, points1, points2, self.config)

    def extra_repr(self) -> str:
        return repr(self.config)


def chain_matches(first: PutativeMatches, second: PutativeMatches, num_middle: int) -> tuple[Tensor, Tensor]:
    """Triplets through the middle image of matches (a → b) and (b → c).

    Args:
        first: matches of image a to image b; second: matches of image b to image c.
        num_middle: number of corners of image b.

    Returns:
        (T,) positions in ``first`` of the matches whose b-corner is matched into c, and (T,)
        the c-corner of each.
    """
    onward = torch.full((num_middle,), -1, dtype=torch.long, device=second.index1.device)
    onward[second.index1] = second.index2
    third = onward[first.index2]
    seen = torch.nonzero(third >= 0).flatten()
    return seen, third[seen]
