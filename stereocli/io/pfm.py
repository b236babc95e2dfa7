"""Portable Float Map (PFM) reading and writing.

Format: a text header ``Pf`` (1 channel) or ``PF`` (3 channels), ``W H``, and a scale whose
sign gives the byte order (negative = little endian), each on its own line; then float32
rows stored **bottom row first**. ``+inf`` marks unknown / invalid disparity.
"""

from __future__ import annotations

import os
import re
from pathlib import Path

import numpy as np

from ..errors import DataError
from .atomic import write_bytes

_HEADER = re.compile(rb"^(P[Ff])\s+(\d+)\s+(\d+)\s+([-+0-9.eE]+)\s")


def read_pfm(path: str | os.PathLike) -> np.ndarray:
    """Read a PFM file into a float32 array, (H, W) for ``Pf`` or (H, W, 3) for ``PF``, top row first."""
    path = Path(path)
    try:
        raw = path.read_bytes()
    except OSError as exc:
        raise DataError(f"{path}: cannot read ({exc.strerror or exc})") from None
    m = _HEADER.match(raw[:256])
    if not m:
        raise DataError(f"{path}: not a PFM file (bad header)")
    kind, width, height = m.group(1), int(m.group(2)), int(m.group(3))
    try:
        scale = float(m.group(4))
    except ValueError:
        raise DataError(f"{path}: not a PFM file (scale {m.group(4).decode()!r} is no number)") from None
    channels = 3 if kind == b"PF" else 1
    dtype = "<f4" if scale < 0 else ">f4"
    count = width * height * channels
    body = raw[m.end():]
    if len(body) < count * 4:
        raise DataError(
            f"{path}: truncated PFM ({len(body)} bytes of data, {count * 4} expected for {width}x{height})"
        )
    data = np.frombuffer(body, dtype=dtype, count=count).astype(np.float32)
    shape = (height, width, 3) if channels == 3 else (height, width)
    return np.ascontiguousarray(data.reshape(shape)[::-1])


def encode_pfm(image: np.ndarray) -> bytes:
    """PFM bytes (little endian, bottom row first) for a (H, W) or (H, W, 3) array."""
    image = np.asarray(image, dtype=np.float32)
    if image.ndim == 2:
        kind = b"Pf"
    elif image.ndim == 3 and image.shape[2] == 3:
        kind = b"PF"
    else:
        raise ValueError(f"PFM holds (H, W) or (H, W, 3) arrays, got shape {image.shape}")
    height, width = image.shape[:2]
    header = kind + f"\n{width} {height}\n-1.0\n".encode()
    return header + np.ascontiguousarray(image[::-1], dtype="<f4").tobytes()


def write_pfm(path: str | os.PathLike, image: np.ndarray) -> None:
    """Write ``image`` as a little-endian PFM, atomically; refuses NaN (:func:`refuse_nan`)."""
    refuse_nan(path, image)
    write_bytes(path, encode_pfm(image))


def refuse_nan(path: str | os.PathLike, values: np.ndarray) -> None:
    """Raise :class:`DataError` naming ``path`` when ``values`` hold NaN: the last guard before a
    map is written, since +inf, never NaN, marks an invalid pixel and readers refuse NaN."""
    nan = int(np.count_nonzero(np.isnan(np.asarray(values, dtype=np.float32))))
    if nan:
        raise DataError(f"{path}: {nan} NaN values; not written (+inf marks invalid pixels)")
