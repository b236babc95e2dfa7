"""Run a configured stage pipeline on one rectified pair.

Order: preprocess (whole image) → per row strip: cost → aggregation → optimizer → volume
refinements (``needs_cost``) → stitch → map refinements (whole image). With one strip (the
usual case when the volume fits the memory budget) this is the plain pipeline. Strip layout
depends only on the image size and the config, never on the thread or job count, so output is
deterministic.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np

from ..config import PipelineConfig
from ..errors import DataError, MemoryBudgetError
from .kernels.cost import mask_invalid_right
from .kernels.volume import wta_right
from .refine import clear_invalid_left
from .state import MatchState

GIB = 1024.0**3


@dataclass
class MatchResult:
    """Outputs of :func:`match_pair`."""

    disparity: np.ndarray  # (H, W) float32 px, left-referenced, +inf invalid
    disparity_right: np.ndarray | None = None  # (H, W) float32 px, right-referenced
    confidence: np.ndarray | None = None  # (H, W) float32 in [0, 1]
    timings: dict[str, float] = field(default_factory=dict)  # seconds per stage
    strips: int = 1
    memory_estimate_gb: float = 0.0


def volume_copies(config: PipelineConfig) -> float:
    """How many (H, W, D) float32 volumes the heaviest stage holds at once (incl. its input)."""
    calls = [config.cost, *config.aggregation, config.optimizer]
    return 1.0 + max(getattr(c.stage.func, "volume_copies", 1.0) for c in calls)


def estimate_memory(config: PipelineConfig, height: int, width: int, ndisp: int) -> float:
    """Estimated peak bytes for one strip of ``height`` rows (volumes + image-sized buffers)."""
    volume = float(height) * width * ndisp * 4
    images = float(height) * width * 4 * 24  # images, census strings, disparities, masks
    return volume * volume_copies(config) + images


def plan_strips(config: PipelineConfig, height: int, width: int, ndisp: int) -> list[tuple[int, int]]:
    """Row ranges ``[(y0, y1), ...]`` to process; raises :class:`MemoryBudgetError` if impossible."""
    rt = config.runtime
    budget = rt.memory_gb * GIB
    if rt.strip_rows == 0 and estimate_memory(config, height, width, ndisp) <= budget:
        return [(0, height)]
    rows = rt.strip_rows
    if rows == 0:
        per_row = estimate_memory(config, 1, width, ndisp)
        rows = int(budget // per_row) - 2 * rt.strip_overlap
        # Strip height is rounded down to a multiple of 16 so the plan is stable.
        rows = (rows // 16) * 16
    needed = estimate_memory(config, min(height, rows + 2 * rt.strip_overlap), width, ndisp)
    if rows < 16 or needed > budget:
        need_gb = estimate_memory(config, min(height, 16 + 2 * rt.strip_overlap), width, ndisp) / GIB
        raise MemoryBudgetError(
            f"{width}x{height} with ndisp={ndisp} needs at least {need_gb:.1f} GiB even in row strips "
            f"(budget runtime.memory_gb={rt.memory_gb:g}); lower ndisp, downscale, or raise the budget"
        )
    return [(y0, min(height, y0 + rows)) for y0 in range(0, height, rows)]


def _as_valid(mask: np.ndarray | None, shape: tuple[int, int], what: str) -> np.ndarray | None:
    if mask is None:
        return None
    if mask.shape[:2] != shape:
        raise DataError(f"{what} valid mask is {mask.shape[1]}x{mask.shape[0]}, image is {shape[1]}x{shape[0]}")
    return np.ascontiguousarray(mask > 0 if mask.dtype != bool else mask)


def match_pair(
    left: np.ndarray,
    right: np.ndarray,
    config: PipelineConfig,
    *,
    min_disp: int = 0,
    ndisp: int,
    left_valid: np.ndarray | None = None,
    right_valid: np.ndarray | None = None,
    want_right: bool = False,
    keep_invalid: bool = False,
) -> MatchResult:
    """Compute the left disparity map of a rectified pair.

    Parameters
    ----------
    left, right : (H, W) or (H, W, 3) arrays (uint8, uint16 or float32 in [0, 255]).
    config : validated pipeline configuration (:func:`stereocli.config.build_config`).
    min_disp, ndisp : search range ``[min_disp, min_disp + ndisp)`` in pixels.
    left_valid, right_valid : optional (H, W) masks of pixels that may be matched (e.g.
        rectification borders are invalid); invalid left pixels come out +inf.
    want_right : also return the right-view disparity.
    keep_invalid : skip ``fill`` stages so holes stay +inf.

    Returns
    -------
    MatchResult with float32 disparity (+inf invalid) and per-stage timings in seconds.
    """
    from ..io.images import to_float_image

    if left.shape != right.shape:
        raise DataError(f"left is {left.shape[1]}x{left.shape[0]}, right is {right.shape[1]}x{right.shape[0]}: sizes differ")
    if ndisp < 1:
        raise DataError(f"ndisp must be at least 1 (got {ndisp})")
    _set_threads(config.runtime.threads)
    shape = left.shape[:2]
    timings: dict[str, float] = {}
    refinements = [c for c in config.refinement if not (keep_invalid and c.stage.name == "fill")]
    want_right = want_right or any(c.stage.needs_right for c in refinements)
    state = MatchState(
        left=to_float_image(np.ascontiguousarray(left)),
        right=to_float_image(np.ascontiguousarray(right)),
        min_disp=int(min_disp),
        ndisp=int(ndisp),
        left_valid=_as_valid(left_valid, shape, "left"),
        right_valid=_as_valid(right_valid, shape, "right"),
        want_right=want_right,
        threads=config.runtime.threads,
    )
    for call in config.preprocess:
        _timed(timings, f"preprocess.{call.stage.name}", call.stage.func, state, call.params)

    strips = plan_strips(config, shape[0], shape[1], ndisp)
    volume_stages = [c for c in refinements if c.stage.needs_cost]
    map_stages = [c for c in refinements if not c.stage.needs_cost]
    disparity = np.empty(shape, np.float32)
    disparity_right = np.empty(shape, np.float32) if want_right else None
    confidence = None
    overlap = config.runtime.strip_overlap if len(strips) > 1 else 0
    for y0, y1 in strips:
        a, b = max(0, y0 - overlap), min(shape[0], y1 + overlap)
        sub = _strip_state(state, a, b)
        _run_volume_stages(sub, config, volume_stages, timings)
        keep = slice(y0 - a, y1 - a)
        disparity[y0:y1] = sub.disparity[keep]
        if want_right:
            disparity_right[y0:y1] = sub.disparity_right[keep]
        if sub.confidence is not None:
            if confidence is None:
                confidence = np.zeros(shape, np.float32)
            confidence[y0:y1] = sub.confidence[keep]
        state.extras.update(sub.extras)

    state.cost = None
    state.disparity, state.disparity_right, state.confidence = disparity, disparity_right, confidence
    for call in map_stages:
        _timed(timings, f"refinement.{call.stage.name}", call.stage.func, state, call.params)
    clear_invalid_left(state)
    return MatchResult(
        disparity=np.ascontiguousarray(state.disparity, dtype=np.float32),
        disparity_right=state.disparity_right,
        confidence=state.confidence,
        timings={k: round(v, 6) for k, v in timings.items()},
        strips=len(strips),
        memory_estimate_gb=estimate_memory(config, min(shape[0], strips[0][1] + 2 * overlap), shape[1], ndisp) / GIB,
    )


def _strip_state(state: MatchState, a: int, b: int) -> MatchState:
    if a == 0 and b == state.shape[0]:
        return MatchState(state.left, state.right, state.min_disp, state.ndisp, state.left_valid,
                          state.right_valid, want_right=state.want_right, threads=state.threads,
                          extras=state.extras)
    crop = lambda m: None if m is None else np.ascontiguousarray(m[a:b])  # noqa: E731
    return MatchState(crop(state.left), crop(state.right), state.min_disp, state.ndisp,
                      crop(state.left_valid), crop(state.right_valid), want_right=state.want_right,
                      row_offset=a, threads=state.threads, extras=dict(state.extras))


def _run_volume_stages(sub: MatchState, config: PipelineConfig, volume_stages, timings) -> None:
    call = config.cost
    _timed(timings, f"cost.{call.stage.name}", call.stage.func, sub, call.params)
    if sub.right_valid is not None:
        mask_invalid_right(sub.cost, sub.right_valid, sub.min_disp, np.float32(sub.cost_max))
    for call in config.aggregation:
        _timed(timings, f"aggregation.{call.stage.name}", call.stage.func, sub, call.params)
    call = config.optimizer
    _timed(timings, f"optimizer.{call.stage.name}", call.stage.func, sub, call.params)
    if sub.want_right and sub.disparity_right is None:
        t0 = time.perf_counter()
        sub.disparity_right = wta_right(sub.cost, sub.min_disp, np.float32(sub.cost_max))
        timings["optimizer.right_view"] = timings.get("optimizer.right_view", 0.0) + time.perf_counter() - t0
    for call in volume_stages:
        _timed(timings, f"refinement.{call.stage.name}", call.stage.func, sub, call.params)
    sub.cost = None


def _timed(timings: dict, key: str, func, state: MatchState, params) -> None:
    t0 = time.perf_counter()
    func(state, params)
    timings[key] = timings.get(key, 0.0) + time.perf_counter() - t0


def _set_threads(threads: int) -> None:
    if threads > 0:
        import numba

        numba.set_num_threads(min(threads, numba.config.NUMBA_NUM_THREADS))
