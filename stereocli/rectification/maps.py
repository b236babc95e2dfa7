"""Rectification maps (``cv2.stereoRectify`` + ``cv2.initUndistortRectifyMap``) and valid masks.

After rectification both cameras share the orientation and focal length of P1/P2, epipolar
lines are image rows and ``x_right = x_left - d``; with ``CALIB_ZERO_DISPARITY`` (always set
here) the principal points coincide, so ``doffs = 0`` unless the rig is unusual.

``alpha`` (OpenCV's free scaling): 0 crops so (almost) every output pixel comes from inside
both images, 1 keeps every source pixel (black borders appear). Either way the valid masks
say exactly which rectified pixels were sampled from inside the source image (255) and which
were not (0); ``match`` reads them so borders never match.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace
from typing import cast

import cv2
import numpy as np

from ..errors import ConfigError, DataError

#: The largest image side (px) rectification handles: ``cv2.remap`` takes images under 32 767
#: (SHRT_MAX) px a side.
MAX_SIDE = 32766


@dataclass
class Rectification:
    """``stereoRectify`` outputs; ``roi1``/``roi2`` are (x, y, w, h) all-valid boxes."""

    R1: np.ndarray
    R2: np.ndarray
    P1: np.ndarray
    P2: np.ndarray
    Q: np.ndarray
    size: tuple[int, int]  # (width, height) of the rectified images
    roi1: tuple[int, int, int, int]
    roi2: tuple[int, int, int, int]

    @property
    def vertical(self) -> bool:
        """Whether the rig is vertical (the second camera above or below the first)."""
        return abs(self.P2[1, 3]) > abs(self.P2[0, 3])


def stereo_rectify(calib, *, alpha: float = 0.0, size: tuple[int, int] | None = None) -> Rectification:
    """Rectify a :class:`~stereocli.io.calib.StereoCalibration` (alpha in [0, 1]; size = (w, h))."""
    if not (0.0 <= alpha <= 1.0) and alpha != -1:
        raise ConfigError(f"--alpha must be in [0, 1], got {alpha}")
    out_size = cast("tuple[int, int]", tuple(int(v) for v in (size or calib.image_size)))  # (w, h)
    if min(out_size) <= 0 or min(calib.image_size) <= 0:
        raise DataError(f"calibration image size {calib.image_size} is not usable for rectification")
    if max(*out_size, *calib.image_size) > MAX_SIDE:
        raise ConfigError(f"rectified size {out_size[0]}x{out_size[1]} (images {calib.image_size[0]}x"
                          f"{calib.image_size[1]}): rectification handles at most {MAX_SIDE} px a side")
    if calib.model == "fisheye":
        R1, R2, P1, P2, Q = cv2.fisheye.stereoRectify(
            calib.K1, calib.D1[:4], calib.K2, calib.D2[:4], calib.image_size, calib.R, calib.T.reshape(3, 1),
            cv2.CALIB_ZERO_DISPARITY, newImageSize=out_size, balance=max(alpha, 0.0), fov_scale=1.0)
        roi = (0, 0, out_size[0], out_size[1])
        rect = Rectification(R1, R2, P1, P2, Q, out_size, roi, roi)
        m1 = valid_mask(*_maps(calib, rect, 1))
        m2 = valid_mask(*_maps(calib, rect, 2))
        rect.roi1, rect.roi2 = inner_box(m1), inner_box(m2)
        return rect
    R1, R2, P1, P2, Q, roi1, roi2 = cv2.stereoRectify(
        calib.K1, calib.D1, calib.K2, calib.D2, calib.image_size, calib.R, calib.T.reshape(3, 1),
        flags=cv2.CALIB_ZERO_DISPARITY, alpha=alpha, newImageSize=out_size)
    return Rectification(R1, R2, P1, P2, Q, out_size, _box(roi1), _box(roi2))


def _box(roi) -> tuple[int, int, int, int]:
    """OpenCV's (x, y, w, h) ROI as four Python ints."""
    x, y, w, h = (int(v) for v in roi)
    return x, y, w, h


def rectified_calibration(calib, *, alpha: float = 0.0, size: tuple[int, int] | None = None,
                          rect: Rectification | None = None):
    """Copy ``calib`` with R1 R2 P1 P2 Q and ``rectified_size`` set.

    They come from ``rect``, or from :func:`stereo_rectify` with ``alpha`` and ``size`` (w, h) when
    ``rect`` is None.
    """
    rect = rect or stereo_rectify(calib, alpha=alpha, size=size)
    return replace(calib, R1=rect.R1, R2=rect.R2, P1=rect.P1, P2=rect.P2, Q=rect.Q, rectified_size=rect.size)


def _maps(calib, rect: Rectification, which: int) -> tuple[np.ndarray, np.ndarray, tuple[int, int]]:
    K, D, Rr, P = (calib.K1, calib.D1, rect.R1, rect.P1) if which == 1 else (calib.K2, calib.D2, rect.R2, rect.P2)
    if calib.model == "fisheye":
        mx, my = cv2.fisheye.initUndistortRectifyMap(K, D[:4], Rr, P, rect.size, cv2.CV_32FC1)
    else:
        mx, my = cv2.initUndistortRectifyMap(K, D, Rr, P, rect.size, cv2.CV_32FC1)
    return mx, my, calib.image_size


def valid_mask(mx: np.ndarray, my: np.ndarray, src_size: tuple[int, int]) -> np.ndarray:
    """uint8 (H, W): 255 where the map samples inside the source image (bilinear support), else 0."""
    w, h = src_size
    ok = (mx >= 0) & (mx <= w - 1) & (my >= 0) & (my <= h - 1)
    return np.where(ok, np.uint8(255), np.uint8(0))


def inner_box(mask: np.ndarray) -> tuple[int, int, int, int]:
    """Find a conservative all-valid (x, y, w, h) box: rows and columns that are valid across the box."""
    ok = mask > 0
    rows = np.flatnonzero(ok.all(axis=1))
    if rows.size == 0:
        rows = np.flatnonzero(ok.mean(axis=1) > 0.5)
    if rows.size == 0:
        return (0, 0, 0, 0)
    y0, y1 = rows[0], rows[-1]
    cols = np.flatnonzero(ok[y0:y1 + 1].all(axis=0))
    if cols.size == 0:
        return (0, 0, 0, 0)
    return (int(cols[0]), int(y0), int(cols[-1] - cols[0] + 1), int(y1 - y0 + 1))


@dataclass
class RectifyMaps:
    """Pixel maps (float32 (H, W)) and valid masks (uint8, 255 = valid) for both cameras."""

    rect: Rectification
    map1x: np.ndarray
    map1y: np.ndarray
    map2x: np.ndarray
    map2y: np.ndarray
    valid1: np.ndarray
    valid2: np.ndarray


def build_maps(calib, *, alpha: float = 0.0, size: tuple[int, int] | None = None) -> RectifyMaps:
    """Rectify ``calib`` and build both remap tables and valid masks.

    :class:`DataError` when they do not fit in memory (four float32 tables and two masks: 18 bytes
    a rectified pixel).
    """
    rect = stereo_rectify(calib, alpha=alpha, size=size)
    try:
        m1x, m1y, src = _maps(calib, rect, 1)
        m2x, m2y, _ = _maps(calib, rect, 2)
        return RectifyMaps(rect, m1x, m1y, m2x, m2y, valid_mask(m1x, m1y, src), valid_mask(m2x, m2y, src))
    except (cv2.error, MemoryError) as exc:
        if isinstance(exc, cv2.error) and exc.code != cv2.Error.StsNoMem:
            raise
        w, h = rect.size
        raise DataError(f"rectified size {w}x{h}: its remap tables need {18 * w * h / 2**30:.1f} GiB, more than "
                        "this machine can allocate (choose a smaller --size)") from None


INTERPOLATIONS = {"nearest": cv2.INTER_NEAREST, "linear": cv2.INTER_LINEAR, "cubic": cv2.INTER_CUBIC,
                  "lanczos": cv2.INTER_LANCZOS4}


def rectify_images(left: np.ndarray, right: np.ndarray, maps: RectifyMaps, *,
                   interpolation: str = "linear") -> tuple[np.ndarray, np.ndarray]:
    """Remap an unrectified pair; pixels outside the source are 0 (see the valid masks)."""
    if interpolation not in INTERPOLATIONS:
        raise ConfigError(f"unknown interpolation {interpolation!r} (choose {', '.join(INTERPOLATIONS)})")
    interp = INTERPOLATIONS[interpolation]
    out = []
    for image, mx, my in ((left, maps.map1x, maps.map1y), (right, maps.map2x, maps.map2y)):
        out.append(cv2.remap(image, mx, my, interp, borderMode=cv2.BORDER_CONSTANT, borderValue=0))
    return out[0], out[1]


def estimate_ndisp(rect: Rectification, *, min_depth: float | None = None, width: int | None = None) -> int:
    """Choose a conservative disparity range (multiple of 16).

    With ``min_depth`` (calibration units): ``ceil16(f·B / min_depth - doffs)``; otherwise a
    quarter of the image width (a common default for hand-held rigs), at least 16.
    """
    f = rect.P1[0, 0]
    baseline = -rect.P2[0, 3] / rect.P2[0, 0]
    doffs = rect.P2[0, 2] - rect.P1[0, 2]
    w = width or rect.size[0]
    if min_depth and min_depth > 0 and baseline > 0:
        d = f * baseline / min_depth - doffs
    else:
        d = w / 4
    return int(max(16, min(16 * math.ceil(max(d, 1) / 16), 16 * math.ceil(w / 16))))


def check_image(left: np.ndarray, right: np.ndarray, rect: Rectification | None = None, *, spacing: int = 32,
                rois: tuple[tuple[int, int, int, int], tuple[int, int, int, int]] | None = None) -> np.ndarray:
    """Side-by-side 8-bit RGB preview with horizontal lines every ``spacing`` px.

    Boxes go round the all-valid areas (``rect``'s ROIs, or ``rois`` = (left, right) (x, y, w, h)
    boxes).
    """
    def rgb8(im: np.ndarray) -> np.ndarray:
        if im.dtype != np.uint8:
            im = cv2.convertScaleAbs(im, alpha=255.0 / max(float(im.max()), 1.0))
        return cv2.cvtColor(im, cv2.COLOR_GRAY2RGB) if im.ndim == 2 else im.copy()

    a, b = rgb8(left), rgb8(right)
    if not rois:
        if rect is None:
            raise ValueError("check_image needs rect or rois")
        rois = (rect.roi1, rect.roi2)
    for im, roi in zip((a, b), rois):
        x, y, w, h = roi
        if w > 0 and h > 0:
            cv2.rectangle(im, (x, y), (x + w - 1, y + h - 1), (0, 255, 0), 1)
    both = np.hstack([a, b])
    colours = ((255, 0, 0), (0, 128, 255), (255, 200, 0))
    for k, y in enumerate(range(spacing // 2, both.shape[0], spacing)):
        cv2.line(both, (0, y), (both.shape[1] - 1, y), colours[k % 3], 1)
    return both
