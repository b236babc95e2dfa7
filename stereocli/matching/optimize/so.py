"""Scanline optimisation (SO): exact 1-D smoothness along each row, no occlusion model.

Energy of one row (Scharstein & Szeliski 2002, §4.3)::

    E = Σ_x C(x, d_x) + Σ_x λ · w_x · min(|d_x − d_{x+1}|, T)

with ``w_x = edge_factor`` where the grey difference between x and x+1 is below
``edge_threshold`` (same surface likely) and 1 across colour edges. Solved by Viterbi in
O(W·D) per row using the truncated-linear distance transform.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ...registry import StageTraits, param, register
from ..kernels.dp import edge_weights, mark_impossible, scanline_optimize
from ..state import MatchState


@dataclass(frozen=True)
class SOParams:
    smoothness: float = param(0.1, "λ: penalty per pixel of disparity change between horizontal neighbours, as a "
                              "fraction of cost_max", unit="1/px", low=0.0, high=1e6)
    truncate: float = param(2.0, "T: the penalty stops growing beyond this jump (1 = Potts)",
                            unit="px", low=0.0, high=1e4)
    edge_threshold: float = param(8.0, "grey difference below which neighbours count as the same surface",
                                  unit="grey levels", low=0.0, high=255.0)
    edge_factor: float = param(2.0, "smoothness multiplier between same-surface neighbours (1 = off)",
                               low=1.0, high=100.0)


# Extra volumes: min-marginals + per-row buffers.
@register("optimizer", "so", SOParams, traits=StageTraits(volume_copies=2.2))
def so(state: MatchState, p: SOParams) -> None:
    """Scanline optimisation: exact minimum of data + 1-D truncated-linear smoothness per row.

    Energy: Σ C(x, d_x) + Σ λ·w_x·min(|d_x − d_{x+1}|, T), w_x = edge_factor inside
    uniform-colour areas. No occlusion model (occluded pixels get some disparity; use
    ``lr_check``). Leaves the rows' min-marginals in the cost volume for sub-pixel fitting.
    Rows are independent (streaks); combine with strong aggregation (``adaptive_weights``,
    ``box``) for the "SO on top of adaptive weights" method. λ is a fraction of the cost
    range ``cost_max`` (like ``sgm``'s penalties).
    """
    wh, _ = edge_weights(np.ascontiguousarray(state.gray("left")), float(p.edge_threshold), float(p.edge_factor))
    labels, marg = scanline_optimize(state.cost, wh, float(p.smoothness) * state.cost_max, float(p.truncate))
    impossible = _all_impossible(state)
    state.cost_max = float(mark_impossible(marg, state.cost, np.float32(state.cost_max)))
    state.cost = marg
    disp = (labels + state.min_disp).astype(np.float32)
    disp[impossible] = np.inf
    state.disparity = disp


def _all_impossible(state: MatchState) -> np.ndarray:
    """(H, W) bool: pixels where every hypothesis holds cost_max (nothing to match)."""
    return np.all(state.cost >= np.float32(state.cost_max), axis=2)
