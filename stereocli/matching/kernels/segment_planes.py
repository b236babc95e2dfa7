"""Compiled kernels of the segment planes refinement (``plane_fit``): region labelling,
per-segment plane fitting (RANSAC and histogram voting) and replacing disparities by the planes."""

from __future__ import annotations

import numpy as np

from ...runtime import chunk_kernel, for_chunks, for_rows, njit

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
            rng[0] = (np.uint64(seed) * np.uint64(6364136223846793005)
                      + np.uint64(s) * np.uint64(1442695040888963407) + np.uint64(1))
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
