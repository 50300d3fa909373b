import pytest
import torch
from torch.testing import assert_close

from torchsfm.config import LMConfig
from torchsfm.geometry.rotation import axis_angle_to_rotation
from torchsfm.optim.lm import DenseLinearization, forward_jacobian, levenberg_marquardt, minimize

DOUBLE = dict(dtype=torch.float64)


def rosenbrock(p):
    """Residuals (B, 2) of the Rosenbrock function, minimum 0 at (1, 1)."""
    return torch.stack([10 * (p[:, 1] - p[:, 0] ** 2), 1 - p[:, 0]], dim=-1)


def test_batched_rosenbrock_converges_per_problem():
    start = torch.tensor([[-1.2, 1.0], [0.5, 0.5], [1.0, 1.0], [3.0, -2.0]], **DOUBLE)
    result = levenberg_marquardt(rosenbrock, start, LMConfig())
    assert_close(result.params, torch.ones(4, 2, **DOUBLE), rtol=0, atol=1e-8)
    assert result.converged.all()
    assert result.num_iterations[2] == 0  # started at the optimum: nothing to do
    assert (result.num_iterations[[0, 3]] > result.num_iterations[1]).all()
    assert (result.cost <= result.initial_cost).all()


def rosenbrock_jacobian(p):
    """(B, 2, 2) analytic Jacobian of :func:`rosenbrock`."""
    return torch.stack([torch.stack([-20 * p[:, 0], torch.full_like(p[:, 0], 10.0)], -1),
                        torch.stack([-torch.ones_like(p[:, 0]), torch.zeros_like(p[:, 0])], -1)], dim=1)


def test_analytic_jacobian_gives_the_same_answer():
    start = torch.tensor([[-1.2, 1.0]], **DOUBLE)
    assert_close(rosenbrock_jacobian(start), forward_jacobian(rosenbrock, start, lambda p, d: p + d, 2))
    result = levenberg_marquardt(rosenbrock, start, LMConfig(), jacobian=rosenbrock_jacobian)
    assert_close(result.params, torch.ones(1, 2, **DOUBLE), rtol=0, atol=1e-8)


def test_residuals_are_computed_once_per_costed_point_with_the_same_result():
    """The dense problem reuses the residuals of the point it has just costed when it linearizes
    there: one residual evaluation per cost evaluation, and bit for bit the result of a problem
    that evaluates them again (four problems that accept their steps at different iterations)."""
    class Recomputing:
        def cost(self, params):
            return 0.5 * rosenbrock(params).square().sum(-1)

        def linearize(self, params):
            return DenseLinearization(rosenbrock_jacobian(params), rosenbrock(params))

        def retract(self, params, delta):
            return params + delta

    calls = []

    def counted(p):
        calls.append(p)
        return rosenbrock(p)

    start = torch.tensor([[-1.2, 1.0], [0.5, 0.5], [3.0, -2.0], [-0.5, 2.0]], **DOUBLE)
    result = levenberg_marquardt(counted, start, LMConfig(), jacobian=rosenbrock_jacobian)
    reference = minimize(Recomputing(), start, LMConfig())
    assert_close(result.params, reference.params, rtol=0, atol=0)
    assert_close(result.cost, reference.cost, rtol=0, atol=0)
    assert torch.equal(result.num_iterations, reference.num_iterations)
    assert len(set(result.num_iterations.tolist())) > 1  # the problems stop at different iterations
    assert len(calls) == 1 + int(result.num_iterations.max())  # the start, then one candidate per iteration


def test_manifold_parameters_with_a_retraction():
    """Recover rotations from noisy vectors: R ← R exp([δ]x), states are flattened 3x3 matrices."""
    g = torch.Generator().manual_seed(0)
    R_true = axis_angle_to_rotation(torch.randn(5, 3, generator=g, **DOUBLE))
    points = torch.randn(5, 20, 3, generator=g, **DOUBLE)
    observed = points @ R_true.transpose(-1, -2)

    def residuals(state):
        return (points @ state.reshape(-1, 3, 3).transpose(-1, -2) - observed).flatten(1)

    def retract(state, delta):
        return (state.reshape(-1, 3, 3) @ axis_angle_to_rotation(delta)).flatten(1)

    start = torch.eye(3, **DOUBLE).expand(5, 3, 3).flatten(1)
    result = levenberg_marquardt(residuals, start, LMConfig(), retract=retract, tangent_dim=3)
    assert_close(result.params.reshape(-1, 3, 3), R_true, rtol=0, atol=1e-9)


def test_iteration_cap_reports_not_converged():
    result = levenberg_marquardt(rosenbrock, torch.tensor([[-1.2, 1.0]], **DOUBLE), LMConfig(max_iterations=2))
    assert not result.converged.any()
    assert result.num_iterations.item() == 2


@pytest.mark.parametrize("shift", [1e3, 1e-3])
def test_damping_adapts_to_scale(shift):
    """A linear least-squares problem is solved whatever the scale of the Jacobian."""
    A = shift * torch.randn(1, 10, 3, generator=torch.Generator().manual_seed(2), **DOUBLE)
    b = torch.randn(1, 10, **DOUBLE, generator=torch.Generator().manual_seed(101))
    result = levenberg_marquardt(lambda p: (A @ p[..., None]).squeeze(-1) - b, torch.zeros(1, 3, **DOUBLE), LMConfig())
    expected = torch.linalg.lstsq(A, b[..., None]).solution.squeeze(-1)
    assert_close(result.params, expected, rtol=1e-6, atol=1e-9)


def test_status_is_honest():
    """A NaN start is ``failed`` (nothing done); a residual no step can decrease (its Jacobian is
    wrong) ends ``stalled``, not ``converged``."""
    nan_start = levenberg_marquardt(rosenbrock, torch.tensor([[float("nan"), 1.0]], **DOUBLE), LMConfig())
    assert nan_start.failed.all() and not nan_start.converged.any() and nan_start.num_iterations.item() == 0

    def residual(p):
        return p.square() + 1.0  # minimum at 0, but the Jacobian below points the wrong way

    def wrong_jacobian(p):
        return -torch.diag_embed(2 * p)

    result = levenberg_marquardt(residual, torch.tensor([[1.0, 2.0]], **DOUBLE), LMConfig(max_iterations=500),
                                 jacobian=wrong_jacobian)
    assert result.stalled.all() and not result.converged.any() and not result.failed.any()


class UndersoldQuadratic:
    """c(p) = ½ h (p - 3)² per problem, p (B, 1), linearized with curvature 1 where the cost has
    h: the model's step goes the share h of the way (gain ratio 2 - h). Counts its cost calls."""

    def __init__(self, curvature: float) -> None:
        self.curvature, self.costs = curvature, 0

    def cost(self, params):
        self.costs += 1
        return 0.5 * self.curvature * (params[:, 0] - 3).square()

    def linearize(self, params):
        return DenseLinearization(torch.ones(params.shape[0], 1, 1, **DOUBLE), self.curvature * (params - 3))

    def retract(self, params, delta):
        return params + delta


def test_a_step_the_model_undersells_is_doubled_while_the_cost_falls(monkeypatch):
    """At curvature 1/4 the model's step from -1 reaches 0 (gain ratio 1.75 > 4/3): doubled to 1,
    then to 3, the minimum (the next doubling, to 7, costs more): one iteration. Without the
    doubling (its threshold out of reach) every step goes a quarter of the remaining way. An exact
    model (gain ratio 1) is never doubled: one cost call per iteration besides the start's."""
    start, config = torch.tensor([[-1.0], [-1.0]], **DOUBLE), LMConfig(initial_damping=1e-12, damping="identity")
    doubled = minimize(UndersoldQuadratic(0.25), start, config)
    assert_close(doubled.params, torch.full((2, 1), 3.0, **DOUBLE), rtol=0, atol=1e-9)  # the damping's 1e-12
    assert doubled.num_iterations.tolist() == [1, 1] and doubled.converged.all()
    exact = UndersoldQuadratic(1.0)
    plain = minimize(exact, start, config)
    assert_close(plain.params, torch.full((2, 1), 3.0, **DOUBLE), rtol=0, atol=1e-9)
    assert exact.costs == 1 + int(plain.num_iterations.max())
    monkeypatch.setattr("torchsfm.optim.lm.EXPANSION_GAIN", float("inf"))
    crawling = minimize(UndersoldQuadratic(0.25), start, config)
    assert (crawling.num_iterations > 20).all()
    assert (crawling.cost > doubled.cost).all()


class Receding:
    """c(p) = 1 / (1 + p): it falls for ever towards 0 (a point receding to infinity), linearized
    twice as curved as it is at p = 0 (gain ratio 1.6 on the first step)."""

    def cost(self, params):
        return 1 / (1 + params[:, 0])

    def linearize(self, params):
        return DenseLinearization(torch.full((params.shape[0], 1, 1), 2.0, **DOUBLE), -0.5 / (1 + params).square())

    def retract(self, params, delta):
        return params + delta


def test_a_step_is_doubled_at_most_ten_times():
    """A cost that never stops falling along the step: its first step (0.25) is doubled ten times,
    to 256, not run out to overflow."""
    result = minimize(Receding(), torch.zeros(1, 1, **DOUBLE), LMConfig(max_iterations=1, initial_damping=1e-12, damping="identity"))
    assert_close(result.params, torch.full((1, 1), 256.0, **DOUBLE), rtol=1e-9, atol=0)  # the damping's 1e-12
