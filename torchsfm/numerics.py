"""Numeric helpers the batched engines share: the one guard of every division by a non-negative
quantity that may be zero, the per-problem choice between two batched tensors, the
conversions to a compressed-sparse-row matrix, and the connected components of a graph."""

from __future__ import annotations

import contextlib
import warnings
from collections.abc import Iterator

import torch
from torch import Tensor


def floor_tiny(x: Tensor) -> Tensor:
    """``x`` clamped below at the smallest positive normal number of its dtype (a fixed constant
    such as 1e-300 is 0 in float32, where it would guard nothing)."""
    return x.clamp_min(torch.finfo(x.dtype).tiny)


def sparse_rows(x: Tensor) -> Tensor:
    """A dense (n, m) matrix as a compressed-sparse-row one (its products with a dense matrix cost
    its nonzeros, and multiply 3x faster than the COO layout's), without PyTorch's warning that
    the layout is in beta (the products used are tested: :func:`_without_beta_warning`)."""
    with _without_beta_warning():
        return x.to_sparse_csr()


def sparse_rows_of_transpose(x: Tensor) -> Tensor:
    """The transpose of a dense (n, m) bool matrix as an (m, n) float32 compressed-sparse-row
    one, built from its set entries (sorted once by column) rather than by transposing the dense
    matrix: the work is its set entries, not n · m."""
    rows, columns = x.nonzero().unbind(1)  # in row order
    order = torch.sort(columns, stable=True).indices  # column order, row order within a column
    crow = torch.zeros(x.shape[1] + 1, dtype=torch.long, device=x.device)
    crow[1:] = torch.bincount(columns, minlength=x.shape[1]).cumsum(0)
    with _without_beta_warning():
        return torch.sparse_csr_tensor(crow, rows[order], torch.ones(rows.numel(), device=x.device),
                                       size=x.shape[::-1], check_invariants=False)


@contextlib.contextmanager
def _without_beta_warning() -> Iterator[None]:
    """PyTorch's warning that the compressed-sparse-row layout is in beta, silenced."""
    with warnings.catch_warnings():
        warnings.filterwarnings("ignore", message="Sparse CSR tensor support is in beta state")
        yield


def where_per_problem(condition: Tensor, a: Tensor, b: Tensor) -> Tensor:
    """Per problem, ``a`` where the (B,) ``condition`` holds, else ``b``: two (B, *M) tensors."""
    return torch.where(condition.reshape(-1, *([1] * (a.dim() - 1))), a, b)


def component_labels(first: Tensor, second: Tensor, count: int) -> Tensor:
    """(count,) the connected component of each of ``count`` nodes joined by the edges (E,)
    ``first`` - (E,) ``second``, named by its smallest node: label propagation along the edges
    with pointer jumping (a handful of passes over the edges, not one per step of the longest path)."""
    labels = torch.arange(count, device=first.device)
    while first.numel():
        smallest = torch.minimum(labels[first], labels[second])
        updated = labels.scatter_reduce(0, first, smallest, "amin").scatter_reduce(0, second, smallest, "amin")
        updated = updated[updated]
        if torch.equal(updated, labels):
            break
        labels = updated
    return labels
