"""``stereocli rectify`` as batch work: pairs -> work items, and the item function workers run.

Per pair, ``OUTDIR/<name>/`` receives ``im0.png``/``im1.png`` (rectified left/right, input
dtype and channels kept), ``valid0.png``/``valid1.png`` (255 = pixel sampled from inside the
source image), ``calib.txt`` (Middlebury style for the rectified pair: cam0/cam1, doffs,
baseline in mm when the unit is known, width/height, ndisp estimate) and optionally
``check.png`` (8-bit side-by-side preview with horizontal lines and valid ROI boxes).

Without a calibration (``--uncalibrated``) the homographies are estimated first, in the
calling process, from every pair of the rig together (:func:`estimate_uncalibrated`); the
items then only warp. ``calib.txt`` holds the rectified views' virtual cameras, the size and
the estimated disparity range, but no baseline (``rectification=uncalibrated``), and
``rectification.json`` the homographies ``H0``/``H1`` and what the estimate found in the pair.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

from ..errors import DataError
from ..io.pairs import StereoInput
from .items import WorkItem, check_output_paths, input_stamps, settings_digest

_MAPS_CACHE: dict = {}


def plan_items(pairs: list[StereoInput], outdir: str | Path, *, calib_path: str, alpha: float = 0.0,
               size: tuple[int, int] | None = None, interpolation: str = "linear", check: bool = False,
               ndisp: int | None = None, min_depth: float | None = None) -> list[WorkItem]:
    """One :class:`WorkItem` per pair; ``size`` is the rectified (width, height)."""
    items = []
    options = {"alpha": alpha, "size": list(size) if size else None, "interpolation": interpolation, "ndisp": ndisp,
               "min_depth": min_depth}
    for pair in pairs:
        out = Path(outdir) / pair.name
        outputs = _outputs(out, check)
        items.append(WorkItem(pair.name, {"left": pair.left, "right": pair.right, "calibration": str(calib_path)},
                              outputs, dict(options), folder=str(out), command="rectify",
                              config_digest=settings_digest(options)))
    check_output_paths(items, outdir)
    return items


def _outputs(folder: Path, check: bool, *more: str) -> dict[str, str]:
    """The output paths of one pair: images, masks, calib.txt, ``more`` files, check.png."""
    names = ["im0.png", "im1.png", "valid0.png", "valid1.png", "calib.txt", *more] + (["check.png"] if check else [])
    return {Path(name).stem: str(folder / name) for name in names}


def _maps_for(calib_path: str, alpha: float, size):
    from ..io.calib import load_calibration
    from ..rectification.maps import build_maps

    p = Path(calib_path)
    key = (str(p.resolve()), p.stat().st_mtime_ns, alpha, tuple(size) if size else None)
    if key not in _MAPS_CACHE:
        calib = load_calibration(p)
        _MAPS_CACHE.clear()  # one calibration per run; keep memory bounded
        _MAPS_CACHE[key] = (calib, build_maps(calib, alpha=alpha, size=tuple(size) if size else None))
    return _MAPS_CACHE[key]


def rectify_item(item: WorkItem) -> dict:
    """Rectify one pair (:func:`stereocli.rectify`; see the module docstring for outputs);
    returns run-record details."""
    from ..api import rectify
    from ..io.exif import orientation_note
    from ..io.images import read_image, write_image
    from ..io.middlebury import write_calib_txt

    opts = item.options
    calib, maps = _maps_for(item.inputs["calibration"], opts["alpha"], opts["size"])
    left, right = read_image(item.inputs["left"]), read_image(item.inputs["right"])
    w, h = calib.image_size
    for path, im in ((item.inputs["left"], left), (item.inputs["right"], right)):
        if im.shape[:2] != (h, w):
            raise DataError(f"{path}: image is {im.shape[1]}x{im.shape[0]} but the calibration is for {w}x{h}")
    if maps.rect.vertical:
        raise DataError(f"{item.inputs['calibration']}: vertical rig; stereocli rectifies horizontal pairs only")
    result = rectify(left, right, calib, interpolation=opts["interpolation"], ndisp=opts["ndisp"],
                     min_depth=opts["min_depth"], maps=maps)
    rect, mb = result.rectification, result.calib_txt
    out = item.outputs
    write_image(out["im0"], result.left)
    write_image(out["im1"], result.right)
    write_image(out["valid0"], _mask_image(result.left_valid))
    write_image(out["valid1"], _mask_image(result.right_valid))
    write_calib_txt(out["calib"], mb)
    if "check" in out:
        write_image(out["check"], result.check_image())
    span = dict(result.range, source="option") if result.range["source"] == "given" else result.range
    notes = [n for n in (orientation_note(item.inputs["left"]), orientation_note(item.inputs["right"])) if n]
    return {"size": list(rect.size), "f": float(rect.P1[0, 0]), "baseline_mm": mb.baseline, "doffs": mb.doffs,
            "ndisp": result.ndisp, "range": span, "roi_left": list(rect.roi1), "roi_right": list(rect.roi2),
            "valid_fraction_left": float(result.left_valid.mean()),
            "valid_fraction_right": float(result.right_valid.mean()), **({"warnings": notes} if notes else {})}


def _mask_image(valid):
    """A valid mask as ``valid0.png`` holds it: uint8, 255 valid, 0 not."""
    import numpy as np

    return np.where(valid, np.uint8(255), np.uint8(0))


# --------------------------------------------------------------------------- without a calibration

#: A pair of a rig is reported when the rig's homographies do not suit it: too few of its matches
#: fit them (another rig, or a camera that moved), or its inliers' residual vertical disparity is
#: above this (px, median).
RIG_DY_WARNING = 1.0


def plan_uncalibrated(pairs: list[StereoInput], outdir: str | Path, *, interpolation: str = "linear",
                      check: bool = False, ndisp: int | None = None, per_pair: bool = False) -> list[WorkItem]:
    """One :class:`WorkItem` per pair for ``rectify --uncalibrated``; :func:`estimate_uncalibrated`
    adds the homographies to their options. With one estimate for the whole rig (not
    ``per_pair``), every pair's outputs depend on every pair's images: each item's settings
    digest covers them all."""
    options = {"uncalibrated": True, "interpolation": interpolation, "ndisp": ndisp}
    rig = None if per_pair else [[pair.name, input_stamps({"left": pair.left, "right": pair.right})] for pair in pairs]
    items = [WorkItem(pair.name, {"left": pair.left, "right": pair.right},
                      _outputs(Path(outdir) / pair.name, check, "rectification.json"), dict(options),
                      folder=str(Path(outdir) / pair.name), command="rectify",
                      config_digest=settings_digest({**options, "per_pair": per_pair, "rig": rig}))
             for pair in pairs]
    check_output_paths(items, outdir)
    return items


class _PairImages:
    """The items' images, read when asked for (one pair in memory at a time)."""

    def __init__(self, items: list[WorkItem]) -> None:
        self.items = items

    def __len__(self) -> int:
        return len(self.items)

    def __getitem__(self, i: int):
        from ..io.images import read_image

        return read_image(self.items[i].inputs["left"]), read_image(self.items[i].inputs["right"])


def estimate_uncalibrated(items: list[WorkItem], *, per_pair: bool = False) -> dict:
    """Estimate the homographies of ``items`` (one pair for all of them, the rig; with
    ``per_pair`` one per item) and store them in each item's options; an item that cannot be
    rectified gets its ``error`` (it fails alone). Returns the report of every estimate."""
    from ..errors import StereoError
    from ..rectification.uncalibrated import estimate_rectification

    groups = [[item] for item in items] if per_pair else [items]
    rigs: list[dict[str, Any]] = []
    for group in groups:
        names = [item.name for item in group]
        try:
            estimate = estimate_rectification(_PairImages(group))
        except StereoError as exc:
            for item in group:
                item.error = str(exc)
            rigs.append({"pairs": names, "error": str(exc)})
            continue
        rect = estimate.rectification.as_dict()
        used = [item.name for item, pair in zip(group, estimate.pairs) if pair.error is None]
        rigs.append({"pairs": names, "estimated_from": used, "magsac_inliers": estimate.magsac_inliers,
                     **{k: v for k, v in rect.items() if k not in ("H0", "H1", "F")}})
        for item, pair in zip(group, estimate.pairs):
            if pair.error:
                item.error = pair.error
                continue
            item.options.update(rectification=rect, pair=pair.as_dict(),
                                range={"min_disp": pair.min_disp, "max_disp": pair.max_disp,
                                       "evidence": pair.evidence},
                                rig={"pairs": names, "estimated_from": used})
    return {"homographies": "one per pair" if per_pair else "one for all pairs", "rigs": rigs}


def rectify_uncalibrated_item(item: WorkItem) -> dict:
    """Warp one pair by the homographies :func:`estimate_uncalibrated` stored in its options."""
    import json
    import re

    from ..api import rectify
    from ..io.atomic import write_text
    from ..io.images import read_image, write_image
    from ..io.middlebury import write_calib_txt
    from ..rectification.uncalibrated import UncalibratedRectification

    opts = item.options
    rect = UncalibratedRectification.from_dict(opts["rectification"])
    left, right = read_image(item.inputs["left"]), read_image(item.inputs["right"])
    span = opts["range"]
    result = rectify(left, right, rect, interpolation=opts["interpolation"], ndisp=opts["ndisp"],
                     disparity_range=(span["min_disp"], span["max_disp"]))
    ndisp, valid0, valid1 = result.ndisp, result.left_valid, result.right_valid
    out = item.outputs
    write_image(out["im0"], result.left)
    write_image(out["im1"], result.right)
    write_image(out["valid0"], _mask_image(valid0))
    write_image(out["valid1"], _mask_image(valid1))
    write_calib_txt(out["calib"], result.calib_txt)
    record = {**opts["rectification"], "convention": "H0, H1: original pixel (x, y, 1) -> rectified pixel; "
              "pixel centres at integer coordinates", "rig": opts["rig"], "pair": opts["pair"], "range": span,
              "ndisp": ndisp}
    # One matrix row per line: the file is read by people as well as by programs.
    text = re.sub(r"\[\s+([^\[\]{}]*?)\s+\]", lambda m: "[" + " ".join(m.group(1).split()) + "]",
                  json.dumps(record, indent=2))
    write_text(out["rectification"], text + "\n")
    if "check" in out:
        write_image(out["check"], result.check_image())
    details = {"size": list(rect.size), "ndisp": ndisp, "range": {k: span[k] for k in ("min_disp", "max_disp")},
               **opts["pair"], "distortion": opts["rectification"]["distortion"],
               "valid_fraction_left": float(valid0.mean()), "valid_fraction_right": float(valid1.mean())}
    pair = opts["pair"]
    if len(opts["rig"]["pairs"]) > 1 and (not pair["fits"] or (pair["dy_median"] or 0) > RIG_DY_WARNING):
        details["warnings"] = [f"only {pair['inliers']} of {pair['matches']} matches fit the rig's homographies "
                               f"(residual vertical disparity {pair['dy_median'] or 0:.2f} px median); if this pair "
                               "comes from another rig, rectify it with --per-pair"]
    return details
