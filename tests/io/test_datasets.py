import pytest
import torch
from torch.testing import assert_close

from torchsfm.camera import project
from torchsfm.errors import InputError
from torchsfm.io.datasets import read_oxford_multiview


@pytest.mark.parametrize("name, views, points", [("oxford_house", 10, 672), ("oxford_merton1", 3, 717)])
def test_oxford_reader_matches_the_provenance(shared_data, name, views, points):
    dataset = read_oxford_multiview(shared_data / name)
    assert dataset.num_views == views and dataset.points3d.shape == (points, 3)
    assert dataset.tracks.shape == (points, views)
    errors = []
    for v in range(views):
        seen = dataset.tracks[:, v] >= 0
        reprojected = project(dataset.P[v], dataset.points3d[seen])
        errors.append((reprojected - dataset.corners[v][dataset.tracks[seen, v]]).norm(dim=-1))
    median = torch.cat(errors).median().item()
    assert median < 0.3  # PROVENANCE: 0.264 px (house), 0.125 px (Merton)


def test_relative_pose_is_a_proper_rotation(shared_data):
    dataset = read_oxford_multiview(shared_data / "oxford_house")
    R, t = dataset.relative_pose(0, 1)
    assert_close(torch.linalg.det(R), torch.tensor(1.0, dtype=torch.float64))
    assert_close(t.norm(), torch.tensor(1.0, dtype=torch.float64))


def test_not_a_dataset_folder(tmp_path):
    with pytest.raises(InputError, match="not an Oxford VGG multi-view folder"):
        read_oxford_multiview(tmp_path)


@pytest.mark.parametrize("root, name, background", [
    ("hopkins155_subset", "cars1", 230), ("hopkins155_subset", "truck1", 83), ("hopkins155_subset", "kanatani1", 117),
    ("hopkins155_dev", "cars8", 110),
])
def test_hopkins155_background_is_the_group_checked_on_the_preview(shared_data, root, name, background):
    """Label 0 is the static background, by the groups checked with the tracks overlaid on each
    preview.jpg (``HOPKINS_BACKGROUND_GROUP``): for cars8 that is group 1 (110 tracks on the trees
    and the traffic light in frame 0, y up), not the highest label (82 tracks on the crossing SUV)."""
    pytest.importorskip("scipy")
    from torchsfm.io.datasets import read_hopkins155

    sequence = read_hopkins155(shared_data / root / name)
    assert int((sequence.labels == 0).sum()) == background


def test_noise_is_added_where_the_tracks_are_seen_only_and_repeats_with_its_seed():
    """``MotionTracks.with_noise``: Gaussian noise of the given σ (sample standard deviation
    within 5 % over 20 000 coordinates) on the visible positions; the unseen ones keep their
    stored value; the same seed, the same noise; the sequence itself unchanged."""
    from torchsfm.io.datasets import MotionTracks

    tracks = torch.rand(10, 1000, 2, generator=torch.Generator().manual_seed(0), dtype=torch.float64) * 640
    visible = torch.rand(10, 1000, generator=torch.Generator().manual_seed(1)) > 0.1
    tracks[~visible] = 0.0
    sequence = MotionTracks(name="s", tracks=tracks.clone(), labels=torch.zeros(1000, dtype=torch.long), image_size=(640, 480),
                            visible=visible)
    noisy = sequence.with_noise(0.5, seed=3)
    difference = noisy.tracks - tracks
    assert_close(difference[~visible], torch.zeros_like(difference[~visible]), rtol=0, atol=0)
    assert abs(float(difference[visible].std()) / 0.5 - 1) < 0.05
    assert_close(sequence.with_noise(0.5, seed=3).tracks, noisy.tracks, rtol=0, atol=0)
    assert_close(sequence.tracks, tracks, rtol=0, atol=0)
    assert noisy.labels is sequence.labels and noisy.visible is sequence.visible


def test_a_sequence_on_some_frames_keeps_the_tracks_seen_in_three_of_them():
    """``MotionTracks.on_frames``: the tracks, labels and visibility of the frames given (in
    their order), without the tracks seen in fewer than ``min_seen`` of them."""
    from torchsfm.io.datasets import MotionTracks

    tracks = torch.arange(6 * 4 * 2, dtype=torch.float64).reshape(6, 4, 2)
    visible = torch.ones(6, 4, dtype=torch.bool)
    visible[:, 1] = torch.tensor([True, False, True, False, False, True])  # seen in 2 of frames 0, 2, 4
    visible[:, 3] = torch.tensor([False, True, False, True, False, True])  # seen in none of them
    sequence = MotionTracks(name="s", tracks=tracks, labels=torch.tensor([0, 1, 2, 3]), image_size=(640, 480), visible=visible)
    cut = sequence.on_frames(torch.tensor([0, 2, 4]))
    assert_close(cut.tracks, tracks[[0, 2, 4]][:, [0, 2]], rtol=0, atol=0)
    assert_close(cut.labels, torch.tensor([0, 2]), rtol=0, atol=0)
    assert cut.visible.shape == (3, 2) and bool(cut.visible.all())
    assert_close(sequence.on_frames(torch.tensor([0, 2, 4]), min_seen=2).labels, torch.tensor([0, 1, 2]), rtol=0, atol=0)


def test_named_frame_cuts_keep_the_first_half_or_every_other_frame_and_two_views_whole():
    """``MotionTracks.cut``: ``first-half`` keeps frames 0..F//2-1 (at least 3), ``every-other``
    the even ones, ``all`` the sequence itself; two views stay as they are; another name, or a
    cut that leaves fewer than 3 frames, is an InputError."""
    from torchsfm.errors import InputError
    from torchsfm.io.datasets import MotionTracks

    tracks = torch.arange(10 * 5 * 2, dtype=torch.float64).reshape(10, 5, 2)
    sequence = MotionTracks(name="s", tracks=tracks, labels=torch.zeros(5, dtype=torch.long), image_size=(640, 480))
    assert_close(sequence.cut("first-half").tracks, tracks[:5], rtol=0, atol=0)
    assert_close(sequence.cut("every-other").tracks, tracks[::2], rtol=0, atol=0)
    assert sequence.cut("all") is sequence
    assert sequence.on_frames(torch.tensor([0, 1, 2, 3])).cut("first-half").tracks.shape[0] == 3
    two_views = sequence.on_frames(torch.tensor([0, 9]), min_seen=2)
    assert two_views.cut("every-other") is two_views
    with pytest.raises(InputError, match="first-half"):
        sequence.cut("last-half")
    with pytest.raises(InputError, match="fewer than 3"):
        sequence.on_frames(torch.tensor([0, 1, 2, 3])).cut("every-other")


def test_a_subset_keeps_a_seeded_share_of_the_tracks_with_their_labels_and_visibility():
    """``MotionTracks.subset``: each track kept with the probability given (4 000 tracks: the
    share kept within 3 % of it), its positions, label and visibility together; the same seed, the
    same tracks, another seed, others; a share outside (0, 1] is an InputError."""
    from torchsfm.errors import InputError
    from torchsfm.io.datasets import MotionTracks

    N = 4000
    tracks = torch.arange(3 * N * 2, dtype=torch.float64).reshape(3, N, 2)
    visible = torch.rand(3, N, generator=torch.Generator().manual_seed(1)) > 0.2
    sequence = MotionTracks(name="s", tracks=tracks, labels=torch.arange(N), image_size=(640, 480), visible=visible)
    half = sequence.subset(0.5, seed=7)
    assert abs(half.labels.numel() / N - 0.5) < 0.03
    assert_close(half.tracks, tracks[:, half.labels], rtol=0, atol=0)  # labels are the track indices here
    assert_close(half.visible, visible[:, half.labels], rtol=0, atol=0)
    assert_close(sequence.subset(0.5, seed=7).labels, half.labels, rtol=0, atol=0)
    assert not torch.equal(sequence.subset(0.5, seed=8).labels, half.labels)
    assert sequence.subset(1.0).labels.numel() == N
    for share in (0.0, 1.5):
        with pytest.raises(InputError, match="share"):
            sequence.subset(share)
