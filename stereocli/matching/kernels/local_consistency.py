"""Compiled kernels of the locally consistent refinement (Mattoccia 2009, ``local_consistency``):
the square-window vote and the vote along lines, with the packed colours and line centres that
the geodesic vote (:mod:`.geodesic_vote`) uses too."""

from __future__ import annotations

import numpy as np

from ...runtime import chunk_kernel, for_chunks, for_rows, njit, prange

INF = np.float32(np.inf)


@njit(cache=True, parallel=True)
def local_consistency(disp, left, right, min_disp: int, ndisp: int, radius: int,
                      gamma_s: float, gamma_c: float, gamma_t: float, fill_invalid: bool, todo,
                      min_change: int = 0):
    """Locally consistent disparity: every pixel takes the hypothesis its neighbours support most.

    Each valid neighbour g of f within ``radius`` votes for its disparity d_g with plausibility
    ``exp(−|g − f|/γs) · exp(−Δc_L(f, g)/γc) · exp(−Δc_R(f − d_g, g − d_g)/γt)``: spatial
    proximity, colour similarity of f and g in the left image, and colour similarity of the
    points both would match in the right image under d_g (Mattoccia 2009, "A locally global
    approach to stereo correspondence", eq. 2–4). Votes are binned per integer disparity; f
    takes the weighted mean disparity of the winning bin. Only pixels where ``todo`` (H, W)
    bool is set are voted on; the others keep their disparity with confidence 1. A valid pixel
    keeps its own value when the winning bin is less than ``min_change`` bins from its own.
    Returns (disparity, confidence = winning share of the vote mass).
    """
    h, w, c = left.shape
    out = np.full((h, w), INF, np.float32)
    conf = np.zeros((h, w), np.float32)
    # Tables instead of exp per vote: spatial weights per offset, colour weights per summed
    # absolute difference in quarter grey levels (exact for 8-bit images).
    side = 2 * radius + 1
    spatial = np.empty((side, side))
    for i in range(side):
        for j in range(side):
            spatial[i, j] = np.exp(-np.sqrt(float((i - radius) ** 2 + (j - radius) ** 2)) / gamma_s)
    steps = 4 * 255 * c + 1
    colour_w = np.empty(steps)
    match_w = np.empty(steps)
    for i in range(steps):
        colour_w[i] = np.exp(-(0.25 * i / c) / gamma_c)
        match_w[i] = np.exp(-(0.25 * i / c) / gamma_t)
    outside_w = np.exp(-255.0 / gamma_t)
    for y in prange(h):
        mass = np.zeros(ndisp)
        sumd = np.zeros(ndisp)
        # Bins that received votes for the current pixel: only those are searched and reset
        # (a window holds at most side² votes; the range may be hundreds of bins).
        touched = np.empty(side * side, np.int64)
        for x in range(w):
            if not todo[y, x]:
                out[y, x] = disp[y, x]
                conf[y, x] = 1.0
                continue
            if not fill_invalid and not np.isfinite(disp[y, x]):
                continue
            n_touched = 0
            total = 0.0
            for yy in range(max(0, y - radius), min(h, y + radius + 1)):
                for xx in range(max(0, x - radius), min(w, x + radius + 1)):
                    dg = disp[yy, xx]
                    if not np.isfinite(dg):
                        continue
                    k = int(np.floor(dg - min_disp + 0.5))
                    if k < 0 or k >= ndisp:
                        continue
                    dc = 0.0
                    for ch in range(c):
                        dc += abs(left[y, x, ch] - left[yy, xx, ch])
                    wgt = spatial[yy - y + radius, xx - x + radius] * colour_w[min(int(4.0 * dc + 0.5), steps - 1)]
                    xf = int(np.floor(x - dg + 0.5))
                    xg = int(np.floor(xx - dg + 0.5))
                    if 0 <= xf < w and 0 <= xg < w:
                        dt = 0.0
                        for ch in range(c):
                            dt += abs(right[y, xf, ch] - right[yy, xg, ch])
                        wgt *= match_w[min(int(4.0 * dt + 0.5), steps - 1)]
                    else:
                        wgt *= outside_w
                    if mass[k] == 0.0:
                        touched[n_touched] = k
                        n_touched += 1
                    mass[k] += wgt
                    sumd[k] += wgt * dg
                    total += wgt
            best = -1
            for j in range(n_touched):
                k = touched[j]
                if best < 0 or mass[k] > mass[best] or (mass[k] == mass[best] and k < best):
                    best = k
            if total > 0:
                own = disp[y, x]
                if not np.isfinite(own) or abs(best - int(np.floor(own - min_disp + 0.5))) >= min_change:
                    out[y, x] = np.float32(sumd[best] / mass[best])
                else:
                    out[y, x] = own
                conf[y, x] = np.float32(mass[best] / total)
            for j in range(n_touched):
                mass[touched[j]] = 0.0
                sumd[touched[j]] = 0.0
    return out, conf


#: Bits per channel of a packed colour (:func:`packed_quarter_levels`): quarter grey levels
#: of 8-bit-range images need 10.
CHANNEL_BITS = 16
CHANNEL_MASK = (1 << CHANNEL_BITS) - 1


@chunk_kernel
def _packed_quarter_levels_rows(image, out, y0: int, y1: int) -> None:
    """:func:`packed_quarter_levels` on rows ``y0`` to ``y1`` (exclusive) of ``out``."""
    _, w, c = image.shape
    for y in range(y0, y1):
        row = image[y]
        out_row = out[y]
        if c == 3:  # written out, so that the loop over x vectorises (the loop below does not)
            for x in range(w):
                out_row[x] = (_quarter_level(row[x, 0]) | (_quarter_level(row[x, 1]) << CHANNEL_BITS)
                              | (_quarter_level(row[x, 2]) << (2 * CHANNEL_BITS)))
        else:
            for x in range(w):
                v = np.int64(0)
                for ch in range(c):
                    v |= _quarter_level(row[x, ch]) << (CHANNEL_BITS * ch)
                out_row[x] = v


@njit(cache=True, inline="always")
def _quarter_level(v) -> int:
    # round(4·v) of a grey level clamped to [0, 255], as an int64.
    return np.int64(4.0 * min(max(v, np.float32(0.0)), np.float32(255.0)) + 0.5)


def packed_quarter_levels(image: np.ndarray) -> np.ndarray:
    """(H, W, C) float32 in [0, 255], C ≤ 3 -> (H, W) int64: each channel's quarter grey level
    round(4·v) in its own 16-bit field (channel ch at bit 16·ch; absent channels are 0). One
    load gives a pixel's colour, and integer colour differences index the vote tables."""
    h, w, _ = image.shape
    out = np.empty((h, w), np.int64)
    for_rows(_packed_quarter_levels_rows, h, image, out)
    return out


@njit(cache=True, inline="always")
def _packed_distance_to(a, f0, f1, f2) -> int:
    # The same against a colour already split into its fields f0, f1, f2 (held in registers).
    return (abs((a & CHANNEL_MASK) - f0) + abs(((a >> CHANNEL_BITS) & CHANNEL_MASK) - f1)
            + abs((a >> (2 * CHANNEL_BITS)) - f2))


@njit(cache=True, inline="always")
def _packed_distance(a, b) -> int:
    # Sum of absolute channel differences of two packed colours (three fields; unused ones are 0).
    return _packed_distance_to(a, b & CHANNEL_MASK, (b >> CHANNEL_BITS) & CHANNEL_MASK, b >> (2 * CHANNEL_BITS))


@chunk_kernel
def _line_centre_mask_chunk(bins, todo, band: int, min_change: int, vertical: bool, keep, n_chunks: int,
                            chunk: int) -> None:
    """:func:`line_centre_mask` on the rows of ``chunk`` (of ``n_chunks``), written into ``keep``."""
    h, w = bins.shape
    use_todo = todo.shape[0] > 0
    none = np.int32(2 ** 30)  # stands for an invalid bin in the running minimum
    # Row buffers allocated once per chunk of rows, not once per row.
    high = np.empty(w, np.int32)
    low = np.empty(w, np.int32)
    for y in range(chunk * h // n_chunks, (chunk + 1) * h // n_chunks):
        # Largest and smallest valid bin within band along the line, for the whole row
        # at once (plain loops over x that vectorise, instead of a search per pixel).
        high[:] = -1
        low[:] = none
        if min_change > 0:
            for t in range(-band, band + 1):
                if vertical:
                    if not 0 <= y + t < h:
                        continue
                    src = bins[y + t]
                    for x in range(w):
                        v = src[x]
                        high[x] = max(high[x], v)
                        low[x] = min(low[x], v if v >= 0 else none)
                else:
                    src = bins[y]
                    # Unsigned indices: no negative-index fix-up, so the loop vectorises. (A name
                    # of its own: numba types one name once, and int64 with uint64 is float64.)
                    for ux in range(np.uint64(max(0, -t)), np.uint64(min(w, w - t))):
                        v = src[ux + np.uint64(t + w) - np.uint64(w)]
                        high[ux] = max(high[ux], v)
                        low[ux] = min(low[ux], v if v >= 0 else none)
        # Branch-free per pixel (bitwise on booleans), so the loop vectorises.
        row = bins[y]
        out = keep[y]
        if min_change > 0:
            for x in range(w):
                own = row[x]
                out[x] = (own >= 0) & ((high[x] - own >= min_change) | (own - low[x] >= min_change))
        else:
            for x in range(w):
                out[x] = row[x] >= 0
        if use_todo:
            for x in range(w):
                out[x] &= todo[y, x]


def line_centre_mask(bins: np.ndarray, todo: np.ndarray, band: int, min_change: int, vertical: bool) -> np.ndarray:
    """(H, W) bool: the pixels a line vote can move: valid bin, ``todo`` (an empty array:
    every pixel) and, with ``min_change`` > 0, a valid bin at least ``min_change`` from
    their own within ``band`` px along the row (or, ``vertical``, the column)."""
    h, w = bins.shape
    keep = np.empty((h, w), np.bool_)  # every row is written by the chunks
    n_chunks = min(h, 8)
    for_chunks(_line_centre_mask_chunk, n_chunks, bins, todo, band, min_change, vertical, keep, n_chunks)
    return keep


@njit(cache=True, inline="always")
def _line_votes(disp, bins, left_packed, right_packed, y: int, x: int, sy: int, sx: int, t0: int, t1: int,
                radius: int, min_disp: int, spatial, colour_w, match_w, outside_w, hist, use_right: bool):
    """Add the votes of the segment ``t0 ≤ t ≤ t1`` of (y, x) into ``hist`` (mass of bin k at
    2k, weighted disparity sum at 2k + 1); returns the smallest and largest bin voted for.
    Called with a literal ``use_right`` so that each caller compiles one straight loop."""
    w = bins.shape[1]
    own = bins[y, x]
    colour = left_packed[y, x]
    f0 = colour & CHANNEL_MASK  # the centre's colour fields, in registers for the whole segment
    f1 = (colour >> CHANNEL_BITS) & CHANNEL_MASK
    f2 = colour >> (2 * CHANNEL_BITS)
    lo = own
    hi = own
    for t in range(t0, t1 + 1):
        gy = y + t * sy
        gx = x + t * sx
        k = bins[gy, gx]
        if k < 0:
            continue
        lo = min(lo, k)
        hi = max(hi, k)
        wgt = spatial[t + radius] * colour_w[_packed_distance_to(left_packed[gy, gx], f0, f1, f2)]
        if use_right:
            kd = k + min_disp
            xf = x - kd
            xg = gx - kd
            if 0 <= xf < w and 0 <= xg < w:
                wgt *= match_w[_packed_distance(right_packed[y, xf], right_packed[gy, xg])]
            else:
                wgt *= outside_w
        hist[2 * k] += wgt
        hist[2 * k + 1] += wgt * disp[gy, gx]
    return lo, hi


@chunk_kernel
def _local_consistency_line_chunk(disp, bins, centres, left_packed, right_packed, min_disp: int, ndisp: int,
                                  radius: int, spatial, colour_w, match_w, outside_w: float, min_change: int,
                                  vertical: bool, use_right: bool, out, share, n_chunks: int, chunk: int) -> None:
    """:func:`local_consistency_line` on the centres of ``chunk`` (of ``n_chunks``), written into ``out``/``share``."""
    h, w = bins.shape
    n_centres = centres.shape[0]
    # Mass and weighted disparity sum of bin k side by side (hist[2k], hist[2k + 1]): one
    # cache line per bin rather than one in each of two arrays.
    hist = np.zeros(2 * ndisp, np.float32)
    for i in range(chunk * n_centres // n_chunks, (chunk + 1) * n_centres // n_chunks):
        y = centres[i] // w
        x = centres[i] - y * w
        own = bins[y, x]
        pos = y if vertical else x
        t0 = max(-radius, -pos)
        t1 = min(radius, (h if vertical else w) - 1 - pos)
        # Literal directions and right-term switch: each branch compiles one straight loop.
        if vertical and use_right:
            lo, hi = _line_votes(disp, bins, left_packed, right_packed, y, x, 1, 0, t0, t1, radius, min_disp,
                                 spatial, colour_w, match_w, outside_w, hist, True)
        elif vertical:
            lo, hi = _line_votes(disp, bins, left_packed, right_packed, y, x, 1, 0, t0, t1, radius, min_disp,
                                 spatial, colour_w, match_w, outside_w, hist, False)
        elif use_right:
            lo, hi = _line_votes(disp, bins, left_packed, right_packed, y, x, 0, 1, t0, t1, radius, min_disp,
                                 spatial, colour_w, match_w, outside_w, hist, True)
        else:
            lo, hi = _line_votes(disp, bins, left_packed, right_packed, y, x, 0, 1, t0, t1, radius, min_disp,
                                 spatial, colour_w, match_w, outside_w, hist, False)
        best = lo
        total = np.float32(0.0)
        for k in range(lo, hi + 1):
            total += hist[2 * k]
            if hist[2 * k] > hist[2 * best]:
                best = k
        if total > 0:
            share[y, x] = hist[2 * best] / total
            if abs(best - own) >= min_change:
                out[y, x] = hist[2 * best + 1] / hist[2 * best]
        for k in range(2 * lo, 2 * hi + 2):
            hist[k] = 0.0


def local_consistency_line(disp, bins, centres, left_packed, right_packed, min_disp: int, ndisp: int, radius: int,
                           spatial, colour_w, match_w, outside_w: float, min_change: int, vertical: bool,
                           use_right: bool = True):
    """Mattoccia's locally consistent vote along one line per pixel: the row segment
    ``|x' − x| ≤ radius`` (or, ``vertical``, the column segment) instead of the square window.

    ``bins`` (H, W) int32 from :func:`~stereocli.matching.kernels.maps.disparity_bins`; ``centres``
    (N,) int64 ascending flat indices ``y·W + x`` of :func:`line_centre_mask`'s pixels;
    ``left_packed``/``right_packed`` (H, W) int64 from :func:`packed_quarter_levels`. Every valid
    g on the segment of f votes for its bin with
    ``spatial[t + radius] · colour_w[ΔL(f, g)] · match_w[ΔR(f − d_g, g − d_g)]`` (t = g − f;
    ``outside_w`` when either right point is outside the image; no right-image factor when
    ``use_right`` is false): the plausibilities of :func:`local_consistency`, tabulated over
    summed quarter-level channel differences. f takes the weighted mean disparity of the
    winning bin (most mass, smaller bin on ties) when that bin is at least ``min_change``
    bins from its own, and keeps its value otherwise. Returns ``(disparity, share)``: share =
    the winning bin's part of the vote mass at the centres, 1 elsewhere.
    """
    h, w = bins.shape
    out = disp.copy()
    share = np.ones((h, w), np.float32)
    n_chunks = min(centres.shape[0], 64)  # centres cluster along edges: many small chunks balance the threads
    for_chunks(_local_consistency_line_chunk, n_chunks, disp, bins, centres, left_packed, right_packed, min_disp,
               ndisp, radius, spatial, colour_w, match_w, outside_w, min_change, vertical, use_right, out, share,
               n_chunks)
    return out, share
