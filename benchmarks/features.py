"""Front-end benchmark: detect + match + robust F on 768×512 pairs, torchsfm beside OpenCV.

Pipelines, each timed from decoded grey images to F and its inliers (median over the neighbouring
pairs of Strecha fountain-P11), with the precision of the inliers against the ground-truth
epipolar geometry (symmetric distance < 1.5 px):

* torchsfm: Harris + biquadric fit → NCC candidates + strength measure + relaxation →
  ``estimate_fundamental`` (bucketed RANSAC + LM);
* OpenCV Harris: ``goodFeaturesToTrack`` (Harris, 2000 corners) + ``cornerSubPix`` → mutual-best
  NCC in the same 100 px disc (NumPy, 11×11 patches) → ``findFundamentalMat`` USAC_MAGSAC;
* torchsfm SIFT (``pairs.matcher=sift`` and the SIFT bridge's features): Kornia's SIFT detector
  with our suppression, patches and pooled descriptor (``sift_features``, 4000 features) → mutual
  nearest neighbours with ratio 0.8 (``mutual_ratio_matches``: Kornia ``match_smnn``'s pairs) →
  ``estimate_fundamental``;
* OpenCV SIFT: SIFT + ratio test 0.8 → ``findFundamentalMat`` USAC_MAGSAC.

The last column is time / torchsfm's time (> 1: torchsfm is faster).

    pip install -e .[bench]
    python benchmarks/features.py [--data ../shared/data] [--threads 2]
"""

from __future__ import annotations

import argparse
import statistics
import time
from pathlib import Path

import numpy as np
import torch

from torchsfm.config import Config
from torchsfm.features.harris import detect_corners
from torchsfm.geometry.fundamental import fundamental_from_pose, symmetric_epipolar_distance
from torchsfm.io.datasets import read_strecha
from torchsfm.images import read_image, to_grey
from torchsfm.matching.matcher import match_corners
from torchsfm.estimators.two_view_geometry import estimate_fundamental
from torchsfm.features.sift import mutual_ratio_matches, sift_features

DEFAULT_DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data"


def torchsfm_pipeline(grey1: torch.Tensor, grey2: torch.Tensor, config: Config):
    corners = detect_corners(torch.stack([grey1, grey2]), config.harris)
    p1, p2 = corners.of_image(0), corners.of_image(1)
    matches = match_corners(grey1, grey2, p1, p2, config.matching)
    x1, x2 = p1[matches.index1].double(), p2[matches.index2].double()
    result = estimate_fundamental(x1, x2, config=config, generator=torch.Generator().manual_seed(0))
    return x1[result.inlier_mask], x2[result.inlier_mask]


def torchsfm_sift_pipeline(grey1: torch.Tensor, grey2: torch.Tensor, config: Config):
    (p1, p2), (d1, d2) = sift_features([grey1, grey2], config.pairs.sift_features)
    index = mutual_ratio_matches(d1, d2, config.pairs.sift_ratio)
    x1, x2 = p1[index[:, 0]], p2[index[:, 1]]
    result = estimate_fundamental(x1, x2, config=config, generator=torch.Generator().manual_seed(0))
    return x1[result.inlier_mask], x2[result.inlier_mask]


def opencv_harris_pipeline(image1: np.ndarray, image2: np.ndarray):
    import cv2

    criteria = (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_MAX_ITER, 30, 0.01)
    points = []
    for image in (image1, image2):
        corners = cv2.goodFeaturesToTrack(image, 2000, 1e-4, 3, useHarrisDetector=True, k=0.04)
        points.append(cv2.cornerSubPix(image, corners, (3, 3), (-1, -1), criteria).reshape(-1, 2))
    patches = [_ncc_patches(image, p, 5) for image, p in zip((image1, image2), points)]
    ncc = patches[0] @ patches[1].T
    distance = np.linalg.norm(points[0][:, None] - points[1][None], axis=-1)
    ncc[distance > 100] = -1
    best12, best21 = ncc.argmax(1), ncc.argmax(0)
    mutual = (best21[best12] == np.arange(len(best12))) & (ncc[np.arange(len(best12)), best12] > 0.8)
    x1, x2 = points[0][mutual], points[1][best12[mutual]]
    _, mask = cv2.findFundamentalMat(x1, x2, cv2.USAC_MAGSAC, 1.0, 0.99, 10000)
    mask = mask.ravel().astype(bool)
    return x1[mask], x2[mask]


def _ncc_patches(image: np.ndarray, points: np.ndarray, half: int) -> np.ndarray:
    import cv2

    size = 2 * half + 1
    patches = np.stack([cv2.getRectSubPix(image, (size, size), (float(x), float(y))).astype(np.float32).ravel() for x, y in points])
    patches -= patches.mean(1, keepdims=True)
    return patches / np.maximum(np.linalg.norm(patches, axis=1, keepdims=True), 1e-6)


def opencv_sift_pipeline(image1: np.ndarray, image2: np.ndarray):
    import cv2

    sift = cv2.SIFT_create()
    (k1, d1), (k2, d2) = sift.detectAndCompute(image1, None), sift.detectAndCompute(image2, None)
    pairs = cv2.BFMatcher(cv2.NORM_L2).knnMatch(d1, d2, k=2)
    good = [m for m, n in pairs if m.distance < 0.8 * n.distance]
    x1 = np.float32([k1[m.queryIdx].pt for m in good])
    x2 = np.float32([k2[m.trainIdx].pt for m in good])
    _, mask = cv2.findFundamentalMat(x1, x2, cv2.USAC_MAGSAC, 1.0, 0.99, 10000)
    mask = mask.ravel().astype(bool)
    return x1[mask], x2[mask]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--data", type=Path, default=DEFAULT_DATA)
    parser.add_argument("--threads", type=int, default=2)
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    sequence = read_strecha(args.data / "strecha_fountain_P11")
    config = Config()
    images = [read_image(path) for path in sequence.images]
    greys = [to_grey(image) for image in images]
    greys8 = [(grey[0] * 255).round().byte().numpy() for grey in greys]
    greys8_torch = [torch.from_numpy(grey)[None] for grey in greys8]
    pipelines = {"torchsfm (Harris+SM+RANSAC/LM)": lambda i, j: torchsfm_pipeline(greys[i], greys[j], config),
                 "torchsfm SIFT (Kornia detector)+SMNN": lambda i, j: torchsfm_sift_pipeline(greys8_torch[i], greys8_torch[j], config)}
    try:
        import cv2

        cv2.setNumThreads(args.threads)
        pipelines["OpenCV Harris+cornerSubPix+NCC+MAGSAC"] = lambda i, j: opencv_harris_pipeline(greys8[i], greys8[j])
        pipelines["OpenCV SIFT+ratio+USAC_MAGSAC"] = lambda i, j: opencv_sift_pipeline(greys8[i], greys8[j])
    except ImportError as error:
        print(f"OpenCV not installed ({error}); pip install -e .[bench]")
    torchsfm_pipeline(greys[0], greys[1], config)  # warm-up
    print(f"fountain-P11, {len(images) - 1} neighbouring pairs at 768x512, {args.threads} threads (medians over pairs)")
    print(f"{'pipeline':40s} {'s/pair':>7s} {'inliers':>8s} {'precision':>10s} {'time/ours':>10s}")
    reference = None
    for name, pipeline in pipelines.items():
        times, counts, precisions = [], [], []
        for i in range(len(images) - 1):
            start = time.perf_counter()
            x1, x2 = pipeline(i, i + 1)
            times.append(time.perf_counter() - start)
            R, t = sequence.relative_pose(i, i + 1)
            F = fundamental_from_pose(sequence.K[i], sequence.K[i + 1], R, t)
            x1, x2 = torch.as_tensor(np.asarray(x1), dtype=torch.float64), torch.as_tensor(np.asarray(x2), dtype=torch.float64)
            counts.append(x1.shape[0])
            precisions.append((symmetric_epipolar_distance(F, x1, x2) < 1.5).double().mean().item())
        seconds = statistics.median(times)
        reference = reference or seconds
        print(f"{name:40s} {seconds:7.3f} {statistics.median(counts):8.0f} {statistics.median(precisions):10.3f} {seconds / reference:10.2f}")


if __name__ == "__main__":
    main()
