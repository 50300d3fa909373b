"""Calibration as composable stages: :class:`DetectBoards` then :class:`CalibrateFromBoards` on
a :class:`BoardViews` state (:func:`calibration_stages`; ``torchsfm calibrate`` runs them and
writes the files). Swap or insert a stage as in the other pipelines, e.g. a detector of your own
in place of :class:`DetectBoards`."""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import torch
from torch import Tensor

from torchsfm.calibration.chessboard import detect_chessboard
from torchsfm.calibration.zhang import Calibration, board_points, calibrate_camera
from torchsfm.config import Config
from torchsfm.errors import InputError, NotEnoughDataError
from torchsfm.images import read_image
from torchsfm.pipeline import ConfiguredStage, Pipeline, Progress


@dataclass
class BoardViews:
    """The state of the calibration stages.

    Fields:
        images: the photos, decoded (3 or 1, H, W) or paths (read one at a time, not kept).
        names: one name per photo.
        pattern: inner corners per row and per column; square: the squares' side (board units).
        report: progress messages.
        sizes: (W, H) of every photo read; corners: per photo whose board was found, its
            (cols * rows, 2) pixels; not_found: per other photo, why; calibration: the result;
            timings: seconds per stage.
    """

    images: list[Tensor | str | Path]
    names: list[str]
    pattern: tuple[int, int]
    square: float
    report: Progress = field(default=lambda message: None)
    sizes: set[tuple[int, int]] = field(default_factory=set)
    corners: dict[str, Tensor] = field(default_factory=dict)
    not_found: dict[str, str] = field(default_factory=dict)
    calibration: Calibration | None = None
    timings: dict[str, float] = field(default_factory=dict)


class DetectBoards(ConfiguredStage):
    """The chessboard of every photo (``calibration.chessboard``): fills ``sizes``, ``corners``
    and ``not_found``."""

    SECTIONS = ("calibration",)

    def forward(self, state: BoardViews) -> BoardViews:
        for name, image in zip(state.names, state.images):
            image = read_image(image) if isinstance(image, (str, Path)) else image
            state.sizes.add((image.shape[-1], image.shape[-2]))
            detection = detect_chessboard(image, state.pattern, self.config.calibration.chessboard)
            state.report(f"{name}: {'board found' if detection.found else detection.reason}")
            if detection.found:
                state.corners[name] = detection.corners
            else:
                state.not_found[name] = detection.reason
        return state


class CalibrateFromBoards(ConfiguredStage):
    """Zhang's method on the boards found (``calibration``): fills ``calibration``. Raises
    InputError when the photos differ in size, NotEnoughDataError (naming the photos without a
    board) when fewer than ``calibration.min_views`` boards were found."""

    SECTIONS = ("calibration",)

    def forward(self, state: BoardViews) -> BoardViews:
        settings = self.config.calibration
        if len(state.sizes) > 1:
            raise InputError(f"the photos differ in size ({sorted(state.sizes)}): one calibration needs one camera setting")
        if len(state.corners) < settings.min_views:
            missing = "; ".join(f"{name}: {reason}" for name, reason in state.not_found.items()) or "none missing"
            cols, rows = state.pattern
            raise NotEnoughDataError(f"the {cols}x{rows} board was found in {len(state.corners)} of {len(state.names)} images, "
                                     f"calibration needs {settings.min_views} ({missing})")
        state.report(f"calibrating from {len(state.corners)} views")
        state.calibration = calibrate_camera(board_points(state.pattern, state.square), torch.stack(list(state.corners.values())),
                                             settings)
        return state


def calibration_stages(config: Config | None = None) -> Pipeline:
    """The stages of ``torchsfm calibrate``, each given its section of ``config``."""
    config = config or Config()
    return Pipeline(DetectBoards.from_config(config), CalibrateFromBoards.from_config(config))
