"""The disparity range of a pair without a calibration: a coarse dense match, checked against
the sparse matches.

The pair is shrunk so that it is about :data:`COARSE_WIDTH` px wide (factor ``s``) and matched
densely by a small SGM (census 5×5, 4 paths) over a wide range, ``[−W/8, W/2)`` of the image
width, widened to take in every sparse match; uniqueness, left-right and speckle checks keep
only confident pixels. The range is then the 0.5th to 99.5th percentile of those disparities
(×s) and of the sparse matches' horizontal disparities, widened by a margin of ``2s + 4`` px
(a coarse pixel spans ``s`` full-resolution pixels, and thin structures vanish at the coarse
scale). Negative disparities are kept: they are legitimate on convergent rigs.

On the 19 scenes of MiddEval3 (Q) and Middlebury 2001/2003 the range covers at least 99.9 %
of the ground truth's finite disparities of every scene, with ``ndisp`` at most 0.8 × (2 × the
ground-truth span + 32) (``tests/test_disparity_range.py``, docs/design.md).
"""

from __future__ import annotations

import functools
from dataclasses import asdict, dataclass

import cv2
import numpy as np

from ..errors import DataError
from .points import PointMatches, match_points

#: Width (px) of the coarse dense match.
COARSE_WIDTH = 160
#: Percentile cut at each end of the disparity distribution (outliers beyond it are ignored).
TAIL_PERCENT = 0.5
#: Coarse pixels with a confident disparity needed (as a fraction of the image) when the
#: sparse matches are too few to decide alone.
MIN_VALID_FRACTION = 0.02
#: Sparse matches that decide a range on their own when the coarse match finds too little.
MIN_SPARSE = 30
#: Coarse winners at an end of the search are dropped when they are fewer than this share.
END_SHARE = 0.01
#: Rows the coarse match needs at least (its census window is 5 x 5).
MIN_COARSE_ROWS = 5


@dataclass(frozen=True)
class DisparityRange:
    """A pair's search range ``[min_disp, min_disp + ndisp)`` in px, with its evidence."""

    min_disp: int
    ndisp: int
    scale: int  # shrink factor of the coarse match
    coarse_valid: float  # fraction of coarse pixels with a confident disparity
    dense_percentiles: tuple[float, float] | None  # 0.5 / 99.5 percentiles of the coarse disparities (px)
    sparse_matches: int
    sparse_percentiles: tuple[float, float] | None  # the same of the sparse matches' disparities (px)
    margin: int  # px added at each end

    @property
    def max_disp(self) -> int:
        return self.min_disp + self.ndisp - 1

    def as_dict(self) -> dict:
        out = asdict(self)
        for key in ("dense_percentiles", "sparse_percentiles"):
            if out[key] is not None:
                out[key] = [round(float(v), 2) for v in out[key]]
        out["coarse_valid"] = round(self.coarse_valid, 4)
        return out


@functools.lru_cache(maxsize=8)
def _coarse_config(speckle: int, threads: int = 0):
    from ..matching.config import validate

    return validate({
        "cost": {"name": "census", "window": [5, 5]},
        "optimizer": {"name": "sgm", "paths": 4},
        "refinement": [{"name": "uniqueness", "ratio": 0.1}, {"name": "lr_check", "max_diff": 1},
                       {"name": "speckle", "max_size": speckle, "max_diff": 1}],
        "runtime": {"threads": threads},
    }, "disparity range estimate")


def coarse_scale(width: int) -> int:
    """The shrink factor of the coarse match of an image ``width`` px wide."""
    return max(1, int(round(width / COARSE_WIDTH)))


def _shrink(image: np.ndarray, scale: int) -> np.ndarray:
    if scale == 1:
        return np.asarray(image, np.float32)
    h, w = image.shape[:2]
    return cv2.resize(np.asarray(image, np.float32), (w // scale, h // scale), interpolation=cv2.INTER_AREA)


def _textured(image: np.ndarray) -> np.ndarray:
    """(H, W) bool: pixels whose 5×5 neighbourhood varies by more than one grey level (RMS).
    Elsewhere every disparity matches equally well, whatever the checks say."""
    grey = image if image.ndim == 2 else image[..., :3] @ np.array([0.299, 0.587, 0.114], np.float32)
    grey = np.ascontiguousarray(grey, dtype=np.float32)
    mean = cv2.boxFilter(grey, -1, (5, 5))
    variance = cv2.boxFilter(grey * grey, -1, (5, 5)) - mean * mean
    return variance > 1.0


def coarse_disparities(left: np.ndarray, right: np.ndarray, lo: float, hi: float,
                       threads: int = 0) -> tuple[np.ndarray, int, float]:
    """Confident disparities (px, full resolution) of a coarse dense match searching ``[lo, hi]``
    px on ``threads`` kernel threads (0: one per core); returns ``(values, scale, valid fraction)``."""
    from ..matching.pipeline import match_pair

    h, w = left.shape[:2]
    scale = coarse_scale(w)
    small_left, small_right = _shrink(left, scale), _shrink(right, scale)
    ws = small_left.shape[1]
    lo_c, hi_c = int(np.floor(lo / scale)), int(np.ceil(hi / scale))
    lo_c, hi_c = max(lo_c, -(ws - 1)), min(hi_c, ws - 1)
    speckle = max(20, int(0.005 * small_left.shape[0] * ws))  # isolated blobs under 0.5 % of the image
    result = match_pair(small_left, small_right, _coarse_config(speckle, threads), min_disp=lo_c,
                        ndisp=hi_c - lo_c + 1)
    finite = np.isfinite(result.disparity) & _textured(small_left)
    values = result.disparity[finite]
    # A winner at an end of the search is what a mismatch looks like (nothing better in range);
    # a few are dropped, many mean a surface beyond the end and are kept.
    at_end = (values <= lo_c + 1) | (values >= hi_c - 1)
    if values.size and at_end.mean() < END_SHARE:
        values = values[~at_end]
    return values * np.float32(w / ws), scale, float(finite.mean())


def estimate_range(left: np.ndarray, right: np.ndarray, matches: PointMatches | None = None, *,
                   threads: int = 0) -> DisparityRange:
    """Estimate ``[min_disp, min_disp + ndisp)`` for a rectified pair (``(H, W)`` or ``(H, W, 3)``).

    ``matches``: sparse matches of the pair (:func:`~stereocli.features.points.match_points`,
    computed here if not given); only those on the same row (|dy − median| ≤ 1 px) count.
    Raises :class:`DataError` when neither the coarse match nor the sparse matches find enough
    texture to decide, and when the pair has too few rows for the coarse match.
    ``threads``: kernel threads of the coarse match (0: one per core; the range does not depend
    on it).
    """
    if left.shape[:2] != right.shape[:2]:
        raise DataError("left and right differ in size")
    h, w = left.shape[:2]
    scale = coarse_scale(w)
    if h < MIN_COARSE_ROWS * scale:
        raise DataError(f"cannot estimate the disparity range of a {w}x{h} px pair: the coarse match needs "
                        f"{MIN_COARSE_ROWS * scale} rows at this width; give --ndisp N (and --min-disp)")
    if matches is None:
        matches = match_points(left, right)
    dx = matches.dx
    if len(dx):
        dx = dx[np.abs(matches.dy - np.median(matches.dy)) <= 1.0]
    sparse = tuple(np.percentile(dx, [TAIL_PERCENT, 100 - TAIL_PERCENT])) if len(dx) >= MIN_SPARSE else None
    lo, hi = -w / 8.0, w / 2.0
    if sparse is not None:
        lo, hi = min(lo, sparse[0] - 16), max(hi, sparse[1] + 16)
    values, scale, valid = coarse_disparities(left, right, lo, hi, threads)
    dense = None
    if valid >= MIN_VALID_FRACTION and len(values):
        dense = tuple(np.percentile(values, [TAIL_PERCENT, 100 - TAIL_PERCENT]))
    if dense is None and sparse is None:
        raise DataError(f"cannot estimate the disparity range: too little texture ({len(dx)} sparse matches, "
                        f"{valid:.1%} of the coarse match confident); give --ndisp N (and --min-disp)")
    ends = [e for e in (dense, sparse) if e is not None]
    margin = 2 * scale + 4
    low = int(np.floor(min(e[0] for e in ends) - margin))
    high = int(np.ceil(max(e[1] for e in ends) + margin))
    return DisparityRange(low, high - low + 1, scale, valid, dense, len(dx), sparse, margin)
