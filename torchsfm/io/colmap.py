"""COLMAP text models (``cameras.txt``, ``images.txt``, ``points3D.txt``): writer and reader.

COLMAP puts the *corner* of the top-left pixel at (0, 0), so its pixel coordinates are ours
plus 0.5 (principal points included); rotations are world-to-camera unit quaternions
(w, x, y, z) and translations camera-from-world, like ours. Cameras without distortion are
written as PINHOLE, with (k1, k2) as OPENCV (p1 = p2 = 0). COLMAP has no skew parameter, so a
K with skew is refused rather than silently changed.
"""

from __future__ import annotations

from contextlib import contextmanager
from pathlib import Path

import torch
from torch import Tensor

from torchsfm.camera import Camera
from torchsfm.errors import InputError
from torchsfm.geometry.rotation import quaternion_to_rotation, rotation_to_quaternion
from torchsfm.io.atomic import atomic_write_text
from torchsfm.reconstruction import Reconstruction

PIXEL_SHIFT = 0.5  # COLMAP pixel coordinate = torchsfm pixel coordinate + 0.5


def _camera_line(camera_id: int, K: Tensor, distortion: Tensor, size: Tensor) -> str:
    fx, fy, cx, cy = float(K[0, 0]), float(K[1, 1]), float(K[0, 2]) + PIXEL_SHIFT, float(K[1, 2]) + PIXEL_SHIFT
    if abs(float(K[0, 1])) > 1e-9 * abs(fx):
        raise InputError(f"camera {camera_id} has skew {float(K[0, 1]):.4g}; COLMAP camera models have no skew")
    width, height = int(size[0]), int(size[1])
    if bool((distortion != 0).any()):
        k1, k2 = (float(v) for v in distortion)
        return f"{camera_id} OPENCV {width} {height} {fx:.17g} {fy:.17g} {cx:.17g} {cy:.17g} {k1:.17g} {k2:.17g} 0 0"
    return f"{camera_id} PINHOLE {width} {height} {fx:.17g} {fy:.17g} {cx:.17g} {cy:.17g}"


def colmap_text(model: Reconstruction) -> dict[str, str]:
    """The three COLMAP text files of a model, keyed by file name."""
    V, P = model.num_views, model.num_points
    cameras = ["# Camera list with one line of data per camera:", "#   CAMERA_ID, MODEL, WIDTH, HEIGHT, PARAMS[]",
               f"# Number of cameras: {V}"]
    for view in range(V):
        cameras.append(_camera_line(view + 1, model.cameras.K[view], model.cameras.distortion[view], model.image_sizes[view]))
    # per view, the observations in a fixed order give each its POINT2D_IDX
    order = torch.argsort(model.observation_views, stable=True)
    views, points = model.observation_views[order], model.observation_points[order]
    keypoints = model.keypoints[order] + PIXEL_SHIFT
    starts = torch.cumsum(torch.bincount(views, minlength=V), 0) - torch.bincount(views, minlength=V)
    point2d_index = torch.arange(views.numel()) - starts[views]
    errors = model.point_errors()
    images = ["# Image list with two lines of data per image:", "#   IMAGE_ID, QW, QX, QY, QZ, TX, TY, TZ, CAMERA_ID, NAME",
              "#   POINTS2D[] as (X, Y, POINT3D_ID)", f"# Number of images: {V}, mean observations per image: {views.numel() / max(V, 1):.2f}"]
    quaternions = rotation_to_quaternion(model.cameras.R.double())
    for view in range(V):
        q, t = quaternions[view].tolist(), model.cameras.t[view].tolist()
        images.append(f"{view + 1} " + " ".join(f"{v:.17g}" for v in q + t) + f" {view + 1} {model.image_names[view]}")
        mine = views == view
        images.append(" ".join(f"{x:.17g} {y:.17g} {p + 1}" for (x, y), p in zip(keypoints[mine].tolist(), points[mine].tolist())))
    tracks: list[list[str]] = [[] for _ in range(P)]
    for view, point, index in zip(views.tolist(), points.tolist(), point2d_index.tolist()):
        tracks[point].append(f"{view + 1} {index}")
    points3d = ["# 3D point list with one line of data per point:",
                "#   POINT3D_ID, X, Y, Z, R, G, B, ERROR, TRACK[] as (IMAGE_ID, POINT2D_IDX)",
                f"# Number of points: {P}, mean track length: {views.numel() / max(P, 1):.2f}"]
    for p, ((x, y, z), (r, g, b), error) in enumerate(zip(model.points3d.tolist(), model.colors.tolist(), errors.tolist())):
        points3d.append(f"{p + 1} {x:.17g} {y:.17g} {z:.17g} {r} {g} {b} {error:.6g} " + " ".join(tracks[p]))
    return {name: "\n".join(lines) + "\n" for name, lines in
            (("cameras.txt", cameras), ("images.txt", images), ("points3D.txt", points3d))}


def write_colmap_text(folder: str | Path, model: Reconstruction) -> None:
    """Write the model into ``folder`` (created if needed); every file is written atomically."""
    files = colmap_text(model)  # everything is formatted before anything is written
    for name, text in files.items():
        atomic_write_text(Path(folder) / name, text)


def _data_lines(path: Path) -> list[str]:
    try:
        return [line for line in path.read_text().splitlines() if not line.startswith("#")]
    except OSError as error:
        raise InputError(f"cannot read COLMAP file {path}: {error.strerror}") from None


def read_colmap_text(folder: str | Path) -> Reconstruction:
    """Read a COLMAP text model written by COLMAP or :func:`write_colmap_text` (PINHOLE,
    SIMPLE_PINHOLE, OPENCV without tangential distortion, RADIAL and SIMPLE_RADIAL cameras) into
    torchsfm's conventions. A malformed line is an :class:`InputError` naming its file and line."""
    folder = Path(folder)
    cameras = {}
    for line in _lines_of(folder / "cameras.txt"):
        with _parsing(folder / "cameras.txt", line):
            fields = line.split()
            camera_id, model_name, width, height = int(fields[0]), fields[1], int(fields[2]), int(fields[3])
            params = [float(v) for v in fields[4:]]
            if model_name == "PINHOLE":
                fx, fy, cx, cy, k1, k2 = *params, 0.0, 0.0
            elif model_name == "SIMPLE_PINHOLE":
                (fx, cx, cy), fy, k1, k2 = params, params[0], 0.0, 0.0
            elif model_name == "OPENCV":
                fx, fy, cx, cy, k1, k2, p1, p2 = params
                if p1 or p2:
                    raise InputError(f"COLMAP camera {camera_id} has tangential distortion (p1, p2 = {p1:g}, {p2:g}), "
                                     "which torchsfm's camera (k1, k2) cannot hold")
            elif model_name == "RADIAL":
                (fx, cx, cy, k1, k2), fy = params, params[0]
            elif model_name == "SIMPLE_RADIAL":
                (fx, cx, cy, k1), fy, k2 = params, params[0], 0.0
            else:
                raise InputError(f"COLMAP camera model {model_name} is not supported (camera {camera_id})")
            K = torch.tensor([[fx, 0.0, cx - PIXEL_SHIFT], [0.0, fy, cy - PIXEL_SHIFT], [0.0, 0.0, 1.0]], dtype=torch.float64)
            cameras[camera_id] = (K, torch.tensor([k1, k2], dtype=torch.float64), (width, height))
    image_lines = _data_lines(folder / "images.txt")
    names, Ks, distortions, sizes, Rs, ts = [], [], [], [], [], []
    observed: list[tuple[int, int, float, float]] = []
    for header, points_line in zip(image_lines[0::2], image_lines[1::2]):
        with _parsing(folder / "images.txt", header):
            fields = header.split()
            values = [float(v) for v in fields[1:8]]
            K, distortion, size = cameras[int(fields[8])]
            names.append(" ".join(fields[9:]))
            Ks.append(K)
            distortions.append(distortion)
            sizes.append(size)
            Rs.append(quaternion_to_rotation(torch.tensor(values[:4], dtype=torch.float64)))
            ts.append(torch.tensor(values[4:], dtype=torch.float64))
        with _parsing(folder / "images.txt", points_line):
            entries = points_line.split()
            for k in range(0, len(entries), 3):
                x, y, point_id = float(entries[k]), float(entries[k + 1]), int(entries[k + 2])
                if point_id >= 0:
                    observed.append((point_id, len(names) - 1, x - PIXEL_SHIFT, y - PIXEL_SHIFT))
    if not names:
        raise InputError(f"COLMAP model {folder} holds no images (images.txt)")
    point_ids, coordinates, colors = {}, [], []
    for line in _lines_of(folder / "points3D.txt"):
        with _parsing(folder / "points3D.txt", line):
            fields = line.split()
            point_ids[int(fields[0])] = len(coordinates)
            coordinates.append([float(v) for v in fields[1:4]])
            colors.append([int(v) for v in fields[4:7]])
    unknown = sorted({o[0] for o in observed} - point_ids.keys())
    if unknown:
        raise InputError(f"COLMAP model {folder}: images.txt observes points missing from points3D.txt (e.g. {unknown[0]})")
    return Reconstruction(
        cameras=Camera(K=torch.stack(Ks), R=torch.stack(Rs), t=torch.stack(ts), distortion=torch.stack(distortions)),
        image_names=names,
        image_sizes=torch.tensor(sizes, dtype=torch.long),
        points3d=torch.tensor(coordinates, dtype=torch.float64).reshape(-1, 3),
        colors=torch.tensor(colors, dtype=torch.uint8).reshape(-1, 3),
        observation_points=torch.tensor([point_ids[o[0]] for o in observed], dtype=torch.long),
        observation_views=torch.tensor([o[1] for o in observed], dtype=torch.long),
        keypoints=torch.tensor([[o[2], o[3]] for o in observed], dtype=torch.float64).reshape(-1, 2),
    )


def _lines_of(path: Path) -> list[str]:
    """The non-empty data lines of a COLMAP text file."""
    return [line for line in _data_lines(path) if line.strip()]


@contextmanager
def _parsing(path: Path, line: str):
    """Turn a malformed ``line`` of ``path`` (too few fields, not a number, an unknown id) into
    an :class:`InputError` that quotes it."""
    try:
        yield
    except (ValueError, IndexError, KeyError) as error:
        raise InputError(f"malformed line in COLMAP file {path}: {line.strip()[:80]!r} ({type(error).__name__}: {error})") from None
