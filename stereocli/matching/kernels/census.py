"""Census transform and Hamming-distance cost volumes (full range and on a windowed SGM's runs).

Layout: ``cost[y, x, k]`` compares left (x, y) with right (x - (min_disp + k), y); entries whose
right pixel is outside the image get ``cost_max``.
"""

from __future__ import annotations

import numpy as np

from ...runtime import chunk_kernel, for_rows, intrinsic, njit


@chunk_kernel
def _census_rows(image: np.ndarray, half_h: int, half_w: int, out, y0: int, y1: int) -> None:
    """:func:`census_transform` of rows ``[y0, y1)``, written into ``out``."""
    # The innermost loop runs along x over row slices with the window offset fixed, which LLVM
    # vectorises (building each pixel's string in turn does not); the ``half_w``
    # columns at each side, whose neighbours are clamped to the border, take a scalar loop
    # (no padded copy of the image). The bits collect in two uint32 halves, the last 32
    # neighbours in ``low`` and any before them in ``high``: lanes as wide as the float32
    # comparisons, so a vector holds as many of them (twice as many as uint64 lanes).
    h, w = image.shape
    n_bits = (2 * half_h + 1) * (2 * half_w + 1) - 1
    x0 = min(half_w, w)  # interior columns [x0, x1): every neighbour inside the row
    x1 = max(w - half_w, x0)
    for y in range(y0, y1):
        high = np.zeros(w, np.uint32)
        low = np.zeros(w, np.uint32)
        centre = image[y]
        bit = 0
        for dy in range(-half_h, half_h + 1):
            row = image[min(max(y + dy, 0), h - 1)]
            for dx in range(-half_w, half_w + 1):
                if dy == 0 and dx == 0:
                    continue
                bits = high if bit < n_bits - 32 else low
                inner_bits = bits[x0:x1]
                inner_centre = centre[x0:x1]
                inner_row = row[x0 + dx:x1 + dx]
                for i in range(x1 - x0):
                    inner_bits[i] = (inner_bits[i] << np.uint32(1)) | np.uint32(inner_centre[i] > inner_row[i])
                for side in range(2):
                    for x in range(0, x0) if side == 0 else range(x1, w):
                        other = row[min(max(x + dx, 0), w - 1)]
                        bits[x] = (bits[x] << np.uint32(1)) | np.uint32(centre[x] > other)
                bit += 1
        for x in range(w):
            out[y, x] = (np.uint64(high[x]) << np.uint64(32)) | np.uint64(low[x])


def census_transform(image: np.ndarray, half_h: int, half_w: int) -> np.ndarray:
    """Census bit strings of a (H, W) float32 image, one uint64 per pixel.

    Bit = 1 where the neighbour is darker than the centre (Zabih & Woodfill 1994), neighbours
    in raster order, most significant first; the centre itself is skipped, so a window may
    hold up to 65 pixels. Neighbours outside the image are clamped to the border (replicate),
    so border pixels still get full-length strings.
    """
    image = np.ascontiguousarray(image, dtype=np.float32)
    out = np.empty(image.shape, np.uint64)
    for_rows(_census_rows, image.shape[0], image, int(half_h), int(half_w), out)
    return out


@intrinsic
def _popcount64(typingctx, value):
    """The number of set bits of a uint64, as LLVM's ``ctpop``: one instruction, vectorised
    where the CPU has one. (A SWAR form was recognised as the same instruction in a single
    count, but not in the three of :func:`_weighted_distance`.)"""
    from llvmlite import ir
    from numba import types

    if value != types.uint64:
        return None

    def codegen(context, builder, signature, args):
        count = builder.module.declare_intrinsic("llvm.ctpop", [ir.IntType(64)])
        return builder.call(count, args)

    return types.uint64(types.uint64), codegen


@njit(cache=True, inline="always")
def _weighted_distance(differ, plane0, plane1, plane2, scale):
    # Sum of the 3-bit weights of the differing bits (bit j of each weight in plane j),
    # scaled to the pixel's range and rounded.
    total = (_popcount64(differ & plane0) + (_popcount64(differ & plane1) << np.uint64(1))
             + (_popcount64(differ & plane2) << np.uint64(2)))
    return np.uint8(np.float32(total) * scale + np.float32(0.5))


@njit(cache=True, inline="always")
def _largest_step(step, nr, ng, nb, r, g, b) -> None:
    # step[i] = max over channels |n_c[i] − c[i]| (selects, not max(): a loop that vectorises).
    for i in range(step.shape[0]):
        d1 = abs(nr[i] - r[i])
        d2 = abs(ng[i] - g[i])
        d3 = abs(nb[i] - b[i])
        m = d1 if d1 > d2 else d2
        step[i] = m if m > d3 else d3


@njit(cache=True, inline="always")
def _shift_in_weights(step, t1, t2, t3, t4, t5, t6, t7, weight, total, plane0, plane1, plane2) -> None:
    # Weight 0-7 (how many of the decreasing thresholds the difference stays below), added to
    # ``total`` and shifted into the three bit planes. One array written per loop, selects
    # instead of branches: each loop vectorises (a single fused loop did not).
    one = np.uint32(1)
    zero = np.uint32(0)
    n = step.shape[0]
    for x in range(n):
        s = step[x]
        weight[x] = ((one if s < t1 else zero) + (one if s < t2 else zero) + (one if s < t3 else zero)
                     + (one if s < t4 else zero) + (one if s < t5 else zero) + (one if s < t6 else zero)
                     + (one if s < t7 else zero))
    for x in range(n):
        total[x] += weight[x]
    for x in range(n):
        plane0[x] = (plane0[x] << one) | (weight[x] & one)
    for x in range(n):
        plane1[x] = (plane1[x] << one) | ((weight[x] >> one) & one)
    for x in range(n):
        plane2[x] = (plane2[x] << one) | (weight[x] >> np.uint32(2))


@chunk_kernel
def _support_rows(planar, half_h: int, half_w: int, thresholds, resolution: int, planes, scale, y0: int,
                  y1: int) -> None:
    """:func:`support_planes` of rows ``[y0, y1)`` of a (3, H, W) image, written into ``planes``
    and ``scale``."""
    # As in _census_rows: one neighbour offset at a time over whole row slices (loops that
    # vectorise), bits shifted in from the right in raster order, so the first neighbour ends
    # up most significant; two uint32 halves per plane.
    _, h, w = planar.shape
    n_bits = (2 * half_h + 1) * (2 * half_w + 1) - 1
    x0 = min(half_w, w)  # interior columns [x0, x1): every neighbour inside the row
    x1 = max(w - half_w, x0)
    step = np.empty(w, np.float32)
    weight = np.empty(w, np.uint32)
    t1, t2, t3, t4, t5, t6, t7 = (thresholds[0], thresholds[1], thresholds[2], thresholds[3], thresholds[4],
                                  thresholds[5], thresholds[6])
    for y in range(y0, y1):
        high = np.zeros((3, w), np.uint32)
        low = np.zeros((3, w), np.uint32)
        total = np.zeros(w, np.uint32)
        r, g, b = planar[0, y], planar[1, y], planar[2, y]
        bit = 0
        for dy in range(-half_h, half_h + 1):
            yy = min(max(y + dy, 0), h - 1)
            nr, ng, nb = planar[0, yy], planar[1, yy], planar[2, yy]
            for dx in range(-half_w, half_w + 1):
                if dy == 0 and dx == 0:
                    continue
                _largest_step(step[x0:x1], nr[x0 + dx:x1 + dx], ng[x0 + dx:x1 + dx], nb[x0 + dx:x1 + dx], r[x0:x1],
                              g[x0:x1], b[x0:x1])
                for side in range(2):  # the columns whose neighbour is clamped to the row's end
                    for x in range(0, x0) if side == 0 else range(x1, w):
                        xx = min(max(x + dx, 0), w - 1)
                        _largest_step(step[x:x + 1], nr[xx:xx + 1], ng[xx:xx + 1], nb[xx:xx + 1], r[x:x + 1],
                                      g[x:x + 1], b[x:x + 1])
                bits = high if bit < n_bits - 32 else low
                _shift_in_weights(step, t1, t2, t3, t4, t5, t6, t7, weight, total, bits[0], bits[1], bits[2])
                bit += 1
        for x in range(w):
            if total[x] == 0:  # no neighbour like the centre: every bit counts fully
                for j in range(3):
                    planes[y, x, j] = ~np.uint64(0) >> np.uint64(64 - n_bits)
                scale[y, x] = np.float32(resolution) / np.float32(7.0)
            else:
                for j in range(3):
                    planes[y, x, j] = (np.uint64(high[j, x]) << np.uint64(32)) | np.uint64(low[j, x])
                scale[y, x] = np.float32(resolution * n_bits) / np.float32(total[x])


def support_planes(image: np.ndarray, half_h: int, half_w: int, gamma: float) -> tuple[np.ndarray, np.ndarray, int]:
    """Colour-adaptive weights of the census bits of an (H, W, C) or (H, W) image (float32 levels).

    Neighbour ``i`` of pixel ``p`` weighs ``round(7·exp(−(Δ/γ)²))`` (0–7), ``Δ`` the largest
    channel difference between them (grey levels): bits of neighbours on another surface
    (another colour) count little, so a window that straddles a depth edge is matched by the
    centre's own side. Returns ``(planes, scale, cost_max)``: (H, W, 3) uint64, bit ``b`` of
    plane ``j`` set where bit ``j`` of census bit ``b``'s weight is; (H, W) float32 ``scale``
    that maps a weight sum to ``[0, cost_max]``; ``cost_max = resolution · n_bits``, the
    largest multiple of the bit count that fits in uint8.
    """
    n_bits = (2 * half_h + 1) * (2 * half_w + 1) - 1
    resolution = max(255 // n_bits, 1)
    # round(7·exp(−(Δ/γ)²)) >= k  <=>  Δ < γ·sqrt(ln(7 / (k − 0.5))), k = 1..7.
    thresholds = np.array([gamma * np.sqrt(np.log(7.0 / (k - 0.5))) for k in range(1, 8)], np.float32)
    image = np.asarray(image, dtype=np.float32)
    image = image if image.ndim == 3 else image[..., None]
    # Three planes (a grey image is its own three channels): one kernel for any image.
    planar = np.ascontiguousarray(np.moveaxis(image, -1, 0)[[min(c, image.shape[2] - 1) for c in range(3)]])
    h, w = planar.shape[1:]
    planes = np.empty((h, w, 3), np.uint64)
    scale = np.empty((h, w), np.float32)
    for_rows(_support_rows, h, planar, int(half_h), int(half_w), thresholds, int(resolution), planes, scale)
    return planes, scale, resolution * n_bits


NO_SUPPORT = (np.zeros((0, 0, 3), np.uint64), np.zeros((0, 0), np.float32))
"""``(planes, scale)`` for plain Hamming distances (every bit weighs 1)."""


@chunk_kernel
def _hamming_rows(census_left, census_right, min_disp: int, cost_max: float, out, y0: int, y1: int) -> None:
    """:func:`hamming_volume` of rows ``[y0, y1)``, written into ``out``."""
    w = census_left.shape[1]
    nd = out.shape[2]
    top = out.dtype.type(cost_max)
    for y in range(y0, y1):
        # The right row reversed, so hypothesis k reads forward: right[x − min_disp − k] =
        # reversed[w − 1 − x + min_disp + k] (contiguous loads; the loop vectorises).
        reversed_right = census_right[y, ::-1].copy()
        for x in range(w):
            o = out[y, x]
            cl = census_left[y, x]
            # Hypotheses k0..k1 have their right pixel x − min_disp − k inside the image.
            k0 = max(0, x - min_disp - (w - 1))
            k1 = min(nd - 1, x - min_disp)
            base = w - 1 - x + min_disp
            if k0 == 0 and k1 == nd - 1:
                # Every hypothesis inside (most pixels): one loop over the whole range, whose
                # bounds LLVM knows (loops over sub-slices with run-time bounds vectorise worse).
                src = reversed_right[base:base + nd]
                for k in range(nd):
                    o[k] = _popcount64(cl ^ src[k])
            else:
                for k in range(nd):
                    o[k] = _popcount64(cl ^ reversed_right[base + k]) if k0 <= k <= k1 else top


@chunk_kernel
def _weighted_rows(census_left, census_right, planes, scale, min_disp: int, cost_max: float, out, y0: int,
                   y1: int) -> None:
    """:func:`hamming_volume` with bit weights, of rows ``[y0, y1)``, written into ``out``."""
    # A kernel of its own: with both kinds of distance in one kernel the plain runs' loop
    # no longer vectorised.
    w = census_left.shape[1]
    nd = out.shape[2]
    top = out.dtype.type(cost_max)
    for y in range(y0, y1):
        reversed_right = census_right[y, ::-1].copy()  # hypothesis k reads forward (as above)
        for x in range(w):
            o = out[y, x]
            cl = census_left[y, x]
            k0 = max(0, x - min_disp - (w - 1))
            k1 = min(nd - 1, x - min_disp)
            base = w - 1 - x + min_disp
            p0, p1, p2, s = planes[y, x, 0], planes[y, x, 1], planes[y, x, 2], scale[y, x]
            if k0 == 0 and k1 == nd - 1:
                src = reversed_right[base:base + nd]
                for k in range(nd):
                    o[k] = _weighted_distance(cl ^ src[k], p0, p1, p2, s)
            else:
                for k in range(nd):
                    o[k] = _weighted_distance(cl ^ reversed_right[base + k], p0, p1, p2, s) if k0 <= k <= k1 else top


@chunk_kernel
def _hamming_runs_rows(census_left, census_right, min_disp: int, cost_max: float, run_lo, run_hi, offset,
                       right_valid, out, y0: int, y1: int) -> None:
    """:func:`hamming_runs` of rows ``[y0, y1)``, written into ``out``."""
    w = census_left.shape[1]
    top = np.uint8(cost_max)
    masked = right_valid.shape[0] > 0
    for y in range(y0, y1):
        reversed_right = census_right[y, ::-1].copy()  # hypothesis k reads forward (as above)
        for x in range(w):
            cl = census_left[y, x]
            a = run_lo[y, x]
            b = run_hi[y, x]
            run = out[offset[y, x]:offset[y, x] + (b - a)]
            # Hypotheses k0..k1 of the run have their right pixel inside the image.
            k0 = max(a, x - min_disp - (w - 1))
            k1 = min(b - 1, x - min_disp)
            base = w - 1 - x + min_disp
            if k0 == a and k1 == b - 1:  # the whole run (most pixels): one plain loop
                src = reversed_right[base + a:base + b]
                for j in range(b - a):
                    run[j] = _popcount64(cl ^ src[j])
            else:
                for j in range(b - a):
                    k = a + j
                    run[j] = _popcount64(cl ^ reversed_right[base + k]) if k0 <= k <= k1 else top
            if masked:
                for k in range(k0, k1 + 1):
                    if not right_valid[y, x - min_disp - k]:
                        run[k - a] = top


@chunk_kernel
def _weighted_runs_rows(census_left, census_right, planes, scale, min_disp: int, cost_max: float, run_lo, run_hi,
                        offset, right_valid, out, y0: int, y1: int) -> None:
    """:func:`hamming_runs` with bit weights, of rows ``[y0, y1)``, written into ``out`` (a
    kernel of its own, as :func:`_weighted_rows`)."""
    w = census_left.shape[1]
    top = np.uint8(cost_max)
    masked = right_valid.shape[0] > 0
    for y in range(y0, y1):
        reversed_right = census_right[y, ::-1].copy()
        for x in range(w):
            cl = census_left[y, x]
            a = run_lo[y, x]
            b = run_hi[y, x]
            run = out[offset[y, x]:offset[y, x] + (b - a)]
            k0 = max(a, x - min_disp - (w - 1))
            k1 = min(b - 1, x - min_disp)
            base = w - 1 - x + min_disp
            p0, p1, p2, s = planes[y, x, 0], planes[y, x, 1], planes[y, x, 2], scale[y, x]
            if k0 == a and k1 == b - 1:
                src = reversed_right[base + a:base + b]
                for j in range(b - a):
                    run[j] = _weighted_distance(cl ^ src[j], p0, p1, p2, s)
            else:
                for j in range(b - a):
                    k = a + j
                    run[j] = _weighted_distance(cl ^ reversed_right[base + k], p0, p1, p2, s) if k0 <= k <= k1 else top
            if masked:
                for k in range(k0, k1 + 1):
                    if not right_valid[y, x - min_disp - k]:
                        run[k - a] = top


def hamming_runs(census_left, census_right, min_disp: int, cost_max: float, run_lo, run_hi, offset, n: int,
                 right_valid, support=NO_SUPPORT):
    """Hamming costs on each pixel's run of hypotheses ``[run_lo, run_hi)`` only, stored ragged
    (pixel (y, x) at ``offset[y, x]``, uint8; the layout of
    :mod:`stereocli.matching.kernels.sgm_window`). ``cost_max`` where the right pixel is outside
    the image or, if ``right_valid`` is not empty, outside its valid mask. ``support``: the
    ``(planes, scale)`` of :func:`support_planes` for weighted distances (``cost_max`` must
    then be its range), or :data:`NO_SUPPORT`."""
    out = np.empty(n, np.uint8)
    if support[0].shape[0] == 0:
        for_rows(_hamming_runs_rows, census_left.shape[0], census_left, census_right, min_disp, cost_max, run_lo,
                 run_hi, offset, right_valid, out)
    else:
        for_rows(_weighted_runs_rows, census_left.shape[0], census_left, census_right, support[0], support[1],
                 min_disp, cost_max, run_lo, run_hi, offset, right_valid, out)
    return out


def hamming_volume(census_left: np.ndarray, census_right: np.ndarray, min_disp: int, ndisp: int,
                   cost_max: float, dtype=np.float32, support=NO_SUPPORT) -> np.ndarray:
    """Hamming distance between left and right census strings for every hypothesis.

    Returns (H, W, ``ndisp``) ``dtype`` (float32, or uint8 for windows of at most 255 bits),
    ``cost_max`` where the right pixel is outside the image. ``support``: as in
    :func:`hamming_runs`.
    """
    h, w = census_left.shape
    out = np.empty((h, w, ndisp), dtype)
    if support[0].shape[0] == 0:
        for_rows(_hamming_rows, h, census_left, census_right, int(min_disp), float(cost_max), out)
    else:
        for_rows(_weighted_rows, h, census_left, census_right, support[0], support[1], int(min_disp),
                 float(cost_max), out)
    return out


# --- nearest bit strings (binary feature descriptors) ----------------------------------------------

@chunk_kernel
def _nearest_rows(queries, candidates, best_index, best, second, y0: int, y1: int) -> None:
    """:func:`nearest_bit_strings` for queries ``[y0, y1)`` (``candidates`` transposed: (words, M))."""
    n_words, n_candidates = candidates.shape  # word k of every candidate in a row: contiguous loads
    distances = np.empty(n_candidates, np.uint64)
    for q in range(y0, y1):
        query = queries[q]
        distances[:] = 0
        for k in range(n_words):  # every distance first, in loops over candidates that vectorise
            word = query[k]
            row = candidates[k]
            for c in range(n_candidates):
                distances[c] += _popcount64(word ^ row[c])
        first_d, second_d, first_c = np.int64(1 << 62), np.int64(1 << 62), -1
        for c in range(n_candidates):  # the first of equal distances wins
            d = np.int64(distances[c])
            if d < first_d:
                second_d, first_d, first_c = first_d, d, c
            elif d < second_d:
                second_d = d
        best_index[q], best[q], second[q] = first_c, first_d, second_d


def nearest_bit_strings(queries: np.ndarray, candidates: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """For each row of ``queries`` (N, B) uint8 (binary descriptors such as ORB's, B a multiple of
    8), its nearest row of ``candidates`` (M, B) by Hamming distance: ``(index, distance,
    second distance)``, (N,) int64 each (the second is 2^62 when M < 2; among equal distances the
    lowest index wins)."""
    q = np.ascontiguousarray(queries, dtype=np.uint8).view(np.uint64)
    c = np.ascontiguousarray(np.ascontiguousarray(candidates, dtype=np.uint8).view(np.uint64).T)
    n = q.shape[0]
    index, best, second = np.empty(n, np.int64), np.empty(n, np.int64), np.empty(n, np.int64)
    for_rows(_nearest_rows, n, q, c, index, best, second)
    return index, best, second
