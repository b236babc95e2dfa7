"""Compiled kernels that build (H, W, D) float32 cost volumes.

Layout: ``cost[y, x, k]`` compares left (x, y) with right (x - (min_disp + k), y); entries whose
right pixel is outside the image get ``cost_max``.
"""

from __future__ import annotations

import numpy as np
from numba import njit, prange


@njit(cache=True, parallel=True)
def census_transform(image: np.ndarray, half_h: int, half_w: int) -> np.ndarray:
    """Census bit strings of a (H, W) float32 image, one uint64 per pixel.

    Bit = 1 where the neighbour is darker than the centre (Zabih & Woodfill 1994); the centre
    itself is skipped, so a window may hold up to 65 pixels. Neighbours outside the image are
    clamped to the border (replicate), so border pixels still get full-length strings.
    """
    h, w = image.shape
    out = np.zeros((h, w), np.uint64)
    for y in prange(h):
        for x in range(w):
            c = image[y, x]
            bits = np.uint64(0)
            for dy in range(-half_h, half_h + 1):
                yy = min(max(y + dy, 0), h - 1)
                for dx in range(-half_w, half_w + 1):
                    if dy == 0 and dx == 0:
                        continue
                    xx = min(max(x + dx, 0), w - 1)
                    bits = (bits << np.uint64(1)) | np.uint64(image[yy, xx] < c)
            out[y, x] = bits
    return out


@njit(cache=True, inline="always")
def _popcount64(v):
    # SWAR popcount; LLVM turns this into the hardware instruction where available.
    v = v - ((v >> np.uint64(1)) & np.uint64(0x5555555555555555))
    v = (v & np.uint64(0x3333333333333333)) + ((v >> np.uint64(2)) & np.uint64(0x3333333333333333))
    v = (v + (v >> np.uint64(4))) & np.uint64(0x0F0F0F0F0F0F0F0F)
    return (v * np.uint64(0x0101010101010101)) >> np.uint64(56)


@njit(cache=True, parallel=True)
def hamming_volume(census_left: np.ndarray, census_right: np.ndarray, min_disp: int, ndisp: int,
                   cost_max: float) -> np.ndarray:
    """Hamming distance between left and right census strings for every hypothesis."""
    h, w = census_left.shape
    out = np.empty((h, w, ndisp), np.float32)
    for y in prange(h):
        for x in range(w):
            cl = census_left[y, x]
            for k in range(ndisp):
                xr = x - (min_disp + k)
                if xr < 0 or xr >= w:
                    out[y, x, k] = cost_max
                else:
                    out[y, x, k] = np.float32(_popcount64(cl ^ census_right[y, xr]))
    return out


@njit(cache=True, parallel=True)
def absdiff_volume(left: np.ndarray, right: np.ndarray, min_disp: int, ndisp: int,
                   cost_max: float, truncate: float) -> np.ndarray:
    """Mean absolute difference over channels, truncated at ``truncate``.

    ``left``/``right`` are (H, W, C) float32 (C = 1 for grey).
    """
    h, w, nc = left.shape
    out = np.empty((h, w, ndisp), np.float32)
    inv = 1.0 / nc
    for y in prange(h):
        for x in range(w):
            for k in range(ndisp):
                xr = x - (min_disp + k)
                if xr < 0 or xr >= w:
                    out[y, x, k] = cost_max
                    continue
                s = 0.0
                for c in range(nc):
                    s += abs(left[y, x, c] - right[y, xr, c])
                s *= inv
                out[y, x, k] = np.float32(min(s, truncate))
    return out


@njit(cache=True, parallel=True)
def mask_invalid_right(cost: np.ndarray, right_valid: np.ndarray, min_disp: int, cost_max: float) -> None:
    """Set ``cost_max`` wherever the right pixel is outside the right valid mask (in place)."""
    h, w, nd = cost.shape
    for y in prange(h):
        for x in range(w):
            for k in range(nd):
                xr = x - (min_disp + k)
                if 0 <= xr < w and not right_valid[y, xr]:
                    cost[y, x, k] = cost_max
