import torch
from torch.testing import assert_close

from torchsfm.camera import from_homogeneous, to_homogeneous
from torchsfm.geometry.homography import homography_jacobian


def test_jacobian_matches_central_differences():
    H = torch.tensor([[1.2, -0.3, 15.0], [0.25, 0.9, -7.0], [3e-4, -2e-4, 1.0]], dtype=torch.float64)
    x = torch.rand(20, 2, generator=torch.Generator().manual_seed(0), dtype=torch.float64) * 600
    step = 1e-4

    def mapped(points):
        return from_homogeneous(to_homogeneous(points) @ H.T)

    numeric = torch.stack([(mapped(x + step * e) - mapped(x - step * e)) / (2 * step)
                           for e in torch.eye(2, dtype=torch.float64)], dim=-1)  # (N, 2 outputs, 2 inputs)
    assert_close(homography_jacobian(H, x), numeric, rtol=0, atol=1e-8)
