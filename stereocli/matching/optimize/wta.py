"""Winner-take-all: each pixel takes the disparity of its lowest cost (local methods).

With a cost stage that offers a fused kernel (``sad``, ``stad``) the pipeline may run cost +
WTA in one pass without the volume (:func:`stereocli.matching.pipeline.fused_cost_wta`); the
pass leaves :class:`~stereocli.matching.state.WinnerCosts` instead of ``cost``, from which the
volume refinements' ``on_winner_costs`` variants read what they would have read from the volume.
"""

from __future__ import annotations

import numpy as np

from ...registry import StageTraits, register
from ..kernels.fused_sad import subpixel_winner
from ..kernels.winners import wta_left
from ..state import MatchState, WinnerCosts


@register("optimizer", "wta", traits=StageTraits(winner_take_all=True))
def wta(state: MatchState, params) -> None:
    """Lowest cost per pixel (no smoothness term); ties go to the smaller disparity."""
    if state.cost is None:  # (never: the pipeline runs a cost stage first)
        raise RuntimeError("optimizer.wta: no cost volume")
    state.disparity, _ = wta_left(state.cost, state.min_disp, state.cost_max)


def check_winner_coverage(missing: int, stage: str) -> None:
    """Raise if ``missing`` pixels needed costs the winner costs do not hold.

    Only reachable with a refinement order the pipeline's fusion rule does not allow (e.g. a
    second sub-pixel fit): a bug of that rule, not of the data.
    """
    if missing:
        raise RuntimeError(f"refinement.{stage}: {missing} pixels need costs beyond the WTA winner's "
                           "neighbours; run without the fused path (stereocli.matching.pipeline.FUSED = False)")


def subpixel_on_winner(winner: WinnerCosts, disparity: np.ndarray, min_disp: int, ndisp: int,
                       equiangular: bool, stage: str = "subpixel", right: bool = False) -> np.ndarray:
    """Sub-pixel refinement of the WTA disparities from ``winner`` (same result as
    :func:`~stereocli.matching.kernels.winners.subpixel_left` on the volume; ``right``: the
    right-view map from ``winner.costs_right``)."""
    if right:
        if winner.disparity_right is None or winner.costs_right is None:  # (never: asked for with the right view)
            raise RuntimeError(f"refinement.{stage}: the winner costs hold no right view")
        refined, missing = subpixel_winner(winner.disparity_right, winner.costs_right, disparity, min_disp, ndisp,
                                           equiangular, False)
    else:
        refined, missing = subpixel_winner(winner.disparity, winner.costs, disparity, min_disp, ndisp, equiangular)
    check_winner_coverage(int(missing), stage)
    return refined
