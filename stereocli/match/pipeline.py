"""Run a configured stage pipeline on one rectified pair.

Order: preprocess (whole image) → per row strip: cost → aggregation → optimizer → volume
refinements (``needs_cost``) → stitch → map refinements (whole image). With one strip (the
usual case when the volume fits the memory budget) this is the plain pipeline. Strip layout
depends only on the image size and the config, never on the thread or job count, so output is
deterministic.

The three phases are separate functions so a cluster can run one pair's strips on different
workers: :func:`prepare` (checks, preprocess, strip plan) → :func:`run_strip` per strip (pure:
a cropped state in, the kept rows out) → :func:`finish` (stitch in plan order, map
refinements). :func:`match_pair` is exactly these three in one process.

What the pipeline knows about a stage comes from its :class:`~stereocli.registry.StageTraits`
only; it never tests a stage's name.

Fused cost + WTA: a local pipeline ``cost → wta`` never needs the whole (H, W, D) volume, only
each pixel's winner. When :func:`fused_cost_wta` finds that the cost stage offers a fused
kernel (the ``fused_wta`` trait: ``sad``, ``stad``), there is no aggregation, the optimizer is
a plain winner-take-all (``winner_take_all``: ``wta``), no right-view disparity is wanted
(e.g. ``lr_check``) and every volume refinement (``needs_cost``) offers an ``on_winner_costs``
variant (``single_matching_phase``, ``subpixel``), the strip runs the fused kernel and those
variants instead (timing key ``cost.<name>+optimizer.wta``). Otherwise, e.g. with
``uniqueness`` or ``confidence`` in the list, it falls back to the volume path. Both paths
give bit-identical maps (``tests/test_fused_sad.py``); set :data:`FUSED` to False to force the
volume path. The memory estimate and strip plan ignore the fusion (they stay those of the
volume path, so the plan does not depend on it).

Integer winners: the volume refinements (``subpixel``) run before every map stage, so a map
stage sees sub-pixel maps. A stage that wants the optimizer's integer maps instead says so
with its ``keeps_integer`` trait (``lr_check`` with ``compare: integer``); the pipeline then copies ``disparity``/``disparity_right`` into
``integer_disparity``/``integer_disparity_right`` right after the optimizer, before the
volume refinements, and stitches them with the maps (two extra (H, W) float32 maps).
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field, replace
from typing import Callable

import numpy as np

from ..errors import DataError, MemoryBudgetError
from .config import PipelineConfig
from .cost import run_cost_stage
from .kernels.images import luma
from .kernels.winners import wta_right
from .refine import clear_invalid_left
from .state import MatchState, Wants
from .visibility import find_unmatched, keep_in_range

#: Use fused cost + WTA kernels when the pipeline allows it (False forces the volume path).
FUSED = True

#: The config of the pair being matched in this process, from :func:`prepare` to :func:`finish`.
_current_config: list = [None]

GIB = 1024.0**3
#: Interpreter, numpy/numba/OpenCV libraries and compiled kernels (measured RSS before matching).
RUNTIME_BASE = 0.35 * GIB


@dataclass
class MatchResult:
    """Outputs of :func:`match_pair`."""

    disparity: np.ndarray  # (H, W) float32 px, left-referenced, +inf invalid
    disparity_right: np.ndarray | None = None  # (H, W) float32 px, right-referenced
    confidence: np.ndarray | None = None  # (H, W) float32 in [0, 1]
    timings: dict[str, float] = field(default_factory=dict)  # seconds per stage
    strips: int = 1
    memory_estimate_gb: float = 0.0
    notes: dict = field(default_factory=dict)  # stage name -> facts a stage found (e.g. row_align's fit)
    #: pixels without a match (:meth:`~stereocli.match.visibility.Unmatched.counts`): invalid, or
    #: filled with their row's background, confidence 0
    unmatched: dict = field(default_factory=dict)


def volume_copies(config: PipelineConfig) -> float:
    """Peak number of (H, W, D) float32-sized volumes alive at once.

    Each stage's ``volume_copies`` trait gives the extra volumes it holds beside its input
    (float32 units, so a uint16 copy counts 0.5); undeclared, a cost stage (no input volume)
    counts 0 and the others 1. When the cost stage can leave an integer volume
    (``integer_cost_itemsize``: bytes per cell) and it goes straight to an optimizer that
    accepts one (``accepts_integer_cost``), that volume counts at its own size and the
    optimizer's extra is its ``integer_volume_copies``.
    """
    optimizer = config.optimizer.stage.traits
    itemsize = config.cost.stage.traits.integer_cost_itemsize
    if itemsize and not config.aggregation and optimizer.accepts_integer_cost:
        extra = optimizer.integer_volume_copies
        return itemsize / 4.0 + (extra if extra is not None else _extra_volumes(config.optimizer))
    return 1.0 + max(_extra_volumes(c) for c in [config.cost, *config.aggregation, config.optimizer])


def _extra_volumes(call) -> float:
    declared = call.stage.traits.volume_copies
    if declared is not None:
        return declared
    return 0.0 if call.stage.kind == "cost" else 1.0


def estimate_memory(config: PipelineConfig, height: int, width: int, ndisp: int) -> float:
    """Estimated peak bytes for one strip of ``height`` rows (volumes + image-sized buffers).

    An optimizer may add fixed per-strip buffers through its ``buffer_bytes`` trait (e.g.
    SGM's path-cost rows).
    """
    volume = float(height) * width * ndisp * 4
    images = float(height) * width * 4 * 24  # images, census strings, disparities, masks
    buffers = config.optimizer.stage.traits.buffer_bytes
    fixed = RUNTIME_BASE + (float(buffers(config.optimizer.params, width, ndisp)) if buffers else 0.0)
    return volume * volume_copies(config) + images + fixed


def plan_strips(config: PipelineConfig, height: int, width: int, ndisp: int) -> list[tuple[int, int]]:
    """Row ranges ``[(y0, y1), ...]`` to process; raises :class:`MemoryBudgetError` if impossible."""
    rt = config.runtime
    budget = rt.memory_gb * GIB
    if rt.strip_rows == 0 and estimate_memory(config, height, width, ndisp) <= budget:
        return [(0, height)]
    rows = rt.strip_rows
    if rows == 0:
        fixed = estimate_memory(config, 0, width, ndisp)
        per_row = estimate_memory(config, 1, width, ndisp) - fixed
        rows = int((budget - fixed) // per_row) - 2 * rt.strip_overlap
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


@dataclass
class PreparedPair:
    """A pair after preprocessing, with its strip plan (input of :func:`run_strip`/:func:`finish`)."""

    state: MatchState  # whole-image state after the preprocess stages
    strips: list[tuple[int, int]]  # kept row ranges [(y0, y1), ...]
    overlap: int  # context rows added above and below each strip
    keep_invalid: bool = False
    timings: dict[str, float] = field(default_factory=dict)  # preprocess seconds per stage
    #: (left, right, left_valid, right_valid) as given to :func:`prepare`, kept only when a map
    #: refinement ``needs_mirrored`` (the mirrored pair is made from them).
    inputs: tuple | None = None


@dataclass
class StripResult:
    """Products of the volume stages on one strip: only the kept rows ``[y0, y1)``."""

    y0: int
    y1: int
    disparity: np.ndarray  # (y1 - y0, W) px, +inf invalid
    disparity_right: np.ndarray | None = None
    confidence: np.ndarray | None = None
    integer_disparity: np.ndarray | None = None  # the optimizer's maps, if ``state.wants.integer_maps``
    integer_disparity_right: np.ndarray | None = None
    extras: dict = field(default_factory=dict)
    timings: dict[str, float] = field(default_factory=dict)


def _refinements(config: PipelineConfig, keep_invalid: bool) -> list:
    # --keep-invalid drops every hole-filling stage (the fills_holes trait).
    return [c for c in config.refinement if not (keep_invalid and c.stage.traits.fills_holes)]


def _keeps_integer(refinements: list) -> bool:
    """True when some refinement reads the optimizer's integer maps (its ``keeps_integer``
    trait says so for its params, e.g. ``lr_check`` with ``compare: integer``)."""
    return any(c.stage.traits.keeps_integer is not None and c.stage.traits.keeps_integer(c.params)
               for c in refinements)


def extend_rows_into_invalid(image: np.ndarray, valid: np.ndarray) -> None:
    """Give every pixel outside ``valid`` the value of the nearest valid pixel of its row, in place.

    ``image`` is (H, W) or (H, W, C) float32, ``valid`` (H, W) bool; rows without a valid pixel
    stay as they are. A rectified image's border outside the source is black; a matching window
    that reaches into it compares black with the other view's texture, and the true match of a
    pixel a few columns from the border loses to a wrong one. Extended rows make those windows
    behave like windows at the image's own edge (on a rectified Middlebury pair: Venus's
    nonocc bad 2.0 0.41 → 0.31 %). Pixels outside ``valid`` stay unmatched either way.
    """
    h, w = valid.shape
    if valid.all():
        return
    columns = np.arange(w)
    before = np.maximum.accumulate(np.where(valid, columns, -1), axis=1)  # last valid at or left of x
    after = np.minimum.accumulate(np.where(valid, columns, w)[:, ::-1], axis=1)[:, ::-1]  # first at or right
    use_after = (after < w) & ((before < 0) | (after - columns < columns - before))
    source = np.where(use_after, after, before)
    rows = (source >= 0).any(axis=1) & valid.any(axis=1)
    source = np.clip(source, 0, w - 1)
    image[rows] = image[np.nonzero(rows)[0][:, None], source[rows]]


def prepare(
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
    want_confidence: bool = False,
) -> PreparedPair:
    """Validate inputs, run the preprocess stages on the whole image and plan the row strips.

    Parameters are those of :func:`match_pair`. The strip plan depends only on the image size
    and ``config`` (never on threads or workers), so every executor stitches the same strips.
    """
    if left.shape != right.shape:
        raise DataError(f"left is {left.shape[1]}x{left.shape[0]}, right is {right.shape[1]}x{right.shape[0]}: sizes differ")
    if ndisp < 1:
        raise DataError(f"ndisp must be at least 1 (got {ndisp})")
    _set_threads(config.runtime.threads)
    _current_config[0] = config
    shape = left.shape[:2]
    timings: dict[str, float] = {}
    refinements = _refinements(config, keep_invalid)
    want_right = want_right or any(c.stage.traits.needs_right for c in refinements)
    calls = [*config.preprocess, config.cost, *config.aggregation, config.optimizer, *refinements]
    state = MatchState(
        left=_working_image(left, grey=not _reads_colour(calls, "left")),
        right=_working_image(right, grey=not _reads_colour(calls, "right")),
        min_disp=int(min_disp),
        ndisp=int(ndisp),
        left_valid=_as_valid(left_valid, shape, "left"),
        right_valid=_as_valid(right_valid, shape, "right"),
        wants=Wants(right=want_right, confidence=want_confidence, integer_maps=_keeps_integer(refinements)),
        threads=config.runtime.threads,
    )
    for image, valid in ((state.left, state.left_valid), (state.right, state.right_valid)):
        if valid is not None:
            extend_rows_into_invalid(image, valid)
    for call in config.preprocess:
        _timed(timings, f"preprocess.{call.stage.name}", call.stage.func, state, call.params)
    strips = plan_strips(config, shape[0], shape[1], ndisp)
    overlap = config.runtime.strip_overlap if len(strips) > 1 else 0
    mirrored = any(c.stage.traits.needs_mirrored for c in refinements)
    inputs = (left, right, left_valid, right_valid) if mirrored else None
    return PreparedPair(state, strips, overlap, keep_invalid, timings, inputs)


def _reads_colour(calls: list, side: str) -> bool:
    """Whether any of the stage ``calls`` that run reads the ``side`` ("left" or "right") view's
    colour channels (:attr:`~stereocli.registry.StageTraits.reads_left_colour`, ``reads_right_colour``:
    a flag or a predicate of the stage's params)."""
    for call in calls:
        reads = getattr(call.stage.traits, f"reads_{side}_colour")
        if reads(call.params) if callable(reads) else reads:
            return True
    return False


def _working_image(image: np.ndarray, grey: bool) -> np.ndarray:
    """An input view as the stages see it: float32 in [0, 255], or with ``grey`` its (H, W) luma
    (what ``state.gray`` would give), taken straight from 8-bit colours without their float
    copy. Grey views make preprocessing (``row_align``'s resampling) move one channel instead of
    three, and save the copy."""
    from ..io.images import to_float_image

    image = np.ascontiguousarray(image)
    if grey and image.ndim == 3:
        return luma(image if image.dtype == np.uint8 else to_float_image(image))
    return to_float_image(image)


def strip_input(prepared: PreparedPair, y0: int, y1: int) -> MatchState:
    """The state one strip's volume stages start from: rows ``[y0, y1)`` plus overlap context.

    A fresh state (cropped copies of the images and masks, its own ``extras`` dict), so it can
    be shipped to another process and run there with :func:`run_strip`.
    """
    state = prepared.state
    a, b = max(0, y0 - prepared.overlap), min(state.shape[0], y1 + prepared.overlap)
    return _strip_state(state, a, b)


def run_strip(sub: MatchState, config: PipelineConfig, y0: int, y1: int, *,
              keep_invalid: bool = False) -> StripResult:
    """Run cost → aggregation → optimizer → volume refinements on one strip state.

    ``sub`` comes from :func:`strip_input` (``sub.row_offset`` is its first image row); only
    the kept rows ``[y0, y1)`` are returned. A pure function of its arguments: running a strip
    in another process gives the same arrays.
    """
    _set_threads(config.runtime.threads)
    timings: dict[str, float] = {}
    volume_stages = [c for c in _refinements(config, keep_invalid) if c.stage.traits.needs_cost]
    _run_volume_stages(sub, config, volume_stages, timings)
    keep = slice(y0 - sub.row_offset, y1 - sub.row_offset)
    whole = keep.start == 0 and keep.stop == sub.shape[0]
    crop = lambda m: None if m is None else (m if whole else np.ascontiguousarray(m[keep]))  # noqa: E731
    return StripResult(y0, y1, crop(sub.disparity), crop(sub.disparity_right) if sub.wants.right else None,
                       crop(sub.confidence), crop(sub.integer_disparity), crop(sub.integer_disparity_right),
                       sub.extras, timings)


def finish(prepared: PreparedPair, results: list[StripResult], config: PipelineConfig) -> MatchResult:
    """Stitch strip results (in plan order) and run the whole-image refinements."""
    state = prepared.state
    shape = state.shape
    if [(r.y0, r.y1) for r in results] != list(prepared.strips):
        raise ValueError("strip results do not match the strip plan")
    timings = dict(prepared.timings)
    disparity = np.empty(shape, np.float32)
    disparity_right = np.empty(shape, np.float32) if state.wants.right else None
    confidence = None
    integer = {"integer_disparity": None, "integer_disparity_right": None}
    for r in results:
        disparity[r.y0:r.y1] = r.disparity
        if state.wants.right:
            disparity_right[r.y0:r.y1] = r.disparity_right
        for key in integer:
            part = getattr(r, key)
            if part is not None:
                if integer[key] is None:
                    integer[key] = np.empty(shape, np.float32)
                integer[key][r.y0:r.y1] = part
        if r.confidence is not None:
            if confidence is None:
                confidence = np.zeros(shape, np.float32)
            confidence[r.y0:r.y1] = r.confidence
        state.extras.update(r.extras)
        for key, seconds in r.timings.items():
            timings[key] = timings.get(key, 0.0) + seconds

    map_stages = [c for c in _refinements(config, prepared.keep_invalid) if not c.stage.traits.needs_cost]
    state.cost = None
    t0 = time.perf_counter()
    # Pixels without a match leave the map before any map stage reads it (visibility.py).
    disparity = keep_in_range(disparity, state.min_disp, state.ndisp)
    unmatched = find_unmatched(shape, state.min_disp, state.ndisp, state.left_valid, state.right_valid)
    disparity = np.where(unmatched.outside_views, np.float32(np.inf), disparity)
    # Pixels invalid at some point from here on, filled or not: their confidence is 0 (a map
    # stage may make the confidence map too).
    holes = ~np.isfinite(disparity)
    timings["unmatched"] = time.perf_counter() - t0
    state.disparity, state.disparity_right, state.confidence = disparity, disparity_right, confidence
    state.integer_disparity, state.integer_disparity_right = integer.values()
    for call in map_stages:
        if call.stage.traits.needs_mirrored:
            t0 = time.perf_counter()
            mirrored = mirrored_disparity(prepared, config, call)
            state.mirrored_disparity = _right_map_rows(state, mirrored, to_input=False)
            key = f"refinement.{call.stage.name}.mirrored_pair"
            timings[key] = timings.get(key, 0.0) + time.perf_counter() - t0
        _timed(timings, f"refinement.{call.stage.name}", call.stage.func, state, call.params)
        state.mirrored_disparity = None
        state.disparity = keep_in_range(state.disparity, state.min_disp, state.ndisp)
        holes |= ~np.isfinite(state.disparity)
    filled = any(c.stage.traits.fills_holes for c in map_stages)
    state.disparity = _settle_outside_views(state.disparity, unmatched.outside_views, filled)
    clear_invalid_left(state)
    if state.confidence is not None:
        state.confidence = np.where(holes | unmatched.outside_views | ~np.isfinite(state.disparity), np.float32(0),
                                    state.confidence).astype(np.float32)
    if state.disparity_right is not None:
        state.disparity_right = keep_in_range(state.disparity_right, state.min_disp, state.ndisp)
        # The right map was matched on ``state.right``, whose rows a preprocess stage may have moved.
        state.disparity_right = _right_map_rows(state, state.disparity_right, to_input=True)
    _current_config[0] = None
    strips, overlap = prepared.strips, prepared.overlap
    return MatchResult(
        disparity=np.ascontiguousarray(state.disparity, dtype=np.float32),
        disparity_right=state.disparity_right,
        confidence=state.confidence,
        timings={k: round(v, 6) for k, v in timings.items()},
        strips=len(strips),
        memory_estimate_gb=estimate_memory(config, min(shape[0], strips[0][1] + 2 * overlap), shape[1],
                                           state.ndisp) / GIB,
        notes=dict(state.notes),
        unmatched=unmatched.counts(),
    )


def _settle_outside_views(disparity: np.ndarray, outside: np.ndarray, filled: bool) -> np.ndarray:
    """``disparity`` with the pixels ``outside`` the views (:class:`~.visibility.Unmatched`)
    invalid, or, when a stage ``filled`` the map's holes, holding the nearest visible background
    of their row (the smaller of the nearest valid disparities on either side, as ``fill``
    gives): whatever the stages after the fill did to them."""
    if not outside.any():
        return disparity
    cleared = np.where(outside, np.float32(np.inf), disparity)
    if not filled:
        return cleared
    from .kernels.maps import fill_background

    return np.where(outside, fill_background(cleared), disparity).astype(np.float32)


def _right_map_rows(state: MatchState, right_map: np.ndarray, *, to_input: bool) -> np.ndarray:
    """A right-referenced map moved between the input right view's rows and those of
    ``state.right`` when a preprocess stage resampled them (``state.right_rows``): back to the
    input's (``to_input``, for the ``--right`` output), or onto ``state.right``'s (where the left
    map's matches read it). Unchanged when no stage moved the rows."""
    if state.right_rows is None:
        return right_map
    from ..features.vertical_offset import move_map_rows

    return move_map_rows(right_map, state.right_rows.reversed() if to_input else state.right_rows)


def mirrored_disparity(prepared: PreparedPair, config: PipelineConfig, call) -> np.ndarray:
    """The right-referenced map a ``needs_mirrored`` refinement ``call`` reads: every stage of
    ``config`` before ``call`` run on the mirrored pair (right image flipped left-right as the
    left, left image flipped as the right, masks likewise), flipped back.

    (H, W) float32 px, +inf invalid: at right-image column ``x`` the disparity ``d`` of the point
    seen at ``x + d`` in the left image. Mirroring keeps the disparity range, and the mirrored
    run sees each occlusion and each census window from the other side, so its errors are
    largely independent of the left map's. A preprocess stage with ``mirrored_params``
    (``row_align``) applies what it found on the pair instead of measuring the mirrored one."""
    left, right, left_valid, right_valid = prepared.inputs
    flip = lambda m: None if m is None else m[:, ::-1]  # noqa: E731
    before = config.refinement[:next(i for i, c in enumerate(config.refinement) if c is call)]
    # Preprocess stages that can repeat what they did to the pair (row_align's plane) do so
    # instead of measuring the mirrored pair again.
    notes = prepared.state.notes
    preprocess = [replace(c, params=c.stage.traits.mirrored_params(c.params, notes.get(c.stage.name)))
                  if c.stage.traits.mirrored_params else c for c in config.preprocess]
    saved = _current_config[0]
    try:
        result = match_pair(flip(right), flip(left), replace(config, preprocess=preprocess, refinement=before),
                            min_disp=prepared.state.min_disp, ndisp=prepared.state.ndisp,
                            left_valid=flip(right_valid), right_valid=flip(left_valid),
                            keep_invalid=prepared.keep_invalid)
    finally:
        _current_config[0] = saved
    return np.ascontiguousarray(result.disparity[:, ::-1])


StripMap = Callable[[PreparedPair, PipelineConfig], list[StripResult]]


def run_strips(prepared: PreparedPair, config: PipelineConfig) -> list[StripResult]:
    """All strips of a prepared pair, one after the other in this process (bounded memory:
    one strip's volumes at a time)."""
    return [run_strip(strip_input(prepared, y0, y1), config, y0, y1, keep_invalid=prepared.keep_invalid)
            for y0, y1 in prepared.strips]


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
    want_confidence: bool = False,
    strip_map: StripMap | None = None,
) -> MatchResult:
    """Compute the left disparity map of a rectified pair.

    Equivalent to ``finish(p, run_strips(p, config), config)`` with ``p = prepare(...)``.

    Parameters
    ----------
    left, right : (H, W) or (H, W, 3) arrays (uint8, uint16 or float32 in [0, 255]).
    config : validated pipeline configuration (:func:`stereocli.config.build_config`).
    min_disp, ndisp : search range ``[min_disp, min_disp + ndisp)`` in pixels.
    left_valid, right_valid : optional (H, W) masks of pixels that may be matched (e.g.
        rectification borders are invalid); invalid left pixels come out +inf.
    want_right : also return the right-view disparity.
    keep_invalid : skip ``fill`` stages so holes stay +inf.
    want_confidence : run the ``confidence`` stages (they are skipped otherwise, so a map
        nobody asked for costs nothing).
    strip_map : runs the strips of a prepared pair and returns their results in plan order
        (default :func:`run_strips`, in this process); e.g. spread over Dask workers by the
        jobs layer (:mod:`stereocli.jobs`). The output does not depend on it.

    Returns
    -------
    MatchResult with float32 disparity (+inf invalid) and per-stage timings in seconds.
    """
    try:
        prepared = prepare(left, right, config, min_disp=min_disp, ndisp=ndisp, left_valid=left_valid,
                           right_valid=right_valid, want_right=want_right, keep_invalid=keep_invalid,
                           want_confidence=want_confidence)
        results = (strip_map or run_strips)(prepared, config)
        return finish(prepared, results, config)
    finally:
        _current_config[0] = None


def _strip_state(state: MatchState, a: int, b: int) -> MatchState:
    # Each strip state gets its own Wants: the strip's volume stages set per-strip requests.
    wants = replace(state.wants)
    if a == 0 and b == state.shape[0]:
        return MatchState(state.left, state.right, state.min_disp, state.ndisp, state.left_valid,
                          state.right_valid, wants=wants, threads=state.threads, extras=state.extras,
                          gray_cache=state.gray_cache)
    crop = lambda m: None if m is None else np.ascontiguousarray(m[a:b])  # noqa: E731
    return MatchState(crop(state.left), crop(state.right), state.min_disp, state.ndisp,
                      crop(state.left_valid), crop(state.right_valid), wants=wants, row_offset=a,
                      threads=state.threads, extras=dict(state.extras))


def _stage_reads(call, what: str, state: MatchState | None) -> bool:
    # Whether a volume stage reads an optional part of ``winner`` that only a windowed SGM
    # keeps: ``needs_second_best`` (``winner.second``, the best cost beyond ±1 of the winner)
    # or ``needs_right_costs`` (``winner.costs_right``); without a state, any stage that may
    # read it counts.
    needs = getattr(call.stage.traits, what)
    return needs is not None and (state is None or needs(state, call.params))


def fused_cost_wta(config: PipelineConfig, volume_stages: list, want_right: bool,
                   state: MatchState | None = None) -> Callable | None:
    """The cost stage's fused cost + WTA function if this strip may skip the volume, else None.

    Conditions (module docstring): :data:`FUSED`, a ``fused_wta`` trait on the cost stage,
    no aggregation, a ``winner_take_all`` optimizer, no right-view disparity wanted, and an
    ``on_winner_costs`` variant on every volume refinement in ``volume_stages``, each stage at
    most once (the winner costs cover the hypotheses within 1 of the WTA winner: enough for one
    sub-pixel fit and any number of claim checks, not for a second fit around a moved value).
    """
    fused = config.cost.stage.traits.fused_wta
    names = [c.stage.name for c in volume_stages]
    if (not FUSED or fused is None or config.aggregation or not config.optimizer.stage.traits.winner_take_all
            or want_right or len(set(names)) != len(names)
            or any(c.stage.traits.on_winner_costs is None or _stage_reads(c, "needs_second_best", state)
                   for c in volume_stages)):
        return None
    return fused


def _run_volume_stages(sub: MatchState, config: PipelineConfig, volume_stages, timings) -> None:
    call = config.cost
    fused = fused_cost_wta(config, volume_stages, sub.wants.right, sub)
    if fused is not None:
        t0 = time.perf_counter()
        fused(sub, call.params, bool(volume_stages))  # winner costs only if a refinement reads them
        key = f"cost.{call.stage.name}+optimizer.wta"
        timings[key] = timings.get(key, 0.0) + time.perf_counter() - t0
        _keep_integer_maps(sub)
        for c in volume_stages:
            _timed(timings, f"refinement.{c.stage.name}", c.stage.traits.on_winner_costs, sub, c.params)
        sub.winner = None
        return
    optimizer = config.optimizer
    owns_cost = optimizer.stage.traits.runs_cost
    # A cost stage may leave a uint8/uint16 volume when its consumer says it accepts one.
    sub.wants.integer_cost = not config.aggregation and optimizer.stage.traits.accepts_integer_cost
    # An optimizer that owns the cost computation (coarse-to-fine SGM: on its windows only)
    # gets the cost stage as an argument and, when its params say so, runs it itself; it then
    # honours ``right_valid`` too. Aggregation stages need the whole volume, so with them the
    # cost stage always runs here.
    if config.aggregation or owns_cost is None or not owns_cost(optimizer.params):
        _timed(timings, f"cost.{call.stage.name}", run_cost_stage, sub, call)
    for call in config.aggregation:
        _timed(timings, f"aggregation.{call.stage.name}", call.stage.func, sub, call.params)
    # An optimizer that never builds the whole volume (SGM's coarse-to-fine search) leaves
    # ``winner`` instead when every volume refinement can work from it.
    sub.wants.volume = any(c.stage.traits.on_winner_costs is None for c in volume_stages)
    sub.wants.second_best = any(_stage_reads(c, "needs_second_best", sub) for c in volume_stages)
    sub.wants.right_costs = sub.wants.right and any(_stage_reads(c, "needs_right_costs", sub)
                                                    for c in volume_stages)
    t0 = time.perf_counter()
    if owns_cost is None:
        optimizer.stage.func(sub, optimizer.params)
    else:
        optimizer.stage.func(sub, optimizer.params, cost=config.cost)
    key = f"optimizer.{optimizer.stage.name}"
    timings[key] = timings.get(key, 0.0) + time.perf_counter() - t0
    if sub.wants.right and sub.disparity_right is None:
        t0 = time.perf_counter()
        sub.disparity_right = wta_right(sub.cost, sub.min_disp, np.float32(sub.cost_max))
        timings["optimizer.right_view"] = timings.get("optimizer.right_view", 0.0) + time.perf_counter() - t0
    _keep_integer_maps(sub)
    on_winner = sub.cost is None and sub.winner is not None
    for call in volume_stages:
        func = call.stage.traits.on_winner_costs if on_winner else call.stage.func
        _timed(timings, f"refinement.{call.stage.name}", func, sub, call.params)
    sub.cost = None
    sub.winner = None


def _keep_integer_maps(sub: MatchState) -> None:
    if sub.wants.integer_maps:  # copies: the volume refinements may edit the maps in place
        sub.integer_disparity = sub.disparity.copy()
        if sub.disparity_right is not None:
            sub.integer_disparity_right = sub.disparity_right.copy()


def _timed(timings: dict, key: str, func, state: MatchState, params) -> None:
    t0 = time.perf_counter()
    func(state, params)
    timings[key] = timings.get(key, 0.0) + time.perf_counter() - t0


def current_config() -> PipelineConfig | None:
    """The config of the pair being matched in this process (between :func:`prepare` and the end
    of :func:`finish`), else None: what the command line warms up when a kernel has to compile."""
    return _current_config[0]


def _set_threads(threads: int) -> None:
    from .kernels import set_threads

    set_threads(threads)  # also numba's, for its prange kernels, once numba has started
