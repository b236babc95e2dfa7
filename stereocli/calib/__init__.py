"""Stereo calibration from target photos: detection (cached, parallel), OpenCV solve, report."""

from __future__ import annotations

import os

import numpy as np

from .detect import Detection, detect_all
from .pattern import Pattern, parse_pattern_size, parse_square
from .stereo import CalibOptions, CalibrationResult, build_views, calibrate_stereo, format_report

__all__ = ["CalibOptions", "CalibrationResult", "Detection", "Pattern", "calibrate_folder", "calibrate_pairs",
           "detect_all", "format_report", "parse_pattern_size", "parse_square"]


def calibrate_folder(folder: str | os.PathLike, pattern: Pattern, options: CalibOptions | None = None, *,
                     detector: str = "auto", jobs: int | None = None, cache: str | os.PathLike | None = None,
                     progress: bool | None = None, swap: bool = False) -> CalibrationResult:
    """Pair, detect and calibrate the photos in ``folder`` (paired by
    :func:`stereocli.io.pairs.find_calibration_pairs`).

    ``swap`` exchanges left and right (for rigs wired the other way round). Raises
    :class:`~stereocli.errors.DataError` when the target is found in no image or in too few pairs.
    """
    from ..errors import DataError
    from ..io.pairs import find_calibration_pairs

    pairs = find_calibration_pairs(folder)
    if swap:
        pairs = [(n, right, left) for n, left, right in pairs]
    paths = [p for _, left, right in pairs for p in (left, right)]
    cache_warnings: list[str] = []
    detections = detect_all(paths, pattern, detector=detector, jobs=jobs, cache=cache, progress=progress,
                            warnings=cache_warnings)
    if not any(d.found for d in detections.values()):
        first = detections[paths[0]]
        raise DataError(f"{folder}: target not found in any of the {len(paths)} images ({first.path}: "
                        f"{first.reason or 'not found'}); check --pattern (COLSxROWS inner corners) and --pattern-type")
    return _calibrate_detected(pairs, detections, pattern, options, cache_warnings, f"{folder}: ")


def calibrate_pairs(pairs: list, pattern: Pattern, options: CalibOptions | None = None, *, detector: str = "auto",
                    jobs: int | None = None, cache: str | os.PathLike | None = None, progress: bool | None = None,
                    swap: bool = False) -> CalibrationResult:
    """Detect and calibrate ``pairs``: ``(left, right)`` image paths or arrays (RGB or grey).

    Paths are detected as :func:`calibrate_folder` detects them (in parallel, cached in
    ``cache``); arrays are named ``pair<i>/left`` and ``pair<i>/right`` in the report.
    """
    from ..errors import DataError
    from .pattern import detect

    named: list[tuple[str, str, str]] = []
    arrays = {}
    for i, pair in enumerate(pairs):
        try:
            left, right = pair
        except (TypeError, ValueError):
            raise DataError(f"calibration pair {i}: expected (left, right)") from None
        keys: list[str] = []
        for side, image in (("left", left), ("right", right)):
            if isinstance(image, (str, os.PathLike)):
                keys.append(str(image))
            else:
                keys.append(f"pair{i}/{side}")
                arrays[keys[-1]] = image
        named.append((f"pair{i}", keys[0], keys[1]))
    if swap:
        named = [(n, right, left) for n, left, right in named]
    if not named:
        raise DataError("no calibration pairs given")
    paths = [p for _, left, right in named for p in (left, right) if p not in arrays]
    cache_warnings: list[str] = []
    detections = detect_all(paths, pattern, detector=detector, jobs=jobs, cache=cache, progress=progress,
                            warnings=cache_warnings)
    for key, image in arrays.items():
        image = np.asarray(image)
        corners, ids, reason = detect(image, pattern, detector=detector)
        detections[key] = Detection(path=key, size=(image.shape[1], image.shape[0]), corners=corners, ids=ids,
                                    reason=reason)
    return _calibrate_detected(named, detections, pattern, options, cache_warnings, "")


def _calibrate_detected(pairs: list[tuple[str, str, str]], detections: dict, pattern: Pattern,
                        options: CalibOptions | None, warnings: list[str], label: str) -> CalibrationResult:
    """Calibrate the named ``pairs`` from their ``detections``, with the detection cache's
    ``warnings`` added to the report; ``label`` starts the error for too few pairs."""
    from ..errors import DataError

    views, missing, size = build_views(pairs, detections, pattern)
    if len(views) < 3:
        raise DataError(f"{label}the target was found in both images of only {len(views)} pair(s); need at least 3"
                        + (f" (e.g. {missing[0]['image']}: {missing[0]['reason']})" if missing else ""))
    result = calibrate_stereo(views, size, pattern, options or CalibOptions(), missing=missing,
                              total_pairs=len(pairs))
    result.report["warnings"] += warnings
    return result
