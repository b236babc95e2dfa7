"""Refinement stages: sub-pixel, consistency checks, filters, hole filling.

Stages registered with ``needs_cost=True`` run inside each row strip while the optimizer's
cost volume is available; the others run on the full stitched disparity map, in list order.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..errors import ConfigError
from ..registry import StageTraits, param, register
from .cost import colour_switch, left_guide
from .kernels import maps as km
from .kernels import refine as kr
from .kernels.winners import subpixel_left, subpixel_right
from .state import MatchState, WinnerCosts, required


def _disparity(state: MatchState, stage: str) -> np.ndarray:
    """``state.disparity``, which the optimizer sets before any refinement runs."""
    return required(state.disparity, f"refinement.{stage}: no disparity map (the optimizer sets it)")


def _winner(state: MatchState, stage: str) -> WinnerCosts:
    """``state.winner``, which the pipeline sets before it runs an ``on_winner_costs`` variant."""
    return required(state.winner, f"refinement.{stage}: no winner costs (a fused cost + WTA pass sets them)")


def _cost(state: MatchState, stage: str) -> np.ndarray:
    """``state.cost``, which a ``needs_cost`` refinement runs beside."""
    return required(state.cost, f"refinement.{stage}: no cost volume")


@dataclass(frozen=True)
class SubpixelParams:
    method: str = param("parabola", "curve fitted through the costs at d-1, d, d+1",
                        choices=("parabola", "equiangular"))
    right: bool = param(True, "also refine the right-view disparity (the --right output and what lr_check then "
                        "compares with); false keeps its integer winners")


def _subpixel_on_winner_costs(state: MatchState, p: SubpixelParams) -> None:
    """the same fit on the costs kept around each winner (right view too, when kept)"""
    from .optimize.wta import subpixel_on_winner

    equi = p.method == "equiangular"
    winner = _winner(state, "subpixel")
    state.disparity = subpixel_on_winner(winner, _disparity(state, "subpixel"), state.min_disp, state.ndisp, equi)
    if p.right and state.disparity_right is not None and winner.costs_right is not None:
        state.disparity_right = subpixel_on_winner(winner, state.disparity_right, state.min_disp, state.ndisp,
                                                   equi, right=True)


def _refines_right_view(state: MatchState, p: SubpixelParams) -> bool:
    """when right: true (the right view's costs around its winners)"""
    return p.right


@register("refinement", "subpixel", SubpixelParams,
          traits=StageTraits(needs_cost=True, on_winner_costs=_subpixel_on_winner_costs,
                             needs_right_costs=_refines_right_view, reads_left_colour=False,
                             reads_right_colour=False))
def subpixel(state: MatchState, p: SubpixelParams) -> None:
    """Sub-pixel disparity from the costs around the winner (left view; right view too if kept).

    Parabola suits smooth (squared-like) costs such as SGM sums; equiangular (a symmetric V)
    suits absolute-difference-like costs and has less bias towards integers on them. With
    ``right: false`` the right view keeps its integer winners: ``lr_check`` then compares the
    sub-pixel left map with them, which on MiddEval3 and Middlebury 2001/2003 scores as well as
    comparing two sub-pixel maps (docs/benchmarks.md), and the windowed SGM skips keeping the right view's
    neighbouring sums.
    """
    equi = p.method == "equiangular"
    cost = _cost(state, "subpixel")
    state.disparity = subpixel_left(cost, _disparity(state, "subpixel"), state.min_disp, equi)
    if state.disparity_right is not None and p.right:
        state.disparity_right = subpixel_right(cost, state.disparity_right, state.min_disp, equi)


@dataclass(frozen=True)
class LRCheckParams:
    max_diff: float = param(1.0, "largest accepted |d_left - d_right| at corresponding pixels",
                            unit="px", low=0.0, high=100.0)
    compare: str = param("final", "which maps are checked: 'final' = the maps as refined so far (after subpixel); "
                         "'integer' = the optimizer's integer winners, before any sub-pixel step (Hosni et al. 2013), "
                         "the rejected pixels being removed from the current map", choices=("final", "integer"))


def _compares_integer(p: LRCheckParams) -> bool:
    """when compare: integer"""
    return p.compare == "integer"


@register("refinement", "lr_check", LRCheckParams,
          traits=StageTraits(needs_right=True, keeps_integer=_compares_integer, reads_left_colour=False,
                             reads_right_colour=False, map_copies=1.5))
def lr_check(state: MatchState, p: LRCheckParams) -> None:
    """Left-right consistency check: invalidate pixels the right view's disparity contradicts.

    Removes occlusions and most mismatches; the right disparity comes from the same volume
    (Hirschmüller 2008, §2.5), so it costs one extra pass, not a second match.

    ``compare: final`` checks the maps as they are when the stage runs, i.e. after ``subpixel``
    (volume refinements run before map stages). ``compare: integer`` decides on the optimizer's
    integer winners instead, as the cost-volume filtering papers do (Rhemann et al. 2011,
    Hosni et al. 2013: WTA, check, then fill) and removes the rejected pixels from the current
    (sub-pixel) map. Each sub-pixel fit moves a winner by up to 0.5 px, so after both fits
    winners 2 px apart can come within 1 px of each other and pass a 1 px check; on integers
    the test counts whole winners. The pipeline keeps the integer maps for it (two (H, W)
    float32 copies). Called outside the pipeline without kept maps, it compares the current ones.
    """
    left, right = state.integer_disparity, state.integer_disparity_right
    if p.compare == "integer" and left is not None and right is not None:
        state.disparity = km.lr_check_onto(left, right, float(p.max_diff), _disparity(state, "lr_check"))
        return
    disparity_right = required(state.disparity_right, "refinement.lr_check: no right-view disparity map "
                                                      "(the pipeline makes it for a stage that needs_right)")
    state.disparity = km.lr_check(_disparity(state, "lr_check"), disparity_right, float(p.max_diff))


@dataclass(frozen=True)
class MedianParams:
    size: int = param(3, "window side (odd)", unit="px", low=3, high=15)


@register("refinement", "median", MedianParams,
          traits=StageTraits(reads_left_colour=False, reads_right_colour=False, map_copies=2.5))
def median(state: MatchState, p: MedianParams) -> None:
    """Median filter over valid disparities only (holes neither spread nor get filled)."""
    if p.size % 2 == 0:
        raise ConfigError(f"refinement.median.size: {p.size} must be odd")
    state.disparity = kr.median_valid(_disparity(state, "median"), p.size // 2)


@register("refinement", "fill",
          traits=StageTraits(fills_holes=True, reads_left_colour=False, reads_right_colour=False, map_copies=1.5))
def fill(state: MatchState, params) -> None:
    """Fill invalid pixels along scanlines with the background (smaller) neighbouring disparity.

    Makes the output dense (the Middlebury v2 tables score dense maps). ``match --keep-invalid``
    skips this stage.
    """
    state.disparity = km.fill_background(_disparity(state, "fill"))


@dataclass(frozen=True)
class UniquenessParams:
    ratio: float = param(0.05, "reject when a non-adjacent hypothesis costs less than best / (1 - ratio) "
                         "(OpenCV uniquenessRatio / 100)", low=0.0, high=0.9)


def _uniqueness_on_winner_costs(state: MatchState, p: UniquenessParams) -> None:
    """the best cost beyond ±1 of the winner among the hypotheses searched (windowed SGM)"""
    w = _winner(state, "uniqueness")
    state.disparity = kr.uniqueness_from_second(w.costs[..., 1], w.second, state.disparity, float(p.ratio))


def _always(state: MatchState, params) -> bool:
    """always"""
    return True


@register("refinement", "uniqueness", UniquenessParams,
          traits=StageTraits(needs_cost=True, on_winner_costs=_uniqueness_on_winner_costs,
                             needs_second_best=_always))
def uniqueness(state: MatchState, p: UniquenessParams) -> None:
    """Invalidate ambiguous pixels: the winner must beat every hypothesis more than 1 px away
    by the margin ``ratio`` (OpenCV's uniqueness check, on the optimised costs)."""
    state.disparity = kr.uniqueness(state.cost, state.disparity, state.min_disp, float(p.ratio))


@dataclass(frozen=True)
class ConfidenceParams:
    lr_scale: float = param(1.0, "left-right disagreement at which the LR factor falls to 1/e",
                            unit="px", low=0.01, high=100.0)
    margin_scale: float = param(0.1, "cost margin 1 - best/second at which the uniqueness factor reaches 1",
                                low=0.001, high=1.0)


def _confidence_on_winner_costs(state: MatchState, p: ConfidenceParams) -> None:
    """uniqueness from the best cost beyond ±1 of the winner among the hypotheses searched
    (windowed SGM), the LR term as on the volume"""
    if not state.wants.confidence:
        return
    w = _winner(state, "confidence")
    right = state.disparity_right if state.disparity_right is not None else np.zeros((0, 0), np.float32)
    state.confidence = kr.confidence_from_second(w.costs[..., 1], w.second, state.disparity, right,
                                                 float(p.lr_scale), float(p.margin_scale))


def _confidence_wanted(state: MatchState, params) -> bool:
    """when a confidence map is wanted (match --confidence)"""
    return state.wants.confidence


@register("refinement", "confidence", ConfidenceParams,
          traits=StageTraits(needs_cost=True, on_winner_costs=_confidence_on_winner_costs,
                             needs_second_best=_confidence_wanted, reads_left_colour=False,
                             reads_right_colour=False, produces_confidence=True))
def confidence(state: MatchState, p: ConfidenceParams) -> None:
    """Per-pixel confidence in [0, 1] (``match --confidence``): cost uniqueness × LR agreement.

    ``min(1, (1 − c_best/c_second)/margin_scale) · exp(−|d_L − d_R|/lr_scale)``, 0 where invalid;
    c_second is the best hypothesis more than 1 px from the winner. Uses the right-view map when
    one exists (e.g. ``lr_check`` in the list); place it after ``subpixel``.
    """
    if not state.wants.confidence:
        return  # nobody asked for the map (match --confidence / match_pair(want_confidence=True))
    right = state.disparity_right if state.disparity_right is not None else np.zeros((0, 0), np.float32)
    state.confidence = kr.confidence(state.cost, state.disparity, right, state.min_disp,
                                     float(p.lr_scale), float(p.margin_scale))



@dataclass(frozen=True)
class SpeckleParams:
    max_size: int = param(100, "largest connected region (px) removed as a speckle", unit="px", low=0, high=100000)
    max_diff: float = param(1.0, "neighbours differing by at most this belong to the same region",
                            unit="px", low=0.0, high=100.0)


@register("refinement", "speckle", SpeckleParams, traits=StageTraits(map_copies=6))
def speckle(state: MatchState, p: SpeckleParams) -> None:
    """Remove small connected regions of similar disparity (isolated mismatches).

    Connected components with 4-neighbours differing by ≤ ``max_diff``; regions of at most
    ``max_size`` pixels become invalid (OpenCV ``filterSpeckles`` on a ×16 int16 copy, so
    disparities must lie in (−2048, 2048)).
    """
    import cv2

    d = _disparity(state, "speckle")
    finite = np.isfinite(d)
    marker = np.int16(-32768)
    fixed = np.where(finite, np.round(np.clip(np.where(finite, d, 0), -2047, 2047) * 16), marker).astype(np.int16)
    cv2.filterSpeckles(fixed, int(marker), int(p.max_size), int(round(p.max_diff * 16)))
    state.disparity = np.where(fixed == marker, np.float32(np.inf), d).astype(np.float32)


@dataclass(frozen=True)
class InterpolateParams:
    max_dist: int = param(0, "search at most this far for valid neighbours (0 = unlimited)",
                          unit="px", low=0, high=100000)
    tol: float = param(1.0, "a hole is a mismatch when a right pixel maps back to it within tol",
                       unit="px", low=0.0, high=10.0)


@register("refinement", "interpolate", InterpolateParams,
          traits=StageTraits(needs_right=True, fills_holes=True, map_copies=18))
def interpolate(state: MatchState, p: InterpolateParams) -> None:
    """Classify holes as occluded or mismatched and fill them (Hirschmüller 2008 §2.5).

    A hole is mismatched when some right-view pixel maps onto it, occluded otherwise.
    Occlusions take the background: the second-lowest of the nearest valid values in 8
    directions; mismatches take their median. ``match --keep-invalid`` skips this stage.

    No bundled preset runs it: in ``quality`` it gained on the tuning scenes (MiddEval3 ArtL)
    but not on the validation scenes, so ``quality`` fills its holes with ``fill``.
    """
    state.disparity = kr.interpolate_holes(_disparity(state, "interpolate"), hole_labels(state, p.tol),
                                           int(p.max_dist))


def hole_labels(state: MatchState, tol: float) -> np.ndarray:
    """(H, W) uint8 labels of the holes of ``state.disparity``: 0 valid, 1 occluded, 2 mismatched
    (some right-view pixel maps onto it within ``tol`` px); Hirschmüller 2008 §2.5."""
    right = state.disparity_right if state.disparity_right is not None else np.zeros((0, 0), np.float32)
    return kr.classify_holes(np.ascontiguousarray(state.disparity, dtype=np.float32),
                             np.ascontiguousarray(right, dtype=np.float32), state.min_disp,
                             state.min_disp + state.ndisp - 1, float(tol))


@dataclass(frozen=True)
class BilateralParams:
    radius: int = param(3, "window half size", unit="px", low=1, high=20)
    sigma_space: float = param(3.0, "spatial Gaussian sigma", unit="px", low=0.1, high=50.0)
    sigma_color: float = param(10.0, "intensity Gaussian sigma on the left grey image",
                               unit="grey levels", low=0.1, high=255.0)


@register("refinement", "bilateral", BilateralParams)
def bilateral(state: MatchState, p: BilateralParams) -> None:
    """Joint bilateral filter of the valid disparities guided by the left image (smooths
    surfaces, keeps depth edges that coincide with intensity edges)."""
    state.disparity = kr.joint_bilateral(state.disparity, np.ascontiguousarray(state.gray("left")), int(p.radius),
                                         float(p.sigma_space), float(p.sigma_color))


@dataclass(frozen=True)
class PlaneSmoothParams:
    radius: int = param(10, "half length of the row and column segments fitted", unit="px", low=1, high=50)
    sigma_space: float = param(10.0, "spatial Gaussian sigma along the segment", unit="px", low=0.1, high=100.0)
    color_range: float = param(20.0, "colour distance (Euclidean, over the channels) beyond which a neighbour gets no "
                               "weight", unit="grey levels", low=0.1, high=500.0)
    gate: float = param(1.0, "neighbours whose disparity differs from the centre's by more than this are left out",
                        unit="px", low=0.0, high=100.0)
    color: bool = param(True, "colour distance on the colour image; false: on the grey image (about a third of the "
                        "distance work, same scores on MiddEval3)")
    step: int = param(1, "fit through every step-th neighbour of the segment (2: half the work)", low=1, high=10)


@register("refinement", "plane_smooth", PlaneSmoothParams,
          traits=StageTraits(reads_left_colour=colour_switch, reads_right_colour=False, map_copies=2.5))
def plane_smooth(state: MatchState, p: PlaneSmoothParams) -> None:
    """Edge-aware sub-pixel smoothing by local line fits along rows, then columns.

    Every valid pixel takes the value, at its own position, of a weighted least-squares line
    through the neighbours on its row (then its column) within ``radius`` px whose disparity is
    within ``gate`` px of its own; weights fall off with distance and with colour difference in
    the left image. It removes the stair-casing that cost-curve sub-pixel fits leave on slanted
    surfaces (pixel locking) and the ±0.3 px noise on flat ones, without averaging across
    depth edges (the gate) or colour edges (the colour weight). Needs no cost volume, so it can
    run last, on the dense map. Costs 2·(2·⌊radius / step⌋ + 1) neighbour visits per pixel.
    """
    state.disparity = kr.plane_smooth(_disparity(state, "plane_smooth"), left_guide(state, p.color), int(p.radius),
                                      float(p.sigma_space), float(p.color_range), float(p.gate), int(p.step))


def clear_invalid_left(state: MatchState) -> None:
    """Mark pixels outside the left valid mask invalid (used by the pipeline)."""
    if state.left_valid is not None and state.disparity is not None:
        state.disparity = np.where(state.left_valid, state.disparity, np.float32(np.inf)).astype(np.float32)
