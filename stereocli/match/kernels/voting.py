"""Compiled kernels of the ADCensus outlier handling (Mei et al. 2011): two-threshold cross
arms, region voting, proper interpolation.

Disparity maps are (H, W) float32 px, left-referenced, +inf = outlier (unreliable). Images are
(H, W, C) float32 in [0, 255]. Small pure-numpy references live in
``tests/test_refine_voting.py``.
"""

from __future__ import annotations

import numpy as np
from numba import njit, prange

INF = np.float32(np.inf)

#: The 16 search directions of the proper interpolation (Mei et al. 2011, §4): the 8
#: compass directions plus the 8 knight moves between them, as (dy, dx) steps.
DIRECTIONS16 = np.array(
    [(0, 1), (1, 2), (1, 1), (2, 1), (1, 0), (2, -1), (1, -1), (1, -2),
     (0, -1), (-1, -2), (-1, -1), (-2, -1), (-1, 0), (-2, 1), (-1, 1), (-1, 2)], np.int32)


@njit(cache=True, inline="always")
def _colour_diff(image: np.ndarray, y0: int, x0: int, y1: int, x1: int) -> float:
    diff = 0.0
    for c in range(image.shape[2]):
        diff = max(diff, abs(image[y1, x1, c] - image[y0, x0, c]))
    return diff


#: Arm directions (dy, dx) in the order of the arms arrays: left, right, up, down.
ARM_STEPS = np.array([(0, -1), (0, 1), (-1, 0), (1, 0)], np.int64)


@njit(cache=True, inline="always")
def _arm_length(image: np.ndarray, y: int, x: int, arm: int, tau1: float, tau2: float, max_len1: int,
                max_len2: int) -> int:
    # One arm of pixel (y, x) by the two-threshold rule (see cross_arms_two_threshold).
    h, w = image.shape[0], image.shape[1]
    dy = ARM_STEPS[arm, 0]
    dx = ARM_STEPS[arm, 1]
    n = 0
    while n < max_len1:
        qx = x + (n + 1) * dx
        qy = y + (n + 1) * dy
        if qx < 0 or qx >= w or qy < 0 or qy >= h:
            break
        if n >= 1:
            dp = _colour_diff(image, y, x, qy, qx)
            dq = _colour_diff(image, qy - dy, qx - dx, qy, qx)
            if dp >= tau1 or dq >= tau1 or (n + 1 > max_len2 and dp >= tau2):
                break
        n += 1
    return n


@njit(cache=True, parallel=True)
def cross_arms_two_threshold(image: np.ndarray, tau1: float, tau2: float, max_len1: int, max_len2: int) -> np.ndarray:
    """Arm lengths (H, W, 4) int32 (left, right, up, down) by the two-threshold rule.

    Mei et al. (2011, eq. 4): the arm grows from p to q while
    (1) D_c(p, q) < τ1 and D_c(q, q_prev) < τ1 (q_prev = the arm pixel before q: the arm
    cannot cross an edge even where it returns to p's colour), (2) |p − q| ≤ L1, and
    (3) D_c(p, q) < τ2 once |p − q| > L2 (long arms only through very similar colours, so
    large textureless regions get large supports without leaking across weak edges).
    D_c = max over channels of the absolute difference. As in
    :func:`stereocli.match.kernels.aggregation.cross_arms`, every arm has length ≥ 1 where the
    image allows.
    """
    h, w = image.shape[0], image.shape[1]
    arms = np.zeros((h, w, 4), np.int32)
    for y in prange(h):
        for x in range(w):
            for a in range(4):
                arms[y, x, a] = _arm_length(image, y, x, a, tau1, tau2, max_len1, max_len2)
    return arms


@njit(cache=True, inline="always")
def _arm(arms: np.ndarray, image: np.ndarray, y: int, x: int, a: int, tau1: float, tau2: float,
         max_len1: int, max_len2: int) -> int:
    # arms[y, x, a], computed on first use (−1 = not yet). Two threads may compute the same
    # entry; both write the same value, so the result does not depend on the schedule.
    n = arms[y, x, a]
    if n < 0:
        n = _arm_length(image, y, x, a, tau1, tau2, max_len1, max_len2)
        arms[y, x, a] = n
    return n


@njit(cache=True, parallel=True)
def region_vote(disp: np.ndarray, arms: np.ndarray, image: np.ndarray, tau1: float, tau2: float,
                max_len1: int, max_len2: int, min_disp: int, ndisp: int, min_votes: int,
                min_share: float) -> np.ndarray:
    """One pass of region voting: each outlier takes the dominant reliable disparity of its
    cross support region.

    The support of p is the union of the horizontal arms of the pixels on p's vertical arm
    (Mei et al. 2011, §4, "iterative region voting"). ``arms`` (H, W, 4) int32 holds arm
    lengths as :func:`cross_arms_two_threshold` gives them for ``image`` and the thresholds;
    entries of −1 are computed here on first use and stored, so a caller can pass
    ``np.full((H, W, 4), -1)`` and pay only for the arms that outliers reach (a few % of the
    image after an LR check) instead of every pixel's. Reliable (finite) disparities vote into
    1-px bins ``round(d) − min_disp``; with S votes and H* in the fullest bin, p takes the mean
    of the votes in that bin when S ≥ ``min_votes`` and H*/S ≥ ``min_share``, else stays
    +inf. Reads only the input map (Jacobi update), so the result does not depend on the
    order pixels are visited. Returns a new map.
    """
    h, w = disp.shape
    out = disp.copy()
    for y in prange(h):
        hist = np.zeros(ndisp, np.int32)
        sums = np.zeros(ndisp, np.float64)
        for x in range(w):
            if np.isfinite(disp[y, x]):
                continue
            hist[:] = 0
            sums[:] = 0.0
            total = 0
            up = _arm(arms, image, y, x, 2, tau1, tau2, max_len1, max_len2)
            down = _arm(arms, image, y, x, 3, tau1, tau2, max_len1, max_len2)
            for yy in range(y - up, y + down + 1):
                left = _arm(arms, image, yy, x, 0, tau1, tau2, max_len1, max_len2)
                right = _arm(arms, image, yy, x, 1, tau1, tau2, max_len1, max_len2)
                for xx in range(x - left, x + right + 1):
                    d = disp[yy, xx]
                    if not np.isfinite(d):
                        continue
                    k = int(np.floor(d + 0.5)) - min_disp
                    if k < 0 or k >= ndisp:
                        continue
                    hist[k] += 1
                    sums[k] += d
                    total += 1
            if total < min_votes or total == 0:
                continue
            best = 0
            for k in range(1, ndisp):
                if hist[k] > hist[best]:
                    best = k
            if hist[best] >= min_share * total:
                out[y, x] = np.float32(sums[best] / hist[best])
    return out


@njit(cache=True, parallel=True)
def proper_interpolation(disp: np.ndarray, label: np.ndarray, image: np.ndarray, dirs: np.ndarray,
                         max_steps: int) -> np.ndarray:
    """Fill outliers from the nearest reliable pixels along 16 directions (Mei et al. 2011, §4).

    ``label`` (H, W) uint8: 0 reliable, 1 occluded, 2 mismatched (e.g. from
    :func:`stereocli.match.kernels.refine.classify_holes`). Occluded pixels take the
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
