"""Stereo calibration from target photos: detection (cached, parallel), OpenCV solve, report."""

from __future__ import annotations

import os

from .detect import Detection, detect_all
from .pattern import Pattern, parse_pattern_size
from .stereo import CalibOptions, CalibrationResult, build_views, calibrate_stereo, format_report

__all__ = ["CalibOptions", "CalibrationResult", "Detection", "Pattern", "calibrate_folder", "detect_all",
           "format_report", "parse_pattern_size"]


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
        pairs = [(n, r, l) for n, l, r in pairs]
    paths = [p for _, l, r in pairs for p in (l, r)]
    cache_warnings: list[str] = []
    detections = detect_all(paths, pattern, detector=detector, jobs=jobs, cache=cache, progress=progress,
                            warnings=cache_warnings)
    if not any(d.found for d in detections.values()):
        first = detections[paths[0]]
        raise DataError(f"{folder}: target not found in any of the {len(paths)} images ({first.path}: "
                        f"{first.reason or 'not found'}); check --pattern (COLSxROWS inner corners) and --pattern-type")
    views, missing, size = build_views(pairs, detections, pattern)
    if len(views) < 3:
        raise DataError(f"{folder}: the target was found in both images of only {len(views)} pair(s); need at least 3"
                        + (f" (e.g. {missing[0]['image']}: {missing[0]['reason']})" if missing else ""))
    result = calibrate_stereo(views, size, pattern, options or CalibOptions(), missing=missing,
                              total_pairs=len(pairs))
    result.report["warnings"] += cache_warnings
    return result
