"""Segmentation-based refinements: plane fitting (RANSAC / histogram) and local consistency."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from stereocli import registry
from stereocli.config import build_config
from stereocli.match.pipeline import match_pair
from stereocli.match.refine_segment import PlaneFitParams, fit_segment_planes, segment_image
from stereocli.match.state import MatchState

A, B, C = 0.06, 0.03, 6.0  # slanted plane d = A·x + B·y + C (left-referenced)


def slanted_scene(h: int = 90, w: int = 120, seed: int = 0):
    """A textured slanted plane rendered exactly in both views (bicubic resampling).

    Left pixel (x, y) sees texture point (x, y); with d = A·x + B·y + C it lands on
    x_r = x − d, so the right image at x_r samples the texture at x = (x_r + B·y + C)/(1 − A).
    """
    rng = np.random.default_rng(seed)
    tex = cv2.resize(rng.random((h // 4 + 4, w // 4 + 4)).astype(np.float32) * 200 + 20, (w * 2, h * 2), interpolation=cv2.INTER_CUBIC)
    ys, xs = np.mgrid[0:h, 0:w].astype(np.float32)

    def sample(x, y):  # texture coordinate -> value (texture upsampled ×2, offset keeps x>=0)
        return cv2.remap(tex, (x + w / 2) * 1.0, y * 1.0, cv2.INTER_CUBIC)

    left = sample(xs, ys)
    right = sample((xs + B * ys + C) / (1 - A), ys)
    gt = (A * xs + B * ys + C).astype(np.float32)
    return left, right, gt


def _state(disp: np.ndarray, image: np.ndarray) -> MatchState:
    s = MatchState(image, image, 0, 32)
    s.disparity = disp.astype(np.float32)
    return s


def test_registered():
    assert {"plane_fit", "local_consistency"} <= set(registry.names("refinement"))


@pytest.mark.parametrize("method", ["ransac", "histogram"])
def test_fit_recovers_plane_despite_outliers_and_holes(method):
    h, w = 60, 80
    ys, xs = np.mgrid[0:h, 0:w]
    gt = (A * xs + B * ys + C).astype(np.float32)
    rng = np.random.default_rng(1)
    disp = gt + rng.normal(0, 0.05, gt.shape).astype(np.float32)
    out = rng.random(gt.shape) < 0.25
    disp[out] = rng.uniform(0, 30, out.sum())  # 25 % gross outliers
    disp[10:20, 10:30] = np.inf  # an occlusion hole
    labels = np.zeros((h, w), np.int32)
    p = PlaneFitParams(method=method, replace="outliers", outlier=1.5, min_inliers=0.5)
    planes, support, inliers, counts = fit_segment_planes(disp, labels, p)
    a, b, c, cx, cy = planes[0]
    assert a == pytest.approx(A, abs=2e-3) and b == pytest.approx(B, abs=2e-3)
    assert c - a * cx - b * cy == pytest.approx(C, abs=0.05)
    assert inliers[0] > 0.7 * support[0]
    # the stage replaces the outliers and fills the hole with the plane
    image = np.full((h, w), 100, np.float32)
    state = _state(disp, image)
    registry.get("refinement", "plane_fit").func(state, p)
    err = np.abs(state.disparity - gt)
    assert np.isfinite(state.disparity).all() and err.max() <= p.outlier + 0.2  # kept: within 1.5 px
    assert err[~out].max() < 0.25  # inliers untouched, the hole filled by the plane


def test_ransac_is_reproducible_with_a_seed():
    rng = np.random.default_rng(2)
    disp = rng.uniform(0, 20, (40, 50)).astype(np.float32)
    labels = np.zeros((40, 50), np.int32)
    p = PlaneFitParams(seed=7, iterations=20)
    first = fit_segment_planes(disp, labels, p)[0]
    np.testing.assert_array_equal(first, fit_segment_planes(disp, labels, p)[0])
    other = fit_segment_planes(disp, labels, PlaneFitParams(seed=8, iterations=20))[0]
    assert not np.array_equal(first, other)


def test_segmentation_separates_colours_and_fits_each_plane():
    h, w = 60, 80
    image = np.zeros((h, w, 3), np.float32)
    image[:, :40] = (200, 40, 40)
    image[:, 40:] = (30, 60, 220)
    labels = segment_image(image, 5, 10.0, 4.0, 20)
    assert labels[0, 0] != labels[0, -1] and len(np.unique(labels)) == 2
    ys, xs = np.mgrid[0:h, 0:w]
    gt = np.where(xs < 40, 5.0 + 0.05 * xs, 20.0 - 0.02 * ys).astype(np.float32)
    disp = gt.copy()
    disp[::7, ::5] = np.inf
    disp[5:15, 30:50] = 3.0  # a wrong blob straddling both segments
    state = _state(disp, image)
    registry.get("refinement", "plane_fit").func(state, PlaneFitParams(replace="outliers"))
    wrong = np.abs(state.disparity - gt) > 0.02
    # mean-shift may move a few pixels at the colour edge into the other segment
    assert wrong.mean() < 0.005 and (np.abs(xs[wrong] - 40) <= 3).all()


@pytest.mark.parametrize("method", ["ransac", "histogram"])
def test_slanted_plane_pipeline_recovers_to_a_tenth_of_a_pixel(method, tmp_path):
    left, right, gt = slanted_scene()
    cfg = tmp_path / "slanted.yaml"
    cfg.write_text(
        "preprocess: []\ncost: {name: census, window: [7, 9]}\naggregation: [{name: box, window: [5, 5]}]\n"
        "optimizer: {name: wta}\nrefinement: [{name: subpixel}, {name: lr_check, max_diff: 1.0}, "
        f"{{name: plane_fit, method: {method}, replace: all, min_size: 300}}, {{name: fill}}]\n"
    )
    config = build_config([str(cfg)], [])
    result = match_pair(left, right, config, ndisp=24)
    inner = (slice(6, -6), slice(20, -6))  # left border: x - d < 0 has no match
    err = np.abs(result.disparity - gt)[inner]
    assert err.max() < 0.1, err.max()


def test_local_consistency_removes_spikes_and_keeps_holes():
    h, w = 40, 50
    image = np.full((h, w), 120, np.float32)
    disp = np.full((h, w), 7.0, np.float32)
    disp[10, 10] = 15.0
    disp[20, 30] = 1.0
    disp[30, 5] = np.inf
    state = _state(disp, image)
    registry.get("refinement", "local_consistency").func(state, registry.get("refinement", "local_consistency").make_params({}))
    expected = np.full((h, w), 7.0, np.float32)
    expected[30, 5] = np.inf
    np.testing.assert_allclose(state.disparity, expected)
    assert state.confidence.shape == (h, w) and state.confidence[0, 0] > 0.9


def test_local_consistency_snaps_edges_to_colour_edges():
    h, w = 30, 60
    image = np.full((h, w), 50, np.float32)
    image[:, 30:] = 200  # colour edge at x = 30
    disp = np.full((h, w), 4.0, np.float32)
    disp[:, 27:] = 10.0  # disparity edge 3 px too far left (foreground fattening)
    state = _state(disp, image)
    state.right = image  # right view irrelevant here: same image
    stage = registry.get("refinement", "local_consistency")
    stage.func(state, stage.make_params({"gamma_t": 1000.0}))
    assert (state.disparity[:, 27:30] == 4.0).all() and (state.disparity[:, 30:] == 10.0).all()


def local_consistency_reference(disp, left, right, min_disp, ndisp, radius, gamma_s, gamma_c, gamma_t):
    """Mattoccia's vote, pixel by pixel (Mattoccia 2009, eq. 2–4), with exp evaluated per vote."""
    h, w, c = left.shape
    out = np.full((h, w), np.inf, np.float32)
    for y in range(h):
        for x in range(w):
            if not np.isfinite(disp[y, x]):
                continue
            mass, sumd = {}, {}
            for yy in range(max(0, y - radius), min(h, y + radius + 1)):
                for xx in range(max(0, x - radius), min(w, x + radius + 1)):
                    dg = float(disp[yy, xx])
                    if not np.isfinite(dg):
                        continue
                    k = int(np.floor(dg - min_disp + 0.5))
                    if not 0 <= k < ndisp:
                        continue
                    wgt = np.exp(-np.hypot(yy - y, xx - x) / gamma_s - np.abs(left[y, x] - left[yy, xx]).mean() / gamma_c)
                    xf, xg = int(np.floor(x - dg + 0.5)), int(np.floor(xx - dg + 0.5))
                    inside = 0 <= xf < w and 0 <= xg < w
                    dt = np.abs(right[y, xf] - right[yy, xg]).mean() if inside else 255.0
                    wgt *= np.exp(-dt / gamma_t)
                    mass[k] = mass.get(k, 0.0) + wgt
                    sumd[k] = sumd.get(k, 0.0) + wgt * dg
            best = min(mass, key=lambda k: (-mass[k], k))  # most support, smaller disparity on ties
            out[y, x] = sumd[best] / mass[best]
    return out


def test_local_consistency_kernel_matches_reference_on_random_maps():
    # 8-bit-valued colour images (the kernel's colour tables are exact there), noisy disparities
    # with holes and two surfaces.
    from stereocli.match.kernels import segment as ks

    rng = np.random.default_rng(11)
    h, w = 16, 21
    left = rng.integers(0, 256, (h, w, 3)).astype(np.float32)
    right = rng.integers(0, 256, (h, w, 3)).astype(np.float32)
    disp = (rng.uniform(2, 4, (h, w)) + np.where(np.arange(w) > 10, 5.0, 0.0)).astype(np.float32)
    disp[rng.random((h, w)) < 0.1] = np.inf
    got, _ = ks.local_consistency(disp, left, right, 0, 12, 3, 3.0, 12.0, 12.0, False, np.ones(disp.shape, bool))
    want = local_consistency_reference(disp, left, right, 0, 12, 3, 3.0, 12.0, 12.0)
    np.testing.assert_array_equal(np.isfinite(got), np.isfinite(want))
    np.testing.assert_allclose(got[np.isfinite(got)], want[np.isfinite(want)], rtol=0, atol=1e-4)


def test_local_consistency_min_spread_votes_only_near_discontinuities():
    # Two noisy flat surfaces (3.3 and 9.7 px ± 0.2) meeting at column 20: with min_spread 2 only pixels
    # whose 7×7 window reaches across the edge (columns 17..22) are voted on; the rest keep
    # their exact input value and confidence 1. The voted pixels get what the full vote gives.
    from stereocli.match.refine_segment import LocalConsistencyParams, local_consistency

    rng = np.random.default_rng(3)
    h, w = 12, 40
    disp = (np.where(np.arange(w) < 20, 3.3, 9.7) + rng.uniform(-0.2, 0.2, (h, w))).astype(np.float32)
    left = rng.integers(0, 256, (h, w, 3)).astype(np.float32)
    right = rng.integers(0, 256, (h, w, 3)).astype(np.float32)

    def run(min_spread):
        state = MatchState(left=left, right=right, min_disp=0, ndisp=16)
        state.disparity = disp.copy()
        local_consistency(state, LocalConsistencyParams(radius=3, min_spread=min_spread))
        return state.disparity, state.confidence

    full, _ = run(0.0)
    banded, conf = run(2.0)
    band = np.zeros(w, bool)
    band[17:23] = True
    np.testing.assert_array_equal(banded[:, ~band], disp[:, ~band])
    assert np.all(conf[:, ~band] == 1.0)
    np.testing.assert_array_equal(banded[:, band], full[:, band])
    assert not np.array_equal(full[:, ~band], disp[:, ~band])  # the full vote does change them
