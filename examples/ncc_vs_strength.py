"""Thesis Figure 3.8 as numbers: NCC alone vs NCC + strength measure, before RANSAC.

For every neighbouring pair of Strecha fountain-P11 and Herz-Jesu-P8 and every pair of Merton
College I, the putative matches of the relaxation ranked by NCC alone and by the strength measure
are counted, and their precision measured against the ground-truth epipolar geometry (a match
is correct when its symmetric epipolar distance is below 1.5 px).

    python examples/ncc_vs_strength.py [--data ../shared/data]
"""

from __future__ import annotations

import argparse
from pathlib import Path

import torch

from torchsfm.config import Config, MatchingConfig
from torchsfm.features.harris import detect_corners
from torchsfm.geometry.fundamental import symmetric_epipolar_distance
from torchsfm.io.datasets import ground_truth_pairs
from torchsfm.images import read_image, to_grey
from torchsfm.matching.matcher import match_corners

DEFAULT_DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--data", type=Path, default=DEFAULT_DATA)
    args = parser.parse_args()
    config = Config()
    print(f"{'pair':26s} {'NCC matches':>12s} {'NCC precision':>14s} {'SM matches':>11s} {'SM precision':>13s}")
    totals = {"ncc": [0, 0], "sm": [0, 0]}
    for pair in ground_truth_pairs(args.data):
        name, F = pair.name, pair.F
        grey = torch.stack([to_grey(read_image(pair.image1)), to_grey(read_image(pair.image2))])
        corners = detect_corners(grey, config.harris)
        points1, points2 = corners.of_image(0), corners.of_image(1)
        cells = []
        for strength in ("ncc", "sm"):
            matching = MatchingConfig(**{**config.matching.__dict__, "strength": strength})
            matches = match_corners(grey[0], grey[1], points1, points2, matching)
            distance = symmetric_epipolar_distance(F, points1[matches.index1].double(), points2[matches.index2].double())
            correct = int((distance < 1.5).sum())
            totals[strength][0] += correct
            totals[strength][1] += distance.numel()
            cells.append(f"{distance.numel():12d} {correct / max(distance.numel(), 1):14.3f}")
        print(f"{name:26s} {cells[0]} {cells[1][1:]}")
    print(f"{'all pairs':26s} {totals['ncc'][1]:12d} {totals['ncc'][0] / totals['ncc'][1]:14.3f}"
          f"{totals['sm'][1]:12d} {totals['sm'][0] / totals['sm'][1]:13.3f}")


if __name__ == "__main__":
    main()
