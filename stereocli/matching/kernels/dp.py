"""Compiled scanline optimisers over (H, W, D) cost volumes: DP with occlusions, and SO.

Both work on each row independently (``prange`` over rows), exactly minimising a 1-D energy
by dynamic programming in O(W·D) per row. Volume layout as everywhere: ``cost[y, x, k]`` is the
cost of left pixel x against right pixel ``x - (min_disp + k)``, lower is better.
"""

from __future__ import annotations

import numpy as np

from ...runtime import njit, prange

INF = np.float32(np.inf)


@njit(cache=True, parallel=True)
def dp_occlusion(cost: np.ndarray, min_disp: int, occlusion: float):
    """Per-row DP over the left/right match matrix with an occlusion cost (ordering constraint).

    A row alignment is a monotone path through (left pixel i, right pixel j) pairs: *match*
    (i, j) at cost ``cost[y, i, i - j - min_disp]``, *left occlusion* (left pixel without a
    match) or *right occlusion* (right pixel without a match), each at cost ``occlusion``.
    Monotonicity is the ordering constraint; every pixel is used at most once (uniqueness).
    Only pairs with ``i - j`` inside the search range are allowed. In disparity space with
    ``F[i, k]`` = best cost of aligning left[0, i) with right[0, j), ``j = i - min_disp - k``::

        F[i, k] = min(F[i-1, k]   + cost[i-1, k],   # match, same disparity
                      F[i-1, k-1] + occlusion,      # left pixel i-1 occluded (d grows)
                      F[i, k+1]   + occlusion)      # right pixel j-1 occluded (d shrinks)

    with a free start (``F[0, :] = 0``) and a free end (min over k of ``F[W, :]``).

    Returns
    -------
    (disparity, disparity_right): float32 (H, W) integer-valued; +inf on occluded pixels
    (left-referenced and right-referenced, consistent with each other by construction).
    """
    h, w, nd = cost.shape
    disp = np.full((h, w), INF, np.float32)
    disp_r = np.full((h, w), INF, np.float32)
    occ = np.float32(occlusion)
    for y in prange(h):
        f = np.empty((w + 1, nd), np.float32)
        back = np.empty((w + 1, nd), np.uint8)  # 0 match, 1 left occlusion, 2 right occlusion
        for k in range(nd):
            f[0, k] = 0.0
            back[0, k] = 3  # start
        for i in range(1, w + 1):
            for k in range(nd - 1, -1, -1):
                best = f[i - 1, k] + cost[y, i - 1, k]
                arg = 0
                if k > 0:
                    c = f[i - 1, k - 1] + occ
                    if c < best:
                        best = c
                        arg = 1
                if k < nd - 1:
                    c = f[i, k + 1] + occ
                    if c < best:
                        best = c
                        arg = 2
                f[i, k] = best
                back[i, k] = arg
        # Backtrack from the best end state.
        k = 0
        for kk in range(1, nd):
            if f[w, kk] < f[w, k]:
                k = kk
        i = w
        while i > 0:
            a = back[i, k]
            if a == 0:
                d = min_disp + k
                disp[y, i - 1] = np.float32(d)
                xr = i - 1 - d
                if 0 <= xr < w:
                    disp_r[y, xr] = np.float32(d)
                i -= 1
            elif a == 1:
                i -= 1
                k -= 1
            elif a == 2:
                k += 1
            else:
                break
    return disp, disp_r


@njit(cache=True, inline="always")
def _dt_truncated_linear(h: np.ndarray, lam: float, trunc: float, out: np.ndarray, arg: np.ndarray) -> None:
    """``out[d] = min_d' h[d'] + lam·min(|d - d'|, trunc)`` and its argmin, in O(D).

    Felzenszwalb–Huttenlocher distance transform for the linear cost (two passes), then the
    truncation as a min with ``min(h) + lam·trunc``. Ties keep the smaller ``|d - d'|``.
    """
    nd = h.shape[0]
    for d in range(nd):
        out[d] = h[d]
        arg[d] = d
    for d in range(1, nd):
        c = out[d - 1] + lam
        if c < out[d]:
            out[d] = c
            arg[d] = arg[d - 1]
    for d in range(nd - 2, -1, -1):
        c = out[d + 1] + lam
        if c < out[d]:
            out[d] = c
            arg[d] = arg[d + 1]
    best = 0
    for d in range(1, nd):
        if h[d] < h[best]:
            best = d
    cap = h[best] + lam * trunc
    for d in range(nd):
        if cap < out[d]:
            out[d] = cap
            arg[d] = best


@njit(cache=True, parallel=True)
def scanline_optimize(cost: np.ndarray, weight: np.ndarray, smoothness: float, truncate: float):
    """Exact minimiser of ``Σ_x C(x, k_x) + Σ_x λ·w_x·min(|k_x − k_{x+1}|, T)`` along each row.

    ``weight`` (H, W) float32 scales the smoothness between x and x+1 (colour-edge dependent
    λ, Scharstein & Szeliski 2002, §4.3). Viterbi forward pass with the truncated-linear
    distance transform, then backtracking. Returns ``(labels, energy)`` where ``labels`` is
    int32 (H, W) in [0, D) and ``energy`` (H, W, D) float32 holds, for the decision volume,
    the forward min-marginals ``M[x, k] - min_k M[x, k]`` plus a backward pass (two-sided
    min-marginals), so sub-pixel fitting has a smooth volume to work on.
    """
    h, w, nd = cost.shape
    labels = np.empty((h, w), np.int32)
    marg = np.empty((h, w, nd), np.float32)
    for y in prange(h):
        fwd = np.empty((w, nd), np.float32)
        bwd = np.empty((w, nd), np.float32)
        back = np.empty((w, nd), np.int32)
        tmp = np.empty(nd, np.float32)
        tmp2 = np.empty(nd, np.float32)
        arg = np.empty(nd, np.int32)
        for k in range(nd):
            fwd[0, k] = cost[y, 0, k]
            back[0, k] = k
        for x in range(1, w):
            lam = np.float32(smoothness * weight[y, x - 1])
            _dt_truncated_linear(fwd[x - 1], lam, truncate, tmp, arg)
            mn = tmp[0]
            for k in range(1, nd):
                mn = min(mn, tmp[k])
            for k in range(nd):
                fwd[x, k] = cost[y, x, k] + tmp[k] - mn  # normalised: bounded values
                back[x, k] = arg[k]
        # Backward messages (for the min-marginals only; the labels come from backtracking).
        for k in range(nd):
            bwd[w - 1, k] = 0.0
        for x in range(w - 2, -1, -1):
            lam = np.float32(smoothness * weight[y, x])
            for k in range(nd):
                tmp2[k] = bwd[x + 1, k] + cost[y, x + 1, k]
            _dt_truncated_linear(tmp2, lam, truncate, bwd[x], arg)
            mn = bwd[x, 0]
            for k in range(1, nd):
                mn = min(mn, bwd[x, k])
            for k in range(nd):
                bwd[x, k] -= mn
        k = 0
        for kk in range(1, nd):
            if fwd[w - 1, kk] < fwd[w - 1, k]:
                k = kk
        for x in range(w - 1, -1, -1):
            labels[y, x] = k
            k = back[x, k]
        for x in range(w):
            for kk in range(nd):
                marg[y, x, kk] = fwd[x, kk] + bwd[x, kk]
    return labels, marg


@njit(cache=True, parallel=True)
def edge_weights(gray: np.ndarray, threshold: float, factor: float):
    """Colour-edge dependent smoothness weights for the edges to the right and below.

    ``wh[y, x]`` (edge (x, y)–(x+1, y)) and ``wv[y, x]`` (edge (x, y)–(x, y+1)) are ``factor``
    where the grey difference is below ``threshold`` (likely the same surface: smoothness
    counts more) and 1 elsewhere; the last column / row hold 0 (no edge).
    """
    h, w = gray.shape
    wh = np.zeros((h, w), np.float32)
    wv = np.zeros((h, w), np.float32)
    for y in prange(h):
        for x in range(w):
            if x + 1 < w:
                wh[y, x] = factor if abs(gray[y, x + 1] - gray[y, x]) < threshold else 1.0
            if y + 1 < h:
                wv[y, x] = factor if abs(gray[y + 1, x] - gray[y, x]) < threshold else 1.0
    return wh, wv


@njit(cache=True, parallel=True)
def mark_impossible(volume: np.ndarray, cost: np.ndarray, cost_max: float) -> float:
    """Give ``volume`` the contract's impossible-entry marking, in place; returns its cost_max.

    Entries where the original ``cost`` holds ``cost_max`` (right pixel outside the image or
    masked) are set to a value above every other entry of ``volume``, which is returned.
    """
    h, w, nd = volume.shape
    rowmax = np.full(h, -np.inf, np.float32)
    for y in prange(h):
        m = np.float32(-np.inf)
        for x in range(w):
            for k in range(nd):
                if cost[y, x, k] < cost_max and volume[y, x, k] > m:
                    m = volume[y, x, k]
        rowmax[y] = m
    top = np.float32(1.0)
    for y in range(h):
        if rowmax[y] + 1 > top:
            top = rowmax[y] + np.float32(1.0)
    for y in prange(h):
        for x in range(w):
            for k in range(nd):
                if cost[y, x, k] >= cost_max or volume[y, x, k] > top:
                    volume[y, x, k] = top
    return top


@njit(cache=True, parallel=True)
def warp_to_right(disp: np.ndarray) -> np.ndarray:
    """Right-view disparity by forward-warping the left map with a z-buffer.

    Left pixel x with disparity d lands on right pixel ``round(x - d)``; the largest (nearest)
    disparity wins, right pixels nobody lands on are +inf. Used by optimizers that produce a
    labelling but no two-view volume (graph cuts), so ``lr_check`` then flags exactly the
    left pixels hidden behind a nearer surface (occlusions).
    """
    h, w = disp.shape
    out = np.full((h, w), INF, np.float32)
    for y in prange(h):
        for x in range(w):
            d = disp[y, x]
            if not np.isfinite(d):
                continue
            xr = int(np.floor(x - d + 0.5))
            if 0 <= xr < w and (not np.isfinite(out[y, xr]) or d > out[y, xr]):
                out[y, xr] = d
    return out
