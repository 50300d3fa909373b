import pytest
import torch
from torch.testing import assert_close

from torchsfm.config import MatchingConfig
from torchsfm.matching.matcher import PutativeMatcher, match_corners
from torchsfm.matching.ncc import CandidateMatches, extract_patches, ncc_candidates, ncc_table, select_candidates
from torchsfm.matching.strength import relaxation, strength_measure


def _textured(seed=0, size=(96, 128)):
    generator = torch.Generator().manual_seed(seed)
    noise = torch.rand(1, 1, size[0] // 4, size[1] // 4, generator=generator)
    return torch.nn.functional.interpolate(noise, size=size, mode="bicubic", align_corners=False)[0]


def test_patches_are_zero_mean_unit_norm_and_flat_patches_vanish():
    image = _textured()
    points = torch.tensor([[30.3, 40.7], [60.0, 50.5]])
    patches = extract_patches(image, points, 3)
    assert patches.shape == (2, 49)
    assert_close(patches.mean(-1), torch.zeros(2), rtol=0, atol=1e-6)
    assert_close(patches.norm(dim=-1), torch.ones(2), rtol=0, atol=1e-5)
    assert (extract_patches(torch.full((1, 32, 32), 0.3), torch.tensor([[16.0, 16.0]]), 3) == 0).all()


def test_ncc_of_an_image_with_itself_finds_every_corner():
    image = _textured()
    points = torch.rand(50, 2, generator=torch.Generator().manual_seed(1)) * torch.tensor([100.0, 70.0]) + 12
    candidates = ncc_candidates(image, image, points, points, MatchingConfig(search_radius=30, ncc_threshold=0.5))
    diagonal = candidates.index1 == candidates.index2
    assert torch.equal(candidates.index1[diagonal], torch.arange(50))
    assert_close(candidates.score[diagonal], torch.ones(50), rtol=0, atol=1e-5)
    distances = (points[candidates.index1] - points[candidates.index2]).norm(dim=-1)
    assert (distances < 30).all() and (candidates.score > 0.5).all()
    matches = match_corners(image, image, points, points, MatchingConfig(search_radius=30))
    assert matches.index1.numel() > 40 and (matches.index1 == matches.index2).all()


def _synthetic_candidates(seed=0, n=60):
    """Points moved by a similarity; each point has its true candidate and two random ones."""
    generator = torch.Generator().manual_seed(seed)
    points1 = torch.rand(n, 2, generator=generator, dtype=torch.float64) * 200
    angle = torch.tensor(0.1, dtype=torch.float64)
    rotation = torch.stack([torch.stack([angle.cos(), -angle.sin()]), torch.stack([angle.sin(), angle.cos()])])
    points2 = points1 @ rotation.T * 1.05 + torch.tensor([15.0, -8.0], dtype=torch.float64)
    true = torch.arange(n)
    decoys = torch.randint(0, n, (n, 2), generator=generator)
    index1 = torch.cat([true, true, true])
    index2 = torch.cat([true, decoys[:, 0], decoys[:, 1]])
    keep = torch.ones_like(index1, dtype=torch.bool)
    keep[n:] = index2[n:] != index1[n:]
    score = torch.cat([0.9 + 0.05 * torch.rand(n, generator=generator, dtype=torch.float64),
                       0.85 + 0.1 * torch.rand(2 * n, generator=generator, dtype=torch.float64)])
    candidates = CandidateMatches(index1=index1[keep], index2=index2[keep], score=score[keep])
    return points1, points2, candidates, n


@pytest.mark.parametrize("size", [(120, 90), (90, 160)])  # strips along x, along y
def test_candidates_in_strips_are_those_of_the_whole_table(size):
    """The strip-blocked products give exactly the candidates (and scores) that the whole NCC
    table within the disc gives, row-major, with disc centres off the corners (a prediction)."""
    generator = torch.Generator().manual_seed(4)
    width, height = size
    image1 = _textured(size=(height + 24, width + 24))
    image2 = torch.roll(image1, shifts=(2, 3), dims=(1, 2))
    points1 = torch.rand(300, 2, generator=generator) * torch.tensor([width, height], dtype=torch.float32) + 12
    points2 = torch.rand(280, 2, generator=generator) * torch.tensor([width, height], dtype=torch.float32) + 12
    centres = points1 + torch.randn(300, 2, generator=generator) * 5
    config = MatchingConfig(search_radius=25, ncc_threshold=0.3)
    candidates = ncc_candidates(image1, image2, points1, points2, config, predicted1=centres)
    reference = select_candidates(ncc_table(image1, image2, points1, points2, config.patch_half_size),
                                  torch.cdist(centres, points2) < config.search_radius, config.ncc_threshold)
    assert candidates.index1.numel() > 100
    assert torch.equal(candidates.index1, reference.index1) and torch.equal(candidates.index2, reference.index2)
    assert_close(candidates.score, reference.score, rtol=0, atol=1e-6)
    none = ncc_candidates(image1, image2, points1[:0], points2, config)
    assert none.index1.numel() == 0 and none.score.numel() == 0


def test_strength_measure_is_symmetric_in_the_two_images():
    points1, points2, candidates, _ = _synthetic_candidates()
    config = MatchingConfig(neighbourhood_radius=80)
    forward = strength_measure(points1, points2, candidates, config)
    swapped = CandidateMatches(index1=candidates.index2, index2=candidates.index1, score=candidates.score)
    backward = strength_measure(points2, points1, swapped, config)
    assert_close(forward, backward, rtol=1e-12, atol=1e-12)


def _strength_by_definition(points1, points2, candidates, config):
    """SM of eq. 3.2.6 with the mutual-best symmetry fix, straight from the definition: every
    candidate against every other (dense (M, M) tables)."""
    i, j, c = candidates.index1, candidates.index2, candidates.score
    exact = "donot_use_mm_for_euclid_dist"  # differences, not |a|² + |b|² - 2a·b: no rounding at the radius
    d1, d2 = torch.cdist(points1[i], points1[i], compute_mode=exact), torch.cdist(points2[j], points2[j], compute_mode=exact)
    radius, epsilon = config.neighbourhood_radius, config.relative_distance_threshold
    dist = (d1 + d2) / 2
    r = (d1 - d2).abs() / dist.clamp_min(1e-12)
    counts = (d1 < radius) & (d2 < radius) & (i[:, None] != i[None]) & (j[:, None] != j[None]) & (r < epsilon)
    value = torch.where(counts, c[None] * torch.exp(-r / epsilon) / (1 + dist), 0.0)  # (M, M): row m, neighbour n

    def best_among(partner, size):  # per (m, n): the largest value of row m over the n' sharing n's corner
        best = value.new_zeros(value.shape[0], size).scatter_reduce(1, partner.expand_as(value), value, "amax")
        return best.gather(1, partner.expand_as(value))

    mutual = (value > 0) & (value == best_among(i[None], points1.shape[0])) & (value == best_among(j[None], points2.shape[0]))
    return c * torch.where(mutual, value, 0.0).sum(1)


@pytest.mark.parametrize("epsilon", [0.3, 2.0])
def test_strength_measure_is_that_of_its_definition(epsilon):
    """Over a 600 × 400 px field with 1200 candidates (several row blocks, neighbours across
    their boundaries, corners with several candidates each), SM as computed equals SM taken
    from its definition candidate against candidate — at the default ε_r and at its largest,
    2, where a neighbour sharing a corner with the row (r = 2 exactly) is left out only by the
    strict test r < ε_r."""
    generator = torch.Generator().manual_seed(5)
    n = 400
    points1 = torch.rand(n, 2, generator=generator, dtype=torch.float64) * torch.tensor([600.0, 400.0], dtype=torch.float64)
    points2 = points1 * 1.02 + torch.tensor([12.0, -5.0], dtype=torch.float64) + torch.randn(n, 2, generator=generator, dtype=torch.float64)
    index1 = torch.arange(n).repeat(3)
    index2 = torch.cat([torch.arange(n), torch.randint(0, n, (2 * n,), generator=generator)])  # the true one and two decoys
    pairs = torch.unique(index1 * n + index2)
    candidates = CandidateMatches(index1=pairs // n, index2=pairs % n,
                                  score=0.8 + 0.2 * torch.rand(pairs.numel(), generator=generator, dtype=torch.float64))
    config = MatchingConfig(neighbourhood_radius=80, relative_distance_threshold=epsilon)
    strength = strength_measure(points1, points2, candidates, config)
    assert (strength > 0).float().mean() > 0.5
    assert_close(strength, _strength_by_definition(points1, points2, candidates, config), rtol=1e-12, atol=1e-12)


@pytest.mark.parametrize("pairs, strips_per_radius", [(1, 1), (7, 1), (1 << 21, 4), (50, 3), (100_000, 2)])
def test_strength_measure_does_not_depend_on_how_the_pairs_are_found(pairs, strips_per_radius, monkeypatch):
    """Chunks of one row to all rows, strips a whole to a quarter radius high: the same SM bit for
    bit (a row's neighbours are summed in (k, l) order however they were found)."""
    from torchsfm.matching import strength

    points1, points2, candidates, _ = _synthetic_candidates(seed=4)
    config = MatchingConfig(neighbourhood_radius=80)
    reference = strength_measure(points1, points2, candidates, config)
    monkeypatch.setattr(strength, "_CHUNK_PAIRS", pairs)
    monkeypatch.setattr(strength, "_STRIPS_PER_RADIUS", strips_per_radius)
    assert torch.equal(strength_measure(points1, points2, candidates, config), reference)
    assert bool((reference > 0).any())


def test_strength_measure_does_not_depend_on_the_candidates_order():
    """The candidates shuffled (not row-major, as ncc_candidates gives them), SM is that of the
    sorted set, shuffled alike; one candidate alone, or none near another, scores 0."""
    points1, points2, candidates, _ = _synthetic_candidates(seed=6)
    config = MatchingConfig(neighbourhood_radius=80)
    reference = strength_measure(points1, points2, candidates, config)
    shuffle = torch.randperm(reference.numel(), generator=torch.Generator().manual_seed(0))
    shuffled = CandidateMatches(candidates.index1[shuffle], candidates.index2[shuffle], candidates.score[shuffle])
    assert_close(strength_measure(points1, points2, shuffled, config), reference[shuffle], rtol=1e-12, atol=0)
    alone = CandidateMatches(candidates.index1[:1], candidates.index2[:1], candidates.score[:1])
    assert torch.equal(strength_measure(points1, points2, alone, config), torch.zeros(1, dtype=torch.float64))
    far = MatchingConfig(neighbourhood_radius=1e-3)
    assert torch.equal(strength_measure(points1, points2, candidates, far), torch.zeros_like(reference))


def test_strength_measure_in_float32_agrees_with_float64_far_from_the_image_origin():
    """Corners a few pixels apart at x ≈ 700 px (a 768-wide image's right edge): distances taken
    as sqrt(|a|² + |b|² - 2a·b) lose their digits there in float32 (SM was 9 % off here)."""
    points1, points2, candidates, _ = _synthetic_candidates(seed=2)
    generator = torch.Generator().manual_seed(3)
    points1, points2 = points1 * 0.1 + 700, points2 * 0.1 + 650  # 20 px wide clusters
    points2 = points2 + 0.05 * torch.randn(points2.shape, generator=generator, dtype=torch.float64)
    config = MatchingConfig(neighbourhood_radius=80)
    reference = strength_measure(points1, points2, candidates, config)
    single = CandidateMatches(index1=candidates.index1, index2=candidates.index2, score=candidates.score.float())
    assert_close(strength_measure(points1.float(), points2.float(), single, config), reference.float(), rtol=1e-4, atol=1e-6)


@pytest.mark.parametrize("mode", ["some_winners", "winner_take_all"])
def test_relaxation_prefers_the_geometrically_consistent_candidates(mode):
    points1, points2, candidates, n = _synthetic_candidates(seed=1)
    config = MatchingConfig(neighbourhood_radius=80, relaxation=mode)
    strength = strength_measure(points1, points2, candidates, config)
    index1, index2 = relaxation(candidates, strength, (n, n), config)
    assert index1.unique().numel() == index1.numel() and index2.unique().numel() == index2.numel()  # one-to-one
    assert (index1 == index2).float().mean() > 0.95 and index1.numel() > 0.9 * n
    # NCC alone cannot tell: the decoys score as high as the true candidates
    ncc1, ncc2 = relaxation(candidates, candidates.score, (n, n), config)
    assert (ncc1 == ncc2).float().mean() < (index1 == index2).float().mean()


def test_matcher_is_a_module():
    matcher = PutativeMatcher(MatchingConfig(strength="ncc"))
    assert isinstance(matcher, torch.nn.Module) and "strength='ncc'" in repr(matcher)


def test_affine_warped_patches_match_through_rotation_and_scale():
    """The bundled fountain view against itself rotated by 30 deg and scaled by 1.5 (with a
    little perspective): with the disc centred on the true homography's prediction, plain NCC
    patches find almost no correct match; patches warped by the homography's local affine map
    find most of those found without any motion (measured: 806 vs 3 within 1.5 px)."""
    import math

    import kornia

    from torchsfm.actions import SAMPLE
    from torchsfm.camera import from_homogeneous, to_homogeneous
    from torchsfm.config import HarrisConfig, MatchingConfig
    from torchsfm.features.harris import detect_corners
    from torchsfm.images import read_image, to_grey
    from torchsfm.matching.matcher import match_corners
    from torchsfm.sfm.view_pairs import patch_warps

    image = to_grey(read_image(SAMPLE / "0004.jpg"))
    height, width = image.shape[-2:]
    angle, scale = math.radians(30), 1.5
    A = scale * torch.tensor([[math.cos(angle), -math.sin(angle)], [math.sin(angle), math.cos(angle)]], dtype=torch.float64)
    centre = torch.tensor([width / 2, height / 2], dtype=torch.float64)
    H = torch.eye(3, dtype=torch.float64)
    H[:2, :2], H[:2, 2], H[2, 0] = A, centre - A @ centre, 2e-4
    moved = kornia.geometry.transform.warp_perspective(image[None], H[None].float(), (height, width), align_corners=True)[0]
    points1 = detect_corners(image[None], HarrisConfig()).of_image(0).double()
    points2 = detect_corners(moved[None], HarrisConfig()).of_image(0).double()
    predicted = from_homogeneous(to_homogeneous(points1) @ H.T)

    def correct(warp):
        matches = match_corners(image, moved, points1, points2, MatchingConfig(), predicted, warp)
        return int(((predicted[matches.index1] - points2[matches.index2]).norm(dim=-1) < 1.5).sum())

    plain, warped = correct(None), correct(patch_warps(H, points1))
    assert plain < 50 and warped > 600


def test_chance_equivalent_threshold_keeps_the_chance_candidates_per_corner():
    """A table of chance scores: candidates among a tenth of the pairs need a lower score, and
    above it they are about as many as above 0.8 among all pairs; never above 0.8."""
    from torchsfm.matching.ncc import chance_equivalent_threshold

    ncc = torch.rand(400, 500, generator=torch.Generator().manual_seed(0), dtype=torch.float64) * 2 - 1
    everything = torch.ones_like(ncc, dtype=torch.bool)
    tenth = torch.zeros_like(everything)
    tenth[:, :50] = True
    threshold = chance_equivalent_threshold(ncc, everything, tenth, 0.8)
    assert threshold < 0.8
    in_tenth, in_all = int((ncc[tenth] > threshold).sum()), int((ncc > 0.8).sum())
    assert abs(in_tenth - in_all) <= 0.25 * in_all  # uniform chance scores: 0.8 -> about -0.2
    assert chance_equivalent_threshold(ncc, tenth, everything, 0.8) == 0.8


def test_radii_shrink_for_a_set_of_smaller_images_only():
    config = MatchingConfig()
    scale = (256 * 384) ** 0.5 / config.reference_size  # half the 768 x 512 images the radii are for
    half = config.for_images((1, 256, 384), (1, 256, 384))
    assert half.search_radius == pytest.approx(config.search_radius * scale, rel=1e-12)
    assert half.neighbourhood_radius == pytest.approx(config.neighbourhood_radius * scale, rel=1e-12)
    assert MatchingConfig(**{**vars(half), "search_radius": 100.0, "neighbourhood_radius": 80.0}) == config  # nothing else
    assert config.for_images((1, 512, 768)) is config
    assert config.for_images((1, 370, 1226)) is config  # a wider image keeps them: they never grow
    assert config.for_images((1, 256, 384), (1, 512, 768)) is config  # the set's largest image decides
    assert MatchingConfig(reference_size=0).for_images((64, 64)) == MatchingConfig(reference_size=0)


def test_the_pipeline_matches_a_set_of_small_images_with_shrunk_radii(monkeypatch):
    import torchsfm.sfm.view_pairs as view_pairs
    from torchsfm.config import Config

    seen = []

    def recording(image1, image2, points1, points2, config=None, predicted1=None, warp1=None):
        seen.append(config)
        return ncc_candidates(image1, image2, points1, points2, config, predicted1, warp1)

    monkeypatch.setattr(view_pairs, "ncc_candidates", recording)
    greys = [(_textured(seed, (120, 160)) * 255).to(torch.uint8) for seed in (0, 1)]
    corners = torch.rand(40, 2, generator=torch.Generator().manual_seed(2)) * torch.tensor([130.0, 90.0]) + 15
    view_pairs.guided_matches(greys, [corners, corners], {(0, 1): None}, Config(), lambda message: None)
    expected = Config().matching.for_images((120, 160))
    assert [config.search_radius for config in seen] == [pytest.approx(expected.search_radius)]
    assert expected.search_radius < Config().matching.search_radius


@pytest.mark.parametrize("mode, alpha", [("some_winners", 0.6), ("some_winners", 0.1), ("winner_take_all", 0.6)])
def test_relaxation_of_many_problems_at_once_is_that_of_each_alone(mode, alpha):
    """Problems of different sizes (one with no candidate), SM or random scores, relaxed in one
    loop: each gets the matches of its own call, bit for bit — the top fractions taken per
    problem, and at α = 0.1 the fallback (the two top tables share no entry: the strongest)
    taken per problem too."""
    from torchsfm.matching.strength import relaxation_batch

    config = MatchingConfig(neighbourhood_radius=80, relaxation=mode, alpha=alpha)
    generator = torch.Generator().manual_seed(7)
    problems = []
    for seed, n in [(0, 60), (1, 25), (2, 90)]:
        points1, points2, candidates, _ = _synthetic_candidates(seed=seed, n=n)
        problems.append((candidates, strength_measure(points1, points2, candidates, config), (n, n)))
    candidates = problems[0][0]
    problems.append((candidates, torch.rand(candidates.index1.numel(), generator=generator, dtype=torch.float64), (60, 60)))
    empty = torch.zeros(0, dtype=torch.long)
    problems.insert(1, (CandidateMatches(empty, empty, torch.zeros(0, dtype=torch.float64)), torch.zeros(0, dtype=torch.float64), (5, 7)))
    together = relaxation_batch(*(list(part) for part in zip(*problems)), config)
    assert len(together) == len(problems) and together[1][0].numel() == 0
    for (index1, index2), problem in zip(together, problems):
        alone = relaxation(*problem, config)
        assert torch.equal(index1, alone[0]) and torch.equal(index2, alone[1])
    assert sum(index1.numel() for index1, _ in together) > 150


def test_top_fractions_are_taken_per_problem():
    """The batched relaxation's top-α selection: each problem's entries against its own
    masked values only — one problem's values ten times another's change nothing — and a
    problem with nothing masked selects nothing."""
    from torchsfm.matching.strength import _in_top_fraction

    generator = torch.Generator().manual_seed(8)
    group = torch.randint(0, 3, (200,), generator=generator)
    values = torch.rand(200, generator=generator, dtype=torch.float64) * torch.tensor([1.0, 10.0, 1.0], dtype=torch.float64)[group]
    mask = (torch.rand(200, generator=generator) < 0.7) & (group != 2)
    together = _in_top_fraction(values, mask, 0.6, group, 4)
    assert not bool(together[group == 2].any())
    for g in (0, 1):
        mine = group == g
        alone = _in_top_fraction(values[mine], mask[mine], 0.6, torch.zeros(int(mine.sum()), dtype=torch.long), 1)
        assert torch.equal(together[mine], alone) and bool(alone.any())
