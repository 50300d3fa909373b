"""Two-view geometry on the Oxford VGG ground truth with 40% of the matches replaced by noise.

For every adjacent view pair of Model House and Merton College I, a fraction of the true
correspondences of view j is replaced by uniform random pixels; ``estimate_fundamental`` and
``estimate_relative_pose`` (K from the ground-truth P) then run, and the inlier recall/precision
and the rotation / translation-direction errors against the ground-truth cameras are printed.

    python examples/oxford_two_view.py [--data ../shared/data] [--seeds 5] [--outliers 0.4]
"""

from __future__ import annotations

import argparse
import statistics
from pathlib import Path

import torchsfm
from torchsfm.io.datasets import read_oxford_multiview
from torchsfm.testing import evaluate_two_view_pair

DATASETS = {"oxford_house": (768, 576), "oxford_merton1": (1024, 768)}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--data", type=Path, default=Path(__file__).resolve().parents[1].parent / "shared" / "data")
    parser.add_argument("--seeds", type=int, default=5)
    parser.add_argument("--outliers", type=float, default=0.4)
    parser.add_argument("--set", action="append", default=[], metavar="KEY=VALUE", help="config override")
    args = parser.parse_args()
    config = torchsfm.with_overrides(torchsfm.Config(), args.set)
    keys = ["F_recall", "F_precision", "pose_recall", "pose_precision", "R_error_deg", "t_error_deg"]
    print(f"{args.outliers:.0%} of matches replaced by random pixels; median [worst] over {args.seeds} seeds")
    print(f"{'pair':24s} {'N':>4s} " + " ".join(f"{key:>20s}" for key in keys))
    totals = []
    for name, size in DATASETS.items():
        dataset = read_oxford_multiview(args.data / name)
        for i in range(dataset.num_views - 1):
            runs = [evaluate_two_view_pair(dataset, i, i + 1, size, args.outliers, seed, config) for seed in range(args.seeds)]
            cells = []
            for key in keys:
                values = [run[key] for run in runs]
                worst = max(values) if key.endswith("deg") else min(values)
                cells.append(f"{statistics.median(values):10.3f} [{worst:6.3f}]")
            print(f"{name} {i}-{i + 1:<10d} {int(runs[0]['matches']):4d} " + " ".join(f"{cell:>20s}" for cell in cells))
            totals.extend(runs)
    pooled = {key: sum(run[key] for run in totals) for key in ("F_hits", "F_kept", "pose_hits", "pose_kept", "true_inliers")}
    print(f"pooled over all pairs and seeds: F recall {pooled['F_hits'] / pooled['true_inliers']:.4f}, "
          f"F precision {pooled['F_hits'] / pooled['F_kept']:.4f}, pose recall {pooled['pose_hits'] / pooled['true_inliers']:.4f}, "
          f"pose precision {pooled['pose_hits'] / pooled['pose_kept']:.4f}")


if __name__ == "__main__":
    main()
