"""Compiled semi-global matching (Hirschmüller 2008, eq. 13–14) on quantised cost volumes.

Layout and numerics (see ``tests/test_kernels_sgm.py`` for the pure-numpy reference):

* ``cq``: (H, W, D) uint8 or uint16 matching costs, D innermost and contiguous, multiplied by
  the integer ``cost_mul`` as they are read (so an integer cost such as a census Hamming
  distance is used as it is, without a quantised copy).
* Path costs ``L_r`` live in int16 row buffers of length ``D + 2``: entries ``0`` and ``D + 1``
  hold a large sentinel so the recursion ``min(L[d], L[d-1] + P1, L[d+1] + P1, minL + P2)``
  has no branches at the ends of the range. All arithmetic of the inner loop is written in
  int16/uint16 so LLVM vectorises it 32 lanes wide (AVX-512BW; 16 with AVX2).
* The caller chooses the quantisation so that ``n_paths · (cap + P2) ≤ 65534`` and
  ``cap + 3·P2 ≤ 32767`` (``cap`` = largest ``cq · cost_mul``): every ``L_r ≤ cap + P2``
  (eq. 13 subtracts the previous minimum), so the uint16 sum ``S = Σ_r L_r`` cannot overflow
  and ``sentinel + P1`` stays inside int16 while never being selected.
* Adaptive P2 depends only on the guide image, so each row's penalties are computed before
  the row's inner loops (a division in the inner loop stops LLVM from vectorising it).
* Two raster passes (Hirschmüller 2008 §2.4): the forward pass (top to bottom, left to right)
  sums the horizontal path from the left and the paths from the rows above; the backward pass
  the mirrored directions. Each keeps three rows of path costs per direction. Both write into
  one uint16 volume ``S``: the forward pass *writes* its sums, the backward pass *adds* its
  own and takes the winner (left and right views) as soon as a row's total is complete. So
  there is no separate combine sweep and only one uint16 volume.
* Two threads share the two passes over the image's top and bottom halves (``STRIPES``, see
  :func:`stripe_pass`) in two phases: first the top half's forward pass and the bottom half's
  backward pass, then the top half's backward pass and the bottom half's forward pass, each
  continuing from the path costs the other thread's pass left at the middle row. So every
  path runs through the whole image (``S`` is exactly that of whole-image passes) and no row
  is computed twice, while each thread writes and then completes the sums of its own half,
  which the later stages, parallel over rows in the same halves, read from the same core
  (data written on one core can be slow to reach another). Only the three rows of path costs
  a pass carries move from one thread to the other between the phases.
* The plan does not depend on the thread count, and every element is computed by one thread
  with integer arithmetic in a fixed order, so the result is bit-identical for any thread
  count.
* The row functions are compiled with ``noalias`` (their array arguments are distinct arrays,
  as for every chunk kernel). Without it LLVM guards each pixel's vector loop with run-time
  tests of whether the path costs it writes overlap the costs and sums it reads; on
  MiddEval3-Q those tests took a fifth of the windowed kernel's time (:mod:`.sgm_window`).
"""

from __future__ import annotations

import numpy as np

from ...runtime import chunk_kernel, for_chunks, for_rows, intrinsic, njit

INF = np.float32(np.inf)
INT16_MAX = 32767

#: Spare elements at the end of each thread's row buffers (at least 64 bytes), so the two
#: threads' buffers never share a cache line. Without them the horizontal buffers of the two
#: passes (a few dozen bytes each, written at every pixel) shared lines, which then travelled
#: between the cores at every step (false sharing; the further apart the cores, the dearer).
GAP = 32

# Directions (dy, dx) of the downward pass: the predecessor of (y, x) is (y - dy, x - dx).
# The upward pass uses the same table mirrored, i.e. the opposite directions.
DOWN_DIRECTIONS = {
    2: np.zeros((0, 2), np.int64),
    4: np.array([[1, 0]], np.int64),
    8: np.array([[1, -1], [1, 0], [1, 1]], np.int64),
    16: np.array([[1, -1], [1, 0], [1, 1], [2, -1], [2, 1], [1, -2], [1, 2]], np.int64),
}


@intrinsic
def borrowed(typingctx, arr):
    """``arr`` without its reference count (a null meminfo), for a :func:`~.chunk_kernel` to
    pass on: the views its callees make of it in their inner loops (a pixel's path costs, a
    row) then do no atomic increments and decrements, as in the body of a ``prange`` loop,
    whose arrays have none either. The
    caller keeps ``arr`` alive for as long as the result is used."""
    from numba import types
    from numba.core import cgutils

    if not isinstance(arr, types.Array):
        return None

    def codegen(context, builder, sig, args):
        out = context.make_array(arr)(context, builder, value=args[0])
        out.meminfo = cgutils.get_null_value(out.meminfo.type)
        return out._getvalue()

    return arr(arr), codegen


@chunk_kernel
def _quantize_rows(cost, scale: float, cap: int, out, y0: int, y1: int) -> None:
    """:func:`quantize` on rows ``y0 ≤ y < y1``."""
    _, w, nd = cost.shape
    s = np.float32(scale)
    top = np.float32(cap)
    for y in range(y0, y1):
        for x in range(w):
            for k in range(nd):
                v = cost[y, x, k] * s + np.float32(0.5)
                v = min(max(v, np.float32(0.0)), top)
                out[y, x, k] = int(v)


def quantize(cost: np.ndarray, scale: float, cap: int, out: np.ndarray) -> None:
    """``out = min(cap, round(cost · scale))`` for a float32 (H, W, D) volume (in place into ``out``)."""
    for_rows(_quantize_rows, cost.shape[0], cost, scale, cap, out)


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
def _start(cf, c0, nd, mul, lf, o0, tf, s0, add: bool) -> int:
    # First pixel of a path: L_r(p, d) = C(p, d), written at lf[o0 + 1 + d]; adds L_r into
    # the sums tf[s0 + d] (or writes them: ``add`` false). Flat arrays and unsigned offsets
    # (signed indices get negative-index fix-ups, which can stop LLVM vectorising).
    m = np.int16(INT16_MAX)
    mul16 = np.int16(mul)
    one = np.uint64(1)
    for d in range(np.uint64(0), nd):
        v = np.int16(np.int16(cf[c0 + d]) * mul16)
        lf[o0 + d + one] = v
        if add:
            tf[s0 + d] = np.uint16(tf[s0 + d] + np.uint16(v))
        else:
            tf[s0 + d] = np.uint16(v)
        m = min(m, v)
    return m


@njit(cache=True, inline="always")
def _step(cf, c0, nd, mul16, lf, p0, pm, jump, pp1, o0, tf, s0, add: bool) -> int:
    # Eq. 13: L(p,d) = C(p,d) + min(L(p-r,d), L(p-r,d±1) + P1, min_k L(p-r,k) + P2) - min_k L(p-r,k),
    # from the previous path costs at lf[p0 .. p0 + nd + 1] (sentinels at both ends) into
    # lf[o0 + 1 + d], with pm = min_k L(p-r,k), jump = pm + P2 and pp1 = P1 (int16); adds L_r
    # into tf[s0 + d] (or writes it). Written in int16 so the loop vectorises at full width.
    m = np.int16(INT16_MAX)
    one = np.uint64(1)
    two = np.uint64(2)
    for d in range(np.uint64(0), nd):
        a = lf[p0 + d + one]
        b = np.int16(min(lf[p0 + d], lf[p0 + d + two]) + pp1)
        v = np.int16(np.int16(min(min(a, b), jump) - pm) + np.int16(np.int16(cf[c0 + d]) * mul16))
        lf[o0 + d + one] = v
        if add:
            tf[s0 + d] = np.uint16(tf[s0 + d] + np.uint16(v))
        else:
            tf[s0 + d] = np.uint16(v)
        m = min(m, v)
    return m


@njit(cache=True, inline="always")
def _pack(cost, k) -> np.uint32:
    # (cost, k) in one uint32 so a plain min — which vectorises — also breaks ties towards the
    # smaller index k (cost ≤ 65535, k < 65536).
    return np.uint32((np.uint32(cost) << np.uint32(16)) | np.uint32(k))


@njit(cache=True, inline="always")
def _min_packed(s, base, k0: int, k1: int, rbest, rb, want_right: bool) -> np.uint32:
    # Smallest (s[base + k], k) packed (:func:`_pack`) over k0 ≤ k ≤ k1: one branch-free pass,
    # ties to the smaller k. With ``want_right`` the right view takes the same values along the
    # diagonals: left pixel x at hypothesis k is right pixel xr = x − min_disp − k, whose slot
    # W − 1 − xr = rb + k runs forward with k. Indices are unsigned (numba then emits no
    # negative-index fix-ups and the loops vectorise): ``base`` and ``rb`` (uint64) may have
    # wrapped, every ``base + k`` and ``rb + k`` is in range.
    best = np.uint32(0xFFFFFFFF)
    if want_right:
        for k in range(np.uint64(k0), np.uint64(k1 + 1)):
            pk = _pack(s[base + k], k)
            best = min(best, pk)
            rbest[rb + k] = min(rbest[rb + k], pk)
    else:
        for k in range(np.uint64(k0), np.uint64(k1 + 1)):
            best = min(best, _pack(s[base + k], k))
    return best


@njit(cache=True, noalias=True)
def _horizontal_row(cf, mul, guide, y: int, forward: bool, add: bool, p1: int, p2: int, gamma: float, hf, hrow,
                    pens, tf, w: int, und) -> None:
    """The horizontal path of row ``y`` (from the left, or the right when not ``forward``):
    writes its costs into the row's sums (the first pass to reach them) or adds them (``add``:
    the second). ``hf`` holds two buffers of
    ``hrow`` int16 used in turn; the penalties go to ``pens``. (The row's paths are small
    functions of their own rather than loops inside :func:`_pass_rows`: there LLVM kept their
    state on the stack rather than in registers.)"""
    s = 1 if forward else -1
    for j in range(1, w):
        x = j if forward else w - 1 - j
        pens[x] = _penalty2(guide[y, x], guide[y, x - s], p1, p2, gamma)
    row = np.uint64(y * w)
    pp1 = np.int16(p1)
    mul16 = np.int16(mul)
    first = 0 if forward else w - 1
    pix = (row + np.uint64(first)) * und
    hmin = _start(cf, pix, und, mul, hf, np.uint64(0), tf, pix, add)
    for j in range(1, w):
        x = j if forward else w - 1 - j
        pix = (row + np.uint64(x)) * und
        pm = np.int16(hmin)
        hmin = _step(cf, pix, und, mul16, hf, np.uint64((j + 1) % 2) * hrow, pm, np.int16(pm + pens[x]), pp1,
                     np.uint64(j % 2) * hrow, tf, pix, add)


@njit(cache=True, noalias=True)
def _direction_row(cf, mul, lf, tf, mins, pens, k: int, ring: int, ip: int, pr: int, shift: int, row0,
                   w: int, und, lrow, cur_row, prev_row, p1: int) -> None:
    """One row of the path from the rows above (below), direction ``k``: its predecessor of x
    is x − ``shift`` in pass row ``ip`` (ring slot ``pr``), or none (the path starts: ``ip``
    before the image's first row in pass order). Costs are read and the sums added at row
    ``row0`` of ``cf`` and ``tf``. A small function of its own, so the compiler keeps its loop
    variables in registers."""
    one = np.uint64(1)
    two = np.uint64(2)
    pp1 = np.int16(p1)
    mul16 = np.int16(mul)
    for x in range(w):
        xp = x - shift
        pix = (row0 + np.uint64(x)) * und
        cur = cur_row + np.uint64(x) * lrow
        if ip < 0 or xp < 0 or xp >= w:
            mins[k, ring, x] = _start(cf, pix, und, mul, lf, cur, tf, pix, True)
        else:
            # :func:`_step` written out: the inlined call compiled to a slower loop than this.
            pm = mins[k, pr, xp]
            jump = np.int16(pm + pens[k + 1, x])
            po = prev_row + np.uint64(xp) * lrow
            m = np.int16(INT16_MAX)
            for d in range(np.uint64(0), und):
                a = lf[po + d + one]
                b = np.int16(min(lf[po + d], lf[po + d + two]) + pp1)
                v = np.int16(np.int16(min(min(a, b), jump) - pm) + np.int16(np.int16(cf[pix + d]) * mul16))
                lf[cur + d + one] = v
                tf[pix + d] = np.uint16(tf[pix + d] + np.uint16(v))
                m = min(m, v)
            mins[k, ring, x] = m


@njit(cache=True, noalias=True)
def _pass_rows(cq, mul, guide, total, dirs, forward: bool, i0: int, i1: int, second: bool,
               p1: int, p2: int, gamma: float, lbuf, mins, hbuf, pens,
               disp, disp_r, rbest, min_disp: int) -> None:
    """Rows ``i0 ≤ i < i1`` (in pass order) of one raster pass; see the module docstring.

    ``forward``: rows top to bottom, pixels left to right, the predecessor of (y, x) is
    (y, x − 1) for the horizontal path and (y − dy, x − dx) for the others; backward is the
    mirror image. The paths start at the image border (pass row 0); a call that starts
    further on continues the path costs in ``lbuf``/``mins``, which an earlier call of the
    same pass left there. The first pass over a row writes its path sums into ``total``; the
    ``second`` adds its own and takes the winners (``disp``/``disp_r`` are written there).
    ``lbuf`` (K, 3, W + 1, D + 2) int16 and ``mins`` (K, 3, W) int16 carry the pass's state
    (the last three rows); ``hbuf`` (2, D + 2) int16, ``pens`` (K + 1, W) int32 and
    ``rbest`` (W,) uint32 (the right view) are the calling thread's scratch (each possibly
    longer: ``GAP``). ``cq``, ``total``, ``lbuf`` and ``hbuf`` are C-contiguous and read
    through flat views (see :func:`_start`).
    """
    h, w, nd = cq.shape
    nk = dirs.shape[0]
    s = 1 if forward else -1
    want_right = disp_r.shape[0] > 0
    cf = cq.reshape(-1)
    tf = total.reshape(-1)
    lf = lbuf.reshape(-1)
    hf = hbuf.reshape(-1)
    und = np.uint64(nd)
    lrow = np.uint64(nd + 2)  # one pixel's path costs in lbuf, sentinels included
    lplane = np.uint64(lbuf.shape[2]) * lrow  # one row of one direction in lbuf
    hrow = np.uint64(hbuf.shape[1])
    for i in range(i0, i1):
        y = i if forward else h - 1 - i
        ring = i % 3
        # Penalties of this row for each direction (the horizontal path's: _horizontal_row).
        for k in range(nk):
            dy = dirs[k, 0]
            if i - dy < 0:
                continue
            for x in range(w):
                xp = x - s * dirs[k, 1]
                if 0 <= xp < w:
                    pens[k + 1, x] = _penalty2(guide[y, x], guide[y - s * dy, xp], p1, p2, gamma)
        row0 = np.uint64(y * w)
        # The horizontal path writes the row's sums in the first pass; every other path adds to them.
        _horizontal_row(cf, mul, guide, y, forward, second, p1, p2, gamma, hf, hrow, pens[0], tf, w, und)
        for k in range(nk):
            ip = i - dirs[k, 0]
            _direction_row(cf, mul, lf, tf, mins, pens, k, ring, ip, ip % 3, s * dirs[k, 1], row0, w, und, lrow,
                           np.uint64(k * 3 + ring) * lplane, np.uint64(k * 3 + ip % 3) * lplane, p1)
        if second:
            # The row's sums are complete: left WTA among hypotheses whose right pixel x − d
            # lies inside the image, and the right view (Hirschmüller 2008 §2.5, same volume:
            # right pixel xr takes the d minimising S[y, xr + d, d]) in the same pass: each left
            # pixel updates a best-so-far array indexed by j = W − 1 − xr (:func:`_min_packed`);
            # (value, k) packed in a uint32 keeps the smallest disparity on ties whatever the
            # order of the pixels.
            if want_right:
                rbest[:] = 0xFFFFFFFF
            for x in range(w):
                k0 = max(0, x - min_disp - (w - 1))
                k1 = min(nd - 1, x - min_disp)
                if k1 < k0:
                    disp[y, x] = INF
                    continue
                best = _min_packed(tf, (row0 + np.uint64(x)) * und, k0, k1, rbest,
                                   np.uint64(w - 1 - x + min_disp), want_right)
                disp[y, x] = np.float32(min_disp + np.int64(best & np.uint32(0xFFFF)))
            if want_right:
                for xr in range(w):
                    v = rbest[w - 1 - xr]
                    if v != 0xFFFFFFFF:
                        disp_r[y, xr] = np.float32(min_disp + np.int64(v & np.uint32(0xFFFF)))
                    else:
                        disp_r[y, xr] = INF


#: Row stripes (the image's top and bottom halves), one thread each (:func:`stripe_pass`). A
#: fixed number, so the result does not depend on the thread count.
STRIPES = 2


@njit(cache=True, inline="always")
def stripe_pass(stripe: int, phase: int, h: int):
    """The part of a raster pass that stripe ``stripe`` (0: rows ``y < h // 2``, 1: the others)
    runs in ``phase`` (0 or 1) on an image of ``h`` rows: ``(forward, i0, i1, second)``, rows
    ``i0 ≤ i < i1`` in pass order (row ``i`` is ``y = i`` forward and ``h − 1 − i``
    backward). ``second``: the other pass has been over these rows already, so this one adds
    its sums and takes the winners. Phase 0 runs the top half's forward pass and the bottom
    half's backward pass, both from the image border; phase 1 the two passes on, through the
    other half."""
    middle = h // 2
    if stripe == 0:
        if phase == 0:
            return True, 0, middle, False
        return False, h - middle, h, True
    if phase == 0:
        return False, 0, h - middle, False
    return True, middle, h, True


@chunk_kernel
def _sgm_two_pass_chunk(cq, mul: int, guide, total, dirs, p1: int, p2: int, gamma: float, min_disp: int, lbuf,
                        hbuf, mins, pens, rbest, disp, disp_r, phase: int, t: int) -> None:
    """Stripe ``t``'s part of ``phase`` (:func:`stripe_pass`): the path state of the pass it
    continues (``lbuf``/``mins`` index 0 forward, 1 backward), the stripe's own scratch."""
    h = cq.shape[0]
    # Without reference counts (:func:`borrowed`): _pass_rows makes views of them pixel by pixel.
    cq, guide, total, dirs, disp, disp_r = borrowed(cq), borrowed(guide), borrowed(total), borrowed(dirs), \
        borrowed(disp), borrowed(disp_r)
    lbuf, hbuf, mins, pens, rbest = borrowed(lbuf), borrowed(hbuf), borrowed(mins), borrowed(pens), borrowed(rbest)
    forward, i0, i1, second = stripe_pass(t, phase, h)
    p = 0 if forward else 1
    _pass_rows(cq, mul, guide, total, dirs, forward, i0, i1, second, p1, p2, gamma,
               lbuf[p], mins[p], hbuf[t], pens[t], disp, disp_r, rbest[t], min_disp)


def sgm_two_pass(cq, mul: int, guide, total, dirs, p1: int, p2: int, gamma: float, min_disp: int,
                 want_right: bool):
    """Both passes over the two row stripes in two phases (module docstring); returns left and
    right WTA disparities.

    ``total`` (H, W, D) uint16 receives ``S``. Disparities are float32 (H, W), integer-valued,
    +inf where no hypothesis is inside the image; the right map is (0, 0) when not wanted.
    """
    h, w, nd = cq.shape
    nk = dirs.shape[0]
    # Path state per pass (forward, backward); scratch per stripe.
    lbuf = np.full((2, nk, 3, w + 1, nd + 2), INT16_MAX - p1, np.int16)  # (a spare pixel: GAP)
    mins = np.zeros((2, nk, 3, w + GAP), np.int16)
    hbuf = np.full((STRIPES, 2, nd + 2 + GAP), INT16_MAX - p1, np.int16)
    pens = np.full((STRIPES, nk + 1, w + GAP), p2, np.int32)
    rbest = np.zeros((STRIPES, w + GAP if want_right else 0), np.uint32)
    disp = np.empty((h, w), np.float32)
    disp_r = np.empty((h if want_right else 0, w if want_right else 0), np.float32)  # rows set by the second pass
    for phase in range(2):
        for_chunks(_sgm_two_pass_chunk, STRIPES, cq, mul, guide, total, dirs, p1, p2, gamma, min_disp, lbuf, hbuf,
                   mins, pens, rbest, disp, disp_r, phase)
    return disp, disp_r


def sgm_aggregate(cq: np.ndarray, guide: np.ndarray, paths: int, p1: int, p2: int, gamma: float,
                  min_disp: int, want_right: bool = False, cost_mul: int = 1):
    """Path-cost sum ``S`` (H, W, D) uint16 for 2, 4, 8 or 16 paths and its WTA disparities.

    ``cq`` holds integer costs (uint8/uint16) used as ``cq · cost_mul``; see the module
    docstring for the bounds the caller guarantees. Returns ``(S, disparity_left,
    disparity_right or None)``.
    """
    if cq.shape[2] > 65535:
        raise ValueError("SGM supports at most 65535 disparities")  # the winner packs k in 16 bits
    cq = np.ascontiguousarray(cq)  # the kernel reads it through a flat view
    total = np.empty(cq.shape, np.uint16)
    guide = np.ascontiguousarray(guide, dtype=np.float32)
    disp, disp_r = sgm_two_pass(cq, int(cost_mul), guide, total, DOWN_DIRECTIONS[paths], int(p1), int(p2),
                                float(gamma), int(min_disp), bool(want_right))
    return total, disp, (disp_r if want_right else None)
