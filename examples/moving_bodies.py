"""Each moving body as its own model, on synthetic scenes with ground truth (issue #11's figures).

Seeded scenes of :func:`torchsfm.testing.synthetic_moving_scene` (5 frames, 640×480, 0.5 px
noise, 10 % outlier tracks, 1–3 boxes of up to 60 tracks moving and turning independently of the
camera) go through :func:`torchsfm.reconstruct_motions` (the number of motions found). Per scene:

- the static scene's camera errors (largest rotation error, largest centre error in % of the path
  after a similarity alignment) beside those of the same tracks without the boxes' tracks (the
  same scene without objects, through the same call), and their ratios;
- per box with at least 20 tracks: the model that holds most of its tracks, its registered
  frames, its per-frame rotation error (the camera's pose relative to the body against the truth,
  R_f O_f, after aligning the model's frame), and its shape error (its points similarity-aligned to
  their true positions, :func:`torchsfm.evaluation.shape_errors`: RMS and largest, in % of the
  box's size, the diagonal of its points' bounding box); in brackets the same for the
  maximum-likelihood model of its true tracks (bundle adjustment from the truth): the noise's limit.

    python examples/moving_bodies.py [--seeds 10]
"""

from __future__ import annotations

import argparse

import torch

from torchsfm import reconstruct_motions
from torchsfm.evaluation import camera_errors, shape_errors
from torchsfm.optim.bundle import BundleProblem, bundle_adjust
from torchsfm.testing import synthetic_moving_scene

MIN_TRACKS = 20
ROTATION_TARGET, SHAPE_TARGET = 0.5, 1.0  # issue #11: degrees per frame, % of the body's size


def scene_errors(model, scene) -> tuple[float, float]:
    """(largest rotation error in degrees, largest centre error in % of the path) of a scene model."""
    views = model.view_indices
    errors = camera_errors(model.cameras.R, model.cameras.t, scene.R[views], scene.t[views])
    return float(errors.rotation.max()), 100 * float(errors.centre.max()) / errors.extent


def body_errors(R, t, points, point_tracks, scene, body: int) -> tuple[float, float, float]:
    """(largest per-frame rotation error in degrees, RMS and largest shape error in % of its size)
    of a model of body ``body`` with cameras (F, 3, 3), (F, 3) in every frame (relative to the
    body) and (P, 3) points of the input tracks ``point_tracks`` (P,)."""
    R_true, t_true = scene.body_cameras(body)
    rotation = float(camera_errors(R, t, R_true, t_true).rotation.max())
    own = scene.labels[point_tracks] == body
    true_points = scene.points[point_tracks[own]]
    size = float((true_points.amax(0) - true_points.amin(0)).norm())
    errors = shape_errors(points[own], true_points) / size
    return rotation, 100 * float(errors.square().mean().sqrt()), 100 * float(errors.max())


def oracle_errors(scene, body: int) -> tuple[float, float, float]:
    """:func:`body_errors` of the maximum-likelihood model of the body's true tracks: bundle
    adjustment of every observation started from the truth (the first camera held) — the noise's
    limit for this body, whatever the segmentation and the mapper do."""
    tracks = torch.nonzero(scene.labels == body).flatten()
    R, t = scene.body_cameras(body)
    F, P = R.shape[0], tracks.numel()
    fixed = torch.zeros(F, dtype=torch.bool)
    fixed[0] = True
    problem = BundleProblem("pinhole", R, t, scene.K.expand(F, 3, 3), scene.points[tracks],
                            torch.arange(F).repeat_interleave(P), torch.arange(P).repeat(F),
                            scene.tracks[:, tracks].reshape(-1, 2), fixed_cameras=fixed)
    adjusted = bundle_adjust(problem).problem
    return body_errors(adjusted.rotations, adjusted.translations, adjusted.points, tracks, scene, body)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seeds", type=int, default=10, help="scene seeds 0..n-1 for each number of boxes")
    args = parser.parse_args()
    print(f"{'seed':>4} {'boxes':>5} {'found':>5}  scene rot° / centre %: with boxes | without | ratio    "
          "per box: tracks, frames, rot° (oracle), shape RMS (oracle) / max %")
    figures, ratios = [], []  # per box over all frames: (rotation, oracle's, shape RMS, oracle's); per scene: (rotation, centre)
    bodies = scene_failures = 0
    for boxes in (1, 2, 3):
        for seed in range(args.seeds):
            scene = synthetic_moving_scene(seed, num_frames=5, num_objects=boxes, object_points=60, noise=0.5,
                                           outlier_fraction=0.1)
            result = reconstruct_motions(scene.tracks, scene.K, generator=torch.Generator().manual_seed(seed))
            without = scene.labels <= 0
            alone = reconstruct_motions(scene.tracks[:, without], scene.K, generator=torch.Generator().manual_seed(seed))
            if 0 not in result.models or 0 not in alone.models:
                failed = "with" if 0 not in result.models else "without"
                print(f"{seed:>4} {boxes:>5} {result.segmentation.num_motions:>5}  no scene model {failed} the boxes: "
                      f"{(result if failed == 'with' else alone).failed[0][:150]}", flush=True)
                scene_failures += 1
                continue
            with_rotation, with_centre = scene_errors(result.models[0], scene)
            plain_rotation, plain_centre = scene_errors(alone.models[0], scene)
            ratio_rotation, ratio_centre = with_rotation / plain_rotation, with_centre / plain_centre
            ratios.append((ratio_rotation, ratio_centre))
            cells = []
            for body in range(1, boxes + 1):
                tracks = scene.labels == body
                if int(tracks.sum()) < MIN_TRACKS:
                    cells.append(f"{int(tracks.sum())} tracks (< {MIN_TRACKS})")
                    continue
                bodies += 1
                overlap = {label: int(tracks[members].sum()) for label, members in result.track_indices.items() if label > 0}
                label = max(overlap, key=overlap.get, default=None)
                if label is None or overlap[label] == 0:
                    cells.append(f"{int(tracks.sum())} tracks: no model")
                    continue
                model = result.models[label]
                if len(model.view_indices) < len(scene.R):
                    cells.append(f"{int(tracks.sum())} tracks: {len(model.view_indices)} of {len(scene.R)} frames")
                    continue
                rotation, shape_rms, shape_max = body_errors(model.cameras.R, model.cameras.t, model.points3d, model.point_tracks,
                                                             scene, body)
                best_rotation, best_rms, _ = oracle_errors(scene, body)
                figures.append((rotation, best_rotation, shape_rms, best_rms))
                cells.append(f"{int(tracks.sum())}, {len(model.view_indices)}, {rotation:.3f} ({best_rotation:.3f}), "
                             f"{shape_rms:.2f} ({best_rms:.2f}) / {shape_max:.2f}")
            print(f"{seed:>4} {boxes:>5} {result.segmentation.num_motions:>5}  {with_rotation:.3f} / {with_centre:.3f} | "
                  f"{plain_rotation:.3f} / {plain_centre:.3f} | {ratio_rotation:.2f} / {ratio_centre:.2f}    " + " ; ".join(cells),
                  flush=True)
    print(f"\nscenes without a scene model (with or without the boxes): {scene_failures} of {3 * args.seeds}")
    print(f"boxes with >= {MIN_TRACKS} tracks reconstructed over all frames: {len(figures)} of {bodies}")
    if figures:
        rotation, best_rotation, shape, best_shape = (torch.tensor(column, dtype=torch.float64) for column in zip(*figures))
        print(f"per-frame rotation <= {ROTATION_TARGET} deg: {int((rotation <= ROTATION_TARGET).sum())} boxes "
              f"(oracle {int((best_rotation <= ROTATION_TARGET).sum())}); shape RMS <= {SHAPE_TARGET} %: "
              f"{int((shape <= SHAPE_TARGET).sum())} (oracle {int((best_shape <= SHAPE_TARGET).sum())})")
        print(f"within 1.5x the oracle: rotation {int((rotation <= 1.5 * best_rotation).sum())}, "
              f"shape {int((shape <= 1.5 * best_shape).sum())} of {len(figures)}")
        print(f"median rotation {rotation.median():.3f} deg (oracle {best_rotation.median():.3f}), median shape "
              f"{shape.median():.2f} % (oracle {best_shape.median():.2f}); worst {rotation.max():.3f} deg "
              f"(oracle {best_rotation.max():.3f}), {shape.max():.2f} % (oracle {best_shape.max():.2f})")
    if ratios:
        print(f"worst scene error ratio (with / without boxes): rotation {max(r for r, _ in ratios):.2f}, "
              f"centre {max(c for _, c in ratios):.2f}")

if __name__ == "__main__":
    main()
