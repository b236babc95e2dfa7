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
``calib.txt``, else (and always with ``--ndisp auto``) it is estimated from the images
(:mod:`stereocli.features.disparity_range`). Every pair's row alignment is measured: by the
config's ``row_align`` when it tracks the rows and the range is known, else (or when its fit is
no measurement) from sparse matches (:mod:`stereocli.features.alignment`). A misaligned pair is
reported with a warning, or fails with ``require_aligned`` (before any output is written).

With ``split_strips`` the item task runs :func:`~stereocli.match.pipeline.prepare` and
:func:`~stereocli.match.pipeline.finish` itself and sends each strip's volume stages
(:func:`~stereocli.match.pipeline.run_strip`, a pure function of the cropped strip state and
the config) to the cluster as a sub-task (:func:`strip_task`). Strips are stitched in plan
order, so the result is bit-identical to matching in one process with the same config,
whichever workers ran the strips.
"""

from __future__ import annotations

import json
import time
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from ..errors import ConfigError, DataError, StereoError
from ..io.atomic import write_text
from ..io.pairs import StereoInput
from .items import WorkItem, check_output_paths, label_message, prepare_worker, settings_digest

if TYPE_CHECKING:
    from ..match.pipeline import PreparedPair, StripMap, StripResult
    from ..match.state import MatchState

_CONFIG_CACHE: dict[str, Any] = {}


#: ``ndisp`` value asking for an estimated range.
AUTO = "auto"


def resolve_range(pair: StereoInput, ndisp: int | str | None, min_disp: int | None) -> tuple[int | None, int | None, dict]:
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
            return (*calib_range(calib, pair.calib), info)
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
        inputs = {"left": pair.left, "right": pair.right}
        for key in ("calib", "left_valid", "right_valid"):
            if getattr(pair, key):
                inputs[key] = getattr(pair, key)
        options = {"config": config, "min_disp": lo, "ndisp": nd, "range_source": info["range_source"],
                   "png16_scale": png16_scale, "keep_invalid": keep_invalid, "require_aligned": require_aligned,
                   "vmin": info.get("vmin"), "vmax": info.get("vmax"), "record": record_info or {}}
        if info.get("note"):
            options["range_note"] = info["note"]
        if split_strips:
            options["split_strips"] = True
        items.append(WorkItem(pair.name, inputs, outputs, options, folder=str(folder), command="match",
                              config_digest=settings_digest(_output_settings(options))))
        if error is not None:
            items[-1].error, items[-1].error_code = label_message(pair.name, str(error)), error.exit_code
    check_output_paths(items, outdir)
    return items


def _output_settings(options: dict) -> dict:
    """The options of a match item that change its outputs: not the run record's extras, the
    kernel threads, nor ``split_strips`` (strips on the cluster stitch to the same bytes)."""
    settings = {k: v for k, v in options.items() if k not in ("record", "split_strips")}
    config = dict(settings["config"])
    config["runtime"] = {k: v for k, v in config.get("runtime", {}).items() if k != "threads"}
    return {**settings, "config": config}


def _config(config: dict):
    # Workers validate the config once per process, not once per item.
    from ..match.config import validate

    key = json.dumps(config, sort_keys=True)
    if key not in _CONFIG_CACHE:
        _CONFIG_CACHE[key] = validate(config, "effective config")
    return _CONFIG_CACHE[key]


def _load_mask(path: str | None) -> np.ndarray | None:
    if not path:
        return None
    from ..io.images import read_image

    mask = read_image(path, gray=True)
    return mask > 127


_WARMED: set = set()


def _tiny_match(config, *, channels: int, dtype: np.dtype, min_disp: int, ndisp: int, masks: bool, **flags):
    """:func:`~stereocli.match.pipeline.match_pair` on a small random pair of this kind
    (channels, dtype, valid masks, wanted outputs) with at most 32 disparities."""
    from ..match.pipeline import match_pair

    nd = max(1, min(int(ndisp), 32))
    h, w = 48, nd + 64
    info = np.iinfo(dtype) if np.issubdtype(dtype, np.integer) else None
    high = info.max if info else 255
    shape = (h, w, channels) if channels > 1 else (h, w)
    left = np.random.default_rng(0).integers(0, high, shape, endpoint=True).astype(dtype)
    right = np.roll(left, -max(0, min_disp) - nd // 2, axis=1)
    valid = np.ones((h, w), bool) if masks else None
    return match_pair(left, right, config, min_disp=int(min_disp), ndisp=nd, left_valid=valid, right_valid=valid,
                      **flags)


def _warm_up(config, left: np.ndarray, *, min_disp: int, ndisp: int, masks: bool, **flags) -> None:
    """Once per process and kind of call, match a tiny pair first, so that the time of the first
    real pair (``time.txt``) holds matching, not loading (or compiling) the kernels. The tiny
    pair takes the code path of the real one (:func:`~stereocli.match.config.small_twin`)."""
    from ..match.config import small_twin

    twin = small_twin(config, left.shape[0], left.shape[1], ndisp)
    key = (id(config), repr(twin.as_dict()), left.ndim, left.dtype.str, masks, tuple(sorted(flags.items())))
    if key in _WARMED:
        return
    _WARMED.add(key)
    try:
        _tiny_match(twin, channels=left.shape[2] if left.ndim == 3 else 1, dtype=left.dtype,
                    min_disp=min_disp, ndisp=ndisp, masks=masks, **flags)
    except Exception:  # noqa: BLE001 - only a warm-up: the real pair reports its own errors
        pass


def check_confidence(config: dict) -> None:
    """Raise :class:`ConfigError` unless the pipeline of ``config`` (a plain dict) produces a
    confidence map (``match --confidence``), found by matching a tiny pair before any work."""
    validated = _config(config)
    result = _tiny_match(validated, channels=3, dtype=np.dtype(np.uint8), min_disp=0, ndisp=16, masks=False,
                         want_confidence=True)
    if result.confidence is None:
        names = ", ".join(c["name"] for c in config.get("refinement", [])) or "none"
        raise ConfigError(f"--confidence: the configured pipeline produces no confidence map (refinement: {names}); "
                          f"add a refinement stage that does, e.g. {_add_confidence(validated)}")


def _add_confidence(config) -> str:
    """The ``--set`` that adds a ``confidence`` stage to the validated ``config``: before the
    first stage that only edits the map (it reads the cost volume)."""
    from ..match.config import first_map_stage

    target = first_map_stage(config.refinement)
    where = "refinement+=" if target == str(len(config.refinement)) else f"refinement.{target}+="
    return f"--set {where}confidence"


def _read_views(item: WorkItem, gray: bool = False) -> tuple[np.ndarray, np.ndarray]:
    """The pair's left and right images, decoded side by side (OpenCV releases the GIL while it
    decodes, so the two decodes overlap). A file's error is raised as reading it alone would."""
    from ..io.images import read_image
    from ..match.kernels import side_by_side

    return side_by_side(lambda: read_image(item.inputs["left"], gray=gray),
                        lambda: read_image(item.inputs["right"], gray=gray))


def match_item(item: WorkItem) -> dict:
    """Match one pair and write its outputs atomically; returns details for the run record."""
    from ..io.exif import orientation_note
    from ..io.images import write_disparity, write_image
    from ..io.pfm import write_pfm
    from ..match.pipeline import match_pair

    opts = item.options
    config = _config(opts["config"])
    t_load = time.perf_counter()
    left, right = _read_views(item)
    if left.shape[:2] != right.shape[:2]:
        raise DataError(
            f"{item.name}: left {left.shape[1]}x{left.shape[0]} and right {right.shape[1]}x{right.shape[0]} differ in size"
        )
    if left.ndim != right.ndim:
        # One colour and one grey view: match in grey.
        left, right = _read_views(item, gray=True)
    left_valid = _load_mask(item.inputs.get("left_valid"))
    right_valid = _load_mask(item.inputs.get("right_valid"))
    load_seconds = time.perf_counter() - t_load

    # With the range known, a config whose row_align measures the rows leaves the alignment to it
    # (its tracks are the better measurement, and the sparse matches would add about an eighth
    # to a Q-size pair's matching time); the sparse matches measure them when it cannot.
    rows_in_match = opts["ndisp"] is not None and _measures_rows(config)
    survey = survey_pair(item.name, left, right, opts, left_valid=left_valid, right_valid=right_valid,
                         measure_rows=not rows_in_match)
    min_disp, ndisp = survey["range"]["min_disp"], survey["range"]["ndisp"]
    check_range_meets_image(item.name, min_disp, ndisp, left.shape[1])
    strip_map = cluster_strip_map(opts["config"]) if opts.get("split_strips") else None
    flags = {"want_right": "right" in item.outputs, "keep_invalid": opts["keep_invalid"],
             "want_confidence": "confidence" in item.outputs}
    _warm_up(config, left, min_disp=min_disp, ndisp=ndisp, masks=left_valid is not None, **flags)
    t0 = time.perf_counter()
    result = match_pair(left, right, config, min_disp=min_disp, ndisp=ndisp,
                        left_valid=left_valid, right_valid=right_valid, strip_map=strip_map, **flags)
    seconds = time.perf_counter() - t0
    if rows_in_match:
        survey.update(_rows_from_match(item.name, result.notes.get("row_align"), left, right, opts,
                                       left_valid=left_valid, right_valid=right_valid))

    out = item.outputs
    write_pfm(out["disparity"], result.disparity)
    png16_lost = 0
    if "png16" in out:
        png16_lost = write_disparity(out["png16"], result.disparity, png_scale=opts["png16_scale"])
    if "npy" in out:
        write_disparity(out["npy"], result.disparity)
    if "viz" in out:
        from ..viz import colorize_disparity

        write_image(out["viz"], colorize_disparity(result.disparity, opts.get("vmin"), opts.get("vmax")))
    if "confidence" in out:
        conf = result.confidence
        if conf is None:
            raise ConfigError("--confidence: the configured pipeline produces no confidence map "
                              f"(add a refinement stage that does, e.g. {_add_confidence(config)})")
        write_pfm(out["confidence"], conf)
    if "right" in out:
        write_pfm(out["right"], result.disparity_right)
    notes = [orientation_note(item.inputs["left"]), orientation_note(item.inputs["right"]), opts.get("range_note")]
    survey["warnings"] = [n for n in notes if n] + _rows_corrected(survey["warnings"], result.notes.get("row_align"))
    h, w = result.disparity.shape
    finite = np.isfinite(result.disparity)
    details = {
        "width": w, "height": h, "min_disp": min_disp, "ndisp": ndisp,
        "seconds": round(seconds, 4), "load_seconds": round(load_seconds, 4),
        "stage_seconds": result.timings, "strips": result.strips,
        "memory_estimate_gb": round(result.memory_estimate_gb, 3),
        "mde_per_s": round(w * h * ndisp / max(seconds, 1e-9) / 1e6, 2),
        "valid_fraction": round(float(finite.mean()), 6),
        # Pixels no right-view pixel shows over the range: invalid, or filled with their row's background.
        "unmatched": result.unmatched,
        **survey,
    }
    if result.notes:
        details["stage_notes"] = result.notes
    if png16_lost:
        details["png16_unrepresentable"] = png16_lost
        details["warnings"] = [*details.get("warnings", []),
                               f"disp0.png: {png16_lost} valid pixels outside [1, 65535] / {opts['png16_scale']:g} px "
                               "written as 0 (invalid); disp0.pfm has them"]
    from ..match.kernels.aot import describe

    params = {"pair": item.name, "inputs": item.inputs, "config": opts["config"], **details,
              "kernels": describe(), **opts.get("record", {})}
    write_text(out["params"], json.dumps(params, indent=2) + "\n")
    write_text(out["time"], f"{seconds:.6f}\n")
    return details


#: The survey's warning for a pair whose rows are off by more than the alignment threshold, and
#: its advice (replaced by what ``row_align`` did when the matching corrected the rows).
ROWS_NOT_ALIGNED = "rows not aligned"
RECTIFY_FIRST = "rectify the pair first"


def check_range_meets_image(name: str, min_disp: int, ndisp: int, width: int) -> None:
    """Raise :class:`DataError` when no disparity of ``[min_disp, min_disp + ndisp)`` puts a left
    pixel's match inside an image ``width`` px wide: every pixel would be invalid."""
    if min_disp >= width or min_disp + ndisp - 1 <= -width:
        raise DataError(f"{name}: the disparity range {min_disp}..{min_disp + ndisp - 1} px lies outside the "
                        f"{width} px wide image (a match needs |d| < {width}); no pixel can match (check --min-disp)")


def _rows_corrected(warnings: list[str], note: dict | None) -> list[str]:
    """The survey's ``warnings`` with the rows warning's advice replaced by what ``row_align``
    did, when it moved the right view's rows (``note``: its ``stage_notes`` entry)."""
    if not note or not note.get("applied"):
        return warnings
    done = f"row_align moved the right view's rows by up to {note['largest_px']:.2f} px (params.json: stage_notes)"
    return [w[:-len(RECTIFY_FIRST)] + done if w.startswith(ROWS_NOT_ALIGNED) and w.endswith(RECTIFY_FIRST) else w
            for w in warnings]


def survey_pair(name: str, left: np.ndarray, right: np.ndarray, opts: dict, *,
                left_valid: np.ndarray | None = None, right_valid: np.ndarray | None = None,
                measure_rows: bool = True) -> dict:
    """Row alignment of the pair, and its disparity range when it is to be estimated.

    Returns the run-record entries ``range`` (``min_disp``, ``ndisp``, ``source`` and, when
    estimated, the ``evidence``), ``alignment`` and ``warnings``, plus ``survey_seconds``.
    Raises :class:`DataError` when a range cannot be estimated, or when the rows are not aligned
    and ``opts["require_aligned"]``. Without ``measure_rows`` and with the range known, nothing
    is matched: ``alignment`` is None and the caller measures the rows
    (:func:`_rows_from_match`).
    """
    from ..features.points import match_points

    t0 = time.perf_counter()
    span = {"min_disp": opts["min_disp"], "ndisp": opts["ndisp"], "source": opts["range_source"]}
    if opts["ndisp"] is not None and not measure_rows:
        return {"range": span, "alignment": None, "warnings": [], "survey_seconds": 0.0}
    matches = match_points(left, right, left_valid=left_valid, right_valid=right_valid)
    rows = _rows_from_matches(name, matches, opts)
    if opts["ndisp"] is None:
        from ..features.disparity_range import estimate_range

        try:
            estimate = estimate_range(left, right, matches)
        except DataError as exc:
            raise DataError(f"{name}: {exc}") from None
        span.update(min_disp=estimate.min_disp, ndisp=estimate.ndisp, evidence=estimate.as_dict())
    return {"range": span, **rows, "survey_seconds": round(time.perf_counter() - t0, 4)}


def _rows_from_matches(name: str, matches, opts: dict) -> dict:
    """``alignment`` and ``warnings`` from the pair's sparse matches (see :func:`_row_warnings`)."""
    from ..features.alignment import row_alignment

    alignment = row_alignment(matches)
    return {"alignment": {"source": "sparse matches", **alignment.as_dict()},
            "warnings": _row_warnings(name, alignment.aligned, alignment.describe(), opts)}


def _row_warnings(name: str, aligned: bool, description: str, opts: dict) -> list[str]:
    """The rows warning of a misaligned pair (none for an aligned one); raises
    :class:`DataError` instead with ``opts["require_aligned"]``."""
    if aligned:
        return []
    message = f"{ROWS_NOT_ALIGNED}: {description}; {RECTIFY_FIRST}"
    if opts.get("require_aligned"):
        raise DataError(f"{name}: {message} (--require-aligned)")
    return [message]


def _measures_rows(config) -> bool:
    """Whether the validated ``config`` measures the pair's rows in its preprocessing
    (``row_align`` with ``measure``)."""
    return any(call.stage.name == "row_align" and call.params.measure for call in config.preprocess)


def _rows_from_match(name: str, note: dict | None, left: np.ndarray, right: np.ndarray, opts: dict, *,
                     left_valid: np.ndarray | None = None, right_valid: np.ndarray | None = None) -> dict:
    """``alignment`` and ``warnings`` from ``row_align``'s fit during the match (``note``, its
    ``stage_notes`` entry) when it measured the rows, else from sparse matches as the survey
    takes them (too few tracks, or tracks that scatter about their plane). A pair counts as
    misaligned when the fitted plane departs from the rows by more than the survey's threshold
    anywhere in the image."""
    from ..features.alignment import DEFAULT_THRESHOLD

    if not note or not note.get("measured"):
        from ..features.points import match_points

        return _rows_from_matches(name, match_points(left, right, left_valid=left_valid, right_valid=right_valid),
                                  opts)
    largest = float(note["largest_px"])
    aligned = largest <= DEFAULT_THRESHOLD
    description = (f"vertical disparity up to {largest:.1f} px (row_align's plane through {note['tracks']} tracks, "
                   f"offset {note['offset_px']:+.2f} px at the centre)")
    return {"alignment": {"source": "row_align", "tracks": note["tracks"], "max_offset": round(largest, 3),
                          "threshold": DEFAULT_THRESHOLD, "aligned": aligned},
            "warnings": _row_warnings(name, aligned, description, opts)}


def cluster_strip_map(config_dict: dict) -> StripMap:
    """A ``strip_map`` for :func:`~stereocli.match.pipeline.match_pair` that spreads strips over
    the cluster the calling task runs on (in-process when there is one strip or no cluster).

    ``config_dict`` is the effective config as a plain dict: workers validate it once per process.
    """

    def strip_map(prepared: PreparedPair, config) -> list[StripResult]:
        from ..match.pipeline import run_strips, strip_input
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
    from ..match.pipeline import run_strip

    prepare_worker()
    return run_strip(sub, _config(config_dict), y0, y1, keep_invalid=keep_invalid)
