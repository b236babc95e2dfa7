"""Dynamic programming along scanlines with an occlusion cost and the ordering constraint.

Energy of one row (Scharstein & Szeliski 2002, §4.3; Bobick & Intille 1999; Cox et al. 1996)::

    E = Σ_{matched left pixels x} C(x, d_x) + κ_occ · (#left-occluded + #right-occluded pixels)

minimised exactly over monotone alignments of the left and right scanlines (ordering
constraint, uniqueness). Rows are independent, so the result shows the classic horizontal
streaks; aggregating the costs first (``aggregation: box``) reduces them.
"""

from __future__ import annotations

from dataclasses import dataclass

from ...registry import param, register
from ..kernels.dp import dp_occlusion
from ..state import MatchState


@dataclass(frozen=True)
class DPParams:
    occlusion: float = param(0.2, "cost κ_occ of one occluded (unmatched) left or right pixel, as a fraction of the "
                             "cost's range (cost_max); higher = fewer occlusions", low=0.0, high=1e4)


@register("optimizer", "dp", DPParams)
def dp(state: MatchState, p: DPParams) -> None:
    """Scanline DP with occlusion cost and ordering constraint (one exact 1-D alignment per row).

    Energy: Σ C(x, d_x) over matched pixels + occlusion · (#unmatched left + right pixels),
    minimised over monotone (order-preserving, one-to-one) row alignments. Left pixels the DP
    labels occluded come out +inf (``fill`` completes them); it sets the right-view disparity
    from the same alignment, so ``lr_check`` agrees with it by construction. Fast (O(W·D) per
    row) but rows are independent: horizontal streaks. ``occlusion`` is a fraction of the cost
    volume's range ``cost_max`` (like ``sgm``'s penalties), so it carries over between costs.
    """
    state.disparity, right = dp_occlusion(state.cost, state.min_disp, float(p.occlusion) * state.cost_max)
    state.disparity_right = right
