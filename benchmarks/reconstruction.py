"""Sequence reconstruction benchmark: torchsfm beside pycolmap's incremental mapper, same process.

Strecha fountain-P11 (11 views) and Herz-Jesu-P8 (8 views) from the 768×512 images and the
ground-truth K only. pycolmap runs SIFT extraction, exhaustive matching and incremental mapping
with the same fixed PINHOLE intrinsics (no focal, principal point or distortion refinement).
Printed for both: views registered, points, mean track length, reprojection RMS, camera errors
after a similarity alignment to the ground truth (:func:`torchsfm.evaluation.camera_errors`)
and wall time. Each pipeline runs ``--repeats`` times, the two alternating (a slow spell of a shared
machine then falls on both); the seconds are the median over the runs, the model figures those of
the last run; the last column is time / torchsfm's time.

    pip install -e .[bench]
    python benchmarks/reconstruction.py [--data ../shared/data] [--threads 2] [--repeats 3]
"""

from __future__ import annotations

import argparse
import statistics
import tempfile
import time
from pathlib import Path

import torch

import torchsfm
from torchsfm.evaluation import camera_errors
from torchsfm.io.datasets import read_strecha

DEFAULT_DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data"


def run_torchsfm(sequence):
    start = time.perf_counter()
    model = torchsfm.reconstruct(sequence.images, sequence.K, generator=torch.Generator().manual_seed(0))
    seconds = time.perf_counter() - start
    index = model.view_indices
    return (model.num_views, model.num_points, model.observation_points.numel() / max(model.num_points, 1),
            model.reprojection_rms(), camera_errors(model.cameras.R, model.cameras.t, sequence.R[index], sequence.t[index]), seconds)


def run_pycolmap(sequence, threads: int):
    import pycolmap


    K = sequence.K[0]
    params = f"{float(K[0, 0])},{float(K[1, 1])},{float(K[0, 2]) + 0.5},{float(K[1, 2]) + 0.5}"  # COLMAP: +0.5 px
    with tempfile.TemporaryDirectory() as folder:
        folder = Path(folder)
        database = folder / "database.db"
        start = time.perf_counter()
        reader = pycolmap.ImageReaderOptions()
        reader.camera_model, reader.camera_params = "PINHOLE", params
        extraction = pycolmap.FeatureExtractionOptions()
        extraction.num_threads = threads
        pycolmap.extract_features(database, sequence.images[0].parent, image_names=[p.name for p in sequence.images],
                                  camera_mode=pycolmap.CameraMode.SINGLE, reader_options=reader, extraction_options=extraction,
                                  device=pycolmap.Device.cpu)
        pycolmap.match_exhaustive(database, device=pycolmap.Device.cpu)
        options = pycolmap.IncrementalPipelineOptions()
        options.ba_refine_focal_length = False
        options.ba_refine_extra_params = False
        options.num_threads = threads
        maps = pycolmap.incremental_mapping(database, sequence.images[0].parent, folder / "sparse", options)
        seconds = time.perf_counter() - start
    model = max(maps.values(), key=lambda reconstruction: reconstruction.num_reg_images())
    names = [p.name for p in sequence.images]
    R, t, index = [], [], []
    for image in model.images.values():
        if not image.has_pose:
            continue
        pose = image.cam_from_world()
        R.append(torch.tensor(pose.rotation.matrix(), dtype=torch.float64))
        t.append(torch.tensor(pose.translation, dtype=torch.float64))
        index.append(names.index(image.name))
    R, t = torch.stack(R), torch.stack(t)
    errors = camera_errors(R, t, sequence.R[index], sequence.t[index])
    observations = sum(point.track.length() for point in model.points3D.values())
    rms = sum(point.error**2 * point.track.length() for point in model.points3D.values()) / max(observations, 1)
    return (len(index), model.num_points3D(), observations / max(model.num_points3D(), 1), rms**0.5, errors, seconds)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--data", type=Path, default=DEFAULT_DATA)
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--repeats", type=int, default=3, help="runs of each pipeline, alternating; the median time is printed")
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    runners = {"torchsfm reconstruct": run_torchsfm}
    try:
        import pycolmap  # noqa: F401

        runners["pycolmap incremental (SIFT)"] = lambda sequence: run_pycolmap(sequence, args.threads)
    except ImportError as error:
        print(f"pycolmap not installed ({error}); pip install -e .[bench]")
    for name in ("strecha_fountain_P11", "strecha_herzjesu_P8"):
        sequence = read_strecha(args.data / name)
        print(f"\n{name}: {len(sequence.images)} views")
        print(f"{'pipeline':28s} {'views':>5s} {'points':>7s} {'track':>6s} {'RMS px':>7s} {'centre %':>9s} {'rot °':>7s} {'rel rot °':>9s} {'s':>7s} {'time/ours':>9s}")
        runs = {runner_name: [] for runner_name in runners}
        for _ in range(args.repeats):
            for runner_name, runner in runners.items():
                runs[runner_name].append(runner(sequence))
        reference = None
        for runner_name, results in runs.items():
            views, points, track, rms, errors, _ = results[-1]
            seconds = statistics.median(result[-1] for result in results)
            reference = reference or seconds
            print(f"{runner_name:28s} {views:5d} {points:7d} {track:6.2f} {rms:7.3f} {100 * float(errors.centre.median()) / errors.extent:9.4f} "
                  f"{float(errors.rotation.median()):7.3f} {float(errors.relative_rotation.median()):9.3f} {seconds:7.1f} {seconds / reference:9.2f}")


if __name__ == "__main__":
    main()
