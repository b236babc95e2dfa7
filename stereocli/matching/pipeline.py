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
with its ``keeps_integer`` trait (``lr_check`` with ``compare: integer``); the pipeline then
copies ``disparity``/``disparity_right`` into ``integer_disparity``/``integer_disparity_right``
right after the optimizer, before the volume refinements, and stitches them with the maps (two
extra (H, W) float32 maps).
"""

from __future__ import annotations

import threading
import time
from dataclasses import dataclass, field, replace
from typing import Callable, Iterable, Iterator

import numpy as np

from ..errors import DataError, MemoryBudgetError
from .config import PipelineConfig
from .cost import run_cost_stage
from .kernels.images import luma
from .kernels.maps import holes_and_range
from .kernels.winners import wta_right
from .refine import clear_invalid_left
from .state import MatchState, Wants, required
from .visibility import find_unmatched, keep_in_range, range_bounds

#: Use fused cost + WTA kernels when the pipeline allows it (False forces the volume path).
FUSED = True

#: The config of the pair each thread is matching (thread id -> config), from :func:`prepare` to
#: :func:`finish`: one thread's call never sees or clears another's.
_current_config: dict[int, PipelineConfig] = {}

GIB = 1024.0**3
#: Interpreter, numpy/OpenCV libraries and compiled kernels: the RSS of ``stereocli match`` on a
#: tiny pair with the kernels built at install (numba's compiler, when a kernel must compile,
#: adds about 0.1 GiB: the warm-up compiles before a pair is planned).
RUNTIME_BASE = 0.08 * GIB
#: Bytes per pixel of a strip beside its search: the strip's maps (disparities both views,
#: confidence, the integer maps) and the volume refinements' work maps.
STRIP_MAP_BYTES = 24


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
    #: pixels without a match (:meth:`~stereocli.matching.visibility.Unmatched.counts`): invalid, or
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


def estimate_memory(config: PipelineConfig, height: int, width: int, ndisp: int, image_rows: int = 0) -> float:
    """Estimated peak bytes for one strip of ``height`` rows (volumes + image-sized buffers) of
    an image of ``image_rows`` rows (0: the strip is the image).

    An optimizer may add fixed per-strip buffers through its ``buffer_bytes`` trait (e.g.
    SGM's path-cost rows), or estimate its whole search itself (``strip_bytes``: a
    coarse-to-fine search holds windows, not volumes).
    """
    optimizer = config.optimizer.stage.traits
    own = _own_search_bytes(config, height, width, ndisp, image_rows)
    if own is not None:
        return RUNTIME_BASE + own + float(height) * width * STRIP_MAP_BYTES
    volume = float(height) * width * ndisp * 4
    images = float(height) * width * 4 * 24  # images, census strings, disparities, masks
    buffers = optimizer.buffer_bytes
    fixed = RUNTIME_BASE + (float(buffers(config.optimizer.params, width, ndisp)) if buffers else 0.0)
    return volume * volume_copies(config) + images + fixed


#: The largest coarse-to-fine search (its own estimate, ``strip_bytes``) a pair runs whole with
#: ``runtime.strip_rows`` 0: a larger pair runs in strips of :data:`AUTO_STRIP_ROWS` rows,
#: so the search's memory grows with the width, not with the whole image. Strip rows are matched
#: with ``runtime.strip_overlap`` rows of context each side (the price: those rows are matched
#: twice). MiddEval3 Q, KITTI and the other pairs up to about half a megapixel run whole.
WHOLE_SEARCH_BYTES = 128 * 2**20
AUTO_STRIP_ROWS = 192


def _own_search_bytes(config: PipelineConfig, height: int, width: int, ndisp: int,
                      image_rows: int = 0) -> float | None:
    """The optimizer's own estimate of its search on a strip (``strip_bytes``), or None."""
    estimate = config.optimizer.stage.traits.strip_bytes
    if estimate is None or config.aggregation:  # (aggregation stages hold whole volumes)
        return None
    return estimate(config.optimizer.params, height, width, ndisp, image_rows or height)


#: Extra (H, W) float32 maps of a preprocess or map stage whose ``map_copies`` trait is None.
MAP_COPIES = 3.0
#: Extra (H, W) float32 maps while :func:`extend_rows_into_invalid` runs on one view (int32
#: column indices and their comparisons).
EXTEND_COPIES = 7.0


@dataclass(frozen=True)
class ImageMemory:
    """Bytes of one pair's whole-image buffers: everything the planner counts beside a row
    strip's own (:func:`estimate_memory`). From :func:`image_memory`.

    ``inputs``: the arrays the caller holds during the match (decoded views, valid masks).
    ``beside``: the working views and the stitched maps, alive while the strips run (a pair
    matched whole has them in its one strip, whose image-sized buffers count them).
    ``mirrored``: a stage needs the mirrored run, whose strips run beside the pair's views and
    maps, with views and maps of their own.
    ``phases``: the largest of the phases that run on the whole image, inputs not included:
    preprocessing (the working views and the largest stage's maps) and the map refinements (the
    working views, the maps and the largest stage's maps).
    """

    inputs: float = 0.0
    beside: float = 0.0
    mirrored: bool = False
    phases: float = 0.0


def _map_copies(call) -> float:
    copies = call.stage.traits.map_copies
    return MAP_COPIES if copies is None else copies


def image_memory(config: PipelineConfig, height: int, width: int, *, input_bytes: float = 0.0,
                 colour: tuple[bool, bool] = (False, False), masks: bool = False, want_right: bool = False,
                 want_confidence: bool = False, keep_invalid: bool = False) -> ImageMemory:
    """The whole-image buffers of a ``height`` × ``width`` pair (:class:`ImageMemory`).

    ``input_bytes``: the inputs as the caller holds them (views and masks); ``colour``: whether
    the left and right views have colour channels; ``masks``: valid masks are given; the flags
    are those of :func:`match_pair`. Depends only on these and ``config``, like the strip plan.
    """
    plane = float(height) * width * 4  # one (H, W) float32 map
    refinements = _refinements(config, keep_invalid)
    calls = [*config.preprocess, config.cost, *config.aggregation, config.optimizer, *refinements]
    views = [plane * (3 if has_colour and _reads_colour(calls, side) else 1)
             for has_colour, side in zip(colour, ("left", "right"))]
    working = sum(views)
    channels = max(views) / plane  # a preprocess stage's maps count per channel of the views
    right = want_right or any(c.stage.traits.needs_right for c in refinements)
    maps = plane * (1 + right + want_confidence + (1 + right) * _keeps_integer(refinements))
    # Making a working view from 16-bit colours holds a float copy of it for a moment.
    preprocess = max([max(views), plane * EXTEND_COPIES * masks,
                      *(plane * channels * _map_copies(c) for c in config.preprocess)])
    map_stages = [c for c in refinements if not c.stage.traits.needs_cost]
    finishing = maps + max([0.0, *(plane * _map_copies(c) for c in map_stages)])
    return ImageMemory(inputs=float(input_bytes), beside=working + maps,
                       mirrored=any(c.stage.traits.needs_mirrored for c in map_stages),
                       phases=working + max(preprocess, finishing))


def _strip_rows(strips: list[tuple[int, int]], overlap: int, height: int) -> int:
    """Rows of the plan's largest strip state (kept rows and their context)."""
    if len(strips) == 1:
        return strips[0][1] - strips[0][0]
    return min(height, max(y1 - y0 for y0, y1 in strips) + 2 * overlap)


def planned_peak(config: PipelineConfig, height: int, width: int, ndisp: int, strips: list[tuple[int, int]],
                 images: ImageMemory | None = None) -> float:
    """Estimated peak bytes of matching a pair with the strip plan ``strips``: one strip's
    volumes (:func:`estimate_memory`, which counts the runtime), the inputs and the whole-image
    buffers (``images``, from :func:`image_memory`; None counts none)."""
    images = images or ImageMemory()
    rows = _strip_rows(strips, config.runtime.strip_overlap, height)
    beside = images.beside * ((len(strips) > 1) + images.mirrored)
    return images.inputs + max(estimate_memory(config, rows, width, ndisp, height) + beside,
                               RUNTIME_BASE + images.phases)


def plan_strips(config: PipelineConfig, height: int, width: int, ndisp: int,
                images: ImageMemory | None = None) -> list[tuple[int, int]]:
    """Row ranges ``[(y0, y1), ...]`` to process; raises :class:`MemoryBudgetError` if impossible.

    ``runtime.strip_rows`` 0 (automatic): a pair runs whole when it fits the budget, unless its
    optimizer estimates its own search (``strip_bytes``: the coarse-to-fine SGM) at more than
    :data:`WHOLE_SEARCH_BYTES`; then, and when the budget needs it, the pair runs in strips of
    :data:`AUTO_STRIP_ROWS` rows or of fewer. The budget counts the
    whole-image buffers ``images`` (:func:`image_memory`; None counts none) beside the strips'
    volumes.
    """
    rt = config.runtime
    budget = rt.memory_gb * GIB
    images = images or ImageMemory()
    whole = [(0, height)]
    rows = rt.strip_rows
    if rows == 0:
        search = _own_search_bytes(config, height, width, ndisp)
        if (search is None or search <= WHOLE_SEARCH_BYTES) and \
                planned_peak(config, height, width, ndisp, whole, images) <= budget:
            return whole
        most = height if search is None else min(height, AUTO_STRIP_ROWS)
        rows = _fitting_rows(config, height, width, ndisp, images, budget, most)
    strips = _row_strips(height, rows) if rows >= 16 else []
    if not strips or planned_peak(config, height, width, ndisp, strips, images) > budget:
        least = _row_strips(height, 16)
        need_gb = planned_peak(config, height, width, ndisp, least, images) / GIB
        floor_gb = planned_peak(config, height, width, 1, least, images) / GIB
        if floor_gb > rt.memory_gb:  # the image buffers alone, whatever the range
            raise MemoryBudgetError(
                f"{width}x{height} needs at least {need_gb:.1f} GiB even in row strips: its whole-image buffers "
                f"(views, working copies, disparity maps) take {floor_gb:.1f} GiB of runtime.memory_gb="
                f"{rt.memory_gb:g}; downscale the pair or raise the budget")
        raise MemoryBudgetError(
            f"{width}x{height} with ndisp={ndisp} needs at least {need_gb:.1f} GiB even in row strips "
            f"(budget runtime.memory_gb={rt.memory_gb:g}); lower ndisp, downscale, or raise the budget"
        )
    return strips


def _row_strips(height: int, rows: int) -> list[tuple[int, int]]:
    return [(y0, min(height, y0 + rows)) for y0 in range(0, height, rows)]


def _fitting_rows(config: PipelineConfig, height: int, width: int, ndisp: int, images: ImageMemory,
                  budget: float, most: int) -> int:
    """The most rows per strip, a multiple of 16 (so the plan is stable) up to ``most``, whose plan
    fits ``budget``; 0 when not even 16 do."""
    rows = 0
    for candidate in range(16, max(most, 16) + 1, 16):
        if planned_peak(config, height, width, ndisp, _row_strips(height, candidate), images) > budget:
            break
        rows = candidate
    return rows


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
    inputs: tuple[np.ndarray, np.ndarray, np.ndarray | None, np.ndarray | None] | None = None
    #: The whole-image buffers the strip plan counted (:func:`image_memory`).
    images: ImageMemory = field(default_factory=ImageMemory)


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
    columns = np.arange(w, dtype=np.int32)  # int32 indices: half the memory of the default int64
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
        raise DataError(f"left is {left.shape[1]}x{left.shape[0]}, right is {right.shape[1]}x{right.shape[0]}: "
                        "sizes differ")
    if ndisp < 1:
        raise DataError(f"ndisp must be at least 1 (got {ndisp})")
    shape = left.shape[:2]
    # Planned before any work, so a pair that cannot fit is refused before its buffers exist.
    masks = [m for m in (left_valid, right_valid) if m is not None]
    images = image_memory(config, shape[0], shape[1], input_bytes=sum(a.nbytes for a in (left, right, *masks)),
                          colour=(left.ndim == 3, right.ndim == 3), masks=bool(masks), want_right=want_right,
                          want_confidence=want_confidence, keep_invalid=keep_invalid)
    strips = plan_strips(config, shape[0], shape[1], ndisp, images)
    _set_threads(config.runtime.threads)
    _current_config[threading.get_ident()] = config
    timings: dict[str, float] = {}
    refinements = _refinements(config, keep_invalid)
    want_right = want_right or any(c.stage.traits.needs_right for c in refinements)
    calls = [*config.preprocess, config.cost, *config.aggregation, config.optimizer, *refinements]
    state = MatchState(
        left=working_image(left, grey=not _reads_colour(calls, "left")),
        right=working_image(right, grey=not _reads_colour(calls, "right")),
        min_disp=int(min_disp),
        ndisp=int(ndisp),
        left_valid=_as_valid(left_valid, shape, "left"),
        right_valid=_as_valid(right_valid, shape, "right"),
        wants=Wants(right=want_right, confidence=want_confidence, integer_maps=_keeps_integer(refinements)),
    )
    for image, valid in ((state.left, state.left_valid), (state.right, state.right_valid)):
        if valid is not None:
            extend_rows_into_invalid(image, valid)
    for call in config.preprocess:
        _timed(timings, f"preprocess.{call.stage.name}", call.stage.func, state, call.params)
    overlap = config.runtime.strip_overlap if len(strips) > 1 else 0
    mirrored = any(c.stage.traits.needs_mirrored for c in refinements)
    inputs = (left, right, left_valid, right_valid) if mirrored else None
    return PreparedPair(state, strips, overlap, keep_invalid, timings, inputs, images)


def _reads_colour(calls: list, side: str) -> bool:
    """Whether any of the stage ``calls`` that run reads the ``side`` ("left" or "right") view's
    colour channels (:attr:`~stereocli.registry.StageTraits.reads_left_colour`, ``reads_right_colour``:
    a flag or a predicate of the stage's params)."""
    for call in calls:
        reads = getattr(call.stage.traits, f"reads_{side}_colour")
        if reads(call.params) if callable(reads) else reads:
            return True
    return False


def working_image(image: np.ndarray, grey: bool) -> np.ndarray:
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

    A fresh state (cropped copies of the images and masks), so it can be shipped to another
    process and run there with :func:`run_strip`.
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
    # A copy: a row slice is a view, which would keep the context rows of every strip alive.
    crop = lambda m: None if m is None else (m if whole else m[keep].copy())  # noqa: E731
    disparity = required(sub.disparity, f"optimizer.{config.optimizer.stage.name}: left no disparity map")
    return StripResult(y0, y1, disparity if whole else disparity[keep].copy(),
                       crop(sub.disparity_right) if sub.wants.right else None,
                       crop(sub.confidence), crop(sub.integer_disparity), crop(sub.integer_disparity_right),
                       timings)


#: The maps of a :class:`StripResult` that :func:`finish` stitches (``confidence`` and the
#: integer maps only when a strip has them).
_STITCHED = ("disparity", "disparity_right", "confidence", "integer_disparity", "integer_disparity_right")


def finish(prepared: PreparedPair, results: Iterable[StripResult], config: PipelineConfig) -> MatchResult:
    """Stitch strip results (in plan order) and run the whole-image refinements.

    ``results`` may be an iterator: each strip's rows are copied into the whole maps as it
    comes, so strips made on demand are never all held at once. A plan of one strip takes its
    maps as they are (without a copy: the map stages may edit them). Pixels no right-view pixel
    can show leave the map before the map stages (:mod:`.visibility`), and every map stage's
    output is kept inside the searched range.
    """
    state = prepared.state
    shape = state.shape
    timings = dict(prepared.timings)
    maps: dict[str, np.ndarray | None] = dict.fromkeys(_STITCHED)
    plan = iter(prepared.strips)
    for result in results:
        if (result.y0, result.y1) != next(plan, None):
            raise ValueError("strip results do not match the strip plan")
        _stitch(maps, result, shape, state.wants.right)
        for key, seconds in result.timings.items():
            timings[key] = timings.get(key, 0.0) + seconds
    if next(plan, None) is not None:
        raise ValueError("strip results do not match the strip plan")

    map_stages = [c for c in _refinements(config, prepared.keep_invalid) if not c.stage.traits.needs_cost]
    state.cost = None
    t0 = time.perf_counter()
    # Pixels without a match leave the map before any map stage reads it (visibility.py).
    # (every strip result holds a disparity map, and a plan has strips)
    disparity = keep_in_range(required(maps["disparity"], "no strip results"), state.min_disp, state.ndisp)
    unmatched = find_unmatched(shape, state.min_disp, state.ndisp, state.left_valid, state.right_valid)
    disparity = np.where(unmatched.outside_views, np.float32(np.inf), disparity)
    # Pixels invalid at some point from here on, filled or not: their confidence is 0 (a map
    # stage may make the confidence map too).
    holes = ~np.isfinite(disparity)
    lo, hi = (float(bound) for bound in range_bounds(state.min_disp, state.ndisp))
    timings["unmatched"] = time.perf_counter() - t0
    state.disparity, state.disparity_right = disparity, maps["disparity_right"]
    state.confidence = maps["confidence"]
    state.integer_disparity, state.integer_disparity_right = maps["integer_disparity"], maps["integer_disparity_right"]
    # Only the state holds the maps now, so a map stage that replaces one frees it.
    del result, maps, disparity
    for call in map_stages:
        if call.stage.traits.needs_mirrored:
            t0 = time.perf_counter()
            mirrored = mirrored_disparity(prepared, config, call)
            state.mirrored_disparity = _right_map_rows(state, mirrored, to_input=False)
            key = f"refinement.{call.stage.name}.mirrored_pair"
            timings[key] = timings.get(key, 0.0) + time.perf_counter() - t0
        _timed(timings, f"refinement.{call.stage.name}", call.stage.func, state, call.params)
        state.mirrored_disparity = None
        # One compiled pass marks the new holes and finds values outside the range (rare: a
        # plane fit reaching beyond it), which only then are clamped.
        if holes_and_range(required(state.disparity, f"refinement.{call.stage.name}: left no disparity map"),
                           lo, hi, holes):
            state.disparity = keep_in_range(state.disparity, state.min_disp, state.ndisp)
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
    _current_config.pop(threading.get_ident(), None)
    strips = prepared.strips
    return MatchResult(
        disparity=np.ascontiguousarray(state.disparity, dtype=np.float32),
        disparity_right=state.disparity_right,
        confidence=state.confidence,
        timings={k: round(v, 6) for k, v in timings.items()},
        strips=len(strips),
        memory_estimate_gb=planned_peak(config, shape[0], shape[1], state.ndisp, strips, prepared.images) / GIB,
        notes=dict(state.notes),
        unmatched=unmatched.counts(),
    )


def _stitch(maps: dict, result: StripResult, shape: tuple[int, int], right: bool) -> None:
    """Copy a strip's maps into the whole maps of ``maps`` (made when first needed; taken as
    they are from a strip that is the whole image). ``right``: the right map is wanted."""
    for key in _STITCHED:
        part = getattr(result, key) if key != "disparity_right" or right else None
        if part is None:
            continue
        if (result.y0, result.y1) == (0, shape[0]) and _own_map(part, shape):
            maps[key] = part
            continue
        if maps[key] is None:  # confidence: zero where a strip has none
            maps[key] = np.zeros(shape, np.float32) if key == "confidence" else np.empty(shape, np.float32)
        maps[key][result.y0:result.y1] = part


def _own_map(part: np.ndarray, shape: tuple[int, int]) -> bool:
    """Whether a whole-image strip map can be the pair's map as it is (what a copy into a fresh
    float32 map would give)."""
    return part.shape == shape and part.dtype == np.float32 and part.flags.c_contiguous and part.flags.writeable
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
    from .vertical_offset import move_map_rows

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
    if prepared.inputs is None:  # (never: prepare keeps them when a map refinement needs_mirrored)
        raise RuntimeError(f"refinement.{call.stage.name}: the pair's inputs were not kept for the mirrored run")
    left, right, left_valid, right_valid = prepared.inputs
    flip = lambda m: None if m is None else m[:, ::-1]  # noqa: E731
    before = config.refinement[:next(i for i, c in enumerate(config.refinement) if c is call)]
    # Preprocess stages that can repeat what they did to the pair (row_align's plane) do so
    # instead of measuring the mirrored pair again.
    preprocess = preprocess_given(config, prepared.state.notes, "mirrored_params")
    # The pair's working views and maps stay alive beside the mirrored run: its budget is what
    # they leave (the inputs it shares with the pair it counts itself).
    runtime = replace(config.runtime, memory_gb=config.runtime.memory_gb - prepared.images.beside / GIB)
    saved = _current_config.get(threading.get_ident())
    try:
        result = match_pair(right[:, ::-1], left[:, ::-1],
                            replace(config, preprocess=preprocess, refinement=before, runtime=runtime),
                            min_disp=prepared.state.min_disp, ndisp=prepared.state.ndisp,
                            left_valid=flip(right_valid), right_valid=flip(left_valid),
                            keep_invalid=prepared.keep_invalid)
    finally:
        if saved is not None:
            _current_config[threading.get_ident()] = saved
    return np.ascontiguousarray(result.disparity[:, ::-1])


def preprocess_given(config: PipelineConfig, notes: dict, trait: str) -> list:
    """``config``'s preprocess calls, those with the ``trait`` (``mirrored_params`` or
    ``repeated_params``) given the params that repeat what they found on a pair (their note in
    ``notes``, a pair's ``state.notes``) instead of measuring again."""
    calls = []
    for call in config.preprocess:
        given = getattr(call.stage.traits, trait)
        calls.append(replace(call, params=given(call.params, notes.get(call.stage.name))) if given else call)
    return calls


StripMap = Callable[[PreparedPair, PipelineConfig], list[StripResult]]


def run_strips(prepared: PreparedPair, config: PipelineConfig) -> list[StripResult]:
    """All strips of a prepared pair, one after the other in this process (bounded memory:
    one strip's volumes at a time)."""
    return list(_strips_one_by_one(prepared, config))


def _popped(results: list) -> Iterator:
    """The items of ``results`` in order, each removed from the list as it is handed out."""
    results.reverse()
    while results:
        yield results.pop()


def _strips_one_by_one(prepared: PreparedPair, config: PipelineConfig) -> Iterator[StripResult]:
    # What :func:`match_pair` stitches by default: each strip is run when finish asks for it.
    for y0, y1 in prepared.strips:
        yield run_strip(strip_input(prepared, y0, y1), config, y0, y1, keep_invalid=prepared.keep_invalid)


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
    config : validated pipeline configuration (:func:`stereocli.matching.config.build_config`).
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
        results = (strip_map or _strips_one_by_one)(prepared, config)
        if isinstance(results, list):  # each result is dropped once stitched
            results = _popped(results)
        return finish(prepared, results, config)
    finally:
        _current_config.pop(threading.get_ident(), None)


def _strip_state(state: MatchState, a: int, b: int) -> MatchState:
    # Each strip state gets its own Wants: the strip's volume stages set per-strip requests.
    wants = replace(state.wants)
    if a == 0 and b == state.shape[0]:
        return MatchState(state.left, state.right, state.min_disp, state.ndisp, state.left_valid,
                          state.right_valid, wants=wants, gray_cache=state.gray_cache)
    crop = lambda m: None if m is None else np.ascontiguousarray(m[a:b])  # noqa: E731
    return MatchState(np.ascontiguousarray(state.left[a:b]), np.ascontiguousarray(state.right[a:b]),
                      state.min_disp, state.ndisp,
                      crop(state.left_valid), crop(state.right_valid), wants=wants, row_offset=a,
                      image_rows=state.image_shape[0])


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
        # (an optimizer that keeps no volume sets the right view itself)
        volume = required(sub.cost, f"optimizer.{optimizer.stage.name}: left no cost volume for the right view")
        sub.disparity_right = wta_right(volume, sub.min_disp, np.float32(sub.cost_max))
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
        sub.integer_disparity = required(sub.disparity, "the optimizer left no disparity map").copy()
        if sub.disparity_right is not None:
            sub.integer_disparity_right = sub.disparity_right.copy()


def _timed(timings: dict, key: str, func, state: MatchState, params) -> None:
    t0 = time.perf_counter()
    func(state, params)
    timings[key] = timings.get(key, 0.0) + time.perf_counter() - t0


def release_config() -> None:
    """Forget the config :func:`prepare` noted for this thread (for a caller that runs only
    :func:`prepare`, e.g. to preprocess a whole frame whose parts it then matches)."""
    _current_config.pop(threading.get_ident(), None)


def current_config() -> PipelineConfig | None:
    """The config of the pair the calling thread is matching (between :func:`prepare` and the end
    of :func:`finish`), else that of a pair another thread is matching (a kernel helper thread
    compiling for it), else None: what the command line warms up when a kernel has to compile."""
    own = _current_config.get(threading.get_ident())
    if own is not None:
        return own
    others = list(_current_config.values())
    return others[-1] if others else None


def _set_threads(threads: int) -> None:
    from ..runtime import set_threads

    set_threads(threads)  # also numba's, for its prange kernels, once numba has started
