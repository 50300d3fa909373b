"""Comparing results with the ground truth: cameras and point sets after a similarity alignment,
pose errors, inlier masks, moving-object decisions, motion labels."""

from __future__ import annotations

import itertools
from dataclasses import dataclass

import torch
from torch import Tensor

from torchsfm.geometry.rotation import angle_between, nearest_rotation, rotation_angle
from torchsfm.numerics import floor_tiny


@dataclass
class CameraErrors:
    """Errors of estimated cameras against the ground truth after a similarity alignment.

    Fields: ``centre`` (V,) camera-centre errors in ground-truth units; ``extent`` the diagonal of
    the ground-truth centres' bounding box; ``rotation`` (V,) degrees; ``relative_rotation``
    (V (V-1) / 2,) degrees between every pair of views (independent of the alignment).
    """

    centre: Tensor
    extent: float
    rotation: Tensor
    relative_rotation: Tensor


def similarity_alignment(R: Tensor, t: Tensor, R_true: Tensor, t_true: Tensor) -> tuple[Tensor, Tensor, Tensor]:
    """The similarity taking the estimated cameras' world (V, 3, 3), (V, 3) (camera from world)
    to the ground truth's: (scale, A (3, 3), offset (3,)) with world_true ≈ scale A world + offset.
    A is the chordal mean of R_trueᵢᵀ Rᵢ (from the orientations, which pin it down even for
    cameras on a line or an arc), scale and offset the least-squares fit of the rotated centres
    to the true centres."""
    centres = (-R.transpose(-1, -2) @ t[..., None])[..., 0]
    true_centres = (-R_true.transpose(-1, -2) @ t_true[..., None])[..., 0]
    A = nearest_rotation((R_true.transpose(-1, -2) @ R).sum(0))
    rotated = centres @ A.T
    mean, true_mean = rotated.mean(0), true_centres.mean(0)
    scale = ((rotated - mean) * (true_centres - true_mean)).sum() / floor_tiny((rotated - mean).square().sum())
    return scale, A, true_mean - scale * mean


def camera_errors(R: Tensor, t: Tensor, R_true: Tensor, t_true: Tensor) -> CameraErrors:
    """Align estimated cameras (V, 3, 3), (V, 3) (camera from world) to the ground truth
    (:func:`similarity_alignment`) and measure their errors."""
    scale, A, offset = similarity_alignment(R, t, R_true, t_true)
    centres = (-R.transpose(-1, -2) @ t[..., None])[..., 0]
    true_centres = (-R_true.transpose(-1, -2) @ t_true[..., None])[..., 0]
    centre = (scale * centres @ A.T + offset - true_centres).norm(dim=-1)
    rotation = rotation_angle(R @ A.T, R_true)
    pairs = torch.triu_indices(R.shape[0], R.shape[0], 1)
    relative = rotation_angle(R[pairs[0]] @ R[pairs[1]].transpose(-1, -2), R_true[pairs[0]] @ R_true[pairs[1]].transpose(-1, -2))
    extent = float((true_centres.amax(0) - true_centres.amin(0)).norm())
    return CameraErrors(centre=centre, extent=extent, rotation=rotation, relative_rotation=relative)


def shape_errors(points: Tensor, true_points: Tensor) -> Tensor:
    """(P,) distances between (P, 3) estimated points, similarity-aligned to their (P, 3) true
    positions (Umeyama 1991: the scale, rotation and offset minimizing the squared distances),
    and the true positions, in ground-truth units: the error of a shape whose scale is its own."""
    mean, true_mean = points.mean(0), true_points.mean(0)
    centred, true_centred = points - mean, true_points - true_mean
    U, S, Vh = torch.linalg.svd(true_centred.T @ centred)
    flip = torch.ones(3, dtype=points.dtype, device=points.device)
    flip[2] = torch.sign(torch.linalg.det(U @ Vh))
    A = U @ torch.diag(flip) @ Vh
    scale = (S * flip).sum() / floor_tiny(centred.square().sum())
    return (scale * centred @ A.T - true_centred).norm(dim=-1)


def misclassification(labels: Tensor, truth: Tensor) -> float:
    """Share of the N points whose (N,) label disagrees with the (N,) ground truth under the best
    one-to-one matching of label values to truth values (the motion-segmentation measure of
    Tron & Vidal, 2007). A label of -1 (unassigned) is a class of its own: it matches a truth of
    -1 (outliers, where the ground truth has them) and is wrong otherwise; labels left without a
    partner are wrong."""
    found = sorted(set(labels.tolist()) - {-1})
    true = sorted(set(truth.tolist()) - {-1})
    overlap = torch.tensor([[int(((labels == a) & (truth == b)).sum()) for b in true] for a in found],
                           dtype=torch.long).reshape(len(found), len(true))
    agree = int(((labels == -1) & (truth == -1)).sum()) + _best_assignment(overlap)
    return 1.0 - agree / max(truth.numel(), 1)


def _best_assignment(overlap: Tensor) -> int:
    """Largest total of a (A, B) table over one-to-one row-column matchings (exhaustive over the
    smaller side's choices: motion counts are small)."""
    if overlap.shape[0] > overlap.shape[1]:
        overlap = overlap.T
    rows, columns = overlap.shape
    best = 0
    for chosen in itertools.permutations(range(columns), rows):
        best = max(best, sum(int(overlap[r, c]) for r, c in enumerate(chosen)))
    return best


def rotation_error_deg(R_estimated: Tensor, R_true: Tensor) -> float:
    """Angle of R_estimatedᵀ R_true in degrees."""
    return float(rotation_angle(R_estimated.double(), R_true.double()))


def translation_direction_error_deg(t_estimated: Tensor, t_true: Tensor) -> float:
    """Angle between two translation directions in degrees (sign matters)."""
    return float(angle_between(t_estimated.double(), t_true.double()))


def mask_recall_precision(estimated: Tensor, truth: Tensor) -> tuple[float, float]:
    """(recall, precision) of an estimated inlier mask against the true one."""
    hits = int((estimated & truth).sum())
    return hits / max(int(truth.sum()), 1), hits / max(int(estimated.sum()), 1)


def rejection_figures(background: Tensor, labels: Tensor) -> dict[str, float]:
    """Table 5.1's counts for a background decision (N,) bool against labels (N,) (0 = static).

    Returns wrong rejections (static vectors rejected), undetected (moving or outlier vectors
    kept), inliers (vectors kept), total, and the rates: wrongly rejected share of the static
    vectors and undetected share of the others.
    """
    static = labels == 0
    wrong = int((static & ~background).sum())
    undetected = int((~static & background).sum())
    return {"wrong_rejections": wrong, "undetected": undetected, "inliers": int(background.sum()), "total": labels.numel(),
            "wrong_rate": wrong / max(int(static.sum()), 1), "undetected_rate": undetected / max(int((~static).sum()), 1)}
