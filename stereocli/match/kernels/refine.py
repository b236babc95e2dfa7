"""Compiled kernels of the refinement stages: uniqueness, confidence, hole classification and
interpolation, median and joint bilateral filters on (H, W) float32 disparity maps (+inf invalid).

Cost volumes may be float32 or uint16 (SGM sums); values are read as float64.
"""

from __future__ import annotations

import numpy as np
from numba import njit, prange

INF = np.float32(np.inf)

# 8 directions (dy, dx) searched for valid neighbours when interpolating holes.
DIRECTIONS8 = np.array([[0, 1], [0, -1], [1, 0], [-1, 0], [1, 1], [1, -1], [-1, 1], [-1, -1]], np.int64)


@njit(cache=True, inline="always")
def _valid_range(x: int, w: int, nd: int, min_disp: int):
    # Hypotheses k whose right pixel x - (min_disp + k) lies inside the image.
    return max(0, x - min_disp - (w - 1)), min(nd - 1, x - min_disp)


@njit(cache=True, parallel=True)
def uniqueness(cost, disp, min_disp: int, ratio: float) -> np.ndarray:
    """Invalidate pixels whose best cost is not clearly below every non-adjacent hypothesis.

    OpenCV's rule: reject when some ``d`` with ``|d − d_best| > 1`` has
    ``cost[d] · (1 − ratio) < cost_best``. ``d_best`` is the volume's own minimum (the
    stage may run after sub-pixel refinement). Returns a new float32 map.
    """
    h, w, nd = cost.shape
    out = disp.copy()
    keep = 1.0 - ratio
    for y in prange(h):
        for x in range(w):
            if not np.isfinite(disp[y, x]):
                continue
            k0, k1 = _valid_range(x, w, nd, min_disp)
            if k1 < k0:
                continue
            bk = k0
            bc = np.float64(cost[y, x, k0])
            for k in range(k0 + 1, k1 + 1):
                v = np.float64(cost[y, x, k])
                if v < bc:
                    bc = v
                    bk = k
            for k in range(k0, k1 + 1):
                if abs(k - bk) > 1 and np.float64(cost[y, x, k]) * keep < bc:
                    out[y, x] = INF
                    break
    return out


@njit(cache=True, parallel=True)
def confidence(cost, disp, disp_right, min_disp: int, lr_scale: float, margin_scale: float) -> np.ndarray:
    """Per-pixel confidence in [0, 1]: cost uniqueness × left-right agreement.

    Uniqueness ``u = 1 − c_best / c_second`` (``c_second``: best hypothesis with
    ``|d − d_best| > 1``, the "PKRN" ratio), mapped as ``min(1, u / margin_scale)``. LR term
    ``exp(−|d_L − d_R(x − d_L)| / lr_scale)`` when ``disp_right`` is given (size > 0), else 1.
    Invalid pixels get 0.
    """
    h, w, nd = cost.shape
    conf = np.zeros((h, w), np.float32)
    has_right = disp_right.shape[0] == h and disp_right.shape[1] == w
    for y in prange(h):
        for x in range(w):
            d = disp[y, x]
            if not np.isfinite(d):
                continue
            k0, k1 = _valid_range(x, w, nd, min_disp)
            if k1 < k0:
                continue
            bk = k0
            bc = np.float64(cost[y, x, k0])
            for k in range(k0 + 1, k1 + 1):
                v = np.float64(cost[y, x, k])
                if v < bc:
                    bc = v
                    bk = k
            sc = np.inf
            for k in range(k0, k1 + 1):
                if abs(k - bk) > 1:
                    sc = min(sc, np.float64(cost[y, x, k]))
            u = 1.0 if not np.isfinite(sc) or sc <= 0 else max(0.0, 1.0 - bc / sc)
            c = min(1.0, u / margin_scale)
            if has_right:
                xr = int(np.floor(x - d + 0.5))
                if xr < 0 or xr >= w or not np.isfinite(disp_right[y, xr]):
                    c = 0.0
                else:
                    c *= np.exp(-abs(d - disp_right[y, xr]) / lr_scale)
            conf[y, x] = np.float32(c)
    return conf


@njit(cache=True, parallel=True)
def classify_holes(disp, disp_right, min_disp: int, max_disp: int, tol: float) -> np.ndarray:
    """Label invalid left pixels: 0 valid, 1 occluded, 2 mismatched (Hirschmüller 2008 §2.5).

    A hole is *mismatched* when some right pixel ``x − d`` claims it, i.e.
    ``|disp_right[y, x − d] − d| ≤ tol`` for a ``d`` in the search range (the epipolar line
    intersects the right disparity function); otherwise nothing in the right view sees it and it
    is *occluded*. Without a right map (size 0) every hole is treated as occluded.
    """
    h, w = disp.shape
    label = np.zeros((h, w), np.uint8)
    has_right = disp_right.shape[0] == h and disp_right.shape[1] == w
    for y in prange(h):
        for x in range(w):
            if np.isfinite(disp[y, x]):
                continue
            label[y, x] = 1
            if not has_right:
                continue
            for d in range(min_disp, max_disp + 1):
                xr = x - d
                if xr < 0 or xr >= w:
                    continue
                if abs(disp_right[y, xr] - d) <= tol:
                    label[y, x] = 2
                    break
    return label


@njit(cache=True, parallel=True)
def interpolate_holes(disp, label, max_dist: int) -> np.ndarray:
    """Fill holes from the nearest valid values along 8 directions (Hirschmüller 2008 §2.5).

    Occluded holes (label 1) take the second-lowest found value (background, robust to one
    outlier); mismatched ones (label 2) the median. Directions without a valid value within
    ``max_dist`` px (0 = unlimited) are ignored; holes with nothing found stay invalid.
    """
    h, w = disp.shape
    out = disp.copy()
    limit = max(h, w) if max_dist <= 0 else max_dist
    for y in prange(h):
        buf = np.empty(8, np.float32)
        for x in range(w):
            lab = label[y, x]
            if lab == 0:
                continue
            n = 0
            for k in range(8):
                dy = DIRECTIONS8[k, 0]
                dx = DIRECTIONS8[k, 1]
                yy = y + dy
                xx = x + dx
                step = 1
                while 0 <= yy < h and 0 <= xx < w and step <= limit:
                    v = disp[yy, xx]
                    if np.isfinite(v):
                        buf[n] = v
                        n += 1
                        break
                    yy += dy
                    xx += dx
                    step += 1
            if n == 0:
                continue
            s = np.sort(buf[:n])
            if lab == 1:
                out[y, x] = s[1] if n > 1 else s[0]
            elif n % 2 == 1:
                out[y, x] = s[n // 2]
            else:
                out[y, x] = np.float32(0.5 * (s[n // 2 - 1] + s[n // 2]))
    return out


@njit(cache=True, parallel=True)
def median_valid(disp: np.ndarray, radius: int) -> np.ndarray:
    """Median over the finite values of a (2r+1)² window (insertion sort in a fixed buffer);
    invalid centres stay invalid (reference: ``tests/test_refine_sgm.py``)."""
    h, w = disp.shape
    out = disp.copy()
    size = (2 * radius + 1) ** 2
    for y in prange(h):
        buf = np.empty(size, np.float32)
        for x in range(w):
            if not np.isfinite(disp[y, x]):
                continue
            n = 0
            for yy in range(max(0, y - radius), min(h, y + radius + 1)):
                for xx in range(max(0, x - radius), min(w, x + radius + 1)):
                    v = disp[yy, xx]
                    if np.isfinite(v):
                        j = n
                        while j > 0 and buf[j - 1] > v:
                            buf[j] = buf[j - 1]
                            j -= 1
                        buf[j] = v
                        n += 1
            if n % 2 == 1:
                out[y, x] = buf[n // 2]
            else:
                out[y, x] = np.float32(0.5 * (buf[n // 2 - 1] + buf[n // 2]))
    return out


@njit(cache=True, parallel=True)
def joint_bilateral(disp, guide, radius: int, sigma_space: float, sigma_color: float) -> np.ndarray:
    """Edge-preserving smoothing of valid disparities, weights from the (grey) guide image:
    ``exp(−r²/2σs² − ΔI²/2σc²)`` over finite neighbours; invalid centres stay invalid."""
    h, w = disp.shape
    out = disp.copy()
    ks = -0.5 / (sigma_space * sigma_space)
    kc = -0.5 / (sigma_color * sigma_color)
    for y in prange(h):
        for x in range(w):
            if not np.isfinite(disp[y, x]):
                continue
            g0 = guide[y, x]
            sw = 0.0
            sv = 0.0
            for yy in range(max(0, y - radius), min(h, y + radius + 1)):
                for xx in range(max(0, x - radius), min(w, x + radius + 1)):
                    v = disp[yy, xx]
                    if not np.isfinite(v):
                        continue
                    dg = guide[yy, xx] - g0
                    wt = np.exp(ks * ((yy - y) ** 2 + (xx - x) ** 2) + kc * dg * dg)
                    sw += wt
                    sv += wt * v
            out[y, x] = np.float32(sv / sw)
    return out
