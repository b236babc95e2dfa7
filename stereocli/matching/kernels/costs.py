"""Compiled kernels for the matching costs other than census: pixel-wise (AD, SD, BT, gradient),
window-based (SAD, NCC, rank, ordinal, AD-census), mutual information, and the right-border mask.

Cost volume layout (the stage contract): ``cost[y, x, k]`` compares left (x, y) with right
(x - (min_disp + k), y); float32, C-contiguous, lower is better; entries whose right pixel lies
outside the image hold ``cost_max``. Images are (H, W, C) float32 (C = 1 for grey).

Window-based kernels return the *mean* over the window clipped to the image (the sum divided
by the number of pixels inside), so costs keep the units of the pixel-wise cost whatever the
window size; WTA is unaffected. Right pixels that a window reaches beyond the image border are
clamped to the border (replicate) so windows straddling the border still compare something.
Tests compare every kernel with a tiny pure-numpy reference (``tests/test_costs.py``).
"""

from __future__ import annotations

import numpy as np

from ...runtime import chunk_kernel, for_rows, njit, prange
from .census import _popcount64

#: pixel-wise cost modes of :func:`window_cost_volume` / :func:`pixel_cost_volume`
MODE_AD = 0  # mean over channels of |L - R|
MODE_SD = 1  # mean over channels of (L - R)^2
MODE_PRODUCT = 2  # sum over channels of L * R (for NCC / ZNCC)


@njit(cache=True, inline="always")
def _valid_k_range(x: int, min_disp: int, ndisp: int, width: int):
    # k is possible iff 0 <= x - (min_disp + k) < width.
    klo = max(0, x - min_disp - width + 1)
    khi = min(ndisp - 1, x - min_disp)
    return klo, khi


@njit(cache=True)
def _pixel_row(left, right, y, min_disp, mode, truncate, row, channel_mean=True):
    # One image row of pixel-wise costs, right pixels clamped to the border. The hypotheses
    # whose right pixel is inside the image read it with unit stride (vectorisable); the rest
    # compare with the border pixel. AD/SD are the mean over channels truncated at
    # ``truncate``, or with ``channel_mean=False`` the channel *sum* truncated at ``truncate``
    # (the caller passes C·T and divides later: exact integer sums for 8-bit images).
    h, w, nc = left.shape
    nd = row.shape[1]
    inv = np.float32(1.0 / nc) if channel_mean else np.float32(1.0)
    for x in range(w):
        klo, khi = _valid_k_range(x, min_disp, nd, w)
        base = x - min_disp
        if nc == 1 and mode == MODE_AD:
            lv = left[y, x, 0]
            rrow = right[y, :, 0]
            out_row = row[x]
            for k in range(klo, khi + 1):
                out_row[k] = min(abs(lv - rrow[base - k]), truncate)
            for k in range(min(klo, nd)):
                out_row[k] = min(abs(lv - rrow[w - 1]), truncate)
            for k in range(max(khi + 1, 0), nd):
                out_row[k] = min(abs(lv - rrow[0]), truncate)
            continue
        for k in range(nd):
            xr = min(max(base - k, 0), w - 1)
            s = np.float32(0.0)
            if mode == MODE_AD:
                for c in range(nc):
                    s += abs(left[y, x, c] - right[y, xr, c])
                s = min(s * inv, truncate)
            elif mode == MODE_SD:
                for c in range(nc):
                    v = left[y, x, c] - right[y, xr, c]
                    s += v * v
                s = min(s * inv, truncate)
            else:
                for c in range(nc):
                    s += left[y, x, c] * right[y, xr, c]
            row[x, k] = s


@njit(cache=True, parallel=True)
def pixel_cost_volume(left: np.ndarray, right: np.ndarray, min_disp: int, ndisp: int, mode: int,
                      truncate: float, cost_max: float) -> np.ndarray:
    """Pixel-wise AD / SD (mean over channels, truncated) or channel product, (H, W, D) float32."""
    h, w, nc = left.shape
    out = np.empty((h, w, ndisp), np.float32)
    trunc = np.float32(truncate)
    cmax = np.float32(cost_max)
    for y in prange(h):
        row = np.empty((w, ndisp), np.float32)
        _pixel_row(left, right, y, min_disp, mode, trunc, row)
        for x in range(w):
            klo, khi = _valid_k_range(x, min_disp, ndisp, w)
            for k in range(ndisp):
                out[y, x, k] = row[x, k] if klo <= k <= khi else cmax
    return out


@njit(cache=True, parallel=True)
def window_cost_volume(left: np.ndarray, right: np.ndarray, min_disp: int, ndisp: int,
                       radius_y: int, radius_x: int, mode: int, truncate: float, cost_max: float,
                       nbands: int) -> np.ndarray:
    """Window mean of a pixel-wise cost by running sums (SAD, SSD, STAD, NCC numerators).

    O(1) per entry whatever the window: each band of rows keeps the column sums of the
    pixel-wise costs (one row added, one removed per step) and a running sum along x, the
    scheme of Di Stefano et al. (2004) and OpenCV's StereoBM. The window is clipped to the
    image and the sum divided by its pixel count. ``nbands`` bands run in parallel (a band
    pays ``2·radius_y`` extra rows to start); output does not depend on ``nbands``
    beyond float32 rounding of the running sums.

    AD/SD sum the channels (truncated at C·``truncate``) and divide the window sum by
    C·pixels, which equals the window mean of the per-pixel channel mean truncated at
    ``truncate``; with 8-bit images every partial sum is then an integer below 2**24, so the
    float32 sums are exact and independent of ``nbands``. The fused SAD + WTA kernel
    (:mod:`.fused_sad`) repeats these float32 operations one for one.
    """
    h, w, nc = left.shape
    out = np.empty((h, w, ndisp), np.float32)
    cnorm = 1 if mode == MODE_PRODUCT else nc  # channel sum -> channel mean at the end
    trunc = np.float32(truncate * cnorm)
    cmax = np.float32(cost_max)
    nbands = max(1, min(nbands, h))
    band = (h + nbands - 1) // nbands
    ring = 2 * radius_y + 2  # rows y - ry - 1 .. y + ry: each pixel row is computed once
    for b in prange(nbands):
        y0 = b * band
        y1 = min(h, y0 + band)
        if y0 >= y1:
            continue
        # float32 sums: exact for 8-bit AD/SD sums below 2^24, else ~1e-6 relative drift
        col = np.zeros((w, ndisp), np.float32)
        rows = np.empty((ring, w, ndisp), np.float32)
        acc = np.zeros(ndisp, np.float32)
        for yy in range(max(0, y0 - radius_y), min(h - 1, y0 + radius_y) + 1):
            row = rows[yy % ring]
            _pixel_row(left, right, yy, min_disp, mode, trunc, row, False)
            for x in range(w):
                for k in range(ndisp):
                    col[x, k] += row[x, k]
        for y in range(y0, y1):
            if y > y0:
                ya = y + radius_y
                yr = y - radius_y - 1
                if ya < h:
                    row = rows[ya % ring]
                    _pixel_row(left, right, ya, min_disp, mode, trunc, row, False)
                    if yr >= 0:
                        old = rows[yr % ring]
                        for x in range(w):
                            for k in range(ndisp):
                                col[x, k] += row[x, k] - old[x, k]
                    else:
                        for x in range(w):
                            for k in range(ndisp):
                                col[x, k] += row[x, k]
                elif yr >= 0:
                    old = rows[yr % ring]
                    for x in range(w):
                        for k in range(ndisp):
                            col[x, k] -= old[x, k]
            ny = min(h - 1, y + radius_y) - max(0, y - radius_y) + 1
            for k in range(ndisp):
                acc[k] = 0.0
            for x in range(min(radius_x, w - 1) + 1):
                for k in range(ndisp):
                    acc[k] += col[x, k]
            for x in range(w):
                nx = min(w - 1, x + radius_x) - max(0, x - radius_x) + 1
                inv = np.float32(1.0 / (nx * ny * cnorm))
                klo, khi = _valid_k_range(x, min_disp, ndisp, w)
                for k in range(min(klo, ndisp)):
                    out[y, x, k] = cmax
                for k in range(max(klo, 0), khi + 1):
                    out[y, x, k] = acc[k] * inv
                for k in range(max(khi + 1, 0), ndisp):
                    out[y, x, k] = cmax
                xa = x + radius_x + 1
                xo = x - radius_x
                if xa < w and xo >= 0:
                    for k in range(ndisp):
                        acc[k] += col[xa, k] - col[xo, k]
                elif xa < w:
                    for k in range(ndisp):
                        acc[k] += col[xa, k]
                elif xo >= 0:
                    for k in range(ndisp):
                        acc[k] -= col[xo, k]
    return out


@njit(cache=True, parallel=True)
def ncc_from_means(prod: np.ndarray, mean_l: np.ndarray, mean_r: np.ndarray, sq_l: np.ndarray,
                   sq_r: np.ndarray, min_disp: int, zero_mean: bool, cost_max: float) -> np.ndarray:
    """Turn window means into ``1 - NCC`` (or ``1 - ZNCC``), in place on ``prod``.

    ``prod[y, x, k]`` = window mean of Σ_c L_c·R_c; ``mean_l/mean_r`` (H, W, C) window means of
    each channel; ``sq_l/sq_r`` (H, W) window means of Σ_c I_c². The right-image statistics
    are read at the right pixel ``x - d`` (the same window shifted by d). Flat windows (no
    variance) get cost 1 (uncorrelated). Range [0, 2].
    """
    h, w, nd = prod.shape
    nc = mean_l.shape[2]
    cmax = np.float32(cost_max)
    for y in prange(h):
        for x in range(w):
            klo, khi = _valid_k_range(x, min_disp, nd, w)
            ml2 = 0.0
            for c in range(nc):
                ml2 += mean_l[y, x, c] * mean_l[y, x, c]
            for k in range(nd):
                if k < klo or k > khi:
                    prod[y, x, k] = cmax
                    continue
                xr = x - min_disp - k
                num = prod[y, x, k]
                vl = sq_l[y, x]
                vr = sq_r[y, xr]
                if zero_mean:
                    mm = 0.0
                    mr2 = 0.0
                    for c in range(nc):
                        mm += mean_l[y, x, c] * mean_r[y, xr, c]
                        mr2 += mean_r[y, xr, c] * mean_r[y, xr, c]
                    num -= mm
                    vl -= ml2
                    vr -= mr2
                den = vl * vr
                if vl <= 1e-6 or vr <= 1e-6:
                    prod[y, x, k] = np.float32(1.0)
                else:
                    v = 1.0 - num / np.sqrt(den)
                    prod[y, x, k] = np.float32(min(max(v, 0.0), 2.0))
    return prod


@njit(cache=True, parallel=True)
def bt_volume(left: np.ndarray, right: np.ndarray, min_disp: int, ndisp: int, truncate: float,
              cost_max: float) -> np.ndarray:
    """Birchfield–Tomasi sampling-insensitive dissimilarity, mean over channels, truncated.

    d(x, xr) = min(d_LR, d_RL) with d_LR = max(0, L(x) − Rmax, Rmin − L(x)) where Rmin/Rmax
    are the extremes of R over [xr − ½, xr + ½] (linear interpolation: R(xr), the half-way
    values to xr ± 1); d_RL symmetric (Birchfield & Tomasi 1998, eq. 1–3).
    """
    h, w, nc = left.shape
    out = np.empty((h, w, ndisp), np.float32)
    inv = np.float32(1.0 / nc)
    trunc = np.float32(truncate)
    cmax = np.float32(cost_max)
    for y in prange(h):
        lmin = np.empty((w, nc), np.float32)
        lmax = np.empty((w, nc), np.float32)
        rmin = np.empty((w, nc), np.float32)
        rmax = np.empty((w, nc), np.float32)
        for x in range(w):
            xa = max(x - 1, 0)
            xb = min(x + 1, w - 1)
            for c in range(nc):
                v = left[y, x, c]
                a = 0.5 * (v + left[y, xa, c])
                b = 0.5 * (v + left[y, xb, c])
                lmin[x, c] = min(v, min(a, b))
                lmax[x, c] = max(v, max(a, b))
                v = right[y, x, c]
                a = 0.5 * (v + right[y, xa, c])
                b = 0.5 * (v + right[y, xb, c])
                rmin[x, c] = min(v, min(a, b))
                rmax[x, c] = max(v, max(a, b))
        for x in range(w):
            klo, khi = _valid_k_range(x, min_disp, ndisp, w)
            for k in range(ndisp):
                if k < klo or k > khi:
                    out[y, x, k] = cmax
                    continue
                xr = x - min_disp - k
                s = np.float32(0.0)
                for c in range(nc):
                    lv = left[y, x, c]
                    rv = right[y, xr, c]
                    dlr = max(np.float32(0.0), max(lv - rmax[xr, c], rmin[xr, c] - lv))
                    drl = max(np.float32(0.0), max(rv - lmax[x, c], lmin[x, c] - rv))
                    s += min(dlr, drl)
                out[y, x, k] = min(s * inv, trunc)
    return out


@njit(cache=True, parallel=True)
def color_gradient_volume(left: np.ndarray, right: np.ndarray, grad_l: np.ndarray,
                          grad_r: np.ndarray, min_disp: int, ndisp: int, alpha: float,
                          tau_color: float, tau_grad: float, cost_max: float) -> np.ndarray:
    """(1 − α)·min(AD_colour, τ_c) + α·min(|∇L − ∇R|, τ_g) (Hosni et al. 2013, eq. 6).

    AD_colour is the mean over channels; ``grad_l``/``grad_r`` are (H, W, G) gradient images
    (their absolute differences are averaged over G).
    """
    h, w, nc = left.shape
    ng = grad_l.shape[2]
    out = np.empty((h, w, ndisp), np.float32)
    cmax = np.float32(cost_max)
    for y in prange(h):
        for x in range(w):
            klo, khi = _valid_k_range(x, min_disp, ndisp, w)
            for k in range(ndisp):
                if k < klo or k > khi:
                    out[y, x, k] = cmax
                    continue
                xr = x - min_disp - k
                a = 0.0
                for c in range(nc):
                    a += abs(left[y, x, c] - right[y, xr, c])
                g = 0.0
                for c in range(ng):
                    g += abs(grad_l[y, x, c] - grad_r[y, xr, c])
                out[y, x, k] = np.float32((1.0 - alpha) * min(a / nc, tau_color) + alpha * min(g / ng, tau_grad))
    return out


@njit(cache=True, parallel=True)
def rank_transform(image: np.ndarray, half_h: int, half_w: int) -> np.ndarray:
    """Rank transform of a (H, W) float32 image: number of window pixels darker than the
    centre (Zabih & Woodfill 1994); the window is clamped at the border (replicate)."""
    h, w = image.shape
    out = np.empty((h, w), np.float32)
    for y in prange(h):
        for x in range(w):
            c = image[y, x]
            n = 0
            for dy in range(-half_h, half_h + 1):
                yy = min(max(y + dy, 0), h - 1)
                for dx in range(-half_w, half_w + 1):
                    xx = min(max(x + dx, 0), w - 1)
                    if image[yy, xx] < c:
                        n += 1
            out[y, x] = n
    return out


@njit(cache=True, parallel=True)
def ad_census_volume(left: np.ndarray, right: np.ndarray, census_l: np.ndarray, census_r: np.ndarray,
                     min_disp: int, ndisp: int, lambda_ad: float, lambda_census: float,
                     robust: bool, cost_max: float) -> np.ndarray:
    """AD-census (Mei et al. 2011, eq. 1–3).

    ``robust``: ρ(c_AD, λ_AD) + ρ(c_census, λ_census) with ρ(c, λ) = 1 − exp(−c/λ) (range
    [0, 2]); otherwise the scaled sum c_AD/λ_AD + c_census/λ_census. c_AD is the mean over
    channels of |L − R|, c_census the Hamming distance of the census strings.
    """
    h, w, nc = left.shape
    out = np.empty((h, w, ndisp), np.float32)
    cmax = np.float32(cost_max)
    for y in prange(h):
        for x in range(w):
            klo, khi = _valid_k_range(x, min_disp, ndisp, w)
            cl = census_l[y, x]
            for k in range(ndisp):
                if k < klo or k > khi:
                    out[y, x, k] = cmax
                    continue
                xr = x - min_disp - k
                a = 0.0
                for c in range(nc):
                    a += abs(left[y, x, c] - right[y, xr, c])
                a /= nc
                hd = float(_popcount64(cl ^ census_r[y, xr]))
                if robust:
                    v = 2.0 - np.exp(-a / lambda_ad) - np.exp(-hd / lambda_census)
                else:
                    v = a / lambda_ad + hd / lambda_census
                out[y, x, k] = np.float32(v)
    return out


@njit(cache=True, inline="always")
def _gather_window(image, y: int, x: int, half_h: int, half_w: int, vals) -> None:
    # The window's pixels in raster order into vals (borders replicated).
    h, w = image.shape
    i = 0
    for dy in range(-half_h, half_h + 1):
        yy = min(max(y + dy, 0), h - 1)
        for dx in range(-half_w, half_w + 1):
            xx = min(max(x + dx, 0), w - 1)
            vals[i] = image[yy, xx]
            i += 1


@njit(cache=True, parallel=True)
def ordinal_tables(left: np.ndarray, right: np.ndarray, half_h: int, half_w: int):
    """Per-pixel window orderings for the Bhat–Nayar ordinal measure.

    Returns ``order_l`` (H, W, n) uint8: window positions of the left window sorted by
    intensity (ties by position), and ``rank_r`` (H, W, n) uint8: the rank of each window
    position in the right window. Windows are clamped at the border.
    """
    h, w = left.shape
    n = (2 * half_h + 1) * (2 * half_w + 1)
    order_l = np.empty((h, w, n), np.uint8)
    rank_r = np.empty((h, w, n), np.uint8)
    for y in prange(h):
        vals = np.empty(n, np.float64)
        for x in range(w):
            _gather_window(left, y, x, half_h, half_w, vals)
            idx = np.argsort(vals, kind="mergesort")  # stable: ties by position
            for j in range(n):
                order_l[y, x, j] = idx[j]
            _gather_window(right, y, x, half_h, half_w, vals)
            idx = np.argsort(vals, kind="mergesort")  # stable: ties by position
            for j in range(n):
                rank_r[y, x, idx[j]] = j
    return order_l, rank_r


@njit(cache=True, parallel=True)
def ordinal_volume(order_l: np.ndarray, rank_r: np.ndarray, min_disp: int, ndisp: int,
                   cost_max: float) -> np.ndarray:
    """Bhat–Nayar distance d_m / ⌊n/2⌋ ∈ [0, 1] for every hypothesis (= (1 − κ)/2).

    s(i) = rank in the right window of the pixel ranked i in the left window; d_m = max_i
    (i − #{j ≤ i : s(j) ≤ i}) (Bhat & Nayar 1998, §3), computed incrementally in O(n).
    """
    h, w, n = order_l.shape
    out = np.empty((h, w, ndisp), np.float32)
    cmax = np.float32(cost_max)
    norm = 1.0 / max(1, n // 2)
    for y in prange(h):
        marked = np.zeros(n, np.uint8)
        for x in range(w):
            klo, khi = _valid_k_range(x, min_disp, ndisp, w)
            for k in range(ndisp):
                if k < klo or k > khi:
                    out[y, x, k] = cmax
                    continue
                xr = x - min_disp - k
                for j in range(n):
                    marked[j] = 0
                count = 0  # #{j <= i : s(j) <= i}
                dm = 0
                for i in range(n):
                    s = rank_r[y, xr, order_l[y, x, i]]
                    marked[s] = 1
                    if s < i:
                        count += 1
                    # rank i itself becomes "<= i": counted if already marked (incl. now)
                    count += marked[i]
                    di = i + 1 - count
                    if di > dm:
                        dm = di
                out[y, x, k] = np.float32(dm * norm)
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


@chunk_kernel
def _mask_invalid_right_rows(cost, right_valid, min_disp: int, cost_max: float, y0: int, y1: int) -> None:
    """:func:`mask_invalid_right` on rows ``[y0, y1)``."""
    _, w, nd = cost.shape
    for y in range(y0, y1):
        for x in range(w):
            for k in range(nd):
                xr = x - (min_disp + k)
                if 0 <= xr < w and not right_valid[y, xr]:
                    cost[y, x, k] = cost_max


def mask_invalid_right(cost: np.ndarray, right_valid: np.ndarray, min_disp: int, cost_max: float) -> None:
    """Set ``cost_max`` wherever the right pixel is outside the right valid mask (in place;
    ``cost`` (H, W, D) float32, uint8 or uint16, ``right_valid`` (H, W) bool)."""
    for_rows(_mask_invalid_right_rows, cost.shape[0], cost, np.ascontiguousarray(right_valid, dtype=np.bool_),
             int(min_disp), float(cost_max))


@njit(cache=True, parallel=True)
def mi_volume(left_bins, right_bins, table, min_disp: int, ndisp: int, cost_max: float) -> np.ndarray:
    """``cost[y, x, k] = table[left_bins[y, x], right_bins[y, x − (min_disp + k)]]``, ``cost_max``
    where the right pixel is outside the image. Returns (H, W, D) float32."""
    h, w = left_bins.shape
    out = np.empty((h, w, ndisp), np.float32)
    for y in prange(h):
        for x in range(w):
            row = table[left_bins[y, x]]
            for k in range(ndisp):
                xr = x - (min_disp + k)
                if xr < 0 or xr >= w:
                    out[y, x, k] = cost_max
                else:
                    out[y, x, k] = row[right_bins[y, xr]]
    return out
