"""Motion segmentation (torchsfm.segment_motions): synthetic multi-body scenes with ground truth,
gaps, degenerate cases, bad input, and real labelled tracks (Hopkins155, KT3DMoSeg)."""

from __future__ import annotations

from pathlib import Path

import numpy
import pytest
import torch

from torchsfm import segment_motions
from torchsfm.config import SegmentationConfig
from torchsfm.errors import InputError, NotEnoughDataError, ShapeError
from torchsfm.evaluation import misclassification
from torchsfm.geometry.rotation import axis_angle_to_rotation
from torchsfm.testing import synthetic_moving_scene

DATA = Path(__file__).resolve().parents[3] / "shared" / "data"


def scene(seed: int, objects: int, **kwargs):
    """A 5-frame scene whose objects stay in view, 0.5 px noise."""
    return synthetic_moving_scene(seed, num_frames=5, num_objects=objects, object_points=60, noise=0.5, **kwargs)


def _hypotheses_with(monkeypatch: pytest.MonkeyPatch, chunk_elements: int, seen_subset: float):
    """The hypotheses module with its block size and seen-track share set for one test."""
    from torchsfm.moving import hypotheses

    monkeypatch.setattr(hypotheses, "CHUNK_ELEMENTS", chunk_elements)
    monkeypatch.setattr(hypotheses, "SEEN_SUBSET", seen_subset)
    return hypotheses


def _box(count: int, low: list[float], high: list[float], generator: torch.Generator) -> torch.Tensor:
    """(count, 3) points uniform in the box low..high (metres)."""
    low_, high_ = torch.tensor(low, dtype=torch.float64), torch.tensor(high, dtype=torch.float64)
    return low_ + torch.rand(count, 3, generator=generator, dtype=torch.float64) * (high_ - low_)


def _yaw(angle: torch.Tensor) -> torch.Tensor:
    """(F, 3, 3) rotations about the vertical axis by (F,) radians."""
    return axis_angle_to_rotation(torch.stack([torch.zeros_like(angle), angle, torch.zeros_like(angle)], -1))


def _seen(points: torch.Tensor, generator: torch.Generator) -> tuple[torch.Tensor, torch.Tensor]:
    """(F, N, 3) camera-frame points -> (F, N, 2) pixels (700 px focal length, 1280 × 480 image,
    0.3 px noise) and (F, N) visibility (in front, inside the image)."""
    pixels = 700 * points[..., :2] / points[..., 2:] + torch.tensor([640.0, 240.0], dtype=torch.float64)
    pixels = pixels + 0.3 * torch.randn(pixels.shape, generator=generator, dtype=torch.float64)
    visible = (pixels >= 0).all(-1) & (pixels[..., 0] < 1280) & (pixels[..., 1] < 480) & (points[..., 2] > 0)
    return pixels, visible


def overtaking_scene(seed: int, frames: int = 10) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """A camera driving forward 0.5 m per frame past 300 static points, and a body of 80 points
    overtaking it at twice its speed (700 px focal length, 1280 × 480 image, 0.3 px noise; a
    point is seen while it is in the image): (F, N, 2) pixels, (F, N) visibility, (N,) labels
    (0 static, 1 the body). Both move straight along the optical axis, so every frame pair's
    epipolar geometry is the same for both, and the body's tracks are exactly those of static
    points behind the cameras (the body's point X(f) = X + f·v is seen like the static point
    −X·c/(v − c), c the camera's speed): only the depths' sign tells them apart."""
    generator = torch.Generator().manual_seed(seed)
    forward = torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64)
    step = torch.arange(frames, dtype=torch.float64)[:, None, None]
    static = _box(300, [-12, -4, 12], [12, 3, 40], generator).expand(frames, -1, -1)
    body = _box(80, [1.5, 0.0, 7], [3.5, 1.5, 10], generator) + 2 * 0.5 * step * forward
    pixels, visible = _seen(torch.cat([static, body], 1) - 0.5 * step * forward, generator)
    return pixels, visible, torch.cat([torch.zeros(300, dtype=torch.long), torch.ones(80, dtype=torch.long)])


def test_a_body_overtaking_the_camera_is_not_taken_for_the_static_scene():
    """The overtaking body (:func:`overtaking_scene`) fits the scene's rigid motion over all
    frames, but behind the cameras: the scene's depth-order check cuts it out (without the check
    the body stays in the scene: the test fails there). Every static track seen in 3 frames stays
    label 0 and every body track is labelled otherwise, at every scene and seed here."""
    for scene_seed in range(3):
        tracks, visible, truth = overtaking_scene(scene_seed)
        judged = visible.sum(0) >= 3
        for seed in range(2):
            labels = segment_motions(tracks, visible, generator=torch.Generator().manual_seed(seed)).labels
            assert bool((labels[judged & (truth == 0)] == 0).all()), (scene_seed, seed)
            assert bool((labels[judged & (truth == 1)] != 0).all()), (scene_seed, seed)


def test_settling_fits_each_scene_plane_once(monkeypatch):
    """Settling asks for the scene's plane residuals in three tests (its parallax for the
    excess, for joining the motions that explain it, for the depth order); each track set's
    are fitted once (a long video's scene: 0.5-0.8 s a fit)."""
    from torchsfm.moving import scene as scene_module

    fitted = []
    plane_residuals = scene_module.plane_residuals
    monkeypatch.setattr(scene_module, "plane_residuals",
                        lambda tracks, visible, members, pairs: fitted.append(members.clone()) or plane_residuals(tracks, visible, members, pairs))
    tracks, visible, _ = overtaking_scene(0)
    segment_motions(tracks, visible, generator=torch.Generator().manual_seed(0))
    assert len(fitted) >= 2  # the scene's and the other motion's (as scene_excess judges it in join_explaining)
    assert not any(torch.equal(fitted[i], fitted[j]) for i in range(len(fitted)) for j in range(i))


def panning_scene(seed: int, frames: int = 10) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """A camera that only turns, following a truck that fills most of the view: 120 road points
    8-40 m ahead (static), and a 5 × 3.5 × 3 m truck of 160 points driving 0.3 m per frame across
    and 0.3 m towards the camera, turning 4° per frame: (F, N, 2) pixels, (F, N) visibility, (N,)
    labels (0 the road, 1 the truck). The truck covers more of the image than the road and has
    parallax; the road moves by one rotation homography per frame pair."""
    generator = torch.Generator().manual_seed(seed)
    step = torch.arange(frames, dtype=torch.float64)
    road = _box(120, [-20, 1.5, 8], [20, 3, 40], generator).expand(frames, -1, -1)
    body = _box(160, [-2.5, -2.5, -1.5], [2.5, 1.0, 1.5], generator)  # about the truck's centre
    centre = torch.stack([0.3 * step, 0 * step, 7 - 0.3 * step], -1)
    truck = body @ _yaw(torch.deg2rad(-4 * step)).transpose(1, 2) + centre[:, None]
    camera = _yaw(torch.atan2(0.3 * step, torch.full_like(step, 8.5)))  # the camera's orientation: turned towards the truck
    pixels, visible = _seen(torch.cat([road, truck], 1) @ camera, generator)  # camera-frame points Rᵀ X
    return pixels, visible, torch.cat([torch.zeros(120, dtype=torch.long), torch.ones(160, dtype=torch.long)])


@pytest.mark.xfail(strict=True, reason="known limit (issue 10, Hopkins155 truck1): the scene is the motion covering most of "
                   "the image; a turning camera's world that an object out-covers is taken for a body")
def test_the_world_of_a_turning_camera_is_the_scene_though_an_object_covers_more():
    """:func:`panning_scene`: the truck covers more grid cells (36 against the road's 28) and has
    parallax; the road moves by one rotation homography per frame pair. The road should be label
    0 and the truck a body; today the truck is taken for the scene. Tried and not kept: taking
    instead a motion without parallax that moves like a rotation of the camera, spans at least
    half the leader's cells and that the leader's rigid motion does not explain. It fixed this
    scene and truck1 (Hopkins155 whole-track means over seeds 0-4: 6.5 / 6.7 → 2.3 / 4.8 %), but
    took a flat patch pasted across Fountain-P11 for the scene, however "like a rotation" was
    judged: by the homographies' eigenvalues (one modulus; frames 2-6 of
    ``tests/sfm/test_moving_pipelines.py``: camera errors beyond the test's bound), by a rotation
    fitted with the focal length searched (``examples/inserted_object.py`` frames 4-8: 26°; the
    patch fits it to 0.44 px at an infinite focal length), or by that fit also having to beat the
    image-plane motion (frames 5-9: a piece of the patch made the scene, the body 58 points
    instead of 211). A flat object sliding across the view moves like a long-focus camera
    turning."""
    tracks, visible, truth = panning_scene(0)
    judged = visible.sum(0) >= 3
    labels = segment_motions(tracks, visible, generator=torch.Generator().manual_seed(0)).labels
    assert bool((labels[judged & (truth == 0)] == 0).all())
    assert bool((labels[judged & (truth == 1)] > 0).all())


def test_misclassification_matches_labels_one_to_one():
    truth = torch.tensor([0, 0, 0, 1, 1, 2, -1])
    assert misclassification(torch.tensor([5, 5, 5, 3, 3, 4, -1]), truth) == 0.0
    assert misclassification(torch.tensor([1, 1, 1, 1, 1, 2, -1]), truth) == pytest.approx(2 / 7)
    assert misclassification(torch.tensor([0, 0, 0, 1, 1, 2, 2]), truth) == pytest.approx(1 / 7)
    assert misclassification(torch.tensor([0, 0, -1, 1, 1, 2, -1]), truth) == pytest.approx(1 / 7)


@pytest.mark.parametrize("objects", [1, 2, 3])
def test_segments_every_object_and_finds_their_number(objects):
    """0.5 px noise, 10 % outlier tracks, five seeds of the hypotheses: the number of motions is
    found in 4 of 5 runs at least (measured over ten seeds: 30 of the 30 runs of 1-3 objects);
    in those the static scene is label 0, at most 2 % of the inlier tracks are misclassified, and
    every motion's robust residual is within 3x the noise (measured 0.43-0.6 px)."""
    data = scene(4, objects)
    inliers = data.labels >= 0
    found = 0
    for seed in range(5):
        result = segment_motions(data.tracks, generator=torch.Generator().manual_seed(seed))
        if result.num_motions != objects + 1:
            continue
        found += 1
        assert misclassification(result.labels[inliers], data.labels[inliers]) <= 0.02
        assert float((result.labels[data.labels == 0] == 0).double().mean()) >= 0.98
        assert result.sizes.shape == result.coverage.shape == (objects + 1,)
        assert bool((result.residuals <= 1.5).all()), result.residuals
    assert found >= 4


def test_the_rigidity_diagnostics_are_made_when_read_and_leave_the_callers_draws_alone():
    """``residuals`` is computed on first read, with draws of its own: whether it is read or not,
    the same generator's next segmentation is the same, and reading it twice gives one tensor."""
    data = scene(3, 1)
    unread, read = torch.Generator().manual_seed(0), torch.Generator().manual_seed(0)
    segment_motions(data.tracks, generator=unread)
    first = segment_motions(data.tracks, generator=read)
    residuals = first.residuals
    assert residuals.shape == (first.num_motions,) and first.residuals is residuals
    assert torch.equal(segment_motions(data.tracks, generator=unread).labels, segment_motions(data.tracks, generator=read).labels)
    assert torch.equal(unread.get_state(), read.get_state())


def test_given_number_of_motions_is_used():
    data = scene(3, 2)
    result = segment_motions(data.tracks, num_motions=3, generator=torch.Generator().manual_seed(0))
    assert result.num_motions == 3
    assert segment_motions(data.tracks, num_motions=numpy.int64(3), generator=torch.Generator().manual_seed(0)).num_motions == 3
    for wrong in (0, -1, 2.5, True, "3"):  # refused before any work, by what is wrong with it
        with pytest.raises(InputError, match="num_motions must be a positive int"):
            segment_motions(data.tracks, num_motions=wrong)
    with pytest.raises(NotEnoughDataError, match="motions"):  # more motions than tracks to cluster
        segment_motions(data.tracks, num_motions=data.tracks.shape[1] + 1)


def test_two_bodies_taken_for_one_are_cut_apart():
    """Two 60-track boxes given one label: of the motions cut in two, the merged one gains most
    (its parts fit one F per frame pair each far better than together) and its cut separates the
    boxes exactly (seed 3; a background half on one wall can gain more: seed 2 cuts it, see
    split_least_rigid)."""
    from torchsfm.moving.scene import split_least_rigid

    data = scene(3, 2)
    found = segment_motions(data.tracks, generator=torch.Generator().manual_seed(0))
    inliers = data.labels >= 0
    assert found.num_motions == 3 and misclassification(found.labels[inliers], data.labels[inliers]) == 0.0
    merged = found.labels.clamp_max(1)
    split = split_least_rigid(data.tracks, torch.ones(data.tracks.shape[:2], dtype=torch.bool), merged, found.pieces,
                              found.affinity, found.clustered, SegmentationConfig(), torch.Generator().manual_seed(0))
    assert misclassification(split[inliers], data.labels[inliers]) == 0.0


def test_one_motion_taken_for_two_is_joined():
    """The converse: the scene of a two-body scene given as two motions (its tracks left and right
    of the median column), four labels in all: of the six pairs, the two halves of the scene are
    the two one rigid motion explains best (their union's reconstruction fits each as well as its
    own), and joining them gives the truth back exactly."""
    from torchsfm.moving.scene import merge_most_rigid

    data = scene(3, 2)
    found = segment_motions(data.tracks, generator=torch.Generator().manual_seed(0))
    inliers = data.labels >= 0
    assert found.num_motions == 3 and misclassification(found.labels[inliers], data.labels[inliers]) == 0.0
    column = data.tracks[0, :, 0]
    halved = torch.where((found.labels == 0) & (column > column[found.labels == 0].median()), 3, found.labels)
    assert misclassification(halved[inliers], data.labels[inliers]) > 0.2
    merged = merge_most_rigid(data.tracks, torch.ones(data.tracks.shape[:2], dtype=torch.bool), halved, SegmentationConfig(),
                              torch.Generator().manual_seed(0))
    assert int(merged.max()) == 2
    assert misclassification(merged[inliers], data.labels[inliers]) == 0.0


def test_the_round_budget_is_shared_by_the_kinds_used(monkeypatch):
    """``segmentation.hypotheses`` per round, split evenly: 1333 each of F, affine and plane
    hypotheses on five frames; on two frames the plane kind is left out and F and affine get
    2000 each (the budget of the two-kind default before plane hypotheses joined it)."""
    from torchsfm.moving import affinity

    counts: dict[str, list[int]] = {}

    def recording(name, fit):
        def wrapped(tracks, visible, count, *args):
            counts.setdefault(name, []).append(count)
            return fit(tracks, visible, count, *args)
        return wrapped

    monkeypatch.setattr(affinity, "MODELS", {name: recording(name, fit) for name, fit in affinity.MODELS.items()})
    config = SegmentationConfig(guided_rounds=0)
    segment_motions(scene(3, 1).tracks, config=config, generator=torch.Generator().manual_seed(0))
    assert counts == {"fundamental": [1333], "affine": [1333], "homography": [1333]}
    counts.clear()
    segment_motions(scene(3, 1).tracks[:2], config=config, generator=torch.Generator().manual_seed(0))
    assert counts == {"fundamental": [2000], "affine": [2000]}


def test_a_static_scene_is_one_motion():
    data = scene(3, 0)
    result = segment_motions(data.tracks, generator=torch.Generator().manual_seed(0))
    assert result.num_motions == 1
    assert bool((result.labels[data.labels == 0] == 0).all())


def test_static_camera_with_a_moving_object():
    """The background does not move at all in the image: still one motion, the object another."""
    data = scene(3, 1, static_camera=True)
    result = segment_motions(data.tracks, generator=torch.Generator().manual_seed(0))
    inliers = data.labels >= 0
    assert result.num_motions == 2
    assert misclassification(result.labels[inliers], data.labels[inliers]) <= 0.02


def test_tracks_with_gaps_and_short_tracks_are_unassigned():
    data = scene(3, 1)
    F, N = data.tracks.shape[:2]
    generator = torch.Generator().manual_seed(1)
    visible = torch.rand(F, N, generator=generator) > 0.15
    short = torch.arange(N) % 10 == 0
    visible[2:, short] = False  # seen in two frames at most
    tracks = torch.where(visible[..., None], data.tracks, float("nan"))
    result = segment_motions(tracks, visible, generator=torch.Generator().manual_seed(0))
    assert bool((result.labels[short] == -1).all())
    judged = ~short & (data.labels >= 0)
    assert misclassification(result.labels[judged], data.labels[judged]) <= 0.05


def test_deterministic_for_a_generator():
    data = scene(4, 2)
    first = segment_motions(data.tracks, generator=torch.Generator().manual_seed(7))
    second = segment_motions(data.tracks, generator=torch.Generator().manual_seed(7))
    torch.testing.assert_close(first.labels, second.labels, rtol=0, atol=0)


def test_bad_input_is_named():
    data = scene(3, 1)
    with pytest.raises(ShapeError, match="tracks"):
        segment_motions(data.tracks[..., :1])
    with pytest.raises(ShapeError, match="visible"):
        segment_motions(data.tracks, torch.ones(2, 3, dtype=torch.bool))
    with pytest.raises(InputError, match="bool"):
        segment_motions(data.tracks, torch.ones(data.tracks.shape[:2]))
    broken = data.tracks.clone()
    broken[1, 4] = float("nan")
    with pytest.raises(InputError, match="non-finite"):
        segment_motions(broken)
    with pytest.raises(NotEnoughDataError):
        segment_motions(data.tracks[:, :5])
    with pytest.raises(Exception, match="must"):
        SegmentationConfig(preference_share=1.5)


needs_data = pytest.mark.skipif(not (DATA / "hopkins155_subset").is_dir(), reason="needs ../shared/data (Hopkins155)")


@needs_data
def test_hopkins155_subset_misclassification():
    """The four sequences of hopkins155_subset (seed 0): given the number of motions, mean
    misclassification <= 5 % (measured 0.1 %: 1R2RC 0.4 %, the others 0 %); the number
    of motions is found on at least 3 of the 4 (measured: all 4; kanatani1's object is weakly
    separated)."""
    pytest.importorskip("scipy")
    from torchsfm.io.datasets import read_hopkins155

    errors, right = [], 0
    for name in ("1R2RC", "cars1", "kanatani1", "truck1"):
        sequence = read_hopkins155(DATA / "hopkins155_subset" / name)
        motions = int(sequence.labels.max()) + 1
        given = segment_motions(sequence.tracks, num_motions=motions, generator=torch.Generator().manual_seed(0))
        errors.append(misclassification(given.labels, sequence.labels))
        found = segment_motions(sequence.tracks, generator=torch.Generator().manual_seed(0))
        right += found.num_motions == motions
    assert sum(errors) / len(errors) <= 0.05, errors
    assert right >= 3


@pytest.mark.parametrize("clip", ["Seq028_Clip02", "Seq038_Clip02"])
def test_a_given_number_of_motions_keeps_the_settled_partition(shared_data, clip):
    """KT3DMoSeg clips whose settled segmentation (number found) has the true number of motions
    at some seeds: at each such seed of 0-3, given that number, the same partition comes back,
    not the unsettled cut into that many, which split the background there (measured: 47.1 % and
    23.0 % misclassified; the settled partitions 1.6-12.3 %). Seq028_Clip02's settled number is
    right at three of these seeds, Seq038_Clip02's at all four."""
    pytest.importorskip("scipy")
    from torchsfm.io.datasets import read_kt3dmoseg

    sequence = read_kt3dmoseg(shared_data / "kt3dmoseg_dev" / f"{clip}_Tracks")
    motions = int(sequence.labels.max()) + 1
    settled = 0
    for seed in range(4):
        found = segment_motions(sequence.tracks, sequence.visible, generator=torch.Generator().manual_seed(seed))
        if found.num_motions != motions:
            continue
        settled += 1
        given = segment_motions(sequence.tracks, sequence.visible, num_motions=motions, generator=torch.Generator().manual_seed(seed))
        assert given.num_motions == motions
        assert torch.equal(given.labels, found.labels), seed
        assert misclassification(given.labels, sequence.labels) <= 0.15, seed
    assert settled >= 3


@pytest.mark.parametrize("seed", [0, 1])
def test_a_given_number_of_motions_cuts_the_motion_that_holds_two(shared_data, seed):
    """Hopkins155 cars2_07: the settled segmentation (number found) takes the two cars for one
    motion at these seeds. Given three motions, the motion that one rigid motion explains worst
    is cut in two — the cars — instead of the pieces being cut into three anew, which split the
    background (measured 47.2 % misclassified at both seeds; now 0.5 %)."""
    pytest.importorskip("scipy")
    from torchsfm.io.datasets import read_hopkins155

    sequence = read_hopkins155(shared_data / "hopkins155_dev" / "cars2_07")
    found = segment_motions(sequence.tracks, generator=torch.Generator().manual_seed(seed))
    given = segment_motions(sequence.tracks, num_motions=3, generator=torch.Generator().manual_seed(seed))
    assert found.num_motions == 2
    assert given.num_motions == 3
    assert misclassification(given.labels, sequence.labels) <= 0.02


def test_a_given_number_of_motions_joins_a_scene_found_in_two(shared_data):
    """Hopkins155 2T3RCTP (seed 2): the number found is 4 — the room's background cut in two
    (132 and 77 tracks, the 77 unlinked to the rest), each object whole. Given three motions,
    the two motions one rigid motion explains best are joined — the background's halves —
    instead of the pieces being cut into three anew, which joined the background's larger half
    to an object (28.1 % misclassified at seed 0 before the pieces were split along unlinked
    groups; joining by one F per frame pair chose the halves too)."""
    pytest.importorskip("scipy")
    from torchsfm.io.datasets import read_hopkins155

    sequence = read_hopkins155(shared_data / "hopkins155_dev" / "2T3RCTP")
    found = segment_motions(sequence.tracks, generator=torch.Generator().manual_seed(2))
    given = segment_motions(sequence.tracks, num_motions=3, generator=torch.Generator().manual_seed(2))
    assert found.num_motions == 4
    assert given.num_motions == 3
    assert misclassification(given.labels, sequence.labels) <= 0.01


def test_the_labels_do_not_depend_on_the_thread_count(shared_data):
    """Hopkins155 2T3RCTP (seed 0) on one and on two threads: the same labels. Its affinity has
    unlinked groups (a repeated leading eigenvalue), whose eigenvector basis LAPACK chooses
    differently on one and two threads; k-means ties sent by rounding once made one thread find
    3 motions (0.2 % misclassified) and two threads 4 (16.6 %)."""
    from torchsfm.io.datasets import read_hopkins155

    sequence = read_hopkins155(shared_data / "hopkins155_dev" / "2T3RCTP")
    threads = torch.get_num_threads()
    labels = []
    try:
        for count in (1, 2):
            torch.set_num_threads(count)
            labels.append(segment_motions(sequence.tracks, generator=torch.Generator().manual_seed(0)).labels)
    finally:
        torch.set_num_threads(threads)
    assert torch.equal(labels[0], labels[1])


@pytest.mark.skipif(not (DATA / "adelaidermf_F").is_dir(), reason="needs ../shared/data (AdelaideRMF)")
def test_adelaidermf_two_views_with_outliers():
    """Two views, several independently moved objects, 35-43 % false matches: the reader's
    conventions, and misclassification (outliers must come out unassigned) with the number of
    structures found (within one: an outlier-rich piece of structure 0 may be cut out as a body):
    measured 0.4 / 5.9 / 22.2 % (biscuitbookbox / breadcartoychips / dinobooks, seed 0; 13.5 /
    9.3 / 31.4 % before pieces were cut from structure 0), bound 16 % on the mean; OpenCV's
    sequential RANSAC: 28 / 35 / 20 %."""
    pytest.importorskip("scipy")
    from torchsfm.io.datasets import read_adelaidermf

    errors = []
    for name in ("biscuitbookbox", "breadcartoychips", "dinobooks"):
        scene = read_adelaidermf(DATA / "adelaidermf_F" / f"{name}.mat")
        assert scene.tracks.shape[0] == 2 and scene.has_outliers and int(scene.labels.min()) == -1
        result = segment_motions(scene.tracks, generator=torch.Generator().manual_seed(0))
        assert abs(result.num_motions - (int(scene.labels.max()) + 1)) <= 1
        errors.append(misclassification(result.labels, scene.labels))
    assert sum(errors) / len(errors) <= 0.16, errors


def test_segmentation_figure_colours_each_motion():
    from torchsfm.visualization import MOTION_COLOURS, segmentation_figure

    data = scene(4, 2)
    result = segment_motions(data.tracks, generator=torch.Generator().manual_seed(0))
    picture = segmentation_figure(data.tracks, torch.ones(data.tracks.shape[:2], dtype=torch.bool), result.labels,
                                  data.image_size)
    assert picture.shape == (3, 480, 640) and picture.dtype == torch.uint8
    for label in range(result.num_motions):
        colour = torch.tensor(MOTION_COLOURS[label], dtype=torch.uint8)[:, None, None]
        assert bool((picture == colour).all(0).any()), f"motion {label} not drawn"


def test_four_point_homography_is_exact_and_the_plane_model_segments():
    """The plane hypotheses' 4-point solver reproduces a homography to 1e-7 (float64, pixel
    coordinates of a few hundred; degenerate samples give NaN); plane hypotheses are used on
    three frames or more only, and with them segmentation still separates the scene's motions."""
    from torchsfm.moving.hypotheses import four_point_homography

    generator = torch.Generator().manual_seed(0)
    H = torch.eye(3, dtype=torch.float64) + 0.1 * torch.randn(5, 3, 3, generator=generator, dtype=torch.float64)
    x1 = 100 + 300 * torch.rand(5, 4, 2, generator=generator, dtype=torch.float64)
    mapped = torch.cat([x1, torch.ones_like(x1[..., :1])], -1) @ H.transpose(-1, -2)
    x2 = mapped[..., :2] / mapped[..., 2:]
    estimate = four_point_homography(x1, x2)
    torch.testing.assert_close(estimate / estimate[:, 2:, 2:], H / H[:, 2:, 2:], rtol=1e-7, atol=1e-7)
    collinear = x1.clone()
    collinear[0, :, 1] = 5.0
    assert bool(four_point_homography(collinear, x2)[0].isnan().all())
    all_three = SegmentationConfig(models="fundamental,affine,homography")
    assert all_three.kinds_for(3) == ["fundamental", "affine", "homography"]
    assert all_three.kinds_for(2) == ["fundamental", "affine"]
    assert SegmentationConfig(models="homography").kinds_for(2) == ["homography"]
    data = scene(4, 2)
    result = segment_motions(data.tracks, config=all_three,
                             generator=torch.Generator().manual_seed(0))
    inliers = data.labels >= 0
    assert result.num_motions == 3
    assert misclassification(result.labels[inliers], data.labels[inliers]) <= 0.02


def test_more_tracks_than_max_tracks_cluster_a_subset_and_fit_the_rest_to_the_motions():
    """The 2-object scene (about 560 tracks, 0.5 px noise, 10 % outliers) with only 250 clustered
    (``max_tracks``): the number of motions is still found, the affinity covers the clustered
    tracks only (the outliers among them dropped), the others go to the motion whose F fits them (inlier misclassification within
    2 %, as with all clustered), and at least 90 % of the outliers stay unassigned."""
    data = scene(4, 2)
    result = segment_motions(data.tracks, config=SegmentationConfig(max_tracks=250), generator=torch.Generator().manual_seed(0))
    inliers = data.labels >= 0
    n = result.clustered.numel()  # the subset less the tracks it finds to be outliers
    assert result.num_motions == 3 and 200 <= n <= 250 and result.affinity.shape == (n, n)
    assert misclassification(result.labels[inliers], data.labels[inliers]) <= 0.02
    assert float((result.labels[~inliers] == -1).double().mean()) >= 0.9


def test_frame_pairs_are_as_wide_as_the_tracks_allow():
    """A third of the sequence for full tracks; the median track span for short video tracks."""
    from torchsfm.moving.pair_fits import frame_pairs, median_span

    full = torch.ones(10, 30, dtype=torch.bool)
    assert frame_pairs(full).tolist() == [[f, f + 3] for f in range(7)]
    assert frame_pairs(full, 3).tolist() == [[0, 3], [3, 6], [6, 9]]
    short = torch.zeros(30, 40, dtype=torch.bool)
    for track in range(40):  # every track seen in 3 consecutive frames: span 2
        short[track % 28:track % 28 + 3, track] = True
    pairs = frame_pairs(short)
    assert median_span(short) == 2 and median_span(full) == 9
    assert (pairs[:, 1] - pairs[:, 0] == 2).all() and pairs.shape[0] == 28


def test_int8_products_are_not_chosen_where_the_build_has_none(monkeypatch):
    """The timing that chooses the product type answers False, not an error, where torch has no
    CPU int8 products; the preference counts then run in float32."""
    from torchsfm.moving import affinity

    def missing(*_):
        raise RuntimeError("_int_mm: not implemented for this CPU")

    monkeypatch.setattr(torch, "_int_mm", missing)
    assert affinity.int8_products_are_faster.__wrapped__() is False


@pytest.mark.parametrize("path", ["int8", "float32", "sparse", "complement"])
def test_preference_counts_and_similarity_are_exact(path, monkeypatch):
    """The int8 and the float32 products of 0/1 preference matrices (whichever this CPU runs
    faster; the symmetric one by blocks), the sparse ones (preferences sparser than
    ``SPARSE_PREFERENCES``: tracks with gaps) and the counts of preferences among defined
    hypotheses as all preferences less a sparse product (undefined entries that sparse: tracks
    seen throughout) are exact, so the Tanimoto similarity equals its definition
    |p_i ∧ p_j| / |p_i ∨ p_j| over the hypotheses defined for both."""
    from torchsfm.moving import affinity
    from torchsfm.moving.affinity import binary_gram, binary_operand, binary_products, tanimoto_similarity
    from torchsfm.numerics import sparse_rows_of_transpose

    monkeypatch.setattr(affinity, "int8_products_are_faster", lambda: path == "int8")
    if path != "complement":
        monkeypatch.setattr(affinity, "SPARSE_PREFERENCES", 1.0 if path == "sparse" else 0.0)
    sparse_calls = []
    monkeypatch.setattr(affinity, "sparse_rows_of_transpose",
                        lambda x: sparse_calls.append(1) or sparse_rows_of_transpose(x))
    g = torch.Generator().manual_seed(3)
    defined = torch.rand(301, 37, generator=g) < (0.995 if path == "complement" else 0.8)  # (H, N)
    preference = (torch.rand(301, 37, generator=g) < 0.3) & defined
    if path in ("int8", "float32"):
        operand = binary_operand(preference)
        assert operand.dtype == (torch.int8 if path == "int8" else torch.float32)
        exact = preference.double().T @ defined.double()
        torch.testing.assert_close(binary_products(operand, binary_operand(defined)).double(), exact, rtol=0, atol=0)
        torch.testing.assert_close(binary_gram(operand).double(), preference.double().T @ preference.double(), rtol=0, atol=0)
    similarity = tanimoto_similarity(preference, defined, torch.float64)
    assert len(sparse_calls) == (path in ("sparse", "complement"))
    both = defined.T[:, None] & defined.T[None]  # (37, 37, 301)
    p_i, p_j = preference.T[:, None] & both, preference.T[None] & both
    union = (p_i | p_j).sum(-1).double()
    expected = torch.where(union > 0, (p_i & p_j).sum(-1).double() / union.clamp_min(1), 0.0).fill_diagonal_(0.0)
    torch.testing.assert_close(similarity, expected, rtol=1e-6, atol=0)


@pytest.mark.parametrize("model", ["fundamental", "homography"])
def test_track_residuals_do_not_depend_on_how_many_pairs_are_fitted_at_once(model, monkeypatch):
    """The trimmed per-pair fits of three track sets over a 12-frame sequence with gaps, one pair
    per block against all pairs in one block: the same residuals (1e-9 px: the batched solvers'
    rounding may differ with the batch) and the same judged tracks."""
    from torchsfm.moving import pair_fits
    from torchsfm.moving.pair_fits import frame_pairs, track_residuals

    g = torch.Generator().manual_seed(8)
    F, N = 12, 200
    base = 600 * torch.rand(N, 2, generator=g, dtype=torch.float64)
    tracks = torch.stack([base * (1 + 0.01 * f) + f + 0.3 * torch.randn(N, 2, generator=g, dtype=torch.float64) for f in range(F)])
    visible = torch.rand(F, N, generator=g) < 0.8
    members = torch.rand(3, N, generator=g) < 0.5
    pairs = frame_pairs(visible)
    monkeypatch.setattr(pair_fits, "BLOCK_ELEMENTS", 1)
    one, judged_one = track_residuals(tracks, visible, members, pairs, model)
    monkeypatch.setattr(pair_fits, "BLOCK_ELEMENTS", 10**9)
    whole, judged_whole = track_residuals(tracks, visible, members, pairs, model)
    assert pairs.shape[0] > 3 and bool(judged_whole.any())
    assert torch.equal(judged_one, judged_whole)
    torch.testing.assert_close(one[judged_one], whole[judged_whole], rtol=0, atol=1e-9)


@pytest.mark.parametrize("model", ["fundamental", "homography"])
def test_track_residuals_measure_every_track_and_fit_only_the_sets(model):
    """Tracks no set holds weigh nothing in the fits, and the last fits measure them too: the
    residuals of three sets' tracks over a sequence with gaps are those of the sets' tracks alone
    (1e-9 px: a fit over fewer columns rounds otherwise) with 300 tracks no set holds appended,
    half of them up to 10⁶ px away; an appended track is judged wherever it is seen in a pair, its
    residual finite. Sets with fewer than 8 tracks in
    every pair are fitted nowhere (no track judged)."""
    from torchsfm.moving.pair_fits import PAIR_MODELS, frame_pairs, track_residuals, trimmed_pair_fits

    g = torch.Generator().manual_seed(8)
    F, N, extra = 12, 120, 300
    base = 600 * torch.rand(N + extra, 2, generator=g, dtype=torch.float64)
    tracks = torch.stack([base * (1 + 0.01 * f) + f + 0.3 * torch.randn(N + extra, 2, generator=g, dtype=torch.float64)
                          for f in range(F)])
    far = torch.arange(N + extra) >= N + extra // 2
    tracks[:, far] += 1e6 * torch.rand(int(far.sum()), 2, generator=g, dtype=torch.float64)
    visible = torch.rand(F, N + extra, generator=g) < 0.8
    members = torch.zeros(3, N + extra, dtype=torch.bool)
    members[:, :N] = torch.rand(3, N, generator=g) < 0.5
    pairs = frame_pairs(visible[:, :N])
    alone, judged_alone = track_residuals(tracks[:, :N], visible[:, :N], members[:, :N], pairs, model)
    rms, judged = track_residuals(tracks, visible, members, pairs, model)
    assert bool(judged_alone.all(1).any()) and torch.equal(judged[:, :N], judged_alone)
    torch.testing.assert_close(rms[:, :N][judged_alone], alone[judged_alone], rtol=0, atol=1e-9)
    seen_in_a_pair = (visible[pairs[:, 0]] & visible[pairs[:, 1]]).any(0)
    assert torch.equal(judged[:, N:], seen_in_a_pair[N:].expand(3, -1))
    assert bool(rms[judged].isfinite().all())
    x1, x2 = tracks[pairs[:, 0]], tracks[pairs[:, 1]]  # one set's fits: each track at its distance to the last fit
    seen = members[0] & visible[pairs[:, 0]] & visible[pairs[:, 1]]
    fits, distances, _ = trimmed_pair_fits(x1, x2, seen, seen.double(), model)
    torch.testing.assert_close(distances, PAIR_MODELS[model][1](fits, x1, x2), rtol=0, atol=0)
    few = torch.zeros_like(members)
    few[:, :7] = True
    _, judged_few = track_residuals(tracks, visible, few, pairs, model)
    assert not bool(judged_few.any())


@pytest.mark.parametrize("seen_subset", [0.0, 1.0])
@pytest.mark.parametrize("chunk_elements", [2**21, 600])
def test_affine_residuals_are_distances_to_the_samples_span(chunk_elements, seen_subset, monkeypatch):
    """Where defined (seen in all of a hypothesis' frames, not one of its sample), a track's
    affine residual is its squared distance per frame to the affine span of the hypothesis' 4
    sampled trajectories over its frames (least squares, written directly); defined exactly
    where that holds for a usable sample. Tracks with visibility gaps, in one chunk and in
    chunks of 2 hypotheses (600 // (3 × 100 tracks), in the order of their first frames), every
    track measured and the tracks seen in a chunk only (1e-6 px²: the products round otherwise)."""
    hypotheses = _hypotheses_with(monkeypatch, chunk_elements, seen_subset)
    g = torch.Generator().manual_seed(6)
    F, N, H = 12, 100, 24
    tracks = 300 * torch.rand(F, N, 2, generator=g, dtype=torch.float64)
    visible = torch.rand(F, N, generator=g) < 0.75
    visible[:, :10] = True  # tracks every sample can be drawn from
    residual, defined = hypotheses.affine_residuals(tracks, visible, H, SegmentationConfig(affine_frames=4),
                                                    torch.Generator().manual_seed(1))
    replay = torch.Generator().manual_seed(1)  # the same draws again: the hypotheses' frames and samples
    frames, sample, _ = hypotheses.sample_hypotheses(tracks, visible, H, 4, 4, SegmentationConfig(affine_frames=4), replay, None)
    centred = torch.where(visible[..., None], tracks - tracks[visible].mean(0), 0.0)
    assert bool(defined.any()) and not torch.equal(frames[:, 0].argsort(), torch.arange(H))  # chunks by first frame differ
    for h in range(H):
        trajectories = centred[frames[h]].permute(1, 0, 2).reshape(N, -1)  # (N, 2m)
        origin = trajectories[sample[h, 0]]
        span = (trajectories[sample[h, 1:]] - origin).T  # (2m, 3)
        offsets = trajectories - origin
        fitted = span @ torch.linalg.lstsq(span, offsets.T).solution
        expected = (offsets.T - fitted).square().sum(0) / frames.shape[1]
        seen = visible[frames[h]].all(0)
        seen[sample[h]] = False
        assert torch.equal(defined[h], seen) or not bool(defined[h].any())
        torch.testing.assert_close(residual[h][defined[h]], expected[defined[h]], rtol=1e-9, atol=1e-6)


@pytest.mark.parametrize("seen_subset", [0.0, 1.0])
@pytest.mark.parametrize("chunk_elements", [2**21, 200])
def test_worst_over_pairs_equals_a_loop_over_hypotheses_and_pairs(chunk_elements, seen_subset, monkeypatch):
    """Each hypothesis' largest residual over the pairs of its frames in which a track is seen,
    against the definition written as loops: tracks with visibility gaps, hypotheses sharing
    frame pairs, one unusable sample and one model that is not finite; exact, scored in one
    block and in blocks of 2 hypotheses (200 // (3 pairs x 30 tracks)), each pair's distances
    taken over every track and over the tracks seen in its first frame only."""
    worst_over_pairs = _hypotheses_with(monkeypatch, chunk_elements, seen_subset).worst_over_pairs

    g = torch.Generator().manual_seed(5)
    F, N, H = 6, 30, 9
    tracks = 100 * torch.rand(F, N, 2, generator=g, dtype=torch.float64)
    visible = torch.rand(F, N, generator=g) < 0.7
    frames = torch.stack([torch.randperm(F, generator=g)[:3].sort().values for _ in range(H)])  # (H, 3)
    frames[1] = frames[0]  # two hypotheses on the same pairs
    sample = torch.stack([torch.randperm(N, generator=g)[:4] for _ in range(H)])
    usable = torch.ones(H, dtype=torch.bool)
    usable[2] = False

    def fit(x1, x2):  # (H, s, 2) -> (H, 3, 3): a model that depends on the sample
        models = torch.eye(3, dtype=torch.float64).repeat(x1.shape[0], 1, 1)
        models[:, :2, 2] = (x2 - x1).mean(1)
        models[3, 0, 0] = float("nan")
        return models

    def distance(models, x1, x2):  # (h, 3, 3), (N, 2), (2, h, N) -> (h, N)
        return (x1[None] @ models[:, :2, :2].transpose(-1, -2) + models[:, None, :2, 2] - x2.permute(1, 2, 0)).square().sum(-1)

    worst, defined = worst_over_pairs(tracks, visible, frames, sample, usable, fit, distance)
    expected = torch.zeros(H, N, dtype=torch.float64)
    seen = torch.zeros(H, N, dtype=torch.bool)
    for h in range(H):
        for p, q in ((0, 1), (0, 2), (1, 2)):
            i, j = int(frames[h, p]), int(frames[h, q])
            model = fit(tracks[i][sample], tracks[j][sample])[h]
            residual = distance(model[None], tracks[i], tracks[j].T[:, None])[0]
            both = visible[i] & visible[j]
            expected[h] = torch.where(both, torch.maximum(expected[h], residual), expected[h])
            seen[h] |= both
    torch.testing.assert_close(worst, expected, rtol=0, atol=0, equal_nan=True)
    expected_defined = seen & usable[:, None] & torch.isfinite(expected)
    expected_defined[torch.arange(H)[:, None], sample] = False
    assert torch.equal(defined, expected_defined)
    assert bool(worst[3].isnan().any()) and not bool(defined[3].any()) and not bool(defined[2].any())


@pytest.mark.parametrize("frames_per", [1, 3, 5])
def test_seen_in_every_frame_of_a_hypothesis_is_its_definition(frames_per):
    """A track is seen in all of a hypothesis' frames exactly where a loop over the frames says,
    on tracks with visibility gaps."""
    from torchsfm.moving.hypotheses import seen_in_every

    g = torch.Generator().manual_seed(3)
    F, N, H = 8, 40, 12
    visible = torch.rand(F, N, generator=g) < 0.7
    frames = torch.stack([torch.randperm(F, generator=g)[:frames_per].sort().values for _ in range(H)])
    expected = torch.ones(H, N, dtype=torch.bool)
    for h in range(H):
        for f in frames[h].tolist():
            expected[h] &= visible[f]
    assert torch.equal(seen_in_every(visible, frames), expected)
    assert bool(expected.any()) and not bool(expected.all())


def test_distances_to_each_models_second_frame_equal_the_shared_frame_ones():
    """The segmentation scores h models each against its own second frame: with the same second
    frame for all, the Sampson and transfer distances equal the geometry modules' (1e-9 relative:
    the algebraic error is summed in another order); a point mapped to infinity gets +inf."""
    from torchsfm.geometry.fundamental import sampson_error_of_hypotheses
    from torchsfm.geometry.homography import transfer_error_of_hypotheses
    from torchsfm.moving.hypotheses import sampson_to_each, transfer_to_each

    g = torch.Generator().manual_seed(6)
    x1, x2 = 640 * torch.rand(2, 50, 2, generator=g, dtype=torch.float64)
    models = torch.randn(7, 3, 3, generator=g, dtype=torch.float64)
    shared = x2.T[:, None].expand(-1, 7, -1)  # (2, h, N): the coordinates apart
    torch.testing.assert_close(sampson_to_each(models, x1, shared), sampson_error_of_hypotheses(models[None], x1[None], x2[None])[0],
                               rtol=1e-9, atol=0)
    torch.testing.assert_close(transfer_to_each(models, x1, shared), transfer_error_of_hypotheses(models, x1, x2), rtol=1e-9, atol=0)
    own = 640 * torch.rand(2, 7, 50, generator=g, dtype=torch.float64)  # a second frame per model: row k against model k alone
    for k in range(7):
        torch.testing.assert_close(sampson_to_each(models, x1, own)[k], sampson_to_each(models[k:k + 1], x1, own[:, k:k + 1])[0],
                                   rtol=1e-12, atol=0)
    at_infinity = torch.tensor([[[1.0, 0, 0], [0, 1, 0], [1 / 320, 0, -1]]], dtype=torch.float64)  # w = 0 at x = 320
    assert transfer_to_each(at_infinity, torch.tensor([[320.0, 5.0]], dtype=torch.float64), own[:, :1, :1]).isinf().all()


def test_a_piece_of_the_scene_that_its_motion_explains_rejoins_it():
    """The static scene split in two (a third of its tracks labelled as a motion of their own)
    and two moving objects: the split-off piece rejoins the scene, the objects stay apart."""
    from torchsfm.moving.pair_fits import frame_pairs
    from torchsfm.moving.scene import join_explained, scene_excess

    data = scene(4, 2)
    labels = data.labels.clone()  # 0 scene, 1 and 2 objects, -1 outliers
    scene_tracks = torch.nonzero(labels == 0)[:, 0]
    labels[scene_tracks[::3]] = 3
    visible = torch.ones(data.tracks.shape[:2], dtype=torch.bool)
    excess = scene_excess(data.tracks, visible, labels == 0, frame_pairs(visible), SegmentationConfig(),
                          torch.Generator().manual_seed(0))
    joined = join_explained(labels, excess)
    assert torch.equal(joined, data.labels)


def test_normalized_cut_is_exact_and_the_direct_cut_recovers_blocks():
    """Two pairs of nodes (links 1 inside a pair, 0.1 across one seam): the pairs' normalized
    cut is 2 × 0.1 / 2.1 exactly, less than any other split's; spectral k-means on the leading
    eigenvectors of three noisy blocks recovers them exactly."""
    from torchsfm.moving.clustering import leading_eigenvectors, normalized_cut, spectral_partition

    affinity = torch.tensor([[0, 1, 0, 0], [1, 0, 0.1, 0], [0, 0.1, 0, 1], [0, 0, 1, 0]], dtype=torch.float64)
    assert normalized_cut(affinity, torch.tensor([0, 0, 1, 1])) == pytest.approx(0.2 / 2.1, rel=1e-12)
    assert normalized_cut(affinity, torch.tensor([0, 1, 1, 0])) > normalized_cut(affinity, torch.tensor([0, 0, 1, 1]))
    g = torch.Generator().manual_seed(0)
    truth = torch.arange(3).repeat_interleave(torch.tensor([30, 20, 10]))
    noise = torch.rand(60, 60, generator=g, dtype=torch.float64) * 0.05
    blocks = (truth[:, None] == truth[None]).double() + noise + noise.T
    _, vectors = leading_eigenvectors(blocks.fill_diagonal_(0), 3)
    found = spectral_partition(vectors, 3, SegmentationConfig(), g)
    assert misclassification(found, truth) == 0


def test_the_sparse_eigensolver_of_large_affinities_matches_the_dense_one(monkeypatch):
    """A sparse affinity over 1600 tracks (the LOBPCG path): four blocks of random links, each
    track linked to 24 others, 5 % of the links across blocks. LOBPCG's 20 leading eigenvalues
    (its answer kept) equal the dense eigh's to 1e-10 and its eigenvectors span the same subspace (cosines 1 - 1e-10);
    where LOBPCG's residual is refused, the dense eigh decides, bit for bit."""
    from torchsfm.moving import clustering

    g = torch.Generator().manual_seed(0)
    N = clustering.SPARSE_EIGEN_TRACKS + 100
    block = torch.arange(N) * 4 // N
    partner = torch.randint(0, N, (N, 24), generator=g)
    same = block[partner] == block[:, None]
    keep = same | (torch.rand(N, 24, generator=g) < 0.05)
    rows = torch.arange(N)[:, None].expand_as(partner)
    links = torch.zeros(N, N, dtype=torch.float64)
    links[rows[keep], partner[keep]] = torch.rand(int(keep.sum()), generator=g, dtype=torch.float64) + 0.5
    affinity = torch.maximum(links, links.T).fill_diagonal_(0)

    solved, layouts = [], []
    lobpcg = torch.lobpcg
    monkeypatch.setattr(torch, "lobpcg", lambda *args, **kwargs: layouts.append(args[0].layout) or solved.append(lobpcg(*args, **kwargs))
                        or solved[-1])
    values, vectors = clustering.leading_eigenvectors(affinity, 20)
    assert len(solved) == 1 and torch.equal(values, solved[0][0].sort(descending=True).values)  # LOBPCG's answer kept
    assert layouts == [torch.sparse_csr]  # the layout whose products are fast (COO: 3x slower)
    degree = affinity.sum(1).rsqrt()
    dense_values, dense_vectors = torch.linalg.eigh(affinity * degree[:, None] * degree[None])
    torch.testing.assert_close(values, dense_values.flip(0)[:20], rtol=0, atol=1e-10)
    cosines = torch.linalg.svdvals(vectors.T @ dense_vectors.flip(1)[:, :20])
    torch.testing.assert_close(cosines, torch.ones(20, dtype=torch.float64), rtol=0, atol=1e-10)
    monkeypatch.setattr(clustering, "EIGEN_RESIDUAL", 0.0)
    fallback_values, fallback_vectors = clustering.leading_eigenvectors(affinity, 20)
    assert torch.equal(fallback_values, dense_values.flip(0)[:20]) and torch.equal(fallback_vectors, dense_vectors.flip(1)[:, :20])


def test_a_piece_is_a_body_only_when_its_own_motion_explains_it_to_noise():
    """The scene and an object at 0.5 px noise are each explained by a rigid motion of their own
    within the χ² bound of 1 px noise; 40 tracks drawn at random in every frame (tracking
    errors) are not; a set of 5 tracks cannot be fitted."""
    from torchsfm.moving.scene import noise_explained

    data = scene(5, 1)
    tracks = data.tracks.clone()
    g = torch.Generator().manual_seed(1)
    junk = torch.nonzero(data.labels == 0)[:40, 0]
    low, high = tracks.amin((0, 1)), tracks.amax((0, 1))
    tracks[:, junk] = low + (high - low) * torch.rand(tracks.shape[0], 40, 2, generator=g, dtype=tracks.dtype)
    visible = torch.ones(tracks.shape[:2], dtype=torch.bool)
    members = torch.zeros(4, tracks.shape[1], dtype=torch.bool)
    members[0] = data.labels == 0
    members[0, junk] = False
    members[1] = data.labels == 1
    members[2, junk] = True
    members[3, torch.nonzero(data.labels == 1)[:5, 0]] = True
    explained = noise_explained(tracks, visible, members, SegmentationConfig())
    assert explained.tolist() == [True, True, False, False]


def test_a_body_seen_in_a_few_frames_is_judged_on_the_frames_it_spans():
    """A body leaving the view after 3 of 10 frames: the sequence's frame pairs (3 frames apart)
    never see it at both ends, its own pairs (2 apart) do, and its rigid motion explains it."""
    from torchsfm.moving.pair_fits import frame_pairs
    from torchsfm.moving.scene import noise_explained

    data = synthetic_moving_scene(1, num_frames=10, num_objects=1, object_points=60, noise=0.5)
    body = data.labels == 1
    visible = torch.ones(data.tracks.shape[:2], dtype=torch.bool)
    visible[3:, body] = False
    pairs = frame_pairs(visible)
    assert int(body.sum()) == 60 and not bool((visible[pairs[:, 0]] & visible[pairs[:, 1]])[:, body].any())
    assert noise_explained(data.tracks, visible, body[None], SegmentationConfig()).tolist() == [True]


def test_the_scene_refitted_without_what_it_cut_cuts_every_body():
    """Three boxes of 120 tracks taken together with a 334-track background as one motion, each
    motion in pieces of about 30 tracks: the scene's first fit, pulled by the boxes, explains
    one of them (its one cut left 30 % misclassified); refitted without the pieces it cut, it
    cuts every box, and each is a body of its own."""
    from torchsfm.moving.scene import settle_scene

    data = synthetic_moving_scene(0, num_frames=5, num_objects=3, object_points=120, noise=0.5,
                                  outlier_fraction=0.0, plane_share=0.0)
    truth, N = data.labels, data.labels.numel()
    assert [int((truth == m).sum()) for m in range(4)] == [334, 120, 120, 120]
    pieces = torch.empty(N, dtype=torch.long)
    order = torch.argsort(data.tracks[0, :, 0])  # vertical strips of each motion
    strips = [chunk for m in range(4) for chunk in order[truth[order] == m].split(30)]
    for piece, members in enumerate(strips):
        pieces[members] = piece
    affinity = (truth[:, None] == truth[None]).double().fill_diagonal_(0) + 0.01
    settled = settle_scene(data.tracks, torch.ones(data.tracks.shape[:2], dtype=torch.bool), torch.zeros(N, dtype=torch.long),
                           pieces, affinity, torch.arange(N), SegmentationConfig(), torch.Generator().manual_seed(0))
    assert int(settled.max()) == 3 and misclassification(settled, truth) == 0


@pytest.mark.parametrize("clip, split", [("Seq028_Clip02", "first"), ("Seq013_Clip01", "x")])
def test_a_background_half_whose_fit_explains_the_scene_joins_it(shared_data, clip, split):
    """KT3DMoSeg background split in two halves (the tracks starting first, or those right of the
    median), the scene the other half with the cars: the scene's fit leaves the half beyond its
    bound (median excess measured 5.87 and 9.90), the half's own fit explains the scene, and
    :func:`join_explaining` joins it."""
    from torchsfm.io.datasets import read_kt3dmoseg
    from torchsfm.moving.pair_fits import frame_pairs
    from torchsfm.moving.scene import join_explaining, scene_excess

    sequence = read_kt3dmoseg(shared_data / "kt3dmoseg_dev" / f"{clip}_Tracks")
    tracks, visible, truth = sequence.tracks, sequence.visible, sequence.labels
    background = truth == 0
    if split == "first":
        start = torch.where(visible, torch.arange(tracks.shape[0])[:, None], tracks.shape[0]).amin(0)
        half = background & (start <= start[background].median())
    else:
        x = torch.where(visible, tracks[..., 0], torch.nan).nanmean(0)
        half = background & (x > x[background].median())
    labels = torch.where(half, 1, torch.where(truth >= 0, 0, -1))
    pairs = frame_pairs(visible)
    excess = scene_excess(tracks, visible, labels == 0, pairs, SegmentationConfig(), torch.Generator().manual_seed(0))
    assert float(excess[half].nanmedian()) > 1
    joined = join_explaining(tracks, visible, labels, pairs, SegmentationConfig(), torch.Generator().manual_seed(0))
    assert int(joined.max()) == 0 and bool((joined[background] == 0).all())


def test_a_scene_without_parallax_is_judged_by_its_homographies():
    """A background all on one wall (no parallax), its left half the scene: the F fitted to a
    plane is degenerate and extrapolates 1.27 px (median) off the right half, beyond its 1 px
    bound; the wall's homographies explain that half (median excess measured 0.84) and not the
    moving box (19.4)."""
    from torchsfm.moving.pair_fits import epipolar_residuals, frame_pairs, plane_residuals, track_residuals
    from torchsfm.moving.scene import has_parallax, scene_excess

    data = synthetic_moving_scene(4, num_frames=5, num_objects=1, object_points=60, noise=0.5, outlier_fraction=0.0,
                                  plane_share=1.0)
    visible = torch.ones(data.tracks.shape[:2], dtype=torch.bool)
    background, x = data.labels == 0, data.tracks[0, :, 0]
    left = background & (x <= x[background].median())
    pairs = frame_pairs(visible)
    assert not has_parallax(plane_residuals(data.tracks, visible, left, pairs), epipolar_residuals(data.tracks, visible, left, pairs),
                            left, SegmentationConfig())
    sampson, _ = track_residuals(data.tracks, visible, left[None], pairs)
    assert float(sampson[0][background & ~left].median()) > SegmentationConfig().scene_tolerance
    excess = scene_excess(data.tracks, visible, left, pairs, SegmentationConfig(), torch.Generator().manual_seed(0))
    assert float(excess[background & ~left].nanmedian()) <= 1 < float(excess[data.labels == 1].nanmedian())


def test_a_scene_without_parallax_joins_only_what_its_homographies_explain():
    """The scene's excess of a scene without parallax is the lesser of F and homography; a
    motion whose median excess is within 1 joins it only if its median homography excess
    (``transfer``) is within 1 too. Without ``transfer`` (a scene with parallax), the excess
    alone decides."""
    from torchsfm.moving.scene import join_explained

    labels = torch.tensor([0, 0, 1, 1, 1, 2, 2, 2])
    excess = torch.tensor([0.1, 0.2, 0.5, 0.6, 0.7, 0.4, 0.5, 0.6], dtype=torch.float64)
    transfer = torch.tensor([0.3, 0.4, 0.8, 0.9, 3.0, 1.2, 1.5, 0.2], dtype=torch.float64)
    torch.testing.assert_close(join_explained(labels, excess, transfer), torch.tensor([0, 0, 0, 0, 0, 1, 1, 1]), rtol=0, atol=0)
    torch.testing.assert_close(join_explained(labels, excess), torch.zeros(8, dtype=torch.long), rtol=0, atol=0)


@pytest.mark.parametrize("name", ["1R2RCR", "1RT2RTCRT_B", "2RT3RCT_A"])
def test_a_body_near_the_degenerate_f_of_a_scene_without_parallax_stays_a_body(shared_data, name):
    """Hopkins155 checkerboard rooms, the first half of their frames (12-14): the background has
    no parallax there (1R2RCR: 0.10 px from one homography per frame pair), and a rotating
    object lies within the 1 px floor of the background's F fits — degenerate, any F compatible
    with the homographies fits — but not of its homographies (1R2RCR: 0.61 and 1.21 px). Judged by
    the lesser of the two, the object joined the scene (2 motions, 19-34 % misclassified); the
    homographies must explain a motion that joins such a scene, and the objects stay apart."""
    from torchsfm.io.datasets import read_hopkins155

    sequence = read_hopkins155(shared_data / "hopkins155_dev" / name)
    frames = sequence.tracks.shape[0] // 2
    found = segment_motions(sequence.tracks[:frames], generator=torch.Generator().manual_seed(0))
    assert found.num_motions == 3
    assert misclassification(found.labels, sequence.labels) <= 0.01


def test_a_flat_motion_joins_the_scene_only_where_its_homographies_explain_it(shared_data):
    """Hopkins155 three-cars, the first half of its frames (7; a static camera): a car that moves
    by one homography per frame pair (no parallax, not even beyond its noise) explained the car
    taken for the scene by its degenerate F fits (median excess 0.89) and joined it, though its
    homographies do not (1.77): one motion found, 53 % misclassified. It now stays a motion of its
    own."""
    from torchsfm.io.datasets import read_hopkins155

    sequence = read_hopkins155(shared_data / "hopkins155_dev" / "three-cars").cut("first-half")
    labels = segment_motions(sequence.tracks, generator=torch.Generator().manual_seed(0)).labels
    scene_motion = int(labels[sequence.labels == 1].mode().values)
    flat_car = labels[sequence.labels == 2]
    assert bool((flat_car == int(flat_car.mode().values)).all()) and int(flat_car.mode().values) != scene_motion


def _wall_tracks(relief: float, noise: float, generator: torch.Generator) -> torch.Tensor:
    """(20, 200, 2) pixels of 200 points on a wall 6 m away (depth spread ``relief`` m, normal)
    seen by a camera that slides 3 cm and turns 0.6° a frame, with Gaussian ``noise`` px."""
    points = torch.rand(200, 3, generator=generator, dtype=torch.float64) * torch.tensor([4.0, 3.0, 0.0]) - torch.tensor([2.0, 1.5, 0.0])
    points[:, 2] = 6 + relief * torch.randn(200, generator=generator, dtype=torch.float64)
    axis = torch.tensor([0.2, 1.0, 0.1], dtype=torch.float64)
    axis = axis / axis.norm()
    frames = []
    for f in range(20):
        R = axis_angle_to_rotation(axis * 0.01 * f)
        camera = points @ R.T + torch.tensor([0.03 * f, 0.005 * f, 0.0], dtype=torch.float64)
        pixels = 600 * camera[:, :2] / camera[:, 2:] + torch.tensor([320.0, 240.0], dtype=torch.float64)
        frames.append(pixels + noise * torch.randn(200, 2, generator=generator, dtype=torch.float64))
    return torch.stack(frames)


def _plane_and_epipolar(tracks: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """(N,) distances of all the (F, N, 2) tracks to their homographies and F fits, and the (N,) members."""
    from torchsfm.moving.pair_fits import epipolar_residuals, frame_pairs, plane_residuals

    visible = torch.ones(tracks.shape[:2], dtype=torch.bool)
    members = torch.ones(tracks.shape[1], dtype=torch.bool)
    pairs = frame_pairs(visible)
    return plane_residuals(tracks, visible, members, pairs), epipolar_residuals(tracks, visible, members, pairs), members


@pytest.mark.parametrize("noise", [0.1, 0.3, 0.6, 1.0])
def test_a_flat_wall_has_no_parallax_whatever_its_noise(noise):
    """A flat wall: noise alone puts its tracks about twice as far from its homographies as from
    its F fits (measured 2.09-2.11), and neither :func:`weak_parallax` nor :func:`has_parallax`
    says parallax — though at 0.6 and 1 px of noise the tracks are 1.2 and 2.0 px (median) from
    the homographies, beyond the 1 px floor."""
    from torchsfm.moving.scene import has_parallax, weak_parallax

    plane, epipolar, members = _plane_and_epipolar(_wall_tracks(0.0, noise, torch.Generator().manual_seed(0)))
    assert 1.8 < float(plane.median() / epipolar.median()) < 2.5
    assert not weak_parallax(plane, epipolar, members)
    assert not has_parallax(plane, epipolar, members, SegmentationConfig())


def test_parallax_without_an_f_fit_is_judged_by_the_floor():
    """Tracks 2 px (median) from their homographies whose F fits failed (NaN: too few tracks in
    every pair for 8 points): the noise is unknown, and beyond the 1 px floor is parallax."""
    from torchsfm.moving.scene import has_parallax

    members = torch.ones(20, dtype=torch.bool)
    plane, epipolar = torch.full((20,), 2.0, dtype=torch.float64), torch.full((20,), float("nan"), dtype=torch.float64)
    assert has_parallax(plane, epipolar, members, SegmentationConfig())
    assert not has_parallax(plane / 4, epipolar, members, SegmentationConfig())


@pytest.mark.parametrize("noise", [0.1, 0.6, 1.0])
def test_a_wall_with_relief_has_parallax_whatever_its_noise(noise):
    """A wall with 1 m of relief: its parallax (1.8 px from the homographies, median, at 0.1 px
    of noise) is found under noise of 0.6 and 1 px too, where the tracks' distance to the
    homographies is mostly noise."""
    from torchsfm.moving.scene import has_parallax

    plane, epipolar, members = _plane_and_epipolar(_wall_tracks(1.0, noise, torch.Generator().manual_seed(0)))
    assert has_parallax(plane, epipolar, members, SegmentationConfig())


def test_weak_parallax_is_parallax_beyond_the_tracks_own_noise():
    """A wall with 20 cm of relief at 0.1 px noise: 4.8 times as far from its homographies as from
    its F fits — parallax, although its distance to the homographies (0.46 px) is within the 1 px
    noise floor (:func:`has_parallax` says no)."""
    from torchsfm.moving.scene import has_parallax, weak_parallax

    generator = torch.Generator().manual_seed(0)
    _wall_tracks(0.0, 0.1, generator)  # the draws of the flat wall first, as measured
    plane, epipolar, members = _plane_and_epipolar(_wall_tracks(0.2, 0.1, generator))
    assert weak_parallax(plane, epipolar, members) and not has_parallax(plane, epipolar, members, SegmentationConfig())


@pytest.mark.parametrize("seed", [1, 2])
def test_a_room_split_into_its_planes_is_one_scene(shared_data, seed):
    """Hopkins155 2T3RCRT, a checkerboard room: the clustering cuts the background in two (221
    and 147 tracks at these seeds), each part within the 1 px noise floor of one homography per
    frame pair (0.61 and 0.68 px) but 3.5 and 4.5 times as far as from its F fits (weak
    parallax). Judged by the part's homographies and F fits alone, the other part stayed a
    motion of its own (4 motions, 27 % misclassified at both seeds); the part's projective
    reconstruction explains it, and the room is one scene."""
    pytest.importorskip("scipy")
    from torchsfm.io.datasets import read_hopkins155

    sequence = read_hopkins155(shared_data / "hopkins155_dev" / "2T3RCRT")
    found = segment_motions(sequence.tracks, generator=torch.Generator().manual_seed(seed))
    assert found.num_motions == 3
    assert misclassification(found.labels, sequence.labels) <= 0.01


@pytest.mark.parametrize("name", ["cars6", "kanatani1", "people1"])
def test_noise_is_not_taken_for_parallax(shared_data, name):
    """Hopkins155 sequences with 0.5 px of Gaussian noise added to every coordinate: their
    backgrounds lie about 1 px (median) from one homography per frame pair — noise, no more —
    where the noise-free tracks lie 0.1-0.2 px. Counted as parallax, the background was judged by
    its projective reconstruction, which a scene without depth does not determine, and cut into
    pieces (59-64 % misclassified on cars6 and kanatani1, 13 % on people1); the noise taken out,
    each background stays one motion."""
    from torchsfm.io.datasets import read_hopkins155

    sequence = read_hopkins155(next(p for root in ("hopkins155_subset", "hopkins155_dev")
                                    for p in [shared_data / root / name] if p.is_dir()))
    noisy = sequence.with_noise(0.5, seed=1000).tracks
    found = segment_motions(noisy, sequence.visible, generator=torch.Generator().manual_seed(0))
    assert found.num_motions == 2
    assert misclassification(found.labels, sequence.labels) <= 0.01


@pytest.mark.parametrize("slide, joined", [(0.0, [1]), (0.5, [])])
def test_pieces_of_one_plane_join_and_a_plane_sliding_over_it_does_not(slide, joined):
    """A flat wall at 0.5 px of noise, its right half a motion of its own: one homography per
    frame pair explains both halves as well as each alone, and the half joins the scene; slid
    0.5 px a frame further (10 px over the 20 frames, a poster moving on the wall), it does not."""
    from torchsfm.moving.pair_fits import frame_pairs, plane_residuals
    from torchsfm.moving.scene import one_plane_motions

    tracks = _wall_tracks(0.0, 0.5, torch.Generator().manual_seed(0))
    right = tracks[0, :, 0] > tracks[0, :, 0].median()
    tracks[:, right, 0] += slide * torch.arange(tracks.shape[0], dtype=tracks.dtype)[:, None]
    visible = torch.ones(tracks.shape[:2], dtype=torch.bool)
    pairs = frame_pairs(visible)
    labels = right.long()
    assert one_plane_motions(tracks, visible, labels, pairs, plane_residuals(tracks, visible, labels == 0, pairs)) == joined


def test_two_frames_join_no_motion_as_one_plane():
    """Two frames give one homography per set and 2 terms a track: no motion joins the scene by
    that test there, not even the other half of one wall."""
    from torchsfm.moving.pair_fits import frame_pairs, plane_residuals
    from torchsfm.moving.scene import one_plane_motions

    tracks = _wall_tracks(0.0, 0.5, torch.Generator().manual_seed(0))[[0, 10]]
    labels = (tracks[0, :, 0] > tracks[0, :, 0].median()).long()
    visible = torch.ones(tracks.shape[:2], dtype=torch.bool)
    pairs = frame_pairs(visible)
    assert one_plane_motions(tracks, visible, labels, pairs, plane_residuals(tracks, visible, labels == 0, pairs)) == []


@pytest.mark.parametrize("name", ["cars2B", "three-cars"])
def test_a_distant_background_cut_apart_under_noise_is_one_scene(shared_data, name):
    """Hopkins155 cars2B with 0.5 px of noise added: the clustering cuts its distant background
    into four pieces, and under that noise no piece's fit explains the others by extrapolation
    (5 motions, 32 % misclassified); the pieces move as one plane with the scene
    (:func:`~torchsfm.moving.scene.one_plane_motions`) and join it. three-cars, a static camera
    and cars moving 9-12 px over its 15 frames, keeps its cars apart under the same noise."""
    from torchsfm.io.datasets import read_hopkins155

    sequence = read_hopkins155(shared_data / "hopkins155_dev" / name)
    noisy = sequence.with_noise(0.5, seed=1000).tracks
    found = segment_motions(noisy, sequence.visible, generator=torch.Generator().manual_seed(0))
    assert found.num_motions == 3
    assert misclassification(found.labels, sequence.labels) <= 0.01


def test_a_scene_rechosen_keeps_the_cuts_only_where_it_was_cut_out_of_the_first():
    """:func:`rechosen_scene` on labels alone: a body cut out of the scene first chosen becomes the
    scene and the two labels swap (the cuts stand); a motion exactly as the clustering gave it
    becomes the scene and every other track goes back to its cluster, outliers staying out."""
    from torchsfm.moving.scene import rechosen_scene

    clusters = torch.tensor([0, 0, 0, 0, 1, 1, 2, -1])
    settled = torch.tensor([0, 0, 3, 3, 1, 1, 2, -1])  # two tracks of the first scene cut out as body 3
    torch.testing.assert_close(rechosen_scene(clusters, settled, 3), torch.tensor([3, 3, 0, 0, 1, 1, 2, -1]))
    clusters = torch.tensor([0, 0, 0, 0, 1, 1, 1, -1])
    settled = torch.tensor([0, 2, 2, -1, 1, 1, 1, -1])  # the first scene cut into body 2 and an outlier
    torch.testing.assert_close(rechosen_scene(clusters, settled, 1), torch.tensor([1, 1, 1, -1, 0, 0, 0, -1]))


def test_a_body_first_taken_for_the_scene_is_whole_again(shared_data, monkeypatch):
    """Hopkins155 cars10's two cars without the background (the two-motion sequence Hopkins155
    forms from them): the larger car (138 tracks) covers more of the image and is first taken
    for the scene, and settling cuts it where its ill-fitting reconstruction does not explain it.
    Where the cut leaves the other car (76) larger and covering more, that car is made the scene
    (:func:`~torchsfm.moving.scene.rechosen_scene`) and the first car's pieces go back to the
    motion the clustering gave them: at every seed 0-11 at which the scene is rechosen, the larger
    car is one motion again, but for the tracks settling left unassigned (-1) — stop 53 measured
    35.5 / 39.7 % misclassified at seeds 0 and 1 when the pieces stayed bodies. Whether the cut
    goes that far depends on the floating-point path (seeds 0 and 1 rechose the scene on stop
    53's machine; on an AVX-512 one, seeds 3, 6, 8 and 10 do, and at six of the others the first
    car stays the scene, cut in 2-4 pieces: README's known limit). At every seed the two cars
    share no motion."""
    pytest.importorskip("scipy")
    from torchsfm.io.datasets import read_hopkins155
    import torchsfm.moving.segmentation as segmentation
    from torchsfm.moving.scene import rechosen_scene

    sequence = read_hopkins155(shared_data / "hopkins155_dev" / "cars10")
    kept = sequence.labels != 0
    truth = sequence.labels[kept]
    larger = int(torch.bincount(truth).argmax())
    rechosen = []
    monkeypatch.setattr(segmentation, "rechosen_scene", lambda *args: rechosen.append(True) or rechosen_scene(*args))
    whole_again = 0
    for seed in range(12):
        rechosen.clear()
        labels = segment_motions(sequence.tracks[:, kept], generator=torch.Generator().manual_seed(seed)).labels
        for motion in labels[labels >= 0].unique():
            assert truth[labels == motion].unique().numel() == 1, f"seed {seed}: motion {int(motion)} mixes the two cars"
        if rechosen:
            assert labels[(truth == larger) & (labels >= 0)].unique().numel() == 1, f"seed {seed}: the larger car not whole again"
            whole_again += 1
    assert whole_again > 0, "the scene was never rechosen: the test checks nothing"


def test_pieces_are_split_along_unlinked_groups_of_tracks():
    """Two groups of 20 tracks linked within and not between (A: 0-19, B: 20-39), and two small
    groups (C: 40-42, D: 43-45). A piece of A's first 12, B's first 8 and C becomes two pieces,
    C going with the larger part (A's); a piece of the rest of A and B becomes two; D, a piece
    of its own without a group of 12 tracks, stays whole."""
    from torchsfm.moving.clustering import split_by_components

    affinity = torch.zeros(46, 46, dtype=torch.float64)
    for group in (slice(0, 20), slice(20, 40), slice(40, 43), slice(43, 46)):
        affinity[group, group] = 1.0
    affinity.fill_diagonal_(0.0)
    pieces = torch.tensor([0] * 12 + [1] * 8 + [0] * 8 + [1] * 12 + [0] * 3 + [2] * 3)
    expected = torch.tensor([0] * 12 + [2] * 8 + [1] * 8 + [3] * 12 + [0] * 3 + [4] * 3)
    torch.testing.assert_close(split_by_components(affinity, pieces, 12), expected, rtol=0, atol=0)


def test_two_objects_seen_by_a_still_camera_are_not_merged_through_one_piece():
    """A still camera and two objects of 60 tracks each (synthetic, 12 frames, seed 3): the
    affinity links no track of one object to the other's, but k-means put 14 and 16 of their
    tracks in one piece, and merging joined both objects through it — two motions found, 10.4 %
    misclassified. Split along the unlinked groups: three motions, none misclassified."""
    data = synthetic_moving_scene(3, num_frames=12, static_camera=True)
    found = segment_motions(data.tracks, generator=torch.Generator().manual_seed(0))
    assert found.num_motions == 3
    assert misclassification(found.labels, data.motion_labels(12)) <= 0.01


def test_kmeans_stops_at_its_fixed_point_with_the_labels_of_every_iteration(monkeypatch):
    """Five blobs of 2-D points, 10 restarts: k-means stops once every restart's labels repeat,
    well before the 30 iterations allowed, with exactly the labels of Lloyd's steps run to the
    end (written out here: the same draws, every iteration)."""
    from torchsfm.moving.clustering import kmeans

    g = torch.Generator().manual_seed(3)
    centres = 10 * torch.randn(5, 2, generator=g, dtype=torch.float64)
    points = (centres[:, None] + torch.randn(5, 40, 2, generator=g, dtype=torch.float64)).reshape(-1, 2)

    def lloyd(iterations: int) -> torch.Tensor:
        generator = torch.Generator().manual_seed(0)
        start = torch.rand(10, points.shape[0], generator=generator).argsort(1)[:, :5]
        means = points[start]
        for _ in range(iterations):
            labels = torch.cdist(points[None].expand(10, -1, -1), means).argmin(2)
            one_hot = torch.nn.functional.one_hot(labels, 5).to(points.dtype)
            counts = one_hot.sum(1)
            means = torch.where(counts[..., None] > 0, (one_hot.transpose(1, 2) @ points) / counts[..., None].clamp_min(1), means)
        labels = torch.cdist(points[None].expand(10, -1, -1), means).argmin(2)
        cost = (points[None] - means.gather(1, labels[..., None].expand(-1, -1, 2))).square().sum((1, 2))
        return labels[int(cost.argmin())]

    distances, cdist = [], torch.cdist

    def counted(*args, **kwargs):
        distances.append(1)
        return cdist(*args, **kwargs)

    monkeypatch.setattr(torch, "cdist", counted)
    found = kmeans(points, 5, 10, 30, torch.Generator().manual_seed(0))
    steps = len(distances)
    monkeypatch.undo()
    assert steps < 30
    assert torch.equal(found, lloyd(30))


def test_kmeans_of_a_spectral_embedding_does_not_depend_on_its_eigenvector_basis():
    """The embedding of three unlinked groups (each group's rows in a subspace of its own,
    orthogonal to the others', as the leading eigenvectors of three unlinked components put
    them), and the same rotated by a random orthogonal matrix — another basis of the same
    eigenspace, which another thread count or LAPACK may return. A point of one group is exactly
    √2 from every centre of the other groups: k-means must give the same labels for both
    bases, at every seed (ties go to the first centre, not to rounding)."""
    from torchsfm.moving.clustering import kmeans

    g = torch.Generator().manual_seed(0)
    blocks = []
    for group in range(3):
        rows = torch.zeros(60, 9, dtype=torch.float64)
        offset = torch.tensor([4.0, 0, 0], dtype=torch.float64)  # each group a cluster about one direction of its subspace
        rows[:, 3 * group:3 * group + 3] = torch.randn(60, 3, generator=g, dtype=torch.float64) + offset
        blocks.append(rows)
    points = torch.cat(blocks)
    points = points / points.norm(dim=1, keepdim=True)
    rotation, _ = torch.linalg.qr(torch.randn(9, 9, generator=g, dtype=torch.float64))
    for seed in range(10):
        assert torch.equal(kmeans(points, 6, 10, 30, torch.Generator().manual_seed(seed)),
                           kmeans(points @ rotation, 6, 10, 30, torch.Generator().manual_seed(seed))), f"seed {seed}"


def test_first_within_tie_takes_the_first_of_values_equal_to_rounding():
    from torchsfm.moving.clustering import first_within_tie

    values = torch.tensor([[2.0, 2 ** 0.5, 2 ** 0.5 * (1 - 1e-15), 1.5], [1.0, 0.5, 0.25, 0.25 + 1e-6]], dtype=torch.float64)
    assert first_within_tie(values).tolist() == [1, 2]


def test_adjusted_rand_index_is_one_for_the_same_partition_and_near_zero_for_unrelated_ones():
    from torchsfm.moving.segmentation import adjusted_rand_index

    labels = torch.tensor([0, 0, 0, 1, 1, 2, -1])
    assert adjusted_rand_index(labels, torch.tensor([7, 7, 7, 3, 3, 5, 9])) == pytest.approx(1.0, abs=1e-12)
    assert adjusted_rand_index(torch.zeros(5, dtype=torch.long), torch.full((5,), 3)) == 1.0
    # by hand: contingency table [[1, 1], [0, 2]]: 1 pair together in both, 2 and 3 in each alone,
    # 2 x 3 / 6 = 1 expected by chance, so (1 - 1) / ((2 + 3) / 2 - 1) = 0
    assert adjusted_rand_index(torch.tensor([0, 0, 1, 1]), torch.tensor([0, 1, 1, 1])) == pytest.approx(0.0, abs=1e-12)
    generator = torch.Generator().manual_seed(0)
    unrelated = [adjusted_rand_index(torch.randint(0, 3, (3000,), generator=generator), torch.randint(0, 4, (3000,), generator=generator))
                 for _ in range(5)]
    assert max(abs(value) for value in unrelated) < 0.01, unrelated


@pytest.mark.skipif(not (DATA / "kt3dmoseg_dev").is_dir(), reason="needs ../shared/data (KT3DMoSeg)")
def test_the_runs_are_outvoted_by_the_partition_most_of_them_agree_with():
    """``runs`` = 3 returns the medoid of the three runs one generator draws in turn (each as a
    call with the default ``runs`` = 1 on it): KT3DMoSeg Seq059_Clip01 at seed 4, whose first run leaves 19.6 % of
    the tracks misclassified, the second 0.4 % and the third 9.3 % (measured): the first is outvoted."""
    from torchsfm.moving.segmentation import adjusted_rand_index
    from torchsfm.io.datasets import read_kt3dmoseg

    sequence = read_kt3dmoseg(DATA / "kt3dmoseg_dev" / "Seq059_Clip01_Tracks")
    generator = torch.Generator().manual_seed(4)
    single = [segment_motions(sequence.tracks, sequence.visible, generator=generator).labels for _ in range(3)]
    agreement = [sum(adjusted_rand_index(a, b) for b in single if b is not a) for a in single]
    ensemble = segment_motions(sequence.tracks, sequence.visible, config=SegmentationConfig(runs=3), generator=torch.Generator().manual_seed(4))
    assert torch.equal(ensemble.labels, single[max(range(3), key=lambda r: (agreement[r], -r))])
    first, ours = misclassification(single[0], sequence.labels), misclassification(ensemble.labels, sequence.labels)
    assert first > 0.05 and ours < 0.01, (first, ours)


def test_a_static_scene_of_a_wall_and_free_points_stays_one_motion():
    """A static scene (a wall 20 m away and points 6-20 m deep; synthetic, seed 2, every object
    out of view) over 12 frames of a camera moving 0.5 m a frame: the clustering cuts the 122
    points off the wall from the 217 on it. The wall, a plane, has no parallax, and
    ``join_explaining`` took that for a camera that only turns — points at infinity, which any
    motion sharing its rotation explains — and asked nothing: the points stayed a motion of their
    own (32.4 % misclassified). No rotation explains how the wall moved, so the points' own
    reconstruction is asked, explains the wall, and they are one scene."""
    data = synthetic_moving_scene(2, num_frames=12)
    assert int(data.labels.max()) == 0
    found = segment_motions(data.tracks, generator=torch.Generator().manual_seed(0))
    assert found.num_motions == 1
    assert misclassification(found.labels, data.labels) <= 0.01


@pytest.mark.parametrize("seed", [0, 2, 3])
@pytest.mark.parametrize("static_camera", [False, True])
def test_a_wall_moves_as_a_turn_only_where_the_camera_did_not_move(seed, static_camera):
    """A wall 20 m away over 5 frames (0.3 px noise): a still camera sees it move by a rotation
    (the identity) as well as by its homographies; a camera that moved 0.5 m a frame does not
    (``turning_only`` compares their medians beyond the tracker's floor)."""
    from torchsfm.moving.pair_fits import frame_pairs, plane_residuals
    from torchsfm.moving.scene import turning_only

    data = synthetic_moving_scene(seed, num_frames=5, static_camera=static_camera)
    visible = torch.ones(data.tracks.shape[:2], dtype=torch.bool)
    wall = (data.labels == 0) & (data.points[:, 2] == 20)
    pairs = frame_pairs(visible)
    plane = plane_residuals(data.tracks, visible, wall, pairs)
    assert turning_only(data.tracks, visible, wall, pairs, plane, SegmentationConfig()) == static_camera


def test_rotation_residuals_vanish_for_a_camera_that_only_turns():
    """Noise-free points 5-30 m deep seen by a camera turning about its centre (0-6 degrees):
    every track is transferred exactly by K R K⁻¹ (float64, 1e-6 px); once the camera also moves
    1 m sideways, the near points are not (beyond 1 px)."""
    from torchsfm.camera import from_homogeneous
    from torchsfm.moving.pair_fits import frame_pairs
    from torchsfm.moving.scene import rotation_residuals

    generator = torch.Generator().manual_seed(0)
    points = _box(200, [-5, -4, 5], [5, 4, 30], generator)
    K = torch.tensor([[800.0, 0.0, 320.0], [0.0, 800.0, 240.0], [0.0, 0.0, 1.0]], dtype=torch.float64)
    turns = _yaw(torch.linspace(0, 0.1, 4, dtype=torch.float64))  # (4, 3, 3)
    everyone = torch.ones(200, dtype=torch.bool)
    visible = torch.ones(4, 200, dtype=torch.bool)
    pixels = from_homogeneous(points @ turns.transpose(-1, -2) @ K.T)
    residual = rotation_residuals(pixels, visible, everyone, frame_pairs(visible), K)
    torch.testing.assert_close(residual, torch.zeros_like(residual), rtol=0, atol=1e-6)
    shift = torch.tensor([1.0, 0.0, 0.0], dtype=torch.float64) * torch.arange(4, dtype=torch.float64)[:, None, None]
    moved = from_homogeneous((points @ turns.transpose(-1, -2) + shift) @ K.T)
    assert float(rotation_residuals(moved, visible, everyone, frame_pairs(visible), K).median()) > 1


@pytest.mark.parametrize("steady", [False, True])
def test_twelve_frame_synthetic_scenes_are_segmented_within_a_percent(steady):
    """Seeds 0-9 of the 12-frame synthetic scenes (a wall and free points, two objects stepping at
    random or at constant velocity, 10 % strays, 0.3 px noise; objects mostly out of view count
    as outliers): mean misclassification at most 1 % and every scene at most 5 % (measured 0.34
    and 0.35 %, worst 3.4 and 3.5 %; before the turning-only exception 22.9 and 10.1 %, worst
    35 %: the static scene split in two)."""
    errors = []
    for seed in range(10):
        data = synthetic_moving_scene(seed, num_frames=12, constant_velocity=steady)
        found = segment_motions(data.tracks, generator=torch.Generator().manual_seed(0))
        errors.append(misclassification(found.labels, data.motion_labels(12)))
    assert sum(errors) / len(errors) <= 0.01 and max(errors) <= 0.05


def test_motion_labels_count_small_motions_as_outliers():
    """Motions with fewer tracks than asked become outliers; the others are renumbered in order."""
    from torchsfm.testing.scenes import MovingObjectScene

    labels = torch.tensor([0, 0, 0, 1, 2, 2, 2, -1, 3, 3, 3])
    scene = MovingObjectScene(K=None, R=None, t=None, tracks=None, labels=labels, image_size=(1, 1), object_rotations=None,
                              object_centres=None, points=None)
    torch.testing.assert_close(scene.motion_labels(3), torch.tensor([0, 0, 0, -1, 1, 1, 1, -1, 2, 2, 2]), rtol=0, atol=0)
