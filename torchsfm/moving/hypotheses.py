"""Motion hypotheses of the preference clustering (step 1 of :mod:`torchsfm.moving.segmentation`).

Minimal samples of tracks seen in the same frames, and every track's residual to the model each
sample spans: a fundamental matrix per pair of its frames, a homography per pair, or the affine
subspace of trajectories (:data:`MODELS`). Residual tables are made a chunk of hypotheses at a
time, so memory stays bounded for thousands of tracks.
"""

from __future__ import annotations

from collections.abc import Callable

import torch
from torch import Tensor

from torchsfm.camera import to_homogeneous
from torchsfm.config import SegmentationConfig
from torchsfm.geometry.fundamental import eight_point_minimal
from torchsfm.geometry.normalization import hartley_normalize
from torchsfm.moving.pair_fits import SAMPLE_SIZE
from torchsfm.robust.samplers import draws_without_replacement

SEEN_SUBSET = 0.25  # share of the tracks seen in a pair's first frame (worst_over_pairs) or in a chunk of affine hypotheses'
# frames (affine_residuals) up to which only they are measured: KITTI 06's clustered tracks (7-14 % seen a frame) F / homography
# tables 535 -> 305 / 412 -> 286 ms, affine 210-276 -> 52-143 ms; KT3DMoSeg's clips (56-87 %) 1.2-1.6x slower so (the scattered
# writes); break-even near 25-35 % on a synthetic 1000-track scene
CHUNK_ELEMENTS = 2**21  # numbers per hypothesis chunk: memory bounded for thousands of tracks; 16 MB of float64,
# under glibc's 32 MB ceiling for serving freed blocks again instead of fresh (page-faulting) maps


def sample_hypotheses(tracks: Tensor, visible: Tensor, count: int, frames_per: int, size: int,
                      config: SegmentationConfig, generator: torch.Generator,
                      guide: Tensor | None) -> tuple[Tensor, Tensor, Tensor]:
    """``count`` samples of ``size`` tracks, each seen in the same ``frames_per`` frames.

    tracks (F, N, 2), visible (F, N), guide None or (N, N) similarity -> frames (H, m) sorted,
    sample (H, size) track indices and usable (H,) bool (every sampled track seen in every chosen
    frame). The seed comes first; without a guide the others are among its ``config.neighbours``
    nearest tracks in the first frame for a share ``config.local_share`` of the samples and
    anywhere for the rest; with a guide they are drawn with probability proportional to their
    similarity to the seed (same-motion tracks spread over the whole body, so the model is fitted
    over its extent rather than a patch).
    """
    F, N, _ = tracks.shape
    H, m = count, min(frames_per, F)
    device = tracks.device
    rows = torch.arange(H, device=device)
    seeds = torch.randint(0, N, (H,), generator=generator, device=device)
    frames = torch.multinomial(visible[:, seeds].T.double(), m, generator=generator).sort(1).values  # (H, m)
    seen_in_all = seen_in_every(visible, frames)  # (H, N)
    local = torch.rand(H, generator=generator, device=device) < config.local_share
    if guide is not None:  # + 1e-9: uniform among the seen where too few are similar; the unseen and the seed 1e-30
        weight = guide[seeds].add_(1e-9).masked_fill_(~seen_in_all, 1e-30)
        weight[rows, seeds] = 1e-30
        drawn = draws_without_replacement(weight, size - 1, generator)
        sample = torch.cat([seeds[:, None], drawn], 1)
        return frames, sample, seen_in_all.gather(1, sample).all(1)
    key = torch.rand(H, N, generator=generator, dtype=tracks.dtype, device=device)
    start = tracks[frames[local, 0]]  # (h, N, 2) the first frames of the local samples
    key[local] = (start - start[torch.arange(start.shape[0], device=device), seeds[local]][:, None]).norm(dim=-1)
    key = torch.where(seen_in_all, key, torch.inf)
    key[rows, seeds] = -1.0  # the seed comes first
    pool = min(config.neighbours, N)
    nearest = key.topk(pool, dim=1, largest=False).indices  # (H, pool), seed first
    pick = torch.rand(H, pool - 1, generator=generator, device=device).argsort(1)[:, :size - 1]
    sample = torch.cat([seeds[:, None], nearest[:, 1:].gather(1, pick)], 1)
    usable = torch.isfinite(key.gather(1, sample)).all(1)
    return frames, sample, usable


def seen_in_every(visible: Tensor, frames: Tensor) -> Tensor:
    """(F, N) visibility, (H, m) frames -> (H, N) bool: each track seen in every frame of the
    row, one (H, N) table per frame column (not an (H, m, N) table reduced)."""
    seen = visible[frames[:, 0]]
    for column in range(1, frames.shape[1]):
        seen &= visible[frames[:, column]]
    return seen


def fundamental_residuals(tracks: Tensor, visible: Tensor, count: int, config: SegmentationConfig, generator: torch.Generator,
                          guide: Tensor | None = None) -> tuple[Tensor, Tensor]:
    """Residuals of every track to ``count`` sampled multi-frame F models.

    tracks (F, N, 2) float64, visible (F, N) -> residuals (H, N) px² (the largest squared Sampson
    distance over the hypothesis' frame pairs: squared, for only their order counts — the
    preferences are ranks) and defined (H, N) bool.
    """
    frames, sample, usable = sample_hypotheses(tracks, visible, count, config.sample_frames, SAMPLE_SIZE, config, generator, guide)

    def fit(x1: Tensor, x2: Tensor) -> Tensor:
        return eight_point_minimal(x1[:, None], x2[:, None], hartley_normalize(x1)[1], hartley_normalize(x2)[1])[:, 0]

    return worst_over_pairs(tracks, visible, frames, sample, usable, fit, sampson_to_each)


def worst_over_pairs(tracks: Tensor, visible: Tensor, frames: Tensor, sample: Tensor, usable: Tensor,
                     fit: Callable[[Tensor, Tensor], Tensor], distance: Callable[[Tensor, Tensor, Tensor], Tensor]
                     ) -> tuple[Tensor, Tensor]:
    """Two-view models of H samples over every pair of their m frames: ``fit`` (H, s, 2) x2 ->
    (H, 3, 3) models, ``distance`` (h models (h, 3, 3), the points (N, 2) of their first frame,
    each model's second frame's points (2, h, N), the coordinates apart) -> (h, N) (pixels, or
    any increasing function of them).
    Returns each track's largest distance over the pairs in which it is seen (H, N), and where
    that is defined (H, N): seen in a pair, a usable sample, a finite model, and not one of the
    sample's tracks. In blocks of hypotheses whose (h · P, N) table of distances fits
    ``CHUNK_ELEMENTS`` (P = m(m - 1)/2 pairs), the models of a block's hypotheses sharing a
    pair's first frame are scored together on its points (one product for all; a video has up
    to F²/2 frame pairs but F first frames), each into its own row of the table (on the tracks
    seen in that frame only where they are at most ``SEEN_SUBSET`` of them: a video of short
    tracks); the largest over a hypothesis' P rows is taken per block."""
    H, m = frames.shape
    N = tracks.shape[1]
    first, second = torch.triu_indices(m, m, 1, device=frames.device)
    a, b = frames[:, first], frames[:, second]  # (H, P) frame pairs of every hypothesis
    P = a.shape[1]
    models = torch.stack([fit(tracks[a[:, p, None], sample], tracks[b[:, p, None], sample]) for p in range(P)], 1).reshape(-1, 3, 3)
    coordinates = tracks.permute(2, 0, 1).contiguous()  # (2, F, N)
    worst = tracks.new_empty(H, N)
    block = max(1, CHUNK_ELEMENTS // (P * N))
    for start in range(0, H, block):
        part = slice(start * P, min(H, start + block) * P)  # row h * P + p: hypothesis h on its pair p
        starts, ends, block_models = a.reshape(-1)[part], b.reshape(-1)[part], models[part]
        per_pair = tracks.new_empty(starts.numel(), N)  # 0 where the track is not seen in the pair
        order = starts.argsort()
        firsts, counts = starts[order].unique_consecutive(return_counts=True)
        for i, rows in zip(firsts.tolist(), order.split(counts.tolist())):
            second = ends[rows]
            seen = torch.nonzero(visible[i])[:, 0]  # (n,)
            if seen.numel() <= SEEN_SUBSET * N:  # the tracks seen in the first frame only
                unseen = ~visible[second[:, None], seen]  # (h, n)
                per_pair[rows] = 0.0
                per_pair[rows[:, None], seen] = distance(block_models[rows], tracks[i, seen],
                                                         coordinates[:, second[:, None], seen]).masked_fill_(unseen, 0.0)
                continue
            unseen = ~(visible[i] & visible[second])  # (h, N)
            per_pair[rows] = distance(block_models[rows], tracks[i], coordinates[:, second]).masked_fill_(unseen, 0.0)
        worst[start:start + block] = per_pair.view(-1, P, N).amax(1)  # residuals are >= 0 (or NaN)
    seen_in_a_pair = visible[a[:, 0]] & visible[b[:, 0]]  # (H, N)
    for p in range(1, P):
        seen_in_a_pair |= visible[a[:, p]] & visible[b[:, p]]
    defined = torch.isfinite(worst).logical_and_(seen_in_a_pair).logical_and_(usable[:, None])
    return worst, defined.scatter_(1, sample, False)


def affine_residuals(tracks: Tensor, visible: Tensor, count: int, config: SegmentationConfig, generator: torch.Generator,
                     guide: Tensor | None = None) -> tuple[Tensor, Tensor]:
    """Residuals of every track to ``count`` sampled affine-camera motions over ``config.affine_frames``
    frames: 4 tracks span the 3-dimensional affine subspace of trajectories of their rigid
    motion (Tomasi & Kanade); a track's residual is its squared distance to it per frame (px²:
    only the order counts). Defined where the track is seen in all the frames. -> (H, N), (H, N)
    bool (the residuals are written where defined at least). In chunks of hypotheses; where every
    chunk of them taken by first frame holds at most ``SEEN_SUBSET`` of the tracks seen in all
    of some hypothesis' frames (a video of short tracks: KITTI 06's clustered tracks 6-13 %, the
    hypotheses in random order 32-37 %), the chunks are taken so and measure those tracks only."""
    frames, sample, usable = sample_hypotheses(tracks, visible, count, config.affine_frames, 4, config, generator, guide)
    H, m = frames.shape
    F, N, _ = tracks.shape
    centred = torch.where(visible[..., None], tracks - tracks[visible].mean(0), 0.0)  # smaller terms to cancel
    flat = centred.permute(1, 0, 2).reshape(N, 2 * F)  # every track's trajectory: x, y of frame 0, of frame 1, ...
    columns = (2 * frames[..., None] + torch.arange(2, device=tracks.device)).reshape(H, 2 * m)
    chosen = flat[sample[..., None], columns[:, None]]  # (H, 4, 2m) the sample's trajectories
    origin = chosen[:, 0]
    basis, triangle = torch.linalg.qr((chosen[:, 1:] - origin[:, None]).transpose(1, 2))  # (H, 2m, 3)
    extent = triangle.diagonal(dim1=1, dim2=2).abs().amin(1)
    rows = torch.arange(H, device=tracks.device)[:, None]
    select = flat.new_zeros(H, 2 * F).index_put_((rows, columns), flat.new_ones(()))
    origin_full = flat.new_zeros(H, 2 * F).index_put_((rows, columns), origin)
    basis_full = flat.new_zeros(H, 2 * F, 3).index_put_((rows, columns), basis)
    origin_norm = origin.square().sum(1, keepdim=True)
    origin_in_basis = (basis * origin[..., None]).sum(1)  # (H, 3)
    residual = tracks.new_empty(H, N)
    trajectories, squares = flat.T, flat.square().T  # (2F, N)
    seen = seen_in_every(visible, frames)  # (H, N)
    chunk = max(1, CHUNK_ELEMENTS // (3 * N))  # hypotheses at a time: (chunk, 3, N) projections
    order = frames[:, 0].argsort()
    held = [seen[order[first:first + chunk]].any(0) for first in range(0, H, chunk)]  # (N,) each
    subset = all(int(tracks_held.sum()) <= SEEN_SUBSET * N for tracks_held in held)
    for first in range(0, H, chunk):  # distance² to the span: |t - o|² - |Bᵀ(t - o)|², B orthonormal
        part = order[first:first + chunk] if subset else slice(first, first + chunk)
        measured = torch.nonzero(held[first // chunk])[:, 0] if subset else slice(None)
        t, t_squared = trajectories[:, measured], squares[:, measured]  # (2F, n)
        offset_norm = select[part] @ t_squared - 2 * origin_full[part] @ t + origin_norm[part]
        axes = basis_full[part].transpose(1, 2)  # (h, 3, 2F): one product for all hypotheses
        projection = (axes.reshape(-1, 2 * F) @ t).view(axes.shape[0], 3, -1).sub_(origin_in_basis[part, :, None])
        distance = (offset_norm - projection.square_().sum(1)).clamp_min(0) / m
        if subset:
            residual[part[:, None], measured] = distance
        else:
            residual[part] = distance
    defined = seen.logical_and_((usable & (extent > 1.0))[:, None])
    return residual, defined.scatter_(1, sample, False)


def homography_residuals(tracks: Tensor, visible: Tensor, count: int, config: SegmentationConfig, generator: torch.Generator,
                         guide: Tensor | None = None) -> tuple[Tensor, Tensor]:
    """Residuals of every track to ``count`` sampled plane motions: 4 tracks over ``config.sample_frames``
    frames, one homography per frame pair (4-point solve in Hartley-normalized coordinates); a
    track's residual is its largest squared transfer distance (px²: only the order counts) over the
    pairs in which it is seen.
    A plane is a local model: it separates a body from the scene around it even where their
    epipolar geometry agrees (a car driving along the camera's direction). -> (H, N), (H, N) bool."""
    frames, sample, usable = sample_hypotheses(tracks, visible, count, config.sample_frames, 4, config, generator, guide)
    return worst_over_pairs(tracks, visible, frames, sample, usable, four_point_homography, transfer_to_each)


def sampson_to_each(F: Tensor, x1: Tensor, x2: Tensor) -> Tensor:
    """Squared Sampson distances (h, N) of h fundamental matrices F (h, 3, 3), each between the
    points x1 (N, 2) and its own second points x2 (2, h, N) (the coordinates apart): the
    epipolar lines F x1 as one (3h, 3) x (3, N) product, the rest element by element."""
    lines = images_by_each(F, x1)  # (3, h, N)
    u, v = x2
    algebraic = lines[0] * u
    algebraic += lines[1] * v
    algebraic += lines[2]
    entry = F[..., None]  # (h, 3, 3, 1): one entry of each model against its row of points
    back_u = entry[:, 0, 0] * u  # (Fᵀ x2) rows 0 and 1
    back_u += entry[:, 1, 0] * v
    back_u += entry[:, 2, 0]
    back_v = entry[:, 0, 1] * u
    back_v += entry[:, 1, 1] * v
    back_v += entry[:, 2, 1]
    gradient = lines[0].square()
    gradient += lines[1].square()
    gradient += back_u.square_()
    gradient += back_v.square_()
    return algebraic.square_().div_(gradient.clamp_min_(1e-30))


def transfer_to_each(G: Tensor, x1: Tensor, x2: Tensor) -> Tensor:
    """Squared transfer distances (h, N) of h homographies G (h, 3, 3), each mapping the points
    x1 (N, 2) onto its own second points x2 (2, h, N) (the coordinates apart); +inf where a
    point maps to infinity."""
    mapped = images_by_each(G, x1)  # (3, h, N)
    w = mapped[2]
    error = (mapped[0] / w - x2[0]).square_()
    error += (mapped[1] / w - x2[1]).square_()
    return torch.where(w.abs() > 1e-12, error, torch.inf)


def images_by_each(M: Tensor, x: Tensor) -> Tensor:
    """Homogeneous images (3, h, N) of the points x (N, 2) under each of h matrices M (h, 3, 3),
    as three (h, 3) x (3, N) products, one per row of the matrices: entry (k, r, n) is row k of
    M_r applied to x_n. (The same numbers as one (3h, 3) x (3, N) product took 5x as long on two
    threads: 0.65 against 0.11 ms for h = 110, N = 1000.)"""
    return torch.matmul(M.transpose(0, 1), to_homogeneous(x).T)


def four_point_homography(x1: Tensor, x2: Tensor) -> Tensor:
    """(H, 4, 2) correspondences -> (H, 3, 3) homographies x2 ~ H x1 (h33 = 1 in normalized
    coordinates; NaN for a degenerate sample)."""
    n1, T1 = hartley_normalize(x1)
    n2, T2 = hartley_normalize(x2)
    x, y, u, v = n1[..., 0], n1[..., 1], n2[..., 0], n2[..., 1]
    one, zero = torch.ones_like(x), torch.zeros_like(x)
    rows_u = torch.stack([x, y, one, zero, zero, zero, -u * x, -u * y], -1)
    rows_v = torch.stack([zero, zero, zero, x, y, one, -v * x, -v * y], -1)
    h, info = torch.linalg.solve_ex(torch.cat([rows_u, rows_v], -2), torch.cat([u, v], -1)[..., None])
    G = torch.cat([h[..., 0], torch.ones_like(h[..., :1, 0])], -1).reshape(-1, 3, 3)
    G = torch.where((info == 0)[:, None, None], G, torch.nan)
    return torch.linalg.inv(T2) @ G @ T1


MODELS = {"fundamental": fundamental_residuals, "affine": affine_residuals, "homography": homography_residuals}
