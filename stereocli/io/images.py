"""Reading and writing images and disparity maps in the formats stereocli supports."""

from __future__ import annotations

import os
from pathlib import Path

import cv2
import numpy as np

from ..errors import DataError
from .atomic import atomic_path, write_bytes
from .pfm import read_pfm, refuse_nan, write_pfm

IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".tif", ".tiff", ".bmp", ".ppm", ".pgm", ".pnm", ".webp")


def read_image(path: str | os.PathLike, *, gray: bool = False) -> np.ndarray:
    """Read an image as (H, W) or (H, W, 3) RGB; 8-bit and 16-bit keep their dtype. An EXIF
    orientation is applied, as image viewers apply it (:mod:`stereocli.io.exif`).

    Raises :class:`DataError` with a one-line message for missing, unreadable or truncated files,
    and for any other pixel type (float or signed TIFFs: their scale is nobody's convention; the
    message counts NaN and infinite pixels).
    """
    path = Path(path)
    if not path.is_file():
        raise DataError(f"{path}: no such file")
    data = np.fromfile(path, dtype=np.uint8)
    if data.size == 0:
        raise DataError(f"{path}: empty file")
    # Not IMREAD_UNCHANGED: it skips a JPEG's orientation, which the TIFF decoder applies anyway.
    flags = cv2.IMREAD_GRAYSCALE if gray else cv2.IMREAD_ANYDEPTH | cv2.IMREAD_ANYCOLOR
    image = cv2.imdecode(data, flags)
    if image is None:
        raise DataError(f"{path}: unreadable or truncated image")
    if image.dtype not in (np.uint8, np.uint16):
        bad = 0  # pixels with a NaN or infinite channel
        if image.dtype.kind == "f":
            finite = np.isfinite(image)
            bad = int(np.count_nonzero(~(finite.all(axis=2) if finite.ndim == 3 else finite)))
        raise DataError(f"{path}: {image.dtype} pixels{f', {bad} of them NaN or infinite' if bad else ''}; "
                        "stereocli reads 8- or 16-bit unsigned images (convert it, e.g. to a 16-bit PNG)")
    if image.ndim == 3:
        if image.shape[2] == 4:
            image = image[..., :3]
        image = cv2.cvtColor(image, cv2.COLOR_BGR2RGB)
    return image


def to_float_image(image: np.ndarray) -> np.ndarray:
    """Convert an 8- or 16-bit image to float32 in [0, 255] (the pipeline's working range); a
    float array passes as it is, unless it holds NaN or inf (:class:`DataError`)."""
    if image.dtype.kind == "f" and not np.isfinite(image).all():
        bad = int(np.count_nonzero(~np.isfinite(image)))
        raise DataError(f"the image holds {bad} NaN or infinite values; intensities must be finite")
    if image.dtype == np.uint16:
        return (image.astype(np.float32) * (255.0 / 65535.0)).astype(np.float32)
    return image.astype(np.float32)


def write_image(path: str | os.PathLike, image: np.ndarray) -> None:
    """Write an RGB or grey uint8/uint16 image atomically (format from the extension)."""
    path = Path(path)
    if image.ndim == 3:
        image = cv2.cvtColor(image, cv2.COLOR_RGB2BGR)
    ok, buf = cv2.imencode(path.suffix or ".png", image)
    if not ok:
        raise DataError(f"{path}: cannot encode image")
    write_bytes(path, buf.tobytes())


def write_disparity_png16(path: str | os.PathLike, disparity: np.ndarray, scale: float = 256.0) -> int:
    """Write disparity as uint16 PNG holding ``round(d * scale)``; 0 = invalid (KITTI style).

    Disparities outside ``[1, 65535] / scale`` (negative, too large, or rounding to 0) cannot be
    represented and are written as invalid; returns how many valid pixels that was. Raises
    :class:`DataError` (writing nothing) when ``scale`` is not a positive finite number, or when
    no valid disparity at all can be represented (the file would hold only "invalid").
    """
    if not 0 < scale < np.inf:
        raise DataError(f"{path}: PNG disparity scale must be a positive finite number, got {scale!r}")
    d = np.asarray(disparity, dtype=np.float64)
    finite = np.isfinite(d)
    value = np.zeros(d.shape, dtype=np.uint16)
    scaled = np.round(np.where(finite, d, 0.0) * scale)
    ok = finite & (scaled >= 1) & (scaled <= 65535)
    lost = int(finite.sum() - ok.sum())
    if finite.any() and not ok.any():
        raise DataError(f"{path}: no valid disparity fits round(d * {scale:g}) in 1..65535 (they span "
                        f"{d[finite].min():.4g}..{d[finite].max():.4g} px); choose another scale")
    value[ok] = scaled[ok].astype(np.uint16)
    write_image(path, value)
    return lost


def read_disparity(path: str | os.PathLike, *, scale: float | None = None, kind: str = "disparity") -> np.ndarray:
    """Read a disparity map as (H, W) float32 pixels with +inf for invalid / unknown.

    ``.pfm`` and ``.npy`` hold pixels directly. Integer images (``.png``, ``.pgm``) hold
    ``d * scale`` with 0 = unknown; ``scale`` is required for them (256 for KITTI 16-bit PNG,
    16/8/4 for Middlebury 2001/2003 8-bit GT) and a 16-bit PNG defaults to 256.
    NaN values are rejected (they are not a stereocli convention). ``kind`` names the map in
    messages (``confidence`` for a confidence map read the same way).
    """
    path = Path(path)
    suffix = path.suffix.lower()
    if suffix == ".pfm":
        disp = read_pfm(path)
        if disp.ndim != 2:
            raise DataError(f"{path}: a {kind} PFM must have one channel (Pf), got PF")
    elif suffix == ".npy":
        try:
            disp = np.load(path).astype(np.float32)
        except (OSError, ValueError) as exc:
            raise DataError(f"{path}: cannot read .npy ({exc})") from None
        if disp.ndim != 2:
            raise DataError(f"{path}: a {kind} array must be 2-D, got shape {disp.shape}")
    elif suffix in IMAGE_SUFFIXES:
        raw = read_image(path)
        if raw.ndim != 2:
            raise DataError(f"{path}: a {kind} image must have one channel")
        if scale is None:
            if raw.dtype != np.uint16:
                raise DataError(
                    f"{path}: 8-bit disparity needs an explicit scale (e.g. 16 Tsukuba, 8 Venus, 4 Teddy/Cones)"
                )
            scale = 256.0
        disp = raw.astype(np.float32) / np.float32(scale)
        disp[raw == 0] = np.inf
    else:
        raise DataError(f"{path}: unknown {kind} format {suffix!r} (use .pfm, .png, .pgm or .npy)")
    if np.isnan(disp).any():
        raise DataError(f"{path}: {kind} contains NaN; stereocli marks invalid pixels with +inf")
    return np.ascontiguousarray(disp, dtype=np.float32)


def write_disparity(path: str | os.PathLike, disparity: np.ndarray, *, png_scale: float = 256.0) -> int:
    """Write disparity by extension: ``.pfm`` (float32, +inf invalid), ``.npy``, ``.png`` (uint16,
    scaled); returns the number of valid pixels the format could not hold (PNG only)."""
    path = Path(path)
    suffix = path.suffix.lower()
    if suffix == ".pfm":
        write_pfm(path, disparity)
    elif suffix == ".npy":
        refuse_nan(path, disparity)
        with atomic_path(path) as tmp:
            with open(tmp, "wb") as fh:
                np.save(fh, np.asarray(disparity, dtype=np.float32))
    elif suffix == ".png":
        return write_disparity_png16(path, disparity, png_scale)
    else:
        raise DataError(f"{path}: unknown disparity output format {suffix!r}")
    return 0
