"""Per-scene error pictures (8-bit previews): disparity, GT, absolute error, bad-pixel overlay.

Estimate and GT share one colour scale (the GT's finite range), so equal colours mean equal
disparities; every picture carries a legend bar. Errors are in the report's units (e.g.
full-resolution px for a Q GT).
"""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np

from ..errors import check_outputs_free
from ..io.images import read_image, write_image
from ..io.pairs import output_name
from ..viz import colorize_disparity, colorize_error, gray_preview, legend_bar, with_legend
from .metrics import KITTI_ABS_THRESH, KITTI_REL_THRESH, abs_error
from .scoring import EvalReport, SceneResult

MAP_FILES = ("disparity.png", "gt.png", "error.png", "bad.png")

_RED = (230, 30, 30)
_ORANGE = (255, 160, 0)
_BLUE = (40, 90, 255)


def primary_threshold(result: SceneResult, thresholds: tuple[float, ...]) -> float:
    """The threshold drawn in the bad-pixel overlay: 1.0 for v2, 2.0 for MiddEval3 (if scored)."""
    preferred = 1.0 if result.kind == "middlebury-v2" else 2.0
    if preferred in thresholds:
        return preferred
    return sorted(thresholds)[len(thresholds) // 2]


def _legend_boxes(items: list[tuple[tuple[int, int, int], str]], width: int) -> np.ndarray:
    canvas = np.full((18 * len(items) + 4, max(width, 60), 3), 255, dtype=np.uint8)
    for i, (colour, text) in enumerate(items):
        y = 4 + 18 * i
        cv2.rectangle(canvas, (4, y), (16, y + 12), colour, -1)
        cv2.putText(canvas, text, (22, y + 11), cv2.FONT_HERSHEY_SIMPLEX, 0.4, (0, 0, 0), 1, cv2.LINE_AA)
    return canvas


def scene_images(result: SceneResult, thresholds: tuple[float, ...]) -> dict[str, np.ndarray]:
    """RGB uint8 pictures of one scored scene (needs ``keep_arrays=True`` at scoring time).

    Keys: ``estimate``, ``gt``, ``error``, ``bad`` and ``left`` when the left image is found.
    """
    a = result.arrays
    est, gt, masks, unit = a["estimate"], a["gt"], a["masks"], a["unit"]
    h, w = gt.shape
    finite_gt = gt[np.isfinite(gt)]
    vmin, vmax = (float(finite_gt.min()), float(finite_gt.max())) if finite_gt.size else (0.0, 1.0)
    if vmax <= vmin:
        vmax = vmin + 1.0
    disp_legend = legend_bar(vmin, vmax, w, kind="disparity", label="px")
    images: dict[str, np.ndarray] = {
        "estimate": with_legend(colorize_disparity(est, vmin, vmax), disp_legend),
        "gt": with_legend(colorize_disparity(gt, vmin, vmax), disp_legend),
    }
    err = abs_error(est, gt) * np.float32(unit)
    known = np.isfinite(gt)
    invalid = known & ~np.isfinite(est)
    err_max = float(max(thresholds)) if thresholds else 4.0
    err_rgb = colorize_error(np.where(invalid, err_max, err), err_max, valid=known)
    err_rgb[invalid] = (0, 200, 255)
    units = "px (full res)" if unit != 1.0 else "px"
    images["error"] = with_legend(err_rgb, legend_bar(0.0, err_max, w, kind="error", label=units))

    base = None
    if result.left_image is not None and Path(result.left_image).is_file():
        left = read_image(result.left_image)
        if left.dtype == np.uint16:
            left = (left / 257.0).astype(np.uint8)
        if left.ndim == 2:
            left = np.repeat(left[..., None], 3, axis=2)
        if left.shape[:2] != (h, w):
            left = cv2.resize(left, (w, h), interpolation=cv2.INTER_AREA)
        images["left"] = left.astype(np.uint8)
        base = gray_preview(images["left"])
    if base is None:
        base = np.full((h, w, 3), 128, dtype=np.uint8)
    overlay = (base.astype(np.float32) * 0.6).astype(np.uint8)
    primary_mask = masks.get("nonocc")
    if primary_mask is None:
        primary_mask = known
    scored_all = masks.get("all") if masks.get("all") is not None else known
    if result.kind == "kitti":
        with np.errstate(invalid="ignore", divide="ignore"):
            bad = (err > KITTI_ABS_THRESH) & (err / np.abs(gt) > KITTI_REL_THRESH)
        label = "D1 outlier"
    else:
        t = primary_threshold(result, thresholds)
        bad = err > np.float32(t)
        label = f"bad > {t:g} {units}"
    unscored = ~(scored_all & known)
    overlay[unscored] = (overlay[unscored] * 0.4).astype(np.uint8)
    overlay[bad & primary_mask & known & ~invalid] = _RED
    overlay[bad & ~primary_mask & scored_all & known & ~invalid] = _ORANGE
    overlay[invalid & scored_all] = _BLUE
    legend = _legend_boxes([(_RED, f"{label} (nonocc)"), (_ORANGE, f"{label} (occluded)"),
                            (_BLUE, "invalid estimate"), ((30, 30, 30), "not scored")], w)
    images["bad"] = with_legend(overlay, legend)
    return images


def write_error_maps(report: EvalReport, out_dir: str | Path, *, overwrite: bool = False) -> list[Path]:
    """Write ``OUT/<scene>/{disparity,gt,error,bad}.png`` for every scored scene (``<scene>``
    made safe as ``match`` makes its output names, :func:`~stereocli.io.pairs.output_name`)."""
    out_dir = Path(out_dir)
    targets = [out_dir / output_name(s.name) / f for s in report.scenes for f in MAP_FILES]
    check_outputs_free(targets, overwrite=overwrite)
    written = []
    for s in report.scenes:
        imgs = scene_images(s, report.thresholds)
        for key, fname in zip(("estimate", "gt", "error", "bad"), MAP_FILES):
            path = out_dir / output_name(s.name) / fname
            write_image(path, imgs[key])
            written.append(path)
    return written
