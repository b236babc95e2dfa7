"""Middlebury 2014 ``calib.txt``: parsing (tolerant of irregular whitespace) and writing."""

from __future__ import annotations

import math
import os
import re
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..errors import DataError, excerpt
from .atomic import write_text
from .text import read_text_limited

_NUMBER = re.compile(r"[-+]?(?:\d+\.?\d*|\.\d+)(?:[eE][-+]?\d+)?")


@dataclass
class MiddleburyCalib:
    """Contents of a Middlebury ``calib.txt`` (units: pixels; baseline in mm)."""

    cam0: np.ndarray  # (3, 3) float64 left intrinsics
    cam1: np.ndarray  # (3, 3) float64 right intrinsics
    doffs: float = 0.0  # cx_right - cx_left, px
    baseline: float = 0.0  # mm
    width: int = 0
    height: int = 0
    ndisp: int = 0
    isint: int = 0
    vmin: float | None = None
    vmax: float | None = None
    dyavg: float | None = None
    dymax: float | None = None
    extra: dict = field(default_factory=dict)

    @property
    def focal(self) -> float:
        return float(self.cam0[0, 0])


#: stereocli's own calib.txt key (``rectify`` writes it): the smallest disparity of the range,
#: which is then ``[mindisp, ndisp)`` (Middlebury's is ``[0, ndisp)``).
MIN_DISP_KEY = "mindisp"


def calib_range(calib: MiddleburyCalib, path: str | os.PathLike) -> tuple[int, int] | None:
    """``(min_disp, ndisp)`` of the range a calib.txt gives: ``[0, ndisp)``, or
    ``[mindisp, ndisp)`` with stereocli's ``mindisp=`` line; None without ``ndisp``."""
    if calib.ndisp <= 0:
        return None
    raw = calib.extra.get(MIN_DISP_KEY)
    if raw is None:
        return 0, int(calib.ndisp)
    try:
        low = int(raw)
    except ValueError:
        raise DataError(f"{path}: {MIN_DISP_KEY}={excerpt(raw, quote=True)} is not an integer") from None
    if low >= calib.ndisp:
        raise DataError(f"{path}: {MIN_DISP_KEY}={low} leaves no disparity below ndisp={calib.ndisp}")
    return low, int(calib.ndisp) - low


def _matrix(text: str, path: Path, key: str) -> np.ndarray:
    values = [float(v) for v in _NUMBER.findall(text)]
    if len(values) != 9 or not all(map(math.isfinite, values)):
        raise DataError(f"{path}: {key} must be a 3x3 matrix like [f 0 cx; 0 f cy; 0 0 1]")
    return np.array(values, dtype=np.float64).reshape(3, 3)


def read_calib_txt(path: str | os.PathLike) -> MiddleburyCalib:
    """Parse a Middlebury ``calib.txt``. Missing cam0 is an error; other keys are optional."""
    path = Path(path)
    try:
        text = read_text_limited(path, "calib.txt")
    except (OSError, UnicodeDecodeError) as exc:
        raise DataError(f"{path}: cannot read calib.txt ({exc})") from None
    entries: dict[str, str] = {}
    for line in text.splitlines():
        if "=" in line:
            key, value = line.split("=", 1)
            entries[key.strip()] = value.strip()
    if "cam0" not in entries:
        raise DataError(f"{path}: no cam0=[...] line; not a Middlebury calib.txt")
    cam0 = _matrix(entries.pop("cam0"), path, "cam0")
    cam1 = _matrix(entries.pop("cam1"), path, "cam1") if "cam1" in entries else cam0.copy()

    def num(key, cast=float, default=None):
        if key not in entries:
            return default
        raw = entries.pop(key)
        try:
            value = float(raw)
        except ValueError:
            raise DataError(f"{path}: {key}={excerpt(raw, quote=True)} is not a number") from None
        if not math.isfinite(value):
            raise DataError(f"{path}: {key}={excerpt(raw, quote=True)} is not a finite number")
        return cast(value)

    return MiddleburyCalib(
        cam0=cam0,
        cam1=cam1,
        doffs=num("doffs", float, 0.0),
        baseline=num("baseline", float, 0.0),
        width=num("width", int, 0),
        height=num("height", int, 0),
        ndisp=num("ndisp", int, 0),
        isint=num("isint", int, 0),
        vmin=num("vmin"),
        vmax=num("vmax"),
        dyavg=num("dyavg"),
        dymax=num("dymax"),
        extra=entries,
    )


def _fmt_matrix(m: np.ndarray) -> str:
    rows = ["; ".join([" ".join(f"{v:.10g}" for v in row)]) for row in m]
    return "[" + "; ".join(rows) + "]"


def format_calib_txt(calib: MiddleburyCalib) -> str:
    lines = [
        f"cam0={_fmt_matrix(calib.cam0)}",
        f"cam1={_fmt_matrix(calib.cam1)}",
        f"doffs={calib.doffs:.10g}",
        f"baseline={calib.baseline:.10g}",
        f"width={calib.width}",
        f"height={calib.height}",
        f"ndisp={calib.ndisp}",
        f"isint={calib.isint}",
    ]
    for key in ("vmin", "vmax", "dyavg", "dymax"):
        value = getattr(calib, key)
        if value is not None:
            lines.append(f"{key}={value:.10g}")
    lines += [f"{k}={v}" for k, v in calib.extra.items()]
    return "\n".join(lines) + "\n"


def write_calib_txt(path: str | os.PathLike, calib: MiddleburyCalib) -> None:
    write_text(path, format_calib_txt(calib))
