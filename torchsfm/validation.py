"""Input checks shared by every public function: shapes bound across arguments, finiteness, counts.

A shape spec is a string of space-separated dimensions: an integer must match exactly, a name
binds a size that must agree wherever the same name appears (across all arguments of one call),
and a leading ``*`` admits any number of leading (batch) dimensions::

    check_shapes(x1=(x1, "* N 2"), x2=(x2, "* N 2"), K1=(K1, "* 3 3"))

Failures raise :class:`~torchsfm.errors.ShapeError` naming the argument, its shape and the spec.
"""

from __future__ import annotations

import torch
from torch import Tensor

from torchsfm.errors import InputError, NotEnoughDataError, ShapeError


def check_shapes(**specs: tuple[Tensor, str]) -> dict[str, int]:
    """Check every ``name=(tensor, spec)``; return the sizes bound to the spec's names."""
    bound: dict[str, int] = {}
    bound_by: dict[str, str] = {}
    for name, (tensor, spec) in specs.items():
        if not isinstance(tensor, Tensor):
            raise InputError(f"{name} must be a torch.Tensor, got {type(tensor).__name__}")
        dims = spec.split()
        any_leading = bool(dims) and dims[0] == "*"
        core = dims[1:] if any_leading else dims
        shape = tuple(tensor.shape)
        if len(shape) < len(core) or (not any_leading and len(shape) != len(core)):
            raise ShapeError(f"{name} must have shape ({', '.join(dims)}), got {shape}")
        for dim, size in zip(core, shape[len(shape) - len(core):]):
            if dim.isdigit():
                if size != int(dim):
                    raise ShapeError(f"{name} must have shape ({', '.join(dims)}), got {shape}")
            elif dim in bound and bound[dim] != size:
                raise ShapeError(
                    f"{name} has {dim}={size} but {bound_by[dim]} has {dim}={bound[dim]} "
                    f"(shapes must agree: {name} is {shape})"
                )
            else:
                bound[dim], bound_by[dim] = size, name
    return bound


def check_finite(**tensors: Tensor) -> None:
    """Raise :class:`InputError` naming the first argument that holds a NaN or an infinity."""
    for name, tensor in tensors.items():
        if not bool(torch.isfinite(tensor).all()):
            bad = int((~torch.isfinite(tensor)).sum())
            raise InputError(f"{name} holds {bad} NaN or infinite value(s)")


def check_min_count(name: str, count: int, minimum: int, what: str) -> None:
    """Raise :class:`NotEnoughDataError` when ``count < minimum``."""
    if count < minimum:
        raise NotEnoughDataError(f"{name}: {what} needs at least {minimum}, got {count}")


def check_floating(**tensors: Tensor) -> None:
    """Raise :class:`InputError` for integer or boolean tensors where coordinates are expected."""
    for name, tensor in tensors.items():
        if not isinstance(tensor, Tensor):
            raise InputError(f"{name} must be a torch.Tensor, got {type(tensor).__name__}")
        if not tensor.is_floating_point():
            raise InputError(f"{name} must be a floating-point tensor, got {tensor.dtype}")


def has_distinct_rows(x: Tensor, k: int) -> Tensor:
    """Whether each (N, D) matrix of x (*, N, D) has at least k distinct rows: (*,) bool, exact.

    The first 4k rows are compared pairwise first (a set that is not degenerate has k distinct
    rows among them); only where they hold fewer is every row counted (:func:`count_distinct_rows`),
    so the usual case costs one small comparison instead of D sorts of all N rows.
    """
    head = x[..., : 4 * k, :]
    same = (head[..., :, None, :] == head[..., None, :, :]).all(-1)  # (*, h, h)
    first = ~torch.tril(same, diagonal=-1).any(-1)  # not a repeat of an earlier row
    enough = first.sum(-1) >= k
    if bool(enough.all()):
        return enough
    return enough | (count_distinct_rows(x) >= k)


def count_distinct_rows(x: Tensor) -> Tensor:
    """Number of distinct rows of each (N, D) matrix of x (*, N, D) -> (*,) int64, by an exact
    lexicographic sort (stable sorts, one per column, every matrix at once)."""
    N, D = x.shape[-2:]
    if N == 0:
        return torch.zeros(x.shape[:-2], dtype=torch.long, device=x.device)
    flat = x.reshape(-1, N, D)
    B = flat.shape[0]
    order = torch.arange(N, device=x.device).expand(B, N)
    for column in reversed(range(D)):
        order = order.gather(1, torch.argsort(flat[..., column].gather(1, order), dim=1, stable=True))
    ordered = flat.gather(1, order[..., None].expand(B, N, D))
    return (1 + (ordered[:, 1:] != ordered[:, :-1]).any(-1).sum(1)).reshape(x.shape[:-2])


def lie_on_one_line(points: Tensor, tolerance: float) -> Tensor:
    """Whether each set of points (*, N, D) lies on one line: its extent across its principal
    axis (second singular value of the centred points) at most ``tolerance`` times its extent
    along it -> (*,) bool (fewer than 3 points: True)."""
    spread = torch.linalg.svdvals(points - points.mean(-2, keepdim=True))  # (*, min(N, D))
    spread = torch.nn.functional.pad(spread, (0, max(0, 2 - spread.shape[-1])))  # nothing across a line of < 3 points
    return spread[..., 1] <= tolerance * spread[..., 0]
