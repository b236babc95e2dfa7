"""EXIF orientation of JPEG and TIFF files, read from their headers.

:func:`~stereocli.io.images.read_image` applies the orientation as image viewers do (OpenCV's
decoders do it), so every command, ``calibrate`` too, sees the picture a viewer shows, and a
calibration fits the pairs it was made from. The batch commands name each such file with
:func:`orientation_note`: a camera held on its side turns a horizontal rig vertical.
"""

from __future__ import annotations

import os
from typing import Literal

#: What a viewer does to the stored pixels for each EXIF orientation (tag 274) but 1 (none).
EXIF_ORIENTATIONS = {2: "mirrored", 3: "turned 180°", 4: "flipped upside down", 5: "transposed",
                     6: "turned 90° clockwise", 7: "transversed", 8: "turned 90° anticlockwise"}


def exif_orientation(path: str | os.PathLike) -> int | None:
    """The EXIF orientation (1-8) of a JPEG or TIFF file, or None (no tag, another format, or
    metadata that cannot be parsed). Reads the file's headers only."""
    try:
        with open(path, "rb") as fh:
            head = fh.read(65536)
            if head[:4] in (b"II*\0", b"MM\0*"):
                return _tiff_orientation(fh, 0)
            if head[:2] != b"\xff\xd8":
                return None
            at = 2  # JPEG: the segments before the image data, looking for APP1 "Exif"
            while at + 4 <= len(head) and head[at] == 0xFF and head[at + 1] != 0xDA:
                length = int.from_bytes(head[at + 2:at + 4], "big")
                if head[at + 1] == 0xE1 and head[at + 4:at + 10] == b"Exif\0\0":
                    return _tiff_orientation(fh, at + 10)
                at += 2 + length
    except (OSError, ValueError):
        return None
    return None


def _tiff_orientation(fh, base: int) -> int | None:
    """The orientation tag of the first image directory of the TIFF structure at ``base``."""
    fh.seek(base)
    header = fh.read(8)
    orders: dict[bytes, Literal["little", "big"]] = {b"II": "little", b"MM": "big"}
    order = orders.get(header[:2])
    if order is None or len(header) < 8:
        return None
    fh.seek(base + int.from_bytes(header[4:8], order))
    count = int.from_bytes(fh.read(2), order)
    entries = fh.read(12 * min(count, 1000))
    for at in range(0, len(entries) - 11, 12):
        if int.from_bytes(entries[at:at + 2], order) == 0x0112:
            value = int.from_bytes(entries[at + 8:at + 10], order)
            return value if 1 <= value <= 8 else None
    return None


def orientation_note(path: str | os.PathLike) -> str | None:
    """A one-line note naming ``path`` when its EXIF orientation turns or mirrors the stored
    pixels (:func:`~stereocli.io.images.read_image` applies it, so every command sees the picture a viewer shows and
    a calibration matches the pairs), else None."""
    orientation = exif_orientation(path)
    if orientation not in EXIF_ORIENTATIONS:
        return None
    return f"{path}: EXIF orientation {orientation}: read {EXIF_ORIENTATIONS[orientation]}, as viewers show it"
