"""Cost-aggregation stages: smooth the cost volume over a support region (local methods).

Each stage reads ``state.cost`` ((H, W, D) float32, lower is better, impossible entries =
``state.cost_max``) and replaces it with an aggregated volume of the same layout and units
(weighted *means* of the input costs), restoring ``cost_max`` on impossible entries. Supports
that depend on colour read ``state.left``/``state.right`` as they are after preprocessing.

The family follows Scharstein & Szeliski (2002, §3.2) and the adaptive-support literature:
fixed windows (``box``), windows that move or change size (``shiftable``,
``multiple_windows``, ``variable_window``, ``cross``), and weighted supports (``adaptive_weights``,
``segment_support``, ``fast_bilateral``, ``guided_filter``, ``locally_consistent``).
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from ..errors import ConfigError
from ..registry import param, register
from .cost import _channels, check_odd_window
from .kernels import aggregation as ka
from .kernels.aggregation import CV_MAX_CHANNELS, box_filter_volume
from .kernels.costs import mask_invalid_right
from .kernels.winners import wta_left
from .state import MatchState


def _finish(state: MatchState, cost: np.ndarray) -> None:
    """Store ``cost``, putting ``cost_max`` back on impossible entries (the volume contract)."""
    ka.restore_impossible(cost, state.min_disp, np.float32(state.cost_max))
    if state.right_valid is not None:
        mask_invalid_right(cost, state.right_valid, state.min_disp, np.float32(state.cost_max))
    state.cost = cost


def _input(state: MatchState) -> np.ndarray:
    """The cost volume to aggregate, with impossible entries replaced by the nearest possible
    one of the same row (in place: ``state.cost`` is replaced by the result anyway)."""
    cost = np.ascontiguousarray(state.cost, dtype=np.float32)
    ka.extend_border_costs(cost, state.min_disp)
    return cost


def _lab(image: np.ndarray) -> np.ndarray:
    """(H, W[, 3]) float32 in [0, 255] -> CIELab (H, W, 3) float32 (L in [0, 100])."""
    rgb = image if image.ndim == 3 else np.repeat(image[..., None], 3, axis=2)
    rgb = np.clip(rgb, 0.0, 255.0).astype(np.float32) * np.float32(1.0 / 255.0)
    return np.ascontiguousarray(cv2.cvtColor(rgb, cv2.COLOR_RGB2Lab))


def _with_volume_copies(n: float):
    def mark(func):
        func.volume_copies = n  # read by stereocli.matching.pipeline.volume_copies
        return func

    return mark


@register("aggregation", "none")
def no_aggregation(state: MatchState, params) -> None:
    """Keep the pixel-wise costs (the optimizer provides the smoothness)."""


@dataclass(frozen=True)
class BoxParams:
    window: tuple[int, int] = param((5, 5), "window (height, width), odd", unit="px", low=1, high=101)

    def __post_init__(self):
        check_odd_window("aggregation.box.window", self.window)


@register("aggregation", "box", BoxParams)
def box_aggregation(state: MatchState, p: BoxParams) -> None:
    """Fixed square window mean, O(1) per pixel by running sums (any window size).

    Fast and simple; blurs depth discontinuities by about half a window ("foreground
    fattening"); larger windows are more reliable in weak texture (Scharstein & Szeliski
    2002, §3.2). With ``ad`` it is SAD, with ``sd`` SSD (the ``sad``/``ssd`` costs fuse both).
    """
    _finish(state, box_filter_volume(_input(state), p.window[0] // 2, p.window[1] // 2))


@dataclass(frozen=True)
class ShiftableParams:
    window: tuple[int, int] = param((9, 9), "window (height, width), odd; each pixel takes the best of all windows of "
                                    "this size containing it", unit="px", low=1, high=101)

    def __post_init__(self):
        check_odd_window("aggregation.shiftable.window", self.window)


@register("aggregation", "shiftable", ShiftableParams)
@_with_volume_copies(2.0)
def shiftable(state: MatchState, p: ShiftableParams) -> None:
    """Shiftable windows: box mean, then a min filter of the same size over window positions.

    Each pixel takes the lowest cost of every window that contains it, so near a depth edge a
    window lying entirely on the pixel's own surface wins: much less foreground fattening than
    a centred box at twice its cost (Bobick & Intille 1999; Scharstein & Szeliski 2002,
    §3.2 "min filter"). May shift the edge the other way in weak texture.
    """
    ry, rx = p.window[0] // 2, p.window[1] // 2
    box = box_filter_volume(_input(state), ry, rx)
    kernel = np.ones((2 * ry + 1, 2 * rx + 1), np.uint8)
    out = np.empty_like(box)
    for k0 in range(0, box.shape[2], CV_MAX_CHANNELS):
        k1 = min(box.shape[2], k0 + CV_MAX_CHANNELS)
        chunk = box if (k0 == 0 and k1 == box.shape[2]) else np.ascontiguousarray(box[:, :, k0:k1])
        out[:, :, k0:k1] = cv2.erode(chunk, kernel, borderType=cv2.BORDER_REPLICATE).reshape(chunk.shape)
    _finish(state, out)


@dataclass(frozen=True)
class MultipleWindowsParams:
    window: tuple[int, int] = param((7, 7), "size of each sub-window (height, width), odd", unit="px", low=1, high=51)
    windows: int = param(5, "5: centre + best 2 of 4 diagonal windows; 9: centre + best 4 of 8 surrounding windows",
                         choices=(5, 9))

    def __post_init__(self):
        check_odd_window("aggregation.multiple_windows.window", self.window)


@register("aggregation", "multiple_windows", MultipleWindowsParams)
@_with_volume_copies(2.0)
def multiple_windows(state: MatchState, p: MultipleWindowsParams) -> None:
    """Multiple windows: centre window plus the best subset of the surrounding windows.

    The support adapts its shape to depth edges by leaving out the surrounding windows that
    match worst (Fusiello, Roberto & Trucco 1997; Hirschmüller, Innocent & Garibaldi, IJCV
    2002: configurations of 5 and 9 windows). Surrounding windows are offset by half a window
    plus one pixel, so they overlap the centre one. 9 windows adapt better, cost more.
    """
    ry, rx = p.window[0] // 2, p.window[1] // 2
    box = box_filter_volume(_input(state), ry, rx)
    oy, ox = ry + 1, rx + 1
    if p.windows == 5:
        off_y = np.array([-oy, -oy, oy, oy], np.int64)
        off_x = np.array([-ox, ox, -ox, ox], np.int64)
        keep = 2
    else:
        off_y = np.array([-oy, -oy, -oy, 0, 0, oy, oy, oy], np.int64)
        off_x = np.array([-ox, 0, ox, -ox, ox, -ox, 0, ox], np.int64)
        keep = 4
    _finish(state, ka.multiple_windows(box, off_y, off_x, keep))


@dataclass(frozen=True)
class VariableWindowParams:
    min_size: int = param(3, "smallest window side, odd", unit="px", low=1, high=101)
    max_size: int = param(21, "largest window side, odd", unit="px", low=1, high=201)
    step: int = param(4, "size increment between candidate sides (even)", unit="px", low=2, high=50)
    alpha: float = param(30.0, "penalty α in (Σ e + α)/|W|: larger prefers larger windows",
                         unit="cost·px", low=0.0, high=1e6)

    def __post_init__(self):
        where = "aggregation.variable_window"
        if self.min_size % 2 == 0 or self.max_size % 2 == 0:
            raise ConfigError(f"{where}.min_size/max_size: {self.min_size}, {self.max_size} must be odd")
        if self.max_size < self.min_size:
            raise ConfigError(f"{where}.max_size: {self.max_size} is smaller than min_size {self.min_size}")
        if self.step % 2:
            raise ConfigError(f"{where}.step: {self.step} must be even (sides stay odd)")


@register("aggregation", "variable_window", VariableWindowParams)
@_with_volume_copies(3.0)
def variable_window(state: MatchState, p: VariableWindowParams) -> None:
    """Veksler's fast variable window: best rectangle per pixel and disparity via integral images.

    Every centred rectangle with sides in [min_size, max_size] (independently in x and y, in
    steps of ``step``) is scored by mean error + α/|W| in O(1) from the summed-area table of each
    disparity slice; the best score is the aggregated cost (Veksler, CVPR 2003). Adapts the
    window to texture and to elongated structures; cost grows with the number of candidate
    shapes. Memory: one float64 summed-area table (2 volumes) besides the input.
    """
    sides = np.arange(p.min_size, p.max_size + 1, p.step)
    ry = np.array([a // 2 for a in sides for _ in sides], np.int64)
    rx = np.array([b // 2 for _ in sides for b in sides], np.int64)
    sat = ka.integral_volume(_input(state))
    out = ka.variable_window(sat, ry, rx, float(p.alpha))
    del sat
    _finish(state, out)


@dataclass(frozen=True)
class CrossParams:
    tau: float = param(20.0, "colour threshold τ: an arm stops at the first pixel differing by ≥ τ in any channel",
                       unit="grey levels", low=1.0, high=255.0)
    max_arm: int = param(17, "longest arm L", unit="px", low=1, high=100)
    iterations: int = param(2, "aggregation passes (alternating horizontal-first and vertical-first)", low=1, high=8)
    tau2: float = param(0.0, "two-threshold rule (Mei et al. 2011): beyond max_arm2 the colour must stay within tau2 "
                        "of the pixel, and each step within tau of the previous arm pixel; 0 = single threshold "
                        "(Zhang et al. 2009)", unit="grey levels", low=0.0, high=255.0)
    max_arm2: int = param(17, "with tau2 > 0: arms longer than this (L2) need the stricter tau2",
                          unit="px", low=1, high=100)

    def __post_init__(self):
        if self.tau2 > 0 and self.max_arm2 > self.max_arm:
            raise ConfigError(f"aggregation.cross: max_arm2 ({self.max_arm2}) must not exceed max_arm ({self.max_arm})")


@register("aggregation", "cross", CrossParams)
@_with_volume_copies(3.0)
def cross(state: MatchState, p: CrossParams) -> None:
    """Cross-based support regions: per-pixel arms by colour similarity, O(1) integration.

    Each pixel gets four arms that grow while the colour stays within τ of the pixel and the
    length within L; its support is the union of the horizontal arms of the pixels on its
    vertical arm, integrated with 1-D running sums along rows then columns (orthogonal
    integral images) and normalised by the pixel count (Zhang, Lu & Lafruit, IEEE TCSVT
    2009). Supports come from the left image. Larger τ/L: smoother, riskier at edges.
    With ``tau2 > 0`` the arms follow the two-threshold rule of ADCensus (Mei et al. 2011):
    long arms (up to ``max_arm`` = L1) in uniform regions, but beyond ``max_arm2`` = L2 only
    through colours within ``tau2`` of the pixel.
    """
    image = _channels(state.left)
    if p.tau2 > 0:
        arms = ka.cross_arms_two_threshold(image, float(p.tau), float(p.tau2), int(p.max_arm), int(p.max_arm2))
    else:
        arms = ka.cross_arms(image, float(p.tau), int(p.max_arm))
    # The vertical-first order uses the transposed support (union of vertical arms).
    ones = np.ones(state.shape + (1,), np.float32)
    count_hv = ka.cross_sum_v(ka.cross_sum_h(ones, arms), arms)[..., 0]
    count_vh = ka.cross_sum_h(ka.cross_sum_v(ones, arms), arms)[..., 0]
    cost = _input(state)
    for it in range(p.iterations):
        if it % 2 == 0:
            cost = ka.cross_sum_v(ka.cross_sum_h(cost, arms), arms)
            cost /= count_hv[..., None]
        else:
            cost = ka.cross_sum_h(ka.cross_sum_v(cost, arms), arms)
            cost /= count_vh[..., None]
    _finish(state, cost)


def _window_offsets(radius_y: int, radius_x: int, stride: int = 1):
    ys, xs = np.meshgrid(np.arange(-radius_y, radius_y + 1, stride), np.arange(-radius_x, radius_x + 1, stride),
                         indexing="ij")
    return ys.ravel().astype(np.int64), xs.ravel().astype(np.int64)


@dataclass(frozen=True)
class AdaptiveWeightsParams:
    window: int = param(35, "support window side, odd", unit="px", low=3, high=101)
    gamma_c: float = param(10.0, "colour similarity scale γ_c (CIELab distance; larger = wider support across colour "
                           "edges)", unit="Lab units", low=0.1, high=200.0)
    gamma_p: float = param(17.5, "proximity scale γ_p", unit="px", low=0.1, high=500.0)
    min_weight: float = param(1e-4, "skip support pixels whose left weight is below this (speed; 0 = exact)",
                              low=0.0, high=0.5)

    def __post_init__(self):
        if self.window % 2 == 0:
            raise ConfigError(f"aggregation.adaptive_weights.window: {self.window} must be odd")


@register("aggregation", "adaptive_weights", AdaptiveWeightsParams)
def adaptive_weights(state: MatchState, p: AdaptiveWeightsParams) -> None:
    """Adaptive support weights (Yoon & Kweon, PAMI 2006): colour- and proximity-weighted mean.

    Each support pixel q of p weighs w(p, q) = exp(−(Δc_pq/γ_c + Δg_pq/γ_p)) with Δc the
    CIELab distance and Δg the spatial distance, in both views (the right view at the
    hypothesised disparity), and the aggregate is Σ w_L·w_R·e / Σ w_L·w_R (eq. 5). Accurate
    at depth edges, slow: O(window² · D) per pixel (Teddy, D = 64: a few seconds on 2 cores).
    Paper settings: 35×35, γ_c = 5, γ_p = 17.5 on truncated AD; with OpenCV's float CIELab
    (L in [0, 100]) γ_c = 10 scores clearly better on the Middlebury 2001/2003 scenes, hence
    the default. Pair it with ``color_gradient`` (``tau_color: 30``, the cost of Julià &
    Monasse's IPOL implementation): the gradient term keeps weakly textured supports from
    locking onto nearby periodic texture (benchmarks/local_methods.py).
    """
    r = p.window // 2
    off_y, off_x = _window_offsets(r, r)
    spatial = np.exp(-np.hypot(off_y, off_x) / p.gamma_p).astype(np.float32)
    lab_l, lab_r = _lab(state.left), _lab(state.right)
    seg = np.zeros((1, 1), np.int32)
    out = ka.weighted_support(_input(state), lab_l, lab_r, seg, seg,
                              off_y, off_x, spatial, float(p.gamma_c), state.min_disp,
                              float(state.cost_max), False, float(p.min_weight))
    _finish(state, out)


@dataclass(frozen=True)
class SegmentSupportParams:
    window: int = param(31, "support window side, odd", unit="px", low=3, high=101)
    gamma_c: float = param(10.0, "colour scale γ_c for pixels outside the segment (CIELab)",
                           unit="Lab units", low=0.1, high=200.0)
    spatial_radius: int = param(7, "mean-shift spatial radius (cv2.pyrMeanShiftFiltering sp)",
                                unit="px", low=1, high=50)
    color_radius: float = param(12.0, "mean-shift colour radius (sr)", unit="grey levels", low=1.0, high=255.0)
    min_weight: float = param(1e-4, "skip support pixels whose left weight is below this (speed; 0 = exact)",
                              low=0.0, high=0.5)

    def __post_init__(self):
        if self.window % 2 == 0:
            raise ConfigError(f"aggregation.segment_support.window: {self.window} must be odd")


def _segments(image: np.ndarray, sp: int, sr: float) -> np.ndarray:
    """Mean-shift segment labels: pixels whose mean-shift mode colour is identical share a label."""
    rgb = image if image.ndim == 3 else np.repeat(image[..., None], 3, axis=2)
    u8 = np.clip(np.rint(rgb), 0, 255).astype(np.uint8)
    mode = cv2.pyrMeanShiftFiltering(u8, sp, sr).astype(np.int32)
    return np.ascontiguousarray((mode[..., 0] << 16) | (mode[..., 1] << 8) | mode[..., 2])


@register("aggregation", "segment_support", SegmentSupportParams)
def segment_support(state: MatchState, p: SegmentSupportParams) -> None:
    """Segment support: weight 1 inside the pixel's colour segment, exp(−Δc/γ_c) outside.

    Segments come from mean-shift filtering (cv2.pyrMeanShiftFiltering; pixels sharing a mode
    colour form a segment), in both views, following Tombari, Mattoccia & Di Stefano (PSIVT
    2007). Trusts whole segments (good on large smooth surfaces, bad when a segment spans a
    depth edge); no proximity term inside the window.
    """
    r = p.window // 2
    off_y, off_x = _window_offsets(r, r)
    spatial = np.ones(off_y.size, np.float32)
    seg_l = _segments(state.left, p.spatial_radius, p.color_radius)
    seg_r = _segments(state.right, p.spatial_radius, p.color_radius)
    out = ka.weighted_support(_input(state), _lab(state.left),
                              _lab(state.right), seg_l, seg_r, off_y, off_x, spatial,
                              float(p.gamma_c), state.min_disp, float(state.cost_max), True,
                              float(p.min_weight))
    _finish(state, out)


@dataclass(frozen=True)
class FastBilateralParams:
    window: int = param(39, "support window side, odd", unit="px", low=3, high=151)
    block: int = param(3, "block side: costs and colours are averaged per block, weights computed per block",
                       unit="px", low=1, high=15)
    gamma_c: float = param(5.0, "colour scale γ_c (CIELab)", unit="Lab units", low=0.1, high=200.0)
    gamma_p: float = param(17.5, "proximity scale γ_p", unit="px", low=0.1, high=500.0)

    def __post_init__(self):
        if self.window % 2 == 0 or self.block % 2 == 0:
            raise ConfigError(f"aggregation.fast_bilateral.window/block: {self.window}, {self.block} must be odd")


@register("aggregation", "fast_bilateral", FastBilateralParams)
@_with_volume_copies(2.0)
def fast_bilateral(state: MatchState, p: FastBilateralParams) -> None:
    """Fast Bilateral Stereo: joint-bilateral weights computed on blocks instead of pixels.

    The window is tiled into block×block cells; each cell contributes its box-mean cost,
    weighted symmetrically (both views) by proximity and by the CIELab distance between the
    mean colours of the pixel's block and of the cell (Mattoccia, Giardino & Gambini, ACCV 2009). block² fewer
    weights than ``adaptive_weights`` with nearly its accuracy; block = 1 is Yoon–Kweon.
    """
    r = (p.window // 2) // p.block * p.block
    off_y, off_x = _window_offsets(r, r, p.block)
    spatial = np.exp(-np.hypot(off_y, off_x) / p.gamma_p).astype(np.float32)
    b = p.block // 2
    cost = box_filter_volume(_input(state), b, b) if b else _input(state)
    from .cost import box_mean_image

    lab_l = np.ascontiguousarray(box_mean_image(_lab(state.left), b, b))
    lab_r = np.ascontiguousarray(box_mean_image(_lab(state.right), b, b))
    # Weights compare block-mean colours (the pixel's block with each cell), Δg between centres.
    seg = np.zeros((1, 1), np.int32)
    out = ka.weighted_support(cost, lab_l, lab_r, seg, seg, off_y, off_x, spatial, float(p.gamma_c),
                              state.min_disp, float(state.cost_max), False, 0.0)
    _finish(state, out)


@dataclass(frozen=True)
class LocallyConsistentParams:
    window: int = param(21, "side of the supports whose assertions are accumulated, odd", unit="px", low=3, high=101)
    gamma_s: float = param(8.0, "proximity scale γ_s", unit="px", low=0.1, high=500.0)
    gamma_c: float = param(15.0, "colour scale γ_c (CIELab, both views)", unit="Lab units", low=0.1, high=500.0)
    gamma_t: float = param(10.0, "matching-cost scale γ_t", unit="grey levels", low=0.1, high=500.0)
    truncate: float = param(30.0, "truncation T of the pixel AD in the plausibility",
                            unit="grey levels", low=1.0, high=255.0)

    def __post_init__(self):
        if self.window % 2 == 0:
            raise ConfigError(f"aggregation.locally_consistent.window: {self.window} must be odd")


@register("aggregation", "locally_consistent", LocallyConsistentParams)
@_with_volume_copies(2.0)
def locally_consistent(state: MatchState, p: LocallyConsistentParams) -> None:
    """Locally consistent stereo: accumulate the plausibility of each support's disparity.

    The incoming volume (typically already aggregated, e.g. ``fast_bilateral``) gives every
    pixel c a WTA disparity d_c; each support centred at c then asserts d_c for every point f
    it contains, with plausibility from proximity, colour similarity in both views and the
    pixel matching cost; the output cost is 1 − Ω_f(d)/Σ_d Ω_f(d) (Mattoccia, "A locally global
    approach to stereo correspondence", ICCV Workshops 2009). Enforces local smoothness of the
    disparity field; O(window²) per pixel, independent of D. Range [0, 1]; points that no
    support asserts get cost 1 (invalid after WTA).
    """
    if state.cost is None:  # (never: the pipeline runs a cost stage first)
        raise RuntimeError("aggregation.locally_consistent: no cost volume")
    disp, _ = wta_left(state.cost, state.min_disp, np.float32(state.cost_max))
    disp_k = np.where(np.isfinite(disp), disp - state.min_disp, -1).astype(np.int32)
    left = np.ascontiguousarray(state.left if state.left.ndim == 3 else state.left[..., None], dtype=np.float32)
    right = np.ascontiguousarray(state.right if state.right.ndim == 3 else state.right[..., None], dtype=np.float32)
    cost = ka.lc_plausibility(disp_k, _lab(state.left), _lab(state.right), left, right, state.min_disp,
                              state.ndisp, p.window // 2, float(p.gamma_s), float(p.gamma_c),
                              float(p.gamma_t), float(p.truncate))
    state.cost_max = 1.0
    _finish(state, cost)


@dataclass(frozen=True)
class GuidedFilterParams:
    radius: int = param(9, "box radius r of the guided filter (window 2r+1)", unit="px", low=1, high=50)
    eps: float = param(1e-4, "regularisation ε for intensities on [0, 1] (larger = smoother, less edge-aware)",
                       unit="(intensity/255)²", low=1e-8, high=1.0)
    right_view: str = param("volume", "right-view disparity (when a later stage needs it, e.g. lr_check): 'volume' = "
                            "read from this left-guided volume by the optimizer/pipeline; 'guided' = WTA of the "
                            "right-referenced volume filtered with the right image as guide (Rhemann/Hosni; for the "
                            "wta optimizer)", choices=("volume", "guided"))


@register("aggregation", "guided_filter", GuidedFilterParams)
def guided_filter(state: MatchState, p: GuidedFilterParams) -> None:
    """Cost-volume filtering with He's guided filter (Hosni et al., PAMI 2013).

    Each disparity slice is filtered with the edge-preserving guided filter (He, Sun & Tang,
    ECCV 2010) guided by the left colour image: q = ā·I + b̄ with a = (Σ + εU)⁻¹ cov(I, p) per
    window. Built from box filters, so O(1) per pixel whatever the radius: the speed of a box
    filter with nearly the edge-awareness of adaptive weights. Paper settings: r = 9,
    ε = 1e-4, on the ``color_gradient`` cost. Memory: a few image-sized buffers per slice.

    The filter is guided by one view, so the volume is not symmetric: the right-view disparity
    read from its diagonal (what ``wta`` + ``lr_check`` do by default) inherits the *left*
    image's edges. With ``right_view: guided`` and a later stage that needs the right view,
    the stage also filters each right-referenced slice C_R(x_r, d) = C(x_r + d, d) guided by the
    right image and sets ``disparity_right`` to its WTA (ties to the smaller disparity), as
    Rhemann et al. (CVPR 2011) and Hosni et al. compute both views before the LR check; it
    doubles the filtering time (a later ``subpixel`` stage refines this map from the costs on
    the volume's diagonal). Meant for the ``wta`` optimizer: ``sgm``, ``dp`` and ``gc`` replace
    the right view with their own, other optimizers would keep this one. On the Middlebury
    2001/2003 scenes (WTA, sub-pixel, LR check, weighted-median fill) it lowers bad > 1 px from
    2.95/0.73/6.99/2.74 to 2.63/0.55/6.62/2.53 % (benchmarks/local_methods.py).
    """
    cost = _input(state)
    out = np.empty_like(cost)
    filt = _GuidedFilter(_guide(state.left), p.radius, p.eps)
    for k in range(cost.shape[2]):  # one slice at a time: OpenCV box filters, little memory
        out[:, :, k] = filt(np.ascontiguousarray(cost[:, :, k]))
    if p.right_view == "guided" and state.wants.right:
        state.disparity_right = _guided_right_view(cost, _GuidedFilter(_guide(state.right), p.radius, p.eps),
                                                   state.min_disp, float(state.cost_max), state.right_valid)
    _finish(state, out)


def _guide(image: np.ndarray) -> np.ndarray:
    """(H, W[, 3]) float32 in [0, 255] -> (H, W, C) float32 guide on [0, 1]."""
    return (image if image.ndim == 3 else image[..., None]).astype(np.float32) / np.float32(255.0)


def _guided_right_view(cost: np.ndarray, filt: _GuidedFilter, min_disp: int, cost_max: float,
                       right_valid: np.ndarray | None) -> np.ndarray:
    """WTA right-view disparity of the right-referenced volume filtered by ``filt``.

    ``cost`` is the left-referenced (H, W, D) float32 input volume; slice k is sheared to the
    right view, C_R[y, x_r] = cost[y, x_r + d], d = min_disp + k, with the entries whose left
    pixel x_r + d is outside the image replaced by the nearest possible one (as
    ``extend_border_costs`` does for the left view), filtered, and the lowest filtered cost
    below ``cost_max`` wins (ties to the smaller disparity, as ``wta_right``). Returns (H, W)
    float32 right-referenced disparities (x_left = x_right + d), +inf where nothing wins or the
    right pixel is invalid.
    """
    h, w, nd = cost.shape
    xr = np.arange(w)
    best = np.full((h, w), np.float32(cost_max), np.float32)
    best_k = np.full((h, w), -1, np.int32)
    for k in range(nd):
        d = min_disp + k
        lo, hi = max(0, d), min(w - 1, w - 1 + d)  # left x with 0 <= x - d <= w - 1
        if lo > hi:
            continue
        src = np.clip(xr + d, lo, hi)
        q = filt(np.ascontiguousarray(cost[:, src, k]))
        possible = (xr + d >= 0) & (xr + d <= w - 1)
        win = (q < best) & possible[None, :]
        best[win] = q[win]
        best_k[win] = k
    disp = np.where(best_k >= 0, np.float32(min_disp) + best_k, np.inf).astype(np.float32)
    if right_valid is not None:
        disp[~right_valid] = np.inf
    return disp


class _GuidedFilter:
    """He et al.'s guided filter (grey or colour guide) with the guide statistics precomputed."""

    def __init__(self, guide: np.ndarray, radius: int, eps: float):
        self.ksize = (2 * radius + 1, 2 * radius + 1)
        self.guide = guide
        nc = guide.shape[2]
        self.mean_i = self._box(guide).reshape(guide.shape)
        if nc == 1:
            var = self._box(guide[..., 0] * guide[..., 0]) - self.mean_i[..., 0] ** 2
            self.inv = (1.0 / (var + eps)).astype(np.float32)
            return
        # Σ + εU per pixel (3×3), inverted in closed form via np.linalg on the stacked matrices.
        cov = np.empty(guide.shape[:2] + (3, 3), np.float32)
        for i in range(3):
            for j in range(i, 3):
                c = self._box(guide[..., i] * guide[..., j]) - self.mean_i[..., i] * self.mean_i[..., j]
                cov[..., i, j] = cov[..., j, i] = c
        cov += eps * np.eye(3, dtype=np.float32)
        self.inv = np.linalg.inv(cov).astype(np.float32)

    def _box(self, img: np.ndarray) -> np.ndarray:
        return cv2.boxFilter(img, -1, self.ksize, borderType=cv2.BORDER_REFLECT)

    def __call__(self, p: np.ndarray) -> np.ndarray:
        g, mi = self.guide, self.mean_i
        nc = g.shape[2]
        stacked = np.concatenate([p[..., None], g * p[..., None]], axis=2)
        means = self._box(stacked).reshape(stacked.shape)
        mean_p = means[..., 0]
        cov_ip = means[..., 1:] - mi * mean_p[..., None]
        if nc == 1:
            a = cov_ip * self.inv[..., None]
        else:
            a = np.einsum("hwij,hwj->hwi", self.inv, cov_ip)
        b = mean_p - np.einsum("hwc,hwc->hw", a, mi)
        ab = self._box(np.concatenate([a, b[..., None]], axis=2).astype(np.float32)).reshape(a.shape[:2] + (nc + 1,))
        return np.einsum("hwc,hwc->hw", ab[..., :nc], g) + ab[..., nc]
