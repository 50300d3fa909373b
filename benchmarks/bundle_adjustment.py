"""Bundle adjustment benchmark: torchsfm against SciPy and Ceres (through pycolmap), same process.

Problems: BAL Ladybug problem-49-7776-pre (``../shared/data/bal_ladybug_49``; the 10 points
seen behind a camera in 31 observations are removed for every solver, because COLMAP drops them
when it loads the model) and a synthetic BAL problem of 50 cameras and 10,000 points (σ = 0.5 px observation noise, perturbed start). Every
solver starts from the same parameters and optimizes the same BAL camera model (rotation,
translation, f, k1, k2 per camera, and the points). Printed: the final cost ½Σ‖r‖² (pixels²),
its relative difference to the best final cost, iterations and wall time, and each peer's time
over torchsfm's (> 1: torchsfm is faster).

* SciPy: ``least_squares(method="trf", jac_sparsity=..., x_scale="jac")`` with 2-point finite
  differences on the sparsity pattern (the SciPy cookbook's large-scale BA), ftol 1e-6.
* Ceres: ``pycolmap.bundle_adjustment`` on the same problem written as a COLMAP model with RADIAL
  cameras (BAL's -z camera turned by 180° about x), function tolerance 1e-6.

    pip install -e .[bench]
    python benchmarks/bundle_adjustment.py [--data ../shared/data] [--threads 2] [--skip-scipy]
"""

from __future__ import annotations

import argparse
import math
import tempfile
import time
from pathlib import Path

import numpy as np
import torch

from torchsfm.geometry.rotation import axis_angle_to_rotation, rotation_to_axis_angle
from torchsfm.io.bal import read_bal
from torchsfm.optim.bundle import BundleProblem, bundle_adjust

DEFAULT_DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data"
FLIP = torch.diag(torch.tensor([1.0, -1.0, -1.0], dtype=torch.float64))  # BAL (-z, y up) <-> COLMAP (+z, y down)


def synthetic_bal(num_cameras: int = 50, num_points: int = 10_000, seed: int = 0) -> BundleProblem:
    """Cameras on a ring looking at a ball of points; each point seen by the cameras within ±40°."""
    generator = torch.Generator().manual_seed(seed)
    points = torch.randn(num_points, 3, generator=generator, dtype=torch.float64)
    points = points / points.norm(dim=-1, keepdim=True) * torch.rand(num_points, 1, generator=generator, dtype=torch.float64) ** (1 / 3) * 2
    angles = torch.arange(num_cameras, dtype=torch.float64) * 2 * math.pi / num_cameras
    rotations, translations = [], []
    for angle in angles:
        centre = torch.stack([8 * torch.cos(angle), 8 * torch.sin(angle), torch.tensor(0.5, dtype=torch.float64)])
        z = -centre / centre.norm()
        x = torch.linalg.cross(torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64), z)
        x = x / x.norm()
        y = torch.linalg.cross(z, x)
        R = FLIP @ torch.stack([x, y, z])  # BAL camera: looks down -z
        rotations.append(R)
        translations.append(-R @ centre)
    R, t = torch.stack(rotations), torch.stack(translations)
    intrinsics = torch.tensor([500.0, -0.05, 0.01], dtype=torch.float64).repeat(num_cameras, 1)
    point_angle = torch.atan2(points[:, 1], points[:, 0])
    difference = torch.remainder(angles[None] - point_angle[:, None] + math.pi, 2 * math.pi) - math.pi
    visible = difference.abs() < math.radians(40)
    point_index, camera_index = torch.nonzero(visible, as_tuple=True)
    truth = BundleProblem("bal", R, t, intrinsics, points, camera_index, point_index, torch.zeros(point_index.numel(), 2, dtype=torch.float64))
    observations = truth.residuals() + 0.5 * torch.randn(point_index.numel(), 2, generator=generator, dtype=torch.float64)
    noise = lambda *shape, scale: scale * torch.randn(*shape, generator=generator, dtype=torch.float64)  # noqa: E731
    return BundleProblem(
        "bal", axis_angle_to_rotation(noise(num_cameras, 3, scale=0.005)) @ R, t + noise(num_cameras, 3, scale=0.02),
        intrinsics * (1 + noise(num_cameras, 3, scale=0.01)), points + noise(num_points, 3, scale=0.01),
        camera_index, point_index, observations)


def run_torchsfm(problem: BundleProblem):
    start = time.perf_counter()
    result = bundle_adjust(problem)
    return result.final_cost, result.num_iterations, time.perf_counter() - start


def run_scipy(problem: BundleProblem):
    from scipy.optimize import least_squares
    from scipy.sparse import lil_matrix

    C, P = problem.num_cameras, problem.num_points
    cameras = torch.cat([rotation_to_axis_angle(problem.rotations), problem.translations, problem.intrinsics], 1).numpy()
    x0 = np.concatenate([cameras.ravel(), problem.points.numpy().ravel()])
    c, p = problem.camera_index.numpy(), problem.point_index.numpy()
    observed = problem.observations.numpy()

    def residuals(x: np.ndarray) -> np.ndarray:
        cams = x[: 9 * C].reshape(C, 9)[c]
        points = x[9 * C:].reshape(P, 3)[p]
        theta = np.linalg.norm(cams[:, :3], axis=1, keepdims=True)
        with np.errstate(invalid="ignore", divide="ignore"):
            axis = np.nan_to_num(cams[:, :3] / theta)
        cos, sin = np.cos(theta), np.sin(theta)
        rotated = cos * points + sin * np.cross(axis, points) + (1 - cos) * np.sum(axis * points, 1, keepdims=True) * axis
        camera_point = rotated + cams[:, 3:6]
        projected = -camera_point[:, :2] / camera_point[:, 2:3]
        r2 = np.sum(projected**2, 1)
        scale = cams[:, 6] * (1 + cams[:, 7] * r2 + cams[:, 8] * r2**2)
        return (projected * scale[:, None] - observed).ravel()

    sparsity = lil_matrix((2 * len(c), x0.size), dtype=int)
    rows = np.arange(len(c))
    for k in range(9):
        sparsity[2 * rows, 9 * c + k] = 1
        sparsity[2 * rows + 1, 9 * c + k] = 1
    for k in range(3):
        sparsity[2 * rows, 9 * C + 3 * p + k] = 1
        sparsity[2 * rows + 1, 9 * C + 3 * p + k] = 1
    start = time.perf_counter()
    result = least_squares(residuals, x0, jac_sparsity=sparsity, x_scale="jac", ftol=1e-6, method="trf")
    return 0.5 * float(np.sum(result.fun**2)), int(result.nfev), time.perf_counter() - start


def run_ceres(problem: BundleProblem):
    import pycolmap

    from torchsfm.io.colmap import read_colmap_text

    C = problem.num_cameras
    R, t = FLIP @ problem.rotations, (FLIP @ problem.translations[..., None])[..., 0]
    observations = problem.observations * torch.tensor([1.0, -1.0], dtype=torch.float64)  # y up -> y down
    from torchsfm.geometry.rotation import rotation_to_quaternion

    with tempfile.TemporaryDirectory() as folder:
        folder = Path(folder)
        lines = [f"{k + 1} RADIAL 2000 2000 {f:.17g} 0.5 0.5 {k1:.17g} {k2:.17g}" for k, (f, k1, k2) in enumerate(problem.intrinsics.tolist())]
        (folder / "cameras.txt").write_text("\n".join(lines) + "\n")
        order = torch.argsort(problem.camera_index, stable=True)
        counts = torch.bincount(problem.camera_index, minlength=C)
        index_in_image = torch.empty_like(order)
        index_in_image[order] = torch.arange(order.numel()) - torch.repeat_interleave(torch.cumsum(counts, 0) - counts, counts)
        images = []
        quaternions = rotation_to_quaternion(R)
        for k in range(C):
            mine = order[problem.camera_index[order] == k]
            images.append(f"{k + 1} " + " ".join(f"{v:.17g}" for v in quaternions[k].tolist() + t[k].tolist()) + f" {k + 1} image{k}.jpg")
            images.append(" ".join(f"{x + 0.5:.17g} {y + 0.5:.17g} {int(problem.point_index[o]) + 1}" for o, (x, y) in zip(mine.tolist(), observations[mine].tolist())))
        (folder / "images.txt").write_text("\n".join(images) + "\n")
        tracks = [[] for _ in range(problem.num_points)]
        for o, (cam, point) in enumerate(zip(problem.camera_index.tolist(), problem.point_index.tolist())):
            tracks[point].append(f"{cam + 1} {int(index_in_image[o])}")
        points = [f"{k + 1} {x:.17g} {y:.17g} {z:.17g} 128 128 128 0 " + " ".join(track)
                  for k, ((x, y, z), track) in enumerate(zip(problem.points.tolist(), tracks))]
        (folder / "points3D.txt").write_text("\n".join(points) + "\n")
        reconstruction = pycolmap.Reconstruction(str(folder))
        options = pycolmap.BundleAdjustmentOptions()
        options.print_summary = False
        options.refine_principal_point = False
        options.ceres.solver_options.function_tolerance = 1e-6
        start = time.perf_counter()
        pycolmap.bundle_adjustment(reconstruction, options)
        seconds = time.perf_counter() - start
        out = folder / "out"
        out.mkdir()
        reconstruction.write_text(str(out))
        model = read_colmap_text(out)
    errors = model.observation_errors()
    return 0.5 * float(errors.square().sum()), -1, seconds


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--data", type=Path, default=DEFAULT_DATA)
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--skip-scipy", action="store_true", help="SciPy takes minutes")
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    ladybug = read_bal(args.data / "bal_ladybug_49" / "problem-49-7776-pre.txt")
    behind = torch.zeros(ladybug.num_points, dtype=torch.bool)
    behind[ladybug.point_index[ladybug.depths() <= 0]] = True
    problems = {f"BAL Ladybug 49 cameras / {int((~behind).sum())} points": ladybug.select_points(~behind),
                "synthetic 50 cameras / 10,000 points": synthetic_bal()}
    solvers = {"torchsfm bundle_adjust": run_torchsfm}
    try:
        import pycolmap  # noqa: F401

        solvers["Ceres (pycolmap)"] = run_ceres
    except ImportError as error:
        print(f"pycolmap not installed ({error}); pip install -e .[bench]")
    if not args.skip_scipy:
        try:
            import scipy  # noqa: F401

            solvers["SciPy least_squares TRF"] = run_scipy
        except ImportError as error:
            print(f"SciPy not installed ({error}); pip install -e .[bench]")
    for name, problem in problems.items():
        print(f"\n{name}: {problem.observations.shape[0]} observations, initial cost {problem.cost():.6e}")
        results = {solver: run(problem) for solver, run in solvers.items()}
        best = min(cost for cost, _, _ in results.values())
        ours = results["torchsfm bundle_adjust"][2]
        print(f"{'solver':26s} {'final cost':>14s} {'vs best':>9s} {'iters':>6s} {'seconds':>8s} {'time/ours':>10s}")
        for solver, (cost, iterations, seconds) in results.items():
            shown = str(iterations) if iterations >= 0 else "-"
            print(f"{solver:26s} {cost:14.6e} {100 * (cost - best) / best:8.3f}% {shown:>6s} {seconds:8.2f} {seconds / ours:10.2f}")


if __name__ == "__main__":
    main()
