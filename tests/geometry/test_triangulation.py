import pytest
import torch
from torch.testing import assert_close

import torchsfm
from torchsfm.camera import from_homogeneous, project, projection_matrix
from torchsfm.errors import DegenerateConfigurationError, InputError, ShapeError
from torchsfm.geometry.fundamental import fundamental_from_projections, sampson_error
from torchsfm.geometry.triangulation import TRIANGULATION_METHODS, correct_correspondences
from torchsfm.testing import synthetic_two_view

DOUBLE = dict(dtype=torch.float64)
METHODS = sorted(TRIANGULATION_METHODS)


def _projective(seed=0):
    """A random projective transformation H (4x4) close enough to identity to keep cameras finite."""
    g = torch.Generator().manual_seed(seed)
    H = torch.eye(4, **DOUBLE) + 0.2 * torch.randn(4, 4, generator=g, **DOUBLE)
    H[3] = torch.tensor([0.05, -0.03, 0.02, 1.0], **DOUBLE)
    return H


def _reprojection_sq(X, scene, P1=None, P2=None):
    P1 = scene.P1 if P1 is None else P1
    P2 = scene.P2 if P2 is None else P2
    return ((project(P1, X) - scene.x1) ** 2).sum(-1) + ((project(P2, X) - scene.x2) ** 2).sum(-1)


@pytest.mark.parametrize("method", METHODS)
def test_every_method_is_exact_without_noise(method):
    scene = synthetic_two_view(100, seed=1)
    X = torchsfm.triangulate(scene.x1, scene.x2, scene.P1, scene.P2, method=method)
    assert_close(X, scene.points3d, rtol=0, atol=1e-8)


@pytest.mark.parametrize("method", METHODS)
def test_every_method_is_exact_after_a_projective_distortion(method):
    scene = synthetic_two_view(100, seed=2)
    H = _projective()
    P1, P2 = scene.P1 @ torch.linalg.inv(H), scene.P2 @ torch.linalg.inv(H)
    X = torchsfm.triangulate(scene.x1, scene.x2, P1, P2, method=method)
    expected = from_homogeneous(torch.cat([scene.points3d, torch.ones(100, 1, **DOUBLE)], -1) @ H.T)
    assert_close(X, expected, rtol=1e-8, atol=1e-8)


@pytest.mark.parametrize("method", METHODS)
def test_shapes_batched_and_float32(method):
    scene = synthetic_two_view(12, seed=3)
    x1, x2 = scene.x1.expand(3, 12, 2), scene.x2.expand(3, 12, 2)
    P1, P2 = scene.P1.expand(3, 3, 4), scene.P2.expand(3, 3, 4)
    assert torchsfm.triangulate(x1, x2, P1, P2, method=method).shape == (3, 12, 3)
    X = torchsfm.triangulate(scene.x1.float(), scene.x2.float(), scene.P1.float(), scene.P2.float(), method=method)
    assert X.dtype == torch.float32


def test_polynomial_is_optimal_point_by_point():
    """No 3-D point reprojects closer to the noisy pair than the polynomial method's (H&Z §12.5)."""
    scene = synthetic_two_view(500, noise=2.0, seed=4)
    optimal = _reprojection_sq(torchsfm.triangulate(scene.x1, scene.x2, scene.P1, scene.P2), scene)
    for method in METHODS:
        other = _reprojection_sq(torchsfm.triangulate(scene.x1, scene.x2, scene.P1, scene.P2, method=method), scene)
        assert (optimal <= other + 1e-7).all(), method


def test_corrected_points_satisfy_the_epipolar_constraint_and_cost_less_than_sampson_bound():
    scene = synthetic_two_view(300, noise=1.5, seed=5)
    x1_hat, x2_hat = correct_correspondences(scene.x1, scene.x2, scene.F)
    assert sampson_error(scene.F, x1_hat, x2_hat).amax() < 1e-18
    moved = ((x1_hat - scene.x1) ** 2).sum(-1) + ((x2_hat - scene.x2) ** 2).sum(-1)
    # the Sampson error is a first-order estimate of exactly this optimal cost
    assert_close(moved, sampson_error(scene.F, scene.x1, scene.x2), rtol=0.05, atol=1e-6)


def test_polynomial_handles_an_epipole_at_infinity():
    """Pure sideways translation: the epipoles are at infinity, the polynomial loses its top degree."""
    K = torch.tensor([[500.0, 0, 320], [0, 500, 240], [0, 0, 1]], **DOUBLE)
    P1 = projection_matrix(K, torch.eye(3, **DOUBLE), torch.zeros(3, **DOUBLE))
    P2 = projection_matrix(K, torch.eye(3, **DOUBLE), torch.tensor([-1.0, 0, 0], **DOUBLE))
    g = torch.Generator().manual_seed(0)
    X = torch.rand(50, 3, generator=g, **DOUBLE) * torch.tensor([4.0, 3, 4], **DOUBLE) + torch.tensor([-2.0, -1.5, 4], **DOUBLE)
    x1 = project(P1, X) + 0.5 * torch.randn(50, 2, generator=g, **DOUBLE)
    x2 = project(P2, X) + 0.5 * torch.randn(50, 2, generator=g, **DOUBLE)
    exact = torchsfm.triangulate(project(P1, X), project(P2, X), P1, P2)
    assert_close(exact, X, rtol=0, atol=1e-8)
    noisy = torchsfm.triangulate(x1, x2, P1, P2)
    assert torch.isfinite(noisy).all()
    # with a horizontal epipolar pencil the optimum averages the two y coordinates
    reprojected = project(P1, noisy)
    assert_close(reprojected[:, 1], (x1[:, 1] + x2[:, 1]) / 2, rtol=0, atol=1e-8)


def test_polynomial_is_projectively_invariant():
    scene = synthetic_two_view(100, noise=1.0, seed=6)
    H = _projective(1)
    X = torchsfm.triangulate(scene.x1, scene.x2, scene.P1, scene.P2)
    X_distorted = torchsfm.triangulate(scene.x1, scene.x2, scene.P1 @ torch.linalg.inv(H), scene.P2 @ torch.linalg.inv(H))
    mapped = from_homogeneous(torch.cat([X, torch.ones(100, 1, **DOUBLE)], -1) @ H.T)
    assert_close(X_distorted, mapped, rtol=1e-7, atol=1e-7)
    assert fundamental_from_projections(scene.P1, scene.P2).shape == (3, 3)


def test_bad_input():
    scene = synthetic_two_view(10, seed=7)
    with pytest.raises(InputError, match="unknown triangulation method 'dlt'"):
        torchsfm.triangulate(scene.x1, scene.x2, scene.P1, scene.P2, method="dlt")
    with pytest.raises(ShapeError):
        torchsfm.triangulate(scene.x1, scene.x2[:5], scene.P1, scene.P2)
    with pytest.raises(ShapeError):
        torchsfm.triangulate(scene.x1, scene.x2, scene.P1[:, :3], scene.P2)
    with pytest.raises(InputError, match="NaN"):
        torchsfm.triangulate(scene.x1 * float("nan"), scene.x2, scene.P1, scene.P2)
    with pytest.raises(DegenerateConfigurationError, match="same centre"):
        torchsfm.triangulate(scene.x1, scene.x2, scene.P1, scene.P1 * 2)
    with pytest.raises(DegenerateConfigurationError, match="not a finite camera"):
        torchsfm.triangulate(scene.x1, scene.x2, torch.zeros(3, 4, **DOUBLE), scene.P2)
    at_infinity = scene.x2.clone()  # point 3 seen along parallel rays: x2 ~ K2 R K1⁻¹ x1
    ray = scene.K2 @ scene.R @ torch.linalg.solve(scene.K1, torch.cat([scene.x1[3], torch.ones(1, **DOUBLE)]))
    at_infinity[3] = ray[:2] / ray[2]
    for method in torchsfm.TRIANGULATION_METHODS:  # NaN, inf or a wrong finite point before
        with pytest.raises(DegenerateConfigurationError, match=r"1 correspondence\(s\) have parallel rays \(the first: point 3\)"):
            torchsfm.triangulate(scene.x1, at_infinity, scene.P1, scene.P2, method=method)


@pytest.mark.parametrize("method", ["linear_eigen", "polynomial"])
def test_a_non_finite_pair_in_a_batch_gives_nan_rows_not_an_error(method):
    """The mapper triangulates a view against many partners in one batch; one pair without a
    finite linear system (here NaN pixels; in a 500-frame video, the optimal correction of a
    near-degenerate pair) comes back as NaN rows (the mapper drops non-finite points), the
    others as alone — linalg.svd raised for the whole batch before."""
    from torchsfm.config import TriangulationConfig
    from torchsfm.geometry.triangulation import triangulate_points

    scene = synthetic_two_view(10, seed=8)
    x1 = torch.stack([scene.x1, scene.x1 * float("nan")])[:, :, None]
    x2 = scene.x2.expand(2, 10, 2)[:, :, None]
    P1, P2 = scene.P1.expand(2, 1, 3, 4), scene.P2.expand(2, 1, 3, 4)
    X = triangulate_points(x1, x2, P1, P2, TriangulationConfig(method=method))[:, :, 0]
    assert_close(X[0], scene.points3d, rtol=0, atol=1e-8)
    assert torch.isnan(X[1]).all()
