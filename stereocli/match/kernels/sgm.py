"""Compiled semi-global matching (Hirschmüller 2008, eq. 13–14) on quantised cost volumes.

Layout and numerics (see ``tests/test_kernels_sgm.py`` for the pure-numpy reference):

* ``cq``: (H, W, D) uint8 or uint16 quantised matching costs, D innermost and contiguous.
* Path costs ``L_r`` live in int16 row buffers of length ``D + 2``: entries ``0`` and ``D + 1``
  hold a large sentinel so the recursion ``min(L[d], L[d-1] + P1, L[d+1] + P1, minL + P2)``
  has no branches at the ends of the range and LLVM vectorises the loop over D.
* The minimum of each path vector is computed while it is written and carried to the next
  pixel (no second pass over D).
* The caller chooses the quantisation so that ``n_paths · (max(cq) + P2) ≤ 65534``: every
  ``L_r ≤ max(cq) + P2`` (eq. 13 subtracts the previous minimum), so the uint16 sum
  ``S = Σ_r L_r`` cannot overflow and no saturation is needed.
* Two raster passes (Hirschmüller 2008 §2.4 / ARCHITECTURE speed notes): the forward pass
  (top to bottom, left to right) sums the horizontal path from the left and the paths from the
  rows above; the backward pass the mirrored directions. Each keeps only three rows of path
  costs per direction. The two passes write separate uint16 sums and run on two threads;
  :func:`combine_wta` adds them in place and takes the left (and right) WTA in one sweep.
  Every element is computed by one thread with integer arithmetic in a fixed order, so the
  result is bit-identical for any thread count.
* Known limit: numba promotes int16 arithmetic to int64, so the loop over D vectorises with
  8 lanes (AVX-512) instead of 32; that is most of the remaining gap to OpenCV's SGBM.
"""

from __future__ import annotations

import numpy as np
from numba import njit, prange

INF = np.float32(np.inf)
SENTINEL = 32767  # int16 path-cost padding at d = -1 and d = D (never selected)

# Directions (dy, dx) of the downward pass: the predecessor of (y, x) is (y - dy, x - dx).
# The upward pass uses the same table mirrored, i.e. the opposite directions.
DOWN_DIRECTIONS = {
    2: np.zeros((0, 2), np.int64),
    4: np.array([[1, 0]], np.int64),
    8: np.array([[1, -1], [1, 0], [1, 1]], np.int64),
    16: np.array([[1, -1], [1, 0], [1, 1], [2, -1], [2, 1], [1, -2], [1, 2]], np.int64),
}


@njit(cache=True, parallel=True)
def quantize(cost: np.ndarray, scale: float, cap: int, out: np.ndarray) -> None:
    """``out = min(cap, round(cost · scale))`` for a float32 (H, W, D) volume (in place into ``out``)."""
    h, w, nd = cost.shape
    s = np.float32(scale)
    top = np.float32(cap)
    for y in prange(h):
        for x in range(w):
            for k in range(nd):
                v = cost[y, x, k] * s + np.float32(0.5)
                v = min(max(v, np.float32(0.0)), top)
                out[y, x, k] = int(v)


@njit(cache=True, inline="always")
def _penalty2(i0: float, i1: float, p1: int, p2: int, gamma: float) -> int:
    """Adaptive P2 = max(P1, P2 · γ / (γ + |ΔI|)); γ ≤ 0 disables adaptation.

    With γ = 1 this is P2 / (|I_p − I_{p−r}| + 1) (Hirschmüller 2008 §2.2 proposes
    P2 = P2' / |I_p − I_{p−r}|; the +γ keeps it finite and tunable).
    """
    if gamma <= 0.0:
        return p2
    v = int(p2 * gamma / (gamma + abs(i0 - i1)))
    return max(v, p1)


@njit(cache=True, inline="always")
def _start(c, out, acc) -> int:
    # First pixel of a path: L_r(p, d) = C(p, d).
    nd = c.shape[0]
    m = SENTINEL
    for d in range(nd):
        v = np.int32(c[d])
        out[d + 1] = v
        acc[d] += v
        m = min(m, v)
    return m


@njit(cache=True, inline="always")
def _step(c, prev, pmin, p1, p2, out, acc) -> int:
    # Eq. 13: L(p,d) = C(p,d) + min(L(p-r,d), L(p-r,d±1) + P1, min_k L(p-r,k) + P2) - min_k L(p-r,k)
    nd = c.shape[0]
    jump = pmin + p2
    m = SENTINEL
    for d in range(nd):
        a = prev[d + 1]
        b = min(prev[d], prev[d + 2]) + p1
        v = min(min(a, b), jump) - pmin + c[d]
        out[d + 1] = v
        acc[d] += v
        m = min(m, v)
    return m


@njit(cache=True)
def sgm_pass(cq, guide, out, dirs, forward: bool, p1: int, p2: int, gamma: float) -> None:
    """One raster pass: the horizontal path plus the directions ``dirs`` (K, 2) of (dy ≥ 1, dx).

    ``forward``: rows top to bottom, pixels left to right; the predecessor of (y, x) is
    (y, x − 1) for the horizontal path and (y − dy, x − dx) for the others. Backward: the
    mirror image (the opposite directions). Writes the sum of these paths' costs into ``out``
    (uint16). Only three rows of path costs per direction are kept (dy ≤ 2).
    """
    h, w, nd = cq.shape
    nk = dirs.shape[0]
    s = 1 if forward else -1
    lbuf = np.full((3, w, nk, nd + 2), SENTINEL, np.int16)
    mins = np.zeros((3, w, nk), np.int32)
    hbuf = np.full((2, nd + 2), SENTINEL, np.int16)
    tot = np.zeros(nd, np.int32)
    for i in range(h):
        y = i if forward else h - 1 - i
        ring = i % 3
        hmin = 0
        for j in range(w):
            x = j if forward else w - 1 - j
            c = cq[y, x]
            tot[:] = 0
            # Horizontal path, predecessor (y, x - s).
            hcur = hbuf[j % 2]
            if j == 0:
                hmin = _start(c, hcur, tot)
            else:
                pen = _penalty2(guide[y, x], guide[y, x - s], p1, p2, gamma)
                hmin = _step(c, hbuf[(j + 1) % 2], hmin, p1, pen, hcur, tot)
            for k in range(nk):
                dy = dirs[k, 0]
                ip = i - dy
                xp = x - s * dirs[k, 1]
                cur = lbuf[ring, x, k]
                if ip < 0 or xp < 0 or xp >= w:
                    mins[ring, x, k] = _start(c, cur, tot)
                else:
                    pr = ip % 3
                    pen = _penalty2(guide[y, x], guide[y - s * dy, xp], p1, p2, gamma)
                    mins[ring, x, k] = _step(c, lbuf[pr, xp, k], mins[pr, xp, k], p1, pen, cur, tot)
            o = out[y, x]
            for d in range(nd):
                o[d] = tot[d]


@njit(cache=True, parallel=True)
def sgm_two_pass(cq, guide, fwd, bwd, dirs, p1: int, p2: int, gamma: float) -> None:
    """The forward and backward passes, one per thread when two are available."""
    for t in prange(2):
        if t == 0:
            sgm_pass(cq, guide, fwd, dirs, True, p1, p2, gamma)
        else:
            sgm_pass(cq, guide, bwd, dirs, False, p1, p2, gamma)


@njit(cache=True, parallel=True)
def combine_wta(fwd, bwd, min_disp: int, want_right: bool):
    """``fwd += bwd`` (the total S, in place) and winner-take-all on it, left and right views.

    Left: restricted to hypotheses whose right pixel ``x − d`` lies inside the image. Right
    (Hirschmüller 2008 §2.5, same volume): right pixel ``xr`` takes the ``d`` minimising
    ``S[y, xr + d, d]``, gathered row by row while the row is in cache. Ties go to the
    smallest disparity. Returns float32 (H, W) integer-valued disparities (left, right),
    +inf where no hypothesis is inside; the right map is (0, 0) when not wanted.
    """
    h, w, nd = fwd.shape
    disp = np.empty((h, w), np.float32)
    rh = h if want_right else 0
    rw = w if want_right else 0
    disp_r = np.full((rh, rw), INF, np.float32)
    for y in prange(h):
        rbest = np.full(rw, 2**31 - 1, np.int64)
        for x in range(w):
            f = fwd[y, x]
            b = bwd[y, x]
            for k in range(nd):
                f[k] = f[k] + b[k]
            k0 = max(0, x - min_disp - (w - 1))
            k1 = min(nd - 1, x - min_disp)
            if k1 < k0:
                disp[y, x] = INF
                continue
            bk = k0
            bc = f[k0]
            for k in range(k0 + 1, k1 + 1):
                v = f[k]
                if v < bc:
                    bc = v
                    bk = k
            disp[y, x] = np.float32(min_disp + bk)
            if want_right:
                # x increases, so for a fixed xr the disparity k = x - xr - min_disp increases:
                # strict < keeps the smallest disparity on ties.
                for k in range(k0, k1 + 1):
                    xr = x - min_disp - k
                    v = np.int64(f[k])
                    if v < rbest[xr]:
                        rbest[xr] = v
                        disp_r[y, xr] = np.float32(min_disp + k)
    return disp, disp_r


def sgm_aggregate(cq: np.ndarray, guide: np.ndarray, paths: int, p1: int, p2: int, gamma: float,
                  min_disp: int, want_right: bool = False):
    """Path-cost sum ``S`` (H, W, D) uint16 for 2, 4, 8 or 16 paths and its WTA disparities.

    Returns ``(S, disparity_left, disparity_right or None)``.
    """
    fwd = np.empty(cq.shape, np.uint16)
    bwd = np.empty(cq.shape, np.uint16)
    guide = np.ascontiguousarray(guide, dtype=np.float32)
    sgm_two_pass(cq, guide, fwd, bwd, DOWN_DIRECTIONS[paths], p1, p2, gamma)
    del_b = bwd
    disp, disp_r = combine_wta(fwd, del_b, min_disp, want_right)
    return fwd, disp, (disp_r if want_right else None)
