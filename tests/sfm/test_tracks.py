import torch

from torchsfm.sfm.tracks import build_tracks


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


def test_no_matches_no_tracks():
    tracks = build_tracks([3, 3], {})
    assert tracks.num_tracks == 0 and tracks.view.numel() == 0
