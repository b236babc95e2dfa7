"""The five subcommands as five functions, plus :func:`read_image`.

:func:`calibrate`, :func:`rectify`, :func:`match`, :func:`triangulate` and :func:`evaluate` take
numpy arrays (and paths where that is natural) and return typed results. ``stereocli CMD`` runs
exactly these functions on each item of a batch (:mod:`stereocli.jobs` adds reading, writing and
the executors), so a call gives the command line's numbers bit for bit.

Images are ``(H, W)`` grey or ``(H, W, 3)`` **RGB** arrays, uint8, uint16 (scaled to [0, 255]
inside) or float in [0, 255], as imageio, scikit-image and :func:`read_image` give them. OpenCV's
``cv2.imread`` gives BGR: pass ``image[..., ::-1]`` (channel order matters: BGR input changes
the disparity of a few percent of the pixels). Disparity is ``(H, W)`` float32 pixels referenced
to the left image (``x_right = x_left - d``), ``+inf`` where invalid.

Every call keeps its settings to itself: ``threads=`` applies to that call only, and calls from
several threads at once give exactly the results they give one after the other.
"""

from __future__ import annotations

import os
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any, Callable, Mapping, Sequence, Union

import numpy as np

from .errors import ConfigError, DataError, named

if TYPE_CHECKING:
    from .calib import CalibrationResult, Pattern
    from .evaluation.api import EvalOptions, EvalReport, SceneScorer
    from .evaluation.datasets import Scene
    from .io.calib import StereoCalibration
    from .io.middlebury import MiddleburyCalib
    from .matching.config import PipelineConfig
    from .rectification.maps import Rectification
    from .rectification.uncalibrated import UncalibratedRectification
    from .triangulation import RectifiedGeometry

__all__ = ["MatchRange", "MatchResult", "RectifyResult", "TriangulationResult", "calibrate", "evaluate", "match",
           "read_image", "rectify", "triangulate"]

PathLike = str | os.PathLike
#: Range sources of :class:`MatchRange`.
RANGE_SOURCES = ("given", "calib.txt", "estimated")


# --------------------------------------------------------------------------- images


def read_image(path: PathLike, *, gray: bool = False) -> np.ndarray:
    """Read an image file in RGB channel order.

    Parameters
    ----------
    path : str or os.PathLike
        PNG, JPEG, TIFF, BMP, PPM/PGM or WebP file.
    gray : bool, default False
        Read as one grey channel.

    Returns
    -------
    numpy.ndarray
        ``(H, W, 3)`` RGB, or ``(H, W)`` for a grey file or with ``gray``; 8-bit and 16-bit files
        keep their dtype (uint8, uint16). An alpha channel is dropped.

    Raises
    ------
    stereocli.errors.DataError
        The file is missing, empty, unreadable or truncated.

    Examples
    --------
    >>> import tempfile
    >>> from pathlib import Path
    >>> import stereocli
    >>> from stereocli.synth.scenes import write_scene
    >>> scene = Path(tempfile.mkdtemp())
    >>> _ = write_scene(scene, "planes", width=160, height=120)  # a synthetic pair, im0.png and im1.png
    >>> left = stereocli.read_image(scene / "im0.png")
    >>> left.shape, left.dtype
    ((120, 160, 3), dtype('uint8'))
    """
    from .io.images import read_image as read

    return read(path, gray=gray)


_IMAGE_DTYPES = (np.uint8, np.uint16, np.float32, np.float64)


def _as_image(image: Any, what: str, name: str = "") -> np.ndarray:
    """``image`` as the pipeline takes it: (H, W) or (H, W, 3) RGB, uint8, uint16 or float."""
    array = np.asarray(image)
    if array.ndim == 3 and array.shape[2] == 1:
        array = array[..., 0]
    elif array.ndim == 3 and array.shape[2] == 4:
        array = array[..., :3]  # RGBA: the alpha channel is not matched (as read_image drops it)
    if array.ndim not in (2, 3) or (array.ndim == 3 and array.shape[2] != 3) or 0 in array.shape:
        raise DataError(named(name, f"{what} image has shape {array.shape}; expected (H, W) grey or (H, W, 3) RGB"))
    if array.dtype not in _IMAGE_DTYPES:
        raise DataError(named(name, f"{what} image is {array.dtype}; expected uint8, uint16 or float (0-255)"))
    if array.dtype.kind == "f":
        if not np.isfinite(array).all():
            raise DataError(named(name, f"{what} image holds NaN or infinite values"))
        array = array.astype(np.float32, copy=False)
    return np.ascontiguousarray(array)  # (a BGR flip's negative strides: OpenCV wants rows in order)


def _grey(image: np.ndarray) -> np.ndarray:
    """(H, W) luma of an RGB view (OpenCV's weights), same dtype."""
    import cv2

    return cv2.cvtColor(np.ascontiguousarray(image), cv2.COLOR_RGB2GRAY)


def _as_mask(mask: Any, what: str, shape: tuple[int, int], name: str) -> np.ndarray | None:
    if mask is None:
        return None
    array = np.asarray(mask)
    if array.shape != shape:
        size = f"{array.shape[1]}x{array.shape[0]}" if array.ndim == 2 else f"of shape {array.shape}"
        raise DataError(named(name, f"{what} valid mask is {size}, image is {shape[1]}x{shape[0]}"))
    return np.ascontiguousarray(array if array.dtype == bool else array > 0)


# --------------------------------------------------------------------------- match


@dataclass(frozen=True)
class MatchRange:
    """The disparities a match searched, ``[min_disp, min_disp + ndisp)`` px, and their source.

    ``source`` is ``"given"`` (``ndisp=``), ``"calib.txt"`` (``calib=``) or ``"estimated"``
    (from the images; ``evidence`` holds what the estimate found).
    """

    min_disp: int
    ndisp: int
    source: str
    evidence: dict | None = field(default=None, repr=False, compare=False)

    @property
    def max_disp(self) -> int:
        """The largest disparity searched, px."""
        return self.min_disp + self.ndisp - 1

    def as_dict(self) -> dict:
        """Return the range as plain JSON types (``params.json``'s ``range``)."""
        out = {"min_disp": self.min_disp, "ndisp": self.ndisp, "source": self.source}
        if self.evidence is not None:
            out["evidence"] = self.evidence
        return out


@dataclass
class MatchResult:
    """What :func:`match` returns.

    Attributes
    ----------
    disparity : (H, W) float32 disparity in px, left-referenced, ``+inf`` where invalid.
    range : the searched range and its source (:class:`MatchRange`).
    confidence : (H, W) float32 in [0, 1] with ``confidence=True``, else None.
    disparity_right : (H, W) float32 right-referenced disparity with ``disparity_right=True``, else None.
    timings : seconds per pipeline stage (``"cost.census"``, ``"optimizer.sgm"``, ...).
    notes : what stages found, by stage name (e.g. ``row_align``'s fit of the rows).
    alignment : how well the pair's rows line up (``max_offset`` px, ``aligned``, the ``source``
        of the measurement), or None when not measured.
    warnings : one line per problem found (e.g. rows not aligned).
    seconds : matching time (the survey and any warm-up excluded), as ``time.txt`` holds it.
    survey_seconds : time spent estimating the range and measuring the rows.
    strips : row strips the pair was matched in (1 when it fits ``runtime.memory_gb``).
    memory_estimate_gb : estimated peak memory of one strip, GiB.
    unmatched : pixels no right-view pixel can show for the searched range (``{"pixels": N, ...}``):
        invalid, or given their row's background by a fill; their confidence is 0.
    config : the effective, validated configuration that ran.
    """

    disparity: np.ndarray
    range: MatchRange
    confidence: np.ndarray | None = None
    disparity_right: np.ndarray | None = None
    timings: dict[str, float] = field(default_factory=dict)
    notes: dict = field(default_factory=dict)
    alignment: dict | None = None
    warnings: list[str] = field(default_factory=list)
    seconds: float = 0.0
    survey_seconds: float = 0.0
    strips: int = 1
    memory_estimate_gb: float = 0.0
    unmatched: dict = field(default_factory=dict)
    config: PipelineConfig | None = field(default=None, repr=False)

    def __repr__(self) -> str:
        h, w = self.disparity.shape
        valid = float(np.isfinite(self.disparity).mean()) if self.disparity.size else 0.0
        extra = "".join(f", {k}=({h}, {w})" for k in ("confidence", "disparity_right") if getattr(self, k) is not None)
        return (f"MatchResult(disparity=({h}, {w}) float32 {100 * valid:.1f}% valid, range={self.range!r}{extra}, "
                f"seconds={self.seconds:.3f}, warnings={self.warnings!r})")


ConfigLike = Union[str, os.PathLike, Mapping, "PipelineConfig", None]
Assignments = Mapping[str, Any] | str | Sequence[str] | None


def match_config(preset: str | None = "default", config: ConfigLike = None, set: Assignments = None,
                 threads: int | None = None) -> PipelineConfig:
    """Build the validated matching configuration of a :func:`match` call (see its parameters).

    Later ones win: the ``default`` preset < ``preset`` < ``config`` < ``set`` < ``threads``.
    """
    from .matching.config import PipelineConfig, build_config

    values: dict[str, Any] = {}
    sets: list[str] = []
    if isinstance(set, Mapping):
        values.update(set)
    elif isinstance(set, str):
        sets = [set]
    elif set is not None:
        sets = [str(s) for s in set]
    if threads is not None:
        if isinstance(threads, bool) or not isinstance(threads, (int, np.integer)) or threads < 0:
            raise ConfigError(f"threads must be a whole number >= 0 (0: one per core), got {threads!r}")
        values["runtime.threads"] = int(threads)
    if isinstance(config, PipelineConfig):
        if preset not in (None, "default"):
            raise ConfigError(f"preset={preset!r} and a config object: give one or the other")
        if not values and not sets:
            return config
        layers: list = [config.as_dict()]
    else:
        layers = [preset] if preset not in (None, "default") else []
        if config is not None:
            layers.append(config)
    return build_config(layers, sets, values=values)


def _given_range(ndisp: int | str | None, min_disp: int | None, calib: Any,
                 name: str) -> tuple[int | None, int | None, str]:
    """``(min_disp, ndisp, source)``: as given, else from ``calib``, else ``(None, None, "estimated")``.

    ``calib`` is a calib.txt path or a :class:`~stereocli.io.middlebury.MiddleburyCalib`.
    """
    if ndisp == "auto":
        ndisp = None
        calib = None
    if ndisp is not None:
        if isinstance(ndisp, bool) or not isinstance(ndisp, (int, np.integer)) or ndisp < 1:
            raise ConfigError(named(name, f"ndisp must be a whole number >= 1, 'auto' or None, got {ndisp!r}"))
        if min_disp is not None and (isinstance(min_disp, bool) or not isinstance(min_disp, (int, np.integer))):
            raise ConfigError(named(name, f"min_disp must be a whole number, got {min_disp!r}"))
        return int(min_disp or 0), int(ndisp), "given"
    if calib is not None:
        from .io.middlebury import MiddleburyCalib, read_calib_txt

        mb = calib if isinstance(calib, MiddleburyCalib) else read_calib_txt(calib)
        if mb.ndisp > 0:
            return int(min_disp or 0), int(mb.ndisp), "calib.txt"
    if min_disp is not None:
        raise ConfigError(named(name, "min_disp needs ndisp (or a calib.txt with ndisp=); an estimated range "
                                       "sets both"))
    return None, None, "estimated"


def match(
    left: np.ndarray,
    right: np.ndarray,
    *,
    ndisp: int | str | None = None,
    min_disp: int | None = None,
    preset: str = "default",
    config: ConfigLike = None,
    set: Assignments = None,
    threads: int | None = None,
    left_valid: np.ndarray | None = None,
    right_valid: np.ndarray | None = None,
    calib: PathLike | MiddleburyCalib | None = None,
    confidence: bool = False,
    disparity_right: bool = False,
    keep_invalid: bool = False,
    require_aligned: bool = False,
    warm_up: bool = False,
    name: str = "",
    strip_map: Callable | None = None,
) -> MatchResult:
    """Compute the disparity map of a rectified stereo pair (``stereocli match``).

    Parameters
    ----------
    left, right : numpy.ndarray
        The rectified views, ``(H, W)`` grey or ``(H, W, 3)`` **RGB** (not OpenCV's BGR),
        uint8, uint16 or float in [0, 255]; the same size. A colour view with a grey one is
        matched in grey.
    ndisp : int, "auto" or None
        Number of disparities searched, ``[min_disp, min_disp + ndisp)``. None takes it from
        ``calib``, else estimates the range from the images as the command line does;
        ``"auto"`` always estimates it.
    min_disp : int, optional
        Smallest disparity searched (default 0; may be negative). Needs ``ndisp`` or ``calib``.
    preset : str, default "default"
        A bundled preset laid over ``default``: ``realtime``, ``fast``, ``default``,
        ``accurate``, ``quality``, ``adcensus`` (``stereocli config presets``).
    config : str, os.PathLike, mapping or PipelineConfig, optional
        More configuration over the preset: a preset name, a YAML file, a mapping like a YAML
        file's contents (``{"optimizer": {"name": "sgm", "p2": 1.2}}``), or a finished config
        object (then without ``preset``).
    set : mapping, str or list of str, optional
        Last overrides, ``{"optimizer.p2": 1.2, "cost.window": [5, 5]}`` (Python values), or
        ``"section.key=value"`` strings as ``--set`` takes them (YAML values).
    threads : int, optional
        Kernel threads for this call only (0: one per core); default ``runtime.threads`` of
        the config. The result does not depend on it.
    left_valid, right_valid : numpy.ndarray, optional
        ``(H, W)`` masks of the pixels that may be matched (bool, or nonzero = valid; e.g. the
        rectification borders are invalid); invalid left pixels come out ``+inf``.
    calib : str, os.PathLike or MiddleburyCalib, optional
        The pair's ``calib.txt``: its ``ndisp`` is the range when ``ndisp`` is None.
    confidence : bool, default False
        Also compute ``result.confidence`` (the config needs a stage that makes it, e.g.
        ``refinement: [..., {name: confidence}]``).
    disparity_right : bool, default False
        Also return the right view's disparity.
    keep_invalid : bool, default False
        Skip every hole-filling stage, so rejected pixels stay ``+inf``.
    require_aligned : bool, default False
        Raise instead of warning when the pair's rows are not aligned.
    warm_up : bool, default False
        First match a tiny pair of the same kind (once per process and kind), so that
        ``seconds`` and ``timings`` hold matching, not loading or compiling the kernels (the
        command line does it for ``time.txt``). The result is the same.
    name : str, optional
        The pair's name, put before error messages and warnings.
    strip_map : callable, optional
        Runs the row strips of a prepared pair (:mod:`stereocli.matching.pipeline`), e.g. on a
        Dask cluster; the result does not depend on it.

    Returns
    -------
    MatchResult
        ``.disparity`` (H, W) float32 px (``+inf`` invalid), ``.range`` (:class:`MatchRange`),
        ``.confidence`` and ``.disparity_right`` when asked, ``.timings``, ``.notes``,
        ``.alignment``, ``.warnings``, ``.seconds``.

    Raises
    ------
    stereocli.errors.ConfigError
        Unknown preset, stage or key, a bad value (the message names it), a bad range option,
        or ``confidence=True`` with a pipeline that makes no confidence map.
    stereocli.errors.DataError
        Images of different sizes or unusable type, a range that cannot be estimated (no
        texture), rows not aligned with ``require_aligned``.
    stereocli.errors.MemoryBudgetError
        The pair cannot be matched within ``runtime.memory_gb`` even in row strips.

    Examples
    --------
    >>> import numpy as np
    >>> import stereocli
    >>> rng = np.random.default_rng(0)
    >>> left = rng.integers(0, 256, (64, 128, 3), dtype=np.uint8)
    >>> right = np.roll(left, -6, axis=1)  # every point 6 px to the left in the right view
    >>> result = stereocli.match(left, right, ndisp=16)
    >>> result.disparity.shape, result.disparity.dtype
    ((64, 128), dtype('float32'))
    >>> float(np.median(result.disparity[:, 16:]))
    6.0
    >>> result.range
    MatchRange(min_disp=0, ndisp=16, source='given')
    >>> fast = stereocli.match(left, right, ndisp=16, preset="fast", set={"optimizer.p2": 1.2}, threads=1)
    >>> fast.config.optimizer.params.p2
    1.2
    """
    from .features.survey import check_range_meets_image, measures_rows, rows_corrected, rows_from_match, survey_pair
    from .matching.pipeline import match_pair
    from .runtime import threads_for_call

    left, right = _as_image(left, "left", name), _as_image(right, "right", name)
    if left.shape[:2] != right.shape[:2]:
        raise DataError(named(name, f"left {left.shape[1]}x{left.shape[0]} and right {right.shape[1]}x"
                                     f"{right.shape[0]} differ in size"))
    if left.ndim != right.ndim:  # one colour and one grey view: match in grey
        left, right = (_grey(v) if v.ndim == 3 else v for v in (left, right))
    shape = left.shape[:2]
    left_valid = _as_mask(left_valid, "left", shape, name)
    right_valid = _as_mask(right_valid, "right", shape, name)
    cfg = match_config(preset, config, set, threads)
    if confidence and not cfg.produces_confidence():
        from .matching.config import confidence_hint

        hint = confidence_hint(cfg)
        key = hint.removeprefix("--set ").split("=", 1)[0]
        names = ", ".join(c.stage.name for c in cfg.refinement) or "none"
        raise ConfigError(named(name, f"confidence: the configured pipeline produces no confidence map (refinement: "
                                       f"{names}); add a refinement stage that does, "
                                       f"e.g. set={{{key!r}: 'confidence'}} ({hint} on the command line)"))
    lo, nd, source = _given_range(ndisp, min_disp, calib, name)
    with threads_for_call(cfg.runtime.threads):
        # With the range known, a config whose row_align measures the rows leaves the alignment
        # to it; the sparse matches measure them when it cannot (features.survey).
        rows_in_match = nd is not None and measures_rows(cfg)
        survey = survey_pair(left, right, min_disp=lo, ndisp=nd, source=source, name=name, left_valid=left_valid,
                             right_valid=right_valid, measure_rows=not rows_in_match,
                             require_aligned=require_aligned, threads=cfg.runtime.threads)
        span = survey["range"]
        check_range_meets_image(span["min_disp"], span["ndisp"], left.shape[1], name=name)
        flags = {"want_right": bool(disparity_right), "keep_invalid": bool(keep_invalid),
                 "want_confidence": bool(confidence)}
        if warm_up:
            from .matching.warmup import warm_up_pair

            warm_up_pair(cfg, left, min_disp=span["min_disp"], ndisp=span["ndisp"], masks=left_valid is not None,
                         **flags)
        t0 = time.perf_counter()
        result = match_pair(left, right, cfg, min_disp=span["min_disp"], ndisp=span["ndisp"], left_valid=left_valid,
                            right_valid=right_valid, strip_map=strip_map, **flags)
        seconds = time.perf_counter() - t0
        note = result.notes.get("row_align")
        if rows_in_match:
            survey.update(rows_from_match(note, left, right, name=name, left_valid=left_valid,
                                          right_valid=right_valid, require_aligned=require_aligned))
    return MatchResult(
        disparity=result.disparity, range=MatchRange(span["min_disp"], span["ndisp"], span["source"],
                                                     span.get("evidence")),
        confidence=result.confidence if confidence else None,
        disparity_right=result.disparity_right if disparity_right else None, timings=result.timings,
        notes=result.notes, alignment=survey["alignment"], warnings=rows_corrected(survey["warnings"], note),
        seconds=seconds, survey_seconds=survey["survey_seconds"], strips=result.strips,
        memory_estimate_gb=result.memory_estimate_gb, unmatched=result.unmatched, config=cfg)


# --------------------------------------------------------------------------- triangulate


@dataclass
class TriangulationResult:
    """What :func:`triangulate` returns.

    Attributes
    ----------
    depth : (H, W) float32 depth Z in ``units``, ``+inf`` where invalid or out of range.
    points : (N, 3) float32 X, Y, Z of the valid pixels (rectified left camera frame: x right,
        y down, z forward), in ``units``.
    colors : (N, 3) uint8 RGB of each point with an ``image``, else None.
    rows, cols : (N,) int32 pixel of each point.
    normals : (N, 3) float32 unit normals with ``normals=True``, else None.
    confidence : (N,) float32 confidence of each point with a ``confidence`` map, else None.
    geometry : the focal length, principal point, baseline and ``doffs`` used.
    dropped : pixels left out of the cloud, by reason (``invalid``, ``outside_range``,
        ``unmatched``, ``at_infinity``, ``low_confidence``, ``depth_limits``).
    """

    depth: np.ndarray
    points: np.ndarray
    rows: np.ndarray
    cols: np.ndarray
    geometry: RectifiedGeometry
    colors: np.ndarray | None = None
    normals: np.ndarray | None = None
    confidence: np.ndarray | None = None
    dropped: dict[str, int] = field(default_factory=dict)

    @property
    def units(self) -> str:
        """The length unit of depth and points (the calibration's, or ``units=``)."""
        return self.geometry.units

    def summary(self) -> dict:
        """Point count, valid fraction, depth percentiles, bounding box, units and frame.

        The ``--summary`` JSON of ``stereocli triangulate``.
        """
        from .triangulation import PointCloud, summarize

        cloud = PointCloud(self.points, self.rows, self.cols, self.colors, self.normals, self.confidence,
                           dropped=dict(self.dropped))
        return summarize(self.depth, cloud, self.geometry)

    def __repr__(self) -> str:
        h, w = self.depth.shape
        return (f"TriangulationResult(depth=({h}, {w}) float32, points={self.points.shape[0]}, units={self.units!r}, "
                f"colors={self.colors is not None})")


def _refuse_uncalibrated(calib: Any) -> None:
    """Refuse the calib.txt of ``rectify --uncalibrated``: no depth can come from it.

    It has no baseline, and only a guessed focal length.
    """
    if isinstance(calib, (str, os.PathLike)) and Path(calib).suffix.lower() == ".txt":
        from .io.middlebury import read_calib_txt

        if read_calib_txt(calib).extra.get("rectification") == "uncalibrated":
            raise DataError(f"{calib}: written by rectify --uncalibrated (no baseline); triangulate needs a "
                            "calibration: calibrate the rig and rectify with --calib")
    elif getattr(calib, "extra", {}).get("rectification") == "uncalibrated":
        raise DataError("the calibration comes from an uncalibrated rectification (no baseline); triangulate needs "
                        "a calibration: calibrate the rig and rectify with it")


def _calibration_label(calib: Any) -> str:
    return str(calib) if isinstance(calib, (str, os.PathLike)) else "calibration"


def _geometry(calib: Any, use_q: bool) -> tuple[RectifiedGeometry, Any]:
    """``(geometry, calibration)`` of ``calib``.

    ``calib`` is a path, a StereoCalibration, a MiddleburyCalib or a RectifiedGeometry (then no
    calibration object).
    """
    from .io.calib import StereoCalibration, from_middlebury, load_calibration
    from .io.middlebury import MiddleburyCalib
    from .triangulation import RectifiedGeometry, geometry_from_calibration

    if isinstance(calib, RectifiedGeometry):
        return calib, None
    if isinstance(calib, (str, os.PathLike)):
        calib = load_calibration(calib)
    elif isinstance(calib, MiddleburyCalib):
        calib = from_middlebury(calib)
    elif not isinstance(calib, StereoCalibration):
        raise ConfigError(f"calib must be a calibration file, a StereoCalibration, a MiddleburyCalib or a "
                          f"RectifiedGeometry, got {type(calib).__name__}")
    return geometry_from_calibration(calib, use_q=use_q), calib


def triangulate(
    disparity: np.ndarray | PathLike,
    calib: PathLike | StereoCalibration | MiddleburyCalib | RectifiedGeometry,
    *,
    image: np.ndarray | PathLike | None = None,
    confidence: np.ndarray | PathLike | None = None,
    units: str | None = None,
    use_q: bool = False,
    min_depth: float | None = None,
    max_depth: float | None = None,
    stride: int = 1,
    normals: bool = False,
    scale: float | None = None,
    disparity_range: tuple[int, int] | None = None,
    left_valid: np.ndarray | PathLike | None = None,
    right_valid: np.ndarray | PathLike | None = None,
    min_confidence: float | None = None,
    supported: bool = True,
) -> TriangulationResult:
    """Turn a disparity map into a depth map and a coloured point cloud (``stereocli triangulate``).

    ``Z = f·B / (d + doffs)``, ``X = Z·(x − cx)/f``, ``Y = Z·(y − cy)/f`` in the rectified left
    camera frame (x right, y down, z forward), in the calibration's length unit (a Middlebury
    ``calib.txt``: mm).

    Parameters
    ----------
    disparity : numpy.ndarray or path
        ``(H, W)`` float disparity in px (``+inf`` invalid), or a ``.pfm``, ``.npy`` or 16-bit
        ``.png`` file.
    calib : path, StereoCalibration, MiddleburyCalib or RectifiedGeometry
        The rectified pair's calibration: a ``calib.txt``, an OpenCV (``.yml/.yaml/.xml/.json``)
        or ROS file (with P1, P2 or Q), or an object.
    image : numpy.ndarray or path, optional
        The left view, ``(H, W, 3)`` **RGB** or grey, for the points' colours.
    confidence : numpy.ndarray or path, optional
        ``(H, W)`` confidence map, kept per point (non-finite values count as 0).
    units : {"m", "cm", "mm"}, optional
        Convert depth and points to this unit.
    use_q : bool, default False
        Take f, cx, cy, B and doffs from the Q matrix instead of P1/P2.
    min_depth, max_depth : float, optional
        Drop depths outside this range (in the output unit): ``+inf`` in ``depth``, no point.
    stride : int, default 1
        Keep every ``stride``-th pixel in x and y in the point cloud.
    normals : bool, default False
        Also compute unit normals from neighbouring depths.
    scale : float, optional
        ``d = value / scale`` for an integer PNG disparity file (16-bit default 256).
    disparity_range : (int, int), optional
        ``(min_disp, ndisp)``: the range the match searched (``params.json``'s ``range``). Points
        whose disparity lies outside it (beyond the sub-pixel slack of 1 px) are dropped.
    left_valid, right_valid : numpy.ndarray or path, optional
        ``(H, W)`` bool masks (or ``valid0.png``/``valid1.png``) of the rectified views: pixels
        outside the left mask, or whose match falls outside the right one, are dropped.
    min_confidence : float, optional
        Drop points whose confidence is below this (needs ``confidence``).
    supported : bool, default True
        Drop what the match does not support (outside the range, unseen, ``d + doffs < 2`` px);
        False keeps those points (``triangulate --keep-unsupported``).

    Returns
    -------
    TriangulationResult
        ``.depth`` (H, W) float32 (``+inf`` invalid), ``.points`` (N, 3) float32, ``.colors``
        (N, 3) uint8 or None, ``.geometry``, ``.summary()``.

    Raises
    ------
    stereocli.errors.DataError
        An unreadable file, a calibration without rectification or baseline, sizes that
        disagree, a disparity with no valid pixel, or no point left in the depth range.
    stereocli.errors.ConfigError
        An unknown calibration format or an unusable argument.

    Examples
    --------
    >>> import numpy as np
    >>> import stereocli
    >>> from stereocli.io.middlebury import MiddleburyCalib
    >>> K = np.array([[500.0, 0, 40], [0, 500, 30], [0, 0, 1]])
    >>> calib = MiddleburyCalib(cam0=K, cam1=K, baseline=100.0, width=80, height=60)  # baseline in mm
    >>> disparity = np.full((60, 80), 25.0, np.float32)
    >>> disparity[0, 0] = np.inf  # invalid
    >>> cloud = stereocli.triangulate(disparity, calib, units="m")
    >>> float(cloud.depth[30, 40]), cloud.units, cloud.points.shape  # columns 0-24 match outside the right view
    (2.0, 'm', (3300, 3))
    >>> cloud.dropped["unmatched"]
    1499
    """
    from .io.images import read_disparity
    from .triangulation import depth_from_disparity, summarize
    from .triangulation import triangulate as compute

    disparity_label = str(disparity) if isinstance(disparity, (str, os.PathLike)) else "disparity"
    calib_label = _calibration_label(calib)
    _refuse_uncalibrated(calib)
    if isinstance(disparity, (str, os.PathLike)):
        disp = read_disparity(disparity, scale=scale)
    else:
        disp = np.asarray(disparity)
        if disp.ndim != 2 or disp.dtype.kind not in "fiu":
            raise DataError(f"disparity must be a 2-D array of numbers, got shape {disp.shape} {disp.dtype}")
        disp = disp.astype(np.float32, copy=False)
        if np.isnan(disp).any():
            raise DataError("disparity contains NaN; stereocli marks invalid pixels with +inf")
    geom, calibration = _geometry(calib, use_q)
    if units:
        geom = geom.scaled(units)
    if calibration is not None:
        size = calibration.rectified_size or calibration.image_size
        if size and all(size) and tuple(size) != (disp.shape[1], disp.shape[0]):
            raise DataError(f"{disparity_label}: disparity is {disp.shape[1]}x{disp.shape[0]} but "
                            f"{calib_label} is for {size[0]}x{size[1]}")
    colours = None
    if image is not None:
        image_label = str(image) if isinstance(image, (str, os.PathLike)) else "image"
        colours = read_image(image) if isinstance(image, (str, os.PathLike)) else np.asarray(image)
        if colours.shape[:2] != disp.shape:
            raise DataError(f"{image_label}: image is {colours.shape[1]}x{colours.shape[0]} but the disparity "
                            f"{disparity_label} is {disp.shape[1]}x{disp.shape[0]}")
    conf = None
    if confidence is not None:
        if isinstance(confidence, (str, os.PathLike)):
            conf = read_disparity(confidence, kind="confidence")
        else:
            conf = np.asarray(confidence, dtype=np.float32)
            if np.isnan(conf).any():
                raise DataError("confidence contains NaN")
        conf = np.where(np.isfinite(conf), conf, 0).astype(np.float32)
        if conf.shape != disp.shape:
            raise DataError(f"{_label(confidence, 'confidence')}: confidence is {conf.shape[1]}x{conf.shape[0]} but "
                            f"the disparity {disparity_label} is {disp.shape[1]}x{disp.shape[0]}")
    if min_confidence is not None and conf is None:
        raise DataError(f"{disparity_label}: --min-confidence needs a confidence map (--confidence FILE, "
                        "or conf0.pfm beside the disparity: match --confidence writes it)")
    if not np.isfinite(disp).any():
        raise DataError(f"{disparity_label}: every disparity is invalid (+inf); nothing to triangulate")
    masks = {key: _valid_mask(value, disp.shape) for key, value in (("left_valid", left_valid),
                                                                     ("right_valid", right_valid))
             if value is not None}
    depth, cloud = compute(disp, geom, image=colours, confidence=conf, normals=normals, stride=stride,
                           min_depth=min_depth, max_depth=max_depth, disparity_range=disparity_range,
                           min_confidence=min_confidence, supported=supported, **masks)
    if cloud.points.shape[0] == 0:
        depth_all = depth_from_disparity(disp, geom)
        if not np.isfinite(depth_all).any():
            raise DataError(f"{disparity_label}: no valid depth: every disparity d has d + doffs <= 0 "
                            f"(doffs {geom.doffs:g} px)")
        if not any(n for reason, n in cloud.dropped.items() if reason != "invalid"):
            raise DataError(f"{disparity_label}: no valid pixel on the --stride {stride} grid")
        dropped = ", ".join(f"{n} {reason}" for reason, n in cloud.dropped.items() if n)
        span = summarize(depth_all, cloud, geom)
        raise DataError(f"{disparity_label}: no point left (pixels dropped: {dropped}; valid depths span "
                        f"{span.get('depth_min')}..{span.get('depth_max')} {geom.units})")
    return TriangulationResult(depth=depth, points=cloud.points, rows=cloud.rows, cols=cloud.cols, geometry=geom,
                               colors=cloud.colors, normals=cloud.normals, confidence=cloud.confidence,
                               dropped=dict(cloud.dropped))


def _label(value: Any, default: str) -> str:
    """How an error names an argument: its path, or ``default`` for an array."""
    return str(value) if isinstance(value, (str, os.PathLike)) else default


def _valid_mask(value: np.ndarray | PathLike, shape: tuple[int, ...]) -> np.ndarray:
    """Return a valid mask as (H, W) bool.

    An array is taken as it is (nonzero valid), a file is read as ``valid0.png`` holds it (above
    127 valid).
    """
    if isinstance(value, (str, os.PathLike)):
        from .io.images import read_valid_mask

        mask = read_valid_mask(value)
    else:
        mask = np.asarray(value).astype(bool)
    if mask.shape[:2] != shape:
        raise DataError(f"{_label(value, 'valid mask')}: valid mask is {mask.shape[1]}x{mask.shape[0]} but the "
                        f"disparity is {shape[1]}x{shape[0]}")
    return mask


# --------------------------------------------------------------------------- rectify


@dataclass
class RectifyResult:
    """What :func:`rectify` returns.

    Attributes
    ----------
    left, right : the rectified views (dtype and channels kept; 0 outside the source image).
    left_valid, right_valid : (h, w) bool, True where the pixel was sampled from inside the
        source image (border pixels are never matched: pass them to :func:`match`).
    calib_txt : the rectified pair's Middlebury ``calib.txt`` (cameras, doffs, baseline in mm,
        size, ``ndisp``; ``vmin``/``vmax`` of an estimated range).
    ndisp : the disparity range ``[0, ndisp)`` written to ``calib_txt``.
    range : where ``ndisp`` came from: ``{"source": "given" | "estimated" | "depth", ...}``.
    rectification : the rectification (calibrated: R1, R2, P1, P2, Q and valid ROIs; without a
        calibration: the homographies ``H0``, ``H1``).
    calibration : the rectified calibration (R1, R2, P1, P2, Q set), None without one.
    pair : without a calibration, what the estimate found in the pair (matches, inliers, |dy|).
    """

    left: np.ndarray
    right: np.ndarray
    left_valid: np.ndarray
    right_valid: np.ndarray
    calib_txt: MiddleburyCalib
    ndisp: int
    range: dict
    rectification: Any
    calibration: StereoCalibration | None = None
    pair: Any = None

    def check_image(self) -> np.ndarray:
        """Draw an 8-bit side-by-side RGB preview with horizontal lines and the valid boxes (``check.png``)."""
        from .rectification.maps import Rectification, check_image, inner_box

        if isinstance(self.rectification, Rectification):
            return check_image(self.left, self.right, self.rectification)
        return check_image(self.left, self.right, rois=(inner_box(self.left_valid), inner_box(self.right_valid)))

    def __repr__(self) -> str:
        h, w = self.left.shape[:2]
        return f"RectifyResult(size=({h}, {w}), ndisp={self.ndisp}, range={self.range.get('source')!r})"


def _rectified_range(left: np.ndarray, right: np.ndarray, rect: Rectification, ndisp: int | None,
                     min_depth: float | None) -> tuple[int, dict]:
    """``ndisp`` for the rectified pair's calib.txt and where it came from.

    ``ndisp`` wins. Otherwise the range is estimated from the rectified images
    (:func:`~stereocli.features.disparity_range.estimate_range`; rectification puts infinity at
    disparity 0, so calib.txt's ``[0, ndisp)`` is rounded up to a multiple of 16 to reach the
    estimate's far end), at least ``f·B / min_depth`` when that is given. A pair without
    enough texture falls back to the depth rule alone (a quarter of the width without
    ``min_depth``).
    """
    from .features.disparity_range import estimate_range
    from .rectification.maps import estimate_ndisp

    if ndisp:
        return int(ndisp), {"source": "given"}
    by_depth = estimate_ndisp(rect, min_depth=min_depth) if min_depth else 0
    try:
        estimate = estimate_range(left, right)
    except DataError as exc:
        return estimate_ndisp(rect, min_depth=min_depth), {"source": "depth", "note": str(exc)}
    ndisp = max(16 * -(-(estimate.max_disp + 1) // 16), by_depth)
    return ndisp, {"source": "estimated", "min_disp": estimate.min_disp, "max_disp": estimate.max_disp,
                   "evidence": estimate.as_dict()}


def rectify(
    left: np.ndarray | PathLike,
    right: np.ndarray | PathLike,
    calib: PathLike | StereoCalibration | UncalibratedRectification | None = None,
    *,
    alpha: float = 0.0,
    size: tuple[int, int] | None = None,
    interpolation: str = "linear",
    ndisp: int | None = None,
    min_depth: float | None = None,
    disparity_range: tuple[int, int] | None = None,
    maps: Any = None,
) -> RectifyResult:
    """Rectify a stereo pair so that its rows line up (``stereocli rectify``).

    Parameters
    ----------
    left, right : numpy.ndarray or path
        The unrectified views, ``(H, W, 3)`` **RGB** or grey, any dtype OpenCV remaps (uint8,
        uint16, float32), or image files.
    calib : path, StereoCalibration, UncalibratedRectification or None
        The rig's calibration (OpenCV, ROS, Kalibr file or object, as ``stereocli calibrate``
        writes it). An :class:`~stereocli.rectification.UncalibratedRectification` warps by its
        homographies; None estimates them from this pair (``rectify --uncalibrated``).
    alpha : float, default 0
        0 crops to valid pixels, 1 keeps every source pixel (calibrated only).
    size : (width, height), optional
        Size of the rectified images (default: the calibration's image size).
    interpolation : {"linear", "nearest", "cubic", "lanczos"}, default "linear"
        Resampling of the images.
    ndisp : int, optional
        The disparity range written to ``calib_txt``; estimated from the rectified pair when not
        given (rounded up to a multiple of 16; at least ``f·B / min_depth``).
    min_depth : float, optional
        Nearest depth expected, in the calibration's unit (calibrated only).
    disparity_range : (min_disp, max_disp), optional
        With homographies: the pair's range in the rectified pair (as their estimate found it);
        estimated from the rectified pair when not given.
    maps : RectifyMaps, optional
        Remap tables built for this ``calib``, ``alpha`` and ``size``
        (:func:`stereocli.rectification.build_maps`), to reuse over many pairs.

    Returns
    -------
    RectifyResult
        ``.left``, ``.right`` (rectified), ``.left_valid``, ``.right_valid`` (bool masks),
        ``.calib_txt``, ``.ndisp``, ``.rectification``, ``.calibration``, ``.check_image()``.

    Raises
    ------
    stereocli.errors.DataError
        Images of another size than the calibration's, a vertical rig, an unreadable file, or
        (without a calibration) too little texture to estimate the rectification.
    stereocli.errors.ConfigError
        An unknown interpolation, an ``alpha`` outside [0, 1], an unknown calibration format.

    Examples
    --------
    >>> import numpy as np
    >>> import stereocli
    >>> from stereocli.io.calib import StereoCalibration
    >>> K = np.array([[400.0, 0, 79.5], [0, 400, 59.5], [0, 0, 1]])
    >>> rig = StereoCalibration(K1=K, D1=np.zeros(5), K2=K, D2=np.zeros(5), R=np.eye(3),
    ...                         T=np.array([-60.0, 0, 0]), image_size=(160, 120), units="mm")
    >>> rng = np.random.default_rng(1)
    >>> left = rng.integers(0, 256, (120, 160, 3), dtype=np.uint8)
    >>> out = stereocli.rectify(left, np.roll(left, -4, axis=1), rig, ndisp=32)
    >>> out.left.shape, out.calib_txt.baseline, out.calib_txt.ndisp
    ((120, 160, 3), 60.0, 32)
    >>> float(out.left_valid.mean()) > 0.9  # the rest lies outside the source image
    True
    """
    from .io.calib import StereoCalibration, load_calibration, to_middlebury
    from .rectification.maps import build_maps, rectified_calibration, rectify_images
    from .rectification.uncalibrated import UncalibratedRectification

    left = read_image(left) if isinstance(left, (str, os.PathLike)) else np.asarray(left)
    right = read_image(right) if isinstance(right, (str, os.PathLike)) else np.asarray(right)
    if calib is None or isinstance(calib, UncalibratedRectification):
        return _rectify_uncalibrated(left, right, calib, interpolation=interpolation, ndisp=ndisp,
                                     disparity_range=disparity_range)
    label = _calibration_label(calib)
    if isinstance(calib, (str, os.PathLike)):
        calib = load_calibration(calib)
    elif not isinstance(calib, StereoCalibration):
        raise ConfigError(f"calib must be a calibration file, a StereoCalibration, an UncalibratedRectification or "
                          f"None, got {type(calib).__name__}")
    w, h = calib.image_size
    for what, image in (("left", left), ("right", right)):
        if image.shape[:2] != (h, w):
            raise DataError(f"{what} image is {image.shape[1]}x{image.shape[0]} but the calibration is for {w}x{h}")
    maps = maps if maps is not None else build_maps(calib, alpha=alpha,
                                                        size=(int(size[0]), int(size[1])) if size else None)
    if maps.rect.vertical:
        raise DataError(f"{label}: vertical rig; stereocli rectifies horizontal pairs only")
    r0, r1 = rectify_images(left, right, maps, interpolation=interpolation)
    rect = maps.rect
    ndisp, span = _rectified_range(r0, r1, rect, ndisp, min_depth)
    rectified = rectified_calibration(calib, rect=rect)
    mb = to_middlebury(rectified, ndisp=ndisp)
    if span.get("evidence"):
        mb.vmin, mb.vmax = float(max(0, span["min_disp"])), float(span["max_disp"])
        if span["min_disp"] > 0:
            from .io.middlebury import MIN_DISP_KEY

            # The estimated range starts above 0: match searches [mindisp, ndisp), so nothing
            # farther than the pair shows is searched (infinity is at 0 after rectification).
            mb.extra[MIN_DISP_KEY] = str(int(span["min_disp"]))
    return RectifyResult(r0, r1, maps.valid1 > 0, maps.valid2 > 0, mb, ndisp, span, rect, rectified)


def _rectify_uncalibrated(left: np.ndarray, right: np.ndarray, rect: UncalibratedRectification | None, *,
                          interpolation: str, ndisp: int | None,
                          disparity_range: tuple[int, int] | None) -> RectifyResult:
    """:func:`rectify` by homographies: given, or estimated from this pair alone."""
    from .rectification.uncalibrated import estimate_rectification, uncalibrated_calib_txt, warp_pair

    pair = None
    if rect is None:
        estimate = estimate_rectification([(left, right)])
        pair = estimate.pairs[0]
        if pair.error or pair.min_disp is None or pair.max_disp is None:
            raise DataError(pair.error or "no disparity range")
        rect, disparity_range = estimate.rectification, (pair.min_disp, pair.max_disp)
    r0, r1, valid0, valid1 = warp_pair(left, right, rect, interpolation=interpolation)
    source = "given" if disparity_range is not None and pair is None else "estimated"
    if disparity_range is None:
        from .features.disparity_range import estimate_range

        found = estimate_range(r0, r1)
        disparity_range = (max(0, found.min_disp), found.max_disp)
    lo, hi = int(disparity_range[0]), int(disparity_range[1])
    ndisp = int(ndisp or 16 * -(-(hi + 1) // 16))
    span = {"source": source, "min_disp": lo, "max_disp": hi}
    return RectifyResult(r0, r1, valid0 > 0, valid1 > 0, uncalibrated_calib_txt(rect, ndisp, lo, hi), ndisp, span,
                         rect, None, pair)


# --------------------------------------------------------------------------- calibrate


def calibrate(
    images: PathLike | Sequence[tuple[np.ndarray | PathLike, np.ndarray | PathLike]],
    pattern: str | tuple[int, int] | Pattern,
    *,
    square: float | str = 1.0,
    units: str | None = None,
    pattern_type: str = "chessboard",
    dictionary: str = "DICT_5X5_100",
    marker_size: float = 0.75,
    detector: str = "auto",
    jobs: int | None = None,
    cache: PathLike | None = None,
    swap: bool = False,
    progress: bool | None = False,
    **options: Any,
) -> CalibrationResult:
    """Calibrate a stereo rig from photos of a chessboard, circle grid or ChArUco board (``stereocli calibrate``).

    Each camera is calibrated alone, then R and T with the intrinsics fixed (unless
    ``joint=True``); outlier views are flagged in the report.

    Parameters
    ----------
    images : path or sequence of (left, right)
        A folder with ``left/`` and ``right/`` (paired by file stem) or ``left*``/``right*``
        files, or the pairs themselves: image paths, or arrays (**RGB** or grey).
    pattern : str, (cols, rows) or Pattern
        Inner corners (circles) per row and column, e.g. ``"9x6"`` for a board of 10×7 squares.
    square : float or str, default 1
        Side of a square (circle spacing): a number in ``units``, or a length like ``"25mm"``.
        Sets the unit of T, of the baseline and of every depth computed later.
    units : str, optional
        The unit of a bare ``square`` (e.g. ``"mm"``).
    pattern_type : {"chessboard", "circles", "acircles", "charuco"}, default "chessboard"
    dictionary : str, default "DICT_5X5_100"
        ChArUco's ArUco dictionary.
    marker_size : float, default 0.75
        ChArUco marker side as a fraction of the square side.
    detector : {"auto", "classic", "sb"}, default "auto"
        Chessboard detector: classic + cornerSubPix, the sector-based one, or classic then SB.
    jobs : int, optional
        Detection threads (default: all cores).
    cache : path, optional
        Detection cache file (JSON); detections of unchanged image files are reused.
    swap : bool, default False
        Exchange left and right (a rig wired the other way round).
    progress : bool or None, default False
        Show a progress bar on stderr (None: when stderr is a terminal).
    **options
        Model options (:class:`stereocli.calib.CalibOptions`): ``fix_principal_point``,
        ``zero_tangent``, ``fix_aspect``, ``fix_k3``, ``rational``, ``fisheye``, ``same_focal``,
        ``joint``, ``max_view_error`` (px: drop worse views and recalibrate), ``alpha`` (the
        rectification stored with the calibration).

    Returns
    -------
    CalibrationResult
        ``.calibration`` (a rectified :class:`~stereocli.io.calib.StereoCalibration`: K, D, R,
        T, P1, P2, Q; save it with :func:`stereocli.io.calib.save_calibration`) and ``.report``
        (per-view RMS, outliers, baseline, rectified epipolar error, warnings).

    Raises
    ------
    stereocli.errors.DataError
        Unreadable images, mixed image sizes, the target found in fewer than 3 pairs.
    stereocli.errors.ConfigError
        A bad pattern, square or option.

    Examples
    --------
    >>> import tempfile
    >>> import stereocli
    >>> from stereocli.synth.rig import render_rig
    >>> folder = tempfile.mkdtemp()
    >>> _ = render_rig(folder, n_pairs=6)  # photos of a 9x6 board (40 mm squares), 120 mm baseline
    >>> result = stereocli.calibrate(folder, "9x6", square="40mm", fix_k3=True)
    >>> result.report["views_used"], round(result.calibration.baseline), result.calibration.units
    (6, 120, 'mm')
    """
    from .calib import CalibOptions, Pattern, calibrate_folder, parse_pattern_size, parse_square

    if isinstance(pattern, Pattern):
        if square != 1.0 or units is not None:
            raise ConfigError("square and units come with the Pattern object; give them there")
        board = pattern
    else:
        cols, rows = parse_pattern_size(pattern) if isinstance(pattern, str) else (int(pattern[0]), int(pattern[1]))
        length, unit = parse_square(square, units)
        board = Pattern(cols, rows, length, pattern_type, unit, marker_size, dictionary)
    try:
        model = CalibOptions(**options)
    except TypeError as exc:
        raise ConfigError(f"calibrate: {exc}") from None
    if model.fisheye and (model.rational or model.zero_tangent or model.fix_k3):
        raise ConfigError("fisheye cannot be combined with rational, zero_tangent or fix_k3")
    if model.same_focal and not model.joint:
        raise ConfigError("same_focal needs joint (intrinsics are fixed in the stereo solve otherwise)")
    if isinstance(images, (str, os.PathLike)):
        return calibrate_folder(images, board, model, detector=detector, jobs=jobs, cache=cache, progress=progress,
                                swap=swap)
    from .calib import calibrate_pairs

    return calibrate_pairs(list(images), board, model, detector=detector, jobs=jobs, cache=cache, progress=progress,
                           swap=swap)


# --------------------------------------------------------------------------- evaluate


def evaluate(
    disparity: np.ndarray | PathLike,
    ground_truth: PathLike | Scene,
    *,
    thresholds: Sequence[float] | None = None,
    ndisp: float | None = None,
    dataset: str | None = None,
    resolution: str = "auto",
    threshold_units: str = "full",
    same_resolution: bool = False,
    gt_scale: float | None = None,
    time: float | None = None,
    name: str | None = None,
    keep_arrays: bool = False,
    options: EvalOptions | None = None,
    scorer: SceneScorer | None = None,
) -> EvalReport:
    """Score disparity against ground truth with the official benchmark rules (``stereocli eval``).

    MiddEval3 (and the bundled samples), Middlebury 2001/2003 and KITTI 2015 layouts are
    detected; a quarter-resolution MiddEval3 GT is scored in full-resolution pixels.

    Parameters
    ----------
    disparity : numpy.ndarray or path
        ``(h, w)`` float32 disparity in px (``+inf`` invalid), or a file (PFM, npy, 16-bit PNG),
        or a folder of results (``<scene>/disp0*.pfm``, scored against a folder of scenes).
    ground_truth : path or Scene
        A scene folder (``disp0GT.pfm`` [+ ``mask0nocc.png``, ``calib.txt``]), a GT file, a
        folder of scenes (the one named ``name`` is used), a KITTI root, or a loaded
        :class:`~stereocli.evaluation.Scene`.
    thresholds : sequence of float, optional
        Bad-pixel thresholds in px (default 0.5, 1, 2, 4).
    ndisp : float, optional
        Disparity range at the estimate's resolution for clipping (default: the scene's
        calib.txt; none for Middlebury v2).
    dataset : {"middlebury2014", "middlebury2003", "middlebury2001", "kitti"}, optional
        Force the GT layout.
    resolution : {"auto", "F", "H", "Q"}, default "auto"
        MiddEval3 resolution of the GT (auto: from a ``trainingQ``-style folder name, else F).
    threshold_units : {"full", "native"}, default "full"
        Thresholds and errors in full-resolution px (official), or in px of the scored grid.
    same_resolution : bool, default False
        UNOFFICIAL: score at the estimate's size instead of upsampling it.
    gt_scale : float, optional
        Middlebury v2 8-bit GT scale (default per scene: Tsukuba 16, Venus 8, Teddy/Cones 4).
    time : float, optional
        Seconds the matcher took (fills the time, s/MP and s/GD columns).
    name : str, optional
        The scene's name (picks it from a folder of scenes; names the row).
    keep_arrays : bool, default False
        Keep the scored arrays on each scene (for error maps).
    options : EvalOptions, optional
        All scoring options at once, instead of the keywords above.
    scorer : callable, optional
        Runs a folder's scene tasks (:mod:`stereocli.jobs.evaluate` runs them on executors).

    Returns
    -------
    EvalReport
        ``.to_dict()`` is ``stereocli eval --format json``'s report; ``.scenes[0].metrics
        ["nonocc"]["bad2.0"]``, ``.average``; :func:`stereocli.evaluation.format_table` renders
        it as text, JSON, CSV or Markdown.

    Raises
    ------
    stereocli.errors.DataError
        Sizes that do not match (other than 1×, 2×, 4×), NaN, an unreadable file, a GT without
        known pixels, no scene of that name.
    stereocli.errors.ConfigError
        A bad option.

    Examples
    --------
    >>> import tempfile
    >>> from pathlib import Path
    >>> import stereocli
    >>> from stereocli.synth.scenes import write_scene
    >>> scene = Path(tempfile.mkdtemp()) / "planes"
    >>> truth = write_scene(scene, "planes", width=160, height=120)["disparity"]
    >>> report = stereocli.evaluate(truth + 1.0, scene)  # every pixel 1 px off
    >>> bad = report.to_dict()["scenes"][0]["nonocc"]
    >>> bad["bad0.5"], bad["bad2.0"]
    (100.0, 0.0)
    """
    from .evaluation.api import EvalOptions, pair_report
    from .evaluation.api import evaluate as evaluate_inputs
    from .evaluation.datasets import Scene

    if options is None:
        options = EvalOptions(thresholds=tuple(thresholds) if thresholds else EvalOptions.thresholds,
                              resolution=resolution, threshold_units=threshold_units, same_resolution=same_resolution,
                              ndisp=ndisp, dataset=dataset, gt_scale=gt_scale, keep_arrays=keep_arrays)
    if isinstance(disparity, (str, os.PathLike)) and not isinstance(ground_truth, Scene) and time is None \
            and name is None:  # what `stereocli eval` does with paths: a file, or folder mode
        return evaluate_inputs(disparity, ground_truth, options=options, scorer=scorer)
    return pair_report(disparity, ground_truth, options=options, time=time, name=name)
