"""Preprocessing stages: filters applied to both images before the matching cost.

Each stage replaces ``state.left`` and ``state.right`` by float32 images of the same shape,
processing every colour channel. Band-pass filters (LoG, mean removal, bilateral background
subtraction) return ``128 + response`` clipped to [0, 255], so later stages keep working on the
pipeline's [0, 255] range; the x-Sobel prefilter returns StereoBM's [0, 2·cap] range. They run
on the whole image (before any row strips), with OpenCV.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from ..registry import param, register
from .state import MatchState


def _apply(state: MatchState, func) -> None:
    state.left = np.ascontiguousarray(func(state.left), dtype=np.float32)
    state.right = np.ascontiguousarray(func(state.right), dtype=np.float32)


def _centred(response: np.ndarray) -> np.ndarray:
    # Signed band-pass responses are offset to mid-grey so the [0, 255] convention holds.
    # In place in float32: ~10x faster than clip(response + 128.0).astype on numpy 2.x.
    out = np.add(response, np.float32(128), dtype=np.float32)
    np.clip(out, np.float32(0), np.float32(255), out=out)
    return out


@register("preprocess", "none")
def no_preprocess(state: MatchState, params) -> None:
    """Leave the images unchanged."""


@dataclass(frozen=True)
class LoGParams:
    sigma: float = param(1.0, "Gaussian scale of the Laplacian of Gaussian (larger = coarser band, less noise)", unit="px", low=0.3, high=20.0)
    gain: float = param(1.0, "multiplier of the response before re-centring at 128", low=0.01, high=100.0)


@register("preprocess", "log", LoGParams)
def log_filter(state: MatchState, p: LoGParams) -> None:
    """Laplacian of Gaussian band-pass filter, output 128 + gain·LoG clipped to [0, 255].

    Removes the local brightness level (and so bias differences between the cameras) and
    emphasises texture at scale σ (Scharstein & Szeliski 2002, §3.1; Nishihara 1984). Large σ
    loses fine texture; small σ keeps noise.
    """

    def f(img):
        blur = cv2.GaussianBlur(img, (0, 0), p.sigma, borderType=cv2.BORDER_REPLICATE)
        lap = cv2.Laplacian(blur, cv2.CV_32F, ksize=1, borderType=cv2.BORDER_REPLICATE)
        return _centred(-p.gain * lap.reshape(img.shape))

    _apply(state, f)


@dataclass(frozen=True)
class MeanRemovalParams:
    window: tuple[int, int] = param((9, 9), "window (height, width) of the local mean, odd", unit="px", low=3, high=101)

    def __post_init__(self):
        from .cost import check_odd_window

        check_odd_window("preprocess.mean_removal.window", self.window)


@register("preprocess", "mean_removal", MeanRemovalParams)
def mean_removal(state: MatchState, p: MeanRemovalParams) -> None:
    """Subtract the local mean (box filter): output 128 + I − mean_window(I), clipped.

    Cancels a brightness offset between the views at the cost of one box filter per image;
    the preprocessing of Di Stefano et al.'s fast area-based matcher (2004). Small windows
    also remove low-frequency texture; large windows leave slow illumination changes.
    """
    ksize = (p.window[1], p.window[0])

    def f(img):
        mean = cv2.boxFilter(img, -1, ksize, borderType=cv2.BORDER_REFLECT)
        return _centred(img - mean.reshape(img.shape))

    _apply(state, f)


@dataclass(frozen=True)
class BilateralSubtractionParams:
    sigma_space: float = param(4.0, "spatial σ of the bilateral filter", unit="px", low=0.5, high=50.0)
    sigma_color: float = param(20.0, "range σ of the bilateral filter", unit="grey levels", low=1.0, high=255.0)


@register("preprocess", "bilateral_subtraction", BilateralSubtractionParams)
def bilateral_subtraction(state: MatchState, p: BilateralSubtractionParams) -> None:
    """Bilateral background subtraction: output 128 + I − bilateral(I), clipped.

    Like mean removal but the background estimate does not blur across edges, so the
    subtraction does not create halos at depth discontinuities (Ansar, Castano & Matthies
    2004). Larger σ_color removes more texture along with the background.
    """
    d = int(2 * round(2 * p.sigma_space) + 1)

    def f(img):
        bil = cv2.bilateralFilter(img, d, p.sigma_color, p.sigma_space, borderType=cv2.BORDER_REFLECT)
        return _centred(img - bil.reshape(img.shape))

    _apply(state, f)


@dataclass(frozen=True)
class XSobelParams:
    cap: int = param(31, "clip the x-derivative to [-cap, cap] (OpenCV preFilterCap)", unit="grey levels", low=1, high=63)


@register("preprocess", "xsobel", XSobelParams)
def xsobel(state: MatchState, p: XSobelParams) -> None:
    """x-Sobel prefilter as in OpenCV StereoBM: clip(Sobel_x(I), −cap, cap) + cap.

    The 3×3 horizontal derivative removes brightness offsets and keeps the texture that
    matters along epipolar lines; clipping limits the influence of strong edges. Output range
    [0, 2·cap] (not [0, 255]); pair with AD/SAD costs.
    """

    def f(img):
        sob = cv2.Sobel(img, cv2.CV_32F, 1, 0, ksize=3, borderType=cv2.BORDER_REFLECT_101)
        return (np.clip(sob.reshape(img.shape), -p.cap, p.cap) + p.cap).astype(np.float32)

    _apply(state, f)


def match_histogram(source: np.ndarray, reference: np.ndarray) -> np.ndarray:
    """Map ``source`` intensities so its histogram matches ``reference`` (per channel).

    Each distinct source value goes to the reference quantile at its mid-rank (monotonic, so
    equal values stay equal). (H, W) or (H, W, C) float32 in, same shape out.
    """
    src = source.reshape(source.shape[0] * source.shape[1], -1)
    ref = reference.reshape(reference.shape[0] * reference.shape[1], -1)
    out = np.empty_like(src, dtype=np.float32)
    for c in range(src.shape[1]):
        values, inverse, counts = np.unique(src[:, c], return_inverse=True, return_counts=True)
        mid = (np.cumsum(counts) - 0.5 * counts) / src.shape[0]
        ref_sorted = np.sort(ref[:, c])
        ref_q = (np.arange(ref_sorted.size) + 0.5) / ref_sorted.size
        out[:, c] = np.interp(mid, ref_q, ref_sorted).astype(np.float32)[inverse.ravel()]
    return out.reshape(source.shape)


@dataclass(frozen=True)
class HistogramParams:
    reference: str = param("left", "which view keeps its histogram (the other is mapped onto it)", choices=("left", "right"))


@register("preprocess", "histogram_matching", HistogramParams)
def histogram_matching(state: MatchState, p: HistogramParams) -> None:
    """Per-pair histogram matching: remap one view so its intensity histogram equals the other's.

    Corrects global photometric differences (exposure, gain, gamma: any monotonic change)
    before a cost that assumes brightness constancy such as AD/SSD; does nothing for local
    changes (vignetting, specularities). Per channel.
    """
    if p.reference == "left":
        state.right = match_histogram(state.right, state.left)
    else:
        state.left = match_histogram(state.left, state.right)
