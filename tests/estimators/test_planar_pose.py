"""Relative pose of two views of a plane from its homography: the twin motion and its rejection."""

import pytest
import torch
from torch.testing import assert_close

from torchsfm.config import Config
from torchsfm.errors import DegenerateConfigurationError
from torchsfm.estimators.planar_pose import choose_by_normal, planar_poses
from torchsfm.testing import sliding_plane_scene


def test_the_twin_motion_is_rejected_by_the_other_pairs_planes():
    """Frames 0-1 of a camera sliding along a plane, the points off the optical axis: both
    decompositions put every point in front, the false twin first. The plane of pairs 0-2 and 0-3
    picks the true motion: R = I, t along the slide, n = (0, 0, 1), to 1e-9 without noise."""
    tracks, K, R, t = sliding_plane_scene(0.0)
    generator = torch.Generator().manual_seed(0)
    poses = planar_poses(tracks[0], tracks[1], K, K, config=Config(), generator=generator)
    assert len(poses) == 2 and all(int(pose.inlier_mask.sum()) == 80 for pose in poses)
    normal = torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64)
    assert float((poses[0].normal - normal).norm()) > 0.5  # the twin comes first: the points do not tell them apart
    others = [torch.stack([pose.normal for pose in planar_poses(tracks[0], tracks[k], K, K, config=Config(), generator=generator)])
              for k in (2, 3)]
    chosen = choose_by_normal(poses, others)
    assert_close(chosen.normal, normal, rtol=0, atol=1e-9)
    assert_close(chosen.R, torch.eye(3, dtype=torch.float64), rtol=0, atol=1e-9)
    assert_close(chosen.t, (t[1] - t[0]) / (t[1] - t[0]).norm(), rtol=0, atol=1e-9)


def test_a_camera_that_only_turns_does_not_start_a_model():
    """The homography of a camera turning 5.7 deg in place: its motions triangulate with no angle,
    and the mapper's planar start refuses the pair, saying so."""
    from torchsfm.sfm.mapping import planar_initial_pair
    from torchsfm.sfm.view_pairs import PairMatches

    tracks, K, _, _ = sliding_plane_scene(0.0)
    turned = torch.linalg.matrix_exp(torch.tensor([[0.0, 0.0, 0.1], [0.0, 0.0, 0.0], [-0.1, 0.0, 0.0]], dtype=torch.float64))
    mapped = torch.cat([tracks[0], torch.ones(80, 1, dtype=torch.float64)], -1) @ (K @ turned @ torch.linalg.inv(K)).T
    every = torch.arange(80)
    pairs = {(0, 1): PairMatches(every, every, 1.0, torch.zeros(3, 3, dtype=torch.float64))}
    with pytest.raises(DegenerateConfigurationError, match="0-1: .*(triangulation angle|in front)"):
        planar_initial_pair(pairs, [tracks[0], mapped[:, :2] / mapped[:, 2:]], K.expand(2, 3, 3), Config(), torch.Generator().manual_seed(0))
