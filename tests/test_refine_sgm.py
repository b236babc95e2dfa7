"""Refinement stages one by one on tiny hand-made inputs (uniqueness, confidence, speckle,
interpolation, median, bilateral; sub-pixel and LR check on uint16 volumes)."""

from __future__ import annotations

import numpy as np
import pytest

from stereocli import registry
from stereocli.matching.state import MatchState

INF = np.float32(np.inf)


def stage(name: str, **params):
    s = registry.get("refinement", name)
    return s, s.make_params(params)


def make_state(disp, cost=None, right=None, min_disp=0, image=None) -> MatchState:
    h, w = disp.shape
    img = np.zeros((h, w), np.float32) if image is None else image
    st = MatchState(img, img, min_disp, 1 if cost is None else cost.shape[2])
    st.disparity = np.asarray(disp, np.float32)
    st.cost = cost
    st.disparity_right = None if right is None else np.asarray(right, np.float32)
    return st


@pytest.mark.parametrize("dtype", [np.float32, np.uint16])
def test_uniqueness(dtype):
    cost = np.zeros((1, 8, 5), dtype)
    cost[0, 7] = [50, 10, 12, 60, 11]  # runner-up (d=4) is 2 px away and within 10 %: ambiguous
    cost[0, 6] = [50, 10, 11, 60, 40]  # runner-up adjacent (d=2) is ignored: unique
    disp = np.array([[0, 0, 0, 0, 0, 0, 1, 1]], np.float32)
    s, p = stage("uniqueness", ratio=0.1)
    st = make_state(disp, cost)
    s.func(st, p)
    assert st.disparity[0, 6] == 1 and st.disparity[0, 7] == INF


def test_uniqueness_ratio_zero_keeps_strict_winners():
    cost = np.zeros((1, 8, 5), np.float32)
    cost[0, 7] = [50, 10, 12, 60, 11]
    s, p = stage("uniqueness", ratio=0.0)
    st = make_state(np.full((1, 8), 1, np.float32), cost)
    s.func(st, p)
    assert st.disparity[0, 7] == 1


@pytest.mark.parametrize("dtype", [np.float32, np.uint16])
def test_subpixel_on_both_dtypes(dtype):
    cost = np.zeros((1, 8, 5), dtype)
    cost[0, 7] = [10, 4, 3, 5, 9]
    s, p = stage("subpixel", method="parabola")
    st = make_state(np.full((1, 8), 2, np.float32), cost)
    s.func(st, p)
    assert st.disparity[0, 7] == pytest.approx(2.0 + 0.5 * (4 - 5) / (4 - 2 * 3 + 5), abs=1e-6)


def test_confidence_range_and_ordering():
    cost = np.zeros((1, 10, 6), np.float32)
    cost[0, 8] = [90, 90, 5, 90, 90, 90]  # clear winner
    cost[0, 9] = [50, 50, 48, 50, 49, 50]  # flat: ambiguous
    disp = np.full((1, 10), INF, np.float32)
    disp[0, 8] = disp[0, 9] = 2
    right = np.full((1, 10), 2, np.float32)
    s, p = stage("confidence")
    st = make_state(disp, cost, right)
    s.func(st, p)
    assert st.confidence is None  # nobody asked for the map: the stage is skipped
    st.wants.confidence = True
    s.func(st, p)
    c = st.confidence
    assert c.dtype == np.float32 and c.shape == (1, 10)
    assert c[0, 8] == pytest.approx(1.0) and 0 <= c[0, 9] < 0.5
    assert np.all(c[0, :8] == 0)  # invalid pixels
    st.disparity_right = np.full((1, 10), 4, np.float32)  # LR disagreement by 2 px
    s.func(st, p)
    assert st.confidence[0, 8] == pytest.approx(np.exp(-2.0), rel=1e-5)


def test_speckle_removes_small_regions_only():
    disp = np.full((10, 10), 3.0, np.float32)
    disp[2:4, 2:4] = 9.0  # 4-pixel island
    disp[6, 6] = INF
    s, p = stage("speckle", max_size=5, max_diff=1.0)
    st = make_state(disp)
    s.func(st, p)
    assert np.all(np.isinf(st.disparity[2:4, 2:4]))
    assert np.isinf(st.disparity[6, 6])
    assert np.isfinite(st.disparity).sum() == 100 - 5
    assert st.disparity[0, 0] == 3.0


def test_interpolate_occlusion_takes_background_mismatch_takes_median():
    # Row: background 2 | hole | foreground 8. Right view: nothing maps back to the hole
    # -> occluded -> background (second lowest of the 8-direction neighbours).
    disp = np.array([[2, 2, 2, INF, 8, 8, 8]] * 3, np.float32)
    right = np.full((3, 7), INF, np.float32)
    s, p = stage("interpolate")
    st = make_state(disp, right=right)
    st.ndisp = 10
    s.func(st, p)
    assert np.all(st.disparity[:, 3] == 2)
    # Mismatch: right pixel x - d = 3 - 1 = 2 says d = 1, so the hole is seen -> median.
    disp = np.array([[2, 2, 2, INF, 8, 8, 8]] * 3, np.float32)
    right = np.full((3, 7), INF, np.float32)
    right[:, 2] = 1
    st = make_state(disp, right=right)
    st.ndisp = 10
    s.func(st, p)
    assert np.all(st.disparity[1, 3] == 5)  # median of {2, 8, 2, 8, 2, 2, 8, 8}: 5


def test_interpolate_is_flagged_as_filling():
    assert registry.get("refinement", "interpolate").traits.fills_holes
    assert registry.get("refinement", "fill").traits.fills_holes
    assert not registry.get("refinement", "median").traits.fills_holes


def _median_of_finite_reference(disp: np.ndarray, radius: int) -> np.ndarray:
    """Pure-numpy reference: median of the finite values in each window; holes stay holes."""
    out = disp.copy()
    h, w = disp.shape
    for y in range(h):
        for x in range(w):
            if np.isfinite(disp[y, x]):
                win = disp[max(0, y - radius):y + radius + 1, max(0, x - radius):x + radius + 1]
                out[y, x] = np.median(win[np.isfinite(win)])
    return out


def test_median_ignores_holes_and_matches_reference():
    rng = np.random.default_rng(0)
    disp = rng.random((9, 11)).astype(np.float32) * 10
    disp[rng.random((9, 11)) < 0.2] = INF
    s, p = stage("median", size=3)
    st = make_state(disp.copy())
    s.func(st, p)
    np.testing.assert_array_equal(st.disparity, _median_of_finite_reference(disp, 1))


@pytest.mark.parametrize("threads", [1, 2])
@pytest.mark.parametrize("size", [3, 5, 7])
@pytest.mark.parametrize("shape", [(48, 57), (5, 40), (90, 7)])
def test_median_matches_reference_dense_or_with_holes(size, shape, threads):
    # Dense maps take OpenCV's median in two row bands (tall enough maps) plus the border
    # kernel, maps with holes also the kernel near them, 7x7 the general kernel everywhere:
    # every path gives the reference's values, whatever the thread count.
    from stereocli.matching.kernels import refine as kr
    from stereocli.matching.kernels import set_threads

    rng = np.random.default_rng(size)
    set_threads(threads)
    try:
        for holes in (0.0, 0.1):
            disp = (rng.random(shape) * 60).astype(np.float32)
            disp[rng.random(shape) < holes] = INF
            np.testing.assert_array_equal(kr.median_valid(disp, size // 2),
                                          _median_of_finite_reference(disp, size // 2))
    finally:
        set_threads(0)


def test_bilateral_keeps_edges_and_holes():
    disp = np.array([[1, 1, 1, 9, 9, 9]] * 4, np.float32)
    disp[0, 0] = INF
    image = np.array([[0, 0, 0, 200, 200, 200]] * 4, np.float32)
    s, p = stage("bilateral", radius=2, sigma_space=2.0, sigma_color=5.0)
    st = make_state(disp.copy(), image=image)
    s.func(st, p)
    assert np.isinf(st.disparity[0, 0])
    np.testing.assert_allclose(st.disparity[1:, :3], 1.0, atol=1e-3)
    np.testing.assert_allclose(st.disparity[1:, 3:], 9.0, atol=1e-3)
