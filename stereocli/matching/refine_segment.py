"""Segmentation-based refinement stages: locally consistent voting and per-segment planes.

Both edit the full disparity map (they do not read the cost volume), so they run after the
row strips are stitched. Put them after ``lr_check`` (so unreliable pixels are +inf) and
before ``fill``.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from ..errors import ConfigError
from ..registry import StageTraits, param, register
from .cost import _channels, colour_switch
from .kernels import geodesic_vote as kg
from .kernels import local_consistency as klc
from .kernels import maps as km
from .kernels import segment_planes as ksp
from .state import MatchState


@dataclass(frozen=True)
class LocalConsistencyParams:
    radius: int = param(9, "half side of the voting window (half length of the segments with separable)",
                        unit="px", low=1, high=50)
    gamma_s: float = param(9.0, "γs: spatial falloff of a neighbour's vote", unit="px", low=0.1, high=1000.0)
    gamma_c: float = param(12.0, "γc: colour falloff in the left image", unit="grey levels", low=0.1, high=1000.0)
    gamma_t: float = param(12.0, "γt: colour falloff between the matched points in the right image",
                           unit="grey levels", low=0.1, high=1000.0)
    fill_invalid: bool = param(False, "also give invalid (+inf) pixels the winning vote")
    min_spread: float = param(0.0, "vote only at pixels whose window spans more than this many px of "
                              "disparity (max − min over valid pixels); 0 = every pixel",
                              unit="px", low=0.0, high=1000.0)
    band: int = param(0, "half side of the window min_spread is measured in; with separable and min_change, how "
                      "far along the line a step must be for a pixel to be voted on (0 = radius)",
                      unit="px", low=0, high=50)
    min_change: int = param(0, "take the winning 1-px bin only when it is at least this many bins from the "
                            "pixel's own (0 = always take the winning bin's mean; 2 keeps sub-pixel values "
                            "and moves only misplaced edges)", low=0, high=1000)
    separable: bool = param(False, "vote along the row segment, then along the column segment "
                            "(2·(2·radius + 1) votes per pixel instead of (2·radius + 1)²)")
    color: bool = param(True, "colour terms on the colour images; false: on the grey images")
    right: bool = param(True, "the right-image term (γt); false: distance and left-image colour only, "
                        "about a third less work per vote with separable")

    def __post_init__(self):
        if self.separable and self.fill_invalid:
            raise ConfigError("refinement.local_consistency: fill_invalid needs the square window "
                              "(separable: false): a hole has no bin of its own to compare along a line")


@register("refinement", "local_consistency", LocalConsistencyParams,
          traits=StageTraits(map_copies=10, produces_confidence=True))
def local_consistency(state: MatchState, p: LocalConsistencyParams) -> None:
    """Locally consistent refinement (Mattoccia 2009): neighbours vote for disparity hypotheses.

    Each valid neighbour within ``radius`` votes for its disparity, weighted by proximity, by
    colour similarity in the left image and by colour similarity of the two points the
    hypothesis maps to in the right image; each pixel takes the best-supported hypothesis
    (weighted mean within the winning 1-px bin). Removes isolated errors and aligns
    disparity edges with colour edges; O(radius²) per pixel. ``min_spread`` restricts the
    vote to pixels whose window (half side ``band``, or ``radius``) straddles a depth
    discontinuity, where foreground fattening and mismatches sit; the others keep their
    disparity. ``min_change`` 2 moves only pixels whose winning bin is 2 or more bins away
    (misplaced edges), so sub-pixel values on slanted surfaces are kept. ``separable`` votes
    along rows, then along columns of the result: O(radius) per pixel instead of O(radius²),
    and with ``min_change`` only at pixels within ``band`` px (along the line) of a step of at
    least ``min_change`` bins (as the ``quality`` preset does). Sets ``confidence`` to the winner's
    share of the votes (1 where no vote was taken; with separable, the product of the two
    passes' shares), or multiplies an existing map (e.g. the ``confidence`` stage's) by it.
    """
    disp = np.ascontiguousarray(state.disparity, dtype=np.float32)
    left = _channels(state.left if p.color else state.gray("left"))
    right = _channels(state.right if p.color else state.gray("right"))
    if p.separable:
        left_packed = klc.packed_quarter_levels(left)
        right_packed = klc.packed_quarter_levels(right) if p.right else np.zeros((0, 0), np.int64)
        tables = _vote_tables(left.shape[2], p)
        # An empty todo stands for every pixel (no min_spread window to measure).
        todo = (_discontinuity_windows(disp, p.band or p.radius, p.min_spread, False) if p.min_spread > 0
                else np.zeros((0, 0), np.bool_))
        shares = []
        for vertical in (False, True):
            bins = km.disparity_bins(disp, state.min_disp, state.ndisp)
            centres = np.flatnonzero(klc.line_centre_mask(bins, todo, p.band or p.radius, int(p.min_change), vertical))
            disp, share = klc.local_consistency_line(disp, bins, centres, left_packed, right_packed, state.min_disp,
                                                    state.ndisp, p.radius, *tables, int(p.min_change), vertical,
                                                    bool(p.right))
            shares.append(share)
        conf = shares[0] * shares[1]
        conf[~np.isfinite(disp)] = 0.0
    else:
        # Without the right-image term every match weight is exp(−Δ/∞) = 1 exactly.
        gamma_t = float(p.gamma_t) if p.right else np.inf
        todo = _discontinuity_windows(disp, p.band or p.radius, p.min_spread, p.fill_invalid)
        disp, conf = klc.local_consistency(
            disp, left, right, state.min_disp, state.ndisp, p.radius, float(p.gamma_s), float(p.gamma_c),
            gamma_t, bool(p.fill_invalid), todo, int(p.min_change),
        )
    state.disparity = disp
    state.confidence = conf if state.confidence is None else state.confidence * conf


@dataclass(frozen=True)
class GeodesicVoteParams:
    gamma_s: float = param(100.0, "distance falloff: each step along the line passes exp(−1/γs) of the support",
                           unit="px", low=0.1, high=1e6)
    gamma_c: float = param(25.0, "colour falloff between neighbouring pixels (mean channel difference)",
                           unit="grey levels", low=0.1, high=1000.0)
    band: int = param(3, "vote only at pixels within this distance (along the line) of a step of at least min_change "
                      "bins", unit="px", low=1, high=50)
    min_change: int = param(2, "take the winning 1-px bin only when it is at least this many bins from the pixel's own "
                            "(2 keeps sub-pixel values and moves only misplaced edges)", low=1, high=1000)
    max_bins: int = param(3, "bins each running vote keeps (the strongest; a new bin replaces the weakest)",
                          low=1, high=16)
    min_lead: float = param(1.0, "move a pixel only when the winning bin's support is at least this many times its own "
                            "bin's (1: whenever another bin wins)", low=1.0, high=100.0)
    lines: str = param("both", "the passes: rows, then columns of the result (both), or one of them (two stages, one "
                       "per pass, can differ in settings)", choices=("both", "rows", "columns"))
    color: bool = param(True, "colour differences on the colour image; false: on the grey image")


@register("refinement", "geodesic_vote", GeodesicVoteParams,
          traits=StageTraits(reads_left_colour=colour_switch, reads_right_colour=False, map_copies=6))
def geodesic_vote(state: MatchState, p: GeodesicVoteParams) -> None:
    """Put depth edges back on colour edges: pixels beside a disparity step take the disparity
    their colour-connected neighbours along the row, then the column, support most.

    Each valid pixel votes for its 1-px bin; the vote reaches another pixel of the same row
    (column) weakened by ``exp(−1/γs − ΔC/γc)`` for every neighbour pair in between (ΔC: the
    pair's mean channel difference), so support flows through a surface's own colours and
    dies at colour edges — foreground disparities that spilled over a colour edge (the census
    window's fattening) are outvoted by the background they now sit in. Two running votes per
    line (one from each end) make it O(1) per pixel whatever the reach, like Yang's recursive
    bilateral filter. Only pixels within ``band`` px along the line of a step of
    ``min_change`` bins or more are decided, and they only move to a bin at least
    ``min_change`` away (the winning bin's weighted mean disparity), so sub-pixel values on
    slanted surfaces stay. Place it on the dense map, after the median and before
    ``plane_smooth`` (which refits the slopes of the pixels it moved), as the ``accurate``
    preset does. Invalid pixels neither vote nor move.

    ``min_lead`` above 1 moves a pixel only when the winning bin outweighs its own bin that
    many times: a thin structure (a stem, a leaf) has support of its own nearly as strong as
    the surface around it and stays, while a fattened edge, whose own bin reaches it only
    through the colour edge it spilled over, still moves. The ``quality`` preset votes along
    rows with a lead of 1.5 and then along columns with 2.5, as two stages.
    """
    disp = np.ascontiguousarray(state.disparity, dtype=np.float32)
    left = _channels(state.left if p.color else state.gray("left"))
    packed = klc.packed_quarter_levels(left)
    # Weight passed between neighbours (distance and colour), by their colour difference.
    passed = np.exp(-1.0 / p.gamma_s - _colour_steps(left.shape[2]) / p.gamma_c)
    everywhere = np.zeros((0, 0), np.bool_)
    passes = {"both": (False, True), "rows": (False,), "columns": (True,)}[p.lines]
    for vertical in passes:
        bins = km.disparity_bins(disp, state.min_disp, state.ndisp)
        centre = klc.line_centre_mask(bins, everywhere, p.band, p.min_change, vertical)
        disp = kg.geodesic_vote_line(disp, bins, packed, centre, passed, int(p.min_change), int(p.max_bins),
                                     int(state.ndisp), vertical, float(p.min_lead))
    state.disparity = disp


def _colour_steps(channels: int) -> np.ndarray:
    """The vote tables' index: a summed channel difference in quarter grey levels (what
    :func:`~stereocli.matching.kernels.local_consistency.packed_quarter_levels` colours give), as the mean
    channel difference in grey levels, for every possible value."""
    return np.arange(1020 * channels + 1) * (0.25 / channels)


def _vote_tables(channels: int, p: LocalConsistencyParams) -> tuple[np.ndarray, np.ndarray, np.ndarray, float]:
    """Weights of the separable vote: spatial (2·radius + 1,) by offset, colour and match
    (float32, by summed channel difference in quarter grey levels) and the match weight of a
    point outside the right image."""
    spatial = np.exp(-np.abs(np.arange(-p.radius, p.radius + 1)) / p.gamma_s).astype(np.float32)
    steps = _colour_steps(channels)
    return (spatial, np.exp(-steps / p.gamma_c).astype(np.float32), np.exp(-steps / p.gamma_t).astype(np.float32),
            float(np.exp(-255.0 / p.gamma_t)))


def _discontinuity_windows(disp: np.ndarray, radius: int, min_spread: float, fill_invalid: bool) -> np.ndarray:
    """(H, W) bool: the (2·radius + 1)² window around the pixel spans more than ``min_spread``
    px of valid disparity (all True for ``min_spread`` 0); invalid pixels too with
    ``fill_invalid``."""
    if min_spread <= 0:
        return np.ones(disp.shape, bool)
    valid = np.isfinite(disp)
    kernel = np.ones((2 * radius + 1, 2 * radius + 1), np.uint8)
    high = cv2.dilate(np.where(valid, disp, -np.inf).astype(np.float32), kernel)
    low = cv2.erode(np.where(valid, disp, np.inf).astype(np.float32), kernel)
    with np.errstate(invalid="ignore"):
        todo = (high - low) > min_spread
    if fill_invalid:
        todo |= ~valid
    return todo


@dataclass(frozen=True)
class PlaneFitParams:
    method: str = param("ransac", "plane estimator per segment", choices=("ransac", "histogram"))
    segmentation: str = param("bilateral", "edge-preserving smoothing before the colour segments are grown: an OpenCV "
                              "bilateral filter or mean-shift filtering (cv2.pyrMeanShiftFiltering, an iterative "
                              "filter, slower; same scores on MiddEval3)", choices=("bilateral", "mean_shift"))
    spatial_radius: int = param(5, "smoothing window radius: mean-shift sp; bilateral: a (2·r − 1)-px filter with "
                                "σ_space = r", unit="px", low=1, high=100)
    colour_radius: float = param(6.0, "colour window radius: mean-shift sr; bilateral: σ_colour = 2·r",
                                 unit="grey levels", low=1.0, high=255.0)
    tolerance: float = param(2.0, "neighbours whose filtered colours differ by at most this join a segment",
                             unit="grey levels", low=0.0, high=255.0)
    min_size: int = param(30, "smaller segments are merged into a neighbour", unit="px", low=1, high=100000)
    min_points: int = param(20, "fit a plane only with at least this many reliable pixels", low=3, high=1000000)
    min_reliable: float = param(0.25, "...and at least this share of the segment reliable", low=0.0, high=1.0)
    min_inliers: float = param(0.8, "use a plane only if this share of its reliable pixels fit it", low=0.0, high=1.0)
    inlier: float = param(1.0, "a reliable pixel within this distance of the plane is an inlier",
                          unit="px", low=0.01, high=100.0)
    outlier: float = param(3.0, "with replace: outliers, replace pixels farther than this from their segment's plane",
                           unit="px", low=0.01, high=1000.0)
    replace: str = param("invalid", "which pixels of a segment with a trusted plane take the plane: invalid ones "
                         "(occlusions, LR failures), also outliers, or all", choices=("invalid", "outliers", "all"))
    iterations: int = param(200, "RANSAC samples per segment", low=1, high=100000)
    slope_bin: float = param(0.05, "histogram method: width of the slope voting bin",
                             unit="px/px", low=0.001, high=10.0)
    seed: int = param(0, "RNG seed of the RANSAC sampling (results are reproducible)", low=0, high=2**31 - 1)


def segment_image(image: np.ndarray, spatial_radius: int, colour_radius: float, tolerance: float, min_size: int,
                  smoothing: str) -> np.ndarray:
    """Colour segmentation: edge-preserving smoothing (OpenCV mean-shift filtering, or a
    bilateral filter with σ_space = ``spatial_radius`` and σ_colour = 2·``colour_radius``)
    + tolerant connected components.

    Parameters
    ----------
    image : (H, W) or (H, W, 3) float32 in [0, 255].
    smoothing : "mean_shift" or "bilateral".

    Returns
    -------
    (H, W) int32 segment labels 0..n-1.
    """
    img = _channels(image)
    if img.shape[2] == 1:
        img = np.repeat(img, 3, axis=2)
    img8 = np.clip(np.rint(img[..., :3]), 0, 255).astype(np.uint8)
    if smoothing == "bilateral":
        # A window radius of two standard deviations of the colour weight, as mean shift's
        # colour radius bounds its window.
        filtered = cv2.bilateralFilter(img8, 2 * int(spatial_radius) - 1, 2.0 * float(colour_radius),
                                       float(spatial_radius))
    elif smoothing == "mean_shift":
        filtered = cv2.pyrMeanShiftFiltering(img8, float(spatial_radius), float(colour_radius))
    else:
        raise ValueError(f"segment_image: unknown smoothing {smoothing!r}")
    return ksp.label_regions(np.ascontiguousarray(filtered, dtype=np.float32), float(tolerance), int(min_size))


def fit_segment_planes(disp: np.ndarray, labels: np.ndarray, p: PlaneFitParams):
    """Planes per segment (see :func:`stereocli.matching.kernels.segment_planes.fit_planes`)."""
    order, starts, counts = ksp.pixels_by_segment(labels)
    planes, support, inliers = ksp.fit_planes(
        np.ascontiguousarray(disp, dtype=np.float32), labels, order, starts,
        0 if p.method == "ransac" else 1, p.iterations, float(p.inlier), p.min_points, p.seed,
        float(p.slope_bin),
    )
    return planes, support, inliers, counts


@register("refinement", "plane_fit", PlaneFitParams, traits=StageTraits(map_copies=16))
def plane_fit(state: MatchState, p: PlaneFitParams) -> None:
    """Segment-based outlier replacement: fit d = a·x + b·y + c per colour segment.

    The left image is segmented (an edge-preserving bilateral filter or mean-shift filtering,
    then connected components of similar colour); each segment's plane is fitted to its
    reliable pixels (the finite ones: place this stage after ``lr_check``) by RANSAC (seeded) or
    by histogram voting on the disparity gradients, then refined by least squares on the
    inliers. Invalid pixels (occlusions, mismatches) of segments with a trustworthy plane are
    replaced by the plane; ``replace: outliers`` also replaces valid pixels far from it, ``all``
    every pixel (only safe when segments never straddle two surfaces). Assumes segments are
    planar surfaces: great on piecewise-planar scenes, can flatten curved or thin structures
    that share a colour segment (the reason ``replace`` defaults to invalid pixels only). The
    ``quality`` preset places it after ``lr_check``, before ``fill``: the rejected pixels inside
    a surface get its plane instead of the scanline fill's background value.
    """
    disp = np.ascontiguousarray(state.disparity, dtype=np.float32)
    labels = segment_image(state.left, p.spatial_radius, p.colour_radius, p.tolerance, p.min_size, p.segmentation)
    planes, support, inliers, counts = fit_segment_planes(disp, labels, p)
    use = ((support >= np.maximum(p.min_points, p.min_reliable * counts))
           & (inliers >= p.min_inliers * np.maximum(support, 1)) & (inliers > 0))
    lo, hi = float(state.min_disp), float(state.min_disp + state.ndisp - 1)
    outlier = float(p.outlier) if p.replace != "invalid" else np.inf
    state.disparity = ksp.replace_by_planes(disp, labels, planes, use, outlier, p.replace == "all", lo, hi)
