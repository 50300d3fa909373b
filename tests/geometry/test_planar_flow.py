"""The quadratic planar flow (eq. 5.2.1 corrected), its RANSAC plug-in, and the joint plane models."""

import torch
from torch.testing import assert_close

from torchsfm.config import RansacConfig
from torchsfm.geometry.planar_flow import fit_planar_flow, planar_flow
from torchsfm.robust.models import HomographyModel, JointModel, PlanarFlowModel
from torchsfm.robust.ransac import ransac


def _points(n: int, seed: int) -> torch.Tensor:
    return torch.rand(n, 2, generator=torch.Generator().manual_seed(seed), dtype=torch.float64) * 2 - 1


def test_least_squares_recovers_the_eight_parameters_exactly():
    """float64, noise-free: p from 20 points to 1e-10."""
    p = torch.tensor([[0.01, -0.02, 0.015, 0.005, 0.1, -0.05, 0.003, -0.002]], dtype=torch.float64)
    x = _points(20, 0)[None]
    flow = planar_flow(p[:, None], x)[:, 0]
    assert_close(fit_planar_flow(x, flow), p, rtol=0, atol=1e-10)


def test_the_corrected_model_has_the_shared_quadratic_terms():
    """u = p1 x + p2 y + p5 + p7 x² + p8 xy, v = p3 x + p4 y + p6 + p7 xy + p8 y² (ERRATA)."""
    p = torch.arange(1.0, 9.0, dtype=torch.float64)[None, None]
    x = torch.tensor([[[2.0, 3.0]]], dtype=torch.float64)
    u = 1 * 2 + 2 * 3 + 5 + 7 * 4 + 8 * 6
    v = 3 * 2 + 4 * 3 + 6 + 7 * 6 + 8 * 9
    assert_close(planar_flow(p, x)[0, 0, 0], torch.tensor([u, v], dtype=torch.float64))


def _two_frame_rows(flows: list[torch.Tensor], n: int, outliers: int, seed: int) -> tuple[torch.Tensor, torch.Tensor]:
    """Rows (x, y, x'_1, y'_1, x'_2, y'_2) in pixels from flows defined on pixel coordinates."""
    g = torch.Generator().manual_seed(seed)
    x = torch.rand(n, 2, generator=g, dtype=torch.float64) * torch.tensor([640.0, 480.0], dtype=torch.float64)
    others = [x + flow(x) for flow in flows]
    inlier = torch.ones(n, dtype=torch.bool)
    inlier[:outliers] = False
    for other in others:
        other[:outliers] += 30 + 20 * torch.rand(outliers, 2, generator=g, dtype=torch.float64)
    return torch.cat([x, *others], dim=-1)[None], inlier


def test_planar_flow_ransac_finds_planted_outliers_and_the_flow_exactly():
    """Two frames, 30% outliers moved 30-50 px: the joint flow model's mask and flows are exact."""
    coefficients = [torch.tensor([0.02, -0.01, 0.01, 0.03, 4.0, -3.0, 1e-5, -2e-5], dtype=torch.float64),
                     torch.tensor([-0.01, 0.02, -0.02, 0.01, -5.0, 2.0, -2e-5, 1e-5], dtype=torch.float64)]
    flows = [lambda x, c=c: planar_flow(c[None, None], x[None])[0, 0] for c in coefficients]
    data, inlier = _two_frame_rows(flows, 200, 60, 1)
    model = PlanarFlowModel(data)
    found = ransac(model, data, RansacConfig(inlier_threshold=1.0), generator=torch.Generator().manual_seed(0))
    assert torch.equal(found.inlier_mask[0], inlier)
    refit = model.fit_weighted(data, found.inlier_mask.double())[0]  # (J, 8), normalized frame
    x, displacement = model.normalize(data)
    predicted = planar_flow(refit[None], x)[0]  # (J, N, 2)
    assert_close(predicted[:, inlier], displacement[0].transpose(0, 1)[:, inlier], rtol=0, atol=1e-10)


def test_joint_homographies_are_exact_and_share_their_inliers():
    H = [torch.tensor([[1.02, 0.01, 5.0], [-0.01, 0.98, -3.0], [1e-5, -2e-5, 1.0]], dtype=torch.float64),
         torch.tensor([[0.97, -0.02, -4.0], [0.02, 1.01, 6.0], [-2e-5, 1e-5, 1.0]], dtype=torch.float64)]

    def mapping(matrix):
        def apply(x):
            mapped = torch.cat([x, torch.ones_like(x[:, :1])], -1) @ matrix.T
            return mapped[:, :2] / mapped[:, 2:] - x
        return apply

    data, inlier = _two_frame_rows([mapping(h) for h in H], 200, 60, 2)
    model = JointModel(HomographyModel, data)
    found = ransac(model, data, RansacConfig(inlier_threshold=1.0), generator=torch.Generator().manual_seed(0))
    assert torch.equal(found.inlier_mask[0], inlier)
    for j in range(2):
        estimate = found.model[0, j] / found.model[0, j, 2, 2]
        assert_close(estimate, H[j], rtol=0, atol=1e-8)


def test_joint_model_is_each_frames_model_batched():
    """Two problems, three frames, padded rows: the joint model's minimal and weighted fits, its
    residuals and its restriction to one problem equal those of each frame's own model (the
    frames run as extra problems of one plug-in), to rounding: a batched solve may sum in
    another order."""
    SAME = {"rtol": 1e-12, "atol": 1e-12}
    g = torch.Generator().manual_seed(0)
    data = 500 * torch.rand(2, 30, 8, generator=g, dtype=torch.float64)
    valid = torch.ones(2, 30, dtype=torch.bool)
    valid[1, 25:] = False
    joint = JointModel(HomographyModel, data, valid)
    frames = [HomographyModel(torch.cat([data[..., :2], data[..., j:j + 2]], -1), valid) for j in (2, 4, 6)]
    samples = data[:, torch.randperm(30, generator=g)[:20]].unflatten(1, (5, 4))  # (2, 5, 4, 8)
    models, solvable = joint.fit_minimal(samples)
    weights = valid.double()
    refit = joint.fit_weighted(data, weights)
    residuals = joint.residuals(models, data)
    per_frame = []
    for j, model in enumerate(frames):
        H, ok = model.fit_minimal(torch.cat([samples[..., :2], samples[..., 2 + 2 * j:4 + 2 * j]], -1))
        assert_close(models[:, :, j], H, **SAME)
        assert ok.all() and solvable.all()
        assert_close(refit[:, j], model.fit_weighted(torch.cat([data[..., :2], data[..., 2 + 2 * j:4 + 2 * j]], -1), weights), **SAME)
        per_frame.append(model.residuals(H, torch.cat([data[..., :2], data[..., 2 + 2 * j:4 + 2 * j]], -1)))
    assert_close(residuals, torch.stack(per_frame).amax(0), **SAME)
    second = joint.restricted(torch.tensor([1]))
    assert_close(second.fit_minimal(samples[1:])[0], models[1:], **SAME)


def test_minimal_homography_solver_is_exact_and_flags_degenerate_samples():
    H = torch.tensor([[1.1, 0.05, 10.0], [-0.03, 0.95, 4.0], [1e-4, 2e-4, 1.0]], dtype=torch.float64)
    x = torch.tensor([[10.0, 20.0], [300.0, 40.0], [280.0, 400.0], [30.0, 350.0]], dtype=torch.float64)
    mapped = torch.cat([x, torch.ones(4, 1, dtype=torch.float64)], -1) @ H.T
    samples = torch.cat([x, mapped[:, :2] / mapped[:, 2:]], -1)
    collinear = samples.clone()
    collinear[:, 1] = collinear[:, 0]  # four points on a line
    model = HomographyModel(samples[None])
    models, ok = model.fit_minimal(torch.stack([samples, collinear])[None])
    assert ok.tolist() == [[True, False]]
    assert_close(models[0, 0] / models[0, 0, 2, 2], H, rtol=0, atol=1e-9)
