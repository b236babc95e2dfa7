"""Compiled image kernels shared by stages: luma of RGB, 2×2 mean downsampling."""

from __future__ import annotations

import numpy as np

from ...runtime import chunk_kernel, for_rows


@chunk_kernel
def _luma_rows(img, out, y0: int, y1: int) -> None:
    """:func:`luma` of rows ``[y0, y1)``, written into ``out``."""
    w = img.shape[1]
    for y in range(y0, y1):
        for x in range(w):
            out[y, x] = np.float32(0.299 * img[y, x, 0] + 0.587 * img[y, x, 1] + 0.114 * img[y, x, 2])


def luma(img: np.ndarray) -> np.ndarray:
    """(H, W, 3) float32 or uint8 RGB -> (H, W) float32 luma 0.299 R + 0.587 G + 0.114 B (the
    same values for 8-bit colours as for their float32 copy)."""
    h, w = img.shape[0], img.shape[1]
    out = np.empty((h, w), np.float32)
    for_rows(_luma_rows, h, img, out)
    return out


@chunk_kernel
def _half_resolution_rows(img, out, r0: int, r1: int) -> None:
    """:func:`half_resolution` of output rows ``[r0, r1)`` of an (H, W, C) image, written into ``out``."""
    h, w, nc = img.shape
    w2 = out.shape[1]
    for y in range(r0, r1):
        y0 = 2 * y
        y1 = min(2 * y + 1, h - 1)
        for x in range(w2):
            x0 = 2 * x
            x1 = min(2 * x + 1, w - 1)
            for c in range(nc):
                out[y, x, c] = np.float32(0.25) * (img[y0, x0, c] + img[y0, x1, c] + img[y1, x0, c] + img[y1, x1, c])


def half_resolution(image: np.ndarray) -> np.ndarray:
    """2×2 mean of an (H, W) or (H, W, C) float32 image: (ceil(H/2), ceil(W/2)[, C]); an odd
    last row/column averages what it has. (Compiled rather than cv2.resize: OpenCV's worker
    threads keep spinning after a call and would slow the numba kernels that follow.)"""
    h, w = image.shape[0], image.shape[1]
    h2, w2 = (h + 1) // 2, (w + 1) // 2
    img = image.reshape(h, w, -1)
    out = np.empty((h2, w2, img.shape[2]), np.float32)
    for_rows(_half_resolution_rows, h2, img, out)
    return out
