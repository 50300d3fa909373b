"""Reconstruction from tracks: the static scene against the true cameras, and one model per
rigid motion of a synthetic scene with two moving boxes."""

import pytest
import torch

from torchsfm.errors import NotEnoughDataError, ShapeError
from torchsfm.evaluation import camera_errors
from torchsfm.sfm.from_tracks import frame_pairs, reconstruct_motions, reconstruct_tracks
from torchsfm.testing import synthetic_moving_scene


def test_frame_pairs_have_near_and_far_partners():
    assert frame_pairs(5) == [(0, 1), (1, 2), (2, 3), (3, 4), (0, 2), (1, 3), (2, 4), (0, 4)]


def test_static_tracks_with_gaps_give_the_true_cameras():
    """Background tracks of a 5-frame scene (0.3 px noise), a fifth of them hidden in one frame:
    every frame registered, rotation within 0.1 deg and centres within 1 % of the path."""
    scene = synthetic_moving_scene(0, num_frames=5, num_objects=0)
    static = scene.tracks[:, scene.labels == 0]
    visible = torch.ones(static.shape[:2], dtype=torch.bool)
    visible[2, ::5] = False
    model = reconstruct_tracks(torch.where(visible[..., None], static, float("nan")), scene.K, visible)
    assert model.view_indices == [0, 1, 2, 3, 4]
    errors = camera_errors(model.cameras.R, model.cameras.t, scene.R, scene.t)
    assert float(errors.rotation.max()) < 0.1 and float(errors.centre.max()) / errors.extent < 0.01
    assert model.reprojection_rms() < 0.6


def test_each_moving_box_becomes_its_own_model():
    """Two boxes moving independently of the camera over 4 frames, with 10 % outlier tracks:
    the static model has the true cameras; each box is a model of its own over every frame whose
    points are (95 %) that box's tracks — the segmentation's strays do not fit its motion — and
    reproject at the noise level."""
    scene = synthetic_moving_scene(1, num_frames=4, num_objects=2, object_points=80)
    result = reconstruct_motions(scene.tracks, scene.K, generator=torch.Generator().manual_seed(0))
    assert result.segmentation.num_motions == 3 and not result.failed
    static = result.models[0]
    errors = camera_errors(static.cameras.R, static.cameras.t, scene.R[static.view_indices], scene.t[static.view_indices])
    assert static.view_indices == [0, 1, 2, 3]
    assert float(errors.rotation.max()) < 0.1 and float(errors.centre.max()) / errors.extent < 0.01
    found = set()
    for label in (1, 2):
        model = result.models[label]
        truth = torch.bincount(scene.labels[model.point_tracks] + 1, minlength=4)  # outliers, static, box 1, box 2
        box = int(truth[2:].argmax()) + 1
        found.add(box)
        assert model.view_indices == [0, 1, 2, 3]
        assert int(truth[box + 1]) >= 0.95 * model.num_points and model.num_points >= 60
        assert model.reprojection_rms() < 0.6
    assert found == {1, 2}


def test_bad_input_is_named():
    with pytest.raises(ShapeError, match="tracks must be an"):
        reconstruct_tracks(torch.zeros(3, 10), torch.eye(3))
    scene = synthetic_moving_scene(0, num_frames=3, num_objects=0, background_points=20)
    with pytest.raises(NotEnoughDataError, match="no frame pair shares 30 tracks"):
        reconstruct_tracks(scene.tracks, scene.K)
