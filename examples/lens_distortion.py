"""A lens whose distortion nobody gives, and no K: which camera model the observations choose.

Strecha fountain-P11 and Herz-Jesu-P8 are resampled as a lens with radial distortion k1 (about
the ground truth's principal point, normalized coordinates) would see them — barrel and
pincushion, k1 in ``--k1`` (0: the images as they are) — and reconstructed without K, with each
``reconstruction.refined_intrinsics`` setting: the default ``f,cx,cy|f,k1`` (both alternatives
refined from the same start, the smallest geometric AIC kept), and each alternative alone. Printed
per run: views registered, median centre error (% of the path extent) and rotation error against
the ground truth, and what the intrinsics refinement kept. ``--views`` reconstructs those views of
each set only (e.g. three: few views pin k1 and the principal point loosely). Beside them, where
it is installed (``bench`` extra), pycolmap at its own default without K on the same images
(SIMPLE_RADIAL: one focal length and k1 refined, the principal point at the centre; through
``examples/real_world.py``).

    python examples/lens_distortion.py [--data ../shared/data] [--k1 -0.05,-0.02,0,0.02,0.05] [--views 0,2,4] [--seed 0] [--no-colmap]
"""

from __future__ import annotations

import argparse
from pathlib import Path

from PIL import Image

import torch

import torchsfm
from torchsfm.camera import distort_image
from torchsfm.config import Config, with_overrides
from torchsfm.evaluation import camera_errors
from torchsfm.images import read_image
from torchsfm.io.datasets import StrechaSequence, read_strecha

from real_world import run_pycolmap  # pycolmap's run and camera errors in examples/real_world.py

DEFAULT_DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data"
SETS = {"fountain-P11": "strecha_fountain_P11", "Herz-Jesu-P8": "strecha_herzjesu_P8"}
SETTINGS = ("f,cx,cy|f,k1", "f,cx,cy", "f,k1")


def distorted_images(data: Path, folder: str, k1: float, views: list[int] | None) -> tuple[list[torch.Tensor], object]:
    """The set's images (``views`` of them, or all) as a lens with radial coefficient ``k1``
    sees them, and the set (those views)."""
    sequence = read_strecha(data / folder)
    if views is not None:
        sequence = StrechaSequence(images=[sequence.images[v] for v in views], K=sequence.K[views], R=sequence.R[views], t=sequence.t[views])
    lens = torch.tensor([k1, 0.0], dtype=torch.float64)
    images = [read_image(path) if k1 == 0 else
              distort_image(read_image(path)[None].float(), sequence.K[v], lens)[0].round().clamp(0, 255).to(torch.uint8)
              for v, path in enumerate(sequence.images)]
    return images, sequence


def pycolmap_row(images: list[torch.Tensor], sequence, folder: Path) -> str:
    """pycolmap without K on ``images`` (written to ``folder`` as PNG): its row of figures."""
    folder.mkdir(parents=True, exist_ok=True)
    paths = []
    for v, image in enumerate(images):
        paths.append(folder / f"{v:04d}.png")
        Image.fromarray(image.permute(1, 2, 0).squeeze(-1).numpy()).save(paths[-1])
    return run_pycolmap(StrechaSequence(images=paths, K=sequence.K, R=sequence.R, t=sequence.t), folder / "colmap", with_K=False)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--data", type=Path, default=DEFAULT_DATA)
    parser.add_argument("--k1", default="-0.05,-0.02,0,0.02,0.05", help="radial coefficients, comma-separated")
    parser.add_argument("--views", default="", help="view indices of each set, comma-separated (empty: all)")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--no-colmap", action="store_true")
    parser.add_argument("--work", type=Path, default=Path("outputs/lens_distortion"), help="pycolmap's images and databases")
    args = parser.parse_args()
    views = [int(view) for view in args.views.split(",")] if args.views else None
    print(f"{'set':13s} {'k1':>6s} {'refined_intrinsics':19s} {'views':>6s} {'centre %':>9s} {'rot °':>7s}  kept")
    for name, folder in SETS.items():
        for k1 in (float(value) for value in args.k1.split(",")):
            images, sequence = distorted_images(args.data, folder, k1, views)
            for setting in SETTINGS:
                messages: list[str] = []
                config = with_overrides(Config(), [f"reconstruction.refined_intrinsics={setting}"])
                model = torchsfm.reconstruct(images, config=config, generator=torch.Generator().manual_seed(args.seed),
                                             progress=messages.append)
                registered = model.view_indices
                errors = camera_errors(model.cameras.R, model.cameras.t, sequence.R[registered], sequence.t[registered])
                report = next((message for message in messages if message.startswith("intrinsics")), "no refinement reported")
                kept = report.split(": ", 1)[-1].split(" — ")[0]
                print(f"{name:13s} {k1:+6.2f} {setting:19s} {len(registered):>2d}/{len(images):<3d} "
                      f"{100 * float(errors.centre.median() / errors.extent):9.3f} {float(errors.rotation.median()):7.3f}  {kept}",
                      flush=True)
            if not args.no_colmap:
                print(f"{name:13s} {k1:+6.2f} {'pycolmap':19s} {pycolmap_row(images, sequence, args.work / f'{folder}_{k1:+.2f}')}", flush=True)


if __name__ == "__main__":
    main()
