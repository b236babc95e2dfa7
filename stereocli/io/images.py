"""Reading and writing images and disparity maps in the formats stereocli supports."""

from __future__ import annotations

import os
import re
import struct
from dataclasses import dataclass
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
    check_decodable(path, read_image_header(path))
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


def _opencv_limit(name: str, default: int) -> int:
    value = os.environ.get(name, "")
    return int(value) if value.isdigit() else default


#: OpenCV's decoding limits (its ``CV_IO_MAX_IMAGE_PIXELS``, ``_WIDTH`` and ``_HEIGHT`` settings).
OPENCV_MAX_PIXELS = _opencv_limit("CV_IO_MAX_IMAGE_PIXELS", 1 << 30)
OPENCV_MAX_SIDE = min(_opencv_limit(f"CV_IO_MAX_IMAGE_{side}", 1 << 20) for side in ("WIDTH", "HEIGHT"))


@dataclass(frozen=True)
class ImageHeader:
    """What an image file declares in its header, read without decoding the pixels."""

    width: int
    height: int
    channels: int  # samples per pixel as OpenCV decodes the file (alpha included)
    itemsize: int  # bytes per sample: 1 (8-bit), 2 (16-bit) or 4 (float32)

    @property
    def decoded_bytes(self) -> int:
        """Bytes of the array OpenCV decodes (before :func:`read_image` drops an alpha channel)."""
        return self.width * self.height * self.channels * self.itemsize

    @property
    def image_bytes(self) -> int:
        """Bytes of the array :func:`read_image` returns (RGB or grey)."""
        return self.width * self.height * min(self.channels, 3) * self.itemsize


def read_image_header(path: str | os.PathLike) -> ImageHeader | None:
    """The size and sample layout a PNG, JPEG, TIFF, BMP, WebP, PNM or PFM file declares, from
    its first bytes (and a TIFF's first directory); None for another format, a header this
    cannot parse or a file it cannot open (decoding then reports what is wrong)."""
    try:
        with open(path, "rb") as fh:
            head = fh.read(64)
            for probe in (_png_header, _jpeg_header, _tiff_header, _bmp_header, _webp_header, _pnm_header):
                header = probe(head, fh)
                if header is not None:
                    return header if header.width > 0 and header.height > 0 else None
    except (OSError, ValueError, IndexError, KeyError, struct.error):
        return None
    return None


def check_decodable(path: str | os.PathLike, header: ImageHeader | None) -> None:
    """Raise :class:`DataError` naming the file when its header declares more pixels than
    OpenCV decodes."""
    if header is not None and (header.width * header.height > OPENCV_MAX_PIXELS
                               or max(header.width, header.height) > OPENCV_MAX_SIDE):
        raise DataError(f"{path}: the header declares {header.width}x{header.height} pixels, more than OpenCV "
                        f"decodes (at most {OPENCV_MAX_PIXELS} pixels, {OPENCV_MAX_SIDE} a side)")


def _png_header(head: bytes, fh) -> ImageHeader | None:
    if not head.startswith(b"\x89PNG\r\n\x1a\n") or head[12:16] != b"IHDR":
        return None
    width, height, depth, colour = struct.unpack(">IIBB", head[16:26])
    # Palettes decode to BGR, grey with alpha to BGRA.
    channels = {0: 1, 2: 3, 3: 3, 4: 4, 6: 4}[colour]
    return ImageHeader(width, height, channels, 2 if depth == 16 else 1)


def _jpeg_header(head: bytes, fh) -> ImageHeader | None:
    if not head.startswith(b"\xff\xd8"):
        return None
    fh.seek(2)
    while True:
        marker = fh.read(2)
        while marker[1:] == b"\xff":  # fill bytes
            marker = marker[1:] + fh.read(1)
        if len(marker) < 2 or marker[0] != 0xFF:
            raise ValueError("no frame header")
        kind = marker[1]
        if kind in (0x01, *range(0xD0, 0xD8)):  # markers without a segment
            continue
        (length,) = struct.unpack(">H", fh.read(2))
        if length < 2:
            raise ValueError("bad segment length")
        if 0xC0 <= kind <= 0xCF and kind not in (0xC4, 0xC8, 0xCC):  # a start of frame
            _, height, width, components = struct.unpack(">BHHB", fh.read(6))
            return ImageHeader(width, height, 1 if components == 1 else 3, 1)
        fh.seek(length - 2, os.SEEK_CUR)


def _tiff_header(head: bytes, fh) -> ImageHeader | None:
    if head[:4] not in (b"II*\x00", b"MM\x00*"):
        return None
    order = "<" if head[:2] == b"II" else ">"
    (offset,) = struct.unpack(order + "I", head[4:8])
    fh.seek(offset)
    (count,) = struct.unpack(order + "H", fh.read(2))
    entries = fh.read(12 * count)
    tags = {}
    for i in range(count):
        tag, kind, n, value = struct.unpack(order + "HHI4s", entries[12 * i:12 * i + 12])
        fmt = {3: "H", 4: "I"}.get(kind)
        if fmt is not None:  # the first value: in the entry, or where it points when it does not fit
            if n * struct.calcsize(fmt) > 4:
                fh.seek(struct.unpack(order + "I", value)[0])
                value = fh.read(4)
            tags[tag] = struct.unpack(order + fmt, value[:struct.calcsize(fmt)])[0]
    bits = tags.get(258, 1)
    return ImageHeader(tags[256], tags[257], tags.get(277, 1), max(1, bits // 8))


def _bmp_header(head: bytes, fh) -> ImageHeader | None:
    if not head.startswith(b"BM"):
        return None
    (size,) = struct.unpack("<I", head[14:18])
    if size == 12:
        width, height, _, bits = struct.unpack("<HHHH", head[18:26])
    else:
        width, height, _, bits = struct.unpack("<iiHH", head[18:30])
    # Palettes (8 bits or fewer) decode to BGR unless all grey (counted as BGR); 32 bits to BGRA.
    return ImageHeader(abs(width), abs(height), 4 if bits == 32 else 3, 1)


def _webp_header(head: bytes, fh) -> ImageHeader | None:
    if head[:4] != b"RIFF" or head[8:12] != b"WEBP":
        return None
    chunk = head[12:16]
    if chunk == b"VP8 ":  # lossy: the key frame's 14-bit sizes
        width, height = struct.unpack("<HH", head[26:30])
        return ImageHeader(width & 0x3FFF, height & 0x3FFF, 3, 1)
    if chunk == b"VP8L":  # lossless: 14 bits each, minus one, then the alpha bit
        (bits,) = struct.unpack("<I", head[21:25])
        return ImageHeader((bits & 0x3FFF) + 1, ((bits >> 14) & 0x3FFF) + 1, 4 if bits >> 28 & 1 else 3, 1)
    if chunk == b"VP8X":  # extended: 24-bit canvas sizes minus one, alpha flag
        width = int.from_bytes(head[24:27], "little") + 1
        height = int.from_bytes(head[27:30], "little") + 1
        return ImageHeader(width, height, 4 if head[20] & 0x10 else 3, 1)
    return None


_PNM = re.compile(rb"^(P[1-6]|P[Ff])(?:\s+(?:#[^\n]*\n)*\s*)(\d+)(?:\s+(?:#[^\n]*\n)*\s*)(\d+)"
                  rb"(?:(?:\s+(?:#[^\n]*\n)*\s*)([-+0-9.eE]+))?")


def _pnm_header(head: bytes, fh) -> ImageHeader | None:
    match = _PNM.match(head)
    if match is None:
        return None
    kind, width, height, last = match.group(1), int(match.group(2)), int(match.group(3)), match.group(4)
    if kind in (b"Pf", b"PF"):
        return ImageHeader(width, height, 3 if kind == b"PF" else 1, 4)
    deep = kind not in (b"P1", b"P4") and last is not None and float(last) > 255
    return ImageHeader(width, height, 3 if kind in (b"P3", b"P6") else 1, 2 if deep else 1)


def to_float_image(image: np.ndarray) -> np.ndarray:
    """Convert an 8- or 16-bit image to float32 in [0, 255] (the pipeline's working range); a
    float array passes as it is, unless it holds NaN or inf (:class:`DataError`)."""
    if image.dtype.kind == "f" and not np.isfinite(image).all():
        bad = int(np.count_nonzero(~np.isfinite(image)))
        raise DataError(f"the image holds {bad} NaN or infinite values; intensities must be finite")
    if image.dtype == np.uint16:
        return (image.astype(np.float32) * (255.0 / 65535.0)).astype(np.float32)
    return image.astype(np.float32)


def grey_uint8(image: np.ndarray) -> np.ndarray:
    """(H, W) uint8 grey of an (H, W) or (H, W, 3) RGB image (uint8, uint16 or float in [0, 255])."""
    img = np.asarray(image)
    if img.ndim == 3 and img.dtype == np.uint8:
        # The same weights in OpenCV's fixed point, on the 8-bit values (no float copy).
        return cv2.cvtColor(np.ascontiguousarray(img[..., :3]), cv2.COLOR_RGB2GRAY)
    if img.ndim == 3:
        img = img[..., :3].astype(np.float32) @ np.array([0.299, 0.587, 0.114], np.float32)
    if img.dtype == np.uint16:
        img = img / 257.0
    return np.ascontiguousarray(np.clip(np.rint(img), 0, 255).astype(np.uint8))


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


def read_valid_mask(path: str | os.PathLike) -> np.ndarray:
    """A valid mask as ``rectify`` writes it (``valid0.png``: 255 valid, 0 not) as (H, W) bool,
    True above 127."""
    return read_image(path, gray=True) > 127


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
