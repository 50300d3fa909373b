import torch
from kornia.feature import SIFTDescriptor, SIFTFeature

from torchsfm.images import to_unit_float
from torchsfm.sfm.sift import DESCRIBED_PER_CALL, InBatches, sift_features


def test_a_patch_module_in_batches_gives_the_same_numbers():
    """Kornia's SIFT descriptor on 600 patches (three blocks of 256, the last one short) and on
    none: bit for bit what it gives on them all at once."""
    describe = SIFTDescriptor(41, rootsift=True)
    patches = torch.rand(600, 1, 41, 41, generator=torch.Generator().manual_seed(0))
    with torch.no_grad():
        assert torch.equal(InBatches(describe, 256)(patches), describe(patches))
        assert InBatches(describe, 256)(patches[:0]).shape == (0, 128)


def test_sift_features_are_kornias():
    """On a textured synthetic image: the keypoints and descriptors of Kornia's SIFTFeature itself
    (over a thousand features, so the descriptor runs in several blocks)."""
    g = torch.Generator().manual_seed(1)
    image = torch.nn.functional.interpolate(torch.rand(1, 1, 60, 80, generator=g), size=(240, 320), mode="bilinear")
    grey = (image[0] * 255).round().to(torch.uint8)
    points, descriptors = sift_features([grey], 2000)
    assert points[0].shape[0] > 2 * DESCRIBED_PER_CALL
    with torch.no_grad():
        frames, _, expected = SIFTFeature(num_features=2000)(to_unit_float(grey[None]))
    assert torch.equal(descriptors[0], expected[0])
    assert torch.equal(points[0], frames[0, :, :, 2].double())
