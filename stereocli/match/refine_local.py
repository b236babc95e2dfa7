"""Outlier handling for local (area-based) matchers: single matching phase, texture threshold.

The uniqueness-ratio test lives in :mod:`stereocli.match.refine` (stage ``uniqueness``); these
stages complement it. Both mark rejected pixels +inf (invalid).
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
from numba import njit, prange

from ..registry import param, register
from .optimize.wta import check_winner_coverage
from .state import MatchState

INF = np.float32(np.inf)


@njit(cache=True, inline="always")
def _resolve_row(disp, out, y, claims, min_disp, ndisp, owner, owner_cost):
    # One left→right pass over row y; claims[x] is the cost of left x at round(disp[y, x]).
    w = disp.shape[1]
    for xr in range(w):
        owner[xr] = -1
    for x in range(w):
        d = disp[y, x]
        if not np.isfinite(d):
            continue
        di = int(np.floor(d + 0.5))
        k = di - min_disp
        xr = x - di
        if xr < 0 or xr >= w or k < 0 or k >= ndisp:
            out[y, x] = INF
            continue
        c = claims[x]
        o = owner[xr]
        if o < 0:
            owner[xr] = x
            owner_cost[xr] = c
        elif c < owner_cost[xr]:
            out[y, o] = INF  # the earlier claim loses: a collision exposes a wrong match
            owner[xr] = x
            owner_cost[xr] = c
        else:
            out[y, x] = INF


@njit(cache=True, parallel=True)
def single_matching_phase_kernel(disp: np.ndarray, cost: np.ndarray, min_disp: int) -> np.ndarray:
    """One left→right pass per row; when two left pixels claim the same right pixel, the one
    with the lower cost keeps it and the other becomes +inf (Di Stefano, Marchionni &
    Mattoccia, IVC 2004, §3). ``disp`` holds integer-valued float32 disparities (+inf invalid);
    ``cost`` is the (H, W, D) volume (float32 or uint16).
    """
    h, w = disp.shape
    nd = cost.shape[2]
    out = disp.copy()
    for y in prange(h):
        owner = np.empty(w, np.int64)
        owner_cost = np.empty(w, np.float32)
        claims = np.zeros(w, np.float32)
        for x in range(w):
            d = disp[y, x]
            if np.isfinite(d):
                k = int(np.floor(d + 0.5)) - min_disp
                if 0 <= k < nd:
                    claims[x] = cost[y, x, k]
        _resolve_row(disp, out, y, claims, min_disp, nd, owner, owner_cost)
    return out


@njit(cache=True, parallel=True)
def single_matching_phase_winner_kernel(disp: np.ndarray, wdisp: np.ndarray, wcosts: np.ndarray,
                                        min_disp: int, ndisp: int):
    """:func:`single_matching_phase_kernel` with the claim costs read from the costs kept around
    each WTA winner (fused cost + WTA path, :class:`~stereocli.match.state.WinnerCosts`).

    Returns ``(out, missing)``; ``missing`` counts pixels whose ``round(disp)`` is more than 1
    from the winner ``wdisp`` (none right after WTA or sub-pixel refinement).
    """
    h, w = disp.shape
    out = disp.copy()
    missing = np.zeros(h, np.int64)
    for y in prange(h):
        owner = np.empty(w, np.int64)
        owner_cost = np.empty(w, np.float32)
        claims = np.zeros(w, np.float32)
        for x in range(w):
            d = disp[y, x]
            if np.isfinite(d):
                k = int(np.floor(d + 0.5)) - min_disp
                if 0 <= k < ndisp:
                    j = k - (int(wdisp[y, x]) - min_disp) if np.isfinite(wdisp[y, x]) else 2
                    if -1 <= j <= 1:
                        claims[x] = wcosts[y, x, j + 1]
                    else:
                        missing[y] += 1
        _resolve_row(disp, out, y, claims, min_disp, ndisp, owner, owner_cost)
    return out, missing.sum()


@register("refinement", "single_matching_phase", needs_cost=True)
def single_matching_phase(state: MatchState, params) -> None:
    """Single matching phase (SMP): reject left pixels whose right match is claimed by a better one.

    Di Stefano, Marchionni & Mattoccia ("A fast area-based stereo matching algorithm", IVC
    2004): matching left to right only, a right pixel claimed twice reveals at least one
    wrong match; the lower-cost claim is kept and the other invalidated. It catches most of
    what a left-right check catches (occlusions, ambiguous matches) without computing the
    right-view disparity. Run it right after WTA, before ``subpixel``.
    """
    state.disparity = single_matching_phase_kernel(state.disparity, state.cost, state.min_disp)


def _single_matching_phase_on_winner_costs(state: MatchState, params) -> None:
    # Fused cost + WTA path (stereocli.match.pipeline): the claim costs come from the costs
    # around each winner instead of the volume; same result.
    win = state.winner
    state.disparity, missing = single_matching_phase_winner_kernel(state.disparity, win.disparity, win.costs,
                                                                   state.min_disp, state.ndisp)
    check_winner_coverage(int(missing), "single_matching_phase")


single_matching_phase.on_winner_costs = _single_matching_phase_on_winner_costs


@dataclass(frozen=True)
class TextureParams:
    window: tuple[int, int] = param((9, 9), "window (height, width) of the local variance, odd", unit="px", low=3, high=101)
    min_std: float = param(2.0, "invalidate pixels whose local grey-level standard deviation is below this", unit="grey levels", low=0.0, high=128.0)

    def __post_init__(self):
        from .cost import check_odd_window

        check_odd_window("refinement.texture.window", self.window)


@register("refinement", "texture", TextureParams)
def texture(state: MatchState, p: TextureParams) -> None:
    """Texture threshold: mark pixels in uniform regions (low local variance) invalid.

    Area-based matching is unreliable where the window has no texture; the local standard
    deviation of the left grey image (after preprocessing) over the window is compared with
    ``min_std`` (a variance threshold of min_std²), like StereoBM's textureThreshold. Higher
    values remove more wrong matches and more correct ones in weak texture.
    """
    gray = np.asarray(state.gray("left"), dtype=np.float32)
    ksize = (p.window[1], p.window[0])
    mean = cv2.boxFilter(gray, -1, ksize, borderType=cv2.BORDER_REFLECT)
    mean_sq = cv2.boxFilter(gray * gray, -1, ksize, borderType=cv2.BORDER_REFLECT)
    var = mean_sq - mean * mean
    disparity = np.array(state.disparity, dtype=np.float32)  # a new map: stages never edit in place
    disparity[var < p.min_std * p.min_std] = INF
    state.disparity = disparity


@njit(cache=True, parallel=True)
def weighted_median_at(disp: np.ndarray, todo: np.ndarray, guide: np.ndarray, radius: int,
                       sigma_s: float, sigma_c: float) -> np.ndarray:
    """Bilateral-weighted median of the finite disparities around each ``todo`` pixel.

    Weight exp(−Δs²/σ_s² − ‖ΔI‖²/σ_c²) with ‖ΔI‖ the colour distance in ``guide`` (H, W, C)
    (Hosni et al. 2013, §4.1). Other pixels are copied unchanged.
    """
    h, w = disp.shape
    nc = guide.shape[2]
    out = disp.copy()
    n = (2 * radius + 1) ** 2
    inv_s = 1.0 / (sigma_s * sigma_s)
    inv_c = 1.0 / (sigma_c * sigma_c)
    for y in prange(h):
        vals = np.empty(n, np.float32)
        wts = np.empty(n, np.float64)
        for x in range(w):
            if not todo[y, x]:
                continue
            m = 0
            total = 0.0
            for qy in range(max(0, y - radius), min(h, y + radius + 1)):
                for qx in range(max(0, x - radius), min(w, x + radius + 1)):
                    v = disp[qy, qx]
                    if not np.isfinite(v):
                        continue
                    dc = 0.0
                    for c in range(nc):
                        t = guide[y, x, c] - guide[qy, qx, c]
                        dc += t * t
                    wt = np.exp(-((qy - y) ** 2 + (qx - x) ** 2) * inv_s - dc * inv_c)
                    vals[m] = v
                    wts[m] = wt
                    total += wt
                    m += 1
            if m == 0:
                continue
            order = np.argsort(vals[:m])
            acc = 0.0
            for i in range(m):
                acc += wts[order[i]]
                if acc >= 0.5 * total:
                    out[y, x] = vals[order[i]]
                    break
    return out


@dataclass(frozen=True)
class FillWeightedMedianParams:
    radius: int = param(9, "window radius of the weighted median", unit="px", low=1, high=50)
    sigma_s: float = param(9.0, "spatial scale σ_s", unit="px", low=0.1, high=100.0)
    sigma_c: float = param(25.5, "colour scale σ_c (0.1 on [0, 1] intensities)", unit="grey levels", low=0.1, high=255.0)


@register("refinement", "fill_weighted_median", FillWeightedMedianParams)
def fill_weighted_median(state: MatchState, p: FillWeightedMedianParams) -> None:
    """Fill holes with the background disparity, then smooth only the filled pixels by a
    bilateral-weighted median.

    The post-processing of Hosni et al.'s cost-volume filtering (PAMI 2013, §4.1): invalid
    pixels (e.g. after ``lr_check``) take the smaller of the nearest valid disparities on
    their scanline, which leaves horizontal streaks; a weighted median guided by the left
    image's colour (window 2r+1) then removes them without touching valid pixels. Dense output.
    """
    from .kernels import maps as km

    invalid = ~np.isfinite(state.disparity)
    filled = km.fill_background(state.disparity)
    guide = np.ascontiguousarray(state.left if state.left.ndim == 3 else state.left[..., None], dtype=np.float32)
    state.disparity = weighted_median_at(filled, invalid, guide, p.radius, float(p.sigma_s), float(p.sigma_c))
