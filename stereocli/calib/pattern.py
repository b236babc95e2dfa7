"""Calibration targets: geometry (object points) and detection in one image.

Pattern sizes count what the detector finds: **inner corners** for chessboards and ChArUco
(a 10x7-square board is ``9x6``), circle centres for circle grids. ``square`` is the side of
one square (chessboard, ChArUco) or the centre spacing (circle grids; for the asymmetric grid
the spacing between neighbouring rows/columns of OpenCV's layout ``((2j + i % 2)·s, i·s)``),
in the calibration's length unit.
"""

from __future__ import annotations

import re
from dataclasses import dataclass

import cv2
import numpy as np

from ..errors import ConfigError, did_you_mean, excerpt

KINDS = ("chessboard", "circles", "acircles", "charuco")
DETECTORS = ("auto", "classic", "sb")


@dataclass(frozen=True)
class Pattern:
    """A planar target. ``cols x rows`` detected points; ``square`` in ``units``."""

    cols: int
    rows: int
    square: float = 1.0
    kind: str = "chessboard"
    units: str = "unit"
    marker: float = 0.75  # ChArUco marker side as a fraction of the square side
    dictionary: str = "DICT_5X5_100"  # ChArUco ArUco dictionary name (cv2.aruco.DICT_*)

    def __post_init__(self) -> None:
        if self.kind not in KINDS:
            raise ConfigError(f"unknown pattern type {self.kind!r} (choose {', '.join(KINDS)})")
        if self.cols < 2 or self.rows < 2:
            raise ConfigError(f"pattern {self.cols}x{self.rows} is too small (need at least 2x2 points)")
        if not self.square > 0:
            raise ConfigError(f"--square must be positive, got {self.square}")
        if self.kind == "charuco" and not (0 < self.marker < 1):
            raise ConfigError(f"ChArUco marker fraction must be in (0, 1), got {self.marker}")
        if self.kind == "charuco":
            _aruco_dictionary_id(self.dictionary)  # an unknown name is a usage error, before any detection

    @property
    def size(self) -> tuple[int, int]:
        return (self.cols, self.rows)

    @property
    def count(self) -> int:
        return self.cols * self.rows

    @property
    def key(self) -> str:
        """Identifies the detection problem (square size does not change detections)."""
        extra = f":{self.dictionary}:{self.marker:g}" if self.kind == "charuco" else ""
        return f"{self.kind}:{self.cols}x{self.rows}{extra}"

    def object_points(self) -> np.ndarray:
        """(cols·rows, 3) float32 board coordinates (z = 0) in detection order."""
        i, j = np.mgrid[0:self.rows, 0:self.cols]
        if self.kind == "acircles":
            x, y = (2 * j + i % 2) * self.square, i * self.square
        else:
            x, y = j * self.square, i * self.square
        pts = np.stack([x.ravel(), y.ravel(), np.zeros(x.size)], axis=1)
        return pts.astype(np.float32)

    def charuco_board(self):
        if not hasattr(cv2, "aruco") or not hasattr(cv2.aruco, "CharucoDetector"):
            raise ConfigError("this OpenCV build has no cv2.aruco.CharucoDetector (ChArUco unsupported)")
        dictionary = cv2.aruco.getPredefinedDictionary(_aruco_dictionary_id(self.dictionary))
        return cv2.aruco.CharucoBoard((self.cols + 1, self.rows + 1), float(self.square),
                                      float(self.square * self.marker), dictionary)


def _aruco_dictionary_id(name: str) -> int:
    """OpenCV's id of a predefined ArUco dictionary (``DICT_5X5_100``), or a ConfigError listing them."""
    aruco = getattr(cv2, "aruco", None)
    known = sorted(n for n in dir(aruco) if n.startswith("DICT_")) if aruco is not None else []
    value = getattr(aruco, str(name).upper(), None) if str(name).upper().startswith("DICT_") else None
    if not isinstance(value, int):
        raise ConfigError(f"--dictionary {excerpt(name, quote=True)}: unknown ArUco dictionary"
                          + did_you_mean(str(name).upper(), known)
                          + f"; e.g. DICT_5X5_100, DICT_4X4_50 ({len(known)} predefined)")
    return value


_PATTERN = re.compile(r"^\s*(\d+)\s*[xX×,]\s*(\d+)\s*$")


def parse_pattern_size(text: str) -> tuple[int, int]:
    """``"9x6"`` → (9, 6); a ConfigError names the expected form otherwise."""
    m = _PATTERN.match(text or "")
    if not m:
        raise ConfigError(f"--pattern {excerpt(text, quote=True)}: expected COLSxROWS inner corners, e.g. 9x6")
    return int(m.group(1)), int(m.group(2))


_SQUARE = re.compile(r"^\s*([0-9]*\.?[0-9]+(?:[eE][-+]?\d+)?)\s*([a-zA-Zµ]*)\s*$")


def parse_square(square: float | str, units: str | None = None) -> tuple[float, str]:
    """``(side, unit)`` of a square: a number in ``units`` (default ``"unit"``), or a length
    with its unit like ``"25mm"`` (which ``units``, when given, must agree with)."""
    if isinstance(square, str):
        m = _SQUARE.match(square)
        if not m:
            raise ConfigError(f"square {square!r}: expected a length like 25mm, 0.025m or 1")
        if units and m.group(2) and units != m.group(2):
            raise ConfigError(f"square {square!r} and units {units!r} disagree")
        value, unit = float(m.group(1)), m.group(2) or units or "unit"
    else:
        value, unit = float(square), units or "unit"
    if not 0 < value < float("inf"):
        raise ConfigError(f"square must be a positive length, got {square!r}")
    return value, unit


def _to_u8(image: np.ndarray) -> np.ndarray:
    if image.ndim == 3:
        image = cv2.cvtColor(image, cv2.COLOR_RGB2GRAY)
    if image.dtype != np.uint8:
        image = cv2.convertScaleAbs(image, alpha=255.0 / max(float(image.max()), 1.0))
    return image


def _subpix_window(corners: np.ndarray, cols: int) -> int:
    # Half the window must stay inside one square or the refinement drifts to the next corner.
    pts = corners.reshape(-1, cols, 2)
    spacing = np.median(np.linalg.norm(np.diff(pts, axis=1), axis=2))
    return int(np.clip(round(spacing * 0.4), 2, 11))


def detect(image: np.ndarray, pattern: Pattern, *, detector: str = "auto"
           ) -> tuple[np.ndarray | None, np.ndarray | None, str]:
    """Find the target in one image.

    Returns ``(corners, ids, reason)``: corners (N, 2) float32 pixels with sub-pixel
    refinement, ids (N,) int32 point indices into :meth:`Pattern.object_points` (``None`` for
    full detections), and an empty reason on success or a short reason on failure.
    """
    if detector not in DETECTORS:
        raise ConfigError(f"unknown detector {detector!r} (choose {', '.join(DETECTORS)})")
    gray = _to_u8(image)
    if pattern.kind == "chessboard":
        corners = None
        if detector in ("auto", "classic"):
            flags = cv2.CALIB_CB_ADAPTIVE_THRESH | cv2.CALIB_CB_NORMALIZE_IMAGE
            ok, found = cv2.findChessboardCorners(gray, pattern.size, flags=flags)
            if ok:
                win = _subpix_window(found, pattern.cols)
                criteria = (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_COUNT, 100, 1e-4)
                corners = cv2.cornerSubPix(gray, found, (win, win), (-1, -1), criteria)
        if corners is None and detector in ("auto", "sb"):
            ok, found = cv2.findChessboardCornersSB(gray, pattern.size, flags=cv2.CALIB_CB_ACCURACY)
            if ok:
                corners = found
        if corners is None:
            return None, None, f"chessboard {pattern.cols}x{pattern.rows} (inner corners) not found"
        return corners.reshape(-1, 2).astype(np.float32), None, ""
    if pattern.kind in ("circles", "acircles"):
        flag = cv2.CALIB_CB_SYMMETRIC_GRID if pattern.kind == "circles" else cv2.CALIB_CB_ASYMMETRIC_GRID
        ok, centres = cv2.findCirclesGrid(gray, pattern.size, flags=flag)
        if not ok:
            return None, None, f"{pattern.kind} grid {pattern.cols}x{pattern.rows} not found"
        return centres.reshape(-1, 2).astype(np.float32), None, ""
    detector_ = cv2.aruco.CharucoDetector(pattern.charuco_board())
    ch_corners, ch_ids, _, marker_ids = detector_.detectBoard(gray)
    if ch_ids is None or len(ch_ids) < 6:
        n = 0 if marker_ids is None else len(marker_ids)
        return None, None, f"ChArUco board: {0 if ch_ids is None else len(ch_ids)} corners ({n} markers) found, need 6"
    return ch_corners.reshape(-1, 2).astype(np.float32), ch_ids.ravel().astype(np.int32), ""
