"""Cooperative stereo (Zitnick & Kanade 2000): iterative 3-D support and inhibition.

Match values ``L(x, y, d)`` start from the costs, ``L0 = exp(−C/σ)``, and are iterated::

    S_n = Σ_{(x', y', d') ∈ Φ(x, y, d)} L_n        (support: a 3-D box in (x, y, d))
    L_{n+1} = L0 · ( S_n / Σ_{Ψ(x, y, d)} S_n )^α  (inhibition along both lines of sight)

Support favours locally smooth (continuous) surfaces; inhibition enforces uniqueness: along the
left and the right line of sight only one element should keep a large value. Each pixel takes
the disparity of its largest L; pixels whose largest L stays below ``min_value`` are declared
occluded (+inf).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ...registry import StageTraits, param, register
from ..kernels.aggregation import box_filter_volume
from ..kernels.coop import box_disparity, inhibit, initial_match_values
from ..state import MatchState


@dataclass(frozen=True)
class CoopParams:
    sigma: float = param(0.13, "σ of the initial match values L0 = exp(−C/σ), as a fraction of cost_max",
                         low=1e-6, high=1e6)
    window: tuple[int, int] = param((5, 5), "support window (height, width) in the image, odd",
                                    unit="px", low=1, high=51)
    disp_radius: int = param(1, "support extends ±this many disparities", unit="px", low=0, high=10)
    alpha: float = param(2.0, "inhibition exponent α (> 1 makes the competition converge)", low=1.0, high=10.0)
    iterations: int = param(10, "support/inhibition iterations", low=1, high=200)
    min_value: float = param(0.0, "declare occluded (+inf) where the largest match value is below this (0 = off)",
                             low=0.0, high=1.0)


# Extra volumes: L0, L, support (+ float64 temporaries of the box filter).
@register("optimizer", "coop", CoopParams, traits=StageTraits(volume_copies=4.5))
def coop(state: MatchState, p: CoopParams) -> None:
    """Cooperative algorithm (Zitnick–Kanade): 3-D local support + inhibition along lines of sight.

    Iterates L ← L0·(S/Σ_Ψ S)^α where S is L averaged over a (window × ±disp_radius) box in
    (x, y, d) and Ψ the elements sharing a left or right line of sight. Enforces continuity
    and uniqueness without an explicit energy; cost ~ iterations × a box filter. The final
    volume ``1 − L`` (lower is better) replaces the cost. Couples rows (window height), so
    row strips are processed separately. ``sigma`` is a fraction of ``cost_max``.
    """
    l0 = initial_match_values(state.cost, np.float32(state.cost_max), float(p.sigma) * state.cost_max)
    values = l0
    for _ in range(p.iterations):
        support = box_filter_volume(values, p.window[0] // 2, p.window[1] // 2)
        if p.disp_radius > 0:
            support = box_disparity(support, p.disp_radius)
        values = inhibit(support, l0, state.min_disp, float(p.alpha))
    best = values.max(axis=2)
    disp = (np.argmax(values, axis=2) + state.min_disp).astype(np.float32)
    disp[(best <= 0) | (best < p.min_value)] = np.inf
    cost = 1.0 - values
    cost[l0 <= 0] = 1.0  # impossible entries hold cost_max (contract)
    state.cost = np.ascontiguousarray(cost, dtype=np.float32)
    state.cost_max = 1.0
    state.disparity = disp
