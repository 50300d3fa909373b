"""Reading images and intrinsics files, with errors that name the file and the problem."""

from __future__ import annotations

from pathlib import Path

import kornia.io
import torch
from kornia.color import rgb_to_grayscale
from torch import Tensor

from torchsfm.errors import InputError, ShapeError


def read_image(path: str | Path) -> Tensor:
    """Read a JPEG/PNG as (3, H, W) uint8 RGB (grey files are expanded to three channels)."""
    path = Path(path)
    if not path.is_file():
        raise InputError(f"cannot read image {path}: no such file")
    try:
        image = kornia.io.load_image(path, kornia.io.ImageLoadType.UNCHANGED)
    except Exception as error:  # kornia_rs raises ValueError, OSError or RuntimeError by format
        raise InputError(f"cannot read image {path}: {error}") from None
    if image.dim() == 2:
        image = image[None]
    if image.shape[0] == 1:
        image = image.expand(3, -1, -1)
    elif image.shape[0] == 4:
        image = image[:3]
    if image.shape[0] != 3 or image.dtype != torch.uint8:
        raise InputError(f"cannot read image {path}: expected an 8-bit grey or colour image, got {tuple(image.shape)} {image.dtype}")
    return image.contiguous()


def to_grey(image: Tensor) -> Tensor:
    """(3, H, W) or (1, H, W) uint8/float -> (1, H, W) float32 in [0, 1]."""
    image = image.float() / 255.0 if image.dtype == torch.uint8 else image.float()
    return rgb_to_grayscale(image) if image.shape[0] == 3 else image


def read_intrinsics(path: str | Path) -> Tensor:
    """A 3x3 K from a text file (three rows of three numbers; '#' starts a comment): float64."""
    path = Path(path)
    try:
        lines = [line.split("#")[0] for line in path.read_text().splitlines()]
    except OSError as error:
        raise InputError(f"cannot read intrinsics file {path}: {error.strerror}") from None
    try:
        rows = [[float(value) for value in line.split()] for line in lines if line.strip()]
    except ValueError as error:
        raise InputError(f"intrinsics file {path} must hold numbers: {error}") from None
    if len(rows) != 3 or any(len(row) != 3 for row in rows):
        raise ShapeError(f"intrinsics file {path} must hold a 3x3 matrix K (3 rows of 3 numbers), got rows of {[len(r) for r in rows]}")
    return torch.tensor(rows, dtype=torch.float64)
