"""Scoring rules of the official stereo evaluators, on arrays.

* **MiddEval3** (``evaldisp.cpp`` of the MiddEval3 SDK): a half/quarter-size estimate is
  upsampled to the GT size by pixel replication and its disparities multiplied by the factor
  (only 1x, 2x, 4x allowed); valid estimates are clipped to ``[0, factor * ndisp]`` (``ndisp``
  is given at the estimate's resolution); GT ``inf`` is not scored; an ``inf`` estimate is
  *invalid*: counted in ``invalid`` and as bad; ``avgerr`` (and here ``rms`` and the error
  quantiles) average over valid pixels only. Errors are computed in float32 like the SDK, and
  a pixel is bad when ``err > threshold`` (strictly).
* **Middlebury v2** (2001/2003): the same arithmetic with 8-bit GT decoded by the scene
  scale and no clipping (the v2 kit had none); standard threshold 1.0.
* **KITTI 2015** (devkit ``evaluate_stereo.cpp``): missing estimates are first filled by
  :func:`kitti_interpolate_background`; a pixel is a D1 outlier when ``|d - gt| > 3`` **and**
  ``|d - gt| / |gt| > 0.05``; density = share of GT pixels with an original estimate.

All functions take and return numpy arrays; disparities are float32 pixels with ``+inf`` for
invalid / unknown (stereocli convention).
"""

from __future__ import annotations

import math
from typing import Iterable, Sequence

import numpy as np

from ..errors import DataError
from .kernels import kitti_fill_cols, kitti_fill_rows, zbuffer_visible

#: Default bad-pixel thresholds (px); JSON keys are ``bad0.5``, ``bad1.0``, ...
DEFAULT_THRESHOLDS: tuple[float, ...] = (0.5, 1.0, 2.0, 4.0)
#: Error quantiles (percent) reported as A50, A90, A95, A99.
DEFAULT_QUANTILES: tuple[float, ...] = (50.0, 90.0, 95.0, 99.0)
#: KITTI 2015 D1 outlier thresholds (devkit ABS_THRESH, REL_THRESH).
KITTI_ABS_THRESH = 3.0
KITTI_REL_THRESH = 0.05
#: Allowed GT/estimate size ratios (MiddEval3 SDK).
ALLOWED_FACTORS = (1, 2, 4)


def threshold_key(threshold: float) -> str:
    """JSON key of a bad-pixel threshold: 0.5 -> ``bad0.5``, 1 -> ``bad1.0``, 0.25 -> ``bad0.25``."""
    t = float(threshold)
    text = f"{t:.1f}" if round(t, 1) == t else f"{t:g}"
    return f"bad{text}"


def quantile_key(q: float) -> str:
    return f"A{q:g}"


def check_estimate(disp: np.ndarray, name: str = "estimate") -> np.ndarray:
    """Validate an estimate: 2-D, no NaN (stereocli marks invalid with +inf). Returns float32."""
    disp = np.asarray(disp)
    if disp.ndim != 2:
        raise DataError(f"{name}: a disparity map must be 2-D, got shape {disp.shape}")
    disp = disp.astype(np.float32, copy=False)
    if np.isnan(disp).any():
        raise DataError(f"{name}: disparity contains NaN; mark invalid pixels with +inf")
    return disp


def size_factor(est_shape: Sequence[int], gt_shape: Sequence[int], name: str = "estimate") -> int:
    """GT size / estimate size: 1, 2 or 4 exactly in both axes, else :class:`DataError`."""
    eh, ew = est_shape[:2]
    gh, gw = gt_shape[:2]
    factor = gw // ew if ew else 0
    if factor not in ALLOWED_FACTORS or factor * ew != gw or factor * eh != gh:
        raise DataError(
            f"{name}: size {ew}x{eh} does not match the GT size {gw}x{gh} "
            f"(the GT must be exactly 1, 2 or 4 times the estimate size)"
        )
    return factor


def upsample_nearest(disp: np.ndarray, factor: int) -> np.ndarray:
    """Upsample by pixel replication and multiply disparities by ``factor`` (inf stays inf).

    GT pixel (y, x) takes estimate pixel (y // factor, x // factor), as in MiddEval3's
    ``evaldisp``: ``d = scale * disp.Pixel(x / scale, y / scale)``.
    """
    disp = np.asarray(disp, dtype=np.float32)
    if factor == 1:
        return disp
    up = np.repeat(np.repeat(disp, factor, axis=0), factor, axis=1)
    return (up * np.float32(factor)).astype(np.float32)


def downsample_gt(gt: np.ndarray, factor: int) -> np.ndarray:
    """Unofficial ``--same-resolution`` helper: GT at the estimate's size (nearest, /factor)."""
    if factor == 1:
        return gt
    return (gt[::factor, ::factor] / np.float32(factor)).astype(np.float32)


def downsample_mask(mask: np.ndarray, factor: int) -> np.ndarray:
    return mask if factor == 1 else mask[::factor, ::factor]


def clip_estimate(disp: np.ndarray, max_disp: float | None) -> np.ndarray:
    """Clip valid (finite) disparities to ``[0, max_disp]``; inf stays inf. ``None`` = no clip."""
    if max_disp is None:
        return disp
    out = disp.copy()
    finite = np.isfinite(out)
    out[finite] = np.clip(out[finite], np.float32(0.0), np.float32(max_disp))
    return out


def prepare_estimate(
    est: np.ndarray,
    gt_shape: Sequence[int],
    *,
    ndisp: float | None = None,
    name: str = "estimate",
) -> tuple[np.ndarray, int]:
    """MiddEval3 preparation: upsample to the GT size (x factor), then clip to [0, factor*ndisp].

    ``ndisp`` is at the estimate's resolution (as the SDK's ``maxdisp``). Returns the prepared
    (Hgt, Wgt) float32 map and the factor.
    """
    est = check_estimate(est, name)
    factor = size_factor(est.shape, gt_shape, name)
    up = upsample_nearest(est, factor)
    max_disp = None if ndisp is None else float(factor) * float(ndisp)
    return clip_estimate(up, max_disp), factor


def abs_error(est: np.ndarray, gt: np.ndarray) -> np.ndarray:
    """|est - gt| in float32 (like the SDKs); inf where either is inf."""
    with np.errstate(invalid="ignore"):
        err = np.abs(est.astype(np.float32) - gt.astype(np.float32))
    err[~(np.isfinite(est) & np.isfinite(gt))] = np.inf
    return err


def _summary(err_valid: np.ndarray, quantiles: Iterable[float]) -> dict[str, float | None]:
    out: dict[str, float | None] = {}
    if err_valid.size:
        e64 = err_valid.astype(np.float64)
        out["avgerr"] = float(e64.mean())
        out["rms"] = float(math.sqrt(float(np.mean(e64 * e64))))
        qs = list(quantiles)
        if qs:
            # Linear interpolation between order statistics (numpy default).
            for q, v in zip(qs, np.percentile(e64, qs)):
                out[quantile_key(q)] = float(v)
    else:
        out["avgerr"] = None
        out["rms"] = None
        for q in quantiles:
            out[quantile_key(q)] = None
    return out


def middlebury_stats(
    est: np.ndarray,
    gt: np.ndarray,
    mask: np.ndarray | None,
    *,
    thresholds: Sequence[float] = DEFAULT_THRESHOLDS,
    quantiles: Sequence[float] = DEFAULT_QUANTILES,
    unit: float = 1.0,
) -> dict[str, float | int | None]:
    """Bad-pixel statistics over one mask, MiddEval3 style.

    Parameters
    ----------
    est : (H, W) float32 prepared estimate (already at the GT size and clipped), inf = invalid.
    gt : (H, W) float32 ground truth, inf = unknown (never scored).
    mask : (H, W) bool, pixels to score (``None`` = all finite-GT pixels).
    thresholds : bad thresholds in *reported* units.
    unit : factor turning GT-resolution pixels into reported pixels (4 for "quarter-resolution
        GT, full-resolution units"); errors are multiplied by it before thresholding and
        averaging, so ``bad2.0`` at ``unit=4`` means an error above 0.5 GT pixels.

    Returns
    -------
    dict with ``n`` (scored pixels), ``coverage`` (% of the image scored), ``badX`` (% of scored
    pixels with err > X, invalid counted as bad), ``invalid`` (%), ``avgerr``, ``rms``,
    ``A50``... (over valid pixels only, reported units).
    """
    scored = np.isfinite(gt)
    if mask is not None:
        scored &= mask
    n = int(scored.sum())
    valid = scored & np.isfinite(est)
    n_valid = int(valid.sum())
    n_invalid = n - n_valid
    err = abs_error(est[valid], gt[valid])
    if unit != 1.0:
        err = (err * np.float32(unit)).astype(np.float32)
    out: dict[str, float | int | None] = {"n": n, "coverage": 100.0 * n / gt.size if gt.size else 0.0}
    for t in thresholds:
        bad = int(np.count_nonzero(err > np.float32(t)))
        out[threshold_key(t)] = 100.0 * (bad + n_invalid) / n if n else None
    out["invalid"] = 100.0 * n_invalid / n if n else None
    out.update(_summary(err, quantiles))
    return out


# --------------------------------------------------------------------------------------------
# KITTI


def kitti_valid(disp: np.ndarray) -> np.ndarray:
    """KITTI validity: finite and ``>= 0`` (the devkit's ``isValid`` is ``d >= 0``)."""
    return np.isfinite(disp) & (disp >= 0)


def kitti_interpolate_background(disp: np.ndarray) -> np.ndarray:
    """KITTI devkit ``interpolateBackground``: fill invalid estimates, returns a new array.

    Along each row, an interior run of invalid pixels takes the *smaller* (background) of its
    two valid neighbours; runs touching the left/right border take the nearest valid value of
    the row; then, per column, rows above the first / below the last valid pixel copy it.
    Fully invalid rows *between* valid rows stay invalid (+inf), exactly as in the devkit.
    Invalid = not finite or negative.
    """
    d = np.array(disp, dtype=np.float32, copy=True)
    d[~kitti_valid(d)] = np.inf
    kitti_fill_rows(d)
    kitti_fill_cols(d)
    return d


def kitti_stats(
    est: np.ndarray,
    gt: np.ndarray,
    *,
    obj_map: np.ndarray | None = None,
    filled: np.ndarray | None = None,
    thresholds: Sequence[float] = DEFAULT_THRESHOLDS,
    quantiles: Sequence[float] = DEFAULT_QUANTILES,
) -> dict[str, float | int | None]:
    """KITTI 2015 statistics for one GT map (``disp_noc_0`` or ``disp_occ_0``).

    ``D1`` = % of GT pixels that are outliers in the background-filled estimate; ``D1-bg`` /
    ``D1-fg`` when ``obj_map`` (0 = background) is given; ``density`` = % of GT pixels with an
    original valid estimate; ``invalid`` = 100 - density. ``badX``, ``avgerr``, ``rms`` and the
    quantiles are computed on the filled map (pixels still invalid after filling count as bad
    and are left out of the averages).
    """
    est = check_estimate(est)
    if est.shape != gt.shape:
        raise DataError(f"estimate size {est.shape[1]}x{est.shape[0]} differs from the KITTI GT size "
                        f"{gt.shape[1]}x{gt.shape[0]} (KITTI scores at the GT size only)")
    if filled is None:
        filled = kitti_interpolate_background(est)
    scored = np.isfinite(gt) & (gt > 0)
    n = int(scored.sum())
    g = gt[scored].astype(np.float32)
    e = filled[scored]
    err = abs_error(e, g)
    with np.errstate(invalid="ignore", divide="ignore"):
        rel = err / np.abs(g)
    outlier = (err > np.float32(KITTI_ABS_THRESH)) & (rel > np.float32(KITTI_REL_THRESH))
    orig_valid = kitti_valid(est)[scored]
    out: dict[str, float | int | None] = {"n": n, "coverage": 100.0 * n / gt.size if gt.size else 0.0}
    out["D1"] = 100.0 * int(outlier.sum()) / n if n else None
    if obj_map is not None:
        obj = obj_map[scored]
        for key, sel in (("D1-bg", obj == 0), ("D1-fg", obj != 0)):
            m = int(sel.sum())
            out[key] = 100.0 * int(outlier[sel].sum()) / m if m else None
    density = 100.0 * int(orig_valid.sum()) / n if n else None
    out["density"] = density
    for t in thresholds:
        out[threshold_key(t)] = 100.0 * int(np.count_nonzero(err > np.float32(t))) / n if n else None
    out["invalid"] = 100.0 - density if density is not None else None
    out.update(_summary(err[np.isfinite(err)], quantiles))
    return out


# --------------------------------------------------------------------------------------------
# Derived non-occlusion masks for Middlebury 2001/2003 (official region masks not available)


def derive_nonocc_mask(gt: np.ndarray, gt_right: np.ndarray | None = None) -> np.ndarray:
    """Non-occluded mask derived from the left GT (MANIFEST rule), (H, W) bool.

    A left pixel with GT ``d`` is occluded when ``x - d`` falls outside the right image or a
    nearer left pixel (larger disparity) of the same row lands within 0.5 px of it (z-buffer
    visibility test; "within" is strict). Unknown GT is never non-occluded. With the right-view
    GT (Teddy/Cones ``disp6``), a pixel visible by the z-buffer test must also agree with the
    right GT sampled at ``round(x - d)`` within 1 px, where that right GT is known.
    """
    gt = np.ascontiguousarray(gt, dtype=np.float32)
    out = np.zeros(gt.shape, dtype=np.bool_)
    zbuffer_visible(gt, out)
    if gt_right is not None:
        if gt_right.shape != gt.shape:
            raise DataError(f"right-view GT size {gt_right.shape[::-1]} differs from the left GT {gt.shape[::-1]}")
        height, width = gt.shape
        ys, xs = np.nonzero(out)
        xr = np.clip(np.rint(xs - gt[ys, xs]).astype(np.int64), 0, width - 1)
        dr = gt_right[ys, xr]
        known = np.isfinite(dr)
        agree = np.abs(dr - gt[ys, xs]) <= 1.0
        out[ys[known & ~agree], xs[known & ~agree]] = False
    return out
