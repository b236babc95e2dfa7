"""Semi-global matching restricted to a window of hypotheses per pixel (coarse-to-fine search).

The same recursion and the same two row stripes and phases (the two passes over each half
shared by two threads, every path through the whole image) as :mod:`.sgm` (read its
docstring first), with each pixel
``p`` searching only ``[lo(p), hi(p))`` (volume indices) instead of the whole range. The
windows come from a coarse disparity map
(:func:`stereocli.matching.optimize.sgm.search_windows`), in the spirit of Rothermel et al.'s
tSGM ("SURE: photogrammetric surface reconstruction from imagery", 2012).

* Path costs are defined on each pixel's window and are +∞ outside it. A step from the
  predecessor ``q`` to ``p`` reads ``L(q, d − 1 .. d + 1)``; where ``q``'s window does not
  reach, only the jump term ``min_k L(q, k) + P2`` is finite, so ``L(p, d) = C(p, d) + P2``.
* Path-cost rows keep the layout of :mod:`.sgm` (one int16 buffer per pixel and direction,
  indexed by the volume index ``k + 2``), and every buffer holds sentinels outside the window
  it holds: after each step the part of the buffer's previous run that the new one does not
  cover is reset (``_clear``). So the step is one branch-free loop, with no case analysis of
  how the two windows overlap.
* Each window is computed inside its *run* ``[run_lo, run_hi)``: the window's bounds rounded
  out to a grid of ``align`` hypotheses, so the vector loops run whole (the kernel's time
  depends more on odd loop tails than on widths). Lanes outside the window store the sentinel,
  so the result is exactly that of the window.
* Costs and sums are stored *ragged*: pixel (y, x) owns ``run_hi − run_lo`` entries at
  ``offset[y, x]`` of one flat array (row-major), so memory and time scale with the windows,
  not with H·W·D.
* Inner loops index with unsigned integers (numba emits no negative-index wrap-around code
  for them, so LLVM vectorises loops that start at a run-time bound). The flat index is
  ``(offset − run_lo) + k`` computed modulo 2⁶⁴, which is exact for every k ≥ run_lo.
* In the forward pass the horizontal path, the first to reach a pixel, overwrites the sums
  (``keep`` mask 0) instead of adding: no separate zeroing pass. The adaptive P2 of every
  pixel and direction is computed once (:func:`penalty_maps`) and shared by both passes.
* Besides the integer winners the kernel returns, per pixel and view, the sums at the winner
  and its two neighbours (sub-pixel fitting without a volume) and, on request, the best sum
  more than one hypothesis from the winner (uniqueness and confidence).

Every element is computed by one thread in a fixed order: bit-identical for any thread count.
The row functions are compiled with ``noalias``, as in :mod:`.sgm`.
"""

from __future__ import annotations

import numpy as np

from ...runtime import chunk_kernel, for_chunks, for_rows, njit
from .sgm import DOWN_DIRECTIONS, GAP, INF, INT16_MAX, STRIPES, _min_packed, _penalty2, borrowed, stripe_pass

#: Sum value of a hypothesis outside a pixel's window in an expanded volume (:func:`expand_sums`).
S_MAX = 65535

U1 = np.uint64(1)
U2 = np.uint64(2)
U3 = np.uint64(3)


@njit(cache=True, inline="always")
def _clear(out, olo: int, ohi: int, lo: int, hi: int, sentinel) -> None:
    # ``out`` held the window [olo, ohi) and now holds [lo, hi): reset what the new window does
    # not cover, so every buffer holds sentinels outside its window.
    for d in range(np.uint64(olo), np.uint64(max(olo, min(ohi, lo)))):
        out[d + U2] = sentinel
    for d in range(np.uint64(max(olo, hi)), np.uint64(max(ohi, hi))):
        out[d + U2] = sentinel


@njit(cache=True, inline="always")
def _step(c, mul, prev, pmin, p1, p2, out, olo: int, ohi: int, total, base, sbase, rlo: int, rhi: int, lo: int,
          hi: int, sentinel, keep):
    # Eq. 13 on p's window [lo, hi). ``prev`` (the predecessor's path costs, indexed k + 2)
    # holds sentinels outside the predecessor's window, so hypotheses it does not reach take
    # the jump term (L = C + P2) in the same branch-free loop, which LLVM vectorises. The loop
    # runs over the run [rlo, rhi) ⊇ [lo, hi) (bounds on a coarse grid, so vector loops have
    # no odd tails) and stores the sentinel outside the window: the result is that of the
    # window alone. The sums (at ``sbase``; the costs at ``base``) are kept (``keep`` = 0xFFFF)
    # or overwritten (0) without a branch.
    mul16 = np.int16(mul)
    pm = np.int16(pmin)
    jump = np.int16(pmin + p2)
    pp1 = np.int16(p1)
    # The window test in 16-bit lanes, like the rest of the loop (D ≤ 65535): on 64-bit
    # indices it took four vector compares per sixteen hypotheses.
    ulo = np.uint16(lo)
    uhi = np.uint16(hi)
    m = np.int16(INT16_MAX)
    for d in range(np.uint64(rlo), np.uint64(rhi)):
        same = prev[d + U2]
        near = np.int16(min(prev[d + U1], prev[d + U3]) + pp1)
        v = np.int16(np.int16(min(min(same, near), jump) - pm) + np.int16(np.int16(c[base + d]) * mul16))
        du = np.uint16(d)
        v = v if (du >= ulo) & (du < uhi) else sentinel
        out[d + U2] = v
        total[sbase + d] = np.uint16((total[sbase + d] & keep) + np.uint16(v))
        m = min(m, v)
    _clear(out, olo, ohi, rlo, rhi, sentinel)
    return m


@njit(cache=True, inline="always")
def _start(c, mul, blank, p1, out, olo: int, ohi: int, total, base, sbase, rlo: int, rhi: int, lo: int, hi: int,
           sentinel, keep):
    # First pixel of a path, L_r(p, d) = C(p, d): a step from a predecessor that reaches
    # nothing (``blank``: all sentinels) with P2 = 0 and min 0.
    return _step(c, mul, blank, 0, p1, 0, out, olo, ohi, total, base, sbase, rlo, rhi, lo, hi, sentinel, keep)


@njit(cache=True, inline="always")
def _sum_at(total, base, lo: int, hi: int, k: int) -> float:
    # S(k) as float32, or -1 where k is outside the window [lo, hi).
    if k < lo or k >= hi:
        return -1.0
    return np.float32(total[base + np.uint64(k)])


@njit(cache=True, inline="always")
def _put_costs(costs, y: int, x: int, c0, c1, c2) -> None:
    # Where a neighbour is undefined (outside the window or the image) both are stored equal
    # to the winner's sum, so a sub-pixel fit keeps the integer (as at the ends of the range).
    if c0 < 0 or c2 < 0:
        c0 = c1
        c2 = c1
    costs[y, x, 0] = c0
    costs[y, x, 1] = c1
    costs[y, x, 2] = c2


@njit(cache=True, noalias=True)
def _horizontal_row(cq, mul, pens, total, off_row, lo_row, hi_row, rlo_row, rhi_row, y: int, forward: bool, p1: int,
                    hbuf, blank, sentinel, keep, h_lo0: int, h_hi0: int, h_lo1: int, h_hi1: int):
    """The horizontal path of row ``y`` (from the left, or from the right when not ``forward``),
    its sums written (``keep`` 0) or added into ``total``. ``hbuf`` holds the two buffers used in
    turn and ``h_lo0 .. h_hi1`` the runs they hold, carried from row to row (returned)."""
    w = lo_row.shape[0]
    hmin = 0
    for j in range(w):
        x = j if forward else w - 1 - j
        lo = lo_row[x]
        hi = hi_row[x]
        rlo = rlo_row[x]
        rhi = rhi_row[x]
        base = np.uint64(off_row[x] - rlo)
        if j % 2 == 0:
            olo, ohi = h_lo0, h_hi0
            h_lo0, h_hi0 = rlo, rhi
            cur, prev = hbuf[0], hbuf[1]
        else:
            olo, ohi = h_lo1, h_hi1
            h_lo1, h_hi1 = rlo, rhi
            cur, prev = hbuf[1], hbuf[0]
        if j == 0:
            hmin = _start(cq, mul, blank, p1, cur, olo, ohi, total, base, base, rlo, rhi, lo, hi, sentinel, keep)
        else:
            # P2 between x and its predecessor x − s, stored at the right one of the two.
            pen = pens[0, y, x] if forward else pens[0, y, x + 1]
            hmin = _step(cq, mul, prev, hmin, p1, pen, cur, olo, ohi, total, base, base, rlo, rhi, lo, hi,
                         sentinel, keep)
    return h_lo0, h_hi0, h_lo1, h_hi1


@njit(cache=True, noalias=True)
def _direction_row(cq, mul, pens, total, off_row, lo_row, hi_row, rlo_row, rhi_row, k: int, dy: int, dx: int,
                   y: int, i: int, forward: bool, p1: int, lbuf, lslot, mins, blank, sentinel) -> None:
    """Row ``y`` (pass row ``i``) of the path from the rows above (below), direction ``k`` =
    (``dy``, ``dx``); the sums are added into ``total`` (the path starts where its predecessor
    is outside the image)."""
    w = lo_row.shape[0]
    s = 1 if forward else -1
    ring = i % 3
    ip = i - dy
    pr = ip % 3
    yp = y - s * dy
    keep = np.uint16(0xFFFF)
    for x in range(w):
        xp = x - s * dx
        lo = lo_row[x]
        hi = hi_row[x]
        rlo = rlo_row[x]
        rhi = rhi_row[x]
        base = np.uint64(off_row[x] - rlo)
        olo = lslot[k, ring, x, 0]
        ohi = lslot[k, ring, x, 1]
        if ip < 0 or xp < 0 or xp >= w:
            mins[k, ring, x] = _start(cq, mul, blank, p1, lbuf[k, ring, x], olo, ohi, total, base, base, rlo, rhi,
                                      lo, hi, sentinel, keep)
        else:
            pen = pens[k + 1, y, x] if forward else pens[k + 1, yp, xp]
            mins[k, ring, x] = _step(cq, mul, lbuf[k, pr, xp], mins[k, pr, xp], p1, pen,
                                     lbuf[k, ring, x], olo, ohi, total, base, base, rlo, rhi, lo, hi,
                                     sentinel, keep)
        lslot[k, ring, x, 0] = rlo
        lslot[k, ring, x, 1] = rhi


@njit(cache=True, noalias=True)
def _winners_row(total, nd: int, off_row, lo_row, hi_row, rlo_row, y: int, min_disp: int, disp, costs, second,
                 rbest, want_right: bool, want_second: bool) -> None:
    """The left winners of row ``y`` (and the right view's best so far in ``rbest``), with the
    sums around them and, if ``want_second``, the best sum beyond them."""
    w = lo_row.shape[0]
    for x in range(w):
        lo = lo_row[x]
        hi = hi_row[x]
        base = np.uint64(off_row[x] - rlo_row[x])
        k0 = max(0, x - min_disp - (w - 1), lo)
        k1 = min(nd - 1, x - min_disp, hi - 1)
        if k1 < k0:
            disp[y, x] = INF
            continue
        # Smallest (sum, k) packed in a uint32, both views in one pass (:func:`.sgm._min_packed`;
        # w − 1 − x + min_disp may be negative: the unsigned sum wraps to the right slot).
        lbest = _min_packed(total, base, k0, k1, rbest, np.uint64(w - 1 - x + min_disp), want_right)
        kb = int(lbest & np.uint32(0xFFFF))
        vmin = lbest >> np.uint32(16)
        disp[y, x] = np.float32(min_disp + kb)
        c1 = np.float32(vmin)
        c0 = _sum_at(total, base, k0, k1 + 1, kb - 1)
        c2 = _sum_at(total, base, k0, k1 + 1, kb + 1)
        _put_costs(costs, y, x, c0, c1, c2)
        if want_second:
            sec = INF
            for k in range(k0, k1 + 1):
                if k < kb - 1 or k > kb + 1:
                    sec = min(sec, np.float32(total[base + np.uint64(k)]))
            second[y, x] = sec


@njit(cache=True, noalias=True)
def _right_row(total, off_row, lo_row, hi_row, rlo_row, y: int, min_disp: int, disp_r, costs_r, rbest,
               want_right_costs: bool) -> None:
    """The right winners of row ``y`` from ``rbest`` and, if ``want_right_costs``, their sums."""
    w = lo_row.shape[0]
    for xr in range(w):
        v = rbest[w - 1 - xr]
        if v == 0xFFFFFFFF:
            continue
        kb = int(v & np.uint32(0xFFFF))
        disp_r[y, xr] = np.float32(min_disp + kb)
        if not want_right_costs:
            continue
        c1 = np.float32(v >> np.uint32(16))
        # Right-view neighbours along the diagonal: S(x − 1, k − 1) and S(x + 1, k + 1).
        x = xr + min_disp + kb
        c0 = np.float32(-1.0)
        c2 = np.float32(-1.0)
        if x - 1 >= 0:
            c0 = _sum_at(total, np.uint64(off_row[x - 1] - rlo_row[x - 1]), lo_row[x - 1], hi_row[x - 1], kb - 1)
        if x + 1 < w:
            c2 = _sum_at(total, np.uint64(off_row[x + 1] - rlo_row[x + 1]), lo_row[x + 1], hi_row[x + 1], kb + 1)
        _put_costs(costs_r, y, xr, c0, c1, c2)


@njit(cache=True, noalias=True)
def _pass_rows(cq, nd: int, mul, pens, total, offset, win_lo, win_hi, run_lo, run_hi, dirs, forward: bool, i0: int,
               i1: int, second_pass: bool, p1: int, lbuf, lslot, mins, hbuf, disp, disp_r, costs,
               costs_r, second, rbest, min_disp: int) -> None:
    """Rows ``i0 ≤ i < i1`` (in pass order) of one raster pass (:func:`.sgm._pass_rows`, windowed).

    The paths start at the image border; a call that starts further on continues the path
    state in ``lbuf``/``lslot``/``mins`` that an earlier call of the same pass left there. The
    first pass over a row writes the sums, the ``second_pass`` adds its own and takes the
    winners.

    ``cq`` holds the matching costs on the runs (ragged, the layout of ``total``), ``nd`` is D.
    ``pens`` (K + 1, H, W) int16: P2 per pixel and direction (:func:`penalty_maps`). ``total``
    is the flat uint16 sum array, ``offset`` (H, W) int64 each pixel's first entry,
    ``win_lo``/``win_hi`` (H, W) int32 its window and ``run_lo``/``run_hi`` the run of
    hypotheses computed around it (sums are stored for the run). In the second pass the row's winners are
    taken (left, and right if ``disp_r`` is not empty) with their neighbouring sums in
    ``costs``/``costs_r`` (H, W, 3) float32 (``costs_r`` only if not empty) and, if ``second``
    is not empty, the best sum more than one hypothesis from the left winner. ``lslot`` (K, 3,
    W, 2) int32 holds the window each path-cost buffer of ``lbuf`` holds (its entries outside
    are sentinels); ``hbuf`` (2, D + 4) is reset to sentinels here. (Each of these buffers may be
    longer than its shape says: the spare ``GAP`` that keeps the threads' buffers apart.)
    """
    h, w = win_lo.shape
    nk = dirs.shape[0]
    want_right = disp_r.shape[0] > 0
    want_right_costs = costs_r.shape[0] > 0
    want_second = second.shape[0] > 0
    sentinel = np.int16(INT16_MAX - p1)  # sentinel + P1 still fits int16; never selected
    hbuf[:] = sentinel
    blank = np.full(nd + 4, sentinel, np.int16)  # the "predecessor" of a path's first pixel
    # Runs the two horizontal buffers hold (locals: per-thread arrays written every pixel would
    # share cache lines between the threads). Each row's paths, winners and right view are
    # functions of their own, which keeps each loop's state in registers (as in .sgm) and the
    # kernel's compile time down.
    h_lo0 = h_hi0 = h_lo1 = h_hi1 = np.int64(0)  # (not a literal 0: one compiled signature)
    # In the first pass the horizontal path is the first to reach each pixel: it overwrites
    # the sums (no separate zeroing pass over them).
    hkeep = np.uint16(0xFFFF) if second_pass else np.uint16(0)
    for i in range(i0, i1):
        y = i if forward else h - 1 - i
        lo_row = win_lo[y]
        hi_row = win_hi[y]
        rlo_row = run_lo[y]
        rhi_row = run_hi[y]
        off_row = offset[y]
        h_lo0, h_hi0, h_lo1, h_hi1 = _horizontal_row(cq, mul, pens, total, off_row, lo_row, hi_row, rlo_row,
                                                     rhi_row, y, forward, p1, hbuf, blank, sentinel, hkeep,
                                                     h_lo0, h_hi0, h_lo1, h_hi1)
        for k in range(nk):
            _direction_row(cq, mul, pens, total, off_row, lo_row, hi_row, rlo_row, rhi_row, k, dirs[k, 0], dirs[k, 1],
                           y, i, forward, p1, lbuf, lslot, mins, blank, sentinel)
        if not second_pass:
            continue
        # The row's sums are complete: winners among hypotheses inside the window whose right
        # pixel x − d lies inside the image, for both views in one pass over each window.
        if want_right:
            rbest[:] = 0xFFFFFFFF
        _winners_row(total, nd, off_row, lo_row, hi_row, rlo_row, y, min_disp, disp, costs, second, rbest,
                     want_right, want_second)
        if want_right:
            _right_row(total, off_row, lo_row, hi_row, rlo_row, y, min_disp, disp_r, costs_r, rbest, want_right_costs)


@chunk_kernel
def _penalty_maps_rows(guide, dirs, p1: int, p2: int, gamma: float, pens, y0: int, y1: int) -> None:
    """:func:`penalty_maps` on rows ``y0 ≤ y < y1``, written into ``pens``."""
    w = guide.shape[1]
    nk = dirs.shape[0]
    for y in range(y0, y1):
        pens[0, y, 0] = p2
        for x in range(1, w):
            pens[0, y, x] = _penalty2(guide[y, x], guide[y, x - 1], p1, p2, gamma)
        for k in range(nk):
            dy = dirs[k, 0]
            dx = dirs[k, 1]
            for x in range(w):
                if y - dy >= 0 and 0 <= x - dx < w:
                    pens[k + 1, y, x] = _penalty2(guide[y, x], guide[y - dy, x - dx], p1, p2, gamma)
                else:
                    pens[k + 1, y, x] = p2


def penalty_maps(guide, dirs, p1: int, p2: int, gamma: float):
    """(K + 1, H, W) int16: the adaptive P2 between each pixel and its predecessor along the
    horizontal path (index 0, predecessor (y, x − 1)) and each direction (dy, dx) of ``dirs``
    (predecessor (y − dy, x − dx)); P2 where the predecessor is outside the image. The
    penalty is symmetric, so the backward pass reads it at its predecessor."""
    h, w = guide.shape
    pens = np.empty((dirs.shape[0] + 1, h, w), np.int16)
    for_rows(_penalty_maps_rows, h, guide, dirs, p1, p2, gamma, pens)
    return pens


@chunk_kernel
def _sgm_window_two_pass_chunk(cq, nd: int, mul: int, pens, total, offset, win_lo, win_hi, run_lo, run_hi, dirs,
                               p1: int, min_disp: int, lbuf, lslot, mins, hbuf, rbest, disp, disp_r, costs,
                               costs_r, second, phase: int, t: int) -> None:
    """Stripe ``t``'s part of ``phase`` (:func:`.sgm.stripe_pass`): the path state of the pass it
    continues (``lbuf``/``lslot``/``mins`` index 0 forward, 1 backward), the stripe's own scratch."""
    h = win_lo.shape[0]
    # Without reference counts, as in .sgm._sgm_two_pass_chunk (:func:`.sgm.borrowed`).
    cq, pens, total, offset, dirs = borrowed(cq), borrowed(pens), borrowed(total), borrowed(offset), borrowed(dirs)
    win_lo, win_hi, run_lo, run_hi = borrowed(win_lo), borrowed(win_hi), borrowed(run_lo), borrowed(run_hi)
    lbuf, lslot, mins, hbuf = borrowed(lbuf), borrowed(lslot), borrowed(mins), borrowed(hbuf)
    rbest, disp, disp_r = borrowed(rbest), borrowed(disp), borrowed(disp_r)
    costs, costs_r, second = borrowed(costs), borrowed(costs_r), borrowed(second)
    forward, i0, i1, second_pass = stripe_pass(t, phase, h)
    p = 0 if forward else 1
    _pass_rows(cq, nd, mul, pens, total, offset, win_lo, win_hi, run_lo, run_hi, dirs, forward, i0, i1,
               second_pass, p1, lbuf[p], lslot[p], mins[p], hbuf[t], disp, disp_r, costs,
               costs_r, second, rbest[t], min_disp)


def sgm_window_two_pass(cq, nd: int, mul: int, pens, total, offset, win_lo, win_hi, run_lo, run_hi, dirs, p1: int,
                        min_disp: int, want_right: bool, want_second: bool, want_right_costs: bool):
    """Both passes over the windows, in the two row stripes and phases of :mod:`.sgm`; returns
    ``(disp, disp_r, costs, costs_r, second)`` (the right-view arrays, ``costs_r`` and
    ``second`` are empty when not wanted)."""
    h, w = win_lo.shape
    nk = dirs.shape[0]
    ns = STRIPES
    # Path state per pass (forward, backward), scratch per stripe; each thread's buffers end
    # with spare elements (GAP: no cache line shared between threads).
    lbuf = np.full((2, nk, 3, w + 1, nd + 4), INT16_MAX - p1, np.int16)
    lslot = np.zeros((2, nk, 3, w + GAP, 2), np.int32)  # every buffer starts as all sentinels
    mins = np.zeros((2, nk, 3, w + GAP), np.int16)
    hbuf = np.empty((ns, 2, nd + 4 + GAP), np.int16)
    rbest = np.zeros((ns, w + GAP if want_right else 0), np.uint32)
    hr = h if want_right else 0
    wr = w if want_right else 0
    disp = np.empty((h, w), np.float32)
    disp_r = np.full((hr, wr), INF, np.float32)
    costs = np.empty((h, w, 3), np.float32)  # written wherever a winner is (only read there)
    costs_r = np.empty((hr if want_right_costs else 0, wr if want_right_costs else 0, 3), np.float32)
    second = np.zeros((h if want_second else 0, w if want_second else 0), np.float32)
    for phase in range(2):
        for_chunks(_sgm_window_two_pass_chunk, ns, cq, nd, mul, pens, total, offset, win_lo, win_hi, run_lo, run_hi,
                   dirs, p1, min_disp, lbuf, lslot, mins, hbuf, rbest, disp, disp_r, costs, costs_r, second, phase)
    return disp, disp_r, costs, costs_r, second


@chunk_kernel
def _expand_sums_rows(total, offset, run_lo, win_lo, win_hi, out, y0: int, y1: int) -> None:
    """:func:`expand_sums` on rows ``y0 ≤ y < y1``, written into ``out``."""
    w = win_lo.shape[1]
    for y in range(y0, y1):
        for x in range(w):
            o = offset[y, x] - run_lo[y, x]
            for k in range(win_lo[y, x], win_hi[y, x]):
                out[y, x, k] = total[o + k]


def expand_sums(total, offset, run_lo, win_lo, win_hi, nd: int):
    """The dense (H, W, D) uint16 volume of ragged sums (stored from ``run_lo`` at ``offset``),
    ``S_MAX`` outside the windows ``[win_lo, win_hi)`` (for stages that need the whole volume)."""
    h, w = win_lo.shape
    out = np.full((h, w, nd), S_MAX, np.uint16)
    for_rows(_expand_sums_rows, h, total, offset, run_lo, win_lo, win_hi, out)
    return out


@chunk_kernel
def _gather_runs_rows(cq, run_lo, run_hi, offset, out, y0: int, y1: int) -> None:
    """:func:`gather_runs` on rows ``y0 ≤ y < y1``, written into ``out``."""
    w = run_lo.shape[1]
    for y in range(y0, y1):
        for x in range(w):
            o = offset[y, x] - run_lo[y, x]
            for k in range(run_lo[y, x], run_hi[y, x]):
                out[o + k] = cq[y, x, k]


def gather_runs(cq, run_lo, run_hi, offset, n: int):
    """The entries of a dense (H, W, D) cost volume on each pixel's run, ragged (for costs
    that offer no windowed kernel)."""
    out = np.empty(n, cq.dtype)
    for_rows(_gather_runs_rows, run_lo.shape[0], cq, run_lo, run_hi, offset, out)
    return out


@chunk_kernel
def _runs_rows(lo, hi, nd: int, down, up, run_lo, run_hi, offset, row_start, row_bad, y0: int, y1: int) -> None:
    """:func:`_runs_and_offsets`' runs of rows ``y0 ≤ y < y1``, their offsets within the row."""
    w = lo.shape[1]
    for y in range(y0, y1):
        used = 0
        bad = 0
        for x in range(w):
            a = lo[y, x]
            b = hi[y, x]
            if a < 0 or b > nd or b <= a:
                bad += 1
                a = 0
                b = nd
            ra = down[a]
            rb = up[b]
            run_lo[y, x] = ra
            run_hi[y, x] = rb
            offset[y, x] = used  # within the row until the row starts are known
            used += rb - ra
        row_start[y + 1] = used
        row_bad[y] = bad


@chunk_kernel
def _offsets_rows(offset, row_start, y0: int, y1: int) -> None:
    """Rows ``y0 ≤ y < y1`` of ``offset`` moved from within the row to within the flat array."""
    w = offset.shape[1]
    for y in range(y0, y1):
        for x in range(w):
            offset[y, x] += row_start[y]


def _runs_and_offsets(lo, hi, nd: int, step: int):
    # Runs on the grid of ``step`` around each window [lo, hi) and their row-major offsets in
    # the flat arrays (each pixel's run follows the previous pixel's); returns ``(run_lo,
    # run_hi, offset, n, bad)``, ``bad`` counting windows outside [0, nd) or empty.
    h, w = lo.shape
    run_lo = np.empty((h, w), np.int32)
    run_hi = np.empty((h, w), np.int32)
    offset = np.empty((h, w), np.int64)
    row_start = np.zeros(h + 1, np.int64)
    row_bad = np.zeros(h, np.int64)
    # Grid bounds of every value 0..nd, looked up per pixel (two divisions per pixel by a
    # run-time step took most of the time of the runs).
    v = np.arange(nd + 1, dtype=np.int64)
    down = (v // step * step).astype(np.int32)
    up = np.minimum((v + step - 1) // step * step, nd).astype(np.int32)
    for_rows(_runs_rows, h, lo, hi, nd, down, up, run_lo, run_hi, offset, row_start, row_bad)
    np.cumsum(row_start, out=row_start)  # the row starts
    for_rows(_offsets_rows, h, offset, row_start)
    return run_lo, run_hi, offset, int(row_start[h]), int(row_bad.sum())


def window_runs(win_lo: np.ndarray, win_hi: np.ndarray, nd: int, align: int = 16):
    """Checked windows and the runs the kernel computes: ``(lo, hi, run_lo, run_hi, offset,
    n)``. Runs enclose the windows with bounds on a grid of ``align`` hypotheses (clipped to
    D), so vector loops run whole; ``offset`` (H, W) int64 and ``n`` place them in the flat
    arrays of costs and sums (row-major, each run right after the previous pixel's)."""
    lo = np.ascontiguousarray(win_lo, dtype=np.int32)
    hi = np.ascontiguousarray(win_hi, dtype=np.int32)
    if nd > 65535:
        raise ValueError("SGM supports at most 65535 disparities")
    if lo.shape != hi.shape or lo.ndim != 2:
        raise ValueError("SGM windows: lo and hi must be (H, W) arrays of one shape")
    run_lo, run_hi, offset, n, bad = _runs_and_offsets(lo, hi, int(nd), max(1, int(align)))
    if bad:
        raise ValueError("SGM windows must satisfy 0 <= lo < hi <= D for every pixel")
    return lo, hi, run_lo, run_hi, offset, int(n)


def sgm_window(costs: np.ndarray, runs, nd: int, guide: np.ndarray, paths: int, p1: int, p2: int, gamma: float,
               min_disp: int, want_right: bool = False, want_second: bool = False, cost_mul: int = 1,
               want_right_costs: bool = True):
    """Windowed SGM (module docstring) on integer costs stored ragged on the runs.

    ``runs``: :func:`window_runs` of the windows; ``costs``: uint8/uint16 flat array in that
    layout (e.g. :func:`gather_runs`, or a cost's own windowed kernel). Returns a dict with
    ``disparity`` and ``disparity_right`` (float32 integer winners, +inf where none; the right
    one None unless wanted), ``costs``/``costs_right`` ((H, W, 3) float32 sums at the winner − 1,
    winner, winner + 1; an undefined neighbour equals the winner's sum; the right one None
    unless ``want_right_costs``), ``second`` ((H, W) float32 or None) and the ragged sums
    ``total`` (for :func:`expand_sums`).
    """
    lo, hi, run_lo, run_hi, offset, n = runs
    total = np.empty(n, np.uint16)
    guide = np.ascontiguousarray(guide, dtype=np.float32)
    dirs = DOWN_DIRECTIONS[paths]
    pens = penalty_maps(guide, dirs, int(p1), int(p2), float(gamma))
    disp, disp_r, wcosts, wcosts_r, second = sgm_window_two_pass(
        costs, int(nd), int(cost_mul), pens, total, offset, lo, hi, run_lo, run_hi, dirs, int(p1), int(min_disp),
        bool(want_right), bool(want_second), bool(want_right and want_right_costs))
    return {"disparity": disp, "disparity_right": disp_r if want_right else None, "costs": wcosts,
            "costs_right": wcosts_r if want_right and want_right_costs else None,
            "second": second if want_second else None, "total": total}


@njit(cache=True)
def _row_min_max(row, rmin, rmax, radius: int) -> None:
    # Min and max of the finite values of ``row`` within ``radius`` of each x.
    w = row.shape[0]
    for x in range(w):
        a = np.float32(np.inf)
        b = np.float32(-np.inf)
        for xx in range(max(0, x - radius), min(w, x + radius + 1)):
            v = row[xx]
            if np.isfinite(v):
                a = min(a, v)
                b = max(b, v)
        rmin[x] = a
        rmax[x] = b


@njit(cache=True)
def _column_min_max(rmin, rmax, lo, hi, y: int, radius: int) -> None:
    # Row y of the column pass: min (max) of the rows of ``rmin`` (``rmax``) within ``radius``.
    h, w = rmin.shape
    y0 = max(0, y - radius)
    for x in range(w):
        lo[x] = rmin[y0, x]
        hi[x] = rmax[y0, x]
    for yy in range(y0 + 1, min(h, y + radius + 1)):
        for x in range(w):
            lo[x] = min(lo[x], rmin[yy, x])
            hi[x] = max(hi[x], rmax[yy, x])


@chunk_kernel
def _square_rows(coarse, radius: int, rmin, rmax, y0: int, y1: int) -> None:
    """The row pass of :func:`square_min_max` on rows ``y0 ≤ y < y1``."""
    for y in range(y0, y1):
        _row_min_max(coarse[y], rmin[y], rmax[y], radius)


@chunk_kernel
def _square_columns_rows(rmin, rmax, radius: int, lo, hi, y0: int, y1: int) -> None:
    """The column pass of :func:`square_min_max` on rows ``y0 ≤ y < y1``."""
    for y in range(y0, y1):
        _column_min_max(rmin, rmax, lo[y], hi[y], y, radius)


def square_min_max(coarse: np.ndarray, radius: int):
    """Min and max of the finite values of ``coarse`` (2-D float32) over the (2r + 1)² square
    around each pixel (separable: rows, then columns); +inf / −inf where none is finite."""
    h, w = coarse.shape
    rmin = np.empty((h, w), np.float32)
    rmax = np.empty((h, w), np.float32)
    for_rows(_square_rows, h, coarse, radius, rmin, rmax)
    lo = np.empty((h, w), np.float32)
    hi = np.empty((h, w), np.float32)
    for_rows(_square_columns_rows, h, rmin, rmax, radius, lo, hi)
    return lo, hi


@chunk_kernel
def _upsample_windows_rows(nmin, nmax, w: int, min_disp: int, ndisp: int, margin: int, lo_map, hi_map, y0: int,
                           y1: int) -> None:
    """:func:`upsample_windows` on rows ``y0 ≤ y < y1``, written into ``lo_map``/``hi_map``."""
    for y in range(y0, y1):
        for x in range(w):
            a = nmin[y // 2, x // 2]
            b = nmax[y // 2, x // 2]
            if b >= a:
                lo = int(2 * a) - margin - min_disp
                hi = int(2 * b) + margin + 1 - min_disp
            else:
                lo = 0
                hi = ndisp
            lo = min(max(lo, 0), ndisp - 1)
            lo_map[y, x] = lo
            hi_map[y, x] = min(max(hi, lo + 1), ndisp)


def upsample_windows(nmin, nmax, h: int, w: int, min_disp: int, ndisp: int, margin: int):
    """(H, W) int32 ``lo``/``hi`` volume indices from the coarse range [nmin, nmax] of each
    pixel's coarse parent (y // 2, x // 2): doubled, ± ``margin``; the full range where the
    range is empty. Clipped to [0, D) and never empty."""
    lo_map = np.empty((h, w), np.int32)
    hi_map = np.empty((h, w), np.int32)
    for_rows(_upsample_windows_rows, h, nmin, nmax, w, min_disp, ndisp, margin, lo_map, hi_map)
    return lo_map, hi_map
