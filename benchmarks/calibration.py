"""Calibration from real chessboard photos: torchsfm against OpenCV on the same images.

../shared/data/chessboard_c920_9x7 (7 photos, 1920×1080, 9×7 inner corners). torchsfm: its
chessboard detector + Zhang's method (k1, k2). OpenCV: findChessboardCorners + cornerSubPix
(11×11) + calibrateCamera, once with the same model (k1, k2: CALIB_ZERO_TANGENT_DIST |
CALIB_FIX_K3) and once with its default five coefficients. Corner agreement is the distance from
each of our corners to the nearest OpenCV corner. Needs the ``bench`` extra (opencv).

    python benchmarks/calibration.py [--data ../shared/data]
"""

from __future__ import annotations

import argparse
import statistics
import time
from pathlib import Path

import cv2
import numpy as np
import torch

from torchsfm.calibration.chessboard import detect_chessboard
from torchsfm.calibration.zhang import board_points, calibrate_camera
from torchsfm.images import read_image

DEFAULT_DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data"
PATTERN = (9, 7)


def timed(function):
    start = time.perf_counter()
    result = function()
    return result, time.perf_counter() - start


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--data", type=Path, default=DEFAULT_DATA)
    args = parser.parse_args()
    torch.set_num_threads(2)
    cv2.setNumThreads(2)
    paths = sorted((args.data / "chessboard_c920_9x7").glob("*.jpg"))
    ours, theirs, ours_time, theirs_time, agreement = [], [], [], [], []
    criteria = (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_MAX_ITER, 30, 0.001)
    for path in paths:
        image = read_image(path)
        detection, seconds = timed(lambda: detect_chessboard(image, PATTERN))
        ours_time.append(seconds)
        grey = cv2.cvtColor(cv2.imread(str(path)), cv2.COLOR_BGR2GRAY)

        def opencv():
            found, corners = cv2.findChessboardCorners(grey, PATTERN)
            return cv2.cornerSubPix(grey, corners, (11, 11), (-1, -1), criteria).reshape(-1, 2) if found else None

        corners, seconds = timed(opencv)
        theirs_time.append(seconds)
        print(f"{path.name}: torchsfm {'found' if detection.found else detection.reason}, OpenCV {'found' if corners is not None else 'not found'}", end="")
        if detection.found and corners is not None:
            gaps = np.linalg.norm(detection.corners.numpy()[:, None] - corners[None], axis=-1).min(1)
            agreement.append(gaps)
            print(f"; corners differ by median {np.median(gaps):.3f} px, max {gaps.max():.3f} px")
        else:
            print()
        if detection.found:
            ours.append(detection.corners)
        if corners is not None:
            theirs.append(corners)
    print(f"\ndetection: torchsfm {len(ours)}/{len(paths)} boards, median {1e3 * statistics.median(ours_time):.0f} ms/image; "
          f"OpenCV {len(theirs)}/{len(paths)}, median {1e3 * statistics.median(theirs_time):.0f} ms/image "
          f"(ratio {statistics.median(ours_time) / statistics.median(theirs_time):.2f}x)")
    if agreement:
        every = np.concatenate(agreement)
        print(f"corner agreement over {every.size} corners: median {np.median(every):.3f} px, 95% {np.quantile(every, 0.95):.3f} px")

    board = board_points(PATTERN, 1.0)
    _, first_seconds = timed(lambda: calibrate_camera(board, torch.stack(ours)))  # the process's first call, apart
    calibration, ours_seconds = timed(lambda: calibrate_camera(board, torch.stack(ours)))
    objects = [np.concatenate([board.numpy(), np.zeros((board.shape[0], 1))], 1).astype(np.float32)] * len(theirs)
    images = [c.astype(np.float32) for c in theirs]
    size = grey.shape[::-1]
    two = cv2.CALIB_ZERO_TANGENT_DIST | cv2.CALIB_FIX_K3
    (rms2, K2, dist2, _, _), seconds2 = timed(lambda: cv2.calibrateCamera(objects, images, size, None, None, flags=two))
    (rms5, K5, dist5, _, _), seconds5 = timed(lambda: cv2.calibrateCamera(objects, images, size, None, None))
    K = calibration.K
    rows = [
        ("torchsfm (k1, k2)", calibration.rms, K[0, 0], K[1, 1], K[0, 2], K[1, 2], calibration.distortion.tolist(), ours_seconds),
        ("OpenCV (k1, k2)", rms2, K2[0, 0], K2[1, 1], K2[0, 2], K2[1, 2], dist2.ravel()[:2].tolist(), seconds2),
        ("OpenCV (5 coefficients)", rms5, K5[0, 0], K5[1, 1], K5[0, 2], K5[1, 2], dist5.ravel().tolist(), seconds5),
    ]
    print(f"\n{'calibration':26s} {'RMS px':>7s} {'fx':>9s} {'fy':>9s} {'cx':>8s} {'cy':>8s} {'s':>6s}  distortion")
    for name, rms, fx, fy, cx, cy, distortion, seconds in rows:
        print(f"{name:26s} {rms:7.3f} {float(fx):9.2f} {float(fy):9.2f} {float(cx):8.2f} {float(cy):8.2f} {seconds:6.2f}  "
              + ", ".join(f"{d:.4f}" for d in distortion))
    print(f"(torchsfm's first calibration in a process took {first_seconds:.2f} s)")
    print(f"\ntorchsfm vs OpenCV (k1, k2): fx {100 * (float(K[0, 0]) / K2[0, 0] - 1):+.2f}%, fy {100 * (float(K[1, 1]) / K2[1, 1] - 1):+.2f}%, "
          f"RMS ratio {calibration.rms / rms2:.3f}; vs OpenCV (5): fx {100 * (float(K[0, 0]) / K5[0, 0] - 1):+.2f}%, "
          f"fy {100 * (float(K[1, 1]) / K5[1, 1] - 1):+.2f}%, RMS ratio {calibration.rms / rms5:.3f}")


if __name__ == "__main__":
    main()
