"""Fused window-AD cost + winner-take-all: SAD/STAD disparities without a cost volume.

The (H, W, D) float32 volume of :func:`~stereocli.matching.kernels.costs.window_cost_volume`
costs 4·H·W·D bytes of memory traffic to write and as much again for WTA to read; OpenCV's
StereoBM never stores it. This kernel runs the same running sums (Di Stefano, Marchionni &
Mattoccia, IVC 2004) and takes each pixel's decision as soon as its window sums are known:
per band of rows it keeps the column sums ``col[x, k]`` (one image row added and one removed
per step, both recomputed from the images rather than kept in a ring of pixel-cost rows), and
per row a running sum along x, and it writes only the winner and the costs next to it.

**Bit-identical to the unfused path.** Every float32 operation that produces a cost is the
one :func:`window_cost_volume` performs, in the same order, with the same band layout
(``nbands``), so the costs compared here are the volume's entries bit for bit, and the winner
is chosen with the volume's rule (lowest cost, ties to the smallest k, ``cost_max`` entries
included). The argmin is vectorised: a float32 cost ``c`` maps to an integer with the same
order (its bit pattern, negative values flipped), packed with ``k`` in the low 32 bits of an
int64 key, so one integer ``min`` reduction finds the lowest cost and, among equal costs, the
smallest ``k``. With 8-bit inputs every sum is an integer below 2**24, so the float32
arithmetic is exact (the same numbers integer arithmetic would give). That is why there is no
separate integer kernel: one float32 path is exact on 8-bit images *and* bit-identical to the
volume path on fractional ones (after mean removal, LoG, ...), and float32 vectors have as
many lanes as int32 ones; only int16 sums would be wider, at the price of a second kernel
(``benchmarks/speed_local.py`` compares it with StereoBM).

Outputs: the WTA disparity (float32, +inf where the best cost is ``cost_max``) and
``(H, W, 3)`` float32 "winner costs", the volume entries at ``k − 1, k, k + 1`` around the
winner ``k`` (``cost_max`` beyond ``[0, D)``): what sub-pixel refinement and the single
matching phase read.
"""

from __future__ import annotations

import numpy as np

from ...runtime import chunk_kernel, for_chunks, for_rows, njit
from .winners import _subpixel_offset

INF = np.float32(np.inf)


@njit(cache=True, inline="always")
def _key(c: np.float32, k: int) -> np.int64:
    # Order-preserving map float32 -> int32 (IEEE bits; negatives reversed), then k below it.
    # c + 0 turns a -0.0 into +0.0 so the two zeros tie as they do in a float comparison.
    b = np.int64(np.float32(c + np.float32(0.0)).view(np.int32))
    b = b ^ ((b >> 31) & 0x7FFFFFFF)
    return (b << 32) | k


# Performance notes. The loops over k must vectorise and the loop over x must stay cheap:
# * no array views (slices, ``col[x]``) are created per pixel: each one costs NRT reference
#   count updates (atomic operations) that dominated the kernel when it used them;
# * every index offset computed per pixel is wrapped in ``max(., 0)`` (a no-op here) so LLVM
#   can prove it non-negative and drop numba's negative-index wraparound, which otherwise
#   blocks unit-stride vector loads.


@njit(cache=True)
def _reversed_row(img: np.ndarray, y: int, min_disp: int, ndisp: int, out: np.ndarray) -> None:
    # out[c, u] = img[y, clamp(w - 1 - min_disp - u), c], u in [0, w + D - 1): the right pixel
    # of left x and hypothesis k is u = (w - 1 - x) + k, increasing in k (unit-stride loads).
    h, w, nc = img.shape
    for c in range(nc):
        for u in range(w + ndisp - 1):
            j = min(max(w - 1 - min_disp - u, 0), w - 1)
            out[c, u] = img[y, j, c]


@njit(cache=True)
def _valid_row(right_valid: np.ndarray, y: int, min_disp: int, ndisp: int, w: int, out: np.ndarray) -> None:
    # out[u] = 1 where hypothesis u = (w - 1 - x) + k has its right pixel inside the image (and
    # inside the right valid mask, if one is given: size 0 means none).
    has_mask = right_valid.shape[0] > 0
    for u in range(w + ndisp - 1):
        j = w - 1 - min_disp - u
        ok = 0 <= j < w
        if ok and has_mask:
            ok = right_valid[y, j]
        out[u] = 1 if ok else 0


@njit(cache=True, inline="always")
def _col_row(col, x, left, yy, fr, nd, trunc, sign):
    # col[x, k] += sign * min(sum_c |L_c - R_c|, trunc) for image row yy: the unfused kernel's
    # ``col += row`` (sign 1) / ``col -= old`` (sign -1), channels summed in the same order.
    nc = left.shape[2]
    x = max(x, 0)
    u0 = max(col.shape[0] - 2 - x, 0)  # w - 1 - x (col has w + 1 rows)
    if nc == 1:
        lv = left[yy, x, 0]
        if sign > 0:
            for k in range(nd):
                col[x, k] += min(abs(lv - fr[0, u0 + k]), trunc)
        else:
            for k in range(nd):
                col[x, k] -= min(abs(lv - fr[0, u0 + k]), trunc)
    elif nc == 3:
        l0 = left[yy, x, 0]
        l1 = left[yy, x, 1]
        l2 = left[yy, x, 2]
        for k in range(nd):
            s = np.float32(0.0) + abs(l0 - fr[0, u0 + k])
            s = s + abs(l1 - fr[1, u0 + k])
            s = s + abs(l2 - fr[2, u0 + k])
            if sign > 0:
                col[x, k] += min(s, trunc)
            else:
                col[x, k] -= min(s, trunc)
    else:
        for k in range(nd):
            s = np.float32(0.0)
            for c in range(nc):
                s += abs(left[yy, x, c] - fr[c, u0 + k])
            if sign > 0:
                col[x, k] += min(s, trunc)
            else:
                col[x, k] -= min(s, trunc)


@njit(cache=True, inline="always")
def _col_update(col, x, left, ya, yr, fa, fo, nd, trunc, add, sub):
    # Column x steps to the next row: ``col += row(ya) - old(yr)`` as the unfused kernel does
    # (``col += row`` / ``col -= old`` when only one of the two rows exists).
    nc = left.shape[2]
    x = max(x, 0)
    u0 = max(col.shape[0] - 2 - x, 0)
    if add and sub and nc == 1:
        la = left[ya, x, 0]
        lo = left[yr, x, 0]
        for k in range(nd):
            col[x, k] += min(abs(la - fa[0, u0 + k]), trunc) - min(abs(lo - fo[0, u0 + k]), trunc)
    elif add and sub and nc == 3:
        a0 = left[ya, x, 0]
        a1 = left[ya, x, 1]
        a2 = left[ya, x, 2]
        o0 = left[yr, x, 0]
        o1 = left[yr, x, 1]
        o2 = left[yr, x, 2]
        for k in range(nd):
            s = np.float32(0.0) + abs(a0 - fa[0, u0 + k])
            s = s + abs(a1 - fa[1, u0 + k])
            s = s + abs(a2 - fa[2, u0 + k])
            t = np.float32(0.0) + abs(o0 - fo[0, u0 + k])
            t = t + abs(o1 - fo[1, u0 + k])
            t = t + abs(o2 - fo[2, u0 + k])
            col[x, k] += min(s, trunc) - min(t, trunc)
    elif add and sub:
        for k in range(nd):
            s = np.float32(0.0)
            t = np.float32(0.0)
            for c in range(nc):
                s += abs(left[ya, x, c] - fa[c, u0 + k])
                t += abs(left[yr, x, c] - fo[c, u0 + k])
            col[x, k] += min(s, trunc) - min(t, trunc)
    elif add:
        _col_row(col, x, left, ya, fa, nd, trunc, 1)
    elif sub:
        _col_row(col, x, left, yr, fo, nd, trunc, -1)


@chunk_kernel
def _sad_wta_chunk(left, right, right_valid, min_disp: int, ndisp: int, radius_y: int, radius_x: int, truncate: float,
                   cost_max: float, band: int, keep_costs: bool, disp, wcost, chunk: int) -> None:
    """:func:`sad_wta` of the band of rows ``chunk`` (``band`` rows each), written into ``disp`` and ``wcost``."""
    h, w, nc = left.shape
    nd = ndisp
    trunc = np.float32(truncate)
    cmax = np.float32(cost_max)
    nu = w + nd - 1
    y0 = chunk * band
    y1 = min(h, y0 + band)
    if y0 >= y1:
        return
    col = np.zeros((w + 1, nd), np.float32)  # row w stays 0: the column "outside" the image
    acc = np.zeros(nd, np.float32)
    cbuf = np.empty(nd, np.float32)
    fa = np.empty((nc, nu), np.float32)
    fo = np.empty((nc, nu), np.float32)
    valid = np.empty(nu, np.uint8)
    invs = np.empty(w, np.float32)
    for yy in range(max(0, y0 - radius_y), min(h - 1, y0 + radius_y) + 1):
        _reversed_row(right, yy, min_disp, nd, fa)
        for x in range(w):
            _col_row(col, x, left, yy, fa, nd, trunc, 1)
    for y in range(y0, y1):
        ya = y + radius_y
        yr = y - radius_y - 1
        add = y > y0 and ya < h
        sub = y > y0 and yr >= 0
        if add:
            _reversed_row(right, ya, min_disp, nd, fa)
        if sub:
            _reversed_row(right, yr, min_disp, nd, fo)
        _valid_row(right_valid, y, min_disp, nd, w, valid)
        ny = min(h - 1, y + radius_y) - max(0, y - radius_y) + 1
        # Columns 0..rx form the first window: step them to this row first; the others
        # are stepped just before the running sum along x takes them in (still in cache).
        for x in range(min(radius_x, w - 1) + 1):
            _col_update(col, x, left, ya, yr, fa, fo, nd, trunc, add, sub)
        for k in range(nd):
            acc[k] = 0.0
        for x in range(min(radius_x, w - 1) + 1):
            for k in range(nd):
                acc[k] += col[x, k]
        for x in range(w):  # 1 / (channels · window pixels), the unfused kernel's factor
            nx = min(w - 1, x + radius_x) - max(0, x - radius_x) + 1
            invs[x] = np.float32(1.0 / (nx * ny * nc))
        for x in range(w):
            xa = x + radius_x + 1
            xo = x - radius_x
            if xa < w:
                _col_update(col, xa, left, ya, yr, fa, fo, nd, trunc, add, sub)
            inv = invs[x]
            u0 = max(w - 1 - x, 0)
            ia = max(xa if xa < w else w, 0)  # column entering the window (w: none)
            io = max(xo if xo >= 0 else w, 0)  # column leaving it
            best = np.int64(0x7FFFFFFFFFFFFFFF)
            for k in range(nd):
                # the volume entry: window mean, or cost_max when the right pixel is outside
                c = acc[k] * inv if valid[u0 + k] else cmax
                cbuf[k] = c
                best = min(best, _key(c, k))
                acc[k] += col[ia, k] - col[io, k]
            kb = max(np.int64(best & 0xFFFFFFFF), 0)
            bc = cbuf[kb]
            disp[y, x] = INF if bc >= cmax else np.float32(min_disp + kb)
            if keep_costs:
                wcost[y, x, 0] = cbuf[max(kb - 1, 0)] if kb > 0 else cmax
                wcost[y, x, 1] = bc
                wcost[y, x, 2] = cbuf[kb + 1] if kb < nd - 1 else cmax


def sad_wta(left: np.ndarray, right: np.ndarray, right_valid: np.ndarray, min_disp: int, ndisp: int,
            radius_y: int, radius_x: int, truncate: float, cost_max: float, nbands: int,
            keep_costs: bool = True):
    """Window mean of min(Σ_c |L_c − R_c|, truncate) + WTA in one pass, no volume.

    Parameters
    ----------
    left, right : (H, W, C) float32 images.
    right_valid : (H, W) bool mask of right pixels that may be matched, or a (0, 0) array.
    min_disp, ndisp : hypotheses ``d = min_disp + k``, ``k in [0, ndisp)``.
    radius_y, radius_x : window half sizes (the window is clipped at the image border).
    truncate : per-pixel truncation of the channel *sum* of |L − R| (``C·T`` for a mean
        truncated at T); the window sum is divided by ``C·n_pixels``.
    cost_max : cost of impossible hypotheses (right pixel outside the image or the mask).
    nbands : bands of rows run in parallel (same layout as ``window_cost_volume``).
    keep_costs : also return the winner costs (else a (0, 0, 3) array).

    Returns
    -------
    disparity : (H, W) float32 integer-valued, +inf where the best cost is ``cost_max``.
    winner_costs : (H, W, 3) float32 costs at k − 1, k, k + 1 of the winner k.
    """
    h, w = left.shape[0], left.shape[1]
    disp = np.empty((h, w), np.float32)
    wcost = np.empty((h if keep_costs else 0, w if keep_costs else 0, 3), np.float32)
    nbands = max(1, min(nbands, h))
    band = (h + nbands - 1) // nbands
    for_chunks(_sad_wta_chunk, nbands, left, right, right_valid, min_disp, ndisp, radius_y, radius_x, truncate,
               cost_max, band, keep_costs, disp, wcost)
    return disp, wcost


# --- sub-pixel refinement from the winner costs (the single matching phase's twin lives in
# stereocli.matching.refine_local) -------------------------------------------------------------


@chunk_kernel
def _subpixel_winner_rows(wdisp, wcosts, disp, min_disp: int, ndisp: int, equiangular: bool, left: bool, out,
                          missing, y0: int, y1: int) -> None:
    """:func:`subpixel_winner` of rows ``[y0, y1)``: refined values into ``out``, counts into ``missing[y]``."""
    w = disp.shape[1]
    for y in range(y0, y1):
        for x in range(w):
            d = disp[y, x]
            if not np.isfinite(d):
                continue
            k = int(d) - min_disp
            if k <= 0 or k >= ndisp - 1 or (left and x - (min_disp + k + 1) < 0):
                continue
            wd = wdisp[y, x]
            if not np.isfinite(wd) or int(wd) - min_disp != k:
                missing[y] += 1
                continue
            off = _subpixel_offset(wcosts[y, x, 0], wcosts[y, x, 1], wcosts[y, x, 2], equiangular)
            out[y, x] = np.float32(d + off)


def subpixel_winner(wdisp: np.ndarray, wcosts: np.ndarray, disp: np.ndarray, min_disp: int, ndisp: int,
                    equiangular: bool, left: bool = True):
    """:func:`~stereocli.matching.kernels.winners.subpixel_left` on the winner costs.

    Same rule (fit through the costs at k − 1, k, k + 1 with ``k = int(disp) − min_disp``, ends
    of the range and neighbours outside the image keep the integer). Returns ``(refined,
    missing)``; ``missing`` counts pixels whose ``k`` is not the WTA winner (left unchanged).
    ``left=False`` for a right-view map, whose neighbours outside the image are already
    marked in ``wcosts`` (both equal to the winner's cost, so the fit keeps the integer).
    """
    h = disp.shape[0]
    out = disp.copy()
    missing = np.zeros(h, np.int64)
    for_rows(_subpixel_winner_rows, h, wdisp, wcosts, disp, min_disp, ndisp, equiangular, left, out, missing)
    return out, int(missing.sum())
