"""IMOR (thesis Alg. 5.4.1) and IMOR + RANSAC: reject the correspondences of independently moving
objects and outliers from N points tracked over three frames.

1. Frames 0 and 2 are registered to frame 1 by their dominant planes (plane + parallax).
2. Seed: N candidates at equal steps of the sorted parallax norms (Fig. 5.4's axis) among the
   vectors with informative parallax; each counts the vectors outside its neighbourhood d1 that
   satisfy the rigidity constraint with it within t1; the best count is the background seed.
3. Of the 4M informative vectors outside the seed's neighbourhood that fit it best, the M with
   the largest consensus (counted as for the seed) become supports (ours: the thesis takes the
   M that fit best, and a moving vector that happens to fit the seed then votes its own object
   in and the background out).
   Consensus counts only informative tests: those where the support's parallax across the line
   to the other point is at least ``min_support_parallax`` (ours: a support on or near the plane
   passes every vector, so a raw count prefers the least informative supports).
4. Each support keeps the vectors it explains (within t1, or its best p, ``selection``).
5. A vector kept by at least K supports is background. If the plane explains a large share of the
   vectors and that rigid group's parallax is offset from zero as a whole, it is an object on a
   planar background (Irani & Anandan's 2D case; ours): only vectors without parallax are kept.
6. (IMOR + RANSAC) robust F on pairs (1, 0), (1, 2), (0, 2) of the background only; a vector
   must be an inlier of all three.

Where the decomposition cannot work — no dominant plane, too little parallax (planar or purely
rotating scenes, all points moving together) — IMOR is skipped, RANSAC alone decides and the
result says why in ``fallback``.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass

import torch
from torch import Tensor

from torchsfm.config import Config, MovingObjectsConfig
from torchsfm.errors import NotEnoughDataError
from torchsfm.estimators.two_view_geometry import estimate_fundamental
from torchsfm.inference import without_autograd
from torchsfm.moving.parallax import PlaneParallax, plane_parallax_batch
from torchsfm.moving.rigidity import rigidity_residuals
from torchsfm.robust.ragged import pad_rows
from torchsfm.validation import check_finite, check_floating, check_shapes

MIN_VECTORS = 12  # the quadratic flow needs 4 points; RANSAC on it and on F needs clearly more
CASCADE_PAIRS = ((1, 0), (1, 2), (0, 2))  # the frame pairs whose F the cascade's RANSAC tests, reference first


@dataclass
class MovingObjectRejection:
    """Result of :func:`reject_moving_objects` for N vectors.

    Fields:
        background_mask: (N,) bool, the final decision (IMOR + RANSAC, or IMOR alone).
        imor_mask: (N,) bool, IMOR's background (all True when IMOR fell back).
        ransac_mask: (N,) bool, inliers of the three fundamental matrices, tested on IMOR's
            background only; None without RANSAC.
        votes: (N,) int64, supports that kept each vector (0 where IMOR did not vote).
        seed_index: the background seed (-1 where none could be chosen).
        supports: (S,) int64 indices of the supports (S <= M).
        parallax: (2, N, 2) residual parallax of frames 0 and 2 against frame 1, pixels.
        plane_inliers: (N,) bool, the dominant plane's inliers (in frames 0 and 2).
        planar_background: IMOR's rigid parallax group looked like an object on a planar
            background (see ``planar_background_ratio``), so only the plane was kept.
        plane_trials: RANSAC samples drawn for the dominant plane.
        ransac_trials: RANSAC samples drawn for the fundamental matrices (0 without RANSAC).
        fallback: why IMOR was skipped (RANSAC alone then decides), else None.
    """

    background_mask: Tensor
    imor_mask: Tensor
    ransac_mask: Tensor | None
    votes: Tensor
    seed_index: int
    supports: Tensor
    parallax: Tensor
    plane_inliers: Tensor
    planar_background: bool
    plane_trials: int
    ransac_trials: int
    fallback: str | None


def check_frames(*frames: Tensor) -> Tensor:
    """Validate three or more (N, 2) point sets of one N; return them stacked (F, N, 2), float64."""
    if len(frames) < 3:
        raise NotEnoughDataError(f"the rigidity constraint needs the points in three frames, got {len(frames)}")
    names = {f"x{i}": (x, "N 2") for i, x in enumerate(frames)}
    sizes = check_shapes(**names)
    check_floating(**{name: x for name, (x, _) in names.items()})
    check_finite(**{name: x for name, (x, _) in names.items()})
    if sizes["N"] < MIN_VECTORS:
        raise NotEnoughDataError(f"{sizes['N']} vectors are too few: the planar flow and RANSAC need at least {MIN_VECTORS}")
    return torch.stack([x.double() for x in frames])


def epipolar_consistency(x0: Tensor, x1: Tensor, x2: Tensor, *, config: Config | None = None,
                         generator: torch.Generator | None = None) -> tuple[Tensor, int]:
    """RANSAC alone: inliers of the robust F of pairs (1, 0), (1, 2) and (0, 2), batched.

    ``config.fundamental``'s RANSAC (with its LO refits) decides; the LM polish of F is skipped:
    only the mask is used, and the pipelines estimate their geometry from the kept vectors.

    Args:
        x0, x1, x2: (N, 2) float64 pixels of the same points in three frames.

    Returns:
        (N,) bool, an inlier of all three F; and the RANSAC samples drawn in total.

    Raises:
        NotEnoughDataError: RANSAC finds no F for one of the pairs.
    """
    found = _consistency([torch.stack([x0, x1, x2])], config or Config(), generator)[0]
    if isinstance(found, str):
        raise NotEnoughDataError(found)
    return found


def _consistency(triplets: list[Tensor], config: Config, generator: torch.Generator | None) -> list[tuple[Tensor, int] | str]:
    """:func:`epipolar_consistency` of T triplets (3, N_t, 2) as one call on their 3T pairs
    (one triplet unpadded: the draws of a call of its own); per triplet its mask and samples
    drawn, or why RANSAC found no F for one of its pairs."""
    config = dataclasses.replace(config, fundamental=dataclasses.replace(config.fundamental, refine=False))
    first = [frames[i] for frames in triplets for i, _ in CASCADE_PAIRS]
    second = [frames[j] for frames in triplets for _, j in CASCADE_PAIRS]
    if len(triplets) == 1:
        try:
            found = estimate_fundamental(torch.stack(first), torch.stack(second), config=config, generator=generator)
        except NotEnoughDataError as error:
            return [str(error)]
        return [(found.inlier_mask.all(0), int(found.num_trials.sum()))]
    data, valid = pad_rows([torch.cat(pair, -1) for pair in zip(first, second)])
    found = estimate_fundamental(data[..., :2], data[..., 2:], valid=valid, config=config, generator=generator)
    results = []
    for t, frames in enumerate(triplets):
        rows = slice(3 * t, 3 * t + 3)
        results.append((found.inlier_mask[rows, : frames.shape[1]].all(0), int(found.num_trials[rows].sum()))
                       if bool(found.success[rows].all()) else "RANSAC found no fundamental matrix with at least 8 inliers")
    return results


def _seed_and_supports(x1: Tensor, warped: Tensor, parallax: Tensor, config: MovingObjectsConfig) -> tuple[int, Tensor] | str:
    """Steps 2–3 of Alg. 5.4.1: the background seed and the supports, or why there are none."""
    norm = parallax.square().sum((0, 2)).sqrt()  # (N,)
    informative = torch.nonzero(norm >= config.min_support_parallax).flatten()
    if informative.numel() < 2:
        return (f"only {informative.numel()} vector(s) show a residual parallax of {config.min_support_parallax} px "
                "(a planar or purely rotating scene, or all points moving together)")
    by_norm = informative[torch.argsort(norm[informative])]
    steps = torch.linspace(0, by_norm.numel() - 1, min(config.seed_candidates, by_norm.numel()), device=norm.device).round().long()
    candidates = by_norm[steps.unique()]
    radius = config.neighbourhood * float((x1.amax(0) - x1.amin(0)).norm())

    def consensus(points: Tensor) -> tuple[Tensor, Tensor, Tensor]:
        """Residuals (P, N), 'an informative test outside the neighbourhood' (P, N), and the
        number of such tests passed (P,)."""
        residuals, strength = rigidity_residuals(points, warped, parallax)
        residuals = residuals.abs()
        tested = (torch.cdist(x1[points], x1) > radius) & (strength >= config.min_support_parallax)
        return residuals, tested, ((residuals <= config.rigidity_threshold) & tested).sum(-1)

    residuals, tested, counts = consensus(candidates)
    best = int(torch.argmax(counts))
    pool = informative[tested[best, informative]]
    if pool.numel() == 0:
        return "no vector with parallax outside the seed's neighbourhood"
    # the 4M vectors that fit the seed best; of those, the M with the largest consensus
    closest = pool[torch.argsort(residuals[best, pool])[: 4 * config.supports]]
    _, _, support_counts = consensus(closest)
    return int(candidates[best]), closest[torch.argsort(support_counts, descending=True, stable=True)[: config.supports]]


def _votes(supports: Tensor, warped: Tensor, parallax: Tensor, config: MovingObjectsConfig) -> Tensor:
    """Steps 4–5: how many supports keep each vector, (N,)."""
    residuals = rigidity_residuals(supports, warped, parallax)[0].abs()  # (S, N)
    if config.selection == "threshold":
        kept = residuals <= config.rigidity_threshold
    else:
        N = residuals.shape[1]
        rank = torch.argsort(torch.argsort(residuals, dim=1), dim=1)
        kept = rank < math.ceil(config.keep_fraction * N)
    return kept.sum(0)


@without_autograd
def reject_moving_objects(x0: Tensor, x1: Tensor, x2: Tensor, *, config: Config | None = None,
                          generator: torch.Generator | None = None) -> MovingObjectRejection:
    """Keep the static background of N points tracked in three frames (IMOR + RANSAC, §5.4).

    Args:
        x0, x1, x2: (N, 2) pixel positions of the same N points in three frames (frame 1 is
            the reference), N >= 12.
        config: ``config.moving_objects`` (IMOR; ``ransac=False`` gives IMOR alone) and
            ``config.fundamental`` (the cascade's RANSAC).
        generator: random source of all RANSACs.

    Returns:
        A :class:`MovingObjectRejection`.

    Raises:
        ShapeError, InputError: malformed or mismatched input. NotEnoughDataError: fewer than 12
        vectors, or RANSAC finds no fundamental matrix.
    """
    result = reject_moving_objects_in_triplets([check_frames(x0, x1, x2)], config=config, generator=generator)[0]
    if isinstance(result, str):
        raise NotEnoughDataError(result)
    return result


def reject_moving_objects_in_triplets(triplets: list[Tensor], *, config: Config | None = None,
                                      generator: torch.Generator | None = None) -> list[MovingObjectRejection | str]:
    """:func:`reject_moving_objects` of T triplets at once: the plane RANSACs of all of them run
    as one ragged call, and so do the cascade's F RANSACs (one call per round size); the seed,
    supports and votes are chosen per triplet.

    Args:
        triplets: T (3, N_t, 2) float64 pixels, N_t >= 12, frame 1 the reference.
        config, generator: as for :func:`reject_moving_objects`.

    Returns:
        Per triplet its :class:`MovingObjectRejection`, or why it has none (RANSAC found no F).
    """
    config = config or Config()
    settings = config.moving_objects
    if len(triplets) == 1:  # unpadded: the same draws as a triplet on its own
        reference, others, valid = triplets[0][1][None], triplets[0][[0, 2]][None], None
    else:
        data, valid = pad_rows([frames.transpose(0, 1).flatten(1) for frames in triplets])  # (T, N, 6)
        frames = data.unflatten(-1, (3, 2)).transpose(1, 2)  # (T, 3, N, 2)
        reference, others = frames[:, 1], frames[:, [0, 2]]
    decompositions = plane_parallax_batch(reference, others, valid, settings, generator)
    outcomes = [_imor(frames, decomposition, settings) for frames, decomposition in zip(triplets, decompositions)]
    cascades: dict[bool, list[int]] = {}  # IMOR's background is nearly clean: RANSAC starts with small rounds
    for t, outcome in enumerate(outcomes):
        if settings.ransac or outcome.fallback is not None:
            cascades.setdefault(outcome.fallback is None, []).append(t)
    consistency: dict[int, tuple[Tensor, int] | str] = {}
    for small_rounds, members in cascades.items():
        cascade = config
        if small_rounds:
            ransac = dataclasses.replace(config.fundamental.ransac, initial_hypotheses=settings.ransac_initial_hypotheses)
            cascade = dataclasses.replace(config, fundamental=dataclasses.replace(config.fundamental, ransac=ransac))
        found = _consistency([triplets[t][:, outcomes[t].background] for t in members], cascade, generator)
        consistency.update(zip(members, found))
    return [_result(outcome, consistency.get(t)) for t, outcome in enumerate(outcomes)]


def _result(outcome: _Outcome, consistency: tuple[Tensor, int] | str | None) -> MovingObjectRejection | str:
    """The rejection of one triplet from IMOR's outcome and the cascade's F inliers among IMOR's
    background (None: no cascade), or why the cascade found no F."""
    if isinstance(consistency, str):
        return consistency
    imor = outcome.background
    ransac_mask, trials, background = None, 0, imor
    if consistency is not None:
        consistent, trials = consistency
        ransac_mask = torch.zeros_like(imor)
        ransac_mask[imor] = consistent
        background = imor & ransac_mask
    decomposition = outcome.decomposition
    return MovingObjectRejection(
        background_mask=background, imor_mask=imor, ransac_mask=ransac_mask, votes=outcome.votes, seed_index=outcome.seed,
        supports=outcome.supports, parallax=decomposition.parallax, plane_inliers=decomposition.plane_inliers,
        planar_background=outcome.planar, plane_trials=decomposition.num_trials,
        ransac_trials=trials, fallback=outcome.fallback,
    )


@dataclass
class _Outcome:
    decomposition: PlaneParallax
    background: Tensor
    votes: Tensor
    seed: int
    supports: Tensor
    planar: bool
    fallback: str | None


def _imor(frames: Tensor, decomposition: PlaneParallax, settings: MovingObjectsConfig) -> _Outcome:
    """Alg. 5.4.1 on (3, N, 2) frames, given their plane + parallax decomposition."""
    N = frames.shape[1]
    warped, parallax = decomposition.warped, decomposition.parallax
    plane_share = decomposition.plane_inliers.sum().item() / N
    votes = torch.zeros(N, dtype=torch.long, device=frames.device)
    seed, supports, planar = -1, torch.zeros(0, dtype=torch.long, device=frames.device), False
    if not torch.isfinite(warped).all():
        fallback = "the dominant plane maps some points to infinity"
    elif plane_share < settings.min_plane_share:
        fallback = f"no dominant plane: the best explains {plane_share:.0%} of the vectors (needs {settings.min_plane_share:.0%})"
    else:
        chosen = _seed_and_supports(frames[1], warped, parallax, settings)
        fallback = chosen if isinstance(chosen, str) else None
    background = torch.ones(N, dtype=torch.bool, device=frames.device)
    if fallback is None:
        seed, supports = chosen
        votes = _votes(supports, warped, parallax, settings)
        background = votes >= math.ceil(settings.min_votes * supports.numel() / settings.supports)
        norm = parallax.square().sum((0, 2)).sqrt()
        rigid = norm[background & (norm >= settings.min_support_parallax)]
        planar = (rigid.numel() > 0 and plane_share >= settings.planar_background_share
                  and bool(torch.quantile(rigid, 0.1) > settings.planar_background_ratio * rigid.median()))
        if planar:  # I&A's 2D case: the rigid parallax group is an object, the plane the background
            background = norm < settings.min_support_parallax
        if int(background.sum()) < MIN_VECTORS:
            fallback = f"IMOR kept only {int(background.sum())} of {N} vectors"
            background = torch.ones(N, dtype=torch.bool, device=frames.device)
    return _Outcome(decomposition, background, votes, seed, supports, planar, fallback)
