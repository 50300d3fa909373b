"""Resection RANSAC benchmark: torchsfm (P3P and DLT minimal samples) beside OpenCV and poselib.

500 3-D↔2-D pairs (points 4–8 m in front of a 640×480 camera, σ = 0.5 px), 30% and 60% of the
image points replaced by random pixels; 10 scenes each. Every method gets a 2 px threshold and
confidence 0.99. Printed (medians): time per call, rotation error, camera-centre error (m),
inlier recall and precision, and the time over torchsfm P3P's (> 1: torchsfm is faster).

Then batches: B problems (B = 16, 64 scenes) in one ``estimate_absolute_pose`` call (P3P) against
OpenCV's ``solvePnPRansac`` one problem at a time on the same scenes: milliseconds per problem,
median recall / precision over the problems, and our time per problem over OpenCV's.

    pip install -e .[bench]
    python benchmarks/resection.py [--scenes 10] [--threads 2] [--batches 16,64]
"""

from __future__ import annotations

import argparse
import statistics
import time

import numpy as np
import torch

import torchsfm
from torchsfm.geometry.rotation import axis_angle_to_rotation, rotation_angle
from torchsfm.testing import mask_recall_precision

K = torch.tensor([[600.0, 0.0, 319.5], [0.0, 600.0, 239.5], [0.0, 0.0, 1.0]], dtype=torch.float64)


def scene(outliers: float, seed: int):
    generator = torch.Generator().manual_seed(seed)
    R = axis_angle_to_rotation(0.3 * torch.randn(3, generator=generator, dtype=torch.float64))
    t = torch.randn(3, generator=generator, dtype=torch.float64)
    depth = 4 + 4 * torch.rand(500, 1, generator=generator, dtype=torch.float64)
    pixels = torch.rand(500, 2, generator=generator, dtype=torch.float64) * torch.tensor([639.0, 479.0], dtype=torch.float64)
    camera = torch.cat([pixels, torch.ones(500, 1, dtype=torch.float64)], -1) @ torch.linalg.inv(K).T * depth
    X = (camera - t) @ R  # world = Rᵀ (camera - t)
    x = pixels + 0.5 * torch.randn(500, 2, generator=generator, dtype=torch.float64)
    n = int(outliers * 500)
    x[:n] = torch.rand(n, 2, generator=generator, dtype=torch.float64) * torch.tensor([639.0, 479.0], dtype=torch.float64)
    truth = torch.ones(500, dtype=torch.bool)
    truth[:n] = False
    return X, x, R, t, truth


def torchsfm_method(solver: str):
    config = torchsfm.with_overrides(torchsfm.Config(), [f"resection.solver={solver}"])

    def run(X, x, seed):
        pose = torchsfm.estimate_absolute_pose(X, x, K, config=config, generator=torch.Generator().manual_seed(seed))
        return pose.R, pose.t, pose.inlier_mask
    return run


def opencv(X, x, seed):
    import cv2

    cv2.setRNGSeed(seed)
    ok, rvec, tvec, inliers = cv2.solvePnPRansac(X.numpy(), x.numpy(), K.numpy(), None, iterationsCount=10000,
                                                 reprojectionError=2.0, confidence=0.99, flags=cv2.SOLVEPNP_P3P)
    mask = torch.zeros(X.shape[0], dtype=torch.bool)
    if ok and inliers is not None:
        mask[torch.from_numpy(inliers.ravel())] = True
    return axis_angle_to_rotation(torch.from_numpy(rvec.ravel())), torch.from_numpy(tvec.ravel()), mask


def poselib_method(X, x, seed):
    import poselib

    camera = {"model": "PINHOLE", "width": 640, "height": 480, "params": [600.0, 600.0, 319.5, 239.5]}
    pose, info = poselib.estimate_absolute_pose(x.numpy(), X.numpy(), camera, {"max_reproj_error": 2.0, "success_prob": 0.99, "seed": seed}, {})
    return torch.from_numpy(np.array(pose.R)), torch.from_numpy(np.array(pose.t)), torch.from_numpy(np.array(info["inliers"]))


def batch_rows(outliers: float, sizes: list[int]) -> None:
    """One batched estimate_absolute_pose call per size against OpenCV one problem at a time."""
    try:
        import cv2  # noqa: F401 - only to know whether the peer is there
    except ImportError as error:
        print(f"OpenCV not installed ({error}): no batch comparison")
        return
    scenes = [scene(outliers, seed) for seed in range(max(sizes))]
    run = torchsfm_method("p3p")
    print(f"\n{outliers:.0%} outliers, batches (per problem, medians over the problems)")
    print(f"{'B':>4s} {'ours ms':>8s} {'OpenCV ms':>9s} {'ours/OpenCV':>11s} {'recall':>7s} {'precis.':>7s}")
    for B in sizes:
        batch = scenes[:B]
        X, x = torch.stack([s[0] for s in batch]), torch.stack([s[1] for s in batch])
        run(X[:2], x[:2], 0)  # warm-up
        start = time.perf_counter()
        _, _, inliers = run(X, x, 0)
        ours = (time.perf_counter() - start) / B
        start = time.perf_counter()
        for seed, (X_b, x_b, *_) in enumerate(batch):
            opencv(X_b, x_b, seed)
        theirs = (time.perf_counter() - start) / B
        figures = [mask_recall_precision(inliers[b], truth) for b, (*_, truth) in enumerate(batch)]
        print(f"{B:4d} {1000 * ours:8.2f} {1000 * theirs:9.2f} {ours / theirs:11.2f} "
              f"{statistics.median(r for r, _ in figures):7.3f} {statistics.median(p for _, p in figures):7.3f}")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--scenes", type=int, default=10)
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--batches", default="16,64", help="batch sizes (empty: none)")
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    methods = {"torchsfm P3P": torchsfm_method("p3p"), "torchsfm DLT": torchsfm_method("dlt")}
    for name, module, method in (("cv2.solvePnPRansac P3P", "cv2", opencv), ("poselib", "poselib", poselib_method)):
        try:
            __import__(module)
            methods[name] = method
        except ImportError as error:
            print(f"{module} not installed ({error}); pip install -e .[bench]")
    for outliers in (0.3, 0.6):
        scenes = [scene(outliers, seed) for seed in range(args.scenes)]
        print(f"\n{outliers:.0%} outliers, 500 pairs, σ = 0.5 px, {args.scenes} scenes (medians)")
        print(f"{'method':26s} {'ms/call':>8s} {'R err °':>8s} {'C err m':>8s} {'recall':>7s} {'precis.':>8s} {'time/ours':>10s}")
        reference = None
        for name, method in methods.items():
            method(*scenes[0][:2], 0)  # warm-up
            times, rotation, centre, recall, precision = [], [], [], [], []
            for seed, (X, x, R, t, truth) in enumerate(scenes):
                start = time.perf_counter()
                R_est, t_est, inliers = method(X, x, seed)
                times.append(time.perf_counter() - start)
                rotation.append(float(rotation_angle(R_est.double(), R)))
                centre.append(float((R_est.double().T @ t_est.double() - R.T @ t).norm()))
                r, p = mask_recall_precision(inliers, truth)
                recall.append(r)
                precision.append(p)
            milliseconds = 1000 * statistics.median(times)
            reference = reference or milliseconds
            print(f"{name:26s} {milliseconds:8.2f} {statistics.median(rotation):8.4f} {statistics.median(centre):8.5f} "
                  f"{statistics.median(recall):7.3f} {statistics.median(precision):8.3f} {milliseconds / reference:10.2f}")
        if args.batches:
            batch_rows(outliers, [int(size) for size in args.batches.split(",")])


if __name__ == "__main__":
    main()
