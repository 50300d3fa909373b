import pytest
import torch
from torch.testing import assert_close

from torchsfm.camera import (
    Camera,
    camera_center,
    check_intrinsics,
    decompose_projection,
    distort_image,
    distort_points,
    normalized_to_pixels,
    pixels_to_normalized,
    project,
    projection_matrix,
    rescale_intrinsics,
    rescale_pixels,
    undistort_image,
    undistort_points,
)
from torchsfm.errors import DegenerateConfigurationError, InputError
from torchsfm.geometry.rotation import axis_angle_to_rotation

DOUBLE = dict(dtype=torch.float64)


def _camera(seed=0):
    g = torch.Generator().manual_seed(seed)
    K = torch.tensor([[800.0, 0.5, 320.0], [0.0, 780.0, 240.0], [0.0, 0.0, 1.0]], **DOUBLE)
    R = axis_angle_to_rotation(0.3 * torch.randn(3, generator=g, **DOUBLE))
    t = torch.randn(3, generator=g, **DOUBLE)
    return K, R, t


def test_projection_centre_and_decomposition_round_trip():
    K, R, t = _camera()
    P = projection_matrix(K, R, t)
    assert_close(camera_center(P), -R.T @ t, rtol=0, atol=1e-12)
    K2, R2, t2 = decompose_projection(-3.0 * P * -1)  # any positive scale
    assert_close(K2, K, rtol=0, atol=1e-9)
    assert_close(R2, R, rtol=0, atol=1e-12)
    assert_close(t2, t, rtol=0, atol=1e-12)


def test_decomposition_keeps_the_sign_of_depth():
    K, R, t = _camera()
    K2, R2, t2 = decompose_projection(-projection_matrix(K, R, t))
    assert_close(K2, K, rtol=0, atol=1e-9)
    assert torch.linalg.det(R2) < 0  # -P: every depth flips sign, so R is a reflection
    assert_close(R2, -R, rtol=0, atol=1e-12)


def test_camera_dataclass_matches_functions():
    K, R, t = _camera()
    X = torch.randn(10, 3, **DOUBLE, generator=torch.Generator().manual_seed(111)) + torch.tensor([0, 0, 8.0], **DOUBLE)
    camera = Camera(K, R, t)
    assert_close(camera.project(X), project(camera.P, X), rtol=0, atol=1e-9)
    assert_close(camera.center, camera_center(camera.P), rtol=0, atol=1e-12)


def test_normalized_round_trip():
    K, _, _ = _camera()
    x = torch.rand(20, 2, **DOUBLE, generator=torch.Generator().manual_seed(112)) * 600
    assert_close(normalized_to_pixels(pixels_to_normalized(x, K), K), x, rtol=0, atol=1e-10)


@pytest.mark.parametrize("distortion", [(0.0, 0.0), (-0.25, 0.08), (0.1, -0.02), (-0.4, 0.15)])
def test_distortion_round_trip(distortion):
    K, _, _ = _camera()
    coefficients = torch.tensor(distortion, **DOUBLE)
    x = torch.rand(200, 2, **DOUBLE, generator=torch.Generator().manual_seed(113)) * torch.tensor([640.0, 480.0], **DOUBLE)
    assert_close(undistort_points(distort_points(x, K, coefficients), K, coefficients), x, rtol=0, atol=1e-9)


def test_distortion_follows_the_documented_model():
    K = torch.eye(3, **DOUBLE)
    x = torch.tensor([[0.3, -0.4]], **DOUBLE)  # r = 0.5
    distorted = distort_points(x, K, torch.tensor([0.1, 0.2], **DOUBLE))
    assert_close(distorted, x * (1 + 0.1 * 0.25 + 0.2 * 0.0625), rtol=0, atol=1e-15)


def test_camera_projection_applies_distortion():
    K, R, t = _camera()
    X = torch.randn(10, 3, **DOUBLE, generator=torch.Generator().manual_seed(114)) * 0.5 + torch.tensor([0, 0, 6.0], **DOUBLE)
    coefficients = torch.tensor([-0.2, 0.05], **DOUBLE)
    ideal = Camera(K, R, t).project(X)
    observed = Camera(K, R, t, coefficients).project(X)
    assert_close(undistort_points(observed, K, coefficients), ideal, rtol=0, atol=1e-9)


def test_undistort_image_moves_a_dot_to_its_ideal_position():
    K = torch.tensor([[200.0, 0, 63.5], [0, 200.0, 47.5], [0, 0, 1]], **DOUBLE)
    coefficients = torch.tensor([-0.3, 0.0], **DOUBLE)
    ideal = torch.tensor([[100.0, 80.0]], **DOUBLE)
    observed = distort_points(ideal, K, coefficients)[0]
    ys, xs = torch.meshgrid(torch.arange(96.0), torch.arange(128.0), indexing="ij")
    image = torch.exp(-((xs - observed[0]) ** 2 + (ys - observed[1]) ** 2) / 4.0)[None, None].float()
    corrected = undistort_image(image, K, coefficients)
    weights = corrected[0, 0].double()
    centroid = torch.stack([(weights * xs).sum(), (weights * ys).sum()]) / weights.sum()
    assert_close(centroid, ideal[0], rtol=0, atol=0.05)


def test_distort_image_moves_a_dot_to_where_the_lens_sees_it():
    """The inverse of the test above: a dot at its ideal position, resampled through the lens,
    lands where distort_points puts it (centroid within 0.05 px)."""
    K = torch.tensor([[200.0, 0, 63.5], [0, 200.0, 47.5], [0, 0, 1]], **DOUBLE)
    coefficients = torch.tensor([-0.3, 0.0], **DOUBLE)
    ideal = torch.tensor([[100.0, 80.0]], **DOUBLE)
    observed = distort_points(ideal, K, coefficients)[0]
    ys, xs = torch.meshgrid(torch.arange(96.0), torch.arange(128.0), indexing="ij")
    image = torch.exp(-((xs - ideal[0, 0]) ** 2 + (ys - ideal[0, 1]) ** 2) / 4.0)[None, None].float()
    weights = distort_image(image, K, coefficients)[0, 0].double()
    centroid = torch.stack([(weights * xs).sum(), (weights * ys).sum()]) / weights.sum()
    assert_close(centroid, observed, rtol=0, atol=0.05)
    assert float((observed - ideal[0]).norm()) > 0.5  # ten times the tolerance: an unmoved dot would fail


def test_singular_intrinsics_are_rejected():
    K = torch.tensor([[800.0, 0, 320], [0, 0, 240], [0, 0, 1]], **DOUBLE)
    with pytest.raises(DegenerateConfigurationError, match="K is singular"):
        check_intrinsics(K=K)


def test_intrinsics_with_a_focal_length_not_positive_are_refused_with_the_values_named():
    """A mirrored camera (fx < 0) or a flipped one (fy < 0) is refused; K scaled by -1 as a whole
    (K[2, 2] < 0 too) is the same camera and passes."""
    K = torch.tensor([[800.0, 0, 320], [0, 800.0, 240], [0, 0, 1]], **DOUBLE)
    for flip in ([-1.0, 1.0, 1.0], [1.0, -1.0, 1.0]):
        with pytest.raises(InputError, match=r"K has a focal length that is not positive \(fx, fy = -?800, -?800\)"):
            check_intrinsics(K=K * torch.tensor(flip, **DOUBLE)[:, None])
    check_intrinsics(K=-K)
    check_intrinsics(K=torch.stack([K, 2 * K]))


def test_a_resampled_image_s_intrinsics_project_to_its_pixels():
    """Projecting with rescale_intrinsics(K, s) gives the rescaled pixels of projecting with K,
    and rescaling by s then 1 / s is the identity (exactly, up to rounding)."""
    K, R, t = _camera()
    X = torch.randn(20, 3, generator=torch.Generator().manual_seed(1), **DOUBLE) + torch.tensor([0.0, 0.0, 6.0], **DOUBLE)
    for scale in (1 / 3, 0.5, 2.0):
        reduced = project(projection_matrix(rescale_intrinsics(K, scale), R, t), X)
        assert_close(reduced, rescale_pixels(project(projection_matrix(K, R, t), X), scale), rtol=0, atol=1e-9)
        assert_close(rescale_intrinsics(rescale_intrinsics(K, scale), 1 / scale), K, rtol=0, atol=1e-9)


def test_reduce_image_averages_blocks_on_the_rescaled_pixel_grid():
    """A 3× reduction of an image that is one value per 3 × 3 block returns those values, in the
    input's dtype; the reduced pixel x sits at the centre (x + 0.5) · 3 − 0.5 of its block."""
    from torchsfm.images import reduce_image

    blocks = torch.randint(0, 256, (3, 4, 5), generator=torch.Generator().manual_seed(0), dtype=torch.uint8)
    image = blocks.repeat_interleave(3, dim=1).repeat_interleave(3, dim=2)
    reduced = reduce_image(image, 3)
    assert reduced.dtype == torch.uint8
    assert torch.equal(reduced, blocks)
    assert_close(rescale_pixels(torch.tensor([[0.0, 0.0], [4.0, 3.0]]), 3.0), torch.tensor([[1.0, 1.0], [13.0, 10.0]]))

