"""Outlier handling for local (area-based) matchers: single matching phase, texture threshold.

The uniqueness-ratio test lives in :mod:`stereocli.matching.refine` (stage ``uniqueness``); these
stages complement it. Both mark rejected pixels +inf (invalid).
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from ..registry import StageTraits, param, register
from .kernels.refine import single_matching_phase_kernel, single_matching_phase_winner_kernel, weighted_median_at
from .optimize.wta import check_winner_coverage
from .state import MatchState, required

INF = np.float32(np.inf)


def _single_matching_phase_on_winner_costs(state: MatchState, params) -> None:
    """the claim costs from the costs kept around each winner (fused cost + WTA)"""
    win = required(state.winner, "refinement.single_matching_phase: no winner costs")
    disparity = required(state.disparity, "refinement.single_matching_phase: no disparity map")
    state.disparity, missing = single_matching_phase_winner_kernel(disparity, win.disparity, win.costs,
                                                                   state.min_disp, state.ndisp)
    check_winner_coverage(int(missing), "single_matching_phase")


@register("refinement", "single_matching_phase",
          traits=StageTraits(needs_cost=True, on_winner_costs=_single_matching_phase_on_winner_costs))
def single_matching_phase(state: MatchState, params) -> None:
    """Single matching phase (SMP): reject left pixels whose right match is claimed by a better one.

    Di Stefano, Marchionni & Mattoccia ("A fast area-based stereo matching algorithm", IVC
    2004): matching left to right only, a right pixel claimed twice reveals at least one
    wrong match; the lower-cost claim is kept and the other invalidated. It catches most of
    what a left-right check catches (occlusions, ambiguous matches) without computing the
    right-view disparity. Run it right after WTA, before ``subpixel``.
    """
    state.disparity = single_matching_phase_kernel(
        required(state.disparity, "refinement.single_matching_phase: no disparity map"),
        required(state.cost, "refinement.single_matching_phase: no cost volume"), state.min_disp)


@dataclass(frozen=True)
class TextureParams:
    window: tuple[int, int] = param((9, 9), "window (height, width) of the local variance, odd",
                                    unit="px", low=3, high=101)
    min_std: float = param(2.0, "invalidate pixels whose local grey-level standard deviation is below this",
                           unit="grey levels", low=0.0, high=128.0)

    def __post_init__(self):
        from .cost import check_odd_window

        check_odd_window("refinement.texture.window", self.window)


@register("refinement", "texture", TextureParams, traits=StageTraits(map_copies=6))
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


@dataclass(frozen=True)
class FillWeightedMedianParams:
    radius: int = param(9, "window radius of the weighted median", unit="px", low=1, high=50)
    sigma_s: float = param(9.0, "spatial scale σ_s", unit="px", low=0.1, high=100.0)
    sigma_c: float = param(25.5, "colour scale σ_c (0.1 on [0, 1] intensities)",
                           unit="grey levels", low=0.1, high=255.0)


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

    disparity = required(state.disparity, "refinement.fill_weighted_median: no disparity map")
    invalid = ~np.isfinite(disparity)
    filled = km.fill_background(disparity)
    guide = np.ascontiguousarray(state.left if state.left.ndim == 3 else state.left[..., None], dtype=np.float32)
    state.disparity = weighted_median_at(filled, invalid, guide, p.radius, float(p.sigma_s), float(p.sigma_c))
