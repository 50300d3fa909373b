"""Pair selection and coarse guidance (sfm/pairs.py)."""

from __future__ import annotations

import pytest
import torch

from torchsfm.config import PairsConfig
from torchsfm.images import read_image, to_grey
from torchsfm.sfm.pairs import (coarse_features, coarse_homographies, pair_scores, pairs_to_match, reduction_factors, second_links,
                                select_pairs, single_links, turned_homographies, view_groups)
from torchsfm.actions import SAMPLE as BUNDLED_FOUNTAIN


def _bundled_greys() -> torch.Tensor:
    return torch.stack([to_grey(read_image(BUNDLED_FOUNTAIN / f"000{v}.jpg")) for v in (4, 5, 6)])


def test_pair_modes():
    scores = torch.tensor([[0, 50, 0, 40], [50, 0, 30, 0], [0, 30, 0, 20], [40, 0, 20, 0]])
    assert select_pairs(scores, PairsConfig(mode="sequential", window=2), 4) == [(0, 1), (0, 2), (1, 2), (1, 3), (2, 3)]
    assert len(select_pairs(scores, PairsConfig(mode="exhaustive"), 4)) == 6
    # auto on a small set: every pair with min_score coarse matches (0-2 and 1-3 have none)
    assert select_pairs(scores, PairsConfig(mode="auto", exhaustive_up_to=4), 4) == [(0, 1), (0, 3), (1, 2), (2, 3)]
    # similarity: each view's best partner (0-3 is far apart in the file order) and the window
    # pairs that score at least min_score (2-3 scores 20: kept; 1-2 scores 30: kept)
    assert select_pairs(scores, PairsConfig(mode="similarity", window=1, neighbours=1, min_score=12), 4) == [(0, 1), (0, 3), (1, 2), (2, 3)]
    assert select_pairs(scores, PairsConfig(mode="similarity", window=1, neighbours=1, min_score=25), 4) == [(0, 1), (0, 3), (1, 2)]


def test_pairs_whose_coarse_homography_fails_are_dropped_unless_a_view_would_be_left_alone():
    """0-3 and 1-2 score well but no homography joins their matches: dropped. When 2-3 fails
    too, views 2 and 3 keep their best-scoring partners (1-2, 0-3) rather than none."""
    scores = torch.tensor([[0, 50, 0, 40], [50, 0, 30, 0], [0, 30, 0, 20], [40, 0, 20, 0]])
    inliers = {(0, 1): 40, (0, 3): 6, (1, 2): 5, (2, 3): 30, (0, 2): 0, (1, 3): 0}
    for config in (PairsConfig(mode="auto", neighbours=1), PairsConfig(mode="similarity", window=1, neighbours=1)):
        assert select_pairs(scores, config, 4, inliers) == [(0, 1), (2, 3)]
        assert select_pairs(scores, config, 4, {**inliers, (2, 3): 7}) == [(0, 1), (0, 3), (1, 2)]


def test_related_views_score_higher_than_an_unrelated_one():
    """Three fountain views and a noise image: every fountain pair scores more coarse matches
    than any pair with the noise image."""
    greys = _bundled_greys()
    noise = torch.rand(1, *greys.shape[1:], generator=torch.Generator().manual_seed(0)).to(greys.dtype)
    scores = pair_scores(coarse_features(torch.cat([greys, noise]), PairsConfig()), 0.8)
    related = scores[:3, :3][~torch.eye(3, dtype=torch.bool)]
    assert int(related.min()) > int(scores[3, :3].max())
    assert torch.equal(scores, scores.T)


def test_scores_over_many_views_are_each_pair_s_mutual_best_count():
    """Twenty views (more than ``SCORED_VIEWS`` are scored against a view per product): each
    pair's score is the number of mutually best NCC matches above the threshold in that pair's
    own table, counted pair by pair."""
    from torchsfm.sfm.pairs import SCORED_VIEWS, CoarseFeatures, _mutual_best

    generator = torch.Generator().manual_seed(0)
    V, K, D = 20, 30, 25
    assert V > 2 * SCORED_VIEWS
    patches = torch.nn.functional.normalize(torch.randn(V, K, D, generator=generator, dtype=torch.float64), dim=-1)
    patches[1:] = 0.8 * patches[:1] + 0.2 * patches[1:]  # similar views: many strong mutual matches
    patches = torch.nn.functional.normalize(patches, dim=-1)
    valid = torch.ones(V, K, dtype=torch.bool)
    features = CoarseFeatures(points=torch.zeros(V, K, 2, dtype=torch.float64), patches=patches, valid=valid)
    scores = pair_scores(features, 0.8)
    expected = torch.zeros(V, V, dtype=torch.long)
    for i in range(V):
        for j in range(V):
            if i != j:
                expected[i, j] = _mutual_best(patches[j] @ patches[i].T, 0.8)[0].numel()
    assert int(expected.max()) > 0
    assert torch.equal(scores, expected)


def test_views_of_different_sizes_are_described_as_each_alone():
    """A landscape view and a portrait one (the same view turned a quarter): each view's coarse
    corners and patches are the ones it gets on its own (one reduction factor: the largest side
    is the same)."""
    grey = _bundled_greys()[0]
    portrait = grey.transpose(-1, -2).flip(-1)
    together = coarse_features([grey, portrait], PairsConfig())
    for v, image in enumerate([grey, portrait]):
        alone = coarse_features([image], PairsConfig())
        count = int(alone.valid[0].sum())
        assert int(together.valid[v].sum()) == count
        torch.testing.assert_close(together.points[v, :count], alone.points[0, :count], rtol=0, atol=0)
        torch.testing.assert_close(together.patches[v, :count], alone.patches[0, :count], rtol=0, atol=0)


def test_predicted_homography_follows_a_large_shift():
    """The second view shifted by (120, -40) px: the coarse homography predicts the shift within
    2 px over the image."""
    grey = _bundled_greys()[0]
    shifted = torch.roll(grey, shifts=(-40, 120), dims=(-2, -1))
    features = coarse_features(torch.stack([grey, shifted]), PairsConfig())
    homographies, inliers = coarse_homographies(features, [(0, 1)], PairsConfig(), torch.Generator().manual_seed(0))
    H = homographies[(0, 1)]
    assert H is not None and inliers[(0, 1)] >= PairsConfig().min_score
    points = torch.tensor([[200.0, 200.0, 1.0], [500.0, 300.0, 1.0], [300.0, 400.0, 1.0]], dtype=torch.float64)
    moved = points @ H.T
    torch.testing.assert_close(moved[:, :2] / moved[:, 2:] - points[:, :2],
                               torch.tensor([[120.0, -40.0]], dtype=torch.float64).expand(3, 2), atol=2.0, rtol=0)


@pytest.mark.parametrize("quarter_turns", [-1, 1, 2])
def test_a_view_turned_by_quarter_turns_gets_its_homography_and_an_upright_one_none(quarter_turns):
    """A view and the same view turned (a portrait shot of a landscape set, upside down): the
    turned patches' homography maps every point where the turn puts it, within 2 px; a pair
    that is not turned (shifted by 30 px) gets no turned homography."""
    grey = _bundled_greys()[0]
    H, W = grey.shape[-2:]
    turned = torch.rot90(grey, k=quarter_turns, dims=(-2, -1))
    features = coarse_features([grey, turned, torch.roll(grey, shifts=30, dims=-1)], PairsConfig())
    found = turned_homographies(features, [(0, 1), (0, 2)], PairsConfig(), torch.Generator().manual_seed(0))
    assert list(found) == [(0, 1)]
    x, y = torch.tensor([200.0, 500.0, 300.0], dtype=torch.float64), torch.tensor([200.0, 300.0, 400.0], dtype=torch.float64)
    expected = {-1: (H - 1 - y, x), 1: (y, W - 1 - x), 2: (W - 1 - x, H - 1 - y)}[quarter_turns]  # torch.rot90's turns
    moved = torch.stack([x, y, torch.ones_like(x)], -1) @ found[(0, 1)].T
    torch.testing.assert_close(moved[:, :2] / moved[:, 2:], torch.stack(expected, -1), atol=2.0, rtol=0)


def test_views_of_several_focal_lengths_are_reduced_to_one_angular_resolution():
    """One camera (one K, one size): one factor, the largest side brought to about
    ``coarse_size`` (768 px -> 2). A view at half size with half the focal length (another camera)
    is reduced by half that factor, a view of one size zoomed in three times by three times that
    factor (whichever comes first), so that all are seen at one scale; without focal lengths, one
    factor for all."""
    big, small = torch.zeros(1, 512, 768, dtype=torch.uint8), torch.zeros(1, 256, 384, dtype=torch.uint8)
    assert reduction_factors([big, big], 320) == [2, 2]
    assert reduction_factors([big, big], 320, torch.tensor([690.0, 690.0])) == [2, 2]
    assert reduction_factors([big, small, big], 320, torch.tensor([690.0, 345.0, 690.0])) == [2, 1, 2]
    assert reduction_factors([big, big, big], 320, torch.tensor([690.0, 2070.0, 690.0])) == [2, 6, 2]
    assert reduction_factors([big, big, big], 320, torch.tensor([2070.0, 690.0, 690.0])) == [6, 2, 2]
    assert reduction_factors([big, small], 320) == [2, 2]
    assert reduction_factors([big, big], 320, torch.tensor([690.0, 69000.0]), smallest=11) == [2, 46]  # 512 // 11: a patch still fits


def test_a_view_at_half_size_gets_its_coarse_homography_given_the_focal_lengths():
    """A fountain view and the next one at half size (half the focal length): given both focal
    lengths, the coarse homography maps the first view's points where the reduced view sees
    them — within 2 px of the full-size pair's homography halved."""
    greys = _bundled_greys()
    half = torch.nn.functional.avg_pool2d(greys[1:2], 2)[0]  # grey in [0, 1]
    focal = torch.tensor([690.0, 345.0])
    features = coarse_features([greys[0], half], PairsConfig(), focal)
    found, inliers = coarse_homographies(features, [(0, 1)], PairsConfig(), torch.Generator().manual_seed(0))
    full, _ = coarse_homographies(coarse_features(greys[:2], PairsConfig()), [(0, 1)], PairsConfig(), torch.Generator().manual_seed(0))
    assert found[(0, 1)] is not None and inliers[(0, 1)] >= PairsConfig().min_score
    points = torch.tensor([[200.0, 200.0, 1.0], [500.0, 300.0, 1.0], [300.0, 400.0, 1.0]], dtype=torch.float64)
    moved, reference = points @ found[(0, 1)].T, points @ full[(0, 1)].T
    halved = (reference[:, :2] / reference[:, 2:] + 0.5) / 2 - 0.5  # pixel centres of the half-size view
    torch.testing.assert_close(moved[:, :2] / moved[:, 2:], halved, atol=2.0, rtol=0)


def test_a_tilted_view_gets_its_homography_from_patches_turned_between_quarter_turns():
    """A view and the same view turned by 30 degrees about its centre (a tilted shot): the
    patches turned by a twelfth of a turn find the homography (the upright and quarter-turned ones
    cannot), mapping every point where the turn puts it within 3 px."""
    from kornia.geometry.transform import rotate

    grey = _bundled_greys()[0]
    H, W = grey.shape[-2:]
    tilted = rotate(grey[None].float(), torch.tensor([30.0]))[0]  # counter-clockwise on screen, about the centre
    features = coarse_features([grey, tilted], PairsConfig())
    upright, _ = coarse_homographies(features, [(0, 1)], PairsConfig(), torch.Generator().manual_seed(0))
    found = turned_homographies(features, [(0, 1)], PairsConfig(), torch.Generator().manual_seed(0))
    assert upright[(0, 1)] is None and list(found) == [(0, 1)]
    centre = torch.tensor([(W - 1) / 2, (H - 1) / 2], dtype=torch.float64)
    points = torch.tensor([[300.0, 200.0], [450.0, 300.0], [380.0, 330.0]], dtype=torch.float64)
    angle = torch.deg2rad(torch.tensor(-30.0, dtype=torch.float64))  # image rows point down: on screen counter-clockwise
    turn = torch.stack([torch.stack([angle.cos(), -angle.sin()]), torch.stack([angle.sin(), angle.cos()])])
    expected = (points - centre) @ turn.T + centre
    moved = torch.cat([points, torch.ones(3, 1, dtype=torch.float64)], -1) @ found[(0, 1)].T
    torch.testing.assert_close(moved[:, :2] / moved[:, 2:], expected, atol=3.0, rtol=0)


def test_view_groups_join_views_through_others():
    assert view_groups([(0, 1), (2, 3), (1, 4)], 6) == [0, 0, 2, 2, 0, 5]
    assert view_groups([], 2) == [0, 1]


@pytest.mark.parametrize("seed", range(6))
def test_single_links_are_the_pairs_whose_removal_splits_the_graph(seed):
    """Random view graphs (several parts, chains, cycles): a pair is reported iff removing it
    leaves more groups (brute force with :func:`view_groups`), and its side is the group of one
    of its ends after the removal."""
    generator = torch.Generator().manual_seed(seed)
    V = 14
    candidates = [(i, j) for i in range(V) for j in range(i + 1, V)]
    keep = torch.rand(len(candidates), generator=generator) < 0.12 + 0.04 * seed
    pairs = [pair for pair, kept in zip(candidates, keep.tolist()) if kept]
    found = dict(single_links(pairs, V))
    groups = len(set(view_groups(pairs, V)))
    for pair in pairs:
        without = view_groups([other for other in pairs if other != pair], V)
        assert (pair in found) == (len(set(without)) > groups)
        if pair in found:
            side = torch.tensor([without[v] == without[pair[1]] for v in range(V)])
            assert torch.equal(found[pair], side) or torch.equal(found[pair], torch.tensor([without[v] == without[pair[0]] for v in range(V)]))
    assert len(found) == len(single_links(pairs, V))


def test_a_chain_of_many_views_is_searched_without_recursion():
    chain = [(v, v + 1) for v in range(3000)]
    assert [pair for pair, _ in single_links(chain, 3001)] == chain[::-1]
    assert single_links(chain + [(0, 3000)], 3001) == []


def test_a_pair_that_alone_joins_two_parts_gets_a_second_pair_across_the_cut():
    """Views 0-2 and 3-5 joined by 2-3 alone: of the considered pairs across that cut with
    ``min_score`` coarse matches, the one with most coarse homography inliers is added (a tie
    goes to the higher score); a pair with fewer coarse matches, one within a part and one to
    another group of views are not; a graph without such a pair gets nothing."""
    chosen = [(0, 1), (0, 2), (1, 2), (2, 3), (3, 4), (3, 5), (4, 5), (6, 7)]
    extra = {(1, 3): (9, 30), (2, 4): (11, 20), (0, 5): (11, 40), (1, 4): (30, 5), (0, 4): (2, 15), (2, 6): (40, 40), (4, 7): (40, 40)}
    considered = chosen + list(extra)
    inliers = {**dict.fromkeys(chosen, 20), **{pair: count for pair, (count, _) in extra.items()}}
    scores = torch.zeros(8, 8, dtype=torch.long)
    for pair in chosen:
        scores[pair] = 50
    for pair, (_, score) in extra.items():
        scores[pair] = score
    config = PairsConfig(min_score=12)
    assert second_links(chosen, considered, scores, inliers, config, 8) == [(0, 5)]
    assert second_links(chosen, considered, scores, {**inliers, (1, 3): 12}, config, 8) == [(1, 3)]
    assert second_links(chosen + [(1, 3)], considered, scores, inliers, config, 8) == []
    assert second_links(chosen, chosen, scores, inliers, config, 8) == []
    # a single view hanging on one pair (view 0 on 0-1 alone) gets a second too
    hanging = [(0, 1), (1, 2), (2, 3), (1, 3)]
    assert [pair for pair, _ in single_links(hanging, 4)] == [(0, 1)]
    scores[0, 2] = 50
    assert second_links(hanging, hanging + [(0, 2)], scores, {**inliers, (0, 2): 30}, config, 4) == [(0, 2)]


def test_a_tilted_view_is_matched_at_pair_selection():
    """Three fountain views, the third tilted by 30 degrees: no upright coarse homography joins
    it to the others, so pair selection tries turned patches, and the pairs with it are chosen
    with a homography; the upright pair keeps the homography it has without the search."""
    from kornia.geometry.transform import rotate

    greys = list(_bundled_greys())
    greys[2] = rotate(greys[2][None].float(), torch.tensor([30.0]))[0]
    features = coarse_features(greys, PairsConfig())
    upright, _ = coarse_homographies(features, [(0, 1), (0, 2), (1, 2)], PairsConfig(), torch.Generator().manual_seed(0))
    assert upright[(0, 1)] is not None and upright[(0, 2)] is None and upright[(1, 2)] is None
    chosen = pairs_to_match(greys, PairsConfig(), torch.Generator().manual_seed(0), guided=True)
    assert chosen[(1, 2)] is not None
    torch.testing.assert_close(chosen[(0, 1)], upright[(0, 1)], rtol=0, atol=0)


def test_bad_mode_is_named():
    from torchsfm.errors import ConfigError

    with pytest.raises(ConfigError, match="mode"):
        PairsConfig(mode="random")


def test_epipolar_band_holds_the_points_on_their_lines():
    """Noise-free correspondences lie in the band of their F; moved 3 px across the line they do not."""
    from torchsfm.geometry.fundamental import fundamental_from_pose
    from torchsfm.sfm.view_pairs import epipolar_band
    from torchsfm.testing import synthetic_two_view

    scene = synthetic_two_view(50, seed=1)
    F = fundamental_from_pose(scene.K1, scene.K2, scene.R, scene.t)
    band = epipolar_band(F, scene.x1, scene.x2, 1.0)
    assert bool(band.diagonal().all())
    line = torch.cat([scene.x1, torch.ones(50, 1, dtype=torch.float64)], -1) @ F.T  # lines F x1 in image 2
    across = scene.x2 + 3.0 * line[:, :2] / line[:, :2].norm(dim=-1, keepdim=True)
    assert not bool(epipolar_band(F, scene.x1, across, 1.0).diagonal().any())


def test_the_oriented_epipolar_constraint_keeps_points_in_front_of_both_cameras():
    """Noise-free correspondences are on the side of the epipole their verified matches take;
    their reflections through the epipole, on the same epipolar lines, are not (their points
    would lie behind a camera)."""
    from torchsfm.geometry.fundamental import fundamental_from_pose
    from torchsfm.sfm.view_pairs import oriented_side
    from torchsfm.testing import synthetic_two_view

    scene = synthetic_two_view(50, seed=1)
    F = fundamental_from_pose(scene.K1, scene.K2, scene.R, scene.t)
    e2 = torch.linalg.svd(F.T)[2][-1]
    e2 = e2[:2] / e2[2]
    assert bool(oriented_side(F, scene.x1, scene.x2, scene.x1[:10], scene.x2[:10]).diagonal().all())
    reflected = 2 * e2 - scene.x2
    assert not bool(oriented_side(F, scene.x1, reflected, scene.x1[:10], scene.x2[:10]).diagonal().any())


def test_the_view_that_sees_the_scene_larger_is_the_one_whose_patches_are_warped():
    """A homography that doubles the scale from view i to view j (area x4) makes view j the one
    that sees the scene larger; its inverse makes view i; a rotation by 30 degrees that shrinks by
    10 % (area x0.81) leaves view i's patches to be warped."""
    from torchsfm.sfm.view_pairs import second_sees_larger

    points = torch.rand(50, 2, generator=torch.Generator().manual_seed(0), dtype=torch.float64) * 400
    zoom = torch.tensor([[2.0, 0.0, 10.0], [0.0, 2.0, -5.0], [0.0, 0.0, 1.0]], dtype=torch.float64)
    angle = torch.tensor(torch.pi / 6, dtype=torch.float64)
    turn = torch.tensor([[0.9 * torch.cos(angle), -0.9 * torch.sin(angle), 0.0], [0.9 * torch.sin(angle), 0.9 * torch.cos(angle), 0.0],
                         [0.0, 0.0, 1.0]], dtype=torch.float64)
    assert second_sees_larger(zoom, points)
    assert not second_sees_larger(torch.linalg.inv(zoom), points)
    assert not second_sees_larger(turn, points)
