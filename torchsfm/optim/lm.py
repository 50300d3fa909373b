"""The one Levenberg–Marquardt of torchsfm (thesis Appendix C, Nielsen's damping update).

It minimizes ``½‖r(p)‖²`` for B independent problems at once: damping ``mu`` (B,), ``nu`` (B,),
acceptance and stopping are tensors and each problem stops on its own. Parameters may live on a
manifold: a ``retract(params, delta)`` maps a tangent step ``delta`` (B, P) to new parameters
(B, S), and the Jacobian is taken with respect to ``delta`` at 0 (forward-mode autodiff unless
an analytic ``jacobian`` is given). The damped normal equations ``(JᵀJ + mu I) delta = -Jᵀr``
are solved by batched Cholesky; a failed factorization counts as a rejected step.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import torch
from torch import Tensor

from torchsfm.config import LMConfig

ResidualFn = Callable[[Tensor], Tensor]
RetractFn = Callable[[Tensor, Tensor], Tensor]

_MAX_DAMPING = 1e32


@dataclass
class LMResult:
    """Outcome of :func:`levenberg_marquardt` for B problems.

    Fields:
        params: (B, S) final parameters.
        initial_cost, cost: (B,) ``½‖r‖²`` before and after.
        num_iterations: (B,) int64, damped steps tried (accepted or not).
        converged: (B,) bool, stopped by a tolerance rather than by ``max_iterations``.
    """

    params: Tensor
    initial_cost: Tensor
    cost: Tensor
    num_iterations: Tensor
    converged: Tensor


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


def levenberg_marquardt(
    residuals: ResidualFn,
    params: Tensor,
    config: LMConfig,
    *,
    retract: RetractFn = add_retraction,
    tangent_dim: int | None = None,
    jacobian: Callable[[Tensor], Tensor] | None = None,
) -> LMResult:
    """Minimize ``½‖residuals(p)‖²`` per problem from ``params`` (B, S).

    Args:
        residuals: maps (B, S) parameters to (B, R) residuals; rows must not mix problems.
        params: initial parameters (B, S).
        config: iteration cap, initial damping tau, tolerances.
        retract: manifold update; defaults to addition (then ``tangent_dim`` = S).
        tangent_dim: P, the size of a step; required with a custom ``retract``.
        jacobian: optional analytic Jacobian (B, S) -> (B, R, P) at delta = 0.
    """
    P = params.shape[-1] if tangent_dim is None else tangent_dim

    def linearize(p: Tensor) -> tuple[Tensor, Tensor]:
        J = jacobian(p) if jacobian is not None else forward_jacobian(residuals, p, retract, P)
        return J.transpose(-1, -2) @ J, J.transpose(-1, -2)

    r = residuals(params)
    cost = 0.5 * r.square().sum(-1)
    initial_cost = cost
    A, Jt = linearize(params)
    g = -(Jt @ r[..., None]).squeeze(-1)  # (B, P): steepest descent direction
    eye = torch.eye(P, dtype=params.dtype, device=params.device)
    mu = config.initial_damping * torch.diagonal(A, dim1=-2, dim2=-1).amax(-1).clamp_min(1e-300)
    nu = torch.full_like(mu, 2.0)
    converged = g.abs().amax(-1) <= config.gradient_tolerance
    active = ~converged
    iterations = torch.zeros_like(mu, dtype=torch.long)
    for _ in range(config.max_iterations):
        if not bool(active.any()):
            break
        L, info = torch.linalg.cholesky_ex(A + mu[:, None, None] * eye)
        solved = info == 0
        delta = torch.cholesky_solve(g[..., None], torch.where(solved[:, None, None], L, eye)).squeeze(-1)
        delta = torch.where(solved[:, None], delta, 0.0)
        tiny_step = solved & (delta.norm(dim=-1) <= config.step_tolerance * (params.norm(dim=-1) + config.step_tolerance))
        candidate = retract(params, delta)
        r_new = residuals(candidate)
        cost_new = 0.5 * r_new.square().sum(-1)
        predicted = 0.5 * (delta * (mu[:, None] * delta + g)).sum(-1)
        rho = (cost - cost_new) / predicted.clamp_min(1e-300)
        accept = active & solved & ~tiny_step & torch.isfinite(cost_new) & (rho > 0)
        small_decrease = accept & (cost - cost_new <= config.cost_tolerance * cost)

        params = torch.where(accept[:, None], candidate, params)
        r = torch.where(accept[:, None], r_new, r)
        cost = torch.where(accept, cost_new, cost)
        A_new, Jt_new = linearize(params)
        A = torch.where(accept[:, None, None], A_new, A)
        g = torch.where(accept[:, None], -(Jt_new @ r[..., None]).squeeze(-1), g)
        shrink = torch.clamp(1 - (2 * rho - 1) ** 3, min=1 / 3)
        mu = torch.where(accept, mu * shrink, torch.where(active, mu * nu, mu))
        nu = torch.where(accept, torch.full_like(nu, 2.0), torch.where(active, nu * 2, nu))

        iterations = iterations + active.long()
        small_gradient = g.abs().amax(-1) <= config.gradient_tolerance
        stalled = mu > _MAX_DAMPING
        converged = converged | (active & (tiny_step | small_decrease | small_gradient | stalled))
        active = active & ~converged
    return LMResult(params=params, initial_cost=initial_cost, cost=cost, num_iterations=iterations, converged=converged)
