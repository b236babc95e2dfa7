"""Compiled kernels for local cost aggregation over (H, W, D) float32 cost volumes.

Layout: ``cost[y, x, k]`` is the cost of left (x, y) against right (x - (min_disp + k), y);
lower is better. Every kernel returns a new volume in the same layout (entries whose right pixel
is outside the image hold ``cost_max``). Small pure-numpy references live in
``tests/test_aggregation.py``.
"""

from __future__ import annotations

import numpy as np

from ...runtime import chunk_kernel, for_rows, njit, prange


@njit(cache=True, inline="always")
def _valid_k_range(x: int, min_disp: int, ndisp: int, width: int):
    klo = max(0, x - min_disp - width + 1)
    khi = min(ndisp - 1, x - min_disp)
    return klo, khi


@njit(cache=True, parallel=True)
def restore_impossible(cost: np.ndarray, min_disp: int, cost_max: float) -> None:
    """Set ``cost_max`` where the right pixel ``x - d`` is outside the image (in place).

    Aggregation mixes neighbouring entries; this keeps the contract that impossible
    hypotheses hold exactly ``cost_max`` (WTA then never picks them).
    """
    h, w, nd = cost.shape
    cmax = np.float32(cost_max)
    for y in prange(h):
        for x in range(w):
            klo, khi = _valid_k_range(x, min_disp, nd, w)
            for k in range(min(klo, nd)):
                cost[y, x, k] = cmax
            for k in range(max(khi + 1, 0), nd):
                cost[y, x, k] = cmax


@njit(cache=True, parallel=True)
def extend_border_costs(cost: np.ndarray, min_disp: int) -> None:
    """Replace impossible entries by the nearest possible entry of the same row and slice
    (in place).

    Supports that reach past the left border would otherwise average in ``cost_max`` for large
    disparities only, biasing pixels near the border towards small disparities; replicating
    the border costs is the same as clamping the right image at its border.
    """
    h, w, nd = cost.shape
    for y in prange(h):
        for k in range(nd):
            x0 = max(0, min_disp + k)  # first x with x - d >= 0
            x1 = min(w - 1, w - 1 + min_disp + k)  # last x with x - d <= w - 1
            if x0 > w - 1 or x1 < 0:
                continue
            v = cost[y, x0, k]
            for x in range(0, x0):
                cost[y, x, k] = v
            v = cost[y, x1, k]
            for x in range(x1 + 1, w):
                cost[y, x, k] = v


# --- multiple windows ----------------------------------------------------------------------


@njit(cache=True, parallel=True)
def multiple_windows(box: np.ndarray, off_y: np.ndarray, off_x: np.ndarray, keep: int) -> np.ndarray:
    """Centre window plus the ``keep`` best of the surrounding windows (Fusiello et al. 1997;
    Hirschmüller et al. 2002).

    ``box`` holds window means; ``off_y``/``off_x`` the centres of the surrounding windows
    relative to the pixel (clamped at the border). Result = (C_0 + Σ best ``keep``)/(keep + 1).
    """
    h, w, nd = box.shape
    m = off_y.size
    out = np.empty_like(box)
    for y in prange(h):
        vals = np.empty(m, np.float32)
        for x in range(w):
            for k in range(nd):
                for i in range(m):
                    yy = min(max(y + off_y[i], 0), h - 1)
                    xx = min(max(x + off_x[i], 0), w - 1)
                    vals[i] = box[yy, xx, k]
                # partial selection sort: the keep smallest
                s = box[y, x, k]
                for j in range(keep):
                    bi = j
                    for i in range(j + 1, m):
                        if vals[i] < vals[bi]:
                            bi = i
                    t = vals[j]
                    vals[j] = vals[bi]
                    vals[bi] = t
                    s += vals[j]
                out[y, x, k] = s / (keep + 1)
    return out


# --- variable window (Veksler) -------------------------------------------------------------


@njit(cache=True)
def integral_volume(cost: np.ndarray) -> np.ndarray:
    """Summed-area table of each disparity slice, (H+1, W+1, D) float64, zero first row/col."""
    h, w, nd = cost.shape
    s = np.zeros((h + 1, w + 1, nd), np.float64)
    rowacc = np.empty(nd, np.float64)
    for y in range(h):
        rowacc[:] = 0.0
        for x in range(w):
            for k in range(nd):
                rowacc[k] += cost[y, x, k]
                s[y + 1, x + 1, k] = s[y, x + 1, k] + rowacc[k]
    return s


@njit(cache=True, parallel=True)
def variable_window(sat: np.ndarray, rad_y: np.ndarray, rad_x: np.ndarray, alpha: float) -> np.ndarray:
    """Best window per pixel and disparity among centred rectangles (Veksler 2003).

    Window cost = (Σ e + α) / |W| = mean error + α/|W|: the penalty α (cost units · px)
    favours large windows where the error is uniformly low. Each candidate window is O(1)
    from the summed-area table ``sat`` (clipped at the border).
    """
    h = sat.shape[0] - 1
    w = sat.shape[1] - 1
    nd = sat.shape[2]
    ns = rad_y.size
    out = np.empty((h, w, nd), np.float32)
    for y in prange(h):
        best = np.empty(nd, np.float64)
        for x in range(w):
            best[:] = np.inf
            for s in range(ns):
                y0 = max(0, y - rad_y[s])
                y1 = min(h, y + rad_y[s] + 1)
                x0 = max(0, x - rad_x[s])
                x1 = min(w, x + rad_x[s] + 1)
                inv = 1.0 / ((y1 - y0) * (x1 - x0))
                pen = alpha * inv
                for k in range(nd):
                    v = (sat[y1, x1, k] - sat[y0, x1, k] - sat[y1, x0, k] + sat[y0, x0, k]) * inv + pen
                    if v < best[k]:
                        best[k] = v
            for k in range(nd):
                out[y, x, k] = np.float32(best[k])
    return out


# --- cross-based support regions (Zhang et al. 2009) ---------------------------------------


#: Arm directions (dy, dx) in the order of the arms arrays: left, right, up, down.
ARM_STEPS = np.array([(0, -1), (0, 1), (-1, 0), (1, 0)], np.int64)


def channel_planes(image: np.ndarray) -> np.ndarray:
    """(H, W, C) -> (C, H, W) float32 C-contiguous, so each channel's rows load contiguously."""
    return np.ascontiguousarray(np.moveaxis(image, 2, 0), dtype=np.float32)


@chunk_kernel
def _arms_rows(planes, tau1: float, tau_step: float, tau2: float, max_len1: int, max_len2: int, arms,
               y0: int, y1: int) -> None:
    # Arm lengths (H, W, 4) of the (C, H, W) image, rows [y0, y1) into ``arms``: an arm grows
    # from p to q while D(p, q) < tau1, D(q_prev, q) < tau_step, and, beyond max_len2 px,
    # D(p, q) < tau2, up to max_len1 px (D = max over channels of |difference|); the first step
    # is always taken. All pixels of a row grow their arm one step at a time; every inner loop
    # runs over an aligned row slice with non-negative indices, so it vectorises.
    nc, h, w = planes.shape
    t1 = np.float32(tau1)
    ts = np.float32(tau_step)
    t2 = np.float32(tau2)
    growing = np.empty(w, np.bool_)  # row buffers, once per chunk of rows
    length = np.empty(w, np.int32)
    to_p = np.empty(w, np.float32)
    to_prev = np.empty(w, np.float32)
    for y in range(y0, y1):
        for a in range(4):
            dy = ARM_STEPS[a, 0]
            dx = ARM_STEPS[a, 1]
            growing[:] = True
            length[:] = 0
            for step in range(1, max_len1 + 1):
                qy = y + step * dy
                if qy < 0 or qy >= h:
                    break
                # Pixels x whose arm pixel q = x + step·dx is inside the row: [x0, x1).
                x0 = max(0, -step * dx)
                x1 = min(w, w - step * dx)
                growing[:x0] = False
                growing[x1:] = False
                n = x1 - x0
                if n <= 0:
                    break
                g = growing[x0:x1]
                ln = length[x0:x1]
                if step == 1:  # the first step is always taken: supports are never one pixel
                    for i in range(n):
                        ln[i] += g[i]
                    continue
                py = qy - dy  # the arm pixel before q
                centre = planes[0, y, x0:x1]
                here = planes[0, qy, x0 + step * dx:x1 + step * dx]
                before = planes[0, py, x0 + (step - 1) * dx:x1 + (step - 1) * dx]
                dp = to_p[x0:x1]
                dq = to_prev[x0:x1]
                if nc > 1:  # colour: the largest channel difference, channel by channel
                    dp[:] = 0.0
                    dq[:] = 0.0
                    for c in range(nc):
                        centre_c = planes[c, y, x0:x1]
                        here_c = planes[c, qy, x0 + step * dx:x1 + step * dx]
                        before_c = planes[c, py, x0 + (step - 1) * dx:x1 + (step - 1) * dx]
                        for i in range(n):
                            dp[i] = max(dp[i], abs(here_c[i] - centre_c[i]))
                            dq[i] = max(dq[i], abs(here_c[i] - before_c[i]))
                alive = 0
                for i in range(n):
                    # Grey images take the differences here (one pass over the row per step:
                    # about twice as fast as going through the buffers).
                    dpi = abs(here[i] - centre[i]) if nc == 1 else dp[i]
                    dqi = abs(here[i] - before[i]) if nc == 1 else dq[i]
                    ok = g[i] and dpi < t1 and dqi < ts and (step <= max_len2 or dpi < t2)
                    g[i] = ok
                    ln[i] += ok
                    alive += ok
                if alive == 0:
                    break
            for x in range(w):
                arms[y, x, a] = length[x]


def _arms(planes: np.ndarray, tau1: float, tau_step: float, tau2: float, max_len1: int, max_len2: int) -> np.ndarray:
    """Arm lengths (H, W, 4) int32 of the (C, H, W) float32 image (:func:`_arms_rows`)."""
    planes = np.ascontiguousarray(planes, dtype=np.float32)
    arms = np.zeros((planes.shape[1], planes.shape[2], 4), np.int32)
    for_rows(_arms_rows, planes.shape[1], planes, float(tau1), float(tau_step), float(tau2), int(max_len1),
             int(max_len2), arms)
    return arms


def cross_arms_two_threshold(image: np.ndarray, tau1: float, tau2: float, max_len1: int, max_len2: int) -> np.ndarray:
    """Arm lengths (H, W, 4) int32 (left, right, up, down) by the two-threshold rule.

    Mei et al. (2011, eq. 4): the arm grows from p to q while
    (1) D_c(p, q) < τ1 and D_c(q, q_prev) < τ1 (q_prev = the arm pixel before q: the arm
    cannot cross an edge even where it returns to p's colour), (2) |p − q| ≤ L1, and
    (3) D_c(p, q) < τ2 once |p − q| > L2 (long arms only through very similar colours, so
    large textureless regions get large supports without leaking across weak edges).
    D_c = max over channels of the absolute difference. As in :func:`cross_arms`, every arm has
    length ≥ 1 where the image allows. ``image`` (H, W, C) float32.
    """
    return _arms(channel_planes(image), tau1, tau1, tau2, max_len1, max_len2)


def cross_arms(image: np.ndarray, tau: float, max_len: int) -> np.ndarray:
    """Arm lengths (H, W, 4) int32: left, right, up, down.

    An arm grows from p while the neighbour q satisfies max_c |I_c(q) − I_c(p)| < τ and the arm
    is at most ``max_len`` pixels (Zhang, Lu, Lafruit 2009, eq. 2); every arm has length ≥ 1
    where the image allows, so the support is never a single pixel. ``image`` (H, W, C) float32.
    """
    return _arms(channel_planes(image), tau, np.inf, np.inf, max_len, max_len)


@njit(cache=True, parallel=True)
def cross_sum_h(cost: np.ndarray, arms: np.ndarray) -> np.ndarray:
    """Σ over each pixel's horizontal segment [x − left arm, x + right arm] (1-D integral)."""
    h, w, nd = cost.shape
    out = np.empty((h, w, nd), np.float32)
    for y in prange(h):
        pre = np.zeros((w + 1, nd), np.float64)
        for x in range(w):
            for k in range(nd):
                pre[x + 1, k] = pre[x, k] + cost[y, x, k]
        for x in range(w):
            a = x - arms[y, x, 0]
            b = x + arms[y, x, 1] + 1
            for k in range(nd):
                out[y, x, k] = np.float32(pre[b, k] - pre[a, k])
    return out


@njit(cache=True, parallel=True)
def cross_sum_v(cost: np.ndarray, arms: np.ndarray) -> np.ndarray:
    """Σ over each pixel's vertical segment [y − up arm, y + down arm], column blocks in parallel."""
    h, w, nd = cost.shape
    out = np.empty((h, w, nd), np.float32)
    bw = 16
    nblocks = (w + bw - 1) // bw
    for b in prange(nblocks):
        x0 = b * bw
        x1 = min(w, x0 + bw)
        pre = np.zeros((h + 1, x1 - x0, nd), np.float64)
        for y in range(h):
            for x in range(x0, x1):
                for k in range(nd):
                    pre[y + 1, x - x0, k] = pre[y, x - x0, k] + cost[y, x, k]
        for y in range(h):
            for x in range(x0, x1):
                a = y - arms[y, x, 2]
                c = y + arms[y, x, 3] + 1
                for k in range(nd):
                    out[y, x, k] = np.float32(pre[c, x - x0, k] - pre[a, x - x0, k])
    return out


# --- adaptive support weights (Yoon–Kweon, segment support, fast bilateral) ----------------


@njit(cache=True, inline="always")
def _colour_weight(feat, seg, y, x, qy, qx, inv_gamma, use_segments):
    # float32 throughout (inv_gamma is float32): two exps per (pixel, offset) dominate the
    # kernel, single-precision sqrt/exp are cheaper, and the weights are float32 anyway.
    if use_segments and seg[y, x] == seg[qy, qx]:
        return np.float32(1.0)
    d = np.float32(0.0)
    for c in range(feat.shape[2]):
        v = feat[y, x, c] - feat[qy, qx, c]
        d += v * v
    return np.exp(-np.sqrt(d) * inv_gamma)


@njit(cache=True, parallel=True)
def weighted_support(cost: np.ndarray, feat_l: np.ndarray, feat_r: np.ndarray, seg_l: np.ndarray,
                     seg_r: np.ndarray, off_y: np.ndarray, off_x: np.ndarray, spatial: np.ndarray,
                     gamma_c: float, min_disp: int, cost_max: float, use_segments: bool,
                     min_weight: float) -> np.ndarray:
    """Symmetric adaptive-support-weight aggregation (Yoon & Kweon 2006, eq. 5).

    C'(p, d) = Σ_q w(p, q)·w(p̄, q̄)·C(q, d) / Σ_q w(p, q)·w(p̄, q̄), over the offsets
    ``(off_y, off_x)``; p̄, q̄ are the right pixels at disparity d. w(p, q) = ``spatial[o]`` ×
    exp(−‖f(p) − f(q)‖/γ_c) on the features ``feat`` (e.g. CIELab), or 1 inside the same
    segment when ``use_segments`` (Tombari et al. 2007). Left weights below ``min_weight`` are
    skipped (their contribution is negligible; it saves most of the work at edges).
    The right-view weights of one row are tabulated per offset, contiguous in x, so the inner
    loop over disparities reads them with unit stride.
    """
    h, w, nd = cost.shape
    n = off_y.size
    out = np.empty((h, w, nd), np.float32)
    inv_g = np.float32(1.0 / gamma_c)
    cmax = np.float32(cost_max)
    min_w = np.float32(min_weight)
    for y in prange(h):
        # wr[o, w - 1 - xr]: right weights stored mirrored so that the loop over k (xr = x − d
        # decreasing) reads them with increasing addresses and vectorises.
        # Padded by nd zeros on both sides: impossible hypotheses get weight 0, so the loop
        # over k needs no bounds and has a fixed trip count.
        wr = np.zeros((n, w + 2 * nd), np.float32)
        for o in range(n):
            qy = y + off_y[o]
            if qy < 0 or qy >= h:
                continue
            for xr in range(w):
                qx = xr + off_x[o]
                if qx < 0 or qx >= w:
                    continue
                wr[o, nd + w - 1 - xr] = spatial[o] * _colour_weight(feat_r, seg_r, y, xr, qy, qx, inv_g, use_segments)
        num = np.empty(nd, np.float32)
        den = np.empty(nd, np.float32)
        for x in range(w):
            klo, khi = _valid_k_range(x, min_disp, nd, w)
            num[:] = 0.0
            den[:] = 0.0
            j0 = nd + w - 1 - (x - min_disp)  # mirrored index of xr at k = 0
            if j0 < 0 or j0 + nd > w + 2 * nd:
                for k in range(nd):
                    out[y, x, k] = cmax
                continue
            for o in range(n):
                qy = y + off_y[o]
                qx = x + off_x[o]
                if qy < 0 or qy >= h or qx < 0 or qx >= w:
                    continue
                wl = spatial[o] * _colour_weight(feat_l, seg_l, y, x, qy, qx, inv_g, use_segments)
                if wl < min_w:
                    continue
                wro = wr[o]
                cq = cost[qy, qx]
                wrk = wro[j0:j0 + nd]
                for k in range(nd):
                    ww = wl * wrk[k]
                    num[k] += ww * cq[k]
                    den[k] += ww
            for k in range(nd):
                if k < klo or k > khi or den[k] <= 0:
                    out[y, x, k] = cmax
                else:
                    out[y, x, k] = num[k] / den[k]
    return out


# --- locally consistent (Mattoccia 2009) ---------------------------------------------------


@njit(cache=True, parallel=True)
def lc_plausibility(disp_k: np.ndarray, lab_l: np.ndarray, lab_r: np.ndarray, left: np.ndarray,
                    right: np.ndarray, min_disp: int, ndisp: int, radius: int, gamma_s: float,
                    gamma_c: float, gamma_t: float, truncate: float) -> np.ndarray:
    """Accumulated plausibility Ω_f(d) of every point f, normalised, as cost 1 − Ω_f(d)/Σ_d Ω_f.

    Each support centred at c (every pixel within ``radius`` of f) asserts its disparity
    d_c (``disp_k``: index k, −1 = none); its plausibility for f is
    exp(−Δ_s(f, c)/γ_s − Δ_c(f, c)/γ_c − Δ_c(f̄, c̄)/γ_c − min(AD(f, f̄), T)/γ_t), colours in
    CIELab (``lab_l``/``lab_r``), AD on the input images (Mattoccia 2009, eq. 1–4). Points no
    support asserts anything for get cost 1 (= cost_max) everywhere.
    """
    h, w, nc = left.shape
    out = np.empty((h, w, ndisp), np.float32)
    inv_s = 1.0 / gamma_s
    inv_c = 1.0 / gamma_c
    inv_t = 1.0 / gamma_t
    for y in prange(h):
        acc = np.empty(ndisp, np.float64)
        for x in range(w):
            acc[:] = 0.0
            for cy in range(max(0, y - radius), min(h, y + radius + 1)):
                for cx in range(max(0, x - radius), min(w, x + radius + 1)):
                    k = disp_k[cy, cx]
                    if k < 0:
                        continue
                    d = min_disp + k
                    xf = x - d
                    xc = cx - d
                    if xf < 0 or xf >= w or xc < 0 or xc >= w:
                        continue
                    ds = np.sqrt(float((cy - y) * (cy - y) + (cx - x) * (cx - x)))
                    dl = 0.0
                    dr = 0.0
                    for c in range(lab_l.shape[2]):
                        v = lab_l[y, x, c] - lab_l[cy, cx, c]
                        dl += v * v
                        v = lab_r[y, xf, c] - lab_r[cy, xc, c]
                        dr += v * v
                    ad = 0.0
                    for c in range(nc):
                        ad += abs(left[y, x, c] - right[y, xf, c])
                    ad = min(ad / nc, truncate)
                    acc[k] += np.exp(-ds * inv_s - (np.sqrt(dl) + np.sqrt(dr)) * inv_c - ad * inv_t)
            total = 0.0
            for k in range(ndisp):
                total += acc[k]
            for k in range(ndisp):
                out[y, x, k] = np.float32(1.0 - acc[k] / total) if total > 0 else np.float32(1.0)
    return out


#: Most channels the OpenCV Python binding converts for its filters (a volume is fed as H×W×D).
CV_MAX_CHANNELS = 128


def box_filter_volume(cost: np.ndarray, radius_y: int, radius_x: int) -> np.ndarray:
    """Mean of each cost slice over a (2·radius_y+1) × (2·radius_x+1) window, O(1) per pixel.

    Windows are clipped at the image border (the mean is over the pixels inside). OpenCV's
    running-sum box filter treats the D slices as channels (at most 128 per call), summing
    in double precision, then each window sum is divided by its pixel count.
    """
    import cv2  # here, not at the top: the kernels compile ahead of time without OpenCV (setup.py)

    cost = np.ascontiguousarray(cost, dtype=np.float32)
    h, w, nd = cost.shape
    ksize = (2 * radius_x + 1, 2 * radius_y + 1)
    count = cv2.boxFilter(np.ones((h, w), np.float32), -1, ksize, normalize=False,
                          borderType=cv2.BORDER_CONSTANT)
    inv = (1.0 / count).astype(np.float32)[..., None]
    out = np.empty_like(cost)
    for k0 in range(0, nd, CV_MAX_CHANNELS):
        k1 = min(nd, k0 + CV_MAX_CHANNELS)
        chunk = cost if (k0 == 0 and k1 == nd) else np.ascontiguousarray(cost[:, :, k0:k1])
        total = cv2.boxFilter(chunk, -1, ksize, normalize=False, borderType=cv2.BORDER_CONSTANT)
        np.multiply(total.reshape(h, w, k1 - k0), inv, out=out[:, :, k0:k1])
    return out
