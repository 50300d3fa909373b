"""VRML 2.0 models like the thesis' figures: the points, and a pyramid per camera."""

from __future__ import annotations

from pathlib import Path

import torch
from torch import Tensor

from torchsfm.io.atomic import atomic_write_text
from torchsfm.reconstruction import Reconstruction


def camera_pyramid(K: Tensor, R: Tensor, t: Tensor, image_size: Tensor, depth: float) -> Tensor:
    """Apex (camera centre) and the four image corners back-projected to ``depth``: (5, 3) world."""
    width, height = float(image_size[0]), float(image_size[1])
    corners = torch.tensor([[0.0, 0.0, 1.0], [width - 1, 0.0, 1.0], [width - 1, height - 1, 1.0], [0.0, height - 1, 1.0]], dtype=K.dtype)
    rays = corners @ torch.linalg.inv(K).T  # (4, 3) camera frame, z = 1
    in_camera = torch.cat([torch.zeros(1, 3, dtype=K.dtype), depth * rays])
    return (in_camera - t) @ R  # world = Rᵀ (x - t)


def vrml_text(model: Reconstruction, camera_size: float | None = None) -> str:
    """VRML 2.0 of a model: coloured PointSet plus one IndexedLineSet pyramid per camera, and for
    every moving body whose :meth:`~torchsfm.reconstruction.MovingObject.steady_trajectory`
    exists its points placed at its first view and the path of its steadiest point as a
    polyline, in the body's colour (its scale from that steady-motion prior).

    ``camera_size`` is the pyramids' depth in world units; by default 5% of the extent of the
    cameras and points together.
    """
    points = model.points3d.double()
    centres = model.cameras.center.double()
    if camera_size is None:
        everything = torch.cat([points, centres])
        extent = float((everything.amax(0) - everything.amin(0)).norm()) if everything.shape[0] > 1 else 1.0
        camera_size = 0.05 * max(extent, 1e-9)
    colors = model.colors.double() / 255
    lines = ["#VRML V2.0 utf8", "# written by torchsfm", "Shape {", "  geometry PointSet {", "    coord Coordinate { point ["]
    lines += [f"      {x:.6g} {y:.6g} {z:.6g}," for x, y, z in points.tolist()]
    lines += ["    ] }", "    color Color { color ["]
    lines += [f"      {r:.4f} {g:.4f} {b:.4f}," for r, g, b in colors.tolist()]
    lines += ["    ] }", "  }", "}"]
    for view in range(model.num_views):
        pyramid = camera_pyramid(model.cameras.K[view].double(), model.cameras.R[view].double(),
                                 model.cameras.t[view].double(), model.image_sizes[view], camera_size)
        lines += [f"# camera {view}: {model.image_names[view]}", "Shape {",
                  "  appearance Appearance { material Material { emissiveColor 1 0.2 0.2 } }",
                  "  geometry IndexedLineSet {", "    coord Coordinate { point ["]
        lines += [f"      {x:.6g} {y:.6g} {z:.6g}," for x, y, z in pyramid.tolist()]
        lines += ["    ] }", "    coordIndex [ 0 1 -1 0 2 -1 0 3 -1 0 4 -1 1 2 3 4 1 -1 ]", "  }", "}"]
    for body in model.objects:
        placement = body.placed_in_scene(model) if body.model is not None else None
        if placement is None:
            continue
        placed, path, scale = placement
        r, g, b = (channel / 255 for channel in body.model.colors[0].tolist())
        lines += [f"# moving body {body.label}: its points at its first view, the path of its steadiest point (scale {scale:.6g} by the steady-motion prior)",
                  "Shape {", "  geometry PointSet {", "    coord Coordinate { point ["]
        lines += [f"      {x:.6g} {y:.6g} {z:.6g}," for x, y, z in placed.tolist()]
        lines += ["    ] }", "    color Color { color [", f"      {r:.4f} {g:.4f} {b:.4f},", "    ] }", "    colorPerVertex FALSE", "  }", "}",
                  "Shape {", f"  appearance Appearance {{ material Material {{ emissiveColor {r:.4f} {g:.4f} {b:.4f} }} }}",
                  "  geometry IndexedLineSet {", "    coord Coordinate { point ["]
        lines += [f"      {x:.6g} {y:.6g} {z:.6g}," for x, y, z in path.tolist()]
        lines += ["    ] }", f"    coordIndex [ {' '.join(str(k) for k in range(path.shape[0]))} -1 ]", "  }", "}"]
    return "\n".join(lines) + "\n"


def write_vrml(path: str | Path, model: Reconstruction, camera_size: float | None = None) -> None:
    """Write :func:`vrml_text` atomically."""
    atomic_write_text(path, vrml_text(model, camera_size))
