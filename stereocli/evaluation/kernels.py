"""Compiled kernels of the evaluation: KITTI background interpolation, z-buffered visibility for derived
nonocc masks."""

from __future__ import annotations

import math

import numpy as np

from ..runtime import njit, prange


@njit(cache=True, parallel=True)
def kitti_fill_rows(d: np.ndarray) -> None:  # pragma: no cover - compiled
    height, width = d.shape
    for v in prange(height):
        count = 0
        for u in range(width):
            if d[v, u] >= 0.0 and d[v, u] < np.inf:
                if count >= 1:
                    u1 = u - count
                    u2 = u - 1
                    # devkit: interior gaps only (a gap touching column 0 is extrapolated below)
                    if u1 > 0 and u2 < width - 1:
                        fill = min(d[v, u1 - 1], d[v, u2 + 1])
                        for uc in range(u1, u2 + 1):
                            d[v, uc] = fill
                count = 0
            else:
                count += 1
        for u in range(width):
            if d[v, u] >= 0.0 and d[v, u] < np.inf:
                for u2 in range(u):
                    d[v, u2] = d[v, u]
                break
        for u in range(width - 1, -1, -1):
            if d[v, u] >= 0.0 and d[v, u] < np.inf:
                for u2 in range(u + 1, width):
                    d[v, u2] = d[v, u]
                break


@njit(cache=True, parallel=True)
def kitti_fill_cols(d: np.ndarray) -> None:  # pragma: no cover - compiled
    height, width = d.shape
    for u in prange(width):
        for v in range(height):
            if d[v, u] >= 0.0 and d[v, u] < np.inf:
                for v2 in range(v):
                    d[v2, u] = d[v, u]
                break
        for v in range(height - 1, -1, -1):
            if d[v, u] >= 0.0 and d[v, u] < np.inf:
                for v2 in range(v + 1, height):
                    d[v2, u] = d[v, u]
                break


@njit(cache=True, parallel=True)
def zbuffer_visible(gt: np.ndarray, out: np.ndarray) -> None:  # pragma: no cover - compiled
    height, width = gt.shape
    for y in prange(height):
        dmax = -1.0
        for x in range(width):
            g = gt[y, x]
            if g < np.inf and g > dmax:
                dmax = g
        for x in range(width):
            d = gt[y, x]
            if not d < np.inf:
                out[y, x] = False
                continue
            xr = x - d
            # outside the right image (pixel footprint [-0.5, W - 0.5])
            if xr < -0.5 or xr > width - 0.5:
                out[y, x] = False
                continue
            visible = True
            # a nearer pixel x2 (d2 > d) landing within 0.5 px needs x2 - d2 > xr - 0.5, i.e.
            # x2 > x, and x2 < xr + 0.5 + d2 <= xr + 0.5 + dmax: a bounded search.
            last = min(width - 1, int(math.floor(xr + 0.5 + dmax)))
            for x2 in range(x + 1, last + 1):
                d2 = gt[y, x2]
                if d2 < np.inf and d2 > d and abs((x2 - d2) - xr) < 0.5:
                    visible = False
                    break
            out[y, x] = visible
