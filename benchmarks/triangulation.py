"""Triangulation benchmark: every torchsfm method against OpenCV on 10,000 noisy correspondences.

OpenCV's optimal two-view triangulation is ``cv2.correctMatches`` (Hartley–Sturm) followed by
``cv2.triangulatePoints`` (linear); torchsfm's ``polynomial`` method does both steps. Printed:
median time of 10 calls, median reprojection error (pixels, RMS over the two images) and the time
ratio OpenCV / torchsfm (> 1 means torchsfm is faster).

    pip install -e .[bench]
    python benchmarks/triangulation.py [--points 10000] [--threads 2]
"""

from __future__ import annotations

import argparse
import statistics
import time

import numpy as np
import torch

import torchsfm
from torchsfm.camera import project
from torchsfm.geometry.fundamental import fundamental_from_projections
from torchsfm.testing import synthetic_two_view


def timed(function, repeats: int = 10):
    function()
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        result = function()
        times.append(time.perf_counter() - start)
    return statistics.median(times), result


def reprojection_px(X: torch.Tensor, scene) -> float:
    squared = ((project(scene.P1, X) - scene.x1) ** 2).sum(-1) + ((project(scene.P2, X) - scene.x2) ** 2).sum(-1)
    return (squared / 2).sqrt().median().item()


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--points", type=int, default=10_000)
    parser.add_argument("--threads", type=int, default=2)
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    scene = synthetic_two_view(args.points, noise=1.0, seed=0)
    print(f"{args.points} correspondences, σ = 1 px, float64")
    print(f"{'method':34s} {'ms/call':>9s} {'reproj px':>10s} {'OpenCV/ours':>12s}")
    results = {}
    for method in torchsfm.TRIANGULATION_METHODS:
        seconds, X = timed(lambda: torchsfm.triangulate(scene.x1, scene.x2, scene.P1, scene.P2, method=method))
        results[method] = (seconds, reprojection_px(X, scene))
    try:
        import cv2
    except ImportError as error:
        print(f"OpenCV not installed ({error}); pip install -e .[bench]")
        cv2 = None
    if cv2 is not None:
        F = fundamental_from_projections(scene.P1, scene.P2).numpy()
        P1, P2 = scene.P1.numpy(), scene.P2.numpy()
        x1, x2 = scene.x1.numpy()[None], scene.x2.numpy()[None]

        def opencv_optimal():
            c1, c2 = cv2.correctMatches(F, x1, x2)
            X = cv2.triangulatePoints(P1, P2, c1[0].T, c2[0].T)
            return X[:3] / X[3]

        def opencv_linear():
            X = cv2.triangulatePoints(P1, P2, x1[0].T, x2[0].T)
            return X[:3] / X[3]

        for name, function in (("OpenCV correctMatches+triangulate", opencv_optimal), ("OpenCV triangulatePoints", opencv_linear)):
            seconds, X = timed(function)
            results[name] = (seconds, reprojection_px(torch.from_numpy(np.ascontiguousarray(X.T)), scene))
    reference = results.get("OpenCV correctMatches+triangulate", (None,))[0]
    for name, (seconds, error) in results.items():
        ratio = f"{reference / seconds:12.2f}" if reference and name in torchsfm.TRIANGULATION_METHODS else ""
        print(f"{name:34s} {1000 * seconds:9.2f} {error:10.4f} {ratio}")


if __name__ == "__main__":
    main()
