"""The two-view pipeline on every real pair with ground truth (issue #3's bar).

Strecha fountain-P11 and Herz-Jesu-P8 (768×512, every neighbouring pair) and Oxford Merton
College I (1024×768, every pair): final matches, the share within 1.5 px (symmetric epipolar
distance) of the ground-truth epipolar geometry, rotation and translation-direction errors, and
the time of the whole pipeline per pair (after a warm-up call).

    python examples/two_view_pairs.py [--data ../shared/data]
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import torch

from torchsfm.geometry.fundamental import symmetric_epipolar_distance
from torchsfm.io.datasets import ground_truth_pairs
from torchsfm.images import read_image
from torchsfm.sfm.two_view import TwoViewReconstruction
from torchsfm.testing import rotation_error_deg, translation_direction_error_deg

DEFAULT_DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--data", type=Path, default=DEFAULT_DATA)
    args = parser.parse_args()
    pipeline = TwoViewReconstruction()
    print(f"{'pair':26s} {'putative':>8s} {'final':>6s} {'<1.5px':>7s} {'R err °':>8s} {'t err °':>8s} {'s':>6s}")
    warm = True
    for pair in ground_truth_pairs(args.data):
        name, K1, K2, R_true, t_true = pair.name, pair.K1, pair.K2, pair.R, pair.t
        image1, image2 = read_image(pair.image1), read_image(pair.image2)
        if warm:
            pipeline(image1, image2, K1, K2, generator=torch.Generator().manual_seed(0))
            warm = False
        start = time.perf_counter()
        model = pipeline(image1, image2, K1, K2, generator=torch.Generator().manual_seed(0))
        seconds = time.perf_counter() - start
        inliers = model.inlier_mask
        F_true = pair.F
        within = (symmetric_epipolar_distance(F_true, model.matches[inliers, :2], model.matches[inliers, 2:]) < 1.5).double().mean()
        print(f"{name:26s} {inliers.numel():8d} {int(inliers.sum()):6d} {within:7.3f} "
              f"{rotation_error_deg(model.cameras.R[1], R_true):8.3f} {translation_direction_error_deg(model.cameras.t[1], t_true):8.3f} {seconds:6.2f}")


if __name__ == "__main__":
    main()
