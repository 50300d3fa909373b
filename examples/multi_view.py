"""Incremental reconstruction of the Strecha sequences from their images and K alone (issue #4).

For fountain-P11 (11 views) and Herz-Jesu-P8 (8 views): views registered, points, mean track
length, reprojection RMS, time per stage, and the camera errors after a similarity alignment to
the ground truth (centre error as a share of the camera path's extent, rotation error; see
:func:`torchsfm.evaluation.camera_errors`). With ``--out`` the models are written too.

    python examples/multi_view.py [--data ../shared/data] [--out outputs/multi_view]
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import torch

import torchsfm
from torchsfm.evaluation import camera_errors
from torchsfm.io.colmap import write_colmap_text
from torchsfm.io.datasets import read_strecha
from torchsfm.io.ply import write_ply

DEFAULT_DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data"


def evaluate(name: str, data: Path, out: Path | None) -> dict:
    sequence = read_strecha(data / name)
    start = time.perf_counter()
    model = torchsfm.reconstruct(sequence.images, sequence.K, generator=torch.Generator().manual_seed(0))
    seconds = time.perf_counter() - start
    index = model.view_indices
    errors = camera_errors(model.cameras.R, model.cameras.t, sequence.R[index], sequence.t[index])
    if out is not None:
        write_colmap_text(out / name / "colmap", model)
        write_ply(out / name / "points.ply", model.points3d, model.colors)
    return {"views": f"{model.num_views}/{len(sequence.images)}", "points": model.num_points,
            "track": model.observation_points.numel() / max(model.num_points, 1), "rms": model.reprojection_rms(),
            "centre_pct": 100 * float(errors.centre.median()) / errors.extent, "centre_max_pct": 100 * float(errors.centre.max()) / errors.extent,
            "rotation": float(errors.rotation.median()), "rotation_max": float(errors.rotation.max()),
            "relative": float(errors.relative_rotation.median()), "seconds": seconds, "timings": model.timings}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--data", type=Path, default=DEFAULT_DATA)
    parser.add_argument("--out", type=Path)
    args = parser.parse_args()
    for name in ("strecha_fountain_P11", "strecha_herzjesu_P8"):
        row = evaluate(name, args.data, args.out)
        print(f"{name}: views {row['views']}, points {row['points']}, mean track {row['track']:.2f}, reprojection RMS {row['rms']:.3f} px, "
              f"{row['seconds']:.1f} s")
        print(f"  centre error median {row['centre_pct']:.3f}% (max {row['centre_max_pct']:.3f}%) of the path extent; rotation error "
              f"median {row['rotation']:.3f} deg (max {row['rotation_max']:.3f}); relative rotations median {row['relative']:.3f} deg")
        print("  seconds per stage: " + ", ".join(f"{stage} {value:.2f}" for stage, value in row["timings"].items()))


if __name__ == "__main__":
    main()
