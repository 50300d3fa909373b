"""The mapper's bundle adjustments on a synthetic sequence: full and local (a window of views)."""

import torch
from torch.testing import assert_close

from torchsfm.camera import project, projection_matrix
from torchsfm.config import Config, with_overrides
from torchsfm.geometry.rotation import axis_angle_to_rotation
import torchsfm.sfm.mapping as mapping
from torchsfm.robust.ransac import required_trials
from torchsfm.sfm.mapping import MapperState, bundle, resect
from torchsfm.sfm.tracks import Tracks
from torchsfm.testing import look_at_rotation


def sequence(num_views: int = 6, num_points: int = 300, seed: int = 0, noise: float = 0.0):
    """Cameras on a line looking at a cloud of points, every point seen in every view; pixels with
    ``noise`` px (standard deviation). Returns the true R (V, 3, 3), t (V, 3), points (N, 3), K and the mapper state."""
    generator = torch.Generator().manual_seed(seed)
    K = torch.tensor([[500.0, 0, 320], [0, 500.0, 240], [0, 0, 1]], dtype=torch.float64)
    points = torch.rand(num_points, 3, generator=generator, dtype=torch.float64) * torch.tensor([4.0, 3.0, 2.0]) + torch.tensor([-2.0, -1.5, 5.0])
    centres = torch.stack([torch.tensor([0.3 * v, 0.0, 0.0], dtype=torch.float64) for v in range(num_views)])
    R = torch.stack([look_at_rotation(c, torch.tensor([0.0, 0.0, 6.0], dtype=torch.float64)) for c in centres])
    t = -(R @ centres[..., None])[..., 0]
    corners = [project(projection_matrix(K, R[v], t[v]), points) + noise * torch.randn(num_points, 2, generator=generator, dtype=torch.float64)
               for v in range(num_views)]
    track = torch.arange(num_points).repeat_interleave(num_views)
    view = torch.arange(num_views).repeat(num_points)
    tracks = Tracks(view=view, corner=track.clone(), track=track, num_tracks=num_points)
    config = Config()
    state = MapperState(tracks, corners, corners, K.expand(num_views, 3, 3), config)
    state.R, state.t, state.points = R.clone(), t.clone(), points.clone()
    state.registered[:] = True
    state.has_point[:] = True
    return R, t, points, state, config


def test_a_local_adjustment_moves_only_the_window_and_recovers_it_exactly():
    """Noise-free pixels, the three newest poses disturbed (about 0.2 deg and 1 cm: reprojection
    errors within the 2 px inlier gate): the local adjustment of those three leaves the others
    bit for bit and recovers the three exactly."""
    R, t, points, state, config = sequence()
    generator = torch.Generator().manual_seed(1)
    for v in (3, 4, 5):
        state.R[v] = axis_angle_to_rotation(torch.randn(3, generator=generator, dtype=torch.float64) * 0.002) @ R[v]
        state.t[v] = t[v] + 0.006 * torch.randn(3, generator=generator, dtype=torch.float64)
    bundle(state, config, 0, free_views=torch.tensor([False, False, False, True, True, True]))
    assert_close(state.R[:3], R[:3], rtol=0, atol=0)
    assert_close(state.t[:3], t[:3], rtol=0, atol=0)
    assert_close(state.R[3:], R[3:], rtol=0, atol=1e-8)
    assert_close(state.t[3:], t[3:], rtol=0, atol=1e-8)
    assert_close(state.points, points, rtol=0, atol=1e-7)


def test_a_local_adjustment_reaches_the_noise_limited_optimum():
    """0.3 px noise: from the disturbed poses, two local adjustments (the mapper adjusts again
    as views arrive) end where the same adjustment started from the true poses ends (0.001 deg
    and 0.1 mm), so the window's accuracy is the data's, not the start's."""
    free = torch.tensor([False, False, False, True, True, True])
    _, _, _, reference, config = sequence(noise=0.3)
    bundle(reference, config, 0, free_views=free)
    R, t, _, state, _ = sequence(noise=0.3)
    generator = torch.Generator().manual_seed(1)
    for v in (3, 4, 5):
        state.R[v] = axis_angle_to_rotation(torch.randn(3, generator=generator, dtype=torch.float64) * 0.002) @ R[v]
        state.t[v] = t[v] + 0.006 * torch.randn(3, generator=generator, dtype=torch.float64)
    for _ in range(2):
        bundle(state, config, 0, free_views=free)
    assert_close(state.R, reference.R, rtol=0, atol=2e-5)
    assert_close(state.t, reference.t, rtol=0, atol=1e-4)


def test_a_resection_that_keeps_too_few_inliers_widens_its_threshold_and_says_so():
    """Points whose errors in the new view are 3 px in random directions (a forward step
    extrapolating their depth errors): no pose brings 50 of the 60 within the 2 px threshold, the
    true one brings all within 4 px, so the pose comes at 4 px; with every pixel scrambled no
    threshold up to 8 px finds 50 inliers, and the reason names it."""
    R, t, points, state, _ = sequence(num_views=2, num_points=60)
    config = with_overrides(Config(), ["reconstruction.min_resection_inliers=50"])
    generator = torch.Generator().manual_seed(1)
    pixels = state.corners[1]
    direction = torch.nn.functional.normalize(torch.randn(60, 2, generator=generator, dtype=torch.float64), dim=-1)
    pose, threshold = resect(points, pixels + 3.0 * direction, state.K[1], config, generator)
    assert threshold == 4.0
    assert int(pose.inlier_mask.sum()) >= 50
    assert_close(pose.R, R[1], atol=0.02, rtol=0)  # 3 px on 60 points: the pose within about a degree
    scrambled = pixels[torch.randperm(60, generator=generator)]
    reason = resect(points, scrambled, state.K[1], config, generator)
    assert isinstance(reason, str) and "within 8 px (needs 50)" in reason


def test_a_resection_draws_only_what_a_usable_pose_takes(monkeypatch):
    """Scrambled pixels (no pose fits): each rung of the threshold ladder stops after the samples
    that would have found a pose with ``min_resection_inliers`` (20) of the 60 points at the
    RANSAC confidence — eq. 3.3.7 at the ratio 1/3 — not after ``max_trials``."""
    _, _, points, state, config = sequence(num_views=2, num_points=60)
    drawn, estimate = [], mapping.estimate_absolute_pose

    def counted(*args, **kwargs):
        pose = estimate(*args, **kwargs)
        drawn.append(int(pose.num_trials))
        return pose

    monkeypatch.setattr(mapping, "estimate_absolute_pose", counted)
    generator = torch.Generator().manual_seed(2)
    scrambled = state.corners[1][torch.randperm(60, generator=generator)]
    assert isinstance(resect(points, scrambled, state.K[1], config, generator), str)
    expected = int(required_trials(torch.tensor([20 / 60]), 3, config.resection.ransac.confidence, config.resection.ransac.max_trials)[0])
    assert drawn == [expected] * 3  # 2, 4 and 8 px


def test_the_parallax_screen_measures_the_triangulation_angle_from_F():
    """From the true F of two noise-free views (and of the same pair with its views swapped), the
    screen's median angle is the median triangulation angle of the true points to 1e-6 degrees."""
    from torchsfm.geometry.fundamental import fundamental_from_pose
    from torchsfm.sfm.mapping import parallax_angles, triangulation_angle
    from torchsfm.sfm.view_pairs import PairMatches
    from torchsfm.testing import synthetic_two_view

    scene = synthetic_two_view(80, seed=3)
    F = fundamental_from_pose(scene.K1, scene.K2, scene.R, scene.t)
    index = torch.arange(80)
    matches = [PairMatches(index, index, 0.0, F), PairMatches(index, index, 0.0, F.T)]
    angles = parallax_angles(matches, [(0, 1), (1, 0)], [scene.x1_true, scene.x2_true], torch.stack([scene.K1, scene.K2]))
    truth = triangulation_angle(scene.points3d, torch.zeros(3, dtype=torch.float64), -scene.R.T @ scene.t).median()
    assert_close(angles, truth.expand(2), rtol=0, atol=1e-6)


def test_a_view_with_too_few_points_is_posed_from_its_verified_pair_and_scaled_by_them():
    """View 2 sees only 5 of the model's points (too few to resect) but has a verified pair
    with view 1 over every point: its pose comes from the pair's relative pose, the length of
    the translation from those 5 points — exactly, on noise-free pixels. With the 5 points moved
    the pose is refused and the reason says how many agree."""
    from torchsfm.sfm.mapping import pose_from_pair
    from torchsfm.sfm.view_pairs import PairMatches

    R, t, points, state, config = sequence(num_views=3)
    state.registered[2] = False
    state.has_point[5:] = False  # view 2 sees 5 reconstructed points
    everything = torch.arange(points.shape[0])
    pairs = {(1, 2): PairMatches(index1=everything, index2=everything, homography_ratio=0.0, F=torch.eye(3, dtype=torch.float64))}
    R2, t2, done = pose_from_pair(state, pairs, 2, config, torch.Generator().manual_seed(0))
    assert_close(R2, R[2], rtol=0, atol=1e-9)
    assert_close(t2, t[2], rtol=0, atol=1e-9)
    assert "pair with view 1" in done and "5 of its 5" in done
    state.points[:5] += torch.tensor([0.5, 0.0, 0.0], dtype=torch.float64) * torch.arange(1, 6)[:, None]  # each off by another amount
    assert "agrees with only" in pose_from_pair(state, pairs, 2, config, torch.Generator().manual_seed(0))
    assert pose_from_pair(state, {}, 2, config, torch.Generator().manual_seed(0)) == "no verified pair with a registered view"


def test_a_pair_pose_whose_length_no_point_fixes_is_refused():
    """Forward motion: cameras 1 m apart along their optical axis, the 5 reconstructed points view
    2 sees 20-40 m ahead within 1 m of the axis (near the epipole; the pair's other 35 matches,
    4-8 m ahead and wider, give its pose parallax). Every reconstructed point agrees with the
    pair's pose whatever the translation's length (10 % of it moves them by 0.1 px at most,
    under the 2 px threshold), so the pose is refused and the reason says that no point fixes
    the length."""
    from torchsfm.sfm.mapping import pose_from_pair
    from torchsfm.sfm.view_pairs import PairMatches

    generator = torch.Generator().manual_seed(0)
    K = torch.tensor([[500.0, 0, 320], [0, 500.0, 240], [0, 0, 1]], dtype=torch.float64)
    points = torch.cat([torch.rand(40, 2, generator=generator, dtype=torch.float64) * 2 - 1,
                        20 + 20 * torch.rand(40, 1, generator=generator, dtype=torch.float64)], -1)
    points[5:, :2] *= 3
    points[5:, 2] = 4 + 4 * torch.rand(35, generator=generator, dtype=torch.float64)
    R = torch.eye(3, dtype=torch.float64).expand(3, 3, 3).clone()
    t = torch.tensor([[0.0, 0.0, 0.0], [0.0, 0.0, -1.0], [0.0, 0.0, -2.0]], dtype=torch.float64)
    corners = [project(projection_matrix(K, R[v], t[v]), points) for v in range(3)]
    track = torch.arange(40).repeat_interleave(3)
    tracks = Tracks(view=torch.arange(3).repeat(40), corner=track.clone(), track=track, num_tracks=40)
    state = MapperState(tracks, corners, corners, K.expand(3, 3, 3), Config())
    state.R, state.t, state.points = R.clone(), t.clone(), points.clone()
    state.registered[:2] = True
    state.has_point[:5] = True
    everything = torch.arange(40)
    pairs = {(1, 2): PairMatches(index1=everything, index2=everything, homography_ratio=0.0, F=torch.eye(3, dtype=torch.float64))}
    reason = pose_from_pair(state, pairs, 2, Config(), torch.Generator().manual_seed(0))
    assert isinstance(reason, str) and "agrees with only 0 of the 0 reconstructed points that fix the length" in reason, reason


def test_a_loose_resection_that_its_verified_pair_contradicts_is_refused():
    """A pose from a resection at a widened threshold (8 px) stands only if the epipolar
    geometry of it and its partner fits most of their verified matches: the true pose of view 2
    fits all 300 (noise-free), one tilted by 3 degrees (across the epipolar lines) fits none, and the
    reason says so."""
    from torchsfm.sfm.mapping import pair_disagreement
    from torchsfm.sfm.view_pairs import PairMatches

    R, t, points, state, _ = sequence(num_views=3)
    state.registered[2] = False
    everything = torch.arange(points.shape[0])
    pairs = {(1, 2): PairMatches(index1=everything, index2=everything, homography_ratio=0.0, F=torch.eye(3, dtype=torch.float64))}
    assert pair_disagreement(state, pairs, 2, R[2], t[2], 8.0) is None
    turned = axis_angle_to_rotation(torch.tensor([3.0, 0.0, 0.0], dtype=torch.float64) * torch.pi / 180) @ R[2]
    reason = pair_disagreement(state, pairs, 2, turned, t[2], 8.0)
    assert reason == "its resection at 8 px disagrees with its verified pair with view 1: 0 of the pair's 300 matches fit the two poses"
    assert pair_disagreement(state, {}, 2, turned, t[2], 8.0) is None  # no pair to check against


def test_still_frames_are_measured_against_their_keyframe_so_a_slow_drift_starts_a_new_one():
    """Six frames of 100 tracks shifted by 0, 0.1, 0.2, 0.35, 0.55, 0.72 px: frames 1-3 stay
    within half a pixel of frame 0 (still); frame 4 has drifted 0.55 px from it and is the next
    keyframe, frame 5 is 0.17 px from frame 4 (still). Sharing only 10 tracks with frame 0 (too
    few to resect from), frame 1 is a keyframe, and so is frame 2, which shares as few with it;
    3 and 4 are then still against 2, and 5, 0.52 px from 2, is not. When every frame is still,
    none is left out (one keyframe cannot start a model)."""
    from torchsfm.sfm.mapping import still_frames

    generator = torch.Generator().manual_seed(0)
    base = torch.rand(100, 2, generator=generator, dtype=torch.float64) * 600
    shifts = [0.0, 0.1, 0.2, 0.35, 0.55, 0.72]
    corners = [base + torch.tensor([shift, 0.0], dtype=torch.float64) for shift in shifts]
    track = torch.arange(100).repeat_interleave(6)
    tracks = Tracks(view=torch.arange(6).repeat(100), corner=track.clone(), track=track, num_tracks=100)
    assert still_frames(tracks, corners, Config()) == {1: 0, 2: 0, 3: 0, 5: 4}

    seen = (tracks.view != 1) | (tracks.track < 10)  # frame 1 sees 10 of the tracks
    sparse = Tracks(view=tracks.view[seen], corner=tracks.corner[seen], track=tracks.track[seen], num_tracks=100)
    assert still_frames(sparse, corners, Config()) == {3: 2, 4: 2}

    assert still_frames(tracks, [base] * 6, Config()) == {}
