"""Compiled kernels of the geodesic vote (``geodesic_vote``): running votes along rows and
columns, support passed between neighbours of similar colour."""

from __future__ import annotations

import numpy as np

from ...runtime import chunk_kernel, for_chunks, njit
from .local_consistency import _packed_distance

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
    :func:`~.local_consistency.packed_quarter_levels`): support travels along the line through similar colours
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
