"""Incremental reconstruction of an image set (thesis chapter 4, Fig. 4.1–4.2): the entry point.

:func:`reconstruct` reads the images, checks K and the distortion, and runs the stages of
:mod:`torchsfm.sfm.stages` — corners of every view → the view pairs worth matching (coarse matching
of every pair, :mod:`torchsfm.sfm.pairs`) → guided putative matches → robust verification →
(without K: the focal length from their F) → tracks → (moving objects rejected) → the incremental
mapper (:mod:`torchsfm.sfm.mapping`).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import replace
from pathlib import Path

import torch
from torch import Tensor

from torchsfm.camera import intrinsics_per_view, rescale_intrinsics, rescale_pixels
from torchsfm.config import Config
from torchsfm.errors import InputError, NotEnoughDataError, ShapeError
from torchsfm.images import (check_mask, is_grey_bytes, one_camera, read_image, read_mask, reduce_image, reduce_mask, sizes_named,
                             to_grey_bytes)
from torchsfm.inference import without_autograd
from torchsfm.io.exif import exif_focal_pixels
from torchsfm.reconstruction import Reconstruction
from torchsfm.sfm.from_tracks import ReconstructObjects
from torchsfm.pipeline import Pipeline, Progress
from torchsfm.sfm.stages import ViewSet, default_pipeline
from torchsfm.sfm.view_pairs import centred_intrinsics
from torchsfm.validation import check_finite


COLOUR_REDUCTION = 2  # a colour file's colours are kept at half size: the points' colours need no more
EXIF_AGREEMENT = 0.01  # the images' EXIF focal lengths are used when they agree to 1 % (one camera, one zoom)


def shared_focal(focals: list[float | None]) -> float | None:
    """The focal length every image's EXIF records (their median), or None if one lacks it or
    they differ by more than ``EXIF_AGREEMENT``."""
    if not focals or any(focal is None for focal in focals):
        return None
    values = torch.tensor(focals, dtype=torch.float64)
    return float(values.median()) if float(values.max() / values.min()) <= 1 + EXIF_AGREEMENT else None


@without_autograd
def reconstruct(images: list[Tensor | str | Path], K: Tensor | None = None, *, distortion: Tensor | None = None,
                names: list[str] | None = None, config: Config | None = None,
                generator: torch.Generator | None = None, progress: Progress | None = None,
                pipeline: Pipeline | None = None, moving_objects: str | None = None,
                masks: list[Tensor | str | Path | None] | Tensor | str | Path | None = None) -> Reconstruction:
    """Reconstruct a calibrated image sequence.

    Images given as paths are read here; one that cannot be read is listed in ``unregistered``
    with the reason and the others are reconstructed without it.

    Args:
        images: V >= 2 image paths or tensors (3, H, W) / (1, H, W), uint8 or float in [0, 1];
            of different sizes only with K (portrait and landscape shots, several cameras) or
            with an EXIF focal length in every file.
        K: intrinsics (3, 3) shared by all views (of one size), or (V, 3, 3); None: unknown — the principal
            point is taken at the image centre, the focal length (shared by all views) is the
            one the files' EXIF records where every image has one and they agree, else it is
            estimated from the verified pairs' fundamental matrices (Mendonça & Cipolla, searched
            around 1.2 × the larger image side); either is refined by bundle adjustment, and the
            estimate is the model's ``cameras.K``. All images must then have one size — unless
            every file records its focal length in EXIF: images of several sizes (several
            cameras), or whose EXIF focal lengths disagree (a zoom), then each get the K of their
            own EXIF focal length with the principal point at their centre, held as given (one
            shared K is what the refinement adjusts).
        distortion: radial (k1, k2) of the camera, (2,) or (V, 2); corners are undistorted
            before any geometry (the model's keypoints are then ideal pixels).
        names: view names (default: the file names, or ``view0``, ``view1``, ...).
        config: every stage's settings; generator: the random source of all RANSACs.
        progress: called with a message at each step.
        pipeline: the stages to run (default: :func:`~torchsfm.sfm.stages.default_pipeline` of
            ``config``, then :class:`~torchsfm.sfm.from_tracks.ReconstructObjects` when
            ``moving_objects.reconstruct_objects``); a user may swap, remove or add stages (see
            :mod:`torchsfm.sfm.stages`).
        moving_objects: ``"reject"`` (independently moving objects' tracks are left out of the
            model: ``moving_objects.enabled``) or ``"reconstruct"`` (and each moving body is
            reconstructed as its own model: ``model.objects``, each body's scale its own);
            None: as ``config`` says.
        masks: where features may be detected (COLMAP's convention: not where a mask is black or
            0): one (H, W) mask or mask file for every image (a video's fixed overlay: a time
            stamp, a logo, the car's bonnet) or a list with one per image (None: the whole image).

    Returns:
        A :class:`~torchsfm.reconstruction.Reconstruction` of the registered views
        (``view_indices`` maps them to the input list; ``unregistered`` gives the others with the
        reason). A set that splits into groups no verified pair links gives the largest group's
        model, the others in ``other_models``. Scale: the initial pair's baseline is 1.
    """
    if len(images) < 2:
        raise NotEnoughDataError(f"a reconstruction needs at least 2 images, got {len(images)}")
    names = names or [Path(image).name if isinstance(image, (str, Path)) else f"view{v}" for v, image in enumerate(images)]
    estimate_focal = K is None
    if estimate_focal:
        if distortion is not None:
            raise InputError("distortion needs K: give both, or neither")
        K = torch.eye(3, dtype=torch.float64)  # replaced once the image size is known
    one_K = K.dim() == 2
    K = intrinsics_per_view(K, len(images))
    if distortion is not None:
        distortion = distortion.double()
        if distortion.shape not in ((2,), (len(images), 2)):
            raise ShapeError(f"distortion must be (2,) or ({len(images)}, 2), got {tuple(distortion.shape)}")
    distortion = K.new_zeros(len(images), 2) if distortion is None else distortion.double().expand(len(images), 2)
    check_finite(distortion=distortion)
    masks = per_image_masks(masks, len(images))
    loaded, kept, unreadable, exif, colours, loaded_masks = [], [], {}, [], [], []
    for v, image in enumerate(images):
        colour = None
        if isinstance(image, (str, Path)):
            try:
                path, image = image, read_image(image)
            except InputError as error:
                unreadable[v] = str(error)
                continue
            exif.append(exif_focal_pixels(path, image.shape[-1], image.shape[-2]) if estimate_focal else None)
            if not is_grey_bytes(image):  # a colour file: its grey for the pipeline, a half-size copy for the colours (memory)
                image, colour = to_grey_bytes(image), reduce_image(image, COLOUR_REDUCTION)
        else:
            exif.append(None)
        loaded.append(image)
        colours.append(colour)
        kept.append(v)
        loaded_masks.append(None if masks is None else masks(v, image))
    if len(loaded) < 2:
        raise NotEnoughDataError(f"only {len(loaded)} of {len(images)} images could be read: " + "; ".join(unreadable.values()))
    if one_K and not estimate_focal and len({image.shape[-2:] for image in loaded}) > 1:
        raise InputError(f"one K for images of different sizes ({sizes_named(loaded)}): give each view's K, (V, 3, 3) "
                         f"(a camera turned to portrait has its K turned with it)")
    several_cameras = not one_camera(loaded)
    if estimate_focal and all(focal is not None for focal in exif) and (several_cameras or shared_focal(exif) is None):
        # several cameras (or a zoom) and no K: each view's K from its own EXIF focal length, held
        # as given (the intrinsics refinement adjusts one K that every view shares)
        K = K.clone()
        K[kept] = centred_intrinsics(exif, [image.shape[-2:] for image in loaded])
        estimate_focal = False
        if progress is not None:
            cameras = (f"images of different sizes ({sizes_named(loaded)})" if several_cameras else
                       f"EXIF focal lengths more than {100 * EXIF_AGREEMENT:g} % apart (a zoom, or several cameras)")
            progress(f"{cameras} without K: each view's K from its EXIF focal length "
                     f"({', '.join(f'{focal:.1f}' for focal in exif)} px), the principal point at its centre, not refined")
    config = config or Config()
    if moving_objects is not None:
        if moving_objects not in ("reject", "reconstruct"):
            raise InputError(f"moving_objects must be 'reject' or 'reconstruct', got {moving_objects!r}")
        config = replace(config, moving_objects=replace(config.moving_objects, enabled=True,
                                                        reconstruct_objects=moving_objects == "reconstruct"))
    # larger images: detection and matching at a working resolution, each image reduced by its own
    # factor (a set from several cameras keeps its smaller images whole: one factor for all would
    # shrink them with the largest and leave them that much coarser than the rest)
    factors = [reduction_factor(image.shape[-2:], config.reconstruction.max_image_size) for image in loaded]
    factor_of = dict(zip(kept, factors))  # by input index
    input_sizes = {v: (image.shape[-1], image.shape[-2]) for v, image in zip(kept, loaded)}  # (W, H) by input index
    loaded = [reduce_image(image, factor) for image, factor in zip(loaded, factors)]
    loaded_masks = reduced_masks(loaded_masks, factors)
    exif = [None if focal is None else focal / factor for focal, factor in zip(exif, factors)]
    K = K[kept] if estimate_focal else torch.stack([rescale_intrinsics(K[v], 1 / factor_of[v]) for v in kept])
    if pipeline is None:
        pipeline = default_pipeline(config)
        if config.moving_objects.enabled and config.moving_objects.reconstruct_objects:
            pipeline.append(ReconstructObjects.from_config(config))
    state = ViewSet.of(loaded, K, distortion=distortion[kept], names=[names[v] for v in kept], generator=generator,
                       progress=progress, estimate_focal=estimate_focal, exif_focal=shared_focal(exif), colours=colours,
                       masks=None if masks is None else loaded_masks)
    del loaded, colours, loaded_masks  # the state holds the images now (and may replace them by lighter copies)
    state = pipeline(state)
    model = state.reconstruction
    model.timings = state.timings
    model.view_indices = [kept[v] for v in model.view_indices]
    bodies = [part for body in model.objects if body.model is not None for part in (body.model, *body.model.other_models)]
    for other in model.other_models + bodies:
        other.view_indices = [kept[v] for v in other.view_indices]
    model.unregistered = {**{kept[v]: reason for v, reason in model.unregistered.items()}, **unreadable}
    model.moving_objects = {tuple(kept[v] for v in triplet): result for triplet, result in model.moving_objects.items()}
    model.moving_rejections_per_view = {kept[v]: count for v, count in model.moving_rejections_per_view.items()}
    if max(factors) > 1:
        for part in (model, *model.other_models, *bodies):
            to_input_resolution(part, [factor_of[v] for v in part.view_indices], [input_sizes[v] for v in part.view_indices])
        if model.segmented_tracks is not None:
            pixels, visible, labels = model.segmented_tracks
            model.segmented_tracks = (rescale_pixels(pixels, torch.tensor(factors, dtype=pixels.dtype)[:, None, None]), visible, labels)
    return model


def per_image_masks(masks: list[Tensor | str | Path | None] | Tensor | str | Path | None, count: int
                    ) -> Callable[[int, Tensor], Tensor | None] | None:
    """The ``masks`` argument of :func:`reconstruct` for ``count`` images as a function of an
    image's index and its (C, H, W) tensor giving its (H, W) bool mask (or None): each mask file
    read, and each mask checked against its image, once (one mask shared by a whole video is
    one tensor, not one per frame). None without masks."""
    if masks is None:
        return None
    given = [masks] * count if isinstance(masks, (Tensor, str, Path)) else list(masks)
    if len(given) != count:
        raise InputError(f"{len(given)} masks for {count} images: give one mask for all, or one per image (None for none)")
    checked: dict[tuple[object, tuple[int, int]], Tensor] = {}

    def mask_of(v: int, image: Tensor) -> Tensor | None:
        mask = given[v]
        if mask is None:
            return None
        key = (str(mask) if isinstance(mask, (str, Path)) else id(mask), tuple(image.shape[-2:]))
        if key not in checked:
            name = f"mask {mask}" if isinstance(mask, (str, Path)) else f"mask {v}"
            checked[key] = check_mask(read_mask(mask) if isinstance(mask, (str, Path)) else mask, image, name)
        return checked[key]

    return mask_of


def reduced_masks(masks: list[Tensor | None], factors: list[int]) -> list[Tensor | None]:
    """Per view (H, W) bool masks (or None) reduced by each view's factor with their images, each
    distinct mask once per factor (:func:`~torchsfm.images.reduce_mask`)."""
    reduced: dict[tuple[int, int], Tensor] = {}
    for mask, factor in zip(masks, factors):
        if mask is not None and (id(mask), factor) not in reduced:
            reduced[(id(mask), factor)] = reduce_mask(mask, factor)
    return [None if mask is None else reduced[(id(mask), factor)] for mask, factor in zip(masks, factors)]


def reduction_factor(size: tuple[int, int], max_size: int) -> int:
    """The smallest integer factor that brings an image of ``size`` (H, W) within ``max_size``
    px on its larger side (1: no reduction, or ``max_size`` 0)."""
    return max(1, -(-max(size) // max_size)) if max_size else 1


def to_input_resolution(model: Reconstruction, factors: list[int], sizes: list[tuple[int, int]]) -> None:
    """A model computed on images reduced by ``factors``, in place: its intrinsics and keypoints
    in pixels of the input images of ``sizes`` (W, H); one factor and size per view of the model.
    Poses and points are unchanged."""
    K = torch.stack([rescale_intrinsics(K, factor) for K, factor in zip(model.cameras.K, factors)]) if factors else model.cameras.K
    model.cameras = replace(model.cameras, K=K)
    scale = torch.tensor(factors, dtype=model.keypoints.dtype)[model.observation_views] if factors else model.keypoints.new_ones(0)
    model.keypoints = rescale_pixels(model.keypoints, scale[:, None])
    model.image_sizes = torch.tensor([list(size) for size in sizes], dtype=model.image_sizes.dtype)
