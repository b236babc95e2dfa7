"""Rectification without a calibration, from point matches (``rectify --uncalibrated``).

1. **Epipolar geometry.** SIFT matches (:func:`~stereocli.features.points.match_points`) go to
   OpenCV's USAC MAGSAC++ (Barath et al., CVPR 2020), which fits a fundamental matrix and
   separates inliers from mismatches. The matches of every pair of one rig are pooled: the
   cameras and their relative pose, hence the geometry, are shared.
2. **Homographies.** Fusiello & Irsara's quasi-Euclidean rectification (Machine Vision and
   Applications 22(4), 2011): each view is re-projected by rotating a virtual camera about its
   centre, ``H = K_n · R · K_o⁻¹`` with ``K_o = [f 0 cx; 0 f cy; 0 0 1]`` centred on the image.
   Five angles (left about y and z; right about x, y and z), the focal length
   ``f = 3^a · (w + h)`` and, added here, a zoom of the right camera (``f_right = e^z · f``, for
   rigs whose views differ slightly in scale) minimise the Sampson error of the rectified
   pair's fundamental matrix ``F = K_o1⁻ᵀ · R1ᵀ · [e1]ₓ · R0 · K_o0⁻¹`` over the inliers, by
   Levenberg–Marquardt from the identity (the angles first, then all seven; the paper's §3),
   under a Cauchy loss (:data:`ROBUST`) and a pull towards the identity for what the matches do
   not decide (:data:`PRIOR`). That is also the fundamental matrix refined on the inliers. A
   rotation about the camera centre is the least distorting rectifying warp (no shear; aspect
   and right angles kept up to perspective); a near-rectified pair gets near-identity warps.
3. **Guided matches.** Descriptor matches favour distinctive texture and miss repeated
   patterns; lens distortion, which no homography removes, then makes the fit favour the depths
   that have matches. So, a few times (:data:`GUIDED_ROUNDS`), corners of the left image are
   matched along the current rectification's rows with the help of a coarse dense match
   (:func:`guided_matches`), and the fit is repeated with them.
4. **Placement.** Both views share the vertical offset (rows must agree); the right view is
   shifted horizontally so that the scene's disparities start at 0 (:func:`shifted`, ranges
   from :func:`~stereocli.features.disparity_range.estimate_range`), which keeps
   ``[0, ndisp)`` short; the rectified images are just large enough to hold the whole left
   image (:func:`framed`), so no pixel of it is lost to the warp.

``H0``/``H1`` map original pixels to rectified pixels (``(x, y, 1)``, pixel centres at integer
coordinates); :func:`disparity_to_original` maps a rectified disparity map back.
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass, field, replace
from typing import Any, Protocol, Sequence, cast

import cv2
import numpy as np

from ..errors import DataError
from ..features.points import PointMatches, match_points
from ..io.images import grey_uint8
from .maps import INTERPOLATIONS

#: Matches the epipolar geometry needs (a fundamental matrix has 7 degrees of freedom; far
#: more are needed to tell inliers from mismatches reliably).
MIN_MATCHES = 30
#: Matches a pair of a rig needs to be checked against the rig's geometry.
MIN_PAIR_MATCHES = 12
#: Share of a pair's matches that must fit the rig's geometry for the pair to count as the rig's
#: (a pair from another rig, or taken after a camera moved, does not).
MIN_INLIER_SHARE = 0.5
#: Largest Sampson distance (px) of an inlier, for MAGSAC++ and for the fitted model.
INLIER_PX = 1.5
#: Scale (px) of the Cauchy loss of the fit: lens distortion, which no homography removes,
#: leaves real rigs' matches off by a pixel or more towards the image borders, and mismatches
#: that passed MAGSAC++ are further still; neither should pull the fit.
ROBUST = 0.5
#: Levenberg–Marquardt iterations per stage.
MAX_ITERATIONS = 100
#: Weights (px per radian, per match) of the pull of the model's parameters towards the identity,
#: for the directions the matches see poorly. Turning both views together (about y or z) and the
#: focal length are held firmest (:data:`PRIOR_COMMON`): on nearly parallel views they hardly
#: change the fit and would only add keystone distortion. The views' relative turns and the
#: zoom are held loosely (:data:`PRIOR`; a turn of 1° costs 3·10⁻⁶ px² per match).
PRIOR = 0.1
PRIOR_COMMON = 0.3
#: Random sequences MAGSAC++ may try (see :func:`fit_fundamental`).
MAGSAC_SEEDS = 8
#: SIFT features per image for the descriptor matches.
SIFT_FEATURES = 4000
#: Rounds of guided matching (:func:`guided_matches`) after the descriptor matches' fit.
GUIDED_ROUNDS = 3
#: Corners per image the guided matching follows.
GUIDED_CORNERS = 1000
#: Width (px) of the coarse dense match that guides it.
GUIDE_WIDTH = 320
#: Largest distance (px) between a corner and where tracking its match back lands.
ROUND_TRIP_PX = 0.3

_E1_CROSS = np.array([[0.0, 0.0, 0.0], [0.0, 0.0, -1.0], [0.0, 1.0, 0.0]])  # [e1]x, e1 = (1, 0, 0)


@dataclass(frozen=True)
class UncalibratedRectification:
    """An uncalibrated rectification: two homographies from the original to the rectified images.

    ``H0``/``H1`` (3, 3) float64 map original pixels (images of ``source_size`` (w, h)) to pixels
    of the rectified images (``size`` (w, h)).
    """

    H0: np.ndarray
    H1: np.ndarray
    size: tuple[int, int]
    source_size: tuple[int, int]
    F: np.ndarray  # (3, 3) fundamental matrix of the model: x_right^T F x_left = 0 (original pixels)
    # (3, 3) camera matrices of the rectified views (the virtual cameras of the model; their focal
    # length is poorly determined when the views are nearly parallel).
    camera0: np.ndarray
    camera1: np.ndarray
    angles_deg: dict[str, float] = field(default_factory=dict)  # left_y, left_z, right_x, right_y, right_z
    right_zoom: float = 1.0
    shift: float = 0.0  # px the right view was moved right by (:func:`shifted`)

    def as_dict(self) -> dict:
        """JSON-able: matrices as nested lists, numbers rounded for reading."""
        return {"H0": self.H0.tolist(), "H1": self.H1.tolist(), "size": list(self.size),
                "source_size": list(self.source_size), "F": self.F.tolist(), "method": "quasi-euclidean",
                "camera0": self.camera0.tolist(), "camera1": self.camera1.tolist(),
                "angles_deg": {k: round(v, 4) for k, v in self.angles_deg.items()},
                "right_zoom": round(self.right_zoom, 6), "shift_px": round(self.shift, 3),
                "distortion": {"left": warp_distortion(self.H0, self.source_size),
                               "right": warp_distortion(self.H1, self.source_size)}}

    @classmethod
    def from_dict(cls, data: dict) -> UncalibratedRectification:
        """Read what :meth:`as_dict` wrote (``rectification.json``)."""
        size = lambda key: (int(data[key][0]), int(data[key][1]))  # noqa: E731
        matrix = lambda key: np.asarray(data[key], np.float64)  # noqa: E731
        return cls(matrix("H0"), matrix("H1"), size("size"), size("source_size"), matrix("F"), matrix("camera0"),
                   matrix("camera1"), dict(data.get("angles_deg", {})), float(data.get("right_zoom", 1.0)),
                   float(data.get("shift_px", 0.0)))


@dataclass(frozen=True)
class RigFit:
    """A rectification fitted to the matches of one or more pairs, with per-pair inlier masks."""

    rectification: UncalibratedRectification
    inliers: list[np.ndarray]  # per pair, (N_i,) bool: the match fits the model within INLIER_PX
    magsac_inliers: int


# --------------------------------------------------------------------------- the model

def _rotation(ax: float, ay: float, az: float) -> np.ndarray:
    """R = Rz · Ry · Rx (radians)."""
    cx, sx, cy, sy, cz, sz = np.cos(ax), np.sin(ax), np.cos(ay), np.sin(ay), np.cos(az), np.sin(az)
    rx = np.array([[1, 0, 0], [0, cx, -sx], [0, sx, cx]])
    ry = np.array([[cy, 0, sy], [0, 1, 0], [-sy, 0, cy]])
    rz = np.array([[cz, -sz, 0], [sz, cz, 0], [0, 0, 1]])
    return rz @ ry @ rx


def _centre(size: tuple[int, int]) -> tuple[float, float]:
    return (size[0] - 1) / 2.0, (size[1] - 1) / 2.0


def _translation(tx: float, ty: float) -> np.ndarray:
    return np.array([[1.0, 0.0, float(tx)], [0.0, 1.0, float(ty)], [0.0, 0.0, 1.0]])


def _intrinsics(f: float, size: tuple[int, int]) -> np.ndarray:
    cx, cy = _centre(size)
    return np.array([[f, 0.0, cx], [0.0, f, cy], [0.0, 0.0, 1.0]])


class _Model:
    """The seven parameters ``(left_y, left_z, right_x, right_y, right_z, a, z)`` of step 2 above."""

    def __init__(self, size: tuple[int, int]) -> None:
        self.size = size
        self.f0 = float(size[0] + size[1])

    def parts(self, p: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """``(K0, K1, R0, R1)`` for parameters ``p``."""
        f = self.f0 * 3.0 ** p[5]
        return (_intrinsics(f, self.size), _intrinsics(f * np.exp(p[6]), self.size),
                _rotation(0.0, p[0], p[1]), _rotation(p[2], p[3], p[4]))

    def fundamental(self, p: np.ndarray) -> np.ndarray:
        K0, K1, R0, R1 = self.parts(p)
        return np.linalg.inv(K1).T @ R1.T @ _E1_CROSS @ R0 @ np.linalg.inv(K0)


def sampson(F: np.ndarray, left: np.ndarray, right: np.ndarray) -> np.ndarray:
    """Signed Sampson distances (px) of matches ``left``/``right`` ((N, 2) px) under ``F``."""
    x0 = np.column_stack([left, np.ones(len(left))])
    x1 = np.column_stack([right, np.ones(len(right))])
    fx0 = x0 @ F.T
    ftx1 = x1 @ F
    err = np.einsum("ij,ij->i", x1, fx0)
    den = fx0[:, 0] ** 2 + fx0[:, 1] ** 2 + ftx1[:, 0] ** 2 + ftx1[:, 1] ** 2
    return err / np.sqrt(np.maximum(den, 1e-30))


def _levenberg_marquardt(residuals, p0: np.ndarray, free: np.ndarray) -> np.ndarray:
    """Minimise ``sum(residuals(p)²)`` over ``p[free]`` from ``p0`` (central-difference Jacobian)."""
    p = p0.astype(np.float64).copy()
    r = residuals(p)
    cost = float(r @ r)
    lam = 1e-3
    idx = np.flatnonzero(free)
    for _ in range(MAX_ITERATIONS):
        J = np.empty((len(r), len(idx)))
        for k, i in enumerate(idx):
            step = np.zeros_like(p)
            step[i] = 1e-6
            J[:, k] = (residuals(p + step) - residuals(p - step)) / 2e-6
        JtJ, Jtr = J.T @ J, J.T @ r
        improved = False
        while lam < 1e10:
            delta = np.linalg.solve(JtJ + lam * np.diag(np.diag(JtJ) + 1e-12), -Jtr)
            trial = p.copy()
            trial[idx] += delta
            r_trial = residuals(trial)
            cost_trial = float(r_trial @ r_trial)
            if cost_trial < cost:
                improved = cost - cost_trial > 1e-12 * cost
                p, r, cost, lam = trial, r_trial, cost_trial, max(lam / 10, 1e-9)
                break
            lam *= 10
        if not improved:
            break
    return p


def _prior_terms(p: np.ndarray) -> np.ndarray:
    """Weigh the parameters as the prior does (see :data:`PRIOR`)."""
    return np.array([PRIOR_COMMON * (p[0] + p[3]) / 2, PRIOR_COMMON * (p[1] + p[4]) / 2, PRIOR_COMMON * p[5],
                     PRIOR * (p[3] - p[0]), PRIOR * (p[4] - p[1]), PRIOR * p[2], PRIOR * p[6]])


def _fit_model(left: np.ndarray, right: np.ndarray, size: tuple[int, int]) -> tuple[_Model, np.ndarray]:
    """Find the seven parameters minimising the (Cauchy-robust) Sampson error of the matches."""
    model = _Model(size)
    left, right = left.astype(np.float64), right.astype(np.float64)

    # A pull of every parameter towards 0 (the identity, f = w + h), so that the directions the
    # matches cannot see stay at the least rotation instead of drifting (PRIOR).
    prior = np.sqrt(len(left))

    def residuals(p):
        r = sampson(model.fundamental(p), left, right)
        # The Cauchy loss as least squares: sum(r'^2) = sum(c^2 log(1 + (r/c)^2)).
        r = np.sign(r) * ROBUST * np.sqrt(np.log1p((r / ROBUST) ** 2))
        return np.concatenate([r, prior * _prior_terms(p)])

    p = np.zeros(7)
    # The angles first, at a fixed focal length: with the focal free from the start the
    # Jacobian is singular at the identity (Fusiello & Irsara, §3).
    p = _levenberg_marquardt(residuals, p, np.array([1, 1, 1, 1, 1, 0, 0], bool))
    p = _levenberg_marquardt(residuals, p, np.ones(7, bool))
    return model, p


def _homographies(model: _Model, p: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``H0``, ``H1`` and the rectified views' camera matrix.

    The left image's centre stays in place, and both views share a vertical offset.
    """
    K0, K1, R0, R1 = model.parts(p)
    Kn = K0
    H0 = Kn @ R0 @ np.linalg.inv(K0)
    H1 = Kn @ R1 @ np.linalg.inv(K1)
    cx, cy = _centre(model.size)
    moved = H0 @ np.array([cx, cy, 1.0])
    T = _translation(cx - moved[0] / moved[2], cy - moved[1] / moved[2])
    return T @ H0, T @ H1, T @ Kn


def fit_fundamental(left: np.ndarray, right: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``(F, inliers)``: MAGSAC++ fundamental matrix of matches ``left``/``right`` ((N, 2) px).

    ``inliers`` is its (N,) bool inlier mask. Raises :class:`DataError` when no geometry is found.
    """
    if len(left) < MIN_MATCHES:
        raise DataError(f"too few point matches for the epipolar geometry ({len(left)}, at least {MIN_MATCHES})")
    a, b = np.float64(left), np.float64(right)
    F = mask = None
    for seed in range(MAGSAC_SEEDS):
        # OpenCV 5's USAC stops on an internal assertion for some match sets (an empty model
        # after local optimisation, e.g. Middlebury's piecewise-planar Venus); another random
        # sequence gets past it. The seeds are fixed, so the result is reproducible.
        try:
            if seed == 0:
                F, mask = cv2.findFundamentalMat(a, b, cv2.USAC_MAGSAC, INLIER_PX, 0.9999, 20000)
            else:
                F, mask = cv2.findFundamentalMat(a, b, mask=None, params=_usac_magsac(seed))
            break
        except cv2.error:
            continue
    if F is None or F.shape != (3, 3) or mask is None or int(mask.sum()) < MIN_MATCHES // 2:
        raise DataError(f"no consistent epipolar geometry in {len(left)} point matches")
    return F, mask.ravel().astype(bool)


def _usac_magsac(seed: int):
    """OpenCV's USAC_MAGSAC settings with another random seed."""
    params = cv2.UsacParams()
    params.score, params.loMethod, params.final_polisher = cv2.SCORE_METHOD_MAGSAC, cv2.LOCAL_OPTIM_SIGMA, cv2.MAGSAC
    params.sampler, params.threshold, params.confidence = cv2.SAMPLING_UNIFORM, INLIER_PX, 0.9999
    params.maxIterations, params.loIterations, params.loSampleSize = 20000, 10, 50
    params.final_polisher_iterations, params.randomGeneratorState = 10, seed
    return params


def fit_rectification(matches: Sequence, size: tuple[int, int]) -> RigFit:
    """Fit one rectification to the matches of one or more pairs of a rig.

    ``matches``: per pair, an object with ``left``/``right`` (N, 2) px arrays
    (:class:`~stereocli.features.points.PointMatches`); ``size``: (w, h) of every image.
    The pooled matches give MAGSAC++'s inliers, the quasi-Euclidean model is fitted to them,
    and fitted again to the matches within :data:`INLIER_PX` of that model.
    """
    left = np.concatenate([np.asarray(m.left, np.float64).reshape(-1, 2) for m in matches])
    right = np.concatenate([np.asarray(m.right, np.float64).reshape(-1, 2) for m in matches])
    _, inliers = fit_fundamental(left, right)
    model, p = _fit_model(left[inliers], right[inliers], size)
    again = np.abs(sampson(model.fundamental(p), left, right)) <= INLIER_PX
    if again.sum() >= MIN_MATCHES:
        model, p = _fit_model(left[again], right[again], size)
    F = model.fundamental(p)
    final = np.abs(sampson(F, left, right)) <= INLIER_PX
    H0, H1, camera = _homographies(model, p)
    angles = dict(zip(("left_y", "left_z", "right_x", "right_y", "right_z"), np.degrees(p[:5]).tolist()))
    size = (int(size[0]), int(size[1]))
    rect = UncalibratedRectification(H0, H1, size, size, F / np.linalg.norm(F), camera, camera.copy(), angles,
                                     float(np.exp(p[6])))
    bounds = np.cumsum([0] + [len(np.asarray(m.left).reshape(-1, 2)) for m in matches])
    return RigFit(rect, [final[a:b] for a, b in zip(bounds[:-1], bounds[1:])], int(inliers.sum()))


def shifted(rect: UncalibratedRectification, shift: float) -> UncalibratedRectification:
    """``rect`` with the right view moved ``shift`` px to the right.

    Every disparity ``x_left − x_right`` decreases by ``shift`` (the shifts add up).
    """
    T = _translation(shift, 0)
    return replace(rect, H1=T @ rect.H1, camera1=T @ rect.camera1, shift=rect.shift + float(shift))


def framed(rect: UncalibratedRectification) -> UncalibratedRectification:
    """``rect`` with the smallest rectified images that hold its pair.

    They hold the whole warped left image and the part of the right image to its left (which
    holds the matches of the left image's first columns), at most half a width more; both views
    move together, so disparities stay.
    """
    w, h = rect.source_size
    corners = np.array([[0, 0], [w - 1, 0], [w - 1, h - 1], [0, h - 1]], np.float64)
    left, right = transform_points(rect.H0, corners), transform_points(rect.H1, corners)
    x0 = max(min(left[:, 0].min(), right[:, 0].min()), left[:, 0].min() - w / 2)
    x0, y0 = np.floor(x0), np.floor(left[:, 1].min())
    x1, y1 = np.ceil(left[:, 0].max()), np.ceil(left[:, 1].max())
    T = _translation(-x0, -y0)
    return replace(rect, H0=T @ rect.H0, H1=T @ rect.H1, camera0=T @ rect.camera0, camera1=T @ rect.camera1,
                   size=(int(x1 - x0) + 1, int(y1 - y0) + 1))


def rectified_matches(rect: UncalibratedRectification, matches: PointMatches) -> PointMatches:
    """Move ``matches`` into the rectified images of ``rect``."""
    return PointMatches(transform_points(rect.H0, matches.left).astype(np.float32),
                        transform_points(rect.H1, matches.right).astype(np.float32), matches.features)


def _from_zero(rect: UncalibratedRectification, matches: Sequence[PointMatches],
               inliers: Sequence[np.ndarray]) -> UncalibratedRectification:
    """``rect`` shifted so that the 1st percentile of the inliers' disparities is 0."""
    dx = np.concatenate([rectified_matches(rect, m).dx[i] for m, i in zip(matches, inliers)])
    return shifted(rect, float(np.percentile(dx, 1)))


# --------------------------------------------------------------------------- guided matching

def _coarse_disparity(left: np.ndarray, right: np.ndarray) -> tuple[np.ndarray, int]:
    """Match a rectified pair coarsely: a rough disparity map and its shrink factor.

    The map is (h, w) float32 px of the full resolution, NaN unknown, of a pair whose disparities
    start near 0: OpenCV's SGBM about :data:`GUIDE_WIDTH` px wide, searching ``[−W/8, W/2)``.
    """
    h, w = left.shape[:2]
    s = max(1, int(round(w / GUIDE_WIDTH)))
    a, b = (cv2.resize(grey_uint8(im), (w // s, h // s), interpolation=cv2.INTER_AREA) for im in (left, right))
    lo = -int(np.ceil(w / 8 / s))
    nd = 16 * int(np.ceil((w / 2 / s - lo) / 16))
    sgbm = cv2.StereoSGBM_create(minDisparity=lo, numDisparities=nd, blockSize=5, P1=8 * 25, P2=32 * 25,
                                 uniquenessRatio=10, disp12MaxDiff=1, speckleWindowSize=50, speckleRange=2,
                                 mode=cv2.STEREO_SGBM_MODE_SGBM_3WAY)
    # SGBM leaves the first lo + nd columns unmatched: pad them on, then crop them off.
    pad = max(0, lo + nd)
    a, b = (cv2.copyMakeBorder(im, 0, 0, pad, 0, cv2.BORDER_REPLICATE) for im in (a, b))
    disparity = sgbm.compute(a, b)[:, pad:].astype(np.float32) / 16.0
    disparity[disparity < lo] = np.nan
    return disparity * s, s


def _lookup(disparity: np.ndarray, scale: int, points: np.ndarray) -> np.ndarray:
    """Coarse disparities at full-resolution ``points`` ((N, 2) px).

    The nearest coarse pixel, else the median of the known ones within 3 coarse pixels; NaN when
    none is known.
    """
    h, w = disparity.shape
    k = 3
    ix = np.clip(np.rint(points[:, 0] / scale).astype(int), 0, w - 1) + k
    iy = np.clip(np.rint(points[:, 1] / scale).astype(int), 0, h - 1) + k
    padded = np.pad(disparity, k, constant_values=np.nan)
    window = np.stack([padded[iy + dy, ix + dx] for dy in range(-k, k + 1) for dx in range(-k, k + 1)])
    centre = padded[iy, ix]
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)  # an all-NaN window gives NaN, as wanted
        return np.where(np.isfinite(centre), centre, np.nanmedian(window, axis=0))


def guided_matches(left: np.ndarray, right: np.ndarray, rect: UncalibratedRectification) -> PointMatches:
    """Find matches by following a first rectification ``rect`` of the pair (original images).

    Corners of the left image (Shi–Tomasi) look up their disparity in a coarse dense match of
    the rectified pair (:func:`_coarse_disparity`), which puts their match in the right image
    within a pixel or two; Lucas–Kanade refines it on the original images (contrast-normalised,
    :func:`_normalised`) and a match is kept
    when tracking it back lands within :data:`ROUND_TRIP_PX` of the corner. Repeated texture
    (a calibration board), which descriptor matching rejects as ambiguous, is matched this way,
    and every depth of the scene gets matches, not just its most distinctive surfaces.
    """
    r0, r1, valid0, _ = warp_pair(left, right, rect)
    disparity, scale = _coarse_disparity(r0, r1)
    a = grey_uint8(left)
    found = cv2.goodFeaturesToTrack(a, GUIDED_CORNERS, 0.01, 8)
    a, b = _normalised(a), _normalised(grey_uint8(right))
    empty = PointMatches(np.zeros((0, 2), np.float32), np.zeros((0, 2), np.float32), 0)
    if found is None:
        return empty
    corners = found.reshape(-1, 2).astype(np.float64)
    at = transform_points(rect.H0, corners)
    d = _lookup(disparity, scale, at)
    h, w = valid0.shape
    inside = (at[:, 0] >= 0) & (at[:, 0] <= w - 1) & (at[:, 1] >= 0) & (at[:, 1] <= h - 1) & np.isfinite(d)
    corners, at, d = corners[inside], at[inside], d[inside]
    if not len(corners):
        return empty
    guess = transform_points(np.linalg.inv(rect.H1), at - np.column_stack([d, np.zeros(len(d))]))
    criteria = (cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT, 30, 0.01)
    start = corners.astype(np.float32).reshape(-1, 1, 2)
    track = dict(winSize=(15, 15), maxLevel=1, criteria=criteria, flags=cv2.OPTFLOW_USE_INITIAL_FLOW)
    there, ok, _ = cv2.calcOpticalFlowPyrLK(a, b, start, guess.astype(np.float32).reshape(-1, 1, 2), **track)
    back, ok_back, _ = cv2.calcOpticalFlowPyrLK(b, a, there, start.copy(), **track)
    there, back = there.reshape(-1, 2), back.reshape(-1, 2)
    keep = (ok.ravel() == 1) & (ok_back.ravel() == 1) & (np.linalg.norm(back - start.reshape(-1, 2), axis=1)
                                                         <= ROUND_TRIP_PX)
    return PointMatches(start.reshape(-1, 2)[keep], there[keep], len(found))


def _normalised(image: np.ndarray) -> np.ndarray:
    """(H, W) uint8 ``image`` with its local mean removed and its local contrast evened out.

    Gaussian windows, σ = 4 px, so that tracking between differently lit or exposed views compares
    structure, not brightness.
    """
    g = image.astype(np.float32)
    mean = cv2.GaussianBlur(g, (0, 0), 4)
    std = np.sqrt(cv2.GaussianBlur((g - mean) ** 2, (0, 0), 4)) + 4
    return np.clip(128 + 40 * (g - mean) / std, 0, 255).astype(np.uint8)


def _joined(a: PointMatches, b: PointMatches) -> PointMatches:
    return PointMatches(np.concatenate([a.left, b.left]), np.concatenate([a.right, b.right]), a.features)


# --------------------------------------------------------------------------- a rig's estimate

@dataclass
class PairEstimate:
    """What the estimate found in one pair (``error`` set when it cannot be rectified)."""

    matches: int = 0  # descriptor + guided matches
    inliers: int = 0
    dy_median: float | None = None  # |y_left − y_right| of the inliers after rectification, px
    dy_p90: float | None = None
    min_disp: int | None = None  # the pair's estimated disparity range in the rectified pair, px
    max_disp: int | None = None
    evidence: dict | None = None  # the range estimate's evidence (DisparityRange.as_dict()), shifted too
    error: str | None = None

    @property
    def fits(self) -> bool:
        """True when at least :data:`MIN_INLIER_SHARE` of the pair's matches fit the geometry."""
        return self.inliers >= MIN_INLIER_SHARE * self.matches

    def as_dict(self) -> dict:
        """Return the report as plain JSON types."""
        out: dict[str, Any] = {"matches": self.matches, "inliers": self.inliers, "fits": self.fits,
               "dy_median": None if self.dy_median is None else round(self.dy_median, 3),
               "dy_p90": None if self.dy_p90 is None else round(self.dy_p90, 3)}
        if self.error:
            out["error"] = self.error
        return out


class ImagePairs(Protocol):
    """The pairs :func:`estimate_rectification` reads: ``len()``, and ``[i]`` for pair ``i``.

    ``[i]`` gives the ``(left, right)`` images of pair ``i``: a list, or an object that reads them
    when asked.
    """

    def __len__(self) -> int: ...

    def __getitem__(self, index: int, /) -> tuple[np.ndarray, np.ndarray]: ...


@dataclass
class RigEstimate:
    """One rectification for every pair of a rig, and what each pair says about it."""

    rectification: UncalibratedRectification
    pairs: list[PairEstimate]
    magsac_inliers: int


def estimate_rectification(pairs: ImagePairs, *,
                           rounds: int = GUIDED_ROUNDS) -> RigEstimate:
    """Estimate one uncalibrated rectification for the pairs of a rig.

    ``pairs[i]`` is the ``(left, right)`` images of pair ``i`` (same size everywhere); it is
    read once per round, so a sequence that loads on access keeps one pair in memory.

    SIFT matches of every pair are pooled for a first fit (:func:`fit_rectification`); then
    ``rounds`` times, guided matches (:func:`guided_matches`) are added and the fit repeated.
    Finally the disparity range of every rectified pair is estimated
    (:func:`~stereocli.features.disparity_range.estimate_range`) and the right view shifted so
    the smallest disparity the rig's estimates expect (:func:`_lowest_disparity`) is 0. A pair
    that cannot be read, has fewer than :data:`MIN_PAIR_MATCHES` matches or no estimable range
    gets an ``error`` (it is not to be rectified). Raises :class:`DataError` when no pair can be used.
    """
    from ..features.disparity_range import estimate_range

    n = len(pairs)
    results = [PairEstimate() for _ in range(n)]
    descriptor: dict[int, PointMatches] = {}
    size = None
    for i in range(n):
        try:
            left, right = pairs[i]
        except DataError as exc:
            results[i].error = str(exc)
            continue
        if left.shape[:2] != right.shape[:2]:
            results[i].error = (f"left is {left.shape[1]}x{left.shape[0]} but right is "
                                f"{right.shape[1]}x{right.shape[0]}")
            continue
        if size is None:
            size = (left.shape[1], left.shape[0])
        elif size != (left.shape[1], left.shape[0]):
            results[i].error = (f"images are {left.shape[1]}x{left.shape[0]}, the rig's first pair "
                                f"{size[0]}x{size[1]}; rectify pairs of another size separately")
            continue
        found = match_points(left, right, method="sift", max_features=SIFT_FEATURES)
        if len(found) < MIN_PAIR_MATCHES:
            results[i].matches = len(found)
            results[i].error = (f"too little texture to rectify: {len(found)} point matches "
                                f"(at least {MIN_PAIR_MATCHES})")
            continue
        descriptor[i] = found
    used = sorted(descriptor)
    if not used or size is None:  # (size is set by every pair in used)
        raise DataError(next((r.error for r in results if r.error), "no pairs"))
    matches = [descriptor[i] for i in used]
    fit = fit_rectification(matches, size)
    rect = _from_zero(fit.rectification, matches, fit.inliers)
    for _ in range(rounds):
        matches = [_joined(descriptor[i], guided_matches(*pairs[i], rect)) for i in used]
        fit = fit_rectification(matches, size)
        rect = _from_zero(fit.rectification, matches, fit.inliers)
    for i, m, inliers in zip(used, matches, fit.inliers):
        dy = np.abs(vertical_residuals(rect, m.left[inliers], m.right[inliers]))
        est = results[i]
        est.matches, est.inliers = len(m), int(inliers.sum())
        if len(dy):
            est.dy_median, est.dy_p90 = float(np.median(dy)), float(np.percentile(dy, 90))
        r0, r1, _, _ = warp_pair(*pairs[i], rect)
        kept = PointMatches(m.left[inliers], m.right[inliers], m.features)
        try:
            pair_range = estimate_range(r0, r1, rectified_matches(rect, kept))
        except DataError as exc:
            est.error = str(exc)
            continue
        est.min_disp, est.max_disp, est.evidence = pair_range.min_disp, pair_range.max_disp, pair_range.as_dict()
    ranged = [r for r in results if r.min_disp is not None]
    if not ranged:
        raise DataError(next((r.error for r in results if r.error), "no disparity range"))
    # The rig's pairs set the shift (a pair that does not fit it has no meaningful range); an
    # integer, so the ranges stay whole pixels.
    # (Every pair in ``ranged`` got min_disp, max_disp and evidence together.)
    shift = min(_lowest_disparity(cast(dict, r.evidence)) for r in ([r for r in ranged if r.fits] or ranged))
    for r in ranged:
        evidence = cast(dict, r.evidence)
        r.min_disp, r.max_disp = max(0, cast(int, r.min_disp) - shift), cast(int, r.max_disp) - shift
        evidence["min_disp"] -= shift
        for key in ("dense_percentiles", "sparse_percentiles"):
            if evidence.get(key) is not None:
                evidence[key] = [round(v - shift, 2) for v in evidence[key]]
    return RigEstimate(framed(shifted(rect, float(shift))), results, fit.magsac_inliers)


def _lowest_disparity(evidence: dict) -> int:
    """Find the smallest disparity (px) a pair's range estimate expects, with a smaller margin.

    The margin is one coarse pixel + 2 px rather than the range's own (``2·scale + 4``). It
    becomes disparity 0 of the rectified pair. Every pixel of margin moves every true match
    one column further right, so the first columns of the left image lose their matches
    beyond the right image's edge; the range's full margin cost up to 14 columns. On the
    Middlebury scenes, the smallest true disparity lies at most 4.8 px below the estimate's
    lower percentile (Pipes, coarse scale 5: margin 7).
    """
    lows = [evidence[key][0] for key in ("dense_percentiles", "sparse_percentiles") if evidence.get(key)]
    return int(np.floor(min(lows) - evidence["scale"] - 2))


# --------------------------------------------------------------------------- applying it

def transform_points(H: np.ndarray, points: np.ndarray) -> np.ndarray:
    """(N, 2) float64 images of (N, 2) ``points`` under homography ``H``."""
    pts = np.asarray(points, np.float64).reshape(-1, 2)
    out = np.column_stack([pts, np.ones(len(pts))]) @ H.T
    return out[:, :2] / out[:, 2:3]


def vertical_residuals(rect: UncalibratedRectification, left: np.ndarray, right: np.ndarray) -> np.ndarray:
    """(N,) float64 ``y_left − y_right`` (px) of matches after rectification (0 when perfect)."""
    return transform_points(rect.H0, left)[:, 1] - transform_points(rect.H1, right)[:, 1]


def _inverse_maps(H: np.ndarray, size: tuple[int, int]) -> tuple[np.ndarray, np.ndarray]:
    """float32 (h, w) source coordinates of every rectified pixel."""
    w, h = size
    ys, xs = np.mgrid[0:h, 0:w].astype(np.float64)
    Hi = np.linalg.inv(H)
    den = Hi[2, 0] * xs + Hi[2, 1] * ys + Hi[2, 2]
    mx = (Hi[0, 0] * xs + Hi[0, 1] * ys + Hi[0, 2]) / den
    my = (Hi[1, 0] * xs + Hi[1, 1] * ys + Hi[1, 2]) / den
    return mx.astype(np.float32), my.astype(np.float32)


def warp_pair(left: np.ndarray, right: np.ndarray, rect: UncalibratedRectification, *,
              interpolation: str = "linear") -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """``(left, right, valid0, valid1)``: the rectified images and their masks.

    The images keep their dtype and channels, 0 outside the source; the masks are uint8 (h, w),
    255 where the pixel lies on the source image.
    """
    if interpolation not in INTERPOLATIONS:
        raise ValueError(f"unknown interpolation {interpolation!r}; valid: {', '.join(INTERPOLATIONS)}")
    for image in (left, right):
        if image.shape[1::-1] != tuple(rect.source_size):
            raise DataError(f"image is {image.shape[1]}x{image.shape[0]} but the rectification is for "
                            f"{rect.source_size[0]}x{rect.source_size[1]}")
    out = []
    w, h = rect.source_size
    for image, H in ((left, rect.H0), (right, rect.H1)):
        mx, my = _inverse_maps(H, rect.size)
        # A pixel is inside the source image when it falls on the area its pixels cover (half a
        # pixel beyond the outer pixel centres); the edge pixels are repeated to sample it.
        inside = (mx >= -0.5) & (mx <= w - 0.5) & (my >= -0.5) & (my <= h - 0.5)
        warped = cv2.remap(image, mx, my, INTERPOLATIONS[interpolation], borderMode=cv2.BORDER_REPLICATE)
        warped[~inside] = 0
        out.append((warped, np.where(inside, np.uint8(255), np.uint8(0))))
    return out[0][0], out[1][0], out[0][1], out[1][1]


def uncalibrated_calib_txt(rect: UncalibratedRectification, ndisp: int, min_disp: int, max_disp: int):
    """Build the Middlebury calib.txt of an uncalibrated rectification ``rect``.

    It holds the rectified views' virtual cameras (``doffs`` = where infinity would be if their
    focal length were right), the size and the disparity range; no baseline (0), and
    ``rectification=uncalibrated`` says why.
    """
    from ..io.middlebury import MiddleburyCalib

    return MiddleburyCalib(cam0=rect.camera0, cam1=rect.camera1, doffs=float(rect.camera1[0, 2] - rect.camera0[0, 2]),
                           baseline=0.0, width=int(rect.size[0]), height=int(rect.size[1]), ndisp=int(ndisp), isint=0,
                           vmin=float(min_disp), vmax=float(max_disp), extra={"rectification": "uncalibrated"})


def warp_distortion(H: np.ndarray, size: tuple[int, int]) -> dict[str, float]:
    """How much ``H`` distorts an image of ``size`` (w, h) (Mallon & Whelan, 2005).

    The midpoints of the image's edges are warped; ``orthogonality_deg`` is the angle between
    the warped horizontal and vertical mid-lines (90 = no shear), ``aspect`` the ratio of their
    lengths relative to the original's (1 = kept), ``area`` the warped image's area over the
    original's.
    """
    w, h = size
    cx, cy = _centre(size)
    mids = transform_points(H, np.array([[cx, 0], [w - 1, cy], [cx, h - 1], [0, cy]], np.float64))
    u, v = mids[1] - mids[3], mids[2] - mids[0]
    angle = np.degrees(np.arccos(np.clip(u @ v / (np.linalg.norm(u) * np.linalg.norm(v)), -1, 1)))
    corners = transform_points(H, np.array([[0, 0], [w - 1, 0], [w - 1, h - 1], [0, h - 1]], np.float64))
    x, y = corners[:, 0], corners[:, 1]
    area = 0.5 * abs(np.dot(x, np.roll(y, -1)) - np.dot(y, np.roll(x, -1)))
    return {"orthogonality_deg": round(float(angle), 4),
            "aspect": round(float(np.linalg.norm(u) / np.linalg.norm(v) * (h - 1) / (w - 1)), 5),
            "area": round(float(area / ((w - 1) * (h - 1))), 5)}


# --------------------------------------------------------------------------- disparities back to the originals

def _sample_disparity(disparity: np.ndarray, x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """``disparity`` at sub-pixel positions.

    Bilinear where the four neighbours are finite and within 1 px of each other (one surface),
    else the nearest pixel (a depth edge or a hole is not blended); +inf outside the map.
    """
    h, w = disparity.shape
    x0, y0 = np.floor(x).astype(np.int64), np.floor(y).astype(np.int64)
    fx, fy = (x - x0).astype(np.float32), (y - y0).astype(np.float32)

    def at(xi, yi):
        inside = (xi >= 0) & (xi < w) & (yi >= 0) & (yi < h)
        values = disparity[np.clip(yi, 0, h - 1), np.clip(xi, 0, w - 1)]
        return np.where(inside, values, np.float32(np.inf))

    a, b, c, d = at(x0, y0), at(x0 + 1, y0), at(x0, y0 + 1), at(x0 + 1, y0 + 1)
    stack = np.stack([a, b, c, d])
    with np.errstate(invalid="ignore"):
        smooth = np.isfinite(stack).all(axis=0) & (stack.max(axis=0) - stack.min(axis=0) <= 1.0)
        blended = (a * (1 - fx) + b * fx) * (1 - fy) + (c * (1 - fx) + d * fx) * fy
    nearest = at(np.rint(x).astype(np.int64), np.rint(y).astype(np.int64))
    return np.where(smooth, blended, nearest).astype(np.float32)


def disparity_to_original(disparity: np.ndarray, H0: np.ndarray, H1: np.ndarray,
                          shape: tuple[int, int]) -> tuple[np.ndarray, np.ndarray]:
    """Map a disparity map of a rectified pair back to the original (unrectified) left image.

    Parameters
    ----------
    disparity : (h, w) float32 disparity of the rectified left image (px, +inf invalid).
    H0, H1 : (3, 3) original → rectified homographies (``rectification.json``).
    shape : (H, W) of the original images (``source_size`` reversed).

    Returns
    -------
    ``(dx, dy)``, each (H, W) float32: for every original left pixel ``p`` whose match ``q`` in
    the original right image is known, ``dx = p.x − q.x`` (the disparity in the originals'
    frame) and ``dy = p.y − q.y`` (0 for a pair that was already rectified); +inf elsewhere.

    Notes
    -----
    ``p`` goes to ``p' = H0·p``; the disparity is read there (bilinear on smooth surfaces,
    nearest at depth edges); the match ``q' = p' − (d, 0)`` goes back by ``q = H1⁻¹·q'``.
    """
    disparity = np.asarray(disparity, np.float32)
    h, w = shape
    ys, xs = np.mgrid[0:h, 0:w].astype(np.float64)
    grid = np.column_stack([xs.ravel(), ys.ravel()])
    rect_left = transform_points(H0, grid)
    d = _sample_disparity(disparity, rect_left[:, 0], rect_left[:, 1])
    ok = np.isfinite(d)
    dx = np.full(h * w, np.inf, np.float32)
    dy = np.full(h * w, np.inf, np.float32)
    rect_right = rect_left[ok] - np.column_stack([d[ok], np.zeros(int(ok.sum()))])
    right = transform_points(np.linalg.inv(H1), rect_right)
    dx[ok] = grid[ok, 0] - right[:, 0]
    dy[ok] = grid[ok, 1] - right[:, 1]
    return dx.reshape(h, w), dy.reshape(h, w)
