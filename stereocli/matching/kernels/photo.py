"""Compiled kernels of the photo-consistency re-decision: the colour residual of a map and the
re-decision of the pixels it flags (:mod:`stereocli.matching.refine_photo`)."""

from __future__ import annotations

import numpy as np

from ...runtime import chunk_kernel, for_chunks, for_rows, njit

# The eight directions a flagged pixel looks along for its candidates (row step, column step).
_STEP_Y = np.array([0, 0, 1, -1, 1, 1, -1, -1], np.int64)
_STEP_X = np.array([1, -1, 0, 0, 1, -1, 1, -1], np.int64)
# Window pixels weighing less than this are skipped (their share of the sum is negligible).
_MIN_WEIGHT = 1e-3


@njit(cache=True, inline="always")
def _shift(d) -> int:
    """Disparity ``d`` (finite) rounded to whole pixels, halves up."""
    return int(np.floor(d + 0.5))


@njit(cache=True, inline="always")
def _difference_at(left, right, y: int, x: int, d):
    """Left pixel (y, x)'s largest channel difference from the right pixel disparity ``d``
    (finite) maps it onto, column ``x − round(d)`` clamped to the row."""
    x_right = min(max(x - _shift(d), 0), left.shape[1] - 1)
    largest = np.float32(0)
    for c in range(left.shape[2]):
        largest = max(largest, abs(left[y, x, c] - right[y, x_right, c]))
    return largest


@njit(cache=True, inline="always")
def _residual_at(left, right, disp, y: int, x: int):
    """:func:`_difference_at` at the pixel's own disparity; 0 where it is invalid or maps the
    pixel outside the right image (nothing to compare it with)."""
    d = disp[y, x]
    if not np.isfinite(d) or not 0 <= x - _shift(d) < disp.shape[1]:
        return np.float32(0)
    return _difference_at(left, right, y, x, d)


@njit(cache=True, inline="always")
def _mean3(residual, y: int, x: int):
    """The mean of ``residual`` over the 3x3 window around (y, x), clipped at the borders: one
    pixel's value of :func:`~stereocli.matching.cost.box_mean_image` with radius 1."""
    h, w = residual.shape
    total = np.float32(0)
    count = 0
    for yy in range(max(y - 1, 0), min(y + 2, h)):
        for xx in range(max(x - 1, 0), min(x + 2, w)):
            total += residual[yy, xx]
            count += 1
    return total / count


@chunk_kernel
def _residual_rows(left, right, disp, out, y0: int, y1: int) -> None:
    """:func:`colour_residual` on rows ``y0`` to ``y1`` (exclusive) of ``out``."""
    for y in range(y0, y1):
        for x in range(disp.shape[1]):
            out[y, x] = _residual_at(left, right, disp, y, x)


def colour_residual(left: np.ndarray, right: np.ndarray, disp: np.ndarray) -> np.ndarray:
    """(H, W) float32: each left pixel's largest channel difference (grey levels) from the right
    pixel its disparity maps it onto, column ``x − round(d)``; 0 where ``disp`` is invalid or
    that column lies outside the image. ``left``/``right`` (H, W, C) float32, ``disp`` (H, W)
    float32 px."""
    out = np.empty(disp.shape, np.float32)
    for_rows(_residual_rows, disp.shape[0], left, right, disp, out)
    return out


@chunk_kernel
def _refresh_chunk(left, right, disp, residual, changed_at, threshold: float, flagged, active, chunk: int) -> None:
    """:func:`refresh_after_change` (one chunk: a pass changes few pixels)."""
    h, w = disp.shape
    active[:, :] = False
    for i in range(changed_at.shape[0]):
        y, x = changed_at[i] // w, changed_at[i] % w
        residual[y, x] = _residual_at(left, right, disp, y, x)
    for i in range(changed_at.shape[0]):
        y, x = changed_at[i] // w, changed_at[i] % w
        for yy in range(max(y - 1, 0), min(y + 2, h)):
            for xx in range(max(x - 1, 0), min(x + 2, w)):
                flagged[yy, xx] = np.isfinite(disp[yy, xx]) and _mean3(residual, yy, xx) > threshold
                active[yy, xx] = True


def refresh_after_change(left: np.ndarray, right: np.ndarray, disp: np.ndarray, residual: np.ndarray,
                         changed_at: np.ndarray, threshold: float, flagged: np.ndarray, active: np.ndarray) -> None:
    """After a pass changed the pixels ``changed_at`` ((N,) int64 flat indices) of ``disp``:
    update their ``residual``, re-flag the pixels whose 3x3 mean that changes (valid and above
    ``threshold``), and make ``active`` (cleared first) those 3x3 neighbourhoods, where the next
    pass re-decides. ``residual``, ``flagged`` and ``active`` are updated in place."""
    for_chunks(_refresh_chunk, 1, left, right, disp, residual, np.ascontiguousarray(changed_at, dtype=np.int64),
               float(threshold), flagged, active)


@chunk_kernel
def _redecide_rows(left, right, disp, flagged, active, offsets, spatial, similarity, truncation: float,
                   reach: int, margin: float, out, changed, y0: int, y1: int) -> None:
    """:func:`redecide_flagged` on rows ``y0`` to ``y1`` (exclusive) of ``out``/``changed``."""
    h, w = disp.shape
    channels = left.shape[2]
    n = offsets.shape[0]
    candidates = np.empty(8, np.float32)
    shifts = np.empty(8, np.int64)
    weights = np.empty((n, n), np.float32)
    for y in range(y0, y1):
        for x in range(w):
            if not flagged[y, x] or not active[y, x]:
                continue
            own = disp[y, x]
            own_shift = _shift(own)
            own_residual = _difference_at(left, right, y, x, own)
            # The nearest unflagged pixel along each of the 8 directions proposes its disparity if
            # it matches the pixel itself better than its own value does: once per whole-pixel
            # shift (the window is compared at the rounded disparity), the first one met.
            count = 0
            for k in range(8):
                yy = y
                xx = x
                for _ in range(reach):
                    yy += _STEP_Y[k]
                    xx += _STEP_X[k]
                    if yy < 0 or yy >= h or xx < 0 or xx >= w:
                        break
                    if flagged[yy, xx] or not np.isfinite(disp[yy, xx]):
                        continue
                    c = disp[yy, xx]
                    shift = _shift(c)
                    fresh = shift != own_shift
                    for i in range(count):
                        if shifts[i] == shift:
                            fresh = False
                    if fresh and _difference_at(left, right, y, x, c) < own_residual:
                        candidates[count] = c
                        shifts[count] = shift
                        count += 1
                    break
            if count == 0:
                continue
            # Adaptive support weights (Yoon & Kweon 2006) from the left image: proximity times
            # colour similarity to the centre (largest channel difference).
            total = 0.0
            for a in range(n):
                qy = y + offsets[a]
                for b in range(n):
                    qx = x + offsets[b]
                    weight = 0.0
                    if 0 <= qy < h and 0 <= qx < w:
                        largest = np.float32(0)
                        for c in range(channels):
                            largest = max(largest, abs(left[qy, qx, c] - left[y, x, c]))
                        weight = spatial[a, b] * similarity[min(int(largest), similarity.shape[0] - 1)]
                        if weight < _MIN_WEIGHT:
                            weight = 0.0
                    weights[a, b] = weight
                    total += weight
            # The pixel's own disparity first: a candidate's weighted sum must stay below the own
            # one's by margin x the weights' total (and below the best so far); its sum stops as
            # soon as it cannot (the terms are non-negative).
            bound = np.inf
            best = own
            for i in range(count + 1):
                shift = own_shift if i == 0 else shifts[i - 1]
                acc = 0.0
                for a in range(n):
                    qy = y + offsets[a]
                    for b in range(n):
                        weight = weights[a, b]
                        if weight == 0.0:
                            continue
                        qx = x + offsets[b]
                        x_right = min(max(qx - shift, 0), w - 1)
                        largest = np.float32(0)
                        for c in range(channels):
                            largest = max(largest, abs(left[qy, qx, c] - right[qy, x_right, c]))
                        acc += weight * min(largest, truncation)
                    if acc >= bound:
                        break
                if i == 0:
                    bound = acc - margin * total
                elif acc < bound:
                    bound = acc
                    best = candidates[i - 1]
            if best != own:
                out[y, x] = best
                changed[y, x] = True


def redecide_flagged(left: np.ndarray, right: np.ndarray, disp: np.ndarray, flagged: np.ndarray,
                     active: np.ndarray, radius: int, step: int, gamma_c: float, gamma_s: float,
                     truncation: float, reach: int, margin: float) -> tuple[np.ndarray, np.ndarray]:
    """Re-decide each flagged and active pixel among its neighbours' disparities.

    Candidates are the disparities of the nearest unflagged valid pixel along each of the 8
    directions (at most ``reach`` px away) that match the pixel itself better than its own
    disparity (centre difference), one per whole-pixel shift (the first met). Each is scored by
    the weighted sum of truncated colour differences (largest channel, capped at ``truncation``
    grey levels) between the left window (half side ``radius``, every ``step``-th pixel, through
    the centre) and the right window shifted by the candidate rounded to whole pixels; weights
    are proximity (``exp(−r/gamma_s)``) times colour similarity to the centre in the left image
    (``exp(−Δ/gamma_c)``, Δ in whole grey levels), and below 1e-3 are dropped. The best candidate
    (the first on a tie) replaces the pixel's disparity when its weighted mean is lower than the
    own disparity's by more than ``margin`` grey levels. ``left``/``right`` (H, W, C) float32,
    ``disp`` (H, W) float32 px, ``flagged``/``active`` (H, W) bool. Returns the new map and the
    (H, W) bool mask of the pixels changed.
    """
    offsets = np.arange(-(radius // step) * step, radius + 1, step, dtype=np.int64)  # symmetric, through 0
    spatial = np.exp(-np.hypot(offsets[:, None], offsets[None, :]) / gamma_s).astype(np.float32)
    # exp(−Δ/γc) by whole grey levels: a table instead of an exp per window pixel.
    similarity = np.exp(-np.arange(256, dtype=np.float64) / gamma_c).astype(np.float32)
    out = disp.copy()
    changed = np.zeros(disp.shape, np.bool_)
    for_rows(_redecide_rows, disp.shape[0], left, right, disp, flagged, active, offsets, spatial, similarity,
             float(truncation), int(reach), float(margin), out, changed)
    return out, changed
