"""Coarse-to-fine SGM: the windowed kernel against a pure-numpy reference, the windowed census
costs, the search windows, and the pipeline around them (winner costs, dense fallback)."""

from __future__ import annotations

import numpy as np
import pytest

from stereocli.matching.config import build_config
from stereocli.matching.kernels import census as kc
from stereocli.matching.kernels import sgm as ks
from stereocli.matching.kernels import sgm_window as kw
from stereocli.matching.kernels.costs import mask_invalid_right
from stereocli.matching.optimize import sgm as osgm
from stereocli.matching.pipeline import match_pair
from stereocli.matching.state import MatchState
from test_kernels_sgm import _layered_costs, reference_sgm
from test_sgm import bad, run, warp_pair

# The default preset searches narrow ranges and small volumes (every test image here) at full
# range; these overrides make it search coarse to fine.
WINDOWED = ["optimizer.coarse_min_ndisp=0", "optimizer.coarse_min_volume=0"]

def _windowed(cq, guide, paths, lo, hi, align, min_disp=0, want_second=True):
    runs = kw.window_runs(lo, hi, cq.shape[2], align)
    costs = kw.gather_runs(cq, runs[2], runs[3], runs[4], runs[5])
    r = kw.sgm_window(costs, runs, cq.shape[2], guide, paths, 3, 20, 4.0, min_disp, True, want_second)
    dense = kw.expand_sums(r["total"], runs[4], runs[2], runs[0], runs[1], cq.shape[2])
    return r, dense


def _random_windows(rng, h, w, nd, widest):
    lo = rng.integers(0, nd - 1, (h, w)).astype(np.int32)
    hi = np.minimum(nd, lo + rng.integers(1, widest + 1, (h, w))).astype(np.int32)
    return lo, hi


def _random_problem(seed, h, w, nd, widest):
    """Random uint8 costs (H, W, D), a grey guide and windows of at most ``widest``."""
    rng = np.random.default_rng(seed)
    cq = rng.integers(0, 40, (h, w, nd)).astype(np.uint8)
    guide = rng.integers(0, 255, (h, w)).astype(np.float32)
    return (cq, guide, *_random_windows(rng, h, w, nd, widest))


@pytest.mark.parametrize("paths", [2, 4, 8, 16])
@pytest.mark.parametrize("align", [1, 4, 8])
def test_windowed_kernel_equals_reference(paths, align):
    cq, guide, lo, hi = _random_problem(paths * 10 + align, 11, 15, 9, 5)
    _, dense = _windowed(cq, guide, paths, lo, hi, align)
    np.testing.assert_array_equal(dense.astype(np.int64), reference_sgm(cq, guide, paths, 3, 20, 4.0, lo, hi))


@pytest.mark.parametrize("paths", [4, 8])
def test_full_windows_equal_the_dense_kernel(paths):
    rng = np.random.default_rng(paths)
    h, w, nd = 12, 16, 9
    cq = rng.integers(0, 40, (h, w, nd)).astype(np.uint8)
    guide = rng.integers(0, 255, (h, w)).astype(np.float32)
    lo = np.zeros((h, w), np.int32)
    hi = np.full((h, w), nd, np.int32)
    r, dense = _windowed(cq, guide, paths, lo, hi, 8, min_disp=-2)
    s, d, dr = ks.sgm_aggregate(cq, guide, paths, 3, 20, 4.0, -2, True)
    np.testing.assert_array_equal(dense, s)
    np.testing.assert_array_equal(r["disparity"], d)
    np.testing.assert_array_equal(r["disparity_right"], dr)


def test_row_stripes_on_a_tall_image():
    # 201 rows: two row stripes and two phases, each pass continuing through the other half.
    # Against the reference on narrow windows around the truth and on random windows and
    # costs, and against the dense kernel on full windows.
    cq, guide, lo, hi = _random_problem(7, 201, 15, 9, 5)
    _, dense = _windowed(cq, guide, 8, lo, hi, 8)
    np.testing.assert_array_equal(dense.astype(np.int64), reference_sgm(cq, guide, 8, 3, 20, 4.0, lo, hi))
    cq, guide, truth = _layered_costs(201, 16, 8, 1)
    rng = np.random.default_rng(1)
    lo = np.clip(truth - rng.integers(0, 3, truth.shape), 0, 7).astype(np.int32)
    hi = np.clip(truth + 1 + rng.integers(0, 3, truth.shape), 1, 8).astype(np.int32)
    _, dense = _windowed(cq, guide, 4, lo, hi, 4)
    np.testing.assert_array_equal(dense.astype(np.int64), reference_sgm(cq, guide, 4, 3, 20, 4.0, lo, hi))
    full_lo = np.zeros(truth.shape, np.int32)
    full_hi = np.full(truth.shape, 8, np.int32)
    r, dense = _windowed(cq, guide, 4, full_lo, full_hi, 8)
    s, d, dr = ks.sgm_aggregate(cq, guide, 4, 3, 20, 4.0, 0, True)
    np.testing.assert_array_equal(dense, s)
    np.testing.assert_array_equal(r["disparity"], d)
    np.testing.assert_array_equal(r["disparity_right"], dr)


def test_winner_costs_match_the_sums():
    h, w, nd = 10, 18, 12
    cq, guide, lo, hi = _random_problem(5, h, w, nd, 7)
    r, dense = _windowed(cq, guide, 4, lo, hi, 4)
    for y in range(h):
        for x in range(w):
            k0, k1 = max(0, x - (w - 1), lo[y, x]), min(nd - 1, x, hi[y, x] - 1)
            if k1 < k0:
                assert np.isinf(r["disparity"][y, x])
                continue
            row = dense[y, x].astype(np.int64)
            k = int(r["disparity"][y, x])
            assert k == k0 + int(np.argmin(row[k0:k1 + 1]))  # first minimum in window and image
            c = r["costs"][y, x]
            assert c[1] == row[k]
            if k - 1 >= k0 and k + 1 <= k1:
                assert (c[0], c[2]) == (row[k - 1], row[k + 1])
            else:  # an undefined neighbour: both equal the winner, so a fit keeps the integer
                assert c[0] == c[1] == c[2]
            beyond = [row[j] for j in range(k0, k1 + 1) if abs(j - k) > 1]
            assert r["second"][y, x] == (min(beyond) if beyond else np.inf)


def test_right_costs_are_skipped_unless_wanted():
    nd = 10
    cq, guide, lo, hi = _random_problem(6, 9, 16, nd, 6)
    runs = kw.window_runs(lo, hi, nd, 4)
    costs = kw.gather_runs(cq, runs[2], runs[3], runs[4], runs[5])
    both = kw.sgm_window(costs, runs, nd, guide, 4, 3, 20, 4.0, 0, True, False)
    lean = kw.sgm_window(costs, runs, nd, guide, 4, 3, 20, 4.0, 0, True, False, want_right_costs=False)
    assert both["costs_right"] is not None and lean["costs_right"] is None
    np.testing.assert_array_equal(lean["disparity_right"], both["disparity_right"])
    np.testing.assert_array_equal(lean["disparity"], both["disparity"])
    found = np.isfinite(lean["disparity"])
    np.testing.assert_array_equal(lean["costs"][found], both["costs"][found])


@pytest.mark.parametrize("coarse", ["true", "false"])
def test_subpixel_right_false_keeps_the_right_winners_integer(coarse):
    gt = np.tile(np.linspace(4.0, 12.0, 96, dtype=np.float32), (48, 1))
    left, right = warp_pair(gt, seed=3)
    search = [f"optimizer.coarse={coarse}", *WINDOWED]
    lean = run(left, right, ["refinement.subpixel.right=false", *search], ndisp=16, want_right=True)
    full = run(left, right, ["refinement.subpixel.right=true", *search], ndisp=16, want_right=True)
    finite = np.isfinite(lean.disparity_right)
    assert finite.mean() > 0.8
    np.testing.assert_array_equal(lean.disparity_right[finite], np.round(lean.disparity_right[finite]))
    # With right: true the right view is sub-pixel on the slant; the left view is in both.
    assert np.mean(full.disparity_right[finite] != np.round(full.disparity_right[finite])) > 0.5
    assert bad(lean.disparity, gt, 20, 0.5) < 0.05


def test_windowed_census_costs_equal_the_dense_volume():
    rng = np.random.default_rng(2)
    h, w, nd, min_disp = 9, 21, 11, -3
    left = rng.integers(0, 2**34, (h, w)).astype(np.uint64)
    right = rng.integers(0, 2**34, (h, w)).astype(np.uint64)
    valid = rng.random((h, w)) > 0.2
    lo, hi = _random_windows(rng, h, w, nd, 6)
    runs = kw.window_runs(lo, hi, nd, 4)
    got = kc.hamming_runs(left, right, min_disp, 34.0, runs[2], runs[3], runs[4], runs[5], valid)
    dense = kc.hamming_volume(left, right, min_disp, nd, 34.0, np.uint8)
    mask_invalid_right(dense, valid, min_disp, np.float32(34.0))
    np.testing.assert_array_equal(got, kw.gather_runs(dense, runs[2], runs[3], runs[4], runs[5]))
    # Weighted bits (census gamma_c): the same costs on the runs as in the dense volume.
    image = rng.uniform(0, 255, (h, w, 3)).astype(np.float32)
    planes, scale, cost_max = kc.support_planes(image, 2, 3, 40.0)  # 34 bits, as the strings
    support = (planes, scale)
    got = kc.hamming_runs(left, right, min_disp, cost_max, runs[2], runs[3], runs[4], runs[5], valid, support)
    dense = kc.hamming_volume(left, right, min_disp, nd, cost_max, np.uint8, support)
    mask_invalid_right(dense, valid, min_disp, np.float32(cost_max))
    assert dense.max() > 34  # on the weighted scale (up to 7 per bit), not the Hamming one
    np.testing.assert_array_equal(got, kw.gather_runs(dense, runs[2], runs[3], runs[4], runs[5]))


def test_search_windows_cover_the_coarse_neighbourhood():
    coarse = np.full((6, 8), np.inf, np.float32)
    coarse[2, 3] = 5.0  # the only valid coarse pixel
    coarse[2, 4] = 7.0
    lo, hi = osgm.search_windows(coarse, (12, 15), min_disp=2, ndisp=30, margin=1, radius=1, max_window=0)
    assert lo.shape == (12, 15)
    # Full-res pixel (5, 7) has coarse parent (2, 3): neighbours hold 5 and 7 -> [10 - 1, 14 + 1] px.
    assert (lo[5, 7], hi[5, 7]) == (10 - 1 - 2, 14 + 1 + 1 - 2)
    # Far from any valid coarse pixel: the full range.
    assert (lo[11, 0], hi[11, 0]) == (0, 30)
    assert (hi > lo).all() and lo.min() >= 0 and hi.max() <= 30


def test_window_runs_on_the_grid_with_row_major_offsets():
    rng = np.random.default_rng(4)
    h, w, nd, align = 7, 13, 37, 8
    lo, hi = _random_windows(rng, h, w, nd, 12)
    got_lo, got_hi, run_lo, run_hi, offset, n = kw.window_runs(lo, hi, nd, align)
    np.testing.assert_array_equal(got_lo, lo)
    np.testing.assert_array_equal(run_lo, lo // align * align)
    np.testing.assert_array_equal(run_hi, np.minimum(-(-hi // align) * align, nd))
    width = (run_hi - run_lo).ravel().astype(np.int64)
    np.testing.assert_array_equal(offset.ravel(), np.concatenate([[0], np.cumsum(width)[:-1]]))
    assert n == width.sum()
    with pytest.raises(ValueError, match="lo < hi"):
        kw.window_runs(lo, lo, nd, align)  # empty windows
    with pytest.raises(ValueError, match="lo < hi"):
        kw.window_runs(lo, hi + nd, nd, align)  # beyond the range


def test_search_windows_equal_a_brute_force_neighbourhood():
    rng = np.random.default_rng(5)
    ch, cw, r, margin, min_disp, nd = 9, 11, 2, 3, -4, 40
    coarse = rng.integers(-2, 17, (ch, cw)).astype(np.float32)  # integer winners, as coarse_disparity gives
    coarse[rng.random((ch, cw)) < 0.4] = np.inf
    coarse[:, :5] = np.inf  # a band wider than the neighbourhood: full range there
    h, w = 2 * ch - 1, 2 * cw
    lo, hi = osgm.search_windows(coarse, (h, w), min_disp, nd, margin, r, max_window=0)
    for y in range(h):
        for x in range(w):
            cy, cx = y // 2, x // 2
            near = coarse[max(0, cy - r):cy + r + 1, max(0, cx - r):cx + r + 1]
            near = near[np.isfinite(near)]
            if near.size == 0:
                want = (0, nd)
            else:
                a = int(np.clip(2 * near.min() - margin - min_disp, 0, nd - 1))
                want = (a, int(np.clip(2 * near.max() + margin + 1 - min_disp, a + 1, nd)))
            assert (lo[y, x], hi[y, x]) == want, (y, x)


def test_half_resolution_is_the_2x2_mean():
    rng = np.random.default_rng(1)
    img = rng.random((7, 9, 3)).astype(np.float32)
    half = osgm.half_resolution(img)
    padded = np.pad(img, ((0, 1), (0, 1), (0, 0)), mode="edge")
    ref = 0.25 * (padded[0::2, 0::2] + padded[1::2, 0::2] + padded[0::2, 1::2] + padded[1::2, 1::2])
    np.testing.assert_allclose(half, ref, rtol=1e-6)


@pytest.mark.parametrize("coarse", [True, False])
def test_slanted_plane_both_searches(coarse):
    gt = np.tile(np.linspace(4.0, 30.0, 120, dtype=np.float32), (64, 1))
    left, right = warp_pair(gt, seed=7)
    res = run(left, right, [f"optimizer.coarse={str(coarse).lower()}", *WINDOWED], ndisp=40)
    assert bad(res.disparity, gt, 32, 1.0) < 0.01
    assert bad(res.disparity, gt, 32, 0.5) < 0.10


@pytest.mark.parametrize("ndisp", [3, 4])
def test_tiny_ranges_run_the_full_range_search(ndisp):
    # Ranges of at most 4 disparities skip the coarse level; the optimizer then runs the cost
    # stage the pipeline left to it (this raised "no cost volume" before).
    gt = np.full((40, 64), 2.0, np.float32)
    left, right = warp_pair(gt)
    res = run(left, right, [], ndisp=ndisp)
    # Scored beyond the default plane_smooth's reach (9 px) of the two occluded, filled left
    # columns: its fit through every third neighbour is pulled there by up to 0.3 px.
    assert bad(res.disparity, gt, 2 + 9, 0.25) == 0.0


@pytest.mark.parametrize("limit, at, below, other", [
    ("coarse_min_ndisp", "24", "23", "coarse_min_volume=0"),
    # 48 x 96 x 24 = 110592 cells: searched at full range up to a limit of 0.110592 M cells.
    ("coarse_min_volume", "0.110592", "0.1105", "coarse_min_ndisp=0"),
])
def test_coarse_limits_fall_back_to_the_full_range_search(limit, at, below, other):
    gt = np.tile(np.linspace(3.0, 14.0, 96, dtype=np.float32), (48, 1))
    left, right = warp_pair(gt, seed=4)
    dense = run(left, right, ["optimizer.coarse=false"], ndisp=24)
    at_limit = run(left, right, [f"optimizer.{limit}={at}", f"optimizer.{other}"], ndisp=24)
    above = run(left, right, [f"optimizer.{limit}={below}", f"optimizer.{other}"], ndisp=24)
    np.testing.assert_array_equal(at_limit.disparity, dense.disparity)
    assert not np.array_equal(above.disparity, dense.disparity)  # the windowed search ran
    assert bad(above.disparity, gt, 20, 1.0) < 0.01


def test_coarse_to_fine_skips_the_dense_cost_volume():
    gt = np.full((40, 64), 6.0, np.float32)
    left, right = warp_pair(gt)
    fine = run(left, right, WINDOWED, ndisp=16)
    dense = run(left, right, ["optimizer.coarse=false"], ndisp=16)
    assert "cost.census" not in fine.timings and "cost.census" in dense.timings
    np.testing.assert_allclose(fine.disparity[6:-6, 20:-6], gt[6:-6, 20:-6], atol=0.25)


def test_confidence_and_uniqueness_from_the_winner_equal_the_dense_volume():
    # The windowed SGM keeps the second-best sum; the same stages on the expanded volume (a
    # stage without an on_winner_costs variant forces it) give the same maps.
    gt = np.tile(np.linspace(3.0, 12.0, 80, dtype=np.float32), (40, 1))
    left, right = warp_pair(gt, seed=2)
    refine = [{"name": "subpixel"}, {"name": "uniqueness", "ratio": 0.02}, {"name": "confidence"},
              {"name": "lr_check"}]
    from stereocli.matching.config import validate

    base = {"cost": {"name": "census", "window": [5, 7]}, "optimizer": {"name": "sgm", "paths": 4, "coarse": True},
            "refinement": refine}
    cfg = validate(base, "<test>")
    winner = match_pair(left, right, cfg, ndisp=16, want_confidence=True)
    from dataclasses import replace

    # Without the variant the pipeline asks the SGM for the dense sums.
    call = cfg.refinement[1]
    call.stage = replace(call.stage, traits=replace(call.stage.traits, on_winner_costs=None))
    volume = match_pair(left, right, cfg, ndisp=16, want_confidence=True)
    np.testing.assert_array_equal(winner.disparity, volume.disparity)
    np.testing.assert_array_equal(winner.confidence, volume.confidence)


def test_coarse_to_fine_is_deterministic_across_thread_counts():
    gt = np.tile(np.linspace(2.0, 20.0, 96, dtype=np.float32), (50, 1))
    left, right = warp_pair(gt, seed=4)
    cfg1 = build_config([], ["runtime.threads=1", *WINDOWED])
    cfg2 = build_config([], ["runtime.threads=2", *WINDOWED])
    a = match_pair(left, right, cfg1, ndisp=32, want_right=True)
    b = match_pair(left, right, cfg2, ndisp=32, want_right=True)
    np.testing.assert_array_equal(a.disparity, b.disparity)
    np.testing.assert_array_equal(a.disparity_right, b.disparity_right)


def test_coarse_to_fine_with_aggregation_uses_the_dense_volume():
    from stereocli.matching.config import validate

    gt = np.full((40, 64), 5.0, np.float32)
    left, right = warp_pair(gt)
    cfg = validate({"cost": {"name": "ad"}, "aggregation": [{"name": "box", "window": [5, 5]}],
                    "optimizer": {"name": "sgm", "paths": 4, "coarse": True}, "refinement": [{"name": "subpixel"}]},
                   "<test>")
    res = match_pair(left, right, cfg, ndisp=16)
    assert "cost.ad" in res.timings and "aggregation.box" in res.timings
    assert bad(res.disparity, gt, 20) < 0.02


@pytest.mark.parametrize("coarse", ["true", "false"])
def test_valid_masks_are_honoured_by_both_searches(coarse):
    # The SGM's integer winners (no refinement): invalid left pixels stay +inf, and no winner
    # points at a right pixel outside the right mask.
    gt = np.full((40, 72), 6.0, np.float32)
    left, right = warp_pair(gt, seed=9)
    left_valid = np.ones(gt.shape, bool)
    left_valid[:, -6:] = False
    right_valid = np.ones(gt.shape, bool)
    right_valid[:, 20:26] = False  # a band of the right image no left pixel may match
    from stereocli.matching.config import validate

    cfg = validate({"cost": {"name": "census", "window": [5, 7]},
                    "optimizer": {"name": "sgm", "paths": 4, "coarse": coarse == "true"}, "refinement": []}, "<test>")
    d = match_pair(left, right, cfg, ndisp=16, left_valid=left_valid, right_valid=right_valid).disparity
    assert np.isinf(d[:, -6:]).all()
    ys, xs = np.nonzero(np.isfinite(d))
    xr = np.rint(xs - d[ys, xs]).astype(int)
    inside = (xr >= 0) & (xr < gt.shape[1])
    assert right_valid[ys[inside], xr[inside]].all()
    assert np.isfinite(d[:, 40:60]).mean() > 0.95  # away from the band the plane is found
    np.testing.assert_allclose(d[:, 40:60][np.isfinite(d[:, 40:60])], 6.0, atol=0.5)


@pytest.mark.parametrize("min_disp, ndisp", [(0, 60), (0, 73), (-5, 30), (3, 16)])
def test_coarse_level_range_covers_the_range_in_whole_vector_steps(monkeypatch, min_disp, ndisp):
    # The coarse level searches [floor(min/2), ceil(max/2)] extended at the far end to a
    # multiple of COARSE_RANGE_STEP hypotheses.
    seen = []
    real = osgm.run_sgm

    def spy(state, p, cost=None, coarse=None):
        seen.append((state.min_disp, state.ndisp))
        return real(state, p, cost, coarse)

    monkeypatch.setattr(osgm, "run_sgm", spy)
    gt = np.full((32, 96), float(max(min_disp + 2, 0)), np.float32)
    left, right = warp_pair(gt, seed=1)
    cfg = build_config([], WINDOWED)
    state = MatchState(left.astype(np.float32), right.astype(np.float32), min_disp, ndisp)
    osgm.coarse_disparity(state, cfg.optimizer.params, cfg.cost)
    lo, n = seen[0]
    assert lo == min_disp // 2
    assert n % osgm.COARSE_RANGE_STEP == 0
    assert lo + n - 1 >= -(-(min_disp + ndisp - 1) // 2) > lo + n - 1 - osgm.COARSE_RANGE_STEP
