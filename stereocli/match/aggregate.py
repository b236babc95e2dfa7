"""Cost-aggregation stages: smooth the cost volume over a support region."""

from __future__ import annotations

from dataclasses import dataclass

from ..registry import param, register
from .kernels.volume import box_filter_volume
from .state import MatchState


@register("aggregation", "none")
def no_aggregation(state: MatchState, params) -> None:
    """Keep the pixel-wise costs (the optimizer provides the smoothness)."""


@dataclass(frozen=True)
class BoxParams:
    window: tuple[int, int] = param((5, 5), "window (height, width), odd", unit="px", low=1, high=101)


@register("aggregation", "box", BoxParams)
def box_aggregation(state: MatchState, p: BoxParams) -> None:
    """Fixed square window mean, O(1) per pixel by running sums (any window size).

    Fast and simple; blurs depth discontinuities by about half a window ("foreground fattening").
    """
    state.cost = box_filter_volume(state.cost, p.window[0] // 2, p.window[1] // 2)
