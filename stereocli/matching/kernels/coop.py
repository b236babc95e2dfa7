"""Compiled kernels of the Zitnick–Kanade cooperative algorithm (support and inhibition)."""

from __future__ import annotations

import numpy as np

from ...runtime import njit, prange


@njit(cache=True, parallel=True)
def initial_match_values(cost: np.ndarray, cost_max: float, sigma: float) -> np.ndarray:
    """L0 = exp(−C / σ) in (0, 1]; impossible entries (C ≥ cost_max) get 0."""
    h, w, nd = cost.shape
    out = np.empty((h, w, nd), np.float32)
    for y in prange(h):
        for x in range(w):
            for k in range(nd):
                c = cost[y, x, k]
                out[y, x, k] = 0.0 if c >= cost_max else np.float32(np.exp(-c / sigma))
    return out


@njit(cache=True, parallel=True)
def box_disparity(vol: np.ndarray, radius: int) -> np.ndarray:
    """Mean over ``[k − radius, k + radius]`` along the disparity axis (clipped at the ends)."""
    h, w, nd = vol.shape
    out = np.empty_like(vol)
    for y in prange(h):
        for x in range(w):
            for k in range(nd):
                a = max(0, k - radius)
                b = min(nd - 1, k + radius)
                s = 0.0
                for j in range(a, b + 1):
                    s += vol[y, x, j]
                out[y, x, k] = np.float32(s / (b - a + 1))
    return out


@njit(cache=True, parallel=True)
def inhibit(support: np.ndarray, l0: np.ndarray, min_disp: int, alpha: float) -> np.ndarray:
    """One cooperative update ``L = L0 · (S / Σ_Ψ S)^α`` (Zitnick & Kanade 2000, eq. 3–4).

    Ψ(x, y, d) is the union of the two lines of sight through the element: all disparities of
    left pixel (x, y), and all elements (x', y, d') seeing the same right pixel x' − d' = x − d.
    The element itself is counted once.
    """
    h, w, nd = support.shape
    out = np.empty_like(support)
    for y in prange(h):
        left_sum = np.zeros(w, np.float64)
        right_sum = np.zeros(w, np.float64)  # indexed by right pixel xr
        for x in range(w):
            for k in range(nd):
                s = support[y, x, k]
                left_sum[x] += s
                xr = x - (min_disp + k)
                if 0 <= xr < w:
                    right_sum[xr] += s
        for x in range(w):
            for k in range(nd):
                s = support[y, x, k]
                xr = x - (min_disp + k)
                tot = left_sum[x] - s
                if 0 <= xr < w:
                    tot += right_sum[xr]
                else:
                    tot += s
                r = s / tot if tot > 0 else 0.0
                out[y, x, k] = np.float32(l0[y, x, k] * r**alpha)
    return out
