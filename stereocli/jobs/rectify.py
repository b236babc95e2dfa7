"""``stereocli rectify`` as batch work: pairs -> work items, and the item function workers run.

Per pair, ``OUTDIR/<name>/`` receives ``im0.png``/``im1.png`` (rectified left/right, input
dtype and channels kept), ``valid0.png``/``valid1.png`` (255 = pixel sampled from inside the
source image), ``calib.txt`` (Middlebury style for the rectified pair: cam0/cam1, doffs,
baseline in mm when the unit is known, width/height, ndisp estimate) and optionally
``check.png`` (8-bit side-by-side preview with horizontal lines and valid ROI boxes).
"""

from __future__ import annotations

from pathlib import Path

from ..errors import DataError
from ..io.pairs import StereoInput
from .items import WorkItem

_MAPS_CACHE: dict = {}


def plan_items(pairs: list[StereoInput], outdir: str | Path, *, calib_path: str, alpha: float = 0.0,
               size: tuple[int, int] | None = None, interpolation: str = "linear", check: bool = False,
               ndisp: int | None = None, min_depth: float | None = None) -> list[WorkItem]:
    """One :class:`WorkItem` per pair; ``size`` is the rectified (width, height)."""
    items = []
    for pair in pairs:
        out = Path(outdir) / pair.name
        outputs = {k: str(out / f) for k, f in (("im0", "im0.png"), ("im1", "im1.png"), ("valid0", "valid0.png"),
                                                ("valid1", "valid1.png"), ("calib", "calib.txt"))}
        if check:
            outputs["check"] = str(out / "check.png")
        items.append(WorkItem(pair.name, {"left": pair.left, "right": pair.right, "calibration": str(calib_path)},
                              outputs, {"alpha": alpha, "size": list(size) if size else None,
                                        "interpolation": interpolation, "ndisp": ndisp, "min_depth": min_depth}))
    return items


def _maps_for(calib_path: str, alpha: float, size):
    from ..io.calib import load_calibration
    from ..rectify.maps import build_maps

    p = Path(calib_path)
    key = (str(p.resolve()), p.stat().st_mtime_ns, alpha, tuple(size) if size else None)
    if key not in _MAPS_CACHE:
        calib = load_calibration(p)
        _MAPS_CACHE.clear()  # one calibration per run; keep memory bounded
        _MAPS_CACHE[key] = (calib, build_maps(calib, alpha=alpha, size=tuple(size) if size else None))
    return _MAPS_CACHE[key]


def rectify_item(item: WorkItem) -> dict:
    """Rectify one pair (see the module docstring for outputs); returns run-record details."""
    from ..io.calib import to_middlebury
    from ..io.images import read_image, write_image
    from ..io.middlebury import write_calib_txt
    from ..rectify.maps import check_image, estimate_ndisp, rectified_calibration, rectify_images

    opts = item.options
    calib, maps = _maps_for(item.inputs["calibration"], opts["alpha"], opts["size"])
    left, right = read_image(item.inputs["left"]), read_image(item.inputs["right"])
    w, h = calib.image_size
    for path, im in ((item.inputs["left"], left), (item.inputs["right"], right)):
        if im.shape[:2] != (h, w):
            raise DataError(f"{path}: image is {im.shape[1]}x{im.shape[0]} but the calibration is for {w}x{h}")
    if maps.rect.vertical:
        raise DataError(f"{item.inputs['calibration']}: vertical rig; stereocli rectifies horizontal pairs only")
    r0, r1 = rectify_images(left, right, maps, interpolation=opts["interpolation"])
    rect = maps.rect
    ndisp = opts["ndisp"] or estimate_ndisp(rect, min_depth=opts["min_depth"] or calib.extra.get("board_depth_min"))
    mb = to_middlebury(rectified_calibration(calib, rect=rect), ndisp=ndisp)
    out = item.outputs
    write_image(out["im0"], r0)
    write_image(out["im1"], r1)
    write_image(out["valid0"], maps.valid1)
    write_image(out["valid1"], maps.valid2)
    write_calib_txt(out["calib"], mb)
    if "check" in out:
        write_image(out["check"], check_image(r0, r1, rect))
    return {"size": list(rect.size), "f": float(rect.P1[0, 0]), "baseline_mm": mb.baseline, "doffs": mb.doffs,
            "ndisp": ndisp, "roi_left": list(rect.roi1), "roi_right": list(rect.roi2),
            "valid_fraction_left": float((maps.valid1 > 0).mean()),
            "valid_fraction_right": float((maps.valid2 > 0).mean())}
