"""Compiled kernels of the segmentation-based refinements: region labelling, per-segment
plane fitting (RANSAC and histogram voting) and locally consistent voting (Mattoccia)."""

from __future__ import annotations

import numpy as np

from . import chunk_kernel, for_chunks, for_rows, njit, prange

INF = np.float32(np.inf)


# --- segmentation -------------------------------------------------------------------------


@njit(cache=True)
def _find(parent: np.ndarray, i: int) -> int:
    root = i
    while parent[root] != root:
        root = parent[root]
    while parent[i] != root:  # path compression
        nxt = parent[i]
        parent[i] = root
        i = nxt
    return root


@njit(cache=True)
def _union(parent: np.ndarray, size: np.ndarray, a: int, b: int) -> None:
    ra = _find(parent, a)
    rb = _find(parent, b)
    if ra == rb:
        return
    if size[ra] < size[rb] or (size[ra] == size[rb] and rb < ra):
        ra, rb = rb, ra
    parent[rb] = ra
    size[ra] += size[rb]


@njit(cache=True, inline="always")
def _similar(img, y: int, x: int, yy: int, xx: int, tolerance: float) -> bool:
    # The largest channel difference of two pixels is within the tolerance.
    diff = 0.0
    for ch in range(img.shape[2]):
        diff = max(diff, abs(img[y, x, ch] - img[yy, xx, ch]))
    return diff <= tolerance


@chunk_kernel
def _label_regions_chunk(img, tolerance: float, min_size: int, labels, n_chunks: int, chunk: int) -> None:
    """:func:`label_regions` into ``labels`` (a single chunk: the union-find runs serially).

    The components do not depend on the order of the unions, so the first pass joins each row's
    runs of similar pixels directly (each pixel points at its run's first pixel) and unites runs
    of neighbouring rows only where a vertical link starts a new pair of runs. The merge of small
    components then visits, in raster order, only the links between two first-pass components
    (the others join a component with itself)."""
    h, w, _ = img.shape
    n = h * w
    parent = np.arange(n)
    size = np.ones(n, np.int64)
    right = np.zeros((h, w), np.bool_)  # pixel linked to its right neighbour
    for y in range(h):
        head = y * w
        for x in range(w - 1):
            right[y, x] = _similar(img, y, x, y, x + 1, tolerance)
            if right[y, x]:
                parent[y * w + x + 1] = head
                size[head] += 1
            else:
                head = y * w + x + 1
    for y in range(h - 1):
        down_before = False  # pixel x − 1 linked to the pixel below it
        for x in range(w):
            down = _similar(img, y, x, y + 1, x, tolerance)
            # The link at x − 1 joined the same two runs when both rows link x − 1 to x.
            if down and not (down_before and right[y, x - 1] and right[y + 1, x - 1]):
                _union(parent, size, y * w + x, (y + 1) * w + x)
            down_before = down
    first = np.empty(n, np.int64)  # each pixel's first-pass component (its root)
    for i in range(n):
        first[i] = _find(parent, i)
    for y in range(h):
        for x in range(w):
            i = y * w + x
            for dy, dx in ((0, 1), (1, 0)):
                yy, xx = y + dy, x + dx
                if yy >= h or xx >= w:
                    continue
                j = yy * w + xx
                if first[i] == first[j]:
                    continue
                ra, rb = _find(parent, first[i]), _find(parent, first[j])
                if ra != rb and (size[ra] < min_size or size[rb] < min_size):
                    _union(parent, size, ra, rb)
    remap = np.full(n, -1, np.int64)
    nxt = 0
    for y in range(h):
        for x in range(w):
            r = _find(parent, first[y * w + x])
            if remap[r] < 0:
                remap[r] = nxt
                nxt += 1
            labels[y, x] = remap[r]


def label_regions(img: np.ndarray, tolerance: float, min_size: int) -> np.ndarray:
    """Connected components of 4-neighbours whose colours differ by at most ``tolerance``.

    ``img`` is (H, W, C) float32 (e.g. mean-shift filtered); the difference is the largest
    channel difference. Components smaller than ``min_size`` pixels are then merged into an
    adjacent component (raster order of the edges, Felzenszwalb–Huttenlocher 2004 style).
    Returns int32 (H, W) labels 0..n-1 in raster order of first appearance (deterministic).
    """
    labels = np.empty(img.shape[:2], np.int32)
    for_chunks(_label_regions_chunk, 1, np.ascontiguousarray(img, dtype=np.float32), float(tolerance), int(min_size),
               labels, 1)
    return labels


# --- plane fitting ----------------------------------------------------------------------


@njit(cache=True, inline="always")
def _xorshift(state: np.ndarray) -> int:
    # xorshift64* (Vigna 2016): a tiny deterministic per-segment RNG, independent of threads.
    s = state[0]
    s ^= s >> np.uint64(12)
    s ^= s << np.uint64(25)
    s ^= s >> np.uint64(27)
    state[0] = s
    return int((s * np.uint64(2685821657736338717)) >> np.uint64(33))


@njit(cache=True)
def _solve3(m: np.ndarray, v: np.ndarray, out: np.ndarray) -> bool:
    """Solve the 3×3 system m·out = v by Cramer's rule; False when (nearly) singular."""
    det = (m[0, 0] * (m[1, 1] * m[2, 2] - m[1, 2] * m[2, 1])
           - m[0, 1] * (m[1, 0] * m[2, 2] - m[1, 2] * m[2, 0])
           + m[0, 2] * (m[1, 0] * m[2, 1] - m[1, 1] * m[2, 0]))
    scale = 0.0
    for i in range(3):
        for j in range(3):
            scale = max(scale, abs(m[i, j]))
    if scale == 0.0 or abs(det) <= 1e-9 * scale * scale * scale:
        return False
    for col in range(3):
        t = m.copy()
        for i in range(3):
            t[i, col] = v[i]
        out[col] = (t[0, 0] * (t[1, 1] * t[2, 2] - t[1, 2] * t[2, 1])
                    - t[0, 1] * (t[1, 0] * t[2, 2] - t[1, 2] * t[2, 0])
                    + t[0, 2] * (t[1, 0] * t[2, 1] - t[1, 1] * t[2, 0])) / det
    return True


@njit(cache=True)
def _least_squares(xs, ys, ds, plane, inlier: float, out: np.ndarray) -> int:
    """Least-squares plane through the points within ``inlier`` of ``plane``; returns count."""
    m = np.zeros((3, 3))
    v = np.zeros(3)
    cnt = 0
    for i in range(xs.shape[0]):
        r = ds[i] - (plane[0] * xs[i] + plane[1] * ys[i] + plane[2])
        if abs(r) <= inlier:
            row = (xs[i], ys[i], 1.0)
            for a in range(3):
                v[a] += row[a] * ds[i]
                for b in range(3):
                    m[a, b] += row[a] * row[b]
            cnt += 1
    if cnt >= 3 and _solve3(m, v, out):
        return cnt
    return 0


@njit(cache=True)
def _count_inliers(xs, ys, ds, plane, inlier: float) -> int:
    cnt = 0
    for i in range(xs.shape[0]):
        if abs(ds[i] - (plane[0] * xs[i] + plane[1] * ys[i] + plane[2])) <= inlier:
            cnt += 1
    return cnt


@njit(cache=True)
def _densest(values: np.ndarray, width: float) -> float:
    """1-D Hough vote: mean of the largest set of values lying in a window of ``width``."""
    v = np.sort(values)
    n = v.shape[0]
    best_i, best_n = 0, 0
    j = 0
    for i in range(n):
        while j < n and v[j] - v[i] <= width:
            j += 1
        if j - i > best_n:
            best_n = j - i
            best_i = i
    s = 0.0
    for t in range(best_i, best_i + best_n):
        s += v[t]
    return s / best_n


@chunk_kernel
def _fit_planes_chunk(disp, labels, order, starts, method: int, iterations: int, inlier: float, min_points: int,
                      seed: int, slope_bin: float, planes, support, inliers, n_chunks: int, chunk: int) -> None:
    """:func:`fit_planes` for the segments of ``chunk`` (of ``n_chunks``), written into
    ``planes``, ``support`` and ``inliers``."""
    h, w = disp.shape
    nseg = starts.shape[0] - 1
    for s in range(chunk * nseg // n_chunks, (chunk + 1) * nseg // n_chunks):
        a0, a1 = starts[s], starts[s + 1]
        n = 0
        for t in range(a0, a1):
            p = order[t]
            if np.isfinite(disp[p // w, p % w]):
                n += 1
        support[s] = n
        if n < max(min_points, 3):
            continue
        xs = np.empty(n)
        ys = np.empty(n)
        ds = np.empty(n)
        i = 0
        cx = 0.0
        cy = 0.0
        for t in range(a0, a1):
            p = order[t]
            d = disp[p // w, p % w]
            if np.isfinite(d):
                xs[i] = p % w
                ys[i] = p // w
                ds[i] = d
                cx += xs[i]
                cy += ys[i]
                i += 1
        cx /= n
        cy /= n
        for i in range(n):
            xs[i] -= cx
            ys[i] -= cy
        best = np.zeros(3)
        cand = np.zeros(3)
        best_cnt = -1
        if method == 0:
            rng = np.empty(1, np.uint64)
            rng[0] = np.uint64(seed) * np.uint64(6364136223846793005) + np.uint64(s) * np.uint64(1442695040888963407) + np.uint64(1)
            m = np.empty((3, 3))
            v = np.empty(3)
            for _ in range(iterations):
                for r in range(3):
                    q = _xorshift(rng) % n
                    m[r, 0] = xs[q]
                    m[r, 1] = ys[q]
                    m[r, 2] = 1.0
                    v[r] = ds[q]
                if not _solve3(m, v, cand):
                    continue
                cnt = _count_inliers(xs, ys, ds, cand, inlier)
                if cnt > best_cnt:
                    best_cnt = cnt
                    best[:] = cand
            if best_cnt < 0:  # all samples degenerate (e.g. a single row): constant plane
                best[0] = 0.0
                best[1] = 0.0
                best[2] = _densest(ds, 2.0 * inlier)
        else:
            # Slopes from neighbour differences within the segment (both pixels reliable).
            gx = np.empty(a1 - a0)
            gy = np.empty(a1 - a0)
            nx = 0
            ny = 0
            for t in range(a0, a1):
                p = order[t]
                y, x = p // w, p % w
                d = disp[y, x]
                if not np.isfinite(d):
                    continue
                if x + 1 < w and labels[y, x + 1] == s and np.isfinite(disp[y, x + 1]):
                    gx[nx] = disp[y, x + 1] - d
                    nx += 1
                if y + 1 < h and labels[y + 1, x] == s and np.isfinite(disp[y + 1, x]):
                    gy[ny] = disp[y + 1, x] - d
                    ny += 1
            best[0] = _densest(gx[:nx], slope_bin) if nx > 0 else 0.0
            best[1] = _densest(gy[:ny], slope_bin) if ny > 0 else 0.0
            res = np.empty(n)
            for i in range(n):
                res[i] = ds[i] - best[0] * xs[i] - best[1] * ys[i]
            best[2] = _densest(res, 2.0 * inlier)
        # Least-squares refits on the inliers (two rounds: the inlier set settles).
        for _ in range(2):
            cnt = _least_squares(xs, ys, ds, best, inlier, cand)
            if cnt == 0:
                break
            best[:] = cand
        inliers[s] = _count_inliers(xs, ys, ds, best, inlier)
        planes[s, 0] = best[0]
        planes[s, 1] = best[1]
        planes[s, 2] = best[2]
        planes[s, 3] = cx
        planes[s, 4] = cy


@chunk_kernel
def _pixels_by_segment_chunk(flat, starts, order, n_chunks: int, chunk: int) -> None:
    """:func:`pixels_by_segment` (one chunk: a counting sort is one pass over the pixels)."""
    next_slot = starts[:-1].copy()
    for i in range(flat.shape[0]):
        label = flat[i]
        order[next_slot[label]] = i
        next_slot[label] += 1


def pixels_by_segment(labels: np.ndarray):
    """The flat pixel indices grouped by segment, each segment's in increasing order (as a
    stable argsort of the labels gives them, by a counting sort: O(n) instead of O(n log n)), and
    ``(order, starts, counts)``: segment s holds ``order[starts[s]:starts[s + 1]]``;
    ``labels`` (H, W) int32 0..n−1."""
    flat = np.ascontiguousarray(labels).ravel()
    counts = np.bincount(flat, minlength=int(flat.max()) + 1 if flat.size else 0)
    starts = np.zeros(counts.shape[0] + 1, np.int64)
    np.cumsum(counts, out=starts[1:])
    order = np.empty(flat.shape[0], np.int64)
    for_chunks(_pixels_by_segment_chunk, 1, flat, starts, order, 1)
    return order, starts, counts


def fit_planes(disp, labels, order, starts, method: int, iterations: int, inlier: float,
               min_points: int, seed: int, slope_bin: float):
    """Fit ``d = a·(x − cx) + b·(y − cy) + c`` per segment to its finite disparities.

    ``order``/``starts``: flat pixel indices sorted by label and the start of each label's run
    (length n_segments + 1). ``method`` 0 = RANSAC (3-point samples from a per-segment
    xorshift RNG seeded by ``seed`` and the segment id, best inlier count, then least-squares
    refits on the inliers), 1 = histogram voting (slopes a, b as the densest bin of horizontal
    / vertical disparity differences inside the segment, then c likewise; Klaus et al. 2006),
    followed by the same least-squares refits.

    Returns (planes (n, 5) float64 [a, b, c, cx, cy], support (n,) int64 reliable pixels,
    inliers (n,) int64); segments with fewer than ``min_points`` reliable pixels or a
    degenerate fit get inliers = 0.
    """
    nseg = starts.shape[0] - 1
    planes = np.zeros((nseg, 5))
    support = np.zeros(nseg, np.int64)
    inliers = np.zeros(nseg, np.int64)
    n_chunks = max(1, min(nseg, 16))  # segments differ in size: several chunks per thread balance them
    for_chunks(_fit_planes_chunk, n_chunks, disp, labels, order, starts, int(method), int(iterations), float(inlier),
               int(min_points), int(seed), float(slope_bin), planes, support, inliers, n_chunks)
    return planes, support, inliers


@chunk_kernel
def _replace_by_planes_rows(disp, labels, planes, use_plane, outlier: float, replace_all: bool, lo: float,
                            hi: float, out, y0: int, y1: int) -> None:
    """:func:`replace_by_planes` on rows ``y0`` to ``y1`` (exclusive) of ``out``."""
    w = disp.shape[1]
    for y in range(y0, y1):
        for x in range(w):
            s = labels[y, x]
            if not use_plane[s]:
                continue
            pv = planes[s, 0] * (x - planes[s, 3]) + planes[s, 1] * (y - planes[s, 4]) + planes[s, 2]
            pv = min(max(pv, lo), hi)
            d = disp[y, x]
            if replace_all or not np.isfinite(d) or abs(d - pv) > outlier:
                out[y, x] = np.float32(pv)


def replace_by_planes(disp, labels, planes, use_plane, outlier: float, replace_all: bool,
                      lo: float, hi: float) -> np.ndarray:
    """Replace invalid pixels and outliers (|d − plane| > ``outlier``) by their segment's plane
    (all pixels with ``replace_all``), for segments with ``use_plane``; plane values are clipped
    to the search range [lo, hi]."""
    out = disp.copy()
    for_rows(_replace_by_planes_rows, disp.shape[0], disp, labels, planes, use_plane, outlier, replace_all, lo, hi,
             out)
    return out


# --- locally consistent voting (Mattoccia) -----------------------------------------------


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

    ``bins`` (H, W) int32 from :func:`~stereocli.matching.kernels.maps.disparity_bins`; ``centres`` (N,) int64 ascending flat
    indices ``y·W + x`` of :func:`line_centre_mask`'s pixels; ``left_packed``/``right_packed`` (H, W) int64 from
    :func:`packed_quarter_levels`. Every valid g on the segment of f votes for its bin with
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


# --- geodesic vote (running votes along rows and columns) ---------------------------------

#: A running vote's scale below which its stored masses are folded back (float64 keeps ~300
#: decades; the product of the per-pixel decays can shrink fast across strong colour edges).
_RESCALE_BELOW = 1e-30


@njit(cache=True, inline="always")
def _running_add(kk, mm, ss, entry, n: int, k: int, m: float, s: float) -> int:
    """Add scaled mass ``m`` and disparity sum ``s`` to bin ``k`` of a running vote of
    ``n`` entries (at most ``kk.shape[0]``; a new bin then replaces the one with the least
    mass). ``entry[bin]`` is the entry holding each kept bin, −1 for the others: one lookup
    instead of a search (a bin changes every few pixels along a line, and the search's
    branches were most of the vote's time). Returns the new ``n``."""
    j = entry[k]
    if j >= 0:
        mm[j] += m
        ss[j] += s
        return n
    if n < kk.shape[0]:
        kk[n] = k
        mm[n] = m
        ss[n] = s
        entry[k] = n
        return n + 1
    weakest = 0
    for j in range(1, n):
        if mm[j] < mm[weakest]:
            weakest = j
    entry[kk[weakest]] = -1
    kk[weakest] = k
    mm[weakest] = m
    ss[weakest] = s
    entry[k] = weakest
    return n


@njit(cache=True, inline="always")
def _forget_bins(kk, entry, n: int) -> None:
    # Before a running vote restarts empty: its kept bins leave the entry map.
    for j in range(n):
        entry[kk[j]] = -1


@njit(cache=True, inline="always")
def _empty_vote():
    # A running vote with no votes yet: ``(n, scale, run_k, run_m, run_s)`` (no kept bins, no
    # run, stored values equal to true ones).
    return 0, 1.0, -1, 0.0, 0.0


@njit(cache=True, inline="always")
def _decay_vote(mm, ss, n: int, scale: float, run_m: float, run_s: float, weight: float):
    """One step along the line: every vote so far is multiplied by ``weight`` — the run's true
    values directly, the kept bins through ``scale`` (folded back into them when it gets tiny).
    Returns ``(scale, run_m, run_s)``."""
    scale *= weight
    run_m *= weight
    run_s *= weight
    if scale < _RESCALE_BELOW:
        for j in range(n):
            mm[j] *= scale
            ss[j] *= scale
        scale = 1.0
    return scale, run_m, run_s


@njit(cache=True, inline="always")
def _add_vote(kk, mm, ss, entry, n: int, scale: float, run_k: int, run_m: float, run_s: float, k: int, d: float):
    """Add a pixel's vote (bin ``k``, disparity ``d``): to the run when it continues it, else
    the run joins the kept bins and a new run starts (``k`` < 0: end the run only). Returns
    ``(n, run_k, run_m, run_s)``."""
    if k != run_k:
        if run_k >= 0:
            n = _running_add(kk, mm, ss, entry, n, run_k, run_m / scale, run_s / scale)
        run_k = k
        run_m = 0.0
        run_s = 0.0
    if k >= 0:
        run_m += 1.0
        run_s += d
    return n, run_k, run_m, run_s


@njit(cache=True, inline="always")
def _heavier(best: int, best_m: float, best_s: float, b: int, m: float, s: float):
    # The winner so far (bin, mass, disparity sum) against bin b: more mass wins, then the
    # smaller bin.
    if m > best_m or (m == best_m and b < best):
        return b, m, s
    return best, best_m, best_s


@njit(cache=True, inline="always")
def _plus_kept(mm, ss, entry, scale: float, b: int, m: float, s: float):
    # (m, s) plus bin b's true mass and disparity sum in a running vote's kept bins, if it
    # keeps b (``entry``: the entry holding each bin, −1 for the others).
    j = entry[b]
    if j >= 0:
        m += mm[j] * scale
        s += ss[j] * scale
    return m, s


@njit(cache=True, inline="always")
def _holds(bins, n: int, b: int) -> bool:
    # Whether the first n entries of bins hold b.
    for i in range(n):
        if bins[i] == b:
            return True
    return False


#: Columns a vertical pass copies at once into row buffers (a tile of whole cache lines), so
#: the line code reads contiguous memory in both directions and compiles once.
_COLUMN_BLOCK = 16


@chunk_kernel
def _vote_chunk(disp, bins, packed, centre, passed, min_change: int, max_bins: int, n_bins: int,
                vertical: bool, min_lead: float, out, n_chunks: int, chunk: int) -> None:
    """:func:`geodesic_vote_line` on the lines of ``chunk`` (of ``n_chunks``), written into ``out``."""
    h, w = bins.shape
    n_lines = w if vertical else h
    n_pos = h if vertical else w
    # Per-thread buffers, reused for every line of the chunk.
    centres = np.empty(n_pos, np.int64)
    decay = np.empty(n_pos, np.float64)  # decay[p]: weight passed between positions p - 1 and p
    fk = np.empty((n_pos, max_bins + 1), np.int32)  # forward vote saved at each centre (true masses)
    fm = np.empty((n_pos, max_bins + 1), np.float64)
    fs = np.empty((n_pos, max_bins + 1), np.float64)
    fn = np.zeros(n_pos, np.int64)
    kk = np.empty(max_bins, np.int32)
    entry = np.full(n_bins, -1, np.int32)  # the entry of kk holding each bin, -1 if none
    n = 0  # bins the running vote keeps (carried to the next reset, which clears them from entry)
    mm = np.empty(max_bins, np.float64)  # masses and disparity sums, stored divided by ``scale``
    ss = np.empty(max_bins, np.float64)
    # A vertical pass copies _COLUMN_BLOCK columns at a time into these, as rows.
    block = _COLUMN_BLOCK if vertical else 0
    disp_t = np.empty((block, n_pos), np.float32)
    bins_t = np.empty((block, n_pos), np.int32)
    packed_t = np.empty((block, n_pos), np.int64)
    centre_t = np.empty((block, n_pos), np.bool_)
    first, stop = chunk * n_lines // n_chunks, (chunk + 1) * n_lines // n_chunks
    for block_start in range(first, stop, max(block, 1)):
        if vertical:
            nb = min(block, stop - block_start)
            for y in range(h):
                for j in range(nb):
                    disp_t[j, y] = disp[y, block_start + j]
                    bins_t[j, y] = bins[y, block_start + j]
                    packed_t[j, y] = packed[y, block_start + j]
                    centre_t[j, y] = centre[y, block_start + j]
        else:
            nb = 1
        for j in range(nb):
            line = block_start + j
            if vertical:
                d_line, b_line, c_line, p_line = disp_t[j], bins_t[j], centre_t[j], packed_t[j]
            else:
                d_line, b_line, c_line, p_line = disp[line], bins[line], centre[line], packed[line]
            n_centres = 0
            for p in range(n_pos):
                if c_line[p]:
                    centres[n_centres] = p
                    n_centres += 1
            if n_centres == 0:
                continue
            # Forward: the running vote arriving at each centre (before its own vote). The
            # current run of one bin is kept in true values (decayed by one multiply-add per
            # pixel); the other bins in stored values, true = stored × scale, so decaying them
            # is one multiplication of ``scale``.
            # Votes beyond the last centre never reach a decision in this direction (nor, in
            # the backward pass, votes before the first), so each pass stops there.
            _forget_bins(kk, entry, n)
            n, scale, run_k, run_m, run_s = _empty_vote()
            ci = 0
            for p in range(centres[n_centres - 1] + 1):
                if p > 0:
                    decay[p] = passed[_packed_distance(p_line[p], p_line[p - 1])]  # kept for the backward pass
                    scale, run_m, run_s = _decay_vote(mm, ss, n, scale, run_m, run_s, decay[p])
                if ci < n_centres and centres[ci] == p:
                    n, run_k, run_m, run_s = _add_vote(kk, mm, ss, entry, n, scale, run_k, run_m, run_s, -1, 0.0)
                    for i in range(n):
                        fk[ci, i] = kk[i]
                        fm[ci, i] = mm[i] * scale
                        fs[ci, i] = ss[i] * scale
                    fn[ci] = n
                    ci += 1
                k = b_line[p]
                if k >= 0:
                    n, run_k, run_m, run_s = _add_vote(kk, mm, ss, entry, n, scale, run_k, run_m, run_s, k,
                                                       d_line[p])
            # Backward, deciding each centre from its own vote and both running votes.
            _forget_bins(kk, entry, n)
            n, scale, run_k, run_m, run_s = _empty_vote()
            ci = n_centres - 1
            for p in range(n_pos - 1, centres[0] - 1, -1):
                if p < n_pos - 1:
                    if p >= centres[n_centres - 1]:  # beyond the forward pass: its weight is not kept
                        decay[p + 1] = passed[_packed_distance(p_line[p + 1], p_line[p])]
                    scale, run_m, run_s = _decay_vote(mm, ss, n, scale, run_m, run_s, decay[p + 1])
                k = b_line[p]
                d = d_line[p]
                if ci >= 0 and centres[ci] == p:
                    n, run_k, run_m, run_s = _add_vote(kk, mm, ss, entry, n, scale, run_k, run_m, run_s, -1, 0.0)
                    # Each bin's mass: its own vote, then the forward and the backward running
                    # votes (each holds a bin once; the backward one is found through entry).
                    best, best_m, best_s = -1, -1.0, 0.0
                    own_m = 0.0  # the own bin's mass once counted (at least its own vote, 1)
                    f_n = fn[ci]
                    for i in range(f_n):
                        b = fk[ci, i]
                        m, s = fm[ci, i], fs[ci, i]
                        if b == k:
                            m, s = 1.0 + m, d + s
                        m, s = _plus_kept(mm, ss, entry, scale, b, m, s)
                        if b == k:
                            own_m = m
                        best, best_m, best_s = _heavier(best, best_m, best_s, b, m, s)
                    if own_m == 0.0:  # the forward vote does not hold the own bin
                        own_m, s = _plus_kept(mm, ss, entry, scale, k, 1.0, np.float64(d))
                        best, best_m, best_s = _heavier(best, best_m, best_s, k, own_m, s)
                    for i in range(n):  # backward bins neither own nor forward
                        b = kk[i]
                        if b != k and not _holds(fk[ci], f_n, b):
                            best, best_m, best_s = _heavier(best, best_m, best_s, b, mm[i] * scale, ss[i] * scale)
                    if abs(best - k) >= min_change and best_m >= min_lead * own_m:
                        v = np.float32(best_s / best_m)
                        if vertical:
                            out[p, line] = v
                        else:
                            out[line, p] = v
                    ci -= 1
                if k >= 0:
                    n, run_k, run_m, run_s = _add_vote(kk, mm, ss, entry, n, scale, run_k, run_m, run_s, k, d)


def geodesic_vote_line(disp, bins, packed, centre, passed, min_change: int, max_bins: int, n_bins: int,
                       vertical: bool, min_lead: float = 1.0):
    """One pass of the geodesic vote along the rows (or, ``vertical``, the columns).

    Every valid pixel g of a line votes for its 1-px bin with the product of the weights
    ``passed[ΔC]`` of the neighbour pairs between g and the pixel f being decided (ΔC:
    summed quarter-level channel difference of the two neighbours, ``packed`` colours from
    :func:`packed_quarter_levels`): support travels along the line through similar colours
    and dies at colour edges, so a pixel sides with the surface it is connected to by colour
    (a recursive, edge-aware filter in the manner of Yang's recursive bilateral filter, with
    votes per disparity bin). One pass from each end gives every pixel both halves of the sum
    in O(1) per pixel and bin kept: each running vote keeps the ``max_bins`` bins of most mass
    (a new bin replaces the weakest). Pixels with ``centre`` (H, W) bool take the weighted
    mean disparity of the winning bin when it is at least ``min_change`` bins from their own
    and its mass at least ``min_lead`` times their own bin's; the others keep their value.
    ``disp`` (H, W) float32 +inf invalid; ``bins`` from
    :func:`~stereocli.matching.kernels.maps.disparity_bins`, all below ``n_bins``. Returns the new map.
    """
    out = disp.copy()
    n_lines = bins.shape[1] if vertical else bins.shape[0]
    n_chunks = min(n_lines, 8)  # few chunks: each allocates its line buffers
    for_chunks(_vote_chunk, n_chunks, disp, bins, packed, centre, passed, min_change, max_bins, n_bins, vertical,
               float(min_lead), out, n_chunks)
    return out
