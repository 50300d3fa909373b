"""Camera files: the calibration YAML written by ``torchsfm calibrate`` and the K text format,
both read by :func:`read_camera` (what ``--K`` accepts)."""

from __future__ import annotations

from pathlib import Path

import torch
import yaml
from torch import Tensor

from torchsfm.calibration.zhang import Calibration
from torchsfm.camera import check_intrinsics
from torchsfm.errors import InputError, ShapeError


def calibration_yaml(calibration: Calibration, *, image_size: tuple[int, int], pattern: tuple[int, int], square: float,
                     views: list[str], not_found: dict[str, str]) -> str:
    """The calibration file: K, distortion, reprojection RMS overall and per view, and the
    images whose board was not found."""
    document = {
        "model": "pinhole with radial distortion: x_d = x (1 + k1 r^2 + k2 r^4) in normalized coordinates",
        "image_size": list(image_size),
        "K": [[round(float(v), 6) for v in row] for row in calibration.K.tolist()],
        "distortion": [round(float(v), 8) for v in calibration.distortion.tolist()],
        "rms_px": round(calibration.rms, 5),
        "pattern": list(pattern),
        "square": square,
        "views": [{"image": name, "rms_px": round(float(rms), 5)} for name, rms in zip(views, calibration.view_rms.tolist())],
        "not_found": [{"image": name, "reason": reason} for name, reason in not_found.items()],
    }
    return "# torchsfm calibrate (Zhang's method)\n" + yaml.safe_dump(document, sort_keys=False)


def read_camera(path: str | Path) -> tuple[Tensor, Tensor]:
    """K (3, 3) and radial distortion (k1, k2) (2,), float64, from a camera file.

    Accepted: a YAML calibration written by ``torchsfm calibrate`` (``.yaml``/``.yml``), or a
    text file with three rows of three numbers (K) and optionally a fourth row ``k1 k2``
    ('#' starts a comment). Without distortion the coefficients are zero.
    """
    path = Path(path)
    try:
        text = path.read_text()
    except OSError as error:
        raise InputError(f"cannot read camera file {path}: {error.strerror}") from None
    if path.suffix.lower() in (".yaml", ".yml"):
        try:
            document = yaml.safe_load(text)
            K = torch.tensor(document["K"], dtype=torch.float64)
            distortion = torch.tensor(document.get("distortion", [0.0, 0.0]), dtype=torch.float64)
        except (yaml.YAMLError, KeyError, TypeError, ValueError) as error:
            raise InputError(f"camera file {path} is not a torchsfm calibration (needs K and distortion): {error}") from None
    else:
        try:
            rows = [[float(v) for v in line.split("#")[0].split()] for line in text.splitlines() if line.split("#")[0].strip()]
        except ValueError as error:
            raise InputError(f"camera file {path} must hold numbers: {error}") from None
        if len(rows) not in (3, 4) or any(len(row) != 3 for row in rows[:3]) or (len(rows) == 4 and len(rows[3]) != 2):
            raise ShapeError(f"camera file {path} must hold a 3x3 matrix K (3 rows of 3 numbers) and optionally a row "
                             f"'k1 k2', got rows of {[len(r) for r in rows]}")
        K = torch.tensor(rows[:3], dtype=torch.float64)
        distortion = torch.tensor(rows[3] if len(rows) == 4 else [0.0, 0.0], dtype=torch.float64)
    if K.shape != (3, 3) or distortion.shape != (2,):
        raise ShapeError(f"camera file {path}: K must be 3x3 and distortion two numbers (k1, k2), "
                         f"got {tuple(K.shape)} and {tuple(distortion.shape)}")
    if not torch.isfinite(distortion).all():
        raise InputError(f"camera file {path}: distortion must be finite, got {distortion.tolist()}")
    check_intrinsics(K=K)
    return K, distortion
