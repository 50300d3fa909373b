"""Reproduce thesis Figures 3.18 / 3.19: triangulation accuracy against image noise.

Random scenes are projected into two views, Gaussian noise of std σ is added to the pixels, and
every method of §3.5 triangulates them, (a) with the Euclidean cameras and (b) after a projective
change of frame H chosen, as in the thesis, so that the first camera becomes [I | 0] (H⁻¹ =
[[K⁻¹, 0], [vᵀ, 1]] with a random v). The median reprojection error (pixels, RMS over the two
images) of the triangulated points is written per method and noise level to a CSV file and
plotted to a PNG (needs matplotlib: ``pip install -e .[plot]``).

    python examples/triangulation_study.py [--out outputs/triangulation_study] [--points 2000]
"""

from __future__ import annotations

import argparse
import csv
from pathlib import Path

import torch

from torchsfm.camera import project
from torchsfm.geometry.triangulation import TRIANGULATION_METHODS
from torchsfm.testing import synthetic_two_view

NOISE_LEVELS = [0.0, 0.25, 0.5, 0.75, 1.0, 1.5, 2.0, 2.5, 3.0]


def projective_frame(K: torch.Tensor, generator: torch.Generator) -> torch.Tensor:
    """H⁻¹ mapping P1 = K [I | 0] to [I | 0], with a random plane at infinity (a real projectivity)."""
    H_inv = torch.zeros(4, 4, dtype=torch.float64)
    H_inv[:3, :3] = torch.linalg.inv(K)
    H_inv[3, :3] = 0.1 * torch.randn(3, generator=generator, dtype=torch.float64)
    H_inv[3, 3] = 1.0
    return H_inv


def reprojection_rms(X: torch.Tensor, x1: torch.Tensor, x2: torch.Tensor, P1: torch.Tensor, P2: torch.Tensor) -> torch.Tensor:
    """Per-point RMS reprojection error over the two images (pixels): (N,)."""
    squared = ((project(P1, X) - x1) ** 2).sum(-1) + ((project(P2, X) - x2) ** 2).sum(-1)
    return (squared / 2).sqrt()


def run(num_points: int, num_scenes: int) -> list[dict[str, float | str]]:
    rows = []
    for noise in NOISE_LEVELS:
        errors = {(frame, method): [] for frame in ("euclidean", "projective") for method in TRIANGULATION_METHODS}
        for scene_index in range(num_scenes):
            # the same scenes, frames and standardized noise at every level (common random numbers)
            scene = synthetic_two_view(num_points, noise=noise, seed=scene_index)
            H_inv = projective_frame(scene.K1, torch.Generator().manual_seed(scene_index))
            frames = {"euclidean": (scene.P1, scene.P2), "projective": (scene.P1 @ H_inv, scene.P2 @ H_inv)}
            for frame, (P1, P2) in frames.items():
                for method, triangulate in TRIANGULATION_METHODS.items():
                    X = triangulate(scene.x1, scene.x2, P1, P2)
                    X = X[..., :3] / X[..., 3:]
                    errors[frame, method].append(reprojection_rms(X, scene.x1, scene.x2, P1, P2))
        for (frame, method), values in errors.items():
            rows.append({"frame": frame, "method": method, "noise_px": noise,
                         "median_reprojection_px": torch.cat(values).median().item()})
    return rows


def plot(rows: list[dict[str, float | str]], path: Path) -> None:
    try:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError as error:
        raise SystemExit(f"the PNG needs matplotlib (pip install -e .[plot]): {error}") from None
    figure, axes = plt.subplots(1, 2, figsize=(11, 4.2), sharey=False)
    for axis, frame, title in zip(axes, ("projective", "euclidean"), ("Fig. 3.18: projective frame", "Fig. 3.19: Euclidean frame")):
        for method in TRIANGULATION_METHODS:
            points = [(row["noise_px"], row["median_reprojection_px"]) for row in rows if row["frame"] == frame and row["method"] == method]
            axis.plot(*zip(*points), marker="o", markersize=3, label=method)
        axis.set_title(title)
        axis.set_xlabel("noise σ (pixels)")
        axis.set_ylabel("median reprojection error (pixels)")
        axis.grid(alpha=0.3)
    axes[0].legend()
    figure.tight_layout()
    temporary = path.with_suffix(".tmp.png")
    figure.savefig(temporary, dpi=120)
    temporary.replace(path)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--out", type=Path, default=Path("outputs/triangulation_study"))
    parser.add_argument("--points", type=int, default=2000)
    parser.add_argument("--scenes", type=int, default=5)
    args = parser.parse_args()
    args.out.mkdir(parents=True, exist_ok=True)
    rows = run(args.points // args.scenes, args.scenes)
    csv_path = args.out / "triangulation_study.csv"
    temporary = csv_path.with_suffix(".tmp")
    with temporary.open("w", newline="") as handle:
        writer = csv.DictWriter(handle, fieldnames=list(rows[0]))
        writer.writeheader()
        writer.writerows(rows)
    temporary.replace(csv_path)
    plot(rows, args.out / "triangulation_study.png")
    for frame in ("projective", "euclidean"):
        print(f"{frame} frame: median reprojection error (px) by noise σ")
        print(f"{'method':16s}" + "".join(f"{noise:8.2f}" for noise in NOISE_LEVELS))
        for method in TRIANGULATION_METHODS:
            values = [row["median_reprojection_px"] for row in rows if row["frame"] == frame and row["method"] == method]
            print(f"{method:16s}" + "".join(f"{value:8.4f}" for value in values))
    print(f"wrote {csv_path} and {args.out / 'triangulation_study.png'}")


if __name__ == "__main__":
    main()
