"""Thesis Table 3.2: pixel vs sub-pixel corners, before vs after LM, on real image pairs.

For each pair, corners are detected with and without the biquadric sub-pixel fit and matched
(NCC + SM + relaxation); RANSAC (no refinement) gives F and its inliers, and LM on the Sampson
error refines F on the same inliers. Printed per setting, averaged over the pairs: the inlier
count, the Sampson error per inlier (px², eq. 3.3.6) and the squared symmetric epipolar
distance per inlier (px²) under the estimated F, before and after LM; and, since ground truth is
at hand, the median symmetric epipolar distance of the inliers under the true F (px).

    python examples/subpixel_and_lm.py [--data ../shared/data]
"""

from __future__ import annotations

import argparse
import statistics
from pathlib import Path

import torch

from torchsfm.config import Config, with_overrides
from torchsfm.features.harris import detect_corners
from torchsfm.geometry.fundamental import sampson_error, symmetric_epipolar_distance
from torchsfm.estimators.fundamental_refinement import refine_fundamental
from torchsfm.io.datasets import ground_truth_pairs
from torchsfm.images import read_image, to_grey
from torchsfm.matching.matcher import match_corners
from torchsfm.estimators.two_view_geometry import estimate_fundamental

DEFAULT_DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--data", type=Path, default=DEFAULT_DATA)
    args = parser.parse_args()
    rows = {True: [], False: []}
    for pair in ground_truth_pairs(args.data):
        F_true = pair.F
        grey = torch.stack([to_grey(read_image(pair.image1)), to_grey(read_image(pair.image2))])
        for subpixel in (True, False):
            config = with_overrides(Config(), [f"harris.subpixel={str(subpixel).lower()}", "fundamental.refine=false"])
            corners = detect_corners(grey, config.harris)
            p1, p2 = corners.of_image(0), corners.of_image(1)
            matches = match_corners(grey[0], grey[1], p1, p2, config.matching)
            x1, x2 = p1[matches.index1].double(), p2[matches.index2].double()
            ransac = estimate_fundamental(x1, x2, config=config, generator=torch.Generator().manual_seed(0))
            inliers = ransac.inlier_mask
            F_lm, _ = refine_fundamental(ransac.F[None], x1[None], x2[None], inliers.double()[None], config.lm)
            row = {"inliers": float(inliers.sum())}
            for stage, F in (("before", ransac.F), ("after", F_lm[0])):
                row[f"sampson_{stage}"] = sampson_error(F, x1[inliers], x2[inliers]).mean().item()
                row[f"epipolar_{stage}"] = symmetric_epipolar_distance(F, x1[inliers], x2[inliers]).square().mean().item()
            row["truth_median"] = symmetric_epipolar_distance(F_true, x1[inliers], x2[inliers]).median().item()
            rows[subpixel].append(row)
    print(f"means over {len(rows[True])} pairs (px²; the last row in px)")
    print(f"{'':40s} {'sub-pixel before':>17s} {'after LM':>10s} {'pixel before':>13s} {'after LM':>10s}")
    mean = lambda key, sub: statistics.mean(r[key] for r in rows[sub])  # noqa: E731
    print(f"{'inliers':40s} {mean('inliers', True):17.1f} {'':>10s} {mean('inliers', False):13.1f}")
    print(f"{'Sampson error per inlier':40s} {mean('sampson_before', True):17.4f} {mean('sampson_after', True):10.4f} "
          f"{mean('sampson_before', False):13.4f} {mean('sampson_after', False):10.4f}")
    print(f"{'squared epipolar distance per inlier':40s} {mean('epipolar_before', True):17.4f} {mean('epipolar_after', True):10.4f} "
          f"{mean('epipolar_before', False):13.4f} {mean('epipolar_after', False):10.4f}")
    print(f"{'median distance to the true epipolar lines':40s} {mean('truth_median', True):17.4f} {'':>10s} {mean('truth_median', False):13.4f}")


if __name__ == "__main__":
    main()
