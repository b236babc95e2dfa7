"""The data every matching stage reads and writes.

Stage contract (see :mod:`stereocli.registry`): ``func(state: MatchState, params) -> None``
mutates ``state``:

* preprocess: replaces ``left``/``right`` (same shape, float32); a stage that resamples the
  right view's rows records how in ``right_rows``.
* cost: sets ``cost`` to a ``(H, W, D)`` C-contiguous float32 volume, ``D = ndisp``,
  (or uint8/uint16 holding integer costs, if ``wants.integer_cost``: the pipeline sets it when
  the volume goes straight to an optimizer whose traits say ``accepts_integer_cost``, e.g. ``sgm``),
  ``cost[y, x, k]`` = dissimilarity of left ``(x, y)`` and right ``(x - (min_disp + k), y)``,
  lower is better; entries whose right pixel falls outside the image (or outside a valid
  mask) hold the volume's maximum cost ``cost_max``.
* aggregation: replaces ``cost`` with an aggregated volume of the same layout.
* optimizer: sets ``disparity`` (float32, integer-valued, +inf invalid) and leaves in ``cost``
  the volume its decision was taken on (so sub-pixel refinement, uniqueness and the
  right-view disparity use the optimised costs); it may set ``disparity_right`` itself.
  That volume may be **uint16** instead of float32 (``sgm`` leaves its path-cost sums, with
  ``cost_max`` = 65535): every kernel that reads ``cost`` after the optimizer (sub-pixel,
  WTA, uniqueness, confidence, ``mask_invalid_right``) accepts float32 and uint16.
* refinement: edits ``disparity`` (and ``disparity_right`` / ``confidence``); stages whose
  traits say ``needs_cost`` run while ``cost`` is still available (inside each row strip),
  the others on the full stitched map. When some refinement wants the optimizer's own
  integer winners (``wants.integer_maps``, e.g. ``lr_check`` with ``compare: integer``), the
  pipeline copies ``disparity`` / ``disparity_right`` into ``integer_disparity`` /
  ``integer_disparity_right`` right after the optimizer (and the right view), before any
  volume refinement moves them, and stitches them like the maps. Before a map refinement
  whose traits say ``needs_mirrored``, the pipeline runs the stages before it on the mirrored
  pair (both images flipped left-right and swapped) and sets ``mirrored_disparity``: that map
  flipped back, referenced to the right image.

What a stage reads about a stage is in its :class:`~stereocli.registry.StageTraits`; what the
rest of the pipeline asks of a stage is in :attr:`MatchState.wants` (:class:`Wants`), set by
the pipeline from the config and the requested outputs.

Fused cost + WTA (see :mod:`stereocli.matching.pipeline`): when a cost stage offers a
``fused_wta`` trait, the pipeline is ``cost → wta`` with no aggregation, no right-view
disparity is wanted and every ``needs_cost`` refinement offers an ``on_winner_costs``
variant, the volume is never built: ``fused_wta`` sets ``disparity`` (exactly what cost +
``wta`` would give, honouring ``right_valid``) and, if asked, ``winner`` (:class:`WinnerCosts`,
the volume entries around each winner); ``cost`` stays None, and the refinements run their
``on_winner_costs`` variants, which must give the same result as on the volume.

When the image is processed in row strips, ``row_offset`` is the strip's first row in the full
image.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import TYPE_CHECKING, TypeVar

import numpy as np

from .kernels.images import luma

if TYPE_CHECKING:
    from .vertical_offset import VerticalOffset

_T = TypeVar("_T")


@dataclass
class WinnerCosts:
    """What a fused cost + WTA pass (or a windowed SGM) keeps of the volume it never stores."""

    disparity: np.ndarray  # (H, W) float32 WTA disparities min_disp + k (integer-valued, +inf invalid)
    costs: np.ndarray  # (H, W, 3) float32 volume entries at k - 1, k, k + 1 (cost_max beyond [0, D))
    costs_right: np.ndarray | None = None  # (H, W, 3) the same for the right-view winners (diagonal neighbours)
    disparity_right: np.ndarray | None = None  # (H, W) float32 right-view winners the costs belong to
    second: np.ndarray | None = None  # (H, W) float32 best cost more than 1 hypothesis from the winner (+inf if none)


@dataclass
class Wants:
    """What later stages and the requested outputs need from the stages that run earlier."""

    right: bool = False  # the right-view disparity (an output, or a stage with needs_right)
    confidence: bool = False  # a confidence map (else the confidence stages skip)
    integer_maps: bool = False  # the optimizer's integer maps, kept in ``integer_disparity[_right]``
    integer_cost: bool = False  # the cost stage may leave a uint8/uint16 volume
    volume: bool = True  # a later stage reads ``cost`` itself (else ``winner`` may stand in for it)
    second_best: bool = False  # a later stage reads ``winner.second`` (uniqueness, confidence)
    right_costs: bool = False  # a later stage reads ``winner.costs_right`` (sub-pixel of the right view)


@dataclass
class MatchState:
    """Images, disparity range and the products of the stages run so far."""

    left: np.ndarray  # (H, W) or (H, W, 3) float32 in [0, 255]; (H, W) grey when no stage reads its colour
    right: np.ndarray  # likewise (a colour pair can have one view grey and the other not)
    min_disp: int  # smallest disparity searched, px (may be negative)
    ndisp: int  # number of disparities searched: [min_disp, min_disp + ndisp)
    left_valid: np.ndarray | None = None  # (H, W) bool, False on rectification borders
    right_valid: np.ndarray | None = None  # (H, W) bool
    cost: np.ndarray | None = None  # (H, W, D) float32 (uint16 after sgm), lower is better
    cost_max: float = 0.0  # value held by impossible entries of ``cost``
    winner: WinnerCosts | None = None  # set instead of ``cost`` by a fused cost + WTA pass
    disparity: np.ndarray | None = None  # (H, W) float32 px, +inf invalid
    disparity_right: np.ndarray | None = None  # (H, W) float32 px, right-referenced, +inf invalid
    confidence: np.ndarray | None = None  # (H, W) float32 in [0, 1]
    # (H, W) float32: ``disparity`` as the optimizer left it (if keep_integer)
    integer_disparity: np.ndarray | None = None
    integer_disparity_right: np.ndarray | None = None  # (H, W) float32: the same for ``disparity_right``
    mirrored_disparity: np.ndarray | None = None  # (H, W) float32 px, right-referenced: for a ``needs_mirrored`` stage
    wants: Wants = field(default_factory=Wants)  # what later stages and outputs need
    row_offset: int = 0  # first image row of this (strip) state
    # Rows of the whole image a strip state is cut from (0: the state is the whole image). A
    # search decides its levels from the whole image's size, so every strip searches alike.
    image_rows: int = 0
    notes: dict = field(default_factory=dict)  # stage name -> JSON-ready facts for the match record
    # Set by a stage that resampled the right view's rows (``row_align``): the
    # :class:`~stereocli.matching.vertical_offset.VerticalOffset` it moved them by. The pipeline
    # moves right-referenced maps between ``right``'s rows and the input's with it.
    right_rows: VerticalOffset | None = None
    gray_cache: dict = field(default_factory=dict, repr=False)  # which -> (image, its grey), see gray()

    @property
    def shape(self) -> tuple[int, int]:
        return self.left.shape[:2]

    @property
    def image_shape(self) -> tuple[int, int]:
        """``(H, W)`` of the whole image this state is (a strip of)."""
        h, w = self.shape
        return (self.image_rows or h, w)

    def gray(self, which: str = "left") -> np.ndarray:
        """The left or right image as (H, W) float32 grey (luma of RGB); computed once per image
        object (stages that replace ``left``/``right`` get a fresh one). Do not modify it."""
        img = self.left if which == "left" else self.right
        if img.ndim == 2:
            return img
        cache = self.gray_cache
        hit = cache.get(which)
        if hit is not None and hit[0] is img:
            return hit[1]
        grey = luma(np.ascontiguousarray(img, dtype=np.float32))
        cache[which] = (img, grey)
        return grey


def required(value: _T | None, error: str) -> _T:
    """``value``, a part of the state that the stage contract sets before the calling stage runs
    (e.g. ``disparity`` for a refinement); raises ``RuntimeError(error)`` when it is None, which
    only a stage called out of order (outside the pipeline) meets."""
    if value is None:
        raise RuntimeError(error)
    return value
