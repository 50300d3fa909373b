"""Candidate matches by normalized cross-correlation in a search disc (thesis §3.2.2.1, eq. 3.2.4).

Patches are sampled once per corner (bilinear, at the sub-pixel position), normalized to zero
mean and unit norm, so correlations are matrix products — of the whole table (:func:`ncc_table`)
or, for the candidates in a disc, of strips of it (:func:`disc_candidates`); the disc and score
threshold then select the candidate match set.
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
        index1, index2: (M,) int64 corner indices in image 1 and image 2, row-major.
        score: (M,) NCC in [-1, 1].
    """

    index1: Tensor
    index2: Tensor
    score: Tensor


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
    return zero_mean_unit_norm(sample_patches(image, points, half_size, warp))


def sample_patches(image: Tensor, points: Tensor, half_size: int, warp: Tensor | None = None) -> Tensor:
    """The bilinear samples (K, (2n + 1)²), row-major, of the (1, H, W) image on the square grid
    of :func:`extract_patches` (n = ``half_size``) around each of the (K, 2) points, as they are."""
    H, W = image.shape[-2:]
    offsets = torch.arange(-half_size, half_size + 1, dtype=points.dtype, device=points.device)
    dy, dx = torch.meshgrid(offsets, offsets, indexing="ij")
    steps = torch.stack([dx.flatten(), dy.flatten()], dim=-1)  # (P, 2)
    steps = steps[None] if warp is None else steps @ warp.to(points.dtype).transpose(1, 2)  # (1 or K, P, 2)
    grid = points[:, None, :] + steps  # (K, P, 2)
    normalized = (2 * grid).div_(torch.tensor([W - 1, H - 1], dtype=points.dtype, device=points.device)).sub_(1)  # x and y at once: no strided halves
    return functional.grid_sample(image[None].to(points.dtype), normalized[None], mode="bilinear",
                                  padding_mode="border", align_corners=True)[0, 0]  # (K, P)


def zero_mean_unit_norm(patches: Tensor) -> Tensor:
    """(K, D) patches less their means, over their norms: correlations become dot products. A
    constant patch becomes all zeros (it correlates with nothing)."""
    centered = patches - patches.mean(-1, keepdim=True)
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
    centres = points1 if predicted1 is None else predicted1.to(points1.dtype)
    return disc_candidates(patches1, patches2, centres, points2, config.search_radius, config.ncc_threshold)


def disc_candidates(patches1: Tensor, patches2: Tensor, centres: Tensor, points2: Tensor, radius: float,
                    threshold: float) -> CandidateMatches:
    """The pairs (a, b) with ``points2[b]`` less than ``radius`` from ``centres[a]`` whose patches'
    correlation exceeds ``threshold``: patches (N1, D), (N2, D) zero-mean and unit-norm, centres
    (N1, 2), points2 (N2, 2). The same set as :func:`select_candidates` on the whole
    :func:`ncc_table` within the disc, but the products are taken in strips of rows one radius
    wide, each against the corners of image 2 within a radius of the strip, along the image's
    longer side: on a 768 × 512 image with a 100 px disc, about 40 % of the table."""
    N1, N2 = centres.shape[0], points2.shape[0]
    if N1 == 0 or N2 == 0:
        empty = torch.zeros(0, dtype=torch.long, device=centres.device)
        return CandidateMatches(index1=empty, index2=empty, score=patches1.new_zeros(0))
    axis = int((points2.amax(0) - points2.amin(0)).argmax())
    order1, order2 = torch.argsort(centres[:, axis]), torch.argsort(points2[:, axis])
    along1, along2 = centres[order1, axis].contiguous(), points2[order2, axis].contiguous()
    sorted1, sorted2 = patches1[order1], patches2[order2]
    strip_ends = torch.cumsum(torch.bincount(torch.div(along1 - along1[0], radius, rounding_mode="floor").long()), 0)
    index1, index2, score = [], [], []
    start = 0
    for end in strip_ends.unique().tolist():  # the non-empty strips
        low = int(torch.searchsorted(along2, along1[start] - radius))
        high = int(torch.searchsorted(along2, along1[end - 1] + radius, right=True))
        table = sorted1[start:end] @ sorted2[low:high].T
        near = torch.cdist(centres[order1[start:end]], points2[order2[low:high]]) < radius
        a, b = torch.nonzero((table > threshold) & near, as_tuple=True)
        index1.append(order1[start + a])
        index2.append(order2[low + b])
        score.append(table[a, b])
        start = end
    index1, index2, score = torch.cat(index1), torch.cat(index2), torch.cat(score)
    row_major = torch.argsort(index1 * N2 + index2)
    return CandidateMatches(index1=index1[row_major], index2=index2[row_major], score=score[row_major])


def ncc_table(image1: Tensor, image2: Tensor, points1: Tensor, points2: Tensor, half_size: int,
              warp1: Tensor | None = None) -> Tensor:
    """(N1, N2) NCC of every corner pair (eq. 3.2.4; the (2n+1)² σσ normalization is in the
    patches' unit norms): one matrix product. ``warp1`` as in :func:`ncc_candidates`."""
    return extract_patches(image1, points1, half_size, warp1) @ extract_patches(image2, points2, half_size).T


def select_candidates(ncc: Tensor, allowed: Tensor, threshold: float) -> CandidateMatches:
    """The pairs of an (N1, N2) NCC table that ``allowed`` (N1, N2) admits and that score above
    ``threshold``."""
    index1, index2 = torch.nonzero((ncc > threshold) & allowed, as_tuple=True)
    return CandidateMatches(index1=index1, index2=index2, score=ncc[index1, index2])


def chance_equivalent_threshold(ncc: Tensor, reference: Tensor, allowed: Tensor, threshold: float) -> float:
    """The NCC threshold at which a corner's candidates among ``allowed`` (N1, N2) pairs are chance
    ones no more often than its candidates above ``threshold`` among ``reference`` pairs (e.g. an
    epipolar band against the search disc: far fewer pairs, so a lower score suffices).

    Chance scores are the table's entries without each row's best (where most true matches
    are); the result is the score they exceed as often as they exceed ``threshold``, times
    |reference| / |allowed|; never above ``threshold``."""
    chance = ncc.scatter(1, ncc.argmax(1, keepdim=True), float("-inf")).flatten()
    rate = float((chance > threshold).double().mean()) * float(reference.sum()) / max(float(allowed.sum()), 1.0)
    count = min(max(1, round(rate * chance.numel())), chance.numel())
    return min(threshold, float(torch.topk(chance, count).values[-1]))
