import math

import torch
from kornia.feature import SIFTDescriptor, SIFTFeature, extract_patches_from_pyramid, laf_from_center_scale_ori, laf_is_filled, \
    match_smnn
from kornia.geometry.subpix import NonMaximaSuppression2d

from torchsfm.images import to_unit_float
from torchsfm.features.sift import DESCRIBED_PER_CALL, InBatches, PooledSIFTDescriptor, SlidingNonMaxima, mutual_ratio_matches, pyramid_patches, \
    sift_features


def test_a_patch_module_in_batches_gives_the_same_numbers():
    """Kornia's SIFT descriptor on 600 patches (three blocks of 256, the last one short) and on
    none: bit for bit what it gives on them all at once."""
    describe = SIFTDescriptor(41, rootsift=True)
    patches = torch.rand(600, 1, 41, 41, generator=torch.Generator().manual_seed(0))
    with torch.no_grad():
        assert torch.equal(InBatches(describe, 256)(patches), describe(patches))
        assert InBatches(describe, 256)(patches[:0]).shape == (0, 128)


def test_the_pooled_descriptor_is_kornias():
    """Smooth random patches (a few strong gradients: bins clipped at 0.2), one of them flat (no
    gradient: a zero descriptor), with and without RootSIFT: Kornia's SIFT descriptor up to the
    order of the pooling sums (float32: within 1e-6 of entries up to 1)."""
    coarse = torch.rand(300, 1, 6, 6, generator=torch.Generator().manual_seed(2))
    patches = torch.nn.functional.interpolate(coarse, size=(41, 41), mode="bilinear")
    patches[7] = 0.5
    for rootsift in (True, False):
        kornia = SIFTDescriptor(41, rootsift=rootsift)
        with torch.no_grad():
            torch.testing.assert_close(PooledSIFTDescriptor.like(kornia)(patches), kornia(patches), rtol=0, atol=1e-6)


def test_sliding_suppression_is_kornias(monkeypatch):
    """Random responses with plateaus (ties are no maxima), odd and even windows, two channels:
    bit for bit Kornia's suppression, and its mask, by the sliding maxima where the window fits
    the image and is at least three pixels both ways; the other windows (one pixel thin, or
    larger than the image) are handed to Kornia's own code, which the last loop checks by
    making the sliding maxima fail."""
    from torchsfm.features import sift

    g = torch.Generator().manual_seed(4)
    shapes = ((2, 2, 64, 90), (1, 1, 15, 15), (1, 1, 12, 40), (1, 1, 300, 17))

    def check(size, shape):
        response = (torch.rand(shape, generator=g) * 20).round()  # whole numbers: many ties
        kornia = NonMaximaSuppression2d(size)
        assert torch.equal(SlidingNonMaxima(size)(response), kornia(response))
        assert torch.equal(SlidingNonMaxima(size)(response, mask_only=True), kornia(response, mask_only=True))

    sliding = [(size, shape) for size in ((15, 15), (16, 9), (3, 3)) for shape in shapes
               if shape[-2] >= size[0] and shape[-1] >= size[1]]
    assert len(sliding) == 9
    for size, shape in sliding:
        check(size, shape)
    def not_handed_over(*_):
        raise AssertionError("the sliding maxima ran where Kornia's own code should")

    monkeypatch.setattr(sift, "running_maximum", not_handed_over)
    for size, shape in [((2, 5), shape) for shape in shapes] + [((1, 1), shapes[0]), ((15, 15), shapes[2]), ((16, 9), shapes[2])]:
        check(size, shape)


def test_pyramid_patches_are_kornias():
    """Frames of scales that pick each pyramid level of a 240 × 320 image (and one beyond the
    coarsest), turned, anisotropic, and reaching over the border: Kornia's
    ``extract_patches_from_pyramid`` patches up to the rounding of the sampling coordinates
    (within 1e-4 of grey values in [0, 1]: measured 2.1e-5 here, 6.3e-5 on a Fountain-P11 photo)."""
    g = torch.Generator().manual_seed(3)
    image = torch.nn.functional.interpolate(torch.rand(1, 1, 30, 40, generator=g), size=(240, 320), mode="bicubic")
    count = 60
    centres = torch.rand(1, count, 2, generator=g) * torch.tensor([340.0, 260.0]) - 10.0  # some outside the image
    scales = torch.logspace(math.log10(5.0), math.log10(400.0), count)[None, :, None, None]
    angles = torch.rand(1, count, 1, generator=g) * 360.0
    frames = laf_from_center_scale_ori(centres, scales, angles)
    frames[:, ::3, :, 0] *= 1.7  # anisotropic
    for size in (41, 19):
        expected = extract_patches_from_pyramid(image, frames, size)[0]
        torch.testing.assert_close(pyramid_patches(image, frames[0], size), expected, rtol=0, atol=1e-4)


def test_sift_features_match_kornias():
    """On three textured synthetic images, described side by side on two threads: the keypoints of
    Kornia's SIFTFeature itself on each image alone (its filled slots), in the views' order, and its descriptors up
    to the rounding of the patches' coordinates (over a thousand features each, so the descriptor
    runs in several blocks): every entry within 3e-3 (unit-length descriptors; a gradient on an
    orientation bin's edge can change bins; measured 4.6e-4 here, 2.2e-3 on a Fountain-P11 photo), all
    but 0.1 % of them within 1e-4 (measured 0.035 %)."""
    g = torch.Generator().manual_seed(1)
    greys = [(torch.nn.functional.interpolate(torch.rand(1, 1, 60, 80, generator=g), size=(240, 320), mode="bilinear")[0] * 255)
             .round().to(torch.uint8) for _ in range(3)]
    threads = torch.get_num_threads()
    torch.set_num_threads(2)
    try:
        points, descriptors = sift_features(greys, 2000)
    finally:
        torch.set_num_threads(threads)
    for grey, view_points, view_descriptors in zip(greys, points, descriptors):
        assert view_points.shape[0] > 2 * DESCRIBED_PER_CALL
        with torch.no_grad():
            frames, _, expected = SIFTFeature(num_features=2000)(to_unit_float(grey[None]))
        filled = laf_is_filled(frames)[0]
        assert torch.equal(view_points, frames[0, filled, :, 2].double())
        difference = (view_descriptors - expected[0, filled]).abs()
        assert float(difference.max()) < 3e-3
        assert float((difference > 1e-4).double().mean()) < 1e-3


def test_unfilled_detector_slots_are_dropped():
    """An image with a few blobs on a flat ground: the detector fills fewer slots than asked for
    and Kornia returns the rest as zero frames sharing one descriptor (which would match each
    other between views); only the filled ones are kept."""
    image = torch.full((1, 200, 200), 128, dtype=torch.uint8)
    for row, column in ((40, 40), (60, 150), (150, 70), (140, 160)):
        image[0, row - 4:row + 4, column - 4:column + 4] = 250
    (points,), (descriptors,) = sift_features([image], 500)
    with torch.no_grad():
        frames, _, _ = SIFTFeature(num_features=500)(to_unit_float(image[None]))
    filled = laf_is_filled(frames)[0]
    assert 0 < int(filled.sum()) < 500
    assert points.shape == (int(filled.sum()), 2) and descriptors.shape == (int(filled.sum()), 128)
    assert torch.equal(points, frames[0, filled, :, 2].double())


def test_mutual_ratio_matches_are_kornias():
    """Descriptors of 300 and 250 points, 150 of them the same points re-described with noise
    (matches; a third of them with a near twin in the other set, which fails the ratio test), a
    descriptor copied twice into the other set (a tie at its nearest: no match), at ratios 0.6,
    0.8, 0.95: Kornia's ``match_smnn`` pairs, in its order; none with fewer than two descriptors."""
    g = torch.Generator().manual_seed(5)
    first = torch.nn.functional.normalize(torch.rand(300, 128, generator=g), dim=1)
    second = torch.nn.functional.normalize(torch.rand(250, 128, generator=g), dim=1)
    second[:150] = torch.nn.functional.normalize(first[100:250] + 0.05 * torch.rand(150, 128, generator=g), dim=1)
    second[150:200] = torch.nn.functional.normalize(first[100:150] + 0.06 * torch.rand(50, 128, generator=g), dim=1)
    second[200], second[201] = first[0], first[0]
    for ratio in (0.6, 0.8, 0.95):
        for a, b in ((first, second), (second, first)):
            _, expected = match_smnn(a, b, ratio)
            found = mutual_ratio_matches(a, b, ratio)
            assert torch.equal(found, expected)
            assert 0 < found.shape[0] < 150 and not bool((found[:, 0 if a is first else 1] == 0).any())
    assert mutual_ratio_matches(first[:1], second, 0.8).shape == (0, 2)
