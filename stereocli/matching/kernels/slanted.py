"""Compiled kernels of the ``slanted_patchmatch`` refinement: census codes on a horizontally
upsampled image, per-pixel plane fits to a disparity map, the slanted-window matching cost of
a plane and the red-black PatchMatch sweeps over per-pixel planes.

A plane is three float64 numbers ``(a, b, c)``: disparity ``d(x, y) = a·x + b·y + c`` in image
coordinates (pixels). The right image is read through an upsampled copy ``right_up`` whose
column ``j`` holds the right image at ``x = (j + 0.5) / up − 0.5`` (OpenCV's ``resize``
convention), so a left pixel ``x`` with disparity ``d`` matches column
``floor((x − d + 0.5) · up)``.
"""

from __future__ import annotations

import numpy as np

from ...runtime import chunk_kernel, for_rows, njit
from .census import _popcount64


@njit(cache=True, inline="always")
def _census_clamped(row, centre, code, off: int, mask, x0: int, x1: int) -> None:
    # Census bit ``mask`` of columns [x0, x1), whose neighbour x + off may lie outside the row:
    # read at the nearest end of the row.
    w = row.shape[0]
    for x in range(x0, x1):
        if row[min(max(x + off, 0), w - 1)] < centre[x]:
            code[x] |= mask


@chunk_kernel
def _census_codes_rows(image, half_h: int, half_w: int, step: int, out, y0: int, y1: int) -> None:
    """:func:`census_codes` of rows ``[y0, y1)``, written into ``out`` (zeros)."""
    h, w = image.shape
    for y in range(y0, y1):
        centre = image[y]
        code = out[y]
        bit = np.uint64(0)
        # One neighbour offset at a time over the whole row: the columns whose neighbour lies
        # inside the image read a shifted row (a loop that vectorises), the few others clamp.
        for dy in range(-half_h, half_h + 1):
            row = image[min(max(y + dy, 0), h - 1)]
            for dx in range(-half_w, half_w + 1):
                if dy == 0 and dx == 0:
                    continue
                off = dx * step
                inner_lo = min(max(-off, 0), w)
                inner_hi = max(min(w - off, w), inner_lo)
                mask = np.uint64(1) << bit
                _census_clamped(row, centre, code, off, mask, 0, inner_lo)
                # 1-D slices and an all-ones/zero mask: LLVM vectorises this form (not a shifted
                # comparison result or a branch).
                shifted = row[inner_lo + off:inner_hi + off]
                centres = centre[inner_lo:inner_hi]
                codes = code[inner_lo:inner_hi]
                for i in range(inner_hi - inner_lo):
                    codes[i] = codes[i] | (mask & (np.uint64(0) - np.uint64(shifted[i] < centres[i])))
                _census_clamped(row, centre, code, off, mask, inner_hi, w)
                bit += np.uint64(1)


def census_codes(image: np.ndarray, half_h: int, half_w: int, step: int) -> np.ndarray:
    """(H, W) uint64 census codes: bit set where the neighbour ``(dy, dx·step)`` is darker than
    the centre, for ``|dy| <= half_h``, ``|dx| <= half_w`` (centre skipped, borders clamped).

    ``step`` is the column spacing of one pixel: 1 on the left image, ``up`` on the right image
    upsampled ``up`` times along rows, so both codes compare the same neighbourhood."""
    out = np.zeros(image.shape, np.uint64)
    for_rows(_census_codes_rows, image.shape[0], image, int(half_h), int(half_w), int(step), out)
    return out


@chunk_kernel
def _fit_planes_rows(disp, guide, radius: int, weights, gate: float, band: float, pa, pb, pc, y0: int,
                     y1: int) -> None:
    """:func:`fit_planes` of rows ``[y0, y1)``, written into ``pa``, ``pb`` (zeros) and ``pc``."""
    h, w = disp.shape
    for y in range(y0, y1):
        for x in range(w):
            d0 = disp[y, x]
            pc[y, x] = d0
            if not np.isfinite(d0):
                continue
            g0 = guide[y, x]
            s0 = su = sv = suu = suv = svv = sd = sud = svd = 0.0
            for yy in range(max(0, y - radius), min(h, y + radius + 1)):
                v = float(yy - y)
                for xx in range(max(0, x - radius), min(w, x + radius + 1)):
                    dq = disp[yy, xx] - d0
                    if not abs(dq) <= gate:
                        continue
                    wq = weights[abs(guide[yy, xx] - g0)]
                    u = float(xx - x)
                    s0 += wq
                    su += wq * u
                    sv += wq * v
                    suu += wq * u * u
                    suv += wq * u * v
                    svv += wq * v * v
                    sd += wq * dq
                    sud += wq * u * dq
                    svd += wq * v * dq
            # Cramer's rule on [[suu suv su] [suv svv sv] [su sv s0]] (a b c)' = (sud svd sd)'.
            det = suu * (svv * s0 - sv * sv) - suv * (suv * s0 - sv * su) + su * (suv * sv - svv * su)
            if not det > 1e-6 * s0 * s0 * s0:
                continue
            a = (sud * (svv * s0 - sv * sv) - suv * (svd * s0 - sv * sd) + su * (svd * sv - svv * sd)) / det
            b = (suu * (svd * s0 - sv * sd) - sud * (suv * s0 - sv * su) + su * (suv * sd - svd * su)) / det
            c = (suu * (svv * sd - sv * svd) - suv * (suv * sd - sv * sud) + su * (suv * svd - svv * sud)) / det
            pa[y, x] = a
            pb[y, x] = b
            pc[y, x] = d0 + min(max(c, -band), band) - a * x - b * y


def fit_planes(disp: np.ndarray, guide: np.ndarray, radius: int, weights: np.ndarray, gate: float, band: float):
    """Each valid pixel's plane: weighted least squares through the neighbours within
    ``radius`` px whose disparity is within ``gate`` px of its own, weight
    ``weights[|guide_q − guide_p|]`` (``guide``: int grey levels).

    Returns (H, W) float64 ``a``, ``b``, ``c`` (``d = a·x + b·y + c``); a pixel whose
    neighbours do not fix a plane (a line of them, or too few) gets the fronto-parallel plane
    through its own disparity, and an invalid pixel ``a = b = 0``, ``c = +inf``. The plane's
    value at the pixel is clamped to within ``band`` px of its input disparity."""
    h, w = disp.shape
    pa = np.zeros((h, w), np.float64)
    pb = np.zeros((h, w), np.float64)
    pc = np.empty((h, w), np.float64)
    for_rows(_fit_planes_rows, h, disp, guide, int(radius), weights, float(gate), float(band), pa, pb, pc)
    return pa, pb, pc


@njit(cache=True, inline="always")
def plane_cost(y: int, x: int, a: float, b: float, c: float, codes_left, codes_right, guide, weights, prior,
               up: int, radius: int, stride: int, tau: float, lam: float, cap: float) -> float:
    """Slanted-window cost of plane ``(a, b, c)`` at pixel (y, x): over the window (every
    ``stride``-th pixel within ``radius``), the mean, weighted by ``weights[|Δguide|]``, of
    ``min(Hamming(census_left, census_right at x − d), tau) + lam·min(|d − prior|, cap)``
    where ``d`` is the plane's disparity at the window pixel (the prior term only where
    ``prior`` is finite; a match outside the right image costs ``tau``)."""
    h, w = codes_left.shape
    wu = codes_right.shape[1]
    g0 = guide[y, x]
    total = 0.0
    wsum = 0.0
    for yy in range(max(0, y - radius), min(h, y + radius + 1), stride):
        row_d = b * yy + c
        for xx in range(max(0, x - radius), min(w, x + radius + 1), stride):
            wq = weights[abs(guide[yy, xx] - g0)]
            d = a * xx + row_d
            j = int(np.floor((xx - d + 0.5) * up))
            if j < 0 or j >= wu:
                cq = tau
            else:
                cq = min(float(_popcount64(codes_left[yy, xx] ^ codes_right[yy, j])), tau)
            dp = prior[yy, xx]
            if lam > 0.0 and np.isfinite(dp):
                cq += lam * min(abs(d - dp), cap)
            total += wq * cq
            wsum += wq
    return total / wsum


@chunk_kernel
def _plane_costs_rows(pa, pb, pc, codes_left, codes_right, guide, weights, prior, up: int, radius: int, stride: int,
                      tau: float, lam: float, cap: float, out, y0: int, y1: int) -> None:
    """:func:`plane_costs` of rows ``[y0, y1)``, written into ``out`` (+inf)."""
    w = pa.shape[1]
    for y in range(y0, y1):
        for x in range(w):
            if np.isfinite(pc[y, x]):
                out[y, x] = plane_cost(y, x, pa[y, x], pb[y, x], pc[y, x], codes_left, codes_right, guide, weights,
                                       prior, up, radius, stride, tau, lam, cap)


def plane_costs(pa, pb, pc, codes_left, codes_right, guide, weights, prior, up: int, radius: int, stride: int,
                tau: float, lam: float, cap: float) -> np.ndarray:
    """(H, W) float64 :func:`plane_cost` of every pixel's own plane (+inf where ``pc`` is not finite)."""
    out = np.full(pa.shape, np.inf)
    for_rows(_plane_costs_rows, pa.shape[0], pa, pb, pc, codes_left, codes_right, guide, weights, prior, int(up),
             int(radius), int(stride), float(tau), float(lam), float(cap), out)
    return out


@njit(cache=True, inline="always")
def _uniform(seed: int, y: int, x: int, k: int) -> float:
    # splitmix64 of the pixel, iteration and draw: the same numbers on any thread count.
    z = np.uint64(seed) * np.uint64(0x9E3779B97F4A7C15) + np.uint64(y) * np.uint64(0xBF58476D1CE4E5B9) \
        + np.uint64(x) * np.uint64(0x94D049BB133111EB) + np.uint64(k) * np.uint64(0x2545F4914F6CDD1D)
    z = (z ^ (z >> np.uint64(30))) * np.uint64(0xBF58476D1CE4E5B9)
    z = (z ^ (z >> np.uint64(27))) * np.uint64(0x94D049BB133111EB)
    z = z ^ (z >> np.uint64(31))
    return float(z >> np.uint64(11)) * (1.0 / 9007199254740992.0)


NEIGHBOURS = np.array([[0, -1], [0, 1], [-1, 0], [1, 0]], np.int64)


@chunk_kernel
def _sweep_rows(pa, pb, pc, cost, changed, only_changed: bool, parity: int, seed: int, shift: float, slope: float,
                samples: int, band: float, same_plane: float, lo: float, hi: float, codes_left, codes_right, guide,
                weights, prior, up: int, radius: int, stride: int, tau: float, lam: float, cap: float, y0: int,
                y1: int) -> None:
    """:func:`sweep` of rows ``[y0, y1)``."""
    h, w = pa.shape
    for y in range(y0, y1):
        for x in range((y + parity) % 2, w, 2):
            if not np.isfinite(pc[y, x]):
                continue
            d0 = prior[y, x]
            ba, bb, bc, best = pa[y, x], pb[y, x], pc[y, x], cost[y, x]
            for n in range(4):
                yy = y + NEIGHBOURS[n, 0]
                xx = x + NEIGHBOURS[n, 1]
                if yy < 0 or yy >= h or xx < 0 or xx >= w:
                    continue
                if only_changed and not changed[yy, xx]:
                    continue
                a, b, c = pa[yy, xx], pb[yy, xx], pc[yy, xx]
                if not np.isfinite(c):
                    continue
                d = a * x + b * y + c
                if d < lo or d > hi or abs(d - d0) > band:
                    continue
                # The largest difference between the two planes over the window (at a corner);
                # an identical plane (0) is skipped at any same_plane.
                if abs(d - (ba * x + bb * y + bc)) + radius * (abs(a - ba) + abs(b - bb)) <= same_plane:
                    continue
                cc = plane_cost(y, x, a, b, c, codes_left, codes_right, guide, weights, prior, up, radius, stride,
                                tau, lam, cap)
                if cc < best:
                    ba, bb, bc, best = a, b, c, cc
            for k in range(samples):
                d = ba * x + bb * y + bc + (2.0 * _uniform(seed, y, x, 3 * k) - 1.0) * shift
                a = ba + (2.0 * _uniform(seed, y, x, 3 * k + 1) - 1.0) * slope
                b = bb + (2.0 * _uniform(seed, y, x, 3 * k + 2) - 1.0) * slope
                if d < lo or d > hi or abs(d - d0) > band:
                    continue
                c = d - a * x - b * y
                cc = plane_cost(y, x, a, b, c, codes_left, codes_right, guide, weights, prior, up, radius, stride,
                                tau, lam, cap)
                if cc < best:
                    ba, bb, bc, best = a, b, c, cc
            changed[y, x] = ba != pa[y, x] or bb != pb[y, x] or bc != pc[y, x]
            pa[y, x], pb[y, x], pc[y, x], cost[y, x] = ba, bb, bc, best


def sweep(pa, pb, pc, cost, changed, only_changed: bool, parity: int, seed: int, shift: float, slope: float,
          samples: int, band: float, same_plane: float, lo: float, hi: float, codes_left, codes_right, guide, weights,
          prior, up: int, radius: int, stride: int, tau: float, lam: float, cap: float) -> None:
    """One half-iteration of red-black PatchMatch, in place: every pixel with
    ``(x + y) % 2 == parity`` tries its four neighbours' planes (which have the other parity,
    so no pixel reads a plane written in the same sweep and the result does not depend on the
    thread count), then ``samples`` random perturbations of its best plane (disparity at the
    pixel ±``shift``, slopes ±``slope``), and keeps the cheapest. A plane is only tried when
    its disparity at the pixel lies in ``[lo, hi]`` and within ``band`` px of ``prior``, and a
    neighbour's plane only when it departs from the pixel's best so far by more than
    ``same_plane`` px somewhere in the window.

    ``changed`` (H, W) bool records whether each pixel's plane changed in its last sweep. With
    ``only_changed`` (every sweep after a pixel's first) a neighbour's plane is tried only if
    it changed in the neighbour's last sweep: an unchanged one is the plane the pixel tried last
    time, whose cost has not changed and did not beat the pixel's plane then (the plane a pixel
    keeps only gets cheaper), so the result is the same as trying it again."""
    for_rows(_sweep_rows, pa.shape[0], pa, pb, pc, cost, changed, bool(only_changed), int(parity), int(seed),
             float(shift), float(slope), int(samples), float(band), float(same_plane), float(lo), float(hi), codes_left,
             codes_right, guide, weights, prior, int(up), int(radius), int(stride), float(tau), float(lam), float(cap))


@chunk_kernel
def _plane_disparity_rows(pa, pb, pc, out, y0: int, y1: int) -> None:
    """:func:`plane_disparity` of rows ``[y0, y1)``, written into ``out``."""
    w = pa.shape[1]
    for y in range(y0, y1):
        for x in range(w):
            out[y, x] = pa[y, x] * x + pb[y, x] * y + pc[y, x]


def plane_disparity(pa, pb, pc) -> np.ndarray:
    """(H, W) float32 disparity of every pixel's own plane at the pixel (+inf where ``pc`` is)."""
    out = np.empty(pa.shape, np.float32)
    for_rows(_plane_disparity_rows, pa.shape[0], pa, pb, pc, out)
    return out
