"""A planar object moving through real images, reconstructed as its own model (issue: multi-body).

A 240 x 200 patch of another data set's photo is pasted into five consecutive frames of Strecha
fountain-P11 (a Herz-Jesu-P8 patch; start frames 0-6) and of Herz-Jesu-P8 (a fountain patch;
start frames 0-3), moving on its own across the images (:data:`POSITIONS`; the thesis' §5.5
experiment over five frames instead of three). ``torchsfm.reconstruct(..., moving_objects=
"reconstruct")`` runs on the pasted frames and on the clean ones. Per case: the body found on the
patch (views, points, the share of its points that lie on the patch), the shape of those points
against the patch — the patch's pixels (u, v, 0) are the truth up to a similarity: the RMS distance after a
similarity alignment, the RMS distance to the points' own plane, both in % of the patch's
diagonal, and the anisotropy (the ratio of the singular values of the affine map from the
points' plane to the patch, minus 1: 0 when the aspect ratio is right) — and the scene's camera
errors (largest rotation error, largest centre error over the path) with and without the patch.

    python examples/inserted_object.py [--data ../shared/data]
"""

from __future__ import annotations

import argparse
from pathlib import Path

import torch

import torchsfm
from torchsfm.errors import TorchSfmError
from torchsfm.evaluation import camera_errors, shape_errors
from torchsfm.images import read_image
from torchsfm.io.datasets import read_strecha
from torchsfm.testing import insert_moving_patch, patch_coordinates

DEFAULT_DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data"
POSITIONS = ((150, 260), (190, 245), (230, 235), (265, 250), (300, 270))  # the patch's top-left corner per frame (x, y)
PATCH = (slice(100, 300), slice(260, 500))  # rows, columns of the source photo


def body_on_patch(model: torchsfm.Reconstruction, boxes: torch.Tensor):
    """The moving body with the largest share of its points on the patch, that share, and its
    points' patch coordinates (:func:`~torchsfm.testing.patch_coordinates`; NaN off the patch),
    or (None, 0, None)."""
    best = (None, 0.0, None)
    for body in model.objects:
        if body.model is None:
            continue
        on_patch, uv = patch_coordinates(body.model, boxes)
        share = float(on_patch.double().mean())
        if share > best[1]:
            best = (body, share, uv)
    return best


def patch_shape(points: torch.Tensor, uv: torch.Tensor) -> tuple[float, float, float]:
    """(P, 3) body points against their (P, 2) patch coordinates: similarity RMS and planarity RMS
    (% of the patch's diagonal) and the anisotropy of the affine map plane -> patch (%)."""
    points, centred_uv = points.double(), uv - uv.mean(0)
    diagonal = float((uv.amax(0) - uv.amin(0)).norm())
    similarity = float(shape_errors(points, torch.cat([uv, torch.zeros_like(uv[:, :1])], dim=-1)).square().mean().sqrt())
    centred = points - points.mean(0)
    _, S, Vh = torch.linalg.svd(centred, full_matrices=False)  # S[2]: the out-of-plane spread
    scale = float(centred_uv.norm() / S[:2].norm())  # patch pixels per model unit
    planarity = scale * float(S[2]) / points.shape[0] ** 0.5
    singular = torch.linalg.svdvals(torch.linalg.lstsq(centred @ Vh[:2].T, centred_uv).solution)
    return 100 * similarity / diagonal, 100 * planarity / diagonal, 100 * float(singular[0] / singular[1] - 1)


def scene_errors(model: torchsfm.Reconstruction, sequence, frames: list[int]) -> tuple[float, float]:
    index = [frames[v] for v in model.view_indices]
    errors = camera_errors(model.cameras.R, model.cameras.t, sequence.R[index], sequence.t[index])
    return float(errors.rotation.max()), 100 * float(errors.centre.max()) / errors.extent


def run_case(sequence, patch: torch.Tensor, first: int) -> str:
    frames = list(range(first, first + len(POSITIONS)))
    clean = [read_image(sequence.images[f]) for f in frames]
    pasted, boxes = insert_moving_patch(clean, patch, POSITIONS)
    K = sequence.K[first]
    try:
        with_patch = torchsfm.reconstruct(pasted, K, moving_objects="reconstruct", generator=torch.Generator().manual_seed(0))
        without = torchsfm.reconstruct(clean, K, moving_objects="reconstruct", generator=torch.Generator().manual_seed(0))
    except TorchSfmError as error:
        return f"failed: {error}"
    body, share, uv = body_on_patch(with_patch, boxes)
    rotation, centre = scene_errors(with_patch, sequence, frames)
    clean_rotation, clean_centre = scene_errors(without, sequence, frames)
    scene = (f"scene {with_patch.num_views}/5 views, rotation {rotation:.3f} deg (clean {clean_rotation:.3f}), "
             f"centre {centre:.3f} % (clean {clean_centre:.3f})")
    if body is None:
        bodies = ", ".join(f"{b.label}: {b.reason}" for b in with_patch.objects) or "no moving body found"
        return f"no body on the patch ({bodies}); {scene}"
    on_patch = uv[:, 0].isfinite()
    similarity, planarity, anisotropy = patch_shape(body.model.points3d[on_patch], uv[on_patch])
    return (f"body {body.model.num_views} views, {body.model.num_points} points ({100 * share:.0f} % on the patch), "
            f"shape {similarity:.2f} %, planarity {planarity:.2f} %, anisotropy {anisotropy:.2f} %; {scene}")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--data", type=Path, default=DEFAULT_DATA)
    args = parser.parse_args()
    fountain = read_strecha(args.data / "strecha_fountain_P11")
    herzjesu = read_strecha(args.data / "strecha_herzjesu_P8")
    cases = [("fountain", fountain, read_image(herzjesu.images[0])[:, PATCH[0], PATCH[1]], first) for first in range(7)]
    cases += [("herzjesu", herzjesu, read_image(fountain.images[0])[:, PATCH[0], PATCH[1]], first) for first in range(4)]
    for name, sequence, patch, first in cases:
        print(f"{name} frames {first}-{first + len(POSITIONS) - 1}: {run_case(sequence, patch, first)}", flush=True)


if __name__ == "__main__":
    main()
