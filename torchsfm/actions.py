"""Whole jobs behind the command line: read inputs, call the library, write every output.

Each job computes everything in memory first and writes only once it has succeeded, each file
atomically, so that a failure leaves no partial model behind.
"""

from __future__ import annotations

import json
import os
import time
from pathlib import Path

import torch
import yaml
from torch import Tensor

from torchsfm.calibration.files import calibration_yaml
from torchsfm.calibration.stages import BoardViews, calibration_stages
from torchsfm.config import Config, config_to_dict
from torchsfm.errors import InputError
from torchsfm.geometry.fundamental import fundamental_from_pose
from torchsfm.io.atomic import atomic_write_bytes, atomic_write_text
from torchsfm.io.colmap import colmap_text
from torchsfm.io.datasets import read_strecha
from torchsfm.images import read_image
from torchsfm.io.ply import ply_bytes
from torchsfm.io.vrml import vrml_text
from torchsfm.sfm.incremental import reconstruct
from torchsfm.reconstruction import MovingObject, Reconstruction
from torchsfm.sfm.two_view import TwoViewReconstruction
from torchsfm.evaluation import rotation_error_deg, translation_direction_error_deg
from torchsfm.visualization import corners_figure, matches_figure, segmentation_figure, write_png
from torchsfm.pipeline import Progress

SAMPLE = Path(__file__).resolve().parent / "data" / "fountain"


def moving_objects_summary(model: Reconstruction) -> list[dict]:
    """Per frame triplet: vectors tested, rejected by IMOR, by the RANSAC after it, kept."""
    rows = []
    for views, result in model.moving_objects.items():
        ransac = result.ransac_mask
        rows.append({"views": list(views), "vectors": int(result.background_mask.numel()),
                     "imor_rejected": int((~result.imor_mask).sum()),
                     "ransac_rejected": 0 if ransac is None else int((result.imor_mask & ~ransac).sum()),
                     "background": int(result.background_mask.sum()), "planar_background": result.planar_background,
                     "fallback": result.fallback, "ransac_trials": result.ransac_trials})
    return rows


def two_view_summary(model: Reconstruction, config: Config, seconds: float) -> dict:
    """What a person wants to know about a two-view model, as JSON-ready values."""
    inliers = model.inlier_mask
    return {
        "images": model.image_names,
        "image_size": model.image_sizes[0].tolist(),
        "putative_matches": int(model.matches.shape[0]),
        "inliers": int(inliers.sum()),
        "points": model.num_points,
        "reprojection_rms_px": model.reprojection_rms(),
        "R": model.cameras.R[1].tolist(),
        "t": model.cameras.t[1].tolist(),
        "K": [model.cameras.K[0].tolist(), model.cameras.K[1].tolist()],
        "seconds": {**model.timings, "total": seconds},
        "moving_objects": moving_objects_summary(model),
        "config": config_to_dict(config),
    }


def model_files(model: Reconstruction, image1: Tensor, image2: Tensor, summary: dict) -> dict[str, bytes | str | Tensor]:
    """Every output of a two-view job, keyed by relative path (PNG as a (3, H, W) image tensor)."""
    F = fundamental_from_pose(model.cameras.K[0], model.cameras.K[1], model.cameras.R[1], model.cameras.t[1])
    files: dict[str, bytes | str | Tensor] = {
        "model.wrl": vrml_text(model),
        "points.ply": ply_bytes(model.points3d, model.colors),
        "matches.png": matches_figure(image1, image2, model.matches[:, :2], model.matches[:, 2:], model.inlier_mask, F),
        "summary.json": json.dumps(summary, indent=2) + "\n",
    }
    files.update({f"colmap/{name}": text for name, text in colmap_text(model).items()})
    return files


def check_writable(out: str | Path) -> None:
    """Raise :class:`InputError` before any work where ``out`` cannot be written: it is a file
    where a folder is meant, or the nearest folder that exists above it is not writable."""
    out = Path(out).absolute()
    if out.exists() and not out.is_dir():
        raise InputError(f"output folder {out} is a file")
    existing = next(folder for folder in (out, *out.parents) if folder.exists())
    if not existing.is_dir() or not os.access(existing, os.W_OK | os.X_OK):
        raise InputError(f"cannot write the output folder {out}: {existing} is not a writable folder")


def write_files(out: Path, files: dict[str, bytes | str | Tensor]) -> None:
    """Write prepared outputs under ``out`` (created if needed), each file atomically; a file
    system's refusal is an :class:`InputError` naming the file."""
    for name, content in files.items():
        path = out / name
        try:
            if isinstance(content, Tensor):
                write_png(path, content)
            elif isinstance(content, bytes):
                atomic_write_bytes(path, content)
            else:
                atomic_write_text(path, content)
        except OSError as error:
            raise InputError(f"cannot write {path}: {error.strerror or error}") from error


def two_view(image1: str | Path, image2: str | Path, K: Tensor, out: str | Path, *, distortion: Tensor | None = None,
             config: Config | None = None, third: str | Path | None = None, seed: int = 0,
             progress: Progress | None = None) -> dict:
    """Reconstruct two images with intrinsics K (and radial distortion); write VRML, PLY, COLMAP
    text, a PNG and a JSON summary into ``out``. ``third`` is the frame after image2, read when
    moving-object rejection is on. Returns the summary."""
    config = config or Config()
    check_writable(out)
    start = time.perf_counter()
    first, second = read_image(image1), read_image(image2)
    third_image = read_image(third) if third is not None and config.moving_objects.enabled else None
    pipeline = TwoViewReconstruction(config)
    model = pipeline(first, second, K, distortion=distortion, third_image=third_image, names=(Path(image1).name, Path(image2).name),
                     generator=torch.Generator().manual_seed(seed), progress=progress)
    summary = two_view_summary(model, config, time.perf_counter() - start)
    if progress:
        progress("writing model files ...")
    write_files(Path(out), model_files(model, first, second, summary))
    return summary


IMAGE_SUFFIXES = {".jpg", ".jpeg", ".png"}


def image_paths(inputs: list[str | Path]) -> list[Path]:
    """Image files from a list of files and/or folders (a folder contributes its sorted images).
    A path that does not exist, or a folder without images, is an :class:`InputError` (a file
    that exists but cannot be read is left out by :func:`torchsfm.reconstruct`, with the reason)."""
    paths: list[Path] = []
    for item in map(Path, inputs):
        if item.is_dir():
            found = sorted(p for p in item.iterdir() if p.suffix.lower() in IMAGE_SUFFIXES)
            if not found:
                raise InputError(f"folder {item} holds no images ({', '.join(sorted(IMAGE_SUFFIXES))})")
            paths += found
        elif item.exists():
            paths.append(item)
        else:
            raise InputError(f"no such file or folder: {item}")
    return paths


def reconstruction_summary(model: Reconstruction, seconds: float, config: Config) -> dict:
    """Views registered, points, track lengths, reprojection RMS and stage times, JSON-ready."""
    return {
        "views_registered": model.num_views,
        "registered": [{"index": index, "image": name} for index, name in zip(model.view_indices, model.image_names)],
        "unregistered": [{"index": index, "reason": reason} for index, reason in sorted(model.unregistered.items())],
        "loose_resections": [{"index": index, "threshold_px": threshold} for index, threshold in sorted(model.loose_resections.items())],
        "tracked_resections": [{"index": index, "inliers": kept} for index, kept in sorted(model.tracked_resections.items())],
        "still_frames": [{"index": index, "keyframe": key} for index, key in model.still_frames.items()],
        "points": model.num_points,
        "observations": int(model.observation_points.numel()),
        "mean_track_length": model.observation_points.numel() / max(model.num_points, 1),
        "reprojection_rms_px": model.reprojection_rms(),
        "K": model.cameras.K[0].tolist() if model.num_views else None,
        "seconds": {**model.timings, "total": seconds},
        "moving_objects": moving_objects_summary(model),
        "moving_observations_rejected_per_view": [{"index": index, "rejected": count}
                                                  for index, count in sorted(model.moving_rejections_per_view.items())],
        "cameras": [{"image": name, "R": model.cameras.R[v].tolist(), "t": model.cameras.t[v].tolist()}
                    for v, name in enumerate(model.image_names)],
        "other_models": [{"folder": f"other_models/{k}", "views": other.view_indices, "images": other.image_names,
                          "points": other.num_points} for k, other in enumerate(model.other_models, start=1)],
        "objects": [{"label": body.label, "tracks": body.num_tracks, "reason": body.reason or None,
                     **({"folder": f"objects/{body.label}", "views": body.model.view_indices, "points": body.model.num_points,
                         "scale": "its own (unknown relative to the scene)", "steady_motion": _steady(body, model)}
                        if body.model is not None else {})}
                    for body in model.objects],
        "config": config_to_dict(config),
    }


def _with_placed_bodies(model: Reconstruction) -> tuple[Tensor, Tensor]:
    """The model's points and colours, then every moving body's that can be placed in it
    (:meth:`~torchsfm.reconstruction.MovingObject.placed_in_scene`), in the body's colour."""
    points, colours = [model.points3d], [model.colors]
    for body in model.objects:
        placement = body.placed_in_scene(model) if body.model is not None else None
        if placement is not None:
            points.append(placement[0])
            colours.append(body.model.colors)
    return torch.cat(points), torch.cat(colours)


def _steady(body: MovingObject, scene: Reconstruction) -> dict | None:
    """A body's scale and path by the steady-motion prior, JSON-ready (None where undetermined)."""
    steady = body.steady_trajectory(scene)
    if steady is None:
        return None
    scale, views, path = steady
    return {"scale": scale, "views": views, "path": path.tolist()}


def reconstruction_files(model: Reconstruction, summary: dict, frame: Tensor | None = None) -> dict[str, bytes | str | Tensor]:
    """The files of a multi-view model, by path under the output folder: ``summary.json``, the
    model's ``model.wrl``, ``points.ply`` and ``colmap/*.txt``, and the same for each of its
    ``other_models`` under ``other_models/k/`` (k from 1) and each moving body's model under
    ``objects/label/`` (its points in the body's colour; the scene's PLY and VRML show each body
    the steady-motion prior places at its first view); with ``segmented_tracks``,
    ``segmentation.png``: the tracks coloured by motion over ``frame`` (an image; else white)."""
    files: dict[str, bytes | str | Tensor] = {"summary.json": json.dumps(summary, indent=2) + "\n"}
    if model.segmented_tracks is not None:
        pixels, visible, labels = model.segmented_tracks
        width, height = model.image_sizes[0].tolist()
        files["segmentation.png"] = segmentation_figure(pixels, visible, labels, (width, height), frame)
    parts = ([("", model)] + [(f"other_models/{k}/", other) for k, other in enumerate(model.other_models, start=1)]
             + [(f"objects/{body.label}/", body.model) for body in model.objects if body.model is not None])
    for folder, part in parts:
        points, colours = _with_placed_bodies(part)
        files.update({f"{folder}model.wrl": vrml_text(part), f"{folder}points.ply": ply_bytes(points, colours)})
        files.update({f"{folder}colmap/{name}": text for name, text in colmap_text(part).items()})
    return files


def reconstruct_sequence(inputs: list[str | Path], K: Tensor | None, out: str | Path, *, distortion: Tensor | None = None,
                         config: Config | None = None, seed: int = 0, progress: Progress | None = None,
                         masks: str | Path | None = None) -> dict:
    """Reconstruct images (files or folders) with intrinsics K (and radial distortion; K None:
    estimated, see :func:`torchsfm.reconstruct`); write VRML, PLY, COLMAP text and a JSON summary
    into ``out`` (a set that split: the largest model there, each other one under
    ``out/other_models/k/``). ``masks``: where features may be detected (:func:`mask_paths`).
    Returns the summary (``K``: the intrinsics used)."""
    config = config or Config()
    check_writable(out)
    start = time.perf_counter()
    paths = image_paths(inputs)
    model = reconstruct(paths, K, distortion=distortion, config=config, generator=torch.Generator().manual_seed(seed),
                        progress=progress, masks=None if masks is None else mask_paths(masks, paths))
    summary = reconstruction_summary(model, time.perf_counter() - start, config)
    frame = read_image(paths[model.view_indices[0]]) if model.segmented_tracks is not None else None
    files = reconstruction_files(model, summary, frame)
    if progress:
        progress("writing model files ...")
    write_files(Path(out), files)
    return summary


def mask_paths(masks: str | Path, images: list[Path]) -> Path | list[Path | None]:
    """The masks of ``images`` from a mask file (one for every image: a video's fixed overlay) or
    a folder holding, as COLMAP's, ``<image file name>.png`` for each image that has one (the
    others: the whole image). A folder that holds none of them is an error (a wrong folder)."""
    masks = Path(masks)
    if not masks.is_dir():
        if not masks.is_file():
            raise InputError(f"masks: {masks} is neither a mask image nor a folder of them")
        return masks
    found = [masks / f"{image.name}.png" for image in images]
    found = [path if path.is_file() else None for path in found]
    if all(path is None for path in found):
        raise InputError(f"masks: {masks} holds no mask named as COLMAP's, <image file name>.png (e.g. {images[0].name}.png)")
    return found


def demo(out: str | Path, *, progress: Progress | None = None) -> dict:
    """The two bundled fountain-P11 views: reconstruct, write the outputs, and compare with the
    ground-truth relative pose (added to the summary as ``ground_truth``)."""
    sample = read_strecha(SAMPLE)
    R_true, t_true = sample.relative_pose(0, 1)
    summary = two_view(sample.images[0], sample.images[1], sample.K[0], out, progress=progress)
    R, t = torch.tensor(summary["R"], dtype=torch.float64), torch.tensor(summary["t"], dtype=torch.float64)
    summary["ground_truth"] = {"rotation_error_deg": rotation_error_deg(R, R_true),
                               "translation_direction_error_deg": translation_direction_error_deg(t, t_true)}
    write_files(Path(out), {"summary.json": json.dumps(summary, indent=2) + "\n"})
    return summary


def calibrate(inputs: list[str | Path], pattern: tuple[int, int], square: float, out: str | Path, *,
              config: Config | None = None, progress: Progress | None = None) -> dict:
    """Calibrate from chessboard photos (files or folders): the stages of
    :func:`~torchsfm.calibration.stages.calibration_stages` detect the boards and run Zhang's
    method; then the calibration YAML goes to ``out`` and a PNG of the detected corners per image
    into ``<out stem>_corners/``. Returns the calibration as a dict (plus ``corners_folder``).

    Raises NotEnoughDataError (naming the images without a board) when fewer than
    ``calibration.min_views`` boards are found.
    """
    config = config or Config()
    check_writable(Path(out).parent)
    paths = image_paths(inputs)
    state = BoardViews(images=paths, names=[path.name for path in paths], pattern=pattern, square=square,
                       report=progress or (lambda message: None))
    state = calibration_stages(config)(state)
    out = Path(out)
    folder = out.parent / f"{out.stem}_corners"
    figures = {path.stem: corners_figure(read_image(path), state.corners[path.name], pattern) for path in paths
               if path.name in state.corners}
    text = calibration_yaml(state.calibration, image_size=state.sizes.pop(), pattern=pattern, square=square,
                            views=list(state.corners), not_found=state.not_found)
    write_files(folder, {f"{stem}.png": figure for stem, figure in figures.items()})
    write_files(out.parent, {out.name: text})
    return {**yaml.safe_load(text), "corners_folder": str(folder)}
