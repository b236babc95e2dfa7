"""Compiled loopy min-sum belief propagation on the 4-connected grid (Felzenszwalb &
Huttenlocher 2006, "Efficient belief propagation for early vision").

Messages are stored by the pixel that *receives* them: ``from_l[y, x]`` is the message from
(x-1, y) to (x, y), ``from_r`` from (x+1, y), ``from_u`` from (x, y-1), ``from_d`` from (x, y+1);
each is an (H, W, D) float32 array. The smoothness term between neighbours p, q is
``λ·w_pq·min(|d_p − d_q|, T)`` (truncated linear), so each message update is the O(D)
distance transform of :func:`stereocli.matching.kernels.dp._dt_truncated_linear`.
Updates follow the checkerboard schedule (FH §3.2): pixels with ``(x + y + parity) % 2 == 0``
send while the others only receive, so a parallel sweep over rows never races.
"""

from __future__ import annotations

import numpy as np

from ...runtime import njit, prange
from .dp import _dt_truncated_linear


@njit(cache=True, inline="always")
def _send(hbuf: np.ndarray, lam: float, trunc: float, out: np.ndarray, tmp: np.ndarray, arg: np.ndarray) -> None:
    _dt_truncated_linear(hbuf, lam, trunc, tmp, arg)
    nd = tmp.shape[0]
    mn = tmp[0]
    for k in range(1, nd):
        mn = min(mn, tmp[k])
    for k in range(nd):
        out[k] = tmp[k] - mn  # normalise: messages stay bounded (min-sum is shift-invariant)


@njit(cache=True, parallel=True)
def bp_iterate(data, from_l, from_r, from_u, from_d, wh, wv, lam: float, trunc: float, iterations: int) -> None:
    """Run ``iterations`` checkerboard sweeps (both colours each), updating messages in place."""
    h, w, nd = data.shape
    for _ in range(iterations):
        for parity in range(2):
            for y in prange(h):
                hb = np.empty(nd, np.float32)
                tmp = np.empty(nd, np.float32)
                arg = np.empty(nd, np.int32)
                for x in range((y + parity) % 2, w, 2):
                    if x + 1 < w:  # to the right neighbour: everything but what it sent us
                        for k in range(nd):
                            hb[k] = data[y, x, k] + from_l[y, x, k] + from_u[y, x, k] + from_d[y, x, k]
                        _send(hb, lam * wh[y, x], trunc, from_l[y, x + 1], tmp, arg)
                    if x > 0:
                        for k in range(nd):
                            hb[k] = data[y, x, k] + from_r[y, x, k] + from_u[y, x, k] + from_d[y, x, k]
                        _send(hb, lam * wh[y, x - 1], trunc, from_r[y, x - 1], tmp, arg)
                    if y + 1 < h:
                        for k in range(nd):
                            hb[k] = data[y, x, k] + from_l[y, x, k] + from_r[y, x, k] + from_u[y, x, k]
                        _send(hb, lam * wv[y, x], trunc, from_u[y + 1, x], tmp, arg)
                    if y > 0:
                        for k in range(nd):
                            hb[k] = data[y, x, k] + from_l[y, x, k] + from_r[y, x, k] + from_d[y, x, k]
                        _send(hb, lam * wv[y - 1, x], trunc, from_d[y - 1, x], tmp, arg)


@njit(cache=True, parallel=True)
def beliefs(data, from_l, from_r, from_u, from_d) -> np.ndarray:
    """Min-sum beliefs ``data + Σ incoming messages`` (H, W, D) float32 (lower is better)."""
    h, w, nd = data.shape
    out = np.empty_like(data)
    for y in prange(h):
        for x in range(w):
            for k in range(nd):
                out[y, x, k] = data[y, x, k] + from_l[y, x, k] + from_r[y, x, k] + from_u[y, x, k] + from_d[y, x, k]
    return out


@njit(cache=True, parallel=True)
def data_term(cost: np.ndarray, weight: float, trunc: float) -> np.ndarray:
    """``weight · min(cost, trunc)`` as float32 (trunc <= 0: no truncation)."""
    h, w, nd = cost.shape
    out = np.empty((h, w, nd), np.float32)
    for y in prange(h):
        for x in range(w):
            for k in range(nd):
                c = cost[y, x, k]
                if trunc > 0 and c > trunc:
                    c = trunc
                out[y, x, k] = np.float32(weight * c)
    return out


@njit(cache=True, parallel=True)
def downsample_data(data: np.ndarray) -> np.ndarray:
    """Coarser level: each node sums the data costs of its (up to) 2×2 children (FH §4)."""
    h, w, nd = data.shape
    hc, wc = (h + 1) // 2, (w + 1) // 2
    out = np.zeros((hc, wc, nd), np.float32)
    for yc in prange(hc):
        for y in range(2 * yc, min(h, 2 * yc + 2)):
            for x in range(w):
                for k in range(nd):
                    out[yc, x // 2, k] += data[y, x, k]
    return out


@njit(cache=True)
def downsample_weights(wh: np.ndarray, wv: np.ndarray):
    """Coarse edge weights: mean of the fine edges crossing between the two coarse blocks."""
    h, w = wh.shape
    hc, wc = (h + 1) // 2, (w + 1) // 2
    ch = np.zeros((hc, wc), np.float32)
    cv = np.zeros((hc, wc), np.float32)
    for yc in range(hc):
        for xc in range(wc):
            # horizontal: fine edges (2xc+1 -> 2xc+2) in rows 2yc, 2yc+1
            x = 2 * xc + 1
            if x + 1 < w:
                s = 0.0
                n = 0
                for y in range(2 * yc, min(h, 2 * yc + 2)):
                    s += wh[y, x]
                    n += 1
                ch[yc, xc] = s / n
            y = 2 * yc + 1
            if y + 1 < h:
                s = 0.0
                n = 0
                for x in range(2 * xc, min(w, 2 * xc + 2)):
                    s += wv[y, x]
                    n += 1
                cv[yc, xc] = s / n
    return ch, cv


@njit(cache=True, parallel=True)
def upsample_messages(coarse: np.ndarray, h: int, w: int) -> np.ndarray:
    """Initial fine-level messages: each pixel takes its coarse parent's message (FH §4)."""
    nd = coarse.shape[2]
    out = np.empty((h, w, nd), np.float32)
    for y in prange(h):
        for x in range(w):
            for k in range(nd):
                out[y, x, k] = coarse[y // 2, x // 2, k]
    return out
