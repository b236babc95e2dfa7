"""``stereocli match`` as batch work: pairs -> work items, the item function workers run, and
one pair's row strips spread over Dask workers (``--split-strips``).

Outputs per pair, in ``OUTDIR/<name>/``:

* ``disp0.pfm`` — float32 disparity, +inf invalid (always);
* ``disp0.png`` — uint16 ``round(d * scale)``, 0 invalid (``png16_scale`` set);
* ``disp0.npy`` — float32 array (``npy``);
* ``disp0_viz.png`` — 8-bit colour preview, not data (``viz``);
* ``conf0.pfm`` — confidence in [0, 1] (``confidence``); ``disp1.pfm`` — right view (``right``);
* ``time.txt`` — matching seconds (Middlebury convention);
* ``params.json`` — effective config, versions, disparity range (and where it came from), row
  alignment, timings per stage.

The disparity range of a pair comes from ``--ndisp``/``--min-disp``, else from its
``calib.txt``, else (and always with ``--ndisp auto``) it is estimated from the images. Each pair
is matched by :func:`stereocli.match`, which also measures its rows (:mod:`stereocli.features.survey`):
a misaligned pair is reported with a warning, or fails with ``require_aligned`` (before any
output is written).

With ``split_strips`` the item task runs :func:`~stereocli.matching.pipeline.prepare` and
:func:`~stereocli.matching.pipeline.finish` itself and sends each strip's volume stages
(:func:`~stereocli.matching.pipeline.run_strip`, a pure function of the cropped strip state and
the config) to the cluster as a sub-task (:func:`strip_task`). Strips are stitched in plan
order, so the result is bit-identical to matching in one process with the same config,
whichever workers ran the strips.
"""

from __future__ import annotations

import json
import os
import time
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any, cast

import numpy as np

from ..errors import ConfigError, DataError, MemoryBudgetError, StereoError
from ..io.atomic import write_text
from ..io.pairs import StereoInput
from .items import WorkItem, check_output_paths, label_message, prepare_worker, settings_digest

if TYPE_CHECKING:
    from ..matching.pipeline import PreparedPair, StripMap, StripResult
    from ..matching.state import MatchState

_CONFIG_CACHE: dict[str, Any] = {}


#: ``ndisp`` value asking for an estimated range.
AUTO = "auto"


def resolve_range(pair: StereoInput, ndisp: int | str | None,
                  min_disp: int | None) -> tuple[int | None, int | None, dict]:
    """Disparity range for a pair: ``--ndisp N`` first, else its ``calib.txt``, else estimated.

    Returns ``(min_disp, ndisp, info)``; both are None when the range is to be estimated from the
    images (``ndisp`` is :data:`AUTO`, or neither an option nor a calib.txt gives it). ``info``
    holds ``range_source`` (``option``, ``calib.txt`` or ``estimated``) and calib.txt's vmin/vmax
    for previews.
    """
    info: dict = {}
    if pair.calib:
        from ..io.middlebury import calib_range, read_calib_txt

        calib = read_calib_txt(pair.calib)
        info = {"vmin": calib.vmin, "vmax": calib.vmax}
        if ndisp is None and calib.ndisp > 0:
            info["range_source"] = "calib.txt"
            if min_disp is not None:
                return int(min_disp), int(calib.ndisp), info
            # ndisp > 0: calib.txt gives a range
            return (*cast("tuple[int, int]", calib_range(calib, pair.calib)), info)
        if ndisp is None and min_disp is None:
            info["note"] = f"{pair.calib}: ndisp={calib.ndisp} gives no range; the range is estimated from the images"
    if ndisp is None or ndisp == AUTO:
        if min_disp is not None:
            raise ConfigError(f"{pair.name}: --min-disp needs --ndisp N (or a calib.txt with ndisp=); "
                              "an estimated range sets both")
        info["range_source"] = "estimated"
        return None, None, info
    info["range_source"] = "option"
    return int(min_disp or 0), int(ndisp), info


def plan_items(
    pairs: list[StereoInput],
    outdir: str | Path,
    *,
    config: dict,
    ndisp: int | str | None,
    min_disp: int | None,
    png16_scale: float | None = None,
    npy: bool = False,
    viz: bool = False,
    viz_range: tuple[float, float] | None = None,
    confidence: bool = False,
    right: bool = False,
    keep_invalid: bool = False,
    split_strips: bool = False,
    require_aligned: bool = False,
    record_info: dict | None = None,
) -> list[WorkItem]:
    """One :class:`WorkItem` per pair with its inputs, outputs and options.

    ``ndisp``: a number, :data:`AUTO` (estimate every pair's range) or None (calib.txt, else
    estimate); ``require_aligned`` fails pairs whose rows are not aligned.

    ``config`` is the effective config as a plain dict; ``split_strips`` spreads each pair's
    strips over the Dask cluster its task runs on (a pair with one strip runs whole).
    ``viz_range`` (px) colours the previews, else calib.txt's vmin/vmax, else each map's robust range.
    """
    outdir = Path(outdir)
    if confidence:
        check_confidence(config)  # a pipeline without a confidence stage fails here, before any work
    items = []
    for pair in pairs:
        error = None
        try:
            lo, nd, info = resolve_range(pair, ndisp, min_disp)
        except StereoError as exc:  # this pair's failure (a bad calib.txt), not the batch's
            error, (lo, nd, info) = exc, (None, None, {"range_source": None})
        folder = outdir / pair.name
        outputs = match_outputs(folder, png16_scale=png16_scale, npy=npy, viz=viz, confidence=confidence, right=right)
        inputs = {"left": pair.left, "right": pair.right}
        for key in ("calib", "left_valid", "right_valid"):
            if getattr(pair, key):
                inputs[key] = getattr(pair, key)
        options = match_options(config, lo, nd, info, png16_scale=png16_scale, keep_invalid=keep_invalid,
                                require_aligned=require_aligned, viz_range=viz_range, record_info=record_info)
        if split_strips:
            options["split_strips"] = True
        items.append(WorkItem(pair.name, inputs, outputs, options, folder=str(folder), command="match",
                              config_digest=settings_digest(output_settings(options))))
        if error is not None:
            items[-1].error, items[-1].error_code = label_message(pair.name, str(error)), error.exit_code
    check_output_paths(items, outdir)
    return items


def match_options(config: dict, min_disp: int | None, ndisp: int | None, range_info: dict, *,
                  png16_scale: float | None, keep_invalid: bool, require_aligned: bool,
                  viz_range: tuple[float, float] | None, record_info: dict | None) -> dict[str, Any]:
    """The options of one match item (what :func:`match_item` and the outputs read): the range
    and where it came from (:func:`resolve_range`'s ``range_info``), the output settings and the
    preview colours (``viz_range``, else calib.txt's vmin/vmax)."""
    options = {"config": config, "min_disp": min_disp, "ndisp": ndisp, "range_source": range_info["range_source"],
               "png16_scale": png16_scale, "keep_invalid": keep_invalid, "require_aligned": require_aligned,
               "vmin": viz_range[0] if viz_range else range_info.get("vmin"),
               "vmax": viz_range[1] if viz_range else range_info.get("vmax"), "record": record_info or {}}
    if range_info.get("note"):
        options["range_note"] = range_info["note"]
    return options


def match_outputs(folder: Path, *, png16_scale: float | None = None, npy: bool = False, viz: bool = False,
                  confidence: bool = False, right: bool = False) -> dict[str, str]:
    """The output paths of one matched pair in ``folder``, by kind (the module's docstring)."""
    outputs = {"disparity": str(folder / "disp0.pfm"), "time": str(folder / "time.txt"),
               "params": str(folder / "params.json")}
    if png16_scale:
        outputs["png16"] = str(folder / "disp0.png")
    if npy:
        outputs["npy"] = str(folder / "disp0.npy")
    if viz:
        outputs["viz"] = str(folder / "disp0_viz.png")
    if confidence:
        outputs["confidence"] = str(folder / "conf0.pfm")
    if right:
        outputs["right"] = str(folder / "disp1.pfm")
    return outputs


def output_settings(options: dict) -> dict:
    """The options of a match item that change its outputs: not the run record's extras, the
    kernel threads, nor ``split_strips`` (strips on the cluster stitch to the same bytes)."""
    settings = {k: v for k, v in options.items() if k not in ("record", "split_strips")}
    config = dict(settings["config"])
    config["runtime"] = {k: v for k, v in config.get("runtime", {}).items() if k != "threads"}
    return {**settings, "config": config}


def _config(config: dict):
    # Workers validate the config once per process, not once per item.
    from ..matching.config import validate

    key = json.dumps(config, sort_keys=True)
    if key not in _CONFIG_CACHE:
        _CONFIG_CACHE[key] = validate(config, "effective config")
    return _CONFIG_CACHE[key]


def _load_mask(path: str | None) -> np.ndarray | None:
    if not path:
        return None
    from ..io.images import read_valid_mask

    return read_valid_mask(path)


def check_confidence(config: dict) -> None:
    """Raise :class:`ConfigError` unless the pipeline of ``config`` (a plain dict) produces a
    confidence map (``match --confidence``): a refinement stage whose traits say so."""
    from ..matching.config import confidence_hint

    validated = _config(config)
    if not validated.produces_confidence():
        names = ", ".join(c["name"] for c in config.get("refinement", [])) or "none"
        raise ConfigError(f"--confidence: the configured pipeline produces no confidence map (refinement: {names}); "
                          f"add a refinement stage that does, e.g. {confidence_hint(validated)}")


def _read_views(item: WorkItem, gray: bool = False) -> tuple[np.ndarray, np.ndarray]:
    """The pair's left and right images, decoded side by side (OpenCV releases the GIL while it
    decodes, so the two decodes overlap). A file's error is raised as reading it alone would."""
    from ..io.images import read_image
    from ..runtime import side_by_side

    return side_by_side(lambda: read_image(item.inputs["left"], gray=gray),
                        lambda: read_image(item.inputs["right"], gray=gray))


#: Extra (H, W) float32 maps the survey (sparse matches, range estimate) holds at its peak
#: beside the views, for grey and for colour views (measured: 2.5 and 3.4).
SURVEY_COPIES = {False: 3.0, True: 4.0}
#: Extra (H, W) float32 maps while an output is written: the PFM's encoded bytes, the 16-bit
#: PNG's float64 arithmetic, the preview's colours.
WRITE_COPIES = {"disparity": 2.0, "png16": 8.0, "viz": 4.0}


@dataclass(frozen=True)
class MemoryPlan:
    """The memory one ``match`` item needs, planned from its images' headers."""

    width: int
    height: int
    outside: float  # bytes at the peak of decoding, the survey or writing (runtime included)
    least: float  # bytes: the smallest peak any strip plan and disparity range can have
    estimate: float | None  # bytes: the planned peak (None until the range is estimated)
    strips: int | None  # row strips of the plan (None until the range is estimated)


def memory_plan(item: WorkItem, config) -> MemoryPlan | None:
    """Plan the memory of matching ``item`` (validated ``config``) before anything is decoded.

    Counts the runtime, decoding the views, the survey, the pipeline's whole-image buffers and
    one strip (:func:`~stereocli.matching.pipeline.planned_peak`) and writing the outputs. Raises
    :class:`DataError` naming the pair when even the least of these exceeds
    ``runtime.memory_gb``, and :class:`~stereocli.errors.MemoryBudgetError` when the pair's
    disparity range cannot fit in row strips. None when an image's header cannot be read
    (the pipeline then plans once the views are decoded).
    """
    from ..features.survey import measures_rows
    from ..io.images import read_image_header
    from ..matching.pipeline import GIB, RUNTIME_BASE, image_memory, plan_strips, planned_peak

    left_view, right_view = (read_image_header(item.inputs[side]) for side in ("left", "right"))
    if (left_view is None or right_view is None
            or left_view.width * left_view.height != right_view.width * right_view.height):
        return None  # sizes that differ are reported once the views are decoded
    views = [left_view, right_view]
    width, height = views[0].width, views[0].height
    plane = 4.0 * width * height  # one (H, W) float32 map
    masks = sum(1 for key in ("left_valid", "right_valid") if key in item.inputs)
    files = [os.path.getsize(item.inputs[side]) for side in ("left", "right")]
    # Decoding: the file's bytes, what OpenCV decodes and, for colours, the RGB copy; both views at once.
    decoding = sum(f + v.decoded_bytes + v.image_bytes * (v.channels >= 3) for f, v in zip(files, views))
    colour = [v.channels >= 3 for v in views]
    inputs = [v.image_bytes for v in views]
    if colour[0] != colour[1]:  # one colour and one grey view: both are read again as grey
        grey = [v.width * v.height * v.itemsize for v in views]
        decoding = max(decoding, sum(inputs) + sum(files) + sum(grey))
        inputs, colour = grey, [False, False]
    held = sum(inputs) + masks * width * height
    opts, outputs = item.options, item.outputs
    results = plane * (1 + ("right" in outputs) + ("confidence" in outputs))
    # The survey's sparse matches run before the match, or after it (beside the maps) when the
    # range is known and the config's row_align, which then measures the rows, finds too few tracks.
    after_match = opts.get("ndisp") is not None and measures_rows(config)
    survey = held + plane * SURVEY_COPIES[any(colour)] + results * after_match
    writing = held + results + plane * max(WRITE_COPIES.get(key, 0.0) for key in outputs)
    outside = RUNTIME_BASE + max(decoding, survey, writing)
    images = image_memory(config, height, width, input_bytes=held, colour=(colour[0], colour[1]), masks=bool(masks),
                          want_right="right" in outputs, want_confidence="confidence" in outputs,
                          keep_invalid=opts.get("keep_invalid", False))
    least = max(outside, min(planned_peak(config, height, width, 1, plan, images)
                             for plan in ([(0, height)], [(y0, min(height, y0 + 16)) for y0 in range(0, height, 16)])))
    budget = config.runtime.memory_gb
    if least > budget * GIB:
        message = (f"{item.name}: {width}x{height} needs at least {least / GIB:.1f} GiB even in row strips "
                   f"(decoded views, working copies, disparity maps; budget runtime.memory_gb={budget:g}); "
                   "downscale the pair or raise runtime.memory_gb")
        # A budget below the runtime's own memory holds no pair at all: the setting is at fault.
        raise (MemoryBudgetError if budget * GIB < RUNTIME_BASE else DataError)(message)
    if opts.get("ndisp") is None:
        return MemoryPlan(width, height, outside, least, None, None)
    strips = plan_strips(config, height, width, opts["ndisp"], images)
    estimate = max(outside, planned_peak(config, height, width, opts["ndisp"], strips, images))
    return MemoryPlan(width, height, outside, least, estimate, len(strips))


def match_item(item: WorkItem) -> dict:
    """Match one pair (:func:`stereocli.match`) and write its outputs atomically; returns
    details for the run record.

    The pair's memory is planned from its images' headers first (:func:`memory_plan`), so a
    pair that cannot fit in ``runtime.memory_gb`` is refused before it is decoded.
    """
    from ..api import match
    from ..io.exif import orientation_note

    opts = item.options
    config = _config(opts["config"])
    memory = memory_plan(item, config)
    t_load = time.perf_counter()
    left, right = _read_views(item)
    if left.ndim != right.ndim:  # (views of different sizes: stereocli.match refuses them)
        # One colour and one grey view: match in grey.
        left, right = _read_views(item, gray=True)
    left_valid = _load_mask(item.inputs.get("left_valid"))
    right_valid = _load_mask(item.inputs.get("right_valid"))
    load_seconds = time.perf_counter() - t_load

    strip_map = cluster_strip_map(opts["config"]) if opts.get("split_strips") else None
    result = match(left, right, ndisp=opts["ndisp"], min_disp=opts["min_disp"], config=config, name=item.name,
                   left_valid=left_valid, right_valid=right_valid, disparity_right="right" in item.outputs,
                   confidence="confidence" in item.outputs, keep_invalid=opts["keep_invalid"],
                   require_aligned=opts["require_aligned"], warm_up=True, strip_map=strip_map)
    notes = [orientation_note(item.inputs["left"]), orientation_note(item.inputs["right"]), opts.get("range_note")]
    return write_match_outputs(item, result, load_seconds=load_seconds, memory=memory, notes=notes)


def write_match_outputs(item: WorkItem, result, *, load_seconds: float, memory: MemoryPlan | None = None,
                        notes: list[str | None] | tuple = (), extra: dict | None = None) -> dict:
    """Write the outputs of ``item`` from ``result`` (a :class:`~stereocli.api.MatchResult`) to
    ``item.outputs``: the disparity and the files its options ask for, then ``params.json`` and
    ``time.txt``; returns the details for the run record.

    ``load_seconds``: time spent decoding the views; ``memory``: the item's plan, when made;
    ``notes``: warnings about the inputs put before the match's own (None entries are left out);
    ``extra``: more entries for the details and ``params.json``.
    """
    from ..io.images import write_disparity, write_image
    from ..io.pfm import write_pfm

    opts = item.options
    seconds = result.seconds
    min_disp, ndisp = result.range.min_disp, result.range.ndisp
    # The plan knows where a given range came from (--ndisp or calib.txt).
    survey: dict[str, Any] = {"range": dict(result.range.as_dict(), source=opts["range_source"]),
                              "alignment": result.alignment, "warnings": result.warnings,
                              "survey_seconds": result.survey_seconds}

    out = item.outputs
    write_pfm(out["disparity"], result.disparity)
    png16_lost = 0
    if "png16" in out:
        png16_lost = write_disparity(out["png16"], result.disparity, png_scale=opts["png16_scale"])
    if "npy" in out:
        write_disparity(out["npy"], result.disparity)
    if "viz" in out:
        from ..viz import disparity_preview

        write_image(out["viz"], disparity_preview(result.disparity, opts.get("vmin"), opts.get("vmax")))
    if "confidence" in out:
        if result.confidence is None:  # (never: match refuses a pipeline that makes no confidence map)
            raise RuntimeError(f"{item.name}: the match made no confidence map")
        write_pfm(out["confidence"], result.confidence)
    if "right" in out:
        if result.disparity_right is None:  # (never: asked for, the right-view map is always made)
            raise RuntimeError(f"{item.name}: the match made no right-view map")
        write_pfm(out["right"], result.disparity_right)
    survey["warnings"] = [n for n in notes if n] + survey["warnings"]
    h, w = result.disparity.shape
    finite = np.isfinite(result.disparity)
    details = {
        "width": w, "height": h, "min_disp": min_disp, "ndisp": ndisp,
        "seconds": round(seconds, 4), "load_seconds": round(load_seconds, 4),
        "stage_seconds": result.timings, "strips": result.strips,
        "memory_estimate_gb": round(_planned_gb(memory, result), 3),
        "mde_per_s": round(w * h * ndisp / max(seconds, 1e-9) / 1e6, 2),
        "valid_fraction": round(float(finite.mean()), 6),
        # Pixels no right-view pixel shows over the range: invalid, or filled with their row's background.
        "unmatched": result.unmatched,
        **survey,
    }
    if result.notes:
        details["stage_notes"] = result.notes
    details.update(extra or {})
    if png16_lost:
        details["png16_unrepresentable"] = png16_lost
        details["warnings"] = [*details.get("warnings", []),
                               f"disp0.png: {png16_lost} valid pixels outside [1, 65535] / {opts['png16_scale']:g} px "
                               "written as 0 (invalid); disp0.pfm has them"]
    from ..runtime.aot import describe

    params = {"pair": item.name, "inputs": item.inputs, "config": opts["config"], **details,
              "kernels": describe(), **opts.get("record", {})}
    write_text(out["params"], json.dumps(params, indent=2) + "\n")
    write_text(out["time"], f"{seconds:.6f}\n")
    return details


def _planned_gb(memory: MemoryPlan | None, result) -> float:
    """The item's planned peak in GiB: the pipeline's (``result.memory_estimate_gb``) or, when
    the headers were read, the larger of it and the item's other phases."""
    from ..matching.pipeline import GIB

    if memory is None:
        return result.memory_estimate_gb
    return max(result.memory_estimate_gb, memory.outside / GIB)


def cluster_strip_map(config_dict: dict) -> StripMap:
    """A ``strip_map`` for :func:`~stereocli.matching.pipeline.match_pair` that spreads strips over
    the cluster the calling task runs on (in-process when there is one strip or no cluster).

    ``config_dict`` is the effective config as a plain dict: workers validate it once per process.
    """

    def strip_map(prepared: PreparedPair, config) -> list[StripResult]:
        from ..matching.pipeline import run_strips, strip_input
        from .dask import in_worker, worker_map

        if len(prepared.strips) < 2 or not in_worker():
            return run_strips(prepared, config)
        # Cropped strip states (image rows only, no volumes) are scattered to the cluster.
        args = [(strip_input(prepared, y0, y1), config_dict, y0, y1, prepared.keep_invalid)
                for y0, y1 in prepared.strips]
        return worker_map(strip_task, args)

    return strip_map


def strip_task(sub: MatchState, config_dict: dict, y0: int, y1: int, keep_invalid: bool) -> StripResult:
    """Sub-task body: the volume stages of one strip, on whichever worker runs it."""
    from ..matching.pipeline import run_strip

    prepare_worker()
    return run_strip(sub, _config(config_dict), y0, y1, keep_invalid=keep_invalid)
