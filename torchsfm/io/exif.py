"""The focal length a JPEG's EXIF block records, in pixels of the image as stored.

Only the tags a focal length needs are read (no dependency): ``FocalLengthIn35mmFilm`` (0xA405),
converted by the 35 mm film diagonal (CIPA DC-008: the equivalent focal length keeps the field of
view across the diagonal, 43.27 mm), else ``FocalLength`` (0x920A, mm) with
``FocalPlaneXResolution`` / ``FocalPlaneResolutionUnit`` (0xA20E / 0xA210, sensor pixels per unit),
rescaled by the stored width over ``PixelXDimension`` (0xA002) when the image was resized.
"""

from __future__ import annotations

import math
import struct
from pathlib import Path

FILM_DIAGONAL_MM = math.hypot(36.0, 24.0)
EXIF_IFD_POINTER = 0x8769
FOCAL_LENGTH = 0x920A
FOCAL_LENGTH_35MM = 0xA405
FOCAL_PLANE_X_RESOLUTION = 0xA20E
FOCAL_PLANE_RESOLUTION_UNIT = 0xA210
PIXEL_X_DIMENSION = 0xA002
RESOLUTION_UNIT_MM = {2: 25.4, 3: 10.0, 4: 1.0, 5: 1e-3}  # inch, cm, mm, µm
TYPE_SIZES = {1: 1, 3: 2, 4: 4, 5: 8, 7: 1, 9: 4, 10: 8}  # BYTE, SHORT, LONG, RATIONAL, UNDEFINED, SLONG, SRATIONAL


def exif_block(data: bytes) -> bytes | None:
    """The TIFF structure of a JPEG's APP1 ``Exif`` segment, or None (not a JPEG, no EXIF)."""
    if not data.startswith(b"\xff\xd8"):
        return None
    offset = 2
    while offset + 4 <= len(data) and data[offset] == 0xFF:
        marker = data[offset + 1]
        if marker in (0xD9, 0xDA):  # end of image, start of scan: no metadata after this
            return None
        length = struct.unpack(">H", data[offset + 2:offset + 4])[0]
        segment = data[offset + 4:offset + 2 + length]
        if marker == 0xE1 and segment.startswith(b"Exif\x00\x00"):
            return segment[6:]
        offset += 2 + length
    return None


def ifd_entries(tiff: bytes, offset: int, order: str) -> dict[int, float]:
    """The numeric tags (first value of each) of the image file directory at ``offset``."""
    entries: dict[int, float] = {}
    if offset + 2 > len(tiff):
        return entries
    count = struct.unpack(order + "H", tiff[offset:offset + 2])[0]
    for k in range(count):
        start = offset + 2 + 12 * k
        if start + 12 > len(tiff):
            break
        tag, kind, n = struct.unpack(order + "HHI", tiff[start:start + 8])
        size = TYPE_SIZES.get(kind)
        if size is None or n == 0:
            continue
        where = start + 8 if size * n <= 4 else struct.unpack(order + "I", tiff[start + 8:start + 12])[0]
        if where + size > len(tiff):
            continue
        raw = tiff[where:where + size]
        if kind in (5, 10):
            numerator, denominator = struct.unpack(order + ("II" if kind == 5 else "ii"), raw)
            if denominator:
                entries[tag] = numerator / denominator
        else:
            entries[tag] = struct.unpack(order + {1: "B", 3: "H", 4: "I", 7: "B", 9: "i"}[kind], raw)[0]
    return entries


def exif_focal_pixels(path: str | Path, width: int, height: int) -> float | None:
    """The focal length (pixels) recorded in the EXIF of the image file at ``path``, stored as
    ``width`` × ``height``; None when the file has no usable focal length."""
    try:
        with open(path, "rb") as file:
            tiff = exif_block(file.read(1 << 17))  # EXIF must sit in the first 64 KiB segment
    except OSError:
        return None
    if tiff is None or len(tiff) < 8 or tiff[:2] not in (b"II", b"MM"):
        return None
    order = "<" if tiff[:2] == b"II" else ">"
    first = ifd_entries(tiff, struct.unpack(order + "I", tiff[4:8])[0], order)
    if EXIF_IFD_POINTER not in first:
        return None
    tags = ifd_entries(tiff, int(first[EXIF_IFD_POINTER]), order)
    if tags.get(FOCAL_LENGTH_35MM, 0) > 0:
        return tags[FOCAL_LENGTH_35MM] * math.hypot(width, height) / FILM_DIAGONAL_MM
    focal, resolution = tags.get(FOCAL_LENGTH, 0), tags.get(FOCAL_PLANE_X_RESOLUTION, 0)
    unit = RESOLUTION_UNIT_MM.get(int(tags.get(FOCAL_PLANE_RESOLUTION_UNIT, 2)))
    if focal <= 0 or resolution <= 0 or unit is None:
        return None
    scale = width / tags[PIXEL_X_DIMENSION] if tags.get(PIXEL_X_DIMENSION, 0) > 0 else 1.0
    return focal * resolution / unit * scale
