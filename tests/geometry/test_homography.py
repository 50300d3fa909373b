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


def test_transfer_errors_of_many_hypotheses_equal_one_at_a_time():
    """The (N, 3) x (3, 3h) product gives each homography's transfer error ‖x2 - π(H x1)‖²
    (float64, to 1e-12 relative against the mapping written out), +inf where a point maps to
    infinity; :func:`transfer_error` is its one-homography case."""
    from torchsfm.geometry.homography import transfer_error, transfer_error_of_hypotheses

    generator = torch.Generator().manual_seed(1)
    H = torch.eye(3, dtype=torch.float64) + 0.05 * torch.randn(7, 3, 3, generator=generator, dtype=torch.float64)
    H[0, 2] = torch.tensor([0.0, 0.0, 0.0], dtype=torch.float64)  # every point at infinity
    x1, x2 = (600 * torch.rand(40, 2, generator=generator, dtype=torch.float64) for _ in range(2))
    batched = transfer_error_of_hypotheses(H, x1, x2)
    assert batched.shape == (7, 40)
    assert bool(batched[0].isinf().all())
    written_out = torch.stack([(from_homogeneous(to_homogeneous(x1) @ h.T) - x2).square().sum(-1) for h in H[1:]])
    assert_close(batched[1:], written_out, rtol=1e-12, atol=0)
    assert_close(transfer_error(H, x1.expand(7, -1, -1), x2.expand(7, -1, -1)), batched, rtol=1e-12, atol=0)


def test_decomposition_recovers_the_motion_and_plane():
    """H = s (R + t nᵀ) for 50 random motions and planes in front of camera 1 (any positive
    scale s): one of the four decompositions is (R, t, n) to 1e-9 (float64); the four come in
    pairs (R, t, n), (R, -t, -n). A pure image translation (a fronto-parallel plane, a camera
    sliding along it) gives R = I, n = (0, 0, 1)."""
    from torchsfm.geometry.homography import decompose_homography
    from torchsfm.geometry.rotation import axis_angle_to_rotation

    generator = torch.Generator().manual_seed(3)
    for _ in range(50):
        R = axis_angle_to_rotation(0.4 * torch.randn(3, generator=generator, dtype=torch.float64))
        t = 0.5 * torch.randn(3, generator=generator, dtype=torch.float64)
        n = torch.randn(3, generator=generator, dtype=torch.float64)
        n[2] = n[2].abs() + 0.5
        n = n / n.norm()
        scale = 0.1 + 5 * float(torch.rand(1, generator=generator))
        Rs, ts, ns = decompose_homography(scale * (R + torch.outer(t, n) / 3.0))
        assert_close(Rs[1::2], Rs[0::2], rtol=0, atol=0)
        assert_close(ts[1::2], -ts[0::2], rtol=0, atol=0)
        assert_close(ns[1::2], -ns[0::2], rtol=0, atol=0)
        error = ((Rs - R).abs().amax((-1, -2)) + (ts - t / 3.0).abs().amax(-1) + (ns - n).abs().amax(-1))
        assert float(error.min()) < 1e-9
    H = torch.eye(3, dtype=torch.float64)
    H[:2, 2] = torch.tensor([0.1, -0.04], dtype=torch.float64)
    Rs, ts, ns = decompose_homography(H)
    found = int(((ns - torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64)).norm(dim=-1)).argmin())
    assert_close(Rs[found], torch.eye(3, dtype=torch.float64), rtol=0, atol=1e-12)
    assert_close(ts[found], H[:, 2] - torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64), rtol=0, atol=1e-12)
