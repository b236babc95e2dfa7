"""Matching-cost stages: build the (H, W, D) float32 cost volume (lower is better).

The cost volume is the contract between stages (see :mod:`stereocli.matching.state`):
``cost[y, x, k]`` is the dissimilarity of left pixel (x, y) and right pixel
(x − (min_disp + k), y); shape (H, W, D) with D = ``ndisp``, C-contiguous float32 (4 bytes
per entry: a 1000×750 image with D = 128 is 384 MB; the pipeline splits larger jobs into row
strips). Lower is better. Every stage sets ``state.cost`` and ``state.cost_max``, the value
held by impossible entries (right pixel outside the image) and an upper bound of the valid
costs. Costs that are small integers (AD of 8-bit images, census, rank) are still stored as
float32 so every aggregator and optimizer reads one dtype.

Window-based costs (SAD, SSD, STAD, NCC, ZNCC) are computed with running sums, O(1) per
entry whatever the window size, and report the window *mean* (sum / pixel count, window
clipped at the image border) so their units do not depend on the window. Colour images use
all channels where the method allows (AD/SD/BT/gradients/NCC: all channels; census, rank
and ordinal measures work on the grey image).
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import cv2
import numpy as np

from ..errors import ConfigError
from ..registry import StageTraits, param, register
from .kernels import census as kc
from .kernels import costs as kl
from .kernels.fused_sad import sad_wta as fused_sad_wta
from .state import MatchState, WinnerCosts


def run_cost_stage(state: MatchState, call) -> None:
    """Run a configured cost stage (a StageCall) on ``state`` and give every hypothesis whose
    right pixel is outside ``state.right_valid`` the volume's maximum cost."""
    call.stage.func(state, call.params)
    if state.right_valid is not None:
        if state.cost is None:
            raise RuntimeError(f"cost.{call.stage.name}: left no cost volume")
        kl.mask_invalid_right(state.cost, state.right_valid, state.min_disp, np.float32(state.cost_max))


def _channels(image: np.ndarray) -> np.ndarray:
    """(H, W) or (H, W, C) -> (H, W, C) float32 C-contiguous."""
    image = image if image.ndim == 3 else image[..., None]
    return np.ascontiguousarray(image, dtype=np.float32)


def left_guide(state: MatchState, color: bool) -> np.ndarray:
    """The left image as an (H, W, C) float32 guide: its channels, or (``color`` false) its
    grey image as one channel (stages with a ``color`` option)."""
    return _channels(state.left if color else state.gray("left"))


def colour_switch(params) -> bool:
    """with ``color: true``"""
    return bool(params.color)


def check_odd_window(where: str, window: tuple[int, int], max_pixels: int | None = None) -> None:
    """Raise :class:`ConfigError` naming ``where`` unless both sizes are odd (and small enough)."""
    if window[0] % 2 == 0 or window[1] % 2 == 0:
        raise ConfigError(f"{where}: {list(window)} must be odd sizes (height, width), e.g. [9, 9]")
    if max_pixels is not None and window[0] * window[1] > max_pixels:
        raise ConfigError(f"{where}: {list(window)} has {window[0] * window[1]} pixels; at most {max_pixels}")


def _bands() -> int:
    from ..runtime import kernel_threads

    # A few bands per thread balances the load; each band pays 2·radius extra rows.
    return 4 * kernel_threads()


def box_mean_image(image: np.ndarray, radius_y: int, radius_x: int) -> np.ndarray:
    """Mean over the (2ry+1)×(2rx+1) window clipped to the image, for (H, W) or (H, W, C) float32.

    Same border rule as the cost kernels (sum of the pixels inside / their count).
    """
    image = np.ascontiguousarray(image, dtype=np.float32)
    ksize = (2 * radius_x + 1, 2 * radius_y + 1)
    total = cv2.boxFilter(image, -1, ksize, normalize=False, borderType=cv2.BORDER_CONSTANT)
    count = cv2.boxFilter(np.ones(image.shape[:2], np.float32), -1, ksize, normalize=False,
                          borderType=cv2.BORDER_CONSTANT)
    total = total.reshape(image.shape)
    return (total / (count if image.ndim == 2 else count[..., None])).astype(np.float32)


# --- pixel-wise costs --------------------------------------------------------------------


@dataclass(frozen=True)
class ADParams:
    truncate: float = param(255.0, "truncate the absolute difference at this value (255 = no truncation)",
                            unit="grey levels", low=1, high=255)


@register("cost", "ad", ADParams)
def ad_cost(state: MatchState, p: ADParams) -> None:
    """Absolute intensity difference, averaged over colour channels, optionally truncated.

    The simplest pixel-wise cost: fast, sensitive to gain/bias changes between the cameras.
    Pair it with an aggregation stage (``box`` = SAD) or a global optimizer.
    """
    state.cost_max = float(p.truncate)
    state.cost = kl.absdiff_volume(_channels(state.left), _channels(state.right), state.min_disp,
                                   state.ndisp, state.cost_max, float(p.truncate))


@dataclass(frozen=True)
class TADParams:
    truncate: float = param(20.0, "truncation of the absolute difference (lower = more robust to occlusions and "
                            "noise, less discriminative)", unit="grey levels", low=1, high=255)


@register("cost", "tad", TADParams)
def tad_cost(state: MatchState, p: TADParams) -> None:
    """Truncated absolute difference min(|L − R|, T), mean over colour channels.

    Truncation bounds the influence of occluded and mismatched pixels inside a support
    window (used by adaptive-weight and cost-filtering methods; Scharstein & Szeliski 2002,
    §3.1). Same kernel as ``ad`` with a lower default threshold.
    """
    state.cost_max = float(p.truncate)
    state.cost = kl.absdiff_volume(_channels(state.left), _channels(state.right), state.min_disp,
                                   state.ndisp, state.cost_max, float(p.truncate))


@dataclass(frozen=True)
class SDParams:
    truncate: float = param(65025.0, "truncate the squared difference at this value (65025 = 255², no truncation)",
                            unit="grey levels²", low=1, high=65025)


@register("cost", "sd", SDParams)
def sd_cost(state: MatchState, p: SDParams) -> None:
    """Squared intensity difference, averaged over colour channels, optionally truncated.

    Weights large differences more than AD: optimal for Gaussian noise, more hurt by
    outliers (occlusions, specularities) (Scharstein & Szeliski 2002, §3.1).
    """
    state.cost_max = float(p.truncate)
    state.cost = kl.pixel_cost_volume(_channels(state.left), _channels(state.right), state.min_disp,
                                      state.ndisp, kl.MODE_SD, float(p.truncate), state.cost_max)


# --- window costs by running sums -----------------------------------------------------------


def _windowed_truncated_ad(state: MatchState, p) -> None:
    """Window mean of per-pixel |L − R| truncated at ``p.truncate`` (shared by sad and stad)."""
    state.cost_max = float(p.truncate)
    state.cost = kl.window_cost_volume(_channels(state.left), _channels(state.right), state.min_disp,
                                       state.ndisp, p.window[0] // 2, p.window[1] // 2, kl.MODE_AD,
                                       float(p.truncate), state.cost_max, _bands())


def _windowed_truncated_ad_wta(state: MatchState, p, winner: bool) -> None:
    """Fused ``sad``/``stad`` + ``wta``: the same disparities without the (H, W, D) volume.

    Sets ``disparity`` bit-identical to running the cost stage, the right-valid masking and
    ``wta`` (same float32 operations in the same order and bands,
    :mod:`~stereocli.matching.kernels.fused_sad`), and with ``winner`` also ``state.winner`` (the
    costs at k − 1, k, k + 1 of each winner, for the volume refinements); ``cost`` stays None.
    Called by the pipeline (:func:`stereocli.matching.pipeline.fused_cost_wta`).
    """
    left = _channels(state.left)
    mask = state.right_valid if state.right_valid is not None else np.zeros((0, 0), np.bool_)
    state.cost_max = float(p.truncate)
    disparity, costs = fused_sad_wta(left, _channels(state.right), mask, state.min_disp, state.ndisp,
                                     p.window[0] // 2, p.window[1] // 2, float(p.truncate) * left.shape[2],
                                     state.cost_max, _bands(), winner)
    state.cost = None
    state.disparity = disparity
    # the refinements replace ``disparity``; the winner keeps the WTA map they started from
    state.winner = WinnerCosts(disparity.copy(), costs) if winner else None


@dataclass(frozen=True)
class WindowADParams:
    window: tuple[int, int] = param((9, 9), "window (height, width), odd; larger = smoother and more reliable in weak "
                                    "texture, but fatter at depth edges", unit="px", low=1, high=101)
    truncate: float = param(255.0, "truncate each pixel's |L − R| before summing (255 = none)",
                            unit="grey levels", low=1, high=255)

    def __post_init__(self):
        check_odd_window("cost.window", self.window)


@register("cost", "sad", WindowADParams, traits=StageTraits(fused_wta=_windowed_truncated_ad_wta))
def sad_cost(state: MatchState, p: WindowADParams) -> None:
    """Sum of absolute differences over a window (reported as the window mean), O(1) per entry.

    AD and box aggregation fused in one pass of running sums (column sums updated one row at a
    time, then a running sum along x), the fast area-based scheme of Di Stefano, Marchionni &
    Mattoccia (2004) and OpenCV's StereoBM; no intermediate pixel-wise volume is stored. The
    classic fixed-window trade-off: bigger windows are more reliable in weak texture and
    fatten foreground objects at depth edges (Scharstein & Szeliski 2002, §5). Followed
    directly by ``wta`` (no aggregation), the pipeline fuses cost and WTA and never stores the
    volume (same output, several times faster; see :mod:`stereocli.matching.pipeline`).
    """
    _windowed_truncated_ad(state, p)


@dataclass(frozen=True)
class STADParams:
    window: tuple[int, int] = param((9, 9), "window (height, width), odd", unit="px", low=1, high=101)
    truncate: float = param(20.0, "per-pixel truncation of |L − R| before summing", unit="grey levels", low=1, high=255)

    def __post_init__(self):
        check_odd_window("cost.window", self.window)


@register("cost", "stad", STADParams, traits=StageTraits(fused_wta=_windowed_truncated_ad_wta))
def stad_cost(state: MatchState, p: STADParams) -> None:
    """Sum of truncated absolute differences over a window (window mean), O(1) per entry.

    Truncating each pixel's difference limits the damage done by the part of the window that
    lies on another surface near depth edges (Scharstein & Szeliski 2002, §3.1).
    """
    _windowed_truncated_ad(state, p)


@dataclass(frozen=True)
class SSDParams:
    window: tuple[int, int] = param((9, 9), "window (height, width), odd", unit="px", low=1, high=101)
    truncate: float = param(65025.0, "per-pixel truncation of (L − R)² before summing (65025 = none)",
                            unit="grey levels²", low=1, high=65025)

    def __post_init__(self):
        check_odd_window("cost.window", self.window)


@register("cost", "ssd", SSDParams)
def ssd_cost(state: MatchState, p: SSDParams) -> None:
    """Sum of squared differences over a window (window mean), O(1) per entry by running sums.

    The textbook area-based cost; with the ``shiftable`` aggregation it is the S&S
    "SSD + min filter" baseline (Scharstein & Szeliski 2002, §5.1).
    """
    state.cost_max = float(p.truncate)
    state.cost = kl.window_cost_volume(_channels(state.left), _channels(state.right), state.min_disp,
                                       state.ndisp, p.window[0] // 2, p.window[1] // 2, kl.MODE_SD,
                                       float(p.truncate), state.cost_max, _bands())


@dataclass(frozen=True)
class NCCParams:
    window: tuple[int, int] = param((9, 9), "window (height, width), odd", unit="px", low=3, high=101)

    def __post_init__(self):
        check_odd_window("cost.window", self.window)


def _ncc(state: MatchState, p: NCCParams, zero_mean: bool) -> None:
    left, right = _channels(state.left), _channels(state.right)
    ry, rx = p.window[0] // 2, p.window[1] // 2
    prod = kl.window_cost_volume(left, right, state.min_disp, state.ndisp, ry, rx, kl.MODE_PRODUCT,
                                 0.0, 0.0, _bands())
    mean_l = box_mean_image(left, ry, rx).reshape(left.shape)
    mean_r = box_mean_image(right, ry, rx).reshape(right.shape)
    sq_l = box_mean_image(np.einsum("ijc,ijc->ij", left, left), ry, rx)
    sq_r = box_mean_image(np.einsum("ijc,ijc->ij", right, right), ry, rx)
    state.cost_max = 2.0
    state.cost = kl.ncc_from_means(prod, mean_l, mean_r, sq_l, sq_r, state.min_disp, zero_mean, 2.0)


@register("cost", "ncc", NCCParams)
def ncc_cost(state: MatchState, p: NCCParams) -> None:
    """1 − normalised cross-correlation over a window (colour: the channels form one vector).

    NCC = Σ L·R / √(Σ L² · Σ R²) is invariant to a gain change between the views, not to an
    offset; window sums by running sums. Range [0, 2] (0 = perfect match); flat windows get 1.
    """
    _ncc(state, p, False)


@register("cost", "zncc", NCCParams)
def zncc_cost(state: MatchState, p: NCCParams) -> None:
    """1 − zero-mean normalised cross-correlation over a window (gain- and offset-invariant).

    ZNCC subtracts each window's mean (per channel) before correlating, so it tolerates
    affine radiometric differences; it is slower than SAD and blurs depth edges like any
    fixed window. Computed from running-sum window means of L·R, L, R, L², R². Range [0, 2].
    """
    _ncc(state, p, True)


# --- gradient costs -----------------------------------------------------------------------


def _gradients(image: np.ndarray, both: bool) -> np.ndarray:
    """Central-difference derivatives per channel, (H, W, C) or (H, W, 2C) float32."""
    img = _channels(image)
    gx = cv2.Sobel(img, cv2.CV_32F, 1, 0, ksize=1, scale=0.5, borderType=cv2.BORDER_REPLICATE)
    gx = gx.reshape(img.shape)
    if not both:
        return np.ascontiguousarray(gx)
    gy = cv2.Sobel(img, cv2.CV_32F, 0, 1, ksize=1, scale=0.5, borderType=cv2.BORDER_REPLICATE).reshape(img.shape)
    return np.ascontiguousarray(np.concatenate([gx, gy], axis=2))


@dataclass(frozen=True)
class GradientParams:
    direction: str = param("xy", "derivatives compared: x only, or x and y", choices=("x", "xy"))
    truncate: float = param(255.0, "truncation of the mean absolute gradient difference (255 = none)",
                            unit="grey levels/px", low=0.1, high=255)


@register("cost", "gradient", GradientParams)
def gradient_cost(state: MatchState, p: GradientParams) -> None:
    """Absolute differences of image gradients (central differences), mean over channels.

    Insensitive to an intensity offset between the views and sharp at edges, but noisy in flat
    regions (Scharstein & Szeliski 2002, §3.1; Klaus et al. 2006).
    """
    both = p.direction == "xy"
    gl, gr = _gradients(state.left, both), _gradients(state.right, both)
    state.cost_max = float(p.truncate)
    state.cost = kl.pixel_cost_volume(gl, gr, state.min_disp, state.ndisp, kl.MODE_AD,
                                      float(p.truncate), state.cost_max)


@dataclass(frozen=True)
class ColorGradientParams:
    alpha: float = param(0.9, "weight of the gradient term (0 = colour only, 1 = gradient only)", low=0.0, high=1.0)
    tau_color: float = param(7.0, "truncation of the colour term", unit="grey levels", low=0.1, high=255)
    tau_gradient: float = param(2.0, "truncation of the gradient term", unit="grey levels/px", low=0.1, high=255)


@register("cost", "color_gradient", ColorGradientParams)
def color_gradient_cost(state: MatchState, p: ColorGradientParams) -> None:
    """Weighted colour + gradient cost: (1 − α)·min(AD, τ_c) + α·min(|∇x L − ∇x R|, τ_g).

    The cost of Hosni et al.'s cost-volume filtering (PAMI 2013, eq. 6; defaults α = 0.9,
    τ_c = 7, τ_g = 2 grey levels, i.e. 7/255 and 2/255 on [0, 1] images): the truncated
    colour term keeps it discriminative, the x-gradient (of the grey image) adds robustness
    to illumination changes. Range [0, (1 − α)τ_c + ατ_g].
    """
    gl = _gradients(state.gray("left"), False)
    gr = _gradients(state.gray("right"), False)
    cmax = (1.0 - p.alpha) * p.tau_color + p.alpha * p.tau_gradient
    state.cost_max = float(cmax)
    state.cost = kl.color_gradient_volume(_channels(state.left), _channels(state.right), gl, gr,
                                          state.min_disp, state.ndisp, float(p.alpha),
                                          float(p.tau_color), float(p.tau_gradient), state.cost_max)


# --- sampling-insensitive ---------------------------------------------------------------


@dataclass(frozen=True)
class BTParams:
    truncate: float = param(255.0, "truncation of the dissimilarity (255 = none)", unit="grey levels", low=1, high=255)


@register("cost", "bt", BTParams)
def bt_cost(state: MatchState, p: BTParams) -> None:
    """Birchfield–Tomasi sampling-insensitive dissimilarity, mean over colour channels.

    Compares each pixel with the linearly interpolated other scanline within ±½ pixel, so
    image sampling does not create spurious costs at intensity edges (Birchfield & Tomasi,
    PAMI 1998). Costs about twice AD; the usual pixel cost for DP/SGM.
    """
    state.cost_max = float(p.truncate)
    state.cost = kl.bt_volume(_channels(state.left), _channels(state.right), state.min_disp,
                              state.ndisp, float(p.truncate), state.cost_max)


# --- non-parametric costs ------------------------------------------------------------------


@dataclass(frozen=True)
class CensusParams:
    window: tuple[int, int] = param((7, 9), "census window (height, width), odd; at most 65 pixels",
                                    unit="px", low=1, high=15)
    gamma_c: float = param(0.0, "colour-adaptive support: a bit weighs exp(−(Δ/γc)²), Δ the largest channel "
                           "difference between its neighbour and the centre in the left image; 0: every bit weighs 1 "
                           "(the Hamming distance)", unit="grey levels", low=0.0, high=1000.0)

    def __post_init__(self):
        check_odd_window("cost.window", self.window, 65)


def _census_weighted(params: CensusParams) -> bool:
    """with ``gamma_c`` > 0"""
    return params.gamma_c > 0


def _census_coarse(params: CensusParams) -> CensusParams:
    """plain distances at SGM's coarse level (weighted, it takes a third longer and its search
    windows leave the scores as they are)"""
    return replace(params, gamma_c=0.0)


def _census_strings(state: MatchState, window: tuple[int, int]) -> tuple[np.ndarray, np.ndarray]:
    """Census bit strings of the left and right grey images for a (height, width) window."""
    wh, ww = window
    return (kc.census_transform(np.ascontiguousarray(state.gray("left")), wh // 2, ww // 2),
            kc.census_transform(np.ascontiguousarray(state.gray("right")), wh // 2, ww // 2))


def _census_support(state: MatchState, p: CensusParams) -> tuple[tuple[np.ndarray, np.ndarray], float]:
    """``(support, cost_max)`` of the census distances: the bit weights of
    :func:`~stereocli.matching.kernels.census.support_planes` on the left image with ``gamma_c``
    > 0, else plain Hamming distances (range: the number of bits)."""
    wh, ww = p.window
    if p.gamma_c <= 0:
        return kc.NO_SUPPORT, float(wh * ww - 1)
    planes, scale, cost_max = kc.support_planes(state.left, wh // 2, ww // 2, float(p.gamma_c))
    return (planes, scale), float(cost_max)


def _census_windowed(state: MatchState, p: CensusParams, runs) -> tuple[np.ndarray, float]:
    """Census costs on the runs of a windowed SGM only (ragged uint8, see
    :func:`stereocli.matching.kernels.sgm_window.window_runs`), honouring ``right_valid``;
    returns ``(costs, cost_max)``."""
    left, right = _census_strings(state, p.window)
    support, cost_max = _census_support(state, p)
    valid = state.right_valid if state.right_valid is not None else np.zeros((0, 0), np.bool_)
    _, _, run_lo, run_hi, offset, n = runs
    return kc.hamming_runs(left, right, state.min_disp, cost_max, run_lo, run_hi, offset, n, valid, support), cost_max


# With ``state.wants.integer_cost`` the Hamming distances stay uint8 (1 byte per cell).
@register("cost", "census", CensusParams,
          traits=StageTraits(integer_cost_itemsize=1, windowed=_census_windowed, reads_left_colour=_census_weighted,
                             reads_right_colour=False, coarse_params=_census_coarse))
def census_cost(state: MatchState, p: CensusParams) -> None:
    """Hamming distance of census transforms (Zabih & Woodfill 1994) on the grey images.

    Each pixel becomes a bit string (neighbour darker than the centre); the cost is the
    popcount of the XOR. Robust to monotonic radiometric changes between the views; larger
    windows are more discriminative and slower. The default for SGM. Range [0, n − 1].

    With ``gamma_c`` > 0, each bit weighs by how close its neighbour's colour is to the
    centre's in the left image (adaptive support weights, Yoon & Kweon 2006, applied to the
    census bits). Where the window straddles a depth edge, the bits on the other surface
    count little, so the background beside an object is no longer matched at the object's
    disparity (foreground fattening). The weights are quantised to 0–7, and the weighted
    distance is scaled to the largest multiple of n − 1 that fits in a byte (240 for 5×5), so
    the costs stay uint8. A coarse-to-fine SGM's coarse level takes plain distances.
    """
    left, right = _census_strings(state, p.window)
    support, state.cost_max = _census_support(state, p)
    dtype = np.uint8 if state.wants.integer_cost else np.float32
    state.cost = kc.hamming_volume(left, right, state.min_disp, state.ndisp, state.cost_max, dtype, support)


@dataclass(frozen=True)
class RankParams:
    window: tuple[int, int] = param((7, 7), "rank-transform window (height, width), odd", unit="px", low=3, high=31)

    def __post_init__(self):
        check_odd_window("cost.window", self.window)


@register("cost", "rank", RankParams)
def rank_cost(state: MatchState, p: RankParams) -> None:
    """Absolute difference of rank transforms (Zabih & Woodfill 1994) on the grey images.

    Each pixel is replaced by the number of window pixels darker than it, which survives any
    monotonic intensity change; less discriminative than census (it keeps a count, not the
    pattern). Aggregate it (``box`` = the paper's SAD of ranks). Range [0, n − 1].
    """
    hh, hw = p.window[0] // 2, p.window[1] // 2
    rl = kl.rank_transform(np.ascontiguousarray(state.gray("left")), hh, hw)[..., None]
    rr = kl.rank_transform(np.ascontiguousarray(state.gray("right")), hh, hw)[..., None]
    n = p.window[0] * p.window[1]
    state.cost_max = float(n - 1)
    state.cost = kl.pixel_cost_volume(rl, rr, state.min_disp, state.ndisp, kl.MODE_AD, float(n), state.cost_max)


@dataclass(frozen=True)
class ADCensusParams:
    window: tuple[int, int] = param((7, 9), "census window (height, width), odd; at most 65 pixels",
                                    unit="px", low=1, high=15)
    lambda_ad: float = param(10.0, "AD scale λ_AD (higher = less weight to colour)",
                             unit="grey levels", low=0.1, high=1000)
    lambda_census: float = param(30.0, "census scale λ_census (higher = less weight to census)",
                                 unit="bits", low=0.1, high=1000)
    combine: str = param("exp", "exp: 2 − exp(−c_AD/λ_AD) − exp(−c_census/λ_census) (Mei et al.); sum: c_AD/λ_AD + "
                         "c_census/λ_census", choices=("exp", "sum"))

    def __post_init__(self):
        check_odd_window("cost.window", self.window, 65)


@register("cost", "ad_census", ADCensusParams)
def ad_census_cost(state: MatchState, p: ADCensusParams) -> None:
    """AD-census: AD (all colour channels) and census combined on a common scale.

    Mei et al. (ICCV Workshops 2011, eq. 1–3): ρ(c, λ) = 1 − exp(−c/λ) maps each cost to
    [0, 1) so neither dominates, then they are added (range [0, 2]); AD helps in repetitive
    structure, census in radiometric differences and weak texture. ``combine: sum`` gives the
    plain scaled sum (unbounded-ish: range [0, 255/λ_AD + (n − 1)/λ_census]), which keeps more
    contrast between large costs. Defaults: 9×7 census, λ_AD = 10, λ_census = 30 (the paper's).
    """
    wh, ww = p.window
    cl, cr = _census_strings(state, p.window)
    robust = p.combine == "exp"
    cmax = 2.0 if robust else 255.0 / p.lambda_ad + (wh * ww - 1) / p.lambda_census
    state.cost_max = float(cmax)
    state.cost = kl.ad_census_volume(_channels(state.left), _channels(state.right), cl, cr,
                                     state.min_disp, state.ndisp, float(p.lambda_ad),
                                     float(p.lambda_census), robust, state.cost_max)


@dataclass(frozen=True)
class OrdinalParams:
    window: tuple[int, int] = param((7, 7), "window (height, width), odd; at most 225 pixels",
                                    unit="px", low=3, high=15)

    def __post_init__(self):
        check_odd_window("cost.window", self.window, 225)


@register("cost", "ordinal", OrdinalParams)
def ordinal_cost(state: MatchState, p: OrdinalParams) -> None:
    """Bhat–Nayar ordinal measure: distance between the rank permutations of two windows.

    Bhat & Nayar (PAMI 1998): with s(i) the rank in the right window of the pixel ranked i in
    the left window, d_m = max_i #{j ≤ i : s(j) > i}; the cost is d_m/⌊n/2⌋ = (1 − κ)/2 in
    [0, 1]. Invariant to monotonic intensity changes and, unlike census/rank, not dominated by
    a few outlier pixels; O(n) per hypothesis, so slower than census (keep windows ≤ 9×9 for
    speed). Works on the grey images; window sums are inherent (no aggregation needed).
    """
    hh, hw = p.window[0] // 2, p.window[1] // 2
    order_l, rank_r = kl.ordinal_tables(np.ascontiguousarray(state.gray("left")),
                                        np.ascontiguousarray(state.gray("right")), hh, hw)
    state.cost_max = 1.0
    state.cost = kl.ordinal_volume(order_l, rank_r, state.min_disp, state.ndisp, 1.0)
