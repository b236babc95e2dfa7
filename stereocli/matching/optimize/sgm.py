"""Semi-global matching (Hirschmüller 2008): the default optimizer.

Full-range search (``coarse: false``): the cost volume is quantised to uint8 (uint16 when a
finer scale is needed), the float volume is released, and the path costs of 2, 4, 8 or 16
directions are summed into a uint16 volume ``S`` that replaces ``state.cost`` (so sub-pixel
fitting, uniqueness, confidence and the right-view disparity work on the optimised costs).
Peak memory is about ``H·W·D·5`` bytes for float costs (the float volume plus the uint8 copy
while quantising; afterwards the uint8 copy plus the uint16 sums), ``H·W·D·3`` for integer
costs such as census (used as they are, no copy), plus ``O(W·D)`` row buffers
(``buffer_bytes``).

Coarse-to-fine search (``coarse: true``, the default preset): the same SGM over the full range
at half resolution (:func:`coarse_disparity`) sets each pixel's window of hypotheses
(:func:`search_windows`); the costs are computed on the windows only (the cost stage's
``windowed`` kernel, else gathered from its dense volume) and a windowed SGM
(:mod:`stereocli.matching.kernels.sgm_window`) runs on them. It leaves
:class:`~stereocli.matching.state.WinnerCosts` (the sums around each winner, both views, and the
second-best sum when a stage reads it) instead of a volume, or the sums expanded to a dense
volume when a later stage needs one. Memory and time scale with the windows (about a fifth
of H·W·D on MiddEval3).
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from typing import Callable

import numpy as np

from ...errors import ConfigError
from ...registry import StageTraits, param, register
from ..cost import run_cost_stage
from ..kernels import sgm as ks
from ..kernels import sgm_window as kw
from ..kernels.images import half_resolution
from ..kernels.maps import lr_check
from ..state import MatchState, Wants, WinnerCosts, required

#: Largest value of the aggregated volume (``state.cost_max`` after SGM); sums stay below it.
S_MAX = 65535
#: Most disparities the kernels handle (the winner's index is packed in 16 bits).
MAX_NDISP = 65535
#: ``f(state, params, cost) -> disparities``: a coarse-to-fine search's coarse level, as
#: :func:`coarse_disparity` computes it.
CoarseLevel = Callable[[MatchState, "SGMParams", object], np.ndarray]


@dataclass(frozen=True)
class SGMParams:
    paths: int = param(8, "number of path directions: 2 = scanlines only (fast, streaky), 4, 8, 16",
                       choices=(2, 4, 8, 16))
    p1: float = param(0.33, "penalty for a 1-px disparity change, as a fraction of the cost's range (cost_max)",
                      unit="× cost_max", low=0.0, high=10.0)
    p2: float = param(1.75, "penalty for larger disparity jumps, as a fraction of cost_max (clamped to ≥ p1)",
                      unit="× cost_max", low=0.0, high=20.0)
    p2_gamma: float = param(16.0, "adaptive P2 = max(P1, P2·γ/(γ+|ΔI|)) from the left image gradient along the path; "
                            "0 = constant P2", unit="grey levels", low=0.0, high=1000.0)
    levels: int = param(255, "quantisation levels for the matching costs (255 keeps them in uint8)", low=15, high=4095)
    coarse: bool = param(False, "coarse-to-fine search: a full-range SGM at half resolution sets each pixel's "
                         "hypotheses")
    margin: int = param(3, "coarse-to-fine: hypotheses beyond the coarse neighbourhood's range, each side",
                        unit="px", low=0, high=64)
    radius: int = param(3, "coarse-to-fine: neighbourhood radius at the coarse level", unit="coarse px", low=0, high=8)
    max_window: int = param(0, "coarse-to-fine: most hypotheses per pixel (0 = as the neighbourhood needs)",
                            low=0, high=4096)
    align: int = param(8, "coarse-to-fine: the kernel computes each window within a run of hypotheses on this grid "
                       "(whole vector loops; same result)", low=1, high=64)
    coarse_paths: int = param(0, "coarse-to-fine: path directions at the coarse level (0 = paths)",
                              choices=(0, 2, 4, 8, 16))
    coarse_min_ndisp: int = param(0, "coarse-to-fine only for ranges of more disparities than this (a narrow range "
                                  "leaves the windows little to cut, and the full-range search is then faster)",
                                  low=0, high=4096)
    coarse_min_volume: float = param(0.0, "coarse-to-fine only for cost volumes of more than this many million cells "
                                     "(H·W·D): on a small volume the coarse level costs more than the windows save, "
                                     "and the full-range search is faster", unit="M cells", low=0.0, high=1e6)
    coarse_levels: int = param(1, "coarse-to-fine: coarser levels below full resolution (each halves the image; only "
                               "the coarsest searches the full range)", low=1, high=4)
    coarse_max_volume: float = param(16.0, "coarse-to-fine: a level below full resolution searches its full range only "
                                     "up to this many million cells (H·W·D at that level); a larger one searches "
                                     "coarse to fine again, one level down (0: coarse_levels alone decides)",
                                     unit="M cells", low=0.0, high=1e6)


def quantization(cost_max: float, paths: int, p1: float, p2: float, levels: int) -> tuple[float, int, int, int]:
    """Scale, cap and integer penalties for quantising a cost volume.

    Costs in ``[0, cost_max]`` map to ``[0, cap]`` with ``cap ≤ levels``; the penalties are
    fractions of ``cost_max``. The scale is reduced if needed so ``paths · (cap + P2) ≤ 65534``,
    which bounds the uint16 path sums (see :mod:`stereocli.matching.kernels.sgm`).
    """
    cmax = cost_max if cost_max > 0 else 1.0
    p2 = max(p2, p1)
    # uint16 sums (paths · (cap + P2) ≤ 65534) and int16 path costs (cap + 3·P2 ≤ 32767).
    levels = min(levels, int(65534 // (paths * (1.0 + p2))), int(32767 // (1.0 + 3.0 * p2)))
    scale = levels / cmax
    cap = int(round(cost_max * scale)) if cost_max > 0 else levels
    return scale, max(cap, 1), int(round(p1 * levels)), int(round(p2 * levels))


#: The coarse level searches a range of a multiple of this many hypotheses (extended beyond
#: the far end). The full-range kernel's vector loops then run whole: an odd tail runs scalar
#: (at D/2 = 31, Shelves' coarse level, a tail of 15 beside 16 vector lanes). The windows clip
#: the extra hypotheses away; MiddEval3 scores move by at most 0.06 per scene.
COARSE_RANGE_STEP = 8


def coarse_range(min_disp: int, ndisp: int) -> tuple[int, int]:
    """``(min_disp, ndisp)`` of the level below, in its px: the range halved and its count rounded
    up to ``COARSE_RANGE_STEP`` hypotheses (extended beyond the far end)."""
    lo_d = int(np.floor(min_disp / 2))
    hi_d = int(np.ceil((min_disp + ndisp - 1) / 2))
    return lo_d, -(-(hi_d - lo_d + 1) // COARSE_RANGE_STEP) * COARSE_RANGE_STEP


def coarse_disparity(state: MatchState, p: SGMParams, cost) -> np.ndarray:
    """Left disparities of the pair at half resolution (full range, rounded up to
    ``COARSE_RANGE_STEP`` hypotheses; same cost and SGM), LR checked (±1 coarse px);
    (ceil(H/2), ceil(W/2)) float32 in coarse px, +inf where rejected. ``cost`` is the configured
    cost StageCall, run on the half-resolution images."""

    def half(img: np.ndarray) -> np.ndarray:
        out = half_resolution(np.ascontiguousarray(img, dtype=np.float32))
        return out[..., 0] if img.ndim == 2 else out

    def half_mask(mask):
        return None if mask is None else half(mask.astype(np.float32)) > 0.999

    lo_d, nd_d = coarse_range(state.min_disp, state.ndisp)
    image_rows = -(-state.image_shape[0] // 2)
    sub = MatchState(half(state.left), half(state.right), lo_d, nd_d, half_mask(state.left_valid),
                     half_mask(state.right_valid),
                     wants=Wants(right=True, integer_cost=state.wants.integer_cost, volume=False),
                     image_rows=image_rows)
    # run_sgm computes this level's costs itself (windowed if it searches coarse to fine again,
    # else the full range) and only its winners are read here.
    coarse_params = cost.stage.traits.coarse_params
    if coarse_params is not None:
        cost = replace(cost, params=coarse_params(cost.params))
    # A large pair's half-resolution volume is itself searched coarse to fine, so the full-range
    # search (the largest volume of the search, and most of its time) stays small on any pair.
    coarse = _searches_level_coarse_to_fine(p, p.coarse_levels, image_rows, sub.shape[1], sub.ndisp)
    run_sgm(sub, replace(p, paths=p.coarse_paths or p.paths, coarse_levels=max(p.coarse_levels - 1, 1)), cost,
            coarse=coarse)
    # run_sgm sets both maps (the coarse state wants the right view).
    return lr_check(required(sub.disparity, "optimizer.sgm: the coarse level left no disparity map"),
                    required(sub.disparity_right, "optimizer.sgm: the coarse level left no right-view map"), 1.0)


def search_windows(coarse: np.ndarray, shape: tuple[int, int], min_disp: int, ndisp: int, margin: int,
                   radius: int, max_window: int) -> tuple[np.ndarray, np.ndarray]:
    """Per-pixel hypothesis windows ``[lo, hi)`` (volume indices, (H, W) int32) from coarse
    disparities: the range of the valid coarse disparities within ``radius`` coarse pixels,
    doubled, plus ``margin`` px each side; the full range where none is valid."""
    h, w = shape
    nmin, nmax = kw.square_min_max(np.ascontiguousarray(coarse, dtype=np.float32), int(radius))
    lo, hi = kw.upsample_windows(nmin, nmax, h, w, int(min_disp), int(ndisp), int(margin))
    if max_window > 0:
        wide = hi - lo > max_window
        own = np.repeat(np.repeat(coarse, 2, 0), 2, 1)[:h, :w]
        centre = np.where(np.isfinite(own), 2 * own - min_disp, (lo + hi) // 2)
        start = np.clip(centre - max_window // 2, 0, max(ndisp - max_window, 0)).astype(np.int32)
        lo = np.where(wide, start, lo).astype(np.int32)
        hi = np.where(wide, np.minimum(start + max_window, ndisp), hi).astype(np.int32)
    return lo, hi


def _integer_costs(cost_max: float, dtype, p: SGMParams) -> tuple[int, float, int, int] | None:
    """``(mul, scale, p1, p2)`` when integer costs (e.g. census Hamming distances) can be
    used as they are, times an integer factor inside the kernel (no quantised copy); else None."""
    scale, cap, p1, p2 = quantization(cost_max, p.paths, p.p1, p.p2, p.levels)
    mul = int(scale)
    if dtype not in (np.uint8, np.uint16) or mul < 1:
        return None
    cap = int(round(cost_max)) * mul  # the largest cost as the kernel reads it
    return mul, float(mul), int(round(p.p1 * cap)), int(round(max(p.p2, p.p1) * cap))


def _quantized(state: MatchState, p: SGMParams) -> tuple[np.ndarray, int, float, int, int]:
    """``state.cost`` as integers for the kernels: ``(cq, mul, scale, p1, p2)``; releases the
    float volume (peak memory, see the module docstring)."""
    cost = required(state.cost, "optimizer.sgm: no cost volume")  # (never: both callers run the cost stage first)
    exact = _integer_costs(state.cost_max, cost.dtype, p)
    if exact is not None:
        mul, scale, p1, p2 = exact
        cq = cost
    else:
        scale, cap, p1, p2 = quantization(state.cost_max, p.paths, p.p1, p.p2, p.levels)
        mul = 1
        cq = np.empty(cost.shape, np.uint8 if cap <= 255 else np.uint16)
        ks.quantize(np.asarray(cost, np.float32), scale, cap, cq)
    state.cost = None
    return cq, mul, scale, p1, p2


def _run_windowed(state: MatchState, p: SGMParams, cost, coarse_level: CoarseLevel | None = None) -> None:
    """Coarse-to-fine SGM: windows from the half-resolution disparities (``coarse_level``,
    default :func:`coarse_disparity`), costs on the windows only (the cost stage's ``windowed``
    kernel, else its dense volume gathered), windowed SGM. Leaves ``winner`` (or, if a later
    stage needs it, the dense sums in ``cost``)."""
    coarse = (coarse_level or coarse_disparity)(state, p, cost)
    lo, hi = search_windows(coarse, state.shape, state.min_disp, state.ndisp, p.margin, p.radius, p.max_window)
    runs = kw.window_runs(lo, hi, state.ndisp, p.align)
    windowed = cost.stage.traits.windowed
    exact = None
    if windowed is not None and state.cost is None:
        costs, state.cost_max = windowed(state, cost.params, runs)
        exact = _integer_costs(state.cost_max, costs.dtype, p)
    if exact is not None:
        mul, _, p1, p2 = exact
    else:
        if state.cost is None:  # the pipeline left the cost to this stage
            run_cost_stage(state, cost)
        cq, mul, _, p1, p2 = _quantized(state, p)
        costs = kw.gather_runs(cq, runs[2], runs[3], runs[4], runs[5])
        del cq
    guide = np.ascontiguousarray(state.gray("left"), dtype=np.float32)
    run = kw.sgm_window(costs, runs, state.ndisp, guide, p.paths, p1, p2, float(p.p2_gamma), state.min_disp,
                        state.wants.right, state.wants.second_best, cost_mul=mul,
                        want_right_costs=state.wants.right_costs)
    del costs
    state.cost_max = float(S_MAX)
    state.disparity = run["disparity"]
    if state.wants.right:
        state.disparity_right = run["disparity_right"]
    if state.wants.volume:
        state.cost = kw.expand_sums(run["total"], runs[4], runs[2], lo, hi, state.ndisp)
    else:
        state.winner = WinnerCosts(run["disparity"].copy(), run["costs"], run["costs_right"],
                                   None if run["disparity_right"] is None else run["disparity_right"].copy(),
                                   run["second"])


def run_sgm(state: MatchState, p: SGMParams, cost=None, coarse: bool | None = None,
            coarse_level: CoarseLevel | None = None) -> None:
    """Run SGM on ``state.cost``; sets ``disparity`` and replaces ``cost`` by the uint16 sums
    (coarse-to-fine: see :func:`_run_windowed`). ``cost``: the configured cost StageCall, which
    the coarse-to-fine search runs itself (without it, only ``state.cost`` is used);
    ``coarse_level``: what that search's coarse level gives instead of computing it."""
    h, w = state.image_shape  # a strip searches as the whole image does
    if (p.coarse if coarse is None else coarse) and cost is not None and _coarse_to_fine_pays(p, h, w, state.ndisp):
        _run_windowed(state, p, cost, coarse_level)
        return
    if state.cost is None and cost is not None:  # left to this stage (runs_cost, coarse level)
        run_cost_stage(state, cost)
    if state.cost is None:
        raise ConfigError("optimizer.sgm: no cost volume (the cost stage did not run)")
    cq, mul, _, p1, p2 = _quantized(state, p)
    guide = np.ascontiguousarray(state.gray("left"), dtype=np.float32)
    acc, state.disparity, right = ks.sgm_aggregate(cq, guide, p.paths, p1, p2, float(p.p2_gamma),
                                                   state.min_disp, state.wants.right, cost_mul=mul)
    if right is not None:
        state.disparity_right = right
    del cq
    state.cost = acc
    state.cost_max = float(S_MAX)


def _coarse_to_fine_pays(p: SGMParams, height: int, width: int, ndisp: int) -> bool:
    return ndisp > max(4, p.coarse_min_ndisp) and height * width * ndisp > p.coarse_min_volume * 1e6


def _small_twin(p: SGMParams, height: int, width: int, ndisp: int) -> SGMParams:
    """A tiny pair searches coarse to fine exactly when a ``height`` × ``width`` pair with
    ``ndisp`` disparities does (the windowed kernels are others than the full-range ones)."""
    if p.coarse and _coarse_to_fine_pays(p, height, width, ndisp):
        return replace(p, coarse_min_ndisp=0, coarse_min_volume=0.0)
    return replace(p, coarse=False)


def _buffer_bytes(p: SGMParams, width: int, ndisp: int) -> float:
    """Path-cost row buffers of each pass and row stripe: 3 rows × directions × (D + 2) int16
    (plus their minima and penalties)."""
    nk = len(ks.DOWN_DIRECTIONS[p.paths])
    return ks.STRIPES * (3 * width * nk * (ndisp + 2) * 2 + 4 * width * nk * 3)


#: Coarse-to-fine memory (the planner's :func:`_strip_bytes`): a windowed level holds on average
#: about ``WINDOW_ENTRIES + ndisp / WINDOW_ENTRIES_PER`` hypotheses per pixel (its windows rounded
#: out to the ``align`` grid: wider for wider ranges, whose slopes span more disparities within
#: a coarse neighbourhood), and ``WINDOW_PIXEL_BYTES`` per pixel beside them (windows, runs and
#: offsets, penalties, winners and their sums both views, the guide and the strip's views).
WINDOW_ENTRIES = 16
WINDOW_ENTRIES_PER = 16
WINDOW_PIXEL_BYTES = 100


def _level_bytes(p: SGMParams, height: int, width: int, ndisp: int, windowed: bool) -> float:
    """Peak bytes of one level of the search: windowed (uint8 costs and uint16 sums on each
    pixel's run) or over the full range (the uint8 cost volume and the uint16 sums)."""
    pixels = float(height) * width
    rows = _buffer_bytes(p, width, ndisp)
    if windowed:
        entries = min(ndisp, WINDOW_ENTRIES + ndisp / WINDOW_ENTRIES_PER)
        return pixels * (entries * 3 + WINDOW_PIXEL_BYTES) + rows
    return pixels * (ndisp * 3 + WINDOW_PIXEL_BYTES) + rows


def _strip_bytes(p: SGMParams, height: int, width: int, ndisp: int, image_rows: int) -> float | None:
    """Peak bytes of the coarse-to-fine search on a ``height`` × ``width`` strip of an image of
    ``image_rows`` rows (whose size decides the levels): its largest level (the levels run one
    after the other, each keeping only its disparities for the next); None for the full-range
    search, which the volume count covers."""
    if not (p.coarse and _coarse_to_fine_pays(p, image_rows, width, ndisp)):
        return None
    peak = 0.0
    levels = p.coarse_levels
    windowed = True
    while True:
        peak = max(peak, _level_bytes(p, height, width, ndisp, windowed))
        if not windowed:
            return peak
        # The next level down, as coarse_disparity makes it.
        height, image_rows, width = -(-height // 2), -(-image_rows // 2), -(-width // 2)
        ndisp = coarse_range(0, ndisp)[1]  # (a range from 0: the estimate knows no min_disp)
        windowed = _searches_level_coarse_to_fine(p, levels, image_rows, width, ndisp)
        levels = max(levels - 1, 1)


def _searches_level_coarse_to_fine(p: SGMParams, levels: int, image_rows: int, width: int, ndisp: int) -> bool:
    """Whether a level below full resolution (``levels``: p.coarse_levels left at the level
    above) searches coarse to fine again: asked for by ``coarse_levels``, or its full range
    larger than ``coarse_max_volume``; and only when that pays (:func:`_coarse_to_fine_pays`).
    Sizes are the whole image's at that level, so every strip of a pair searches alike."""
    too_large = 0 < p.coarse_max_volume * 1e6 < float(image_rows) * width * ndisp
    return (levels > 1 or too_large) and _coarse_to_fine_pays(p, image_rows, width, ndisp)


def _searches_coarse_to_fine(p: SGMParams) -> bool:
    """when coarse: true (it runs the cost stage at half resolution, then on its windows)"""
    return p.coarse


# Memory: the uint8 copy beside the float input (0.25 volumes; afterwards uint8 + 2 × uint16
# = 1.25 in total, the same peak; levels > 255 use a uint16 copy: 0.5). Integer costs
# (census) are used as they are: no float volume, no quantised copy, only the uint16 sums.
@register("optimizer", "sgm", SGMParams,
          traits=StageTraits(volume_copies=0.25, accepts_integer_cost=True, integer_volume_copies=0.5,
                             buffer_bytes=_buffer_bytes, strip_bytes=_strip_bytes, runs_cost=_searches_coarse_to_fine,
                             small_twin=_small_twin, takes_coarse_level=True, reads_left_colour=False,
                             reads_right_colour=False))
def sgm(state: MatchState, p: SGMParams, cost=None, coarse_level: CoarseLevel | None = None) -> None:
    """Semi-global matching: sum of 1-D smoothness-constrained path costs (Hirschmüller 2008).

    P1 penalises 1-px disparity steps (slanted surfaces), P2 larger jumps (discontinuities);
    P2 shrinks across strong intensity edges (``p2_gamma``) where depth edges are likely.
    Penalties are fractions of the cost's range, so one setting suits census, AD-census, BT or
    MI costs. Works for any disparity range (negative ``min_disp``, any ``ndisp``); the output
    is bit-identical for any thread count. Replaces the cost volume by the uint16 path sums.
    ``coarse: true`` searches coarse to fine: a full-range SGM at half resolution narrows each
    pixel's hypotheses to the range of its coarse neighbourhood (± ``margin``), which is
    faster and, on MiddEval3, as accurate (see the module docstring).
    """
    if state.ndisp > MAX_NDISP:
        raise ConfigError(f"optimizer.sgm: searches at most {MAX_NDISP} disparities (ndisp={state.ndisp}); "
                          "lower ndisp or choose another optimizer")
    run_sgm(state, p, cost, coarse_level=coarse_level)
