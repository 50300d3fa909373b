"""Candidate matches by normalized cross-correlation in a search disc (thesis §3.2.2.1, eq. 3.2.4).

Patches are sampled once per corner (bilinear, at the sub-pixel position), normalized to zero
mean and unit norm, and all correlations of a pair of images are one matrix product; the disc and
score threshold then select the candidate match set.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
import torch.nn.functional as functional
from torch import Tensor

from torchsfm.config import MatchingConfig


@dataclass
class CandidateMatches:
    """Candidate matches between two corner sets.

    Fields:
        index1, index2: (M,) int64 corner indices in image 1 and image 2.
        score: (M,) NCC in [-1, 1].
        ncc: (N1, N2) the full correlation matrix restricted to the disc (-inf outside), kept for
            studies such as thesis Table 3.1.
    """

    index1: Tensor
    index2: Tensor
    score: Tensor
    ncc: Tensor


def extract_patches(image: Tensor, points: Tensor, half_size: int, warp: Tensor | None = None) -> Tensor:
    """Zero-mean, unit-norm square patches around sub-pixel points.

    Args:
        image: (1, H, W) grey image.
        points: (K, 2) pixel positions (x, y).
        half_size: n; patches are (2n + 1)².
        warp: (K, 2, 2) per point, the linear map from patch offsets to image offsets (a patch
            warped by a local affine transform, e.g. to look as the other view sees it);
            default: the identity.

    Returns:
        (K, (2n + 1)²) patches; a constant patch becomes all zeros (it correlates with nothing).
    """
    H, W = image.shape[-2:]
    offsets = torch.arange(-half_size, half_size + 1, dtype=points.dtype, device=points.device)
    dy, dx = torch.meshgrid(offsets, offsets, indexing="ij")
    steps = torch.stack([dx.flatten(), dy.flatten()], dim=-1)  # (P, 2)
    steps = steps[None] if warp is None else steps @ warp.to(points.dtype).transpose(1, 2)  # (1 or K, P, 2)
    grid = points[:, None, :] + steps  # (K, P, 2)
    normalized = torch.stack([2 * grid[..., 0] / (W - 1) - 1, 2 * grid[..., 1] / (H - 1) - 1], dim=-1)
    samples = functional.grid_sample(image[None].to(points.dtype), normalized[None], mode="bilinear",
                                     padding_mode="border", align_corners=True)[0, 0]  # (K, P)
    centered = samples - samples.mean(-1, keepdim=True)
    norm = centered.norm(dim=-1, keepdim=True)
    return torch.where(norm > 1e-8, centered / norm.clamp_min(1e-12), torch.zeros_like(centered))


def ncc_candidates(image1: Tensor, image2: Tensor, points1: Tensor, points2: Tensor,
                   config: MatchingConfig | None = None, predicted1: Tensor | None = None,
                   warp1: Tensor | None = None) -> CandidateMatches:
    """All pairs within the search disc whose NCC exceeds the threshold (Alg. 3.2.2 step 1).

    Args:
        image1, image2: (1, H, W) grey images.
        points1, points2: (N1, 2), (N2, 2) corner positions (pixels).
        config: patch size, search radius, score threshold.
        predicted1: (N1, 2) where the corners of image 1 are expected in image 2 (the disc's
            centres; default: their own positions).
        warp1: (N1, 2, 2) the local affine map from image 2's offsets to image 1's around each
            corner of image 1 (its patch is sampled as image 2 would see it: rotation, scale and
            foreshortening undone); default: none.

    Returns:
        :class:`CandidateMatches`.
    """
    config = config or MatchingConfig()
    patches1 = extract_patches(image1, points1, config.patch_half_size, warp1)
    patches2 = extract_patches(image2, points2, config.patch_half_size)
    ncc = patches1 @ patches2.T  # (N1, N2): eq. 3.2.4 (the (2n+1)² σσ normalization is in the unit norms)
    centres = points1 if predicted1 is None else predicted1.to(points1.dtype)
    inside = torch.cdist(centres, points2) < config.search_radius
    ncc = torch.where(inside, ncc, float("-inf"))
    index1, index2 = torch.nonzero(ncc > config.ncc_threshold, as_tuple=True)
    return CandidateMatches(index1=index1, index2=index2, score=ncc[index1, index2], ncc=ncc)
