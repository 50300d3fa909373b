"""The one RANSAC engine of torchsfm (thesis §3.3.3, Alg. 3.3.3), batched over problems.

Models plug in through the :class:`RobustModel` protocol (minimal fit, weighted fit, residuals),
samplers and scoring rules through registries. Each round draws a whole batch of minimal samples
for every problem, fits and scores them as tensors, and keeps each problem's best model; the
adaptive trial count of eq. 3.3.7 is then updated per problem from its best inlier ratio and a
problem stops once it has drawn enough samples (or hit ``max_trials``). The only host
synchronisation is one scalar per round.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Protocol

import torch
from torch import Tensor

from torchsfm.config import RansacConfig
from torchsfm.numerics import where_per_problem
from torchsfm.robust.samplers import SAMPLERS, UniformSampler, resolve_generator

ROUND_ELEMENTS = 2**23  # hypotheses × rows of one round's block of problems (see ``ransac``)


class RobustModel(Protocol):
    """What a model must provide to be estimated by :func:`ransac`.

    Data are rows of a (B, N, D) tensor (e.g. D = 4 for a correspondence x1 ↔ x2). Model
    parameters have any trailing shape M (e.g. (3, 3) for F).
    """

    sample_size: int

    def fit_minimal(self, samples: Tensor) -> tuple[Tensor, Tensor]:
        """(B, K, s, D) minimal samples -> models (B, H, *M) and validity (B, H); H = K × solutions."""

    def fit_weighted(self, data: Tensor, weights: Tensor) -> Tensor:
        """Non-minimal fit on (B, N, D) with (B, N) weights -> (B, *M)."""

    def residuals(self, models: Tensor, data: Tensor) -> Tensor:
        """Squared residuals (B, H, N) of models (B, H, *M), in the threshold's unit squared."""

    def sampling_coordinates(self, data: Tensor) -> Tensor:
        """(B, N, 2) image positions the bucketed sampler uses."""

    def restricted(self, problems: Tensor) -> RobustModel:
        """The same model for the problems (P,) of the batch only (the rounds after some problems
        have stopped run on the others alone)."""


def inlier_count_score(squared_residuals: Tensor, inliers: Tensor, threshold_sq: float) -> Tensor:
    """Number of inliers (thesis): (B, H, N) -> (B, H)."""
    return inliers.sum(-1).to(squared_residuals.dtype)


def msac_score(squared_residuals: Tensor, inliers: Tensor, threshold_sq: float) -> Tensor:
    """Negated truncated quadratic loss (Torr & Zisserman 2000): (B, H, N) -> (B, H), higher is better."""
    loss = torch.where(inliers, squared_residuals, torch.full_like(squared_residuals, threshold_sq))
    return -loss.sum(-1)


SCORINGS = {"inlier_count": inlier_count_score, "msac": msac_score}


@dataclass
class RansacResult:
    """Outcome of :func:`ransac` for B problems.

    Fields:
        model: (B, *M) best model (refined on its inliers when ``local_refits`` > 0).
        inlier_mask: (B, N) bool, residual below the threshold under ``model``.
        num_trials: (B,) int64, minimal samples drawn.
        success: (B,) bool, a model with at least ``sample_size`` inliers was found.
    """

    model: Tensor
    inlier_mask: Tensor
    num_trials: Tensor
    success: Tensor


def required_trials(inlier_ratio: Tensor, sample_size: int, confidence: float, max_trials: int) -> Tensor:
    """Trials needed by eq. 3.3.7, N = log(1 - p) / log(1 - w^s), clamped to [1, max_trials]: (B,)."""
    good_sample = inlier_ratio.double().clamp(0, 1) ** sample_size
    needed = math.log(1 - confidence) / torch.log1p(-good_sample.clamp_max(1 - 1e-16))
    needed = torch.where(good_sample > 0, needed, torch.full_like(needed, float(max_trials)))
    return needed.ceil().clamp(1, max_trials).long()


def ransac(
    model: RobustModel,
    data: Tensor,
    config: RansacConfig,
    *,
    valid: Tensor | None = None,
    generator: torch.Generator | None = None,
) -> RansacResult:
    """Robustly fit ``model`` to each of B point sets.

    Each round draws a batch of minimal samples per problem (the batch doubles from
    ``initial_hypotheses`` up to ``hypotheses_per_round``), fits them, and scores them. With ``preemptive_points`` > 0 every
    hypothesis is first scored on a random subset of that many points and only the best
    ``preemptive_keep`` fraction is scored on all points (Nistér's preemptive scoring). When a
    round's best minimal model scores higher than every minimal model the problem drew before,
    it is re-fitted on its inliers up to ``local_refits`` times while the score does not drop
    (LO-RANSAC, Chum et al. 2003), and becomes the problem's best if it then scores higher, so the
    adaptive stopping rule sees the inlier ratio of a refined model; each refit runs on the
    problems whose inliers moved at the last one only, and the refits end once none did (a refit
    of the same inliers would repeat the last one). Chum et al. polish a model that beats the
    polished best: a minimal model of noisy points then has to beat a refined one unrefined, and
    a refined local optimum holds out against the samples that would lead to the right model
    (measured: F at 60 % outliers, 0.5 px noise, ended at 223-309 of ~380 true inliers on 13 of 90
    runs, where nine in ten all-inlier samples score below such an optimum before refinement).
    Records of the minimal models' scores are few (about the log of the rounds drawn), so
    polishing them costs a few refits more (F, 30 synthetic scenes: 6.6 → 9.6 refits per problem
    at 30 % outliers, 17 → 32 at 60 %; with them the 60 % runs off by more than 3 degrees in t
    went from 13 to 3 of 90). A problem stops drawing once its adaptive trial
    count is reached (its inlier ratio taken as at least ``min_inliers`` / N: a model with fewer
    is of no use); later rounds run on the problems still drawing only (the model plug-in's
    ``restricted``), so a batch costs about what its problems cost one at a time, not its
    slowest problem times B.

    Args:
        model: the estimator plug-in (see :class:`RobustModel`).
        data: (B, N, D) rows, one problem per batch entry.
        config: threshold, confidence, trial cap, sampler, scoring, refits, preemption.
        valid: optional (B, N) bool; False rows are padding and never sampled nor counted.
        generator: source of all random draws; None means a generator seeded with 0 (the one
            policy of torchsfm: results are reproducible unless the caller passes its own).

    Returns:
        A :class:`RansacResult`; problems with fewer than ``sample_size`` valid rows report
        ``success = False`` and zero trials.
    """
    B, N, D = data.shape
    s = model.sample_size
    device = data.device
    generator = resolve_generator(generator, device)
    if valid is None:
        valid = torch.ones(B, N, dtype=torch.bool, device=device)
    num_valid = valid.sum(-1)
    valid_counts = num_valid.clamp_min(1).double()  # (B,) the denominators of the inlier ratios
    useful_ratio = config.min_inliers / valid_counts  # (B,): the adaptive count's floor
    padded = not bool(valid.all())
    threshold_sq = config.inlier_threshold**2
    score_fn = SCORINGS[config.scoring]
    sampler = SAMPLERS[config.sampler](model.sampling_coordinates(data), valid, config.grid_size)
    preemptive = 0 < config.preemptive_points < N
    subset_sampler = UniformSampler(data, valid) if preemptive else None

    def evaluate(model: RobustModel, models: Tensor, ok: Tensor, rows: Tensor, rows_valid: Tensor) -> tuple[Tensor, Tensor]:
        """Score (P, H) and inlier mask (P, H, N) of hypotheses (P, H, *M) valid (P, H) on their rows."""
        residuals = model.residuals(models, rows)  # (P, H, N); NaN is no inlier
        inliers = residuals < threshold_sq
        if padded:
            inliers &= rows_valid[:, None, :]
        # an invalid hypothesis scores -inf: it is never chosen, whatever its inliers read
        return torch.where(ok, score_fn(residuals, inliers, threshold_sq), float("-inf")), inliers

    def score_block(model: RobustModel, models: Tensor, ok: Tensor, rows: Tensor, rows_valid: Tensor, subset: Tensor | None,
                    block: slice) -> tuple[Tensor, Tensor, Tensor]:
        """The ``block`` of a round's P problems, hypotheses (P, H, *M) valid (P, H): with a
        preemptive (P, m) row subset, the best ``preemptive_keep`` of them on it kept; -> each
        problem's best of them on all its rows: model (b, *M), score (b,) and inlier mask (b, N)."""
        if block.stop < models.shape[0] or block.start > 0:
            model = model.restricted(torch.arange(models.shape[0], device=device)[block])
        models, ok, rows, rows_valid = models[block], ok[block], rows[block], rows_valid[block]
        problem = torch.arange(models.shape[0], device=device)
        if subset is not None:
            subset = subset[block]
            partial, _ = evaluate(model, models, ok, torch.gather(rows, 1, subset[..., None].expand(*subset.shape, D)),
                                  torch.gather(rows_valid, 1, subset))
            keep = torch.topk(partial, max(1, math.ceil(config.preemptive_keep * models.shape[1])), dim=1).indices
            models, ok = models[problem[:, None], keep], ok[problem[:, None], keep]
        score, inliers = evaluate(model, models, ok, rows, rows_valid)
        score, best = score.max(dim=1)
        return models[problem, best], score, inliers[problem, best]

    best_model: Tensor | None = None
    best_score = torch.full((B,), float("-inf"), dtype=torch.float64, device=device)
    best_raw_score = best_score.clone()  # (B,) the best minimal (unpolished) model's score so far
    best_inliers = torch.zeros(B, N, dtype=torch.bool, device=device)
    trials = torch.zeros(B, dtype=torch.long, device=device)
    needed = torch.full((B,), config.max_trials, dtype=torch.long, device=device)
    active = num_valid >= s
    round_size = min(config.initial_hypotheses, config.hypotheses_per_round)
    while True:
        remaining = int(torch.where(active, needed - trials, 0).max()) if B else 0
        if remaining <= 0:
            break
        num_samples = min(remaining, round_size)
        round_size = min(2 * round_size, config.hypotheses_per_round)
        # the round runs on the problems still drawing only: a batch costs what its open problems cost
        everyone = bool(active.all())
        live = slice(None) if everyone else torch.nonzero(active).flatten()  # (P,) problems
        live_model, live_data, live_valid = (model, data, valid) if everyone else (model.restricted(live), data[live], valid[live])
        P = live_data.shape[0]
        indices = sampler.sample(num_samples, s, generator, None if everyone else live)  # (P, K, s)
        samples = torch.gather(live_data[:, None].expand(P, num_samples, N, D), 2, indices[..., None].expand(*indices.shape, D))
        models, ok = live_model.fit_minimal(samples)  # (P, H, *M), (P, H)
        subset = None
        if preemptive and models.shape[1] > 1:
            subset = subset_sampler.sample(1, config.preemptive_points, generator, None if everyone else live)[:, 0]  # (P, m)
        # scored a few problems at a time: the (problems, hypotheses, rows) residuals of a large
        # batch do not fit in the caches (256 problems in one block ran at half the speed)
        step = max(1, ROUND_ELEMENTS // (models.shape[1] * N))
        blocks = [score_block(live_model, models, ok, live_data, live_valid, subset, slice(a, a + step)) for a in range(0, P, step)]
        chosen, round_score, chosen_inliers = (torch.cat(parts) for parts in zip(*blocks))
        # a record minimal model is polished, then compared with the best (see the docstring)
        record = round_score > best_raw_score[live]  # (P,)
        best_raw_score[live] = torch.where(record, round_score.double(), best_raw_score[live])
        if best_model is None:  # problems that never draw keep zeros (they have fewer than s rows: no inliers)
            best_model = chosen.new_zeros(B, *chosen.shape[1:])
        current, current_score, current_inliers = chosen, round_score, chosen_inliers
        refitting = record  # (P,) the problems whose refits go on
        for _ in range(config.local_refits if bool(record.any()) else 0):
            # only the problems whose inliers moved: the others' refit would repeat their last one
            rows = torch.nonzero(refitting).flatten()  # (R,)
            own = live_model if rows.numel() == P else live_model.restricted(rows)
            mine = current_inliers[rows]
            refit = own.fit_weighted(live_data[rows], mine.to(data.dtype))
            score, inliers = evaluate(own, refit[:, None], (mine.sum(-1) >= s)[:, None], live_data[rows], live_valid[rows])
            better = score[:, 0] >= current_score[rows]
            moved = better & (inliers[:, 0] != mine).any(-1)
            current[rows] = where_per_problem(better, refit, current[rows])
            current_score[rows] = torch.where(better, score[:, 0], current_score[rows])
            current_inliers[rows] = where_per_problem(better, inliers[:, 0], mine)
            if not bool(moved.any()):
                break
            refitting = torch.zeros_like(record).index_fill_(0, rows[moved], True)
        improved = record & (current_score > best_score[live])  # (P,)
        best_model[live] = where_per_problem(improved, current, best_model[live])
        best_inliers[live] = where_per_problem(improved, current_inliers, best_inliers[live])
        best_score[live] = torch.where(improved, current_score.double(), best_score[live])
        trials[live] += num_samples
        ratio = torch.maximum(best_inliers.sum(-1).double() / valid_counts, useful_ratio)
        needed = required_trials(ratio, s, config.confidence, config.max_trials)
        active = active & (trials < needed)

    if best_model is None:  # no problem had enough valid rows: a placeholder of the right shape
        best_model = model.fit_weighted(data, valid.to(data.dtype))
    success = best_inliers.sum(-1) >= s
    return RansacResult(model=best_model, inlier_mask=best_inliers, num_trials=trials, success=success)
