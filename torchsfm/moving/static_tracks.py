"""Rigid motions over whole tracks: a projective reconstruction of one rigid group over all
frames, and every track judged by how well a single point of that group explains it (ours).

The rigidity constraint of chapter 5 sees only what changes inside three frames. Over F frames
a rigid group has one projective reconstruction: cameras P_f (3×4) and, for every member, one
point X (4-vector) with x_f ~ P_f X wherever the track is seen. Two-view epipolar tests
constrain one direction only (an object moving along its epipolar lines passes them); the
multi-view test also constrains where along the line the point lies in every frame. No
calibration is needed, and tracks may have gaps.

1. Reference frame r: the frame that sees the most candidate tracks. Partner f*: among the
   frames sharing at least half of them, the one whose shared tracks moved furthest (median).
2. Robust F of (r, f*) (the project's RANSAC): its inliers seed the group; canonical cameras
   P_r = [I | 0], P_f* = [[e']x F | e'] and linear triangulation.
3. Every frame's camera by RANSAC on the 6-point projective DLT over the seed's points it sees
   (one batched call over all frames).
4. Alternation (at most ``refinements`` times; it stops once the core repeats and σ² moved by
   at most ``SETTLED`` of itself, a fixed point): triangulate every track from all its frames
   (reweighted linear triangulation, i.e. the reprojection error), keep as the group's core the
   tracks whose reprojection sum of squares is within the χ²(2m − 3) quantile of
   ``significance`` (σ estimated from the core, m the frames a track is seen in), and re-fit
   each camera by DLT on the core, its rows scaled by 1 / |p3ᵀX| as in the triangulation, so
   that both steps lower the reprojection error the bounds assume (unweighted rows weigh points
   by their projective depth: on KITTI clips that bias cut whole background pieces).
5. Membership: RMS reprojection error within the larger of that χ² bound and ``threshold`` (the
   tracker's pixel noise floor: real tracks drift, and σ from a self-fitted core is optimistic).

Everything works in coordinates normalized once for all frames (Hartley), so the projective DLT
and triangulation are well conditioned; residuals are reported in pixels.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
from torch import Tensor

from torchsfm.config import RansacConfig
from torchsfm.geometry.normalization import hartley_normalize
from torchsfm.geometry.projective import (
    canonical_cameras,
    project,
    projection_distance_squared,
    triangulate_multiview,
)
from torchsfm.numerics import floor_tiny
from torchsfm.robust.models import FundamentalModel, ProjectiveResectionModel
from torchsfm.robust.ransac import ransac

DEPTH_FLOOR = 0.1  # of a camera's median |p3ᵀX|: a point near its focal plane weighs at most 100× the median
SETTLED = 1e-3  # relative change of σ² below which, with the core repeated, the alternation has converged


@dataclass
class RigidGroup:
    """One rigid motion reconstructed projectively over F frames, N tracks measured against it.

    Fields:
        members: (N,) bool, tracks of the group (RMS within the threshold, seen in >= 3 frames).
        rms: (N,) root mean square reprojection error of every track under the group's cameras,
            pixels (+inf for tracks seen in fewer than 3 frames with a camera).
        frames_seen: (N,) frames in which each track is seen and the group has a camera.
        cameras: (F, 3, 4) projective cameras in normalized coordinates.
        camera_valid: (F,) bool.
        reference, partner: the two frames that started the reconstruction.
    """

    members: Tensor
    rms: Tensor
    frames_seen: Tensor
    cameras: Tensor
    camera_valid: Tensor
    reference: int
    partner: int


def chi2_quantile(dof: Tensor, probability: float) -> Tensor:
    """Wilson–Hilferty approximation of the χ² quantile (relative error < 1% for dof >= 1)."""
    z = math.sqrt(2) * torch.erfinv(torch.tensor(2 * probability - 1, dtype=torch.float64)).item()
    k = dof.double().clamp_min(1)
    return k * (1 - 2 / (9 * k) + z * torch.sqrt(2 / (9 * k))) ** 3


def rms_bound(sigma_sq: Tensor | float, dof: Tensor, terms: Tensor, significance: float, floor: float) -> Tensor:
    """The largest RMS residual over ``terms`` squared terms of ``dof`` degrees of freedom that
    noise of variance ``sigma_sq`` reaches with probability 1 − ``significance``:
    max(floor, sqrt(σ² χ²_(1−α)(dof) / terms)), per entry of dof / terms."""
    return torch.sqrt(sigma_sq * chi2_quantile(dof, 1 - significance) / terms.clamp_min(1)).clamp_min(floor)


def starting_frames(tracks: Tensor, visible: Tensor) -> tuple[int, int]:
    """(r, f*): the frame seeing most tracks, and the frame sharing at least half of them whose
    shared tracks moved furthest (median displacement)."""
    counts = visible.sum(1)
    r = int(counts.argmax())
    shared = visible & visible[r]  # (F, N)
    displacement = torch.where(shared, (tracks - tracks[r]).norm(dim=-1), torch.nan).nanmedian(dim=1).values
    eligible = shared.sum(1) >= max(FundamentalModel.sample_size * 2, int(counts[r]) // 2)
    eligible[r] = False
    if not bool(eligible.any()):
        eligible = shared.sum(1) >= FundamentalModel.sample_size * 2
        eligible[r] = False
    displacement = torch.where(eligible, torch.nan_to_num(displacement, nan=-1.0), -1.0)
    return r, int(displacement.argmax())


def rigid_group(tracks: Tensor, visible: Tensor, members: Tensor, *, fundamental_ransac: RansacConfig,
                resection_ransac: RansacConfig, refinements: int = 3, threshold: float = 1.0,
                significance: float = 1e-3, generator: torch.Generator | None = None) -> RigidGroup | str:
    """Reconstruct the largest rigid group among ``members`` projectively over all frames, and
    measure every track (members or not) against it.

    Args:
        tracks: (F, N, 2) float64 pixels (any finite value where not visible).
        visible: (F, N) bool.
        members: (N,) bool, the tracks the group is looked for among.
        fundamental_ransac: RANSAC of the starting pair's F (threshold: Sampson distance, px).
        resection_ransac: RANSAC of every frame's camera (threshold: reprojection error, px).
        refinements: camera / point alternations at most (fewer once they converge, step 4).
        threshold: RMS reprojection error (px) up to which a track belongs to the group while
            the cameras are refined.
        generator: random source of the RANSACs.

    Returns:
        A :class:`RigidGroup`, or why no group could be reconstructed.
    """
    F, N, _ = tracks.shape
    normalized, T = hartley_normalize(tracks[visible])
    scale = float(T[0, 0])
    x = torch.zeros_like(tracks)
    x[visible] = normalized
    seen = visible & members
    r, partner = starting_frames(tracks, seen)
    shared = seen[r] & seen[partner]
    if int(shared.sum()) < 2 * FundamentalModel.sample_size:
        return f"no two frames share {2 * FundamentalModel.sample_size} tracks"
    pair = torch.cat([tracks[r, shared], tracks[partner, shared]], dim=-1)[None]  # pixels: thresholds in px
    found = ransac(FundamentalModel(pair), pair, fundamental_ransac, generator=generator)
    if not bool(found.success[0]):
        return f"no fundamental matrix between frames {r} and {partner}"
    T_inv = torch.linalg.inv(T)
    P_r, P_f = canonical_cameras(T_inv.transpose(-1, -2) @ found.model[0] @ T_inv)  # in normalized coordinates
    group = torch.zeros(N, dtype=torch.bool, device=tracks.device)
    group[shared] = found.inlier_mask[0]
    cameras = torch.zeros(F, 3, 4, dtype=tracks.dtype, device=tracks.device)
    cameras[r], cameras[partner] = P_r, P_f
    two = torch.zeros(F, dtype=torch.bool, device=tracks.device)
    two[[r, partner]] = True
    X = triangulate_multiview(cameras[two], x[two], (visible[two] & group).double())
    model = ProjectiveResectionModel(scale)
    found = ransac(model, torch.cat([X.expand(F, N, 4), x], dim=-1), resection_ransac, valid=visible & group, generator=generator)
    camera_valid = found.success
    cameras = torch.where(camera_valid[:, None, None], found.model, cameras)
    # the camera / point alternations involve the members only; every track is measured once at the end
    index = torch.nonzero(members).flatten()
    x_members, visible_members, core = x[:, index], visible[:, index], group[index]
    M = index.numel()
    previous = None  # the last step's σ² and core
    for step in range(refinements + 1):
        observed = visible_members & camera_valid[:, None]
        X = triangulate_multiview(cameras, x_members, observed.double())
        projected = project(cameras, X.expand(F, M, 4))  # (F, M, 3)
        sse, frames_seen = _reprojection_sums(projected, x_members, observed, scale)
        tested = frames_seen >= 3
        dof = (2 * frames_seen - 3).clamp_min(1)
        reference = core & tested
        if int(reference.sum()) < ProjectiveResectionModel.sample_size:
            return "too few tracks of the group are seen in three frames"
        correction = (1 - 2 / (9 * dof[reference].double())) ** 3  # median of χ²_k / k
        sigma_sq = float((sse[reference] / dof[reference] / correction).median())
        core = tested & (sse <= sigma_sq * chi2_quantile(dof, 1 - significance))
        settled = previous is not None and abs(sigma_sq - previous[0]) <= SETTLED * previous[0] and bool(torch.equal(core, previous[1]))
        if step == refinements or settled:
            break
        previous = sigma_sq, core
        used = observed & core
        depth = projected[..., 2].abs()  # (F, M): rows scaled by 1 / |p3ᵀX|
        typical = floor_tiny(torch.where(used, depth, torch.nan).nanmedian(1).values[:, None])
        weights = torch.where(used, (typical / depth.maximum(DEPTH_FLOOR * typical)).square(), 0.0)
        enough = used.sum(1) >= ProjectiveResectionModel.sample_size
        refit = model.fit_weighted(torch.cat([X.expand(F, M, 4), x_members], dim=-1), weights)
        camera_valid = camera_valid & enough
        cameras = torch.where(enough[:, None, None], refit, cameras)
    observed = visible & camera_valid[:, None]
    X = triangulate_multiview(cameras, x, observed.double())
    sse, frames_seen = _reprojection_sums(project(cameras, X.expand(F, N, 4)), x, observed, scale)
    tested = frames_seen >= 3
    rms = torch.where(tested, (sse / (2 * frames_seen).clamp_min(1)).sqrt(), torch.full_like(sse, float("inf")))
    bound = rms_bound(sigma_sq, (2 * frames_seen - 3).clamp_min(1), 2 * frames_seen, significance, threshold)
    group = members & tested & (rms <= bound)
    return RigidGroup(members=group, rms=rms, frames_seen=frames_seen, cameras=cameras, camera_valid=camera_valid,
                      reference=r, partner=partner)


def _reprojection_sums(projected: Tensor, x: Tensor, observed: Tensor, scale: float) -> tuple[Tensor, Tensor]:
    """Each track's sum of squared reprojection errors in pixels (normalized coordinates over the
    normalization's ``scale``) over the frames it is ``observed`` in, and that count: (F, n, 3)
    homogeneous projections, (F, n, 2) points, (F, n) bool -> (n,), (n,)."""
    squared = torch.where(observed, projection_distance_squared(projected, x), 0.0) / scale**2
    return squared.sum(0), observed.sum(0)
