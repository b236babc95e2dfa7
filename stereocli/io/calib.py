"""Stereo calibration files: one in-memory model, several on-disk formats.

Formats (``load_calibration`` detects them from the extension and the content):

* **OpenCV FileStorage** (``.yml``/``.yaml``/``.xml``/``.json``; written and read through
  ``cv2.FileStorage`` because PyYAML cannot parse ``%YAML:1.0`` / ``!!opencv-matrix``).
  Keys: ``M1 D1 M2 D2 R T E F R1 R2 P1 P2 Q`` (``K1``/``K2`` accepted on read),
  ``image_width``, ``image_height``, ``rms``, ``units``, ``model``. Lossless (17 digits).
* **ROS camera_info pair**: ``OUT_left.yaml`` + ``OUT_right.yaml`` (``image_width``,
  ``image_height``, ``camera_name``, ``camera_matrix``, ``distortion_model``,
  ``distortion_coefficients``, ``rectification_matrix``, ``projection_matrix`` with the
  right ``P[0,3] = -fx'·B``). ROS lengths are metres (REP 103): writing converts from the
  calibration's unit (and refuses an unknown one), reading gives ``units="m"``. R and T are
  recovered exactly from R1, R2, P2 (``R = R2ᵀ·R1``, ``T = R2ᵀ·[P2[0,3]/P2[0,0], 0, 0]``); the
  RMS is not stored by ROS.
  Reading accepts either file of the pair, the base name ``OUT.yaml`` when only the pair
  exists, or one file holding the two documents (left first).
* **Kalibr camchain** (``cam0``/``cam1`` with ``intrinsics``, ``distortion_coeffs``,
  ``T_cn_cnm1`` = cam0 → cam1), read only; ``radtan`` → OpenCV pinhole, ``equidistant`` →
  fisheye. Kalibr works in metres.
* **Middlebury calib.txt** for an already rectified pair: ``cam0``/``cam1`` become K1/K2 and
  the rectified P1/P2 (no distortion, R = I), ``baseline`` (mm) becomes ``T = [-B, 0, 0]``
  with units ``mm``. Writing needs a rectified calibration (P1, P2).

Conventions (OpenCV): ``X_right = R · X_left + T``; for a left→right rig ``T[0] ≈ -B``.
"""

from __future__ import annotations

import math
import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, overload

import numpy as np

from ..errors import ConfigError, DataError, excerpt
from .atomic import atomic_path, write_text
from .middlebury import MiddleburyCalib, format_calib_txt, read_calib_txt
from .text import check_text_size, read_text_limited

if TYPE_CHECKING:
    from numpy.typing import ArrayLike

OPENCV_SUFFIXES = (".yml", ".yaml", ".xml", ".json")
FORMATS = ("opencv", "ros", "middlebury")

#: Length units we can convert between (value = metres per unit).
UNIT_SCALE = {"m": 1.0, "cm": 0.01, "mm": 0.001, "um": 1e-6, "in": 0.0254, "ft": 0.3048}


@dataclass
class StereoCalibration:
    """A calibrated stereo rig (OpenCV conventions).

    Attributes
    ----------
    K1, K2 : (3, 3) float64 intrinsics of the left / right camera (pixels).
    D1, D2 : (N,) float64 distortion (OpenCV order k1 k2 p1 p2 [k3 ...], or 4 fisheye k1..k4).
    R, T : (3, 3), (3,) float64, ``X_right = R · X_left + T``; T in ``units``.
    E, F : (3, 3) essential and fundamental matrices (derived when absent).
    R1, R2, P1, P2, Q : rectification (``stereoRectify`` outputs) or None when not computed.
    image_size : (width, height) of the unrectified images; ``rectified_size`` of P1/P2.
    rms : stereo reprojection RMS in pixels, or None.
    units : length unit of T (and hence of depth), e.g. ``"m"``, ``"mm"``, ``"square"``.
    model : ``"pinhole"`` or ``"fisheye"``.
    """

    K1: np.ndarray
    D1: np.ndarray
    K2: np.ndarray
    D2: np.ndarray
    R: np.ndarray
    T: np.ndarray
    image_size: tuple[int, int]
    E: np.ndarray | None = None
    F: np.ndarray | None = None
    R1: np.ndarray | None = None
    R2: np.ndarray | None = None
    P1: np.ndarray | None = None
    P2: np.ndarray | None = None
    Q: np.ndarray | None = None
    rectified_size: tuple[int, int] | None = None
    rms: float | None = None
    units: str = "unit"
    model: str = "pinhole"
    extra: dict = field(default_factory=dict)

    def __post_init__(self) -> None:
        self.K1, self.K2 = _float64(self.K1, (3, 3)), _float64(self.K2, (3, 3))
        self.D1, self.D2 = _float64(self.D1).ravel(), _float64(self.D2).ravel()
        self.R, self.T = _float64(self.R, (3, 3)), _float64(self.T).ravel()
        for key, shape in (("E", (3, 3)), ("F", (3, 3)), ("R1", (3, 3)), ("R2", (3, 3)), ("P1", (3, 4)),
                           ("P2", (3, 4)), ("Q", (4, 4))):
            setattr(self, key, _float64(getattr(self, key), shape))
        self.image_size = (int(self.image_size[0]), int(self.image_size[1]))
        if self.rectified_size is not None:
            self.rectified_size = (int(self.rectified_size[0]), int(self.rectified_size[1]))
        if self.T.shape != (3,):
            raise DataError(f"T must have 3 elements, got {self.T.size}")
        for key in ("K1", "K2"):
            _check_camera_matrix(key, getattr(self, key))
        if self.E is None:
            self.E = skew(self.T) @ self.R
        if self.F is None:
            self.F = np.linalg.inv(self.K2).T @ self.E @ np.linalg.inv(self.K1)

    @property
    def baseline(self) -> float:
        """Distance between the camera centres, in ``units``."""
        return float(np.linalg.norm(self.T))

    @property
    def is_rectified(self) -> bool:
        return self.P1 is not None and self.P2 is not None


@overload
def _float64(a: None, shape: tuple[int, ...] | None = None) -> None: ...
@overload
def _float64(a: ArrayLike, shape: tuple[int, ...] | None = None) -> np.ndarray: ...
def _float64(a, shape=None):
    """``a`` as a float64 array of ``shape`` (default: its own); None stays None."""
    return None if a is None else np.asarray(a, dtype=np.float64).reshape(shape or np.shape(a))


def skew(t: np.ndarray) -> np.ndarray:
    """The cross-product matrix ``[t]×`` (so ``E = [T]× R``)."""
    x, y, z = np.asarray(t, dtype=np.float64).ravel()
    return np.array([[0, -z, y], [z, 0, -x], [-y, x, 0]], dtype=np.float64)


def q_from_projections(P1: np.ndarray, P2: np.ndarray) -> np.ndarray:
    """OpenCV's horizontal-rig Q from rectified P1, P2: ``[x y d 1] → [X Y Z W]``.

    With ``Tx = P2[0,3] / P2[0,0]`` (= -B): ``W = (d - (cx1 - cx2)) / -Tx`` and ``Z = f / W``,
    i.e. ``Z = f·B / (d + doffs)`` with ``doffs = cx2 - cx1``.
    """
    f, cx1, cy = P1[0, 0], P1[0, 2], P1[1, 2]
    cx2 = P2[0, 2]
    tx = P2[0, 3] / P2[0, 0]
    return np.array([[1, 0, 0, -cx1], [0, 1, 0, -cy], [0, 0, 0, f], [0, 0, -1 / tx, (cx1 - cx2) / tx]],
                    dtype=np.float64)


# --------------------------------------------------------------------------- OpenCV FileStorage

def _fs_open(path: Path, mode: int):
    import cv2

    try:
        fs = cv2.FileStorage(str(path), mode)
    except (cv2.error, SystemError) as exc:  # SystemError: OpenCV's parser error surfacing through pybind
        cause = exc.__cause__ or exc.__context__ or exc
        lines = str(cause).strip().splitlines()
        msg = lines[-1].strip() if lines else "parse error"
        raise DataError(f"{path}: corrupt OpenCV FileStorage file ({msg})") from None
    if not fs.isOpened():
        raise DataError(f"{path}: cannot open as OpenCV FileStorage")
    return fs


def write_opencv(path: str | os.PathLike, calib: StereoCalibration) -> None:
    """Write ``calib`` as OpenCV FileStorage; the format follows the extension."""
    import cv2

    path = Path(path)
    if path.suffix.lower() not in OPENCV_SUFFIXES:
        raise ConfigError(f"{path}: OpenCV FileStorage needs a .yml, .yaml, .xml or .json name")
    with atomic_path(path) as tmp:
        fs = _fs_open(tmp, cv2.FILE_STORAGE_WRITE)
        fs.write("image_width", int(calib.image_size[0]))
        fs.write("image_height", int(calib.image_size[1]))
        fs.write("units", calib.units)
        fs.write("model", calib.model)
        if calib.rms is not None:
            fs.write("rms", float(calib.rms))
        for key, value in (("M1", calib.K1), ("D1", calib.D1.reshape(1, -1)), ("M2", calib.K2),
                           ("D2", calib.D2.reshape(1, -1)), ("R", calib.R), ("T", calib.T.reshape(3, 1)),
                           ("E", calib.E), ("F", calib.F), ("R1", calib.R1), ("R2", calib.R2),
                           ("P1", calib.P1), ("P2", calib.P2), ("Q", calib.Q)):
            if value is not None:
                fs.write(key, np.asarray(value, dtype=np.float64))
        if calib.rectified_size is not None:
            fs.write("rectified_width", int(calib.rectified_size[0]))
            fs.write("rectified_height", int(calib.rectified_size[1]))
        for key, value in calib.extra.items():
            if isinstance(value, (int, float)) and not isinstance(value, bool):
                fs.write(key, float(value) if isinstance(value, float) else int(value))
            elif isinstance(value, str):
                fs.write(key, value)
            elif isinstance(value, np.ndarray):
                fs.write(key, value.astype(np.float64))
        fs.release()


def read_opencv(path: str | os.PathLike) -> StereoCalibration:
    """Read an OpenCV FileStorage calibration (``M1``/``K1``, ``D1``, ..., ``R``, ``T`` required)."""
    import cv2

    path = Path(path)
    check_text_size(path, "calibration file")
    fs = _fs_open(path, cv2.FILE_STORAGE_READ)
    try:
        root = fs.root()
        keys = set(root.keys()) if root.isMap() else set()

        def mat(*names: str, required: bool = False):
            for name in names:
                node = fs.getNode(name)
                if not node.empty():
                    m = node.mat()
                    if m is None:
                        raise DataError(f"{path}: key {name} is not a matrix")
                    return m
            if required:
                raise DataError(f"{path}: missing key {names[0]} (calibration needs M1 D1 M2 D2 R T)")
            return None

        def num(name: str):
            node = fs.getNode(name)
            return None if node.empty() else node.real()

        def text(name: str, default: str) -> str:
            node = fs.getNode(name)
            return default if node.empty() else (node.string() or default)

        K1, K2 = mat("M1", "K1", "cameraMatrix1", required=True), mat("M2", "K2", "cameraMatrix2", required=True)
        D1, D2 = mat("D1", "distCoeffs1", required=True), mat("D2", "distCoeffs2", required=True)
        R, T = mat("R", required=True), mat("T", required=True)
        width, height = num("image_width"), num("image_height")
        if width is None or height is None:
            size = mat("image_size", "imageSize")
            if size is None:
                raise DataError(f"{path}: missing key image_width/image_height")
            width, height = size.ravel()[:2]
        rw, rh = num("rectified_width"), num("rectified_height")
        known = {"M1", "K1", "M2", "K2", "D1", "D2", "R", "T", "E", "F", "R1", "R2", "P1", "P2", "Q", "rms",
                 "units", "model", "image_width", "image_height", "rectified_width", "rectified_height",
                 "cameraMatrix1", "cameraMatrix2", "distCoeffs1", "distCoeffs2", "image_size", "imageSize"}
        extra = {}
        for key in sorted(keys - known):
            node = fs.getNode(key)
            if node.isString():
                extra[key] = node.string()
            elif node.isInt():
                extra[key] = int(node.real())
            elif node.isReal():
                extra[key] = node.real()
            elif node.isMap() and node.mat() is not None:
                extra[key] = node.mat()
        try:
            return StereoCalibration(
                K1=K1, D1=D1, K2=K2, D2=D2, R=R, T=T, E=mat("E"), F=mat("F"), R1=mat("R1"), R2=mat("R2"),
                P1=mat("P1"), P2=mat("P2"), Q=mat("Q"), image_size=(int(width), int(height)),
                rectified_size=(int(rw), int(rh)) if rw is not None and rh is not None else None,
                rms=num("rms"), units=text("units", "unit"), model=text("model", "pinhole"), extra=extra)
        except ValueError as exc:
            raise DataError(f"{path}: a matrix has the wrong shape ({exc})") from None
    finally:
        fs.release()


# --------------------------------------------------------------------------- ROS camera_info

def ros_pair_paths(path: str | os.PathLike) -> tuple[Path, Path]:
    """``OUT.yaml`` → (``OUT_left.yaml``, ``OUT_right.yaml``); either member maps to the pair."""
    path = Path(path)
    stem, suffix = path.stem, path.suffix or ".yaml"
    for side in ("_left", "_right"):
        if stem.endswith(side):
            stem = stem[: -len(side)]
    return path.with_name(f"{stem}_left{suffix}"), path.with_name(f"{stem}_right{suffix}")


def _ros_doc(name: str, K, D, R, P, size, model: str) -> str:
    def block(key: str, m: np.ndarray) -> str:
        m = np.atleast_2d(m)
        data = ", ".join(repr(float(v)) for v in m.ravel())
        return f"{key}:\n  rows: {m.shape[0]}\n  cols: {m.shape[1]}\n  data: [{data}]\n"

    dist_model = "equidistant" if model == "fisheye" else ("rational_polynomial" if D.size > 5 else "plumb_bob")
    return (f"image_width: {size[0]}\nimage_height: {size[1]}\ncamera_name: {name}\n" + block("camera_matrix", K)
            + f"distortion_model: {dist_model}\n" + block("distortion_coefficients", D.reshape(1, -1))
            + block("rectification_matrix", R) + block("projection_matrix", P))


def write_ros(path: str | os.PathLike, calib: StereoCalibration) -> tuple[Path, Path]:
    """Write the ROS ``camera_info`` pair ``<stem>_left.yaml`` / ``<stem>_right.yaml``; returns both paths.

    ``calib`` must be rectified (R1, R2, P1, P2: :func:`stereocli.rectification.rectified_calibration`)
    and in a known length unit (:data:`UNIT_SCALE`): the projection matrices' translations
    (``P[:, 3]``, ``-fx'·B`` on the right) are written in metres, as ROS reads them.
    """
    if not calib.is_rectified:
        raise DataError(f"{path}: ROS camera_info needs a rectified calibration: rectify the calibration first "
                        "(P1, P2 missing)")
    if calib.units not in UNIT_SCALE:
        raise DataError(f"{path}: ROS camera_info is in metres, but the calibration's unit is "
                        f"{excerpt(calib.units, quote=True)}, no known length ({', '.join(UNIT_SCALE)}); "
                        "calibrate with --square SIZE[UNIT], e.g. 25mm")
    left, right = ros_pair_paths(path)
    size = calib.rectified_size or calib.image_size
    if size != calib.image_size:
        raise ConfigError(f"{path}: ROS camera_info needs the rectified size to equal the image size")
    metres = np.diag([1.0, 1.0, 1.0, UNIT_SCALE[calib.units]])
    write_text(left, _ros_doc("left", calib.K1, calib.D1, calib.R1, calib.P1 @ metres, calib.image_size, calib.model))
    write_text(right, _ros_doc("right", calib.K2, calib.D2, calib.R2, calib.P2 @ metres, calib.image_size,
                               calib.model))
    return left, right


def _yaml_docs(path: Path) -> list:
    import yaml

    from ..config import check_yaml_limits

    try:
        text = read_text_limited(path, "calibration file")
    except (OSError, UnicodeDecodeError) as exc:
        raise DataError(f"{path}: cannot read ({exc})") from None
    try:
        check_yaml_limits(text, str(path))
        return [d for d in yaml.safe_load_all(text) if d is not None]
    except ConfigError as exc:  # a hostile file is bad data here, not a bad option
        raise DataError(str(exc)) from None
    except yaml.YAMLError as exc:
        line = getattr(getattr(exc, "problem_mark", None), "line", None)
        where = f" near line {line + 1}" if line is not None else ""
        raise DataError(f"{path}: corrupt YAML{where}") from None


def _ros_matrix(doc: dict, key: str, path: Path) -> np.ndarray:
    try:
        node = doc[key]
        data = np.asarray(node["data"], dtype=np.float64)
        return data.reshape(int(node["rows"]), int(node["cols"]))
    except (KeyError, TypeError, ValueError):
        raise DataError(f"{path}: missing or malformed {key} (rows, cols, data)") from None


def _from_ros(left: dict, right: dict, where: Path) -> StereoCalibration:
    K1, K2 = _ros_matrix(left, "camera_matrix", where), _ros_matrix(right, "camera_matrix", where)
    D1 = _ros_matrix(left, "distortion_coefficients", where).ravel()
    D2 = _ros_matrix(right, "distortion_coefficients", where).ravel()
    R1, R2 = _ros_matrix(left, "rectification_matrix", where), _ros_matrix(right, "rectification_matrix", where)
    P1, P2 = _ros_matrix(left, "projection_matrix", where), _ros_matrix(right, "projection_matrix", where)
    if P2[0, 0] == 0:
        raise DataError(f"{where}: right projection_matrix has fx = 0")
    tx = P2[0, 3] / P2[0, 0]
    # Rectified frames differ by a pure x shift: X_r2 = X_r1 + [tx, 0, 0]; undo R1, R2.
    R = R2.T @ R1
    T = R2.T @ np.array([tx, 0.0, 0.0])
    size = (int(left.get("image_width", 0)), int(left.get("image_height", 0)))
    model = "fisheye" if str(left.get("distortion_model", "")).lower() in ("equidistant", "fisheye") else "pinhole"
    return StereoCalibration(K1=K1, D1=D1, K2=K2, D2=D2, R=R, T=T, R1=R1, R2=R2, P1=P1, P2=P2,
                             Q=q_from_projections(P1, P2), image_size=size, rectified_size=size,
                             units="m", model=model)


def read_ros(path: str | os.PathLike) -> StereoCalibration:
    """Read a ROS camera_info pair (see the module docstring for accepted names)."""
    path = Path(path)
    if path.is_file():
        docs = _yaml_docs(path)
        if len(docs) >= 2 and all(isinstance(d, dict) and "camera_matrix" in d for d in docs[:2]):
            return _from_ros(docs[0], docs[1], path)
    left, right = ros_pair_paths(path)
    for p in (left, right):
        if not p.is_file():
            raise DataError(f"{p}: missing (a ROS calibration is the pair {left.name} + {right.name})")
    dl, dr = _yaml_docs(left), _yaml_docs(right)
    if not dl or not dr or not isinstance(dl[0], dict) or not isinstance(dr[0], dict):
        raise DataError(f"{left}: empty ROS camera_info file")
    return _from_ros(dl[0], dr[0], left)


# --------------------------------------------------------------------------- Kalibr

def _from_kalibr(doc: dict, path: Path) -> StereoCalibration:
    try:
        cam0, cam1 = doc["cam0"], doc["cam1"]
    except KeyError:
        raise DataError(f"{path}: a Kalibr camchain needs cam0 and cam1") from None

    def cam(c: dict, key: str):
        try:
            fu, fv, pu, pv = (float(v) for v in c["intrinsics"])
            dist = np.asarray(c.get("distortion_coeffs", [0, 0, 0, 0]), dtype=np.float64)
            w, h = (int(v) for v in c["resolution"])
        except (KeyError, TypeError, ValueError):
            raise DataError(f"{path}: {key} needs intrinsics [fu, fv, pu, pv] and resolution [w, h]") from None
        if str(c.get("camera_model", "pinhole")) != "pinhole":
            raise DataError(f"{path}: {key}: camera_model {c.get('camera_model')!r} is not supported (pinhole only)")
        model = str(c.get("distortion_model", "radtan"))
        if model not in ("radtan", "equidistant", "none"):
            raise DataError(f"{path}: {key}: distortion_model {model!r} is not supported (radtan, equidistant)")
        return np.array([[fu, 0, pu], [0, fv, pv], [0, 0, 1.0]]), dist, (w, h), model

    K1, D1, size, m1 = cam(cam0, "cam0")
    K2, D2, _, _ = cam(cam1, "cam1")
    try:
        Tm = np.asarray(cam1["T_cn_cnm1"], dtype=np.float64).reshape(4, 4)
    except (KeyError, ValueError):
        raise DataError(f"{path}: cam1.T_cn_cnm1 (4x4, cam0 -> cam1) is missing or malformed") from None
    return StereoCalibration(K1=K1, D1=D1, K2=K2, D2=D2, R=Tm[:3, :3], T=Tm[:3, 3], image_size=size,
                             units="m", model="fisheye" if m1 == "equidistant" else "pinhole")


# --------------------------------------------------------------------------- Middlebury calib.txt

def to_middlebury(calib: StereoCalibration, *, ndisp: int = 0) -> MiddleburyCalib:
    """The rectified pair's ``calib.txt``: cam0/cam1 from P1/P2, doffs = cx1 - cx0, baseline in mm.

    The baseline is converted to millimetres when ``units`` is a known length unit; otherwise
    it stays in the calibration's unit and ``units=`` records it in the file.
    """
    P1, P2 = calib.P1, calib.P2
    if P1 is None or P2 is None:  # not calib.is_rectified
        raise DataError("calib.txt describes a rectified pair: rectify the calibration first (P1, P2 missing)")
    if abs(P1[1, 2] - P2[1, 2]) > 1e-6 or abs(P1[0, 3]) > 1e-9 or abs(P2[1, 3]) > 1e-9:
        raise DataError("calib.txt needs a horizontal rectified rig (P2 shifted along x only)")
    baseline = -P2[0, 3] / P2[0, 0]
    extra = {}
    if calib.units in UNIT_SCALE:
        baseline *= UNIT_SCALE[calib.units] / UNIT_SCALE["mm"]
    else:
        extra["units"] = calib.units
    size = calib.rectified_size or calib.image_size
    return MiddleburyCalib(cam0=P1[:, :3].copy(), cam1=P2[:, :3].copy(), doffs=float(P2[0, 2] - P1[0, 2]),
                           baseline=float(baseline), width=size[0], height=size[1], ndisp=int(ndisp), extra=extra)


def from_middlebury(mb: MiddleburyCalib) -> StereoCalibration:
    """A rectified :class:`StereoCalibration` (units mm unless the file says otherwise)."""
    units = str(mb.extra.get("units", "mm"))
    for key in ("cam0", "cam1"):
        _check_camera_matrix(key, np.asarray(getattr(mb, key), np.float64))
    f = mb.cam0[0, 0]
    P1 = np.hstack([mb.cam0, np.zeros((3, 1))])
    P2 = np.hstack([mb.cam1, np.array([[-mb.cam1[0, 0] * mb.baseline], [0.0], [0.0]])])
    size = (mb.width, mb.height)
    calib = StereoCalibration(K1=mb.cam0, D1=np.zeros(5), K2=mb.cam1, D2=np.zeros(5), R=np.eye(3),
                              T=np.array([-mb.baseline, 0.0, 0.0]), R1=np.eye(3), R2=np.eye(3), P1=P1, P2=P2,
                              Q=q_from_projections(P1, P2) if f and mb.baseline else None, image_size=size,
                              rectified_size=size, units=units)
    calib.extra.update({"ndisp": mb.ndisp, "doffs": mb.doffs})
    return calib


def write_middlebury(path: str | os.PathLike, calib: StereoCalibration, *, ndisp: int = 0) -> None:
    write_text(path, format_calib_txt(to_middlebury(calib, ndisp=ndisp)))


# --------------------------------------------------------------------------- detection and dispatch

def detect_format(path: str | os.PathLike) -> str:
    """``opencv``, ``ros``, ``kalibr`` or ``middlebury`` from the name and a peek at the content."""
    path = Path(path)
    suffix = path.suffix.lower()
    if suffix == ".txt":
        return "middlebury"
    if suffix not in OPENCV_SUFFIXES:
        raise ConfigError(f"{path}: unknown calibration format {suffix!r} "
                          "(use .yml/.yaml/.xml/.json, ROS _left/_right .yaml, Kalibr camchain .yaml or calib.txt)")
    if not path.is_file():
        left, right = ros_pair_paths(path)
        if suffix in (".yaml", ".yml") and left.is_file():
            return "ros"
        raise DataError(f"{path}: no such file")
    check_text_size(path, "calibration file")
    if suffix in (".xml", ".json"):
        return "opencv"
    with open(path, "rb") as fh:
        head = fh.read(4096)
    if head.startswith(b"%YAML") or b"!!opencv-matrix" in head:
        return "opencv"
    if b"camera_matrix" in head and b"projection_matrix" in head:
        return "ros"
    if b"T_cn_cnm1" in head or (b"cam0" in head and b"intrinsics" in head):
        return "kalibr"
    return "opencv"  # FileStorage also reads plain YAML; it reports a clear error if not.


def load_calibration(path: str | os.PathLike) -> StereoCalibration:
    """Read any supported calibration file (format auto-detected; see the module docstring)."""
    path = Path(path)
    try:
        return _load_calibration(path)
    except DataError as exc:  # a check of the matrices (StereoCalibration) does not know the file
        if str(exc).startswith(str(path)):
            raise
        raise DataError(f"{path}: {exc}") from exc


def _load_calibration(path: Path) -> StereoCalibration:
    fmt = detect_format(path)
    if fmt == "middlebury":
        return _finite(from_middlebury(read_calib_txt(path)), path)
    if fmt == "ros":
        return _finite(read_ros(path), path)
    if fmt == "kalibr":
        docs = _yaml_docs(path)
        if not docs or not isinstance(docs[0], dict):
            raise DataError(f"{path}: empty Kalibr camchain")
        return _finite(_from_kalibr(docs[0], path), path)
    calib = read_opencv(path)
    for key in ("K1", "K2"):
        if not np.all(np.isfinite(getattr(calib, key))) or getattr(calib, key)[0, 0] <= 0:
            raise DataError(f"{path}: {key} is not a valid camera matrix")
    return _finite(calib, path)


def _check_camera_matrix(key: str, K: np.ndarray) -> None:
    """Raise :class:`DataError` unless ``K`` (3, 3) is a pinhole camera matrix: finite, focal
    lengths > 0, last row (0, 0, 1)."""
    if not np.isfinite(K).all():
        raise DataError(f"{key} holds NaN or infinite values")
    if K[0, 0] <= 0 or K[1, 1] <= 0:
        raise DataError(f"{key} is no camera matrix: focal lengths fx={K[0, 0]:g}, fy={K[1, 1]:g} "
                        "(both must be > 0 px)")
    if not np.allclose(K[2], (0.0, 0.0, 1.0)):
        raise DataError(f"{key} is no camera matrix: its last row is {K[2].tolist()}, not [0, 0, 1]")


def _finite(calib: StereoCalibration, path: Path) -> StereoCalibration:
    """``calib``, or a DataError naming the first matrix holding NaN or inf."""
    for key, value in vars(calib).items():
        if isinstance(value, np.ndarray) and value.dtype.kind in "fc" and not np.isfinite(value).all():
            raise DataError(f"{path}: {key} holds NaN or infinite values")
    return calib


def save_calibration(path: str | os.PathLike, calib: StereoCalibration, fmt: str | None = None,
                     *, ndisp: int = 0) -> list[Path]:
    """Write ``calib`` as ``fmt`` (``opencv``/``ros``/``middlebury``; default from the extension).

    ``ros`` and ``middlebury`` need a rectified calibration
    (:func:`stereocli.rectification.rectified_calibration`). Returns the written paths (ROS writes two files).
    """
    path = Path(path)
    if fmt is None:
        fmt = "middlebury" if path.suffix.lower() == ".txt" else "opencv"
    if fmt not in FORMATS:
        raise ConfigError(f"unknown calibration output format {fmt!r} (choose {', '.join(FORMATS)})")
    if fmt == "opencv":
        write_opencv(path, calib)
        return [path]
    if fmt == "ros":
        return list(write_ros(path, calib))
    write_middlebury(path, calib, ndisp=ndisp)
    return [path]


def rotation_angle_deg(Ra: np.ndarray, Rb: np.ndarray) -> float:
    """Angle of ``Ra · Rbᵀ`` in degrees (distance between two rotations)."""
    c = (np.trace(np.asarray(Ra) @ np.asarray(Rb).T) - 1.0) / 2.0
    return math.degrees(math.acos(max(-1.0, min(1.0, c))))
