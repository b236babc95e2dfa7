"""Compiled kernels of the ADCensus outlier handling (Mei et al. 2011): region voting and proper
interpolation (the two-threshold cross arms are in :mod:`.aggregation`).

Disparity maps are (H, W) float32 px, left-referenced, +inf = outlier (unreliable). Images are
(H, W, C) float32 in [0, 255]. Small pure-numpy references live in
``tests/test_refine_voting.py``.
"""

from __future__ import annotations

import numpy as np

from ...runtime import chunk_kernel, for_rows, njit, prange
from .maps import disparity_bins

INF = np.float32(np.inf)

#: The 16 search directions of the proper interpolation (Mei et al. 2011, §4): the 8
#: compass directions plus the 8 knight moves between them, as (dy, dx) steps.
DIRECTIONS16 = np.array(
    [(0, 1), (1, 2), (1, 1), (2, 1), (1, 0), (2, -1), (1, -1), (1, -2),
     (0, -1), (-1, -2), (-1, -1), (-2, -1), (-1, 0), (-2, 1), (-1, 1), (-1, 2)], np.int32)


def region_vote(disp: np.ndarray, arms: np.ndarray, min_disp: int, ndisp: int, min_votes: int,
                min_share: float, stride: int = 1) -> np.ndarray:
    """One pass of region voting: each outlier takes the dominant reliable disparity of its
    cross support region.

    The support of p is the union of the horizontal arms of the pixels on p's vertical arm (Mei et
    al. 2011, §4, "iterative region voting"); ``arms`` (H, W, 4) int32 as
    :func:`stereocli.matching.kernels.aggregation.cross_arms_two_threshold` gives them. Reliable
    (finite) disparities vote into 1-px bins ``round(d) − min_disp``; with S votes and H* in the
    fullest bin, p takes the mean of the votes in that bin when S ≥ ``min_votes`` and H*/S ≥
    ``min_share``, else stays +inf. ``stride`` > 1 samples the support on a grid of that step
    through p (every ``stride``-th row of the vertical arm, every ``stride``-th pixel of each
    horizontal arm): about stride² fewer votes, with ``min_votes`` counted on the full region
    (divided by stride²). Reads only the input map (Jacobi update), so the result does not depend on
    the order pixels are visited. Returns a new map.
    """
    disp = np.ascontiguousarray(disp, dtype=np.float32)
    arms = np.ascontiguousarray(arms, dtype=np.int32)
    h, w = disp.shape
    out = disp.copy()
    need = max(1, (int(min_votes) + stride * stride - 1) // (stride * stride))
    # An arm of length a reaches a − a mod stride on the grid: looked up, not divided, per row.
    snap = np.arange(max(h, w) + 1, dtype=np.int64) // stride * stride
    # Each pixel's vote, computed once (a pixel is in the regions of up to ~300 outliers): its
    # 1-px bin, or −1 for an outlier or a disparity outside the range.
    bins = disparity_bins(disp, min_disp, ndisp)
    for_rows(_region_vote_rows, h, disp, arms, bins, snap, int(ndisp), int(need), float(min_share), int(stride), out)
    return out


@chunk_kernel
def _region_vote_rows(disp, arms, bins, snap, ndisp: int, need: int, min_share: float, stride: int, out,
                      i0: int, i1: int) -> None:
    """:func:`region_vote` of the rows ``i0 ≤ i < i1`` of the interleaved order."""
    h, w = disp.shape
    half = (h + 1) // 2
    hist = np.zeros(ndisp, np.int32)
    sums = np.zeros(ndisp, np.float64)
    for i in range(i0, i1):
        # Rows interleaved from both halves of the image: outliers cluster (occluded bands,
        # textureless areas), and each chunk is one contiguous block of i.
        y = i // 2 if i % 2 == 0 else half + i // 2
        for x in range(w):
            if np.isfinite(disp[y, x]):
                continue
            total = 0
            kmin = ndisp
            kmax = -1
            # While loops: a range with a run-time step costs a division per loop.
            yy = y - snap[arms[y, x, 2]]
            y_end = y + arms[y, x, 3] + 1
            while yy < y_end:
                row_bins = bins[yy]
                row_disp = disp[yy]
                xx = x - snap[arms[yy, x, 0]]
                x_end = x + arms[yy, x, 1] + 1
                while xx < x_end:
                    k = row_bins[xx]
                    if k >= 0:
                        hist[k] += 1
                        sums[k] += row_disp[xx]
                        total += 1
                        kmin = min(kmin, k)
                        kmax = max(kmax, k)
                    xx += stride
                yy += stride
            if total == 0:
                continue
            # Only the bins in [kmin, kmax] were touched: scan them, then clear them again (the
            # histograms stay all zero between outliers).
            best = kmin
            for k in range(kmin + 1, kmax + 1):
                if hist[k] > hist[best]:
                    best = k
            if total >= need and hist[best] >= min_share * total:
                out[y, x] = np.float32(sums[best] / hist[best])
            hist[kmin:kmax + 1] = 0
            sums[kmin:kmax + 1] = 0.0


@njit(cache=True, parallel=True)
def proper_interpolation(disp: np.ndarray, label: np.ndarray, image: np.ndarray, dirs: np.ndarray,
                         max_steps: int) -> np.ndarray:
    """Fill outliers from the nearest reliable pixels along 16 directions (Mei et al. 2011, §4).

    ``label`` (H, W) uint8: 0 reliable, 1 occluded, 2 mismatched (e.g. from
    :func:`stereocli.matching.kernels.refine.classify_holes`). Occluded pixels take the
    smallest found disparity (an occlusion belongs to the background surface); mismatched
    ones the disparity of the found pixel whose colour is most similar (sum of absolute
    channel differences), since a mismatch lies inside some visible surface. Only reliable
    pixels of the input are used (one pass, order independent); a pixel with nothing found
    within ``max_steps`` steps in any direction stays +inf. Returns a new map.
    """
    h, w = disp.shape
    nc = image.shape[2]
    out = disp.copy()
    nd = dirs.shape[0]
    for y in prange(h):
        for x in range(w):
            if np.isfinite(disp[y, x]) or label[y, x] == 0:
                continue
            best = INF
            best_cd = np.inf
            for i in range(nd):
                dy = dirs[i, 0]
                dx = dirs[i, 1]
                qy, qx = y + dy, x + dx
                s = 1
                while 0 <= qy < h and 0 <= qx < w and s <= max_steps:
                    d = disp[qy, qx]
                    if np.isfinite(d):
                        if label[y, x] == 1:
                            if d < best:
                                best = d
                        else:
                            cd = 0.0
                            for c in range(nc):
                                cd += abs(image[qy, qx, c] - image[y, x, c])
                            if cd < best_cd:
                                best_cd = cd
                                best = d
                        break
                    qy += dy
                    qx += dx
                    s += 1
            out[y, x] = best
    return out
