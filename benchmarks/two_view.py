"""Two-view geometry benchmark: torchsfm against OpenCV, Kornia, poselib and pycolmap, same process.

1000 synthetic correspondences (640x480, σ = 0.5 px) at 30% and 60% outliers, 10 scenes each.
Every estimator gets the same data, a 1 px threshold and confidence 0.99 where it takes them.
Printed per method: median time per call, inlier recall / precision against the planted labels,
median symmetric epipolar distance of the true (noise-free) correspondences under the estimated
geometry, median rotation / translation-direction error and the largest translation-direction
error over the scenes. torchsfm's relative pose runs as configured by default (RANSAC on F, LM
from 17 starts), with RANSAC on the five-point E, and with the five-point E as the LM's only
start. Fundamental-matrix methods get
their pose from E = Kᵀ F K through torchsfm's decomposition and cheirality test, so their R, t
errors measure the F. The last column is each method's time over torchsfm's (estimate_fundamental
for F methods, estimate_relative_pose for pose methods); > 1 means torchsfm is faster.

Then batches: B problems (B = 16, 64, 256 scenes) in one ``estimate_fundamental`` call against
OpenCV USAC_MAGSAC one problem at a time on the same scenes: milliseconds per problem, median
recall / precision / epipolar error over the problems, and OpenCV's time per problem over ours.

    pip install -e .[bench]
    python benchmarks/two_view.py [--scenes 10] [--threads 2] [--batches 16,64,256]
"""

from __future__ import annotations

import argparse
import statistics
import time
from collections.abc import Callable

import numpy as np
import torch

import torchsfm
from torchsfm.camera import pixels_to_normalized
from torchsfm.geometry.essential import POSE_CANDIDATES, essential_from_fundamental, select_pose
from torchsfm.geometry.fundamental import symmetric_epipolar_distance
from torchsfm.testing import TwoViewScene, mask_recall_precision, rotation_error_deg, synthetic_two_view, translation_direction_error_deg

THRESHOLD = 1.0
CONFIDENCE = 0.99
MAX_TRIALS = 10_000

# A method maps (scene, seed) to (F or None, R or None, t or None, inlier mask as bool array).
Method = Callable[[TwoViewScene, int], tuple]


def pose_from_fundamental(F: torch.Tensor, scene: TwoViewScene, inliers: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    E = essential_from_fundamental(F, scene.K1, scene.K2)
    n1, n2 = pixels_to_normalized(scene.x1, scene.K1), pixels_to_normalized(scene.x2, scene.K2)
    R, t, _ = select_pose(*POSE_CANDIDATES["svd"](E), n1, n2, inliers.double())
    return R, t


def torchsfm_fundamental(scene, seed):
    result = torchsfm.estimate_fundamental(scene.x1, scene.x2, generator=torch.Generator().manual_seed(seed))
    return result.F, None, None, result.inlier_mask


SEVEN_POINT = torchsfm.with_overrides(torchsfm.Config(), ["fundamental.minimal_solver=seven_point"])


def torchsfm_fundamental_seven_point(scene, seed):
    result = torchsfm.estimate_fundamental(scene.x1, scene.x2, config=SEVEN_POINT, generator=torch.Generator().manual_seed(seed))
    return result.F, None, None, result.inlier_mask


def torchsfm_pose(config: torchsfm.Config | None = None) -> Method:
    def run(scene, seed):
        result = torchsfm.estimate_relative_pose(scene.x1, scene.x2, scene.K1, scene.K2, config=config,
                                                 generator=torch.Generator().manual_seed(seed))
        return result.F, result.R, result.t, result.inlier_mask
    return run


FIVE_POINT = torchsfm.with_overrides(torchsfm.Config(), ["relative_pose.solver=five_point"])
FIVE_POINT_ONE_START = torchsfm.with_overrides(FIVE_POINT, ["relative_pose.num_starts=0"])


def opencv_methods() -> dict[str, Method]:
    import cv2

    cv2.setRNGSeed(0)

    def fundamental(flag):
        def run(scene, seed):
            F, mask = cv2.findFundamentalMat(scene.x1.numpy(), scene.x2.numpy(), flag, THRESHOLD, CONFIDENCE, MAX_TRIALS)
            return torch.from_numpy(F[:3]).clone(), None, None, torch.from_numpy(mask.ravel().astype(bool))
        return run

    def essential(scene, seed):
        K = scene.K1.numpy()
        E, mask = cv2.findEssentialMat(scene.x1.numpy(), scene.x2.numpy(), K, cv2.USAC_MAGSAC, CONFIDENCE, THRESHOLD)
        _, R, t, mask = cv2.recoverPose(E, scene.x1.numpy(), scene.x2.numpy(), K, mask=mask.copy())
        F = torch.linalg.inv(scene.K2).T @ torch.from_numpy(E) @ torch.linalg.inv(scene.K1)
        return F, torch.from_numpy(R).clone(), torch.from_numpy(t.ravel()).clone(), torch.from_numpy(mask.ravel() > 0)

    return {
        "OpenCV F USAC_MAGSAC": fundamental(cv2.USAC_MAGSAC),
        "OpenCV F FM_RANSAC": fundamental(cv2.FM_RANSAC),
        "OpenCV E USAC_MAGSAC+recoverPose": essential,
    }


def kornia_methods() -> dict[str, Method]:
    from kornia.geometry.ransac import RANSAC

    def fundamental(model_type):
        def run(scene, seed):
            estimator = RANSAC(model_type=model_type, inl_th=THRESHOLD, max_iter=10, confidence=CONFIDENCE, seed=seed)
            F, mask = estimator(scene.x1, scene.x2)
            return F.double(), None, None, mask
        return run

    return {"Kornia RANSAC fundamental_8pt": fundamental("fundamental_8pt"), "Kornia RANSAC fundamental (7pt)": fundamental("fundamental")}


def poselib_methods() -> dict[str, Method]:
    import poselib

    options = {"max_epipolar_error": THRESHOLD, "success_prob": CONFIDENCE, "max_iterations": MAX_TRIALS}

    def fundamental(scene, seed):
        F, info = poselib.estimate_fundamental(scene.x1.numpy(), scene.x2.numpy(), {**options, "seed": seed}, {})
        return torch.from_numpy(np.array(F)), None, None, torch.from_numpy(np.array(info["inliers"]))

    def relative_pose(scene, seed):
        pose, info = poselib.estimate_relative_pose(scene.x1.numpy(), scene.x2.numpy(), _camera(scene.K1, scene),
                                                    _camera(scene.K2, scene), {**options, "seed": seed}, {})
        R, t = torch.from_numpy(np.array(pose.R)), torch.from_numpy(np.array(pose.t))
        F = torch.linalg.inv(scene.K2).T @ torchsfm.geometry.rotation.skew(t) @ R @ torch.linalg.inv(scene.K1)
        return F, R, t, torch.from_numpy(np.array(info["inliers"]))

    return {"poselib fundamental": fundamental, "poselib relative pose": relative_pose}


def _camera(K: torch.Tensor, scene: TwoViewScene) -> dict:
    return {"model": "PINHOLE", "width": scene.image_size[0], "height": scene.image_size[1],
            "params": [float(K[0, 0]), float(K[1, 1]), float(K[0, 2]), float(K[1, 2])]}


def pycolmap_methods() -> dict[str, Method]:
    import pycolmap

    def options(seed):
        return pycolmap.RANSACOptions(max_error=THRESHOLD, confidence=CONFIDENCE, max_num_trials=MAX_TRIALS, random_seed=seed)

    def fundamental(scene, seed):
        result = pycolmap.estimate_fundamental_matrix(scene.x1.numpy(), scene.x2.numpy(), options(seed))
        return torch.from_numpy(result["F"]), None, None, torch.from_numpy(np.array(result["inlier_mask"]))

    def essential(scene, seed):
        cameras = [pycolmap.Camera(**{k: v for k, v in _camera(K, scene).items()}) for K in (scene.K1, scene.K2)]
        result = pycolmap.estimate_essential_matrix(scene.x1.numpy(), scene.x2.numpy(), *cameras, options(seed))
        pose = result["cam2_from_cam1"]
        R = torch.from_numpy(pose.rotation.matrix())
        t = torch.from_numpy(np.array(pose.translation))
        F = torch.linalg.inv(scene.K2).T @ torch.from_numpy(result["E"]) @ torch.linalg.inv(scene.K1)
        return F, R, t / t.norm(), torch.from_numpy(np.array(result["inlier_mask"]))

    return {"pycolmap fundamental": fundamental, "pycolmap essential": essential}


def evaluate(method: Method, scenes: list[TwoViewScene]) -> dict[str, float]:
    method(scenes[0], 0)  # warm-up
    times, recall, precision, epipolar, rotation, translation = [], [], [], [], [], []
    for seed, scene in enumerate(scenes):
        start = time.perf_counter()
        F, R, t, inliers = method(scene, seed)
        times.append(time.perf_counter() - start)
        if R is None:
            R, t = pose_from_fundamental(F.double(), scene, inliers)
        r, p = mask_recall_precision(inliers, scene.is_inlier)
        recall.append(r)
        precision.append(p)
        epipolar.append(symmetric_epipolar_distance(F.double(), scene.x1_true, scene.x2_true).median().item())
        rotation.append(rotation_error_deg(R.double(), scene.R))
        translation.append(translation_direction_error_deg(t.double().flatten(), scene.t))
    median = statistics.median
    return {"time_ms": 1000 * median(times), "recall": median(recall), "precision": median(precision),
            "epipolar_px": median(epipolar), "R_deg": median(rotation), "t_deg": median(translation), "t_max": max(translation)}


def batch_rows(outliers: float, sizes: list[int]) -> None:
    """One batched estimate_fundamental call per size against OpenCV one problem at a time."""
    try:
        import cv2
    except ImportError as error:
        print(f"OpenCV not installed ({error}): no batch comparison")
        return
    scenes = [synthetic_two_view(1000, noise=0.5, outlier_ratio=outliers, seed=seed) for seed in range(max(sizes))]
    print(f"\n{outliers:.0%} outliers, batches (per problem, medians over the problems)")
    print(f"{'B':>4s} {'ours ms':>8s} {'OpenCV ms':>9s} {'ours/OpenCV':>11s} {'recall':>7s} {'precis.':>7s} {'epi px':>7s}")
    for B in sizes:
        batch = scenes[:B]
        x1, x2 = torch.stack([scene.x1 for scene in batch]), torch.stack([scene.x2 for scene in batch])
        torchsfm.estimate_fundamental(x1[:2], x2[:2])  # warm-up
        start = time.perf_counter()
        result = torchsfm.estimate_fundamental(x1, x2, generator=torch.Generator().manual_seed(0))
        ours = (time.perf_counter() - start) / B
        start = time.perf_counter()
        for scene in batch:
            cv2.findFundamentalMat(scene.x1.numpy(), scene.x2.numpy(), cv2.USAC_MAGSAC, THRESHOLD, CONFIDENCE, MAX_TRIALS)
        opencv = (time.perf_counter() - start) / B
        figures = [mask_recall_precision(result.inlier_mask[b], scene.is_inlier) for b, scene in enumerate(batch)]
        epipolar = [symmetric_epipolar_distance(result.F[b], scene.x1_true, scene.x2_true).median().item() for b, scene in enumerate(batch)]
        median = statistics.median
        print(f"{B:4d} {1000 * ours:8.2f} {1000 * opencv:9.2f} {ours / opencv:11.2f} {median(r for r, _ in figures):7.3f} "
              f"{median(p for _, p in figures):7.3f} {median(epipolar):7.3f}")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--scenes", type=int, default=10)
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--batches", default="16,64,256", help="batch sizes (empty: none)")
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    methods: dict[str, Method] = {"torchsfm estimate_fundamental": torchsfm_fundamental,
                                  "torchsfm estimate_fundamental 7pt": torchsfm_fundamental_seven_point,
                                  "torchsfm estimate_relative_pose": torchsfm_pose(),
                                  "torchsfm relative pose 5pt": torchsfm_pose(FIVE_POINT),
                                  "torchsfm relative pose 5pt, 1 start": torchsfm_pose(FIVE_POINT_ONE_START)}
    for name, provider in (("OpenCV", opencv_methods), ("Kornia", kornia_methods), ("poselib", poselib_methods), ("pycolmap", pycolmap_methods)):
        try:
            methods.update(provider())
        except ImportError as error:
            print(f"{name} not installed ({error}); pip install -e .[bench]")
    header = (f"{'method':36s} {'ms/call':>8s} {'recall':>7s} {'precis.':>7s} {'epi px':>7s} {'R deg':>7s} {'t deg':>7s} "
              f"{'t max':>7s} {'time/ours':>9s}")
    for outliers in (0.3, 0.6):
        scenes = [synthetic_two_view(1000, noise=0.5, outlier_ratio=outliers, seed=seed) for seed in range(args.scenes)]
        print(f"\n{outliers:.0%} outliers, 1000 correspondences, 640x480, σ = 0.5 px, {args.scenes} scenes (medians)")
        print(header)
        results = {name: evaluate(method, scenes) for name, method in methods.items()}
        for name, row in results.items():
            is_pose = "pose" in name or "essential" in name or " E " in name
            reference = results["torchsfm estimate_relative_pose" if is_pose else "torchsfm estimate_fundamental"]["time_ms"]
            print(f"{name:36s} {row['time_ms']:8.1f} {row['recall']:7.3f} {row['precision']:7.3f} {row['epipolar_px']:7.3f} "
                  f"{row['R_deg']:7.3f} {row['t_deg']:7.3f} {row['t_max']:7.3f} {row['time_ms'] / reference:9.2f}")
    for outliers in (0.3, 0.6):
        if args.batches:
            batch_rows(outliers, [int(size) for size in args.batches.split(",")])


if __name__ == "__main__":
    main()
