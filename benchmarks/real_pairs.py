"""Robust F on real putative matches: torchsfm's RANSAC beside OpenCV's, against ground truth.

The thesis' matcher (Harris corners, NCC in a 100 px disc, strength measure, relaxation; no
guidance) on Strecha fountain-P11 and Herz-Jesu-P8 pairs (i, i + g), g = 1, 2, 3 (fountain) and
1, 2 (Herz-Jesu), every other i: wider pairs hold fewer and less reliable matches. A match is true
when its Sampson distance to the ground-truth F is below 1 px. Per pair: matches, the true share,
and how well the strength measure ranks them (AUC: the chance that a true match scores above a
false one). Per method: milliseconds per call, RANSAC trials (torchsfm), and the recall and
precision of its inlier mask against the true matches (1 px threshold, confidence 0.99, 10 000
trials at most). Methods: ``estimate_fundamental`` (bucketed RANSAC, LO, LM), OpenCV USAC_MAGSAC,
and OpenCV USAC_PROSAC given the matches sorted by the strength measure (what a quality order
buys a C++ RANSAC on these matches), each over seeds 0-2 (the worst recall and precision of the
three, the median time). Last, medians over the pairs and the worst pair, over the pairs with
at least ``MIN_TRUE`` true matches (a pair whose matcher found fewer — Herz-Jesu 4-6, where the
disc cannot follow the motion and 1 % of the matches are true — has no F to recover: listed, not
summarised).

    pip install -e .[bench]
    python benchmarks/real_pairs.py [--data ../shared/data] [--threads 2]
"""

from __future__ import annotations

import argparse
import statistics
import time
from pathlib import Path

import torch

import torchsfm
from torchsfm.config import Config
from torchsfm.features.harris import detect_corners
from torchsfm.geometry.fundamental import sampson_error
from torchsfm.geometry.rotation import skew
from torchsfm.images import read_image, to_grey
from torchsfm.io.datasets import read_strecha
from torchsfm.matching.matcher import PutativeMatches, match_corners

DEFAULT_DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data"
PAIRS = {"strecha_fountain_P11": (1, 2, 3), "strecha_herzjesu_P8": (1, 2)}
SEEDS = (0, 1, 2)
MIN_TRUE = 20


def match_strength(matches: PutativeMatches, num_points2: int) -> torch.Tensor:
    """(M,) the strength measure of every accepted match (its candidate's)."""
    candidate_key = matches.candidates.index1 * num_points2 + matches.candidates.index2
    ordered, position = candidate_key.sort()
    return matches.strength[position[torch.searchsorted(ordered, matches.index1 * num_points2 + matches.index2)]]


def recall_precision(mask: torch.Tensor, true: torch.Tensor) -> tuple[float, float]:
    hits = float((mask & true).sum())
    return hits / max(float(true.sum()), 1.0), hits / max(float(mask.sum()), 1.0)


def torchsfm_method(x1, x2, strength, seed):
    start = time.perf_counter()
    result = torchsfm.estimate_fundamental(x1, x2, generator=torch.Generator().manual_seed(seed))
    return time.perf_counter() - start, result.inlier_mask, int(result.num_trials)


def opencv_method(flag, ranked: bool):
    import cv2

    def run(x1, x2, strength, seed):
        order = strength.argsort(descending=True) if ranked else torch.arange(x1.shape[0])
        cv2.setRNGSeed(seed)
        start = time.perf_counter()
        _, found = cv2.findFundamentalMat(x1[order].numpy(), x2[order].numpy(), flag, 1.0, 0.99, 10_000)
        seconds = time.perf_counter() - start
        mask = torch.zeros(x1.shape[0], dtype=torch.bool)
        if found is not None:
            mask[order] = torch.from_numpy(found.ravel().astype(bool))
        return seconds, mask, None
    return run


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--data", type=Path, default=DEFAULT_DATA)
    parser.add_argument("--threads", type=int, default=2)
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    methods = {"torchsfm": torchsfm_method}
    try:
        import cv2

        cv2.setNumThreads(args.threads)
        methods["OpenCV MAGSAC"] = opencv_method(cv2.USAC_MAGSAC, ranked=False)
        methods["OpenCV PROSAC"] = opencv_method(cv2.USAC_PROSAC, ranked=True)
    except ImportError as error:
        print(f"OpenCV not installed ({error}); pip install -e .[bench]")
    config = Config()
    heading = "  ".join(f"{name + ' ms / trials / recall / precision':>44s}" for name in methods)
    print(f"{'pair':16s} {'matches':>7s} {'true':>5s} {'AUC':>5s}  {heading}")
    rows = {name: [] for name in methods}
    warm = True
    for folder, gaps in PAIRS.items():
        sequence = read_strecha(args.data / folder)
        greys = [to_grey(read_image(path)) for path in sequence.images]
        corners = [detect_corners(grey[None], config.harris).of_image(0).double() for grey in greys]
        for gap in gaps:
            for i in range(0, len(greys) - gap, 2):
                j = i + gap
                matches = match_corners(greys[i], greys[j], corners[i], corners[j], config.matching)
                strength = match_strength(matches, corners[j].shape[0])
                x1, x2 = corners[i][matches.index1], corners[j][matches.index2]
                R, t = sequence.relative_pose(i, j)
                F_true = torch.linalg.inv(sequence.K[j]).T @ skew(t) @ R @ torch.linalg.inv(sequence.K[i])
                true = sampson_error(F_true, x1, x2) < 1.0
                auc = float((strength[true][:, None] > strength[~true][None]).double().mean()) if bool((~true).any()) else float("nan")
                cells = []
                for name, method in methods.items():
                    if warm:
                        method(x1, x2, strength, 0)
                    runs = [method(x1, x2, strength, seed) for seed in SEEDS]
                    seconds = statistics.median(run[0] for run in runs)
                    recall, precision = (min(values) for values in zip(*(recall_precision(run[1], true) for run in runs)))
                    trials = statistics.median(run[2] for run in runs) if runs[0][2] is not None else None
                    if int(true.sum()) >= MIN_TRUE:
                        rows[name].append((1000 * seconds, recall, precision))
                    cells.append(f"{1000 * seconds:8.1f} / {'-' if trials is None else int(trials):>5} / {recall:.3f} / {precision:.3f}")
                warm = False
                name = f"{folder.split('_')[1]} {i}-{j}"
                results = "  ".join(f"{cell:>44s}" for cell in cells)
                print(f"{name:16s} {x1.shape[0]:7d} {float(true.double().mean()):5.2f} {auc:5.2f}  {results}")
    print(f"\nover the {len(rows['torchsfm'])} pairs with {MIN_TRUE} true matches or more")
    print(f"{'method':16s} {'median ms':>9s} {'median recall':>13s} {'worst recall':>12s} "
          f"{'median precision':>16s} {'worst precision':>15s}")
    for name, values in rows.items():
        times, recalls, precisions = zip(*values)
        print(f"{name:16s} {statistics.median(times):9.1f} {statistics.median(recalls):13.3f} {min(recalls):12.3f} "
              f"{statistics.median(precisions):16.3f} {min(precisions):15.3f}")


if __name__ == "__main__":
    main()
