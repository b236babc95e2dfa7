"""Colour maps for disparity and error previews (8-bit RGB: previews only, never data).

Shared by ``match --viz``, ``eval --error-maps`` and the HTML report, so every picture of a
disparity map in the project uses the same colours for the same values, with a colour bar
labelled with the range's numbers.
"""

from __future__ import annotations

import cv2
import numpy as np

#: Percentiles of the finite disparities used as the colour range when none is given; robust
#: to a few wild values that would otherwise squash the whole map into one colour.
ROBUST_PERCENTILES = (1.0, 99.0)


def disparity_range(disp: np.ndarray, percentiles: tuple[float, float] = ROBUST_PERCENTILES) -> tuple[float, float]:
    """Robust (vmin, vmax) of the finite values of ``disp``; (0, 1) when nothing is finite."""
    finite = np.asarray(disp)[np.isfinite(disp)]
    if finite.size == 0:
        return 0.0, 1.0
    lo, hi = np.percentile(finite, percentiles)
    lo, hi = float(lo), float(hi)
    if hi <= lo:
        hi = lo + 1.0
    return lo, hi


def _apply_colormap(values: np.ndarray, valid: np.ndarray, vmin: float, vmax: float, cmap: int) -> np.ndarray:
    scaled = np.zeros(values.shape, dtype=np.float64)
    span = vmax - vmin if vmax > vmin else 1.0
    np.divide(np.where(valid, values, vmin) - vmin, span, out=scaled)
    index = np.clip(np.round(scaled * 255.0), 0, 255).astype(np.uint8)
    rgb = cv2.cvtColor(cv2.applyColorMap(index, cmap), cv2.COLOR_BGR2RGB)
    rgb[~valid] = 0
    return rgb


def colorize_disparity(disp: np.ndarray, vmin: float | None = None, vmax: float | None = None) -> np.ndarray:
    """Colour a disparity map for viewing (turbo colour map: blue = far, red = near).

    Parameters
    ----------
    disp : (H, W) float array, pixels; +inf (or any non-finite value) = invalid.
    vmin, vmax : colour range in pixels; each missing bound comes from the 1st / 99th
        percentile of the finite values. Values outside the range saturate.

    Returns
    -------
    (H, W, 3) uint8 RGB; invalid pixels are black.
    """
    disp = np.asarray(disp, dtype=np.float32)
    if disp.ndim != 2:
        raise ValueError(f"disparity must be (H, W), got shape {disp.shape}")
    if vmin is None or vmax is None:
        lo, hi = disparity_range(disp)
        vmin = lo if vmin is None else vmin
        vmax = hi if vmax is None else vmax
    return _apply_colormap(disp, np.isfinite(disp), float(vmin), float(vmax), cv2.COLORMAP_TURBO)


def colorize_error(error: np.ndarray, vmax: float, valid: np.ndarray | None = None) -> np.ndarray:
    """Colour an absolute-error map (inferno: black/purple = small, yellow = ``>= vmax``).

    ``error`` is (H, W) float pixels; pixels outside ``valid`` (default: finite errors) are
    drawn dark grey so "not scored" differs from "error 0".
    """
    error = np.asarray(error, dtype=np.float32)
    if valid is None:
        valid = np.isfinite(error)
    rgb = _apply_colormap(error, valid, 0.0, float(vmax), cv2.COLORMAP_INFERNO)
    rgb[~valid] = (40, 40, 40)
    return rgb


def legend_bar(vmin: float, vmax: float, width: int, *, kind: str = "disparity", label: str = "px",
               height: int = 34, zoom: float = 1.0) -> np.ndarray:
    """A horizontal colour bar with min / mid / max labels, (height·zoom, width, 3) uint8 RGB.

    ``kind`` is ``"disparity"`` (turbo) or ``"error"`` (inferno), matching the colourisers;
    ``zoom`` enlarges the bar and its text (for wide images).
    """
    width = max(int(width), 60)
    height, bar_rows = round(height * zoom), round(12 * zoom)
    ramp = np.tile(np.linspace(vmin, vmax, width, dtype=np.float32), (bar_rows, 1))
    if kind == "error":
        bar = colorize_error(ramp, vmax)
    else:
        bar = colorize_disparity(ramp, vmin, vmax)
    canvas = np.full((height, width, 3), 255, dtype=np.uint8)
    canvas[:bar_rows] = bar
    font, scale, thickness = cv2.FONT_HERSHEY_SIMPLEX, 0.4 * zoom, max(1, round(zoom))
    texts = [(f"{vmin:.3g}", 0), (f"{(vmin + vmax) / 2:.3g}", 1), (f"{vmax:.3g} {label}", 2)]
    for text, where in texts:
        (tw, _), _ = cv2.getTextSize(text, font, scale, thickness)
        x = [0, (width - tw) // 2, width - tw - 1][where]
        cv2.putText(canvas, text, (max(x, 0), height - round(6 * zoom)), font, scale, (0, 0, 0), thickness,
                    cv2.LINE_AA)
    return canvas


def disparity_preview(disp: np.ndarray, vmin: float | None = None, vmax: float | None = None) -> np.ndarray:
    """``match --viz``: the coloured disparity (:func:`colorize_disparity`) above a colour bar
    labelled with the range's numbers in px, (H + bar, max(W, 60), 3) uint8 RGB.

    A missing bound comes from the map's robust range (:func:`disparity_range`). The bar grows
    with the image width, so its numbers stay readable on large maps.
    """
    disp = np.asarray(disp, dtype=np.float32)
    if vmin is None or vmax is None:
        lo, hi = disparity_range(disp)
        vmin = lo if vmin is None else vmin
        vmax = hi if vmax is None else vmax
    width = disp.shape[1] if disp.ndim == 2 else 0
    legend = legend_bar(float(vmin), float(vmax), width, label="px", zoom=max(1.0, width / 800))
    return with_legend(colorize_disparity(disp, vmin, vmax), legend)


def with_legend(image: np.ndarray, legend: np.ndarray) -> np.ndarray:
    """Stack ``legend`` under ``image`` (both RGB uint8), padding the narrower one with white."""
    width = max(image.shape[1], legend.shape[1])

    def pad(a: np.ndarray) -> np.ndarray:
        if a.shape[1] == width:
            return a
        out = np.full((a.shape[0], width, 3), 255, dtype=np.uint8)
        out[:, : a.shape[1]] = a
        return out

    return np.vstack([pad(image), pad(legend)])


def gray_preview(image: np.ndarray) -> np.ndarray:
    """(H, W, 3) uint8 RGB grey version of an 8/16-bit grey or RGB image (for overlays)."""
    img = np.asarray(image)
    if img.dtype == np.uint16:
        img = (img / 257.0).astype(np.uint8)
    elif img.dtype != np.uint8:
        img = np.clip(img, 0, 255).astype(np.uint8)
    if img.ndim == 3:
        img = cv2.cvtColor(img, cv2.COLOR_RGB2GRAY)
    return np.repeat(img[..., None], 3, axis=2)
