import torch
from kornia.feature import SIFTDescriptor, SIFTFeature

from torchsfm.images import to_unit_float
from torchsfm.sfm.sift import DESCRIBED_PER_CALL, InBatches, PooledSIFTDescriptor, sift_features


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
    gradient: a zero descriptor), with and without RootSIFT: bit for bit Kornia's SIFT descriptor."""
    coarse = torch.rand(300, 1, 6, 6, generator=torch.Generator().manual_seed(2))
    patches = torch.nn.functional.interpolate(coarse, size=(41, 41), mode="bilinear")
    patches[7] = 0.5
    for rootsift in (True, False):
        kornia = SIFTDescriptor(41, rootsift=rootsift)
        with torch.no_grad():
            assert torch.equal(PooledSIFTDescriptor.like(kornia)(patches), kornia(patches))


def test_sift_features_are_kornias():
    """On three textured synthetic images, described side by side on two threads: the keypoints
    and descriptors of Kornia's SIFTFeature itself on each image alone, in the views' order (over
    a thousand features each, so the descriptor runs in several blocks)."""
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
        assert torch.equal(view_descriptors, expected[0])
        assert torch.equal(view_points, frames[0, :, :, 2].double())
