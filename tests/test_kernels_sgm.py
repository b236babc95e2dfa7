"""The compiled SGM kernels against a tiny pure-numpy reference of Hirschmüller 2008 eq. 13."""

from __future__ import annotations

import numpy as np
import pytest

from stereocli.matching.kernels import sgm as ks


def _penalty(i0: float, i1: float, p1: int, p2: int, gamma: float) -> int:
    if gamma <= 0:
        return p2
    return max(int(p2 * gamma / (gamma + abs(i0 - i1))), p1)


def reference_sgm(cq: np.ndarray, guide: np.ndarray, paths: int, p1: int, p2: int, gamma: float,
                  lo: np.ndarray | None = None, hi: np.ndarray | None = None) -> np.ndarray:
    """Sum over directions r of L_r(p, d) = C(p, d) + min(L_r(p−r, d), L_r(p−r, d±1) + P1,
    min_k L_r(p−r, k) + P2) − min_k L_r(p−r, k); paths start where p − r leaves the image.

    With per-pixel windows ``[lo, hi)`` (the coarse-to-fine search) L_r is +∞ outside a
    pixel's window and the sums are 65535 there."""
    h, w, nd = cq.shape
    big = 10**9
    inwin = np.ones((h, w, nd), bool)
    if lo is not None:
        k = np.arange(nd)[None, None, :]
        inwin = (k >= lo[..., None]) & (k < hi[..., None])
    down = [tuple(r) for r in ks.DOWN_DIRECTIONS[paths]]
    offsets = [(0, 1), (0, -1)] + down + [(-dy, -dx) for dy, dx in down]
    total = np.zeros((h, w, nd), np.int64)
    for ry, rx in offsets:
        lr = np.full((h, w, nd), big, np.int64)
        ys = range(h) if ry >= 0 else range(h - 1, -1, -1)
        xs = list(range(w)) if rx >= 0 else list(range(w - 1, -1, -1))
        for y in ys:
            for x in xs:
                c = cq[y, x].astype(np.int64)
                yp, xp = y - ry, x - rx
                if not (0 <= yp < h and 0 <= xp < w):
                    val = c
                else:
                    prev = lr[yp, xp]
                    m = prev.min()
                    pen2 = _penalty(float(guide[y, x]), float(guide[yp, xp]), p1, p2, gamma)
                    up = np.concatenate([prev[1:], [big]])
                    dn = np.concatenate([[big], prev[:-1]])
                    val = c + np.minimum.reduce([prev, up + p1, dn + p1, np.full(nd, m + pen2)]) - m
                lr[y, x] = np.where(inwin[y, x], val, big)
        total += np.where(inwin, lr, 0)
    return np.where(inwin, total, 65535)


@pytest.mark.parametrize("paths", [2, 4, 8, 16])
@pytest.mark.parametrize("gamma", [0.0, 4.0])
def test_sgm_kernel_equals_reference(paths, gamma):
    rng = np.random.default_rng(paths)
    cq = rng.integers(0, 40, (12, 16, 5)).astype(np.uint8)
    guide = rng.integers(0, 255, (12, 16)).astype(np.float32)
    s, disp, right = ks.sgm_aggregate(cq, guide, paths, 3, 20, gamma, 0, True)
    ref = reference_sgm(cq, guide, paths, 3, 20, gamma)
    assert s.dtype == np.uint16
    np.testing.assert_array_equal(s.astype(np.int64), ref)
    # WTA restricted to in-image hypotheses (x - d >= 0), ties to the smaller disparity.
    for x in range(16):
        k1 = min(4, x)
        np.testing.assert_array_equal(disp[:, x], np.argmin(ref[:, x, : k1 + 1], axis=1))


def test_sgm_uint16_costs_and_negative_min_disp():
    rng = np.random.default_rng(5)
    cq = rng.integers(0, 600, (6, 9, 4)).astype(np.uint16)
    guide = np.zeros((6, 9), np.float32)
    s, disp, _ = ks.sgm_aggregate(cq, guide, 8, 10, 90, 0.0, -2)
    np.testing.assert_array_equal(s.astype(np.int64), reference_sgm(cq, guide, 8, 10, 90, 0.0))
    # min_disp = -2: hypotheses k = 0..3 are d = -2..1; at x = 8 (last column) d = -2 would
    # land at x_r = 10 outside the image, so only k >= 1 compete there.
    assert np.all(disp[:, 8] >= -1)
    assert np.all(np.isfinite(disp))


@pytest.mark.parametrize("min_disp", [0, -3, 4])
@pytest.mark.parametrize("height", [1, 5, 8])
def test_sgm_right_view_and_cost_multiplier_match_reference(min_disp, height):
    # The right-view WTA is taken while the backward pass finishes each row: it must equal
    # the volume-level WTA (stereocli.matching.kernels.winners.wta_right) on the final sums, for
    # odd/even/single-row heights (the two stripes split the rows at H // 2).
    from stereocli.matching.kernels.winners import wta_right

    rng = np.random.default_rng(height)
    cq = rng.integers(0, 20, (height, 14, 6)).astype(np.uint8)
    guide = rng.integers(0, 255, (height, 14)).astype(np.float32)
    s, disp, right = ks.sgm_aggregate(cq, guide, 8, 6, 40, 4.0, min_disp, True, cost_mul=3)
    ref = reference_sgm(cq.astype(np.int64) * 3, guide, 8, 6, 40, 4.0)
    np.testing.assert_array_equal(s.astype(np.int64), ref)
    np.testing.assert_array_equal(right, wta_right(s, min_disp, 65535.0))


def test_quantize_rounds_and_caps():
    cost = np.array([[[0.0, 0.49, 0.51, 10.0, 99.0]]], np.float32)
    out = np.empty(cost.shape, np.uint8)
    ks.quantize(cost, 2.0, 40, out)
    np.testing.assert_array_equal(out[0, 0], [0, 1, 1, 20, 40])


def _layered_costs(h: int, w: int, nd: int, seed: int):
    # Costs of a scene of two disparities (2 and 5 px) in blocks, with noise: the winners and
    # the path costs settle within a few rows of any change.
    rng = np.random.default_rng(seed)
    yy, xx = np.mgrid[0:h, 0:w]
    truth = 2 + 3 * ((xx // 5 + yy // 37) % 2)
    k = np.arange(nd)[None, None, :]
    cq = np.minimum(np.abs(k - truth[..., None]) * 4 + rng.integers(0, 6, (h, w, nd)), 30).astype(np.uint8)
    return cq, (truth * 40).astype(np.float32), truth


@pytest.mark.parametrize("height", [2, 3, 96, 201])
def test_sgm_row_stripes_equal_whole_image_passes(height):
    # Two threads share the passes over the two halves in two phases, each phase continuing
    # the other's paths: every path runs through the whole image, so the sums equal those of
    # whole-image passes exactly, also across the seam at H // 2 and on random costs, where a
    # path cut short anywhere would show.
    assert ks.STRIPES == 2
    rng = np.random.default_rng(height)
    cq = rng.integers(0, 40, (height, 16, 8)).astype(np.uint8)
    guide = rng.integers(0, 255, (height, 16)).astype(np.float32)
    s, disp, right = ks.sgm_aggregate(cq, guide, 8, 5, 40, 4.0, 0, True)
    np.testing.assert_array_equal(s.astype(np.int64), reference_sgm(cq, guide, 8, 5, 40, 4.0))
    cq, guide, truth = _layered_costs(height, 16, 8, 4)
    s, disp, _ = ks.sgm_aggregate(cq, guide, 4, 5, 40, 4.0, 0, False)
    np.testing.assert_array_equal(s.astype(np.int64), reference_sgm(cq, guide, 4, 5, 40, 4.0))
    inside = np.arange(16)[None, :] >= truth  # the true match lies inside the right image
    assert np.mean(disp[inside] == truth[inside]) > 0.95


def on_one_and_two_threads(run):
    """``[run(), run()]`` with the kernels on one thread, then on two (where available): numba's
    ``prange`` kernels and the chunk kernels' pool alike; the thread counts are restored afterwards."""
    import numba

    from stereocli import runtime

    old, old_chunks = numba.get_num_threads(), runtime.get_threads()
    results = []
    try:
        for threads in (1, min(2, numba.config.NUMBA_NUM_THREADS)):
            numba.set_num_threads(threads)
            runtime.set_threads(threads)
            results.append(run())
    finally:
        numba.set_num_threads(old)
        runtime.set_threads(old_chunks)
    return results


def test_sgm_deterministic_across_thread_counts():
    rng = np.random.default_rng(9)
    # Taller than two stripes, so the passes cross the seam between the phases.
    cq = rng.integers(0, 255, (130, 70, 23)).astype(np.uint8)
    guide = rng.random((130, 70)).astype(np.float32) * 255
    a, b = on_one_and_two_threads(lambda: ks.sgm_aggregate(cq, guide, 8, 20, 200, 16.0, 0, True))
    for x, y in zip(a, b):
        np.testing.assert_array_equal(x, y)
