"""The ``slanted_patchmatch`` refinement: its kernels against pure-numpy references on tiny
inputs, and a slanted plane recovered to a tenth of a pixel from a pixel-locked map."""

from __future__ import annotations

import numpy as np
import pytest

from stereocli import registry
from stereocli.errors import ConfigError
from stereocli.matching.kernels import slanted as ksl
from stereocli.matching.state import MatchState
from test_kernels_sgm import on_one_and_two_threads

INF = np.float32(np.inf)


def census_reference(image, half_h, half_w, step):
    h, w = image.shape
    out = np.zeros((h, w), np.uint64)
    for y in range(h):
        for x in range(w):
            bit = 0
            for dy in range(-half_h, half_h + 1):
                for dx in range(-half_w, half_w + 1):
                    if dy == 0 and dx == 0:
                        continue
                    yy, xx = min(max(y + dy, 0), h - 1), min(max(x + dx * step, 0), w - 1)
                    if image[yy, xx] < image[y, x]:
                        out[y, x] |= np.uint64(1 << bit)
                    bit += 1
    return out


def fit_reference(disp, guide, radius, weights, gate):
    """Weighted least squares by numpy's solver, pixel by pixel."""
    h, w = disp.shape
    planes = np.zeros((h, w, 3))
    for y in range(h):
        for x in range(w):
            rows, rhs = [], []
            for yy in range(max(0, y - radius), min(h, y + radius + 1)):
                for xx in range(max(0, x - radius), min(w, x + radius + 1)):
                    if abs(disp[yy, xx] - disp[y, x]) <= gate:
                        s = np.sqrt(weights[abs(guide[yy, xx] - guide[y, x])])
                        rows.append([s * xx, s * yy, s])
                        rhs.append(s * disp[yy, xx])
            planes[y, x] = np.linalg.lstsq(np.array(rows), np.array(rhs), rcond=None)[0]
    return planes


def cost_reference(plane, y, x, codes_left, codes_right, guide, weights, prior, up, radius, stride, tau, lam, cap):
    a, b, c = plane
    total = wsum = 0.0
    h, w = codes_left.shape
    for yy in range(max(0, y - radius), min(h, y + radius + 1), stride):
        for xx in range(max(0, x - radius), min(w, x + radius + 1), stride):
            wq = weights[abs(guide[yy, xx] - guide[y, x])]
            d = a * xx + b * yy + c
            j = int(np.floor((xx - d + 0.5) * up))
            cq = tau if not 0 <= j < codes_right.shape[1] else min(
                bin(int(codes_left[yy, xx]) ^ int(codes_right[yy, j])).count("1"), tau)
            if np.isfinite(prior[yy, xx]):
                cq += lam * min(abs(d - prior[yy, xx]), cap)
            total += wq * cq
            wsum += wq
    return total / wsum


def textured_pair(h, w, plane, seed=0):
    """A left image of smooth random texture and the right image it gives for the disparity
    plane ``d = a·x + b·y + c`` (both sampled from the same band-limited function)."""
    rng = np.random.default_rng(seed)
    freq = rng.uniform(0.2, 1.2, (24, 2)) * rng.choice([-1, 1], (24, 2))
    phase = rng.uniform(0, 2 * np.pi, 24)

    def texture(xs, ys):
        return 128 + 90 / np.sqrt(24) * np.sin(xs[..., None] * freq[:, 0] + ys[..., None] * freq[:, 1] + phase).sum(-1)

    a, b, c = plane
    ys, xs = np.mgrid[0:h, 0:w].astype(float)
    left = texture(xs, ys)
    # The right pixel x' shows the left point x with x − (a·x + b·y + c) = x'.
    right = texture((xs + b * ys + c) / (1 - a), ys)
    return left.astype(np.float32), right.astype(np.float32), (a * xs + b * ys + c).astype(np.float32)


def test_census_codes_match_reference():
    rng = np.random.default_rng(1)
    image = rng.integers(0, 6, (7, 30)).astype(np.float32)
    for step in (1, 3):
        np.testing.assert_array_equal(ksl.census_codes(image, 1, 2, step), census_reference(image, 1, 2, step))
    # Narrower than the neighbour offsets: every column clamps on one side or both.
    narrow = rng.integers(0, 6, (5, 3)).astype(np.float32)
    np.testing.assert_array_equal(ksl.census_codes(narrow, 2, 3, 4), census_reference(narrow, 2, 3, 4))


def test_fit_planes_matches_reference_and_recovers_planes():
    rng = np.random.default_rng(2)
    disp = (rng.normal(8, 0.4, (9, 11)) + np.arange(11) * 0.3).astype(np.float32)
    guide = rng.integers(0, 40, (9, 11)).astype(np.int64)
    weights = np.exp(-np.arange(256) / 10.0)
    pa, pb, pc = ksl.fit_planes(disp, guide, 2, weights, 1.0, np.inf)
    ref = fit_reference(disp, guide, 2, weights, 1.0)
    np.testing.assert_allclose(np.stack([pa, pb, pc], -1), ref, atol=1e-6)
    ys, xs = np.mgrid[0:9, 0:11]
    exact = (0.25 * xs - 0.125 * ys + 5.0).astype(np.float32)
    exact[4, 5] = INF
    pa, pb, pc = ksl.fit_planes(exact, guide, 2, weights, 1.0, 0.5)
    finite = np.isfinite(exact)
    np.testing.assert_allclose(pa[finite], 0.25, atol=1e-9)
    np.testing.assert_allclose(pb[finite], -0.125, atol=1e-9)
    np.testing.assert_allclose(pc[finite], 5.0, atol=1e-9)
    assert pc[4, 5] == np.inf


def test_plane_costs_match_reference():
    rng = np.random.default_rng(3)
    left = rng.uniform(0, 255, (9, 16)).astype(np.float32)
    right_up = rng.uniform(0, 255, (9, 64)).astype(np.float32)
    codes_left, codes_right = ksl.census_codes(left, 1, 1, 1), ksl.census_codes(right_up, 1, 1, 4)
    guide = np.rint(left).astype(np.int64)
    weights = np.exp(-np.arange(256) / 10.0)
    prior = rng.uniform(1, 4, (9, 16)).astype(np.float32)
    prior[2, 3] = INF
    pa, pb = rng.uniform(-0.2, 0.2, (2, 9, 16))
    pc = rng.uniform(0, 5, (9, 16))
    costs = ksl.plane_costs(pa, pb, pc, codes_left, codes_right, guide, weights, prior, 4, 3, 2, 5.0, 2.0, 1.0)
    for y, x in [(0, 0), (4, 8), (8, 15), (2, 3), (5, 1)]:
        ref = cost_reference((pa[y, x], pb[y, x], pc[y, x]), y, x, codes_left, codes_right, guide, weights, prior,
                             4, 3, 2, 5.0, 2.0, 1.0)
        assert costs[y, x] == pytest.approx(ref, rel=1e-12)


def run_stage(left, right, disp, ndisp, **values):
    stage = registry.get("refinement", "slanted_patchmatch")
    state = MatchState(left=left, right=right, min_disp=0, ndisp=ndisp)
    state.disparity = disp.copy()
    stage.func(state, stage.make_params(values))
    return state.disparity


def test_slanted_plane_recovered_from_pixel_locked_map():
    """The input is the true slanted plane rounded to whole pixels (errors up to 0.5 px, mean
    0.25); PatchMatch with the input as a weak prior brings 99 % of the interior pixels within
    0.1 px (the census cost is flat over a few hundredths of a pixel, so a few stop short)."""
    left, right, truth = textured_pair(48, 80, (0.06, 0.03, 6.3))
    locked = np.rint(truth).astype(np.float32)
    locked[20, 40] = INF
    assert np.abs(locked - truth)[np.isfinite(locked)].mean() > 0.2
    results = on_one_and_two_threads(lambda: run_stage(left, right, locked, 16, band=1.0, prior=0.5, iterations=4,
                                                       samples=2, stride=1))
    np.testing.assert_array_equal(results[0], results[1])  # the same bytes on any thread count
    out = results[0]
    assert out[20, 40] == np.inf  # invalid pixels stay invalid
    inner = np.zeros_like(truth, bool)
    inner[6:-6, 14:-6] = True  # the right view's left border has no match
    inner[20, 40] = False
    err = np.abs(out - truth)[inner]
    assert np.percentile(err, 99) < 0.1 and err.max() < 0.15 and err.mean() < 0.03
    # The band: no pixel moves more than band px from its input.
    moved = run_stage(left, right, locked, 16, band=0.2, iterations=2)
    finite = np.isfinite(locked)
    assert np.abs(moved[finite] - locked[finite]).max() <= 0.2 + 1e-4


def test_zero_iterations_is_the_plane_fit():
    left, right, truth = textured_pair(24, 40, (0.1, 0.0, 4.0))
    out = run_stage(left, right, truth, 16, iterations=0)
    np.testing.assert_allclose(out, truth, atol=1e-4)


def test_census_window_must_be_odd():
    with pytest.raises(ConfigError, match="census"):
        registry.get("refinement", "slanted_patchmatch").make_params({"census": [4, 7]})


@pytest.mark.parametrize("same_plane, expected", [(0.01, 5.05), (0.1, 5.0)])
def test_same_plane_skips_only_neighbour_planes_within_it(same_plane, expected):
    # Three pixels in a row, a flat image (every census code 0), and a prior at 5.05 that makes
    # a plane's cost its distance from 5.05: the left neighbour's plane (5.05, 0.05 from the
    # middle pixel's 5.0 everywhere) is the cheapest, and is tried only if it differs by more
    # than same_plane; the right neighbour's (5.5) is tried and loses.
    pa, pb = np.zeros((1, 3)), np.zeros((1, 3))
    pc = np.array([[5.05, 5.0, 5.5]])
    codes = np.zeros((1, 3), np.uint64)
    guide = np.zeros((1, 3), np.int64)
    weights = np.ones(256)
    prior = np.full((1, 3), 5.05, np.float32)
    window = (codes, codes, guide, weights, prior, 1, 1, 1, 5.0, 1.0, 10.0)
    cost = ksl.plane_costs(pa, pb, pc, *window)
    changed = np.ones((1, 3), np.bool_)
    ksl.sweep(pa, pb, pc, cost, changed, False, 1, 0, 0.0, 0.0, 0, 10.0, same_plane, 0.0, 20.0, *window)
    assert pc[0, 1] == expected
    assert pc[0, 0] == 5.05 and pc[0, 2] == 5.5  # the other parity is not swept


def test_same_plane_beyond_every_difference_leaves_the_plane_fit():
    left, right, truth = textured_pair(24, 40, (0.06, 0.03, 4.3))
    locked = np.rint(truth).astype(np.float32)
    fitted = run_stage(left, right, locked, 16, iterations=0, samples=0)
    skipped = run_stage(left, right, locked, 16, iterations=2, samples=0, same_plane=100.0)
    np.testing.assert_array_equal(skipped, fitted)
    assert not np.array_equal(run_stage(left, right, locked, 16, iterations=2, samples=0), fitted)
