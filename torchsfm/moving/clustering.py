"""Spectral clustering of the tracks' affinity (step 4 of :mod:`torchsfm.moving.segmentation`).

The leading eigenvectors of the normalized affinity, batched k-means on them, the merges of an
over-segmentation down to a number of motions (found before the largest drop of the merge links
where not given), and the normalized cut that compares partitions.
"""

from __future__ import annotations

import torch
from torch import Tensor

from torchsfm.config import SegmentationConfig
from torchsfm.numerics import component_labels, sparse_rows

SPARSE_EIGEN_TRACKS = 1500  # from here the sparse LOBPCG beats the dense eigh (0.16 s against 0.37 s; at 1000, 0.12 against 0.14;
# measured with a COO matrix, which multiplies 3x slower than the CSR one now used: KITTI 06's 3000 tracks 1.73 -> 0.59 s)
TIE = 1e-9  # values this close (times the largest, at least 1) count as equal (first_within_tie); float64 rounding here stays near 1e-13
EIGEN_RESIDUAL = 1e-6  # largest LOBPCG residual accepted: it stops near 1e-8 (sqrt of float64 eps); a stalled run is far off


def leading_eigenvectors(affinity: Tensor, count: int) -> tuple[Tensor, Tensor]:
    """The ``count`` largest eigenvalues (descending) and eigenvectors (N, count) of the
    normalized affinity D^-1/2 A D^-1/2.

    From ``SPARSE_EIGEN_TRACKS`` tracks on, by LOBPCG on the sparse matrix (each row keeps about
    2 × ``links`` entries; a fixed-seed start, so the result is reproducible), kept where every
    pair's residual ‖M v − λ v‖ is at most ``EIGEN_RESIDUAL`` (M's norm is at most 1), else by the
    dense ``eigh``. On a 3000-track video's affinity both give the eigenvalues to 1e-14 and the
    subspace to 1e-13 (residuals near 1e-8), in 0.7 s instead of 3.4 s."""
    degree = affinity.sum(1).clamp_min(torch.finfo(affinity.dtype).tiny)
    scale = degree.rsqrt()
    normalized = affinity * scale[:, None] * scale[None]
    N = normalized.shape[0]
    count = min(count, N)
    if N >= SPARSE_EIGEN_TRACKS and 3 * count <= N:
        start = torch.randn(N, count, generator=torch.Generator(normalized.device).manual_seed(0), dtype=normalized.dtype,
                            device=normalized.device)
        values, vectors = torch.lobpcg(sparse_rows(normalized), k=count, X=start, largest=True)
        values, order = values.sort(descending=True)
        vectors = vectors[:, order]
        if float((normalized @ vectors - vectors * values).norm(dim=0).max()) <= EIGEN_RESIDUAL:
            return values, vectors
    values, vectors = torch.linalg.eigh(normalized)
    return values.flip(0)[:count], vectors.flip(1)[:, :count]


def kmeans(points: Tensor, k: int, restarts: int, iterations: int, generator: torch.Generator) -> Tensor:
    """Lloyd's k-means on (N, D) points with ``restarts`` random initializations run as one
    batch, for ``iterations`` steps or until every restart's labels repeat (a fixed point: the
    centres, and so every later step, would repeat too); the labels (N,) of the restart with the
    smallest within-cluster sum of squares. Ties — a point as far from two centres, two restarts
    of one cost — go to the first, whatever the rounding (:func:`first_within_tie`), so the labels
    depend on the points' distances only, not on the basis they are written in."""
    N = points.shape[0]
    start = torch.rand(restarts, N, generator=generator, device=points.device).argsort(1)[:, :k]
    centres = points[start]  # (R, k, D)
    previous = None
    for _ in range(iterations):
        labels = _nearest(points, centres)  # (R, N)
        if previous is not None and torch.equal(labels, previous):
            break
        previous = labels
        one_hot = torch.nn.functional.one_hot(labels, k).to(points.dtype)  # (R, N, k)
        counts = one_hot.sum(1)  # (R, k)
        sums = one_hot.transpose(1, 2) @ points  # (R, k, D)
        centres = torch.where(counts[..., None] > 0, sums / counts[..., None].clamp_min(1), centres)
    labels = _nearest(points, centres)
    cost = (points[None] - centres.gather(1, labels[..., None].expand(-1, -1, points.shape[1]))).square().sum((1, 2))
    return labels[int(first_within_tie(cost))]


def _nearest(points: Tensor, centres: Tensor) -> Tensor:
    """(R, N) the nearest of each restart's (R, k, D) centres to every (N, D) point, ties (within
    ``TIE``) to the first. The rows of a spectral embedding of unlinked groups are orthogonal:
    a point is then exactly as far from several centres, and rounding — which differs with the
    eigenvector basis, itself arbitrary for repeated eigenvalues and so different on another
    thread count or LAPACK — would pick among them and send Lloyd's steps elsewhere. Distances
    are computed directly (cdist's matrix-product form loses about 8 digits to cancellation)."""
    distances = torch.cdist(points[None].expand(centres.shape[0], -1, -1), centres,
                            compute_mode="donot_use_mm_for_euclid_dist")
    return first_within_tie(distances)


def first_within_tie(values: Tensor) -> Tensor:
    """(*,) the index along the last dimension of the first of the (*, k) ``values`` within
    ``TIE`` (times their largest magnitude, at least 1) of their smallest: an argmin whose ties do
    not depend on rounding."""
    tolerance = TIE * values.abs().amax(-1, keepdim=True).clamp_min(1)
    return (values <= values.amin(-1, keepdim=True) + tolerance).to(torch.uint8).argmax(-1)


def spectral_partition(vectors: Tensor, count: int, config: SegmentationConfig, generator: torch.Generator) -> Tensor:
    """(N,) labels 0..count-1: k-means (``config.restarts`` restarts) of the rows of the
    ``count`` leading (N, >= count) eigenvectors of the normalized affinity, each row scaled to
    unit length (Ng, Jordan & Weiss 2001)."""
    embedding = vectors[:, :count]
    embedding = embedding / embedding.norm(dim=1, keepdim=True).clamp_min(torch.finfo(embedding.dtype).tiny)
    return kmeans(embedding, count, config.restarts, config.kmeans_iterations, generator)


def split_by_components(affinity: Tensor, labels: Tensor, min_size: int) -> Tensor:
    """(N,) labels 0..K'-1: the (N,) pieces ``labels`` of a spectral cut, each split along the
    connected components of the (N, N) ``affinity`` graph that hold ``min_size`` tracks or more;
    the tracks of smaller components stay with the largest such part of their piece (or as the
    piece was, where it has none). Tracks that no chain of links joins share no evidence of one
    motion, yet k-means may put them in one piece: the rows of unlinked groups are orthogonal,
    but a piece's centre between two groups can be a local minimum of its cost. Merging then
    joins both groups through that piece. Measured: a still camera's two objects (synthetic, 12
    frames, seed 3; 60 tracks each, no link between them) had 14 and 16 tracks in one piece and
    were found as one motion (10.4 % misclassified; now 0); in Hopkins155 2T3RCTP (seed 0) a
    piece held 23 tracks of a 77-track part of the background that no link joins to the rest and
    19 of an object's 110, and that part stayed a motion of its own (16.6 %; now its tracks come
    out as clusters of their own, which settling joins into one scene: 0.2 %)."""
    rows, columns = torch.nonzero(affinity > 0, as_tuple=True)
    component = component_labels(rows, columns, labels.numel())
    large = torch.bincount(component, minlength=labels.numel())[component] >= min_size
    part = torch.where(large, component, -1)
    for piece in labels.unique().tolist():
        members = labels == piece
        parts, sizes = part[members & large].unique(return_counts=True)
        if parts.numel():
            part[members & ~large] = parts[sizes.argmax()]
    _, split = torch.unique(torch.stack([labels, part], 1), dim=0, return_inverse=True)
    return split


def merge_clusters(affinity: Tensor, labels: Tensor, count: int | None, config: SegmentationConfig) -> Tensor:
    """Merge the clusters of an over-segmentation (N,) labels 0..K-1 down to ``count`` clusters.

    Each step joins the two clusters most strongly linked relative to the smaller one's volume,
    cut(A, B) / min(vol(A), vol(B)): the pieces of one motion are linked along their borders,
    distinct motions hardly at all. Without ``count`` the merges run down to one cluster and the
    number kept is the one before the largest relative drop of that link,
    (s_c + floor) / (s_(c-1) + floor) over c = 2..``config.max_motions`` (s_c: the link of the
    merge that leaves c clusters, ``config.link_floor`` the link counted as none); one cluster
    if no drop reaches ``config.min_link_drop``. Returns labels 0..C-1, most tracks first.
    """
    K = int(labels.max()) + 1
    one_hot = torch.nn.functional.one_hot(labels, K).to(affinity.dtype)  # (N, K)
    links = one_hot.T @ affinity @ one_hot  # (K, K)
    alive = torch.bincount(labels, minlength=K) > 0
    tiny = torch.finfo(links.dtype).tiny
    merges: list[tuple[int, int, float]] = []
    while int(alive.sum()) > 1:
        volume = links.sum(1)
        score = links / torch.minimum(volume[:, None], volume[None]).clamp_min(tiny)
        score = torch.where(alive[:, None] & alive[None], score, -1.0).fill_diagonal_(-1.0)
        best = int(score.argmax())
        a, b = divmod(best, K)
        merges.append((a, b, float(score.view(-1)[best])))
        links[a] += links[b]
        links[:, a] += links[:, b]
        links[b] = 0
        links[:, b] = 0
        alive[b] = False
    start = len(merges) + 1  # clusters before any merge
    if count is None:
        link = {start - 1 - i: merge[2] for i, merge in enumerate(merges)}  # clusters left -> link
        drops = {c: (link[c] + config.link_floor) / (link[c - 1] + config.link_floor)
                 for c in range(2, min(config.max_motions, start - 1) + 1)}
        count = max(drops, key=drops.get) if drops and max(drops.values()) >= config.min_link_drop else 1
    groups = torch.arange(K, device=labels.device)
    for a, b, _ in merges[:max(start - count, 0)]:
        groups[groups == b] = a
    merged = groups[labels]
    return largest_first(merged)


def largest_first(labels: Tensor) -> Tensor:
    """(N,) labels >= 0 renumbered 0..C-1 by decreasing number of tracks."""
    survivors, sizes = labels.unique(return_counts=True)
    survivors = survivors[sizes.argsort(descending=True)]
    renumber = torch.full((int(labels.max()) + 1,), -1, dtype=torch.long, device=labels.device)
    renumber[survivors] = torch.arange(survivors.numel(), device=labels.device)
    return renumber[labels]


def normalized_cut(affinity: Tensor, labels: Tensor) -> float:
    """Shi & Malik's normalized cut of a partition, sum over its clusters of cut(c, rest) /
    vol(c): (n, n) affinity, (n,) labels 0..C-1 (every label used)."""
    one_hot = torch.nn.functional.one_hot(labels).to(affinity.dtype)  # (n, C)
    links = one_hot.T @ affinity @ one_hot  # (C, C)
    volume = links.sum(1)
    return float(((volume - links.diagonal()) / volume.clamp_min(torch.finfo(volume.dtype).tiny)).sum())
