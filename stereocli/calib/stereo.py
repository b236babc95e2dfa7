"""Stereo calibration with OpenCV, made explainable: per-view errors, outliers, checks, warnings.

Steps (:func:`calibrate_stereo`):

1. each camera alone (``cv2.calibrateCameraExtended``; fisheye: ``cv2.fisheye.calibrate``),
   which conditions the problem far better than a joint solve from scratch;
2. the stereo extrinsics R, T with the intrinsics fixed (``CALIB_FIX_INTRINSIC``, default) or
   refined jointly (``joint=True`` → ``CALIB_USE_INTRINSIC_GUESS``);
3. optionally drop views whose per-view RMS exceeds ``max_view_error`` and repeat;
4. rectify (``cv2.stereoRectify``, alpha 0) and measure the rectified epipolar error: the
   mean and max of ``|y_left − y_right|`` of corresponding corners after undistortion and
   rectification (``cv2.undistortPoints`` with R1/P1, R2/P2).
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, field
from typing import Any

import cv2
import numpy as np

from ..errors import DataError
from ..io.calib import StereoCalibration, rotation_angle_deg
from .detect import Detection
from .pattern import Pattern

MIN_VIEWS = 3
RECOMMENDED_VIEWS = 10
#: A corner whose rectified rows differ by more than this (px) is named in a warning: matching
#: searches along rows, and a pair rectified with such an error loses its matches there.
EPIPOLAR_LIMIT = 1.0
#: Corners a warning names per view (report.json lists them all).
NAMED_CORNERS = 3


@dataclass(frozen=True)
class CalibOptions:
    """Readable names for OpenCV calibration flags (see ``stereocli calibrate --help``)."""

    fix_principal_point: bool = False  # CALIB_FIX_PRINCIPAL_POINT (stays at the image centre)
    zero_tangent: bool = False  # CALIB_ZERO_TANGENT_DIST (p1 = p2 = 0)
    fix_aspect: bool = False  # CALIB_FIX_ASPECT_RATIO (fx / fy fixed at 1)
    fix_k3: bool = False  # CALIB_FIX_K3 (narrow lenses: k3 is poorly observable)
    rational: bool = False  # CALIB_RATIONAL_MODEL (k4..k6; wide lenses)
    fisheye: bool = False  # cv2.fisheye equidistant model (k1..k4)
    same_focal: bool = False  # CALIB_SAME_FOCAL_LENGTH (joint only)
    joint: bool = False  # refine intrinsics in the stereo solve instead of fixing them
    max_view_error: float | None = None  # drop views above this RMS (px) and recalibrate
    alpha: float = 0.0  # rectification alpha stored in the file

    def mono_flags(self) -> int:
        """Return the flags of the single-camera calibration (``cv2.calibrateCamera`` or ``cv2.fisheye.calibrate``)."""
        if self.fisheye:
            flags = cv2.CALIB_RECOMPUTE_EXTRINSIC | cv2.CALIB_FIX_SKEW
            return flags | (cv2.CALIB_FIX_PRINCIPAL_POINT if self.fix_principal_point else 0)
        flags = 0
        for on, flag in ((self.fix_principal_point, cv2.CALIB_FIX_PRINCIPAL_POINT),
                         (self.zero_tangent, cv2.CALIB_ZERO_TANGENT_DIST),
                         (self.fix_aspect, cv2.CALIB_FIX_ASPECT_RATIO),
                         (self.fix_k3, cv2.CALIB_FIX_K3), (self.rational, cv2.CALIB_RATIONAL_MODEL)):
            if on:
                flags |= flag
        return flags

    def stereo_flags(self) -> int:
        """Return the flags of the stereo solve: intrinsics fixed, or refined too with ``joint``."""
        if not self.joint:
            return cv2.CALIB_FIX_INTRINSIC
        flags = self.mono_flags() | cv2.CALIB_USE_INTRINSIC_GUESS
        if self.same_focal and not self.fisheye:
            flags |= cv2.CALIB_SAME_FOCAL_LENGTH
        return flags


@dataclass
class View:
    """One pair whose images both show the target: the corners seen in both."""

    name: str
    left: str
    right: str
    object_points: np.ndarray  # (N, 3) float32
    left_points: np.ndarray  # (N, 2) float32
    right_points: np.ndarray


@dataclass
class CalibrationResult:
    """What :func:`stereocli.calibrate` returns.

    Attributes
    ----------
    calibration : the rig (K1, D1, K2, D2, R, T, rectified with R1, R2, P1, P2, Q), in the
        square's unit; save it with :func:`stereocli.io.calib.save_calibration`.
    report : images without the target and why, stereo / left / right and per-view RMS (px) with
        outliers flagged, intrinsics, baseline, rotation, rectified epipolar error, warnings (the
        ``OUT.report.json`` of ``stereocli calibrate``).
    """

    calibration: StereoCalibration
    report: dict = field(default_factory=dict)


def build_views(pairs: list[tuple[str, str, str]], detections: dict[str, Detection], pattern: Pattern
                ) -> tuple[list[View], list[dict], tuple[int, int]]:
    """Pair up detections; returns usable views, the images not used (with reasons) and the image size."""
    sizes: dict[tuple[int, int], str] = {}
    for _, left, right in pairs:
        for p in (left, right):
            sizes.setdefault(detections[p].size, p)
    if len(sizes) > 1:
        (s0, p0), (s1, p1) = list(sizes.items())[:2]
        raise DataError(f"mixed image sizes: {p0} is {s0[0]}x{s0[1]} but {p1} is {s1[0]}x{s1[1]}")
    size = next(iter(sizes))
    obj_all = pattern.object_points()
    views, missing = [], []
    for name, left, right in pairs:
        dl, dr = detections[left], detections[right]
        for d in (dl, dr):
            if not d.found:
                missing.append({"image": d.path, "reason": d.reason})
        left_corners, right_corners = dl.corners, dr.corners
        if left_corners is None or right_corners is None:  # not (dl.found and dr.found)
            continue
        if dl.ids is None and dr.ids is None:
            views.append(View(name, left, right, obj_all, left_corners, right_corners))
            continue
        if dl.ids is None or dr.ids is None:  # (never: both images are searched for the same pattern)
            raise DataError(f"{left} + {right}: ChArUco ids in one image only")
        common, il, ir = np.intersect1d(dl.ids, dr.ids, return_indices=True)
        if common.size < 6:
            missing.append({"image": f"{left} + {right}", "reason": f"only {common.size} ChArUco corners seen by both"})
            continue
        views.append(View(name, left, right, obj_all[common], left_corners[il], right_corners[ir]))
    return views, missing, size


def _mono(views: list[View], side: str, size, opts: CalibOptions):
    # cv2.fisheye insists on (1, N, 3) / (1, N, 2) float64; the pinhole API takes (N, 1, k) float32.
    lead = (1, -1) if opts.fisheye else (-1, 1)
    obj = [v.object_points.reshape(*lead, 3).astype(np.float64 if opts.fisheye else np.float32) for v in views]
    img = [getattr(v, f"{side}_points").reshape(*lead, 2).astype(np.float64 if opts.fisheye else np.float32)
           for v in views]
    crit = (cv2.TERM_CRITERIA_COUNT + cv2.TERM_CRITERIA_EPS, 100, 1e-10)
    try:
        if opts.fisheye:
            rms, K, D, rvecs, tvecs = cv2.fisheye.calibrate(obj, img, size, np.eye(3), np.zeros(4),
                                                            flags=opts.mono_flags(), criteria=crit)
            errs = []
            for o, i, r, t in zip(obj, img, rvecs, tvecs):
                proj, _ = cv2.fisheye.projectPoints(o, r, t, K, D)
                errs.append(math.sqrt(np.mean(np.sum((proj - i) ** 2, axis=-1))))
            return rms, K, D.ravel(), np.array(errs)
        K0 = np.eye(3)
        if opts.fix_aspect:
            K0[0, 0] = K0[1, 1] = 1.0
        res = cv2.calibrateCameraExtended(obj, img, size, K0, None, flags=opts.mono_flags(), criteria=crit)
    except cv2.error as exc:
        raise DataError(f"{side} camera calibration failed in OpenCV: {str(exc).strip().splitlines()[-1]}") from None
    rms, K, D = res[0], res[1], res[2]
    return rms, K, D.ravel(), np.asarray(res[7]).ravel()


def _stereo(views: list[View], size, K1, D1, K2, D2, opts: CalibOptions):
    dt = np.float64 if opts.fisheye else np.float32
    lead = (1, -1) if opts.fisheye else (-1, 1)
    obj = [v.object_points.reshape(*lead, 3).astype(dt) for v in views]
    il = [v.left_points.reshape(*lead, 2).astype(dt) for v in views]
    ir = [v.right_points.reshape(*lead, 2).astype(dt) for v in views]
    crit = (cv2.TERM_CRITERIA_COUNT + cv2.TERM_CRITERIA_EPS, 200, 1e-10)
    try:
        if opts.fisheye:
            out = cv2.fisheye.stereoCalibrate(obj, il, ir, K1, D1.reshape(4, 1), K2, D2.reshape(4, 1), size,
                                              flags=opts.stereo_flags() if opts.joint else
                                              cv2.CALIB_FIX_INTRINSIC, criteria=crit)
            rms, K1, D1, K2, D2, R, T = out[:7]
            rvecs, tvecs = out[7], out[8]
            per_view = []
            for o, a, b, rv, tv in zip(obj, il, ir, rvecs, tvecs):
                pa, _ = cv2.fisheye.projectPoints(o, rv, tv, K1, D1)
                Rb = R @ cv2.Rodrigues(rv)[0]
                pb, _ = cv2.fisheye.projectPoints(o, cv2.Rodrigues(Rb)[0], R @ tv.reshape(3, 1) + T.reshape(3, 1),
                                                  K2, D2)
                per_view.append([math.sqrt(np.mean(np.sum((pa - a) ** 2, -1))),
                                 math.sqrt(np.mean(np.sum((pb - b) ** 2, -1)))])
            return rms, K1, D1.ravel(), K2, D2.ravel(), R, T.ravel(), np.array(per_view), tvecs
        out = cv2.stereoCalibrateExtended(obj, il, ir, K1.copy(), D1.copy(), K2.copy(), D2.copy(), size,
                                          np.eye(3), np.zeros((3, 1)), flags=opts.stereo_flags(), criteria=crit)
    except cv2.error as exc:
        raise DataError(f"stereo calibration failed in OpenCV: {str(exc).strip().splitlines()[-1]}") from None
    rms, K1, D1, K2, D2, R, T, E, F, rvecs, tvecs, per_view = out
    return rms, K1, D1.ravel(), K2, D2.ravel(), R, T.ravel(), np.asarray(per_view).reshape(-1, 2), tvecs


def outlier_threshold(errors: np.ndarray) -> float:
    """Robust cut: ``max(2·median, median + 4·1.4826·MAD, median + 0.1 px)`` of the per-view RMS.

    The absolute 0.1 px floor keeps near-perfect sets (synthetic, ~0.03 px) from flagging noise.
    """
    med = float(np.median(errors))
    mad = float(np.median(np.abs(errors - med))) * 1.4826
    return max(2.0 * med, med + 4.0 * mad, med + 0.1)


def rectified_epipolar_error(calib: StereoCalibration, views: list[View]) -> dict:
    """Return ``|y_left − y_right|`` (px) of all corresponding corners after rectification.

    The dict holds ``mean``, ``max``, ``points``, each view's max (``per_view``: name → px) and
    the corners above :data:`EPIPOLAR_LIMIT` (``above_limit``: per view, ``name``, the two images,
    ``max`` and ``corners``, each with its ``index`` in detection order, left-image ``x``/``y`` and
    ``dy``, largest first).
    """
    P2 = calib.P2
    if P2 is None:
        raise DataError("calibration has no rectification (P1, P2): no rectified epipolar error")
    undistort = cv2.fisheye.undistortPoints if calib.model == "fisheye" else cv2.undistortPoints
    dys, per_view, above = [], {}, []
    for v in views:
        D1 = calib.D1[:4] if calib.model == "fisheye" else calib.D1
        D2 = calib.D2[:4] if calib.model == "fisheye" else calib.D2
        a = undistort(v.left_points.reshape(-1, 1, 2).astype(np.float64), calib.K1, D1, R=calib.R1, P=calib.P1)
        b = undistort(v.right_points.reshape(-1, 1, 2).astype(np.float64), calib.K2, D2, R=calib.R2, P=calib.P2)
        axis = 0 if abs(P2[1, 3]) > abs(P2[0, 3]) else 1
        dy = np.abs(a[:, 0, axis] - b[:, 0, axis])
        dys.append(dy)
        per_view[v.name] = float(dy.max())
        high = np.flatnonzero(dy > EPIPOLAR_LIMIT)
        if high.size:
            high = high[np.argsort(-dy[high], kind="stable")]
            above.append({"name": v.name, "left_image": v.left, "right_image": v.right, "max": float(dy.max()),
                          "corners": [{"index": int(i), "x": float(v.left_points[i, 0]),
                                       "y": float(v.left_points[i, 1]), "dy": float(dy[i])} for i in high]})
    d = np.concatenate(dys)
    return {"mean": float(d.mean()), "max": float(d.max()), "points": int(d.size), "per_view": per_view,
            "above_limit": above}


def _epipolar_warning(above: list[dict]) -> str:
    """Return the warning naming the views and corners whose rectified rows differ by more than the limit.

    The limit is :data:`EPIPOLAR_LIMIT`.
    """
    corners = sum(len(v["corners"]) for v in above)
    parts = []
    for v in above:
        named = ", ".join(f"corner {c['index']} at ({c['x']:.0f}, {c['y']:.0f}) {c['dy']:.2f} px"
                          for c in v["corners"][:NAMED_CORNERS])
        more = len(v["corners"]) - NAMED_CORNERS
        parts.append(f"{v['name']} ({named}{f' and {more} more' if more > 0 else ''})")
    return (f"rectified |y_left - y_right| above {EPIPOLAR_LIMIT:g} px at {corners} corner(s) of {len(above)} "
            f"view(s): {'; '.join(parts)}; rows that far apart lose their matches: check these detections "
            "(corner index in detection order, left-image pixels) or calibrate without these views")


def _warnings(calib: StereoCalibration, board_distance: float, n_views: int) -> list[str]:
    out = []
    T, B = calib.T, calib.baseline
    if abs(T[1]) > abs(T[0]) or abs(T[2]) > abs(T[0]):
        out.append(f"vertical or depth-offset rig: T = {np.round(T, 4).tolist()} is not mainly along x; "
                   "stereocli match expects a horizontal pair")
    elif T[0] > 0:
        out.append("left and right look swapped (T[0] > 0: the 'right' camera is on the left); "
                   "swap the inputs (--swap) before matching")
    if B <= 0 or not math.isfinite(B):
        out.append("baseline is zero: both views come from the same position")
    elif board_distance > 0:
        ratio = B / board_distance
        if ratio < 0.01 or ratio > 2.0:
            out.append(f"implausible baseline {B:.4g} {calib.units}: {ratio:.3g} x the median board distance "
                       f"{board_distance:.4g} {calib.units} (check --square and the pairing)")
    angle = rotation_angle_deg(calib.R, np.eye(3))
    if angle > 20:
        out.append(f"cameras are rotated {angle:.1f} deg relative to each other; "
                   "rectification will lose much of the image")
    if n_views < RECOMMENDED_VIEWS:
        out.append(f"only {n_views} views used; {RECOMMENDED_VIEWS}+ with varied board poses are recommended")
    return out


def calibrate_stereo(views: list[View], image_size: tuple[int, int], pattern: Pattern, opts: CalibOptions,
                     *, missing: list[dict] | None = None, total_pairs: int | None = None) -> CalibrationResult:
    """Calibrate a rig from views (both cameras saw the target); see the module docstring."""
    if len(views) < MIN_VIEWS:
        raise DataError(f"only {len(views)} usable view pair(s) (the target was found in both images); "
                        f"need at least {MIN_VIEWS}")
    dropped: list[dict] = []
    active = list(views)
    for _round in range(5):
        rms_l, K1, D1, per_l = _mono(active, "left", image_size, opts)
        rms_r, K2, D2, per_r = _mono(active, "right", image_size, opts)
        rms, K1, D1, K2, D2, R, T, per_view, tvecs = _stereo(active, image_size, K1, D1, K2, D2, opts)
        worst = per_view.max(axis=1)
        if opts.max_view_error is None or worst.max() <= opts.max_view_error:
            break
        keep = worst <= opts.max_view_error
        if keep.sum() < MIN_VIEWS:
            raise DataError(f"--max-view-error {opts.max_view_error} px leaves {int(keep.sum())} views; "
                            f"need at least {MIN_VIEWS} (worst view RMS {worst.max():.3f} px)")
        dropped += [{"name": v.name, "rms": float(e)} for v, e, k in zip(active, worst, keep) if not k]
        active = [v for v, k in zip(active, keep) if k]

    calib = StereoCalibration(K1=K1, D1=D1, K2=K2, D2=D2, R=R, T=T, image_size=image_size, rms=float(rms),
                              units=pattern.units, model="fisheye" if opts.fisheye else "pinhole")
    from ..rectification.maps import rectified_calibration, stereo_rectify

    rect = stereo_rectify(calib, alpha=opts.alpha)
    calib = rectified_calibration(calib, rect=rect)
    epi = rectified_epipolar_error(calib, active)
    board_distance = float(np.median([np.linalg.norm(t) for t in tvecs]))
    depths = [float(np.asarray(t).ravel()[2]) for t in tvecs]
    calib.extra["board_depth_min"] = float(min(depths))
    thr = outlier_threshold(per_view.max(axis=1))
    per: list[dict[str, Any]] = [{"name": v.name, "left_image": v.left, "right_image": v.right, "left": float(e[0]),
            "right": float(e[1]), "outlier": bool(max(e) > thr)} for v, e in zip(active, per_view)]
    for p in per:
        p["epipolar_error_max"] = epi["per_view"][p["name"]]
    warnings = _warnings(calib, board_distance, len(active))
    outliers = [p["name"] for p in per if p["outlier"]]
    if outliers:
        warnings.append(f"{len(outliers)} outlier view(s) ({', '.join(outliers[:5])}) above {thr:.3f} px; "
                        "consider --max-view-error")
    if epi["above_limit"]:
        warnings.append(_epipolar_warning(epi["above_limit"]))

    def cam(K, D):
        return {"fx": float(K[0, 0]), "fy": float(K[1, 1]), "cx": float(K[0, 2]), "cy": float(K[1, 2]),
                "distortion": [float(v) for v in D]}

    report = {
        "pattern": {**asdict(pattern), "points": pattern.count},
        "image_size": list(image_size),
        "units": pattern.units,
        "model": calib.model,
        "options": {k: v for k, v in asdict(opts).items()},
        "pairs_total": total_pairs if total_pairs is not None else len(views),
        "views_used": len(active),
        "not_found": list(missing or []),
        "dropped": dropped,
        "rms": {"stereo": float(rms), "left": float(rms_l), "right": float(rms_r)},
        "outlier_threshold": thr,
        "per_view": per,
        "intrinsics": {"left": cam(K1, D1), "right": cam(K2, D2)},
        "baseline": {"length": calib.baseline, "units": calib.units,
                     "direction": (calib.T / max(calib.baseline, 1e-300)).tolist(), "T": calib.T.tolist()},
        "rotation_deg": rotation_angle_deg(calib.R, np.eye(3)),
        "board_distance_median": board_distance,
        "rectified": {"alpha": opts.alpha, "epipolar_error_mean": epi["mean"], "epipolar_error_max": epi["max"],
                      "points": epi["points"], "epipolar_limit": EPIPOLAR_LIMIT,
                      "above_limit": epi["above_limit"], "roi_left": list(rect.roi1), "roi_right": list(rect.roi2),
                      "focal": float(calib.P1[0, 0]),
                      "doffs": float(calib.P2[0, 2] - calib.P1[0, 2])},
        "warnings": warnings,
    }
    return CalibrationResult(calib, report)


def format_report(report: dict) -> str:
    """Return the human-readable report (``calibrate`` prints it on stdout)."""
    r = report
    u = r["units"]
    lines = [f"calibrated {r['views_used']} of {r['pairs_total']} pairs "
             f"({r['pattern']['kind']} {r['pattern']['cols']}x{r['pattern']['rows']}, "
             f"square {r['pattern']['square']:g} {u}, "
             f"image {r['image_size'][0]}x{r['image_size'][1]}, {r['model']})"]
    for item in r["not_found"]:
        lines.append(f"  not used: {item['image']}: {item['reason']}")
    for item in r["dropped"]:
        lines.append(f"  dropped: {item['name']} (RMS {item['rms']:.3f} px > --max-view-error)")
    lines.append(f"RMS reprojection error: stereo {r['rms']['stereo']:.4f} px "
                 f"(left {r['rms']['left']:.4f}, right {r['rms']['right']:.4f})")
    limit = r["rectified"].get("epipolar_limit", EPIPOLAR_LIMIT)
    lines.append(f"per-view RMS (px), outlier above {r['outlier_threshold']:.3f}; rectified max |dy| (px):")
    for p in r["per_view"]:
        flag = "  <- outlier" if p["outlier"] else ""
        dy = p.get("epipolar_error_max")
        dy_text = "" if dy is None else f"  max |dy| {dy:.2f}{f' > {limit:g}' if dy > limit else ''}"
        lines.append(f"  {p['name']:>12s}  left {p['left']:.4f}  right {p['right']:.4f}{dy_text}{flag}")
    for side in ("left", "right"):
        c = r["intrinsics"][side]
        dist = " ".join(f"{v:.5g}" for v in c["distortion"])
        lines.append(f"{side:5s} fx {c['fx']:.3f} fy {c['fy']:.3f} cx {c['cx']:.3f} cy {c['cy']:.3f}  dist [{dist}]")
    b = r["baseline"]
    lines.append(f"baseline {b['length']:.6g} {u}, direction [{', '.join(f'{v:+.4f}' for v in b['direction'])}], "
                 f"rotation {r['rotation_deg']:.3f} deg")
    rc = r["rectified"]
    lines.append(f"rectified (alpha {rc['alpha']:g}): epipolar error mean {rc['epipolar_error_mean']:.4f} px, "
                 f"max {rc['epipolar_error_max']:.4f} px over {rc['points']} corners; f {rc['focal']:.3f}, "
                 f"ROI left {tuple(rc['roi_left'])}, right {tuple(rc['roi_right'])}")
    for w in r["warnings"]:
        lines.append(f"warning: {w}")
    return "\n".join(lines)
