"""The one Levenberg–Marquardt of torchsfm (thesis Appendix C, Nielsen's damping update).

:func:`minimize` is the loop: it minimizes a cost for B independent problems at once — damping
``mu`` (B,), ``nu`` (B,), acceptance and stopping are tensors and each problem stops on its own.
It talks to a problem only through :class:`LMProblem` (cost, linearization, damped solve,
retraction), so dense problems and the sparse bundle adjustment share the same iteration.

:func:`levenberg_marquardt` wraps the dense case: residuals (B, R) of parameters (B, S) that may
live on a manifold (a ``retract(params, delta)`` maps a tangent step (B, P) to new parameters;
the Jacobian is taken with respect to the step at 0, by forward-mode autodiff unless an analytic
``jacobian`` is given), with the damped normal equations solved by batched Cholesky.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Protocol

import torch
from torch import Tensor

from torchsfm.config import LMConfig
from torchsfm.numerics import floor_tiny, where_per_problem

ResidualFn = Callable[[Tensor], Tensor]
RetractFn = Callable[[Tensor, Tensor], Tensor]

_MAX_DAMPING = 1e32
EXPANSION_GAIN = 4 / 3  # gain ratio above which doubling an accepted step lowers the cost further (see _expanded)
EXPANSION_DOUBLINGS = 10  # at most 2^10 times the step: a cost falling toward a limit (a point receding to
# infinity) does not carry the parameters out to overflow


class Linearization(Protocol):
    """A problem linearized at the current parameters.

    ``gradient`` (B, P) is the steepest-descent direction -Jᵀr; ``diagonal`` (B, P) is diag(JᵀJ).
    """

    gradient: Tensor
    diagonal: Tensor

    def solve(self, damping: Tensor) -> tuple[Tensor, Tensor]:
        """Solve (JᵀJ + D) δ = gradient for a damping matrix D = diag(damping (B, P)).
        Returns δ (B, P) and a (B,) bool of successful solves."""


class LMProblem(Protocol):
    """What :func:`minimize` needs from a least-squares problem over parameters (B, S)."""

    def cost(self, params: Tensor) -> Tensor:
        """(B,) cost, ½ Σ ρ(r²) (ρ the identity for plain least squares)."""

    def linearize(self, params: Tensor) -> Linearization:
        """Gradient, diagonal and damped solver at ``params``."""

    def retract(self, params: Tensor, delta: Tensor) -> Tensor:
        """Parameters after the tangent step ``delta`` (B, P)."""


@dataclass
class LMResult:
    """Outcome of :func:`minimize` for B problems.

    Fields:
        params: (B, S) final parameters.
        initial_cost, cost: (B,) cost before and after.
        num_iterations: (B,) int64, damped steps tried (accepted or not).
        converged: (B,) bool, stopped by a tolerance (step, cost decrease or gradient).
        stalled: (B,) bool, stopped because the damping exploded: no step decreased the cost
            (not converged: the result is the last accepted point, which may be far from a minimum).
        failed: (B,) bool, the initial cost was not finite: nothing was done.
        A problem none of the three describes ran out of ``max_iterations``.
    """

    params: Tensor
    initial_cost: Tensor
    cost: Tensor
    num_iterations: Tensor
    converged: Tensor
    stalled: Tensor
    failed: Tensor


def _merge(accept: Tensor, new: Linearization, old: Linearization) -> Linearization:
    """Per problem, the new linearization where a step was accepted, else the old one."""
    if bool(accept.all()):
        return new
    if not bool(accept.any()):
        return old
    return new.where(accept, old)  # only batched (dense) linearizations get here


def minimize(problem: LMProblem, params: Tensor, config: LMConfig) -> LMResult:
    """Levenberg–Marquardt with Nielsen's damping update on a batch of problems.

    The damping matrix is ``mu I`` (thesis, ``config.damping = "identity"``) or ``mu diag(JᵀJ)``
    (Marquardt's scaling, ``"diagonal"``, for parameters of very different units). An accepted
    step that lowered the cost by more than 4/3 of what the model predicted is doubled while the
    cost keeps falling (:func:`_expanded`: a robust loss otherwise creeps to its minimum).
    """
    cost = problem.cost(params)
    initial_cost = cost
    linear = problem.linearize(params)
    diagonal_damping = config.damping == "diagonal"

    def damping_matrix(mu: Tensor, linear: Linearization) -> Tensor:
        scale = linear.diagonal.clamp_min(1e-12) if diagonal_damping else torch.ones_like(linear.diagonal)
        return mu[:, None] * scale

    mu = config.initial_damping * (torch.ones_like(cost) if diagonal_damping else floor_tiny(linear.diagonal.amax(-1)))
    nu = torch.full_like(mu, 2.0)
    failed = ~torch.isfinite(cost)
    converged = ~failed & (linear.gradient.abs().amax(-1) <= config.gradient_tolerance)
    stalled = torch.zeros_like(converged)
    active = ~converged & ~failed
    iterations = torch.zeros_like(mu, dtype=torch.long)
    for _ in range(config.max_iterations):
        if not bool(active.any()):
            break
        damping = damping_matrix(mu, linear)
        delta, solved = linear.solve(damping)
        delta = torch.where(solved[:, None], delta, 0.0)
        tiny_step = solved & (delta.norm(dim=-1) <= config.step_tolerance * (params.norm(dim=-1) + config.step_tolerance))
        candidate = problem.retract(params, delta)
        cost_new = problem.cost(candidate)
        predicted = 0.5 * (delta * (damping * delta + linear.gradient)).sum(-1)
        rho = (cost - cost_new) / floor_tiny(predicted)
        accept = active & solved & ~tiny_step & torch.isfinite(cost_new) & (rho > 0)
        longer = accept & (rho > EXPANSION_GAIN)
        if bool(longer.any()):
            candidate, cost_new = _expanded(problem, params, delta, candidate, cost_new, longer)
        small_decrease = accept & (cost - cost_new <= config.cost_tolerance * cost)

        params = where_per_problem(accept, candidate, params)
        cost_before = cost
        cost = torch.where(accept, cost_new, cost)
        if bool(accept.any()):  # at the candidate: it is ``params`` wherever the step was accepted, and only there is it used
            linear = _merge(accept, problem.linearize(candidate), linear)
        shrink = torch.clamp(1 - (2 * rho - 1) ** 3, min=1 / 3)
        mu = torch.where(accept, mu * shrink, torch.where(active, mu * nu, mu))
        nu = torch.where(accept, torch.full_like(nu, 2.0), torch.where(active, nu * 2, nu))

        iterations = iterations + active.long()
        small_gradient = linear.gradient.abs().amax(-1) <= config.gradient_tolerance
        # a vanishing step is convergence only if it does not raise the cost; a step that shrank
        # because every larger one was rejected (the damping grew) is a stall
        no_worse = torch.isfinite(cost_new) & (cost_new <= cost_before)
        converged = converged | (active & ((tiny_step & no_worse) | small_decrease | small_gradient))
        stalled = stalled | (active & ~converged & ((tiny_step & ~no_worse) | (mu > _MAX_DAMPING)))
        active = active & ~converged & ~stalled
    return LMResult(params=params, initial_cost=initial_cost, cost=cost, num_iterations=iterations, converged=converged,
                    stalled=stalled, failed=failed)


def _expanded(problem: LMProblem, params: Tensor, delta: Tensor, candidate: Tensor, cost: Tensor, longer: Tensor
              ) -> tuple[Tensor, Tensor]:
    """The accepted steps of the ``longer`` (B,) problems doubled while that lowers the cost:
    the candidates (B, *S) and their costs (B,). Along a step δ of the damped model, a quadratic
    cost c(α δ) whose curvature is h_true where the model has h (the model's minimum at α = 1)
    gives the gain ratio ρ = 2 - h_true / h, and c(2 δ) < c(δ) exactly when h_true < 2h/3, i.e.
    ρ > 4/3 (``EXPANSION_GAIN``; with damping the model's minimum lies beyond δ, and ρ > 4/3
    still implies it; each doubling is kept only if the cost did fall). A robust loss puts the model there: its weights ignore the
    loss's negative second derivative, the model is too curved along the steps that release
    outliers, and every step goes about half way (ρ near 2: the iterative-reweighting crawl).
    At most ``EXPANSION_DOUBLINGS`` doublings."""
    reach = torch.ones_like(cost)
    for _ in range(EXPANSION_DOUBLINGS):
        if not bool(longer.any()):
            break
        trial = problem.retract(params, (2 * reach)[:, None] * delta)
        trial_cost = problem.cost(trial)
        longer = longer & torch.isfinite(trial_cost) & (trial_cost < cost)
        candidate = where_per_problem(longer, trial, candidate)
        cost = torch.where(longer, trial_cost, cost)
        reach = torch.where(longer, 2 * reach, reach)
    return candidate, cost


class DenseLinearization:
    """Jᵀ J (B, P, P) and -Jᵀ r of a dense problem; damped solves by batched Cholesky."""

    def __init__(self, jacobian: Tensor, residuals: Tensor) -> None:
        Jt = jacobian.transpose(-1, -2)
        self.normal = Jt @ jacobian
        self.gradient = -(Jt @ residuals[..., None]).squeeze(-1)
        self.diagonal = torch.diagonal(self.normal, dim1=-2, dim2=-1)

    def where(self, condition: Tensor, other: DenseLinearization) -> DenseLinearization:
        """Per problem, this linearization where ``condition`` (B,) holds, else ``other``."""
        blended = DenseLinearization.__new__(DenseLinearization)
        blended.normal = torch.where(condition[:, None, None], self.normal, other.normal)
        blended.gradient = torch.where(condition[:, None], self.gradient, other.gradient)
        blended.diagonal = torch.where(condition[:, None], self.diagonal, other.diagonal)
        return blended

    def solve(self, damping: Tensor) -> tuple[Tensor, Tensor]:
        L, info = torch.linalg.cholesky_ex(self.normal + torch.diag_embed(damping))
        solved = info == 0
        eye = torch.eye(L.shape[-1], dtype=L.dtype, device=L.device)
        delta = torch.cholesky_solve(self.gradient[..., None], torch.where(solved[:, None, None], L, eye)).squeeze(-1)
        return delta, solved


def add_retraction(params: Tensor, delta: Tensor) -> Tensor:
    """Euclidean parameters: ``params + delta``."""
    return params + delta


def forward_jacobian(residuals: ResidualFn, params: Tensor, retract: RetractFn, tangent_dim: int) -> Tensor:
    """d r(retract(params, delta)) / d delta at delta = 0 by forward-mode AD: (B, R, P)."""
    B = params.shape[0]
    zero = params.new_zeros(B, tangent_dim)
    basis = torch.eye(tangent_dim, dtype=params.dtype, device=params.device)[:, None, :].expand(tangent_dim, B, tangent_dim)

    def along(direction: Tensor) -> Tensor:
        return torch.func.jvp(lambda delta: residuals(retract(params, delta)), (zero,), (direction,))[1]

    columns = torch.func.vmap(along)(basis)  # (P, B, R)
    return columns.permute(1, 2, 0)


class _DenseProblem:
    """A dense problem for :func:`minimize`. The residuals of the last ``cost`` call are kept:
    :func:`minimize` linearizes at the parameters it has just costed (the start, an accepted
    candidate), and the residuals need not be computed twice."""

    def __init__(self, residuals: ResidualFn, retract: RetractFn, tangent_dim: int,
                 jacobian: Callable[[Tensor], Tensor] | None) -> None:
        self.residuals, self.retract, self.tangent_dim, self.jacobian = residuals, retract, tangent_dim, jacobian
        self._costed: tuple[Tensor, Tensor] | None = None  # (params, residuals) of the last cost

    def cost(self, params: Tensor) -> Tensor:
        residuals = self.residuals(params)
        self._costed = params, residuals
        return 0.5 * residuals.square().sum(-1)

    def linearize(self, params: Tensor) -> DenseLinearization:
        J = self.jacobian(params) if self.jacobian is not None else forward_jacobian(self.residuals, params, self.retract, self.tangent_dim)
        costed = self._costed is not None and self._costed[0] is params
        return DenseLinearization(J, self._costed[1] if costed else self.residuals(params))


def levenberg_marquardt(
    residuals: ResidualFn,
    params: Tensor,
    config: LMConfig,
    *,
    retract: RetractFn = add_retraction,
    tangent_dim: int | None = None,
    jacobian: Callable[[Tensor], Tensor] | None = None,
) -> LMResult:
    """Minimize ``½‖residuals(p)‖²`` per problem from ``params`` (B, S) (dense normal equations).

    Args:
        residuals: maps (B, S) parameters to (B, R) residuals; rows must not mix problems.
        params: initial parameters (B, S).
        config: iteration cap, initial damping tau, damping mode, tolerances.
        retract: manifold update; defaults to addition (then ``tangent_dim`` = S).
        tangent_dim: P, the size of a step; required with a custom ``retract``.
        jacobian: optional analytic Jacobian (B, S) -> (B, R, P) at delta = 0.
    """
    P = params.shape[-1] if tangent_dim is None else tangent_dim
    return minimize(_DenseProblem(residuals, retract, P, jacobian), params, config)
