"""Refinement stages: sub-pixel, consistency checks, filters, hole filling.

Stages registered with ``needs_cost=True`` run inside each row strip while the optimizer's
cost volume is available; the others run on the full stitched disparity map, in list order.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..registry import param, register
from .kernels import maps as km
from .kernels.volume import subpixel_left, subpixel_right
from .state import MatchState


@dataclass(frozen=True)
class SubpixelParams:
    method: str = param("parabola", "curve fitted through the costs at d-1, d, d+1", choices=("parabola", "equiangular"))


@register("refinement", "subpixel", SubpixelParams, needs_cost=True)
def subpixel(state: MatchState, p: SubpixelParams) -> None:
    """Sub-pixel disparity from the costs around the winner (left and, if present, right view).

    Parabola suits smooth (squared-like) costs such as SGM sums; equiangular (a symmetric V)
    suits absolute-difference-like costs and has less bias towards integers on them.
    """
    equi = p.method == "equiangular"
    state.disparity = subpixel_left(state.cost, state.disparity, state.min_disp, equi)
    if state.disparity_right is not None:
        state.disparity_right = subpixel_right(state.cost, state.disparity_right, state.min_disp, equi)


@dataclass(frozen=True)
class LRCheckParams:
    max_diff: float = param(1.0, "largest accepted |d_left - d_right| at corresponding pixels", unit="px", low=0.0, high=100.0)


@register("refinement", "lr_check", LRCheckParams, needs_right=True)
def lr_check(state: MatchState, p: LRCheckParams) -> None:
    """Left-right consistency check: invalidate pixels the right view's disparity contradicts.

    Removes occlusions and most mismatches; the right disparity comes from the same volume
    (Hirschmüller 2008, §2.5), so it costs one extra pass, not a second match.
    """
    state.disparity = km.lr_check(state.disparity, state.disparity_right, float(p.max_diff))


@dataclass(frozen=True)
class MedianParams:
    size: int = param(3, "window side (odd)", unit="px", low=3, high=15)


@register("refinement", "median", MedianParams)
def median(state: MatchState, p: MedianParams) -> None:
    """Median filter over valid disparities only (holes neither spread nor get filled)."""
    if p.size % 2 == 0:
        from ..errors import ConfigError

        raise ConfigError(f"refinement.median.size: {p.size} must be odd")
    state.disparity = km.median_finite(state.disparity, p.size // 2)


@register("refinement", "fill")
def fill(state: MatchState, params) -> None:
    """Fill invalid pixels along scanlines with the background (smaller) neighbouring disparity.

    Makes the output dense (the Middlebury v2 tables score dense maps). ``match --keep-invalid``
    skips this stage.
    """
    state.disparity = km.fill_background(state.disparity)


def clear_invalid_left(state: MatchState) -> None:
    """Mark pixels outside the left valid mask invalid (used by the pipeline)."""
    if state.left_valid is not None and state.disparity is not None:
        state.disparity = np.where(state.left_valid, state.disparity, np.float32(np.inf)).astype(np.float32)
