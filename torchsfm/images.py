"""Reading images and intrinsics files, with errors that name the file and the problem."""

from __future__ import annotations

from pathlib import Path

import kornia.io
import torch
from kornia.color import rgb_to_grayscale
from torch import Tensor
from torch.nn import functional

from torchsfm.errors import InputError, ShapeError


def read_image(path: str | Path) -> Tensor:
    """Read a JPEG/PNG as (3, H, W) uint8 RGB (a grey file's channels are one plane expanded:
    stride 0, no copy). A 16-bit PNG is scaled so that its largest value becomes 255: a camera
    that fills 10 or 12 of the 16 bits keeps 8 bits of contrast (everything downstream —
    Harris' relative threshold, NCC — is invariant to the gain)."""
    path = Path(path)
    if not path.is_file():
        raise InputError(f"cannot read image {path}: {'a folder, not an image file' if path.is_dir() else 'no such file'}")
    try:
        image = kornia.io.load_image(path, kornia.io.ImageLoadType.UNCHANGED)
    except Exception as error:  # kornia_rs raises ValueError, OSError or RuntimeError by format
        raise InputError(f"cannot read image {path}: {error}") from None
    if image.dim() == 2:
        image = image[None]
    if image.shape[0] == 4:
        image = image[:3]
    if image.dtype == torch.uint16:  # torch has few uint16 kernels: through int32
        wide = image.to(torch.int32)
        image = (wide.float() * (255 / max(int(wide.max()), 1))).round().to(torch.uint8)
    if image.shape[0] not in (1, 3) or image.dtype != torch.uint8:
        raise InputError(f"cannot read image {path}: expected an 8-bit grey or colour image, got {tuple(image.shape)} {image.dtype}")
    return image.contiguous().expand(3, -1, -1)  # a grey file's three channels share one plane: no copy


def check_image(image: Tensor, name: str = "image") -> None:
    """A (3, H, W) colour or (1, H, W) grey tensor, uint8 or float without NaN or inf; else a
    ShapeError or InputError naming ``name``."""
    if not isinstance(image, Tensor) or image.dim() != 3 or image.shape[0] not in (1, 3):
        shape = tuple(image.shape) if isinstance(image, Tensor) else type(image).__name__
        raise ShapeError(f"{name} must be a (3, H, W) colour or (1, H, W) grey tensor, got {shape}")
    if image.is_floating_point() and not bool(torch.isfinite(image).all()):
        raise InputError(f"{name} holds NaN or infinite intensities")


def to_unit_float(image: Tensor) -> Tensor:
    """uint8 (values 0..255) or float images of any shape -> float32 in [0, 1]."""
    return image.float() / 255.0 if image.dtype == torch.uint8 else image.float()


def to_grey(image: Tensor) -> Tensor:
    """(3, H, W) or (1, H, W) uint8/float -> (1, H, W) float32 in [0, 1]."""
    if image.shape[0] == 1:
        return to_unit_float(image)
    if image.dtype == torch.uint8:  # weigh the colours first: one plane to divide, not three
        return rgb_to_grayscale(image.float()) / 255.0
    return rgb_to_grayscale(image.float())


def is_grey_bytes(image: Tensor) -> bool:
    """Whether a (3 or 1, H, W) image is uint8 grey held as one plane (a grey file as
    :func:`read_image` returns it, or a single channel)."""
    return image.dtype == torch.uint8 and (image.shape[0] == 1 or image.stride(0) == 0)


def to_grey_bytes(image: Tensor) -> Tensor:
    """(3, H, W) or (1, H, W) uint8/float -> (1, H, W) uint8 grey (a quarter of float32's memory;
    exact for grey files)."""
    if is_grey_bytes(image):
        return image[:1].clone()
    return (to_grey(image) * 255).round().to(torch.uint8)


def reduce_image(image: Tensor, factor: int) -> Tensor:
    """(C, H, W) uint8/float image averaged over ``factor`` × ``factor`` blocks -> (C, H // factor,
    W // factor) of the same dtype; pixel x of the result is pixel (x + 0.5) · factor − 0.5 of the
    input (:func:`torchsfm.camera.rescale_pixels`)."""
    if factor == 1:
        return image
    reduced = functional.avg_pool2d(to_unit_float(image)[None], factor)[0]
    return (reduced * 255).round().to(torch.uint8) if image.dtype == torch.uint8 else reduced.to(image.dtype)


def same_size_batches(images: list[Tensor], batch: int) -> list[list[int]]:
    """The indices of (C, H, W) images in batches of at most ``batch`` images of one size (H, W),
    sizes in order of first appearance: each batch stacks into one tensor."""
    groups: dict[tuple[int, int], list[int]] = {}
    for v, image in enumerate(images):
        groups.setdefault(tuple(image.shape[-2:]), []).append(v)
    return [group[first:first + batch] for group in groups.values() for first in range(0, len(group), batch)]


def sizes_named(images: list[Tensor]) -> str:
    """The distinct sizes of (C, H, W) images as text, e.g. ``384x256, 768x512 px``."""
    return ", ".join(f"{w}x{h}" for h, w in sorted({tuple(image.shape[-2:]) for image in images})) + " px"


def one_camera(images: list[Tensor]) -> bool:
    """Whether (C, H, W) images can share one camera's intrinsics about their centres: one size,
    or one size and its transpose (the camera turned to portrait for some)."""
    sizes = {tuple(image.shape[-2:]) for image in images}
    return len(sizes) == 1 or (len(sizes) == 2 and min(sizes) == max(sizes)[::-1])


def read_mask(path: str | Path) -> Tensor:
    """Read a mask image (COLMAP's convention: features only where it is not black) as (H, W)
    bool, True where features may be detected."""
    return read_image(path).amax(0) > 0


def check_mask(mask: Tensor, image: Tensor, name: str = "mask") -> Tensor:
    """An (H, W) mask (bool, or numbers: nonzero keeps) of a (C, H, W) image as bool; a
    ShapeError naming ``name`` and both sizes where it does not fit the image."""
    if not isinstance(mask, Tensor) or mask.dim() not in (2, 3) or (mask.dim() == 3 and mask.shape[0] != 1):
        shape = tuple(mask.shape) if isinstance(mask, Tensor) else type(mask).__name__
        raise ShapeError(f"{name} must be an (H, W) or (1, H, W) tensor, got {shape}")
    mask = mask.reshape(mask.shape[-2:])
    if mask.shape != image.shape[-2:]:
        raise ShapeError(f"{name} is {mask.shape[1]}x{mask.shape[0]} px, its image {image.shape[-1]}x{image.shape[-2]} px")
    return mask if mask.dtype == torch.bool else mask != 0


def reduce_mask(mask: Tensor, factor: int) -> Tensor:
    """An (H, W) bool mask over ``factor`` × ``factor`` blocks -> (H // factor, W // factor): a
    block keeps only where every pixel of it does (the blocks of :func:`reduce_image`)."""
    if factor == 1:
        return mask
    return functional.max_pool2d((~mask)[None, None].float(), factor)[0, 0] == 0


def inside_mask(points: Tensor, mask: Tensor | None) -> Tensor:
    """(K,) bool: which (K, 2) pixel positions (x, y) fall on a pixel the (H, W) bool ``mask``
    keeps (all of them without a mask)."""
    if mask is None:
        return torch.ones(points.shape[0], dtype=torch.bool, device=points.device)
    H, W = mask.shape
    x = points[:, 0].round().long().clamp(0, W - 1)
    y = points[:, 1].round().long().clamp(0, H - 1)
    return mask[y, x]


def stacked_masks(masks: list[Tensor | None] | None, views: list[int], size: tuple[int, int]) -> Tensor | None:
    """The (B, H, W) bool masks of ``views`` (of one size (H, W)) from per-view ``masks`` (None
    entries: everywhere); None where no view of them has one."""
    if masks is None or all(masks[v] is None for v in views):
        return None
    return torch.stack([torch.ones(size, dtype=torch.bool) if masks[v] is None else masks[v] for v in views])
