import torch
from torch.testing import assert_close

from torchsfm.sfm.tracks import Tracks, build_tracks, chained_matches


def test_matches_chain_into_tracks_and_conflicts_are_dropped():
    # view 0 corner 0 - view 1 corner 2 - view 2 corner 1 ; view 0 corner 1 - view 1 corner 0 (a 2-view track)
    # conflict: view 0 corner 3 - view 1 corner 3 - view 2 corner 3, and view 2 corner 3 - view 0 corner 4 (two corners of view 0)
    matches = {
        (0, 1): (torch.tensor([0, 1, 3]), torch.tensor([2, 0, 3])),
        (1, 2): (torch.tensor([2, 3]), torch.tensor([1, 3])),
        (0, 2): (torch.tensor([4]), torch.tensor([3])),
    }
    tracks = build_tracks([5, 4, 4], matches)
    assert tracks.num_tracks == 2
    assert sorted(tracks.lengths().tolist()) == [2, 3]
    table = tracks.lookup(0, 5)
    assert table[0] >= 0 and table[1] >= 0 and table[0] != table[1]
    assert (table[[2, 3, 4]] == -1).all()  # corner 2 unmatched, corners 3 and 4 in the inconsistent component
    long_track = table[0]
    assert tracks.lookup(1, 4)[2] == long_track and tracks.lookup(2, 4)[1] == long_track


def test_only_matches_that_chain_over_three_views_are_kept():
    """Corner 0 of view 0 - corner 1 of view 1 - corner 2 of view 2 chains over three views and
    is kept in both its pairs; the two-view match (view 0 corner 3 - view 1 corner 0) and the
    lone match of pair (1, 2) are dropped, and a pair left empty is left out."""
    matches = {
        (0, 1): (torch.tensor([0, 3]), torch.tensor([1, 0])),
        (1, 2): (torch.tensor([1, 3]), torch.tensor([2, 0])),
        (0, 3): (torch.tensor([1]), torch.tensor([1])),
    }
    kept = chained_matches([4, 4, 4, 4], matches, min_views=3)
    assert sorted(kept) == [(0, 1), (1, 2)]
    assert kept[(0, 1)][0].tolist() == [0] and kept[(0, 1)][1].tolist() == [1]
    assert kept[(1, 2)][0].tolist() == [1] and kept[(1, 2)][1].tolist() == [2]
    assert chained_matches([4, 4, 4, 4], matches, min_views=2)[(0, 3)][0].tolist() == [1]


def test_no_matches_no_tracks():
    tracks = build_tracks([3, 3], {})
    assert tracks.num_tracks == 0 and tracks.view.numel() == 0


def test_covisibility_shared_corners_and_disparity_of_every_view_pair():
    """Three views, three tracks: track 0 in views 0, 1, 2; track 1 in views 0, 2; track 2 in
    views 1, 2. Corners move by known amounts, so the RMS displacements are known exactly."""
    from torchsfm.sfm.mapping import rms_disparity

    tracks = Tracks(view=torch.tensor([0, 1, 2, 0, 2, 1, 2]), corner=torch.tensor([0, 0, 0, 1, 1, 1, 2]),
                    track=torch.tensor([0, 0, 0, 1, 1, 2, 2]), num_tracks=3)
    corners = [torch.tensor([[0.0, 0.0], [10.0, 0.0]]), torch.tensor([[3.0, 4.0], [5.0, 5.0]]),
               torch.tensor([[6.0, 8.0], [10.0, 1.0], [5.0, 5.0]])]
    counts = tracks.covisibility(3)
    assert counts.tolist() == [[0, 1, 2], [1, 0, 2], [2, 2, 0]]
    corner0, corner2 = tracks.shared(0, 2)
    assert corner0.tolist() == [0, 1] and corner2.tolist() == [0, 1]
    disparity = rms_disparity(tracks, tracks.gather(corners).double(), 3, counts)
    expected = torch.tensor([[0.0, 5.0, ((100 + 1) / 2) ** 0.5], [5.0, 0.0, ((25 + 0) / 2) ** 0.5], [0.0, 0.0, 0.0]], dtype=torch.float64)
    expected[2, :2] = expected[:2, 2]
    assert_close(disparity, expected, rtol=0, atol=1e-9)


def test_observations_are_read_by_view_and_by_track():
    """``of_view`` gives each view's observations in ascending order (as ``view == v`` would,
    empty for a view without any), ``observations_of`` every observation of the named tracks,
    track by track in the order asked, with the position of its track."""
    tracks = Tracks(view=torch.tensor([0, 1, 2, 0, 2, 1, 2, 3]), corner=torch.tensor([0, 0, 0, 1, 1, 1, 2, 0]),
                    track=torch.tensor([0, 0, 0, 1, 1, 2, 2, 2]), num_tracks=3)
    for view in range(6):
        assert tracks.of_view(view).tolist() == torch.nonzero(tracks.view == view).flatten().tolist()
    members, owner = tracks.observations_of(torch.tensor([2, 0]))
    assert members.tolist() == [5, 6, 7, 0, 1, 2] and owner.tolist() == [0, 0, 0, 1, 1, 1]
    members, owner = tracks.observations_of(torch.tensor([], dtype=torch.long))
    assert members.numel() == 0 and owner.numel() == 0
