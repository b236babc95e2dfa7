"""What a pair's images say before it is matched: its disparity range when none is given, and
how well its rows are aligned (the survey that :func:`stereocli.match` and ``stereocli match``
run on every pair).

The range is ``[min_disp, min_disp + ndisp)`` given by the caller, else estimated from the
images (:mod:`.disparity_range`). The rows are measured from sparse matches (:mod:`.alignment`),
or, when the range is known and the config's ``row_align`` measures them, by that stage's fit
during the match (:func:`rows_from_match`: its tracks are the better measurement, and the sparse
matches would add about an eighth to a Q-size pair's matching time). A misaligned pair gets a
warning, or fails with ``require_aligned``.

The records are plain dicts, as the run record (``params.json``) stores them.
"""

from __future__ import annotations

import time

import numpy as np

from ..errors import DataError, named

__all__ = ["RECTIFY_FIRST", "ROWS_NOT_ALIGNED", "check_range_meets_image", "measures_rows", "rows_corrected",
           "rows_from_match", "survey_pair"]

#: The survey's warning for a pair whose rows are off by more than the alignment threshold, and
#: its advice (replaced by what ``row_align`` did when the matching corrected the rows).
ROWS_NOT_ALIGNED = "rows not aligned"
RECTIFY_FIRST = ("rectify the pair first (stereocli rectify --calib RIG.yml, or stereocli rectify --uncalibrated "
                 "without a calibration)")


def check_range_meets_image(min_disp: int, ndisp: int, width: int, *, name: str = "") -> None:
    """Raise :class:`DataError` when no disparity of ``[min_disp, min_disp + ndisp)`` puts a left
    pixel's match inside an image ``width`` px wide: every pixel would be invalid."""
    if min_disp >= width or min_disp + ndisp - 1 <= -width:
        raise DataError(named(name, f"the disparity range {min_disp}..{min_disp + ndisp - 1} px lies outside the "
                                     f"{width} px wide image (a match needs |d| < {width}); no pixel can match "
                                     "(check --min-disp)"))


def survey_pair(left: np.ndarray, right: np.ndarray, *, min_disp: int | None, ndisp: int | None,
                source: str | None, name: str = "", left_valid: np.ndarray | None = None,
                right_valid: np.ndarray | None = None, measure_rows: bool = True, require_aligned: bool = False,
                threads: int = 0) -> dict:
    """Row alignment of the pair, and its disparity range when it is to be estimated
    (``ndisp`` None).

    ``left``, ``right``: (H, W) or (H, W, 3) RGB views; ``source`` names where a given range
    came from. Returns the run-record entries ``range`` (``min_disp``, ``ndisp``, ``source``
    and, when estimated, the ``evidence``), ``alignment`` and ``warnings``, plus
    ``survey_seconds``. Raises :class:`DataError` (prefixed with ``name``) when a range cannot
    be estimated, or when the rows are not aligned and ``require_aligned``. Without
    ``measure_rows`` and with the range known, nothing is matched: ``alignment`` is None and
    the caller measures the rows (:func:`rows_from_match`). ``threads``: kernel threads of the
    estimate's coarse match (0: one per core).
    """
    from .points import match_points

    t0 = time.perf_counter()
    span: dict = {"min_disp": min_disp, "ndisp": ndisp, "source": source}
    if ndisp is not None and not measure_rows:
        return {"range": span, "alignment": None, "warnings": [], "survey_seconds": 0.0}
    matches = match_points(left, right, left_valid=left_valid, right_valid=right_valid)
    rows = _rows_from_matches(name, matches, require_aligned)
    if ndisp is None:
        from .disparity_range import estimate_range

        try:
            estimate = estimate_range(left, right, matches, threads=threads)
        except DataError as exc:
            raise DataError(named(name, str(exc))) from None
        span.update(min_disp=estimate.min_disp, ndisp=estimate.ndisp, evidence=estimate.as_dict())
    return {"range": span, **rows, "survey_seconds": round(time.perf_counter() - t0, 4)}


def _rows_from_matches(name: str, matches, require_aligned: bool) -> dict:
    """``alignment`` and ``warnings`` from the pair's sparse matches (see :func:`_row_warnings`)."""
    from .alignment import row_alignment

    alignment = row_alignment(matches)
    return {"alignment": {"source": "sparse matches", **alignment.as_dict()},
            "warnings": _row_warnings(name, alignment.aligned, alignment.describe(), require_aligned)}


def _row_warnings(name: str, aligned: bool, description: str, require_aligned: bool) -> list[str]:
    """The rows warning of a misaligned pair (none for an aligned one); raises
    :class:`DataError` instead with ``require_aligned``."""
    if aligned:
        return []
    message = f"{ROWS_NOT_ALIGNED}: {description}; {RECTIFY_FIRST}"
    if require_aligned:
        raise DataError(named(name, f"{message} (--require-aligned)"))
    return [message]


def measures_rows(config) -> bool:
    """Whether the validated ``config`` measures the pair's rows in its preprocessing
    (``row_align`` with ``measure``)."""
    return any(call.stage.name == "row_align" and call.params.measure for call in config.preprocess)


def rows_from_match(note: dict | None, left: np.ndarray, right: np.ndarray, *, name: str = "",
                    left_valid: np.ndarray | None = None, right_valid: np.ndarray | None = None,
                    require_aligned: bool = False) -> dict:
    """``alignment`` and ``warnings`` from ``row_align``'s fit during the match (``note``, its
    ``stage_notes`` entry) when it measured the rows, else from sparse matches as the survey
    takes them (too few tracks, or tracks that scatter about their plane). A pair counts as
    misaligned when the fitted plane departs from the rows by more than the survey's threshold
    anywhere in the image."""
    from .alignment import DEFAULT_THRESHOLD

    if not note or not note.get("measured"):
        from .points import match_points

        return _rows_from_matches(name, match_points(left, right, left_valid=left_valid, right_valid=right_valid),
                                  require_aligned)
    largest = float(note["largest_px"])
    aligned = largest <= DEFAULT_THRESHOLD
    description = (f"vertical disparity up to {largest:.1f} px (row_align's plane through {note['tracks']} tracks, "
                   f"offset {note['offset_px']:+.2f} px at the centre)")
    return {"alignment": {"source": "row_align", "tracks": note["tracks"], "max_offset": round(largest, 3),
                          "threshold": DEFAULT_THRESHOLD, "aligned": aligned},
            "warnings": _row_warnings(name, aligned, description, require_aligned)}


def rows_corrected(warnings: list[str], note: dict | None) -> list[str]:
    """The survey's ``warnings`` with the rows warning's advice replaced by what ``row_align``
    did, when it moved the right view's rows (``note``: its ``stage_notes`` entry)."""
    if not note or not note.get("applied"):
        return warnings
    done = f"row_align moved the right view's rows by up to {note['largest_px']:.2f} px (params.json: stage_notes)"
    return [w[:-len(RECTIFY_FIRST)] + done if w.startswith(ROWS_NOT_ALIGNED) and w.endswith(RECTIFY_FIRST) else w
            for w in warnings]
