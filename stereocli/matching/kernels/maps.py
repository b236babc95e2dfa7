"""Compiled kernels over (H, W) disparity maps: consistency checks, fusion, filling, median, 1-px bins."""

from __future__ import annotations

import numpy as np

from ...runtime import chunk_kernel, for_rows, njit

INF = np.float32(np.inf)


def lr_check(disp_left: np.ndarray, disp_right: np.ndarray, max_diff: float) -> np.ndarray:
    """Invalidate left disparities that the right view does not confirm.

    Left pixel x with disparity d maps to right pixel ``xr = round(x - d)``; it is kept when
    ``|d - disp_right[y, xr]| <= max_diff``. Returns a new float32 map with +inf where rejected.
    """
    return lr_check_onto(disp_left, disp_right, max_diff, disp_left)


@chunk_kernel
def _lr_check_onto_rows(disp_left, disp_right, max_diff: float, out, y0: int, y1: int) -> None:
    """:func:`lr_check_onto` on rows ``y0`` to ``y1`` (exclusive) of ``out``."""
    w = disp_left.shape[1]
    for y in range(y0, y1):
        for x in range(w):
            d = disp_left[y, x]
            if not np.isfinite(d):
                continue
            xr = int(np.floor(x - d + 0.5))
            if xr < 0 or xr >= w:
                out[y, x] = INF
                continue
            dr = disp_right[y, xr]
            if not np.isfinite(dr) or abs(d - dr) > max_diff:
                out[y, x] = INF


def lr_check_onto(disp_left: np.ndarray, disp_right: np.ndarray, max_diff: float,
                  target: np.ndarray) -> np.ndarray:
    """A copy of ``target`` (H, W) with +inf where the pair ``disp_left``/``disp_right`` fails
    the check of :func:`lr_check` (e.g. the check decided on the integer winners, applied to
    the sub-pixel map); pixels where ``disp_left`` is invalid keep their ``target`` value."""
    out = target.copy()
    for_rows(_lr_check_onto_rows, disp_left.shape[0], disp_left, disp_right, float(max_diff), out)
    return out


@njit(cache=True, inline="always")
def _read_right_map(right_map, y: int, x: int, d):
    """``right_map`` read where left pixel (``y``, ``x``) lands at disparity ``d`` (finite):
    column ``x − d`` of row ``y``, linearly interpolated between the two nearest columns; +inf
    where ``x − d`` falls outside ``[0, W − 1]`` or a column read at a weight above 0 is
    invalid."""
    w = right_map.shape[1]
    x_right = np.float32(x) - d
    if x_right < 0 or x_right > w - 1:
        return INF
    if w < 2:
        return right_map[y, x]
    # The two columns around x − d; at x − d = W − 1 exactly, (W − 2, W − 1) at weight 1.
    column = min(int(np.floor(x_right)), w - 2)
    weight = x_right - np.float32(column)
    before, after = right_map[y, column], right_map[y, column + 1]
    # A column read at weight 0 may be invalid.
    if not np.isfinite(before):
        if weight != 1:
            return INF
        before = np.float32(0)
    if not np.isfinite(after):
        if weight != 0:
            return INF
        after = np.float32(0)
    return before + weight * (after - before)


@chunk_kernel
def _fuse_mirrored_rows(disp, right_map, tolerance: float, out, y0: int, y1: int) -> None:
    """:func:`fuse_mirrored` on rows ``y0`` to ``y1`` (exclusive) of ``out``."""
    w = disp.shape[1]
    half = np.float32(0.5)
    tol = np.float32(tolerance)  # compared in float32, as numpy compares a float32 map with a float
    for y in range(y0, y1):
        for x in range(w):
            d = disp[y, x]
            out[y, x] = d
            if not np.isfinite(d):
                continue
            sampled = _read_right_map(right_map, y, x, d)
            if abs(sampled - d) < tol:
                out[y, x] = half * (d + sampled)


def fuse_mirrored(disp: np.ndarray, right_map: np.ndarray, tolerance: float) -> np.ndarray:
    """(H, W) float32: the mean of each left disparity ``d`` and ``right_map`` read at column
    ``x − d`` of its row (linear interpolation between the two nearest columns) where the two
    differ by less than ``tolerance`` px; ``d`` itself where they do not, where ``x − d`` falls
    outside ``[0, W − 1]`` or a column read at a weight above 0 is invalid. ``disp`` (H, W)
    float32 px left-referenced, +inf invalid; ``right_map`` (H, W) float32 px referenced to the
    right image."""
    out = np.empty_like(disp)
    for_rows(_fuse_mirrored_rows, disp.shape[0], disp, right_map, float(tolerance), out)
    return out


@chunk_kernel
def _reassign_contradicted_rows(disp, right_map, above: float, radius: int, within: float, out,
                                y0: int, y1: int) -> None:
    """:func:`reassign_contradicted` on rows ``y0`` to ``y1`` (exclusive) of ``out``."""
    h, w = disp.shape
    above32, within32 = np.float32(above), np.float32(within)  # float32 comparisons, as numpy's
    for y in range(y0, y1):
        for x in range(w):
            d = disp[y, x]
            out[y, x] = d
            if not np.isfinite(d):
                continue
            sampled = _read_right_map(right_map, y, x, d)
            if not np.isfinite(sampled) or abs(sampled - d) <= above32:
                continue
            best = INF
            # Candidates in a fixed order (row before column, nearer before farther, the right
            # or lower side first); a later one must be strictly better to replace one.
            for along_column in range(2):
                for step in range(1, radius + 1):
                    for side in range(2):
                        offset = step if side == 0 else -step
                        yy, xx = (y + offset, x) if along_column else (y, x + offset)
                        if yy < 0 or yy >= h or xx < 0 or xx >= w:
                            continue
                        candidate = disp[yy, xx]
                        if not np.isfinite(candidate):
                            continue
                        error = abs(_read_right_map(right_map, y, x, candidate) - candidate)
                        if error <= within32 and error < best:
                            best = error
                            out[y, x] = candidate


def reassign_contradicted(disp: np.ndarray, right_map: np.ndarray, above: float, radius: int,
                          within: float) -> np.ndarray:
    """(H, W) float32: ``disp`` where ``right_map`` read at ``x − d`` (as in
    :func:`fuse_mirrored`) contradicts it by ``above`` px or less, or cannot be read; elsewhere
    the disparity ``c`` of the neighbour, up to ``radius`` px away along the row or the column,
    that ``right_map`` read at ``x − c`` confirms best, if within ``within`` px (else ``d``).
    Every pixel decides on the input map, so the result does not depend on the order of rows."""
    out = np.empty_like(disp)
    for_rows(_reassign_contradicted_rows, disp.shape[0], disp, right_map, float(above), int(radius),
             float(within), out)
    return out


@chunk_kernel
def _fill_background_rows(disp, out, y0: int, y1: int) -> None:
    """:func:`fill_background` on rows ``y0`` to ``y1`` (exclusive) of ``out``."""
    w = disp.shape[1]
    left_val = np.empty(w, np.float32)
    for y in range(y0, y1):
        last = INF
        for x in range(w):
            if np.isfinite(disp[y, x]):
                last = disp[y, x]
            left_val[x] = last
        nxt = INF
        for x in range(w - 1, -1, -1):
            if np.isfinite(disp[y, x]):
                nxt = disp[y, x]
            else:
                a = left_val[x]
                if np.isfinite(a) and np.isfinite(nxt):
                    out[y, x] = min(a, nxt)
                elif np.isfinite(a):
                    out[y, x] = a
                else:
                    out[y, x] = nxt


def fill_background(disp: np.ndarray) -> np.ndarray:
    """Fill invalid pixels along each row with the smaller (background) of the nearest valid
    disparities to the left and right; rows with no valid pixel stay invalid.

    Occlusions next to a foreground object belong to the background surface, hence the minimum
    (Hirschmüller 2008, §2.5 / the KITTI devkit's background interpolation).
    """
    out = disp.copy()
    for_rows(_fill_background_rows, disp.shape[0], disp, out)
    return out


@njit(cache=True, inline="always")
def _bins_rows(disp, min_disp: int, ndisp: int, bins, y0: int, y1: int) -> None:
    for y in range(y0, y1):
        for x in range(disp.shape[1]):
            v = disp[y, x] - min_disp + 0.5  # +inf and NaN fail both tests below
            bins[y, x] = int(v) if (v >= 0.0 and v < ndisp) else -1


@chunk_kernel
def _disparity_bins_rows(disp, min_disp: int, ndisp: int, bins, y0: int, y1: int) -> None:
    """:func:`disparity_bins` on rows ``y0`` to ``y1`` (exclusive) of ``bins``."""
    _bins_rows(disp, min_disp, ndisp, bins, y0, y1)


def disparity_bins(disp: np.ndarray, min_disp: int, ndisp: int) -> np.ndarray:
    """(H, W) int32 1-px bins ``round(d) − min_disp``; −1 for invalid (+inf) disparities and
    those outside ``[min_disp, min_disp + ndisp)``."""
    bins = np.empty(disp.shape, np.int32)
    for_rows(_disparity_bins_rows, disp.shape[0], disp, int(min_disp), int(ndisp), bins)
    return bins


@chunk_kernel
def _holes_and_range_rows(disp, lo: float, hi: float, holes, outside, y0: int, y1: int) -> None:
    """:func:`holes_and_range` on rows ``y0`` to ``y1`` (exclusive)."""
    w = disp.shape[1]
    low = np.float32(lo)
    high = np.float32(hi)
    for y in range(y0, y1):
        count = 0
        for x in range(w):
            d = disp[y, x]
            if d == INF:
                holes[y, x] = True
            elif d < low or d > high:
                count += 1
        outside[y] = count


def holes_and_range(disp: np.ndarray, lo: float, hi: float, holes: np.ndarray) -> bool:
    """Mark the invalid (+inf) pixels of ``disp`` (H, W) float32 in ``holes`` (H, W) bool (in place,
    added to what it holds) and tell whether any finite value lies outside ``[lo, hi]``: one pass
    instead of numpy's several over the map."""
    outside = np.zeros(disp.shape[0], np.int64)
    for_rows(_holes_and_range_rows, disp.shape[0], np.ascontiguousarray(disp, dtype=np.float32), float(lo), float(hi),
             holes, outside)
    return bool(outside.any())

