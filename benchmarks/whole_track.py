"""Whole-track moving-object rejection: seconds for a 20-frame, ~1000-track sequence.

A seeded synthetic scene (640×480, f = 800 px): 900 static points 8–20 m deep, a camera moving
0.1 m and turning 0.2° per frame, two 2 m objects of 50 points each taking a new random step and
turn every frame, 0.3 px noise; each ``track_method`` timed after a warm-up call (median of 3),
with the rejection figures.

    python benchmarks/whole_track.py
"""

from __future__ import annotations

import statistics
import time

import torch

from torchsfm.config import Config, with_overrides
from torchsfm.geometry.rotation import axis_angle_to_rotation
from torchsfm.moving.whole_track import reject_moving_objects_in_tracks
from torchsfm.testing import rejection_figures


def scene(frames: int = 20, seed: int = 0) -> tuple[torch.Tensor, torch.Tensor]:
    """(F, N, 2) pixel tracks and (N,) labels (0 static, 1, 2 objects) of the scene above."""
    g = torch.Generator().manual_seed(seed)
    K = torch.tensor([[800.0, 0, 320], [0, 800.0, 240], [0, 0, 1]], dtype=torch.float64)
    uniform = lambda n, low, high: low + (high - low) * torch.rand(n, generator=g, dtype=torch.float64)  # noqa: E731
    static = torch.stack([uniform(900, -6, 6), uniform(900, -4, 4), uniform(900, 8, 20)], -1)
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
    labels = torch.cat([torch.zeros(900, dtype=torch.long), torch.ones(50, dtype=torch.long), torch.full((50,), 2)])
    return torch.stack(tracks), labels


def main() -> None:
    torch.set_num_threads(2)
    tracks, labels = scene()
    F, N, _ = tracks.shape
    print(f"{F} frames, {N} tracks ({int((labels != 0).sum())} moving)")
    for method in ("triplets", "rigid_groups", "both"):
        config = with_overrides(Config(), [f"moving_objects.track_method={method}"])
        run = lambda: reject_moving_objects_in_tracks(tracks, config=config, generator=torch.Generator().manual_seed(0))  # noqa: E731
        run()
        times = []
        for _ in range(3):
            start = time.perf_counter()
            result = run()
            times.append(time.perf_counter() - start)
        figures = rejection_figures(result.background_mask, labels)
        print(f"{method:13s} {statistics.median(times):6.2f} s   undetected {100 * figures['undetected_rate']:5.1f}%   "
              f"wrongly rejected {100 * figures['wrong_rate']:5.1f}%")


if __name__ == "__main__":
    main()
