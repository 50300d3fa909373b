"""Whole-track moving-object rejection and motion segmentation: seconds on 20-frame sequences.

A seeded synthetic scene (640×480, f = 800 px): 900 static points 8–20 m deep (400 for the
segmentation's 500-track case), a camera moving 0.1 m and turning 0.2° per frame, two 2 m objects
of 50 points each taking a new random step and turn every frame, 0.3 px noise. Each
``track_method`` of :func:`torchsfm.reject_moving_objects_in_tracks` on the ~1000-track scene,
then :func:`torchsfm.segment_motions` on the 500-track one (number of motions found), timed after
a warm-up call (median of 3), with the rejection figures / misclassification; beside it, OpenCV's
sequential RANSAC on F between the first and last frames (``bench`` extra), the baseline of
``examples/motion_segmentation.py``.

    python benchmarks/whole_track.py
"""

from __future__ import annotations

import statistics
import time

import torch

from torchsfm.config import Config, with_overrides
from torchsfm.geometry.rotation import axis_angle_to_rotation
from torchsfm.evaluation import misclassification
from torchsfm.moving.segmentation import segment_motions
from torchsfm.moving.whole_track import reject_moving_objects_in_tracks
from torchsfm.testing import rejection_figures


def scene(frames: int = 20, seed: int = 0, static_points: int = 900) -> tuple[torch.Tensor, torch.Tensor]:
    """(F, N, 2) pixel tracks and (N,) labels (0 static, 1, 2 objects) of the scene above."""
    g = torch.Generator().manual_seed(seed)
    K = torch.tensor([[800.0, 0, 320], [0, 800.0, 240], [0, 0, 1]], dtype=torch.float64)
    uniform = lambda n, low, high: low + (high - low) * torch.rand(n, generator=g, dtype=torch.float64)  # noqa: E731
    static = torch.stack([uniform(static_points, -6, 6), uniform(static_points, -4, 4), uniform(static_points, 8, 20)], -1)
    objects = [torch.stack([uniform(50, -1, 1), uniform(50, -1, 1), uniform(50, -1, 1)], -1) + torch.tensor(c, dtype=torch.float64)
               for c in ((-2.0, 0.5, 9.0), (2.0, -0.5, 11.0))]
    tracks = []
    for f in range(frames):
        R = axis_angle_to_rotation(torch.tensor([0.0, 0.2 * f, 0.0], dtype=torch.float64) * torch.pi / 180)
        t = torch.tensor([-0.1 * f, 0.0, 0.0], dtype=torch.float64)
        moved = [points + uniform(3, -0.3, 0.3) * (f > 0) for points in objects]
        objects = moved
        world = torch.cat([static, *moved])
        camera = world @ R.T + t
        pixels = camera @ K.T
        tracks.append(pixels[:, :2] / pixels[:, 2:] + 0.3 * torch.randn(world.shape[0], 2, generator=g, dtype=torch.float64))
    labels = torch.cat([torch.zeros(static_points, dtype=torch.long), torch.ones(50, dtype=torch.long), torch.full((50,), 2)])
    return torch.stack(tracks), labels


def main() -> None:
    torch.set_num_threads(2)
    tracks, labels = scene()
    F, N, _ = tracks.shape
    print(f"{F} frames, {N} tracks ({int((labels != 0).sum())} moving)")
    for method in ("triplets", "rigid_groups", "both", "segmentation"):
        config = with_overrides(Config(), [f"moving_objects.track_method={method}"])
        seconds, result = timed(lambda: reject_moving_objects_in_tracks(tracks, config=config,
                                                                        generator=torch.Generator().manual_seed(0)))
        figures = rejection_figures(result.background_mask, labels)
        print(f"{method:13s} {seconds:6.2f} s   undetected {100 * figures['undetected_rate']:5.1f}%   "
              f"wrongly rejected {100 * figures['wrong_rate']:5.1f}%")
    tracks, labels = scene(static_points=400)
    segment_seconds, result = timed(lambda: segment_motions(tracks, generator=torch.Generator().manual_seed(0)))
    print(f"\nsegment_motions, {tracks.shape[0]} frames x {tracks.shape[1]} tracks: {segment_seconds:.2f} s, "
          f"{result.num_motions} motions found (3 true), misclassification {100 * misclassification(result.labels, labels):.1f}%")
    try:
        import cv2
    except ImportError:
        print("OpenCV not installed (pip install -e .[bench]): no peer ratio")
        return
    x1, x2 = tracks[0].numpy(), tracks[-1].numpy()

    def sequential_ransac() -> torch.Tensor:
        found = torch.full((tracks.shape[1],), -1, dtype=torch.long)
        remaining = torch.arange(tracks.shape[1])
        for motion in range(3):
            if motion == 2:
                found[remaining] = motion
                break
            _, mask = cv2.findFundamentalMat(x1[remaining.numpy()], x2[remaining.numpy()], cv2.USAC_MAGSAC, 1.0, 0.99)
            inliers = torch.from_numpy(mask.ravel().astype(bool))
            found[remaining[inliers]] = motion
            remaining = remaining[~inliers]
        return found

    opencv_seconds, found = timed(sequential_ransac)
    print(f"OpenCV sequential RANSAC (given 3 motions): {opencv_seconds:.3f} s, misclassification "
          f"{100 * misclassification(found, labels):.1f}%; time ratio torchsfm / OpenCV {segment_seconds / opencv_seconds:.1f}")


def timed(run):
    """Median seconds of 3 calls after a warm-up call, and the last result."""
    run()
    times = []
    for _ in range(3):
        start = time.perf_counter()
        result = run()
        times.append(time.perf_counter() - start)
    return statistics.median(times), result


if __name__ == "__main__":
    main()
