"""Re-decision of the pixels whose match the colours contradict (``photo_consistency``)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..registry import StageTraits, param, register
from .cost import _channels, box_mean_image, colour_switch
from .kernels import photo as kp
from .state import MatchState


@dataclass(frozen=True)
class PhotoConsistencyParams:
    ratio: float = param(4.0, "a pixel is re-decided where its residual (3x3 mean) exceeds this many times the "
                         "map's median residual", low=1.0, high=100.0)
    min_residual: float = param(10.0, "a pixel is re-decided only where its residual (3x3 mean) also exceeds this",
                                unit="grey levels", low=0.0, high=255.0)
    radius: int = param(7, "half side of the support window", unit="px", low=1, high=30)
    step: int = param(2, "the window reads every step-th pixel along rows and columns", unit="px", low=1, high=10)
    gamma_c: float = param(10.0, "colour scale of the support weights, exp(-Δ/γc), Δ the largest channel difference "
                           "from the centre in the left image", unit="grey levels", low=0.1, high=255.0)
    gamma_s: float = param(7.0, "spatial scale of the support weights, exp(-r/γs)", unit="px", low=0.1, high=100.0)
    truncation: float = param(20.0, "colour differences between the views are capped at this", unit="grey levels",
                              low=1.0, high=255.0)
    margin: float = param(3.0, "a candidate replaces the pixel's disparity when its weighted mean difference is "
                          "lower by more than this", unit="grey levels", low=0.0, high=255.0)
    reach: int = param(8, "candidates come from the nearest unflagged pixel up to this far along the 8 "
                       "directions", unit="px", low=1, high=1000)
    iterations: int = param(3, "passes; each after the first re-decides only around the pixels the last one "
                            "changed", low=1, high=20)
    color: bool = param(True, "colour differences on the colour images; false: on the grey images")


@register("refinement", "photo_consistency", PhotoConsistencyParams,
          traits=StageTraits(reads_left_colour=colour_switch, reads_right_colour=colour_switch, map_copies=7))
def photo_consistency(state: MatchState, p: PhotoConsistencyParams) -> None:
    """Re-decide the pixels whose colours disagree with the pixel they match in the right image.

    A wrong disparity usually maps a pixel onto a right pixel of another colour: a thin
    structure given the background's disparity lands on the background, fattened background
    lands on the object. Such pixels are flagged where their colour residual (largest channel
    difference from right pixel ``x − round(d)``, averaged over 3x3) exceeds ``ratio`` times the
    map's median residual and ``min_residual``. Each flagged pixel then chooses among the
    disparities of the nearest unflagged pixels along the 8 directions (those its own colour
    matches better than its value), scored by an adaptive-weight window (Yoon & Kweon 2006:
    proximity and colour similarity in the left image) of truncated colour differences between
    the views; the best replaces its value when better by ``margin``. Passes after the first
    re-decide only next to the pixels the last one changed, which then usually stand out no
    more and offer their value: corrections spread along thin structures. Costs little where
    few pixels stand out (about 6 % of ``quality``'s time on MiddEval3-Q). Invalid pixels are
    left alone and offer no candidate. Notes the threshold (grey levels) and the shares of
    pixels flagged and changed.
    """
    disparity = np.ascontiguousarray(state.disparity, dtype=np.float32)
    left = _channels(state.left if p.color else state.gray("left"))
    right = _channels(state.right if p.color else state.gray("right"))
    valid = np.isfinite(disparity)
    residual = kp.colour_residual(left, right, disparity)
    # The median is the map's usual residual (noise, exposure and sampling differences between
    # the views): a pixel stands out only against it. Every fourth row, every other column.
    smoothed = box_mean_image(residual, 1, 1)
    sample = smoothed[::4, ::2][valid[::4, ::2]]
    threshold = max(p.ratio * float(np.median(sample)), p.min_residual) if sample.size else p.min_residual
    flagged = valid & (smoothed > threshold)
    first_flagged = int(flagged.sum())
    active = np.ones(disparity.shape, np.bool_)
    changed_total = 0
    for _ in range(p.iterations if first_flagged else 0):
        disparity, changed = kp.redecide_flagged(left, right, disparity, flagged, active, p.radius, p.step,
                                                 p.gamma_c, p.gamma_s, p.truncation, p.reach, p.margin)
        changed_at = np.flatnonzero(changed)
        if not len(changed_at):
            break
        changed_total += len(changed_at)
        kp.refresh_after_change(left, right, disparity, residual, changed_at, threshold, flagged, active)
    state.disparity = disparity
    state.notes["photo_consistency"] = {"threshold": round(threshold, 2),
                                        "flagged": round(first_flagged / disparity.size, 4),
                                        "changed": round(changed_total / disparity.size, 4)}
