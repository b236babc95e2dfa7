"""Aggregation stages: pure-numpy references on tiny volumes, recovery of a known disparity,
the volume contract (impossible entries keep cost_max) and parameter errors."""

from __future__ import annotations

import numpy as np
import pytest

from local_scene import run_stages, scene, wta
from stereocli import registry
from stereocli.errors import ConfigError
from stereocli.matching.config import build_config
from stereocli.matching.kernels import aggregation as ka
from stereocli.matching.kernels.aggregation import box_filter_volume

AGGREGATIONS = ["box", "shiftable", "multiple_windows", "variable_window", "cross", "adaptive_weights",
                "segment_support", "fast_bilateral", "locally_consistent", "guided_filter"]
SMALL = {  # keep windows small on the 64×96 test scene
    "adaptive_weights": {"window": 15},
    "segment_support": {"window": 15},
    "fast_bilateral": {"window": 15},
    "locally_consistent": {"window": 9},
    "guided_filter": {"radius": 4},
}


def box_ref(cost, ry, rx):
    h, w, _ = cost.shape
    out = np.empty_like(cost)
    for y in range(h):
        for x in range(w):
            out[y, x] = cost[max(0, y - ry):y + ry + 1, max(0, x - rx):x + rx + 1].mean(axis=(0, 1))
    return out


def test_box_filter_volume_matches_reference():
    rng = np.random.default_rng(0)
    cost = rng.random((11, 13, 5)).astype(np.float32)
    np.testing.assert_allclose(box_filter_volume(cost, 2, 3), box_ref(cost, 2, 3), atol=1e-6)
    big = rng.random((6, 7, 300)).astype(np.float32)  # more slices than OpenCV's channel limit
    np.testing.assert_allclose(box_filter_volume(big, 1, 1), box_ref(big, 1, 1), atol=1e-6)


def test_shiftable_is_min_over_window_positions():
    rng = np.random.default_rng(1)
    cost = rng.random((9, 10, 1)).astype(np.float32)  # D = 1 at d = 0: every entry possible
    from stereocli.matching.state import MatchState

    st = MatchState(np.zeros((9, 10), np.float32), np.zeros((9, 10), np.float32), 0, 1, cost=cost.copy(), cost_max=1.0)
    shiftable = registry.get("aggregation", "shiftable")
    shiftable.func(st, shiftable.make_params({"window": [3, 3]}))
    box = box_ref(cost, 1, 1)
    ref = np.empty_like(box)
    for y in range(9):
        for x in range(10):
            ref[y, x] = box[max(0, y - 1):y + 2, max(0, x - 1):x + 2].min(axis=(0, 1))
    np.testing.assert_allclose(st.cost, ref, atol=1e-6)


def test_multiple_windows_reference():
    rng = np.random.default_rng(2)
    box = rng.random((6, 7, 2)).astype(np.float32)
    off_y = np.array([-2, -2, 2, 2], np.int64)
    off_x = np.array([-2, 2, -2, 2], np.int64)
    out = ka.multiple_windows(box, off_y, off_x, 2)
    for y, x, k in [(0, 0, 0), (3, 3, 1), (5, 6, 0)]:
        vals = sorted(box[min(max(y + dy, 0), 5), min(max(x + dx, 0), 6), k] for dy, dx in zip(off_y, off_x))
        assert out[y, x, k] == pytest.approx((box[y, x, k] + vals[0] + vals[1]) / 3, abs=1e-6)


def test_variable_window_reference():
    rng = np.random.default_rng(3)
    cost = rng.random((8, 9, 2)).astype(np.float32)
    sat = ka.integral_volume(cost)
    ry = np.array([0, 1, 2, 1], np.int64)
    rx = np.array([0, 1, 1, 2], np.int64)
    out = ka.variable_window(sat, ry, rx, 0.5)
    for y, x, k in [(0, 0, 0), (4, 4, 1), (7, 8, 1)]:
        scores = []
        for a, b in zip(ry, rx):
            win = cost[max(0, y - a):y + a + 1, max(0, x - b):x + b + 1, k]
            scores.append((win.sum() + 0.5) / win.size)
        assert out[y, x, k] == pytest.approx(min(scores), rel=1e-5)


def test_cross_arms_and_sums_reference():
    img = np.zeros((5, 8, 1), np.float32)
    img[:, 5:] = 100  # an edge between x = 4 and 5
    arms = ka.cross_arms(img, 20.0, 3)
    assert list(arms[2, 4]) == [3, 1, 2, 2]  # right arm stops at the edge but is at least 1
    assert list(arms[2, 6]) == [1, 1, 2, 2]
    cost = np.arange(5 * 8, dtype=np.float32).reshape(5, 8, 1)
    h = ka.cross_sum_h(cost, arms)
    assert h[2, 4, 0] == cost[2, 1:6, 0].sum()
    v = ka.cross_sum_v(cost, arms)
    assert v[0, 4, 0] == cost[0:4, 4, 0].sum()  # up arm 0 at the top row, down arm 3


def test_weighted_support_reference():
    rng = np.random.default_rng(4)
    h, w, nd, md = 7, 10, 3, 1
    cost = rng.random((h, w, nd)).astype(np.float32)
    fl = (rng.random((h, w, 3)) * 20).astype(np.float32)
    fr = (rng.random((h, w, 3)) * 20).astype(np.float32)
    oy, ox = (a.ravel().astype(np.int64) for a in np.meshgrid(np.arange(-2, 3), np.arange(-2, 3), indexing="ij"))
    sp = np.exp(-np.hypot(oy, ox) / 3).astype(np.float32)
    seg = np.zeros((1, 1), np.int32)
    out = ka.weighted_support(cost, fl, fr, seg, seg, oy, ox, sp, 5.0, md, 9.0, False, 0.0)
    for y in range(h):
        for x in range(w):
            for k in range(nd):
                d = md + k
                if not 0 <= x - d < w:
                    assert out[y, x, k] == 9.0
                    continue
                num = den = 0.0
                for o in range(oy.size):
                    qy, qx = y + oy[o], x + ox[o]
                    if 0 <= qy < h and 0 <= qx < w and 0 <= qx - d < w:
                        wgt = sp[o] ** 2 * np.exp(-np.linalg.norm(fl[y, x] - fl[qy, qx]) / 5) \
                            * np.exp(-np.linalg.norm(fr[y, x - d] - fr[qy, qx - d]) / 5)
                        num += wgt * cost[qy, qx, k]
                        den += wgt
                assert out[y, x, k] == pytest.approx(num / den, abs=1e-5)


def test_guided_filter_keeps_constant_and_follows_guide_edges():
    from stereocli.matching.aggregate import _GuidedFilter

    guide = np.zeros((20, 20, 1), np.float32)
    guide[:, 10:] = 1.0
    gf = _GuidedFilter(guide, 3, 1e-4)
    np.testing.assert_allclose(gf(np.full((20, 20), 7.0, np.float32)), 7.0, atol=1e-4)
    p = np.where(guide[..., 0] > 0, 10.0, 0.0).astype(np.float32)
    q = gf(p)  # a step aligned with the guide's edge survives the filter
    assert abs(q[5, 8]) < 0.1 and abs(q[5, 11] - 10) < 0.1


def _guided_state(left, right, ndisp, min_disp=0, right_view="guided", want_right=True, cost=None):
    from stereocli.matching.state import MatchState, Wants

    state = MatchState(left.copy(), right.copy(), min_disp, ndisp, wants=Wants(right=want_right))
    if cost is None:
        stage = registry.get("cost", "color_gradient")
        stage.func(state, stage.make_params({}))
    else:
        state.cost, state.cost_max = cost.copy(), 1.0
    stage = registry.get("aggregation", "guided_filter")
    stage.func(state, stage.make_params({"radius": 4, "right_view": right_view}))
    return state


@pytest.mark.parametrize("min_disp", [0, -3])
def test_guided_right_view_recovers_right_disparity(min_disp):
    d_bg, d_fg = 3, 9
    left, right, gt, _ = scene(color=True, d_bg=d_bg, d_fg=d_fg)
    h, w = gt.shape
    # right-view truth: the foreground covers right pixels x_r with x_r + d_fg inside it
    xs = np.arange(w)
    y0, y1, x0, x1 = h // 4, 3 * h // 4, w // 3, 2 * w // 3
    gt_r = np.full((h, w), d_bg, np.float32)
    gt_r[y0:y1, (xs + d_fg >= x0) & (xs + d_fg < x1)] = d_fg
    mask_r = np.zeros((h, w), bool)
    mask_r[8:-8, 8:-16] = True
    mask_r[y0 - 4:y1 + 4, x0 - d_fg - 4:x0 - d_fg + 4] = False  # foreground edges in the right view
    mask_r[y0 - 4:y1 + 4, x1 - d_fg - 4:x1 - d_bg + 4] = False  # ... and the band occluded in the left
    mask_r[y0 - 4:y0 + 4] = False
    mask_r[y1 - 4:y1 + 4] = False
    st = _guided_state(left, right, 16, min_disp)
    assert st.disparity_right.dtype == np.float32 and st.disparity_right.shape == (h, w)
    assert (st.disparity_right[mask_r] == gt_r[mask_r]).mean() > 0.98


def test_guided_right_view_equals_diagonal_for_flat_guides():
    # With flat guide images the guided filter is a plain (twice applied) box filter, which
    # commutes with the shift that maps a slice to the right view: away from the borders the
    # right-guided WTA must equal wta_right read from the left-guided volume.
    from stereocli.matching.kernels.winners import wta_right

    rng = np.random.default_rng(5)
    h, w, nd = 30, 60, 6
    cost = rng.random((h, w, nd)).astype(np.float32) * 0.9
    flat = np.full((h, w, 3), 100.0, np.float32)
    st = _guided_state(flat, flat, nd, cost=cost)
    ref = wta_right(st.cost, 0, np.float32(1.0))
    inner = (slice(9, h - 9), slice(9, w - 9 - nd))
    assert (st.disparity_right[inner] == ref[inner]).mean() > 0.99


def test_guided_right_view_only_on_request():
    left, right, _, _ = scene(color=True)
    assert _guided_state(left, right, 16, right_view="volume").disparity_right is None
    assert _guided_state(left, right, 16, want_right=False).disparity_right is None


@pytest.mark.parametrize("name", AGGREGATIONS)
def test_recovers_known_disparity(name):
    left, right, gt, mask = scene(color=True)
    cost = ("cost", "color_gradient", {}) if name == "guided_filter" else ("cost", "tad", {"truncate": 30})
    stages = [cost]
    if name == "locally_consistent":
        stages.append(("aggregation", "box", {"window": [5, 5]}))
    stages.append(("aggregation", name, SMALL.get(name, {})))
    st = run_stages(left, right, 16, stages)
    assert st.cost.shape == (*gt.shape, 16) and st.cost.dtype == np.float32
    assert (st.cost[:, 0, 1:] == np.float32(st.cost_max)).all()  # contract kept
    assert (wta(st)[mask] == gt[mask]).mean() > 0.98


def test_negative_min_disp_and_grey():
    left, right, gt, mask = scene(color=False, d_bg=1, d_fg=5)
    for name in AGGREGATIONS:
        stages = [("cost", "tad", {"truncate": 30})]
        if name == "locally_consistent":
            stages.append(("aggregation", "box", {"window": [5, 5]}))
        st = run_stages(left, right, 10, stages + [("aggregation", name, SMALL.get(name, {}))], min_disp=-3)
        assert (wta(st)[mask] == gt[mask]).mean() > 0.95, name


@pytest.mark.parametrize("name,values,key", [
    ("box", {"window": [4, 5]}, "window"),
    ("shiftable", {"window": [3, 200]}, "window"),
    ("multiple_windows", {"windows": 7}, "windows"),
    ("variable_window", {"min_size": 4}, "min_size"),
    ("variable_window", {"min_size": 9, "max_size": 5}, "max_size"),
    ("variable_window", {"step": 3}, "step"),
    ("cross", {"tau": 0}, "tau"),
    ("cross", {"max_arm": 0}, "max_arm"),
    ("adaptive_weights", {"window": 34}, "window"),
    ("adaptive_weights", {"gamma_c": 0}, "gamma_c"),
    ("segment_support", {"spatial_radius": 0}, "spatial_radius"),
    ("fast_bilateral", {"block": 2}, "block"),
    ("locally_consistent", {"gamma_t": -1}, "gamma_t"),
    ("guided_filter", {"eps": 0}, "eps"),
    ("guided_filter", {"radiu": 3}, "radiu"),
    ("guided_filter", {"right_view": "both"}, "right_view"),
])
def test_invalid_parameters(name, values, key):
    with pytest.raises(ConfigError, match=key):
        registry.get("aggregation", name).make_params(values, source="x.yaml", section="aggregation[0]")


def test_invalid_parameter_through_config(tmp_path):
    typo = tmp_path / "typo.yaml"
    typo.write_text("aggregation: [{name: guided_filte}]\n")
    with pytest.raises(ConfigError, match="guided_filter"):  # close-match suggestion
        build_config([str(typo)])
    good = tmp_path / "gf.yaml"
    good.write_text("aggregation: [{name: guided_filter, radius: 5}]\n")
    assert build_config([str(good)]).aggregation[0].params.radius == 5
    with pytest.raises(ConfigError, match="radius"):
        build_config([str(good)], sets=["aggregation.guided_filter.radius=0"])
