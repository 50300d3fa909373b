"""A long video from the KITTI 06 excerpt: its 51 frames played forward, backward, forward, ...
for ``--frames`` frames (default 500), reconstructed with the ground-truth K. Prints views
registered, points, the camera errors against the ground truth and seconds per stage; run it
under ``/usr/bin/time -v`` for the peak resident memory (issue #12's bound for 500 frames).

    /usr/bin/time -v python examples/long_video.py [--frames 500] [--data ../shared/data] [--set pairs.mode=sequential]
"""

from __future__ import annotations

import argparse
import resource
import time
from pathlib import Path

import torch

import torchsfm
from torchsfm.config import with_overrides
from torchsfm.evaluation import camera_errors
from torchsfm.io.datasets import read_kitti_odometry

DEFAULT_DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--data", type=Path, default=DEFAULT_DATA)
    parser.add_argument("--frames", type=int, default=500)
    parser.add_argument("--set", action="append", default=[], metavar="KEY=VALUE", help="override one config value")
    args = parser.parse_args()
    sequence = read_kitti_odometry(args.data / "kitti_odom_seq06_000-050")
    cycle = list(range(51)) + list(range(49, 0, -1))
    order = [cycle[k % len(cycle)] for k in range(args.frames)]
    start = time.perf_counter()

    peak = [0.0]

    def progress(message: str) -> None:
        rss = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 2**20  # GiB (Linux reports KiB)
        if rss > peak[0] + 0.05 or not message.startswith(("registering", "matching views")):
            print(f"{time.perf_counter() - start:8.1f} s  peak {rss:.2f} GiB  {message}", flush=True)
        peak[0] = max(peak[0], rss)

    model = torchsfm.reconstruct([sequence.images[i] for i in order], sequence.K[0], config=with_overrides(torchsfm.Config(), args.set),
                                 generator=torch.Generator().manual_seed(0), progress=progress)
    truth = [order[v] for v in model.view_indices]
    errors = camera_errors(model.cameras.R, model.cameras.t, sequence.R[truth], sequence.t[truth])
    print(f"{args.frames} frames: {model.num_views} registered, {model.num_points} points, {time.perf_counter() - start:.1f} s")
    print(f"centre error median {100 * float(errors.centre.median()) / errors.extent:.3f} % (max "
          f"{100 * float(errors.centre.max()) / errors.extent:.3f} %) of the path, rotation median "
          f"{float(errors.rotation.median()):.3f} deg (max {float(errors.rotation.max()):.3f})")
    print("seconds:", {name: round(seconds, 1) for name, seconds in model.timings.items()})


if __name__ == "__main__":
    main()
