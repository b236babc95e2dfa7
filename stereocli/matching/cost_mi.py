"""Hierarchical mutual information cost ``hmi`` (Hirschmüller 2008, §2.3, eq. 5–11).

MI between the left image and the right image *warped by a disparity map* is turned into a
pixel-wise cost table ``cost(i, k) = −mi(i, k)`` over intensity bins ``(i, k)``:

* joint histogram ``P`` of (left bin, right bin at x − D(x)) over pixels with a valid disparity,
* entropies ``h(i, k) = −log(P ⊗ g) ⊗ g`` (``g``: 7×7 Gaussian; the paper's Parzen estimate)
  and the marginals likewise; ``mi = h_L(i) + h_R(k) − h_LR(i, k)``.

The disparity comes from coarse to fine: at the coarsest level (1/2^(levels−1) size) a random
disparity map seeds ``iterations`` rounds of "MI table → cost → SGM"; each finer level runs one
round starting from the previous level's disparity (doubled and upsampled). The full-resolution
cost uses the table of the finest round. Occluded/mismatched pixels are excluded from the
histograms by a left-right check. The nested SGM uses :func:`stereocli.matching.optimize.sgm.run_sgm`
with its default penalties.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from ..registry import StageTraits, param, register
from .kernels.costs import mi_volume
from .kernels.maps import lr_check
from .state import MatchState, Wants


@dataclass(frozen=True)
class HMIParams:
    levels: int = param(4, "pyramid levels (coarsest = 1/2^(levels-1) size)", low=1, high=8)
    iterations: int = param(3, "MI/SGM rounds at the coarsest level (one per finer level)", low=1, high=10)
    bins: int = param(64, "intensity bins per image for the histograms", low=8, high=256)
    sigma: float = param(1.0, "Gaussian (7×7) smoothing of the histograms, in bins", unit="bins", low=0.1, high=10.0)
    seed: int = param(0, "seed of the random initial disparity (deterministic)", low=0, high=2**31 - 1)


def _bins(gray: np.ndarray, bins: int) -> np.ndarray:
    return np.minimum((gray * (bins / 256.0)).astype(np.int32), bins - 1).astype(np.int32)


def mi_table(left_bins: np.ndarray, right_bins: np.ndarray, disp: np.ndarray, bins: int, sigma: float) -> np.ndarray:
    """Cost table ``−mi`` (bins, bins) float32, shifted to start at 0, from the pixels whose
    (rounded) disparity is finite and lands inside the right image."""
    h, w = left_bins.shape
    ys, xs = np.nonzero(np.isfinite(disp))
    xr = xs - np.floor(disp[ys, xs] + 0.5).astype(np.int64)
    ok = (xr >= 0) & (xr < w)
    ys, xs, xr = ys[ok], xs[ok], xr[ok]
    counts = np.bincount(left_bins[ys, xs] * bins + right_bins[ys, xr], minlength=bins * bins)
    joint = counts.reshape(bins, bins).astype(np.float64) + 1e-3  # keep log() finite
    p = joint / joint.sum()
    eps = 1e-9

    def blur(a):
        return cv2.GaussianBlur(a, (7, 7), sigma, borderType=cv2.BORDER_REPLICATE)

    h_joint = blur(-np.log(np.maximum(blur(p), eps)))
    pl, pr = p.sum(axis=1), p.sum(axis=0)
    h_l = blur(-np.log(np.maximum(blur(np.tile(pl[:, None], (1, 7))), eps)))[:, 3]
    h_r = blur(-np.log(np.maximum(blur(np.tile(pr[None, :], (7, 1))), eps)))[3, :]
    mi = h_l[:, None] + h_r[None, :] - h_joint
    cost = -mi
    return (cost - cost.min()).astype(np.float32)


def _round(left_g, right_g, disp, min_disp, ndisp, p: HMIParams, want_right: bool):
    """One MI round at one level: table from ``disp``, cost, SGM. Returns (table, state)."""
    from .optimize.sgm import SGMParams, run_sgm

    lb, rb = _bins(left_g, p.bins), _bins(right_g, p.bins)
    table = mi_table(lb, rb, disp, p.bins, p.sigma)
    cmax = float(table.max())
    st = MatchState(left_g, right_g, min_disp, ndisp, wants=Wants(right=want_right))
    st.cost = mi_volume(lb, rb, table, min_disp, ndisp, cmax)
    st.cost_max = cmax
    run_sgm(st, SGMParams())
    return table, st


# Only its output volume counts: the nested levels are at most 1/4 of its size.
@register("cost", "hmi", HMIParams, traits=StageTraits(volume_copies=0.0))
def hmi_cost(state: MatchState, p: HMIParams) -> None:
    """Hierarchical mutual information (Hirschmüller 2008): a cost learnt from the pair itself.

    Models any (even non-monotonic) global intensity mapping between the views; computed
    coarse to fine with the previous level's disparity warping the right image (see module
    docstring). Costs are −MI of intensity bins, shifted to start at 0.
    """
    left_g = np.ascontiguousarray(state.gray("left"), np.float32)
    right_g = np.ascontiguousarray(state.gray("right"), np.float32)
    h, w = left_g.shape
    rng = np.random.default_rng(p.seed)
    disp = None
    for level in range(p.levels - 1, 0, -1):
        f = 2**level
        sw, sh = max(8, w // f), max(8, h // f)
        lg = cv2.resize(left_g, (sw, sh), interpolation=cv2.INTER_AREA)
        rg = cv2.resize(right_g, (sw, sh), interpolation=cv2.INTER_AREA)
        md = int(np.floor(state.min_disp * sw / w))
        nd = max(2, int(np.ceil(state.ndisp * sw / w)) + 1)
        if disp is None:
            disp = (md + rng.integers(0, nd, (sh, sw))).astype(np.float32)
            rounds = p.iterations
        else:
            disp = _resize_disp(disp, sw, sh)
            rounds = 1
        for _ in range(rounds):
            _, st = _round(lg, rg, disp, md, nd, p, True)
            disp = lr_check(st.disparity, st.disparity_right, 1.0)
    if disp is None:  # a single level: random start, `iterations` rounds at full size
        disp = (state.min_disp + rng.integers(0, state.ndisp, (h, w))).astype(np.float32)
        for _ in range(p.iterations - 1):
            _, st = _round(left_g, right_g, disp, state.min_disp, state.ndisp, p, True)
            disp = lr_check(st.disparity, st.disparity_right, 1.0)
    else:
        disp = _resize_disp(disp, w, h)
    lb, rb = _bins(left_g, p.bins), _bins(right_g, p.bins)
    table = mi_table(lb, rb, disp, p.bins, p.sigma)
    state.cost_max = float(table.max())
    state.cost = mi_volume(lb, rb, table, state.min_disp, state.ndisp, state.cost_max)


def _resize_disp(disp: np.ndarray, w: int, h: int) -> np.ndarray:
    """Nearest-neighbour upsampling with disparities scaled by the width ratio (+inf kept)."""
    scale = w / disp.shape[1]
    ys = np.minimum((np.arange(h) * disp.shape[0] / h).astype(np.int64), disp.shape[0] - 1)
    xs = np.minimum((np.arange(w) * disp.shape[1] / w).astype(np.int64), disp.shape[1] - 1)
    return (disp[ys][:, xs] * np.float32(scale)).astype(np.float32)
