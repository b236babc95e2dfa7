"""Fused SAD/STAD + WTA (no cost volume) gives exactly what the volume path gives.

The fused kernel must reproduce the volume path bit for bit: same disparities (ties to the
smallest disparity, ``cost_max`` hypotheses included), same costs around each winner, for grey
and colour, integer and fractional images, negative ``min_disp``, D not a multiple of 16 and
right valid masks; and the pipeline must pick it only where it is allowed.
"""

from __future__ import annotations

import numpy as np
import pytest

from local_scene import scene
from stereocli.matching import pipeline
from stereocli.matching.config import build_config, validate
from stereocli.matching.kernels import costs as kl
from stereocli.matching.kernels.costs import mask_invalid_right
from stereocli.matching.kernels.fused_sad import sad_wta
from stereocli.matching.kernels.winners import wta_left
from stereocli.matching.pipeline import fused_cost_wta, match_pair


def _images(rng, h, w, nc, kind):
    shape = (h, w, nc)
    if kind == "int":
        return [rng.integers(0, 256, shape).astype(np.float32) for _ in range(2)]
    if kind == "ties":  # three grey levels: many equal window sums
        return [rng.integers(0, 3, shape).astype(np.float32) for _ in range(2)]
    return [rng.uniform(0, 255, shape).astype(np.float32) for _ in range(2)]  # fractional


def _volume_path(left, right, mask, md, nd, ry, rx, trunc, nbands):
    vol = kl.window_cost_volume(left, right, md, nd, ry, rx, kl.MODE_AD, trunc, trunc, nbands)
    if mask is not None:
        mask_invalid_right(vol, mask, md, np.float32(trunc))
    disp, _ = wta_left(vol, md, trunc)
    return disp, vol


CASES = [  # (h, w, channels, min_disp, ndisp, radius_y, radius_x, truncate, kind, mask, bands)
    (23, 41, 1, 0, 16, 2, 2, 255.0, "int", False, 3),
    (17, 37, 3, -5, 13, 1, 3, 255.0, "int", False, 2),
    (19, 29, 1, -7, 37, 3, 1, 2.0, "ties", True, 4),
    (21, 33, 3, 2, 21, 2, 2, 1.0, "ties", False, 1),
    (16, 30, 1, -3, 9, 0, 0, 20.0, "ties", False, 5),
    (15, 26, 3, -2, 19, 2, 4, 20.0, "float", True, 3),
    (9, 12, 1, 4, 40, 4, 7, 255.0, "float", False, 2),  # window and range larger than the image
]


@pytest.mark.parametrize("h,w,nc,md,nd,ry,rx,trunc,kind,masked,bands", CASES)
def test_kernel_equals_volume_then_wta(h, w, nc, md, nd, ry, rx, trunc, kind, masked, bands):
    rng = np.random.default_rng(h * w + nd)
    left, right = _images(rng, h, w, nc, kind)
    mask = rng.random((h, w)) > 0.25 if masked else None
    ref, vol = _volume_path(left, right, mask, md, nd, ry, rx, trunc, bands)
    disp, wc = sad_wta(left, right, np.zeros((0, 0), np.bool_) if mask is None else mask, md, nd, ry, rx,
                       trunc * nc, trunc, bands)
    np.testing.assert_array_equal(disp, ref)
    # the costs kept around each winner are the volume's entries (cost_max beyond the range)
    ys, xs = np.nonzero(np.isfinite(ref))
    k = (ref[ys, xs] - md).astype(int)
    padded = np.concatenate([np.full((h, w, 1), trunc, np.float32), vol, np.full((h, w, 1), trunc, np.float32)], 2)
    for j in range(3):
        np.testing.assert_array_equal(wc[ys, xs, j], padded[ys, xs, k + j])
    if kind == "ties":
        assert np.isfinite(ref).any()


def test_kernel_against_numpy_reference():
    # Integer images: window sums are exact, so the winner is the first minimum of the exact mean.
    rng = np.random.default_rng(5)
    h, w, md, nd, r = 7, 13, -2, 7, 1
    left, right = _images(rng, h, w, 1, "ties")
    disp, _ = sad_wta(left, right, np.zeros((0, 0), np.bool_), md, nd, r, r, 255.0, 255.0, 2)
    for y in range(h):
        for x in range(w):
            costs = np.full(nd, 255.0)
            for k in range(nd):
                d = md + k
                if 0 <= x - d < w:
                    win = [abs(left[yy, xx, 0] - right[yy, min(max(xx - d, 0), w - 1), 0])
                           for yy in range(max(0, y - r), min(h, y + r + 1))
                           for xx in range(max(0, x - r), min(w, x + r + 1))]
                    costs[k] = np.mean(win)
            k = int(np.argmin(costs))  # first minimum: ties to the smallest disparity
            assert disp[y, x] == (np.inf if costs[k] >= 255.0 else md + k), (y, x)


def _both_paths(monkeypatch, left, right, config, **kw):
    fused = match_pair(left, right, config, **kw)
    monkeypatch.setattr(pipeline, "FUSED", False)
    volume = match_pair(left, right, config, **kw)
    monkeypatch.setattr(pipeline, "FUSED", True)
    return fused, volume


def _config(cost, refinement=(), **extra):
    return validate({"cost": cost, "aggregation": [], "optimizer": {"name": "wta"},
                     "refinement": list(refinement), **extra}, "<test>")


PIPELINES = {
    "realtime": lambda: build_config(["realtime"]),
    "sad": lambda: _config({"name": "sad", "window": [7, 5]}),
    "stad_subpixel_first": lambda: _config({"name": "stad", "window": [5, 5], "truncate": 12},
                                           [{"name": "subpixel", "method": "equiangular"},
                                            {"name": "single_matching_phase"}]),
    "strips": lambda: build_config(["realtime"], ["runtime.strip_rows=16", "runtime.strip_overlap=8"]),
}


@pytest.mark.parametrize("name", sorted(PIPELINES))
@pytest.mark.parametrize("color", [True, False])
def test_pipeline_fused_equals_volume_path(monkeypatch, name, color):
    config = PIPELINES[name]()
    left, right, gt, mask = scene(color=color)
    h, w = gt.shape
    valid = np.ones((h, w), bool)
    valid[:, :3] = False  # a rectification border on the right image
    for kw in ({"min_disp": 0, "ndisp": 16}, {"min_disp": -4, "ndisp": 19, "right_valid": valid}):
        fused, volume = _both_paths(monkeypatch, left, right, config, **kw)
        assert any("+optimizer.wta" in key for key in fused.timings), fused.timings  # fused ran
        assert not any("+optimizer.wta" in key for key in volume.timings)
        assert fused.disparity.dtype == np.float32
        np.testing.assert_array_equal(fused.disparity, volume.disparity)
    good = np.isfinite(fused.disparity) & mask
    assert good.sum() > 0.8 * mask.sum() and (np.abs(fused.disparity[good] - gt[good]) < 1).all()


def test_pipeline_fused_equals_volume_path_on_random_images(monkeypatch):
    rng = np.random.default_rng(11)
    for kind, nc in (("ties", 1), ("int", 3), ("float", 1)):
        left, right = _images(rng, 40, 57, nc, kind)
        if nc == 1:
            left, right = left[..., 0], right[..., 0]
        for config in (PIPELINES["realtime"](), PIPELINES["sad"]()):
            fused, volume = _both_paths(monkeypatch, left, right, config, min_disp=-3, ndisp=21)
            np.testing.assert_array_equal(fused.disparity, volume.disparity)


@pytest.mark.parametrize("config,reason", [
    (lambda: _config({"name": "sad"}, [{"name": "uniqueness"}]), "uniqueness reads the whole cost vector"),
    (lambda: _config({"name": "sad"}, [{"name": "subpixel"}, {"name": "lr_check"}]), "right view wanted"),
    (lambda: _config({"name": "sad"}, [{"name": "subpixel"}, {"name": "subpixel"}]), "a volume stage twice"),
    (lambda: validate({"cost": {"name": "ad"}, "aggregation": [{"name": "box"}], "optimizer": {"name": "wta"}},
                      "<test>"), "no fused kernel for ad + box"),
    (lambda: _config({"name": "ssd"}), "no fused kernel for ssd"),
])
def test_pipeline_falls_back_to_the_volume(monkeypatch, config, reason):
    config = config()
    volume_stages = [c for c in config.refinement if c.stage.traits.needs_cost]
    want_right = any(c.stage.traits.needs_right for c in config.refinement)
    assert fused_cost_wta(config, volume_stages, want_right) is None, reason
    left, right, gt, mask = scene(color=False)
    result = match_pair(left, right, config, ndisp=16)
    assert f"cost.{config.cost.stage.name}" in result.timings and "optimizer.wta" in result.timings
    # the same run with want_right (e.g. --right) falls back too, and still gets both views
    if reason == "a volume stage twice":
        assert match_pair(left, right, config, ndisp=16, want_right=True).disparity_right is not None


def test_fused_path_is_chosen_without_volume_refinements():
    config = PIPELINES["realtime"]()
    stages = [c for c in config.refinement if c.stage.traits.needs_cost]
    assert [c.stage.name for c in stages] == ["single_matching_phase", "subpixel"]
    assert fused_cost_wta(config, stages, False) is not None
    assert fused_cost_wta(config, stages, True) is None  # a right-view disparity needs the volume
