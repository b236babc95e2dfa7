"""Segmentation-based refinements: plane fitting (RANSAC / histogram) and local consistency."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from stereocli import registry
from stereocli.matching.config import build_config
from stereocli.matching.pipeline import match_pair
from stereocli.matching.refine_segment import PlaneFitParams, fit_segment_planes, segment_image
from stereocli.matching.state import MatchState
from test_kernels_sgm import on_one_and_two_threads

A, B, C = 0.06, 0.03, 6.0  # slanted plane d = A·x + B·y + C (left-referenced)


def slanted_scene(h: int = 90, w: int = 120, seed: int = 0):
    """A textured slanted plane rendered exactly in both views (bicubic resampling).

    Left pixel (x, y) sees texture point (x, y); with d = A·x + B·y + C it lands on
    x_r = x − d, so the right image at x_r samples the texture at x = (x_r + B·y + C)/(1 − A).
    """
    rng = np.random.default_rng(seed)
    tex = cv2.resize(rng.random((h // 4 + 4, w // 4 + 4)).astype(np.float32) * 200 + 20, (w * 2, h * 2),
                     interpolation=cv2.INTER_CUBIC)
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


def test_pixels_by_segment_is_a_stable_sort_of_the_labels():
    from stereocli.matching.kernels.segment_planes import pixels_by_segment

    rng = np.random.default_rng(4)
    labels = rng.integers(0, 9, (23, 31)).astype(np.int32)
    labels[labels == 5] = 4  # a label with no pixel
    order, starts, counts = pixels_by_segment(labels)
    np.testing.assert_array_equal(order, np.argsort(labels.ravel(), kind="stable"))
    np.testing.assert_array_equal(counts, np.bincount(labels.ravel(), minlength=9))
    np.testing.assert_array_equal(starts, np.concatenate(([0], np.cumsum(counts))))
    assert counts[5] == 0 and starts[5] == starts[6]


def test_ransac_is_reproducible_with_a_seed():
    rng = np.random.default_rng(2)
    disp = rng.uniform(0, 20, (40, 50)).astype(np.float32)
    labels = np.zeros((40, 50), np.int32)
    p = PlaneFitParams(seed=7, iterations=20)
    first = fit_segment_planes(disp, labels, p)[0]
    np.testing.assert_array_equal(first, fit_segment_planes(disp, labels, p)[0])
    other = fit_segment_planes(disp, labels, PlaneFitParams(seed=8, iterations=20))[0]
    assert not np.array_equal(first, other)


def _label_regions_reference(img: np.ndarray, tolerance: float, min_size: int) -> np.ndarray:
    """label_regions by its definition: union-find over 4-neighbour links of similar colour in
    raster order, then, in raster order of the links, merging of components under min_size;
    labels in raster order of first appearance."""
    h, w, _ = img.shape
    parent = list(range(h * w))
    size = [1] * (h * w)

    def find(i):
        while parent[i] != i:
            i = parent[i]
        return i

    def union(a, b):
        ra, rb = find(a), find(b)
        if ra != rb:
            parent[rb] = ra
            size[ra] += size[rb]

    links = [(y * w + x, (y + dy) * w + x + dx) for y in range(h) for x in range(w)
             for dy, dx in ((0, 1), (1, 0)) if y + dy < h and x + dx < w]
    for i, j in links:
        if np.abs(img.reshape(-1, img.shape[2])[i] - img.reshape(-1, img.shape[2])[j]).max() <= tolerance:
            union(i, j)
    for i, j in links:
        ri, rj = find(i), find(j)
        if ri != rj and (size[ri] < min_size or size[rj] < min_size):
            union(ri, rj)
    first: dict[int, int] = {}
    return np.array([first.setdefault(find(i), len(first)) for i in range(h * w)], np.int32).reshape(h, w)


@pytest.mark.parametrize("tolerance, min_size", [(0.0, 1), (1.0, 1), (1.0, 4), (2.0, 10)])
def test_label_regions_matches_its_definition(tolerance, min_size):
    from stereocli.matching.kernels.segment_planes import label_regions

    rng = np.random.default_rng(int(tolerance * 10) + min_size)
    # Blocky colours (large components) plus noise of 0-2 levels (links that hold or break).
    blocks = np.repeat(np.repeat(rng.integers(0, 4, (6, 8, 3)) * 10, 5, axis=0), 5, axis=1)
    img = (blocks + rng.integers(0, 3, blocks.shape)).astype(np.float32)
    np.testing.assert_array_equal(label_regions(img, tolerance, min_size),
                                  _label_regions_reference(img, tolerance, min_size))


@pytest.mark.parametrize("smoothing", ["bilateral", "mean_shift"])
def test_segmentation_separates_colours_and_fits_each_plane(smoothing):
    h, w = 60, 80
    image = np.zeros((h, w, 3), np.float32)
    image[:, :40] = (200, 40, 40)
    image[:, 40:] = (30, 60, 220)
    # Noise the smoothing has to remove: raw pixels differ from their neighbours by up to 12
    # grey levels, far beyond the tolerance of 4 that grows the segments.
    image += np.random.default_rng(3).uniform(-6, 6, image.shape).astype(np.float32)
    labels = segment_image(image, 5, 10.0, 4.0, 20, smoothing)
    assert labels[0, 0] != labels[0, -1] and len(np.unique(labels)) == 2
    ys, xs = np.mgrid[0:h, 0:w]
    gt = np.where(xs < 40, 5.0 + 0.05 * xs, 20.0 - 0.02 * ys).astype(np.float32)
    disp = gt.copy()
    disp[::7, ::5] = np.inf
    disp[5:15, 30:50] = 3.0  # a wrong blob straddling both segments
    state = _state(disp, image)
    registry.get("refinement", "plane_fit").func(state, PlaneFitParams(replace="outliers", segmentation=smoothing))
    wrong = np.abs(state.disparity - gt) > 0.02
    # the smoothing may move a few pixels at the colour edge into the other segment
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
    local_consistency = registry.get("refinement", "local_consistency")
    local_consistency.func(state, local_consistency.make_params({}))
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
                    wgt = np.exp(-np.hypot(yy - y, xx - x) / gamma_s
                                 - np.abs(left[y, x] - left[yy, xx]).mean() / gamma_c)
                    xf, xg = int(np.floor(x - dg + 0.5)), int(np.floor(xx - dg + 0.5))
                    inside = 0 <= xf < w and 0 <= xg < w
                    dt = np.abs(right[y, xf] - right[yy, xg]).mean() if inside else 255.0
                    wgt *= np.exp(-dt / gamma_t)
                    mass[k] = mass.get(k, 0.0) + wgt
                    sumd[k] = sumd.get(k, 0.0) + wgt * dg
            best = min(mass, key=lambda k: (-mass[k], k))  # most support, smaller disparity on ties
            out[y, x] = sumd[best] / mass[best]
    return out


def _two_surface_problem(rng, h: int, w: int, split: int):
    # Random 8-bit-valued colour images (the kernel's colour tables are exact there) and noisy
    # disparities of two surfaces, 2-4 px up to column ``split`` and 7-9 px beyond it.
    left = rng.integers(0, 256, (h, w, 3)).astype(np.float32)
    right = rng.integers(0, 256, (h, w, 3)).astype(np.float32)
    disp = (rng.uniform(2, 4, (h, w)) + np.where(np.arange(w) > split, 5.0, 0.0)).astype(np.float32)
    return left, right, disp


def test_local_consistency_kernel_matches_reference_on_random_maps():
    # 8-bit-valued colour images (the kernel's colour tables are exact there), noisy disparities
    # with holes and two surfaces.
    from stereocli.matching.kernels import local_consistency as klc

    rng = np.random.default_rng(11)
    h, w = 16, 21
    left, right, disp = _two_surface_problem(rng, h, w, 10)
    disp[rng.random((h, w)) < 0.1] = np.inf
    got, _ = klc.local_consistency(disp, left, right, 0, 12, 3, 3.0, 12.0, 12.0, False, np.ones(disp.shape, bool))
    want = local_consistency_reference(disp, left, right, 0, 12, 3, 3.0, 12.0, 12.0)
    np.testing.assert_array_equal(np.isfinite(got), np.isfinite(want))
    np.testing.assert_allclose(got[np.isfinite(got)], want[np.isfinite(want)], rtol=0, atol=1e-4)


def test_local_consistency_min_spread_votes_only_near_discontinuities():
    # Two noisy flat surfaces (3.3 and 9.7 px ± 0.2) meeting at column 20: with min_spread 2 only pixels
    # whose 7×7 window reaches across the edge (columns 17..22) are voted on; the rest keep
    # their exact input value and confidence 1. The voted pixels get what the full vote gives.
    from stereocli.matching.refine_segment import LocalConsistencyParams, local_consistency

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


def line_vote_reference(disp, left, right, min_disp, ndisp, radius, gamma_s, gamma_c, gamma_t, min_change,
                        band, vertical):
    """One pass of the separable vote, pixel by pixel with exp per vote (the kernel's tables
    are exact for 8-bit-valued images): centres are the valid pixels with a bin at least
    ``min_change`` away within ``band`` along the line; votes come from the segment."""
    h, w, c = left.shape
    out = disp.copy()

    def bin_of(d):
        return int(np.floor(d - min_disp + 0.5)) if np.isfinite(d) and 0 <= np.floor(d - min_disp + 0.5) < ndisp else -1

    for y in range(h):
        for x in range(w):
            own = bin_of(disp[y, x])
            if own < 0:
                continue
            line = [(y + t, x) if vertical else (y, x + t) for t in range(-radius, radius + 1)]
            line = [(t, gy, gx) for t, (gy, gx) in zip(range(-radius, radius + 1), line) if 0 <= gy < h and 0 <= gx < w]
            if min_change > 0 and not any(abs(t) <= band and bin_of(disp[gy, gx]) >= 0
                                          and abs(bin_of(disp[gy, gx]) - own) >= min_change for t, gy, gx in line):
                continue
            mass, sumd = {}, {}
            for t, gy, gx in line:
                k = bin_of(disp[gy, gx])
                if k < 0:
                    continue
                wgt = np.exp(-abs(t) / gamma_s - np.abs(left[y, x] - left[gy, gx]).mean() / gamma_c)
                kd = k + min_disp
                inside = 0 <= x - kd < w and 0 <= gx - kd < w
                dt = np.abs(right[y, x - kd] - right[gy, gx - kd]).mean() if inside else 255.0
                wgt *= np.exp(-dt / gamma_t)
                mass[k] = mass.get(k, 0.0) + wgt
                sumd[k] = sumd.get(k, 0.0) + wgt * float(disp[gy, gx])
            best = min(mass, key=lambda k: (-mass[k], k))
            if abs(best - own) >= min_change:
                out[y, x] = sumd[best] / mass[best]
    return out


@pytest.mark.parametrize("min_change,channels,right", [(0, 3, True), (2, 3, True), (2, 1, True), (0, 3, False)])
def test_separable_local_consistency_matches_reference(min_change, channels, right):
    # Rows, then columns of the result, on noisy random maps with holes, two surfaces and a
    # range that starts below zero; colour (or grey) images with 8-bit values.
    from stereocli.matching.refine_segment import LocalConsistencyParams, local_consistency

    rng = np.random.default_rng(5)
    h, w = 17, 23
    left = rng.integers(0, 256, (h, w, channels)).astype(np.float32)
    right_image = rng.integers(0, 256, (h, w, channels)).astype(np.float32)
    disp = (rng.uniform(-1, 2, (h, w)) + np.where(np.arange(w) > 11, 6.0, 0.0)).astype(np.float32)
    disp[rng.random((h, w)) < 0.1] = np.inf
    p = LocalConsistencyParams(separable=True, radius=4, gamma_s=4.0, band=2, min_change=min_change, right=right)
    state = MatchState(left if channels == 3 else left[..., 0], right_image if channels == 3 else right_image[..., 0],
                       -2, 14)
    state.disparity = disp.copy()
    local_consistency(state, p)
    want = disp.copy()
    for vertical in (False, True):
        # No right-image term = every match weight exp(−Δ/∞) = 1.
        want = line_vote_reference(want, left, right_image, -2, 14, 4, 4.0, 12.0, 12.0 if right else np.inf,
                                   min_change, 2, vertical)
    np.testing.assert_array_equal(np.isfinite(state.disparity), np.isfinite(disp))
    fin = np.isfinite(want)
    np.testing.assert_allclose(state.disparity[fin], want[fin], rtol=0, atol=1e-4)
    assert not np.array_equal(state.disparity[fin], disp[fin])  # the vote did move some pixels
    assert ((state.confidence > 0) & (state.confidence <= 1))[fin].all() and (state.confidence[~fin] == 0).all()


def test_separable_local_consistency_moves_fattened_edges_and_keeps_slants():
    # A foreground square (disparity 12) fattened by 3 px to the right and 2 px downwards onto a
    # slanted background (sub-pixel values 3.0..5.4): the separable vote with min_change 2 puts
    # the disparity edges back on the colour edges and leaves every background value as it was.
    from stereocli.matching.refine_segment import LocalConsistencyParams, local_consistency

    h, w = 40, 60
    image = np.full((h, w, 3), 60, np.float32)
    image[10:25, 20:35] = 200  # the foreground square in the left image
    background = (3.0 + 0.04 * np.arange(w)[None, :] + 0.0 * np.arange(h)[:, None]).astype(np.float32)
    truth = background.copy()
    truth[10:25, 20:35] = 12.0
    fattened = background.copy()
    fattened[10:27, 20:38] = 12.0
    state = MatchState(image, image, 0, 16)  # right view = left: the match term is uniform
    state.disparity = fattened.copy()
    local_consistency(state, LocalConsistencyParams(separable=True, radius=8, gamma_s=8.0, band=4, min_change=2,
                                                    gamma_t=1000.0))
    np.testing.assert_array_equal(state.disparity[10:25, 20:35], 12.0)
    moved = (fattened == 12.0) & (truth != 12.0)
    assert moved.sum() == 17 * 18 - 15 * 15
    # Moved pixels take the weighted mean of the background bin that won: within 0.5 px of truth.
    assert np.abs(state.disparity[moved] - truth[moved]).max() < 0.5
    np.testing.assert_array_equal(state.disparity[fattened != 12.0], truth[fattened != 12.0])


def test_local_consistency_min_change_keeps_sub_pixel_values():
    # A slanted plane whose 1-px bins change every 10 px: with min_change 2 no pixel moves (the
    # winning bin is never 2 bins away); with 0 every voted pixel takes its bin's mean.
    from stereocli.matching.refine_segment import LocalConsistencyParams, local_consistency

    h, w = 12, 50
    rng = np.random.default_rng(2)
    image = rng.integers(0, 256, (h, w, 3)).astype(np.float32)
    disp = np.tile((4.0 + 0.1 * np.arange(w)).astype(np.float32), (h, 1))
    for separable in (False, True):
        kept = MatchState(image, image, 0, 16)
        kept.disparity = disp.copy()
        local_consistency(kept, LocalConsistencyParams(radius=3, separable=separable, min_change=2))
        np.testing.assert_array_equal(kept.disparity, disp)
        moved = MatchState(image, image, 0, 16)
        moved.disparity = disp.copy()
        local_consistency(moved, LocalConsistencyParams(radius=3, separable=separable, min_change=0))
        assert not np.array_equal(moved.disparity, disp)


def test_local_consistency_separable_rejects_fill_invalid_and_multiplies_confidence():
    from stereocli.errors import ConfigError
    from stereocli.matching.refine_segment import LocalConsistencyParams, local_consistency

    with pytest.raises(ConfigError, match="fill_invalid needs the square window"):
        registry.get("refinement", "local_consistency").make_params({"separable": True, "fill_invalid": True})
    h, w = 10, 30
    image = np.full((h, w, 3), 90, np.float32)
    disp = np.full((h, w), 5.0, np.float32)
    disp[:, 15:] = 9.0
    state = MatchState(image, image, 0, 16)
    state.disparity = disp
    state.confidence = np.full((h, w), 0.5, np.float32)  # e.g. from the confidence stage
    local_consistency(state, LocalConsistencyParams(separable=True, radius=5, min_change=2))
    # Far from the edge nothing is voted on (share 1): the earlier map is kept; at the edge it
    # is multiplied by the winning share (< 1: both surfaces vote).
    assert (state.confidence[:, :8] == 0.5).all()
    assert (state.confidence[:, 14] < 0.5).all()


def test_square_local_consistency_without_right_term_matches_reference():
    from stereocli.matching.refine_segment import LocalConsistencyParams, local_consistency

    rng = np.random.default_rng(8)
    h, w = 14, 19
    left, right, disp = _two_surface_problem(rng, h, w, 9)
    state = MatchState(left, right, 0, 12)
    state.disparity = disp.copy()
    local_consistency(state, LocalConsistencyParams(radius=3, gamma_s=3.0, right=False))
    want = local_consistency_reference(disp, left, right, 0, 12, 3, 3.0, 12.0, np.inf)
    np.testing.assert_allclose(state.disparity, want, rtol=0, atol=1e-4)
    with_right = local_consistency_reference(disp, left, right, 0, 12, 3, 3.0, 12.0, 12.0)
    assert not np.allclose(want, with_right, atol=1e-3)  # the right term does matter on these maps


def test_separable_local_consistency_is_deterministic_across_thread_counts():
    from stereocli.matching.refine_segment import LocalConsistencyParams, local_consistency

    rng = np.random.default_rng(4)
    h, w = 60, 90
    left = rng.integers(0, 256, (h, w, 3)).astype(np.float32)
    right = rng.integers(0, 256, (h, w, 3)).astype(np.float32)
    disp = (rng.uniform(0, 3, (h, w)) + np.where((np.arange(w) // 15) % 2 == 1, 8.0, 0.0)).astype(np.float32)
    p = LocalConsistencyParams(separable=True, radius=8, gamma_s=8.0, band=3, min_change=2)

    def run():
        state = MatchState(left, right, 0, 16)
        state.disparity = disp.copy()
        local_consistency(state, p)
        return state.disparity, state.confidence

    results = on_one_and_two_threads(run)
    np.testing.assert_array_equal(results[0][0], results[1][0])
    np.testing.assert_array_equal(results[0][1], results[1][1])
    assert not np.array_equal(results[0][0], disp)


def geodesic_reference(disp, image, min_disp, ndisp, gamma_s, gamma_c, band, min_change, min_lead=1.0,
                       lines="both"):
    """The geodesic vote by its definition, pixel by pixel: rows, then columns of the result
    (or one of the two passes). Exact sums over the whole line (the kernel keeps the 3
    strongest bins of each running vote; with at most 3 bins on a line that is the same)."""
    c = image.shape[2]

    def bin_of(d):
        if not np.isfinite(d):
            return -1
        k = int(np.floor(d - min_disp + 0.5))
        return k if 0 <= k < ndisp else -1

    def one_pass(src, vertical):
        out = src.copy()
        h, w = src.shape
        for line in range(w if vertical else h):
            idx = [(p, line) if vertical else (line, p) for p in range(h if vertical else w)]
            bins = [bin_of(src[i]) for i in idx]
            q = np.round(image[tuple(np.array(idx).T)] * 4).astype(np.int64)  # quarter levels
            steps = [1.0] + [np.exp(-1.0 / gamma_s - np.abs(q[p] - q[p - 1]).sum() * 0.25 / c / gamma_c)
                             for p in range(1, len(idx))]
            for f, own in enumerate(bins):
                if own < 0 or not any(b >= 0 and abs(b - own) >= min_change
                                      for b in bins[max(0, f - band): f + band + 1]):
                    continue
                mass, total = {}, {}
                for g, b in enumerate(bins):
                    if b < 0:
                        continue
                    wgt = np.prod(steps[min(f, g) + 1: max(f, g) + 1])
                    mass[b] = mass.get(b, 0.0) + wgt
                    total[b] = total.get(b, 0.0) + wgt * float(src[idx[g]])
                best = min(mass, key=lambda b: (-mass[b], b))
                if abs(best - own) >= min_change and mass[best] >= min_lead * mass[own]:
                    out[idx[f]] = total[best] / mass[best]
        return out

    out = disp
    for vertical in {"both": (False, True), "rows": (False,), "columns": (True,)}[lines]:
        out = one_pass(out, vertical)
    return out


@pytest.mark.parametrize("seed, min_lead, lines", [(0, 1.0, "both"), (1, 1.0, "both"), (0, 1.5, "rows"),
                                                    (1, 1.5, "columns"), (3, 1.5, "both")])
def test_geodesic_vote_matches_reference(seed, min_lead, lines):
    from stereocli.matching.refine_segment import GeodesicVoteParams, geodesic_vote

    rng = np.random.default_rng(seed)
    h, w = 14, 19
    image = rng.integers(0, 256, (h, w, 3)).astype(np.float32)
    # Three surfaces (1-px bins 2, 6 and 10 with noise inside each bin) and some holes.
    level = rng.integers(0, 3, (h, w))
    disp = (2.0 + 4.0 * level + rng.uniform(-0.4, 0.4, (h, w))).astype(np.float32)
    disp[rng.random((h, w)) < 0.08] = np.inf
    p = GeodesicVoteParams(gamma_s=6.0, gamma_c=150.0, band=2, min_change=2, max_bins=3, min_lead=min_lead,
                           lines=lines)
    state = MatchState(image, image, 0, 16)
    state.disparity = disp.copy()
    geodesic_vote(state, p)
    want = geodesic_reference(disp, image, 0, 16, 6.0, 150.0, 2, 2, min_lead, lines)
    np.testing.assert_array_equal(np.isfinite(state.disparity), np.isfinite(disp))  # holes neither vote nor move
    fin = np.isfinite(want)
    np.testing.assert_allclose(state.disparity[fin], want[fin], rtol=0, atol=1e-4)
    assert not np.array_equal(state.disparity[fin], disp[fin])  # some pixels did move
    if min_lead > 1:  # ... and the lead kept some that a plain majority would have moved
        plain = geodesic_reference(disp, image, 0, 16, 6.0, 150.0, 2, 2, 1.0, lines)
        assert not np.array_equal(plain[fin], want[fin])


@pytest.mark.parametrize("min_lead", [1.0, 2.5])
def test_geodesic_vote_moves_fattened_edges_and_keeps_slants(min_lead):
    # A foreground square (disparity 12) fattened by 3 px to the right and 2 px downwards onto
    # a slanted background (3.0..5.4 px): every fattened pixel goes back to the background
    # (the mean of the background bin most of its colour-connected row or column holds: within
    # 1.5 px on this slant, from 7.6–9 px off); the square and the rest stay exactly. The
    # fattened pixels' own bin reaches them only across the colour edge, so a required lead
    # of 2.5 moves them too.
    from stereocli.matching.refine_segment import GeodesicVoteParams, geodesic_vote

    h, w = 40, 60
    image = np.full((h, w, 3), 60, np.float32)
    image[10:25, 20:35] = 200
    background = np.tile((3.0 + 0.04 * np.arange(w)).astype(np.float32), (h, 1))
    truth = background.copy()
    truth[10:25, 20:35] = 12.0
    fattened = background.copy()
    fattened[10:27, 20:38] = 12.0
    state = MatchState(image, image, 0, 16)
    state.disparity = fattened.copy()
    geodesic_vote(state, GeodesicVoteParams(band=4, min_lead=min_lead))
    np.testing.assert_array_equal(state.disparity[10:25, 20:35], 12.0)
    moved = (fattened == 12.0) & (truth != 12.0)
    assert np.abs(state.disparity[moved] - truth[moved]).max() < 1.5
    np.testing.assert_array_equal(state.disparity[fattened != 12.0], truth[fattened != 12.0])


def test_geodesic_vote_is_deterministic_across_thread_counts():
    from stereocli.matching.refine_segment import GeodesicVoteParams, geodesic_vote

    # Stripes of two colours with disparity edges 2 px off the colour edges, plus noise.
    rng = np.random.default_rng(6)
    h, w = 50, 80
    stripe = (np.arange(w) // 13) % 2 == 1
    image = np.where(stripe[None, :, None], 180.0, 70.0) + rng.normal(0, 4, (h, w, 3))
    image = image.astype(np.float32)
    disp = (rng.uniform(0, 0.8, (h, w)) + np.where(np.roll(stripe, 2), 9.0, 2.0)).astype(np.float32)

    def run():
        state = MatchState(image, image, 0, 16)
        state.disparity = disp.copy()
        geodesic_vote(state, GeodesicVoteParams())
        return state.disparity

    results = on_one_and_two_threads(run)
    np.testing.assert_array_equal(results[0], results[1])
    assert not np.array_equal(results[0], disp)
