"""Compiled kernels of the refinement stages: uniqueness, confidence, hole classification and
interpolation, median and joint bilateral filters, and the line fits of ``plane_smooth``, on
(H, W) float32 disparity maps (+inf invalid).

Cost volumes may be float32 or uint16 (SGM sums); values are read as float64.
"""

from __future__ import annotations

import numpy as np

from ...runtime import chunk_kernel, for_chunks, for_rows, njit, side_by_side
from .aggregation import channel_planes

INF = np.float32(np.inf)

# 8 directions (dy, dx) searched for valid neighbours when interpolating holes.
DIRECTIONS8 = np.array([[0, 1], [0, -1], [1, 0], [-1, 0], [1, 1], [1, -1], [-1, 1], [-1, -1]], np.int64)


@njit(cache=True, inline="always")
def _valid_range(x: int, w: int, nd: int, min_disp: int):
    # Hypotheses k whose right pixel x - (min_disp + k) lies inside the image.
    return max(0, x - min_disp - (w - 1)), min(nd - 1, x - min_disp)


@njit(cache=True, inline="always")
def _insert_sorted(buf, n: int, v) -> int:
    # Insert v into the sorted buf[:n] (insertion sort step); returns the new length.
    j = n
    while j > 0 and buf[j - 1] > v:
        buf[j] = buf[j - 1]
        j -= 1
    buf[j] = v
    return n + 1


@njit(cache=True, inline="always")
def _sorted_median(buf, n: int):
    # Median of the sorted buf[:n] (mean of the two middle values for even n), float32.
    if n % 2 == 1:
        return buf[n // 2]
    return np.float32(0.5 * (buf[n // 2 - 1] + buf[n // 2]))


@njit(cache=True, inline="always")
def _range_min(row, k0: int, k1: int) -> float:
    # Smallest of row[k0..k1] as float64 (+inf for an empty range); the loop runs in the
    # row's own dtype so it vectorises.
    if k1 < k0:
        return np.inf
    best = row[k0]
    for k in range(k0 + 1, k1 + 1):
        best = min(best, row[k])
    return np.float64(best)


@njit(cache=True, inline="always")
def _first_min(row, k0: int, k1: int) -> int:
    # Index of the smallest of row[k0..k1], the first one on ties.
    best = row[k0]
    for k in range(k0 + 1, k1 + 1):
        best = min(best, row[k])
    for k in range(k0, k1 + 1):
        if row[k] == best:
            return k
    return k0


@chunk_kernel
def _uniqueness_rows(cost, disp, min_disp: int, ratio: float, out, y0: int, y1: int) -> None:
    """:func:`uniqueness` on rows ``y0`` to ``y1`` (exclusive) of ``out``."""
    _, w, nd = cost.shape
    keep = 1.0 - ratio
    for y in range(y0, y1):
        for x in range(w):
            if not np.isfinite(disp[y, x]):
                continue
            k0, k1 = _valid_range(x, w, nd, min_disp)
            if k1 < k0:
                continue
            row = cost[y, x]
            bk = _first_min(row, k0, k1)
            bc = np.float64(row[bk])
            second = min(_range_min(row, k0, bk - 2), _range_min(row, bk + 2, k1))
            if second * keep < bc:
                out[y, x] = INF


def uniqueness(cost, disp, min_disp: int, ratio: float) -> np.ndarray:
    """Invalidate pixels whose best cost is not clearly below every non-adjacent hypothesis.

    OpenCV's rule: reject when some ``d`` with ``|d − d_best| > 1`` has
    ``cost[d] · (1 − ratio) < cost_best``. ``d_best`` is the volume's own minimum (the
    stage may run after sub-pixel refinement). Returns a new float32 map.
    """
    out = disp.copy()
    for_rows(_uniqueness_rows, cost.shape[0], cost, disp, min_disp, ratio, out)
    return out


@chunk_kernel
def _uniqueness_from_second_rows(best, second, disp, ratio: float, out, y0: int, y1: int) -> None:
    """:func:`uniqueness_from_second` on rows ``y0`` to ``y1`` (exclusive) of ``out``."""
    w = disp.shape[1]
    keep = 1.0 - ratio
    for y in range(y0, y1):
        for x in range(w):
            if np.isfinite(disp[y, x]) and np.float64(second[y, x]) * keep < np.float64(best[y, x]):
                out[y, x] = INF


def uniqueness_from_second(best, second, disp, ratio: float) -> np.ndarray:
    """:func:`uniqueness` from each pixel's winning cost and its best cost beyond ±1 ((H, W)
    float32 each, +inf where there is none)."""
    out = disp.copy()
    for_rows(_uniqueness_from_second_rows, disp.shape[0], best, second, disp, ratio, out)
    return out


@njit(cache=True, inline="always")
def _confidence_value(bc: float, sc: float, d: float, x: int, y: int, disp_right, has_right: bool,
                      lr_scale: float, margin_scale: float) -> float:
    # min(1, u / margin_scale) · exp(−|d_L − d_R(x − d_L)| / lr_scale), u = 1 − c_best / c_second.
    u = 1.0 if not np.isfinite(sc) or sc <= 0 else max(0.0, 1.0 - bc / sc)
    c = min(1.0, u / margin_scale)
    if has_right:
        xr = int(np.floor(x - d + 0.5))
        if xr < 0 or xr >= disp_right.shape[1] or not np.isfinite(disp_right[y, xr]):
            return 0.0
        c *= np.exp(-abs(d - disp_right[y, xr]) / lr_scale)
    return c


@chunk_kernel
def _confidence_from_second_rows(best, second, disp, disp_right, has_right: bool, lr_scale: float,
                                 margin_scale: float, conf, y0: int, y1: int) -> None:
    """:func:`confidence_from_second` on rows ``y0`` to ``y1`` (exclusive) of ``conf``."""
    w = disp.shape[1]
    for y in range(y0, y1):
        for x in range(w):
            d = disp[y, x]
            if np.isfinite(d):
                conf[y, x] = np.float32(_confidence_value(np.float64(best[y, x]), np.float64(second[y, x]), d, x, y,
                                                          disp_right, has_right, lr_scale, margin_scale))


def confidence_from_second(best, second, disp, disp_right, lr_scale: float, margin_scale: float) -> np.ndarray:
    """:func:`confidence` from each pixel's winning cost and its best cost beyond ±1 ((H, W)
    float32 each, +inf where there is none)."""
    h, w = disp.shape
    conf = np.zeros((h, w), np.float32)
    has_right = disp_right.shape[0] == h and disp_right.shape[1] == w
    for_rows(_confidence_from_second_rows, h, best, second, disp, disp_right, has_right, lr_scale, margin_scale,
             conf)
    return conf


@chunk_kernel
def _confidence_rows(cost, disp, disp_right, has_right: bool, min_disp: int, lr_scale: float, margin_scale: float,
                     conf, y0: int, y1: int) -> None:
    """:func:`confidence` on rows ``y0`` to ``y1`` (exclusive) of ``conf``."""
    _, w, nd = cost.shape
    for y in range(y0, y1):
        for x in range(w):
            d = disp[y, x]
            if not np.isfinite(d):
                continue
            k0, k1 = _valid_range(x, w, nd, min_disp)
            if k1 < k0:
                continue
            row = cost[y, x]
            bk = _first_min(row, k0, k1)
            bc = np.float64(row[bk])
            sc = min(_range_min(row, k0, bk - 2), _range_min(row, bk + 2, k1))
            conf[y, x] = np.float32(_confidence_value(bc, sc, d, x, y, disp_right, has_right, lr_scale, margin_scale))


def confidence(cost, disp, disp_right, min_disp: int, lr_scale: float, margin_scale: float) -> np.ndarray:
    """Per-pixel confidence in [0, 1]: cost uniqueness × left-right agreement.

    Uniqueness ``u = 1 − c_best / c_second`` (``c_second``: best hypothesis with
    ``|d − d_best| > 1``, the "PKRN" ratio), mapped as ``min(1, u / margin_scale)``. LR term
    ``exp(−|d_L − d_R(x − d_L)| / lr_scale)`` when ``disp_right`` is given (size > 0), else 1.
    Invalid pixels get 0.
    """
    h, w, _ = cost.shape
    conf = np.zeros((h, w), np.float32)
    has_right = disp_right.shape[0] == h and disp_right.shape[1] == w
    for_rows(_confidence_rows, h, cost, disp, disp_right, has_right, min_disp, lr_scale, margin_scale, conf)
    return conf


@chunk_kernel
def _classify_holes_rows(disp, disp_right, has_right: bool, min_disp: int, max_disp: int, tol: float, label,
                         y0: int, y1: int) -> None:
    """:func:`classify_holes` on rows ``y0`` to ``y1`` (exclusive) of ``label``."""
    w = disp.shape[1]
    claimed = np.empty(w, np.bool_)
    for y in range(y0, y1):
        # Scatter from the right view instead of searching every d for every hole: right
        # pixel xr with disparity v claims x = xr + d for each integer d in [v − tol, v + tol]
        # inside the range — the same set of (x, d) pairs, O(W·tol) per row.
        for x in range(w):
            claimed[x] = False
        if has_right:
            for xr in range(w):
                v = disp_right[y, xr]
                if not np.isfinite(v):
                    continue
                lo = max(min_disp, int(np.ceil(v - tol)))
                hi = min(max_disp, int(np.floor(v + tol)))
                for d in range(lo, hi + 1):
                    x = xr + d
                    if 0 <= x < w:
                        claimed[x] = True
        for x in range(w):
            if not np.isfinite(disp[y, x]):
                label[y, x] = 2 if claimed[x] else 1


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
    for_rows(_classify_holes_rows, h, disp, disp_right, has_right, min_disp, max_disp, tol, label)
    return label


@njit(cache=True)
def _nearest_along(disp, dy: int, dx: int, value, dist) -> None:
    # value[y, x] / dist[y, x]: the first finite disparity met walking from (y, x) in steps of
    # (dy, dx), and the number of steps (0 = none found). One sweep in the order where the
    # neighbour (y + dy, x + dx) is already done: O(H·W) instead of a walk per hole.
    h, w = disp.shape
    for i in range(h):
        y = h - 1 - i if dy > 0 else i
        for j in range(w):
            x = w - 1 - j if dx > 0 else j
            yy = y + dy
            xx = x + dx
            if yy < 0 or yy >= h or xx < 0 or xx >= w:
                dist[y, x] = 0
            elif np.isfinite(disp[yy, xx]):
                value[y, x] = disp[yy, xx]
                dist[y, x] = 1
            elif dist[yy, xx] > 0:
                value[y, x] = value[yy, xx]
                dist[y, x] = dist[yy, xx] + 1
            else:
                dist[y, x] = 0


@chunk_kernel
def _nearest_all_chunk(disp, value, dist, k: int) -> None:
    """The nearest valid values along direction ``k`` of :data:`DIRECTIONS8`."""
    _nearest_along(disp, DIRECTIONS8[k, 0], DIRECTIONS8[k, 1], value[k], dist[k])


@chunk_kernel
def _fill_from_nearest_rows(disp, label, value, dist, limit: int, out, y0: int, y1: int) -> None:
    """:func:`interpolate_holes` on rows ``y0`` to ``y1`` (exclusive) of ``out``."""
    w = disp.shape[1]
    buf = np.empty(8, np.float32)
    for y in range(y0, y1):
        for x in range(w):
            lab = label[y, x]
            if lab == 0:
                continue
            n = 0
            for k in range(8):
                steps = dist[k, y, x]
                if steps > 0 and steps <= limit:
                    n = _insert_sorted(buf, n, value[k, y, x])
            if n == 0:
                continue
            if lab == 1:
                out[y, x] = buf[1] if n > 1 else buf[0]
            else:
                out[y, x] = _sorted_median(buf, n)


def interpolate_holes(disp: np.ndarray, label: np.ndarray, max_dist: int) -> np.ndarray:
    """Fill holes from the nearest valid values along 8 directions (Hirschmüller 2008 §2.5).

    Occluded holes (label 1) take the second-lowest found value (background, robust to one
    outlier); mismatched ones (label 2) the median. Directions without a valid value within
    ``max_dist`` px (0 = unlimited) are ignored; holes with nothing found stay invalid.
    """
    disp = np.ascontiguousarray(disp, dtype=np.float32)
    h, w = disp.shape
    value = np.empty((8, h, w), np.float32)
    dist = np.empty((8, h, w), np.int32)
    for_chunks(_nearest_all_chunk, 8, disp, value, dist)
    limit = max(h, w) if max_dist <= 0 else max_dist
    out = disp.copy()
    for_rows(_fill_from_nearest_rows, h, disp, label, value, dist, int(limit), out)
    return out


@njit(cache=True, inline="always")
def _median_of_finite_window(disp, y: int, x: int, radius: int, buf):
    # Median of the finite values of the (2r+1)² window at (y, x) clipped to the image
    # (insertion sort into buf); the mean of the two middle values for an even count.
    h, w = disp.shape
    n = 0
    for yy in range(max(0, y - radius), min(h, y + radius + 1)):
        for xx in range(max(0, x - radius), min(w, x + radius + 1)):
            v = disp[yy, xx]
            if np.isfinite(v):
                n = _insert_sorted(buf, n, v)
    return _sorted_median(buf, n)


@chunk_kernel
def _median_valid_where_rows(disp, radius: int, todo, out, y0: int, y1: int) -> None:
    """:func:`_median_valid_where` on rows ``y0`` to ``y1`` (exclusive)."""
    w = disp.shape[1]
    buf = np.empty((2 * radius + 1) ** 2, np.float32)
    for y in range(y0, y1):
        for x in range(w):
            if todo[y, x] and np.isfinite(disp[y, x]):
                out[y, x] = _median_of_finite_window(disp, y, x, radius, buf)


@chunk_kernel
def _median_valid_frame_rows(disp, radius: int, out, y0: int, y1: int) -> None:
    """The general median at the finite pixels within ``radius`` of the image border, rows
    ``y0`` to ``y1`` (exclusive): whole rows at the top and bottom, ``radius`` columns at
    each side of the others."""
    h, w = disp.shape
    buf = np.empty((2 * radius + 1) ** 2, np.float32)
    for y in range(y0, y1):
        whole_row = y < radius or y >= h - radius
        left_end = w if whole_row else min(radius, w)  # columns [0, left_end) ...
        right_start = w if whole_row else max(radius, w - radius)  # ... and [right_start, w)
        for x in range(left_end):
            if np.isfinite(disp[y, x]):
                out[y, x] = _median_of_finite_window(disp, y, x, radius, buf)
        for x in range(right_start, w):
            if np.isfinite(disp[y, x]):
                out[y, x] = _median_of_finite_window(disp, y, x, radius, buf)


def _median_valid_where(disp: np.ndarray, radius: int, todo: np.ndarray, out: np.ndarray) -> None:
    # General case at the pixels flagged in ``todo``: median of the finite values of the
    # window clipped to the image; invalid centres stay invalid.
    for_rows(_median_valid_where_rows, disp.shape[0], disp, radius, todo, out)


def median_valid(disp: np.ndarray, radius: int) -> np.ndarray:
    """Median over the finite values of a (2r+1)² window clipped to the image; invalid
    centres stay invalid (reference: ``tests/test_refine_sgm.py``). Returns a new map.

    Windows that are whole and all finite (most of them) take OpenCV's vectorised
    ``medianBlur`` (float32 supports 3×3 and 5×5; two row bands side by side, as it runs on
    one thread); the rest — near holes and the border — the general kernels. Same values
    either way.
    """
    disp = np.ascontiguousarray(disp, dtype=np.float32)
    h, w = disp.shape
    size = 2 * radius + 1
    if radius < 1 or radius > 2 or h < size or w < size:
        out = disp.copy()
        _median_valid_where(disp, radius, np.ones((h, w), np.bool_), out)
        return out
    out = _median_blur(disp, size)
    invalid = ~np.isfinite(disp)
    if invalid.any():
        import cv2

        out[invalid] = np.inf
        todo = cv2.dilate(invalid.view(np.uint8), np.ones((size, size), np.uint8)).view(np.bool_)
        _median_valid_where(disp, radius, todo, out)
    for_rows(_median_valid_frame_rows, h, disp, radius, out)
    return out


def _median_blur(disp: np.ndarray, size: int) -> np.ndarray:
    """``cv2.medianBlur(disp, size)``, the top and bottom halves side by side (each with the
    rows of context its windows read; the same values)."""
    import cv2

    h = disp.shape[0]
    radius = size // 2
    middle = h // 2
    if h < 8 * size:
        return cv2.medianBlur(disp, size)
    top, bottom = side_by_side(lambda: cv2.medianBlur(disp[:middle + radius], size),
                               lambda: cv2.medianBlur(disp[middle - radius:], size))
    return np.concatenate([top[:middle], bottom[radius:]])


@chunk_kernel
def _joint_bilateral_rows(disp, guide, radius: int, sigma_space: float, sigma_color: float, out,
                          y0: int, y1: int) -> None:
    """:func:`joint_bilateral` on rows ``y0`` to ``y1`` (exclusive) of ``out``."""
    h, w = disp.shape
    ks = -0.5 / (sigma_space * sigma_space)
    kc = -0.5 / (sigma_color * sigma_color)
    for y in range(y0, y1):
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


def joint_bilateral(disp, guide, radius: int, sigma_space: float, sigma_color: float) -> np.ndarray:
    """Edge-preserving smoothing of valid disparities, weights from the (grey) guide image:
    ``exp(−r²/2σs² − ΔI²/2σc²)`` over finite neighbours; invalid centres stay invalid."""
    out = disp.copy()
    for_rows(_joint_bilateral_rows, disp.shape[0], disp, guide, radius, sigma_space, sigma_color, out)
    return out


@chunk_kernel
def _line_fit_pass_rows(disp, image, radius: int, step: int, vertical: bool, sigma_space: float, color_range: float,
                        gate: float, out, y0: int, y1: int) -> None:
    """:func:`_line_fit_pass` on rows ``y0`` to ``y1`` (exclusive) of ``out``."""
    h, w = disp.shape
    nc = image.shape[0]
    inv_range2 = np.float32(1.0 / (color_range * color_range))
    step_y = 1 if vertical else 0
    step_x = 1 - step_y
    # Row buffers allocated once per range of rows, not once per row.
    s = np.empty(w, np.float32)
    st = np.empty(w, np.float32)
    stt = np.empty(w, np.float32)
    sv = np.empty(w, np.float32)
    stv = np.empty(w, np.float32)
    dist2 = np.empty(w, np.float32)
    for y in range(y0, y1):
        # Weighted moments about each pixel of the row (t = offset along the line), values
        # relative to the pixel's own disparity so the sums stay well conditioned.
        for x in range(w):
            s[x] = 0.0
            st[x] = 0.0
            stt[x] = 0.0
            sv[x] = 0.0
            stv[x] = 0.0
        d0 = disp[y]
        for t in range(-(radius // step) * step, radius + 1, step):
            yy = y + t * step_y
            dx = t * step_x
            if yy < 0 or yy >= h:
                continue
            ws = np.float32(np.exp(-0.5 * t * t / (sigma_space * sigma_space)))
            tf = np.float32(t)
            nb = disp[yy]
            x0 = max(0, -dx)
            x1 = min(w, w - dx)
            n = x1 - x0
            # Row slices aligned so that element i is pixel x0 + i and its neighbour: loops over
            # range(n) index with non-negative ints, so numba drops its negative-index
            # wrap-around and LLVM vectorises them (indexing with x + dx does not).
            centre_d = d0[x0:x1]
            other_d = nb[x0 + dx:x1 + dx]
            centre_g = image[0, y, x0:x1]
            other_g = image[0, yy, x0 + dx:x1 + dx]
            d2 = dist2[x0:x1]
            if nc > 1:  # colour: squared distances summed channel by channel (x inside)
                d2[:] = 0.0
                for c in range(nc):
                    centre = image[c, y, x0:x1]
                    other = image[c, yy, x0 + dx:x1 + dx]
                    for i in range(n):
                        q = other[i] - centre[i]
                        d2[i] += q * q
            s_, st_, stt_, sv_, stv_ = s[x0:x1], st[x0:x1], stt[x0:x1], sv[x0:x1], stv[x0:x1]
            for i in range(n):
                v = other_d[i] - centre_d[i]
                near = abs(v) <= gate  # False for another surface, or an inf neighbour
                # Grey guides take the distance here (one pass per offset, not two).
                q = other_g[i] - centre_g[i]
                q2 = q * q if nc == 1 else d2[i]
                # Tukey's biweight of the colour distance (arithmetic only, unlike exp).
                cw = max(np.float32(0.0), np.float32(1.0) - q2 * inv_range2)
                wt = ws * cw * cw if near else np.float32(0.0)
                v = v if near else np.float32(0.0)
                s_[i] += wt
                st_[i] += wt * tf
                stt_[i] += wt * tf * tf
                sv_[i] += wt * v
                stv_[i] += wt * tf * v
        for x in range(w):
            if not np.isfinite(d0[x]):
                out[y, x] = d0[x]
                continue
            # Least-squares line v = a·t + c; its value at t = 0 is c. The weighted mean where
            # the neighbours sit on one side only or are too few to fix a slope. The correction
            # is kept within the gate: a one-sided fit must not extrapolate a pixel away.
            det = s[x] * stt[x] - st[x] * st[x]
            if det > 1e-4 * s[x] * s[x]:
                corr = (stt[x] * sv[x] - st[x] * stv[x]) / det
            else:
                corr = sv[x] / s[x]
            out[y, x] = d0[x] + min(max(corr, -gate), gate)


def _line_fit_pass(disp, image, radius: int, step: int, vertical: bool, sigma_space: float, color_range: float,
                   gate: float) -> np.ndarray:
    # One 1-D pass of plane_smooth, along rows (vertical=False) or columns. Loops run over
    # whole rows for each offset t so they vectorise.
    out = np.empty(disp.shape, disp.dtype)
    for_rows(_line_fit_pass_rows, disp.shape[0], disp, image, radius, step, vertical, sigma_space, color_range, gate,
             out)
    return out


def plane_smooth(disp: np.ndarray, image: np.ndarray, radius: int, sigma_space: float, color_range: float,
                 gate: float, step: int = 1) -> np.ndarray:
    """Edge-aware sub-pixel smoothing by local weighted line fits, along rows then columns.

    Each valid pixel takes the value at its own position of the least-squares line through
    its neighbours on the row (then, on that result, the column) within ``radius`` px whose
    disparity is within ``gate`` px of its own (so a fit never mixes two surfaces across a
    depth edge), weighted by ``exp(−t²/2σs²)·max(0, 1 − ‖ΔI‖²/R²)²`` with ‖ΔI‖ the Euclidean
    colour distance in ``image`` ((H, W, C) float32, grey levels) and R = ``color_range``
    (Tukey's biweight: close to a Gaussian of σ = R/2 near 0, exactly 0 beyond R). Each pass
    moves a pixel by at most ``gate``. Two 1-D fits follow a slanted plane like one 2-D fit at
    a fraction of its cost; on a fronto-parallel surface the result is the gated,
    colour-weighted mean. ``step`` > 1 fits through every step-th neighbour only (offsets that
    are multiples of it; the pixel itself is one). ``disp`` (H, W) float32 px, +inf invalid
    (stays so).
    """
    planes = channel_planes(image)
    out = _line_fit_pass(disp, planes, radius, step, False, sigma_space, color_range, gate)
    return _line_fit_pass(out, planes, radius, step, True, sigma_space, color_range, gate)


@njit(cache=True, inline="always")
def _resolve_row(disp, out, y, claims, min_disp, ndisp, owner, owner_cost):
    # One left→right pass over row y; claims[x] is the cost of left x at round(disp[y, x]).
    w = disp.shape[1]
    for xr in range(w):
        owner[xr] = -1
    for x in range(w):
        d = disp[y, x]
        if not np.isfinite(d):
            continue
        di = int(np.floor(d + 0.5))
        k = di - min_disp
        xr = x - di
        if xr < 0 or xr >= w or k < 0 or k >= ndisp:
            out[y, x] = INF
            continue
        c = claims[x]
        o = owner[xr]
        if o < 0:
            owner[xr] = x
            owner_cost[xr] = c
        elif c < owner_cost[xr]:
            out[y, o] = INF  # the earlier claim loses: a collision exposes a wrong match
            owner[xr] = x
            owner_cost[xr] = c
        else:
            out[y, x] = INF


@chunk_kernel
def _single_matching_phase_rows(disp, cost, min_disp: int, out, y0: int, y1: int) -> None:
    """:func:`single_matching_phase_kernel` on rows ``y0`` to ``y1`` (exclusive) of ``out``."""
    w = disp.shape[1]
    nd = cost.shape[2]
    owner = np.empty(w, np.int64)
    owner_cost = np.empty(w, np.float32)
    claims = np.empty(w, np.float32)
    for y in range(y0, y1):
        for x in range(w):
            claims[x] = 0.0
            d = disp[y, x]
            if np.isfinite(d):
                k = int(np.floor(d + 0.5)) - min_disp
                if 0 <= k < nd:
                    claims[x] = cost[y, x, k]
        _resolve_row(disp, out, y, claims, min_disp, nd, owner, owner_cost)


def single_matching_phase_kernel(disp: np.ndarray, cost: np.ndarray, min_disp: int) -> np.ndarray:
    """One left→right pass per row; when two left pixels claim the same right pixel, the one
    with the lower cost keeps it and the other becomes +inf (Di Stefano, Marchionni &
    Mattoccia, IVC 2004, §3). ``disp`` holds integer-valued float32 disparities (+inf invalid);
    ``cost`` is the (H, W, D) volume (float32 or uint16).
    """
    out = disp.copy()
    for_rows(_single_matching_phase_rows, disp.shape[0], disp, cost, min_disp, out)
    return out


@chunk_kernel
def _single_matching_phase_winner_rows(disp, wdisp, wcosts, min_disp: int, ndisp: int, out, missing,
                                       y0: int, y1: int) -> None:
    """:func:`single_matching_phase_winner_kernel` on rows ``y0`` to ``y1`` (exclusive) of ``out``
    and ``missing``."""
    w = disp.shape[1]
    owner = np.empty(w, np.int64)
    owner_cost = np.empty(w, np.float32)
    claims = np.empty(w, np.float32)
    for y in range(y0, y1):
        for x in range(w):
            claims[x] = 0.0
            d = disp[y, x]
            if np.isfinite(d):
                k = int(np.floor(d + 0.5)) - min_disp
                if 0 <= k < ndisp:
                    j = k - (int(wdisp[y, x]) - min_disp) if np.isfinite(wdisp[y, x]) else 2
                    if -1 <= j <= 1:
                        claims[x] = wcosts[y, x, j + 1]
                    else:
                        missing[y] += 1
        _resolve_row(disp, out, y, claims, min_disp, ndisp, owner, owner_cost)


def single_matching_phase_winner_kernel(disp: np.ndarray, wdisp: np.ndarray, wcosts: np.ndarray,
                                        min_disp: int, ndisp: int):
    """:func:`single_matching_phase_kernel` with the claim costs read from the costs kept around
    each WTA winner (fused cost + WTA path, :class:`~stereocli.matching.state.WinnerCosts`).

    Returns ``(out, missing)``; ``missing`` counts pixels whose ``round(disp)`` is more than 1
    from the winner ``wdisp`` (none right after WTA or sub-pixel refinement).
    """
    h = disp.shape[0]
    out = disp.copy()
    missing = np.zeros(h, np.int64)
    for_rows(_single_matching_phase_winner_rows, h, disp, wdisp, wcosts, min_disp, ndisp, out, missing)
    return out, int(missing.sum())


@chunk_kernel
def _weighted_median_at_rows(disp, todo, guide, radius: int, sigma_s: float, sigma_c: float, out,
                             y0: int, y1: int) -> None:
    """:func:`weighted_median_at` on rows ``y0`` to ``y1`` (exclusive) of ``out``."""
    h, w = disp.shape
    nc = guide.shape[2]
    n = (2 * radius + 1) ** 2
    inv_s = 1.0 / (sigma_s * sigma_s)
    inv_c = 1.0 / (sigma_c * sigma_c)
    vals = np.empty(n, np.float32)
    wts = np.empty(n, np.float64)
    for y in range(y0, y1):
        for x in range(w):
            if not todo[y, x]:
                continue
            m = 0
            total = 0.0
            for qy in range(max(0, y - radius), min(h, y + radius + 1)):
                for qx in range(max(0, x - radius), min(w, x + radius + 1)):
                    v = disp[qy, qx]
                    if not np.isfinite(v):
                        continue
                    dc = 0.0
                    for c in range(nc):
                        t = guide[y, x, c] - guide[qy, qx, c]
                        dc += t * t
                    wt = np.exp(-((qy - y) ** 2 + (qx - x) ** 2) * inv_s - dc * inv_c)
                    vals[m] = v
                    wts[m] = wt
                    total += wt
                    m += 1
            if m == 0:
                continue
            order = np.argsort(vals[:m])
            acc = 0.0
            for i in range(m):
                acc += wts[order[i]]
                if acc >= 0.5 * total:
                    out[y, x] = vals[order[i]]
                    break


def weighted_median_at(disp: np.ndarray, todo: np.ndarray, guide: np.ndarray, radius: int,
                       sigma_s: float, sigma_c: float) -> np.ndarray:
    """Bilateral-weighted median of the finite disparities around each ``todo`` pixel.

    Weight exp(−Δs²/σ_s² − ‖ΔI‖²/σ_c²) with ‖ΔI‖ the colour distance in ``guide`` (H, W, C)
    (Hosni et al. 2013, §4.1). Other pixels are copied unchanged.
    """
    out = disp.copy()
    for_rows(_weighted_median_at_rows, disp.shape[0], disp, todo, guide, radius, sigma_s, sigma_c, out)
    return out
