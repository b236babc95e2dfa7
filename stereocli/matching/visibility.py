"""What a matched map may claim: which left pixels the right view can show over the searched
range, and the range a disparity must stay in.

A left pixel ``x`` of row ``y`` with disparity ``d`` is seen by the right view at ``x − d``, if
that lies inside the right image (and inside its valid mask, when there is one). A pixel is
**outside the views**, and has no match, when no ``d`` of the searched range
``[min_disp, min_disp + ndisp)`` lands on a (valid) right pixel: the left border strip
``x < min_disp`` (and ``x ≥ W + min_disp + ndisp − 1`` for negative ranges), the parts of rows
that the right view's valid mask leaves black; or when it lies outside the left valid mask.
The matcher would still give such a pixel a disparity (its costs all equal, the smallest
disparity wins): a stand-in, not a match.

The pipeline marks them invalid before the map refinements (:func:`find_unmatched`) and sets
them again at the end: invalid, or, when a stage filled the map's holes, the nearest visible
background of their row (see ``pipeline.finish``). Every stage's output is kept within the
range, allowing the 1 px a sub-pixel fit may add at either end (:func:`keep_in_range`).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

#: How far a disparity may leave the searched range: a sub-pixel fit at its last hypothesis (px).
RANGE_SLACK = 1.0


@dataclass
class Unmatched:
    """The left pixels without a match."""

    outside_views: np.ndarray  # (H, W) bool

    def counts(self) -> dict[str, int]:
        """``{"pixels": N}``, what ``params.json`` records."""
        return {"pixels": int(self.outside_views.sum())}


def right_candidates(shape: tuple[int, int], min_disp: int, ndisp: int,
                     right_valid: np.ndarray | None = None) -> np.ndarray:
    """How many disparities of ``[min_disp, min_disp + ndisp)`` put each left pixel's match on a
    right pixel: (1, W) int32 without ``right_valid`` (the same for every row), else (H, W)
    int32 counting valid right pixels only."""
    h, w = shape
    x = np.arange(w, dtype=np.int64)
    first = np.maximum(x - min_disp - ndisp + 1, 0)  # right columns x − d, d from the top of the range
    last = np.minimum(x - min_disp, w - 1)
    if right_valid is None:
        return np.maximum(last - first + 1, 0).astype(np.int32)[None, :]
    cumulative = np.zeros((h, w + 1), np.int32)
    np.cumsum(right_valid, axis=1, dtype=np.int32, out=cumulative[:, 1:])
    ok = last >= first
    lo, hi = np.clip(first, 0, w), np.clip(last + 1, 0, w)
    return np.where(ok[None, :], cumulative[:, hi] - cumulative[:, lo], 0).astype(np.int32)


def find_unmatched(shape: tuple[int, int], min_disp: int, ndisp: int, left_valid: np.ndarray | None = None,
                   right_valid: np.ndarray | None = None) -> Unmatched:
    """The pixels of a left map of ``shape`` (H, W), searched over ``[min_disp, min_disp + ndisp)``,
    that lie outside the views (module docstring); masks (H, W) bool or None."""
    outside = np.broadcast_to(right_candidates(shape, min_disp, ndisp, right_valid) == 0, shape)
    if left_valid is not None:
        outside = outside | ~left_valid
    return Unmatched(np.ascontiguousarray(outside))


def range_bounds(min_disp: int, ndisp: int) -> tuple[np.float32, np.float32]:
    """The disparities a map may hold for the range ``[min_disp, min_disp + ndisp)``: the range
    plus :data:`RANGE_SLACK` each side, px."""
    return np.float32(min_disp - RANGE_SLACK), np.float32(min_disp + ndisp - 1 + RANGE_SLACK)


def keep_in_range(disparity: np.ndarray, min_disp: int, ndisp: int) -> np.ndarray:
    """``disparity`` (H, W) float32 with finite values clamped to ``[min_disp − 1, min_disp + ndisp]``
    (the range plus :data:`RANGE_SLACK`); the same array when nothing is outside."""
    lo, hi = range_bounds(min_disp, ndisp)
    if disparity.size == 0:
        return disparity
    finite = disparity != np.inf  # +inf is the only non-finite value a map holds
    if disparity.min() >= lo and np.max(disparity, where=finite, initial=lo) <= hi:
        return disparity
    return np.where(finite, np.clip(disparity, lo, hi), disparity).astype(np.float32)
