"""Ragged batches: problems of different sizes as one padded tensor and a validity mask, the form
every estimator and the RANSAC engine take."""

from __future__ import annotations

import torch
from torch import Tensor


def pad_rows(rows: list[Tensor]) -> tuple[Tensor, Tensor]:
    """B row sets (N_b, D) -> zero-padded (B, max N_b, D) and the (B, max N_b) bool mask of real rows."""
    counts = torch.tensor([r.shape[0] for r in rows], device=rows[0].device)
    valid = torch.arange(int(counts.max()), device=counts.device)[None] < counts[:, None]
    data = rows[0].new_zeros(*valid.shape, rows[0].shape[-1])
    data[valid] = torch.cat(rows)
    return data, valid


def fill_padding(data: Tensor, valid: Tensor) -> Tensor:
    """(B, N, D) rows with every row that is not ``valid`` (B, N) replaced by its problem's first
    valid row (zeros in a problem without one): padding then holds finite, ordinary values, so
    every computation on it stays finite while its weight or mask leaves it out."""
    first = data[torch.arange(data.shape[0], device=data.device), valid.long().argmax(-1)]  # (B, D)
    first = torch.where(valid.any(-1, keepdim=True), first, 0.0)
    return torch.where(valid[..., None], data, first[:, None])


def weighted_rows_first(weights: Tensor, *data: Tensor) -> tuple[Tensor, ...]:
    """The rows with a weight of (B, N) ``weights`` and of each (B, N, D) ``data``, gathered in
    their order to the front of (B, M, ·) copies, M the largest count of weighted rows (zero
    weights pad the rest; the inputs themselves where no row is dropped): a least-squares fit
    then costs what its weighted rows need, not what its outliers would."""
    weighted = weights > 0
    M = max(1, int(weighted.sum(-1).amax())) if weighted.shape[0] else 1
    if M == weights.shape[-1]:
        return (weights, *data)
    rows = torch.argsort(weighted.to(torch.uint8), dim=-1, descending=True, stable=True)[:, :M]
    return (weights.gather(1, rows), *(x.gather(1, rows[..., None].expand(-1, -1, x.shape[-1])) for x in data))
