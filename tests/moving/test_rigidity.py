"""Plane + parallax and the rigidity constraint on noise-free scenes."""

import torch

from torchsfm.config import MovingObjectsConfig, RansacConfig
from torchsfm.moving.parallax import plane_parallax
from torchsfm.moving.rigidity import rigidity_residuals
from torchsfm.testing import synthetic_moving_scene


def _decomposition(noise: float, plane_threshold: float = 2.0):
    scene = synthetic_moving_scene(0, noise=noise, outlier_fraction=0.0)
    config = MovingObjectsConfig(plane_ransac=RansacConfig(inlier_threshold=plane_threshold, initial_hypotheses=64))
    decomposition = plane_parallax(scene.tracks[1], scene.tracks[[0, 2]], config, torch.Generator().manual_seed(0))
    return scene, decomposition


def test_static_points_satisfy_the_constraint_exactly_and_moving_ones_do_not():
    """Exact homography registration (a 1e-6 px plane threshold keeps only the wall), no noise:
    every static pair gives 0 (1e-6 px); moving points against static supports are far from 0."""
    scene, decomposition = _decomposition(0.0, plane_threshold=1e-6)
    static = torch.nonzero(scene.labels == 0).flatten()
    norm = decomposition.parallax.norm(dim=-1).amax(0)
    supports = static[norm[static] > 5][:10]
    residuals, strength = rigidity_residuals(supports, decomposition.warped, decomposition.parallax)
    assert residuals.shape == strength.shape == (10, scene.labels.numel())
    assert residuals[:, static].abs().max() < 1e-6
    moving = residuals[:, scene.labels > 0].abs()
    assert float(moving.median()) > 1.0
    assert torch.isfinite(residuals).all()


def test_plane_points_have_no_parallax():
    scene, decomposition = _decomposition(0.0)
    on_plane = decomposition.plane_inliers
    assert int(on_plane.sum()) > 100
    assert float(decomposition.parallax[:, on_plane].norm(dim=-1).max()) < 2.0  # the RANSAC threshold


def test_residuals_are_in_pixels_of_noise():
    """With 0.3 px noise the static residuals stay at the noise level (median < 0.5 px)."""
    scene, decomposition = _decomposition(0.3)
    static = torch.nonzero(scene.labels == 0).flatten()
    norm = decomposition.parallax.norm(dim=-1).amax(0)
    supports = static[norm[static] > 5][:10]
    residuals, _ = rigidity_residuals(supports, decomposition.warped, decomposition.parallax)
    assert float(residuals[:, static].abs().median()) < 0.5
