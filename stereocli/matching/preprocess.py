"""Preprocessing stages: filters applied to both images before the matching cost,
``column_pattern``, which removes a sensor's even/odd column offset, and ``row_align``, which
resamples the right view onto the left view's rows.

Each filter replaces ``state.left`` and ``state.right`` by float32 images of the same shape,
processing every colour channel. Band-pass filters (LoG, mean removal, bilateral background
subtraction) return ``128 + response`` clipped to [0, 255], so later stages keep working on the
pipeline's [0, 255] range; the x-Sobel prefilter returns StereoBM's [0, 2·cap] range. They run
on the whole image (before any row strips), with OpenCV.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import TYPE_CHECKING, Literal, cast

import cv2
import numpy as np

from ..registry import StageTraits, param, register
from .kernels.images import luma
from .state import MatchState

if TYPE_CHECKING:
    from .vertical_offset import VerticalOffset


def _apply(state: MatchState, func) -> None:
    state.left = np.ascontiguousarray(func(state.left), dtype=np.float32)
    state.right = np.ascontiguousarray(func(state.right), dtype=np.float32)


def _centred(response: np.ndarray) -> np.ndarray:
    # Signed band-pass responses are offset to mid-grey so the [0, 255] convention holds.
    # In place in float32: no float64 temporaries and no extra copy, as clip(response + 128.0).astype
    # would make.
    out = np.add(response, np.float32(128), dtype=np.float32)
    np.clip(out, np.float32(0), np.float32(255), out=out)
    return out


@register("preprocess", "none")
def no_preprocess(state: MatchState, params) -> None:
    """Leave the images unchanged."""


@dataclass(frozen=True)
class LoGParams:
    sigma: float = param(1.0, "Gaussian scale of the Laplacian of Gaussian (larger = coarser band, less noise)",
                         unit="px", low=0.3, high=20.0)
    gain: float = param(1.0, "multiplier of the response before re-centring at 128", low=0.01, high=100.0)


@register("preprocess", "log", LoGParams, traits=StageTraits(map_copies=6.5))
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


@register("preprocess", "mean_removal", MeanRemovalParams, traits=StageTraits(map_copies=3.5))
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


@register("preprocess", "bilateral_subtraction", BilateralSubtractionParams, traits=StageTraits(map_copies=3.5))
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
    cap: int = param(31, "clip the x-derivative to [-cap, cap] (OpenCV preFilterCap)",
                     unit="grey levels", low=1, high=63)


@register("preprocess", "xsobel", XSobelParams, traits=StageTraits(map_copies=3.5))
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
    reference: str = param("left", "which view keeps its histogram (the other is mapped onto it)",
                           choices=("left", "right"))


@register("preprocess", "histogram_matching", HistogramParams, traits=StageTraits(map_copies=10.5))
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


_DETECTION_ROW_STEP = 8


@dataclass(frozen=True)
class ColumnPattern:
    """An even/odd column offset measured in one image (:func:`measure_column_pattern`)."""

    #: (W,) float32 grey levels: even columns read this much brighter than the scene, odd ones
    #: this much darker.
    amplitude: np.ndarray
    #: median of ``|amplitude|`` over the columns, grey levels
    level: float
    #: standard error of ``amplitude`` (the scene's detail left in the column means, from the
    #: scatter between neighbouring columns' own estimates), grey levels
    noise: float


def measure_column_pattern(image: np.ndarray, *, window: int = 32, clip: float = 2.0,
                           valid: np.ndarray | None = None, row_step: int = 1) -> ColumnPattern:
    """Measure an even/odd column offset in an image.

    Sensors that read even and odd columns through different amplifiers leave this pattern.
    Each pixel's difference from the mean of its four row neighbours (x ± 1, x ± 2) holds
    ``a·(−1)^x`` exactly (the neighbours' offsets cancel), plus the scene's own detail (a
    brightness ramp across the columns cancels too). Signed by the column's parity, these
    differences' robust mean down each column is ``a`` there: their sum clipped to ±``clip``
    grey levels over the number of unclipped ones (one Newton step of a Huber M-estimate from
    0, so that edges and strong texture neither dominate it nor shrink it), then averaged over
    the columns within ``window / 2`` (the amplitude drifts slowly across a sensor; 0: one
    amplitude for the whole image). The two columns at each border, which lack neighbours on
    one side, take the amplitude of the nearest column that has them.

    Parameters
    ----------
    image : (H, W) array, grey levels.
    window : columns of the moving average of the amplitude (0: its mean over the image).
    clip : the clip, grey levels.
    valid : optional (H, W) bool mask of the pixels to use (rectification borders excluded).
    row_step : use every ``row_step``-th row only (a quicker, noisier estimate).
    """
    # numpy rather than OpenCV, and few calls: OpenCV's worker threads keep spinning after a call
    # and would slow the compiled kernels that follow by more than this measurement takes
    grey = np.asarray(image[::row_step], dtype=np.float32)
    height, width = grey.shape
    if width < 8 or height < 1:
        return ColumnPattern(np.zeros(width, np.float32), 0.0, float("inf"))
    detail = grey[:, 2:-2] - np.float32(0.25) * (grey[:, :-4] + grey[:, 1:-3] + grey[:, 3:-1] + grey[:, 4:])
    detail[:, 1::2] *= -1.0  # its first column is column 2: + on even columns, − on odd ones
    unclipped = np.abs(detail) < clip
    np.clip(detail, -clip, clip, out=detail)
    if valid is None:
        count = np.full(width - 4, height, np.float32)
    else:
        # a pixel counts only when its four row neighbours are valid too
        v = valid[::row_step]
        used = v[:, 2:-2] & v[:, :-4] & v[:, 1:-3] & v[:, 3:-1] & v[:, 4:]
        detail[~used] = 0.0
        unclipped &= used
        count = used.sum(axis=0).astype(np.float32)
    # the slope of the clipped sum is the number of unclipped values; held to at least a quarter
    # of the column's, so that a busy column is not scaled up by a handful of flat pixels
    columns = detail.sum(axis=0) / np.maximum(unclipped.sum(axis=0), np.maximum(0.25 * count, 1.0))
    # The scatter of one column's estimate, from differences between neighbouring columns of
    # the same parity (a slow drift of the amplitude cancels in them); MAD-based.
    counted = count > 0
    same_parity = np.diff(columns[counted][::2])
    scatter = 1.4826 * float(np.median(np.abs(same_parity))) / np.sqrt(2.0) if same_parity.size else float("inf")
    # the average over columns weighs each by its pixels used (none on an invalid column)
    weighted = np.concatenate(([0.0], np.cumsum(columns * count, dtype=np.float64)))
    weights = np.concatenate(([0.0], np.cumsum(count, dtype=np.float64)))
    n = width - 4
    if window <= 0:
        lo, hi = np.zeros(n, np.int64), np.full(n, n)
    else:
        index = np.arange(n)
        lo, hi = np.maximum(index - window // 2, 0), np.minimum(index + window // 2 + 1, n)
    amplitude = np.empty(width, np.float32)
    amplitude[2:-2] = (weighted[hi] - weighted[lo]) / np.maximum(weights[hi] - weights[lo], 1e-6)
    amplitude[:2], amplitude[-2:] = amplitude[2], amplitude[-3]
    averaged = max(min(window | 1 if window > 0 else n, int(counted.sum())), 1)
    return ColumnPattern(amplitude=amplitude, level=float(np.median(np.abs(amplitude))),
                         noise=scatter / np.sqrt(averaged))


def remove_column_pattern(image: np.ndarray, amplitude: np.ndarray) -> np.ndarray:
    """``image`` (H, W) or (H, W, C) minus ``amplitude[x]·(−1)^x`` in every column x, float32;
    ``amplitude`` is (W,) for all channels or (W, C) per channel."""
    width = image.shape[1]
    parity = np.where(np.arange(width) % 2 == 0, 1.0, -1.0).astype(np.float32)
    offset = amplitude * (parity if amplitude.ndim == 1 else parity[:, None])
    out = np.subtract(image, offset[None] if image.ndim == amplitude.ndim + 1 else offset[None, :, None],
                      dtype=np.float32)
    np.clip(out, np.float32(0), np.float32(255), out=out)
    return out


@dataclass(frozen=True)
class ColumnPatternParams:
    min_amplitude: float = param(0.2, "a view whose median amplitude is below this is left as it is (photographs "
                                 "without the pattern measure 0.01–0.07)", unit="grey levels", low=0.0, high=50.0)
    min_significance: float = param(3.0, "...and one whose amplitude is below this many times its own standard error "
                                    "(the scene's detail left in the column means: small or strongly textured views)",
                                    low=0.0, high=1000.0)
    window: int = param(32, "columns over which the amplitude is averaged (it drifts slowly across a sensor); 0: one "
                        "amplitude for the whole image", unit="px", low=0, high=100000)
    clip: float = param(2.0, "the column estimate's clip: differences from its row neighbours beyond this count as "
                        "this far, so that edges and strong texture do not sway it",
                        unit="grey levels", low=0.1, high=255.0)


@register("preprocess", "column_pattern", ColumnPatternParams,
          traits=StageTraits(reads_left_colour=False, reads_right_colour=False, map_copies=0.5))
def column_pattern(state: MatchState, p: ColumnPatternParams) -> None:
    """Remove an even/odd column offset (fixed-pattern sensor noise) from each view that has one.

    Some sensors read even and odd columns through different amplifiers, so every other column
    is a little brighter. Census bits compare a pixel with its neighbours; on a weakly
    textured surface, a pattern of half a grey level decides many of them, and the cost then
    prefers disparities that line the columns' parities up (even ones), whatever the surface's
    true disparity. The stage measures the pattern in each view's grey image
    (:func:`measure_column_pattern`) and, where its median amplitude reaches ``min_amplitude``
    and ``min_significance`` standard errors, subtracts it from every channel (each measured on
    its own). Views without the pattern are left untouched. The amplitudes go into the match
    record (``stage_notes``).

    No bundled preset runs it: its gain rests on one scene (Tsukuba, whose camera has the
    pattern), and none of the validation scenes has the pattern, so it shows no gain there. Put
    it first in ``preprocess`` for a camera that has one.
    """
    note = {}
    for which in ("left", "right"):
        valid = state.left_valid if which == "left" else state.right_valid
        image = state.left if which == "left" else state.right
        # The grey of every eighth row tells a pattern apart from none (Tsukuba's views: 0.66 and
        # 0.68 grey levels, 5.1 and 6.5 standard errors; every other benchmark view at most 0.11
        # and 0.5); views that have one are then measured on every other row, per channel.
        rows = np.ascontiguousarray(image[::_DETECTION_ROW_STEP])
        found = measure_column_pattern(rows if rows.ndim == 2 else luma(rows), window=p.window, clip=p.clip,
                                       valid=None if valid is None else valid[::_DETECTION_ROW_STEP])
        applied = found.level >= p.min_amplitude and found.level >= p.min_significance * found.noise
        note[f"{which}_amplitude"] = round(found.level, 3)
        note[f"{which}_standard_error"] = round(found.noise, 3)
        note[f"{which}_applied"] = bool(applied)
        if not applied:
            continue
        channels = [image] if image.ndim == 2 else [image[..., c] for c in range(image.shape[2])]
        amplitude = np.stack([measure_column_pattern(ch, window=p.window, clip=p.clip, valid=valid,
                                                     row_step=2).amplitude for ch in channels], axis=-1)
        corrected = remove_column_pattern(image, amplitude[:, 0] if image.ndim == 2 else amplitude)
        if which == "left":
            state.left = corrected
        else:
            state.right = corrected
    state.notes["column_pattern"] = note


@dataclass(frozen=True)
class RowAlignParams:
    model: str = param("plane", "vertical offset model: a plane (shift, rotation, scale difference) or a constant "
                       "shift", choices=("plane", "constant"))
    points: int = param(600, "corners of the left image tracked into the right one", low=10, high=100000)
    window: int = param(21, "Lucas–Kanade window side", unit="px", low=5, high=99)
    sigma: float = param(3.0, "scale of the local brightness normalisation the tracking runs on (0 = raw grey)",
                         unit="px", low=0.0, high=50.0)
    min_tracks: int = param(30, "fewest surviving tracks to correct the pair at all (a plane needs three times as "
                            "many)", low=3, high=100000)
    max_offset: float = param(8.0, "largest correction: a larger fitted offset leaves the pair as it is (rectify it "
                              "instead)", unit="px", low=0.0, high=50.0)
    max_spread: float = param(0.5, "the tracks' robust standard deviation about the plane above which the pair is "
                              "left as it is (its rows are off in a way a plane does not describe: rectify it)",
                              unit="px", low=0.0, high=50.0)
    min_offset: float = param(0.1, "smallest correction: a pair whose fitted offset stays below this everywhere is "
                              "left as it is (the fit's own error on aligned pairs reaches 0.06 px, and resampling "
                              "blurs a little)", unit="px", low=0.0, high=50.0)
    reduce: int = param(2, "track on the images reduced by this factor (1: full resolution, four times the pixels, "
                        "same MiddEval3 scores)", choices=(1, 2, 4))
    min_pixels: int = param(0, "fewest pixels of the reduced images: smaller pairs track at half the factor, or at "
                            "full resolution (a small image reduced 4x leaves too few corners)", low=0, high=10**9)
    measure: bool = param(True, "track corners and fit the plane; false: apply offset, tilt_x and tilt_y as given (a "
                          "rig's known rows, e.g. from an earlier pair's params.json), without tracking")
    offset: float = param(0.0, "with measure: false, how far below its left-view row a point appears in the right "
                          "view at the image centre", unit="px", low=-50.0, high=50.0)
    tilt_x: float = param(0.0, "with measure: false, the change of that offset across the image width",
                          unit="px", low=-50.0, high=50.0)
    tilt_y: float = param(0.0, "with measure: false, the change of that offset across the image height",
                          unit="px", low=-50.0, high=50.0)


def _mirrored_row_align(p: RowAlignParams, note: dict | None) -> RowAlignParams:
    """The pair's plane given to the mirrored pair (the flipped right view as the left, the
    flipped left view as the right), whose right view must move the other way.

    Swapping the views negates the offset and its change down the image; flipping the columns
    negates the change across them once more, so ``tilt_x`` keeps its sign. A pair left as it
    was (too few tracks, scattered ones, an offset too small) stays as it is mirrored too. The
    plane is read at the other view's column (``x − d``): with a tilt of 1 px across the width
    and disparities of a tenth of it, 0.1 px off at most, well within the fit's spread."""
    return _given_plane(p, note, sign=-1.0)


def _repeated_row_align(p: RowAlignParams, note: dict | None) -> RowAlignParams:
    """The pair's plane given to another pair of the same rig (a later frame): the same
    correction, or none where the pair was left as it was."""
    return _given_plane(p, note, sign=1.0)


def _given_plane(p: RowAlignParams, note: dict | None, *, sign: float) -> RowAlignParams:
    """``p`` applying the plane of ``note`` (what row_align found on a pair) without measuring:
    its offset and its change down the image times ``sign``, its change across the image as it
    is; no correction when the pair was left as it was (or left no note)."""
    if note is None or not note.get("applied"):
        return dataclasses.replace(p, measure=False, offset=0.0, tilt_x=0.0, tilt_y=0.0)
    return dataclasses.replace(p, measure=False, offset=sign * note["offset_px"], tilt_x=note["tilt_x_px"],
                               tilt_y=sign * note["tilt_y_px"])


@register("preprocess", "row_align", RowAlignParams,
          traits=StageTraits(reads_left_colour=False, reads_right_colour=False, mirrored_params=_mirrored_row_align,
                             repeated_params=_repeated_row_align,
                             map_copies=2.5))
def row_align(state: MatchState, p: RowAlignParams) -> None:
    """Resample the right view onto the left view's rows: corrects a residual vertical offset.

    Rectification leaves the rows of real pairs off by a few tenths of a pixel (calibration
    error, a rig that moved), and every census window then compares slightly different rows.
    The stage tracks up to ``points`` corners of the left image into the right one
    (Lucas–Kanade on locally normalised images, kept when the track survives the round trip),
    fits their vertical disparity robustly as a plane over the image (shift, rotation and
    scale difference; a constant with few tracks) and resamples the right view (cubic) so its
    rows meet the left view's. The left view, and so the disparity map's geometry, is left as
    it is. A pair with fewer than ``min_tracks`` tracks, tracks that scatter about the plane by
    more than ``max_spread`` px, or a fitted offset beyond ``max_offset`` px or below
    ``min_offset`` px everywhere, is left unchanged. Only rows move, so the disparities stay
    those of the right view as given (the part of a rotation along the rows stays in them), and
    the pipeline moves the right-referenced map (``--right``) back onto the input's rows. The
    fit goes into the match record (``stage_notes``). ``measure: false`` applies ``offset``,
    ``tilt_x`` and ``tilt_y`` as given instead (a rig whose rows are known: every pair of a batch
    gets the same correction, without tracking). See :mod:`stereocli.matching.vertical_offset`.
    """
    from .vertical_offset import VerticalOffset, fit_vertical_offset, track_rows

    h, w = state.shape
    if not p.measure:
        given = VerticalOffset(p.offset, p.tilt_x, p.tilt_y, w, h, 0, 0.0)
        if given.largest > 0:
            _move_right_rows(state, given)
        state.notes["row_align"] = {**given.as_dict(), "applied": given.largest > 0, "given": True}
        return
    lo, hi = state.min_disp - 1.0, state.min_disp + state.ndisp
    scale = p.reduce
    while scale > 1 and (h // scale) * (w // scale) < p.min_pixels:
        scale //= 2
    left_xy, right_xy = track_rows(state.gray("left"), state.gray("right"), disparity_range=(lo, hi),
                                   left_valid=state.left_valid, points=p.points, window=p.window, sigma=p.sigma,
                                   max_offset=p.max_offset, scale=scale)
    model = cast(Literal["plane", "constant"], p.model)  # one of the parameter's choices
    plane = fit_vertical_offset(left_xy, right_xy, w, h, model=model, min_tracks=p.min_tracks)
    # ``measured``: the plane is a measurement of the rows (enough tracks, close to it), whether
    # or not it was applied; the match job then takes the pair's row alignment from it.
    note: dict = {"tracks_found": int(len(left_xy)), "reduced": scale}
    if plane is None:
        note.update(applied=False, measured=False, reason=f"fewer than {p.min_tracks} tracks")
    elif plane.spread > p.max_spread:
        note.update(plane.as_dict(), applied=False, measured=False,
                    reason=f"tracks scatter {plane.spread:.2f} px about the plane, "
                           f"beyond max_spread {p.max_spread:g} px")
    elif plane.largest > p.max_offset:
        note.update(plane.as_dict(), applied=False, measured=True,
                    reason=f"offset beyond max_offset {p.max_offset:g} px")
    elif plane.largest < p.min_offset:
        note.update(plane.as_dict(), applied=False, measured=True,
                    reason=f"offset below min_offset {p.min_offset:g} px")
    else:
        note.update(plane.as_dict(), applied=True, measured=True)
        _move_right_rows(state, plane)
    state.notes["row_align"] = note


def _move_right_rows(state: MatchState, plane: VerticalOffset) -> None:
    """Resample the right view (and its mask) onto the left view's rows by ``plane``."""
    from .vertical_offset import resample_rows

    state.right = resample_rows(state.right, plane)
    state.right_rows = plane
    if state.right_valid is not None:
        state.right_valid = resample_rows(state.right_valid.astype(np.uint8), plane, cv2.INTER_NEAREST) > 0
