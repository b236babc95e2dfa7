"""``stereocli match`` as batch work: pairs -> work items, the item function workers run, and
one pair's row strips spread over Dask workers (``--split-strips``).

Outputs per pair, in ``OUTDIR/<name>/``:

* ``disp0.pfm`` — float32 disparity, +inf invalid (always);
* ``disp0.png`` — uint16 ``round(d * scale)``, 0 invalid (``png16_scale`` set);
* ``disp0.npy`` — float32 array (``npy``);
* ``disp0_viz.png`` — 8-bit colour preview, not data (``viz``);
* ``conf0.pfm`` — confidence in [0, 1] (``confidence``); ``disp1.pfm`` — right view (``right``);
* ``time.txt`` — matching seconds (Middlebury convention);
* ``params.json`` — effective config, versions, disparity range, timings per stage.

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

from ..errors import ConfigError, DataError
from ..io.atomic import write_text
from ..io.pairs import StereoInput
from .items import WorkItem, prepare_worker

if TYPE_CHECKING:
    from ..match.pipeline import PreparedPair, StripMap, StripResult
    from ..match.state import MatchState

_CONFIG_CACHE: dict[str, Any] = {}


def resolve_range(pair: StereoInput, ndisp: int | None, min_disp: int | None) -> tuple[int, int, dict]:
    """Disparity range for a pair: options first, else its ``calib.txt``, else a ConfigError.

    Returns ``(min_disp, ndisp, calib_info)`` where ``calib_info`` holds vmin/vmax for previews.
    """
    info: dict = {}
    if pair.calib:
        from ..io.middlebury import read_calib_txt

        calib = read_calib_txt(pair.calib)
        info = {"vmin": calib.vmin, "vmax": calib.vmax}
        if ndisp is None and calib.ndisp > 0:
            ndisp = calib.ndisp
    if ndisp is None:
        raise ConfigError(
            f"{pair.name}: no disparity range: give --ndisp N (and --min-disp) or put a calib.txt with ndisp= in "
            f"{pair.folder or Path(pair.left).parent}"
        )
    return int(min_disp or 0), int(ndisp), info


def plan_items(
    pairs: list[StereoInput],
    outdir: str | Path,
    *,
    config: dict,
    ndisp: int | None,
    min_disp: int | None,
    png16_scale: float | None = None,
    npy: bool = False,
    viz: bool = False,
    confidence: bool = False,
    right: bool = False,
    keep_invalid: bool = False,
    split_strips: bool = False,
    record_info: dict | None = None,
) -> list[WorkItem]:
    """One :class:`WorkItem` per pair with its inputs, outputs and options.

    ``config`` is the effective config as a plain dict; ``split_strips`` spreads each pair's
    strips over the Dask cluster its task runs on (a pair with one strip runs whole).
    """
    outdir = Path(outdir)
    items = []
    for pair in pairs:
        lo, nd, info = resolve_range(pair, ndisp, min_disp)
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
        options = {"config": config, "min_disp": lo, "ndisp": nd, "png16_scale": png16_scale,
                   "keep_invalid": keep_invalid, "vmin": info.get("vmin"), "vmax": info.get("vmax"),
                   "record": record_info or {}}
        if split_strips:
            options["split_strips"] = True
        items.append(WorkItem(pair.name, inputs, outputs, options))
    return items


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


def _remove_stale_temporaries(folder: Path) -> None:
    # The pair's folder is its own: any temporary in it is a dead attempt's (never a final name).
    if folder.is_dir():
        for tmp in folder.glob(".*.tmp*"):
            tmp.unlink(missing_ok=True)


def match_item(item: WorkItem) -> dict:
    """Match one pair and write its outputs atomically; returns details for the run record."""
    from ..io.images import read_image, write_disparity, write_image
    from ..io.pfm import write_pfm
    from ..match.pipeline import match_pair

    opts = item.options
    config = _config(opts["config"])
    _remove_stale_temporaries(Path(item.outputs["disparity"]).parent)
    t_load = time.perf_counter()
    left = read_image(item.inputs["left"])
    right = read_image(item.inputs["right"])
    if left.shape[:2] != right.shape[:2]:
        raise DataError(
            f"{item.name}: left {left.shape[1]}x{left.shape[0]} and right {right.shape[1]}x{right.shape[0]} differ in size"
        )
    if left.ndim != right.ndim:
        # One colour and one grey view: match in grey.
        left = read_image(item.inputs["left"], gray=True)
        right = read_image(item.inputs["right"], gray=True)
    left_valid = _load_mask(item.inputs.get("left_valid"))
    right_valid = _load_mask(item.inputs.get("right_valid"))
    load_seconds = time.perf_counter() - t_load

    strip_map = cluster_strip_map(opts["config"]) if opts.get("split_strips") else None
    t0 = time.perf_counter()
    result = match_pair(left, right, config, min_disp=opts["min_disp"], ndisp=opts["ndisp"],
                        left_valid=left_valid, right_valid=right_valid,
                        want_right="right" in item.outputs, keep_invalid=opts["keep_invalid"],
                        want_confidence="confidence" in item.outputs, strip_map=strip_map)
    seconds = time.perf_counter() - t0

    out = item.outputs
    write_pfm(out["disparity"], result.disparity)
    if "png16" in out:
        write_disparity(out["png16"], result.disparity, png_scale=opts["png16_scale"])
    if "npy" in out:
        write_disparity(out["npy"], result.disparity)
    if "viz" in out:
        from ..viz import colorize_disparity

        write_image(out["viz"], colorize_disparity(result.disparity, opts.get("vmin"), opts.get("vmax")))
    if "confidence" in out:
        conf = result.confidence
        if conf is None:
            raise ConfigError("--confidence: the configured pipeline produces no confidence map "
                              "(add a refinement stage that does, e.g. {name: confidence})")
        write_pfm(out["confidence"], conf)
    if "right" in out:
        write_pfm(out["right"], result.disparity_right)
    h, w = result.disparity.shape
    finite = np.isfinite(result.disparity)
    details = {
        "width": w, "height": h, "min_disp": opts["min_disp"], "ndisp": opts["ndisp"],
        "seconds": round(seconds, 4), "load_seconds": round(load_seconds, 4),
        "stage_seconds": result.timings, "strips": result.strips,
        "memory_estimate_gb": round(result.memory_estimate_gb, 3),
        "mde_per_s": round(w * h * opts["ndisp"] / max(seconds, 1e-9) / 1e6, 2),
        "valid_fraction": round(float(finite.mean()), 6),
    }
    params = {"pair": item.name, "inputs": item.inputs, "config": opts["config"], **details,
              **opts.get("record", {})}
    write_text(out["params"], json.dumps(params, indent=2) + "\n")
    # time.txt last: its presence marks a complete result for resumption tools.
    write_text(out["time"], f"{seconds:.6f}\n")
    return details


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
