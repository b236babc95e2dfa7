"""Hierarchical loopy min-sum belief propagation (Felzenszwalb & Huttenlocher 2006).

Energy on the 4-connected pixel grid (an MRF)::

    E(d) = Σ_p D_p(d_p) + Σ_{(p,q) ∈ N4} λ · w_pq · min(|d_p − d_q|, T)
    D_p(d) = data_weight · min(C(p, d), data_trunc)

with ``w_pq = edge_factor`` where the grey difference of p and q is below ``edge_threshold``.
Min-sum messages are computed in O(D) by the truncated-linear distance transform, updated in
a checkerboard schedule, and initialised coarse-to-fine: level l+1 nodes cover 2×2 blocks of
level l and sum their data costs; after ``iterations`` sweeps a level's messages initialise
the next finer level (FH §4). The final beliefs ``D_p + Σ incoming messages`` become the
cost volume (so sub-pixel fitting and the right view use them).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ...registry import StageTraits, param, register
from ..kernels import bp as kb
from ..kernels.dp import edge_weights, mark_impossible
from ..state import MatchState


@dataclass(frozen=True)
class BPParams:
    smoothness: float = param(0.065, "λ: penalty per pixel of disparity difference between 4-neighbours, as a "
                              "fraction of cost_max", unit="1/px", low=0.0, high=1e6)
    truncate: float = param(2.0, "T: the penalty stops growing beyond this jump (discontinuity cost λ·T)",
                            unit="px", low=0.0, high=1e4)
    data_weight: float = param(1.0, "multiplier of the data cost", low=0.0, high=1e6)
    data_trunc: float = param(0.0, "truncate the data cost at this fraction of cost_max (0 = off), robust to outliers",
                              low=0.0, high=1.0)
    iterations: int = param(6, "message-passing sweeps per pyramid level", low=1, high=1000)
    levels: int = param(5, "pyramid levels (1 = plain loopy BP on the full grid)", low=1, high=12)
    edge_threshold: float = param(8.0, "grey difference below which neighbours count as the same surface",
                                  unit="grey levels", low=0.0, high=255.0)
    edge_factor: float = param(2.0, "smoothness multiplier between same-surface neighbours (1 = off)",
                               low=1.0, high=100.0)


# Extra volumes: data term, 4 message volumes, beliefs.
@register("optimizer", "bp", BPParams, traits=StageTraits(volume_copies=6.5))
def bp(state: MatchState, p: BPParams) -> None:
    """Hierarchical loopy min-sum belief propagation, truncated-linear smoothness (FH 2006).

    Energy: Σ_p data_weight·min(C, data_trunc) + Σ_{4-neighbours} λ·w_pq·min(|d_p − d_q|, T).
    A global 2-D MRF: fills textureless areas and keeps discontinuities at colour edges, at
    about iterations × levels × 4 message passes of O(D) per pixel (seconds on 0.2 MP). The
    final beliefs replace the cost volume. Memory: 6 volumes. In row strips (only for very
    large images) each strip is optimised on its own. λ and data_trunc are fractions of
    the cost range ``cost_max`` (like ``sgm``'s penalties).
    """
    cost = state.cost
    if cost is None:  # (never: the pipeline runs a cost stage first)
        raise RuntimeError("optimizer.bp: no cost volume")
    h, w, nd = cost.shape
    data0 = kb.data_term(cost, float(p.data_weight), float(p.data_trunc) * state.cost_max)
    wh0, wv0 = edge_weights(np.ascontiguousarray(state.gray("left")), float(p.edge_threshold), float(p.edge_factor))
    pyramid = [(data0, wh0, wv0)]
    for _ in range(1, p.levels):
        d, a, b = pyramid[-1]
        if min(d.shape[0], d.shape[1]) < 4:
            break
        ca, cb = kb.downsample_weights(a, b)
        pyramid.append((kb.downsample_data(d), ca, cb))
    msgs: list[np.ndarray] = []
    for data, wh, wv in reversed(pyramid):
        lh, lw = data.shape[:2]
        if not msgs:
            msgs = [np.zeros((lh, lw, nd), np.float32) for _ in range(4)]
        else:
            msgs = [kb.upsample_messages(m, lh, lw) for m in msgs]
        kb.bp_iterate(data, *msgs, wh, wv, float(p.smoothness) * state.cost_max, float(p.truncate), int(p.iterations))
    belief = kb.beliefs(data0, *msgs)
    del msgs
    impossible = np.all(cost >= np.float32(state.cost_max), axis=2)
    state.cost_max = float(mark_impossible(belief, cost, np.float32(state.cost_max)))
    state.cost = belief
    disp = (np.argmin(belief, axis=2) + state.min_disp).astype(np.float32)
    disp[impossible] = np.inf
    state.disparity = disp
