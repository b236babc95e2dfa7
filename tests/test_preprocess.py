"""Preprocessing stages: exact behaviour on simple images, recovery of a known disparity
through each filter, and parameter errors."""

from __future__ import annotations

import numpy as np
import pytest

from local_scene import run_stages, scene, wta
from stereocli import registry
from stereocli.errors import ConfigError
from stereocli.matching.config import build_config
from stereocli.matching.preprocess import match_histogram
from stereocli.matching.state import MatchState

FILTERS = ["none", "log", "mean_removal", "bilateral_subtraction", "xsobel", "histogram_matching"]


def apply(name, left, right, values=None):
    stage = registry.get("preprocess", name)
    st = MatchState(left.copy(), right.copy(), 0, 4)
    stage.func(st, stage.make_params(values or {}))
    return st


@pytest.mark.parametrize("name", FILTERS)
@pytest.mark.parametrize("color", [True, False])
def test_shape_dtype_and_range(name, color):
    left, right, _, _ = scene(color=color)
    st = apply(name, left, right)
    for img, orig in ((st.left, left), (st.right, right)):
        assert img.shape == orig.shape and img.dtype == np.float32 and img.flags.c_contiguous
        assert img.min() >= 0 and img.max() <= 255


@pytest.mark.parametrize("name", ["log", "mean_removal", "bilateral_subtraction"])
def test_band_pass_filters_remove_a_brightness_offset(name):
    flat = np.full((20, 24), 90.0, np.float32)
    st = apply(name, flat, flat + 40)
    np.testing.assert_allclose(st.left, 128.0, atol=1e-3)
    np.testing.assert_allclose(st.right, 128.0, atol=1e-3)
    left = scene(color=False)[0] * 0.7 + 10  # no saturation: the offset disappears exactly
    st = apply(name, left, left + 20)
    np.testing.assert_allclose(st.left, st.right, atol=1e-3)


def test_xsobel_matches_stereobm_definition():
    ramp = np.tile(np.arange(16, dtype=np.float32) * 2, (5, 1))  # slope 2 grey levels/px
    st = apply("xsobel", ramp, ramp, {"cap": 31})
    # 3x3 Sobel of a slope-2 ramp is 8·2 = 16 inside; clipped to ±31 then +31
    np.testing.assert_allclose(st.left[:, 1:-1], 31 + 16)
    st = apply("xsobel", ramp * 4, ramp * 4, {"cap": 31})
    np.testing.assert_allclose(st.left[:, 1:-1], 62)  # clipped at cap


def test_histogram_matching_undoes_a_monotonic_change():
    rng = np.random.default_rng(0)
    left = rng.permutation(np.arange(400, dtype=np.float32)).reshape(20, 20) * 0.5
    right = np.sqrt(left) * 10 + 3  # monotonic: gamma + gain + offset
    np.testing.assert_allclose(match_histogram(right, left), left, atol=1e-4)
    st = apply("histogram_matching", left, right, {"reference": "right"})
    np.testing.assert_allclose(st.left, right, atol=1e-3)


@pytest.mark.parametrize("name", FILTERS)
def test_recovers_known_disparity_after_filter(name):
    left, right, gt, mask = scene(color=True)
    # a gain and offset between the views: the filters that remove it must still match
    right = np.clip(right * 0.9 + 12, 0, 255).astype(np.float32)
    stages = [("preprocess", name, {}), ("cost", "sad" if name != "none" else "zncc", {"window": [7, 7]})]
    st = run_stages(left, right, 16, stages)
    assert (wta(st)[mask] == gt[mask]).mean() > 0.97


@pytest.mark.parametrize("name,values,key", [
    ("log", {"sigma": 0}, "sigma"),
    ("log", {"gain": 1000}, "gain"),
    ("mean_removal", {"window": [8, 9]}, "window"),
    ("bilateral_subtraction", {"sigma_color": 0}, "sigma_color"),
    ("xsobel", {"cap": 64}, "cap"),
    ("xsobel", {"cap": 2.5}, "cap"),
    ("histogram_matching", {"reference": "both"}, "reference"),
])
def test_invalid_parameters(name, values, key):
    with pytest.raises(ConfigError, match=key):
        registry.get("preprocess", name).make_params(values, source="x.yaml", section="preprocess[0]")


def test_preprocess_list_through_config():
    cfg = build_config(["realtime"])
    assert [c.stage.name for c in cfg.preprocess] == ["mean_removal"]
    with pytest.raises(ConfigError, match="sigma"):
        build_config(["realtime"], sets=["preprocess.mean_removal.sigma=2"])
