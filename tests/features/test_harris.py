import pytest
import torch
from torch.testing import assert_close

from torchsfm.config import HarrisConfig
from torchsfm.errors import ShapeError
from torchsfm.features.harris import HarrisCorners, biquadric_peaks, detect_corners, harris_response
from torchsfm.testing import random_squares, render_squares, square_corners


def _repeatability(subpixel: bool, trials: int = 10) -> torch.Tensor:
    """|detected shift - true shift| for every square corner of two shifted renderings."""
    generator = torch.Generator().manual_seed(0)
    config = HarrisConfig(subpixel=subpixel, max_corners=100, spread_grid=0, relative_threshold=0.05)
    errors = []
    for _ in range(trials):
        geometry_seed = int(torch.randint(0, 10_000, (1,), generator=generator))
        shift = (torch.rand(2, generator=generator, dtype=torch.float64) - 0.5).tolist()
        first, second = random_squares(geometry_seed), random_squares(geometry_seed, shift)
        images = torch.stack([render_squares(first), render_squares(second)]).float()
        corners = detect_corners(images, config)
        a, b = corners.of_image(0).double(), corners.of_image(1).double()
        for truth in square_corners(first):
            da, db = (a - truth).norm(dim=-1), (b - truth - torch.tensor(shift)).norm(dim=-1)
            assert da.min() < 3 and db.min() < 3  # found in both renderings (Harris peaks sit ~1-2 px inside)
            errors.append(((b[db.argmin()] - a[da.argmin()]) - torch.tensor(shift)).norm())
    return torch.stack(errors)


def test_subpixel_repeatability_is_below_a_tenth_of_a_pixel():
    subpixel, pixel = _repeatability(True), _repeatability(False)
    assert subpixel.median() < 0.1 and subpixel.mean() < 0.1
    assert pixel.median() > 3 * subpixel.median()  # the fit is what buys the accuracy


def test_biquadric_fit_recovers_the_peak_of_a_quadric_exactly():
    ys, xs = torch.meshgrid(torch.arange(9.0), torch.arange(9.0), indexing="ij")
    peak = torch.tensor([4.3, 3.8])
    surface = -((xs - peak[0]) ** 2) - 2 * (ys - peak[1]) ** 2 + 0.5 * (xs - peak[0]) * (ys - peak[1])
    offsets, proper = biquadric_peaks(surface[None], torch.tensor([[4, 4]]), 3)
    assert proper.all()
    assert_close(torch.tensor([4.0, 4.0]) + offsets[0], peak, rtol=0, atol=1e-5)


def test_response_is_positive_at_a_corner_and_negative_on_an_edge():
    image = render_squares([(50.0, 40.0, 150.0, 120.0, 0.7)])[None].float()
    response = harris_response(image)[0, 0]
    assert response[40, 50] > 0 and response[80, 50] < 0 and abs(response[80, 100]) < 1e-6


@pytest.mark.parametrize("grid", [0, 4])
def test_selection_shapes_batching_and_spread(grid):
    generator = torch.Generator().manual_seed(1)
    images = torch.rand(2, 1, 96, 128, generator=generator)
    config = HarrisConfig(max_corners=64, spread_grid=grid)
    corners = HarrisCorners(config)(images)
    assert corners.positions.shape == (2, 64, 2) and corners.valid.all()
    border = config.border
    positions = corners.positions
    assert (positions[..., 0] >= border - 1).all() and (positions[..., 0] <= 128 - border).all()
    if grid:
        cells = (positions[0, :, 1] * grid // 96).long() * grid + (positions[0, :, 0] * grid // 128).long()
        assert torch.bincount(cells.clamp(0, grid * grid - 1), minlength=grid * grid).min() >= 1  # every cell holds corners


def test_a_flat_image_has_no_corners():
    corners = detect_corners(torch.full((1, 1, 64, 64), 0.5))
    assert corners.positions.shape == (1, 0, 2) and corners.of_image(0).shape == (0, 2)


def test_a_mask_keeps_corners_off_its_pixels_and_out_of_the_relative_threshold():
    # faint squares on the right, a high-contrast square on the left: the strong one's response
    # sets the relative threshold over the whole image and hides the faint corners; masked out,
    # it no longer does
    squares = [(20.3, 40.7, 60.2, 90.4, 1.0), (110.6, 30.2, 140.1, 60.8, 0.03), (150.4, 90.3, 185.7, 130.5, 0.03)]
    image = render_squares(squares, background=0.0)[None].float()
    config = HarrisConfig(max_corners=100, spread_grid=0, relative_threshold=0.05)
    mask = torch.ones(1, 160, 200, dtype=torch.bool)
    mask[:, :, :100] = False
    unmasked = detect_corners(image, config).of_image(0)
    masked = detect_corners(image, config, mask).of_image(0)
    assert int((unmasked[:, 0] >= 100).sum()) == 0  # the faint corners lose against the strong square
    assert bool((masked[:, 0] >= 100).all())  # nothing on the masked pixels
    faint = torch.tensor([[x, y] for x0, y0, x1, y1, _ in squares[1:] for x, y in ((x0, y0), (x1, y0), (x0, y1), (x1, y1))])
    assert bool(((masked[:, None].double() - faint[None]).norm(dim=-1).amin(0) < 3).all())  # every faint corner found
    with pytest.raises(ShapeError, match=r"mask must be \(1, 160, 200\)"):
        detect_corners(image, config, mask[:, :, :50])
