"""Compiled kernels that pick winners on (H, W, D) cost volumes: WTA (left and right view) and
sub-pixel fits around the winners.

Cost volume layout: ``cost[y, x, k]`` is the cost of left pixel (x, y) against right pixel
(x - (min_disp + k), y); lower is better; float32 or uint16 (SGM sums), C-contiguous.
"""

from __future__ import annotations

import numpy as np

from ...runtime import chunk_kernel, for_rows, njit

INF = np.float32(np.inf)


@chunk_kernel
def _wta_left_rows(cost, min_disp: int, cost_max: float, disp, best, y0: int, y1: int) -> None:
    """:func:`wta_left` of rows ``[y0, y1)``, written into ``disp`` and ``best``."""
    w, nd = cost.shape[1], cost.shape[2]
    for y in range(y0, y1):
        for x in range(w):
            bk = 0
            bc = cost[y, x, 0]
            for k in range(1, nd):
                c = cost[y, x, k]
                if c < bc:
                    bc = c
                    bk = k
            best[y, x] = bc
            disp[y, x] = INF if bc >= cost_max else np.float32(min_disp + bk)


def wta_left(cost: np.ndarray, min_disp: int, cost_max: float):
    """Winner-take-all along D for each left pixel.

    Returns ``(disparity, best_cost)``: float32 (H, W) integer-valued disparities (``+inf`` where
    every hypothesis holds ``cost_max``, i.e. nothing could be matched) and the winning cost.
    Ties go to the smallest disparity (deterministic).
    """
    h, w = cost.shape[0], cost.shape[1]
    disp = np.empty((h, w), np.float32)
    best = np.empty((h, w), np.float32)
    for_rows(_wta_left_rows, h, cost, min_disp, cost_max, disp, best)
    return disp, best


@chunk_kernel
def _wta_right_rows(cost, min_disp: int, cost_max: float, disp, y0: int, y1: int) -> None:
    """:func:`wta_right` of rows ``[y0, y1)``, written into ``disp``."""
    w, nd = cost.shape[1], cost.shape[2]
    for y in range(y0, y1):
        for xr in range(w):
            bk = -1
            bc = np.float32(cost_max)
            for k in range(nd):
                x = xr + min_disp + k
                if x < 0 or x >= w:
                    continue
                c = cost[y, x, k]
                if c < bc:
                    bc = c
                    bk = k
            disp[y, xr] = INF if bk < 0 else np.float32(min_disp + bk)


def wta_right(cost: np.ndarray, min_disp: int, cost_max: float):
    """Right-view winner-take-all from the left-referenced volume.

    For right pixel ``xr`` and hypothesis ``k`` the matching left pixel is ``x = xr + d``
    (``d = min_disp + k``), so ``C_R(xr, k) = cost[y, xr + d, k]`` (Hirschmüller 2008, §2.5).
    Returns float32 (H, W) right-referenced disparities (``x_left = x_right + d``), +inf where
    no hypothesis lands inside the image.
    """
    h, w = cost.shape[0], cost.shape[1]
    disp = np.empty((h, w), np.float32)
    for_rows(_wta_right_rows, h, cost, min_disp, cost_max, disp)
    return disp


@njit(cache=True, inline="always")
def _subpixel_offset(a0: float, a1: float, a2: float, equiangular: bool) -> float:
    # c1 is the minimum; c0, c2 its neighbours. Parabola: vertex of the fitted quadratic.
    # Equiangular (symmetric V, Shimizu & Okutomi 2001) suits costs that are |.|-like.
    # Cast first: volumes may be uint16 (SGM sums), whose differences would wrap around.
    c0 = np.float64(a0)
    c1 = np.float64(a1)
    c2 = np.float64(a2)
    if equiangular:
        if c0 > c2:
            den = c0 - c1
            return 0.0 if den <= 0 else 0.5 * (c0 - c2) / den
        den = c2 - c1
        return 0.0 if den <= 0 else 0.5 * (c0 - c2) / den
    den = c0 - 2.0 * c1 + c2
    if den <= 0:
        return 0.0
    off = 0.5 * (c0 - c2) / den
    if off > 0.5:
        off = 0.5
    elif off < -0.5:
        off = -0.5
    return off


@chunk_kernel
def _subpixel_left_rows(cost, disp, min_disp: int, equiangular: bool, out, y0: int, y1: int) -> None:
    """:func:`subpixel_left` of rows ``[y0, y1)``, written into ``out``."""
    w, nd = cost.shape[1], cost.shape[2]
    for y in range(y0, y1):
        for x in range(w):
            d = disp[y, x]
            if not np.isfinite(d):
                continue
            k = int(d) - min_disp
            if k <= 0 or k >= nd - 1 or x - (min_disp + k + 1) < 0:
                continue
            off = _subpixel_offset(cost[y, x, k - 1], cost[y, x, k], cost[y, x, k + 1], equiangular)
            out[y, x] = np.float32(d + off)


def subpixel_left(cost: np.ndarray, disp: np.ndarray, min_disp: int, equiangular: bool) -> np.ndarray:
    """Refine integer left disparities to sub-pixel by fitting the costs at d-1, d, d+1.

    Pixels at the ends of the range, or whose neighbours are not both defined, keep the integer.
    """
    out = disp.copy()
    for_rows(_subpixel_left_rows, cost.shape[0], cost, disp, min_disp, equiangular, out)
    return out


@chunk_kernel
def _subpixel_right_rows(cost, disp_right, min_disp: int, equiangular: bool, out, y0: int, y1: int) -> None:
    """:func:`subpixel_right` of rows ``[y0, y1)``, written into ``out``."""
    w, nd = cost.shape[1], cost.shape[2]
    for y in range(y0, y1):
        for xr in range(w):
            d = disp_right[y, xr]
            if not np.isfinite(d):
                continue
            k = int(d) - min_disp
            if k <= 0 or k >= nd - 1:
                continue
            x0 = xr + min_disp + k - 1
            x2 = xr + min_disp + k + 1
            if x0 < 0 or x2 >= w:
                continue
            off = _subpixel_offset(cost[y, x0, k - 1], cost[y, x0 + 1, k], cost[y, x2, k + 1], equiangular)
            out[y, xr] = np.float32(d + off)


def subpixel_right(cost: np.ndarray, disp_right: np.ndarray, min_disp: int, equiangular: bool) -> np.ndarray:
    """Sub-pixel refinement of right-view disparities along the volume's diagonal."""
    out = disp_right.copy()
    for_rows(_subpixel_right_rows, cost.shape[0], cost, disp_right, min_disp, equiangular, out)
    return out
