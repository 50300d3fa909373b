import dataclasses
import math

import pytest
import torch
from torch.testing import assert_close

from torchsfm.config import FundamentalConfig, RansacConfig
from torchsfm.geometry.fundamental import normalize_scale, sampson_error
from torchsfm.robust.models import FundamentalModel, HomographyModel, ProjectiveResectionModel
from torchsfm.robust.ransac import SCORINGS, ransac, required_trials
from torchsfm.testing import synthetic_two_view


def _data(*scenes):
    return torch.stack([torch.cat([s.x1, s.x2], -1) for s in scenes])


def test_required_trials_follows_eq_3_3_7():
    ratio = torch.tensor([0.5, 1.0, 0.0, 0.9])
    needed = required_trials(ratio, 8, 0.99, 10_000)
    assert needed[0] == math.ceil(math.log(0.01) / math.log(1 - 0.5**8))
    assert needed[1] == 1 and needed[2] == 10_000
    assert needed[3] == math.ceil(math.log(0.01) / math.log(1 - 0.9**8))


@pytest.mark.parametrize("sampler", ["bucketed", "uniform"])
@pytest.mark.parametrize("scoring", sorted(SCORINGS))
def test_planted_outliers_are_found_exactly(sampler, scoring):
    """Noise-free inliers, outliers at least 5 px from the epipolar geometry: the mask is exact.
    (An outlier within a few pixels can legitimately win: an F that also fits it has one inlier
    more under the 1 px threshold.)"""
    scenes = [synthetic_two_view(300, outlier_ratio=0.5, seed=seed) for seed in range(3)]
    far = [s.is_inlier | (sampson_error(s.F, s.x1, s.x2) > 25) for s in scenes]
    keep = min(int(f.sum()) for f in far)
    data = torch.stack([torch.cat([s.x1, s.x2], -1)[f][:keep] for s, f in zip(scenes, far)])
    expected = [s.is_inlier[f][:keep] for s, f in zip(scenes, far)]
    config = dataclasses.replace(RansacConfig(), sampler=sampler, scoring=scoring)
    result = ransac(FundamentalModel(data), data, config, generator=torch.Generator().manual_seed(0))
    for b, scene in enumerate(scenes):
        assert torch.equal(result.inlier_mask[b], expected[b])
        F, truth = normalize_scale(result.model[b]), scene.F
        assert_close(F * torch.sign((F * truth).sum()), truth, rtol=0, atol=1e-8)
    assert result.success.all()


def test_adaptive_stop_draws_few_samples_without_outliers():
    scene = synthetic_two_view(200, seed=1)
    data = _data(scene)
    result = ransac(FundamentalModel(data), data, RansacConfig(), generator=torch.Generator().manual_seed(0))
    assert result.num_trials.item() <= 32  # the first round already reaches confidence


def test_more_outliers_need_more_trials_and_the_cap_holds():
    low = _data(synthetic_two_view(300, noise=0.3, outlier_ratio=0.2, seed=2))
    high = _data(synthetic_two_view(300, noise=0.3, outlier_ratio=0.6, seed=2))
    config = RansacConfig()
    low_trials = ransac(FundamentalModel(low), low, config, generator=torch.Generator().manual_seed(0)).num_trials
    high_trials = ransac(FundamentalModel(high), high, config, generator=torch.Generator().manual_seed(0)).num_trials
    assert low_trials < high_trials
    capped = ransac(FundamentalModel(high), high, dataclasses.replace(config, max_trials=100), generator=torch.Generator().manual_seed(0))
    assert capped.num_trials.item() <= 100


def test_a_problem_without_a_useful_model_stops_where_one_would_have_been_found():
    """``min_inliers`` = 100 of 200 rows: a problem whose best model keeps fewer (20 % inliers)
    draws what eq. 3.3.7 asks at the ratio 0.5, not ``max_trials``; a problem with such a model
    (70 % inliers) still finds every one of them."""
    poor, rich = synthetic_two_view(200, outlier_ratio=0.8, seed=4), synthetic_two_view(200, outlier_ratio=0.3, seed=5)
    data = _data(poor, rich)
    config = dataclasses.replace(RansacConfig(), min_inliers=100)
    result = ransac(FundamentalModel(data), data, config, generator=torch.Generator().manual_seed(0))
    assert result.num_trials[0] == required_trials(torch.tensor([0.5]), 8, 0.99, 10_000)[0]
    assert result.inlier_mask[1][rich.is_inlier].all() and result.inlier_mask[1].sum() < 150
    plain = ransac(FundamentalModel(data[:1]), data[:1], RansacConfig(), generator=torch.Generator().manual_seed(0))
    assert plain.num_trials[0] == 10_000


def test_padding_and_too_small_problems():
    a = synthetic_two_view(100, outlier_ratio=0.3, seed=3)
    data = torch.zeros(2, 100, 4, dtype=torch.float64)
    data[0] = torch.cat([a.x1, a.x2], -1)
    data[1, :5] = torch.cat([a.x1[:5], a.x2[:5]], -1)
    valid = torch.zeros(2, 100, dtype=torch.bool)
    valid[0] = True
    valid[1, :5] = True
    result = ransac(FundamentalModel(data, valid), data, RansacConfig(), valid=valid, generator=torch.Generator().manual_seed(0))
    assert result.success.tolist() == [True, False]
    assert result.num_trials[1] == 0
    assert torch.equal(result.inlier_mask[0], a.is_inlier)
    assert not result.inlier_mask[1, 5:].any()


def test_same_seed_same_result():
    data = _data(synthetic_two_view(300, noise=0.5, outlier_ratio=0.4, seed=4))
    runs = [ransac(FundamentalModel(data), data, RansacConfig(), generator=torch.Generator().manual_seed(7)) for _ in range(2)]
    assert torch.equal(runs[0].model, runs[1].model)
    assert torch.equal(runs[0].inlier_mask, runs[1].inlier_mask)


@pytest.mark.parametrize("model_class", [FundamentalModel, HomographyModel])
def test_a_problem_that_stops_early_in_a_batch_keeps_its_exact_answer(model_class):
    """A batch of an outlier-free problem and an unrelated one: the first stops after one round
    and later rounds run on the second alone (the plug-in's ``restricted``); the first keeps
    every point, the second draws up to the cap, and the first matches its own single call."""
    scene = synthetic_two_view(200, seed=1)
    easy = _data(scene)
    if model_class is HomographyModel:  # a planar scene: image 2 = a homography of image 1
        H = torch.tensor([[1.1, 0.05, 20.0], [-0.03, 0.95, -10.0], [1e-4, 5e-5, 1.0]], dtype=torch.float64)
        moved = torch.cat([scene.x1, torch.ones(200, 1, dtype=torch.float64)], -1) @ H.T
        easy = torch.cat([scene.x1, moved[:, :2] / moved[:, 2:]], -1)[None]
    unrelated = torch.rand(1, 200, 4, dtype=torch.float64, generator=torch.Generator().manual_seed(2)) * 600
    data = torch.cat([easy, unrelated])
    config = RansacConfig(max_trials=300)
    batch = ransac(model_class(data), data, config, generator=torch.Generator().manual_seed(0))
    single = ransac(model_class(easy), easy, config, generator=torch.Generator().manual_seed(0))
    assert batch.inlier_mask[0].all() and batch.num_trials[0] <= 32
    assert batch.num_trials[1] == 300
    assert torch.equal(batch.inlier_mask[0], single.inlier_mask[0])
    assert_close(normalize_scale(batch.model[0]).abs(), normalize_scale(single.model[0]).abs(), rtol=0, atol=1e-9)


def test_a_round_scored_in_blocks_of_problems_gives_the_same_answer(monkeypatch):
    """A batch's round is fitted and scored a block of problems at a time (``ROUND_ELEMENTS``):
    with blocks of one problem, four problems at 40 % outliers get bitwise the same models,
    masks and trials as in one block."""
    import torchsfm.robust.ransac as engine

    data = torch.cat([_data(synthetic_two_view(300, noise=0.5, outlier_ratio=0.4, seed=seed)) for seed in range(4)])
    whole = ransac(FundamentalModel(data), data, RansacConfig(), generator=torch.Generator().manual_seed(3))
    monkeypatch.setattr(engine, "ROUND_ELEMENTS", 1)
    blocks = ransac(FundamentalModel(data), data, RansacConfig(), generator=torch.Generator().manual_seed(3))
    assert torch.equal(whole.model, blocks.model) and torch.equal(whole.inlier_mask, blocks.inlier_mask)
    assert torch.equal(whole.num_trials, blocks.num_trials)


@pytest.mark.parametrize("local_refits", [0, 1, 3])
@pytest.mark.parametrize("model_class", [FundamentalModel, HomographyModel])
def test_the_inlier_mask_is_the_returned_models_mask(model_class, local_refits):
    """The engine carries each problem's inlier mask with its best model through the rounds and
    the LO refits instead of scoring the final model again: the mask must be exactly the points
    under the threshold of the returned model (padding excluded), for a batch whose problems stop
    after different rounds (10 % and 60 % outliers, one padded)."""
    scenes = [synthetic_two_view(200, noise=0.5, outlier_ratio=ratio, seed=seed) for seed, ratio in enumerate((0.1, 0.6, 0.4))]
    data = _data(*scenes)
    if model_class is HomographyModel:  # a planar scene: the inliers' second image a homography of the first, 0.5 px noise
        H = torch.tensor([[1.1, 0.05, 20.0], [-0.03, 0.95, -10.0], [1e-4, 5e-5, 1.0]], dtype=torch.float64)
        moved = torch.cat([data[..., :2], torch.ones_like(data[..., :1])], -1) @ H.T
        noise = 0.5 * torch.randn(3, 200, 2, dtype=torch.float64, generator=torch.Generator().manual_seed(1))
        inlier = torch.stack([scene.is_inlier for scene in scenes])[..., None]
        data[..., 2:] = torch.where(inlier, moved[..., :2] / moved[..., 2:] + noise, data[..., 2:])
    valid = torch.ones(3, 200, dtype=torch.bool)
    valid[2, 150:] = False
    data[2, 150:] = 0.0
    config = dataclasses.replace(RansacConfig(initial_hypotheses=8), local_refits=local_refits)
    model = model_class(data, valid)
    result = ransac(model, data, config, valid=valid, generator=torch.Generator().manual_seed(0))
    assert (result.num_trials[0] < result.num_trials[1]) and result.success.all()
    residuals = torch.nan_to_num(model.residuals(result.model[:, None], data)[:, 0], nan=float("inf"))
    assert torch.equal(result.inlier_mask, (residuals < config.inlier_threshold**2) & valid)


def test_local_refits_stop_once_the_inliers_stop_moving():
    """Noise-free inliers and far outliers: a minimal sample of inliers already has every
    inlier, so the first refit of an improved round finds the inliers it was fitted on and ends
    the refits (a second would repeat it); the answer is the one a single refit gives."""
    scene = synthetic_two_view(200, outlier_ratio=0.3, seed=4)
    data = _data(scene)

    class Counting(FundamentalModel):
        refits = 0

        def fit_weighted(self, data, weights):
            Counting.refits += 1
            return super().fit_weighted(data, weights)

    found = {}
    for refits in (1, 3):
        Counting.refits = 0
        config = dataclasses.replace(RansacConfig(), local_refits=refits)
        found[refits] = ransac(Counting(data), data, config, generator=torch.Generator().manual_seed(0)), Counting.refits
    (one, one_calls), (three, three_calls) = found[1], found[3]
    assert torch.equal(three.inlier_mask, one.inlier_mask) and torch.equal(three.inlier_mask[0], scene.is_inlier)
    assert_close(three.model, one.model, rtol=0, atol=1e-12)
    assert three_calls == one_calls > 0


@pytest.mark.parametrize("outlier_ratio", [0.3, 0.5])
def test_fundamental_lo_climbs_until_a_refit_gains_no_inlier(outlier_ratio):
    """Noisy matches (0.5 px), 6 scenes: with the F section's settings the LO refits go on while
    the inliers move, so a further refit on the returned inliers keeps no more of them (at most
    as many: the refits stopped at a local maximum of the count). Stopped after 3 refits, 7 of
    these 12 scenes could still climb (e.g. 132 -> 141 inliers)."""
    config = FundamentalConfig().ransac
    for seed in range(6):
        scene = synthetic_two_view(300, noise=0.5, outlier_ratio=outlier_ratio, seed=seed)
        data = _data(scene)
        model = FundamentalModel(data)
        found = ransac(model, data, config, generator=torch.Generator().manual_seed(0))
        refit = model.fit_weighted(data, found.inlier_mask.to(data.dtype))
        again = model.residuals(refit[:, None], data)[:, 0] < config.inlier_threshold**2
        assert int(again.sum()) <= int(found.inlier_mask.sum()), seed


def test_a_record_minimal_model_is_polished_though_the_polished_best_scores_higher():
    """F at 60 % outliers, 0.5 px noise, 40 scenes of 500 matches: the inliers found hold at least
    85 % of the planted ones on all but 2 scenes. Polishing only a minimal model that beats the
    polished best (Chum et al.), 10 of the 40 ended at a local optimum holding 43-82 % of them: a
    good sample's minimal model scores below such an optimum before it is refined."""
    stuck = []
    for seed in range(40):
        scene = synthetic_two_view(500, noise=0.5, outlier_ratio=0.6, seed=seed)
        data = _data(scene).double()
        found = ransac(FundamentalModel(data), data, FundamentalConfig().ransac, generator=torch.Generator().manual_seed(0))
        kept = float((found.inlier_mask[0] & scene.is_inlier).sum() / scene.is_inlier.sum())
        if kept < 0.85:
            stuck.append((seed, kept))
    assert len(stuck) <= 2, stuck


def test_local_refits_run_on_the_problems_whose_inliers_moved():
    """One batch of a noise-free problem (its first refit finds the inliers it was fitted on) and
    a noisy one (its inliers move for several refits): after a round's first refit the refits
    run on the noisy problem alone, and the noise-free one keeps its exact inliers."""
    clean = synthetic_two_view(200, outlier_ratio=0.3, seed=4)
    noisy = synthetic_two_view(200, noise=0.5, outlier_ratio=0.3, seed=1)
    data = _data(clean, noisy)

    class Counting(FundamentalModel):
        sizes: list[int] = []

        def fit_weighted(self, data, weights):
            Counting.sizes.append(data.shape[0])
            return super().fit_weighted(data, weights)

    found = ransac(Counting(data), data, FundamentalConfig().ransac, generator=torch.Generator().manual_seed(0))
    assert torch.equal(found.inlier_mask[0], clean.is_inlier)
    assert Counting.sizes[0] == 2 and len(Counting.sizes) > 2 and set(Counting.sizes[1:]) == {1}, Counting.sizes


def test_projective_resection_residuals_of_many_cameras_equal_one_at_a_time():
    """B = 2 problems, H = 5 cameras each scored in one product against each camera written out
    (1e-12 relative); a point on a camera's principal plane (projection at infinity) gets +inf."""
    g = torch.Generator().manual_seed(3)
    X = torch.cat([torch.randn(2, 40, 3, generator=g, dtype=torch.float64), torch.ones(2, 40, 1, dtype=torch.float64)], -1)
    x = torch.randn(2, 40, 2, generator=g, dtype=torch.float64)
    cameras = torch.randn(2, 5, 3, 4, generator=g, dtype=torch.float64)
    cameras[1, 2, 2] = torch.tensor([0.0, 0.0, 1.0, 0.0], dtype=torch.float64)
    X[1, 7, 2] = 0.0  # p3ᵀX = 0 under camera (1, 2)
    model = ProjectiveResectionModel(scale=0.5)
    residuals = model.residuals(cameras, torch.cat([X, x], -1))  # (2, 5, 40)
    for b in range(2):
        for h in range(5):
            projected = X[b] @ cameras[b, h].T
            expected = ((projected[:, :2] / projected[:, 2:] - x[b]).square().sum(-1)) / 0.5**2
            finite = projected[:, 2].abs() > 1e-12
            assert_close(residuals[b, h, finite], expected[finite], rtol=1e-12, atol=0)
            assert bool(torch.isinf(residuals[b, h, ~finite]).all())
    assert bool(torch.isinf(residuals[1, 2, 7]))


def test_a_nan_residual_is_never_an_inlier():
    """A model whose residual is NaN on some rows (a degenerate projection, say): under either
    scoring those rows are never inliers (the engine compares residuals with the threshold, where
    NaN is False), and over 90 % of the other true inliers are still found."""
    scene = synthetic_two_view(200, noise=0.3, outlier_ratio=0.2, seed=3)
    data = _data(scene)

    class NaNRows(FundamentalModel):
        def residuals(self, models, rows):
            residuals = super().residuals(models, rows)
            return torch.where(rows[..., None, :, 0] < 100, float("nan"), residuals)

    for scoring in sorted(SCORINGS):
        config = dataclasses.replace(RansacConfig(), scoring=scoring)
        result = ransac(NaNRows(data), data, config, generator=torch.Generator().manual_seed(0))
        poisoned = data[0, :, 0] < 100
        assert poisoned.any() and not result.inlier_mask[0, poisoned].any()
        assert result.inlier_mask[0, ~poisoned & scene.is_inlier].float().mean() > 0.9
