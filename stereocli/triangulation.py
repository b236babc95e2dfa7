"""Disparity + rectified calibration → depth maps and 3-D points.

Frame and units
---------------
Points are in the **rectified left camera frame**: x right, y down, z forward (OpenCV), in
the calibration's length unit (Middlebury ``calib.txt``: millimetres). Pixel coordinates use
the pixel-centre convention of OpenCV and Middlebury: column ``x`` and row ``y`` are integer
indices at pixel centres.

Formulas (Middlebury 2014; OpenCV's Q encodes the same)::

    Z = f · B / (d + doffs)        doffs = cx_right − cx_left
    X = Z · (x − cx) / f
    Y = Z · (y − cy) / fy          (fy = f after rectification)

From OpenCV rectification: ``f = P1[0,0]``, ``cx = P1[0,2]``, ``cy = P1[1,2]``,
``B = −P2[0,3] / P2[0,0]``, ``doffs = P2[0,2] − P1[0,2]``. From Q (``[x y d 1] → [X Y Z W]``):
``cx = −Q[0,3]``, ``cy = −Q[1,3]``, ``f = Q[2,3]``, ``B = 1 / Q[3,2]``, ``doffs = Q[3,3] / Q[3,2]``.

Which pixels become points
--------------------------
:func:`triangulate` writes only what the match supports. A pixel is dropped (depth +inf in the
depth map, no point in the cloud, never a sentinel point), for the first of these reasons
(:data:`DROP_REASONS`, counted in :attr:`PointCloud.dropped`):

* ``invalid``: its disparity is not finite;
* ``outside_range``: its disparity lies outside the range the match searched
  ``[min_disp, min_disp + ndisp)`` by more than the 1 px a sub-pixel fit may add
  (when the range is known);
* ``unmatched``: no right-view pixel shows it: ``x − d`` rounds to a column outside the right
  image or outside the right valid mask, or the pixel is outside the left valid mask;
* ``at_infinity``: ``d + doffs < 2`` px (:data:`MIN_DEPTH_DISPARITY`). Depth goes as
  ``1 / (d + doffs)``: there, a disparity 1 px too large (the bad-pixel threshold of every
  benchmark) has at least doubled the depth, and below 1 px the depth allowed is unbounded.
  Such points carry no depth worth keeping; they are what matches of patterns fixed to both
  sensors (compression blocks, sensor noise, identical in two barely warped views) and
  ambiguous textureless regions put near infinity;
* ``low_confidence``: its confidence is below ``min_confidence`` (when given);
* ``depth_limits``: its depth lies outside ``[min_depth, max_depth]``.

``supported=False`` keeps every pixel with a finite disparity and ``d + doffs > 0`` (the depth
limits still apply).
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np

from .errors import DataError
from .io.calib import UNIT_SCALE, StereoCalibration

__all__ = ["FRAME", "PointCloud", "RectifiedGeometry", "depth_from_disparity", "geometry_from_calibration",
           "geometry_from_q", "normals_from_depth", "points_from_depth", "reproject_q", "summarize", "triangulate",
           "write_depth", "write_depth_png16_mm"]

FRAME = "rectified left camera: x right, y down, z forward"

#: Points need ``d + doffs`` at least this (px): below it a 1 px disparity error more than doubles
#: the depth (module docstring).
MIN_DEPTH_DISPARITY = 2.0
#: How far a disparity may lie outside the searched range and still count (px): a sub-pixel fit
#: at the range's last hypothesis (as :data:`stereocli.matching.visibility.RANGE_SLACK`).
RANGE_SLACK = 1.0
#: Why a pixel gives no point, in the order the reasons are tested (each pixel counts once).
DROP_REASONS = ("invalid", "outside_range", "unmatched", "at_infinity", "low_confidence", "depth_limits")


@dataclass(frozen=True)
class RectifiedGeometry:
    """The numbers triangulation needs (pixels; baseline in ``units``)."""

    f: float
    cx: float
    cy: float
    baseline: float
    doffs: float = 0.0
    fy: float | None = None
    units: str = "unit"

    def __post_init__(self) -> None:
        for key in ("f", "cx", "cy", "baseline", "doffs"):
            if not math.isfinite(getattr(self, key)):
                raise DataError(f"calibration: {key} is not finite")
        if self.f <= 0:
            raise DataError(f"calibration: focal length must be positive, got {self.f}")
        if self.baseline <= 0:
            raise DataError(f"calibration: baseline must be positive, got {self.baseline:g} {self.units} "
                            "(left and right swapped, or a right-to-left rig?)")

    @property
    def focal_y(self) -> float:
        return self.fy if self.fy else self.f

    def scaled(self, units: str) -> RectifiedGeometry:
        """The same geometry with the baseline (hence depth) in ``units`` (known length units only)."""
        if units == self.units:
            return self
        if self.units not in UNIT_SCALE or units not in UNIT_SCALE:
            raise DataError(f"cannot convert depth from {self.units!r} to {units!r} "
                            f"(known units: {', '.join(UNIT_SCALE)})")
        k = UNIT_SCALE[self.units] / UNIT_SCALE[units]
        return RectifiedGeometry(self.f, self.cx, self.cy, self.baseline * k, self.doffs, self.fy, units)

    def as_dict(self) -> dict:
        return asdict(self)


def geometry_from_q(Q: np.ndarray, units: str = "unit") -> RectifiedGeometry:
    """Read f, cx, cy, B, doffs from OpenCV's 4x4 Q (horizontal rig)."""
    Q = np.asarray(Q, dtype=np.float64)
    if Q.shape != (4, 4) or Q[3, 2] == 0:
        raise DataError("calibration: Q must be 4x4 with Q[3,2] = 1/B != 0")
    return RectifiedGeometry(f=float(Q[2, 3]), cx=float(-Q[0, 3]), cy=float(-Q[1, 3]), baseline=float(1 / Q[3, 2]),
                             doffs=float(Q[3, 3] / Q[3, 2]), units=units)


def geometry_from_calibration(calib: StereoCalibration, *, use_q: bool = False) -> RectifiedGeometry:
    """Rectified geometry from P1/P2 (preferred) or Q; the calibration must be rectified."""
    if use_q or (not calib.is_rectified and calib.Q is not None):
        if calib.Q is None:
            raise DataError("calibration has no Q matrix (needed for --use-q)")
        return geometry_from_q(calib.Q, calib.units)
    P1, P2 = calib.P1, calib.P2
    if P1 is None or P2 is None:  # not calib.is_rectified
        raise DataError("calibration has no rectification (P1, P2 or Q): triangulate needs the calibration "
                        "of the rectified pair (rectify writes calib.txt beside im0.png)")
    if abs(P2[1, 3]) > abs(P2[0, 3]):
        raise DataError("calibration describes a vertical rig (P2 shifted along y); "
                        "only horizontal pairs are supported")
    if P2[0, 0] == 0:
        raise DataError("calibration: P2[0,0] (focal length) is zero")
    return RectifiedGeometry(f=float(P1[0, 0]), cx=float(P1[0, 2]), cy=float(P1[1, 2]),
                             baseline=float(-P2[0, 3] / P2[0, 0]), doffs=float(P2[0, 2] - P1[0, 2]),
                             fy=float(P1[1, 1]), units=calib.units)


def depth_from_disparity(disparity: np.ndarray, geom: RectifiedGeometry, *, min_depth: float | None = None,
                         max_depth: float | None = None) -> np.ndarray:
    """(H, W) float32 depth Z in ``geom.units``; +inf where invalid or out of range."""
    d = np.asarray(disparity, dtype=np.float32)
    finite = np.isfinite(d)
    ok = finite.copy()
    # float64 for d + doffs and the division: exact to float32 rounding of f·B/(d + doffs).
    denom = d[finite].astype(np.float64) + geom.doffs
    ok[finite] = denom > 0
    depth = np.full(d.shape, np.inf, dtype=np.float32)
    depth[ok] = (geom.f * geom.baseline / denom[denom > 0]).astype(np.float32)
    if min_depth is not None:
        depth[depth < min_depth] = np.inf
    if max_depth is not None:
        depth[depth > max_depth] = np.inf
    return depth


@dataclass
class PointCloud:
    """Valid points only: (N, 3) float32 xyz, their (row, col) pixels, optional colours/normals."""

    points: np.ndarray
    rows: np.ndarray
    cols: np.ndarray
    colors: np.ndarray | None = None
    normals: np.ndarray | None = None
    confidence: np.ndarray | None = None
    #: pixels of the whole map (before ``stride``) that give no point, by reason (:data:`DROP_REASONS`)
    dropped: dict[str, int] = field(default_factory=dict)


def supported_pixels(disparity: np.ndarray, geom: RectifiedGeometry, *,
                     disparity_range: tuple[int, int] | None = None, left_valid: np.ndarray | None = None,
                     right_valid: np.ndarray | None = None, confidence: np.ndarray | None = None,
                     min_confidence: float | None = None, supported: bool = True) -> tuple[np.ndarray, dict[str, int]]:
    """The pixels of ``disparity`` (H, W) float32 px that the match supports, (H, W) bool, and how
    many of the others each reason of :data:`DROP_REASONS` drops (module docstring; all but
    ``depth_limits``, which :func:`triangulate` counts).

    ``disparity_range``: ``(min_disp, ndisp)`` the match searched, if known; masks (H, W) bool
    or None; ``confidence`` (H, W) float32, read with ``min_confidence``. With ``supported``
    False only the invalid pixels and those with ``d + doffs ≤ 0`` (no depth at all, counted as
    ``at_infinity``) are dropped.
    """
    d = np.asarray(disparity, dtype=np.float32)
    h, w = d.shape
    keep = np.isfinite(d)
    dropped = {"invalid": int(d.size - keep.sum())}

    def drop(reason: str, bad: np.ndarray) -> None:
        bad = bad & keep
        dropped[reason] = int(bad.sum())
        keep[bad] = False

    value = np.where(keep, d, 0).astype(np.float64)
    if supported and disparity_range is not None:
        low, ndisp = disparity_range
        drop("outside_range", (value < low - RANGE_SLACK) | (value > low + ndisp - 1 + RANGE_SLACK))
    if supported:
        unseen = np.zeros((h, w), bool)
        for y0 in range(0, h, 256):  # row strips keep the temporaries of a large map small
            rows = slice(y0, min(h, y0 + 256))
            column = np.floor(np.arange(w)[None, :] - value[rows] + 0.5)  # the right column the match lands on
            unseen[rows] = (column < 0) | (column > w - 1)
            if right_valid is not None:
                inside = np.clip(column, 0, w - 1).astype(np.intp)
                unseen[rows] |= ~np.take_along_axis(right_valid[rows], inside, axis=1)
        if left_valid is not None:
            unseen |= ~left_valid
        drop("unmatched", unseen)
    drop("at_infinity", value + geom.doffs < (MIN_DEPTH_DISPARITY if supported else np.finfo(np.float64).tiny))
    if min_confidence is not None and confidence is not None:
        drop("low_confidence", ~(np.asarray(confidence) >= min_confidence))
    return keep, {reason: dropped.get(reason, 0) for reason in DROP_REASONS[:-1]}


def points_from_depth(depth: np.ndarray, geom: RectifiedGeometry, *, stride: int = 1,
                      strip_rows: int = 256) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Back-project finite depths; returns (N, 3) float32 points and their row/col indices.

    Works in row strips so temporaries stay bounded for large images.
    """
    if stride < 1:
        raise DataError(f"--stride must be >= 1, got {stride}")
    h, w = depth.shape
    cols_all = np.arange(0, w, stride)
    xs = ((cols_all - geom.cx) / geom.f).astype(np.float64)
    out_pts, out_r, out_c = [], [], []
    for r0 in range(0, h, strip_rows * stride):
        rows = np.arange(r0, min(h, r0 + strip_rows * stride), stride)
        z = depth[np.ix_(rows, cols_all)]
        rr, cc = np.nonzero(np.isfinite(z))
        zz = z[rr, cc].astype(np.float64)
        ys = (rows[rr] - geom.cy) / geom.focal_y
        pts = np.empty((zz.size, 3), dtype=np.float32)
        pts[:, 0] = zz * xs[cc]
        pts[:, 1] = zz * ys
        pts[:, 2] = zz
        out_pts.append(pts)
        out_r.append(rows[rr].astype(np.int32))
        out_c.append(cols_all[cc].astype(np.int32))
    if not out_pts:
        return np.zeros((0, 3), np.float32), np.zeros(0, np.int32), np.zeros(0, np.int32)
    return np.concatenate(out_pts), np.concatenate(out_r), np.concatenate(out_c)


def normals_from_depth(depth: np.ndarray, geom: RectifiedGeometry, rows: np.ndarray, cols: np.ndarray) -> np.ndarray:
    """Unit normals (N, 3) at (rows, cols) from differences of the organised point grid.

    Central differences, falling back to one-sided ones next to invalid pixels; oriented
    towards the camera; (0, 0, 0) where no tangent can be formed.
    """
    h, w = depth.shape
    r0, r1 = np.clip(rows - 1, 0, h - 1), np.clip(rows + 1, 0, h - 1)
    c0, c1 = np.clip(cols - 1, 0, w - 1), np.clip(cols + 1, 0, w - 1)

    def xyz(r, c):
        z = depth[r, c].astype(np.float64)
        return np.stack([z * (c - geom.cx) / geom.f, z * (r - geom.cy) / geom.focal_y, z], axis=1)

    def tangent(a, centre, b):
        with np.errstate(invalid="ignore"):
            t = b - a
            for alt in (b - centre, centre - a):
                bad = ~np.isfinite(t).all(axis=1) | ~np.any(t, axis=1)
                t[bad] = alt[bad]
        return t

    centre = xyz(rows, cols)
    du = tangent(xyz(rows, c0), centre, xyz(rows, c1))
    dv = tangent(xyz(r0, cols), centre, xyz(r1, cols))
    with np.errstate(invalid="ignore", divide="ignore"):
        n = np.cross(du, dv)
        n = n / np.linalg.norm(n, axis=1, keepdims=True)
    flip = np.sum(n * centre, axis=1) > 0
    n[flip] *= -1
    n[~np.isfinite(n).all(axis=1)] = 0.0
    return n.astype(np.float32)


def reproject_q(disparity: np.ndarray, Q: np.ndarray) -> np.ndarray:
    """(H, W, 3) float32 ``[X Y Z] = (Q·[x y d 1])[:3] / W`` — OpenCV's ``reprojectImageTo3D`` in numpy.

    Non-finite disparity gives non-finite points (callers drop them).
    """
    d = np.asarray(disparity, dtype=np.float64)
    h, w = d.shape
    x = np.arange(w, dtype=np.float64)[None, :]
    y = np.arange(h, dtype=np.float64)[:, None]
    Q = np.asarray(Q, dtype=np.float64)
    comps = [Q[i, 0] * x + Q[i, 1] * y + Q[i, 2] * d + Q[i, 3] for i in range(4)]
    with np.errstate(divide="ignore", invalid="ignore"):
        return np.stack([comps[0] / comps[3], comps[1] / comps[3], comps[2] / comps[3]], axis=-1).astype(np.float32)


def triangulate(disparity: np.ndarray, geom: RectifiedGeometry, *, image: np.ndarray | None = None,
                confidence: np.ndarray | None = None, normals: bool = False, stride: int = 1,
                min_depth: float | None = None, max_depth: float | None = None,
                disparity_range: tuple[int, int] | None = None, left_valid: np.ndarray | None = None,
                right_valid: np.ndarray | None = None, min_confidence: float | None = None,
                supported: bool = True) -> tuple[np.ndarray, PointCloud]:
    """Depth map (H, W) float32 and the points the match supports (with colours from ``image``
    when given); the pixels dropped, by reason, in ``cloud.dropped`` (module docstring,
    :func:`supported_pixels` for the arguments)."""
    d = np.asarray(disparity, dtype=np.float32)
    if d.ndim != 2:
        raise DataError(f"disparity must be 2-D, got shape {d.shape}")
    for name, arr in (("image", image), ("confidence", confidence), ("left valid mask", left_valid),
                      ("right valid mask", right_valid)):
        if arr is not None and arr.shape[:2] != d.shape:
            raise DataError(f"{name} is {arr.shape[1]}x{arr.shape[0]} but the disparity is {d.shape[1]}x{d.shape[0]}")
    keep, dropped = supported_pixels(d, geom, disparity_range=disparity_range, left_valid=left_valid,
                                     right_valid=right_valid, confidence=confidence, min_confidence=min_confidence,
                                     supported=supported)
    depth = depth_from_disparity(np.where(keep, d, np.float32(np.inf)), geom, min_depth=min_depth,
                                 max_depth=max_depth)
    dropped["depth_limits"] = int((keep & ~np.isfinite(depth)).sum())
    pts, rows, cols = points_from_depth(depth, geom, stride=stride)
    cloud = PointCloud(pts, rows, cols, dropped=dropped)
    if image is not None:
        img = image
        if img.dtype == np.uint16:
            img = (img >> 8).astype(np.uint8)
        elif img.dtype != np.uint8:
            img = np.clip(img, 0, 255).astype(np.uint8)
        col = img[rows, cols]
        cloud.colors = np.repeat(col[:, None], 3, axis=1) if col.ndim == 1 else col[:, :3]
    if confidence is not None:
        cloud.confidence = np.asarray(confidence, dtype=np.float32)[rows, cols]
    if normals:
        cloud.normals = normals_from_depth(depth, geom, rows, cols)
    return depth, cloud


def summarize(depth: np.ndarray, cloud: PointCloud, geom: RectifiedGeometry) -> dict:
    """Point count, valid fraction, depth percentiles, bounding box, units and frame (JSON-able)."""
    finite = depth[np.isfinite(depth)]
    out = {"points": int(cloud.points.shape[0]), "pixels": int(depth.size),
           "valid_fraction": float(finite.size / depth.size) if depth.size else 0.0,
           "units": geom.units, "frame": FRAME, "geometry": geom.as_dict()}
    if cloud.dropped:
        out["dropped"] = dict(cloud.dropped)
    if finite.size:
        q = np.percentile(finite, [1, 5, 50, 95, 99])
        out["depth_percentiles"] = {k: float(v) for k, v in zip(("p1", "p5", "p50", "p95", "p99"), q)}
        out["depth_min"], out["depth_max"] = float(finite.min()), float(finite.max())
    if cloud.points.shape[0]:
        out["bbox_min"] = cloud.points.min(axis=0).astype(float).tolist()
        out["bbox_max"] = cloud.points.max(axis=0).astype(float).tolist()
    return out


# --------------------------------------------------------------------------- files

def write_depth(path: str | Path, depth: np.ndarray) -> None:
    """float32 depth by extension: ``.pfm`` (+inf invalid), ``.npy``, ``.tif``/``.tiff``."""
    import cv2

    from .io.atomic import atomic_path
    from .io.pfm import write_pfm

    path = Path(path)
    suffix = path.suffix.lower()
    if suffix == ".pfm":
        write_pfm(path, depth)
    elif suffix == ".npy":
        with atomic_path(path) as tmp, open(tmp, "wb") as fh:
            np.save(fh, depth.astype(np.float32))
    elif suffix in (".tif", ".tiff"):
        ok, buf = cv2.imencode(suffix, depth.astype(np.float32))
        if not ok:
            raise DataError(f"{path}: cannot encode float32 TIFF")
        from .io.atomic import write_bytes

        write_bytes(path, buf.tobytes())
    else:
        raise DataError(f"{path}: unknown depth format {suffix!r} (pfm, npy, tif)")


def write_depth_png16_mm(path: str | Path, depth: np.ndarray, units: str) -> int:
    """uint16 PNG of depth in millimetres (0 = invalid or beyond 65.535 m); returns clipped count."""
    from .io.images import write_image

    if units not in UNIT_SCALE:
        raise DataError(f"--depth-png16 needs a known length unit, calibration says {units!r}")
    mm = depth.astype(np.float64) * (UNIT_SCALE[units] / UNIT_SCALE["mm"])
    finite = np.isfinite(mm)
    value = np.zeros(depth.shape, np.uint16)
    ok = finite & (mm >= 0.5) & (mm < 65535.5)
    value[ok] = np.rint(mm[ok]).astype(np.uint16)
    write_image(path, value)
    return int((finite & ~ok).sum())
