"""Hand-computed tiny cases for every scoring rule (MiddEval3, v2, KITTI) and the colouriser."""

from __future__ import annotations

import math

import numpy as np
import pytest

from stereocli.errors import ConfigError, DataError
from stereocli.evaluation import EvalOptions, SceneResult, evaluate_pair, weighted_average
from stereocli.evaluation.datasets import Scene, load_middlebury_v2, middeval3_weight
from stereocli.evaluation.metrics import (
    derive_nonocc_mask,
    kitti_interpolate_background,
    kitti_stats,
    middlebury_stats,
    prepare_estimate,
    size_factor,
    threshold_key,
    upsample_nearest,
)
from stereocli.io.images import write_image
from stereocli.viz import colorize_disparity

INF = np.inf


def f32(rows):
    return np.array(rows, dtype=np.float32)


def test_threshold_keys():
    assert [threshold_key(t) for t in (0.5, 1, 2.0, 4)] == ["bad0.5", "bad1.0", "bad2.0", "bad4.0"]
    assert threshold_key(0.25) == "bad0.25"


def test_upsampling_replicates_and_scales():
    est = f32([[1, 2], [INF, 3]])
    up = upsample_nearest(est, 2)
    np.testing.assert_array_equal(up, f32([[2, 2, 4, 4], [2, 2, 4, 4], [INF, INF, 6, 6], [INF, INF, 6, 6]]))


def test_half_size_estimate_scored_at_full_resolution():
    est = f32([[1, 2]])  # half size: upsampled to [[2,2,4,4],[2,2,4,4]]
    gt = f32([[2, 2.6, 4, 3], [INF, 2, 4, 4]])
    prepared, factor = prepare_estimate(est, gt.shape)
    assert factor == 2
    s = middlebury_stats(prepared, gt, None, thresholds=(0.5, 1.0), quantiles=())
    # errors over the 7 known pixels: 0, 0.6, 0, 1, 0, 0, 0
    assert s["n"] == 7
    assert s["bad0.5"] == pytest.approx(100 * 2 / 7)
    assert s["bad1.0"] == 0.0  # 1.0 is not > 1.0
    assert s["avgerr"] == pytest.approx(1.6 / 7, rel=1e-6)
    assert s["rms"] == pytest.approx(math.sqrt((0.36 + 1) / 7), rel=1e-6)


def test_clipping_to_ndisp_at_estimate_resolution():
    # ndisp = 3 at the half-size estimate -> clip to [0, 6] after scaling (SDK: maxd = scale*maxdisp)
    est = f32([[5, -1]])
    gt = f32([[6, 6, 0, 0], [6, 6, 0, 0]])
    prepared, _ = prepare_estimate(est, gt.shape, ndisp=3)
    np.testing.assert_array_equal(prepared, f32([[6, 6, 0, 0], [6, 6, 0, 0]]))
    s = middlebury_stats(prepared, gt, None, thresholds=(0.5,), quantiles=())
    assert s["bad0.5"] == 0.0


def test_invalid_counts_as_bad_but_not_in_avgerr():
    gt = f32([[1, 1, 1, 1]])
    est = f32([[1, INF, 3, 1.5]])
    s = middlebury_stats(est, gt, None, thresholds=(0.5, 1.0, 4.0), quantiles=(50,))
    assert s["invalid"] == 25.0
    assert s["bad0.5"] == 50.0  # 3 (err 2) + the invalid one; 1.5 (err 0.5) is not > 0.5
    assert s["bad1.0"] == 50.0
    assert s["bad4.0"] == 25.0  # only the invalid one
    assert s["avgerr"] == pytest.approx((0 + 2 + 0.5) / 3)  # valid pixels only
    assert s["rms"] == pytest.approx(math.sqrt((4 + 0.25) / 3))
    assert s["A50"] == pytest.approx(0.5)  # median of {0, 0.5, 2}


def test_mask_and_unknown_gt_are_not_scored():
    gt = f32([[1, INF, 1, 1]])
    est = f32([[9, 9, 1, 9]])
    mask = np.array([[False, True, True, True]])
    s = middlebury_stats(est, gt, mask, thresholds=(1.0,), quantiles=())
    assert s["n"] == 2  # pixel 0 masked out, pixel 1 unknown GT
    assert s["bad1.0"] == 50.0


def test_threshold_units_full_resolution_multiplies_errors():
    gt = f32([[10, 10, 10]])
    est = f32([[10.4, 10.6, 11.2]])  # errors 0.4, 0.6, 1.2 at Q -> 1.6, 2.4, 4.8 full-res px
    s = middlebury_stats(est, gt, None, thresholds=(2.0, 4.0), quantiles=(), unit=4.0)
    assert s["bad2.0"] == pytest.approx(200 / 3)
    assert s["bad4.0"] == pytest.approx(100 / 3)
    assert s["avgerr"] == pytest.approx((1.6 + 2.4 + 4.8) / 3, rel=1e-5)


def test_size_mismatch_and_nan_are_errors():
    with pytest.raises(DataError, match="1, 2 or 4"):
        size_factor((10, 10), (30, 30))
    with pytest.raises(DataError, match="1, 2 or 4"):
        size_factor((10, 10), (20, 21))
    with pytest.raises(DataError, match="NaN"):
        prepare_estimate(f32([[1, np.nan]]), (1, 2))


def _scene(name, gt, nonocc=None, ndisp=None, resolution="F", kind="middlebury2014"):
    masks = {"nonocc": nonocc if nonocc is not None else np.isfinite(gt), "all": np.isfinite(gt)}
    from pathlib import Path

    return Scene(name=name, kind=kind, gt=gt, masks=masks, gt_path=Path(name), ndisp=ndisp,
                 weight=middeval3_weight(name), resolution=resolution)


def test_evaluate_pair_q_gt_full_units_and_time():
    gt = np.full((4, 4), 8.0, dtype=np.float32)
    est = np.full((2, 2), 4.3, dtype=np.float32)  # half of Q: up -> 8.6, err 0.6 Q px = 2.4 full px
    scene = _scene("Adirondack", gt, ndisp=16, resolution="Q")
    r = evaluate_pair(est, scene, time=2.0)
    assert r.factor == 2 and r.unit == 4.0
    assert r.metrics["nonocc"]["bad2.0"] == 100.0 and r.metrics["nonocc"]["bad4.0"] == 0.0
    assert r.metrics["all"]["avgerr"] == pytest.approx(2.4, rel=1e-5)
    assert r.time_per_mp == pytest.approx(2.0 / (4 / 1e6))
    assert r.time_per_gd == pytest.approx(2.0 / (4 * 8 / 1e9))  # ndisp 16 at Q -> 8 at the estimate
    native = evaluate_pair(est, scene, options=EvalOptions(threshold_units="native"))
    assert native.metrics["all"]["bad0.5"] == 100.0 and native.metrics["all"]["bad1.0"] == 0.0
    same = evaluate_pair(est, scene, options=EvalOptions(same_resolution=True, threshold_units="native"))
    assert same.metrics["all"]["avgerr"] == pytest.approx(0.3, rel=1e-5)  # GT 8/2=4 vs 4.3


def test_weights_and_weighted_average():
    assert middeval3_weight("PianoL") == 0.5 and middeval3_weight("Vintage") == 0.5
    assert middeval3_weight("Piano") == 1.0

    def res(name, bad):
        return SceneResult(name=name, kind="middlebury2014", weight=middeval3_weight(name),
                           metrics={"nonocc": {"bad2.0": bad}}, size=(1, 1), factor=1, unit=1.0, time=1.0)

    avg = weighted_average([res("Adirondack", 10.0), res("PianoL", 40.0), res("Shelves", 40.0)])
    assert avg["nonocc"]["bad2.0"] == pytest.approx((10 + 0.5 * 40 + 0.5 * 40) / 2.0)
    assert avg["weight"] == 2.0


def test_v2_scale_decoding(tmp_path):
    folder = tmp_path / "tsukuba"
    folder.mkdir()
    write_image(folder / "disp3.pgm", np.array([[0, 80, 224], [96, 16, 255]], dtype=np.uint8))
    scene = load_middlebury_v2(folder)
    np.testing.assert_array_equal(scene.gt, f32([[INF, 5, 14], [6, 1, 255 / 16]]))
    assert scene.gt_scale == 16 and "nonocc" in scene.mask_notes  # derived, labelled
    other = tmp_path / "mystery"
    other.mkdir()
    write_image(other / "disp2.pgm", np.array([[8, 16]], dtype=np.uint8))
    with pytest.raises(ConfigError, match="--gt-scale"):
        load_middlebury_v2(other)
    np.testing.assert_array_equal(load_middlebury_v2(other, gt_scale=8).gt, f32([[1, 2]]))


def test_v2_pair_has_no_clipping_and_bad1_default_ok(tmp_path):
    gt = f32([[1, 1, 1]])
    scene = _scene("venus", gt, ndisp=1, kind="middlebury-v2")
    r = evaluate_pair(f32([[3, 1, 1]]), scene)  # 3 stays 3 (v2 kit had no clipping)
    assert r.metrics["all"]["bad1.0"] == pytest.approx(100 / 3)


def test_derived_nonocc_mask_hand_case():
    # Row 0: x - d = [-1, 0, 1, 0, 1, 4, 5, 6]; x=0 leaves the image, x=1 and x=2 are hidden by
    # the nearer x=3 and x=4 (d=3) that land on the same right pixels.
    row0 = [1, 1, 1, 3, 3, 1, 1, 1]
    # Row 1: x=2 (d=0, xr=2) vs x=3 (d=0.5, xr=2.5): exactly 0.5 apart -> still visible;
    # x=5 (d=0, xr=5) vs x=6 (d=0.6, xr=5.4): 0.4 apart -> hidden. Unknown GT is never nonocc.
    row1 = [0, 0, 0, 0.5, INF, 0, 0.6, 0]
    gt = f32([row0, row1])
    mask = derive_nonocc_mask(gt)
    expected = np.array([[0, 0, 0, 1, 1, 1, 1, 1], [1, 1, 1, 1, 0, 0, 1, 1]], dtype=bool)
    np.testing.assert_array_equal(mask, expected)
    # Right-view cross-check: x=7 of row 0 maps to right x=6; a right GT of 3 there disagrees.
    right = np.full_like(gt, INF)
    right[0, 6] = 3.0
    right[0, 5] = 1.4  # x=6 -> right x=5: agrees within 1 px
    mask2 = derive_nonocc_mask(gt, right)
    assert not mask2[0, 7] and mask2[0, 6]


def test_kitti_background_interpolation():
    d = f32([
        [INF, 5, INF, INF, 3, INF],
        [INF, INF, INF, INF, INF, INF],   # interior empty row: devkit leaves it invalid
        [2, -1, 4, 4, 4, 4],              # negative = invalid (devkit isValid: d >= 0)
        [INF, INF, INF, INF, INF, INF],   # below the last valid row: copied from above
    ])
    out = kitti_interpolate_background(d)
    np.testing.assert_array_equal(out[0], f32([5, 5, 3, 3, 3, 3]))
    assert np.isinf(out[1]).all()
    np.testing.assert_array_equal(out[2], f32([2, 2, 4, 4, 4, 4]))
    np.testing.assert_array_equal(out[3], out[2])
    top = kitti_interpolate_background(f32([[INF, INF], [1, INF]]))
    np.testing.assert_array_equal(top, f32([[1, 1], [1, 1]]))


def test_kitti_d1_rule_and_density():
    gt = f32([[100, 10, 10, 10, 50, INF]])
    est = f32([[104, 14, 12.9, INF, 20, 1]])
    # 104 vs 100: err 4 > 3 but 4 % <= 5 %  -> inlier; 14 vs 10: 4 > 3 and 40 % -> outlier;
    # 12.9 vs 10: 2.9 <= 3 -> inlier; INF is filled with min(12.9, 20) = 12.9 -> inlier;
    # 20 vs 50 -> outlier. GT inf not scored.
    s = kitti_stats(est, gt, thresholds=(1.0,), quantiles=())
    assert s["n"] == 5
    assert s["D1"] == pytest.approx(40.0)
    assert s["density"] == pytest.approx(80.0) and s["invalid"] == pytest.approx(20.0)
    obj = np.array([[0, 1, 1, 1, 0, 0]], dtype=np.uint8)
    s2 = kitti_stats(est, gt, obj_map=obj, thresholds=(1.0,), quantiles=())
    assert s2["D1-bg"] == pytest.approx(50.0) and s2["D1-fg"] == pytest.approx(100 / 3)


def test_colorize_disparity():
    d = f32([[0, 1, 2, INF]])
    rgb = colorize_disparity(d, 0, 2)
    assert rgb.shape == (1, 4, 3) and rgb.dtype == np.uint8
    assert (rgb[0, 3] == 0).all() and rgb[0, :3].any(axis=1).all()
    assert not np.array_equal(rgb[0, 0], rgb[0, 2])
    auto = colorize_disparity(np.array([[1.0, 2.0], [3.0, 1000.0]], dtype=np.float32))
    assert auto.shape == (2, 2, 3)
    assert colorize_disparity(np.full((2, 2), INF, dtype=np.float32)).max() == 0
