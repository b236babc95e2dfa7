"""Fusion of the left map with the same pipeline's map of the mirrored pair (``mirror_fusion``)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..registry import StageTraits, param, register
from .kernels import maps as km
from .state import MatchState, required


@dataclass(frozen=True)
class MirrorFusionParams:
    tolerance: float = param(1.0, "the two maps are averaged where they differ by less than this", unit="px",
                             low=0.0, high=1000.0)
    reassign_above: float = param(0.0, "a pixel whose disparity the mirrored map contradicts by more than this takes "
                                  "a neighbour's disparity the mirrored map confirms (0: never)", unit="px",
                                  low=0.0, high=1000.0)
    reassign_radius: int = param(2, "neighbours offering their disparity lie up to this far along the row and the "
                                 "column", unit="px", low=1, high=20)
    reassign_within: float = param(1.0, "a neighbour's disparity c is confirmed where the mirrored map, read at "
                                   "x − c, is within this of c", unit="px", low=0.0, high=1000.0)


def sample_right_map(disparity: np.ndarray, right_map: np.ndarray) -> np.ndarray:
    """``right_map`` read where each left pixel lands: at column ``x − d`` of its row, linearly
    interpolated between the two nearest columns.

    ``disparity`` (H, W) float32 px, left-referenced; ``right_map`` (H, W) float32 px,
    referenced to the right image. Returns (H, W) float32; +inf where ``d`` is invalid, ``x − d``
    falls outside ``[0, W − 1]`` or a column it reads (at a weight above 0) is invalid."""
    h, w = disparity.shape
    finite = np.isfinite(disparity)
    x_right = np.arange(w, dtype=np.float32)[None, :] - np.where(finite, disparity, np.float32(0))
    inside = finite & (x_right >= 0) & (x_right <= w - 1)
    if w < 2:
        return np.where(inside, right_map, np.float32(np.inf)).astype(np.float32)
    # The left column of the two read; at x − d = W − 1 exactly, the pair (W − 2, W − 1) at weight 1.
    column = np.clip(np.floor(x_right), 0, w - 2).astype(np.intp)
    weight = (x_right - column).astype(np.float32)
    rows = np.arange(h)[:, None]
    before, after = right_map[rows, column], right_map[rows, column + 1]
    # A column read at weight 0 may be invalid: an integer x − d needs only its own column.
    before_valid, after_valid = np.isfinite(before), np.isfinite(after)
    usable = inside & (before_valid | (weight == 1)) & (after_valid | (weight == 0))
    before = np.where(before_valid, before, np.float32(0))
    after = np.where(after_valid, after, np.float32(0))
    sampled = np.where(usable, before + weight * (after - before), np.inf)
    return sampled.astype(np.float32)


def fuse_with_mirrored(disparity: np.ndarray, right_map: np.ndarray, tolerance: float) -> np.ndarray:
    """(H, W) float32: the mean of each left pixel's disparity and ``right_map`` at the pixel it
    matches (:func:`sample_right_map`) where the two differ by less than ``tolerance`` px; the
    left disparity elsewhere (invalid pixels stay invalid). One compiled pass over the rows
    (:func:`~stereocli.matching.kernels.maps.fuse_mirrored`), without numpy's temporaries."""
    return km.fuse_mirrored(np.ascontiguousarray(disparity, dtype=np.float32),
                            np.ascontiguousarray(right_map, dtype=np.float32), tolerance)


def reassign_contradicted(disparity: np.ndarray, right_map: np.ndarray, above: float, radius: int,
                          within: float) -> np.ndarray:
    """(H, W) float32: each pixel whose disparity ``d`` the right-referenced ``right_map``, read at
    ``x − d`` (:func:`sample_right_map`), contradicts by more than ``above`` px takes the
    disparity ``c`` of a neighbour up to ``radius`` px away along its row or column for which
    ``right_map`` read at ``x − c`` is within ``within`` px of ``c`` (the best confirmed; the
    nearest on a tie, along the row first, the right or lower side first); every other pixel
    keeps its value. All pixels decide on the input map. One compiled pass over the rows
    (:func:`~stereocli.matching.kernels.maps.reassign_contradicted`)."""
    return km.reassign_contradicted(np.ascontiguousarray(disparity, dtype=np.float32),
                                    np.ascontiguousarray(right_map, dtype=np.float32), above, radius, within)


@register("refinement", "mirror_fusion", MirrorFusionParams, traits=StageTraits(needs_mirrored=True))
def mirror_fusion(state: MatchState, p: MirrorFusionParams) -> None:
    """Average the map with the mirrored pair's map where they agree; optionally reassign what it contradicts.

    The pipeline first runs every stage before this one on the mirrored pair (both images
    flipped left-right and swapped, so the right view is matched as a left view) and flips the
    result back: a map referenced to the right image whose census windows, SGM paths and
    occlusions lie on the other side. Each left pixel reads it where it matches (``x − d``,
    linear interpolation) and, where the two differ by less than ``tolerance`` px, takes their
    mean: two largely independent estimates of the same surface point, so the sub-pixel error
    shrinks. Elsewhere (occlusions, the two maps disagreeing) the pixel keeps its value. The
    mirrored run costs as much as the stages before this one; place it on a dense map (after
    the fill), before the stages that only polish the map, which then need not run twice.

    With ``reassign_above`` > 0, a pixel that the mirrored map then contradicts by more than that
    (a gross error in one of the two maps) takes the disparity of a neighbour within
    ``reassign_radius`` px along its row or column that the mirrored map confirms within
    ``reassign_within`` px, the best confirmed one. The two maps' gross errors lie largely in
    different places, so where a pixel's own disparity is contradicted and its neighbour's is
    confirmed, the neighbour's is the likelier one; where no neighbour's is confirmed (e.g. in
    an occlusion, which has no match to confirm anything) the pixel keeps its value.
    """
    if state.mirrored_disparity is None:
        raise RuntimeError("mirror_fusion: the pipeline did not provide the mirrored pair's map")
    fused = fuse_with_mirrored(required(state.disparity, "mirror_fusion: no disparity map"), state.mirrored_disparity,
                               float(p.tolerance))
    if p.reassign_above > 0:
        fused = reassign_contradicted(fused, state.mirrored_disparity, float(p.reassign_above),
                                      int(p.reassign_radius), float(p.reassign_within))
    state.disparity = fused
