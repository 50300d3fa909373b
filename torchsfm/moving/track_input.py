"""Validation of (F, N, 2) tracks with an (F, N) visibility, shared by the whole-track methods."""

from __future__ import annotations

import torch
from torch import Tensor

from torchsfm.errors import InputError, NotEnoughDataError, ShapeError
from torchsfm.moving.imor import MIN_VECTORS


def check_tracks(tracks: Tensor, visible: Tensor | None, min_frames: int = 3) -> tuple[Tensor, Tensor]:
    """Validate (F, N, 2) tracks and an (F, N) bool visibility: F >= ``min_frames`` and at
    least 12 tracks seen in ``min_frames`` frames. Returns float64 tracks (zeros where not
    visible) and the visibility."""
    if not isinstance(tracks, Tensor) or tracks.dim() != 3 or tracks.shape[-1] != 2:
        raise ShapeError(f"tracks must be an (F, N, 2) tensor, got {tuple(tracks.shape) if isinstance(tracks, Tensor) else type(tracks).__name__}")
    if not tracks.is_floating_point():
        raise InputError(f"tracks must be floating point pixels, got {tracks.dtype}")
    F, N, _ = tracks.shape
    if F < min_frames:
        raise NotEnoughDataError(f"judging a track needs {min_frames} frames, got {F}")
    if visible is None:
        visible = torch.ones(F, N, dtype=torch.bool, device=tracks.device)
    if not isinstance(visible, Tensor) or visible.shape != (F, N):
        raise ShapeError(f"visible must be ({F}, {N}) like tracks' first two dimensions, got "
                         f"{tuple(visible.shape) if isinstance(visible, Tensor) else type(visible).__name__}")
    if visible.dtype != torch.bool:
        raise InputError(f"visible must be a bool tensor, got {visible.dtype}")
    bad = visible & ~torch.isfinite(tracks).all(-1)
    if bool(bad.any()):
        f, n = (int(v) for v in torch.nonzero(bad)[0])
        raise InputError(f"tracks hold {int(bad.sum())} non-finite positions where visible (first: frame {f}, track {n})")
    long_enough = int((visible.sum(0) >= min_frames).sum())
    if long_enough < MIN_VECTORS:
        raise NotEnoughDataError(f"only {long_enough} tracks are seen in {min_frames} frames or more (needs {MIN_VECTORS})")
    return torch.where(visible[..., None], tracks.double(), 0.0), visible
