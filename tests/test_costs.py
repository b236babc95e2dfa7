"""Matching-cost stages: exact values against pure-numpy references, recovery of a known
disparity, the volume contract, and parameter errors."""

from __future__ import annotations

import numpy as np
import pytest

from local_scene import run_stages, scene, two_colour_scene, wta
from stereocli import registry
from stereocli.errors import ConfigError
from stereocli.matching.config import build_config

ALL_COSTS = ["ad", "sd", "tad", "sad", "ssd", "stad", "ncc", "zncc", "gradient", "color_gradient",
             "bt", "census", "rank", "ad_census", "ordinal"]


def tiny(color=True, seed=3, h=6, w=9):
    rng = np.random.default_rng(seed)
    shape = (h, w, 3) if color else (h, w)
    return (rng.integers(0, 256, shape).astype(np.float32), rng.integers(0, 256, shape).astype(np.float32))


def _ch(img):
    return img if img.ndim == 3 else img[..., None]


def ref_pixel(left, right, min_disp, nd, fn, cost_max):
    """Reference volume: fn(left pixel vector, right pixel vector) or cost_max."""
    L, R = _ch(left), _ch(right)
    h, w = L.shape[:2]
    out = np.full((h, w, nd), cost_max, np.float64)
    for y in range(h):
        for x in range(w):
            for k in range(nd):
                xr = x - (min_disp + k)
                if 0 <= xr < w:
                    out[y, x, k] = fn(L, R, y, x, xr)
    return out


def ref_window(left, right, min_disp, nd, r, pix, cost_max):
    """Window mean (clipped window, right pixel clamped) of a pixel cost pix(lv, rv)."""
    L, R = _ch(left), _ch(right)
    h, w = L.shape[:2]
    out = np.full((h, w, nd), cost_max, np.float64)
    for y in range(h):
        for x in range(w):
            for k in range(nd):
                d = min_disp + k
                if not 0 <= x - d < w:
                    continue
                vals = [pix(L[yy, xx], R[yy, min(max(xx - d, 0), w - 1)])
                        for yy in range(max(0, y - r), min(h, y + r + 1))
                        for xx in range(max(0, x - r), min(w, x + r + 1))]
                out[y, x, k] = np.mean(vals)
    return out


@pytest.mark.parametrize("color", [True, False])
def test_pixel_costs_exact(color):
    left, right = tiny(color)
    md, nd = -1, 4
    ad = lambda L, R, y, x, xr: np.abs(L[y, x] - R[y, xr]).mean()  # noqa: E731
    cases = {
        "ad": ({}, ad, 255.0),
        "tad": ({"truncate": 20}, lambda *a: min(ad(*a), 20.0), 20.0),
        "sd": ({}, lambda L, R, y, x, xr: ((L[y, x] - R[y, xr]) ** 2).mean(), 65025.0),
    }
    for name, (params, fn, cmax) in cases.items():
        st = run_stages(left, right, nd, [("cost", name, params)], min_disp=md)
        assert st.cost.dtype == np.float32 and st.cost.flags.c_contiguous and st.cost_max == cmax
        np.testing.assert_allclose(st.cost, ref_pixel(left, right, md, nd, fn, cmax), rtol=1e-5, atol=1e-3)


def test_bt_exact():
    left, right = tiny(True)

    def bt(L, R, y, x, xr):
        w = L.shape[1]

        def ext(img, xx):
            v = img[y, xx]
            a = 0.5 * (v + img[y, max(xx - 1, 0)])
            b = 0.5 * (v + img[y, min(xx + 1, w - 1)])
            return np.minimum(v, np.minimum(a, b)), np.maximum(v, np.maximum(a, b))

        rmin, rmax = ext(R, xr)
        lmin, lmax = ext(L, x)
        dlr = np.maximum(0, np.maximum(L[y, x] - rmax, rmin - L[y, x]))
        drl = np.maximum(0, np.maximum(R[y, xr] - lmax, lmin - R[y, xr]))
        return np.minimum(dlr, drl).mean()

    st = run_stages(left, right, 4, [("cost", "bt", {})])
    np.testing.assert_allclose(st.cost, ref_pixel(left, right, 0, 4, bt, 255.0), atol=1e-3)
    # BT never exceeds AD
    ad = run_stages(left, right, 4, [("cost", "ad", {})]).cost
    assert (st.cost <= ad + 1e-4).all()


def test_gradient_costs_exact():
    left, right = tiny(False)

    def grad(img):
        p = np.pad(img, 1, mode="edge")
        return 0.5 * (p[1:-1, 2:] - p[1:-1, :-2]), 0.5 * (p[2:, 1:-1] - p[:-2, 1:-1])

    (lx, ly), (rx, ry) = grad(left), grad(right)
    st = run_stages(left, right, 3, [("cost", "gradient", {"direction": "xy"})])
    ref = ref_pixel(left, right, 0, 3,
                    lambda L, R, y, x, xr: 0.5 * (abs(lx[y, x] - rx[y, xr]) + abs(ly[y, x] - ry[y, xr])), 255.0)
    np.testing.assert_allclose(st.cost, ref, atol=1e-3)
    st = run_stages(left, right, 3, [("cost", "color_gradient", {"alpha": 0.25, "tau_color": 30, "tau_gradient": 9})])
    ref = ref_pixel(left, right, 0, 3, lambda L, R, y, x, xr: 0.75 * min(abs(L[y, x, 0] - R[y, xr, 0]), 30)
                    + 0.25 * min(abs(lx[y, x] - rx[y, xr]), 9), 0.75 * 30 + 0.25 * 9)
    np.testing.assert_allclose(st.cost, ref, atol=1e-3)


@pytest.mark.parametrize("name,pix,cmax", [
    ("sad", lambda a, b: np.abs(a - b).mean(), 255.0),
    ("ssd", lambda a, b: ((a - b) ** 2).mean(), 65025.0),
    ("stad", lambda a, b: min(np.abs(a - b).mean(), 20.0), 20.0),
])
def test_window_costs_exact(name, pix, cmax):
    left, right = tiny(True, h=7, w=11)
    st = run_stages(left, right, 5, [("cost", name, {"window": [3, 3]})], min_disp=-1)
    np.testing.assert_allclose(st.cost, ref_window(left, right, -1, 5, 1, pix, cmax), rtol=1e-5, atol=1e-2)


@pytest.mark.parametrize("zero_mean", [False, True])
def test_ncc_exact_inside(zero_mean):
    left, right = tiny(True, h=9, w=14)
    nd, r = 3, 1
    st = run_stages(left, right, nd, [("cost", "zncc" if zero_mean else "ncc", {"window": [3, 3]})])
    h, w = left.shape[:2]
    for y in range(r, h - r):
        for x in range(r + nd, w - r):  # windows fully inside both images
            for k in range(nd):
                a = left[y - r:y + r + 1, x - r:x + r + 1].astype(np.float64)
                b = right[y - r:y + r + 1, x - k - r:x - k + r + 1].astype(np.float64)
                if zero_mean:
                    a = a - a.mean(axis=(0, 1))
                    b = b - b.mean(axis=(0, 1))
                ref = 1 - (a * b).sum() / np.sqrt((a * a).sum() * (b * b).sum())
                assert st.cost[y, x, k] == pytest.approx(ref, abs=2e-4)


def test_census_rank_ordinal_exact():
    left, right = tiny(False, h=7, w=10)
    h, w = left.shape

    def win(img, y, x, r=1):
        return np.array([img[min(max(y + dy, 0), h - 1), min(max(x + dx, 0), w - 1)]
                         for dy in range(-r, r + 1) for dx in range(-r, r + 1)])

    def census(img, y, x):
        v = win(img, y, x)
        return np.delete(v < img[y, x], 4)

    st = run_stages(left, right, 3, [("cost", "census", {"window": [3, 3]})])
    np.testing.assert_array_equal(st.cost, ref_pixel(
        left, right, 0, 3, lambda L, R, y, x, xr: np.sum(census(left, y, x) != census(right, y, xr)), 8.0))
    st = run_stages(left, right, 3, [("cost", "rank", {"window": [3, 3]})])
    np.testing.assert_array_equal(st.cost, ref_pixel(
        left, right, 0, 3,
        lambda L, R, y, x, xr: abs(np.sum(win(left, y, x) < left[y, x]) - np.sum(win(right, y, xr) < right[y, xr])),
        8.0))

    def ordinal(L, R, y, x, xr):
        a, b = win(left, y, x), win(right, y, xr)
        ra = np.argsort(np.argsort(a, kind="stable"), kind="stable")  # rank of each position
        rb = np.argsort(np.argsort(b, kind="stable"), kind="stable")
        order = np.argsort(ra)  # positions by left rank
        s = rb[order]
        n = a.size
        dm = max(sum(1 for j in range(i + 1) if s[j] > i) for i in range(n))
        return dm / (n // 2)

    st = run_stages(left, right, 3, [("cost", "ordinal", {"window": [3, 3]})])
    np.testing.assert_allclose(st.cost, ref_pixel(left, right, 0, 3, ordinal, 1.0), atol=1e-6)
    # identical windows: distance 0; reversed order: distance 1
    assert run_stages(left, left, 1, [("cost", "ordinal", {"window": [3, 3]})]).cost[3, 5, 0] == 0
    assert run_stages(left, 255 - left, 1, [("cost", "ordinal", {"window": [3, 3]})]).cost[3, 5, 0] == 1


def test_ad_census_combination():
    left, right = tiny(True)
    ad = run_stages(left, right, 3, [("cost", "ad", {})]).cost
    cen = run_stages(left, right, 3, [("cost", "census", {"window": [3, 5]})]).cost
    st = run_stages(left, right, 3, [("cost", "ad_census", {"window": [3, 5], "lambda_ad": 10, "lambda_census": 30})])
    ok = ad < 255
    ref = 2 - np.exp(-ad / 10) - np.exp(-cen / 30)
    np.testing.assert_allclose(st.cost[ok], ref[ok], atol=1e-5)
    assert st.cost_max == 2.0 and (st.cost[~ok] == 2.0).all()
    st = run_stages(left, right, 3, [("cost", "ad_census", {"window": [3, 5], "combine": "sum"})])
    np.testing.assert_allclose(st.cost[ok], (ad / 10 + cen / 30)[ok], rtol=1e-5)


@pytest.mark.parametrize("name", ALL_COSTS)
def test_recovers_known_disparity(name):
    left, right, gt, mask = scene(color=True)
    stages = [("cost", name, {})]
    if name in ("ad", "sd", "tad", "gradient", "color_gradient", "bt", "census", "rank", "ad_census"):
        stages.append(("aggregation", "box", {"window": [7, 7]}))
    st = run_stages(left, right, 16, stages)
    assert st.cost.shape == (*gt.shape, 16) and st.cost.dtype == np.float32
    # impossible hypotheses (right pixel left of the image) hold cost_max
    assert (st.cost[:, 0, 1:] == np.float32(st.cost_max)).all()
    disp = wta(st)
    assert (disp[mask] == gt[mask]).mean() > 0.98


def test_grey_images_work_for_every_cost():
    left, right, gt, mask = scene(color=False)
    for name in ALL_COSTS:
        st = run_stages(left, right, 12, [("cost", name, {}), ("aggregation", "box", {"window": [5, 5]})])
        assert (wta(st)[mask] == gt[mask]).mean() > 0.95, name


@pytest.mark.parametrize("name,values,key", [
    ("sad", {"window": [4, 5]}, "window"),
    ("ssd", {"window": [0, 3]}, "window"),
    ("stad", {"truncate": 0}, "truncate"),
    ("ncc", {"window": [1, 1]}, "window"),
    ("zncc", {"window": [8, 9]}, "window"),
    ("census", {"window": [9, 9]}, "window"),
    ("rank", {"window": [2, 3]}, "window"),
    ("ordinal", {"window": [17, 17]}, "window"),
    ("ad_census", {"combine": "product"}, "combine"),
    ("ad_census", {"lambda_ad": -1}, "lambda_ad"),
    ("gradient", {"direction": "y"}, "direction"),
    ("color_gradient", {"alpha": 1.5}, "alpha"),
    ("bt", {"truncate": 300}, "truncate"),
    ("sd", {"truncat": 3}, "truncat"),
    ("tad", {"truncate": "big"}, "truncate"),
])
def test_invalid_parameters(name, values, key):
    with pytest.raises(ConfigError, match=key):
        registry.get("cost", name).make_params(values, source="x.yaml", section="cost")


def test_invalid_parameter_through_config():
    with pytest.raises(ConfigError, match=r"cost\.window"):
        build_config(sets=["cost.name=sad", "cost.window=[4,4]"])
    cfg = build_config(sets=["cost.name=zncc", "cost.window=[5,7]"])
    assert cfg.cost.params.window == (5, 7)


@pytest.mark.parametrize("window", [(3, 3), (5, 7), (7, 9), (5, 13)])
def test_census_transform_bit_strings(window):
    # Strings longer than 32 bits are built in two halves: the order must stay raster order,
    # most significant first, bit = neighbour darker than the centre, border replicated.
    from stereocli.matching.kernels.census import census_transform

    rng = np.random.default_rng(sum(window))
    img = rng.integers(0, 6, (9, 15)).astype(np.float32)  # many ties: equal is not darker
    hh, hw = window[0] // 2, window[1] // 2
    h, w = img.shape
    got = census_transform(img, hh, hw)
    for y in range(h):
        for x in range(w):
            expected = 0
            for dy in range(-hh, hh + 1):
                for dx in range(-hw, hw + 1):
                    if dy or dx:
                        neighbour = img[min(max(y + dy, 0), h - 1), min(max(x + dx, 0), w - 1)]
                        expected = (expected << 1) | int(neighbour < img[y, x])
            assert int(got[y, x]) == expected


def weighted_census_reference(left, right, window, gamma, nd):
    """Census with colour-weighted bits, pixel by pixel: neighbour i weighs
    q_i = round(7·exp(−(Δ_i/γ)²)), Δ_i its largest channel difference from the centre in the
    left image (border replicated); the cost is Σ q_i·[bit i differs], scaled by
    resolution·n / Σ q_i (every q_i = 7 if they are all 0) and rounded, in float32 as the kernel."""
    hh, hw = window[0] // 2, window[1] // 2
    n = window[0] * window[1] - 1
    resolution = 255 // n
    colour = _ch(left)
    h, w = colour.shape[:2]

    def offsets():
        return [(dy, dx) for dy in range(-hh, hh + 1) for dx in range(-hw, hw + 1) if dy or dx]

    def bits(grey, y, x):
        return np.array([grey[min(max(y + dy, 0), h - 1), min(max(x + dx, 0), w - 1)] < grey[y, x]
                         for dy, dx in offsets()])

    from stereocli.matching.state import luma  # the grey images the census strings are made of

    gl = luma(np.ascontiguousarray(colour)) if colour.shape[2] == 3 else colour[..., 0]
    gr = luma(np.ascontiguousarray(_ch(right))) if colour.shape[2] == 3 else _ch(right)[..., 0]
    out = np.full((h, w, nd), resolution * n, np.float64)
    for y in range(h):
        for x in range(w):
            steps = np.array([
                np.abs(colour[min(max(y + dy, 0), h - 1), min(max(x + dx, 0), w - 1)] - colour[y, x]).max()
                for dy, dx in offsets()])
            q = np.rint(7 * np.exp(-(steps / gamma) ** 2))
            if q.sum() == 0:
                q[:] = 7
            scale = np.float32(resolution * n) / np.float32(q.sum())
            for k in range(nd):
                if x - k >= 0:
                    differ = bits(gl, y, x) != bits(gr, y, x - k)
                    out[y, x, k] = np.floor(np.float32(q[differ].sum()) * scale + np.float32(0.5))
    return out


@pytest.mark.parametrize("color, window", [(True, (3, 3)), (True, (5, 5)), (True, (3, 13)), (False, (5, 5))])
def test_weighted_census_matches_a_numpy_reference(color, window):
    # (3, 13) has 38 bits: their weights are built in two halves, as the strings are.
    left, right = tiny(color, seed=4, h=8, w=17)
    gamma = 70.0
    st = run_stages(left, right, 5, [("cost", "census", {"window": list(window), "gamma_c": gamma})])
    n = window[0] * window[1] - 1
    assert st.cost_max == (255 // n) * n
    np.testing.assert_array_equal(st.cost, weighted_census_reference(left, right, window, gamma, 5))


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_weighted_census_keeps_the_background_beside_an_object(seed):
    # Right of the object the background is visible in both views, but a 5x5 census window
    # there still holds two columns of the object, which match at the object's disparity: the
    # background takes it (fattening). Weighted by colour, those bits count little.
    left, right, gt, (y0, y1, x0, x1) = two_colour_scene(seed=seed)
    beside = np.zeros(gt.shape, bool)
    beside[y0 + 2:y1 - 2, x1:x1 + 2] = True  # the two background columns right of the object
    inner = np.zeros(gt.shape, bool)
    inner[4:-4, 16:-4] = True
    inner[y0 - 3:y1 + 3, x0 - 10:x1 + 3] = False  # away from the object's edges and occlusion
    wrong = {}
    for gamma in (0.0, 60.0):
        d = wta(run_stages(left, right, 16, [("cost", "census", {"window": [5, 5], "gamma_c": gamma})]))
        wrong[gamma] = ((d != gt)[beside].sum(), (d != gt)[inner].sum())
    assert wrong[0.0][0] >= 10  # plain census: a quarter or more of the strip fattened
    assert wrong[60.0][0] <= 3
    assert wrong[60.0][1] <= wrong[0.0][1] + 2  # and no worse inside the surfaces


def test_weighted_census_coarse_level_takes_plain_distances(monkeypatch):
    # A coarse-to-fine SGM's coarse level only bounds the search: it runs without the weights.
    from stereocli.matching.kernels import census as kc
    from stereocli.matching.pipeline import match_pair

    shapes = []
    original = kc.support_planes
    monkeypatch.setattr(kc, "support_planes", lambda image, *a: shapes.append(image.shape[:2]) or original(image, *a))
    left, right, gt, _ = two_colour_scene(h=64, w=128)
    cfg = build_config(sets=["cost.name=census", "cost.window=[5,5]", "cost.gamma_c=60", "optimizer.name=sgm",
                             "optimizer.coarse=true", "optimizer.coarse_min_volume=0", "optimizer.coarse_min_ndisp=0"])
    out = match_pair(left, right, cfg, ndisp=16).disparity
    assert shapes == [(64, 128)]
    assert np.mean(np.abs(out - gt)[8:-8, 24:-8] <= 1) > 0.9


@pytest.mark.parametrize("threads", [1, 2])
def test_nearest_bit_strings_match_a_numpy_reference_ties_included(threads):
    from stereocli.matching.kernels.census import nearest_bit_strings
    from stereocli.runtime import set_threads

    rng = np.random.default_rng(5)
    queries = rng.integers(0, 256, (37, 32), dtype=np.uint8)
    candidates = rng.integers(0, 256, (23, 32), dtype=np.uint8)
    candidates[7] = candidates[3]  # equal distances to two candidates: the lower index wins
    queries[:5] = candidates[3]  # distance 0
    queries[5] = candidates[3]
    queries[5, 0] ^= 1  # distance 1, as to candidate 7
    bits = np.unpackbits(queries[:, None, :] ^ candidates[None, :, :], axis=2).sum(axis=2)
    set_threads(threads)
    try:
        index, best, second = nearest_bit_strings(queries, candidates)
    finally:
        set_threads(0)
    np.testing.assert_array_equal(index, bits.argmin(axis=1))
    np.testing.assert_array_equal(best, bits.min(axis=1))
    np.testing.assert_array_equal(second, np.sort(bits, axis=1)[:, 1])
    assert index[0] == 3 and best[0] == 0 and second[0] == 0 and index[5] == 3 and best[5] == 1
