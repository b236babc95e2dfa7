"""Outlier handling of ADCensus (Mei et al. 2011): iterative region voting and proper
interpolation.

X. Mei, X. Sun, M. Zhou, S. Jiao, H. Wang, X. Zhang, "On building an accurate stereo matching
system on graphics hardware", ICCV Workshops (GPUCV) 2011, §4. The chain there is: LR check
(outliers = +inf) → ``region_voting`` → ``proper_interpolation`` → depth-discontinuity
adjustment → sub-pixel → median 3×3. Both stages here edit the full disparity map (after
``lr_check``, before ``median``). The discontinuity adjustment and the sub-pixel step read the
cost volume, which the pipeline drops before any map stage runs (volume refinements run
first, inside the row strips), so they cannot follow the voting here.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..errors import ConfigError
from ..registry import StageTraits, param, register
from .cost import _channels, left_guide
from .kernels import aggregation as ka
from .kernels import voting as kv
from .refine import InterpolateParams, hole_labels
from .state import MatchState


@dataclass(frozen=True)
class RegionVotingParams:
    tau1: float = param(20.0, "τ1: an arm stops where the colour differs by ≥ τ1 from the pixel or from the previous "
                        "arm pixel", unit="grey levels", low=1.0, high=255.0)
    tau2: float = param(6.0, "τ2: beyond L2 the colour must stay within τ2 of the pixel",
                        unit="grey levels", low=0.0, high=255.0)
    max_arm: int = param(34, "L1: longest arm", unit="px", low=1, high=200)
    max_arm2: int = param(17, "L2: arms longer than this need the stricter τ2", unit="px", low=1, high=200)
    min_votes: int = param(20, "τS: least number of reliable pixels in the support region", low=1, high=100000)
    min_share: float = param(0.4, "τH: least share of the votes in the winning 1-px bin", low=0.0, high=1.0)
    iterations: int = param(5, "voting passes (outliers filled in one pass vote in the next)", low=1, high=50)
    color: bool = param(True, "build the support arms on the colour image (max difference over channels, "
                        "as Mei et al.); false: on the grey image (one channel to compare instead of three)")
    stride: int = param(1, "sample the support every stride-th row and pixel (about stride² fewer votes; min_votes "
                        "stays a full-region count)", low=1, high=8)

    def __post_init__(self):
        if self.max_arm2 > self.max_arm:
            raise ConfigError(f"refinement.region_voting: max_arm2 ({self.max_arm2}) must not exceed "
                              f"max_arm ({self.max_arm})")


@register("refinement", "region_voting", RegionVotingParams, traits=StageTraits(fills_holes=True, map_copies=9))
def region_voting(state: MatchState, p: RegionVotingParams) -> None:
    """Iterative region voting (Mei et al. 2011): outliers take the dominant reliable disparity
    of their cross support region.

    Place after ``lr_check`` (outliers = +inf). Supports are cross regions of the left image
    built with the two-threshold arm rule (τ1, τ2, L1, L2); every reliable pixel in an
    outlier's support votes for its disparity (1-px bins), and the outlier takes the winning
    bin if there are at least ``min_votes`` votes and the bin holds at least ``min_share`` of
    them. Filled pixels vote in the next pass. Recovers occlusions and mismatches inside
    surfaces whose colour region is mostly right; pixels without a clear majority stay +inf
    for ``proper_interpolation``/``fill``. Assumes a colour region is one fronto-parallel-ish
    surface (1-px bins): slanted surfaces spanning many bins vote less decisively.
    """
    arms = ka.cross_arms_two_threshold(left_guide(state, p.color), float(p.tau1), float(p.tau2), int(p.max_arm),
                                       int(p.max_arm2))
    disp = np.ascontiguousarray(state.disparity, dtype=np.float32)
    for i in range(p.iterations):
        new = kv.region_vote(disp, arms, state.min_disp, state.ndisp, int(p.min_votes), float(p.min_share),
                             int(p.stride))
        done = i == p.iterations - 1 or np.array_equal(np.isfinite(new), np.isfinite(disp))
        disp = new
        if done:
            break  # the last pass, or nothing was filled: further passes would see the same votes
    state.disparity = disp


@register("refinement", "proper_interpolation", InterpolateParams,
          traits=StageTraits(needs_right=True, fills_holes=True, map_copies=2))
def proper_interpolation(state: MatchState, p: InterpolateParams) -> None:
    """Fill outliers from the nearest reliable pixels in 16 directions (Mei et al. 2011).

    Outliers are classified from the right-view disparity (as ``interpolate`` does): a
    *mismatch* when some right pixel maps onto it, an *occlusion* otherwise. Occlusions take
    the lowest (background) of the 16 nearest reliable disparities; mismatches the one whose
    left-image colour is most similar. Unlike ``fill`` (row-wise background) it uses colour for
    mismatches and 2-D neighbourhoods for both, so thin foreground structures and holes inside
    surfaces are filled from the right surface. Costs 16 ray walks per outlier.
    """
    steps = max(state.shape) if p.max_dist <= 0 else int(p.max_dist)
    state.disparity = kv.proper_interpolation(np.ascontiguousarray(state.disparity, dtype=np.float32),
                                              hole_labels(state, p.tol), _channels(state.left),
                                              kv.DIRECTIONS16, steps)
