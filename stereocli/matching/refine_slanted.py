"""Slanted-plane refinement: PatchMatch over per-pixel planes around an existing disparity map.

The stage edits the full disparity map (it reads the images, not the cost volume), so it runs
after the row strips are stitched, on a dense map: place it at the end of a refinement chain.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from ..registry import StageTraits, param, register
from .cost import check_odd_window
from .kernels import slanted as ksl
from .state import MatchState


@dataclass(frozen=True)
class SlantedPatchMatchParams:
    radius: int = param(10, "half side of the slanted matching window", unit="px", low=1, high=50)
    stride: int = param(2, "use every stride-th row and column of the window", low=1, high=10)
    census: tuple[int, int] = param((5, 7), "census window (height, width), odd, at most 63 pixels",
                                    unit="px", low=1, high=15)
    upsample: int = param(8, "right image sampled at 1/upsample px (cubic interpolation along rows)", low=1, high=32)
    gamma_c: float = param(10.0, "window weight exp(−Δgrey/γc) against the centre pixel",
                           unit="grey levels", low=0.1, high=1000.0)
    tau: float = param(20.0, "truncation of a window pixel's census Hamming cost", low=1.0, high=64.0)
    prior: float = param(4.0, "weight of the input map: each window pixel adds prior·min(|d − input|, prior_cap)",
                         low=0.0, high=1000.0)
    prior_cap: float = param(1.0, "truncation of the input-map term", unit="px", low=0.0, high=1000.0)
    band: float = param(0.5, "a pixel's disparity stays within this distance of its input value",
                        unit="px", low=0.0, high=1000.0)
    same_plane: float = param(0.0, "a neighbour's plane is not tried where it stays within this distance of the "
                              "pixel's own across the whole window (its cost could hardly differ); 0: only identical "
                              "planes are skipped", unit="px", low=0.0, high=100.0)
    iterations: int = param(2, "PatchMatch iterations (each: propagation + random search, red then black pixels)",
                            low=0, high=20)
    samples: int = param(1, "random plane perturbations tried per pixel and iteration", low=0, high=16)
    shift: float = param(0.5, "range of the random disparity perturbation (halved every iteration)",
                         unit="px", low=0.0, high=100.0)
    slope: float = param(0.1, "range of the random slope perturbation (halved every iteration)",
                         unit="px/px", low=0.0, high=10.0)
    fit_radius: int = param(5, "half side of the window of the initial plane fit", unit="px", low=1, high=50)
    fit_gate: float = param(1.0, "neighbours within this many px of a pixel's disparity enter its plane fit",
                            unit="px", low=0.01, high=1000.0)
    seed: int = param(0, "seed of the random perturbations (results are reproducible)", low=0, high=2**31 - 1)

    def __post_init__(self):
        check_odd_window("refinement.slanted_patchmatch.census", self.census, 63)


@register("refinement", "slanted_patchmatch", SlantedPatchMatchParams, traits=StageTraits(map_copies=22))
def slanted_patchmatch(state: MatchState, p: SlantedPatchMatchParams) -> None:
    """Sub-pixel refinement with slanted support windows (PatchMatch stereo, Bleyer et al. 2011).

    Every valid pixel gets a plane ``d = a·x + b·y + c``: first the weighted least-squares
    plane through its neighbours' input disparities (within ``fit_radius``, gated and
    colour-weighted), then ``iterations`` rounds of PatchMatch in red-black order (Galliani et
    al. 2015): each pixel tries its four neighbours' planes and ``samples`` random
    perturbations of its best one and keeps the plane of lowest cost. The cost of a plane
    follows it across an adaptive-weight window: census Hamming distances between each left
    window pixel and the right image at the plane's sub-pixel disparity there (read from a
    copy upsampled ``upsample`` times), plus a truncated pull towards the input map
    (``prior``), which keeps weakly textured windows where the input put them. A pixel moves at
    most ``band`` px from its input value, so the stage refines slopes and sub-pixel values
    (the stair-casing SGM leaves on slanted surfaces) and leaves depth edges to the voting
    stages before it. Invalid pixels stay invalid. About (1 + 5·iterations)·(radius/stride)²
    census comparisons per pixel.
    """
    disp = np.ascontiguousarray(state.disparity, dtype=np.float32)
    left = np.ascontiguousarray(state.gray("left"), dtype=np.float32)
    right = np.ascontiguousarray(state.gray("right"), dtype=np.float32)
    h, w = left.shape
    guide = np.clip(np.rint(left), 0, 255).astype(np.int64)
    weights = np.exp(-np.arange(256) / p.gamma_c)
    pa, pb, pc = ksl.fit_planes(disp, guide, p.fit_radius, weights, float(p.fit_gate), float(p.band))
    if p.iterations > 0:
        up = int(p.upsample)
        right_up = cv2.resize(right, (w * up, h), interpolation=cv2.INTER_CUBIC) if up > 1 else right
        half_h, half_w = p.census[0] // 2, p.census[1] // 2
        codes_left = ksl.census_codes(left, half_h, half_w, 1)
        codes_right = ksl.census_codes(np.ascontiguousarray(right_up), half_h, half_w, up)
        window = (codes_left, codes_right, guide, weights, disp, up, int(p.radius), int(p.stride), float(p.tau),
                  float(p.prior), float(p.prior_cap))
        cost = ksl.plane_costs(pa, pb, pc, *window)
        lo, hi = float(state.min_disp), float(state.min_disp + state.ndisp - 1)
        # Whether each pixel's plane changed in its last sweep: after the first iteration a pixel
        # retries only the neighbours' planes that did (same result, fewer window costs).
        changed = np.ones((h, w), np.bool_)
        for it in range(p.iterations):
            scale = 0.5 ** it
            for parity in (0, 1):
                ksl.sweep(pa, pb, pc, cost, changed, it > 0, parity, int(p.seed) * 1009 + 2 * it + parity,
                          p.shift * scale, p.slope * scale, int(p.samples), float(p.band), float(p.same_plane), lo, hi,
                          *window)
    state.disparity = ksl.plane_disparity(pa, pb, pc)
