"""Winner-take-all: each pixel takes the disparity of its lowest cost (local methods)."""

from __future__ import annotations

from ...registry import register
from ..kernels.volume import wta_left
from ..state import MatchState


@register("optimizer", "wta")
def wta(state: MatchState, params) -> None:
    """Lowest cost per pixel (no smoothness term); ties go to the smaller disparity."""
    state.disparity, _ = wta_left(state.cost, state.min_disp, state.cost_max)
