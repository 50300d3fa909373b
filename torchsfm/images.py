"""Reading images and intrinsics files, with errors that name the file and the problem."""

from __future__ import annotations

from pathlib import Path

import kornia.io
import torch
from kornia.color import rgb_to_grayscale
from torch import Tensor

from torchsfm.errors import InputError


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
