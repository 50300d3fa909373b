"""Motion segmentation on real labelled tracks: per-sequence misclassification (issue: multi-body).

Data (``../shared/data``): every rigid sequence of ``hopkins155_subset`` + ``hopkins155_dev``
(all frames; static-camera sequences included; the non-rigid ``arm``, ``articulated``,
``dancing`` left out), every clip of ``kt3dmoseg_dev`` (KITTI tracks with visibility gaps), and
the three scenes of ``adelaidermf_F`` (two views, per-match labels with gross outliers). Row
set ``Hopkins155-2``: the two-motion sequences Hopkins155 forms from each three-motion one
(every two of its groups; ``_g12`` the two objects without the background, ``_g13`` and
``_g23`` an object and the background, as the benchmark names them) — 54 of its 120
two-motion sequences are such subsets.

Columns: misclassification of :func:`torchsfm.segment_motions` with the number of motions found by
the method (``found``) and given (``given``), and of a baseline written with OpenCV: sequential
RANSAC on F (USAC_MAGSAC, 1 px, p = 0.99; given the number of motions; on the frame pair
(0, F - 1), for KT3DMoSeg the pair at least (F - 1) / 2 apart that shares most tracks; the
tracks not seen in that pair are left unassigned). Misclassification: the share of tracks whose
label disagrees with the ground truth under the best one-to-one assignment; unassigned tracks
count as wrong (for AdelaideRMF, "unassigned" is right for a labelled outlier).

Published anchors (whole data sets, k given, so only a rough yardstick for these subsets):
Hopkins155 — SSC 2.2 % mean (Elhamifar & Vidal, TPAMI 2013), LRR 1.6 % (Liu et al., TPAMI 2013),
MSMC 0.3–0.8 % (Xu, Cheong & Li, CVPR 2018); KT3DMoSeg — MSMC 8–10 % (Xu et al., 2018), SSC
21–26 %; AdelaideRMF F — RPA 10 %, T-linkage 9–10 % (Magri & Fusiello, 2015–2016).

The figures depend on the random hypotheses: ``--seeds N`` runs N seeds and reports means over
them (per sequence, pooled, and the pooled mean of each seed with their spread).

With ``--noise SIGMA``, Gaussian noise of SIGMA px (seeded) is added to every tracked position
first (``MotionTracks.with_noise``): how the figures hold for a tracker noisier than these data
sets' (Hopkins155's tracks lie 0.05-0.2 px from one F per frame pair).

With ``--frames first-half`` (or ``every-other``), each sequence is cut to the first half of its
frames (or to every other frame; ``MotionTracks.cut``, the tracks seen in fewer than 3 of
them dropped; two-view sets as they are): how the figures hold on shorter sequences, with less
motion between their ends, and at a lower frame rate.

With ``--tracks SHARE``, each track is kept with probability SHARE (seeded;
``MotionTracks.subset``), after the frames are cut: how the figures hold for a sparser tracker,
with fewer tracks on every motion (an object left with fewer than 12 cannot be found).

With ``--synthetic``, the rows are synthetic scenes instead, where every label is known
(``torchsfm.testing.synthetic_moving_scene``: a static wall and free points, two objects moving
independently, 10 % random-pixel strays labelled as outliers, 0.3 px noise): seeds 0-9 at 5, 8
and 12 frames, each with a camera that moves, with a still camera (``still``) and with objects
at constant velocity (``steady``) — shapes of scene and motion the real sets hold few of.

With ``--png DIR``, a picture per sequence of its tracks coloured by the labels found
(``torchsfm.visualization.segmentation_figure``; the static scene grey, unassigned black).

    python examples/motion_segmentation.py [--data ../shared/data] [--png DIR] [--seed 0] [--seeds 1] [--noise 0]
        [--frames all|first-half|every-other] [--tracks 1] [--synthetic] [--set KEY=VALUE ...]
"""

from __future__ import annotations

import argparse
import statistics
import time
from pathlib import Path

import torch

from torchsfm.config import Config, with_overrides
from torchsfm.evaluation import misclassification
from torchsfm.io.datasets import FRAME_CUTS, MotionTracks, read_adelaidermf, read_hopkins155, read_kt3dmoseg
from torchsfm.moving.imor import MIN_VECTORS
from torchsfm.moving.segmentation import segment_motions
from torchsfm.testing import synthetic_moving_scene
from torchsfm.visualization import segmentation_figure, write_png

DEFAULT_DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data"
NON_RIGID = {"arm", "articulated", "dancing"}


def sequences(data: Path) -> list[tuple[str, MotionTracks]]:
    """(data set, sequence) for every sequence the table covers."""
    found = []
    for root in ("hopkins155_subset", "hopkins155_dev"):
        for folder in sorted(p for p in (data / root).iterdir() if p.is_dir() and p.name not in NON_RIGID):
            found.append(("Hopkins155", read_hopkins155(folder)))
    for folder in sorted(p for p in (data / "kt3dmoseg_dev").iterdir() if p.is_dir()):
        found.append(("KT3DMoSeg", read_kt3dmoseg(folder)))
    for path in sorted((data / "adelaidermf_F").glob("*.mat")):
        found.append(("AdelaideRMF-F", read_adelaidermf(path)))
    found += [("Hopkins155-2", pair) for name, sequence in found if name == "Hopkins155"
              for pair in two_motion_subsets(sequence)]
    return found


def synthetic_sequences() -> list[tuple[str, MotionTracks]]:
    """("Synthetic", sequence) for seeds 0-9 of ``synthetic_moving_scene`` at 5, 8 and 12 frames,
    each with a moving camera, a still one and objects at constant velocity (see the module
    docstring); an object left with fewer tracks in view than a motion needs (12) counts as
    outliers."""
    kinds = {"moving": {}, "still": {"static_camera": True}, "steady": {"constant_velocity": True}}
    found = []
    for kind, options in kinds.items():
        for frames in (5, 8, 12):
            for seed in range(10):
                scene = synthetic_moving_scene(seed, num_frames=frames, **options)
                found.append(("Synthetic", MotionTracks(f"{kind}_F{frames}_s{seed}", scene.tracks, scene.motion_labels(MIN_VECTORS),
                                                        scene.image_size, has_outliers=True)))
    return found


def two_motion_subsets(sequence: MotionTracks) -> list[MotionTracks]:
    """Every two groups of a three-motion sequence as a sequence of its own, named as Hopkins155
    names them (its groups 1, 2 the objects — our labels 1, 2 — and 3 the background, our 0),
    labels 0, 1 in their order; none for a two-motion sequence."""
    if int(sequence.labels.max()) != 2:
        return []
    subsets = []
    for groups, suffix in (((1, 2), "g12"), ((0, 1), "g13"), ((0, 2), "g23")):
        kept = torch.isin(sequence.labels, torch.tensor(groups))
        subsets.append(MotionTracks(name=f"{sequence.name}_{suffix}", tracks=sequence.tracks[:, kept],
                                    labels=(sequence.labels[kept] == groups[1]).long(),
                                    image_size=sequence.image_size, visible=sequence.visible[:, kept]))
    return subsets


def opencv_sequential_ransac(sequence: MotionTracks, motions: int) -> torch.Tensor | None:
    """Sequential RANSAC on F between two frames (module docstring): (N,) labels, or None
    without OpenCV. A round in which OpenCV finds no F, or raises (it did on a sequence cut to half
    its tracks), ends the sequence: the tracks left stay unassigned."""
    try:
        import cv2
        import numpy as np
    except ImportError:
        return None
    tracks, visible = sequence.tracks, sequence.visible
    F = tracks.shape[0]
    pairs = [(a, b) for a in range(F) for b in range(a + (F - 1) // 2, F) if b > a]
    a, b = max(pairs, key=lambda pair: int((visible[pair[0]] & visible[pair[1]]).sum()))
    labels = torch.full((tracks.shape[1],), -1, dtype=torch.long)
    remaining = torch.nonzero(visible[a] & visible[b])[:, 0]
    for motion in range(motions):
        if remaining.numel() < 8:
            break
        if motion == motions - 1 and not sequence.has_outliers:
            labels[remaining] = motion
            break
        x1, x2 = (tracks[f, remaining].numpy().astype(np.float64) for f in (a, b))
        try:
            _, mask = cv2.findFundamentalMat(x1, x2, cv2.USAC_MAGSAC, 1.0, 0.99)
        except cv2.error:
            mask = None
        if mask is None:
            break
        inliers = torch.from_numpy(mask.ravel().astype(bool))
        labels[remaining[inliers]] = motion
        remaining = remaining[~inliers]
    return labels


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--data", type=Path, default=DEFAULT_DATA)
    parser.add_argument("--png", type=Path, default=None, help="write a picture of each segmentation here")
    parser.add_argument("--seed", type=int, default=0, help="seed of every random choice (the figures vary with it)")
    parser.add_argument("--seeds", type=int, default=1, help="run seeds seed .. seed + seeds - 1; figures are means over them")
    parser.add_argument("--noise", type=float, default=0.0,
                        help="Gaussian noise (px, seeded) added to every tracked position: a noisier tracker's view")
    parser.add_argument("--frames", choices=sorted(FRAME_CUTS), default="all",
                        help="cut each sequence to the first half of its frames or every other frame")
    parser.add_argument("--tracks", type=float, default=1.0,
                        help="share of the tracks kept (seeded): a sparser tracker's view")
    parser.add_argument("--synthetic", action="store_true", help="synthetic scenes instead of the real data sets")
    parser.add_argument("--set", nargs="*", default=[], metavar="KEY=VALUE",
                        help="config overrides, e.g. segmentation.models=fundamental,affine")
    args = parser.parse_args()
    config = with_overrides(Config(), args.set).segmentation
    seeds = range(args.seed, args.seed + args.seeds)
    table: dict[str, list[tuple[list[float], list[float], float | None, list[bool]]]] = {}
    print(f"{'data set':14s} {'sequence':16s} {'F':>3s} {'N':>5s} {'k':>2s} {'found':>5s} "
          f"{'found %':>8s} {'given %':>8s} {'OpenCV %':>9s} {'s':>6s}")
    for name, sequence in synthetic_sequences() if args.synthetic else sequences(args.data):
        sequence = sequence.cut(args.frames)
        sequence = sequence.subset(args.tracks)  # share 1 keeps every track
        sequence = sequence.with_noise(args.noise) if args.noise else sequence
        truth = sequence.labels
        motions = int(truth.max()) + 1
        found_errors, given_errors, counts, seconds = [], [], [], 0.0
        for seed in seeds:
            start = time.perf_counter()
            found = segment_motions(sequence.tracks, sequence.visible, config=config,
                                    generator=torch.Generator().manual_seed(seed))
            seconds += time.perf_counter() - start
            given = segment_motions(sequence.tracks, sequence.visible, config=config, num_motions=motions,
                                    generator=torch.Generator().manual_seed(seed))
            found_errors.append(100 * misclassification(found.labels, truth))
            given_errors.append(100 * misclassification(given.labels, truth))
            counts.append(found.num_motions)
            if args.png is not None and seed == args.seed:
                picture = segmentation_figure(sequence.tracks, sequence.visible, found.labels, sequence.image_size)
                write_png(args.png / f"{sequence.name}.png", picture)
        baseline = opencv_sequential_ransac(sequence, motions)
        opencv = None if baseline is None else 100 * misclassification(baseline, truth)
        table.setdefault(name, []).append((found_errors, given_errors, opencv, [c == motions for c in counts]))
        found_count = str(counts[0]) if min(counts) == max(counts) else f"{min(counts)}-{max(counts)}"
        print(f"{name:14s} {sequence.name:16s} {sequence.tracks.shape[0]:3d} {truth.numel():5d} {motions:2d} "
              f"{found_count:>5s} {statistics.mean(found_errors):8.1f} {statistics.mean(given_errors):8.1f} "
              f"{'n/a' if opencv is None else f'{opencv:.1f}':>9s} {seconds / len(seeds):6.2f}", flush=True)
    print(f"\npooled over the sequences: mean / median / worst misclassification % (means over {len(seeds)} seed(s)), "
          "motions found right")
    for name, rows in table.items():
        for column, label in ((0, "found"), (1, "given"), (2, "OpenCV")):
            values = [row[column] if column == 2 else statistics.mean(row[column]) for row in rows]
            values = [value for value in values if value is not None]
            if values:
                print(f"{name:14s} {label:7s} {statistics.mean(values):6.2f} / {statistics.median(values):6.2f} / "
                      f"{max(values):6.2f}")
        right = sum(sum(row[3]) for row in rows)
        print(f"{name:14s} number of motions right in {right} of {len(rows) * len(seeds)} runs")
        if len(seeds) > 1:
            per_seed = [statistics.mean(row[0][k] for row in rows) for k in range(len(seeds))]
            print(f"{name:14s} found, mean of each seed: " + " ".join(f"{value:.2f}" for value in per_seed)
                  + f" (sd {statistics.stdev(per_seed):.2f})")


if __name__ == "__main__":
    main()
